"""Each injected fault against an independent recount: the same scenario built without it,
and the reference filter fed with what the fault is predicted to do."""

from __future__ import annotations

import tomllib

import numpy as np
import pytest

from maglog.sim.stimulus import sentences
from maglog.sim.reference import COUNTER_NAMES, Kind, ReferenceFilter, reference_filter
from maglog.sim.stimulus import default_scenario_path
from maglog.sim.stimulus.build import NOISE_BYTES
from maglog.sim.stimulus.config import CHANNEL_NAMES, scenario_from_dict

FRAME_FAULTS = ("noise_burst", "dropped_bytes", "bad_checksum")
KINDS = (Kind.PMAG, Kind.NMEA, Kind.CESIUM)


@pytest.fixture(scope="module")
def without_frame_faults():
    """The default scenario without its noise bursts, dropped bytes and bad checksums."""
    data = tomllib.loads(default_scenario_path().read_text())
    for kind in FRAME_FAULTS:
        del data["faults"][kind]
    return scenario_from_dict(data, source="default.toml").build()


def test_frame_fault_counts_against_a_build_without_them(default_stim, without_frame_faults):
    truth, clean = default_stim.truth, without_frame_faults.truth
    expected = {name: dict.fromkeys(COUNTER_NAMES, 0) for name in CHANNEL_NAMES}
    for fault in truth["faults"]:
        if fault["kind"] in FRAME_FAULTS:
            expected[fault["channel"]][fault["expect"]["cause"]] += fault["expect"]["frames"]
            expected[fault["channel"]]["kept"] += fault["kept_delta"]
            assert fault["count"] == fault["expect"]["frames"] == -fault["kept_delta"]
    for name in CHANNEL_NAMES:
        got = {c: truth["frames"][name][c] - clean["frames"][name][c] for c in COUNTER_NAMES}
        assert got == expected[name], name
    # Each kind of frame fault is in the default scenario, on more than one channel.
    assert {(f["kind"], f["channel"]) for f in truth["faults"]} >= {
        ("noise_burst", "mag"), ("noise_burst", "gps"), ("noise_burst", "cesium"),
        ("dropped_bytes", "mag"), ("dropped_bytes", "cesium"), ("bad_checksum", "gps")}


def test_each_faulted_frame_is_what_its_fault_says(default_stim, without_frame_faults):
    clean = {(it.channel, it.type, it.seq): it.data for it in without_frame_faults.items}
    faults = default_stim.scenario.faults
    seen = 0
    for item in default_stim.items:
        for index in item.faults:
            fault = faults[index]
            before = clean[(item.channel, item.type, item.seq)]
            after = item.data
            if fault.kind == "noise_burst":
                extra = len(after) - len(before)
                assert extra == fault.params["length"]
                at = next(i for i in range(len(after)) if after[i] in NOISE_BYTES)
                assert after[:at] + after[at + extra:] == before
                assert all(b in NOISE_BYTES for b in after[at:at + extra])
                cause = "bad_byte"
            elif fault.kind == "dropped_bytes":
                assert len(after) == len(before) - 1
                assert any(before[:i] + before[i + 1:] == after for i in range(len(before)))
                cause = "not_whitelisted" if item.type == "cesium" else "checksum"
            else:
                star = before.index(b"*")
                assert after[:star + 1] == before[:star + 1] and after[star + 3:] == before[star + 3:]
                assert int(after[star + 1:star + 3], 16) != sentences.nmea_checksum(
                    before[1:star])
                cause = "checksum"
            result = reference_filter(KINDS[item.channel], after)
            assert result.counters[cause] == 1 and not result.frames
            seen += 1
    assert seen == sum(f.params["count"] for f in faults if f.kind in FRAME_FAULTS)


def test_baud_error_window_predicted_independently(default_stim):
    """At 10 % slow every ASCII character's stop bit is sampled in its last data bit (0), so
    the receiver flags each: the prediction replaces the window's bytes by error marks."""
    system, truth = default_stim.system, default_stim.truth
    (fault,) = [f for f in truth["faults"] if f["kind"] == "baud_error" and f["error"] < -0.05]
    k = CHANNEL_NAMES.index(fault["channel"])
    nominal = system.channels[k].baud
    ref = ReferenceFilter(KINDS[k])
    slow = 0
    for burst in system.channel_bursts(k):
        if burst.baud is None:
            ref.feed_all(burst.data)
        else:
            assert burst.baud == pytest.approx(nominal * 0.9)
            assert all(b < 0x80 for b in burst.data)
            for byte in burst.data:
                ref.feed(byte, True)
            slow += 1
    assert slow == fault["count"] >= 2
    counters = ref.result.counters
    assert {c: truth["frames"][fault["channel"]][c] for c in counters} == counters
    assert fault["expect"] == {"cause": "uart_error", "frames": 1}
    assert fault["kept_delta"] < 0


def test_small_baud_error_leaves_every_frame(default_stim):
    """The GPS line 1.5 % fast for the whole run: decoded at the nominal bit time, every
    character arrives intact."""
    system, truth = default_stim.system, default_stim.truth
    (fault,) = [f for f in truth["faults"] if f["kind"] == "baud_error" and f["error"] > 0]
    k = CHANNEL_NAMES.index(fault["channel"])
    bursts = system.channel_bursts(k)
    assert all(b.baud == pytest.approx(9600 * 1.015) for b in bursts)
    events, _ = system.received(k)
    assert events == [(byte, False) for byte in system.channel_bytes(k)]
    assert fault["expect"] == {"cause": "uart_error", "frames": 0} and fault["kept_delta"] == 0


def test_gps_outage(default_stim):
    system, truth = default_stim.system, default_stim.truth
    (fault,) = [f for f in truth["faults"] if f["kind"] == "gps_outage"]
    starts = np.array([b.start for b in system.channel_bursts(1)])
    inside = (starts >= fault["start_s"]) & (starts < fault["end_s"])
    assert not inside.any()
    # Groups once a second around it, none in it: five missing.
    groups = sorted({int(np.floor(s)) for s in starts})
    missing = [s for s in range(groups[0], groups[-1]) if s not in groups]
    assert missing == list(range(int(fault["start_s"]), int(fault["end_s"])))
    assert fault["count"] == len(missing) == 5 and fault["expect"] is None


def test_card_busy_goes_to_the_card(default_stim):
    (fault,) = [f for f in default_stim.truth["faults"] if f["kind"] == "card_busy"]
    assert default_stim.card == {"busy_spikes": [[fault["start_s"], fault["end_s"],
                                                  fault["busy_s"]]]}
