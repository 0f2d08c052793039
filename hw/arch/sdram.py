"""SDR SDRAM: commands, mode register and the chips the logger's boards carry.

# Ref: JEDEC JESD21-C §3.11.5 (SDR SDRAM commands: CS#, RAS#, CAS#, WE# truth table) and the
#      chips' data sheets: Micron MT48LC4M32B2 (128 Mb, x32, "4 Meg x 32"), -7 speed grade;
#      ISSI IS42S16160 (256 Mb, x16, "16M x 16"), -7 speed grade.
"""

import enum
import math
from dataclasses import dataclass


__all__ = ["Command", "Geometry", "Timing", "Chip", "MT48LC4M32B2", "IS42S16160",
           "mode_register", "BurstLength"]


class Command(enum.IntEnum):
    """Commands as the 3-bit value {RAS#, CAS#, WE#} with CS# low.

    Ref: MT48LC4M32B2 data sheet, "Truth Table 1 – Commands and DQM Operation".
    """
    LOAD_MODE    = 0b000
    REFRESH      = 0b001    # auto refresh (CKE high)
    PRECHARGE    = 0b010    # A10 high: all banks
    ACTIVE       = 0b011
    WRITE        = 0b100    # A10 high: with auto precharge
    READ         = 0b101
    BURST_TERMINATE = 0b110
    NOP          = 0b111


#: Address bit that selects "all banks" (PRECHARGE) or auto precharge (READ, WRITE).
A10 = 10


class BurstLength(enum.IntEnum):
    """Mode register A2..A0. Ref: data sheets, "Mode Register Definition"."""
    ONE  = 0b000
    TWO  = 0b001
    FOUR = 0b010
    EIGHT = 0b011
    FULL_PAGE = 0b111


def mode_register(*, cas_latency, burst_length=BurstLength.ONE, single_write=False):
    """The mode register value: burst length (A2..A0), sequential bursts (A3 = 0), CAS
    latency (A6..A4), standard operation (A8..A7 = 0), write burst mode (A9)."""
    if cas_latency not in (2, 3):
        raise ValueError(f"CAS latency must be 2 or 3, not {cas_latency!r}")
    return int(burst_length) | (cas_latency << 4) | (int(single_write) << 9)


@dataclass(frozen=True)
class Geometry:
    """Banks, rows, columns and data width of a chip."""
    banks: int
    rows: int
    columns: int
    data_width: int

    @property
    def bank_bits(self):
        return (self.banks - 1).bit_length()

    @property
    def row_bits(self):
        return (self.rows - 1).bit_length()

    @property
    def column_bits(self):
        return (self.columns - 1).bit_length()

    @property
    def address_bits(self):
        """Width of the A bus: rows need all of it (columns use fewer, A10 apart)."""
        return max(self.row_bits, A10 + 1)

    @property
    def words(self):
        return self.banks * self.rows * self.columns

    @property
    def word_address_bits(self):
        return self.bank_bits + self.row_bits + self.column_bits


@dataclass(frozen=True)
class Timing:
    """Timing in nanoseconds (and clocks where the data sheet gives clocks)."""
    t_rcd: float          # ACTIVE to READ/WRITE
    t_rp: float           # PRECHARGE to next command in the bank
    t_ras: float          # ACTIVE to PRECHARGE (minimum)
    t_ras_max: float      # ACTIVE to PRECHARGE (maximum)
    t_rc: float           # ACTIVE to ACTIVE in the same bank
    t_rfc: float          # REFRESH to next command
    t_wr: float           # last write data to PRECHARGE
    t_mrd_clocks: int     # LOAD MODE to next command, in clocks
    t_ref_ms: float       # every row refreshed within this period
    power_up_us: float    # stable clock, CKE high, NOPs before the first PRECHARGE
    init_refreshes: int   # auto refreshes in the initialisation

    def clocks(self, ns, clk_freq):
        """Whole clocks that cover ``ns`` at ``clk_freq`` (at least 1)."""
        return max(1, math.ceil(ns * 1e-9 * clk_freq - 1e-9))


@dataclass(frozen=True)
class Chip:
    name: str
    geometry: Geometry
    timing: Timing

    def refresh_interval_clocks(self, clk_freq):
        """Clocks between auto refreshes so that every row is refreshed in time."""
        return math.floor(self.timing.t_ref_ms * 1e-3 / self.geometry.rows * clk_freq)


# Ref: Micron MT48LC4M32B2 data sheet, -7 speed grade (143 MHz, CL3; 100 MHz at CL2):
#      tRCD 20 ns, tRP 20 ns, tRAS 42 ns .. 120 µs, tRC 70 ns, tRFC 70 ns, tWR 1 CLK + 7 ns
#      (14 ns), tMRD 2 CLK, 64 ms / 4,096 rows; 100 µs power-up, 2 auto refreshes.
MT48LC4M32B2 = Chip(
    "MT48LC4M32B2",
    Geometry(banks=4, rows=4096, columns=256, data_width=32),
    Timing(t_rcd=20, t_rp=20, t_ras=42, t_ras_max=120_000, t_rc=70, t_rfc=70, t_wr=14,
           t_mrd_clocks=2, t_ref_ms=64, power_up_us=100, init_refreshes=2),
)

# Ref: ISSI IS42S16160 data sheet, -7 speed grade (143 MHz, CL3): tRCD 20 ns, tRP 20 ns,
#      tRAS 42 ns .. 100 µs, tRC 63 ns, tRFC 63 ns, tWR 14 ns, tMRD 2 CLK, 64 ms / 8,192
#      rows; 200 µs power-up, 8 auto refreshes.
IS42S16160 = Chip(
    "IS42S16160",
    Geometry(banks=4, rows=8192, columns=512, data_width=16),
    Timing(t_rcd=20, t_rp=20, t_ras=42, t_ras_max=100_000, t_rc=63, t_rfc=63, t_wr=14,
           t_mrd_clocks=2, t_ref_ms=64, power_up_us=200, init_refreshes=8),
)

CHIPS = {chip.name: chip for chip in (MT48LC4M32B2, IS42S16160)}
