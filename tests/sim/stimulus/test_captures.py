"""A recorded capture in place of a generated stream."""

from __future__ import annotations

from maglog.sim.stimulus.captures import load_capture
from maglog.sim.reference import Kind, reference_filter
from maglog.sim.stimulus import load_scenario

from .conftest import SHORT


def _scenario(tmp_path, text):
    path = tmp_path / "scenario.toml"
    path.write_text(SHORT + text)
    return load_scenario(path)


def test_gps_capture_in_one_second_groups(tmp_path, external):
    capture = external.capture("et-332.log")
    stim = _scenario(tmp_path, f"[channels.gps]\ncapture = '{capture}'\n").build()
    system = stim.system
    lines = load_capture(capture).splitlines(keepends=True)
    sent = system.channel_bytes(1)
    assert sent and b"".join(lines).startswith(sent)          # the capture's lines, in order
    assert sent.endswith(b"\n")
    # A group opens at each GGA (the capture's ZDA comes before it), once a second.
    group_starts = [b.start for b in system.channel_bursts(1) if b.data[3:7] == b"GGA,"]
    gaps = [round(b - a, 6) for a, b in zip(group_starts, group_starts[1:])]
    assert gaps and all(0.99 <= g <= 1.01 for g in gaps)
    result = reference_filter(Kind.NMEA, sent)
    assert stim.truth["frames"]["gps"]["kept"] == len(result.frames) > 0
    assert stim.truth["frames"]["gps"]["flushes"] == len(result.flushes) > 0
    # The recording holds the capture's GGAs between the presses.
    assert any(f.startswith(b"$GPGGA,153") for f in system.recorded_frames())


def test_capture_relative_to_the_scenario_and_stream_timing(tmp_path):
    (tmp_path / "cs.log").write_bytes(b"# header\n" + b"$ 48000.000,1000\r\n" * 400)
    stim = _scenario(tmp_path, "[channels.cesium]\ncapture = 'cs.log'\ntiming = 'stream'\n"
                               "first_s = 0.5\n").build()
    bursts = stim.system.channel_bursts(2)
    assert all(b.data == b"$ 48000.000,1000\r\n" for b in bursts)
    # Back to back at the line's rate (18 bytes, 18.75 ms), but for the presses' windows.
    starts = [b.start for b in bursts]
    assert starts[0] == 0.5 and abs(starts[1] - starts[0] - 18 * 10 / 9600) < 1e-3
    assert stim.truth["frames"]["cesium"]["kept"] == len(bursts)
    assert stim.truth["withheld"]["cesium"] > 0


def test_shared_prefix_names_the_shared_data(tmp_path, external):
    external.capture("skytraq.log")
    stim = _scenario(tmp_path, "[channels.gps]\ncapture = 'shared:nmea/skytraq.log'\n").build()
    assert stim.truth["frames"]["gps"]["sent_bytes"] > 0
