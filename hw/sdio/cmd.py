"""SD CMD line engine: sends 48-bit commands and receives and checks the responses."""

from amaranth import *
from amaranth.lib import data, enum, wiring
from amaranth.lib.wiring import In, Out

from ..arch import sd as arch
from .crc import Crc7


__all__ = ["ResponseKind", "CmdStatus", "CmdEngine"]


class ResponseKind(enum.Enum, shape=2):
    """What follows a command on the CMD line; values from :class:`~maglog.hw.arch.sd.
    ResponseKind` (the firmware's view of the same field).

    Ref: PLSS §4.9 (responses R1, R1b, R2, R3, R6, R7).
    """
    NONE   = arch.ResponseKind.NONE.value    # CMD0
    SHORT  = arch.ResponseKind.SHORT.value   # R1, R1b, R6, R7: CRC7 and index checked
    OCR    = arch.ResponseKind.OCR.value     # R3: index field and CRC all ones, not checked
    LONG   = arch.ResponseKind.LONG.value    # R2: 136 bits, CID/CSD with its own CRC7


class CmdStatus(data.Struct):
    """Outcome of the last command (valid from ``done`` until the next ``start``)."""
    timeout:   1    # no response start bit within the timeout
    crc_error: 1    # the response's CRC7 does not match
    format_error: 1 # wrong command index or transmission bit in the response
    end_error: 1    # the response's end bit is not 1


class _State(enum.Enum, shape=3):
    IDLE      = 0   # waits for `start`
    SEND      = 1   # sends the 48 command bits, one per falling edge
    WAIT      = 2   # waits for the response's start bit, `timeout` clocks at most
    RECEIVE   = 3   # takes the response's bits, one per rising edge, then checks them
    GAP       = 4   # keeps N_CC clocks before the next command


class CmdEngine(wiring.Component):
    """Sends one command and receives its response, bit by bit on the SD clock's strobes.

    Bits go out on ``fall`` (MSB first: start 0, transmission 1, index, argument, CRC7,
    end 1) and come in on ``rise``. After the response (or the command, when none is
    expected) the engine stays busy for N_CC clocks so that the next command keeps its
    distance (PLSS §4.12.4, N_RC and N_CC).

    Members
    -------
    rise, fall : ``In(1)``
        Strobes of :class:`SdClock`.
    cmd_o, cmd_oe : ``Out(1)``
    cmd_i : ``In(1)``
    start : ``In(1)``
        Send ``index`` and ``argument``, expecting a response of ``kind``; ignored when busy.
    index : ``In(6)``
    argument : ``In(32)``
    kind : ``In(ResponseKind)``
    timeout : ``In(16)``
        Clocks from the command's end bit to the response's start bit (PLSS: N_CR ≤ 64).
    busy, done : ``Out(1)``
        ``done`` is a one-cycle strobe when the response has been checked.
    status : ``Out(CmdStatus)``
    response : ``Out(128)``
        The last 128 bits received (never cleared: above a 48-bit response sit the bits of
        earlier ones): for a 48-bit response its bits 47..0 sit in 47..0 (the
        card status or OCR in 39..8), for R2 the CID/CSD register's bits 127..1 and the end bit.
    """
    rise:     In(1)
    fall:     In(1)
    cmd_o:    Out(1, init=1)
    cmd_oe:   Out(1)
    cmd_i:    In(1, init=1)
    start:    In(1)
    index:    In(arch.CMD_INDEX_BITS)
    argument: In(arch.CMD_ARGUMENT_BITS)
    kind:     In(ResponseKind)
    timeout:  In(16, init=arch.N_CR_MAX)
    busy:     Out(1)
    done:     Out(1)
    status:   Out(CmdStatus)
    response: Out(arch.R2_CONTENT_BITS)

    def elaborate(self, platform):
        m = Module()
        m.submodules.crc = crc = Crc7()

        state   = Signal(_State)
        count   = Signal(range(arch.R2_BITS + 1))     # bits sent or received so far
        waited  = Signal(16)
        kind    = Signal(ResponseKind)
        long    = Signal()                            # kind == LONG, decoded once
        index   = Signal(arch.CMD_INDEX_BITS, reset_less=True)
        shreg   = Signal(arch.CMD_BITS - 8, reset_less=True)   # start, transmission,
                                                               # index, argument
        # The receive shift register, read as it is (a pure datapath: no reset, no clear).
        response = Signal(arch.R2_CONTENT_BITS, reset_less=True)
        m.d.comb += self.response.eq(response)

        count_1 = Signal.like(count)                  # one incrementer for every state
        m.d.comb += [self.busy.eq(state != _State.IDLE), count_1.eq(count + 1)]
        m.d.sync += self.done.eq(0)

        # The CRC covers the first 40 bits of a command or 48-bit response, and bits 8..127
        # of an R2 (its register contents without the CRC and end bit).
        crc_span = Mux(long, (count >= arch.R2_CRC_FIRST) & (count < arch.R2_CRC_LAST),
                       count < arch.CMD_CRC_LAST)
        last_bit = Mux(long, count == arch.R2_BITS - 1, count == arch.CMD_BITS - 1)

        with m.Switch(state):
            with m.Case(_State.IDLE):
                # Waits for a command to send.
                with m.If(self.start):
                    m.d.sync += [
                        shreg.eq(Cat(self.argument, self.index, C(1, 1), C(0, 1))),
                        index.eq(self.index),
                        kind.eq(self.kind),
                        long.eq(self.kind == ResponseKind.LONG),
                        count.eq(0),
                        self.status.eq(0),
                        state.eq(_State.SEND),
                    ]
                    m.d.comb += crc.clear.eq(1)

            with m.Case(_State.SEND):
                # Puts a bit on CMD at each falling edge: 40 of command, 7 of CRC, the end bit.
                with m.If(self.fall):
                    m.d.sync += count.eq(count_1)
                    with m.If(count < arch.CMD_CRC_LAST):
                        m.d.sync += [
                            self.cmd_oe.eq(1),
                            self.cmd_o.eq(shreg[-1]),
                            shreg.eq(shreg << 1),
                        ]
                        m.d.comb += [crc.en.eq(1), crc.bit.eq(shreg[-1])]
                    with m.Elif(count < arch.CMD_BITS - 1):
                        # The CRC goes out from its top bit; fed back into itself it shifts.
                        m.d.sync += self.cmd_o.eq(crc.crc[-1])
                        m.d.comb += [crc.en.eq(1), crc.bit.eq(crc.crc[-1])]
                    with m.Elif(count == arch.CMD_BITS - 1):
                        m.d.sync += self.cmd_o.eq(1)
                    with m.Else():
                        # The end bit has been sampled: release the line.
                        m.d.sync += [self.cmd_oe.eq(0), self.cmd_o.eq(1), count.eq(0),
                                     waited.eq(0)]
                        with m.If(kind == ResponseKind.NONE):
                            m.d.sync += [state.eq(_State.GAP), self.done.eq(1)]
                        with m.Else():
                            m.d.sync += state.eq(_State.WAIT)
                        m.d.comb += crc.clear.eq(1)

            with m.Case(_State.WAIT):
                # Waits for the response's start bit, at most `timeout` clocks (`waited`
                # counts up from 0 one step at a time: equality is `>=`).
                with m.If(self.rise):
                    with m.If(self.cmd_i == 0):
                        m.d.sync += [
                            count.eq(1),
                            response.eq(Cat(self.cmd_i, response[:-1])),   # the start bit, 0
                            state.eq(_State.RECEIVE),
                        ]
                        m.d.comb += [crc.en.eq(~long), crc.bit.eq(0)]
                    with m.Elif(waited == self.timeout):
                        m.d.sync += [self.status.timeout.eq(1), count.eq(0),
                                     state.eq(_State.GAP), self.done.eq(1)]
                    with m.Else():
                        m.d.sync += waited.eq(waited + 1)

            with m.Case(_State.RECEIVE):
                # Takes a bit at each rising edge until the response is complete.
                with m.If(self.rise):
                    m.d.sync += [
                        count.eq(count_1),
                        response.eq(Cat(self.cmd_i, response[:-1])),
                    ]
                    m.d.comb += [crc.en.eq(crc_span), crc.bit.eq(self.cmd_i)]
                    with m.If(last_bit):
                        # This is the end bit; the bits before it are in `response`.
                        received_crc = response[:arch.CRC7_BITS]
                        checked = kind != ResponseKind.OCR
                        fmt_ok = Mux(kind == ResponseKind.SHORT,
                                     (response[39:45] == index) & (response[45] == 0),
                                     1)
                        m.d.sync += [
                            self.status.crc_error.eq(checked & (received_crc != crc.crc)),
                            self.status.format_error.eq(~fmt_ok),
                            self.status.end_error.eq(self.cmd_i != 1),
                            count.eq(0),
                            state.eq(_State.GAP),
                            self.done.eq(1),
                        ]

            with m.Case(_State.GAP):
                # Keeps N_CC clocks between this response and the next command.
                with m.If(self.rise):
                    m.d.sync += count.eq(count_1)
                    with m.If(count == arch.N_CC - 1):
                        m.d.sync += state.eq(_State.IDLE)

        return m
