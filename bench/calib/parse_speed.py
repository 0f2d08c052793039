"""Log parsing speed: ``maglog.calib.logparse.parse_log`` from log text to parsed arrays.

Two logs of the UAV flight of bench/calib/run.py's one-hour run: the hour itself
(``make_flight(coverage="uav", seconds=3600, rate=50, seed=9).log(mag_rate=50)``, 180,000
magnetometer samples) and the same flight over ten hours (``seconds=36000``, 1,800,000
samples; the sequence counter wraps 18 times). Each is parsed ``--repeats`` times from its
bytes in memory (reading the file is not timed): the wall and CPU time of every repeat, best,
median and worst, megabytes and lines per second, and the ten-hour time over ten times the
hour's (1.0: linear in size).

Beside them, ``--reference-repeats`` times on the hour, the per-line reader every line went
through before the bulk reading (``logparse._parse(..., per_line=True)``), and a check that
both readings give identical results (every array bit for bit, every list, report and
message).

Everything runs on one thread: the numpy operations of the parser do not thread (the BLAS
and OpenMP thread variables are recorded anyway).

Goals (issue 13): the hour well under 0.3 s, ten hours about 3 s or less, both on one thread.

Run from the repository root: ``.venv/bin/python bench/calib/parse_speed.py`` (``--help``).
"""

import argparse
import dataclasses
import math
import os
import statistics
import sys
import time
from pathlib import Path

import numpy as np

BENCH = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(BENCH))

from _machine import load, packages, write_report

from maglog.calib import logparse
from maglog.sim.stimulus.scenario import make_flight

DEFAULT_OUTPUT = BENCH / "results" / "calib_parse.json"
#: The flight of bench/calib/run.py's hour_flight.
FLIGHT = {"coverage": "uav", "rate": 50, "seed": 9}
MAG_RATE = 50
GOAL_HOUR_SECONDS = 0.3
GOAL_TEN_HOURS_SECONDS = 3.0
THREAD_VARIABLES = ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS",
                    "NUMBA_NUM_THREADS")


def summary(seconds):
    """Best, median and worst of repeats, with every repeat."""
    return {"repeats": len(seconds), "best": min(seconds),
            "median": statistics.median(seconds), "worst": max(seconds),
            "all": list(seconds)}


def flight_log(hours):
    started = time.perf_counter()
    data = make_flight(seconds=3600 * hours, **FLIGHT).log(mag_rate=MAG_RATE)
    print(f"{hours} h log: {len(data):,} bytes, made in {time.perf_counter() - started:.1f} s")
    return data


def time_parse(data, repeats, parse=logparse.parse_log):
    """(last result, wall seconds of every repeat, CPU seconds of every repeat)."""
    wall, cpu = [], []
    for _ in range(repeats):
        w0, c0 = time.perf_counter(), time.process_time()
        parsed = parse(data)
        cpu.append(time.process_time() - c0)
        wall.append(time.perf_counter() - w0)
    return parsed, wall, cpu


def differences(fast, slow, where="parsed"):
    """Where two parse results differ (empty: identical; arrays compared bit for bit)."""
    if dataclasses.is_dataclass(fast):
        return [found for member in dataclasses.fields(fast)
                for found in differences(getattr(fast, member.name),
                                         getattr(slow, member.name), f"{where}.{member.name}")]
    if isinstance(fast, np.ndarray):
        same = (isinstance(slow, np.ndarray) and fast.dtype == slow.dtype
                and fast.shape == slow.shape and fast.tobytes() == slow.tobytes())
        return [] if same else [where]
    if isinstance(fast, (list, tuple, dict)):
        if type(fast) is not type(slow) or len(fast) != len(slow):
            return [where]
        if isinstance(fast, dict):
            if list(fast) != list(slow):
                return [where]
            return [found for key in fast
                    for found in differences(fast[key], slow[key], f"{where}[{key!r}]")]
        return [found for index, (one, other) in enumerate(zip(fast, slow))
                for found in differences(one, other, f"{where}[{index}]")]
    if isinstance(fast, float) and math.isnan(fast):
        return [] if isinstance(slow, float) and math.isnan(slow) else [where]
    return [] if type(fast) is type(slow) and fast == slow else [where]


def measure(name, data, repeats):
    parsed, wall, cpu = time_parse(data, repeats)
    report = parsed.report
    out = {"log_bytes": len(data), "lines": report.lines, "samples": len(parsed.mag),
           "counts": report.counts, "bad_lines": sum(report.bad.values()),
           "mag_timing": report.mag_timing, "wall": summary(wall), "cpu": summary(cpu),
           "megabytes_per_second_best": len(data) / min(wall) / 1e6,
           "lines_per_second_best": report.lines / min(wall)}
    print(f"{name}: {out['samples']:,} samples, {report.lines:,} lines: best "
          f"{min(wall):.3f} s, median {statistics.median(wall):.3f} s, worst "
          f"{max(wall):.3f} s wall (CPU best {min(cpu):.3f} s); "
          f"{out['megabytes_per_second_best']:.0f} MB/s")
    return parsed, out


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeats", type=int, default=7,
                        help="repeats of each timed parse (default: %(default)s)")
    parser.add_argument("--reference-repeats", type=int, default=2,
                        help="repeats of the per-line reference on the hour "
                             "(default: %(default)s)")
    parser.add_argument("--long-hours", type=int, default=10,
                        help="length of the long log in hours (default: %(default)s)")
    parser.add_argument("--output", type=Path, default=DEFAULT_OUTPUT)
    args = parser.parse_args(argv)
    if args.repeats < 1 or args.reference_repeats < 1 or args.long_hours < 1:
        parser.error("repeats and hours must be at least 1")
    load_start = load()
    hour = flight_log(1)
    logparse.parse_log(hour[: 1 << 16])                  # imports, first calls
    parsed, one_hour = measure("1 h", hour, args.repeats)

    reference, wall, cpu = time_parse(
        hour, args.reference_repeats,
        lambda data: logparse._parse(data, "log", 0.0, per_line=True))
    differ = differences(parsed, reference)
    per_line = {"wall": summary(wall), "cpu": summary(cpu),
                "speedup_best": min(wall) / one_hour["wall"]["best"],
                "identical_to_bulk": not differ, "differences": differ[:20]}
    print(f"1 h per line (reference): best {min(wall):.3f} s; bulk is "
          f"{per_line['speedup_best']:.1f}x faster; results "
          f"{'identical' if not differ else 'DIFFER: ' + ', '.join(differ[:5])}")
    del parsed, reference

    long_log = flight_log(args.long_hours)
    _, long_hours = measure(f"{args.long_hours} h", long_log, args.repeats)
    del long_log
    scale = args.long_hours
    linearity = {"hours": scale,
                 "best_over_hour_best_times_hours":
                     long_hours["wall"]["best"] / (scale * one_hour["wall"]["best"]),
                 "median_over_hour_median_times_hours":
                     long_hours["wall"]["median"] / (scale * one_hour["wall"]["median"])}
    goals = {"hour_seconds": GOAL_HOUR_SECONDS,
             "hour_met_best": one_hour["wall"]["best"] < GOAL_HOUR_SECONDS,
             "hour_met_median": one_hour["wall"]["median"] < GOAL_HOUR_SECONDS,
             "ten_hours_seconds": GOAL_TEN_HOURS_SECONDS,
             "ten_hours_met_median": long_hours["wall"]["median"] <= GOAL_TEN_HOURS_SECONDS
             if scale == 10 else None}
    print(f"{scale} h over {scale} x 1 h: {linearity['best_over_hour_best_times_hours']:.2f} "
          f"(best), {linearity['median_over_hour_median_times_hours']:.2f} (median)")
    write_report(args.output, "calib_parse", argv, load_start, packages("numpy"),
                 threads={name: os.environ.get(name) for name in THREAD_VARIABLES},
                 flight=dict(FLIGHT, mag_rate=MAG_RATE,
                             maker="maglog.sim.stimulus.scenario.make_flight(...).log(...)"),
                 one_hour=one_hour, per_line_reference_one_hour=per_line,
                 long=dict(long_hours, hours=scale), linearity=linearity, goals=goals)


if __name__ == "__main__":
    sys.exit(main())
