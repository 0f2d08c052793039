"""UartRx on the Amaranth simulator against the line encoder's expected characters."""

import random

import pytest

from maglog.hw.uart import UartRx
from maglog.sim.backends.amaranth import collect_payloads, drive_line, run_simulation
from maglog.sim.stimulus.uart_line import LineTrace, RxEvent, encode, segments_from_levels


def run_rx(steps, *, divisor_init=1, ready=None, tail_cycles=200):
    """Drive ``(divisor, segments)`` steps into a UartRx (divisor None: leave it); return the
    payloads it offered and that were taken."""
    dut = UartRx(divisor_init=divisor_init)
    got = []

    async def line(ctx):
        for divisor, segments in steps:
            if divisor is not None:
                ctx.set(dut.divisor, divisor)
            await drive_line(ctx, dut.rx, segments)
        await ctx.tick().repeat(tail_cycles)

    async def sink(ctx):
        await collect_payloads(ctx, dut.o, got, ready=ready)

    run_simulation(dut, [line], background=[sink], name="uart_rx", deadline=1.0)
    return got


def receive(trace, *, divisor, ready=None):
    """Drive ``trace`` into a UartRx and return what it reports as RxEvents, and raw."""
    got = run_rx([(None, trace.segments)], divisor_init=divisor, ready=ready,
                 tail_cycles=40 * divisor)
    return [RxEvent(0 if p.brk else p.data, bool(p.framing_error or p.brk or p.overrun))
            for p in got], got


def same(events, expected):
    """Compare, ignoring the (untrustworthy) value of errored characters."""
    norm = lambda evs: [(e.error, None if e.error else e.data) for e in evs]
    return norm(events) == norm(expected)


@pytest.mark.parametrize("divisor", [1, 2, 5])
def test_random_bytes_back_to_back(divisor):
    rng = random.Random(divisor)
    data = bytes(rng.randrange(256) for _ in range(96))
    trace = encode(data, bit_cycles=16 * divisor)
    events, _ = receive(trace, divisor=divisor)
    assert events == trace.expected


@pytest.mark.parametrize("error", [-0.03, -0.02, -0.01, 0.01, 0.02, 0.03])
def test_baud_error(error):
    rng = random.Random(int(error * 1000))
    data = bytes(rng.randrange(256) for _ in range(64)) + b"\x00\xff\x55\xaa"
    trace = encode(data, bit_cycles=32, baud_error=error)
    events, _ = receive(trace, divisor=2)
    assert events == trace.expected


def test_glitches_shorter_than_a_quarter_bit_are_rejected():
    data = b"$GPGGA"
    # 64-cycle bits: every width up to just under 16 cycles (a quarter bit).
    glitches = [(i % len(data), width) for i, width in enumerate(range(1, 16))]
    trace = encode(data, bit_cycles=64, glitches=glitches)
    events, _ = receive(trace, divisor=4)
    assert events == trace.expected == [RxEvent(b) for b in data]


def test_glitch_inside_a_bit_is_voted_out():
    # A one-tick pulse on each bit's middle sample; majority vote keeps the value.
    divisor = 4
    bit = 16 * divisor
    data = bytes([0x00, 0xFF, 0x5A])
    clean = encode(data, bit_cycles=bit, gap_bits=1.0)
    levels = clean.levels().copy()
    for start in clean.byte_starts:
        for k in range(10):
            centre = start + k * bit + bit // 2
            levels[centre:centre + divisor] ^= 1
    trace = LineTrace(segments=segments_from_levels(levels), cycles=len(levels),
                      expected=[RxEvent(b) for b in data])
    events, _ = receive(trace, divisor=divisor)
    assert events == trace.expected


def test_framing_errors_and_breaks_are_flagged_and_recovered():
    data = b"$PMAG1,12345*00\r\n"
    trace = encode(data, bit_cycles=32, framing_errors=[3, 9], breaks=[(12, 20), (len(data), 30)])
    events, raw = receive(trace, divisor=2)
    assert same(events, trace.expected)
    breaks = [p for p in raw if p.brk]
    assert len(breaks) == 2 and all(p.framing_error for p in breaks)
    # Every byte after a fault came through clean.
    assert bytes(e.data for e in events if not e.error) == bytes(
        b for i, b in enumerate(data) if i not in (3, 9))


def test_overrun_flags_the_character_that_replaced_an_unread_one():
    data = b"ABC"
    trace = encode(data, bit_cycles=16)
    # Not ready until long after the second character: the first is lost.
    bit_cycles = 16
    events, raw = receive(trace, divisor=1,
                          ready=lambda cycle: cycle > trace.byte_starts[1] + 11 * bit_cycles)
    assert [(p.data, bool(p.overrun)) for p in raw] == [(ord("B"), True), (ord("C"), False)]


def test_divisor_changes_at_run_time():
    got = run_rx([(None, encode(b"fast", bit_cycles=16).segments),
                  (3, encode(b"slow", bit_cycles=48).segments)])
    assert bytes(p.data for p in got) == b"fastslow"
    assert not any(p.framing_error for p in got)


def test_divisor_zero_acts_as_one():
    got = run_rx([(0, encode(b"zero", bit_cycles=16).segments)], divisor_init=5)
    assert bytes(p.data for p in got) == b"zero"


def test_parameters_are_checked():
    with pytest.raises(TypeError, match="Divisor width must be a positive integer, not 0"):
        UartRx(divisor_bits=0)
    with pytest.raises(ValueError, match="Initial divisor must be an integer from 1 to 255, "
                                         "not 256"):
        UartRx(divisor_bits=8, divisor_init=256)
