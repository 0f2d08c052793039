"""The gateware's UART receiver (hw/uart.py's ``UartRx``) at decision level, for the
transaction-level model: what it reports for bytes on a line that does not run at its own
bit time (a transmitter off the nominal rate, or a divisor that does not divide the clock
exactly).

The receiver is modelled as the gateware samples, from the line's level changes in clock
cycles, jumping from one sampling decision to the next rather than clocking:

- The line passes a two flip-flop synchroniser: the receiver's logic sees the pin
  :data:`SYNC_CYCLES` cycles late.
- An oversampling tick every ``divisor`` cycles, free-running from the end of reset
  (cycles ``origin``, ``origin + divisor``, ...): ``f_clk / (16 * divisor)`` baud.
- Hunting (IDLE): the first tick whose sample is space is tick 0 of a start bit.
- Each bit is decided at its tick 9 (``arch.VOTE_TICKS[-1]``) as the majority of its ticks
  7, 8 and 9; bit ``k`` (0 the start bit, 1-8 the data LSB first, 9 the stop bit) at tick
  ``16 k + 9`` after tick 0.
- A start bit that is not space at its vote is a glitch: back to hunting from the next tick.
- The stop bit's vote emits the character. Mark: back to hunting. Space with data 0: a
  break, wait for a tick that samples mark, then hunt. Space with other data: a framing
  error, and the receiver keeps its bit timing: the next bit slot (16 ticks on) is taken as
  a start bit if its vote is space.

No overrun: the frame filter is always ready. Nothing here predicts from the scenario's
truth: the model and the truth's ideal receiver (sim/stimulus/uart_line.py's ``decode``)
are independent, and tests hold both to the gateware.
"""

from __future__ import annotations

import bisect
import functools
import math

from ...hw.arch import uart as arch_uart


__all__ = ["UartReceiver", "RxChar", "SYNC_CYCLES", "line_changes", "received_as_sent"]

#: Cycles from the ``uart_rx`` pin to the receiver's logic (the two-flop synchroniser).
SYNC_CYCLES = 2

_MARK, _SPACE = arch_uart.MARK, arch_uart.SPACE
_OVER = arch_uart.OVERSAMPLING
_VOTES = arch_uart.VOTE_TICKS
_DECIDE = _VOTES[-1]
_STOP = arch_uart.CHARACTER_BITS - 1

_IDLE, _START, _RECEIVE, _WAIT_MARK = range(4)


class RxChar(tuple):
    """``(cycle, data, error)``: a character the receiver emits at ``cycle`` (its stop
    bit's vote), its data bits and whether the stop bit was space (framing error or break)."""
    __slots__ = ()

    def __new__(cls, cycle, data, error):
        return super().__new__(cls, (cycle, data, error))

    cycle = property(lambda self: self[0])
    data = property(lambda self: self[1])
    error = property(lambda self: self[2])


def line_changes(first, data, bit_cycles):
    """The level changes ``(cycle, level)`` of ``data`` sent 8N1 back to back from cycle
    ``first`` at ``bit_cycles`` clock cycles a bit, and the cycle the last stop bit ends.

    Byte ``i`` is due at ``first + round(10 i bit_cycles)`` (later if the previous one has
    not ended: each character is whole), and its bit ``k`` starts ``floor(k bit_cycles +
    1/2)`` cycles after its start bit, as the Verilator harness's transmitter sends them
    (sim/backends/fast_harness.cpp)."""
    changes = []
    level = _MARK
    end = first
    offsets = [int(k * bit_cycles + 0.5) for k in range(arch_uart.CHARACTER_BITS + 1)]
    for i, byte in enumerate(data):
        start = max(first + round(i * arch_uart.CHARACTER_BITS * bit_cycles), end)
        bits = (_SPACE, *((byte >> b) & 1 for b in range(arch_uart.DATA_BITS)), _MARK)
        for k, bit in enumerate(bits):
            if bit != level:
                changes.append((start + offsets[k], bit))
                level = bit
        end = start + offsets[-1]
    return changes, end


@functools.lru_cache(maxsize=256)
def received_as_sent(bit_cycles, divisor, latency=SYNC_CYCLES):
    """Whether every vote of every character sent back to back at ``bit_cycles`` falls
    inside its own bit, whatever the tick's phase against the start edge, for a receiver
    that is hunting when the first start bit begins: then the receiver reports each byte
    as sent, and is hunting again before the next start bit. (Sufficient, not necessary.)
    """
    divisor = max(1, divisor)
    if bit_cycles <= divisor:
        return False
    for k in range(arch_uart.CHARACTER_BITS):
        begin, end = int(k * bit_cycles + 0.5), int((k + 1) * bit_cycles + 0.5)
        # Tick 0 is the first tick to sample the start bit: 0 .. divisor-1 cycles after its
        # edge reached the logic.
        earliest = (_OVER * k + _VOTES[0]) * divisor
        latest = (_OVER * k + _VOTES[-1]) * divisor + divisor - 1
        if not (begin <= earliest and latest < end):
            return False
    return True


class UartReceiver:
    """hw/uart.py's ``UartRx`` over a line given as level changes (module docstring).

    Feed the line in time order with :meth:`extend`, then :meth:`run` up to a cycle: every
    character whose votes all fall before it is emitted; the receiver stops where a sample
    would need the line beyond it, and resumes there after more is fed.

    Parameters
    ----------
    divisor : int
        Clock cycles per oversampling tick (0 acts as 1).
    latency : int
        Cycles from the pin to the logic (default :data:`SYNC_CYCLES`).
    origin : int
        The first tick's cycle (the end of reset).
    """
    def __init__(self, divisor, *, latency=SYNC_CYCLES, origin=0):
        if isinstance(divisor, bool) or not isinstance(divisor, int) or divisor < 0:
            raise ValueError(f"Divisor must be a non-negative integer, not {divisor!r}")
        self.divisor = max(1, divisor)
        self.latency = latency
        self.origin = origin
        self._times = []            # pin cycles of the level changes, increasing
        self._levels = []           # the level from each change on
        self.state = _IDLE
        self._tick = origin         # IDLE, WAIT_MARK: the next tick to look at
        self._tau = 0               # START, RECEIVE: the cycle of the start bit's tick 0
        self._bit = 0               # RECEIVE: the next bit to decide (1-9)
        self._data = 0

    @property
    def hunting(self):
        """Whether the receiver waits for a start bit (IDLE)."""
        return self.state == _IDLE

    def extend(self, changes):
        """Level changes ``(cycle, level)`` after every one fed so far."""
        for cycle, level in changes:
            if self._times and cycle <= self._times[-1]:
                raise ValueError(f"Line changes must come in time order: {cycle} after "
                                 f"{self._times[-1]}")
            if level != (self._levels[-1] if self._levels else _MARK):
                self._times.append(cycle)
                self._levels.append(level)

    def skip_to(self, cycle):
        """The receiver hunts and the line has been mark up to pin cycle ``cycle`` (bytes
        received as sent, :func:`received_as_sent`): hunt on from there."""
        if self.state != _IDLE:
            raise ValueError("The receiver is not hunting")
        self._tick = max(self._tick, self._tick_from(cycle + self.latency))

    def _level(self, pin_cycle):
        index = bisect.bisect_right(self._times, pin_cycle) - 1
        return self._levels[index] if index >= 0 else _MARK

    def _tick_from(self, cycle):
        """The first tick at or after ``cycle``."""
        d = self.divisor
        return self.origin + max(0, -(-(cycle - self.origin) // d)) * d

    def _vote(self, tick0, bit):
        """The majority of bit ``bit``'s vote samples after the start tick ``tick0``."""
        base = tick0 + _OVER * bit * self.divisor - self.latency
        ones = sum(self._level(base + v * self.divisor) for v in _VOTES)
        return int(2 * ones > len(_VOTES))

    def _next_change_to(self, pin_cycle, level):
        """The first change to ``level`` after ``pin_cycle``, or None."""
        index = bisect.bisect_right(self._times, pin_cycle)
        while index < len(self._times):
            if self._levels[index] == level:
                return self._times[index]
            index += 1
        return None

    def _find(self, level, horizon):
        """From the next tick on, the first tick that samples ``level`` before pin cycle
        ``horizon``; None (the next tick kept) when there is none."""
        d, lat = self.divisor, self.latency
        tick = self._tick
        while tick - lat < horizon:
            if self._level(tick - lat) == level:
                return tick
            change = self._next_change_to(tick - lat, level)
            if change is None or change >= horizon:
                break
            tick = self._tick_from(change + lat)
        # Every tick sampling before the horizon has been looked at.
        self._tick = tick if horizon == math.inf else \
            max(tick, self._tick_from(horizon + lat))
        return None

    def run(self, horizon):
        """The characters emitted while every sample needed falls before pin cycle
        ``horizon`` (the line up to it is known), as :class:`RxChar`."""
        d, lat = self.divisor, self.latency
        out = []
        while True:
            if self.state == _IDLE:
                tick = self._find(_SPACE, horizon)
                if tick is None:
                    return out
                self._tau, self.state = tick, _START
            elif self.state == _WAIT_MARK:
                tick = self._find(_MARK, horizon)
                if tick is None:
                    return out
                self._tick, self.state = tick + d, _IDLE
            elif self.state == _START:
                decide = self._tau + _DECIDE * d
                if decide - lat >= horizon:
                    return out
                if self._vote(self._tau, 0) != _SPACE:
                    self._tick, self.state = decide + d, _IDLE       # a glitch
                else:
                    self._bit, self._data, self.state = 1, 0, _RECEIVE
            else:
                decide = self._tau + (_OVER * self._bit + _DECIDE) * d
                if decide - lat >= horizon:
                    return out
                value = self._vote(self._tau, self._bit)
                if self._bit < _STOP:
                    self._data |= value << (self._bit - 1)
                    self._bit += 1
                    continue
                out.append(RxChar(decide, self._data, value != _MARK))
                if value == _MARK:
                    self._tick, self.state = decide + d, _IDLE
                elif self._data == 0:
                    self._tick, self.state = decide + d, _WAIT_MARK  # a break
                else:
                    # A damaged stop bit: the next bit slot is taken as a start bit.
                    self._tau += _OVER * arch_uart.CHARACTER_BITS * d
                    self.state = _START
