"""sim.stimulus.system's bursts at an off-nominal rate (the baud-error fault's carrier)."""

from __future__ import annotations

import pytest

from maglog.hw.frame_filter import ChannelKind
from maglog.hw.frontend import ChannelConfig
from maglog.sim.stimulus import sentences
from maglog.sim.stimulus.system import Burst, SystemScenario, Timeline

CHANNELS = (ChannelConfig(ChannelKind.PMAG, 115_200), ChannelConfig(ChannelKind.NMEA, 9_600),
            ChannelConfig(ChannelKind.CESIUM, 9_600))
CLK = 1_843_200.0


def _scenario(bursts):
    return SystemScenario(channels=CHANNELS, clk_freq=CLK, bursts=bursts, presses=[0.001, 0.9],
                          until=1.0)


def test_line_runs_at_the_bursts_rate():
    frame = sentences.cesium(48_000.0, 1000)
    s = _scenario([Burst(2, 0.01, frame, 9600 * 0.9)])
    bit = CLK / (9600 * 0.9)
    edges, level = [], 1
    for cycle, uart_rx, _ in s.pin_changes():
        if (uart_rx >> 2) & 1 != level:
            level ^= 1
            edges.append((cycle, level))
    assert edges[0] == (round(0.01 * CLK), 0)                        # the first start bit
    # "$" = 0x24 LSB first after the start bit: 0 0 1 0 0 1 0 0, then the stop bit: the
    # line rises at bit 3, falls at 4, rises at 6, falls at 7, rises at 9 (the stop bit).
    start = edges[0][0]
    assert [round((c - start) / bit) for c, _ in edges[1:6]] == [3, 4, 6, 7, 9]
    assert s.channel_bursts(2)[0].end(9600) == pytest.approx(0.01 + 18 * 10 / (9600 * 0.9))


@pytest.mark.parametrize("error, kept, uart_errors", [(0.015, 1, 0), (-0.015, 1, 0),
                                                     (-0.10, 0, 1)])
def test_received_decodes_at_the_nominal_bit_time(error, kept, uart_errors):
    frame = sentences.cesium(48_000.0, 1000)
    head, tail = frame[:5], frame[5:]
    line = Timeline(CHANNELS)
    end = line.add(2, 0.01, head)
    line.add(2, end, tail, 9600 * (1 + error))
    s = _scenario(line.bursts)
    events, times = s.received(2)
    result = s.received_filter(2)
    assert len(result.frames) == kept and result.counters["uart_error"] == uart_errors
    assert len(events) == len(frame) and times == sorted(times)
    assert [t for t, _ in s.kept_frames(2)] == ([times[-1]] if kept else [])


def test_json_keeps_the_rate_and_nominal_bursts_stay_as_they_were():
    bursts = [Burst(1, 0.1, b"$GPZDA*00\r\n"), Burst(1, 0.2, b"$GPZDA*00\r\n", 9744.0)]
    data = _scenario(bursts).to_json()
    assert data["bursts"][0] == [1, 0.1, b"$GPZDA*00\r\n".hex()]       # as before
    assert data["bursts"][1][3] == 9744.0
    assert SystemScenario.from_json(data).bursts == bursts
