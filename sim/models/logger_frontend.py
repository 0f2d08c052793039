"""The logger's serial front end at frame level, for the transaction-level model.

Each channel's line carries bytes back to back from the start of each burst, one per ten
bit times (8N1) at the burst's rate; the receiver has a byte at the middle of its stop bit
(:data:`RECEIVED_BITS` after its start bit begins, as hw/uart.py's UartRx decides it). A
burst the receiver cannot be sure to take whole (off its rate: a baud-error fault) goes
through the gateware's receiver as sim/models/logger_uart.py models it, which gives the
characters, their framing errors and their times. What the frame filter makes of the
characters comes from the reference filter (sim/reference/): the frames it keeps and its
counters. This module places every decision
in time: a kept frame at its line end, a dropped candidate at the byte on which the rules
drop it (the byte-by-byte reading of docs/frame-rules.md, found by feeding the candidate to
a fresh reference filter one byte at a time). A candidate still open when the line goes
quiet gets no decision.
"""

from __future__ import annotations

import bisect
import math
import re
from dataclasses import dataclass

from ...hw.arch import uart as arch_uart
from ...hw.frame_filter import ChannelKind
from ..reference import ERROR_MARK, KEPT, Kind, ReferenceFilter
from .logger_uart import UartReceiver, line_changes, received_as_sent


__all__ = ["Decision", "ChannelLine", "parse_zda", "RECEIVED_BITS"]

#: Bit times from a byte's start bit to the receiver's decision on its stop bit: the last
#: vote of the stop bit (tick 9 of 16 of bit 9), the start edge being seen half a tick late
#: on average.
RECEIVED_BITS = arch_uart.CHARACTER_BITS - 1 + \
    (arch_uart.VOTE_TICKS[-1] + 0.5) / arch_uart.OVERSAMPLING

_KIND = {ChannelKind.PMAG: Kind.PMAG, ChannelKind.NMEA: Kind.NMEA,
         ChannelKind.CESIUM: Kind.CESIUM}
#: A candidate frame ends at the next `$` (which starts the next one), LF or error-flagged
#: character.
_END = re.compile(f"[$\\n{ERROR_MARK}]")
_INF_CYCLE = math.inf


def _chars_chunk(chars):
    """A chunk of :meth:`ChannelLine.received` from the receiver's characters."""
    return ("".join(ERROR_MARK if c.error else chr(c.data) for c in chars),
            [c.cycle for c in chars])


def _events(text):
    """The reference filter's events for a chunk's text."""
    if ERROR_MARK not in text:
        return text.encode("latin-1")
    return [(0, True) if char == ERROR_MARK else (ord(char), False) for char in text]

# Ref: NMEA 0183 v4.11 §6.3 ZDA, read as hw/peripherals.py's GpsTime reads it: any two-letter
#      talker, hhmmss with optional decimals, then day, month and year of fixed widths, each
#      ended by a comma.
_ZDA = re.compile(rb"\$[A-Z]{2}ZDA,(\d\d)(\d\d)(\d\d)[.0-9]*,(\d\d),(\d\d),(\d{4}),")


def parse_zda(frame):
    """``(hour, minute, second, day, month, year)`` of a ZDA frame as the gateware's GPS
    time capture takes it, or None when it leaves its registers unchanged."""
    match = _ZDA.match(frame)
    if match is None:
        return None
    hour, minute, second, day, month, year = (int(g) for g in match.groups())
    if hour < 24 and minute < 60 and second < 60 and 1 <= day <= 31 and 1 <= month <= 12 \
            and year < 1 << 12:
        return hour, minute, second, day, month, year
    return None


@dataclass(frozen=True)
class Decision:
    """The frame filter's decision on one candidate frame of one channel.

    ``time`` is the cycle of the deciding byte's stop bit, ``start`` that of the candidate's
    ``$``; ``outcome`` the counter it goes to (``kept`` or a drop cause); ``frame`` the kept
    bytes (None for a drop); ``flush`` a kept GGA with a fix.
    """
    time: int
    start: int
    channel: int
    outcome: str
    frame: bytes | None = None
    flush: bool = False


class ChannelLine:
    """The bursts fed to one channel, what its receiver reports of them, and the filter's
    decisions on that.

    A burst whose bit time the receiver takes whole (:func:`~.logger_uart.received_as_sent`:
    every vote inside its bit, the nominal rate from a divisor that divides the clock well)
    and that finds the receiver hunting is received as sent, each byte at
    :data:`RECEIVED_BITS` after its start bit. Any other burst (a baud-error fault) is
    placed on the line as the transmitter sends it (:func:`~.logger_uart.line_changes`) and
    received by the gateware's receiver (:class:`~.logger_uart.UartReceiver`), until the
    receiver hunts again before a burst.

    Parameters
    ----------
    channel : int
    kind : ChannelKind
    max_frame : int
    clk_freq : float
    divisor : int or None
        The receiver's divisor (the gateware's after reset, from the channel's nominal
        baud rate); None: the nearest one to the rate of the first burst fed.
    """
    def __init__(self, channel, kind, *, max_frame, clk_freq, divisor=None):
        self.channel = channel
        self.kind = _KIND[ChannelKind(kind)]
        self.max_frame = max_frame
        self.clk_freq = clk_freq
        self.divisor = divisor
        self._bursts = []   # (start cycle, bit cycles, data)
        self._end = 0                  # cycle after the last byte fed so far
        self._decisions = None
        self._received = None

    def feed(self, data, *, start, baud):
        """Bytes back to back from ``start`` seconds at ``baud``."""
        if not isinstance(data, (bytes, bytearray)):
            raise ValueError(f"Channel data must be bytes, not {type(data).__name__}")
        if isinstance(baud, bool) or not isinstance(baud, (int, float)) or baud <= 0:
            raise ValueError(f"Baud rate must be a positive number, not {baud!r}")
        if isinstance(start, bool) or not isinstance(start, (int, float)) or start < 0:
            raise ValueError(f"Start must be a time in seconds >= 0, not {start!r}")
        first = round(start * self.clk_freq)
        bit = self.clk_freq / baud
        if first < self._end:
            raise ValueError(f"Channel {self.channel}'s bytes from {start} s overlap those fed "
                             f"up to {self._end / self.clk_freq} s (feed each channel in "
                             f"order)")
        if data:
            if self.divisor is None:
                self.divisor = max(1, round(bit / arch_uart.OVERSAMPLING))
            self._bursts.append((first, bit, bytes(data)))
            self._end = first + round(len(data) * arch_uart.CHARACTER_BITS * bit)
            self._decisions = self._received = None

    @property
    def data(self):
        """Every byte the line carried, in order."""
        return b"".join(data for *_, data in self._bursts)

    def received(self):
        """What the receiver reports, as chunks ``(text, timing)`` in order: ``text`` the
        characters as the reference filter reads them (an error-flagged one as
        ``ERROR_MARK``); ``timing`` ``(first, cycles per byte, cycles to the first
        decision)`` for a burst received as sent, or the cycle of each character's
        decision."""
        if self._received is None:
            self._received = self._receive()
        return self._received

    def _receive(self):
        chunks = []
        rx = UartReceiver(self.divisor or 1)
        bursts = self._bursts
        for i, (first, bit, data) in enumerate(bursts):
            edge = first        # the first start bit's edge
            chars = rx.run(edge)
            if chars:
                chunks.append(_chars_chunk(chars))
            if rx.hunting and received_as_sent(bit, rx.divisor, rx.latency):
                per_byte = arch_uart.CHARACTER_BITS * bit
                chunks.append((data.decode("latin-1"),
                               (first, per_byte, RECEIVED_BITS * bit)))
                rx.skip_to(first + round(len(data) * per_byte))
                continue
            changes, _ = line_changes(first, data, bit)
            rx.extend(changes)
        chars = rx.run(_INF_CYCLE)
        if chars:
            chunks.append(_chars_chunk(chars))
        return chunks

    def decisions(self):
        """Every decision on the bytes fed so far, in time order."""
        if self._decisions is None:
            self._decisions = self._decide()
        return self._decisions

    def reference(self):
        """The reference filter's result over what the receiver reported."""
        ref = ReferenceFilter(self.kind, self.max_frame)
        for text, _ in self.received():
            ref.feed_all(_events(text))
        return ref.result

    def _decide(self):
        chunks = self.received()
        offsets, total = [], 0
        for text, _ in chunks:
            offsets.append(total)
            total += len(text)
        text = "".join(text for text, _ in chunks)

        def time_of(index):
            c = bisect.bisect_right(offsets, index) - 1
            timing = chunks[c][1]
            if isinstance(timing, list):
                return timing[index - offsets[c]]
            first, per_byte, received = timing
            return first + round((index - offsets[c]) * per_byte + received)

        reference = self.reference()
        kept, flushes = reference.frames, set(reference.flushes)
        decisions, counts = [], dict.fromkeys(reference.counters, 0)
        k = 0
        pos = text.find("$")
        while pos >= 0:
            end = _END.search(text, pos + 1)
            stop = end.start() if end else len(text)
            if end is not None and text[stop] == "\n" and k < len(kept) \
                    and text[pos:stop + 1] == kept[k].decode("latin-1"):
                decisions.append(Decision(time_of(stop), time_of(pos), self.channel, KEPT,
                                          kept[k], k in flushes))
                counts[KEPT] += 1
                k += 1
            else:
                last = stop if end is not None else stop - 1
                outcome, at = self._judge(text[pos:last + 1])
                if outcome is not None:
                    decisions.append(Decision(time_of(pos + at), time_of(pos), self.channel,
                                              outcome))
                    counts[outcome] += 1
            pos = stop if end is not None and text[stop] == "$" else text.find("$", stop)
        if counts != reference.counters or k != len(kept):
            raise AssertionError(f"Channel {self.channel}: the model's frame walk found "
                                 f"{counts}, the reference filter {reference.counters}")
        return decisions

    def _judge(self, candidate):
        """The outcome of a dropped candidate and the index of its deciding byte, or
        ``(None, None)`` for a candidate still open."""
        ref = ReferenceFilter(self.kind, self.max_frame)
        for index, char in enumerate(candidate):
            if char == ERROR_MARK:
                ref.feed(0, True)
            else:
                ref.feed(ord(char))
            counters = ref.result.counters
            for name, value in counters.items():
                if value:
                    return name, index
        return None, None
