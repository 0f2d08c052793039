"""Calibration on held-out data (issue 13): fit on the first half of a flight, score on the
second half against the true field; like-for-like swarm timing; log text to parameters.

1. The held-out grid: coverages full / uav / planar x error models ``default`` / ``paper_a``
   (paper A's Table 1) x noise 5 / 20 / 100 nT x ``--seeds`` seeds; 100 s flights at 20 Hz
   (``sim.stimulus.scenario.make_flight``), the reference a cesium-like r = |B_true| +
   N(0, 0.05 nT). Each estimator fits the first half; the score is

       ratio = RMS(|K b - c| - |B_true|) / RMS of the same with the true K and c

   on the second half (held out) and on the first (in sample). Estimators: maglog's
   ``calibrate_scalar`` (default: errors in variables) and ``objective="paper"``; scipy's
   ``least_squares`` on the paper's objective from the identity (``lm``, and ``trf`` within
   ``calibrate_scalar``'s search box); pyswarms' ``GlobalBestPSO`` driving maglog's numba
   kernel, then maglog's paper polish; magyc's Fang ellipsoid fit (in the peers' venv, its
   magnitude scaled by the one factor that best matches the reference on the fitted half).
   Collapses (a diagonal element of K below 0.1 in size) and reflections (det K < 0) are
   counted.
   For maglog's two objectives, the z-scores (estimate - truth) / reported 1 sigma over the
   seeds, per parameter (parameters held to the prior left out and counted), and the
   coverage gate's verdict (``determined`` false, ``held`` true) per coverage.
2. Like-for-like timing on one thread (numba and the BLAS): ``calibrate_scalar`` (default,
   and the paper's objective) against pyswarms' ``GlobalBestPSO`` and ``LocalBestPSO`` (k = 3
   ring) driving ``_pso.cost_numba`` on the same samples, the same swarm (40 particles, 300
   iterations, bench/calib/run.py's constants), then the paper objective's polish; 2,000 and
   20,000 samples; start-up (imports, numba's JIT) timed apart; whether each reached the floor;
   and ``calibrate_scalar`` with the BLAS threads left to their default, for comparison.
3. A one-hour (50 Hz, 180,000 samples) and a ten-hour flight from log text to parameters,
   stage by stage (read, parse_log, screening of the cesium and the samples when
   ``maglog.calib.screen`` exists, alignment of the cesium, calibrate_scalar). The logs are
   cached under build/bench/ keyed by their parameters and the simulator's source.

Run from the repository root: ``.venv/bin/python bench/calib/heldout.py`` (``--help``).
"""

import argparse
import dataclasses
import hashlib
import importlib.util
import json
import os
import statistics
import subprocess
import sys
import time
from pathlib import Path

#: One thread for the BLAS under numpy and scipy as well as for numba (set in main): OpenBLAS
#: reads OMP_NUM_THREADS when OPENBLAS_NUM_THREADS is unset, and only before numpy's import.
#: (What its default threads cost on this machine: :func:`blas_threads`.)
os.environ.setdefault("OMP_NUM_THREADS", "1")
BLAS_VARIABLES = ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS")

import numba
import numpy as np

HERE = Path(__file__).resolve().parent
BENCH = HERE.parent
REPO = BENCH.parent
sys.path.insert(0, str(BENCH))
sys.path.insert(0, str(HERE))

from _machine import load, packages, write_report

import run as calib_run
from run import InScratch, magyc_fits, pyswarms_run, repeat, scipy_fit, summary

from maglog.calib import _pso, scalar
from maglog.calib.scalar import PARAMETERS, apply_scalar, calibrate_scalar
from maglog.sim.stimulus import errors as error_models
from maglog.sim.stimulus.scenario import make_flight

DEFAULT_OUTPUT = BENCH / "results" / "calib_heldout.json"
CACHE = REPO / "build" / "bench" / "calib_heldout"
COVERAGES = ("full", "uav", "planar")
ERROR_MODELS = ("default", "paper_a")
NOISES = (5.0, 20.0, 100.0)
SECONDS, RATE = 100.0, 20.0
REFERENCE_NOISE_NT = 0.05
COLLAPSE_DIAGONAL = 0.1
#: A held-out ratio this far below the floor: K shrunk so far that the noise shrinks with it
#: (the simulated true field is constant over a flight, so a shrunk K is not punished).
SHRUNK_RATIO = 0.9
FLOOR_GOAL = 1.01
PARTICLES, ITERATIONS = 40, 300
ESTIMATORS = ("maglog_eiv", "maglog_paper", "scipy_lm", "scipy_trf", "pyswarms_gbest",
              "magyc_fang")
#: The flights of part 2 and 3 (run.py's hour flight: UAV coverage, seed 9, 50 Hz).
TIMING_FLIGHT = {"coverage": "uav", "rate": 50.0, "seed": 8}
HOUR_FLIGHT = {"coverage": "uav", "rate": 50, "seed": 9, "mag_rate": 50}
GOAL_SPEEDUP = 10.0
GOAL_HOURS_SECONDS = {1: 0.5, 10: 5.0}


# --- scoring ---------------------------------------------------------------------------

def truth_vector(errors):
    k, c = errors.truth()
    return np.array([k[0, 0], k[0, 1], k[0, 2], k[1, 1], k[1, 2], k[2, 2], *c])


def residual_rms(k, c, b, total):
    return float(np.sqrt(np.mean((np.linalg.norm(apply_scalar(k, c, b), axis=1) - total)
                                 ** 2)))


def verdict(k, c, b_fit, total_fit, b_test, total_test, floors, clean_test):
    """Held-out and in-sample ratios, the systematic error on the held-out half's attitudes
    (the noise-free samples there: what the parameters themselves get wrong, in nT),
    collapse and reflection of one fit (K, c)."""
    finite = bool(np.all(np.isfinite(k)) and np.all(np.isfinite(c)))
    if not finite:
        return {"finite": False, "heldout": None, "insample": None, "systematic_nT": None,
                "collapse": True, "reflection": False}
    return {"finite": True,
            "heldout": residual_rms(k, c, b_test, total_test) / floors[1],
            "insample": residual_rms(k, c, b_fit, total_fit) / floors[0],
            "systematic_nT": residual_rms(k, c, clean_test, total_test),
            "collapse": bool(np.min(np.abs(np.diag(k))) < COLLAPSE_DIAGONAL),
            "reflection": bool(np.linalg.det(k) < 0)}


# --- estimators (each: b, r of the fitted half -> K, c, notes) ---------------------------

def maglog(b, r, objective):
    result = calibrate_scalar(b, r, objective=objective)
    return result.K, result.c, {"success": bool(result.success), "x": result.x,
                                "uncertainties": result.uncertainties,
                                "determined": result.determined, "held": result.held,
                                "warnings": list(result.warnings)}


def scipy_trf(b, r):
    """scipy's least_squares (trf) on the paper's objective from the identity, within
    calibrate_scalar's search box (scalar._box); the identity of run.py's scipy_fit."""
    from scipy.optimize import least_squares
    lower, upper, scale = scalar._box(b, r)
    x0 = np.array([scale, 0, 0, scale, 0, scale, 0, 0, 0], dtype=float)

    def residual(p):
        k, c = _pso.unpack(p)
        return np.linalg.norm(b @ k.T - c, axis=1) - r
    return least_squares(residual, x0, method="trf", bounds=(lower, upper))


def paper_polish(b, r, start):
    """maglog's polish of the paper objective (``objective="paper"``) from ``start``: the
    same code calibrate_scalar runs after its swarm (least_squares from the start, and from
    the identity too when that ends on the box or fails; Talwar's robust rounds)."""
    lower, upper, scale = scalar._box(b, r)
    return scalar._fit_paper(b, r, start, None, True, lower, upper, scale, "lm", None)


def pyswarms_fit(kind, b, r, seed=0):
    """pyswarms (``kind`` "gbest" or "ring") on ``_pso.cost_numba`` over every sample in
    calibrate_scalar's box, then maglog's paper polish. (result, swarm s, polish s)."""
    lower, upper, _ = scalar._box(b, r)
    t0 = time.perf_counter()
    _, best = pyswarms_run(kind, lambda x: _pso.cost_numba(x, b, r), lower, upper,
                           PARTICLES, ITERATIONS, seed)
    t1 = time.perf_counter()
    result = paper_polish(b, r, np.asarray(best, float))
    return result, t1 - t0, time.perf_counter() - t1


def fit_all(b, r):
    """Every estimator but magyc's on one fitted half: name -> (K, c, notes)."""
    out = {"maglog_eiv": maglog(b, r, "eiv"), "maglog_paper": maglog(b, r, "paper")}
    lm = scipy_fit(b, r)
    out["scipy_lm"] = (*_pso.unpack(lm.x), {"status": int(lm.status)})
    trf = scipy_trf(b, r)
    out["scipy_trf"] = (*_pso.unpack(trf.x), {"status": int(trf.status)})
    swarm, _, _ = pyswarms_fit("gbest", b, r)
    out["pyswarms_gbest"] = (swarm.K, swarm.c, {"success": bool(swarm.success)})
    return out


def fang_kc(fit, b, r):
    """K, c of magyc's Fang fit: calibrated = s soft^-1 (b - hard), s the one factor that
    best matches the reference on the fitted samples."""
    inverse = np.linalg.inv(np.array(fit["soft_iron"]))
    hard = np.array(fit["hard_iron"])
    magnitude = np.linalg.norm((b - hard) @ inverse.T, axis=1)
    s = float(magnitude @ r / (magnitude @ magnitude))
    return s * inverse, s * inverse @ hard


# --- 1. the held-out grid ----------------------------------------------------------------

def case_key(coverage, model, noise, seed):
    return f"{coverage}_{model}_{noise:g}_{seed}"


def grid(seeds):
    rows, halves = [], {}
    started = time.perf_counter()
    for coverage in COVERAGES:
        for model in ERROR_MODELS:
            for noise in NOISES:
                errors = error_models.preset(model, noise=noise)
                truth = truth_vector(errors)
                k_true, c_true = errors.truth()
                for seed in seeds:
                    flight = make_flight(coverage=coverage, seconds=SECONDS, rate=RATE,
                                         errors=errors, seed=seed)
                    rng = np.random.default_rng(10_000 + seed)
                    r_all = flight.total + rng.normal(0.0, REFERENCE_NOISE_NT,
                                                      flight.total.size)
                    half = flight.total.size // 2
                    b, r, total = flight.b_meas[:half], r_all[:half], flight.total[:half]
                    b_test, total_test = flight.b_meas[half:], flight.total[half:]
                    # The same attitudes without the sensor's noise (apply() adds none at
                    # zero noise): what the parameters alone do there.
                    clean_test = dataclasses.replace(errors, noise=0.0).apply(
                        flight.b_earth[half:], np.random.default_rng(0))
                    floors = (residual_rms(k_true, c_true, b, total),
                              residual_rms(k_true, c_true, b_test, total_test))
                    key = case_key(coverage, model, noise, seed)
                    halves[key] = (b, r, total, b_test, total_test, floors, clean_test)
                    row = {"case": key, "coverage": coverage, "errors": model,
                           "noise_nT": noise, "seed": seed, "fit_samples": half,
                           "test_samples": int(b_test.shape[0]),
                           "floor_fit_nT": floors[0], "floor_test_nT": floors[1],
                           "estimators": {}}
                    for name, (k, c, notes) in fit_all(b, r).items():
                        got = verdict(k, c, b, total, b_test, total_test, floors,
                                      clean_test)
                        if name.startswith("maglog_"):
                            unc = notes["uncertainties"]
                            z = (notes["x"] - truth) / unc
                            counted = ~notes["held"] & np.isfinite(unc)
                            got.update(success=notes["success"],
                                       z=[float(v) if ok else None
                                          for v, ok in zip(z, counted)],
                                       determined=notes["determined"].tolist(),
                                       held=notes["held"].tolist(),
                                       warnings=notes["warnings"])
                        else:
                            got.update({key_: value for key_, value in notes.items()})
                        row["estimators"][name] = got
                    rows.append(row)
                done = [x for x in rows if x["coverage"] == coverage and x["errors"] == model
                        and x["noise_nT"] == noise]
                print(f"{coverage:6s} {model:7s} {noise:5.0f} nT, held-out worst: " + ", ".join(
                    f"{name} {max(x['estimators'][name]['heldout'] or np.inf for x in done):.4f}"
                    for name in ESTIMATORS[:-1]) + f" ({time.perf_counter() - started:.0f} s)")
    peers, why = magyc_fits({key: value[0] for key, value in halves.items()})
    for row in rows:
        b, r, total, b_test, total_test, floors, clean_test = halves[row["case"]]
        if peers is None:
            row["estimators"]["magyc_fang"] = {"not_run": why}
            continue
        fit = peers["cases"][row["case"]]["ellipsoid_fit_fang"]
        if "error" in fit:
            row["estimators"]["magyc_fang"] = {"error": fit["error"], "heldout": None,
                                              "insample": None, "systematic_nT": None,
                                              "collapse": True, "reflection": False,
                                              "finite": False}
            continue
        k, c = fang_kc(fit, b, r)
        row["estimators"]["magyc_fang"] = dict(verdict(k, c, b, total, b_test, total_test,
                                                       floors, clean_test),
                                               seconds=fit["seconds"])
    magyc = None if peers is None else {k: v for k, v in peers.items() if k != "cases"}
    return rows, magyc, why


def case_summaries(rows):
    """Per (coverage, errors, noise): per estimator the worst and median held-out ratio,
    the worst in-sample ratio, collapses, reflections; z-score RMS per parameter for
    maglog's objectives; the gate's verdicts."""
    out = []
    groups = {}
    for row in rows:
        groups.setdefault((row["coverage"], row["errors"], row["noise_nT"]), []).append(row)
    for (coverage, model, noise), group in groups.items():
        entry = {"coverage": coverage, "errors": model, "noise_nT": noise,
                 "seeds": len(group), "estimators": {}}
        for name in ESTIMATORS:
            got = [row["estimators"][name] for row in group]
            if any("not_run" in g for g in got):
                entry["estimators"][name] = {"not_run": got[0]["not_run"]}
                continue
            # A collapsed fit (K near 0, |c| near r) scores near 0 against these flights'
            # constant true field: it is counted, and left out of the ratios.
            sound = [g for g in got if g["finite"] and not g["collapse"]]
            held = [g["heldout"] for g in sound]
            ins = [g["insample"] for g in sound]
            systematic = [g["systematic_nT"] for g in sound]
            one = {"heldout_worst": max(held, default=None),
                   "systematic_worst_nT": max(systematic, default=None),
                   "systematic_median_nT": (statistics.median(systematic) if systematic
                                            else None),
                   "heldout_median": statistics.median(held) if held else None,
                   "insample_worst": max(ins, default=None),
                   "insample_median": statistics.median(ins) if ins else None,
                   "heldout_all": [g["heldout"] for g in got],
                   "insample_all": [g["insample"] for g in got],
                   "scored": len(sound),
                   "collapses": sum(g["collapse"] for g in got),
                   "reflections": sum(g["reflection"] for g in got),
                   "shrunk": sum(g["heldout"] < SHRUNK_RATIO for g in sound),
                   "errors": sum("error" in g for g in got)}
            if name.startswith("maglog_"):
                z = np.array([[np.nan if v is None else v for v in g["z"]] for g in got])
                counted = np.isfinite(z)
                one["z_rms"] = [float(np.sqrt(np.mean(z[counted[:, j], j] ** 2)))
                                if counted[:, j].any() else None for j in range(9)]
                one["z_counted"] = counted.sum(axis=0).tolist()
                one["held"] = np.sum([g["held"] for g in got], axis=0).tolist()
                one["undetermined"] = (len(got) - np.sum([g["determined"] for g in got],
                                                         axis=0)).tolist()
                one["unsuccessful"] = sum(not g["success"] for g in got)
            entry["estimators"][name] = one
        out.append(entry)
    return out


def gate_verdicts(rows):
    """Per coverage, for maglog's default and paper objectives: in how many fits each
    parameter was reported not determined, and held to the prior."""
    out = {}
    for coverage in COVERAGES:
        mine = [row for row in rows if row["coverage"] == coverage]
        out[coverage] = {"fits": len(mine)}
        for name in ("maglog_eiv", "maglog_paper"):
            determined = np.array([row["estimators"][name]["determined"] for row in mine])
            held = np.array([row["estimators"][name]["held"] for row in mine])
            out[coverage][name] = {
                "undetermined": dict(zip(PARAMETERS, (~determined).sum(axis=0).tolist())),
                "held": dict(zip(PARAMETERS, held.sum(axis=0).tolist()))}
    return out


# --- 2. like-for-like timing ---------------------------------------------------------------

def timing(samples_list, repeats):
    out = []
    for samples in samples_list:
        flight = make_flight(seconds=samples / TIMING_FLIGHT["rate"], **TIMING_FLIGHT)
        rng = np.random.default_rng(samples)
        b = flight.b_meas[:samples]
        total = flight.total[:samples]
        r = total + rng.normal(0.0, REFERENCE_NOISE_NT, total.size)
        k_true, c_true = flight.errors.truth()
        floor = residual_rms(k_true, c_true, b, total)
        runs = {}

        def record(name, fits, seconds, stages=None):
            ratios = [residual_rms(f.K, f.c, b, total) / floor for f in fits]
            runs[name] = {"seconds": summary(seconds), "insample_ratios": ratios,
                          "at_floor": bool(max(ratios) <= FLOOR_GOAL),
                          "stages": stages}
            print(f"{samples:6d} samples {name:22s}: best {min(seconds) * 1e3:7.1f} ms, "
                  f"median {statistics.median(seconds) * 1e3:7.1f} ms, in-sample ratio "
                  f"{max(ratios):.4f}")

        for name, objective in (("maglog_eiv", "eiv"), ("maglog_paper", "paper")):
            fits, seconds = [], []
            for _ in range(repeats):
                t0 = time.perf_counter()
                fits.append(calibrate_scalar(b, r, objective=objective))
                seconds.append(time.perf_counter() - t0)
            record(name, fits, seconds)
        lower, upper, _ = scalar._box(b, r)
        _, seconds = repeat(lambda: scalar._swarm(b, r, lower, upper, kernel="moments",
                                                  seed=0, particles=PARTICLES,
                                                  iterations=ITERATIONS, pso_samples=samples),
                            repeats)
        swarm_only = {"maglog_moments_swarm": summary(seconds)}
        print(f"{samples:6d} samples maglog swarm alone (moments): median "
              f"{statistics.median(seconds) * 1e3:.1f} ms")
        for kind, name in (("gbest", "pyswarms_gbest"), ("ring", "pyswarms_lbest")):
            fits, seconds, swarm, polish = [], [], [], []
            for seed in range(repeats):
                t0 = time.perf_counter()
                fit, s_swarm, s_polish = pyswarms_fit(kind, b, r, seed=seed)
                seconds.append(time.perf_counter() - t0)
                fits.append(fit)
                swarm.append(s_swarm)
                polish.append(s_polish)
            record(name, fits, seconds, {"swarm": summary(swarm), "polish": summary(polish)})
        speedups = [{"maglog": ours, "pyswarms": theirs,
                     "median": runs[theirs]["seconds"]["median"]
                     / runs[ours]["seconds"]["median"],
                     "best": runs[theirs]["seconds"]["best"] / runs[ours]["seconds"]["best"]}
                    for ours in ("maglog_eiv", "maglog_paper")
                    for theirs in ("pyswarms_gbest", "pyswarms_lbest")]
        swarm_speedups = [{"pyswarms": theirs, "median": runs[theirs]["stages"]["swarm"]["median"]
                           / swarm_only["maglog_moments_swarm"]["median"],
                           "best": runs[theirs]["stages"]["swarm"]["best"]
                           / swarm_only["maglog_moments_swarm"]["best"]}
                          for theirs in ("pyswarms_gbest", "pyswarms_lbest")]
        for s in speedups:
            print(f"{samples:6d} samples {s['pyswarms']} / {s['maglog']}: {s['median']:.1f}x "
                  f"(median), {s['best']:.1f}x (best)")
        out.append({"samples": samples, "flight": dict(TIMING_FLIGHT, seconds=samples
                                                       / TIMING_FLIGHT["rate"]),
                    "floor_nT": floor, "repeats": repeats, "runs": runs,
                    "speedups": speedups, "swarm_alone": swarm_only,
                    "swarm_speedups": swarm_speedups,
                    "goal_speedup": GOAL_SPEEDUP,
                    "goal_met_median": {ours: all(s["median"] >= GOAL_SPEEDUP
                                                  for s in speedups if s["maglog"] == ours)
                                        for ours in ("maglog_eiv", "maglog_paper")}})
    return out


def first_calls():
    """In-process first calls (imports, numba compile or cache load) before any timing."""
    warm = make_flight(coverage="full", seconds=10, seed=1)
    out = {}
    for name, call in (("calibrate_scalar_eiv", lambda: calibrate_scalar(warm.b_meas,
                                                                          warm.total)),
                       ("calibrate_scalar_paper",
                        lambda: calibrate_scalar(warm.b_meas, warm.total, objective="paper")),
                       ("pyswarms_gbest_and_polish",
                        lambda: pyswarms_fit("gbest", warm.b_meas, warm.total)),
                       ("pyswarms_lbest_and_polish",
                        lambda: pyswarms_fit("ring", warm.b_meas, warm.total))):
        t0 = time.perf_counter()
        call()
        out[name] = time.perf_counter() - t0
    return out


BLAS_PROBE = """
import json, sys, time
import numpy as np
from maglog.calib.scalar import calibrate_scalar
from maglog.sim.stimulus.scenario import make_flight
flight = make_flight(seconds=2000 / 50.0, coverage="uav", rate=50.0, seed=8)
b, total = flight.b_meas[:2000], flight.total[:2000]
r = total + np.random.default_rng(2000).normal(0.0, 0.05, total.size)
out = {}
for objective in ("eiv", "paper"):
    calibrate_scalar(b, r, objective=objective)
    seconds = []
    for _ in range(int(sys.argv[1])):
        t0 = time.perf_counter()
        calibrate_scalar(b, r, objective=objective)
        seconds.append(time.perf_counter() - t0)
    out[objective] = seconds
print(json.dumps(out))
"""


def blas_threads(repeats):
    """``calibrate_scalar`` on the 2,000 timing samples in fresh interpreters: with the BLAS
    threads left to their default (the variables unset) and with OMP_NUM_THREADS=1 (numba on
    one thread in both)."""
    out = {}
    for name, value in (("default", None), ("one", "1")):
        env = {k: v for k, v in os.environ.items() if k not in BLAS_VARIABLES}
        env["NUMBA_NUM_THREADS"] = "1"
        if value is not None:
            env["OMP_NUM_THREADS"] = value
        done = subprocess.run([sys.executable, "-c", BLAS_PROBE, str(repeats)],
                              capture_output=True, text=True, env=env, check=True)
        got = json.loads(done.stdout)
        out[name] = {"OMP_NUM_THREADS": value,
                     **{objective: summary(seconds) for objective, seconds in got.items()}}
        print(f"BLAS threads {name}: " + ", ".join(
            f"{objective} median {statistics.median(seconds) * 1e3:.1f} ms"
            for objective, seconds in got.items()))
    return out


# --- 3. log text to parameters -------------------------------------------------------------

def simulator_digest():
    digest = hashlib.sha256()
    for path in sorted((REPO / "sim" / "stimulus").glob("*.py")):
        digest.update(path.name.encode() + b"\0" + path.read_bytes())
    return digest.hexdigest()[:12]


def flight_log(hours):
    """The log of the hour flight over ``hours`` hours, cached in build/bench/."""
    key = (f"uav_{hours}h_rate{HOUR_FLIGHT['rate']}_mag{HOUR_FLIGHT['mag_rate']}_seed"
           f"{HOUR_FLIGHT['seed']}_sim{simulator_digest()}")
    path = CACHE / f"{key}.txt"
    if path.exists():
        print(f"{hours} h log: cached {path.relative_to(REPO)}")
        return path, key, None
    t0 = time.perf_counter()
    flight = make_flight(coverage=HOUR_FLIGHT["coverage"], seconds=3600 * hours,
                         rate=HOUR_FLIGHT["rate"], seed=HOUR_FLIGHT["seed"])
    data = flight.log(mag_rate=HOUR_FLIGHT["mag_rate"])
    CACHE.mkdir(parents=True, exist_ok=True)
    partial = path.with_suffix(".part")
    partial.write_bytes(data)
    partial.replace(path)
    made = time.perf_counter() - t0
    print(f"{hours} h log: made in {made:.1f} s, cached {path.relative_to(REPO)}")
    return path, key, made


def log_to_parameters(hours, repeats):
    from maglog.calib.logparse import parse_log
    screen = (importlib.import_module("maglog.calib.screen")
              if importlib.util.find_spec("maglog.calib.screen") else None)
    path, key, made = flight_log(hours)
    names = ["read", "parse_log", "screen_reference", "align", "screen_samples",
             "calibrate_scalar", "total"]
    stages = {name: [] for name in names}
    for _ in range(repeats):
        t = [time.perf_counter()]
        data = path.read_bytes()
        t.append(time.perf_counter())
        parsed = parse_log(data)
        t.append(time.perf_counter())
        ces = parsed.cesium
        if screen is not None:
            ref_screen = screen.screen_reference(ces.t, ces.field)
            ces_t, ces_field = ces.t[ref_screen.keep], ces.field[ref_screen.keep]
        else:
            ces_t, ces_field = ces.t, ces.field
        t.append(time.perf_counter())
        reference = np.interp(parsed.mag.t, ces_t, ces_field, left=np.nan, right=np.nan)
        inside = np.isfinite(reference)
        b, r, mag_t = parsed.mag.b[inside], reference[inside], parsed.mag.t[inside]
        t.append(time.perf_counter())
        keep = screen.screen_samples(mag_t, b, r).keep if screen is not None else None
        t.append(time.perf_counter())
        result = calibrate_scalar(b, r, keep=keep)
        t.append(time.perf_counter())
        for k, name in enumerate(names[:-1]):
            stages[name].append(t[k + 1] - t[k])
        stages["total"].append(t[-1] - t[0])
        del data, parsed
    if screen is None:
        stages["screen_reference"] = stages["screen_samples"] = None
    goal = GOAL_HOURS_SECONDS.get(hours)
    total = summary(stages["total"])
    out = {"hours": hours, "log": key, "log_bytes": path.stat().st_size,
           "log_made_seconds": made, "samples": int(inside.size),
           "samples_fitted": int(result.kept.sum()) if result.kept is not None else None,
           "screening": screen is not None,
           "rejected_by_screen": None if keep is None else int((~keep).sum()),
           "objective": result.objective, "rms_nT": result.rms,
           "success": bool(result.success),
           "stages": {name: None if values is None else summary(values)
                      for name, values in stages.items()},
           "goal_seconds": goal,
           "goal_met_best": None if goal is None else total["best"] <= goal,
           "goal_met_median": None if goal is None else total["median"] <= goal}
    print(f"{hours} h ({out['samples']:,} samples) log text -> parameters: best "
          f"{total['best']:.2f} s, median {total['median']:.2f} s; median stages: " + ", ".join(
              f"{name} {out['stages'][name]['median']:.3f} s" for name in names[:-1]
              if out["stages"][name] is not None))
    return out


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seeds", type=int, default=20,
                        help="seeds per case of the held-out grid (default: %(default)s)")
    parser.add_argument("--repeats", type=int, default=5,
                        help="repeats of each like-for-like timing (default: %(default)s)")
    parser.add_argument("--hour-repeats", type=int, default=3,
                        help="repeats of the log-to-parameters runs (default: %(default)s)")
    parser.add_argument("--long-hours", type=int, default=10,
                        help="length of the long flight in hours (default: %(default)s)")
    parser.add_argument("--output", type=Path, default=DEFAULT_OUTPUT)
    args = parser.parse_args(argv)
    if min(args.seeds, args.repeats, args.hour_repeats, args.long_hours) < 1:
        parser.error("seeds, repeats and hours must be at least 1")
    load_start = load()
    numba.set_num_threads(1)
    threading = {"threads": numba.get_num_threads(),
                 "threading_layer": numba.threading_layer()
                 if numba.get_num_threads() else None,
                 "NUMBA_NUM_THREADS": numba.config.NUMBA_NUM_THREADS}
    started = time.perf_counter()
    with InScratch():                      # pyswarms writes report.log where it runs
        startup = calib_run.startup_times(1)
        startup["first_calls_in_process"] = first_calls()
        threading["threading_layer"] = numba.threading_layer()
        print("start-up: " + ", ".join(f"{k} {v:.2f} s" for k, v in startup.items()
                                       if isinstance(v, float)))
        rows, magyc, why = grid(range(args.seeds))
        times = timing((2000, 20000), args.repeats)
        blas = blas_threads(args.repeats)
    grid_done = time.perf_counter()
    hours = [log_to_parameters(1, args.hour_repeats),
             log_to_parameters(args.long_hours, args.hour_repeats)]
    write_report(args.output, "calib_heldout", argv, load_start,
                 packages("numpy", "numba", "scipy", "pyswarms"),
                 numba_threading=threading,
                 blas_threads={"variables": {name: os.environ.get(name)
                                             for name in BLAS_VARIABLES},
                               "default_against_one": blas},
                 settings={"coverages": COVERAGES, "error_models": ERROR_MODELS,
                           "noises_nT": NOISES, "seeds": args.seeds,
                           "flight_seconds": SECONDS, "rate_hz": RATE,
                           "fit_samples": rows[0]["fit_samples"],
                           "test_samples": rows[0]["test_samples"],
                           "fit": "first half", "score": "second half, against |B_true|",
                           "reference_noise_nT": REFERENCE_NOISE_NT,
                           "collapse_diagonal": COLLAPSE_DIAGONAL,
                           "shrunk_ratio": SHRUNK_RATIO,
                           "particles": PARTICLES, "iterations": ITERATIONS,
                           "pyswarms_options": calib_run.PYSWARMS_OPTIONS,
                           "pyswarms_ring": calib_run.PYSWARMS_RING,
                           "floor_goal": FLOOR_GOAL},
                 peers_python=str(calib_run.PEERS_PYTHON), magyc=magyc, magyc_not_run=why,
                 cases=case_summaries(rows), gate=gate_verdicts(rows),
                 startup=startup, timing=times, log_to_parameters=hours,
                 bench_seconds={"grid_and_timing": grid_done - started,
                                "whole": time.perf_counter() - started})


if __name__ == "__main__":
    sys.exit(main())
