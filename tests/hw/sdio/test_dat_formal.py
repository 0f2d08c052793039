"""DatWriter (hw/sdio/dat.py) proven with SymbiYosys: every block it puts on the DAT lines is
framed exactly, carries the bytes taken from ``i`` and a correct CRC16 per line, the lines
stay released while the card answers, and ``busy``/``done`` bracket a run.

The writer's inputs are free, with what its neighbours guarantee assumed: ``rise`` and
``fall`` alternate, never in the same cycle, and a rise only comes while ``run`` is high (as
SdClock makes them, at any divisor, 0 included); ``i`` obeys the stream rules (a byte offered
stays, unchanged, until taken); ``blocks`` is at least 1. ``dat_i``, ``start``,
``wait_busy``, ``tick`` and both timeouts are free in every cycle.

A monitor in the harness follows the lines as the card sees them: one step per falling
edge, in the cycle after the strobe, when the writer's registered outputs show the new level.
Its phases are OFF (released), ONES (``count`` ones driven), START, DATA (``count`` nibbles),
CRC (``count`` bits per line) and END. The byte model keeps the last byte taken from ``i``
and ``owed``, how many of its nibbles are still to go out (2, 1 or 0); a byte taken ahead
is dropped when the run ends (``done``), as DatWriter documents; only a failed run can
hold one then (after the last block's data ``i.ready`` stays low, which
``tests/hw/sdio/test_dat.py`` checks in simulation). The reference CRC16 is computed by the
harness itself from the nibbles seen on the lines.

Properties (each a group of ``Assert``\\ s, selected by name):

``framing``
    Counted on falling edges while ``dat_oe`` is high: ``N_WR`` ones, the start bit (0 on
    all lines), exactly ``DATA_NIBBLES`` data nibbles, exactly ``CRC16_BITS`` CRC bits, the
    end bit (all ones), then the lines are released; the lines only change right after a
    falling edge.
``data``
    The data nibbles are the high, then the low nibble of each byte taken from ``i``, in
    order: none before its byte is taken, none skipped, none sent twice.
``crc``
    The CRC bits of each line are that line's CRC16 (x^16 + x^12 + x^5 + 1, from 0, most
    significant bit first) over its data bits.
``released``
    While the writer waits for the CRC status token and for the end of busy, ``dat_oe`` is
    low.
``busy``
    ``dat_oe`` is never high while the writer is idle; ``busy`` rises exactly one cycle
    after a ``start`` or ``wait_busy`` while idle and falls exactly when ``done`` pulses.

A block is ``DATA_NIBBLES`` (1024) falling edges long, far too deep for bounded checks from
reset; ``mode prove`` (k-induction) closes because of invariants that tie the monitor, the
byte model and the reference CRC to DatWriter's registers (its ``state``, ``count``,
``byte``, ``loaded``, ``low`` and CRC registers, reached through ``ProbedDatWriter``).

Broken variants must fail, each at the check its fault should trip. One is caught from
reset by a bounded check. The others go wrong at the end of a block, ~2000 cycles in; they
are checked from "anywhere": no reset, every register free in the first step except as the
invariants (assumed there) constrain the writer's registers and the harness's, so the check
may start late in a block. The real writer is proven from the same start: whatever fails
from there is the variant's fault. (The invariants describe the writer's registers, not a
variant's outputs, and a variant's own register starts clear: otherwise the check could
start in a state that only the fault's output makes look consistent.) These bounded checks
also assume the fastest clock and a byte source that is never late (``fast``): a
counterexample in that narrower environment is one all the same, and found much sooner.

The cover (a block, token accepted, a busy period, ``done`` with ``accepted == 1``) is
~2100 cycles deep from reset: a cover at that depth (only its last step checked) ran
boolector out after ~6 minutes. It is split: the start of a block from reset, and the end
of a block (last nibbles, CRC, end bit, token, busy, ``done``) from anywhere in the data of
a one-block run. That the whole run is reachable is shown by the simulation tests
(test_dat.py), not here.
"""

import functools
import unittest.mock
from types import SimpleNamespace

import pytest
from amaranth import *
from amaranth.hdl import Assert, Assume, Cover, Fragment
from amaranth.lib import enum, wiring
from amaranth.lib.wiring import In

from maglog.hw.arch import sd as arch
from maglog.hw.sdio.crc import Crc16Lanes
from maglog.hw.sdio.dat import DatWriter, _WState
import formal      # tests/support/formal.py, on sys.path by tests/conftest.py


pytestmark = pytest.mark.formal

CHECKS = ("framing", "data", "crc", "released", "busy")
INDUCTION_STEPS = 2         # k of k-induction; the invariants make it close from k = 1
ANYWHERE_STEPS = 40         # from anywhere: a short block shows at its release, step 37
RESET_STEPS = 16            # from reset: preamble and start bit
COVER_START_STEPS = 16      # reset to the second data nibble: 12 cycles
COVER_END_STEPS = 56        # last nibble to done: 19 falls, token and busy: ~50 cycles
SBY_TIMEOUT = 120           # seconds, for one run

ALL_LINES = 0b1111
LANES = 4
#: The CRC16 generator, written here from the spec rather than taken from the design:
#: x^16 + x^12 + x^5 + 1 (PLSS §4.5), register from 0, message most significant bit first.
CRC16_TERMS = (12, 5, 0)
CRC16_GENERATOR = sum(1 << term for term in CRC16_TERMS)


class _Phase(enum.Enum, shape=3):
    OFF   = 0
    ONES  = 1
    START = 2
    DATA  = 3
    CRC   = 4
    END   = 5


def _crc16_step(crc, bit):
    """The reference CRC16 register after one more message bit."""
    feedback = crc[-1] ^ bit
    return Cat(C(0, 1), crc[:-1]) ^ Mux(feedback, CRC16_GENERATOR, 0)


class _Elaborated(Elaboratable):
    """A fragment elaborated ahead of its parent, so that its probes exist when the parent
    is built."""
    def __init__(self, fragment):
        self.fragment = fragment

    def elaborate(self, platform):
        return self.fragment


def _assigned_signals(statements):
    # Assignments carry `lhs`, switches (m.If, m.Switch, FSMs) their `cases`.
    for statement in statements:
        lhs = getattr(statement, "lhs", None)
        if isinstance(lhs, Signal):
            yield lhs
        for _patterns, body, _src_loc in getattr(statement, "cases", ()):
            yield from _assigned_signals(body)


class ProbedDatWriter(DatWriter):
    """DatWriter, unchanged, with its CRC16 lanes (as the host gives it: it alone drives them
    through a write) and handles on the registers the invariants are about.

    DatWriter keeps its state in local variables of ``elaborate()``: no attribute reaches
    them. They are found by name among the signals its elaborated fragment assigns
    (``Fragment.statements``, walked through assignments' ``lhs`` and switches' ``cases``);
    a renamed or missing one is an error here, not a silently weaker proof. The CRC
    registers are the ``crc`` ports of the ``Crc16Lanes`` added here on its ``crc`` port,
    and the values of ``state`` are its (private) enum ``_WState``. After elaboration,
    ``probes`` holds ``state``, ``count``, ``byte``, ``loaded``, ``low``, ``crc`` (one
    signal per line), the
    writer's own ``dat_o`` and ``dat_oe`` registers, ``nibbles`` (the block length it was
    built for) and ``initial``: conditions on a variant's own registers for a check from
    anywhere (none here).
    """
    PROBED = ("state", "count", "byte", "loaded", "low")
    #: Data nibbles per block this writer is built for (a broken variant sends fewer).
    DATA_NIBBLES = arch.DATA_NIBBLES

    probes = None

    def elaborate(self, platform):
        m = super().elaborate(platform)
        m.submodules.crc16 = crc = Crc16Lanes(LANES)
        wiring.connect(m, self.crc, crc)
        fragment = Fragment.get(m, platform)
        found = {name: {} for name in self.PROBED}
        for domain in ("sync", "comb"):
            for signal in _assigned_signals(fragment.statements.get(domain, ())):
                if signal.name in found:
                    found[signal.name][id(signal)] = signal
        for name, signals in found.items():
            if len(signals) != 1:
                raise LookupError(f"DatWriter should assign one signal named {name!r}, "
                                  f"not {len(signals)}")
        self.probes = SimpleNamespace(
            **{name: next(iter(signals.values())) for name, signals in found.items()},
            crc=[crc.crc[lane] for lane in range(LANES)], dat_o=self.dat_o,
            dat_oe=self.dat_oe, nibbles=self.DATA_NIBBLES, initial=[])
        return fragment


class ShortBlockWriter(ProbedDatWriter):
    """DatWriter built for one data nibble fewer per block (its constant patched while it
    elaborates)."""
    DATA_NIBBLES = arch.DATA_NIBBLES - 1

    def elaborate(self, platform):
        with unittest.mock.patch.object(arch, "DATA_NIBBLES", self.DATA_NIBBLES):
            return super().elaborate(platform)


class MisdrivenWriter(wiring.Component):
    """A DatWriter whose DAT outputs are altered by one fault, to show that the properties
    can fail. The writer itself runs unchanged; its probes are this component's, with the
    fault's own register (if any) clear in ``initial``: checked from anywhere, the fault has
    not shown yet."""
    FAULTS = ("short_preamble", "early_release", "late_release", "bad_crc")

    def __init__(self, fault):
        if fault not in self.FAULTS:
            raise ValueError(f"Fault must be one of {self.FAULTS!r}, not {fault!r}")
        self.fault = fault
        self.writer = ProbedDatWriter()
        super().__init__(self.writer.signature)

    probes = None

    def elaborate(self, platform):
        m = Module()
        writer = self.writer
        m.submodules.writer = _Elaborated(Fragment.get(writer, platform))
        w = writer.probes
        state = _WState
        initial = []
        self.probes = SimpleNamespace(**{**vars(w), "initial": initial})
        for path, member, port in self.signature.flatten(self):
            if path in (("dat_o",), ("dat_oe",)) or path[0] == "crc":
                continue            # (the CRC port is tied to the writer's own lanes)
            inner = functools.reduce(getattr, path, writer)
            if member.flow == In:
                m.d.comb += inner.eq(port)
            else:
                m.d.comb += port.eq(inner)

        dat_o, dat_oe = writer.dat_o, writer.dat_oe
        if self.fault == "short_preamble":
            # The first of the N_WR ones is not driven.
            dat_oe = dat_oe & ~((w.state == state.PREAMBLE) & (w.count == 1))
        if self.fault == "early_release":
            # The lines are released together with the end bit, one falling edge early.
            dat_oe = dat_oe & (w.state != state.RELEASE)
        if self.fault == "late_release":
            # The lines are released one falling edge late.
            late = Signal()
            with m.If(writer.fall):
                m.d.sync += late.eq(w.state == state.RELEASE)
            dat_oe = dat_oe | late
            initial.append(~late)
        if self.fault == "bad_crc":
            # One CRC bit on DAT0 is inverted.
            dat_o = dat_o ^ ((w.state == state.CRC) & (w.count == 8))
        m.d.comb += [self.dat_o.eq(dat_o), self.dat_oe.eq(dat_oe)]
        return m


class DatWriterSpec(Elaboratable):
    """Formal harness around a DatWriter (or a variant with the same ports and probes).

    Parameters
    ----------
    dut : ProbedDatWriter or MisdrivenWriter
        The design under proof. Its inputs are left undriven: they become free inputs.
    checks : iterable of str
        Property groups to assert (see the module docstring).
    start : "reset" or "anywhere"
        From reset (in the first cycle only), or from anywhere: no reset, and every
        register free in the first step except as the invariants constrain it (assumed
        there; the sby script must clear the initial values, see :meth:`script`).
    invariants : bool
        Assert the invariants that k-induction needs.
    covers : iterable of str
        ``"block_start"`` (the second data nibble of a block), ``"block_end"`` (from
        anywhere in the data of the only block of a run: ``done``, all well, with
        ``accepted == 1`` after a busy period).
    fast : bool
        Also assume SdClock at divisor 0 (the clock toggles in every cycle unless ``run``
        holds it) and a byte source that always has a byte: fewer traces to search.
    """
    COVERS = ("block_start", "block_end")

    def __init__(self, dut, *, checks=CHECKS, start="reset", invariants=True, covers=(),
                 fast=False):
        unknown = set(checks) - set(CHECKS)
        if unknown:
            raise ValueError(f"Checks must be among {CHECKS!r}, not {sorted(unknown)!r}")
        if start not in ("reset", "anywhere"):
            raise ValueError(f"Start must be 'reset' or 'anywhere', not {start!r}")
        unknown = set(covers) - set(self.COVERS)
        if unknown:
            raise ValueError(f"Covers must be among {self.COVERS!r}, not {sorted(unknown)!r}")
        if "block_end" in covers and start != "anywhere":
            raise ValueError("The block_end cover needs start='anywhere'")
        self.dut = dut
        self.checks = frozenset(checks)
        self.start = start
        self.invariants = invariants
        self.covers = frozenset(covers)
        self.fast = fast
        self.lines = {}         # group, label or "cover": source lines of its statements

    def ports(self):
        d = self.dut
        return [d.rise, d.fall, d.run, d.dat_o, d.dat_oe, d.dat_i, d.i.valid, d.i.ready,
                d.i.payload, d.start, d.blocks, d.tick, d.token_timeout, d.busy_timeout,
                d.wait_busy, d.busy, d.done, d.status.as_value(), d.accepted, d.r1b_timeout]

    def script(self):
        """Yosys commands for sby's script: from anywhere, only ``first_cycle`` keeps its
        initial value."""
        if self.start == "anywhere":
            return ["setattr -unset init w:* top/w:first_cycle %d"]
        return []

    def elaborate(self, platform):
        m = Module()
        dut = self.dut
        m.submodules.dut = _Elaborated(Fragment.get(dut, platform))
        w = dut.probes
        state = _WState

        first = Signal(init=1, reset_less=True, name="first_cycle")
        m.d.sync += first.eq(0)
        if self.start == "anywhere":
            m.d.comb += Assume(~ResetSignal())
            m.d.comb += [Assume(~first | test) for test in w.initial]
        else:
            m.d.comb += Assume(ResetSignal() == first)

        def check(group, test, label=None):
            if group in self.checks:
                m.d.comb += (prop := Assert(first | test, src_loc_at=1))
                for key in (group, label):
                    self.lines.setdefault(key, set()).add(prop.src_loc[1])

        def invariant(test):
            if self.invariants:
                m.d.comb += Assert(test, src_loc_at=1)
            if self.start == "anywhere":
                m.d.comb += Assume(~first | test)

        def cover(name, test):
            if name in self.covers:
                m.d.comb += (prop := Cover(test, src_loc_at=1))
                self.lines.setdefault("cover", set()).add(prop.src_loc[1])

        # --- What the writer's neighbours guarantee ---------------------------------------
        # The SD clock: it rises (only while `run` is high) and falls in turn, never both in
        # one cycle.
        clk = Signal()
        m.d.comb += [
            Assume(~(dut.rise & dut.fall)),
            Assume(~dut.rise | (~clk & dut.run)),
            Assume(~dut.fall | clk),
        ]
        if self.fast:
            # SdClock at divisor 0, and a byte source that is never late.
            m.d.comb += Assume(dut.rise | dut.fall | (~clk & ~dut.run))
            m.d.comb += Assume(dut.i.valid)
        with m.If(dut.rise):
            m.d.sync += clk.eq(1)
        with m.If(dut.fall):
            m.d.sync += clk.eq(0)
        # The byte source follows the stream rules.
        stalled = Signal()
        offered = Signal(8)
        m.d.sync += [stalled.eq(dut.i.valid & ~dut.i.ready), offered.eq(dut.i.payload)]
        m.d.comb += Assume(~stalled | (dut.i.valid & (dut.i.payload == offered)))
        m.d.comb += Assume(dut.blocks != 0)

        # --- The lines as the card sees them ---------------------------------------------
        fell = Signal()                     # the writer's outputs show a falling edge's level
        m.d.sync += fell.eq(dut.fall)
        phase = Signal(_Phase)
        count = Signal(range(arch.DATA_NIBBLES + 1))
        ref = [Signal(arch.CRC16_BITS, name=f"ref_crc{lane}") for lane in range(LANES)]
        last_byte = Signal(8)               # the byte taken from `i` last
        owed = Signal(2)                    # its nibbles not yet sent
        # After this cycle's edge (the registers hold the state before it).
        next_phase = Signal(_Phase)
        next_count = Signal.like(count)
        next_ref = [Signal.like(ref[lane], name=f"next_ref_crc{lane}") for lane in range(LANES)]
        next_owed = Signal(2)
        owed_now = Signal(2)
        m.d.comb += owed_now.eq(Mux(dut.done, 0, owed))     # dropped with the run
        m.d.comb += [next_phase.eq(phase), next_count.eq(count), next_owed.eq(owed_now)]
        m.d.comb += [next_ref[lane].eq(ref[lane]) for lane in range(LANES)]

        crc_bit = Signal(range(arch.CRC16_BITS))
        m.d.comb += crc_bit.eq(arch.CRC16_BITS - 1 - count)
        ref_bits = Cat(ref[lane].bit_select(crc_bit, 1) for lane in range(LANES))
        data_nibble = Signal()
        drives = dut.dat_oe

        with m.If(fell):
            with m.Switch(phase):
                with m.Case(_Phase.OFF):
                    with m.If(drives):
                        check("framing", dut.dat_o == ALL_LINES)
                        m.d.comb += [next_phase.eq(_Phase.ONES), next_count.eq(1)]
                with m.Case(_Phase.ONES):
                    check("framing", drives)
                    with m.If(count < arch.N_WR):
                        check("framing", dut.dat_o == ALL_LINES, "preamble")
                        m.d.comb += next_count.eq(count + 1)
                    with m.Else():
                        check("framing", dut.dat_o == 0)
                        m.d.comb += [next_phase.eq(_Phase.START), next_count.eq(0)]
                        m.d.comb += [next_ref[lane].eq(0) for lane in range(LANES)]
                with m.Case(_Phase.START):
                    check("framing", drives)
                    m.d.comb += [data_nibble.eq(1), next_phase.eq(_Phase.DATA),
                                 next_count.eq(1)]
                with m.Case(_Phase.DATA):
                    check("framing", drives)
                    with m.If(count < arch.DATA_NIBBLES):
                        m.d.comb += [data_nibble.eq(1), next_count.eq(count + 1)]
                    with m.Else():
                        check("crc", dut.dat_o == Cat(ref[lane][-1] for lane in range(LANES)),
                              "crc_bits")
                        m.d.comb += [next_phase.eq(_Phase.CRC), next_count.eq(1)]
                with m.Case(_Phase.CRC):
                    check("framing", drives, "driven_to_end_bit")
                    with m.If(count < arch.CRC16_BITS):
                        check("crc", dut.dat_o == ref_bits, "crc_bits")
                        m.d.comb += next_count.eq(count + 1)
                    with m.Else():
                        check("framing", dut.dat_o == ALL_LINES)
                        m.d.comb += [next_phase.eq(_Phase.END), next_count.eq(0)]
                with m.Case(_Phase.END):
                    check("framing", ~drives, "released_after_end_bit")
                    m.d.comb += next_phase.eq(_Phase.OFF)
        # The lines only change right after a falling edge.
        prev_dat_o = Signal(4, init=ALL_LINES)
        prev_dat_oe = Signal()
        m.d.sync += [prev_dat_o.eq(dut.dat_o), prev_dat_oe.eq(dut.dat_oe)]
        check("framing", fell | ((dut.dat_o == prev_dat_o) & (dut.dat_oe == prev_dat_oe)))

        # Data nibbles: the high then the low nibble of the last byte taken.
        with m.If(data_nibble):
            check("data", owed_now != 0)
            check("data", dut.dat_o == Mux(owed_now == 2, last_byte[4:], last_byte[:4]))
            m.d.comb += next_owed.eq(owed_now - 1)
            m.d.comb += [next_ref[lane].eq(_crc16_step(ref[lane], dut.dat_o[lane]))
                         for lane in range(LANES)]
        taken = dut.i.valid & dut.i.ready
        check("data", ~taken | (next_owed == 0))
        with m.If(taken):
            m.d.sync += last_byte.eq(dut.i.payload)
        m.d.sync += [phase.eq(next_phase), count.eq(next_count),
                     owed.eq(next_owed + Mux(taken, 2, 0))]
        m.d.sync += [ref[lane].eq(next_ref[lane]) for lane in range(LANES)]

        # --- Released lines, busy and done -----------------------------------------------
        check("released",
              ~w.state.matches(state.TOKEN, state.BUSY_START, state.BUSY) | ~dut.dat_oe,
              "released_for_card")
        busy_before = Signal()
        start_before = Signal()
        m.d.sync += [busy_before.eq(dut.busy), start_before.eq(dut.start | dut.wait_busy)]
        check("busy", dut.busy | ~dut.dat_oe)
        check("busy", (dut.busy & ~busy_before) == (start_before & ~busy_before))
        check("busy", dut.done == (busy_before & ~dut.busy))

        # --- Invariants: the harness's view against DatWriter's registers -----------------
        def at(phase, count=None):
            test = next_phase == phase
            return test if count is None else test & (next_count == count)

        crc_matches = Cat(w.crc[lane] == next_ref[lane] for lane in range(LANES)).all()
        # While the CRC goes out, the writer's CRC registers shift up, one bit per bit sent.
        crc_shifted = Cat(w.crc[lane] == (next_ref[lane] << w.count)[:arch.CRC16_BITS]
                          for lane in range(LANES)).all()
        released = ~w.dat_oe & (w.dat_o == ALL_LINES)
        with m.Switch(w.state):
            with m.Case(state.IDLE, state.TOKEN, state.BUSY_START, state.BUSY):
                invariant(released & at(_Phase.OFF) & ~w.low)
            with m.Case(state.PREAMBLE):
                invariant((w.count < arch.N_WR) & (w.dat_o == ALL_LINES) & ~w.low &
                          (w.dat_oe == (w.count != 0)))
                invariant(Mux(w.count == 0, at(_Phase.OFF), at(_Phase.ONES, w.count)))
            with m.Case(state.START):
                invariant((w.count == arch.N_WR) & w.dat_oe & (w.dat_o == ALL_LINES) &
                          ~w.low & at(_Phase.ONES, arch.N_WR))
            with m.Case(state.DATA):
                invariant((w.count < w.nibbles) & w.dat_oe & (w.low == w.count[0]) &
                          crc_matches)
                invariant(Mux(w.count == 0, at(_Phase.START) & (w.dat_o == 0),
                              at(_Phase.DATA, w.count)))
            with m.Case(state.CRC):
                invariant((w.count < arch.CRC16_BITS) & w.dat_oe & ~w.low & crc_shifted)
                invariant(Mux(w.count == 0, at(_Phase.DATA, arch.DATA_NIBBLES),
                              at(_Phase.CRC, w.count)))
            with m.Case(state.END):
                invariant((w.count == arch.CRC16_BITS) & w.dat_oe & ~w.low & crc_shifted &
                          at(_Phase.CRC, arch.CRC16_BITS))
            with m.Case(state.RELEASE):
                invariant(w.dat_oe & (w.dat_o == ALL_LINES) & ~w.low & at(_Phase.END))
            with m.Default():
                invariant(C(0))
        # The byte model is the writer's byte register; a rise in the data is only let
        # through when the byte for the next falling edge is there.
        invariant(w.byte == last_byte)
        invariant(next_owed == Mux(w.loaded, Mux(w.low, 1, 2), 0))
        invariant(~w.low | w.loaded)
        invariant(~(clk & (w.state == state.DATA) & ~w.low) | w.loaded)
        invariant(~dut.done | (w.state == state.IDLE))

        # --- Covers --------------------------------------------------------------------
        # A busy period: DAT0 low at a rising edge while the writer waits for its end.
        busy_seen = Signal()
        with m.If(dut.start & ~dut.busy):
            m.d.sync += busy_seen.eq(0)
        with m.Elif(dut.rise & w.state.matches(state.BUSY_START, state.BUSY) & ~dut.dat_i[0]):
            m.d.sync += busy_seen.eq(1)
        cover("block_start", fell & (phase == _Phase.DATA) & (count == 1))
        if "block_end" in self.covers:
            # Anywhere in the data of the only block of a run, its first nibble sent.
            m.d.comb += Assume(dut.blocks == 1)
            m.d.comb += Assume(~first | ((w.state == state.DATA) & (w.count != 0) &
                                         (dut.accepted == 0) &
                                         (dut.status.as_value() == 0) & ~busy_seen))
            cover("block_end", dut.done & (dut.status.as_value() == 0) & (dut.accepted == 1) &
                  busy_seen)
        return m


# --- running SymbiYosys ---------------------------------------------------------------------

def run_sby(sby_env, directory, spec, *, mode, steps):
    """Prove (or cover, or bounded-check) ``spec``; return (returncode, log)."""
    return formal.run_sby(sby_env, directory, spec, ports=spec.ports(), mode=mode,
                          depth=steps, script=spec.script(), timeout=SBY_TIMEOUT)


def reported_lines(pattern, log):
    """Source lines (in this file) of the statements sby reports with ``pattern``."""
    return formal.reported_lines(pattern, log, __file__)


# --- the proof ------------------------------------------------------------------------------

def test_properties_proven(sby_env, tmp_path):
    spec = DatWriterSpec(ProbedDatWriter())
    rc, log = run_sby(sby_env, tmp_path / "prove", spec, mode="prove", steps=INDUCTION_STEPS)
    assert rc == 0 and "DONE (PASS" in log, log
    assert "successful proof by k-induction" in log, log


def test_properties_proven_from_anywhere(sby_env, tmp_path):
    # Where the broken variants below are checked from, the real writer never fails.
    spec = DatWriterSpec(ProbedDatWriter(), start="anywhere")
    rc, log = run_sby(sby_env, tmp_path / "prove", spec, mode="prove", steps=INDUCTION_STEPS)
    assert rc == 0 and "DONE (PASS" in log, log
    assert "successful proof by k-induction" in log, log


def test_block_start_is_reachable(sby_env, tmp_path):
    spec = DatWriterSpec(ProbedDatWriter(), invariants=False, covers=["block_start"],
                         fast=True)
    rc, log = run_sby(sby_env, tmp_path / "cover", spec, mode="cover",
                      steps=COVER_START_STEPS)
    assert rc == 0 and "DONE (PASS" in log, log
    assert reported_lines("Reached cover statement in step \\d+ at top:", log) == \
        spec.lines["cover"], log


def test_block_end_reaches_done(sby_env, tmp_path):
    spec = DatWriterSpec(ProbedDatWriter(), start="anywhere", invariants=False,
                         covers=["block_end"], fast=True)
    rc, log = run_sby(sby_env, tmp_path / "cover", spec, mode="cover", steps=COVER_END_STEPS)
    assert rc == 0 and "DONE (PASS" in log, log
    assert reported_lines("Reached cover statement in step \\d+ at top:", log) == \
        spec.lines["cover"], log


@pytest.mark.parametrize("make, group, label, start", [
    (lambda: MisdrivenWriter("short_preamble"), "framing", "preamble", "reset"),
    (ShortBlockWriter, "framing", "driven_to_end_bit", "anywhere"),
    (lambda: MisdrivenWriter("early_release"), "framing", "driven_to_end_bit", "anywhere"),
    (lambda: MisdrivenWriter("late_release"), "framing", "released_after_end_bit",
     "anywhere"),
    (lambda: MisdrivenWriter("late_release"), "released", "released_for_card", "anywhere"),
    (lambda: MisdrivenWriter("bad_crc"), "crc", "crc_bits", "anywhere"),
], ids=["short_preamble", "short_block", "early_release", "late_release-framing",
        "late_release-released", "bad_crc"])
def test_broken_writer_fails(sby_env, tmp_path, make, group, label, start):
    steps = ANYWHERE_STEPS if start == "anywhere" else RESET_STEPS
    spec = DatWriterSpec(make(), checks=[group], start=start, invariants=False, fast=True)
    rc, log = run_sby(sby_env, tmp_path / "bmc", spec, mode="bmc", steps=steps)
    assert rc != 0 and "DONE (FAIL" in log, log
    failed = reported_lines("Assert failed in top:", log)
    assert failed and failed <= spec.lines[label], log
