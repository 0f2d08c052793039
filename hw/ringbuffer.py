"""Frame-safe ring buffer in SDRAM: whole frames in, whole sectors out."""

from amaranth import *
from amaranth.lib import stream, wiring
from amaranth.lib.memory import Memory
from amaranth.lib.wiring import In, Out
from amaranth.utils import exact_log2

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
        Read sector ``read_sector`` after the read pointer (taken while not ``reading`` and
        not ``release``).
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
        Frames stored; frames dropped because the ring was full (each counted the clock
        after its last byte).
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
    pointer: the bytes committed as its read starts, then zeros (the last, partial sector
    of a flush is written padded, and again with more data at the next flush). ``release``
    moves the read pointer on by whole sectors once the card has them.

    Each byte is one SDRAM word write with a byte mask (the serial data rate is far below
    what that costs); sector reads are word reads, one a clock, into a sector buffer (one
    M9K), whose bytes leave as their words arrive.

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
        sector_bits = exact_log2(arch_sd.BLOCK_BYTES)
        sbits = bits - sector_bits             # a pointer counted in sectors
        sector_words = arch_sd.BLOCK_BYTES // lanes
        word_bits = exact_log2(sector_words)
        port = self.dma

        # Pointers modulo twice the capacity (the top bit tells full from empty). The read
        # pointer only ever moves by whole sectors, so it is kept in sectors.
        wr = Signal(bits)          # next byte to write (tentative)
        commit = Signal(bits)      # end of the last whole frame
        rd = Signal(sbits)         # first sector not yet released
        dropping = Signal()        # skipping the rest of a frame that did not fit
        keep_event, drop_event = Signal(), Signal()
        m.d.sync += [keep_event.eq(0), drop_event.eq(0)]

        # Committed bytes not yet released: the low bits of `commit` as they are.
        m.d.comb += port.level.eq(Cat(commit[:sector_bits], commit[sector_bits:] - rd))
        # The high-water mark is taken from the level, with no reset of its own: the clock
        # after a reset it takes the level, zero then.
        high_water = Signal(bits, reset_less=True)
        restart = Signal(init=1)
        m.d.sync += restart.eq(0)
        m.d.comb += port.high_water.eq(high_water)
        with m.If((port.level > high_water) | restart):
            m.d.sync += high_water.eq(port.level)

        # Write side: a byte per word write, with only its lane enabled. Full: the write
        # pointer is the read pointer plus the capacity, i.e. equal to it but for the top bit.
        write_valid = Signal()
        write_taken = Signal()
        full = Signal()
        m.d.comb += full.eq(wr == Cat(C(0, sector_bits), rd ^ (1 << (sbits - 1))))
        with m.If(self.i.valid):
            with m.If(dropping):
                m.d.comb += self.i.ready.eq(1)
                with m.If(self.i.payload.last):
                    m.d.sync += dropping.eq(0)
            with m.Elif(full):
                # No room: the frame so far is forgotten, the rest skipped.
                m.d.comb += self.i.ready.eq(1)
                m.d.sync += [wr.eq(commit), drop_event.eq(1),
                             dropping.eq(~self.i.payload.last)]
            with m.Else():
                m.d.comb += [write_valid.eq(1), self.i.ready.eq(write_taken)]
                with m.If(write_taken):
                    m.d.sync += wr.eq(wr + 1)
                    with m.If(self.i.payload.last):
                        m.d.sync += [commit.eq(wr + 1), keep_event.eq(1)]

        # The frame counters count a clock after the event.
        with m.If(keep_event):
            m.d.sync += port.kept.eq(port.kept + 1)
        with m.If(drop_event):
            m.d.sync += port.dropped.eq(port.dropped + 1)

        # One adder for the read pointer's two sums: a release and the start of a sector read
        # never come in the same clock (the DMA does not start a read while it releases).
        rd_sum = Signal(sbits)
        m.d.comb += rd_sum.eq(rd + Mux(port.release, port.release_sectors, port.read_sector))
        with m.If(port.release):
            m.d.sync += rd.eq(rd_sum)
        # Clear wins over a write and a release in the same cycle (the firmware clears only
        # with no frame coming in and no sector being read).
        with m.If(port.clear):
            m.d.sync += [wr.eq(0), commit.eq(0), rd.eq(0), dropping.eq(0)]

        # Read side: a sector's words, read one a clock, into a sector buffer (one M9K); its
        # bytes leave as their words have arrived. A sector's 512 bytes always all go out, so
        # the buffer is empty again at the start of the next.
        m.submodules.words = words = Memory(shape=g.data_width, depth=sector_words, init=[])
        w_port = words.write_port()
        r_port = words.read_port()
        # Which bytes of the sector read are committed, as its read starts: all of them
        # (`whole`), or its first `end` (`part`, until the count reaches `end`), or none.
        whole = Signal()
        part = Signal()
        end = Signal(sector_bits, reset_less=True)
        base = Signal(sbits, reset_less=True)       # the sector read, in the ring
        issued = Signal(word_bits + 1)              # words asked of the controller
        arrived = Signal(word_bits + 1)             # words in the buffer
        arrived_before = Signal(word_bits + 1)      # ... as the read port saw the buffer
        out_count = Signal(sector_bits)             # bytes out (back to 0 after the last)
        read_valid = Signal()
        read_taken = Signal()
        with m.If(out_count == end):
            m.d.sync += part.eq(0)
        with m.If(port.read_start & ~port.reading & ~port.release):
            m.d.sync += [
                port.reading.eq(1),
                whole.eq(port.read_sector < port.level[sector_bits:]),
                part.eq(port.read_sector == port.level[sector_bits:]),
                end.eq(commit[:sector_bits]),
                base.eq(rd_sum),
                issued.eq(0), arrived.eq(0),
            ]
        m.d.comb += read_valid.eq(port.reading & ~issued[word_bits])
        with m.If(read_taken):
            m.d.sync += issued.eq(issued + 1)
        with m.If(self.mem_data.valid):
            m.d.sync += arrived.eq(arrived + 1)
        m.d.sync += arrived_before.eq(arrived)
        with m.If(port.read_start & ~port.reading & ~port.release):
            m.d.sync += arrived_before.eq(0)
        m.d.comb += [
            w_port.addr.eq(arrived[:word_bits]),
            w_port.data.eq(self.mem_data.payload),
            w_port.en.eq(self.mem_data.valid),
        ]

        # The controller's port: writes first (they are few), then sector reads. Byte
        # addresses within the ring, in words. Every field is given by an expression, none
        # in an `If` (see `Dma._fill_from_sd` on Icarus and partly driven signals).
        m.d.comb += [
            self.mem.valid.eq(write_valid | read_valid),
            write_taken.eq(write_valid & self.mem.ready),
            read_taken.eq(~write_valid & read_valid & self.mem.ready),
            self.mem.payload.write.eq(write_valid),
            self.mem.payload.addr.eq(Mux(write_valid, wr[lane_bits:bits - 1],
                                         Cat(issued[:word_bits], base[:sbits - 1]))),
            self.mem.payload.data.eq(Cat([self.i.payload.data] * lanes)),
            self.mem.payload.mask.eq(Const(1, lanes) << wr[:lane_bits] if lane_bits else 1),
        ]

        # Bytes out, low lane first; bytes past the committed end are padding. The read port
        # is given the word of the next byte (its data come a clock later), which has
        # arrived if the buffer held it a clock ago.
        word = out_count[lane_bits:]
        step = port.data.valid & port.data.ready
        next_word = Signal(word_bits)
        m.d.comb += next_word.eq(word)
        if lane_bits:
            with m.If(step & out_count[:lane_bits].all()):
                m.d.comb += next_word.eq(word + 1)
        else:
            with m.If(step):
                m.d.comb += next_word.eq(word + 1)
        m.d.comb += r_port.addr.eq(next_word)
        at_end = out_count == end
        committed_byte = whole | (part & ~at_end)
        byte = r_port.data.word_select(out_count[:lane_bits], 8) if lanes > 1 else r_port.data
        m.d.comb += [
            port.data.valid.eq(port.reading & (arrived_before != word)),
            port.data.payload.eq(Mux(committed_byte, byte, 0)),
        ]
        with m.If(step):
            m.d.sync += out_count.eq(out_count + 1)
            with m.If(out_count == arch_sd.BLOCK_BYTES - 1):
                m.d.sync += port.reading.eq(0)

        return m
