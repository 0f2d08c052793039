"""`$`-frame filter: keeps the frames of one channel's rule set, drops the rest whole.

The rules, byte by byte and with the counter each dropped frame goes to, are those of
docs/frame-rules.md.
"""

import operator

from amaranth import *
from amaranth.lib import enum, stream, wiring
from amaranth.lib.wiring import In, Out

from .arch import frames as arch
from .frame_fifo import FrameByte, FrameFifo
from .uart import RxByte


__all__ = ["ChannelKind", "FrameFilter", "counters_signature"]


class ChannelKind(enum.Enum):
    """Which rule set a channel applies."""
    NMEA   = "nmea"
    PMAG   = "pmag"
    CESIUM = "cesium"


class _Word(enum.Enum, shape=2):
    """Which whitelisted NMEA formatter the address field is spelling."""
    GGA = 0
    ZDA = 1
    VTG = 2


class _Quality(enum.Enum, shape=2):
    """The GGA quality field so far."""
    EMPTY = 0
    FIX   = 1    # exactly one character, 1-9
    OTHER = 2


def counters_signature(width):
    """Frame counters of one channel: kept frames, then dropped frames by cause."""
    return wiring.Signature({name: Out(width) for name in arch.COUNTER_NAMES})


def _between(value, low, high):
    return (value >= ord(low)) & (value <= ord(high))


def _hex_digit(char):
    """(is a hex digit, its value) of an ASCII character, either case."""
    # Digits are 0x30-0x39, letters 0x41-0x46 or 0x61-0x66 (bit 5 is the case): a letter's
    # value is its low nibble plus 9.
    is_digit  = (char[4:] == 0x3) & (char[:4] <= 9)
    is_letter = (char[6:] == 0b01) & (char[3:5] == 0) & (char[:3] != 0) & (char[:3] != 7)
    value = Mux(is_digit, char[:4], char[:4] + 9)[:4]
    return is_digit | is_letter, value


class FrameFilter(wiring.Component):
    """Frame filter of one channel.

    Bytes are written to a :class:`FrameFifo` as they arrive, committed when the frame ends
    well and discarded as soon as a rule fails, so a dropped frame leaves nothing behind.

    Parameters
    ----------
    kind : ChannelKind
        The channel's rule set.
    max_frame : int
        Longest NMEA or ``$PMAG1`` frame in bytes, ``$`` through LF (cesium frames have a
        fixed length).
    fifo_depth : int
        Bytes of frame FIFO (a power of two).
    counter_width : int
        Width of each frame counter (they wrap); 0 for no counters, only their ``events``
        (for a counter bank elsewhere).

    Members
    -------
    i : ``In(stream.Signature(RxByte))``
        Received characters; always ready.
    o : ``Out(stream.Signature(FrameByte))``
        Kept frames, whole, ``last`` on the LF.
    flush : ``Out(1)``
        One-cycle strobe for each kept GGA whose fix quality is 1-9 (NMEA channels only).
    events : ``Out(len(COUNTER_NAMES))``
        One-cycle strobe per counter, in :data:`~maglog.hw.arch.frames.COUNTER_NAMES` order:
        a frame kept, or dropped for that cause. At most one strobe per received character.
    counters : ``Out(counters_signature(counter_width))``
        Kept frames and dropped frames by cause (only when ``counter_width`` is not 0).
    """
    def __init__(self, kind, *, max_frame=arch.DEFAULT_MAX_FRAME, fifo_depth=1024,
                 counter_width=32):
        kind = ChannelKind(kind)
        if kind == ChannelKind.CESIUM:
            max_frame = arch.CESIUM_MAX_FRAME
        elif (not isinstance(max_frame, int) or
                not 1 + arch.CHECKED_MIN_BODY + 1 <= max_frame <= arch.MAX_FRAME_LIMIT):
            raise ValueError(f"Maximum frame length must be an integer from "
                             f"{1 + arch.CHECKED_MIN_BODY + 1} to {arch.MAX_FRAME_LIMIT}, "
                             f"not {max_frame!r}")
        if not isinstance(fifo_depth, int) or fifo_depth < max_frame:
            raise ValueError(f"FIFO depth must hold at least one frame of {max_frame} bytes, "
                             f"not {fifo_depth!r}")
        if fifo_depth > arch.MAX_FIFO_DEPTH:
            raise ValueError(f"FIFO depth must be at most {arch.MAX_FIFO_DEPTH} bytes (the "
                             f"block RAM of the target), not {fifo_depth!r}")
        if not isinstance(counter_width, int) or not 0 <= counter_width <= 64:
            raise ValueError(f"Counter width must be an integer from 0 to 64, "
                             f"not {counter_width!r}")
        self._kind = kind
        self._max_frame = max_frame
        self._fifo = FrameFifo(depth=fifo_depth)
        members = {
            "i":      In(stream.Signature(RxByte())),
            "o":      Out(stream.Signature(FrameByte())),
            "flush":  Out(1),
            "events": Out(len(arch.COUNTER_NAMES)),
        }
        if counter_width:
            members["counters"] = Out(counters_signature(counter_width))
        super().__init__(members)

    @property
    def kind(self):
        return self._kind

    @property
    def max_frame(self):
        return self._max_frame

    def elaborate(self, platform):
        m = Module()
        m.submodules.fifo = fifo = self._fifo
        wiring.connect(m, wiring.flipped(self.o), fifo.o)

        kind = self._kind
        checked = kind in (ChannelKind.NMEA, ChannelKind.PMAG)

        # Frame state.
        # Only `in_frame` is reset: the rest is set by every `$` before it is used.
        in_frame   = Signal()
        length     = Signal(range(self._max_frame + 1),   # bytes so far, `$` and CR included
                            reset_less=True)
        pending_cr = Signal(reset_less=True)
        xor        = Signal(8, reset_less=True)           # of the body bytes so far
        tail       = Signal(24, reset_less=True)          # last three body bytes, newest low
        word       = Signal(_Word, reset_less=True)
        star_seen  = Signal(reset_less=True)
        field      = Signal(range(arch.GGA_QUALITY_FIELD + 2), reset_less=True)
        quality    = Signal(_Quality, reset_less=True)

        m.d.comb += self.i.ready.eq(1)
        char  = self.i.payload.data
        error = self.i.payload.framing_error | self.i.payload.brk | self.i.payload.overrun
        valid = self.i.valid

        # Decisions for this byte (all combinational, acted on below).
        start     = Signal()   # `$`: a new frame starts with this byte
        drop      = Signal()   # the frame so far is dropped
        cause     = Signal(arch.DropCause)
        append    = Signal()   # this byte belongs to the frame and is written
        finish    = Signal()   # ... and it is the LF of a good frame
        position_ok = Signal()

        printable = _between(char, chr(arch.PRINTABLE_MIN), chr(arch.PRINTABLE_MAX))
        is_dollar = char == arch.DOLLAR
        is_cr     = char == arch.CR
        is_lf     = char == arch.LF

        # Position check of the channel's kind, for a body byte at position `length`. The
        # first NMEA positions come one-hot from `head` (bit k: `length == k + 1`), set by `$`
        # and shifted by every byte appended, instead of compares of `length`.
        n_head = arch.NMEA_ADDRESS_END_POS if kind == ChannelKind.NMEA else 0
        head = Signal(max(1, n_head), reset_less=True)

        def at(position):
            return head[position - 1]

        m.d.comb += position_ok.eq(1)
        if kind == ChannelKind.NMEA:
            with m.If(at(1) | at(2)):
                m.d.comb += position_ok.eq(_between(char, "A", "Z"))
            for offset in range(3):
                with m.If(at(arch.NMEA_FORMATTER_POS + offset)):
                    letters = {_Word[name]: ord(name[offset]) for name in arch.NMEA_WHITELIST}
                    if offset == 0:
                        m.d.comb += position_ok.eq(
                            Cat(char == letter for letter in letters.values()).any())
                    else:
                        with m.Switch(word):
                            for w, letter in letters.items():
                                with m.Case(w):
                                    m.d.comb += position_ok.eq(char == letter)
            with m.If(at(arch.NMEA_ADDRESS_END_POS)):
                m.d.comb += position_ok.eq(char == arch.COMMA)
        elif kind == ChannelKind.PMAG:
            with m.Switch(length):
                for offset, letter in enumerate(arch.PMAG_HEADER):
                    with m.Case(1 + offset):
                        m.d.comb += position_ok.eq(char == letter)
        elif kind == ChannelKind.CESIUM:
            with m.Switch(length):
                for offset, template in enumerate(arch.CESIUM_TEMPLATE):
                    with m.Case(1 + offset):
                        if template == ord("s"):
                            m.d.comb += position_ok.eq((char == arch.SPACE) | (char == ord("1")))
                        elif template == ord("d"):
                            m.d.comb += position_ok.eq(_between(char, "0", "9"))
                        else:
                            m.d.comb += position_ok.eq(char == template)
                with m.Default():
                    # Position 16 and beyond: only the line end may come.
                    m.d.comb += position_ok.eq(0)

        # End checks at the LF.
        # The body's length is `length - 1 - pending_cr`; compared with constants per
        # `pending_cr` (no subtraction).
        def body_len_is(op, value):
            return Mux(pending_cr, op(length, value + 2), op(length, value + 1))
        end_ok    = Signal()
        end_cause = Signal(arch.DropCause)
        if checked:
            star, high, low = tail[16:24], tail[8:16], tail[0:8]
            high_ok, high_value = _hex_digit(high)
            low_ok, low_value = _hex_digit(low)
            with m.If(body_len_is(operator.lt, arch.CHECKED_MIN_BODY)):
                m.d.comb += end_cause.eq(arch.DropCause.NOT_WHITELISTED)
            with m.Elif((star == arch.STAR) & high_ok & low_ok &
                        ((xor ^ arch.STAR ^ high ^ low) == Cat(low_value, high_value))):
                m.d.comb += end_ok.eq(1)
            with m.Else():
                m.d.comb += end_cause.eq(arch.DropCause.CHECKSUM)
        else:
            m.d.comb += [
                end_ok.eq(body_len_is(operator.eq, arch.CESIUM_BODY)),
                end_cause.eq(arch.DropCause.NOT_WHITELISTED),
            ]

        with m.If(valid):
            with m.If(~in_frame):
                # Outside a frame only a good `$` matters.
                m.d.comb += start.eq(~error & is_dollar)
            with m.Elif(error):
                m.d.comb += [drop.eq(1), cause.eq(arch.DropCause.UART_ERROR)]
            with m.Elif(is_dollar):
                m.d.comb += [drop.eq(1), cause.eq(arch.DropCause.BAD_BYTE), start.eq(1)]
            with m.Elif(pending_cr & ~is_lf):
                m.d.comb += [drop.eq(1), cause.eq(arch.DropCause.BAD_BYTE)]
            with m.Elif(~is_cr & ~is_lf & ~printable):
                m.d.comb += [drop.eq(1), cause.eq(arch.DropCause.BAD_BYTE)]
            with m.Elif(length == self._max_frame):   # it never goes beyond
                m.d.comb += [drop.eq(1), cause.eq(arch.DropCause.OVERLONG)]
            with m.Elif(is_lf):
                with m.If(end_ok):
                    m.d.comb += [append.eq(1), finish.eq(1)]
                with m.Else():
                    m.d.comb += [drop.eq(1), cause.eq(end_cause)]
            with m.Elif(is_cr | position_ok):
                m.d.comb += append.eq(1)
            with m.Else():
                m.d.comb += [drop.eq(1), cause.eq(arch.DropCause.NOT_WHITELISTED)]

        # Writing to the FIFO; no room drops the frame being written (`overflow`).
        overflow = Signal()
        m.d.comb += [
            overflow.eq(Mux(start, fifo.full_committed, fifo.full) & (start | append)),
            fifo.w_en.eq((start | append) & ~overflow),
            fifo.w_data.eq(char),
            fifo.w_last.eq(finish),
            fifo.commit.eq(finish & ~overflow),
            fifo.discard.eq(drop | overflow),
        ]

        # Frame state updates.
        with m.If(overflow):
            m.d.sync += in_frame.eq(0)
        with m.Elif(start):
            m.d.sync += [
                in_frame.eq(1),
                length.eq(1),
                head.eq(1),
                pending_cr.eq(0),
                xor.eq(0),
                # `tail` is not cleared: the checksum is looked at only with 9 body bytes or
                # more, so its three bytes are always of this frame by then.
                star_seen.eq(0),
                field.eq(0),
                quality.eq(_Quality.EMPTY),
            ]
        with m.Elif(drop | finish):
            m.d.sync += in_frame.eq(0)
        with m.Elif(append):
            m.d.sync += [length.eq(length + 1), head.eq(head << 1)]
            with m.If(is_cr):
                m.d.sync += pending_cr.eq(1)
            with m.Else():
                m.d.sync += [
                    xor.eq(xor ^ char),
                    tail.eq(Cat(char, tail[:16])),
                ]
                if kind == ChannelKind.NMEA:
                    with m.If(at(arch.NMEA_FORMATTER_POS)):
                        for name in arch.NMEA_WHITELIST:
                            with m.If(char == ord(name[0])):
                                m.d.sync += word.eq(_Word[name])
                    with m.If(~head[:arch.NMEA_ADDRESS_END_POS - 1].any()):   # length >= 6
                        # Fields count from the address field's comma; `*` ends them.
                        with m.If(char == arch.STAR):
                            m.d.sync += star_seen.eq(1)
                        with m.Elif(star_seen):
                            pass
                        with m.Elif(char == arch.COMMA):
                            with m.If(field <= arch.GGA_QUALITY_FIELD):
                                m.d.sync += field.eq(field + 1)
                        with m.Elif(field == arch.GGA_QUALITY_FIELD):
                            with m.If((quality == _Quality.EMPTY) & _between(char, "1", "9")):
                                m.d.sync += quality.eq(_Quality.FIX)
                            with m.Else():
                                m.d.sync += quality.eq(_Quality.OTHER)

        # Counter events, the counters, and the flush event.
        counts = {name: Signal(name=f"count_{name}") for name in arch.COUNTER_NAMES}
        m.d.comb += counts["kept"].eq(finish & ~overflow)
        for c in arch.DropCause:
            if c == arch.DropCause.OVERFLOW:
                m.d.comb += counts[c.counter].eq(overflow | (drop & (cause == c)))
            else:
                m.d.comb += counts[c.counter].eq(drop & (cause == c))
        m.d.comb += self.events.eq(Cat(counts.values()))
        if "counters" in self.signature.members:
            for name, strobe in counts.items():
                counter = getattr(self.counters, name)
                with m.If(strobe):
                    m.d.sync += counter.eq(counter + 1)

        if kind == ChannelKind.NMEA:
            m.d.sync += self.flush.eq(finish & ~overflow & (word == _Word.GGA) &
                                      (quality == _Quality.FIX))
        else:
            m.d.comb += self.flush.eq(0)

        return m
