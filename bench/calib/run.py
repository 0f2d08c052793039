"""Calibration benchmark: accuracy against the noise floor, speed against peers.

On seeded synthetic flights (sim.scenario) with full-sphere, UAV-like (±30°) and
near-planar (±5°) attitude coverage at noise 5, 20 and 100 nT:

- residual RMS of the total field as a ratio to the noise floor (the true parameters' own
  residual), for maglog's PSO + LM;
- scipy ``least_squares`` (from the identity) on the same objective, same ratio and time;
- the PSO stage against ``pyswarms`` (GlobalBestPSO) with the same swarm size and
  iterations on the same objective (time), when pyswarms is installed;
- time of a deterministic (LM) fit of 2000 samples, and of a one-hour 50 Hz flight
  (180,000 samples) calibrated end to end from its log text.

Run from the repository root: ``.venv/bin/python bench/calib/run.py``.
"""

import argparse
import sys
import time
from pathlib import Path

import numpy as np

BENCH = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(BENCH))

from _machine import load, packages, write_report

from maglog.calib import _pso
from maglog.calib.scalar import apply_scalar, calibrate_scalar
from maglog.sim.scenario import COVERAGES, ErrorModel, make_flight

DEFAULT_OUTPUT = BENCH / "results" / "calib.json"
NOISES = (5.0, 20.0, 100.0)


def floor_rms(flight):
    k, c = flight.errors.truth()
    return float(np.sqrt(np.mean((np.linalg.norm(apply_scalar(k, c, flight.b_meas), axis=1)
                                  - flight.total) ** 2)))


def best_of(fn, repeat=5):
    times = []
    for _ in range(repeat):
        start = time.perf_counter()
        value = fn()
        times.append(time.perf_counter() - start)
    return value, min(times)


def scipy_fit(b, r):
    from scipy.optimize import least_squares
    scale = float(np.median(r) / np.median(np.linalg.norm(b, axis=1)))
    x0 = np.array([scale, 0, 0, scale, 0, scale, 0, 0, 0], dtype=float)

    def residual(p):
        k, c = _pso.unpack(p)
        return np.linalg.norm(b @ k.T - c, axis=1) - r
    return least_squares(residual, x0, method="lm")


def pyswarms_stage(b, r, particles, iterations, lower, upper):
    import os
    import tempfile
    # pyswarms writes a report.log into the working directory on import: keep it out of
    # the tree.
    here = os.getcwd()
    with tempfile.TemporaryDirectory() as scratch:
        os.chdir(scratch)
        try:
            return _pyswarms_run(b, r, particles, iterations, lower, upper)
        finally:
            os.chdir(here)


def _pyswarms_run(b, r, particles, iterations, lower, upper):
    import pyswarms
    options = {"c1": 1.49618, "c2": 1.49618, "w": 0.72984}
    optimizer = pyswarms.single.GlobalBestPSO(n_particles=particles, dimensions=9,
                                              options=options, bounds=(lower, upper))
    return optimizer.optimize(lambda x: _pso.cost_numpy(x, b, r), iters=iterations,
                              verbose=False)


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seconds", type=float, default=100.0,
                        help="flight length for the accuracy runs (default: %(default)s)")
    parser.add_argument("--output", type=Path, default=DEFAULT_OUTPUT)
    args = parser.parse_args(argv)
    load_start = load()
    calibrate_scalar(np.eye(3).repeat(4, axis=0) * 5e4 + 1, 5e4)      # JIT warm-up

    accuracy = []
    for coverage in COVERAGES:
        for noise in NOISES:
            flight = make_flight(coverage=coverage, seconds=args.seconds, seed=7,
                                 errors=ErrorModel(noise=noise))
            floor = floor_rms(flight)
            ours, t_ours = best_of(lambda: calibrate_scalar(flight.b_meas, flight.total), 3)
            theirs, t_scipy = best_of(lambda: scipy_fit(flight.b_meas, flight.total), 3)
            scipy_rms = float(np.sqrt(np.mean(theirs.fun ** 2)))
            row = {"coverage": coverage, "noise_nT": noise, "samples": len(flight.b_meas),
                   "floor_rms_nT": floor, "maglog_ratio": ours.rms / floor,
                   "maglog_seconds": t_ours, "maglog_warnings": ours.warnings,
                   "scipy_ratio": scipy_rms / floor, "scipy_seconds": t_scipy}
            accuracy.append(row)
            print(f"{coverage:7s} noise {noise:5.0f} nT: maglog {row['maglog_ratio']:.4f} "
                  f"({t_ours * 1e3:.0f} ms), scipy least_squares {row['scipy_ratio']:.4f} "
                  f"({t_scipy * 1e3:.0f} ms)")

    flight = make_flight(coverage="uav", seconds=40, rate=50, seed=8)
    b, r = flight.b_meas[:2000], flight.total[:2000]
    _, t_lm = best_of(lambda: calibrate_scalar(b, r, method="lm"), 20)
    print(f"deterministic (LM) fit of 2000 samples: {t_lm * 1e3:.2f} ms")

    lower = np.array([0.5, -0.5, -0.5, 0.5, -0.5, 0.5, -3e4, -3e4, -3e4])
    upper = np.array([2.0, 0.5, 0.5, 2.0, 0.5, 2.0, 3e4, 3e4, 3e4])
    _, t_pso = best_of(lambda: _pso.pso(lambda x: _pso.cost_numba(x, b, r), lower, upper,
                                        particles=40, iterations=300, seed=1), 3)
    pso_row = {"samples": 2000, "particles": 40, "iterations": 300, "maglog_seconds": t_pso}
    try:
        _, t_pyswarms = best_of(lambda: pyswarms_stage(b, r, 40, 300, lower, upper), 1)
        pso_row.update(pyswarms_seconds=t_pyswarms, speedup=t_pyswarms / t_pso)
        print(f"PSO stage (40 particles, 300 iterations, 2000 samples): maglog "
              f"{t_pso * 1e3:.0f} ms, pyswarms {t_pyswarms * 1e3:.0f} ms "
              f"({t_pyswarms / t_pso:.1f}x)")
    except ImportError:
        pso_row["pyswarms_seconds"] = None
        print(f"PSO stage: maglog {t_pso * 1e3:.0f} ms (pyswarms not installed)")

    from maglog.calib.logparse import parse_log
    hour = make_flight(coverage="uav", seconds=3600, rate=50, seed=9)
    text = hour.log(mag_rate=50)
    start = time.perf_counter()
    parsed = parse_log(text)
    ces = parsed.cesium
    reference = np.interp(parsed.mag.t, ces.t, ces.field)
    keep = np.isfinite(reference)
    result = calibrate_scalar(parsed.mag.b[keep], reference[keep])
    t_hour = time.perf_counter() - start
    print(f"one-hour 50 Hz flight ({len(parsed.mag.b)} samples) from log text to "
          f"parameters: {t_hour:.2f} s (RMS {result.rms:.2f} nT)")

    write_report(args.output, "calib", argv, load_start,
                 packages("numpy", "numba", "scipy", "pyswarms"),
                 accuracy=accuracy, lm_2000_seconds=t_lm, pso_stage=pso_row,
                 hour_flight={"samples": int(len(parsed.mag.b)), "seconds": t_hour,
                              "rms_nT": result.rms})


if __name__ == "__main__":
    sys.exit(main())
