"""The survey path (``maglog survey``): compensation against deinterf, accuracy against the
truth, time per flight-hour, and the batch path's speed-up on Dask.

Flights: the built-in ``survey`` scenario (13.3 min: calibration box, eight 300 m lines,
three tie lines over three dipoles, Tolles–Lawson interference, diurnal variation with a
base station) with ``--seeds`` seeds, each flown through the logger on the ``model`` backend
to a card image (``maglog.cli.run.simulate``), truth and base station beside it.

Per flight, on the same samples, the same calibration box and the same direction cosines:
maglog's Tolles–Lawson with 18 and 16 terms (band from the manoeuvres, ridge by blocked
cross-validation) and deinterf's ``TollesLawson`` with 18 terms (its own settings: fixed
0.1-0.6 Hz band, RidgeCV over 13 alphas with 10 folds). The improvement ratio and the figure
of merit are computed for all in maglog's band; the residual is the compensated cesium
against the truth's total field in the box (RMS about its mean), beside the noise floor
(the cesium's own noise). Then the map's figures against the truth.

Time: each seed is flown (scenario build + model backend) and its card reduced
(``survey_card`` + ``write_products``: everything from the card image to the written
products) serially in this process; the reduction's wall time over the flight's hours is the
time per flight-hour. Then the batch path on a local Dask cluster of ``--workers``
processes (``calib.batch.run_batch``, cluster start included), twice: the whole path per
seed (fly + reduce, as ``maglog survey --scenario survey --seeds 1-N``) against the serial
fly + reduce, and the reduction alone of the same cards against the serial reductions.
The digests of the maps and samples of all three runs must agree.

Run from the repository root: ``.venv/bin/python bench/survey.py`` (``--help``).
"""

import argparse
import contextlib
import dataclasses
import io
import statistics
import sys
import time
from pathlib import Path

BENCH = Path(__file__).resolve().parent
sys.path.insert(0, str(BENCH))

from _machine import load, packages, scratch_dir, write_report

DEFAULT_OUTPUT = BENCH / "results" / "survey.json"


def fly(seed, folder):
    from maglog.cli.run import simulate
    from maglog.sim.stimulus.config import load_scenario
    started = time.perf_counter()
    stimulus = dataclasses.replace(load_scenario("survey"), seed=seed).build()
    built = time.perf_counter()
    with contextlib.redirect_stderr(io.StringIO()):
        simulate(stimulus, folder / "card.img", backend="model", build_dir=folder / "build",
                 progress=False)
    done = time.perf_counter()
    return {"seed": seed, "flight_s": stimulus.system.until, "build_s": built - started,
            "simulate_s": done - built}


def reduce_serial(folder):
    from maglog.calib.batch import product_digest
    from maglog.calib.survey import SurveyOptions, summary, survey_card, write_products
    started = time.perf_counter()
    result = survey_card(folder / "card.img", SurveyOptions(
        base_station=folder / "base.csv", truth=folder / "truth.json"))
    write_products(result, folder / "products")
    wall = time.perf_counter() - started
    return {"wall_s": wall, "steps_s": result.times, "digest": product_digest(result),
            "figures": summary(result)}


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seeds", type=int, default=4, help="flights (seeds 1..N)")
    parser.add_argument("--workers", type=int, default=2)
    parser.add_argument("--output", type=Path, default=DEFAULT_OUTPUT)
    parser.add_argument("--keep", action="store_true", help="keep the scratch folder")
    args = parser.parse_args(argv)
    load_start = load()
    from maglog.calib.batch import run_batch
    flights = []
    with scratch_dir("maglog-bench-survey-", keep=args.keep) as scratch:
        for seed in range(1, args.seeds + 1):
            folder = scratch / f"seed-{seed}"
            flight = fly(seed, folder)
            print(f"seed {seed}: flown ({flight['build_s']:.1f} s build, "
                  f"{flight['simulate_s']:.1f} s model backend)", flush=True)
            flight.update(reduce_serial(folder))
            print(f"seed {seed}: reduced in {flight['wall_s']:.1f} s", flush=True)
            flights.append(flight)
        card_jobs = [{"card": str(scratch / f"seed-{f['seed']}" / "card.img"),
                      "out": str(scratch / f"seed-{f['seed']}" / "dask"),
                      "options": {"base_station": str(scratch / f"seed-{f['seed']}" / "base.csv"),
                                  "truth": str(scratch / f"seed-{f['seed']}" / "truth.json")}}
                     for f in flights]
        fly_jobs = [{"scenario": "survey", "seed": f["seed"],
                     "out": str(scratch / "dask-fly" / f"seed-{f['seed']}")} for f in flights]
        started = time.perf_counter()
        fly_records = run_batch(fly_jobs, workers=args.workers)
        fly_wall = time.perf_counter() - started
        print(f"Dask fly + reduce: {fly_wall:.1f} s", flush=True)
        started = time.perf_counter()
        records = run_batch(card_jobs, workers=args.workers)
        dask_wall = time.perf_counter() - started
        print(f"Dask reduce: {dask_wall:.1f} s", flush=True)
        records = records + fly_records
    if not all(r["ok"] for r in records):
        raise SystemExit(f"a Dask job failed: {[r['error'] for r in records]}")
    serial_wall = sum(f["wall_s"] for f in flights)
    serial_fly = sum(f["wall_s"] + f["build_s"] + f["simulate_s"] for f in flights)
    hours = sum(f["flight_s"] for f in flights) / 3600
    n = len(flights)
    batch = {"workers": args.workers, "jobs": n,
             "serial_wall_s": serial_wall, "dask_wall_s": dask_wall,
             "speedup": serial_wall / dask_wall,
             "serial_fly_reduce_wall_s": serial_fly, "dask_fly_reduce_wall_s": fly_wall,
             "fly_reduce_speedup": serial_fly / fly_wall,
             "identical": all(r["digest"] == f["digest"]
                              for r, f in zip(records, flights + flights)),
             "dask_job_wall_s": [r["wall_s"] for r in records]}
    per_hour = {"reduce_s_per_flight_hour": serial_wall / hours,
                "fly_s_per_flight_hour": sum(f["build_s"] + f["simulate_s"]
                                             for f in flights) / hours,
                "flight_hours": hours,
                "median_reduce_s": statistics.median(f["wall_s"] for f in flights)}
    print(f"reduce: {per_hour['reduce_s_per_flight_hour']:.0f} s per flight-hour; "
          f"Dask speed-up on {args.workers} workers: fly + reduce "
          f"{batch['fly_reduce_speedup']:.2f}, reduce {batch['speedup']:.2f} "
          f"(identical: {batch['identical']})")
    write_report(args.output, "survey", argv, load_start,
                 packages("numpy", "scipy", "verde", "harmonica", "deinterf", "dask",
                          "distributed", "xarray", "rioxarray"),
                 flights=flights, per_hour=per_hour, batch=batch)


if __name__ == "__main__":
    main()
