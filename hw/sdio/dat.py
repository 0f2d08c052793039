"""SD DAT lines, 4-bit: block writer (CRC status token, busy wait) and block reader."""

from amaranth import *
from amaranth.lib import data, enum, stream, wiring
from amaranth.lib.wiring import In, Out

from ..arch import sd as arch
from .clock import TICK_CLOCKS
from .crc import crc16_lanes_signature


__all__ = ["BUSY_TIMEOUT_TICKS", "READ_TIMEOUT_TICKS", "WriteStatus", "DatWriter",
           "ReadStatus", "DatReader"]

LANES = 4
ALL_LINES = (1 << LANES) - 1

#: The default long timeouts in ticks of TICK_CLOCKS SD clocks (a timeout of N ticks ends
#: N to N + 1 ticks after its start): the clocks of hw/arch, to within a tick.
BUSY_TIMEOUT_TICKS = arch.BUSY_TIMEOUT_CLOCKS // TICK_CLOCKS
READ_TIMEOUT_TICKS = arch.READ_TIMEOUT_CLOCKS // TICK_CLOCKS
TIMEOUT_TICK_BITS = 16


class WriteStatus(data.Struct):
    """Why a multi-block write stopped early (all zero: every block was accepted)."""
    crc_rejected:  1    # the card answered the CRC status `101`
    write_error:   1    # any other token
    no_token:      1    # no token start bit within the token timeout
    bad_token_end: 1    # the token's end bit was 0
    busy_timeout:  1    # DAT0 stayed busy past the busy timeout


class _WState(enum.Enum, shape=4):
    IDLE       = 0    # waits for `start`
    PREAMBLE   = 1    # N_WR clocks of ones before the start bit
    START      = 2    # the start bit on every line
    DATA       = 3    # 1024 nibbles, high nibble first
    CRC        = 4    # each line's CRC16
    END        = 5    # the end bit
    RELEASE    = 6    # lines released after the end bit was sampled
    TOKEN      = 7    # waits for the CRC status token on DAT0 and reads it
    BUSY_START = 9    # waits for busy (DAT0 low) to begin, BUSY_START_CLOCKS at most
    BUSY       = 8    # waits for the end of busy (DAT0 high), up to the busy timeout


class DatWriter(wiring.Component):
    """Writes ``blocks`` 512-byte blocks back to back (one CMD24, or a CMD25 run).

    Per block, on the SD clock's falling edges: N_WR clocks of ones, the start bit (0 on all
    lines), 1024 nibbles high nibble first, 16 CRC bits per line, the end bit; the lines are
    then released and, on rising edges, the CRC status token is awaited on DAT0 (start 0,
    three status bits, end 1) and then the busy: its start (DAT0 low) within
    ``arch.BUSY_START_CLOCKS`` clocks of the token's end bit, then its end (DAT0 high
    again); a card that shows no busy in that window has finished. The next block
    follows without CPU help. A rejected block, a missing token or a busy timeout stops the
    run and is reported; ``accepted`` counts the blocks the card took.

    ``wait_busy`` runs the busy wait alone, as after a block's token: the R1b busy after a
    command (CMD7, CMD12). It changes neither ``accepted`` nor ``status``; its timeout shows
    in ``r1b_timeout`` instead.

    When the next byte is not there in time the clock pauses (``run`` low) instead of
    sending a bit that is not ready.

    Members
    -------
    rise, fall : ``In(1)``
    run : ``Out(1)``
    dat_o : ``Out(4)``, dat_oe : ``Out(1)``, dat_i : ``In(4)``
    i : ``In(stream.Signature(8))``
        The bytes of the blocks, in order.
    start : ``In(1)``; blocks : ``In(16)``
    tick : ``In(1)``
        :class:`~.clock.SdClock`'s ``tick``, with a ``rise`` every TICK_CLOCKS rising edges.
    token_timeout : ``In(8)``
        Clocks from the end bit to the token's start bit.
    busy_timeout : ``In(16)``
        Ticks of busy before giving up, counted from the token's end bit (or ``wait_busy``):
        the wait ends N to N + 1 ticks after it (250 ms at 25 MHz by default).
    wait_busy : ``In(1)``
        Wait for the end of an R1b busy (ignored when busy).
    busy, done : ``Out(1)``; status : ``Out(WriteStatus)``; accepted : ``Out(16)``
    r1b_timeout : ``Out(1)``
        The last ``wait_busy`` ended by the busy timeout.
    crc : ``Out(crc16_lanes_signature(4))``
        To a :class:`~.crc.Crc16Lanes` (shared with the reader in the host): cleared at the
        start bit, fed each data nibble and CRC bit; the lines' top bits are sent.

    ``blocks`` must stay unchanged through a run: the run ends when ``accepted + 1`` blocks
    equal it at a block's end.
    """
    rise:          In(1)
    fall:          In(1)
    run:           Out(1)
    dat_o:         Out(LANES, init=ALL_LINES)
    dat_oe:        Out(1)
    dat_i:         In(LANES, init=ALL_LINES)
    i:             In(stream.Signature(8))
    start:         In(1)
    blocks:        In(16)
    tick:          In(1)
    token_timeout: In(8, init=arch.TOKEN_TIMEOUT_CLOCKS)
    busy_timeout:  In(TIMEOUT_TICK_BITS, init=BUSY_TIMEOUT_TICKS)
    wait_busy:     In(1)
    busy:          Out(1)
    done:          Out(1)
    status:        Out(WriteStatus)
    accepted:      Out(16)
    r1b_timeout:   Out(1)
    crc:           Out(crc16_lanes_signature(LANES))

    def elaborate(self, platform):
        m = Module()
        crc = self.crc

        state   = Signal(_WState)
        count   = Signal(range(arch.DATA_NIBBLES + 1))
        waited  = Signal(8)                        # rising edges since the block's end,
                                                   # then since the token's
        ticks   = Signal(TIMEOUT_TICK_BITS)        # busy timeout ticks left
        past    = Signal()                         # the busy timeout has run out
        r1b     = Signal()                         # the busy wait is an R1b's
        token   = Signal(arch.TOKEN_STATUS_BITS, reset_less=True)
        byte    = Signal(8, reset_less=True)
        loaded  = Signal()                         # `byte` holds the next byte to send
        low     = Signal()                         # its high nibble has gone out

        # The state machine below only decides; the registers are updated after it, each
        # in one place, from these strobes.
        count_clear = Signal()
        count_step  = Signal()
        waited_step = Signal()
        reload      = Signal()                     # restart the busy timeout
        block_done  = Signal()                     # busy over: the card took the block
        finish      = Signal()                     # the run (or R1b wait) ends
        flags       = Signal(WriteStatus)          # errors it ends with
        next_state  = Signal(_WState)
        m.d.comb += next_state.eq(state)

        # The block going out is the run's last (`blocks` is constant through a run). One
        # cycle late: it is only used from a block's CRC on, long after `accepted` moved.
        last = Signal()
        next_accepted = Signal(16)
        m.d.comb += next_accepted.eq(self.accepted + 1)
        m.d.sync += last.eq(next_accepted == self.blocks)

        in_state = {s: state == s for s in _WState}
        go_write = in_state[_WState.IDLE] & self.start & (self.blocks != 0)
        go_busy  = in_state[_WState.IDLE] & self.wait_busy & ~go_write

        # A byte is wanted while this block's data goes out, and after it only if another
        # block follows (its first byte is then taken ahead, during the token and busy).
        wanted = Signal()
        m.d.comb += wanted.eq(
            state.as_value().matches(_WState.PREAMBLE, _WState.START, _WState.DATA) |
            (~r1b & ~last &
             state.as_value().matches(_WState.CRC, _WState.END, _WState.RELEASE,
                                      _WState.TOKEN, _WState.BUSY_START, _WState.BUSY)))
        m.d.comb += [
            self.busy.eq(~in_state[_WState.IDLE]),
            self.i.ready.eq(~loaded & wanted),
            # Pause before a rising edge if the falling edge after it needs a byte that has
            # not arrived (and is not arriving in this cycle).
            self.run.eq(~(in_state[_WState.DATA] & ~low & ~loaded & ~self.i.valid &
                          (count < arch.DATA_NIBBLES))),
        ]

        # The busy timeout: `ticks` counts down from `busy_timeout` and runs out at the next
        # tick after it reached 0; `past` keeps that when it happens before BUSY (a timeout
        # shorter than the busy start window ends at BUSY's first edge).
        out = self.tick & (ticks == 0)
        reached = past | out

        nibble = Mux(low, byte[:4], byte[4:])
        top = Cat(crc.crc[lane][-1] for lane in range(LANES))   # each line's next CRC bit

        with m.Switch(state):
            with m.Case(_WState.IDLE):
                # Waits for a write, or an R1b busy wait.
                with m.If(go_write):
                    m.d.comb += next_state.eq(_WState.PREAMBLE)
                with m.Elif(go_busy):
                    m.d.comb += next_state.eq(_WState.BUSY_START)

            with m.Case(_WState.PREAMBLE):
                # Drives ones for N_WR clocks before the start bit.
                with m.If(self.fall):
                    m.d.comb += count_step.eq(1)
                    with m.If(count == arch.N_WR - 1):
                        m.d.comb += next_state.eq(_WState.START)

            with m.Case(_WState.START):
                # Drives the start bit on all lines.
                with m.If(self.fall):
                    m.d.comb += [count_clear.eq(1), next_state.eq(_WState.DATA)]

            with m.Case(_WState.DATA):
                # Drives a nibble at each falling edge, high nibble first.
                with m.If(self.fall):
                    m.d.comb += count_step.eq(1)
                    with m.If(count == arch.DATA_NIBBLES - 1):
                        m.d.comb += [count_clear.eq(1), next_state.eq(_WState.CRC)]

            with m.Case(_WState.CRC):
                # Drives each line's CRC16, most significant bit first: its top bit, fed
                # back into it, shifts the register up by one.
                with m.If(self.fall):
                    m.d.comb += count_step.eq(1)
                    with m.If(count == arch.CRC16_BITS - 1):
                        m.d.comb += next_state.eq(_WState.END)

            with m.Case(_WState.END):
                # Drives the end bit.
                with m.If(self.fall):
                    m.d.comb += next_state.eq(_WState.RELEASE)

            with m.Case(_WState.RELEASE):
                # Releases the lines after the end bit has been sampled.
                with m.If(self.fall):
                    m.d.comb += [count_clear.eq(1), next_state.eq(_WState.TOKEN)]

            with m.Case(_WState.TOKEN):
                # Waits for the CRC status token on DAT0 and reads it. (`waited` counts up
                # from 0 one step at a time: equality is `>=`.)
                with m.If(self.rise):
                    with m.If(count == 0):
                        m.d.comb += waited_step.eq(1)
                        with m.If(self.dat_i[0] == 0):
                            m.d.comb += count_step.eq(1)
                        with m.Elif(waited == self.token_timeout):
                            m.d.comb += [finish.eq(1), flags.no_token.eq(1)]
                    with m.Elif(count <= arch.TOKEN_STATUS_BITS):
                        m.d.comb += count_step.eq(1)
                    with m.Else():
                        # The token's end bit.
                        with m.If(self.dat_i[0] != 1):
                            m.d.comb += [finish.eq(1), flags.bad_token_end.eq(1)]
                        with m.Elif(token == arch.TOKEN_CRC_ERROR):
                            m.d.comb += [finish.eq(1), flags.crc_rejected.eq(1)]
                        with m.Elif(token != arch.TOKEN_ACCEPTED):
                            m.d.comb += [finish.eq(1), flags.write_error.eq(1)]
                        with m.Else():
                            m.d.comb += [count_clear.eq(1), reload.eq(1),
                                         next_state.eq(_WState.BUSY_START)]

            with m.Case(_WState.BUSY_START):
                # Waits for the card to pull DAT0 low (busy): at the rising edges 1 to
                # BUSY_START_CLOCKS + 1 after the token's end bit. DAT0 high at all of them:
                # the card shows no busy, the block is programmed.
                with m.If(self.rise):
                    m.d.comb += waited_step.eq(1)
                    with m.If(self.dat_i[0] == 0):
                        m.d.comb += next_state.eq(_WState.BUSY)
                    with m.Elif(waited == arch.BUSY_START_CLOCKS):
                        m.d.comb += block_done.eq(1)

            with m.Case(_WState.BUSY):
                # Waits for the card to release DAT0 (programming done), with a timeout
                # counted from the token's end bit.
                with m.If(self.rise):
                    with m.If(self.dat_i[0] == 1):
                        m.d.comb += block_done.eq(1)
                    with m.Elif(reached):
                        m.d.comb += [finish.eq(1), flags.busy_timeout.eq(~r1b)]
                        m.d.sync += self.r1b_timeout.eq(r1b)

        # A block done ends an R1b wait, or the run after its last block.
        block_counted = block_done & ~r1b
        with m.If(block_done):
            with m.If(r1b | last):
                m.d.comb += finish.eq(1)
            with m.Else():
                m.d.comb += next_state.eq(_WState.PREAMBLE)
        with m.If(finish):
            m.d.comb += next_state.eq(_WState.IDLE)
        m.d.sync += [state.eq(next_state), self.done.eq(finish)]

        # The registers.
        with m.If(in_state[_WState.IDLE] | count_clear | block_done):
            m.d.sync += count.eq(0)
        with m.Elif(count_step):
            m.d.sync += count.eq(count + 1)
        with m.If(in_state[_WState.IDLE] | (self.fall & in_state[_WState.RELEASE]) | reload):
            m.d.sync += waited.eq(0)
        with m.Elif(waited_step):
            m.d.sync += waited.eq(waited + 1)
        with m.If(in_state[_WState.IDLE] | reload):
            m.d.sync += ticks.eq(self.busy_timeout)
        with m.Elif(self.tick & (ticks != 0)):
            m.d.sync += ticks.eq(ticks - 1)
        with m.If(in_state[_WState.IDLE] | in_state[_WState.TOKEN]):
            m.d.sync += past.eq(0)
        with m.Else():
            m.d.sync += past.eq(reached)
        with m.If(in_state[_WState.IDLE]):
            m.d.sync += r1b.eq(~go_write)
        with m.If(go_write):
            m.d.sync += [self.accepted.eq(0), self.status.eq(0)]
        with m.Elif(block_counted):
            m.d.sync += self.accepted.eq(next_accepted)
        with m.Elif(finish):
            m.d.sync += self.status.eq(self.status.as_value() | flags.as_value())
        with m.If(go_busy):
            m.d.sync += self.r1b_timeout.eq(0)
        with m.If(self.rise & in_state[_WState.TOKEN] & (count != 0) &
                  (count <= arch.TOKEN_STATUS_BITS)):
            m.d.sync += token.eq(Cat(self.dat_i[0], token[:-1]))

        # The lines: driven from the first preamble bit to the end bit; each falling edge
        # puts the next level on them.
        with m.If(self.fall & in_state[_WState.PREAMBLE]):
            m.d.sync += self.dat_oe.eq(1)
        with m.If(self.fall & in_state[_WState.RELEASE]):
            m.d.sync += self.dat_oe.eq(0)
        with m.If(self.fall & state.as_value().matches(_WState.PREAMBLE, _WState.START,
                                                       _WState.DATA, _WState.CRC,
                                                       _WState.END)):
            with m.Switch(state):
                with m.Case(_WState.START):
                    m.d.sync += self.dat_o.eq(0)
                with m.Case(_WState.DATA):
                    m.d.sync += self.dat_o.eq(nibble)
                with m.Case(_WState.CRC):
                    m.d.sync += self.dat_o.eq(top)
                with m.Default():
                    m.d.sync += self.dat_o.eq(ALL_LINES)
        m.d.comb += [
            crc.clear.eq(in_state[_WState.START]),
            crc.en.eq(self.fall & (in_state[_WState.DATA] | in_state[_WState.CRC])),
            crc.bits.eq(Mux(in_state[_WState.CRC], top, nibble)),
        ]

        # The byte to send: taken when wanted; a byte taken ahead for a block that will not
        # be sent is dropped with the run (the next run starts from its own first byte).
        with m.If(self.i.valid & self.i.ready):
            m.d.sync += [byte.eq(self.i.payload), loaded.eq(1)]
        with m.If((self.fall & in_state[_WState.DATA] & low) | finish):
            m.d.sync += loaded.eq(0)
        with m.If(self.fall & in_state[_WState.START]):
            m.d.sync += low.eq(0)
        with m.Elif(self.fall & in_state[_WState.DATA]):
            m.d.sync += low.eq(~low)

        return m


class ReadStatus(data.Struct):
    """Outcome of a block read."""
    timeout:   1    # no start bit within the read timeout
    crc_error: 1    # a line's CRC16 does not match
    end_error: 1    # the end bit was not 1 on every line


class _RState(enum.Enum, shape=2):
    IDLE  = 0    # waits for `start`
    WAIT  = 1    # waits for the start bit on every line, `timeout` clocks at most
    DATA  = 2    # takes 1024 nibbles, a byte out per two
    CRC   = 3    # compares each line's CRC16, then checks the end bit


class DatReader(wiring.Component):
    """Reads one 512-byte block (CMD17) from the 4-bit bus, checking each line's CRC16.

    Bytes go out on ``o`` as they complete; when ``o`` is not ready the clock pauses before
    the card can send more. ``done`` ends the block with ``status``.

    Members
    -------
    rise, fall : ``In(1)``; run : ``Out(1)``; dat_i : ``In(4)``
    tick : ``In(1)``
        :class:`~.clock.SdClock`'s ``tick``, with a ``rise`` every TICK_CLOCKS rising edges.
    start : ``In(1)``
    timeout : ``In(16)``
        Ticks to wait for the start bit: the wait ends N to N + 1 ticks after ``start``
        (100 ms at 25 MHz by default, PLSS §4.6.2.1).
    o : ``Out(stream.Signature(8))``
    busy, done : ``Out(1)``; status : ``Out(ReadStatus)``
    crc : ``Out(crc16_lanes_signature(4))``
        To a :class:`~.crc.Crc16Lanes` (shared with the writer in the host): cleared while
        the start bit is awaited, fed the data and CRC bits received.
    """
    rise:    In(1)
    fall:    In(1)
    run:     Out(1)
    dat_i:   In(LANES, init=ALL_LINES)
    tick:    In(1)
    start:   In(1)
    timeout: In(TIMEOUT_TICK_BITS, init=READ_TIMEOUT_TICKS)
    o:       Out(stream.Signature(8))
    busy:    Out(1)
    done:    Out(1)
    status:  Out(ReadStatus)
    crc:     Out(crc16_lanes_signature(LANES))

    def elaborate(self, platform):
        m = Module()
        crc = self.crc

        state   = Signal(_RState)
        count   = Signal(range(arch.DATA_NIBBLES))   # nibbles, then CRC bits (it wraps
                                                     # to 0 after the last nibble)
        ticks   = Signal(TIMEOUT_TICK_BITS)          # read timeout ticks left
        high    = Signal(4, reset_less=True)   # the high nibble of the byte being received
        payload = Signal(8, reset_less=True)
        mismatch = Signal()
        m.d.comb += self.o.payload.eq(payload)

        idle, wait, data, check = (state == s for s in _RState)
        # Each line's next CRC bit: the received bits go into the CRC after the data too;
        # while they match its top bit, it shifts up by one and its next top bit is the next
        # one expected.
        expected = Cat(crc.crc[lane][-1] for lane in range(LANES))
        crc_bits = check & (count < arch.CRC16_BITS)
        m.d.comb += [
            self.busy.eq(~idle),
            # Hold the clock while a received byte waits to be taken.
            self.run.eq(~(self.o.valid & ~self.o.ready)),
            crc.clear.eq(wait),
            crc.en.eq(self.rise & (data | crc_bits)),
            crc.bits.eq(self.dat_i),
        ]
        with m.If(self.o.ready):
            m.d.sync += self.o.valid.eq(0)
        with m.If(idle | wait):
            m.d.sync += count.eq(0)
        with m.Elif(self.rise):
            m.d.sync += count.eq(count + 1)
        with m.If(idle):
            m.d.sync += ticks.eq(self.timeout)
        with m.Elif(self.tick & (ticks != 0)):
            m.d.sync += ticks.eq(ticks - 1)
        m.d.sync += self.done.eq(0)

        with m.Switch(state):
            with m.Case(_RState.IDLE):
                # Waits for a read to be started (after the CMD17 was sent).
                with m.If(self.start):
                    m.d.sync += [self.status.eq(0), mismatch.eq(0), state.eq(_RState.WAIT)]

            with m.Case(_RState.WAIT):
                # Waits for the start bit on all lines.
                with m.If(self.rise):
                    with m.If(self.dat_i == 0):
                        m.d.sync += state.eq(_RState.DATA)
                    with m.Elif(self.tick & (ticks == 0)):
                        m.d.sync += [self.status.timeout.eq(1), self.done.eq(1),
                                     state.eq(_RState.IDLE)]

            with m.Case(_RState.DATA):
                # Takes a nibble at each rising edge; a byte per two.
                with m.If(self.rise):
                    with m.If(count[0] == 0):
                        m.d.sync += high.eq(self.dat_i)
                    with m.Else():
                        m.d.sync += [payload.eq(Cat(self.dat_i, high)),
                                     self.o.valid.eq(1)]
                    with m.If(count == arch.DATA_NIBBLES - 1):
                        m.d.sync += state.eq(_RState.CRC)

            with m.Case(_RState.CRC):
                # Compares each line's CRC16 bit by bit, then checks the end bit.
                with m.If(self.rise):
                    with m.If(crc_bits):
                        with m.If(expected != self.dat_i):
                            m.d.sync += mismatch.eq(1)
                    with m.Else():
                        m.d.sync += [
                            self.status.crc_error.eq(mismatch),
                            self.status.end_error.eq(self.dat_i != ALL_LINES),
                            self.done.eq(1),
                            state.eq(_RState.IDLE),
                        ]

        return m
