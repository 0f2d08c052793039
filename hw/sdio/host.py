"""SD host: clock, CMD and DAT engines behind amaranth-soc registers."""

from amaranth import *
from amaranth.lib import enum, stream, wiring
from amaranth.lib.wiring import In, Out

from ..arch import sd as arch
from ..soc import WordBridge, csr
from .clock import TICK_CLOCKS, SdClock
from .cmd import CmdEngine, CmdStatus, ResponseKind
from .crc import SharedCrc16Lanes
from .dat import (BUSY_TIMEOUT_TICKS, READ_TIMEOUT_TICKS, TIMEOUT_TICK_BITS, DatReader,
                  DatWriter, ReadStatus, WriteStatus)


__all__ = ["DataPhase", "sd_pins_signature", "SdioHost"]

#: Address bits of the register window (words of 32 bits, byte addresses).
ADDR_WIDTH = 4
#: Width of the clock divider: 400 kHz from up to 100 MHz needs a half period of 125 cycles.
DIVISOR_BITS = 10


def sd_pins_signature():
    """The SD card's pins in 4-bit SD mode, as the host drives them (``Out``: host to card).

    Each bidirectional line is split into output, output enable and input, as an FPGA's
    I/O buffer takes it; an undriven line reads high (the bus's pull-ups). ``dat_oe``
    enables all four DAT lines together.
    """
    return wiring.Signature({
        "clk":    Out(1),
        "cmd_o":  Out(1, init=1),
        "cmd_oe": Out(1),
        "cmd_i":  In(1, init=1),
        "dat_o":  Out(4, init=0xF),
        "dat_oe": Out(1),
        "dat_i":  In(4, init=0xF),
    })


class DataPhase(enum.Enum, shape=2):
    """What the DAT lines do after a command; values from :class:`~maglog.hw.arch.sd.
    DataPhase` (the firmware's view of the same field)."""
    NONE  = arch.DataPhase.NONE.value
    WRITE = arch.DataPhase.WRITE.value   # after a good response, write `blocks` blocks from `i`
    READ  = arch.DataPhase.READ.value    # read one block to `o`; armed when the command starts


class SdioHost(wiring.Component):
    """4-bit SD host for the logger: the CPU sets up commands over CSR registers, block
    data moves through streams (``i`` for writes, from the DMA; ``o`` for reads).

    Writing ``command`` sends it with ``argument``; its ``data`` field chains a data phase
    and ``r1b`` a wait for the end of busy on DAT0 (after CMD7, CMD12). ``status`` shows the
    engines busy and every error bit of the last command and transfer; nothing is retried in
    gateware, so the driver sees every failure. The settings are write-only (the firmware
    never reads them back): only the status, the accepted count and the response read.

    Members
    -------
    bus : ``In(csr.Signature(addr_width=ADDR_WIDTH, data_width=32))``
        Register access.
    i : ``In(stream.Signature(8))``; o : ``Out(stream.Signature(8))``
    sd : ``Out(sd_pins_signature())``
        The card's pins.
    """
    bus: In(csr.Signature(addr_width=ADDR_WIDTH, data_width=32))
    i:   In(stream.Signature(8))
    o:   Out(stream.Signature(8))
    sd:  Out(sd_pins_signature())

    class Clock(csr.Register, access="w"):
        """SD clock: f_sys / (2 * (divisor + 1)); `run` keeps it running while idle (the
        74 clocks of power-up, and between commands)."""
        divisor: csr.Field(csr.action.W, DIVISOR_BITS)
        run:     csr.Field(csr.action.W, 1)

    class Argument(csr.Register, access="w"):
        """Argument of the next command."""
        value: csr.Field(csr.action.W, arch.CMD_ARGUMENT_BITS)

    class Command(csr.Register, access="w"):
        """Writing sends a command: its index, the response expected, whether to wait for
        busy after it (R1b), and the data phase that follows."""
        index: csr.Field(csr.action.W, arch.CMD_INDEX_BITS)
        kind:  csr.Field(csr.action.W, ResponseKind)
        r1b:   csr.Field(csr.action.W, 1)
        data:  csr.Field(csr.action.W, DataPhase)

    class Blocks(csr.Register, access="w"):
        """Blocks to write in the next write data phase (1 at power-up; kept through a
        reset, as are the argument and the timeouts). Not to be changed during a write."""
        count: csr.Field(csr.action.W, 16)

    class Timeouts(csr.Register, access="w"):
        """Response timeout, in SD clocks (N_CR; 64 at power-up)."""
        response: csr.Field(csr.action.W, 16)

    class BusyTimeout(csr.Register, access="w"):
        """Busy timeout after a block or an R1b, in ticks of 256 SD clocks: it ends N to
        N + 1 ticks after the block's token or the R1b response (250 ms at 25 MHz at
        power-up)."""
        ticks: csr.Field(csr.action.W, TIMEOUT_TICK_BITS)

    class ReadTimeout(csr.Register, access="w"):
        """Read access timeout, in ticks of 256 SD clocks: it ends N to N + 1 ticks after
        the read command is written (100 ms at 25 MHz at power-up)."""
        ticks: csr.Field(csr.action.W, TIMEOUT_TICK_BITS)

    class Status(csr.Register, access="r"):
        """Engines busy, and the errors of the last command, write and read."""
        cmd_busy:     csr.Field(csr.action.R, 1)
        dat_busy:     csr.Field(csr.action.R, 1)
        cmd:          csr.Field(csr.action.R, CmdStatus)
        write:        csr.Field(csr.action.R, WriteStatus)
        read:         csr.Field(csr.action.R, ReadStatus)
        busy_timeout: csr.Field(csr.action.R, 1)
        dat_level:    csr.Field(csr.action.R, 4)

    class Accepted(csr.Register, access="r"):
        """Blocks the card accepted in the last write data phase."""
        count: csr.Field(csr.action.R, 16)

    class Response(csr.Register, access="r"):
        """32 bits of the last response (word 0 holds bits 31..0)."""
        value: csr.Field(csr.action.R, 32)

    def __init__(self):
        regs = csr.Builder(addr_width=ADDR_WIDTH, data_width=32, granularity=8)
        self._clock    = regs.add("clock", self.Clock())
        self._argument = regs.add("argument", self.Argument())
        self._command  = regs.add("command", self.Command())
        self._blocks   = regs.add("blocks", self.Blocks())
        self._timeouts = regs.add("timeouts", self.Timeouts())
        self._busy_timeout = regs.add("busy_timeout", self.BusyTimeout())
        self._read_timeout = regs.add("read_timeout", self.ReadTimeout())
        self._status   = regs.add("status", self.Status())
        self._accepted = regs.add("accepted", self.Accepted())
        # (Named response0..3: the vendored Bridge cannot name registers under an Index.)
        self._response = [regs.add(f"response{word}", self.Response())
                          for word in range(arch.R2_CONTENT_BITS // 32)]
        self._bridge = WordBridge(regs.as_memory_map())
        super().__init__()
        self.bus.memory_map = self._bridge.bus.memory_map

    def elaborate(self, platform):
        m = Module()
        # Every register is one bus word: WordBridge needs no shadow (hw/soc.py).
        m.submodules.bridge = self._bridge
        m.submodules.clock  = clock  = SdClock(divisor_bits=DIVISOR_BITS)
        m.submodules.cmd    = cmd    = CmdEngine()
        m.submodules.writer = writer = DatWriter()
        m.submodules.reader = reader = DatReader()
        # One data phase at a time (a read is armed by its command, a write or busy wait
        # follows its command's response): the writer and the reader share the CRC16 lanes.
        m.submodules.crc16  = crc16  = SharedCrc16Lanes(4, users=2)
        wiring.connect(m, writer.crc, crc16.users[0])
        wiring.connect(m, reader.crc, crc16.users[1])
        wiring.connect(m, wiring.flipped(self.bus), self._bridge.bus)

        for engine in (cmd, writer, reader):
            m.d.comb += [engine.rise.eq(clock.rise), engine.fall.eq(clock.fall)]

        # Pins.
        sd = self.sd
        m.d.comb += [
            sd.clk.eq(clock.clk),
            sd.cmd_o.eq(cmd.cmd_o),
            sd.cmd_oe.eq(cmd.cmd_oe),
            cmd.cmd_i.eq(sd.cmd_i),
            sd.dat_o.eq(writer.dat_o),
            sd.dat_oe.eq(writer.dat_oe),
            writer.dat_i.eq(sd.dat_i),
            reader.dat_i.eq(sd.dat_i),
        ]
        wiring.connect(m, wiring.flipped(self.i), writer.i)
        wiring.connect(m, reader.o, wiring.flipped(self.o))

        # Settings: write-only, kept here. Only the clock's are reset: the others keep their
        # values through a reset (their initial values are the defaults); the firmware
        # writes the argument and the block count before each command that uses them and
        # never changes the timeouts, and nothing reads them back.
        divisor      = Signal(DIVISOR_BITS)
        run          = Signal()
        argument     = Signal(arch.CMD_ARGUMENT_BITS, reset_less=True)
        blocks       = Signal(16, init=1, reset_less=True)
        timeout      = Signal(16, init=arch.N_CR_MAX, reset_less=True)
        busy_timeout = Signal(TIMEOUT_TICK_BITS, init=BUSY_TIMEOUT_TICKS, reset_less=True)
        read_timeout = Signal(TIMEOUT_TICK_BITS, init=READ_TIMEOUT_TICKS, reset_less=True)
        for field, target in ((self._clock.f.divisor, divisor), (self._clock.f.run, run),
                              (self._argument.f.value, argument),
                              (self._blocks.f.count, blocks),
                              (self._timeouts.f.response, timeout),
                              (self._busy_timeout.f.ticks, busy_timeout),
                              (self._read_timeout.f.ticks, read_timeout)):
            with m.If(field.w_stb):
                m.d.sync += target.eq(field.w_data)
        m.d.comb += [
            clock.divisor.eq(divisor),
            cmd.argument.eq(argument),
            cmd.timeout.eq(timeout),
            writer.blocks.eq(blocks),
            writer.tick.eq(clock.tick),
            writer.busy_timeout.eq(busy_timeout),
            reader.tick.eq(clock.tick),
            reader.timeout.eq(read_timeout),
        ]

        # A command write starts the CMD engine (and arms a read at once: the card may start
        # its block soon after the response); after a good response a write data phase
        # starts, or the R1b busy wait (the writer's busy wait, without a block).
        phase   = Signal(DataPhase)
        r1b     = Signal()
        pending = Signal()           # a data phase or busy wait waits for the response
        command = self._command.f
        with m.If(command.index.w_stb & ~cmd.busy):
            m.d.comb += [
                cmd.start.eq(1),
                cmd.index.eq(command.index.w_data),
                cmd.kind.eq(command.kind.w_data),
                reader.start.eq(command.data.w_data == DataPhase.READ),
            ]
            m.d.sync += [
                phase.eq(command.data.w_data),
                r1b.eq(command.r1b.w_data),
                pending.eq(1),
            ]

        response_ok = ~cmd.status.as_value().any()
        with m.If(pending & cmd.done):
            m.d.sync += pending.eq(0)
            with m.If(response_ok):
                with m.If(phase == DataPhase.WRITE):
                    m.d.comb += writer.start.eq(1)
                with m.Elif(r1b):
                    m.d.comb += writer.wait_busy.eq(1)

        dat_busy = writer.busy | reader.busy
        m.d.comb += clock.run.eq((run | cmd.busy | dat_busy | pending) &
                                 writer.run & reader.run)

        # Status and results.
        status = self._status.f
        m.d.comb += [
            status.cmd_busy.r_data.eq(cmd.busy | pending),
            status.dat_busy.r_data.eq(dat_busy),
            status.cmd.r_data.eq(cmd.status),
            status.write.r_data.eq(writer.status),
            status.read.r_data.eq(reader.status),
            status.busy_timeout.r_data.eq(writer.r1b_timeout),
            status.dat_level.r_data.eq(self.sd.dat_i),
            self._accepted.f.count.r_data.eq(writer.accepted),
        ]
        for word, reg in enumerate(self._response):
            m.d.comb += reg.f.value.r_data.eq(cmd.response[32 * word:32 * (word + 1)])

        return m
