"""UART receiver: 8N1, 16x oversampling, run-time divisor."""

from amaranth import *
from amaranth.lib import data, enum, stream, wiring
from amaranth.lib.cdc import FFSynchronizer
from amaranth.lib.wiring import In, Out

from .arch import uart as arch


__all__ = ["RxByte", "UartRx"]


class RxByte(data.StructLayout):
    """A received character and what went wrong with it.

    ``framing_error``: the stop bit was space. ``brk``: a whole character of space (a break;
    ``framing_error`` is set too). ``overrun``: the previous character was still unread when
    this one arrived and was lost. A character with any flag set carries no trustworthy value.
    """
    def __init__(self):
        super().__init__({
            "data":          arch.DATA_BITS,
            "framing_error": 1,
            "brk":           1,
            "overrun":       1,
        })


class _State(enum.Enum, shape=2):
    IDLE      = 0
    START     = 1       # in the start bit
    RECEIVE   = 2       # in a data bit, or the stop bit once the marker reaches shreg[0]
    WAIT_MARK = 3


class UartRx(wiring.Component):
    """8N1 UART receiver.

    The line is sampled ``arch.OVERSAMPLING`` times per bit: one sample every ``divisor``
    clock cycles, so the baud rate is ``f_clk / (16 * divisor)``; a divisor of 0 acts as 1.
    The line passes a two flip-flop synchroniser first. A start bit must still be space at
    the middle of the bit (majority of the three middle samples), so a glitch shorter than
    about half a bit is ignored. Each bit is the majority of its three middle samples.

    A character whose stop bit is space is reported with ``framing_error``. In a continuous
    stream the next start bit then follows the damaged stop bit with no edge between them,
    so the receiver keeps its bit timing and takes the next bit slot as a start bit if the
    line is space in its middle (and returns to hunting for an edge otherwise). After a
    break (a whole character of space) it waits for the line to return to mark instead, and
    reports the break once.

    Parameters
    ----------
    divisor_bits : int
        Width of the run-time divisor.
    divisor_init : int
        Divisor after reset.

    Members
    -------
    rx : ``In(1)``
        Serial line (asynchronous).
    divisor : ``In(divisor_bits)``
        Clock cycles per oversampling tick.
    o : ``Out(stream.Signature(RxByte))``
        Received characters. There is no flow control on a serial line: a character not
        taken before the next one is complete is replaced, and the new one flags ``overrun``.
    """
    def __init__(self, *, divisor_bits=arch.DIVISOR_BITS, divisor_init=1):
        if not isinstance(divisor_bits, int) or divisor_bits < 1:
            raise TypeError(f"Divisor width must be a positive integer, not {divisor_bits!r}")
        if (not isinstance(divisor_init, int) or divisor_init < 1 or
                divisor_init >= 1 << divisor_bits):
            raise ValueError(f"Initial divisor must be an integer from 1 to "
                             f"{(1 << divisor_bits) - 1}, not {divisor_init!r}")
        self._divisor_bits = divisor_bits
        super().__init__({
            "rx":      In(1, init=arch.MARK),
            "divisor": In(divisor_bits, init=divisor_init),
            "o":       Out(stream.Signature(RxByte())),
        })

    def elaborate(self, platform):
        m = Module()

        line = Signal(init=arch.MARK)
        m.submodules.sync = FFSynchronizer(self.rx, line, init=arch.MARK)

        # Oversampling tick: a down-counter from `divisor` reaching 1 (or 0, so that a
        # divisor of 0 acts as 1); a new divisor counts from the next tick on. It keeps its
        # reset: its next value depends on itself, so in a simulator an unknown divisor
        # before the reset (an undriven port) would leave it unknown for ever. Datapath
        # registers below are loaded before they are used, so they need no reset.
        count = Signal(self._divisor_bits)
        tick  = Signal()
        m.d.comb += tick.eq(count[1:] == 0)
        m.d.sync += count.eq(Mux(tick, self.divisor, count - 1))

        phase = Signal(range(arch.OVERSAMPLING), reset_less=True)  # tick in the bit, 0 = first
        votes = Signal(len(arch.VOTE_TICKS) - 1, reset_less=True)
        # The data bits shift in from the top behind a marker bit: once the marker reaches
        # shreg[0], the eight data bits are in shreg[1:] and the bit now is the stop bit.
        shreg = Signal(1 + arch.DATA_BITS, reset_less=True)
        data  = shreg[1:]
        last_vote = arch.VOTE_TICKS[-1]
        assert arch.VOTE_TICKS == tuple(range(last_vote - len(votes), last_vote + 1))

        # The majority of the earlier votes and the sample taken now.
        value = Signal()
        m.d.comb += value.eq((votes[0] & votes[1]) | (votes[0] & line) | (votes[1] & line))

        # Emit: hold the character until it is taken; a newer one replaces it (overrun).
        payload = Signal(RxByte(), reset_less=True)
        m.d.comb += self.o.payload.eq(payload)
        emit  = Signal()
        ferr  = Signal()
        with m.If(emit):
            m.d.sync += [
                self.o.valid.eq(1),
                payload.data.eq(data),
                payload.framing_error.eq(ferr),
                payload.brk.eq(ferr & (data == 0)),
                payload.overrun.eq(self.o.valid & ~self.o.ready),
            ]
        with m.Elif(self.o.ready):
            m.d.sync += self.o.valid.eq(0)

        state = Signal(_State)
        with m.If(tick):
            # The samples of the last ticks: at the last vote tick, those of the earlier ones.
            m.d.sync += [phase.eq(phase + 1), votes.eq(Cat(votes[1:], line))]
        decide = tick & (phase == last_vote)     # the middle of a bit: its majority is known
        with m.Switch(state):
            with m.Case(_State.IDLE):
                # Waits for a sample at space: the possible start of a start bit.
                with m.If(tick & (line == arch.SPACE)):
                    m.d.sync += [phase.eq(1), state.eq(_State.START)]

            with m.Case(_State.START):
                with m.If(decide):
                    with m.If(value != arch.SPACE):
                        # A glitch, not a start bit.
                        m.d.sync += state.eq(_State.IDLE)
                    with m.Else():
                        m.d.sync += [shreg.eq(1 << arch.DATA_BITS), state.eq(_State.RECEIVE)]

            with m.Case(_State.RECEIVE):
                with m.If(decide & ~shreg[0]):
                    m.d.sync += shreg.eq(Cat(shreg[1:], value))
                with m.If(decide & shreg[0]):
                    # The stop bit decides at its middle, so the next start bit is seen on
                    # time even from a fast transmitter.
                    m.d.comb += [
                        emit.eq(1),
                        ferr.eq(value != arch.MARK),
                    ]
                    with m.If(value == arch.MARK):
                        m.d.sync += state.eq(_State.IDLE)
                    with m.Elif(data == 0):
                        # A break: nothing to align to until the line is mark.
                        m.d.sync += state.eq(_State.WAIT_MARK)
                    with m.Else():
                        # A damaged stop bit: in a continuous stream the next start bit
                        # follows it with no edge between them, so keep counting and take
                        # the next bit slot as a start bit if it is space there.
                        m.d.sync += state.eq(_State.START)

            with m.Case(_State.WAIT_MARK):
                # Waits for the line to return to mark after a framing error or break.
                with m.If(tick & (line == arch.MARK)):
                    m.d.sync += state.eq(_State.IDLE)

        return m
