"""SdramChip driven clock by clock by command sequences written here, from the data sheets.

A sequence is a list of (command, bank, address, data[, dqm]) per clock: `data` is what the
controller drives on DQ (None: DQ released), a command of None is a deselect (CS# high).
:class:`Program` lays commands out at chosen cycles and fills the gaps with NOPs; its
clock counts come from the presets' nanoseconds, rounded up to whole clocks. Nothing here
comes from a controller.
"""

from __future__ import annotations

import math
import random

import pytest

from maglog.hw.arch.sdram import (A10, IS42S16160, MT48LC4M32B2, BurstLength, Command,
                                  mode_register)
from maglog.sim.models.sdram import SdramChip, SdramTimingError, decode_mode_register

CHIPS = [MT48LC4M32B2, IS42S16160]
ACTIVE, READ, WRITE = Command.ACTIVE, Command.READ, Command.WRITE
PRECHARGE, REFRESH, LOAD_MODE = Command.PRECHARGE, Command.REFRESH, Command.LOAD_MODE
NOP, BURST_TERMINATE = Command.NOP, Command.BURST_TERMINATE
DESELECT = None
ALL_BANKS = AUTO_PRECHARGE = 1 << A10
BURST_WORDS = {BurstLength.ONE: 1, BurstLength.TWO: 2, BurstLength.FOUR: 4,
               BurstLength.EIGHT: 8}
INTERLEAVED = 1 << 3            # mode register A3. Ref: data sheets, "Burst Type"
FAST_CLOCK = 133e6              # every timing rule but tRC on the ISSI part can be broken alone
SLOW_CLOCK = 1e6                # the refresh period in few clocks


def run(chip: SdramChip, steps, *, cke=1) -> list:
    """Feed the steps to the chip, one edge each; the chip's DQ output after each edge."""
    out = []
    for command, bank, address, data, *rest in steps:
        dqm = rest[0] if rest else 0
        bits = NOP if command is None else int(command)
        out.append(chip.edge(cke=cke, cs_n=int(command is None), ras_n=bits >> 2 & 1,
                             cas_n=bits >> 1 & 1, we_n=bits & 1, ba=bank, a=address, dqm=dqm,
                             dq_oe=int(data is not None), dq=0 if data is None else data))
    return out


def byte_mask(dqm):
    return sum(0xFF << (8 * n) for n in range(8) if dqm >> n & 1)


class Program:
    """A command sequence, one step per clock, with the chip's timing in clocks."""

    def __init__(self, chip, clk_freq):
        t = chip.timing
        self.chip, self.clk_freq = chip, clk_freq

        def clocks(ns):
            return max(1, math.ceil(ns * clk_freq / 1e9 - 1e-9))

        self.t_rcd, self.t_rp, self.t_ras = clocks(t.t_rcd), clocks(t.t_rp), clocks(t.t_ras)
        self.t_rc, self.t_rfc, self.t_wr = clocks(t.t_rc), clocks(t.t_rfc), clocks(t.t_wr)
        self.t_mrd = t.t_mrd_clocks
        self.t_ras_max = math.floor(t.t_ras_max * clk_freq / 1e9 + 1e-9)
        self.t_ref = math.floor(t.t_ref_ms * clk_freq / 1e3 + 1e-9)
        self.power_up = clocks(t.power_up_us * 1e3)
        self.steps: list = []
        self.ready = 0          # first cycle after the initialisation's last wait
        self.init_end = None    # cycle of the initialisation's last command

    @property
    def now(self):
        return len(self.steps)

    def nop(self, n=1, data=None, dqm=0):
        self.steps += [(NOP, 0, 0, data, dqm)] * n

    def at(self, cycle, command, bank=0, address=0, data=None, dqm=0):
        """`command` at `cycle`, after NOPs from the current end."""
        assert cycle >= self.now, f"cycle {cycle} is already taken (now {self.now})"
        self.nop(cycle - self.now)
        self.steps.append((command, bank, address, data, dqm))
        return cycle

    def init(self, mode, *, mode_first=False):
        """Power-up NOPs (deselects), PRECHARGE ALL, REFRESHes and LOAD_MODE (either order)."""
        self.steps += [(DESELECT, 0, 0, None)] * self.power_up
        last = self.at(self.now, PRECHARGE, address=ALL_BANKS)
        gap = self.t_rp
        refreshes = [(REFRESH, 0, self.t_rfc)] * self.chip.timing.init_refreshes
        load = [(LOAD_MODE, mode, self.t_mrd)]
        for command, address, after in (load + refreshes if mode_first else refreshes + load):
            last = self.at(last + gap, command, address=address)
            gap = after
        self.init_end, self.ready = last, last + gap
        return self


def reads(out, read_cycle, cas_latency, words):
    """The words of a read burst as the controller samples them."""
    return out[read_cycle + cas_latency - 1:read_cycle + cas_latency - 1 + words]


def burst_columns(start, words, *, interleaved=False):
    """Column order of a burst (data sheets, "Burst Definition")."""
    block = words - 1
    if interleaved:
        return [(start & ~block) | ((start & block) ^ i) for i in range(words)]
    return [(start & ~block) | ((start + i) & block) for i in range(words)]


# -- correct sequences ---------------------------------------------------------------------------

@pytest.mark.parametrize("burst", [BurstLength.ONE, BurstLength.FOUR, BurstLength.EIGHT],
                         ids=lambda b: f"BL{BURST_WORDS[b]}")
@pytest.mark.parametrize("cas_latency", [2, 3], ids=lambda cl: f"CL{cl}")
@pytest.mark.parametrize("chip", CHIPS, ids=lambda c: c.name)
def test_write_read(chip, cas_latency, burst):
    """Back-to-back write bursts (the second with DQM byte masks), then back-to-back reads."""
    words = BURST_WORDS[burst]
    rng = random.Random(f"{chip.name}/{cas_latency}/{words}")
    width, dqm_all = chip.geometry.data_width, (1 << chip.geometry.data_width // 8) - 1
    p = Program(chip, 100e6).init(mode_register(cas_latency=cas_latency, burst_length=burst),
                                  mode_first=cas_latency == 3)
    bank, row, start, total = 2, chip.geometry.rows - 3, 13, 8
    expected = {}
    act = p.at(p.ready, ACTIVE, bank, row)
    cycle = act + p.t_rcd
    for masked in (False, True):
        for burst_start in range(start, start + total, words):
            for i, column in enumerate(burst_columns(burst_start, words)):
                data = rng.getrandbits(width)
                dqm = rng.choice([0, dqm_all, 1, dqm_all >> 1, rng.randrange(dqm_all)]) \
                    if masked else 0
                command = WRITE if i == 0 else NOP
                p.at(cycle, command, bank, burst_start, data, dqm)
                old = expected.get(column, 0)
                expected[column] = (old & byte_mask(dqm)) | (data & ~byte_mask(dqm))
                cycle += 1
    read_at = []
    cycle += p.t_wr
    for burst_start in range(start, start + total, words):
        read_at.append((p.at(cycle, READ, bank, burst_start), burst_start))
        cycle += words
    p.at(max(cycle + cas_latency, act + p.t_ras), PRECHARGE, address=ALL_BANKS)
    p.nop(p.t_rp)

    sdram = SdramChip(chip, clk_freq=100e6)
    out = run(sdram, p.steps)
    assert sdram.errors == []
    assert sdram.mode["cas_latency"] == cas_latency
    assert sdram.mode["burst_length"] == words
    assert sdram.initialised and sdram.open_rows == [None] * 4
    for read_cycle, burst_start in read_at:
        got = reads(out, read_cycle, cas_latency, words)
        assert got == [expected[c] for c in burst_columns(burst_start, words)]
    # The bus is released outside the read data.
    data_cycles = {r + cas_latency - 1 + i for r, _ in read_at for i in range(words)}
    assert all(v is None for n, v in enumerate(out) if n not in data_cycles)
    for column, value in expected.items():
        assert sdram.peek(bank, row, column) == value
    assert sdram.peek(bank, row + 1, start) == 0
    assert sdram.peek(0, row, start) == 0


@pytest.mark.parametrize("cas_latency", [2, 3], ids=lambda cl: f"CL{cl}")
@pytest.mark.parametrize("chip", CHIPS, ids=lambda c: c.name)
def test_read_dqm_masks_two_clocks_later(chip, cas_latency):
    width = chip.geometry.data_width
    dqm_all = (1 << width // 8) - 1
    p = Program(chip, 100e6).init(mode_register(cas_latency=cas_latency,
                                                burst_length=BurstLength.EIGHT))
    sdram = SdramChip(chip, clk_freq=100e6)
    pattern = [random.Random(n).getrandbits(width) for n in range(8)]
    for column, value in enumerate(pattern):
        sdram.poke(1, 7, column, value)
    act = p.at(p.ready, ACTIVE, 1, 7)
    r = p.at(act + p.t_rcd, READ, 1, 0)
    # DQM at cycle k blanks the word sampled at k + 2: word k + 2 - (r + CL).
    p.at(r + 1, NOP, dqm=dqm_all)
    p.at(r + 3, NOP, dqm=0b01)
    p.at(r + 4 + cas_latency, PRECHARGE, 1)     # truncates the burst
    p.nop(12)
    out = run(sdram, p.steps)
    words = reads(out, r, cas_latency, 8)
    expected = list(pattern)
    expected[r + 1 + 2 - (r + cas_latency)] = None
    expected[r + 3 + 2 - (r + cas_latency)] &= ~0xFF
    # PRECHARGE at P = R + 4 + CL: column accesses at R .. P - 1, so words 0 .. 3 + CL (the
    # last one sampled at P + CL - 1).
    expected[4 + cas_latency:] = [None] * (4 - cas_latency)
    assert words == expected
    assert sdram.errors == []


def test_burst_interrupts_and_full_page():
    """READ interrupts READ, BURST_TERMINATE ends a full-page write and read, a WRITE ends a
    read (DQM masking the word at the WRITE), interleaved bursts."""
    chip, cl = MT48LC4M32B2, 2
    columns = chip.geometry.columns
    full_page = mode_register(cas_latency=cl, burst_length=BurstLength.FULL_PAGE)
    p = Program(chip, 100e6).init(full_page)
    act = p.at(p.ready, ACTIVE, 0, 100)
    w = p.at(act + p.t_rcd, WRITE, 0, columns - 2, 0xA0)
    for n in range(1, 5):
        p.at(w + n, NOP, data=0xA0 + n)
    p.at(w + 5, BURST_TERMINATE, data=0xFF)     # data at BURST_TERMINATE is not written
    r = p.at(w + 6, READ, 0, columns - 1)
    bt = p.at(r + 3, BURST_TERMINATE)           # three words: columns-1, 0, 1
    # READ (full page) interrupted by READ after 2 words.
    r2 = p.at(bt + 4, READ, 0, 0)
    r3 = p.at(r2 + 2, READ, 0, columns - 2)
    # ...and by a WRITE: DQM two clocks before the WRITE masks the word sampled at it.
    p.at(r3 + 1, NOP, dqm=0b1111)
    w2 = p.at(r3 + 3, WRITE, 0, 5, 0x55)
    p.at(w2 + 1, BURST_TERMINATE)
    p.nop(8)
    sdram = SdramChip(chip, clk_freq=100e6)
    out = run(sdram, p.steps)
    assert sdram.errors == []
    assert [sdram.peek(0, 100, c) for c in (columns - 2, columns - 1, 0, 1, 2, 3)] == \
        [0xA0, 0xA1, 0xA2, 0xA3, 0xA4, 0]
    assert reads(out, r, cl, 4) == [0xA1, 0xA2, 0xA3, None]
    assert reads(out, r2, cl, 2) == [0xA2, 0xA3]
    # Word 1 is sampled at the WRITE's edge (masked), word 2 is never driven.
    assert reads(out, r3, cl, 3) == [0xA0, None, None]
    assert out[w2 - 1:] == [None] * (len(out) - w2 + 1)
    assert sdram.peek(0, 100, 5) == 0x55 and sdram.peek(0, 100, 6) == 0

    # Interleaved burst of 8 starting at column 3.
    mode = mode_register(cas_latency=3, burst_length=BurstLength.EIGHT) | INTERLEAVED
    p = Program(chip, 100e6).init(mode)
    act = p.at(p.ready, ACTIVE, 3, 1)
    r = p.at(act + p.t_rcd, READ, 3, 3)
    p.nop(12)
    sdram = SdramChip(chip, clk_freq=100e6)
    for c in range(8):
        sdram.poke(3, 1, c, c + 100)
    out = run(sdram, p.steps)
    assert sdram.mode["burst_type"] == "interleaved"
    assert reads(out, r, 3, 8) == [c + 100 for c in burst_columns(3, 8, interleaved=True)]
    assert reads(out, r, 3, 8) == [103, 102, 101, 100, 107, 106, 105, 104]


@pytest.mark.parametrize("chip", CHIPS, ids=lambda c: c.name)
def test_auto_precharge_at_the_limits(chip):
    """WRITE and READ with auto precharge, next ACTIVE exactly tWR + tRP after the last data
    and tRP after the end of the read burst; single-location writes (A9)."""
    mode = mode_register(cas_latency=2, burst_length=BurstLength.FOUR, single_write=True)
    p = Program(chip, FAST_CLOCK).init(mode)
    act = p.at(p.ready, ACTIVE, 1, 9)
    w = p.at(act + p.t_ras, WRITE, 1, 4 | AUTO_PRECHARGE, 0x1234)   # one word: single write
    act2 = p.at(w + p.t_wr + p.t_rp, ACTIVE, 1, 9)
    r = p.at(act2 + p.t_ras, READ, 1, 4 | AUTO_PRECHARGE)           # a burst of 4
    p.at(r + 4 + p.t_rp, ACTIVE, 1, 9)
    p.nop(4)
    sdram = SdramChip(chip, clk_freq=FAST_CLOCK)
    out = run(sdram, p.steps)
    assert sdram.errors == []
    assert reads(out, r, 2, 4) == [0x1234, 0, 0, 0]
    assert sdram.open_rows[1] == 9


@pytest.mark.parametrize("chip", CHIPS, ids=lambda c: c.name)
def test_refresh_on_time(chip):
    """A REFRESH every refresh_interval_clocks for two and a half refresh periods."""
    p = Program(chip, SLOW_CLOCK).init(mode_register(cas_latency=2))
    interval = chip.refresh_interval_clocks(SLOW_CLOCK)
    cycle = p.init_end
    while cycle < p.init_end + 5 * p.t_ref // 2:
        cycle = p.at(cycle + interval, REFRESH)
    sdram = SdramChip(chip, clk_freq=SLOW_CLOCK)
    run(sdram, p.steps)
    assert sdram.errors == []
    assert sdram.command_counts[REFRESH] > 2 * chip.geometry.rows


# -- one broken rule per case ----------------------------------------------------------------------

MODE = mode_register(cas_latency=2, burst_length=BurstLength.ONE)


def trcd(p, ok):
    act = p.init(MODE).at(p.ready, ACTIVE, 2, 5)
    return p.at(act + p.t_rcd - (not ok), READ, 2, 0)


def trp(p, ok):
    act = p.init(MODE).at(p.ready, ACTIVE, 1, 5)
    pre = p.at(act + max(p.t_ras, p.t_rc - p.t_rp + 1), PRECHARGE, 1)
    return p.at(pre + p.t_rp - (not ok), ACTIVE, 1, 6)


def tras_min(p, ok):
    act = p.init(MODE).at(p.ready, ACTIVE, 0, 5)
    return p.at(act + p.t_ras - (not ok), PRECHARGE, 0)


def tras_max(p, ok):
    act = p.init(MODE).at(p.ready, ACTIVE, 3, 5)
    if ok:
        p.at(act + p.t_ras_max, PRECHARGE, address=ALL_BANKS)
    p.nop(act + p.t_ras_max + 5 - p.now)
    return act + p.t_ras_max + 1


def trc(p, ok):
    act = p.init(MODE).at(p.ready, ACTIVE, 1, 5)
    pre = p.at(act + p.t_ras, PRECHARGE, 1)
    assert pre + p.t_rp <= act + p.t_rc - 1, "tRC must be longer than tRAS + tRP here"
    return p.at(act + p.t_rc - (not ok), ACTIVE, 1, 6)


def trfc(p, ok):
    ref = p.init(MODE).at(p.ready, REFRESH)
    return p.at(ref + p.t_rfc - (not ok), ACTIVE, 0, 1)


def twr(p, ok):
    act = p.init(MODE).at(p.ready, ACTIVE, 2, 5)
    w = p.at(act + p.t_ras, WRITE, 2, 7, 0xBEEF)
    return p.at(w + p.t_wr - (not ok), PRECHARGE, 2)


def twr_auto_precharge(p, ok):
    act = p.init(MODE).at(p.ready, ACTIVE, 2, 5)
    w = p.at(act + max(p.t_ras, p.t_rc), WRITE, 2, 7 | AUTO_PRECHARGE, 0xBEEF)
    return p.at(w + p.t_wr + p.t_rp - (not ok), ACTIVE, 2, 5)


def tmrd(p, ok):
    load = p.init(MODE).at(p.ready, LOAD_MODE, address=MODE)
    return p.at(load + p.t_mrd - (not ok), ACTIVE, 0, 1)


def refresh_interval(p, ok):
    """A REFRESH every interval (+ 1 clock: late, adding up to a row missed)."""
    p.init(MODE)
    interval = p.chip.refresh_interval_clocks(p.clk_freq) + (not ok)
    cycle = p.init_end
    while cycle < p.init_end + p.t_ref + 2 * interval:
        cycle = p.at(cycle + interval, REFRESH)
    # The rows are refreshed in order from the end of the initialisation; every one within
    # t_ref of it, so the `rows`-th REFRESH is due by then.
    return p.init_end + p.t_ref + 1


def init_without_precharge_all(p, ok):
    p.steps += [(DESELECT, 0, 0, None)] * p.power_up
    return p.at(p.now, PRECHARGE if ok else REFRESH, address=ALL_BANKS)


def init_power_up_too_short(p, ok):
    p.nop(p.power_up - (not ok))
    return p.at(p.now, PRECHARGE, address=ALL_BANKS)


def init_load_mode_between_refreshes(p, ok):
    cycle = p.power_up
    p.at(cycle, PRECHARGE, address=ALL_BANKS)
    cycle = p.at(cycle + p.t_rp, REFRESH)
    for _ in range(p.chip.timing.init_refreshes - 1 if ok else 0):
        cycle = p.at(cycle + p.t_rfc, REFRESH)
    return p.at(cycle + p.t_rfc, LOAD_MODE, address=MODE)


def init_active_before_load_mode(p, ok):
    cycle = p.power_up
    p.at(cycle, PRECHARGE, address=ALL_BANKS)
    cycle += p.t_rp
    for _ in range(p.chip.timing.init_refreshes):
        cycle = p.at(cycle, REFRESH) + p.t_rfc
    if ok:
        cycle = p.at(cycle, LOAD_MODE, address=MODE) + p.t_mrd
    return p.at(cycle, ACTIVE, 0, 1)


def closed_row(p, ok):
    act = p.init(MODE).at(p.ready, ACTIVE, 0, 1)
    pre = p.at(act + p.t_ras, PRECHARGE, 3 if ok else 0)
    return p.at(pre + 1, WRITE, 0, 2, 0x77)


def open_bank(p, ok):
    act = p.init(MODE).at(p.ready, ACTIVE, 0, 1)
    if ok:
        p.at(act + p.t_ras, PRECHARGE, 0)
    return p.at(act + p.t_ras + p.t_rc, ACTIVE, 0, 2)


def refresh_with_bank_open(p, ok):
    act = p.init(MODE).at(p.ready, ACTIVE, 1, 1)
    pre = p.at(act + p.t_ras, PRECHARGE, 1 if ok else 2)
    return p.at(pre + p.t_rp, REFRESH)


def load_mode_with_bank_open(p, ok):
    act = p.init(MODE).at(p.ready, ACTIVE, 3, 1)
    pre = p.at(act + p.t_ras, PRECHARGE, 3 if ok else 0)
    return p.at(pre + p.t_rp, LOAD_MODE, address=MODE)


def contention(p, ok):
    """READ, then a WRITE when the read data is on the bus; DQM two clocks before masks it."""
    act = p.init(MODE).at(p.ready, ACTIVE, 1, 1)
    r = p.at(act + p.t_rcd, READ, 1, 0)
    cas_latency, all_bytes = 2, (1 << p.chip.geometry.data_width // 8) - 1
    if ok:
        p.steps[r + cas_latency - 2] = (READ, 1, 0, None, all_bytes)
    return p.at(r + cas_latency, WRITE, 1, 1, 0x99)


def write_data_not_driven(p, ok):
    act = p.init(mode_register(cas_latency=2, burst_length=BurstLength.TWO)).at(
        p.ready, ACTIVE, 1, 1)
    w = p.at(act + p.t_rcd, WRITE, 1, 0, 0x1)
    all_bytes = (1 << p.chip.geometry.data_width // 8) - 1
    return p.at(w + 1, NOP, dqm=all_bytes if ok else 0b10)


def reserved_mode(p, ok):
    return p.init(MODE if ok else MODE | 0b100).init_end


def full_page_auto_precharge(p, ok):
    full_page = mode_register(cas_latency=2, burst_length=BurstLength.FULL_PAGE)
    act = p.init(full_page).at(p.ready, ACTIVE, 1, 1)
    return p.at(act + p.t_rcd, READ, 1, 0 if ok else AUTO_PRECHARGE)


CASES = [
    ("tRCD", trcd), ("tRP", trp), ("tRAS min", tras_min), ("tRAS max", tras_max),
    ("tRC", trc), ("tRFC", trfc), ("tWR", twr), ("tWR", twr_auto_precharge), ("tMRD", tmrd),
    ("refresh interval", refresh_interval),
    ("init sequence", init_without_precharge_all), ("power-up", init_power_up_too_short),
    ("init sequence", init_load_mode_between_refreshes),
    ("init sequence", init_active_before_load_mode),
    ("closed row", closed_row), ("open bank", open_bank),
    ("all banks precharged", refresh_with_bank_open), ("all banks idle", load_mode_with_bank_open),
    ("contention", contention), ("write data", write_data_not_driven),
    ("mode register", reserved_mode), ("auto precharge", full_page_auto_precharge),
]
# tRC cannot be broken alone on the IS42S16160: tRAS + tRP (42 + 20 ns) rounds up to at
# least the clocks of tRC (63 ns) at every clock frequency.
RULE_PARAMS = [pytest.param(chip, rule, case, id=f"{chip.name}-{case.__name__}")
               for chip in CHIPS for rule, case in CASES
               if not (rule == "tRC" and chip is IS42S16160)]


def _program(chip, case):
    return Program(chip, SLOW_CLOCK if case is refresh_interval else FAST_CLOCK)


@pytest.mark.parametrize("chip, rule, case", RULE_PARAMS)
def test_rule_broken(chip, rule, case):
    p = _program(chip, case)
    bad = case(p, ok=False)
    p.nop(3)
    sdram = SdramChip(chip, clk_freq=p.clk_freq)
    with pytest.raises(SdramTimingError) as caught:
        run(sdram, p.steps)
    error = caught.value
    assert (error.cycle, error.rule) == (bad, rule), str(error)
    assert str(error).startswith(f"cycle {bad}: ")
    assert rule in str(error)
    assert sdram.cycle == bad + 1


@pytest.mark.parametrize("chip, rule, case", RULE_PARAMS)
def test_rule_kept(chip, rule, case):
    """The same sequence one clock later (timing rules) or with the right command."""
    p = _program(chip, case)
    case(p, ok=True)
    p.nop(8)
    sdram = SdramChip(chip, clk_freq=p.clk_freq)
    run(sdram, p.steps)
    assert sdram.errors == []


def test_collects_errors_when_not_strict():
    """Violations are collected in order; the chip carries on (data written despite tRCD)."""
    chip = MT48LC4M32B2
    p = Program(chip, FAST_CLOCK).init(MODE)
    act = p.at(p.ready, ACTIVE, 0, 3)
    w = p.at(act + 1, WRITE, 0, 4, 0xCAFE)                 # tRCD
    r = p.at(act + p.t_rcd, READ, 0, 4)
    pre = p.at(r + 1, PRECHARGE, 0)                        # tRAS min
    bad_read = p.at(pre + p.t_rp, READ, 0, 4)              # closed row
    p.nop(4)
    sdram = SdramChip(chip, clk_freq=FAST_CLOCK, strict=False)
    out = run(sdram, p.steps)
    assert [e.split(":")[0] for e in sdram.errors] == \
        [f"cycle {c}" for c in (w, pre, bad_read)]
    for error, rule in zip(sdram.errors, ["tRCD", "tRAS min", "closed row"]):
        assert rule in error
    assert sdram.errors[0] == f"cycle {w}: WRITE to bank 0 only 1 clocks after ACTIVE " \
        f"(tRCD needs {p.t_rcd})"
    assert out[r + 1] == 0xCAFE
    assert sdram.peek(0, 3, 4) == 0xCAFE
    assert all(v is None for v in out[bad_read:])


def test_cke_low_holds_off_power_up():
    """Edges with CKE low before power-up register nothing and do not count as power-up."""
    chip = IS42S16160
    sdram = SdramChip(chip, clk_freq=FAST_CLOCK)
    run(sdram, [(PRECHARGE, 0, ALL_BANKS, None)] * 10, cke=0)
    p = Program(chip, FAST_CLOCK).init(MODE)
    run(sdram, p.steps)
    assert sdram.initialised and sdram.errors == []
    with pytest.raises(SdramTimingError, match="CKE"):
        run(sdram, [(NOP, 0, 0, None)], cke=0)


def test_mode_register_decoding():
    mode, problems = decode_mode_register(
        mode_register(cas_latency=3, burst_length=BurstLength.FULL_PAGE, single_write=True),
        columns=256)
    assert problems == []
    assert mode == {"value": 0x237, "burst_length": 256, "full_page": True,
                    "burst_type": "sequential", "cas_latency": 3, "operating_mode": 0,
                    "write_burst": "single"}
    _, problems = decode_mode_register(0b1_1000_1101, columns=256)
    assert len(problems) == 3       # full page interleaved, CAS latency 0, operating mode


@pytest.mark.parametrize("bad, message", [
    (dict(clk_freq=0), "Clock frequency must be a positive number, not 0"),
    (dict(chip="MT48LC4M32B2"), "Chip must be a Chip preset, not 'MT48LC4M32B2'"),
])
def test_bad_arguments(bad, message):
    args = dict(chip=MT48LC4M32B2, clk_freq=100e6) | bad
    with pytest.raises((TypeError, ValueError), match=message):
        SdramChip(args.pop("chip"), **args)
