"""Mutation run of the surfaces issue 23's fuzz reached first: its counts as JSON.

Runs the seeded inputs of ``tests/cli/mutants_surfaces.py`` (scenario TOML files through
``maglog simulate --backend model --max-seconds 40``, calibration flights through ``maglog
run --backend model``, ``card format``, ``hdl`` verilog /
regmap / build / component, ``replay`` and ``record`` on ``loop://`` ports) through
``maglog.cli.main.main`` in process, one worker per core with a time and address-space limit
per input, and writes the outcomes by class to ``bench/results/surfaces_mutation.json``:
inputs, tracebacks, hangs, out-of-memory, silent nonsense (the goal is 0 of each), clean
errors, usage errors, results, and every failure with its input.

The defaults are the slow test's run (``tests/cli/test_surfaces_mutation.py``, 720 inputs,
seed 20); ``--inputs 60 --seed 10`` is the default suite's short one.

Run from the repository root: ``.venv/bin/python bench/cli/surfaces_mutation.py``.
"""

import argparse
import sys
import time
from pathlib import Path

BENCH = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(BENCH))
sys.path.insert(0, str(BENCH.parent / "tests" / "cli"))

from _machine import load, packages, write_report

import mutants_surfaces as mutants

DEFAULT_OUTPUT = BENCH / "results" / "surfaces_mutation.json"


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--inputs", type=int, default=720, help="inputs (default: 720)")
    parser.add_argument("--seed", type=int, default=20, help="run seed (default: 20)")
    parser.add_argument("--processes", type=int, default=None,
                        help="worker processes (default: up to 2)")
    parser.add_argument("--time-limit", type=int, default=mutants.TIME_LIMIT,
                        help="seconds per input before it counts as a hang "
                             "(default: %(default)s)")
    parser.add_argument("--output", type=Path, default=DEFAULT_OUTPUT,
                        help="JSON file (default: bench/results/surfaces_mutation.json)")
    args = parser.parse_args(argv)

    load_start = load()
    start = time.perf_counter()
    done = {}

    def progress(result):
        done[result["outcome"]] = done.get(result["outcome"], 0) + 1
        if result["outcome"] in mutants.FAILURES:
            print(f"#{result['index']} {result['kind']} {result['outcome']}: "
                  f"{result['detail']} -> {result['reason']}", file=sys.stderr)
        if sum(done.values()) % 100 == 0:
            print(f"{sum(done.values())}/{args.inputs}: {done}", file=sys.stderr)

    results = mutants.run(args.inputs, seed=args.seed, processes=args.processes,
                          time_limit=args.time_limit, progress=progress)
    seconds = time.perf_counter() - start
    totals, by_class = mutants.counts(results)
    examples = {}
    for result in results:
        examples.setdefault(result["outcome"], [])
        if len(examples[result["outcome"]]) < 5:
            examples[result["outcome"]].append(
                {k: result[k] for k in ("index", "kind", "detail", "reason")})
    tools = packages("numpy", "amaranth", "pyserial", "harmonica")
    write_report(args.output, "surfaces_mutation", argv, load_start, tools,
                 inputs=len(results), seed=args.seed, time_limit_s=args.time_limit,
                 memory_limit_bytes=mutants.MEMORY_LIMIT, max_seconds=mutants.MAX_SECONDS,
                 seconds=round(seconds, 1), counts=totals,
                 failures_total=sum(totals[o] for o in mutants.FAILURES),
                 by_class=by_class, failures=mutants.failures(results), examples=examples,
                 slowest=sorted(results, key=lambda r: -r.get("seconds", 0))[:5])
    print(f"{len(results)} inputs in {seconds:.0f} s: {totals}")
    for kind, row in by_class.items():
        print(f"  {kind:20s} {row}")
    return 1 if any(totals[o] for o in mutants.FAILURES) else 0


if __name__ == "__main__":
    sys.exit(main())
