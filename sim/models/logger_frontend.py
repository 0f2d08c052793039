"""The logger's serial front end at frame level, for the transaction-level model.

Each channel's line carries bytes back to back from the start of each burst, one per ten
bit times (8N1); the receiver has a byte at the middle of its stop bit
(:data:`RECEIVED_BITS` after its start bit begins, as hw/uart.py's UartRx decides it). What
the gateware's receiver and frame filter make of the bytes comes from the reference filter
(sim/reference/): the frames it keeps and its counters. This module places every decision
in time: a kept frame at its line end, a dropped candidate at the byte on which the rules
drop it (the byte-by-byte reading of docs/frame-rules.md, found by feeding the candidate to
a fresh reference filter one byte at a time). A candidate still open when the line goes
quiet gets no decision.
"""

from __future__ import annotations

import bisect
import re
from dataclasses import dataclass

from ...hw.arch import uart as arch_uart
from ...hw.frame_filter import ChannelKind
from ..reference import KEPT, Kind, ReferenceFilter, reference_filter


__all__ = ["Decision", "ChannelLine", "parse_zda", "RECEIVED_BITS"]

#: Bit times from a byte's start bit to the receiver's decision on its stop bit: the last
#: vote of the stop bit (tick 9 of 16 of bit 9), the start edge being seen half a tick late
#: on average.
RECEIVED_BITS = arch_uart.CHARACTER_BITS - 1 + \
    (arch_uart.VOTE_TICKS[-1] + 0.5) / arch_uart.OVERSAMPLING

_KIND = {ChannelKind.PMAG: Kind.PMAG, ChannelKind.NMEA: Kind.NMEA,
         ChannelKind.CESIUM: Kind.CESIUM}
#: A candidate frame ends at the next `$` (which starts the next one) or LF.
_END = re.compile(r"[$\n]")

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
    """The bursts fed to one channel and the filter's decisions on them.

    Parameters
    ----------
    channel : int
    kind : ChannelKind
    max_frame : int
    clk_freq : float
    """
    def __init__(self, channel, kind, *, max_frame, clk_freq):
        self.channel = channel
        self.kind = _KIND[ChannelKind(kind)]
        self.max_frame = max_frame
        self.clk_freq = clk_freq
        self._bursts = []   # (start cycle, cycles per byte, cycles to the first byte, data)
        self._end = 0                  # cycle after the last byte fed so far
        self._decisions = None

    def feed(self, data, *, start, baud):
        """Bytes back to back from ``start`` seconds at ``baud``."""
        if not isinstance(data, (bytes, bytearray)):
            raise ValueError(f"Channel data must be bytes, not {type(data).__name__}")
        if isinstance(baud, bool) or not isinstance(baud, (int, float)) or baud <= 0:
            raise ValueError(f"Baud rate must be a positive number, not {baud!r}")
        if isinstance(start, bool) or not isinstance(start, (int, float)) or start < 0:
            raise ValueError(f"Start must be a time in seconds >= 0, not {start!r}")
        first = round(start * self.clk_freq)
        per_byte = arch_uart.CHARACTER_BITS * self.clk_freq / baud
        received = RECEIVED_BITS * self.clk_freq / baud
        if first < self._end:
            raise ValueError(f"Channel {self.channel}'s bytes from {start} s overlap those fed "
                             f"up to {self._end / self.clk_freq} s (feed each channel in "
                             f"order)")
        if data:
            self._bursts.append((first, per_byte, received, bytes(data)))
            self._end = first + round(len(data) * per_byte)
            self._decisions = None

    @property
    def data(self):
        """Every byte the line carried, in order."""
        return b"".join(data for *_, data in self._bursts)

    def decisions(self):
        """Every decision on the bytes fed so far, in time order."""
        if self._decisions is None:
            self._decisions = self._decide()
        return self._decisions

    def reference(self):
        """The reference filter's result over the whole line."""
        return reference_filter(self.kind, self.data, max_frame=self.max_frame)

    def _decide(self):
        bursts = self._bursts
        offsets, total = [], 0
        for *_, data in bursts:
            offsets.append(total)
            total += len(data)
        text = self.data.decode("latin-1")

        def time_of(index):
            b = bisect.bisect_right(offsets, index) - 1
            first, per_byte, received, _ = bursts[b]
            return first + round((index - offsets[b]) * per_byte + received)

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
            pos = text.find("$", stop) if end is None or text[stop] == "\n" else stop
        if counts != reference.counters or k != len(kept):
            raise AssertionError(f"Channel {self.channel}: the model's frame walk found "
                                 f"{counts}, the reference filter {reference.counters}")
        return decisions

    def _judge(self, candidate):
        """The outcome of a dropped candidate and the index of its deciding byte, or
        ``(None, None)`` for a candidate still open."""
        ref = ReferenceFilter(self.kind, self.max_frame)
        for index, char in enumerate(candidate):
            ref.feed(ord(char))
            counters = ref.result.counters
            for name, value in counters.items():
                if value:
                    return name, index
        return None, None
