"""Mutation run of ``maglog calibrate`` and ``maglog survey``: its counts as JSON.

Runs the seeded inputs of ``tests/calib/mutants.py`` (card images, logs, truth and
base-station files and option values mutated as a new user would meet them) through
``maglog.cli.main.main`` in process, one worker per core with a time limit per input, and
writes the outcomes by class to ``bench/results/calib_mutation.json``: inputs, tracebacks,
hangs, silent nonsense (the goal is 0, 0, 0), clean errors, usage errors, results with and
without warnings, and every failure with its input; the survey inputs' counts also apart
(``survey_inputs``, ``survey_counts``).

The defaults are the slow test's run (``tests/calib/test_mutation.py``, 1,210 calibrate and
420 survey inputs, seed 20); ``--inputs 55 --survey 6 --seed 10`` is the default suite's
short one.

Run from the repository root: ``.venv/bin/python bench/calib/mutation.py``.
"""

import argparse
import sys
import time
from collections import Counter
from pathlib import Path

BENCH = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(BENCH))
sys.path.insert(0, str(BENCH.parent / "tests" / "calib"))

from _machine import command_version, load, packages, write_report

import cards
import mutants

DEFAULT_OUTPUT = BENCH / "results" / "calib_mutation.json"


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--inputs", type=int, default=1210, help="inputs (default: 1210)")
    parser.add_argument("--survey", type=int, default=420,
                        help="maglog survey inputs after the calibrate ones (default: 420)")
    parser.add_argument("--seed", type=int, default=20, help="run seed (default: 20)")
    parser.add_argument("--processes", type=int, default=None,
                        help="worker processes (default: up to 2)")
    parser.add_argument("--time-limit", type=int, default=mutants.TIME_LIMIT,
                        help="seconds per input before it counts as a hang "
                             "(default: %(default)s)")
    parser.add_argument("--output", type=Path, default=DEFAULT_OUTPUT,
                        help="JSON file (default: bench/results/calib_mutation.json)")
    args = parser.parse_args(argv)

    load_start = load()
    start = time.perf_counter()
    done = Counter()

    def progress(result):
        done[result["outcome"]] += 1
        if result["outcome"] in mutants.FAILURES:
            print(f"#{result['index']} {result['kind']} {result['outcome']}: "
                  f"{result['detail']} -> {result['reason']}", file=sys.stderr)
        if sum(done.values()) % 100 == 0:
            print(f"{sum(done.values())}/{args.inputs + args.survey}: {dict(done)}",
                  file=sys.stderr)

    results, with_images = mutants.run(args.inputs, seed=args.seed, tools=cards.find_fat_tools(),
                                       processes=args.processes, time_limit=args.time_limit,
                                       progress=progress, survey=args.survey)
    seconds = time.perf_counter() - start
    totals, by_class = mutants.counts(results)
    survey = [r for r in results if mutants.is_survey(r)]
    survey_totals, _ = mutants.counts(survey)
    calibrate_totals, _ = mutants.counts([r for r in results if not mutants.is_survey(r)])
    examples = {}
    for result in results:
        examples.setdefault(result["outcome"], [])
        if len(examples[result["outcome"]]) < 5:
            examples[result["outcome"]].append(
                {k: result[k] for k in ("index", "kind", "detail", "reason")})
    tools = packages("numpy", "scipy", "numba", "matplotlib", "markdown", "html5lib", "ppigrf",
                     "verde", "harmonica", "dask", "distributed")
    tools["mkfs.fat"] = command_version("mkfs.fat", "--help") if with_images else None
    write_report(args.output, "calib_mutation", argv, load_start, tools,
                 inputs=len(results), seed=args.seed, images=with_images,
                 time_limit_s=args.time_limit, seconds=round(seconds, 1),
                 counts=totals, failures_total=sum(totals[o] for o in mutants.FAILURES),
                 calibrate_inputs=len(results) - len(survey), calibrate_counts=calibrate_totals,
                 survey_inputs=len(survey), survey_counts=survey_totals,
                 survey_seconds=round(sum(r.get("seconds", 0) for r in survey), 1),
                 by_class=by_class, failures=mutants.failures(results),
                 examples=examples,
                 slowest=sorted(results, key=lambda r: -r.get("seconds", 0))[:5])
    print(f"{len(results)} inputs in {seconds:.0f} s: {totals}")
    print(f"  calibrate: {len(results) - len(survey)} inputs: {calibrate_totals}")
    print(f"  survey: {len(survey)} inputs: {survey_totals}")
    for kind, row in by_class.items():
        print(f"  {kind:16s} {row}")
    return 1 if any(totals[o] for o in mutants.FAILURES) else 0


if __name__ == "__main__":
    sys.exit(main())
