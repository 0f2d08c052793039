"""A timing-checking SDR SDRAM chip, clock by clock, in plain Python.

:class:`SdramChip` is written from the chips' data sheets (JEDEC SDR SDRAM, see
:mod:`maglog.hw.arch.sdram`), independently of the controller: it shares nothing with hw/
but the commands, the mode register layout and the chip presets. Adapters for the Amaranth
simulator and for cocotb call :meth:`SdramChip.edge` once per rising clock edge with the
controller's pins and drive DQ with what it returns until the next edge.

Clocking convention. ``edge(...)`` is rising edge number :attr:`SdramChip.cycle` (counted
from 0). Its inputs are the pin levels sampled at that edge; its result is what the chip
drives on DQ during the following clock period, so the controller samples it at the next
edge. A READ registered at edge R with CAS latency CL puts word ``i`` of its burst on the bus
to be sampled at edge ``R + CL + i``: ``edge`` number ``R + CL - 1 + i`` returns it.
A timing of "n clocks" between two commands means their edge numbers differ by at least n.
Nanosecond minimums become clocks with :meth:`~maglog.hw.arch.sdram.Timing.clocks` (round
up); maximums (tRAS max, the refresh period) round down.

What the chip does:

* Commands from {CS#, RAS#, CAS#, WE#}; CS# high is a deselect (a NOP). CKE is only used
  for power-up: the first edge with CKE high starts the initialisation; CKE low after that is
  reported (power-down and self refresh are not modelled) and the edge registers no command.
* Banks are idle or have one open row. ACTIVE opens a row, PRECHARGE closes one bank or,
  with A10 high, all; a PRECHARGE to an idle bank is a NOP for it (it does not restart tRP).
  READ/WRITE with A10 high auto-precharge the bank: as if a PRECHARGE were registered at
  the first edge after the burst's last read column (READ), or tWR after the last data edge
  (WRITE; tWR counts from the interrupting command when the burst is interrupted), but never
  before tRAS min ("tRAS lockout", Micron "earliest valid stage"). Auto precharge with a
  full-page burst is reported and ignored.
* Mode register (LOAD_MODE, A9..A0): burst length 1/2/4/8/full page, sequential or
  interleaved bursts (full page sequential only), CAS latency 2 or 3, standard operation,
  burst or single-location writes. Reserved values are reported and leave the mode unchanged.
* Bursts: the column counter wraps within the burst-length-aligned block (a full page wraps
  around the row and runs until interrupted). READ, WRITE, BURST_TERMINATE, and a PRECHARGE
  of the burst's bank interrupt a burst at their edge: a read burst makes no further column
  accesses (the data already in the CAS-latency pipeline still comes out, so the last word
  is sampled CL - 1 edges after the interrupting command); a write burst takes no data at the
  interrupting edge. A WRITE also stops the read pipeline: read data that would be sampled
  after the WRITE's edge is dropped (DQ turn to inputs).
* Data: storage is a dict of ``data_width``-bit words (unwritten words read as 0). A write
  stores DQ at the WRITE's edge and at the following burst edges; DQM (bit n masks byte n,
  DQ[8n+7:8n]) masks bytes at the same edge (write latency 0). Reads fetch the word at the
  edge of its column access (the READ's edge, then one per edge) and put it out CL clocks
  later. DQM masks read data with latency 2: DQM sampled at edge n blanks the bytes the chip
  would drive for the controller to sample at edge n + 2. Masked bytes are not driven; they
  read as 0 in the returned word, and when every byte is masked ``edge`` returns None (the
  chip does not drive DQ).

Checks. Each violation is raised as :class:`SdramTimingError` ("cycle N: <what> (<rule> ...)")
when ``strict``, else appended to :attr:`SdramChip.errors` as the same string, and the chip
carries on as well as it can (a READ/WRITE to a closed bank, or before a mode is loaded, does
nothing; a command that breaks a timing rule still executes). The rule names, as in
:attr:`SdramTimingError.rule`:

``tRCD`` ACTIVE to READ/WRITE in the bank; ``tRP`` PRECHARGE (or auto precharge) to ACTIVE
of the bank, to REFRESH and to LOAD_MODE; ``tRAS min`` ACTIVE to PRECHARGE; ``tRAS max`` a row
open too long (reported at the first edge past it); ``tRC`` ACTIVE to ACTIVE in a bank;
``tRFC`` REFRESH to any command but NOP/deselect; ``tWR`` last written data (an edge where a
WRITE burst stored at least one byte) to PRECHARGE of the bank, and with auto precharge
"tWR + tRP" from the last data to the next ACTIVE; ``tMRD`` LOAD_MODE to any command;
``all banks precharged`` REFRESH with a row open; ``all banks idle`` LOAD_MODE with a row
open; ``open bank`` ACTIVE to a bank with an open row; ``closed row`` READ/WRITE to a bank
with no open row (or whose auto precharge is under way); ``contention`` the controller drives
DQ (``dq_oe``) at an edge for which the chip drives read data; ``write data`` a write burst
edge with unmasked bytes but DQ not driven (nothing is stored); ``auto precharge``;
``mode register`` reserved mode fields; ``CKE``; ``init sequence`` and ``power-up``.

Initialisation. From the first edge with CKE high: NOP/deselect only for at least
``power_up_us`` (``power-up``: the first command must come no earlier), then PRECHARGE ALL,
then ``init_refreshes`` REFRESH commands and one LOAD_MODE. JEDEC allows the mode register
to be loaded before or after the refreshes: both orders are accepted (more refreshes than
required are fine), a LOAD_MODE between them is not. A READ, WRITE or ACTIVE before the
initialisation is complete, and any command other than PRECHARGE ALL first, is an
``init sequence`` error. The initialisation completes at the edge of its last command.

Refresh interval (``refresh interval``). The chip refreshes its rows in order, one row (in
every bank) per REFRESH, from an internal counter; every row must be refreshed again within
``t_ref_ms`` of its previous refresh, and the first round is counted from the end of the
initialisation (the refreshes in the initialisation do not count). Equivalently: the first
``rows`` REFRESH commands after the initialisation lie within t_ref of its end, and any
REFRESH is followed by ``rows`` more within t_ref. A controller that issues a REFRESH every
:meth:`~maglog.hw.arch.sdram.Chip.refresh_interval_clocks` passes; one that is late by a clock
each time fails once the lateness adds up. The violation is reported at the first edge past
the deadline, once until the controller has caught up.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

from ...hw.arch.sdram import A10, BurstLength, Chip, Command

__all__ = ["SdramChip", "SdramTimingError", "ClockTiming", "decode_mode_register", "PINS"]

#: The controller's outputs the chip samples at each rising edge, as :meth:`SdramChip.edge`
#: takes them (with ``dq``, the controller's ``dq_o``); every simulator adapter reads these.
PINS = ("cke", "cs_n", "ras_n", "cas_n", "we_n", "ba", "a", "dqm", "dq_oe")

_BYTE_BITS = 8
#: Mode register fields. Ref: MT48LC4M32B2 / IS42S16160 data sheets, "Mode Register
#: Definition": A2..A0 burst length, A3 burst type, A6..A4 CAS latency, A8..A7 operating
#: mode, A9 write burst mode.
_BURST_LENGTH_MASK = 0b111
_BURST_TYPE_BIT = 3
_CAS_LATENCY_SHIFT, _CAS_LATENCY_MASK = 4, 0b111
_OP_MODE_SHIFT, _OP_MODE_MASK = 7, 0b11
_WRITE_BURST_BIT = 9
_CAS_LATENCIES = (2, 3)
_FIXED_BURSTS = {BurstLength.ONE: 1, BurstLength.TWO: 2, BurstLength.FOUR: 4,
                 BurstLength.EIGHT: 8}
#: Commands by their {RAS#, CAS#, WE#} value (decoded at every edge: a lookup, not a call).
_COMMANDS = tuple(Command(value) for value in range(len(Command)))


class SdramTimingError(Exception):
    """A protocol or timing violation: ``str(error)`` is "cycle N: message", with the rule
    named in the message; :attr:`cycle` and :attr:`rule` hold both separately."""

    def __init__(self, cycle: int, rule: str, message: str):
        super().__init__(f"cycle {cycle}: {message}")
        self.cycle = cycle
        self.rule = rule


@dataclass(frozen=True)
class ClockTiming:
    """The chip's timing in clocks at one clock frequency (what the checks compare with)."""
    t_rcd: int
    t_rp: int
    t_ras: int
    t_ras_max: int
    t_rc: int
    t_rfc: int
    t_wr: int
    t_mrd: int
    t_ref: int
    power_up: int

    @classmethod
    def of(cls, chip: Chip, clk_freq: float) -> ClockTiming:
        t = chip.timing

        def at_most(seconds):   # maximums round down: the whole clocks that fit
            return math.floor(seconds * clk_freq + 1e-9)

        return cls(
            t_rcd=t.clocks(t.t_rcd, clk_freq), t_rp=t.clocks(t.t_rp, clk_freq),
            t_ras=t.clocks(t.t_ras, clk_freq), t_ras_max=at_most(t.t_ras_max * 1e-9),
            t_rc=t.clocks(t.t_rc, clk_freq), t_rfc=t.clocks(t.t_rfc, clk_freq),
            t_wr=t.clocks(t.t_wr, clk_freq), t_mrd=t.t_mrd_clocks,
            t_ref=at_most(t.t_ref_ms * 1e-3),
            power_up=t.clocks(t.power_up_us * 1e3, clk_freq))


def decode_mode_register(value: int, columns: int) -> tuple[dict, list[str]]:
    """The mode register ``value`` (A9..A0) as a dict, and the reserved fields it uses.

    Keys: ``value``, ``burst_length`` (words; ``columns`` for a full page), ``full_page``,
    ``burst_type`` ("sequential" or "interleaved"), ``cas_latency``, ``operating_mode``,
    ``write_burst`` ("burst" or "single")."""
    problems = []
    code = value & _BURST_LENGTH_MASK
    interleaved = bool(value >> _BURST_TYPE_BIT & 1)
    if code == BurstLength.FULL_PAGE:
        burst_length, full_page = columns, True
        if interleaved:
            problems.append("full-page burst with interleaved burst type is reserved")
    elif code in _FIXED_BURSTS.keys():
        burst_length, full_page = _FIXED_BURSTS[BurstLength(code)], False
    else:
        burst_length, full_page = None, False
        problems.append(f"burst length code {code:03b} is reserved")
    cas_latency = value >> _CAS_LATENCY_SHIFT & _CAS_LATENCY_MASK
    if cas_latency not in _CAS_LATENCIES:
        problems.append(f"CAS latency {cas_latency} is not supported (2 or 3)")
    operating_mode = value >> _OP_MODE_SHIFT & _OP_MODE_MASK
    if operating_mode:
        problems.append(f"operating mode {operating_mode:02b} is reserved (standard is 00)")
    mode = {"value": value, "burst_length": burst_length, "full_page": full_page,
            "burst_type": "interleaved" if interleaved else "sequential",
            "cas_latency": cas_latency, "operating_mode": operating_mode,
            "write_burst": "single" if value >> _WRITE_BURST_BIT & 1 else "burst"}
    return mode, problems


class _Bank:
    __slots__ = ("row", "activated", "precharged", "precharge_cause", "last_write",
                 "auto_precharge", "auto_precharge_at", "ras_max_reported")

    def __init__(self):
        self.row: int | None = None             # open row
        self.activated: int | None = None       # edge of the last ACTIVE
        self.precharged: int | None = None      # edge at which the last precharge began
        self.precharge_cause = "PRECHARGE"      # what began it (for messages)
        self.last_write: int | None = None      # last edge that stored data in the open row
        self.auto_precharge: str | None = None  # "READ"/"WRITE" burst with auto precharge
        self.auto_precharge_at: int | None = None   # edge its precharge begins, once known
        self.ras_max_reported = False


class _Burst:
    __slots__ = ("write", "bank", "row", "column", "length", "interleaved", "index",
                 "auto_precharge", "cas_latency")

    def __init__(self, write, bank, row, column, length, interleaved, auto_precharge,
                 cas_latency):
        self.write = write
        self.bank = bank
        self.row = row
        self.column = column
        self.length = length                # words; None: full page, until interrupted
        self.interleaved = interleaved
        self.auto_precharge = auto_precharge
        self.cas_latency = cas_latency
        self.index = 0                      # next word of the burst


class SdramChip:
    """An SDR SDRAM chip (:class:`~maglog.hw.arch.sdram.Chip` preset) clocked at
    ``clk_freq`` Hz. See the module documentation for the conventions and the checks."""

    def __init__(self, chip: Chip, *, clk_freq: float, strict: bool = True):
        if not isinstance(chip, Chip):
            raise TypeError(f"Chip must be a Chip preset, not {chip!r}")
        if not isinstance(clk_freq, (int, float)) or not clk_freq > 0:
            raise ValueError(f"Clock frequency must be a positive number, not {clk_freq!r}")
        self.chip = chip
        self.clk_freq = clk_freq
        self.strict = strict
        self.timing = ClockTiming.of(chip, clk_freq)
        geometry = chip.geometry
        self._banks_n = geometry.banks
        self._rows = geometry.rows
        self._columns = geometry.columns
        self._data_bits = geometry.data_width
        self._data_mask = (1 << geometry.data_width) - 1
        self._dqm_bits = geometry.data_width // _BYTE_BITS
        self._dqm_all = (1 << self._dqm_bits) - 1
        # Bit masks of the bytes a DQM value masks, for every DQM value.
        self._byte_masks = [
            sum(0xFF << (_BYTE_BITS * n) for n in range(self._dqm_bits) if dqm >> n & 1)
            for dqm in range(1 << self._dqm_bits)]

        #: Violations, as "cycle N: message", when not ``strict``.
        self.errors: list[str] = []
        #: Rising edges seen so far (the number of the next edge).
        self.cycle = 0
        #: Decoded mode register (see :func:`decode_mode_register`); empty until loaded.
        self.mode: dict = {}
        #: Commands registered, by command (NOPs and deselects not counted).
        self.command_counts: dict[Command, int] = {}

        self._storage: dict[int, int] = {}
        self._banks = [_Bank() for _ in range(self._banks_n)]
        self._burst: _Burst | None = None
        self._read_out: dict[int, int] = {}     # edge number -> word edge() returns then
        self._prev_dqm = 0
        self._driving = False                   # the chip drives DQ until the next edge
        self._auto_precharges = 0               # banks with an auto precharge scheduled
        self._ras_deadline = math.inf           # first edge at which a row is open too long
        self._cke_since: int | None = None
        self._cke_low_reported = False
        self._last_refresh: int | None = None
        self._last_load_mode: int | None = None
        # Initialisation: "power-up" (waiting for PRECHARGE ALL), "sequence", "done".
        self._init_state = "power-up"
        self._init_refreshes = 0
        self._init_mode_loaded = False
        # Refresh: edge of the last refresh of each row, the next row to refresh.
        self._row_refreshed: list[int] | None = None
        self._refresh_row = 0
        self._refresh_deadline = math.inf
        self._refresh_reported = False

    # -- storage -------------------------------------------------------------------------------

    def _key(self, bank, row, column):
        return (bank * self._rows + row) * self._columns + column

    def peek(self, bank: int, row: int, column: int) -> int:
        """The stored word (unwritten words read as 0)."""
        return self._storage.get(self._key(bank, row, column), 0)

    def poke(self, bank: int, row: int, column: int, value: int) -> None:
        """Store a word directly (no timing, no checks), e.g. to preload a test pattern."""
        self._storage[self._key(bank, row, column)] = value & self._data_mask

    @property
    def initialised(self) -> bool:
        """The initialisation sequence has completed."""
        return self._init_state == "done"

    @property
    def open_rows(self) -> list[int | None]:
        """The open row of each bank (None: idle or precharging)."""
        return [bank.row for bank in self._banks]

    # -- reporting -----------------------------------------------------------------------------

    def _error(self, rule: str, message: str) -> None:
        error = SdramTimingError(self.cycle, rule, message)
        if self.strict:
            raise error
        self.errors.append(str(error))

    # -- the bus -------------------------------------------------------------------------------

    def edge(self, *, cke, cs_n, ras_n, cas_n, we_n, ba, a, dqm, dq_oe, dq) -> int | None:
        """One rising clock edge with the controller's pin values at that edge (``dq`` is
        what the controller drives when ``dq_oe``, else ignored). Returns the data the chip
        drives on DQ during the following cycle (read data, per CAS latency), or None when it
        does not drive."""
        now = self.cycle
        try:
            if self._cke_since is None:
                if not cke:                 # not powered up yet: nothing is registered
                    return None
                self._cke_since = now
            if cs_n:
                command = Command.NOP
            else:
                command = _COMMANDS[(ras_n & 1) << 2 | (cas_n & 1) << 1 | (we_n & 1)]
            if not cke:
                if not self._cke_low_reported:
                    self._cke_low_reported = True
                    self._error("CKE", "CKE low after power-up (power-down and self "
                                "refresh are not modelled; CKE must stay high)")
                command = Command.NOP
            else:
                self._cke_low_reported = False

            if dq_oe and self._driving:
                self._error("contention", "the controller drives DQ while the chip drives "
                            "read data (bus contention)")

            burst = self._burst
            if burst is not None:
                if (command in (Command.READ, Command.WRITE, Command.BURST_TERMINATE)
                        or command == Command.PRECHARGE and (a >> A10 & 1 or ba == burst.bank)):
                    self._end_burst(burst, now, interrupted=True)
                else:
                    self._burst_step(burst, now, dqm, dq_oe, dq)
            if self._auto_precharges:
                self._begin_auto_precharges(now)
            if now >= self._ras_deadline:
                self._check_ras_max(now)
            if now > self._refresh_deadline and not self._refresh_reported:
                self._refresh_reported = True
                row = self._refresh_row
                late = now - self._row_refreshed[row]
                self._error("refresh interval",
                            f"row {row} not refreshed for {late} clocks (refresh interval: "
                            f"every row within {self.chip.timing.t_ref_ms:g} ms = "
                            f"{self.timing.t_ref} clocks)")

            if command != Command.NOP:
                self._command(now, command, ba, a, dqm, dq_oe, dq)

            out = None
            if self._read_out:
                out = self._read_out.pop(now, None)
                if out is not None and self._prev_dqm:
                    # DQM read latency 2: DQM at edge n - 1 blanks what is sampled at n + 1.
                    out = None if self._prev_dqm == self._dqm_all else \
                        out & ~self._byte_masks[self._prev_dqm]
            self._driving = out is not None
            return out
        finally:
            self._prev_dqm = dqm & self._dqm_all
            self.cycle = now + 1

    # -- commands ------------------------------------------------------------------------------

    def _command(self, now, command, ba, a, dqm, dq_oe, dq):
        t = self.timing
        self.command_counts[command] = self.command_counts.get(command, 0) + 1
        name = command.name
        if self._last_load_mode is not None and now - self._last_load_mode < t.t_mrd:
            self._error("tMRD", f"{name} only {now - self._last_load_mode} clocks after "
                        f"LOAD_MODE (tMRD needs {t.t_mrd})")
        if self._last_refresh is not None and now - self._last_refresh < t.t_rfc:
            self._error("tRFC", f"{name} only {now - self._last_refresh} clocks after REFRESH "
                        f"(tRFC needs {t.t_rfc})")
        if self._init_state != "done":
            self._init_step(now, command, a)

        if command == Command.ACTIVE:
            self._active(now, ba, a & (self._rows - 1))
        elif command in (Command.READ, Command.WRITE):
            self._read_write(now, command, ba, a, dqm, dq_oe, dq)
        elif command == Command.PRECHARGE:
            self._precharge(now, range(self._banks_n) if a >> A10 & 1 else (ba,))
        elif command == Command.REFRESH:
            self._refresh(now)
        elif command == Command.LOAD_MODE:
            self._load_mode(now, a)
        # BURST_TERMINATE: ending the burst (in edge()) is all it does.

    def _init_step(self, now, command, a):
        t = self.timing
        sequence = (f"PRECHARGE ALL, {self.chip.timing.init_refreshes} REFRESH and LOAD_MODE "
                    f"after {self.chip.timing.power_up_us:g} µs of NOP")
        if command in (Command.ACTIVE, Command.READ, Command.WRITE):
            self._error("init sequence", f"{command.name} before the initialisation is "
                        f"complete (init sequence: {sequence})")
            return
        if self._init_state == "power-up":
            if now - self._cke_since < t.power_up:
                self._error("power-up", f"init sequence: {command.name} only "
                            f"{now - self._cke_since} clocks after CKE high (power-up needs "
                            f"{t.power_up} clocks of NOP = {self.chip.timing.power_up_us:g} µs)")
            if command == Command.PRECHARGE and a >> A10 & 1:
                self._init_state = "sequence"
            elif command != Command.BURST_TERMINATE:
                name = "PRECHARGE of one bank" if command == Command.PRECHARGE else command.name
                self._error("init sequence", f"{name} before the first PRECHARGE ALL "
                            f"(init sequence: {sequence})")
            return
        required = self.chip.timing.init_refreshes
        if command == Command.REFRESH:
            self._init_refreshes += 1
        elif command == Command.LOAD_MODE:
            if 0 < self._init_refreshes < required:
                self._error("init sequence", f"LOAD_MODE after {self._init_refreshes} of "
                            f"{required} REFRESH commands (init sequence: the mode register "
                            f"is loaded before or after all of them)")
            self._init_mode_loaded = True
        if self._init_mode_loaded and self._init_refreshes >= required:
            self._init_state = "done"
            self._row_refreshed = [now] * self._rows
            self._refresh_row = 0
            self._refresh_deadline = now + t.t_ref
            self._refresh_reported = False

    def _active(self, now, b, row):
        t = self.timing
        bank = self._banks[b]
        if bank.row is not None:
            if bank.auto_precharge_at is None:
                self._error("open bank", f"ACTIVE to bank {b} which has row {bank.row} open "
                            f"(ACTIVE to an open bank; PRECHARGE it first)")
            else:
                self._active_too_early(now, b, bank)
            self._close(bank, now, "ACTIVE")
        elif bank.precharged is not None and now - bank.precharged < t.t_rp:
            self._active_too_early(now, b, bank)
        if bank.activated is not None and now - bank.activated < t.t_rc:
            self._error("tRC", f"ACTIVE to bank {b} only {now - bank.activated} clocks after "
                        f"the previous ACTIVE (tRC needs {t.t_rc})")
        bank.row = row
        bank.activated = now
        bank.last_write = None
        bank.ras_max_reported = False
        self._ras_deadline = min(self._ras_deadline, now + t.t_ras_max + 1)

    def _active_too_early(self, now, b, bank):
        """ACTIVE before the bank's (auto) precharge has had tRP."""
        t = self.timing
        if bank.precharge_cause == "WRITE" and bank.last_write is not None:
            self._error("tWR", f"ACTIVE to bank {b} only {now - bank.last_write} clocks after "
                        f"the last data of a WRITE with auto precharge (tWR + tRP needs "
                        f"{t.t_wr} + {t.t_rp})")
        elif bank.row is not None:
            self._error("tRP", f"ACTIVE to bank {b} before its auto precharge begins at cycle "
                        f"{bank.auto_precharge_at} (tRP needs {t.t_rp} after it)")
        else:
            cause = ("PRECHARGE" if bank.precharge_cause == "PRECHARGE"
                     else "its auto precharge began")
            self._error("tRP", f"ACTIVE to bank {b} only {now - bank.precharged} clocks after "
                        f"{cause} (tRP needs {t.t_rp})")

    def _read_write(self, now, command, b, a, dqm, dq_oe, dq):
        t = self.timing
        write = command == Command.WRITE
        name = command.name
        bank = self._banks[b]
        auto_precharge = bool(a >> A10 & 1)
        if bank.row is None or bank.auto_precharge is not None:
            state = "no open row" if bank.row is None else "its auto precharge under way"
            self._error("closed row", f"{name} to bank {b} with {state} (access to a closed "
                        f"row; ACTIVE it first)")
            return
        if now - bank.activated < t.t_rcd:
            self._error("tRCD", f"{name} to bank {b} only {now - bank.activated} clocks after "
                        f"ACTIVE (tRCD needs {t.t_rcd})")
        if not self.mode:
            self._error("init sequence", f"{name} before a mode register is loaded (ignored)")
            return
        mode = self.mode
        if write and mode["write_burst"] == "single":
            length = 1
        else:
            length = None if mode["full_page"] else mode["burst_length"]
        if auto_precharge and length is None:
            self._error("auto precharge", f"{name} with auto precharge and a full-page burst "
                        f"(auto precharge is not allowed with full-page bursts; ignored)")
            auto_precharge = False
        if write:
            # DQ turn to inputs: read data not yet on the bus is dropped.
            for edge in [edge for edge in self._read_out if edge >= now]:
                del self._read_out[edge]
        if auto_precharge:
            bank.auto_precharge = name
            bank.auto_precharge_at = None
        burst = _Burst(write, b, bank.row, a & (self._columns - 1),
                       length, mode["burst_type"] == "interleaved", auto_precharge,
                       mode["cas_latency"])
        self._burst = burst
        self._burst_step(burst, now, dqm, dq_oe, dq)

    def _burst_step(self, burst, now, dqm, dq_oe, dq):
        """The burst's next column access at edge ``now``."""
        i = burst.index
        if burst.length is None:
            column = (burst.column + i) % self._columns
        else:
            block = burst.length - 1
            if burst.interleaved:
                column = (burst.column & ~block) | ((burst.column & block) ^ i)
            else:
                column = (burst.column & ~block) | ((burst.column + i) & block)
        key = self._key(burst.bank, burst.row, column)
        if burst.write:
            dqm &= self._dqm_all
            if dqm != self._dqm_all:
                if not dq_oe:
                    self._error("write data", f"write data for bank {burst.bank} column "
                                f"{column} not driven in a WRITE burst (DQ released, DQM "
                                f"{dqm:#b} leaves bytes unmasked; nothing stored)")
                else:
                    masked = self._byte_masks[dqm]
                    old = self._storage.get(key, 0)
                    self._storage[key] = (old & masked) | (dq & self._data_mask & ~masked)
                    self._banks[burst.bank].last_write = now
        else:
            self._read_out[now + burst.cas_latency - 1] = self._storage.get(key, 0)
        burst.index = i + 1
        if burst.length is not None and burst.index == burst.length:
            self._end_burst(burst, now + 1, interrupted=False)

    def _end_burst(self, burst, end, *, interrupted):
        """The burst makes no column access from edge ``end`` on."""
        self._burst = None
        if not burst.auto_precharge:
            return
        t = self.timing
        bank = self._banks[burst.bank]
        if bank.auto_precharge is None:     # an explicit PRECHARGE took over
            return
        if burst.write:
            # Micron: tWR from the last data, or from the command that interrupts the burst.
            begin = (end if interrupted else end - 1) + t.t_wr
        else:
            begin = end
        cause = burst.write and "WRITE" or "READ"
        ras_lockout = bank.activated + t.t_ras
        if ras_lockout > begin:
            begin, cause = ras_lockout, "tRAS lockout"
        bank.auto_precharge_at = begin
        bank.precharge_cause = cause
        self._auto_precharges += 1

    def _begin_auto_precharges(self, now):
        for bank in self._banks:
            if bank.auto_precharge_at is not None and bank.auto_precharge_at <= now:
                begin, cause = bank.auto_precharge_at, bank.precharge_cause
                last_write = bank.last_write
                self._close(bank, begin, cause)
                bank.last_write = last_write    # for the tWR message on an early ACTIVE

    def _close(self, bank, begin, cause):
        if bank.auto_precharge_at is not None:
            self._auto_precharges -= 1
        bank.row = None
        bank.precharged = begin
        bank.precharge_cause = cause
        bank.auto_precharge = None
        bank.auto_precharge_at = None
        bank.last_write = None

    def _precharge(self, now, banks):
        t = self.timing
        for b in banks:
            bank = self._banks[b]
            if bank.row is None:
                continue        # a NOP for an idle or precharging bank
            if bank.auto_precharge is None:
                if now - bank.activated < t.t_ras:
                    self._error("tRAS min", f"PRECHARGE to bank {b} only "
                                f"{now - bank.activated} clocks after ACTIVE (tRAS min needs "
                                f"{t.t_ras})")
                if bank.last_write is not None and now - bank.last_write < t.t_wr:
                    self._error("tWR", f"PRECHARGE to bank {b} only {now - bank.last_write} "
                                f"clocks after the last write data (tWR needs {t.t_wr})")
            self._close(bank, now, "PRECHARGE")
        self._update_ras_deadline()

    def _idle_check(self, now, command, rule, needs):
        t = self.timing
        for b, bank in enumerate(self._banks):
            if bank.row is not None:
                self._error(rule, f"{command} with bank {b} open (row {bank.row}; {command} "
                            f"needs {needs})")
            elif bank.precharged is not None and now - bank.precharged < t.t_rp:
                self._error("tRP", f"{command} only {now - bank.precharged} clocks after the "
                            f"precharge of bank {b} began (tRP needs {t.t_rp})")

    def _refresh(self, now):
        self._idle_check(now, "REFRESH", "all banks precharged", "all banks precharged")
        self._last_refresh = now
        if self._row_refreshed is not None:
            rows = self._row_refreshed
            rows[self._refresh_row] = now
            self._refresh_row = row = (self._refresh_row + 1) % self._rows
            self._refresh_deadline = rows[row] + self.timing.t_ref
            if now <= self._refresh_deadline:
                self._refresh_reported = False

    def _load_mode(self, now, a):
        self._idle_check(now, "LOAD_MODE", "all banks idle", "all banks idle")
        self._last_load_mode = now
        mode, problems = decode_mode_register(a, self._columns)
        if problems:
            self._error("mode register", f"LOAD_MODE {a:#x}: {'; '.join(problems)} "
                        f"(mode register unchanged)")
        else:
            self.mode = mode

    def _check_ras_max(self, now):
        t = self.timing
        for b, bank in enumerate(self._banks):
            if (bank.row is not None and not bank.ras_max_reported
                    and now - bank.activated > t.t_ras_max):
                bank.ras_max_reported = True
                self._error("tRAS max", f"bank {b} open for {now - bank.activated} clocks "
                            f"since ACTIVE (tRAS max allows {t.t_ras_max})")
        self._update_ras_deadline()

    def _update_ras_deadline(self):
        t = self.timing
        self._ras_deadline = min(
            (bank.activated + t.t_ras_max + 1 for bank in self._banks
             if bank.row is not None and not bank.ras_max_reported), default=math.inf)
