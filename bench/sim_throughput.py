"""Simulation speed of one serial channel on the three simulation backends.

One `$PMAG1` channel (``FrontEnd`` with a single PMAG channel: UART receiver, frame filter
with its FIFO, arbiter) is run through the project's own runner,
:class:`maglog.sim.runners.frontend.FrontEndBench`, on a stream of valid ``$PMAG1`` sentences
sent back to back at divisor 1 (16 clock cycles per bit). Every kept frame is checked
against the sent sentences, so a fast but wrong run does not count.

Build time (Verilog generation and compilation, cocotb backends only) is measured apart from
run time. A run's time covers everything :meth:`FrontEndBench.run` does: for Amaranth the
elaboration and the simulation, for cocotb starting the simulator process, cocotb, the
simulation and reading the result. Each backend first runs a short probe, then a run sized
to last about ``--target-seconds``; the two give a straight-line fit, run time = fixed
overhead + cycles / steady-state rate.

Run: ``.venv/bin/python bench/sim_throughput.py`` (``--help`` for options).
"""

import argparse
import math
import os
import random
import sys
import time
from pathlib import Path

from maglog.hw.arch import uart as arch_uart
from maglog.hw.frame_filter import ChannelKind
from maglog.hw.frontend import ChannelConfig
from maglog.sim.runners.frontend import BACKENDS, CLOCK_NS, FrontEndBench
from maglog.sim.stimulus.uart_line import ChannelStimulus
from maglog.sim.stimulus.sentences import pmag1

# The helper beside this script: no __pycache__ in the tree for it.
sys.dont_write_bytecode = True
from _machine import command_version, load, packages, scratch_dir, write_report


BENCH_DIR = Path(__file__).resolve().parent
DEFAULT_OUTPUT = BENCH_DIR / "results" / "sim_throughput.json"

CHANNEL = ChannelConfig(ChannelKind.PMAG, 115200)
#: Sentences of the first (probe) run of each backend at divisor 1: about a second each
#: (fewer at larger divisors).
PROBE_SENTENCES = {"amaranth": 5, "icarus": 20, "verilator": 50}
#: Bits on the wire per character (8N1).
CHARACTER_BITS = arch_uart.CHARACTER_BITS
#: Magnetometer field components: a plausible survey range, in nT.
FIELD_RANGE_NT = 65_000.0
MAX_SIZING_RUNS = 4


def sentences(count, seed):
    """``count`` valid ``$PMAG1`` sentences with seeded random field values."""
    rng = random.Random(seed)
    return [pmag1(seq, *(round(rng.uniform(-FIELD_RANGE_NT, FIELD_RANGE_NT), 1)
                         for _ in range(3)))
            for seq in range(count)]


def run_once(bench, count, divisor, seed):
    frames = sentences(count, seed)
    result = bench.run([ChannelStimulus(divisor=divisor, data=b"".join(frames),
                                        expected=frames)])
    kept = result.counters[0]["kept"] if result.counters else None
    if result.mismatches or kept != count or len(result.frames) != count:
        raise RuntimeError(f"{bench.backend}: wrong result for {count} sentences: kept "
                           f"{kept}, {len(result.frames)} frames out, mismatches "
                           f"{result.mismatches[:3]}")
    return {
        "sentences": count,
        "bytes": sum(map(len, frames)),
        "cycles": result.cycles,
        "seconds": round(result.seconds, 3),
        "cycles_per_second": round(result.cycles / result.seconds),
    }


def fit(runs):
    """(overhead seconds, steady-state cycles/s) through the last two runs, or None."""
    a, b = runs[-2], runs[-1]
    if b["cycles"] == a["cycles"] or b["seconds"] <= a["seconds"]:
        return None
    rate = (b["cycles"] - a["cycles"]) / (b["seconds"] - a["seconds"])
    return max(0.0, a["seconds"] - a["cycles"] / rate), rate


def measure(backend, build_dir, args):
    bench = FrontEndBench(channels=[CHANNEL], backend=backend, build_dir=build_dir)
    start = time.perf_counter()
    bench.build()
    build_seconds = time.perf_counter() - start

    cycles_per_sentence = None
    runs = []
    count = max(1, round(PROBE_SENTENCES[backend] / args.divisor))
    for _ in range(MAX_SIZING_RUNS):
        print(f"  {backend}: {count} sentences ...", file=sys.stderr, flush=True)
        runs.append(run_once(bench, count, args.divisor, args.seed))
        last = runs[-1]
        cycles_per_sentence = last["bytes"] / count * CHARACTER_BITS * \
            arch_uart.OVERSAMPLING * args.divisor
        if len(runs) > 1 and (last["seconds"] >= args.min_seconds or
                              count >= args.max_sentences or args.sentences is not None):
            break
        if args.sentences is not None:
            count = args.sentences
            continue
        # Size the next run for the target from what the runs so far showed.
        estimate = fit(runs) if len(runs) > 1 else None
        overhead, rate = estimate if estimate else (0.0, last["cycles"] / last["seconds"])
        wanted = math.ceil(max(0.0, args.target_seconds - overhead) * rate /
                           cycles_per_sentence)
        count = min(args.max_sentences, max(wanted, count * 2))

    main = runs[-1]
    estimate = fit(runs)
    return {
        "backend": backend,
        "build_seconds": round(build_seconds, 3),
        "runs": runs,
        "main": main,
        "overhead_seconds": round(estimate[0], 3) if estimate else None,
        "steady_cycles_per_second": round(estimate[1]) if estimate else None,
        "slowdown_vs_hardware": round(1e9 / CLOCK_NS / main["cycles_per_second"]),
    }


def table(results):
    head = (f"{'backend':<10} {'build s':>8} {'sentences':>9} {'cycles':>10} {'run s':>7} "
            f"{'cycles/s':>9} {'steady c/s':>10} {'overhead s':>10} {'x slower':>9}")
    lines = [head, "-" * len(head)]
    for r in results:
        m = r["main"]
        steady = r["steady_cycles_per_second"]
        overhead = r["overhead_seconds"]
        lines.append(f"{r['backend']:<10} {r['build_seconds']:>8.2f} {m['sentences']:>9} "
                     f"{m['cycles']:>10} {m['seconds']:>7.2f} {m['cycles_per_second']:>9} "
                     f"{steady if steady is not None else '-':>10} "
                     f"{overhead if overhead is not None else '-':>10} "
                     f"{r['slowdown_vs_hardware']:>9}")
    return "\n".join(lines)


def main(argv=None):
    parser = argparse.ArgumentParser(
        description="Clock cycles per second of one $PMAG1 channel (UART receiver, frame "
                    "filter, FIFO, arbiter) on the Amaranth simulator, cocotb+Icarus and "
                    "cocotb+Verilator, through maglog.sim.runners.frontend.FrontEndBench.")
    parser.add_argument("--backends", nargs="+", choices=BACKENDS, default=list(BACKENDS),
                        help="backends to measure (default: all)")
    parser.add_argument("--target-seconds", type=float, default=10.0,
                        help="wall time to size each backend's main run for (default: 10)")
    parser.add_argument("--min-seconds", type=float, default=5.0,
                        help="a main run shorter than this is repeated larger (default: 5)")
    parser.add_argument("--sentences", type=int, default=None,
                        help="fixed sentence count of the main run (no sizing)")
    parser.add_argument("--max-sentences", type=int, default=20000,
                        help="upper bound of a run's sentence count (default: 20000)")
    parser.add_argument("--divisor", type=int, default=1,
                        help="UART divisor: clock cycles per oversampling tick (default: 1)")
    parser.add_argument("--seed", type=int, default=1, help="field value seed (default: 1)")
    parser.add_argument("--output", type=Path, default=DEFAULT_OUTPUT,
                        help=f"result JSON (default: "
                             f"{DEFAULT_OUTPUT.relative_to(BENCH_DIR.parent)})")
    parser.add_argument("--keep", action="store_true",
                        help="keep the temporary build directories and print their path")
    args = parser.parse_args(argv)
    if args.divisor < 1:
        parser.error(f"Divisor must be a positive integer, not {args.divisor!r}")

    # The cocotb runner finds `verilator` and `iverilog` on PATH, and Verilator's makefiles
    # need `python`: the venv's bin comes first.
    venv_bin = str(Path(sys.executable).parent)
    os.environ["PATH"] = venv_bin + os.pathsep + os.environ.get("PATH", "")

    load_start = load()
    results = []
    with scratch_dir("maglog-simspeed-", args.keep) as workdir:
        for backend in args.backends:
            print(f"{backend}:", file=sys.stderr, flush=True)
            results.append(measure(backend, workdir / backend, args))

    print(table(results))
    write_report(
        args.output, "sim_throughput", argv, load_start,
        {**packages("amaranth", "cocotb", "cocotbext-uart", "verilator"),
         "iverilog": command_version("iverilog", "-V")},
        design=f"FrontEnd([ChannelConfig(ChannelKind.{CHANNEL.kind.name}, {CHANNEL.baud})])",
        stimulus=f"valid $PMAG1 sentences back to back, divisor {args.divisor} "
                 f"({arch_uart.OVERSAMPLING * args.divisor} cycles per bit), seed {args.seed}",
        clock_ns=CLOCK_NS, results=results)
    return 0


if __name__ == "__main__":
    sys.exit(main())
