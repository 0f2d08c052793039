"""DMA between the ring buffer, a CPU sector buffer and the SD host's byte streams."""

from amaranth import *
from amaranth.lib import data, enum, stream, wiring
from amaranth.lib.memory import Memory
from amaranth.lib.wiring import In, Out

from .arch import sd as arch_sd
from .ringbuffer import RingPort
from .soc import csr


__all__ = ["DmaSource", "Dma"]

WORD_BYTES = 4
BUFFER_WORDS = arch_sd.BLOCK_BYTES // WORD_BYTES

#: A write into the sector buffer: word address, data, byte-lane enables.
BufferWrite = data.StructLayout({
    "addr": range(BUFFER_WORDS),
    "data": 32,
    "en":   WORD_BYTES,
})


class DmaSource(enum.Enum, shape=1):
    """Where the bytes of the next write come from."""
    RING   = 0    # `sectors` sectors from the ring's read pointer on
    BUFFER = 1    # the CPU sector buffer (one sector: FAT, directory, boot sectors)


class Dma(wiring.Component):
    """Feeds the SD host's write stream and fills the CPU sector buffer from its read stream.

    ``start`` (register ``control``) arms a write: from the ring, sector after sector (each
    one asked of the ring as the previous one ends), or the sector buffer once. The SD host
    pulls the bytes as its DAT writer needs them, so a stalled card stalls the DMA, never the
    other way round. ``release`` hands sectors the card has accepted back to the ring. Read
    data from the SD host always goes into the sector buffer (from its start after
    ``arm_read``). The CPU reads and writes the buffer a 32-bit word at a time through
    ``buffer_data``, at ``buffer_index``, which moves on by one at each access.

    Members
    -------
    bus : ``In(csr.Signature(...))``
    ring : ``Out(RingPort(level_bits))``
        To the ring buffer's ``dma`` port.
    sd_i : ``Out(stream.Signature(8))``  (to ``SdioHost.i``)
    sd_o : ``In(stream.Signature(8, always_ready=True))``   (from ``SdioHost.o``)
    busy : ``Out(1)``
        A write is armed (register ``status.busy``).
    """

    class Control(csr.Register, access="w"):
        """Writing arms a DMA write of `sectors` sectors from `source` (for the ring: from
        its sector `first` after the read pointer on), or (arm_read) points the sector
        buffer's fill position back at its start. `abort` ends an armed write (after a
        failed transfer): the rest of a sector already asked of the ring is read and
        dropped, so the ring stays in step. `clear` empties the ring (write, committed and read
        pointers back to the start; its counters keep counting): only while not recording,
        the DMA idle and no frame in flight."""
        start:    csr.Field(csr.action.W, 1)
        source:   csr.Field(csr.action.W, DmaSource)
        arm_read: csr.Field(csr.action.W, 1)
        sectors:  csr.Field(csr.action.W, 12)
        first:    csr.Field(csr.action.W, 12)
        abort:    csr.Field(csr.action.W, 1)
        clear:    csr.Field(csr.action.W, 1)

    class Release(csr.Register, access="w"):
        """Sectors the card has accepted, handed back to the ring."""
        sectors: csr.Field(csr.action.W, 16)

    class Status(csr.Register, access="r"):
        """A write is armed and not all its sectors have gone out; sectors sent so far."""
        busy: csr.Field(csr.action.R, 1)
        sent: csr.Field(csr.action.R, 16)

    class Level(csr.Register, access="r"):
        """Committed bytes in the ring that the card does not have yet."""
        bytes: csr.Field(csr.action.R, 32)

    class HighWater(csr.Register, access="r"):
        """The most committed bytes the ring ever held."""
        bytes: csr.Field(csr.action.R, 32)

    class Kept(csr.Register, access="r"):
        """Frames stored in the ring."""
        frames: csr.Field(csr.action.R, 32)

    class Dropped(csr.Register, access="r"):
        """Frames dropped because the ring was full."""
        frames: csr.Field(csr.action.R, 32)

    class BufferSeek(csr.Register, access="w"):
        """Moves the sector buffer's word index (for `buffer_write` and `buffer_read`)."""
        index: csr.Field(csr.action.W, 7)

    class BufferWrite(csr.Register, access="w"):
        """Writes a word (bytes low first) at the index, which moves on by one."""
        word: csr.Field(csr.action.W, 32)

    class BufferRead(csr.Register, access="r"):
        """The word at the index; reading moves the index on by one."""
        word: csr.Field(csr.action.R, 32)

    def __init__(self, *, level_bits=32):
        regs = csr.Builder(addr_width=4, data_width=32, granularity=8)
        self._control = regs.add("control", self.Control())
        self._release = regs.add("release", self.Release())
        self._status = regs.add("status", self.Status())
        self._level = regs.add("level", self.Level())
        self._high_water = regs.add("high_water", self.HighWater())
        self._kept = regs.add("kept", self.Kept())
        self._dropped = regs.add("dropped", self.Dropped())
        self._buffer_seek = regs.add("buffer_seek", self.BufferSeek())
        self._buffer_write = regs.add("buffer_write", self.BufferWrite())
        self._buffer_read = regs.add("buffer_read", self.BufferRead())
        memory_map = regs.as_memory_map()
        super().__init__({
            "bus":                  In(csr.Signature(addr_width=memory_map.addr_width,
                                                     data_width=memory_map.data_width)),
            "ring":                 Out(RingPort(level_bits)),
            "sd_i":                 Out(stream.Signature(8)),
            "sd_o":                 In(stream.Signature(8, always_ready=True)),
            "busy":                 Out(1),
        })
        self.bus.memory_map = memory_map

    def _registers(self, m):
        """The registers on the CSR bus. Every register is one bus word, so reads need no
        shadow: a read strobe latches the register (other reads latch zero, the bus's idle
        value) and the data are on the bus the next clock; a write reaches its register a
        clock after the bus write, with the data latched then (as amaranth-soc's
        multiplexer does)."""
        bus = self.bus
        w_data = Signal(bus.data_width, reset_less=True)
        m.d.sync += w_data.eq(bus.w_data)
        # Without reset: it latches zero whenever there is no read, so also while the
        # CPU is held in reset.
        r_data = Signal(bus.data_width, reset_less=True)
        r_fanin = 0
        for reg, name, (start, end) in bus.memory_map.resources():
            assert end == start + 1
            m.submodules["_".join(name)] = reg
            element, selected = reg.element, bus.addr == start
            if element.access.readable():
                m.d.comb += element.r_stb.eq(bus.r_stb & selected)
                r_fanin |= Mux(element.r_stb, element.r_data, 0)
            if element.access.writable():
                m.d.sync += element.w_stb.eq(bus.w_stb & selected)
                m.d.comb += element.w_data.eq(w_data)
        m.d.sync += r_data.eq(r_fanin)
        m.d.comb += bus.r_data.eq(r_data)

    def elaborate(self, platform):
        m = Module()
        self._registers(m)

        m.submodules.buffer = buffer = Memory(shape=32, depth=BUFFER_WORDS, init=[])
        # One write port and one synchronous read port, so that the buffer is one M9K: CPU
        # words and SD read bytes share the write port (a fill wins; the firmware does not
        # write the buffer while a read fills it), the CPU and the DMA share the read port
        # (the DMA while it sends the buffer). A read port is given the next cycle's address.
        write_port = buffer.write_port(granularity=8)
        read_port = buffer.read_port()
        cpu_write = Signal(BufferWrite)
        fill_write = Signal(BufferWrite)
        with m.If(fill_write.en.any()):
            m.d.comb += [write_port.addr.eq(fill_write.addr), write_port.data.eq(fill_write.data),
                         write_port.en.eq(fill_write.en)]
        with m.Else():
            m.d.comb += [write_port.addr.eq(cpu_write.addr), write_port.data.eq(cpu_write.data),
                         write_port.en.eq(cpu_write.en)]

        self._ring_status(m)
        # The buffer's word index serves the CPU and, while it sends the buffer, the DMA.
        send_start, send_next = Signal(), Signal()
        m.d.comb += read_port.addr.eq(
            self._buffer_index(m, cpu_write, read_port.data, send_start, send_next))
        self._fill_from_sd(m, fill_write)
        self._write_side(m, read_port, send_start, send_next)
        return m

    def _ring_status(self, m):
        """The ring's figures to the registers; releases and clear to the ring."""
        ring, control = self.ring, self._control.f
        m.d.comb += [
            self._level.f.bytes.r_data.eq(ring.level),
            self._high_water.f.bytes.r_data.eq(ring.high_water),
            self._kept.f.frames.r_data.eq(ring.kept),
            self._dropped.f.frames.r_data.eq(ring.dropped),
            ring.release.eq(self._release.f.sectors.w_stb),
            ring.release_sectors.eq(self._release.f.sectors.w_data),
            ring.clear.eq(control.clear.w_stb & control.clear.w_data),
        ]

    def _buffer_index(self, m, cpu_write, read_data, send_start, send_next):
        """CPU access to the sector buffer, a word at a time, the index moving on; the DMA
        sending the buffer moves the same index (from 0 at `send_start`, on at `send_next`;
        the firmware seeks before it accesses the buffer). Returns the next index, the
        read port's address."""
        index = Signal(range(BUFFER_WORDS))
        index_next = Signal.like(index)
        seek, write, read = (self._buffer_seek.f.index, self._buffer_write.f.word,
                             self._buffer_read.f.word)
        with m.If(send_start):
            m.d.comb += index_next.eq(0)
        with m.Elif(seek.w_stb):
            m.d.comb += index_next.eq(seek.w_data)
        with m.Elif(write.w_stb | read.r_stb | send_next):
            m.d.comb += index_next.eq(index + 1)
        with m.Else():
            m.d.comb += index_next.eq(index)
        m.d.sync += index.eq(index_next)
        m.d.comb += [
            read.r_data.eq(read_data),
            cpu_write.addr.eq(index),
            cpu_write.data.eq(write.w_data),
            cpu_write.en.eq(Mux(write.w_stb, (1 << WORD_BYTES) - 1, 0)),
        ]
        # The read port is given the next index (a word just written is not read back at once).
        return index_next

    def _fill_from_sd(self, m, fill_write):
        """SD read data fills the buffer from its start (after `arm_read`), a byte lane at a
        time."""
        fill = Signal(range(arch_sd.BLOCK_BYTES + 1))
        filling = Signal()
        control = self._control.f
        # Every field of `fill_write` is given by an expression, none in an `If`: a signal
        # driven partly by a process comes out of Yosys's Verilog as a `reg` whose other bits
        # are set by bare `always @*` blocks, which Icarus (-g2012, as cocotb builds) first
        # runs when their inputs change, so the first bytes of a block of zeros were written
        # with an undefined address and data.
        m.d.comb += [
            filling.eq(self.sd_o.valid & (fill < arch_sd.BLOCK_BYTES)),
            fill_write.addr.eq(fill[2:]),
            fill_write.data.eq(Cat([self.sd_o.payload] * WORD_BYTES)),
            fill_write.en.eq(Mux(filling, 1 << fill[:2], 0)),
        ]
        with m.If(filling):
            m.d.sync += fill.eq(fill + 1)
        with m.If(control.arm_read.w_stb & control.arm_read.w_data):
            m.d.sync += fill.eq(0)

    def _write_side(self, m, read_port, send_start, send_next):
        """Sectors from the ring, or the buffer, to the SD host."""
        ring, control = self.ring, self._control.f
        sector_bits = control.sectors.w_data.shape().width
        busy    = Signal()
        source  = Signal(DmaSource)
        sectors = Signal(sector_bits, reset_less=True)
        sent    = Signal(sector_bits)
        # The ring's sector of the current one: `first` + `sent`, kept as a count of its own.
        sector  = Signal(sector_bits + 1, reset_less=True)
        count   = Signal(range(arch_sd.BLOCK_BYTES))   # bytes of the sector (wraps at its end)
        count_next = Signal.like(count)
        sent_next = Signal.like(sent)
        sent_next = Signal.like(sent)
        asked   = Signal()                 # the ring was asked for the current sector
        m.d.comb += [
            self._status.f.busy.r_data.eq(busy),
            self._status.f.sent.r_data.eq(sent),
            self.busy.eq(busy),
            ring.read_sector.eq(sector),
            count_next.eq(count + 1),
            sent_next.eq(sent + 1),
        ]
        last_byte = count == arch_sd.BLOCK_BYTES - 1
        starting = Signal()
        m.d.comb += starting.eq(control.start.w_stb & control.start.w_data & ~busy &
                                (control.sectors.w_data != 0))
        with m.If(starting):
            m.d.sync += [
                busy.eq(1), source.eq(control.source.w_data),
                sectors.eq(control.sectors.w_data),
                sent.eq(0), count.eq(0), asked.eq(0), sector.eq(control.first.w_data),
            ]
        discarding = Signal()
        with m.If(control.abort.w_stb & control.abort.w_data & busy):
            with m.If((source == DmaSource.RING) & asked):
                m.d.sync += discarding.eq(1)
            with m.Else():
                m.d.sync += busy.eq(0)
        with m.If(discarding):
            m.d.comb += ring.data.ready.eq(1)
            with m.If(ring.data.valid):
                m.d.sync += count.eq(count_next)
                with m.If(last_byte):
                    m.d.sync += [asked.eq(0), busy.eq(0), discarding.eq(0)]
        with m.Elif(busy & (source == DmaSource.RING)):
            with m.If(~asked):
                # Asks the ring for the next sector once it is free (and not in a release's
                # clock: the ring has one adder for both).
                with m.If(~ring.reading & ~ring.release):
                    m.d.comb += ring.read_start.eq(1)
                    m.d.sync += asked.eq(1)
            with m.Else():
                m.d.comb += [
                    self.sd_i.valid.eq(ring.data.valid),
                    self.sd_i.payload.eq(ring.data.payload),
                    ring.data.ready.eq(self.sd_i.ready),
                ]
        with m.If(busy & ~discarding & (source == DmaSource.BUFFER)):
            m.d.comb += [
                self.sd_i.valid.eq(1),
                self.sd_i.payload.eq(read_port.data.word_select(count[:2], 8)),
            ]
        # The buffer's read port is given the word of the byte after a transfer (the first
        # word as sending starts).
        step = self.sd_i.valid & self.sd_i.ready
        sending = busy & (source == DmaSource.BUFFER)
        m.d.comb += [
            send_start.eq(starting & (control.source.w_data == DmaSource.BUFFER)),
            send_next.eq(sending & step & count[:2].all()),
        ]
        with m.If(step):
            m.d.sync += count.eq(count_next)
            with m.If(last_byte):
                m.d.sync += [asked.eq(0), sent.eq(sent_next), sector.eq(sector + 1)]
                # The buffer is sent once, whatever `sectors` says.
                with m.If((source == DmaSource.BUFFER) | (sent_next == sectors)):
                    m.d.sync += busy.eq(0)
