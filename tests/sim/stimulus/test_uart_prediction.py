"""The baud-error prediction (sim.stimulus.uart_line.decode at the gateware's bit time) against the
gateware's own receiver (hw.uart.UartRx on the Amaranth simulator), on the default
scenario's lines as the logger's pin sees them."""

from __future__ import annotations

from dataclasses import replace

import pytest

from maglog.hw.frontend import divisor_for
from uart_gateware import uartrx_receives


def _line(system, channel, start, stop):
    """The channel's line level from ``start`` to ``stop`` (s), as segments, from the
    scenario's own pin changes; and the bursts it carries."""
    bursts = [b for b in system.channel_bursts(channel) if start <= b.start < stop]
    shift = bursts[0].start - 1e-3
    part = replace(system, bursts=[replace(b, start=b.start - shift) for b in bursts],
                   presses=[], until=stop - shift)
    changes = part.pin_changes()
    tail = round(4 * part.sampling_bit_cycles(channel))
    segments, now, level = [], 0, 1
    for cycle, uart_rx, _ in changes[1:]:
        bit = (uart_rx >> channel) & 1
        if bit != level:
            segments.append((level, cycle - now))
            now, level = cycle, bit
    segments.append((level, tail))
    return segments, bursts, part


def _gateware(segments, divisor):
    return uartrx_receives(segments, divisor, name="uart_prediction", deadline=10.0)


@pytest.mark.parametrize("channel, start, stop", [
    (2, 150.04, 150.10),        # cesium: the frame cut by the 10 % slow window, its start
    (2, 150.24, 150.35),        # cesium: the window's end and the line back at 9600
    (1, 20.0, 20.07),           # GPS, 1.5 % fast: the first sentences of a group
])
def test_gateware_receives_what_the_truth_predicts(default_stim, channel, start, stop):
    system = default_stim.system
    segments, bursts, part = _line(system, channel, start, stop)
    predicted = [(error, None if error else byte)
                 for burst in bursts for byte, error in part.burst_events(burst)]
    divisor = divisor_for(system.clk_freq, system.channels[channel].baud)
    got = _gateware(segments, divisor)
    assert got == predicted
    assert any(b.baud for b in bursts)
