"""System scenarios: what the log of a recording must hold comes from the reference filter,
and a scenario whose frame order or record window would depend on the backend is refused."""

import pytest

from maglog.hw.frame_filter import ChannelKind
from maglog.hw.frontend import ChannelConfig
from maglog.sim.stimulus import sentences
from maglog.sim.reference import Kind, reference_filter
from maglog.sim.stimulus.system import (MIN_END_GAP_S, UART_FRAME_BITS, Burst, SystemScenario,
                               short_scenario)


CHANNELS = (ChannelConfig(ChannelKind.PMAG, 230_400), ChannelConfig(ChannelKind.NMEA, 230_400))
PMAG = sentences.pmag1(1, 10.0, 20.0, 30.0)
GGA = sentences.gga(43200.0, 47.0, 8.0)


def scenario(bursts, presses=(0.0, 1.0)):
    return SystemScenario(channels=CHANNELS, clk_freq=3.6864e6, bursts=bursts,
                          presses=list(presses), until=1.0)


def test_short_scenario_records_every_channel_and_four_fixes():
    s = short_scenario()
    frames = s.recorded_frames()
    # Independently of the scenario's own bookkeeping: the reference filter over each
    # channel's whole stream, restricted to the recording by content.
    for k, kind in enumerate((Kind.PMAG, Kind.NMEA, Kind.CESIUM)):
        kept = reference_filter(kind, s.channel_bytes(k)).frames
        in_log = [f for f in frames if f in kept]
        assert in_log, f"channel {k} has no frame in the log"
    flushes = [f for f in frames if f.startswith(b"$GPGGA") and f.split(b",")[6] != b"0"]
    assert len(flushes) == 4
    # The idle-time ZDA and GGA are kept by the filter but not recorded.
    assert not any(f.startswith(b"$GPZDA") for f in frames)
    assert frames == short_scenario().recorded_frames()       # seeded: the same twice


def test_log_order_is_by_frame_end():
    baud = CHANNELS[0].baud
    pmag_start = 0.010
    pmag_end = pmag_start + len(PMAG) * UART_FRAME_BITS / baud
    # The GGA (channel 1) starts first and ends first, though the PMAG is on channel 0;
    # then a second PMAG ends last.
    gga_start = pmag_end - MIN_END_GAP_S * 2 - len(GGA) * UART_FRAME_BITS / baud
    s = scenario([Burst(0, pmag_start, PMAG), Burst(1, gga_start, GGA),
                  Burst(0, 0.020, PMAG)])
    assert gga_start < pmag_start
    assert s.log_frames(0.0, 1.0) == [GGA, PMAG, PMAG]
    assert s.log_frames(0.0, 0.015) == [GGA, PMAG]


def test_frames_ending_too_close_are_refused():
    baud = CHANNELS[0].baud
    end = 0.010 + len(PMAG) * UART_FRAME_BITS / baud
    gga_start = end + MIN_END_GAP_S / 4 - len(GGA) * UART_FRAME_BITS / baud
    s = scenario([Burst(0, 0.010, PMAG), Burst(1, gga_start, GGA)])
    with pytest.raises(ValueError, match="closer than"):
        s.log_frames(0.0, 1.0)


def test_overlapping_bursts_on_one_line_are_refused():
    with pytest.raises(ValueError, match="overlap"):
        scenario([Burst(0, 0.010, PMAG), Burst(0, 0.0101, PMAG)])


def test_a_busy_line_at_a_press_is_refused():
    s = scenario([Burst(0, 0.010, PMAG)], presses=(0.0101, 0.5))
    with pytest.raises(ValueError, match="busy within"):
        s.check_quiet(0.001)
    s.presses = [0.5, 0.9]
    s.check_quiet(0.001)


def test_a_burst_on_a_channel_that_does_not_exist_is_refused():
    with pytest.raises(ValueError, match="Burst channel must be in 0..1, not 2"):
        scenario([Burst(2, 0.0, PMAG)])


def _line(changes, bit, end):
    segments = []
    for (cycle, uart_rx, _), (next_cycle, _, _) in zip(changes, changes[1:] + [(end, 0, 0)]):
        level = (uart_rx >> bit) & 1
        if segments and segments[-1][0] == level:
            segments[-1] = (level, segments[-1][1] + next_cycle - cycle)
        else:
            segments.append((level, next_cycle - cycle))
    return segments


def test_pin_changes_carry_every_byte_and_the_presses():
    from maglog.sim.stimulus.uart_line import decode
    s = short_scenario()
    changes = s.pin_changes()
    end = round(s.until * s.clk_freq)
    assert changes[0] == (0, 0b111, 0)
    for k in range(3):
        events = decode(_line(changes, k, end), bit_cycles=s.bit_cycles(k))
        assert bytes(e.data for e in events) == s.channel_bytes(k)
        assert not any(e.error for e in events)
    edges = [(cycle, button) for (cycle, _, button), (_, _, before)
             in zip(changes[1:], changes) if button != before]
    assert edges == [(round(p * s.clk_freq), 1) if n % 2 == 0 else
                     (round((s.presses[n // 2] + s.hold) * s.clk_freq), 0)
                     for n, p in enumerate(x for p in s.presses for x in (p, p))]


def test_a_scenario_survives_json():
    import json
    s = short_scenario(seed=3)
    back = SystemScenario.from_json(json.loads(json.dumps(s.to_json())))
    assert back.pin_changes() == s.pin_changes()
    assert back.recorded_frames() == s.recorded_frames()
    assert (back.until, back.hold, back.debounce_s, back.timestamp) == (
        s.until, s.hold, s.debounce_s, s.timestamp)
