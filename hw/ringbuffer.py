"""Frame-safe ring buffer in SDRAM: whole frames in, whole sectors out."""

from amaranth import *
from amaranth.lib import stream, wiring
from amaranth.lib.fifo import SyncFIFOBuffered
from amaranth.lib.wiring import In, Out
from amaranth.utils import ceil_log2, exact_log2

from .arch import sd as arch_sd
from .frame_fifo import FrameByte
from .sdram import request_layout


__all__ = ["RingPort", "RingBuffer"]


class RingPort(wiring.Signature):
    """The link between the DMA (the initiator: ``Out`` members are the DMA's outputs) and
    the ring buffer.

    Members
    -------
    read_start : ``Out(1)``; read_sector : ``Out(16)``
        Read sector ``read_sector`` after the read pointer (taken while not ``reading``).
    data : ``In(stream.Signature(8))``
        The sector's 512 bytes.
    reading : ``In(1)``
        A sector read is under way.
    release : ``Out(1)``; release_sectors : ``Out(16)``
        Move the read pointer on by whole sectors the card has.
    clear : ``Out(1)``
        Empty the ring: write, committed and read pointers back to the start (the counters
        keep counting). Only while nothing is read and no frame is coming in.
    level, high_water : ``In(level_bits)``
        Committed bytes not yet released; the most there ever were.
    kept, dropped : ``In(32)``
        Frames stored; frames dropped because the ring was full.
    """
    def __init__(self, level_bits):
        if not isinstance(level_bits, int) or level_bits < 1:
            raise ValueError(f"Level width must be a positive integer, not {level_bits!r}")
        self.level_bits = level_bits
        super().__init__({
            "read_start":      Out(1),
            "read_sector":     Out(16),
            "data":            In(stream.Signature(8)),
            "reading":         In(1),
            "release":         Out(1),
            "release_sectors": Out(16),
            "clear":           Out(1),
            "level":           In(level_bits),
            "high_water":      In(level_bits),
            "kept":            In(32),
            "dropped":         In(32),
        })

    def __eq__(self, other):
        return isinstance(other, RingPort) and other.level_bits == self.level_bits

    def __hash__(self):
        return hash((RingPort, self.level_bits))

    def __repr__(self):
        return f"RingPort({self.level_bits})"


class RingBuffer(wiring.Component):
    """A byte ring over an :class:`~maglog.hw.sdram.SdramController`'s port.

    Frames from the arbiter are written at the write pointer and become readable when their
    last byte is in (the committed pointer). A frame that does not fit is dropped whole and
    counted: the ring never writes over bytes that have not been released, i.e. that have
    not reached the card. The read side serves 512-byte sectors counted from the read
    pointer: committed bytes, then zeros (the last, partial sector of a flush is written
    padded, and again with more data at the next flush). ``release`` moves the read pointer
    on by whole sectors once the card has them.

    Each byte is one SDRAM word write with a byte mask (the serial data rate is far below
    what that costs); sector reads are word reads, one a clock, into a sector FIFO.

    Parameters
    ----------
    geometry : arch.sdram.Geometry
    capacity : int
        Bytes of ring, a power of two, a multiple of the sector size, at most the chip's.

    Members
    -------
    i : ``In(stream.Signature(FrameByte))``
    mem : ``Out(stream.Signature(request_layout(geometry)))``
    mem_data : ``In(stream.Signature(data_width, always_ready=True))``
        The controller's port (read data has no backpressure).
    dma : ``In(RingPort(log2(capacity) + 1))``
        Sector reads, releases, clear and the ring's status, for the DMA.
    """
    def __init__(self, geometry, *, capacity=None):
        chip_bytes = geometry.words * geometry.data_width // 8
        if capacity is None:
            capacity = chip_bytes
        if (not isinstance(capacity, int) or capacity & (capacity - 1) or
                capacity % arch_sd.BLOCK_BYTES or not arch_sd.BLOCK_BYTES <= capacity <= chip_bytes):
            raise ValueError(f"Capacity must be a power of two of whole sectors, at most "
                             f"{chip_bytes} bytes, not {capacity!r}")
        self.geometry = geometry
        self.capacity = capacity
        bits = exact_log2(capacity) + 1
        super().__init__({
            "i":               In(stream.Signature(FrameByte())),
            "mem":             Out(stream.Signature(request_layout(geometry))),
            "mem_data":        In(stream.Signature(geometry.data_width, always_ready=True)),
            "dma":             In(RingPort(bits)),
        })

    def elaborate(self, platform):
        m = Module()
        g = self.geometry
        lanes = g.data_width // 8
        lane_bits = exact_log2(lanes)
        bits = exact_log2(self.capacity) + 1
        mask = self.capacity - 1
        sector_words = arch_sd.BLOCK_BYTES // lanes
        port = self.dma

        wr = Signal(bits)          # next byte to write (tentative)
        commit = Signal(bits)      # end of the last whole frame
        rd = Signal(bits)          # first byte not yet released
        dropping = Signal()        # skipping the rest of a frame that did not fit

        m.d.comb += port.level.eq(commit - rd)
        with m.If(port.level > port.high_water):
            m.d.sync += port.high_water.eq(port.level)

        # Write side: a byte per word write, with only its lane enabled.
        write_req = Signal(request_layout(g))
        write_valid = Signal()
        write_taken = Signal()
        full = Signal()
        m.d.comb += [
            full.eq((wr - rd)[:bits] == self.capacity),
            write_req.write.eq(1),
            write_req.addr.eq((wr & mask) >> lane_bits),
            write_req.data.eq(Cat([self.i.payload.data] * lanes)),
            write_req.mask.eq(Const(1, lanes) << wr[:lane_bits] if lane_bits else 1),
        ]
        with m.If(self.i.valid):
            with m.If(dropping):
                m.d.comb += self.i.ready.eq(1)
                with m.If(self.i.payload.last):
                    m.d.sync += dropping.eq(0)
            with m.Elif(full):
                # No room: the frame so far is forgotten, the rest skipped.
                m.d.comb += self.i.ready.eq(1)
                m.d.sync += [wr.eq(commit), port.dropped.eq(port.dropped + 1),
                             dropping.eq(~self.i.payload.last)]
            with m.Else():
                m.d.comb += [write_valid.eq(1), self.i.ready.eq(write_taken)]
                with m.If(write_taken):
                    m.d.sync += wr.eq(wr + 1)
                    with m.If(self.i.payload.last):
                        m.d.sync += [commit.eq(wr + 1), port.kept.eq(port.kept + 1)]

        with m.If(port.release):
            m.d.sync += rd.eq(rd + (port.release_sectors << exact_log2(arch_sd.BLOCK_BYTES)))
        # Clear wins over a write and a release in the same cycle (the firmware clears only
        # with no frame coming in and no sector being read).
        with m.If(port.clear):
            m.d.sync += [wr.eq(0), commit.eq(0), rd.eq(0), dropping.eq(0)]

        # Read side: word reads into a sector FIFO, as many as it has room for.
        m.submodules.words = words = SyncFIFOBuffered(width=g.data_width, depth=sector_words)
        base = Signal(bits)
        issued = Signal(range(sector_words + 1))
        in_flight = Signal(range(sector_words + 1))
        out_count = Signal(range(arch_sd.BLOCK_BYTES + 1))
        read_valid = Signal()
        read_taken = Signal()
        with m.If(port.read_start & ~port.reading):
            m.d.sync += [
                port.reading.eq(1),
                base.eq(rd + (port.read_sector << exact_log2(arch_sd.BLOCK_BYTES))),
                issued.eq(0), out_count.eq(0),
            ]
        room = Signal()
        m.d.comb += [
            room.eq(words.level + in_flight < sector_words),
            read_valid.eq(port.reading & (issued < sector_words) & room),
        ]
        with m.If(read_taken):
            m.d.sync += issued.eq(issued + 1)
        arrived = self.mem_data.valid
        m.d.comb += [words.w_en.eq(arrived), words.w_data.eq(self.mem_data.payload)]
        m.d.sync += in_flight.eq(in_flight + read_taken - arrived)

        # The controller's port: writes first (they are few), then sector reads.
        read_req = Signal(request_layout(g))
        m.d.comb += [
            read_req.write.eq(0),
            read_req.addr.eq(((base & mask) >> lane_bits) + issued),
        ]
        with m.If(write_valid):
            m.d.comb += [self.mem.valid.eq(1), self.mem.payload.eq(write_req),
                         write_taken.eq(self.mem.ready)]
        with m.Elif(read_valid):
            m.d.comb += [self.mem.valid.eq(1), self.mem.payload.eq(read_req),
                         read_taken.eq(self.mem.ready)]

        # Bytes out, low lane first; bytes past the committed end are padding.
        lane = Signal(range(max(lanes, 2)))
        position = Signal(bits)
        m.d.comb += position.eq(base + out_count)
        committed_byte = (position - rd)[:bits] < (commit - rd)[:bits]
        byte = words.r_data.word_select(lane, 8) if lanes > 1 else words.r_data
        m.d.comb += [
            port.data.valid.eq(port.reading & words.r_rdy),
            port.data.payload.eq(Mux(committed_byte, byte, 0)),
        ]
        with m.If(port.data.valid & port.data.ready):
            m.d.sync += out_count.eq(out_count + 1)
            if lanes > 1:
                m.d.sync += lane.eq(lane + 1)
            with m.If((lane == lanes - 1) if lanes > 1 else C(1)):
                m.d.comb += words.r_en.eq(1)
                if lanes > 1:
                    m.d.sync += lane.eq(0)
            with m.If(out_count == arch_sd.BLOCK_BYTES - 1):
                m.d.sync += port.reading.eq(0)

        return m
