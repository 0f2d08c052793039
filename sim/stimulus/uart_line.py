"""8N1 UART line: what the wire carries, in clock cycles, and what a receiver should report.

:func:`encode` turns bytes into a run-length trace of the line level (idle high, start bit
low, eight data bits LSB first, stop bit high) at a given bit period in clock cycles, with a
baud-rate error and the faults a receiver must survive: framing errors, breaks and short
glitches. Alongside the trace it gives the :class:`RxEvent` list an ideal receiver reports.
:class:`ChannelStimulus` is what one line of a bench carries: bytes at the nominal bit time,
:class:`Segments` of levels, or both in order.

:func:`decode` is that ideal receiver, kept deliberately plain (edge, centre sampling,
wait for the line to go high after an error); tests use it to cross-check :func:`encode`.
It is not the gateware's receiver.

Edge times are computed as floats from the start of the trace and each is rounded to a whole
cycle on its own, so rounding never accumulates into drift.
"""

from __future__ import annotations

import bisect
import math
from collections.abc import Iterable
from dataclasses import dataclass, field

import numpy as np

from ...hw.arch import uart as arch_uart

__all__ = ["RxEvent", "LineTrace", "encode", "decode", "segments_from_levels", "MIN_BREAK_BITS",
           "GLITCH_MAX_BITS", "Segments", "ChannelStimulus"]

IDLE = 1
SPACE = 0
DATA_BITS = 8
BYTE_MASK = (1 << DATA_BITS) - 1
#: Start bit + data bits + stop bit.
FRAME_BITS = 1 + DATA_BITS + 1
#: A break holds the line low at least this many bit periods (longer than one 8N1 frame).
MIN_BREAK_BITS = 11
#: High time after a framing error or a break before the next start bit, in bit periods.
RECOVERY_BITS = 2.0
#: High time on each side of a glitch, in bit periods.
GLITCH_GUARD_BITS = 1.5
#: A glitch must be shorter than this fraction of a bit to be rejected with certainty.
GLITCH_MAX_BITS = 0.25
#: Smallest bit period: a rejectable glitch must still be at least one cycle wide.
MIN_BIT_CYCLES = 4.0
#: Largest baud-rate error accepted by :func:`encode` (fraction of the nominal rate).
MAX_BAUD_ERROR = 0.25
#: The lead idle must let a receiver see the line high before the first start bit.
MIN_LEAD_IDLE_BITS = 1.0
#: Where in a bit :func:`decode` samples (its centre).
SAMPLE_POINT = 0.5


@dataclass(frozen=True)
class RxEvent:
    """What an ideal receiver reports for one received byte."""

    data: int
    #: Framing error (stop bit low) or break; ``data`` is then not trustworthy.
    error: bool = False


@dataclass(frozen=True)
class LineTrace:
    """A line level trace: ``segments`` of ``(level, cycles)``, alternating levels."""

    segments: list[tuple[int, int]]
    expected: list[RxEvent]
    cycles: int
    #: Actual bit period in cycles (nominal times ``1 + baud_error``).
    bit_period: float = 0.0
    #: Cycle of each data byte's start-bit falling edge, in byte order.
    byte_starts: list[int] = field(default_factory=list)

    def levels(self) -> np.ndarray:
        """The line level in every cycle, as a ``uint8`` array of length ``cycles``."""
        return np.repeat(
            np.array([level for level, _ in self.segments], dtype=np.uint8),
            [duration for _, duration in self.segments],
        )


def _check_positive(value: float, what: str, minimum: float = 0.0, inclusive: bool = True) -> float:
    ok = isinstance(value, (int, float)) and not isinstance(value, bool) and math.isfinite(value)
    ok = ok and (value >= minimum if inclusive else value > minimum)
    if not ok:
        relation = ">=" if inclusive else ">"
        raise ValueError(f"{what} must be a finite number {relation} {minimum:g}, not {value!r}")
    return float(value)


def _index_set(items: Iterable[int], count: int, what: str) -> set[int]:
    result = set()
    for index in items:
        if isinstance(index, bool) or not isinstance(index, int) or not 0 <= index < count:
            raise ValueError(f"{what} index must be an integer 0..{count - 1}, not {index!r}")
        result.add(index)
    return result


def _by_index(items: Iterable[tuple[int, float]], count: int, what: str) -> dict[int, list[float]]:
    result: dict[int, list[float]] = {}
    for item in items:
        index, amount = item
        if isinstance(index, bool) or not isinstance(index, int) or not 0 <= index <= count:
            raise ValueError(f"{what} position must be an integer 0..{count}, not {index!r}")
        result.setdefault(index, []).append(amount)
    return result


class _Line:
    """Accumulates level changes at float times; rounds each one on its own."""

    def __init__(self) -> None:
        self.level = IDLE
        self.changes: list[tuple[float, int]] = []

    def set(self, time: float, level: int) -> None:
        if level != self.level:
            self.changes.append((time, level))
            self.level = level

    def segments(self, end: float) -> list[tuple[int, int]]:
        edges = [0] + [_round_cycle(time) for time, _ in self.changes] + [_round_cycle(end)]
        levels = [IDLE] + [level for _, level in self.changes]
        segments = []
        for level, start, stop in zip(levels, edges, edges[1:]):
            if stop <= start:
                raise ValueError("Bit period too short: two line edges fall on the same cycle")
            segments.append((level, stop - start))
        return segments


def _round_cycle(time: float) -> int:
    return math.floor(time + 0.5)  # half up, independent of float formatting


def encode(
    data: bytes,
    *,
    bit_cycles: float,
    baud_error: float = 0.0,
    gap_bits: float = 0.0,
    framing_errors: Iterable[int] = (),
    breaks: Iterable[tuple[int, float]] = (),
    glitches: Iterable[tuple[int, int]] = (),
    lead_idle_bits: float = 2.0,
    tail_idle_bits: float = 2.0,
) -> LineTrace:
    """Encode ``data`` as an 8N1 line trace with optional faults.

    - ``bit_cycles``: nominal bit period in clock cycles; the actual one is
      ``bit_cycles * (1 + baud_error)``.
    - ``gap_bits``: idle time after each stop bit, in bit periods.
    - ``framing_errors``: indices of bytes sent with a low stop bit; the line then stays high
      for at least 2 bit periods. Expected ``RxEvent(byte, True)``.
    - ``breaks``: ``(before_index, length_bits)``, ``length_bits >= 11``: the line is held low
      that long before byte ``before_index`` (``len(data)``: after the last byte), then high
      for at least 2 bit periods. Expected ``RxEvent(0, True)``.
    - ``glitches``: ``(before_index, width_cycles)``: a low pulse in the idle time before byte
      ``before_index``, shorter than a quarter bit, with at least 1.5 bit periods of high line
      on each side. Expected: nothing.
    """
    data = bytes(data)
    nominal = _check_positive(bit_cycles, "Bit period in cycles", MIN_BIT_CYCLES)
    if not isinstance(baud_error, (int, float)) or not abs(baud_error) <= MAX_BAUD_ERROR:
        raise ValueError(f"Baud error must be within ±{MAX_BAUD_ERROR}, not {baud_error!r}")
    period = nominal * (1 + baud_error)
    gap = _check_positive(gap_bits, "Gap in bits") * period
    lead = _check_positive(lead_idle_bits, "Lead idle in bits", MIN_LEAD_IDLE_BITS) * period
    tail = _check_positive(tail_idle_bits, "Tail idle in bits") * period
    bad_stops = _index_set(framing_errors, len(data), "Framing error")
    break_map = _by_index(breaks, len(data), "Break")
    for lengths in break_map.values():
        for length in lengths:
            _check_positive(length, "Break length in bits", MIN_BREAK_BITS)
    glitch_map = _by_index(glitches, len(data), "Glitch")
    max_glitch = GLITCH_MAX_BITS * period
    for widths in glitch_map.values():
        for width in widths:
            if isinstance(width, bool) or not isinstance(width, int) or width < 1:
                raise ValueError(f"Glitch width must be a positive whole number of cycles, not {width!r}")
            if width >= max_glitch:
                raise ValueError(
                    f"Glitch width must be shorter than a quarter bit ({max_glitch:g} cycles), "
                    f"not {width!r}: a receiver's response to it is undefined"
                )

    line = _Line()
    expected: list[RxEvent] = []
    byte_starts: list[float] = []
    now = lead  # earliest time the next start bit, break or glitch may begin
    high_since = 0.0  # when the line last went high

    for index in range(len(data) + 1):
        for width in glitch_map.get(index, []):
            start = math.ceil(max(now, high_since + GLITCH_GUARD_BITS * period))
            line.set(start, SPACE)
            line.set(start + width, IDLE)
            high_since = start + width
            now = high_since + GLITCH_GUARD_BITS * period
        for length in break_map.get(index, []):
            line.set(now, SPACE)
            high_since = now + length * period
            line.set(high_since, IDLE)
            expected.append(RxEvent(0, True))
            now = high_since + RECOVERY_BITS * period
        if index == len(data):
            break
        byte = data[index]
        framing_error = index in bad_stops
        bits = [SPACE] + [(byte >> bit) & 1 for bit in range(DATA_BITS)]
        bits.append(SPACE if framing_error else IDLE)
        byte_starts.append(now)
        for bit, level in enumerate(bits):
            if level == IDLE and line.level == SPACE:
                high_since = now + bit * period
            line.set(now + bit * period, level)
        end = now + FRAME_BITS * period
        expected.append(RxEvent(byte, framing_error))
        if framing_error:
            line.set(end, IDLE)
            high_since = end
            now = end + max(gap, RECOVERY_BITS * period)
        else:
            now = end + gap

    end = now + tail
    segments = line.segments(end)
    return LineTrace(
        segments=segments,
        expected=expected,
        cycles=sum(duration for _, duration in segments),
        bit_period=period,
        byte_starts=[_round_cycle(time) for time in byte_starts],
    )


def decode(segments: Iterable[tuple[int, int]], *, bit_cycles: float) -> list[RxEvent]:
    """An ideal 8N1 receiver over a segment trace.

    It waits for the line to be high, takes the next falling edge as a start bit, checks the
    start bit's centre is still low (else it was a glitch), samples each data bit and the stop
    bit at their centres, and reports a framing error or break when the stop bit is low; after
    an error it waits for the line to go high again. A byte cut off by the end of the trace
    is not reported.
    """
    period = _check_positive(bit_cycles, "Bit period in cycles", 0.0, inclusive=False)
    starts: list[int] = []
    levels: list[int] = []
    time = 0
    for level, duration in segments:
        if duration < 1:
            raise ValueError(f"Segment durations must be at least one cycle, not {duration!r}")
        if levels and level == levels[-1]:  # merge equal neighbours
            time += duration
            continue
        starts.append(time)
        levels.append(level)
        time += duration
    total = time

    def level_at(at: float) -> int:
        return levels[bisect.bisect_right(starts, math.floor(at)) - 1]

    def next_change(after: float, to_level: int) -> int | None:
        """First cycle > ``after`` at which the line changes to ``to_level``."""
        index = bisect.bisect_right(starts, math.floor(after))
        while index < len(starts):
            if levels[index] == to_level:
                return starts[index]
            index += 1
        return None

    events: list[RxEvent] = []
    cursor: float = -1.0
    if levels and levels[0] == SPACE:  # the line starts low: wait for it to go high first
        high = next_change(0, IDLE)
        cursor = total if high is None else high
    while True:
        edge = next_change(cursor, SPACE)
        if edge is None:
            break
        centre = edge + SAMPLE_POINT * period
        stop_centre = edge + (FRAME_BITS - 1 + SAMPLE_POINT) * period
        if stop_centre >= total:
            break
        if level_at(centre) != SPACE:
            cursor = centre  # glitch: not a start bit
            continue
        byte = 0
        for bit in range(DATA_BITS):
            byte |= level_at(centre + (1 + bit) * period) << bit
        if level_at(stop_centre) == IDLE:
            events.append(RxEvent(byte, False))
            cursor = stop_centre
        else:
            events.append(RxEvent(byte, True))
            high = next_change(stop_centre, IDLE)
            if high is None:
                break
            cursor = high
    return events


def segments_from_levels(levels) -> list[tuple[int, int]]:
    """Run-length ``(level, cycles)`` segments of a per-cycle level array (the inverse of
    :meth:`LineTrace.levels`), for tests that edit a line cycle by cycle."""
    levels = np.asarray(levels, dtype=np.uint8)
    if levels.size == 0:
        return []
    edges = np.flatnonzero(np.diff(levels)) + 1
    starts = np.concatenate(([0], edges))
    lengths = np.diff(np.concatenate((starts, [levels.size])))
    return [(int(levels[a]), int(n)) for a, n in zip(starts, lengths)]


class Segments(list):
    """A piece of a line given as ``(level, cycles)`` pairs (as :func:`encode` gives)."""


@dataclass
class ChannelStimulus:
    """What one serial line carries.

    ``data`` is sent as plain 8N1 characters back to back at the divisor's nominal bit time
    (by cocotbext-uart's ``UartSource`` on the cocotb backends); ``segments`` are
    ``(level, cycles)`` pairs, for baud error and line faults. ``parts`` mixes both in
    order: each item is ``bytes`` or a :class:`Segments`. ``expected`` frames, if given, are
    checked in order by the scoreboard as they arrive.
    """
    divisor: int
    data: bytes | None = None
    segments: list | None = None
    expected: list | None = None
    parts: list | None = None

    def __post_init__(self):
        given = [x is not None for x in (self.data, self.segments, self.parts)]
        if sum(given) != 1:
            raise ValueError("A channel's stimulus is one of data, segments or parts")
        if self.parts is None:
            self.parts = [bytes(self.data)] if self.data is not None else [
                Segments(self.segments)]
        for part in self.parts:
            if not isinstance(part, (bytes, Segments)):
                raise ValueError(f"A stimulus part is bytes or Segments, not {part!r}")

    @property
    def bit_cycles(self):
        return arch_uart.OVERSAMPLING * self.divisor

    def line_segments(self):
        segments = []
        for part in self.parts:
            if isinstance(part, Segments):
                segments.extend(part)
            else:
                # Back to back from the first start bit, as UartSource sends them.
                segments.extend(encode(part, bit_cycles=self.bit_cycles, lead_idle_bits=1.0,
                                       tail_idle_bits=0.0).segments)
        return segments

    def line_cycles(self):
        return sum(cycles for _, cycles in self.line_segments())
