"""The default scenario and the truth it writes."""

from __future__ import annotations

import hashlib
import json
import re
import time

import numpy as np

from maglog.sim.reference import Kind, reference_filter
from maglog.sim.stimulus import load_scenario, loads_scenario
from maglog.sim.stimulus.system import MIN_END_GAP_S, SystemScenario

from .conftest import SHORT

FLUSHING_GGA = re.compile(rb"\$[A-Z]{2}GGA,(?:[^,*]*,){5}[1-9][,*]")


def test_default_builds_in_a_few_seconds():
    start = time.perf_counter()
    stim = load_scenario().build()
    assert time.perf_counter() - start < 8.0
    truth = stim.truth
    # About three minutes of flight, every phase in order.
    names = [p["name"] for p in truth["flight"]["phases"]]
    assert names == ["ground", "takeoff", "calibration", "survey", "landing", "ground"]
    assert 150 <= truth["until_s"] <= 200
    assert stim.system.clk_freq == 1_843_200.0
    assert [c.baud for c in stim.system.channels] == [115_200, 9_600, 9_600]


def test_deterministic():
    one, two = (loads_scenario(SHORT).build() for _ in range(2))
    assert one.truth == two.truth
    assert one.system.to_json() == two.system.to_json()
    other = loads_scenario(SHORT.replace("seed = 3", "seed = 4")).build()
    assert other.truth["recorded"]["sha256"] != one.truth["recorded"]["sha256"]


def test_recorded_frames_with_flushes(default_stim):
    system, truth = default_stim.system, default_stim.truth
    frames = system.recorded_frames()
    log = b"".join(frames)
    assert truth["recorded"]["frames"] == len(frames) > 5000
    assert truth["recorded"]["sha256"] == hashlib.sha256(log).hexdigest()
    assert sum(truth["recorded"]["per_channel"].values()) == len(frames)
    assert truth["recorded"]["per_channel"]["mag"] == sum(f.startswith(b"$PMAG1,")
                                                         for f in frames)
    # The fix is acquired after the start press: GGAs without a fix, then with one.
    fixes = [bool(FLUSHING_GGA.match(f)) for f in frames if f[3:6] == b"GGA"]
    first = fixes.index(True)
    assert first >= 1 and not any(fixes[:first]) and all(fixes[first:])
    assert len(fixes) - first > 150
    # Everything the presses enclose: the lines are quiet around both presses.
    start, stop = system.presses
    assert start < truth["flight"]["phases"][1]["start_s"]           # before take-off
    assert stop > truth["flight"]["phases"][4]["end_s"]              # after landing
    rec = default_stim.scenario.recording
    for press in system.presses:
        for k, channel in enumerate(system.channels):
            assert all(b.end(channel.baud) <= press - rec.quiet_before_s
                       or b.start >= press + rec.quiet_after_s
                       for b in system.channel_bursts(k))


def test_frames_are_the_reference_filters(default_stim):
    """The truth's counts against a recount of the lines as sent (the GPS line runs 1.5 %
    fast, which leaves every character intact; the cesium window is the only place where
    the receiver sees something else)."""
    system, truth = default_stim.system, default_stim.truth
    for k, (name, kind) in enumerate((("mag", Kind.PMAG), ("gps", Kind.NMEA))):
        result = reference_filter(kind, system.channel_bytes(k))
        counts = truth["frames"][name]
        assert counts["kept"] == len(result.frames)
        assert {c: counts[c] for c in result.counters} == result.counters
        assert counts["flushes"] == len(result.flushes)
        assert counts["sent_bytes"] == len(system.channel_bytes(k))
    # GPS: one flush a second with a fix, but for the outage and the GGAs spoiled by faults.
    assert truth["frames"]["gps"]["flushes"] > 150


def test_truth_schema_and_files(default_stim, tmp_path):
    truth = default_stim.truth
    assert truth["version"] == 1 and truth["scenario"] == "default"
    assert set(truth) >= {"seed", "clk_freq", "timestamp", "presses_s", "until_s", "channels",
                          "frames", "recorded", "faults", "errors", "reference",
                          "noise_floor_nT", "flight"}
    assert [c["name"] for c in truth["channels"]] == ["mag", "gps", "cesium"]
    assert [c["kind"] for c in truth["channels"]] == ["pmag", "nmea", "cesium"]
    assert truth["channels"][1]["baud_actual"] == 9600 * 1.015
    assert truth["timestamp"] == "2026-06-01T10:00:00+00:00"
    for counts in truth["frames"].values():
        assert set(counts) == {"sent_bytes", "kept", "checksum", "not_whitelisted", "overlong",
                               "bad_byte", "uart_error", "overflow", "flushes"}
    errors = truth["errors"]
    assert np.allclose(np.tril(errors["K"], -1), 0) and np.all(np.diag(errors["K"]) > 0)
    assert truth["flight"]["samples"] == default_stim.flight.t.size
    assert truth["flight"]["mag_rate_hz"] == 20.0 and truth["flight"]["cesium_rate_hz"] == 10.0
    path = default_stim.write_truth(tmp_path / "out")
    assert json.loads(path.read_text()) == json.loads(json.dumps(truth))
    csv = (tmp_path / "out" / "attitude.csv").read_text().splitlines()
    assert csv[0] == "t,roll_deg,pitch_deg,heading_deg" and len(csv) == truth["flight"]["samples"] + 1


def test_system_round_trips_through_json(default_stim):
    system = default_stim.system
    again = SystemScenario.from_json(json.loads(json.dumps(system.to_json())))
    assert again.bursts == system.bursts
    assert any(b.baud is not None for b in again.bursts)
    assert again.timestamp == system.timestamp


def test_kept_frames_end_apart(default_stim):
    """No two kept frames of different channels end closer than MIN_END_GAP_S (Timeline),
    so their order in the log is certain."""
    system = default_stim.system
    ends = sorted((t, k) for k in range(3) for t, _ in system.kept_frames(k))
    assert all(t1 - t0 >= MIN_END_GAP_S or k0 == k1
               for (t0, k0), (t1, k1) in zip(ends, ends[1:]))


def test_noise_floor_is_the_ideal_residual(default_stim):
    """The stated formula against the residual of the true K and c on the magnetometer's
    frames as sent (quantised to 0.1 nT) and the cesium frames interpolated to them."""
    stim = default_stim
    k, c = np.array(stim.truth["errors"]["K"]), np.array(stim.truth["errors"]["c"])
    mag = [it for it in stim.items if it.type == "pmag" and not it.faults]
    ces = [it for it in stim.items if it.type == "cesium" and not it.faults]
    b = np.array([[float(x) for x in it.data.split(b"*")[0].split(b",")[2:5]] for it in mag])
    t_mag = np.array([it.t for it in mag])
    t_ces = np.array([it.t for it in ces])
    f_ces = np.array([float(it.data[1:11]) for it in ces])
    residual = np.linalg.norm(b @ k.T - c, axis=1) - np.interp(t_mag, t_ces, f_ces)
    floor = stim.truth["noise_floor_nT"]
    assert abs(np.sqrt(np.mean(residual ** 2)) - floor) < 0.05 * floor


def test_built_in_scenarios():
    """Each built-in scenario builds by name; every counter but the GPS distractors'
    not_whitelisted is what its faults say, and the recording holds flushes."""
    from maglog.sim.stimulus.config import preset_names
    assert {"default", "short"} <= set(preset_names())
    stim = load_scenario("short").build()
    truth = stim.truth
    assert truth["scenario"] == "short" and truth["until_s"] < 30
    expected = {}
    for fault in truth["faults"]:
        if fault["expect"]:
            key = (fault["channel"], fault["expect"]["cause"])
            expected[key] = expected.get(key, 0) + fault["expect"]["frames"]
    for name, counts in truth["frames"].items():
        for cause in ("checksum", "not_whitelisted", "overlong", "bad_byte", "uart_error",
                      "overflow"):
            if (name, cause) != ("gps", "not_whitelisted"):
                assert counts[cause] == expected.get((name, cause), 0), (name, cause)
    frames = stim.system.recorded_frames()
    assert sum(bool(FLUSHING_GGA.match(f)) for f in frames) >= 10
