"""The swarm like for like (issue 24): maglog's PSO against pyswarms' on the same objective,
what the moment surrogate buys, and whether the swarm changes a calibration's result.

1. Like for like. The samples of heldout.py's timing (UAV coverage, default errors, 50 Hz,
   seed 8; 2,000 and 20,000 samples; reference = true field + N(0, 0.05 nT)); the same
   objective for both swarms, the paper's exact cost on every sample (``_pso.cost_numba``);
   the same search box (``calibrate_scalar``'s), swarm (40 particles x 300 iterations,
   bench/calib/run.py's constants), seeds 0..R-1 (one per repeat) and the same polish after
   it (heldout.py's ``paper_polish``, the one ``objective="paper"`` runs): maglog's gbest
   against pyswarms' ``GlobalBestPSO``, maglog's ring against ``LocalBestPSO`` (k = 3),
   the repeats interleaved. Timed: the swarm alone and the swarm + polish; the polished
   fit's in-sample ratio.
2. What the surrogate buys (maglog against maglog, labelled as such): the same ring swarm on
   the moment surrogate (``scalar._swarm(kernel="moments")``, whose cost does not visit the
   samples) against the exact cost on every sample; and ``calibrate_scalar`` whole
   (default, and ``kernel="numba", pso_samples=N``) with the largest difference of their
   parameters.
3. Whether the swarm changes the result: ``calibrate_scalar`` with the swarm (``method=
   "pso"``, the default) against the deterministic start alone (``method="lm"``: the moment
   problem's linear solution for "eiv", the identity for "paper"), both objectives, on
   heldout.py's grid (coverages full / uav / planar x error models default / paper_a x noise
   5 / 20 / 100 nT x ``--seeds`` seeds, 100 s at 20 Hz, the first half fitted) and on poor
   starts: errors far from the identity (:data:`POOR`: offsets up to 22,000 nT against a
   48,000 nT field, scale factors 0.62-1.45, off-diagonal terms up to 0.3; the last two on
   and beyond the search box's edge). For each fit: the largest
   |difference| of K (unitless) and c (nT), against the fit's own 1 sigma; and the held-out
   ratio of each (heldout.py's score) where the two differ.

Run from the repository root: ``.venv/bin/python bench/calib/swarm.py`` (``--help``); pyswarms
from ``make bench-peers`` (or on PYTHONPATH).
"""

import argparse
import os
import statistics
import sys
import time
from pathlib import Path

os.environ.setdefault("OMP_NUM_THREADS", "1")     # as heldout.py: the BLAS on one thread

import numba
import numpy as np

HERE = Path(__file__).resolve().parent
BENCH = HERE.parent
sys.path.insert(0, str(BENCH))
sys.path.insert(0, str(HERE))

from _machine import load, packages, write_report

import heldout
import run as calib_run
from run import InScratch, pyswarms_run, summary

from maglog.calib import _pso, scalar
from maglog.calib.scalar import calibrate_scalar
from maglog.sim.stimulus import errors as error_models
from maglog.sim.stimulus.scenario import make_flight

DEFAULT_OUTPUT = BENCH / "results" / "calib_swarm.json"
PARTICLES, ITERATIONS = heldout.PARTICLES, heldout.ITERATIONS
SIZES = (2000, 20000)
#: A parameter difference below this (K unitless, c in nT / the field) is "the same fit".
SAME = 1e-9
#: Poor starts: (name, forward error matrix A, offset b in nT), the field about 48,000 nT;
#: calibrate_scalar's box allows K's diagonal 0.5-2, its off-diagonal +-0.5 (times the
#: data's scale) and offsets of half the largest reference (about 24,000 nT).
POOR = (
    ("offsets of 15,000 nT", [[1.05, 0.02, 0.0], [0.02, 0.95, 0.02], [0.0, 0.02, 1.0]],
     [15000.0, -12000.0, 10000.0]),
    ("offsets of 22,000 nT, scale factors 0.75-1.3",
     [[1.3, 0.08, -0.05], [0.08, 0.75, 0.08], [-0.05, 0.08, 1.1]],
     [22000.0, -18000.0, 15000.0]),
    ("soft iron with K's k12 on the box's edge",
     [[1.3, 0.15, -0.1], [0.15, 0.8, 0.15], [-0.1, 0.15, 1.15]], [2000.0, -1500.0, 1000.0]),
    ("soft iron beyond the box", [[1.45, 0.25, -0.2], [0.25, 0.62, 0.3], [-0.2, 0.3, 1.2]],
     [3000.0, -2000.0, 1500.0]),
)


def _flight(samples):
    flight = make_flight(seconds=samples / heldout.TIMING_FLIGHT["rate"],
                         **heldout.TIMING_FLIGHT)
    rng = np.random.default_rng(samples)
    b, total = flight.b_meas[:samples], flight.total[:samples]
    r = total + rng.normal(0.0, heldout.REFERENCE_NOISE_NT, total.size)
    k_true, c_true = flight.errors.truth()
    return b, r, total, heldout.residual_rms(k_true, c_true, b, total)


def like_for_like(samples, repeats):
    """Part 1 and 2 at one size."""
    b, r, total, floor = _flight(samples)
    lower, upper, _ = scalar._box(b, r)
    cost = lambda x: _pso.cost_numba(x, b, r)          # noqa: E731 - one objective for all
    variants = (("maglog_gbest", "gbest", None), ("pyswarms_gbest", None, "gbest"),
                ("maglog_ring", "ring", None), ("pyswarms_lbest", None, "ring"))
    measured = {name: {"swarm": [], "whole": [], "ratios": [], "costs": []}
                for name, _, _ in variants}
    # The repeats interleaved (each seed runs every variant in turn): a load that changes
    # during the bench falls on all of them alike.
    for seed in range(repeats):
        for name, topology, kind in variants:
            m = measured[name]
            t0 = time.perf_counter()
            if topology is not None:
                best, best_cost, _, _ = _pso.pso(cost, lower, upper, particles=PARTICLES,
                                                 iterations=ITERATIONS, seed=seed,
                                                 topology=topology)
            else:
                best_cost, best = pyswarms_run(kind, cost, lower, upper, PARTICLES,
                                               ITERATIONS, seed)
            t1 = time.perf_counter()
            fit = heldout.paper_polish(b, r, np.asarray(best, float))
            t2 = time.perf_counter()
            m["swarm"].append(t1 - t0)
            m["whole"].append(t2 - t0)
            m["costs"].append(float(best_cost))
            m["ratios"].append(heldout.residual_rms(fit.K, fit.c, b, total) / floor)
    runs = {}
    for name, m in measured.items():
        runs[name] = {"swarm": summary(m["swarm"]), "swarm_and_polish": summary(m["whole"]),
                      "best_cost_median": statistics.median(m["costs"]),
                      "insample_ratios": m["ratios"]}
        print(f"{samples:6d} samples {name:15s}: swarm median "
              f"{statistics.median(m['swarm']) * 1e3:7.1f} ms (best "
              f"{min(m['swarm']) * 1e3:7.1f} ms), + polish "
              f"{statistics.median(m['whole']) * 1e3:7.1f} ms, worst ratio "
              f"{max(m['ratios']):.4f}")
    pairs = []
    for ours, theirs in (("maglog_gbest", "pyswarms_gbest"), ("maglog_ring", "pyswarms_lbest")):
        pairs.append({"maglog": ours, "pyswarms": theirs, **{
            f"{stage}_{stat}": runs[theirs][stage][stat] / runs[ours][stage][stat]
            for stage in ("swarm", "swarm_and_polish") for stat in ("median", "best")}})
    # What the surrogate buys: the same (ring) swarm on the moments against the exact cost.
    surrogate = {}
    for kernel in ("moments", "numba"):
        seconds = []
        for seed in range(repeats):
            t0 = time.perf_counter()
            scalar._swarm(b, r, lower, upper, kernel=kernel, seed=seed, particles=PARTICLES,
                          iterations=ITERATIONS, pso_samples=samples)
            seconds.append(time.perf_counter() - t0)
        surrogate[f"swarm_{kernel}"] = summary(seconds)
    fits = {}
    for name, options in (("calibrate_scalar_moments", {}),
                          ("calibrate_scalar_exact", {"kernel": "numba",
                                                      "pso_samples": samples})):
        seconds = []
        for seed in range(repeats):
            t0 = time.perf_counter()
            fit = calibrate_scalar(b, r, seed=seed, **options)
            seconds.append(time.perf_counter() - t0)
        fits[name] = fit
        surrogate[name] = summary(seconds)
    a, e = fits["calibrate_scalar_moments"], fits["calibrate_scalar_exact"]
    surrogate["result_difference"] = {"K": float(np.max(np.abs(a.K - e.K))),
                                      "c_nT": float(np.max(np.abs(a.c - e.c)))}
    print(f"{samples:6d} samples surrogate: swarm {surrogate['swarm_moments']['median'] * 1e3:.1f}"
          f" ms against {surrogate['swarm_numba']['median'] * 1e3:.1f} ms on the exact cost; "
          f"fits differ by K {surrogate['result_difference']['K']:.2g}, c "
          f"{surrogate['result_difference']['c_nT']:.2g} nT")
    return {"samples": samples, "floor_nT": floor, "repeats": repeats, "runs": runs,
            "pairs": pairs, "surrogate": surrogate}


def _difference(a, b):
    """(largest |dK|, largest |dc| nT, largest |d| in units of the first fit's 1 sigma)."""
    dk = float(np.max(np.abs(a.K - b.K)))
    dc = float(np.max(np.abs(a.c - b.c)))
    sigma = np.asarray(a.uncertainties, float)
    dx = np.abs(np.asarray(a.x, float) - np.asarray(b.x, float))
    finite = np.isfinite(sigma) & (sigma > 0)
    z = float(np.max(dx[finite] / sigma[finite])) if finite.any() else float("nan")
    return dk, dc, z


def _compare(b, r, total_test, b_test, floor_test, field):
    """Each objective's fit with the swarm and from the deterministic start alone."""
    out = {}
    for objective in ("eiv", "paper"):
        fits = {}
        for method in ("pso", "lm"):
            try:
                fits[method] = calibrate_scalar(b, r, objective=objective, method=method)
            except Exception as error:        # noqa: BLE001 - a failed fit is a finding
                fits[method] = error
        entry = {}
        for method, fit in fits.items():
            if isinstance(fit, Exception):
                entry[method] = {"error": f"{type(fit).__name__}: {fit}"}
            else:
                entry[method] = {"success": bool(fit.success),
                                 "heldout": heldout.residual_rms(fit.K, fit.c, b_test,
                                                                 total_test) / floor_test}
        if not any(isinstance(f, Exception) for f in fits.values()):
            dk, dc, z = _difference(fits["pso"], fits["lm"])
            entry.update(dK=dk, dc_nT=dc, dz=z,
                         same=bool(dk <= SAME and dc <= SAME * field))
        out[objective] = entry
    return out


def grid_cases(seeds):
    """Part 3 on heldout.py's grid."""
    rows = []
    for coverage in heldout.COVERAGES:
        for model in heldout.ERROR_MODELS:
            for noise in heldout.NOISES:
                errors = error_models.preset(model, noise=noise)
                for seed in seeds:
                    rows.append(_case(coverage, model, noise, seed, errors))
    return rows


def poor_cases(seeds, noise=5.0):
    """Part 3 on errors far from the identity."""
    rows = []
    for name, a, offset in POOR:
        errors = error_models.from_forward(np.array(a), np.array(offset), noise=noise)
        for coverage in ("full", "uav"):
            for seed in seeds:
                rows.append(_case(coverage, name, noise, seed, errors))
    return rows


def _case(coverage, model, noise, seed, errors):
    flight = make_flight(coverage=coverage, seconds=heldout.SECONDS, rate=heldout.RATE,
                         errors=errors, seed=seed)
    rng = np.random.default_rng(10_000 + seed)
    r_all = flight.total + rng.normal(0.0, heldout.REFERENCE_NOISE_NT, flight.total.size)
    half = flight.total.size // 2
    k_true, c_true = errors.truth()
    b_test, total_test = flight.b_meas[half:], flight.total[half:]
    floor_test = heldout.residual_rms(k_true, c_true, b_test, total_test)
    field = float(np.median(flight.total))
    row = {"coverage": coverage, "errors": model, "noise_nT": noise, "seed": seed,
           **_compare(flight.b_meas[:half], r_all[:half], total_test, b_test, floor_test,
                      field)}
    return row


def verdict(rows):
    """Per objective: fits, how many differ, the largest differences, and the held-out
    ratios of the two where they differ."""
    out = {}
    for objective in ("eiv", "paper"):
        entries = [row[objective] for row in rows]
        compared = [e for e in entries if "dK" in e]
        differ = [e for e in compared if not e["same"]]
        out[objective] = {
            "fits": len(entries), "compared": len(compared),
            "errors": [e.get("pso", {}).get("error") or e.get("lm", {}).get("error")
                       for e in entries if "dK" not in e],
            "differ": len(differ),
            "max_dK": max((e["dK"] for e in compared), default=None),
            "max_dc_nT": max((e["dc_nT"] for e in compared), default=None),
            "max_dz": max((e["dz"] for e in compared if np.isfinite(e["dz"])), default=None),
            "success_pso": sum(e["pso"].get("success", False) for e in entries),
            "success_lm": sum(e["lm"].get("success", False) for e in entries),
            "heldout_where_differ": [[e["pso"]["heldout"], e["lm"]["heldout"]]
                                     for e in differ],
            "success_differs": sum(e["pso"].get("success") != e["lm"].get("success")
                                   for e in entries),
        }
    return out


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeats", type=int, default=7,
                        help="repeats (seeds 0..N-1) of each timing (default: %(default)s)")
    parser.add_argument("--seeds", type=int, default=5,
                        help="seeds per case of the result comparison (default: %(default)s)")
    parser.add_argument("--output", type=Path, default=DEFAULT_OUTPUT)
    args = parser.parse_args(argv)
    if min(args.repeats, args.seeds) < 1:
        parser.error("repeats and seeds must be at least 1")
    load_start = load()
    numba.set_num_threads(1)
    started = time.perf_counter()
    with InScratch():                      # pyswarms writes report.log where it is imported
        _flight(200)                       # first calls (imports, numba) out of the timing
        b, r, _, _ = _flight(2000)
        lower, upper, _ = scalar._box(b, r)
        pyswarms_run("gbest", lambda x: _pso.cost_numba(x, b, r), lower, upper, 5, 3, 0)
        _pso.pso(lambda x: _pso.cost_numba(x, b, r), lower, upper, particles=5, iterations=3)
        calibrate_scalar(b, r)
        calibrate_scalar(b, r, objective="paper", method="lm")
        timing = [like_for_like(samples, args.repeats) for samples in SIZES]
    timed = time.perf_counter()
    grid = grid_cases(range(args.seeds))
    poor = poor_cases(range(args.seeds))
    results = {"grid": verdict(grid), "poor": verdict(poor)}
    for part, found in results.items():
        for objective, v in found.items():
            print(f"{part} {objective}: {v['differ']} of {v['compared']} fits differ; largest "
                  f"|dK| {v['max_dK']:.2g}, |dc| {v['max_dc_nT']:.2g} nT")
    write_report(args.output, "calib_swarm", argv, load_start,
                 packages("numpy", "numba", "scipy", "pyswarms"),
                 numba_threading={"threads": numba.get_num_threads(),
                                  "threading_layer": numba.threading_layer()},
                 settings={"particles": PARTICLES, "iterations": ITERATIONS,
                           "repeats": args.repeats, "seeds": args.seeds,
                           "timing_flight": heldout.TIMING_FLIGHT,
                           "reference_noise_nT": heldout.REFERENCE_NOISE_NT,
                           "pyswarms_options": calib_run.PYSWARMS_OPTIONS,
                           "pyswarms_ring": calib_run.PYSWARMS_RING,
                           "same": SAME, "grid": {"coverages": heldout.COVERAGES,
                                                  "error_models": heldout.ERROR_MODELS,
                                                  "noises_nT": heldout.NOISES,
                                                  "flight_seconds": heldout.SECONDS,
                                                  "rate_hz": heldout.RATE},
                           "poor": [{"name": n, "matrix": a, "offset_nT": o}
                                    for n, a, o in POOR],
                           "omp_num_threads": os.environ.get("OMP_NUM_THREADS")},
                 timing=timing, results=results, cases={"grid": grid, "poor": poor},
                 bench_seconds={"timing": timed - started,
                                "whole": time.perf_counter() - started})


if __name__ == "__main__":
    sys.exit(main())
