"""FrameFifo (hw/frame_fifo.py) proven with SymbiYosys: discarded frames never come out,
committed frames come out whole and in order, and the reader never runs ahead of the commits.

The harness is a reference model of the FIFO kept in counters: ``committed`` and ``emitted``
count bytes (modulo ``2**width``, wide enough that the bytes in flight never wrap), ``pending``
counts the bytes written since the last commit or discard. Each written byte gets the index
it will have among the committed bytes if its frame is committed (``committed + pending``,
after a discard in the same cycle); a free constant ``n`` picks one index, and the harness
remembers the byte written last with that index. When the ``n``-th byte comes out, it must be
that byte. As ``n`` is free, this holds for every index: the output is the committed byte
sequence, nothing skipped, duplicated or reordered, data and ``last`` flag alike.

Properties (each a group of ``Assert``\\ s, selected by name):

``discarded``
    A free constant ``poison`` value and a free ``poison_en`` bit: when set, the writer is
    assumed never to commit a frame that holds a byte of that value, so those bytes are all
    discarded; no byte of that value ever comes out.
``order``
    The ``n``-th byte out equals the ``n``-th byte committed.
``ahead``
    ``o.valid`` only while a committed byte is not yet out; never more than ``depth + 1``
    committed bytes not yet out (so the read count cannot wrap past the commit count).
``stream``
    The output obeys the stream rules: valid and payload hold until taken.
``status``
    ``level``, ``full`` and ``full_committed`` agree with the reference model.

The induction step also needs invariants that tie the model to FrameFifo's pointers and to
the memory cell holding the ``n``-th byte; those are local to ``FrameFifo.elaborate()``, so
the proof runs on ``ProbedFrameFifo``, FrameFifo with copies of them. Broken variants are
checked by bounded model checking with the properties alone, and must fail.
"""

import pytest
from amaranth import *
from amaranth.hdl import Assert, Assume, Cover
from amaranth.lib import wiring
from amaranth.utils import ceil_log2

from maglog.hw.frame_fifo import FrameByte, FrameFifo
import formal      # tests/support/formal.py, on sys.path by tests/conftest.py


pytestmark = pytest.mark.formal

PROOF_DEPTHS = (2, 4, 8)  # 2 is the smallest; 16 takes ~40 s
SMALL_DEPTH = 4           # for the cover and the broken variants
INDUCTION_STEPS = 3       # k of k-induction; the invariants make it close from k = 1
COVER_STEPS = 20
BMC_STEPS = 12            # enough for every broken variant below to show its fault
CHECKS = ("discarded", "order", "ahead", "stream", "status")
SBY_TIMEOUT = 120         # seconds; a run takes a few


class FrameFifoSpec(Elaboratable):
    """Formal harness around a FrameFifo (or a variant with the same ports).

    Parameters
    ----------
    fifo : FrameFifo
        The design under proof. Its inputs are left undriven: they become free inputs of the
        top, together with ``n``, ``poison`` and ``poison_en``.
    checks : iterable of str
        Property groups to assert (see the module docstring).
    invariants : bool
        Also assert the invariants over FrameFifo's internals that k-induction needs
        (``fifo`` must then be a ProbedFrameFifo).
    """
    def __init__(self, fifo, *, checks=CHECKS, invariants=True):
        unknown = set(checks) - set(CHECKS)
        if unknown:
            raise ValueError(f"Checks must be among {CHECKS!r}, not {sorted(unknown)!r}")
        if invariants and not isinstance(fifo, ProbedFrameFifo):
            raise TypeError(f"Invariants need a ProbedFrameFifo, not {type(fifo).__name__}")
        self.fifo = fifo
        self.checks = frozenset(checks)
        self.invariants = invariants
        self.lines = {}         # group (or "cover"): source lines of its statements, as sby
                                # reports them
        depth = fifo.depth
        # Committed-but-not-out (up to depth + 1) plus pending (up to depth) never wraps.
        self.width = ceil_log2(2 * depth + 2) + 1
        self.n = Signal(self.width)
        self.poison = Signal(8)
        self.poison_en = Signal()

    def ports(self):
        f = self.fifo
        return [self.n, self.poison, self.poison_en,
                f.w_en, f.w_data, f.w_last, f.commit, f.discard, f.o.ready,
                f.o.valid, f.o.payload.as_value(), f.full, f.full_committed, f.level]

    def elaborate(self, platform):
        m = Module()
        fifo, depth, width = self.fifo, self.fifo.depth, self.width
        m.submodules.fifo = fifo

        def check(group, test):
            if group in self.checks:
                m.d.comb += (prop := Assert(test, src_loc_at=1))
                self.lines.setdefault(group, set()).add(prop.src_loc[1])

        # Reset in the first cycle only; n, poison and poison_en are held constant after it.
        first = Signal(init=1, reset_less=True)
        m.d.sync += first.eq(0)
        m.d.comb += Assume(ResetSignal() == first)
        held = [self.n, self.poison, self.poison_en]
        earlier = Signal(len(Cat(held)), reset_less=True)
        m.d.sync += earlier.eq(Cat(held))
        m.d.comb += Assume(first | (Cat(held) == earlier))

        # Reference model.
        committed = Signal(width)           # bytes committed so far
        emitted   = Signal(width)           # bytes taken from o so far
        pending   = Signal(range(depth + 1))
        tracked   = Signal(FrameByte())     # last byte written with commit index n
        unread    = Signal(width)           # committed, not yet out
        stored    = Signal(width)           # committed, in memory (not in o's register)
        m.d.comb += [
            unread.eq(committed - emitted),
            stored.eq(unread - fifo.o.valid),
        ]

        w_byte = Signal(FrameByte())
        m.d.comb += [w_byte.data.eq(fifo.w_data), w_byte.last.eq(fifo.w_last)]
        kept = Mux(fifo.discard, 0, pending)        # discard first, then write, then commit
        accept = Signal()
        m.d.comb += accept.eq(fifo.w_en & (stored + kept < depth))
        index = (committed + kept)[:width]
        with m.If(accept & (index == self.n)):
            m.d.sync += tracked.eq(w_byte)
        new_pending = kept + accept
        with m.If(fifo.commit):
            m.d.sync += [committed.eq(committed + new_pending), pending.eq(0)]
        with m.Else():
            m.d.sync += pending.eq(new_pending)

        transfer = fifo.o.valid & fifo.o.ready
        with m.If(transfer):
            m.d.sync += emitted.eq(emitted + 1)
        emit_n = transfer & (emitted == self.n)

        # The writer never commits a frame holding a poison byte, so all of them are dropped.
        poisoned = Signal()                 # a pending byte is poison
        poisoned_now = Mux(fifo.discard, 0, poisoned) | (accept & (fifo.w_data == self.poison))
        m.d.comb += Assume(~(self.poison_en & fifo.commit & poisoned_now))
        m.d.sync += poisoned.eq(poisoned_now & ~fifo.commit)

        # Where the n-th byte is: committed and not out, or pending.
        position = Signal(width)            # counted from the next byte out
        m.d.comb += position.eq(self.n - emitted)
        n_unread = position < unread
        n_pending = ((self.n - committed)[:width] < pending)
        # Model facts (true by construction; they keep the induction from starting in
        # states the model cannot reach).
        m.d.comb += [
            Assert(pending <= depth),
            Assert(~(self.poison_en & n_unread) | (tracked.data != self.poison)),
            Assert(~(n_pending & (tracked.data == self.poison)) | poisoned),
        ]

        # (1) No byte of a discarded frame comes out. Only the n-th byte out is checked (a
        # free n covers them all), so that the induction needs to follow that byte only.
        check("discarded", ~(self.poison_en & emit_n) | (fifo.o.payload.data != self.poison))
        # (2) The n-th byte out is the n-th byte committed.
        check("order", ~emit_n | (fifo.o.payload.as_value() == tracked.as_value()))
        # (3) The reader never runs ahead of the commits.
        check("ahead", ~fifo.o.valid | (unread != 0))
        check("ahead", unread <= depth + 1)
        # Stream rules: once offered, a byte stays, unchanged, until taken.
        stalled = Signal()
        offered = Signal(FrameByte())
        m.d.sync += [stalled.eq(fifo.o.valid & ~fifo.o.ready), offered.eq(fifo.o.payload)]
        check("stream", ~stalled | (fifo.o.valid &
                                    (fifo.o.payload.as_value() == offered.as_value())))
        # Status outputs.
        check("status", stored + pending <= depth)
        check("status", fifo.level == stored + pending)
        check("status", fifo.full == (stored + pending == depth))
        check("status", fifo.full_committed == (stored == depth))

        if self.invariants:
            # Pointers count bytes modulo 2 * depth; the n-th byte sits in o's register or in
            # the memory cell `position` bytes after the next one to be read.
            wr_ptr, commit_ptr, rd_ptr = fifo.wr_ptr, fifo.commit_ptr, fifo.rd_ptr
            modulo = 2 * depth - 1
            in_register = fifo.o.valid & (position == 0)
            m.d.comb += [
                fifo.peek_addr.eq(rd_ptr + position - fifo.o.valid),
                Assert(((commit_ptr - rd_ptr) & modulo) == stored),
                Assert(((wr_ptr - commit_ptr) & modulo) == pending),
                Assert(~in_register | (fifo.o.payload.as_value() == tracked.as_value())),
                Assert(~(n_unread | n_pending) | in_register |
                       (fifo.peek_data.as_value() == tracked.as_value())),
            ]

        # Not vacuous: a frame of two bytes or more holding a poison byte is dropped, then a
        # frame of two bytes or more (`last` on its final byte only) is committed and comes out
        # to its final byte; and the FIFO can fill with committed bytes.
        ended = Signal()                    # a pending byte has `last` set
        ended_before = Mux(fifo.discard, 0, ended)
        m.d.sync += ended.eq((ended_before | (accept & fifo.w_last)) & ~fifo.commit)
        whole_frame = (fifo.commit & accept & fifo.w_last & ~ended_before &
                       (new_pending >= 2))
        dropped = Signal()
        kept_frame = Signal()
        kept_end = Signal(width)            # commit count after that frame
        with m.If(fifo.discard & poisoned & (pending >= 2)):
            m.d.sync += dropped.eq(1)
        with m.If(dropped & ~kept_frame & whole_frame):
            m.d.sync += [kept_frame.eq(1), kept_end.eq(committed + new_pending)]
        for test in [self.poison_en & kept_frame & transfer & fifo.o.payload.last &
                     ((emitted + 1)[:width] == kept_end),
                     fifo.full_committed]:
            m.d.comb += (prop := Cover(test))
            self.lines.setdefault("cover", set()).add(prop.src_loc[1])
        return m


class ProbedFrameFifo(FrameFifo):
    """FrameFifo, unchanged, with one more (combinational, read-only) port on its memory.

    The invariants that let k-induction close are about FrameFifo's pointers (its white-box
    attributes) and the memory cell that holds the tracked byte.
    """
    def __init__(self, *, depth):
        super().__init__(depth=depth)
        self.peek_addr = Signal(range(depth))
        self.peek_data = Signal(FrameByte())

    def elaborate(self, platform):
        m = super().elaborate(platform)
        peek = m.submodules.mem.read_port(domain="comb")
        m.d.comb += [peek.addr.eq(self.peek_addr), self.peek_data.eq(peek.data)]
        return m


class BrokenFifo(FrameFifo):
    """FrameFifo with one fault in front of it, to show that the properties can fail."""
    FAULTS = ("ignores_discard", "forwards_uncommitted")

    def __init__(self, *, depth, fault):
        if fault not in self.FAULTS:
            raise ValueError(f"Fault must be one of {self.FAULTS!r}, not {fault!r}")
        self.fault = fault
        super().__init__(depth=depth)

    def elaborate(self, platform):
        m = Module()
        m.submodules.inner = inner = FrameFifo(depth=self.depth)
        commit, discard = self.commit, self.discard
        if self.fault == "ignores_discard":
            discard = C(0)          # dropped frames stay and go out with the next commit
        if self.fault == "forwards_uncommitted":
            commit = C(1)           # every byte is readable as soon as it is written
        m.d.comb += [
            inner.w_en.eq(self.w_en),
            inner.w_data.eq(self.w_data),
            inner.w_last.eq(self.w_last),
            inner.commit.eq(commit),
            inner.discard.eq(discard),
            self.full.eq(inner.full),
            self.full_committed.eq(inner.full_committed),
            self.level.eq(inner.level),
        ]
        wiring.connect(m, inner.o, wiring.flipped(self.o))
        return m


# --- running SymbiYosys ---------------------------------------------------------------------

def run_sby(sby_env, directory, spec, *, mode, steps):
    """Prove (or cover, or bounded-check) ``spec``; return (returncode, log)."""
    return formal.run_sby(sby_env, directory, spec, ports=spec.ports(), mode=mode,
                          depth=steps, timeout=SBY_TIMEOUT)


def reported_lines(pattern, log):
    """Source lines (in this file) of the statements sby reports with ``pattern``."""
    return formal.reported_lines(pattern, log, __file__)


@pytest.mark.parametrize("depth", PROOF_DEPTHS)
def test_properties_proven(sby_env, tmp_path, depth):
    spec = FrameFifoSpec(ProbedFrameFifo(depth=depth))
    rc, log = run_sby(sby_env, tmp_path / "prove", spec, mode="prove", steps=INDUCTION_STEPS)
    assert rc == 0 and "DONE (PASS" in log, log
    assert "successful proof by k-induction" in log, log


def test_frame_kept_after_a_discarded_one_is_reachable(sby_env, tmp_path):
    spec = FrameFifoSpec(ProbedFrameFifo(depth=SMALL_DEPTH))
    rc, log = run_sby(sby_env, tmp_path / "cover", spec, mode="cover", steps=COVER_STEPS)
    assert rc == 0 and "DONE (PASS" in log, log
    assert reported_lines("Reached cover statement in step \\d+ at top:", log) == \
        spec.lines["cover"], log


@pytest.mark.parametrize("fault, group", [
    ("ignores_discard", "discarded"),
    ("ignores_discard", "order"),
    ("forwards_uncommitted", "discarded"),
    ("forwards_uncommitted", "ahead"),
])
def test_broken_fifo_fails(sby_env, tmp_path, fault, group):
    spec = FrameFifoSpec(BrokenFifo(depth=SMALL_DEPTH, fault=fault), checks=[group],
                         invariants=False)
    rc, log = run_sby(sby_env, tmp_path / "bmc", spec, mode="bmc", steps=BMC_STEPS)
    assert rc != 0 and "DONE (FAIL" in log, log
    failed = reported_lines("Assert failed in top:", log)
    assert failed and failed <= spec.lines[group], log
