"""Calibration benchmark: accuracy against the noise floor, speed against peers.

On seeded synthetic flights (sim.scenario) with full-sphere, UAV-like (±30°) and
near-planar (±5°) attitude coverage at noise 5, 20 and 100 nT:

- residual RMS of the total field as a ratio to the noise floor (the true parameters' own
  residual), for maglog's PSO + LM;
- scipy ``least_squares`` (from the identity) on the same objective, same ratio and time;
- the PSO stage against ``pyswarms`` (GlobalBestPSO) with the same swarm size and
  iterations on the same objective (time), when pyswarms is installed;
- time of a deterministic (LM) fit of 2000 samples, and of a one-hour 50 Hz flight
  (180,000 samples) calibrated end to end from its log text;
- maglog's ellipsoid fits (algebraic and constrained) against the `magyc` package's
  (``ellipsoid_fit`` and ``ellipsoid_fit_fang``) on the same samples: the total-field ratio
  (each fit's magnitude scaled by the one factor that best matches the reference, as an
  ellipsoid fit knows the shape, not the field), the direction error left after the best
  proper rotation onto the true body field (a reversed axis cannot be rotated away), the
  sign of the calibration matrix, and time. magyc pins numpy < 2, so it runs in its own
  venv (``make bench-peers``) through ``bench/calib/magyc_worker.py``;
- the heading offset found on the straight, level lines of a survey flight with the sensor
  yawed in the airframe, against the truth.

Run from the repository root: ``.venv/bin/python bench/calib/run.py``.
"""

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

BENCH = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(BENCH))

from _machine import load, packages, write_report

from maglog.calib import _pso
from maglog.calib.ellipsoid import fit_ellipsoid
from maglog.calib.scalar import apply_scalar, calibrate_scalar
from maglog.sim.scenario import COVERAGES, ErrorModel, make_flight, make_survey

DEFAULT_OUTPUT = BENCH / "results" / "calib.json"
PEERS_PYTHON = Path(os.environ.get("MAGLOG_PEERS_PYTHON",
                                   BENCH.parent / ".venv-peers" / "bin" / "python"))
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
            fit, seconds = best_of(lambda: fit_ellipsoid(flight.b_meas,
                                                         float(np.median(flight.total)),
                                                         method=method), 3)
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
                # Does the field magyc returns agree with its own parameters?
                own = bool(np.allclose(head, vectors[:len(head)], rtol=1e-6, atol=1e-3))
                row[f"magyc_{name}"] = dict(metrics, seconds=got["seconds"], finite=finite,
                                            returned_field_matches_parameters=own,
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


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seconds", type=float, default=100.0,
                        help="flight length for the accuracy runs (default: %(default)s)")
    parser.add_argument("--output", type=Path, default=DEFAULT_OUTPUT)
    args = parser.parse_args(argv)
    load_start = load()
    calibrate_scalar(np.eye(3).repeat(4, axis=0) * 5e4 + 1, 5e4)      # JIT warm-up

    accuracy = []
    flights = {}
    for coverage in COVERAGES:
        for noise in NOISES:
            flight = make_flight(coverage=coverage, seconds=args.seconds, seed=7,
                                 errors=ErrorModel(noise=noise))
            floor = floor_rms(flight)
            flights[f"{coverage}_{noise:g}"] = (flight, floor)
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
    hour_times = []
    for _ in range(3):
        start = time.perf_counter()
        parsed = parse_log(text)
        ces = parsed.cesium
        reference = np.interp(parsed.mag.t, ces.t, ces.field)
        keep = np.isfinite(reference)
        result = calibrate_scalar(parsed.mag.b[keep], reference[keep])
        hour_times.append(time.perf_counter() - start)
    t_hour = min(hour_times)
    print(f"one-hour 50 Hz flight ({len(parsed.mag.b)} samples) from log text to "
          f"parameters: best of 3 {t_hour:.2f} s, worst {max(hour_times):.2f} s "
          f"(RMS {result.rms:.2f} nT)")

    ellipsoids, peers = ellipsoid_section(flights)
    headings = heading_section()

    write_report(args.output, "calib", argv, load_start,
                 packages("numpy", "numba", "scipy", "pyswarms"),
                 ellipsoid=ellipsoids, peers_venv=peers, heading=headings,
                 accuracy=accuracy, lm_2000_seconds=t_lm, pso_stage=pso_row,
                 hour_flight={"samples": int(len(parsed.mag.b)), "seconds": t_hour,
                              "worst_seconds": max(hour_times),
                              "rms_nT": result.rms})


if __name__ == "__main__":
    sys.exit(main())
