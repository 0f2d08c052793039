"""The model's UART receiver (sim/models/logger_uart.py) against the gateware's (hw/uart.py's
UartRx on the Amaranth simulator) on bytes off the receiver's rate, and the model's front end
(sim/models/logger_frontend.py) against the scenario's truth on the default scenario's
baud-error faults."""

from __future__ import annotations

import math
import random

import pytest

from maglog.hw.arch import uart as arch_uart
from maglog.hw.frontend import divisor_for
from maglog.sim.models.logger_frontend import ChannelLine
from maglog.sim.models.logger_uart import UartReceiver, line_changes, received_as_sent
from maglog.sim.reference import ERROR_MARK
from maglog.sim.stimulus.config import CHANNEL_NAMES
from uart_gateware import uartrx_receives

#: NMEA text (ASCII: bit 7 space, so a stop bit read one bit early is a framing error), then
#: bytes that exercise the data bits both ways and a 0x00 (read late: a break).
DATA = (b"$GPGGA,120000.00,4722.6140,N,*6A\r\n" + bytes([0x00, 0xFF, 0x55, 0xAA, 0x80])
        + b"$PMAG1,1,2,3*00\r\n")


def _segments(changes, end):
    """Level changes from cycle 0 (the line idle before) as ``(level, cycles)`` segments
    ending at ``end``."""
    segments, now, level = [], 0, arch_uart.MARK
    for cycle, new in changes:
        segments.append((level, cycle - now))
        now, level = cycle, new
    segments.append((level, end - now))
    return segments


def _gateware(segments, divisor):
    return uartrx_receives(segments, divisor, name="model_uart", deadline=1.0)


def _model(changes, divisor):
    rx = UartReceiver(divisor)
    rx.extend(changes)
    return [(c.error, None if c.error else c.data) for c in rx.run(math.inf)]


# Bit times off the receiver's 16 x divisor by `error` (negative: a fast transmitter):
# around where characters start to fail (the model finds a continuous stream received
# intact from -3.5 % to +5.5 % at divisor 2, damaged beyond -3.9 % and +5.8 %), both signs,
# and far off (resynchronising on edges inside characters).
@pytest.mark.parametrize("divisor, error, intact", [
    (2, -0.045, False), (2, -0.041, False), (2, -0.036, True), (2, 0.056, True),
    (2, 0.059, False), (2, -0.15, False), (2, 0.15, False), (3, 0.06, False),
])
def test_the_model_receives_off_rate_bytes_as_the_gateware_does(divisor, error, intact):
    rng = random.Random(f"{divisor} {error}")
    # The first start bit at a random phase of the receiver's ticks.
    first = 10 + rng.randrange(4 * divisor)
    changes, end = line_changes(first, DATA, arch_uart.OVERSAMPLING * divisor * (1 + error))
    segments = _segments(changes, end + 24 * arch_uart.OVERSAMPLING * divisor)
    got = _model(changes, divisor)
    assert got == _gateware(segments, divisor)
    assert (got == [(False, b) for b in DATA]) is intact


def test_a_glitch_a_break_and_a_damaged_stop_bit_as_the_gateware_takes_them():
    divisor, bit = 2, 32
    changes, end = line_changes(20, b"\x41\x00\x7e", bit * 1.0)
    changes = [(5, 0), (9, 1)] + changes                # a glitch shorter than half a bit
    tail = [(end + 40, 0), (end + 40 + 14 * bit, 1)]    # a break, 14 bits of space
    more, end2 = line_changes(end + 40 + 16 * bit, b"\x5a", bit * 1.0)
    # A stop bit sent as space, the next character right behind it.
    damaged = [(end2 + 30, 0), (end2 + 30 + 2 * bit, 1), (end2 + 30 + 9 * bit, 0),
               (end2 + 30 + 11 * bit, 1)]
    changes = changes + tail + more + damaged
    segments = _segments(changes, end2 + 60 + 40 * bit)
    got = _model(changes, divisor)
    assert got == _gateware(segments, divisor)
    assert (True, None) in got and got[:3] == [(False, 0x41), (False, 0x00), (False, 0x7E)]


@pytest.mark.parametrize("divisor", [1, 2, 3, 12, 22, 326])
def test_bursts_judged_received_as_sent_are(divisor):
    """received_as_sent (the model's shortcut past the receiver) only when the receiver,
    at every tick phase, reports a continuous stream as sent."""
    nominal = arch_uart.OVERSAMPLING * divisor
    rng = random.Random(divisor)
    data = bytes(rng.randrange(256) for _ in range(60)) + DATA
    judged = []
    for permille in range(-60, 61, 6):
        bit = nominal * (1 + permille / 1000)
        if not received_as_sent(bit, divisor):
            continue
        judged.append(permille)
        for origin in range(0, divisor, max(1, divisor // 3)):
            changes, _ = line_changes(7, data, bit)
            rx = UartReceiver(divisor, origin=origin)
            rx.extend(changes)
            assert [(c.error, c.data) for c in rx.run(math.inf)] == \
                [(False, b) for b in data], (permille, origin)
    assert 0 in judged and min(judged) < 0 < max(judged)


def test_the_receiver_resumes_where_the_line_fed_so_far_ends():
    divisor, bit = 3, 48 * 1.08
    changes, end = line_changes(11, DATA, bit)
    whole = _model(changes, divisor)
    rx = UartReceiver(divisor)
    got = []
    for cut in range(0, len(changes), 7):
        rx.extend(changes[cut:cut + 7])
        horizon = changes[cut + 7][0] if cut + 7 < len(changes) else math.inf
        got += [(c.error, None if c.error else c.data) for c in rx.run(horizon)]
    assert got == whole and any(error for error, _ in whole)


def _model_line(system, k):
    """The model's front end for channel ``k`` of a built scenario, fed its bursts."""
    channel = system.channels[k]
    line = ChannelLine(k, channel.kind, max_frame=system.max_frame,
                       clk_freq=system.clk_freq,
                       divisor=divisor_for(system.clk_freq, channel.baud))
    for burst in system.channel_bursts(k):
        line.feed(burst.data, start=burst.start, baud=burst.baud or channel.baud)
    return line


def test_the_model_agrees_with_the_truth_on_the_default_scenarios_baud_faults(default_built):
    system, truth = default_built.system, default_built.truth
    faulted = {f["channel"] for f in truth["faults"] if f["kind"] == "baud_error"}
    assert faulted
    damaged = 0
    for name in sorted(faulted):
        k = CHANNEL_NAMES.index(name)
        line = _model_line(system, k)
        # Character by character, what the receiver reports.
        text = "".join(text for text, _ in line.received())
        events, _ = system.received(k)
        assert [(c == ERROR_MARK, None if c == ERROR_MARK else ord(c)) for c in text] == \
            [(error, None if error else byte) for byte, error in events]
        damaged += text.count(ERROR_MARK)
        # The frames, as the truth counts them.
        result = line.reference()
        assert result.frames == system.received_filter(k).frames
        expected = {cause: n for cause, n in truth["frames"][name].items()
                    if cause in result.counters}
        assert result.counters == expected
        # And the decisions the model times agree with them.
        decisions = line.decisions()
        assert sum(d.outcome == "uart_error" for d in decisions) == expected["uart_error"]
        assert all(a.time <= b.time for a, b in zip(decisions, decisions[1:]))
    # The faults do damage characters (else this test would not test the receiver).
    assert damaged > 0
    fault = [f for f in truth["faults"] if f["kind"] == "baud_error"
             and f["expect"]["frames"] > 0]
    assert fault


def test_the_model_receives_the_default_scenarios_damaged_line_as_the_gateware(
        default_built):
    """The cesium line around the start of its slow window, on the gateware's receiver and
    the model's, from the same line."""
    system = default_built.system
    k = CHANNEL_NAMES.index("cesium")
    window = [b for b in system.channel_bursts(k) if 150.04 <= b.start < 150.10]
    assert any(b.baud for b in window)
    clk = system.clk_freq
    shift = round(window[0].start * clk) - 100
    divisor = divisor_for(clk, system.channels[k].baud)
    changes, end = [], 0
    for burst in window:
        more, end = line_changes(round(burst.start * clk) - shift, burst.data,
                                 clk / (burst.baud or system.channels[k].baud))
        changes += more
    segments = _segments(changes, end + 4 * arch_uart.OVERSAMPLING * divisor)
    got = _model(changes, divisor)
    assert got == _gateware(segments, divisor)
    assert any(error for error, _ in got)
