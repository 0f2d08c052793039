"""Calibration benchmark: accuracy against the noise floor, speed against peers.

On seeded synthetic flights (sim.stimulus.scenario) with full-sphere, UAV-like (±30°) and
near-planar (±5°) attitude coverage at noise 5, 20 and 100 nT:

- residual RMS of the total field as a ratio to the noise floor (the true parameters' own
  residual), for maglog's PSO + LM on the paper's objective (``objective="paper"``, the
  issue-5 measurement; the default errors-in-variables fit and the held-out scores are
  bench/calib/heldout.py's);
- scipy ``least_squares`` (from the identity) on the same objective, same ratio and time;
- the PSO stage against ``pyswarms`` like for like: maglog's gbest beside pyswarms'
  ``GlobalBestPSO`` and maglog's ring beside its ``LocalBestPSO``, each on maglog's numba
  cost kernel and on its numpy twin, with the same swarm, iterations, constants, search box
  and repeats; every pairing is recorded, start-up (imports, numba's JIT compile) apart;
- time of a deterministic (LM) fit of 2000 samples, and of a one-hour 50 Hz flight
  (180,000 samples) calibrated end to end from its log file, stage by stage (read, parse,
  align, PSO, polish);
- maglog's ellipsoid fits (algebraic and constrained) against the `magyc` package's
  (``ellipsoid_fit`` and ``ellipsoid_fit_fang``) on the same samples: the total-field ratio
  (each fit's magnitude scaled by the one factor that best matches the reference, as an
  ellipsoid fit knows the shape, not the field), the direction error left after the best
  proper rotation onto the true body field (a reversed axis cannot be rotated away), the
  sign of the calibration matrix, and time. magyc pins numpy < 2, so it runs in its own
  venv (``make bench-peers``) through ``bench/calib/magyc_worker.py``;
- the heading offset found on the straight, level lines of a survey flight with the sensor
  yawed in the airframe, against the truth.

Every timing keeps all its repeats (best, median and worst are derived from them). numba's
kernels run on ``--threads`` threads (default 1, recorded).

Run from the repository root: ``.venv/bin/python bench/calib/run.py``.
"""

import argparse
import json
import os
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numba
import numpy as np

BENCH = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(BENCH))

from _machine import load, packages, write_report

from maglog.calib import _pso
from maglog.calib.ellipsoid import fit_ellipsoid
from maglog.calib.scalar import apply_scalar, calibrate_scalar
from maglog.sim.stimulus.scenario import COVERAGES, ErrorModel, make_flight, make_survey

DEFAULT_OUTPUT = BENCH / "results" / "calib.json"
PEERS_PYTHON = Path(os.environ.get("MAGLOG_PEERS_PYTHON",
                                   BENCH.parent / ".venv-peers" / "bin" / "python"))
NOISES = (5.0, 20.0, 100.0)
#: Bratton and Kennedy's constriction form, v = chi (v + c1 r1 (p - x) + c2 r2 (l - x)), is
#: the inertia form w v + c1' r1 (p - x) + c2' r2 (l - x) of pyswarms with w = chi and
#: c' = chi c.
PYSWARMS_OPTIONS = {"w": _pso.CHI, "c1": _pso.CHI * _pso.C1, "c2": _pso.CHI * _pso.C2}
#: pyswarms' ring (LocalBestPSO): the k nearest particles by position, the particle itself
#: among them (cKDTree.query returns it first, at distance 0), so k = 3 is itself and two
#: neighbours, as maglog's ring; p = 2 is the Euclidean distance; static = neighbours found
#: once, as maglog's ring is fixed.
PYSWARMS_RING = {"k": 3, "p": 2}
PYSWARMS_STATIC = True


def floor_rms(flight):
    k, c = flight.errors.truth()
    return float(np.sqrt(np.mean((np.linalg.norm(apply_scalar(k, c, flight.b_meas), axis=1)
                                  - flight.total) ** 2)))


def repeat(fn, times=5):
    """(last value, every repeat's wall time in seconds)."""
    seconds = []
    for _ in range(times):
        start = time.perf_counter()
        value = fn()
        seconds.append(time.perf_counter() - start)
    return value, seconds


def best_of(fn, times=5):
    value, seconds = repeat(fn, times)
    return value, min(seconds)


def summary(seconds):
    """Best, median and worst of repeats, with every repeat."""
    return {"repeats": len(seconds), "best": min(seconds),
            "median": statistics.median(seconds), "worst": max(seconds),
            "all": list(seconds)}


def scipy_fit(b, r):
    from scipy.optimize import least_squares
    scale = float(np.median(r) / np.median(np.linalg.norm(b, axis=1)))
    x0 = np.array([scale, 0, 0, scale, 0, scale, 0, 0, 0], dtype=float)

    def residual(p):
        k, c = _pso.unpack(p)
        return np.linalg.norm(b @ k.T - c, axis=1) - r
    return least_squares(residual, x0, method="lm")


class InScratch:
    """Runs code in a temporary working directory: pyswarms writes a report.log into the
    working directory when it is imported."""
    def __enter__(self):
        self._here = os.getcwd()
        self._scratch = tempfile.TemporaryDirectory()
        os.chdir(self._scratch.name)

    def __exit__(self, *exc):
        os.chdir(self._here)
        self._scratch.cleanup()


def pyswarms_run(kind, cost, lower, upper, particles, iterations, seed):
    """pyswarms' GlobalBestPSO ("gbest") or LocalBestPSO ("ring") on ``cost`` ((P, 9) -> (P,),
    maglog's kernel), set up as close to maglog's PSO as pyswarms allows: the same constants,
    a velocity clamp of ± the search range per dimension, positions held at the box's wall.
    Returns (best cost, best position)."""
    import pyswarms
    np.random.seed(seed)              # pyswarms draws from numpy's global generator
    span = upper - lower
    common = dict(n_particles=particles, dimensions=len(lower), bounds=(lower, upper),
                  velocity_clamp=(-span, span), bh_strategy="nearest",
                  vh_strategy="unmodified")
    if kind == "gbest":
        optimizer = pyswarms.single.GlobalBestPSO(options=dict(PYSWARMS_OPTIONS), **common)
    else:
        optimizer = pyswarms.single.LocalBestPSO(options=dict(PYSWARMS_OPTIONS, **PYSWARMS_RING),
                                                 static=PYSWARMS_STATIC, **common)
    return optimizer.optimize(cost, iters=iterations, verbose=False)


def startup_times(threads):
    """Start-up costs kept out of the PSO timings, each in a fresh interpreter: importing
    pyswarms; importing maglog's PSO (numba); the first call of the numba kernel with an
    empty cache (JIT compile) and with the cache the first filled (load)."""
    probe = ("import time, numpy as np\n"
             "t0 = time.perf_counter()\n"
             "from maglog.calib import _pso\n"
             "t1 = time.perf_counter()\n"
             "_pso.cost_numba(np.ones((4, 9)), np.ones((10, 3)), np.ones(10))\n"
             "t2 = time.perf_counter()\n"
             "print(t1 - t0, t2 - t1)\n")
    out = {}
    with tempfile.TemporaryDirectory() as scratch:
        env = dict(os.environ, NUMBA_CACHE_DIR=scratch, NUMBA_NUM_THREADS=str(threads))
        for name in ("cold_cache", "warm_cache"):
            done = subprocess.run([sys.executable, "-c", probe], capture_output=True,
                                  text=True, env=env, cwd=scratch, check=True)
            imported, first = map(float, done.stdout.split())
            out[f"maglog_pso_import_seconds_{name}"] = imported
            out[f"numba_first_call_seconds_{name}"] = first
        done = subprocess.run([sys.executable, "-c",
                               "import time; t = time.perf_counter(); import pyswarms; "
                               "print(time.perf_counter() - t)"],
                              capture_output=True, text=True, cwd=scratch)
        out["pyswarms_import_seconds"] = float(done.stdout) if done.returncode == 0 else None
    return out


def pso_comparison(b, r, lower, upper, *, particles=40, iterations=300, repeats=5,
                   threads=1):
    """maglog's PSO ({ring, gbest} x {numba, numpy} cost) against pyswarms' (LocalBestPSO,
    GlobalBestPSO) on the same two costs: the same repeats for each, every repeat kept."""
    costs = {"numba": lambda x: _pso.cost_numba(x, b, r),
             "numpy": lambda x: _pso.cost_numpy(x, b, r)}
    costs["numba"](np.tile(lower, (2, 1)))           # compiled (or loaded) before timing
    runs = {}
    for topology in ("gbest", "ring"):
        for kernel, cost in costs.items():
            results, seconds = [], []
            for k in range(repeats):
                start = time.perf_counter()
                _, best_cost, _, _ = _pso.pso(cost, lower, upper, particles=particles,
                                              iterations=iterations, seed=k,
                                              topology=topology)
                seconds.append(time.perf_counter() - start)
                results.append(float(best_cost))
            runs[f"maglog_{topology}_{kernel}"] = {
                "optimiser": "maglog", "topology": topology, "kernel": kernel,
                "seconds": summary(seconds), "best_costs": results,
                "cost_evaluations": iterations + 1}
            print(f"PSO maglog {topology:5s} on {kernel}: best {min(seconds) * 1e3:.0f} ms, "
                  f"median {statistics.median(seconds) * 1e3:.0f} ms")
    try:
        with InScratch():
            import pyswarms
            for topology, name in (("gbest", "GlobalBestPSO"), ("ring", "LocalBestPSO")):
                for kernel, cost in costs.items():
                    results, seconds = [], []
                    for k in range(repeats):
                        start = time.perf_counter()
                        best_cost, _ = pyswarms_run(topology, cost, lower, upper, particles,
                                                    iterations, seed=k)
                        seconds.append(time.perf_counter() - start)
                        results.append(float(best_cost))
                    runs[f"pyswarms_{topology}_{kernel}"] = {
                        "optimiser": f"pyswarms {name}", "topology": topology,
                        "kernel": kernel, "seconds": summary(seconds),
                        "best_costs": results, "cost_evaluations": iterations}
                    print(f"PSO pyswarms {name} on {kernel}: best {min(seconds) * 1e3:.0f} "
                          f"ms, median {statistics.median(seconds) * 1e3:.0f} ms")
        version = pyswarms.__version__
    except ImportError:
        version = None
    pairings = []
    for ours in (key for key in runs if key.startswith("maglog_")):
        for theirs in (key for key in runs if key.startswith("pyswarms_")):
            a, b_ = runs[ours], runs[theirs]
            pairings.append({
                "maglog": ours, "pyswarms": theirs,
                "like_for_like": a["topology"] == b_["topology"] and a["kernel"] == b_["kernel"],
                "speedup_median": b_["seconds"]["median"] / a["seconds"]["median"],
                "speedup_best": b_["seconds"]["best"] / a["seconds"]["best"]})
    return {
        "samples": len(b), "particles": particles, "iterations": iterations,
        "repeats": repeats, "numba_threads": threads, "pyswarms": version,
        "search_box": {"lower": lower.tolist(), "upper": upper.tolist()},
        "maglog_settings": {"chi": _pso.CHI, "c1": _pso.C1, "c2": _pso.C2,
                            "velocity_clamp": "± (upper - lower) per dimension",
                            "initial_velocity": "uniform in ± (upper - lower) / 2",
                            "walls": "position clipped to the box, that velocity component "
                                     "zeroed",
                            "neighbourhood": "ring: itself and its two index neighbours, "
                                             "fixed",
                            "seeds": list(range(repeats))},
        "pyswarms_settings": {"options": PYSWARMS_OPTIONS, "ring": PYSWARMS_RING,
                              "static": PYSWARMS_STATIC,
                              "velocity_clamp": "± (upper - lower) per dimension",
                              "initial_velocity": "uniform in the clamp, ± (upper - lower)",
                              "walls": "bh_strategy nearest (clipped), velocity unchanged "
                                       "(vh_strategy unmodified)",
                              "neighbourhood": "ring: itself and the 2 nearest particles "
                                               "by Euclidean distance in parameter space, "
                                               "found once from the initial positions "
                                               "(static)",
                              "seeds": f"numpy.random.seed(0..{repeats - 1})"},
        "runs": runs, "pairings": pairings,
    }


def kabsch_angles(vectors, truth):
    """Angles (deg) between the calibrated directions and the true ones after the best
    proper rotation (det +1) of the calibrated frame."""
    u = vectors / np.linalg.norm(vectors, axis=1)[:, None]
    v = truth / np.linalg.norm(truth, axis=1)[:, None]
    left, _, right = np.linalg.svd(u.T @ v)
    d = np.sign(np.linalg.det(right.T @ left.T))
    rotation = right.T @ np.diag([1.0, 1.0, d]) @ left.T
    return np.degrees(np.arccos(np.clip(np.sum((u @ rotation.T) * v, axis=1), -1, 1)))


def ellipsoid_metrics(vectors, matrix, flight, floor):
    magnitude = np.linalg.norm(vectors, axis=1)
    scale = float(magnitude @ flight.total / (magnitude @ magnitude))
    rms = float(np.sqrt(np.mean((scale * magnitude - flight.total) ** 2)))
    angles = kabsch_angles(vectors, flight.b_earth)
    symmetric = (matrix + matrix.T) / 2
    return {"ratio": rms / floor, "direction_rms_deg": float(np.sqrt(np.mean(angles ** 2))),
            "det": float(np.linalg.det(matrix)),
            "positive_definite": bool(np.all(np.linalg.eigvalsh(symmetric) > 0))}


def magyc_fits(samples):
    """magyc's ellipsoid fits on each (N, 3) array, through the peers' venv."""
    if not PEERS_PYTHON.exists():
        return None, f"{PEERS_PYTHON} not found: run `make bench-peers`"
    with tempfile.TemporaryDirectory() as scratch:
        path = Path(scratch) / "samples.npz"
        np.savez(path, **samples)
        done = subprocess.run([str(PEERS_PYTHON), str(BENCH / "calib" / "magyc_worker.py"),
                               str(path)], capture_output=True, text=True, cwd=scratch)
    if done.returncode != 0:
        return None, f"magyc worker failed: {done.stderr.strip().splitlines()[-1:]}"
    return json.loads(done.stdout), None


def ellipsoid_section(flights):
    rows = []
    peers, why = magyc_fits({key: f.b_meas for key, (f, _) in flights.items()})
    for key, (flight, floor) in flights.items():
        row = {"case": key}
        for method in ("algebraic", "constrained"):
            # No gate: magyc has none, and the fit's accuracy is what is compared (the gate
            # about the fitted centre refuses the UAV and near-planar flights).
            fit, seconds = best_of(lambda: fit_ellipsoid(flight.b_meas,
                                                         float(np.median(flight.total)),
                                                         method=method, gate=False), 3)
            if fit.success:
                vectors = (flight.b_meas - fit.center) @ fit.W.T
                row[f"maglog_{method}"] = dict(ellipsoid_metrics(vectors, fit.W, flight,
                                                                 floor), seconds=seconds)
            else:
                row[f"maglog_{method}"] = {"refused": fit.message, "seconds": seconds}
        if peers is None:
            row["magyc"] = {"not_run": why}
        else:
            for name, got in peers["cases"][key].items():
                if "error" in got:
                    row[f"magyc_{name}"] = {"error": got["error"]}
                    continue
                inverse = np.linalg.inv(np.array(got["soft_iron"]))
                vectors = (flight.b_meas - np.array(got["hard_iron"])) @ inverse.T
                metrics = ellipsoid_metrics(vectors, inverse, flight, floor)
                finite = bool(np.all(np.isfinite(vectors)))
                head = np.array(got["calibrated_head"])
                # Does the field magyc returns agree with its own parameters? And with the
                # same parameters applied to the (N, 3) samples reshaped (not transposed)
                # to 3 x N?
                own = bool(np.allclose(head, vectors[:len(head)], rtol=1e-6, atol=1e-3))
                hard = np.array(got["hard_iron"])[:, None]
                reshaped = (inverse @ (flight.b_meas.reshape(3, -1) - hard)).T
                as_reshaped = bool(np.allclose(head, reshaped[:len(head)], rtol=1e-6,
                                               atol=1e-3))
                # The soft-iron matrix used directly instead of its inverse.
                direct = np.array(got["soft_iron"])
                direct_metrics = ellipsoid_metrics(
                    (flight.b_meas - np.array(got["hard_iron"])) @ direct.T, direct, flight,
                    floor)
                row[f"magyc_{name}"] = dict(metrics, seconds=got["seconds"], finite=finite,
                                            returned_field_matches_parameters=own,
                                            returned_field_matches_reshaped_input=as_reshaped,
                                            soft_iron_used_directly_ratio=direct_metrics[
                                                "ratio"],
                                            warnings=got["warnings"])
        rows.append(row)
        print(f"ellipsoid {key}: " + "; ".join(
            f"{name} " + (f"ratio {m['ratio']:.3f}, direction {m['direction_rms_deg']:.2f} deg"
                          f"{'' if m['positive_definite'] else ', NOT positive definite'}"
                          if "ratio" in m else str(next(iter(m.values()))))
            for name, m in row.items() if name != "case"))
    return rows, (None if peers is None else {"numpy": peers["numpy"]})


def heading_section():
    """The heading offset ``maglog calibrate`` finds from the course over ground on a
    survey's lines, against the truth (the constant part of the heading error computed
    with the true attitude)."""
    from maglog.calib.heading import (tilt_compensated_heading, true_heading,
                                      wrap_degrees)
    from maglog.calib.pipeline import calibrate_card
    rows = []
    for yaw in (0.0, 3.0, -6.0):
        flight = make_survey(errors=ErrorModel(mounting=(0.0, 0.0, yaw)), seed=11)
        with tempfile.TemporaryDirectory() as scratch:
            path = Path(scratch) / "LOG00001.TXT"
            path.write_bytes(flight.log())
            run = calibrate_card(path)
        analysis, alignment = run.heading, run.heading.alignment
        truth_t = flight.t + flight.start_seconds_of_day
        roll = np.interp(run.t, truth_t, flight.roll)
        pitch = np.interp(run.t, truth_t, flight.pitch)
        truth = np.interp(run.t, truth_t, np.degrees(np.unwrap(flight.heading)))
        error = wrap_degrees(true_heading(tilt_compensated_heading(run.vectors, roll, pitch),
                                          analysis.declination) - truth)
        means = [float(np.mean(error[(run.t >= leg.start) & (run.t <= leg.end)]))
                 for leg in analysis.legs]
        constant = float(np.mean(means))            # equal numbers of legs each way
        row = {"mounting_yaw_deg": yaw, "legs": len(analysis.legs),
               "true_offset_deg": constant, "found_offset_deg": alignment.offset,
               "found_std_deg": alignment.offset_std}
        rows.append(row)
        print(f"heading: mounting yaw {yaw:+.1f} deg: offset true {constant:+.2f}, found "
              f"{alignment.offset:+.2f} +- {alignment.offset_std:.2f} deg from "
              f"{len(analysis.legs)} legs")
    return rows


def thread_scaling(b, r, lower, upper, repeats, particles=40, iterations=300):
    """maglog's ring PSO on the numba cost with 1 thread and with every thread numba has:
    what the thread count chosen for the benchmark costs or saves on this machine now."""
    out = []
    for threads in sorted({1, numba.config.NUMBA_NUM_THREADS}):
        numba.set_num_threads(threads)
        _, seconds = repeat(lambda: _pso.pso(lambda x: _pso.cost_numba(x, b, r, threads=True),
                                             lower, upper, particles=particles,
                                             iterations=iterations, seed=0), repeats)
        out.append({"threads": threads, "seconds": summary(seconds)})
        print(f"PSO maglog ring on numba, {threads} thread(s): best {min(seconds) * 1e3:.0f} "
              f"ms, median {statistics.median(seconds) * 1e3:.0f} ms")
    return out


class StageClock:
    """Times the PSO inside ``calibrate_scalar`` by wrapping ``_pso.pso`` while it runs (the
    rest of the call is the polish, the uncertainties and the checks)."""
    def __init__(self):
        self.seconds = []

    def __enter__(self):
        self._pso = _pso.pso

        def timed(*args, **kwargs):
            start = time.perf_counter()
            try:
                return self._pso(*args, **kwargs)
            finally:
                self.seconds.append(time.perf_counter() - start)
        _pso.pso = timed
        return self

    def __exit__(self, *exc):
        _pso.pso = self._pso


def hour_flight(repeats):
    """A one-hour 50 Hz flight from its log file to parameters, stage by stage: read the
    file, parse it, align the cesium reference to the magnetometer's times, then
    ``calibrate_scalar`` (PSO, then the polish and the rest)."""
    from maglog.calib.logparse import parse_log
    hour = make_flight(coverage="uav", seconds=3600, rate=50, seed=9)
    stages = {name: [] for name in ("read", "parse", "align", "pso", "polish_and_rest",
                                    "total")}
    with tempfile.TemporaryDirectory() as scratch:
        path = Path(scratch) / "LOG00001.TXT"
        path.write_bytes(hour.log(mag_rate=50))
        size = path.stat().st_size
        for _ in range(repeats):
            t0 = time.perf_counter()
            data = path.read_bytes()
            t1 = time.perf_counter()
            parsed = parse_log(data)
            t2 = time.perf_counter()
            ces = parsed.cesium
            reference = np.interp(parsed.mag.t, ces.t, ces.field)
            keep = np.isfinite(reference)
            b, r = parsed.mag.b[keep], reference[keep]
            t3 = time.perf_counter()
            with StageClock() as clock:
                result = calibrate_scalar(b, r, objective="paper", kernel="numba")
            t4 = time.perf_counter()
            pso_seconds = sum(clock.seconds) if clock.seconds else None
            for name, value in (("read", t1 - t0), ("parse", t2 - t1), ("align", t3 - t2),
                                ("pso", pso_seconds),
                                ("polish_and_rest", None if pso_seconds is None else
                                 t4 - t3 - pso_seconds),
                                ("total", t4 - t0)):
                stages[name].append(value)
    out = {"samples": int(len(parsed.mag.b)), "samples_fitted": int(keep.sum()),
           "log_bytes": size, "rms_nT": result.rms, "success": result.success,
           "message": result.message,
           "stages": {name: summary(values) if None not in values else None
                      for name, values in stages.items()}}
    total = out["stages"]["total"]
    # The stages of the fastest whole run, and each stage's share of it.
    fastest = stages["total"].index(total["best"])
    out["fastest_run_stages"] = {name: values[fastest] for name, values in stages.items()}
    print(f"one-hour 50 Hz flight ({out['samples']} samples) from log file to parameters: "
          f"best of {repeats} {total['best']:.2f} s, median {total['median']:.2f} s, worst "
          f"{total['worst']:.2f} s; fastest run: " + ", ".join(
              f"{name} {value:.3f} s" for name, value in out["fastest_run_stages"].items()
              if value is not None and name != "total"))
    return out


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seconds", type=float, default=100.0,
                        help="flight length for the accuracy runs (default: %(default)s)")
    parser.add_argument("--threads", type=int, default=1,
                        help="numba threads for the cost kernel (default: %(default)s)")
    parser.add_argument("--pso-repeats", type=int, default=5,
                        help="repeats of each PSO run (default: %(default)s)")
    parser.add_argument("--hour-repeats", type=int, default=3,
                        help="repeats of the one-hour flight (default: %(default)s)")
    parser.add_argument("--output", type=Path, default=DEFAULT_OUTPUT)
    args = parser.parse_args(argv)
    load_start = load()
    numba.set_num_threads(args.threads)
    warm = make_flight(coverage="full", seconds=10, seed=1)
    calibrate_scalar(warm.b_meas, warm.total)       # JIT compile (or cache load), imports
    threading = {"threads": numba.get_num_threads(),
                 "threading_layer": numba.threading_layer(),
                 "NUMBA_NUM_THREADS": numba.config.NUMBA_NUM_THREADS}
    print(f"numba: {threading['threads']} thread(s), {threading['threading_layer']} layer")

    accuracy = []
    flights = {}
    for coverage in COVERAGES:
        for noise in NOISES:
            flight = make_flight(coverage=coverage, seconds=args.seconds, seed=7,
                                 errors=ErrorModel(noise=noise))
            floor = floor_rms(flight)
            flights[f"{coverage}_{noise:g}"] = (flight, floor)
            ours, t_ours = repeat(lambda: calibrate_scalar(flight.b_meas, flight.total,
                                                           objective="paper"), 3)
            theirs, t_scipy = repeat(lambda: scipy_fit(flight.b_meas, flight.total), 3)
            scipy_rms = float(np.sqrt(np.mean(theirs.fun ** 2)))
            k, c = _pso.unpack(theirs.x)
            row = {"coverage": coverage, "noise_nT": noise, "samples": len(flight.b_meas),
                   "floor_rms_nT": floor, "maglog_ratio": ours.rms / floor,
                   "maglog_seconds": min(t_ours), "maglog_timing": summary(t_ours),
                   "maglog_warnings": ours.warnings, "maglog_success": ours.success,
                   "scipy_ratio": scipy_rms / floor, "scipy_seconds": min(t_scipy),
                   "scipy_timing": summary(t_scipy), "scipy_status": int(theirs.status),
                   "scipy_k_diagonal": np.diag(k).tolist(),
                   "scipy_c_norm_nT": float(np.linalg.norm(c)),
                   "reference_median_nT": float(np.median(flight.total))}
            accuracy.append(row)
            print(f"{coverage:7s} noise {noise:5.0f} nT: maglog {row['maglog_ratio']:.4f} "
                  f"({min(t_ours) * 1e3:.0f} ms), scipy least_squares {row['scipy_ratio']:.4f} "
                  f"({min(t_scipy) * 1e3:.0f} ms)")

    flight = make_flight(coverage="uav", seconds=40, rate=50, seed=8)
    b, r = flight.b_meas[:2000], flight.total[:2000]
    _, t_lm = repeat(lambda: calibrate_scalar(b, r, method="lm", objective="paper"), 20)
    print(f"deterministic (LM) fit of 2000 samples: best {min(t_lm) * 1e3:.2f} ms, median "
          f"{statistics.median(t_lm) * 1e3:.2f} ms")

    lower = np.array([0.5, -0.5, -0.5, 0.5, -0.5, 0.5, -3e4, -3e4, -3e4])
    upper = np.array([2.0, 0.5, 0.5, 2.0, 0.5, 2.0, 3e4, 3e4, 3e4])
    startup = startup_times(args.threads)
    print("start-up: " + ", ".join(f"{key} {value:.2f} s" for key, value in startup.items()
                                   if value is not None))
    comparison = pso_comparison(b, r, lower, upper, repeats=args.pso_repeats,
                                threads=numba.get_num_threads())
    comparison["startup"] = startup
    comparison["thread_scaling"] = thread_scaling(b, r, lower, upper, args.pso_repeats)
    numba.set_num_threads(args.threads)
    for pairing in comparison["pairings"]:
        if pairing["like_for_like"]:
            print(f"like for like: {pairing['pyswarms']} / {pairing['maglog']}: "
                  f"{pairing['speedup_median']:.1f}x (median), "
                  f"{pairing['speedup_best']:.1f}x (best)")

    hour = hour_flight(args.hour_repeats)

    ellipsoids, peers = ellipsoid_section(flights)
    headings = heading_section()

    write_report(args.output, "calib", argv, load_start,
                 packages("numpy", "numba", "scipy", "pyswarms"),
                 numba_threading=threading,
                 ellipsoid=ellipsoids, peers_venv=peers, heading=headings,
                 accuracy=accuracy, lm_2000_seconds=min(t_lm), lm_2000_timing=summary(t_lm),
                 pso_comparison=comparison, hour_flight=hour)


if __name__ == "__main__":
    sys.exit(main())
