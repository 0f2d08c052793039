"""Tests for maglog.sim.stimulus.uart_line: exact traces, round trips with baud error and faults."""

from __future__ import annotations

import numpy as np
import pytest

from maglog.sim.stimulus.uart_line import LineTrace, RxEvent, decode, encode

BAUD_ERRORS = [-0.03, -0.02, -0.01, 0.0, 0.01, 0.02, 0.03]
BIT_CYCLES = [16, 10.4, 104.17]


def random_bytes(seed: int, count: int = 64) -> bytes:
    return bytes(np.random.default_rng(seed).integers(0, 256, size=count).tolist())


def check_trace(trace: LineTrace) -> None:
    """Structural invariants of every trace."""
    assert trace.segments, "empty trace"
    assert trace.segments[0][0] == 1, "the line must start idle (high)"
    assert trace.segments[-1][0] == 1, "the line must end idle (high)"
    for (level, duration), (next_level, _) in zip(trace.segments, trace.segments[1:]):
        assert level in (0, 1) and next_level in (0, 1)
        assert level != next_level, "consecutive segments must alternate"
    assert all(isinstance(d, int) and d >= 1 for _, d in trace.segments)
    assert sum(d for _, d in trace.segments) == trace.cycles
    assert len(trace.levels()) == trace.cycles


def low_runs(trace: LineTrace) -> list[tuple[int, int]]:
    """(start cycle, length) of every low segment."""
    runs, time = [], 0
    for level, duration in trace.segments:
        if level == 0:
            runs.append((time, duration))
        time += duration
    return runs


# --- exact traces -------------------------------------------------------------------------


def test_exact_trace_of_0x55() -> None:
    trace = encode(b"\x55", bit_cycles=8)
    # idle 2 bits, start 0, data 1 0 1 0 1 0 1 0 (LSB first), stop 1, idle 2 bits
    assert trace.segments == [(1, 16)] + [(0, 8), (1, 8)] * 4 + [(0, 8), (1, 8 + 16)]
    assert trace.expected == [RxEvent(0x55, False)]
    assert trace.cycles == 16 + 10 * 8 + 16
    assert trace.byte_starts == [16]


def test_exact_trace_of_0x0f_lsb_first() -> None:
    trace = encode(b"\x0f", bit_cycles=10, lead_idle_bits=1, tail_idle_bits=0)
    assert trace.segments == [(1, 10), (0, 10), (1, 40), (0, 40), (1, 10)]


def test_edges_do_not_drift() -> None:
    bit = 10.4
    data = random_bytes(1, 300)
    trace = encode(data, bit_cycles=bit, gap_bits=0.3)
    for index, start in enumerate(trace.byte_starts):
        assert start == int(np.floor((2 + index * 10.3) * bit + 0.5))
    assert trace.cycles == int(np.floor((2 + len(data) * 10.3 + 2) * bit + 0.5))
    check_trace(trace)


def test_baud_error_scales_the_bit_period() -> None:
    data = random_bytes(2, 100)
    slow = encode(data, bit_cycles=16, baud_error=0.03)
    fast = encode(data, bit_cycles=16, baud_error=-0.03)
    assert slow.bit_period == pytest.approx(16 * 1.03)
    assert slow.cycles == pytest.approx(16 * 1.03 * (4 + 10 * len(data)), abs=1)
    assert fast.cycles == pytest.approx(16 * 0.97 * (4 + 10 * len(data)), abs=1)
    # The decoder at the nominal rate cannot follow a 10 % error: the error really is applied.
    assert decode(encode(data, bit_cycles=16, baud_error=0.1).segments, bit_cycles=16) != [
        RxEvent(b, False) for b in data
    ]


# --- round trips --------------------------------------------------------------------------


@pytest.mark.parametrize("bit_cycles", BIT_CYCLES)
@pytest.mark.parametrize("baud_error", BAUD_ERRORS)
def test_round_trip_clean(bit_cycles: float, baud_error: float) -> None:
    data = random_bytes(int(bit_cycles * 1000 + baud_error * 100))
    for gap in (0.0, 0.5, 3.0):
        trace = encode(data, bit_cycles=bit_cycles, baud_error=baud_error, gap_bits=gap)
        check_trace(trace)
        assert trace.expected == [RxEvent(b, False) for b in data]
        assert decode(trace.segments, bit_cycles=bit_cycles) == trace.expected


@pytest.mark.parametrize("baud_error", BAUD_ERRORS)
def test_round_trip_framing_errors(baud_error: float) -> None:
    rng = np.random.default_rng(11)
    data = random_bytes(12, 80)
    bad = {int(i) for i in rng.choice(len(data), size=12, replace=False)} | {0, len(data) - 1}
    trace = encode(data, bit_cycles=16, baud_error=baud_error, framing_errors=bad)
    check_trace(trace)
    assert trace.expected == [RxEvent(b, i in bad) for i, b in enumerate(data)]
    assert decode(trace.segments, bit_cycles=16) == trace.expected
    # After a bad stop bit the line is high for at least two bit periods before the next start.
    levels = trace.levels()
    for index in sorted(bad - {len(data) - 1}):
        stop_end = trace.byte_starts[index] + round(10 * trace.bit_period)
        next_start = trace.byte_starts[index + 1]
        assert next_start - stop_end >= 2 * trace.bit_period - 2  # two edges, each rounded
        assert levels[stop_end + 1 : next_start].all()


@pytest.mark.parametrize("baud_error", BAUD_ERRORS)
def test_round_trip_breaks(baud_error: float) -> None:
    data = random_bytes(13, 30)
    breaks = [(0, 11), (7, 20.5), (7, 11), (15, 100), (30, 12)]
    trace = encode(data, bit_cycles=16, baud_error=baud_error, breaks=breaks)
    check_trace(trace)
    expected = [RxEvent(b, False) for b in data]
    for position in sorted({p for p, _ in breaks}, reverse=True):
        expected[position:position] = [RxEvent(0, True)] * sum(1 for p, _ in breaks if p == position)
    assert trace.expected == expected
    assert decode(trace.segments, bit_cycles=16) == expected
    long_lows = [length for _, length in low_runs(trace) if length >= 11 * trace.bit_period - 1]
    assert long_lows == pytest.approx([length * trace.bit_period for _, length in breaks], abs=1)


@pytest.mark.parametrize("baud_error", BAUD_ERRORS)
def test_round_trip_glitches(baud_error: float) -> None:
    data = random_bytes(14, 40)
    period = 16 * (1 + baud_error)
    widths = [1, 2, int(np.ceil(period / 4)) - 1]
    glitches = [(0, widths[0]), (5, widths[1]), (5, widths[2]), (20, 1), (40, widths[2])]
    trace = encode(data, bit_cycles=16, baud_error=baud_error, glitches=glitches)
    check_trace(trace)
    assert trace.expected == [RxEvent(b, False) for b in data]
    assert decode(trace.segments, bit_cycles=16) == trace.expected
    # Each glitch is there, exactly as wide as asked, with 1.5 bits of high line around it.
    short = [(start, length) for start, length in low_runs(trace) if length < period / 4]
    assert [length for _, length in short] == [width for _, width in glitches]
    levels = trace.levels()
    guard = int(np.ceil(1.5 * period)) - 1
    for start, length in short:
        assert levels[start - guard : start].all()
        assert levels[start + length : start + length + guard].all()


@pytest.mark.parametrize("baud_error", [-0.03, 0.0, 0.03])
@pytest.mark.parametrize("seed", range(5))
def test_round_trip_all_faults_together(baud_error: float, seed: int) -> None:
    rng = np.random.default_rng(seed)
    data = random_bytes(100 + seed, 120)
    framing = [int(i) for i in rng.choice(len(data), size=6, replace=False)]
    breaks = [(int(i), float(rng.uniform(11, 30))) for i in rng.integers(0, len(data) + 1, size=4)]
    glitches = [(int(i), int(rng.integers(1, 3))) for i in rng.integers(0, len(data) + 1, size=8)]
    for bit_cycles in (16, 10.4):
        trace = encode(
            data,
            bit_cycles=bit_cycles,
            baud_error=baud_error,
            gap_bits=float(rng.uniform(0, 2)),
            framing_errors=framing,
            breaks=breaks,
            glitches=glitches,
            lead_idle_bits=1.0,
            tail_idle_bits=0.0,
        )
        check_trace(trace)
        assert len(trace.expected) == len(data) + len(breaks)
        assert sum(e.error for e in trace.expected) == len(set(framing)) + len(breaks)
        assert decode(trace.segments, bit_cycles=bit_cycles) == trace.expected


# --- decode on hand-made traces -----------------------------------------------------------


def test_decode_hand_made() -> None:
    bit = 6
    # 'A' = 0x41: LSB first 1 0 0 0 0 0 1 0
    a = [(0, bit), (1, bit), (0, 5 * bit), (1, bit), (0, bit), (1, bit)]
    assert decode([(1, 3)] + a + [(1, 7)], bit_cycles=bit) == [RxEvent(0x41, False)]
    # Same byte with a low stop bit, then the line returns high.
    bad = [(0, bit), (1, bit), (0, 5 * bit), (1, bit), (0, 2 * bit), (1, 3 * bit)]
    assert decode([(1, 3)] + bad, bit_cycles=bit) == [RxEvent(0x41, True)]
    # A break, a glitch, then 0x00.
    trace = [(1, 10), (0, 20 * bit), (1, 2 * bit), (0, 1), (1, 2 * bit), (0, 9 * bit), (1, 2 * bit)]
    assert decode(trace, bit_cycles=bit) == [RxEvent(0, True), RxEvent(0, False)]
    # A line that starts low is not a start bit; a byte cut off by the end is not reported.
    assert decode([(0, 30), (1, 10), (0, bit), (1, 3 * bit)], bit_cycles=bit) == []
    # Equal neighbouring segments merge.
    assert decode([(1, 2), (1, 1)] + a + [(1, 7)], bit_cycles=bit) == [RxEvent(0x41, False)]


# --- argument checks ----------------------------------------------------------------------


@pytest.mark.parametrize(
    ("kwargs", "message"),
    [
        ({"bit_cycles": 3}, "Bit period in cycles must be a finite number >= 4"),
        ({"baud_error": 0.5}, "Baud error"),
        ({"gap_bits": -1}, "Gap in bits"),
        ({"lead_idle_bits": 0.5}, "Lead idle in bits"),
        ({"framing_errors": [3]}, "Framing error index must be an integer 0..2, not 3"),
        ({"breaks": [(0, 10)]}, "Break length in bits must be a finite number >= 11"),
        ({"breaks": [(4, 12)]}, "Break position must be an integer 0..3, not 4"),
        ({"glitches": [(0, 4)]}, "Glitch width must be shorter than a quarter bit"),
        ({"glitches": [(0, 0)]}, "Glitch width must be a positive whole number"),
        ({"glitches": [(0, 1.5)]}, "Glitch width must be a positive whole number"),
    ],
)
def test_encode_argument_checks(kwargs: dict, message: str) -> None:
    args = {"bit_cycles": 16} | kwargs
    with pytest.raises(ValueError, match=message):
        encode(b"abc", **args)


def test_glitch_limit_follows_baud_error() -> None:
    encode(b"a", bit_cycles=16, baud_error=0.03, glitches=[(0, 4)])  # 4 < 16.48 / 4
    with pytest.raises(ValueError, match="quarter bit"):
        encode(b"a", bit_cycles=16, baud_error=-0.03, glitches=[(0, 4)])


def test_empty_data() -> None:
    trace = encode(b"", bit_cycles=16)
    assert trace.segments == [(1, 64)] and trace.expected == []
    trace = encode(b"", bit_cycles=16, breaks=[(0, 11)])
    assert decode(trace.segments, bit_cycles=16) == trace.expected == [RxEvent(0, True)]
