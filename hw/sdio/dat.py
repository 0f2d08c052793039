"""SD DAT lines, 4-bit: block writer (CRC status token, busy wait) and block reader."""

from amaranth import *
from amaranth.lib import data, enum, stream, wiring
from amaranth.lib.wiring import In, Out

from ..arch import sd as arch
from .crc import Crc16Lanes


__all__ = ["WriteStatus", "DatWriter", "ReadStatus", "DatReader"]

LANES = 4
ALL_LINES = (1 << LANES) - 1


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
    token_timeout : ``In(8)``
        Clocks from the end bit to the token's start bit.
    busy_timeout : ``In(32)``
        Clocks of busy before giving up (250 ms at 25 MHz by default).
    busy, done : ``Out(1)``; status : ``Out(WriteStatus)``; accepted : ``Out(16)``
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
    token_timeout: In(8, init=arch.TOKEN_TIMEOUT_CLOCKS)
    busy_timeout:  In(32, init=arch.BUSY_TIMEOUT_CLOCKS)
    busy:          Out(1)
    done:          Out(1)
    status:        Out(WriteStatus)
    accepted:      Out(16)

    def elaborate(self, platform):
        m = Module()
        m.submodules.crc16 = crc = Crc16Lanes(LANES)

        state   = Signal(_WState)
        count   = Signal(range(arch.DATA_NIBBLES + 1))
        left    = Signal(16)                       # blocks still to send
        waited  = Signal(32)
        token   = Signal(arch.TOKEN_STATUS_BITS)
        byte    = Signal(8)
        loaded  = Signal()                         # `byte` holds the next byte to send
        low     = Signal()                         # its high nibble has gone out

        # A byte is wanted while this block's data goes out, and after it only if another
        # block follows (its first byte is then taken ahead, during the token and busy).
        wanted = Signal()
        m.d.comb += wanted.eq(
            state.as_value().matches(_WState.PREAMBLE, _WState.START, _WState.DATA) |
            ((left > 1) & state.as_value().matches(_WState.CRC, _WState.END, _WState.RELEASE,
                                                   _WState.TOKEN, _WState.BUSY_START,
                                                   _WState.BUSY)))
        m.d.comb += [
            self.busy.eq(state != _WState.IDLE),
            self.i.ready.eq(~loaded & wanted),
            # Pause before a rising edge if the falling edge after it needs a byte that has
            # not arrived (and is not arriving in this cycle).
            self.run.eq(~((state == _WState.DATA) & ~low & ~loaded & ~self.i.valid &
                          (count < arch.DATA_NIBBLES))),
        ]
        with m.If(self.i.valid & self.i.ready):
            m.d.sync += [byte.eq(self.i.payload), loaded.eq(1)]
        m.d.sync += self.done.eq(0)

        def finish(**flags):
            # A byte taken ahead for a block that will not be sent is dropped with the run:
            # the next run starts from its own first byte.
            m.d.sync += [state.eq(_WState.IDLE), self.done.eq(1), self.dat_oe.eq(0),
                         self.dat_o.eq(ALL_LINES), loaded.eq(0)]
            for name, value in flags.items():
                m.d.sync += getattr(self.status, name).eq(value)

        with m.Switch(state):
            with m.Case(_WState.IDLE):
                # Waits for a write.
                with m.If(self.start & (self.blocks != 0)):
                    m.d.sync += [left.eq(self.blocks), self.accepted.eq(0),
                                 self.status.eq(0), count.eq(0), state.eq(_WState.PREAMBLE)]

            with m.Case(_WState.PREAMBLE):
                # Drives ones for N_WR clocks before the start bit.
                with m.If(self.fall):
                    m.d.sync += [self.dat_oe.eq(1), self.dat_o.eq(ALL_LINES),
                                 count.eq(count + 1)]
                    with m.If(count == arch.N_WR - 1):
                        m.d.sync += state.eq(_WState.START)

            with m.Case(_WState.START):
                # Drives the start bit on all lines.
                m.d.comb += crc.clear.eq(1)
                with m.If(self.fall):
                    m.d.sync += [self.dat_o.eq(0), count.eq(0), low.eq(0),
                                 state.eq(_WState.DATA)]

            with m.Case(_WState.DATA):
                # Drives a nibble at each falling edge, high nibble first.
                with m.If(self.fall):
                    nibble = Mux(low, byte[:4], byte[4:])
                    m.d.sync += [self.dat_o.eq(nibble), low.eq(~low), count.eq(count + 1)]
                    m.d.comb += [crc.en.eq(1), crc.bits.eq(nibble)]
                    with m.If(low):
                        m.d.sync += loaded.eq(0)
                    with m.If(count == arch.DATA_NIBBLES - 1):
                        m.d.sync += [count.eq(0), state.eq(_WState.CRC)]

            with m.Case(_WState.CRC):
                # Drives each line's CRC16, most significant bit first.
                with m.If(self.fall):
                    bit = Signal(range(arch.CRC16_BITS))
                    m.d.comb += bit.eq(arch.CRC16_BITS - 1 - count)
                    m.d.sync += [
                        self.dat_o.eq(Cat(crc.crc[lane].bit_select(bit, 1)
                                          for lane in range(LANES))),
                        count.eq(count + 1),
                    ]
                    with m.If(count == arch.CRC16_BITS - 1):
                        m.d.sync += state.eq(_WState.END)

            with m.Case(_WState.END):
                # Drives the end bit.
                with m.If(self.fall):
                    m.d.sync += [self.dat_o.eq(ALL_LINES), state.eq(_WState.RELEASE)]

            with m.Case(_WState.RELEASE):
                # Releases the lines after the end bit has been sampled.
                with m.If(self.fall):
                    m.d.sync += [self.dat_oe.eq(0), waited.eq(0), state.eq(_WState.TOKEN),
                                 count.eq(0)]

            with m.Case(_WState.TOKEN):
                # Waits for the CRC status token on DAT0 and reads it.
                with m.If(self.rise):
                    with m.If(count == 0):
                        with m.If(self.dat_i[0] == 0):
                            m.d.sync += count.eq(1)
                        with m.Elif(waited >= self.token_timeout):
                            finish(no_token=1)
                        with m.Else():
                            m.d.sync += waited.eq(waited + 1)
                    with m.Elif(count <= arch.TOKEN_STATUS_BITS):
                        m.d.sync += [token.eq(Cat(self.dat_i[0], token[:-1])),
                                     count.eq(count + 1)]
                    with m.Else():
                        # The token's end bit.
                        with m.If(self.dat_i[0] != 1):
                            finish(bad_token_end=1)
                        with m.Elif(token == arch.TOKEN_CRC_ERROR):
                            finish(crc_rejected=1)
                        with m.Elif(token != arch.TOKEN_ACCEPTED):
                            finish(write_error=1)
                        with m.Else():
                            m.d.sync += [waited.eq(0), count.eq(0),
                                         state.eq(_WState.BUSY_START)]

            def block_done():
                m.d.sync += [self.accepted.eq(self.accepted + 1), left.eq(left - 1),
                             count.eq(0)]
                with m.If(left == 1):
                    finish()
                with m.Else():
                    m.d.sync += state.eq(_WState.PREAMBLE)

            with m.Case(_WState.BUSY_START):
                # Waits for the card to pull DAT0 low (busy): at the rising edges 1 to
                # BUSY_START_CLOCKS + 1 after the token's end bit. DAT0 high at all of them:
                # the card shows no busy, the block is programmed.
                with m.If(self.rise):
                    m.d.sync += waited.eq(waited + 1)
                    with m.If(self.dat_i[0] == 0):
                        m.d.sync += state.eq(_WState.BUSY)
                    with m.Elif(waited >= arch.BUSY_START_CLOCKS):
                        block_done()

            with m.Case(_WState.BUSY):
                # Waits for the card to release DAT0 (programming done), with a timeout
                # counted from the token's end bit.
                with m.If(self.rise):
                    m.d.sync += waited.eq(waited + 1)
                    with m.If(self.dat_i[0] == 1):
                        block_done()
                    with m.Elif(waited >= self.busy_timeout):
                        finish(busy_timeout=1)

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
    start : ``In(1)``
    timeout : ``In(32)``
        Clocks to wait for the start bit (100 ms at 25 MHz by default, PLSS §4.6.2.1).
    o : ``Out(stream.Signature(8))``
    busy, done : ``Out(1)``; status : ``Out(ReadStatus)``
    """
    rise:    In(1)
    fall:    In(1)
    run:     Out(1)
    dat_i:   In(LANES, init=ALL_LINES)
    start:   In(1)
    timeout: In(32, init=arch.READ_TIMEOUT_CLOCKS)
    o:       Out(stream.Signature(8))
    busy:    Out(1)
    done:    Out(1)
    status:  Out(ReadStatus)

    def elaborate(self, platform):
        m = Module()
        m.submodules.crc16 = crc = Crc16Lanes(LANES)

        state   = Signal(_RState)
        count   = Signal(range(arch.DATA_NIBBLES + 1))
        waited  = Signal(32)
        high    = Signal(4)                  # the high nibble of the byte being received
        mismatch = Signal()

        m.d.comb += [
            self.busy.eq(state != _RState.IDLE),
            # Hold the clock while a received byte waits to be taken.
            self.run.eq(~(self.o.valid & ~self.o.ready)),
        ]
        with m.If(self.o.ready):
            m.d.sync += self.o.valid.eq(0)
        m.d.sync += self.done.eq(0)

        with m.Switch(state):
            with m.Case(_RState.IDLE):
                # Waits for a read to be started (after the CMD17 was sent).
                with m.If(self.start):
                    m.d.sync += [waited.eq(0), self.status.eq(0), mismatch.eq(0),
                                 state.eq(_RState.WAIT)]
                m.d.comb += crc.clear.eq(1)

            with m.Case(_RState.WAIT):
                # Waits for the start bit on all lines.
                with m.If(self.rise):
                    with m.If(self.dat_i == 0):
                        m.d.sync += [count.eq(0), state.eq(_RState.DATA)]
                    with m.Elif(waited >= self.timeout):
                        m.d.sync += [self.status.timeout.eq(1), self.done.eq(1),
                                     state.eq(_RState.IDLE)]
                    with m.Else():
                        m.d.sync += waited.eq(waited + 1)

            with m.Case(_RState.DATA):
                # Takes a nibble at each rising edge; a byte per two.
                with m.If(self.rise):
                    m.d.comb += [crc.en.eq(1), crc.bits.eq(self.dat_i)]
                    m.d.sync += count.eq(count + 1)
                    with m.If(count[0] == 0):
                        m.d.sync += high.eq(self.dat_i)
                    with m.Else():
                        m.d.sync += [self.o.payload.eq(Cat(self.dat_i, high)),
                                     self.o.valid.eq(1)]
                    with m.If(count == arch.DATA_NIBBLES - 1):
                        m.d.sync += [count.eq(0), state.eq(_RState.CRC)]

            with m.Case(_RState.CRC):
                # Compares each line's CRC16 bit by bit, then checks the end bit.
                with m.If(self.rise):
                    m.d.sync += count.eq(count + 1)
                    with m.If(count < arch.CRC16_BITS):
                        bit = Signal(range(arch.CRC16_BITS))
                        m.d.comb += bit.eq(arch.CRC16_BITS - 1 - count)
                        expected = Cat(crc.crc[lane].bit_select(bit, 1) for lane in range(LANES))
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
