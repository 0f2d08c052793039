"""Frame-safe ring buffer in SDRAM: whole frames in, whole sectors out."""

from amaranth import *
from amaranth.lib import stream, wiring
from amaranth.lib.fifo import SyncFIFOBuffered
from amaranth.lib.wiring import In, Out
from amaranth.utils import ceil_log2, exact_log2

from .arch import sd as arch_sd
from .frame_fifo import FrameByte
from .sdram import request_layout


__all__ = ["RingBuffer"]


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
    mem : ``Out(stream.Signature(request_layout(geometry)))``; mem_data : ``In(stream ...)``
        The controller's port (``mem_data`` has no backpressure).
    read_start : ``In(1)``; read_sector : ``In(16)``
        Read sector ``read_sector`` after the read pointer.
    o : ``Out(stream.Signature(8))``
        The sector's 512 bytes.
    reading : ``Out(1)``
    release : ``In(1)``; release_sectors : ``In(16)``
    level, high_water : ``Out(range(capacity + 1))``
        Committed bytes not yet released; the most there ever were.
    kept, dropped : ``Out(32)``
        Frames stored; frames dropped because the ring was full.
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
            "mem_data":        In(stream.Signature(geometry.data_width)),
            "read_start":      In(1),
            "read_sector":     In(16),
            "o":               Out(stream.Signature(8)),
            "reading":         Out(1),
            "release":         In(1),
            "release_sectors": In(16),
            "level":           Out(bits),
            "high_water":      Out(bits),
            "kept":            Out(32),
            "dropped":         Out(32),
        })

    def elaborate(self, platform):
        m = Module()
        g = self.geometry
        lanes = g.data_width // 8
        lane_bits = exact_log2(lanes)
        bits = exact_log2(self.capacity) + 1
        mask = self.capacity - 1
        sector_words = arch_sd.BLOCK_BYTES // lanes

        wr = Signal(bits)          # next byte to write (tentative)
        commit = Signal(bits)      # end of the last whole frame
        rd = Signal(bits)          # first byte not yet released
        dropping = Signal()        # skipping the rest of a frame that did not fit

        m.d.comb += self.level.eq(commit - rd)
        with m.If(self.level > self.high_water):
            m.d.sync += self.high_water.eq(self.level)

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
                m.d.sync += [wr.eq(commit), self.dropped.eq(self.dropped + 1),
                             dropping.eq(~self.i.payload.last)]
            with m.Else():
                m.d.comb += [write_valid.eq(1), self.i.ready.eq(write_taken)]
                with m.If(write_taken):
                    m.d.sync += wr.eq(wr + 1)
                    with m.If(self.i.payload.last):
                        m.d.sync += [commit.eq(wr + 1), self.kept.eq(self.kept + 1)]

        with m.If(self.release):
            m.d.sync += rd.eq(rd + (self.release_sectors << exact_log2(arch_sd.BLOCK_BYTES)))

        # Read side: word reads into a sector FIFO, as many as it has room for.
        m.submodules.words = words = SyncFIFOBuffered(width=g.data_width, depth=sector_words)
        base = Signal(bits)
        issued = Signal(range(sector_words + 1))
        in_flight = Signal(range(sector_words + 1))
        out_count = Signal(range(arch_sd.BLOCK_BYTES + 1))
        read_valid = Signal()
        read_taken = Signal()
        with m.If(self.read_start & ~self.reading):
            m.d.sync += [
                self.reading.eq(1),
                base.eq(rd + (self.read_sector << exact_log2(arch_sd.BLOCK_BYTES))),
                issued.eq(0), out_count.eq(0),
            ]
        room = Signal()
        m.d.comb += [
            room.eq(words.level + in_flight < sector_words),
            read_valid.eq(self.reading & (issued < sector_words) & room),
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
            self.o.valid.eq(self.reading & words.r_rdy),
            self.o.payload.eq(Mux(committed_byte, byte, 0)),
        ]
        with m.If(self.o.valid & self.o.ready):
            m.d.sync += out_count.eq(out_count + 1)
            if lanes > 1:
                m.d.sync += lane.eq(lane + 1)
            with m.If((lane == lanes - 1) if lanes > 1 else C(1)):
                m.d.comb += words.r_en.eq(1)
                if lanes > 1:
                    m.d.sync += lane.eq(0)
            with m.If(out_count == arch_sd.BLOCK_BYTES - 1):
                m.d.sync += self.reading.eq(0)

        return m
