"""Frame FIFO: bytes are written tentatively and become readable only when committed."""

from amaranth import *
from amaranth.lib import data, stream, wiring
from amaranth.lib.memory import Memory
from amaranth.lib.wiring import In, Out
from amaranth.utils import ceil_log2


__all__ = ["FrameByte", "FrameFifo"]


class FrameByte(data.StructLayout):
    """A byte of a frame; ``last`` marks its final byte."""
    def __init__(self):
        super().__init__({
            "data": 8,
            "last": 1,
        })


class FrameFifo(wiring.Component):
    """A FIFO of whole frames.

    The writer writes the bytes of a frame as they arrive, then either commits them (the
    frame was good) or discards them (the write pointer returns to the last commit), so the
    reader never sees a byte of a frame that was not committed. Committed frames come out
    in order, whole, at up to one byte per cycle.

    Parameters
    ----------
    depth : int
        Bytes of storage, a power of two (1024 fills one Cyclone IV M9K at 9 bits).

    Members
    -------
    w_en : ``In(1)``
        Write ``w_data`` (with ``w_last``) after the uncommitted bytes. Ignored when there
        is no room (``full``, or ``full_committed`` with ``discard``): the writer must then
        discard the frame, or a later commit would make it readable with a byte missing.
    w_data, w_last : ``In(8)``, ``In(1)``
    commit : ``In(1)``
        Make every byte written so far readable, a byte written in the same cycle included.
    discard : ``In(1)``
        Forget the uncommitted bytes. A byte written in the same cycle is kept as the first
        byte of the next frame (so a frame can be dropped and the next one started at once).
        In one cycle the order is: discard, then write, then commit.
    full : ``Out(1)``
        No room after the uncommitted bytes.
    full_committed : ``Out(1)``
        No room even after a discard: the committed bytes fill the FIFO.
    o : ``Out(stream.Signature(FrameByte))``
        Committed bytes.
    wr_ptr, commit_ptr, rd_ptr : Signal
        The write, commit and read pointers (white box, for formal proofs and probes).
    level : ``Out(range(depth + 1))``
        Bytes held, committed or not. The output register holds one more committed byte
        (so up to ``depth + 1`` bytes are held in all).
    """
    def __init__(self, *, depth=1024):
        if not isinstance(depth, int) or depth < 2 or depth & (depth - 1):
            raise ValueError(f"Depth must be a power of two, at least 2, not {depth!r}")
        self._depth = depth
        # Pointers carry one extra bit so that full and empty differ. They are attributes
        # (not locals of `elaborate`) so that formal invariants and debug probes can name them.
        abits = ceil_log2(depth)
        self.wr_ptr     = Signal(abits + 1)
        self.commit_ptr = Signal(abits + 1)
        self.rd_ptr     = Signal(abits + 1)
        super().__init__({
            "w_en":    In(1),
            "w_data":  In(8),
            "w_last":  In(1),
            "commit":  In(1),
            "discard": In(1),
            "full":    Out(1),
            "full_committed": Out(1),
            "o":       Out(stream.Signature(FrameByte())),
            "level":   Out(range(depth + 1)),
        })

    @property
    def depth(self):
        return self._depth

    def elaborate(self, platform):
        m = Module()

        abits = ceil_log2(self._depth)
        m.submodules.mem = mem = Memory(shape=FrameByte(), depth=self._depth, init=[])
        wport = mem.write_port()
        rport = mem.read_port(transparent_for=())

        wr_ptr, commit_ptr, rd_ptr = self.wr_ptr, self.commit_ptr, self.rd_ptr

        w_addr = Signal(abits + 1)
        # The commit and read pointers at the same cell: the FIFO is either full of committed
        # bytes or has none to read (one compare for both).
        same_cell = Signal()
        m.d.comb += same_cell.eq(commit_ptr[:abits] == rd_ptr[:abits])
        m.d.comb += [
            w_addr.eq(Mux(self.discard, commit_ptr, wr_ptr)),
            # Full: the pointers differ by exactly `depth`, that is in their top bit only
            # (equality compares, no subtraction).
            self.full.eq((wr_ptr[:abits] == rd_ptr[:abits]) & (wr_ptr[abits] != rd_ptr[abits])),
            self.full_committed.eq(same_cell & (commit_ptr[abits] != rd_ptr[abits])),
            self.level.eq(wr_ptr - rd_ptr),
        ]

        write = Signal()
        m.d.comb += [
            write.eq(self.w_en & ~Mux(self.discard, self.full_committed, self.full)),
            wport.addr.eq(w_addr[:abits]),
            wport.data.data.eq(self.w_data),
            wport.data.last.eq(self.w_last),
            wport.en.eq(write),
        ]
        next_wr = Signal(abits + 1)
        m.d.comb += next_wr.eq(Mux(write, w_addr + 1, w_addr))
        m.d.sync += wr_ptr.eq(next_wr)
        with m.If(self.commit):
            m.d.sync += commit_ptr.eq(next_wr)

        # Read side: the memory's output register is the stream's payload.
        load = Signal()
        m.d.comb += [
            load.eq((~same_cell | (commit_ptr[abits] != rd_ptr[abits])) &
                    (~self.o.valid | self.o.ready)),
            rport.addr.eq(rd_ptr[:abits]),
            rport.en.eq(load),
            self.o.payload.eq(rport.data),
        ]
        with m.If(load):
            m.d.sync += [
                rd_ptr.eq(rd_ptr + 1),
                self.o.valid.eq(1),
            ]
        with m.Elif(self.o.ready):
            m.d.sync += self.o.valid.eq(0)

        return m
