"""The scalar calibration's polish: the hand-written Levenberg-Marquardt maglog had against
``scipy.optimize.least_squares`` (MINPACK's "lm", and the bounded "trf").

On the project's cases -- 2,000 samples of sim.stimulus.scenario flights with full-sphere, UAV-like
(±30°) and near-planar (±5°) attitude coverage -- each polish starts from the isotropic
identity (``calibrate_scalar(method="lm")``) and from the swarm's best (the PSO + polish
path), with the box calib.scalar uses. Recorded per case and start: the best-of-N time,
the cost and residual RMS reached, evaluations or iterations, scipy's status, and the
largest difference of K and c from the "lm" solution.

The hand-written LM is kept here, as it was in calib/scalar.py up to commit a8b714c (it had
no convergence status: it stopped when a step decreased the cost by less than 1e-12 of it,
when twenty damping increases found no decrease, or at 200 iterations, and called all of
them "converged"), so that the decision to replace it can be re-checked.

Run from the repository root: ``.venv/bin/python bench/calib/lm.py``; writes
``bench/results/calib_lm.json``.
"""

import argparse
import sys
import time
from pathlib import Path

import numpy as np

BENCH = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(BENCH))

from _machine import load, packages, write_report

from maglog.calib import _pso, scalar
from maglog.sim.stimulus.scenario import COVERAGES, make_flight

DEFAULT_OUTPUT = BENCH / "results" / "calib_lm.json"


def hand_lm(p, b, r, lower, upper, *, max_iter=200, tol=1e-12):
    """calib.scalar._lm of commit a8b714c (without the prior rows): damped Gauss-Newton
    steps projected into the box. Returns (x, cost, iterations, how it stopped)."""
    e, u, norm = scalar._residuals(p, b, r)
    cost = float(e @ e)
    lam = 1e-3
    it = 0
    stop = "iteration limit"
    for it in range(1, max_iter + 1):
        j = scalar._jacobian(u, norm, b)
        a = j.T @ j
        g = j.T @ e
        improved = False
        for _ in range(20):
            try:
                step = np.linalg.solve(a + lam * np.diag(np.diag(a) + 1e-12), -g)
            except np.linalg.LinAlgError:
                lam *= 10
                continue
            trial = np.clip(p + step, lower, upper)
            e_t, u_t, n_t = scalar._residuals(trial, b, r)
            cost_t = float(e_t @ e_t)
            if cost_t < cost:
                improved = True
                decrease = cost - cost_t
                p, e, u, norm, cost = trial, e_t, u_t, n_t, cost_t
                lam = max(lam / 10, 1e-12)
                break
            lam *= 10
        if not improved:
            stop = "no decrease in 20 damping steps"
            break
        if decrease <= tol * max(cost, 1e-300):
            stop = "relative decrease below 1e-12"
            break
    return p, cost, it, stop


def box(b, r):
    """calib.scalar's search box and identity start for these samples."""
    scale = float(np.median(r) / np.median(np.linalg.norm(b, axis=1)))
    reach = scalar.OFFSET_FRACTION * float(np.max(r))
    lo_d, hi_d = scalar.DIAGONAL_RANGE
    off = scalar.OFF_DIAGONAL * scale
    lower = np.array([lo_d * scale, -off, -off, lo_d * scale, -off, lo_d * scale,
                      -reach, -reach, -reach])
    upper = np.array([hi_d * scale, off, off, hi_d * scale, off, hi_d * scale,
                      reach, reach, reach])
    return lower, upper, np.array([scale, 0, 0, scale, 0, scale, 0, 0, 0], dtype=float)


def best_of(fn, repeat):
    times, out = [], None
    for _ in range(repeat):
        start = time.perf_counter()
        out = fn()
        times.append(time.perf_counter() - start)
    return out, min(times), float(np.median(times))


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeat", type=int, default=15, help="timings per case (best of)")
    parser.add_argument("--output", type=Path, default=DEFAULT_OUTPUT)
    args = parser.parse_args(argv)
    load_start = load()
    rows = []
    for coverage in COVERAGES:
        flight = make_flight(coverage=coverage, seconds=100, seed=3)      # 2,000 samples
        b, r = flight.b_meas, flight.total
        lower, upper, identity = box(b, r)
        swarm, *_ = _pso.pso(lambda x: _pso.cost_numba(x, b, r), lower, upper, seed=0)
        for start_name, start in (("identity", identity), ("pso", swarm)):
            reference = scalar._polish(start, b, r, lower, upper, solver="lm")
            for name in ("hand", "lm", "trf"):
                if name == "hand":
                    (x, cost, steps, stop), best, median = best_of(
                        lambda: hand_lm(start, b, r, lower, upper), args.repeat)
                    status, solver = None, "hand"
                else:
                    out, best, median = best_of(
                        lambda: scalar._polish(start, b, r, lower, upper, solver=name),
                        args.repeat)
                    x, cost, steps, status = out.x, out.cost, out.nfev, out.status
                    solver = out.solver     # "lm" from a start on the box's wall is trf
                    stop = scalar.STATUS_MESSAGES[status]
                k, c = _pso.unpack(x)
                k_ref, c_ref = _pso.unpack(reference.x)
                row = {"coverage": coverage, "start": start_name, "polish": name,
                       "solver_used": solver,
                       "samples": len(b), "seconds_best": best, "seconds_median": median,
                       "cost": cost, "rms_nT": float(np.sqrt(cost / len(b))),
                       "steps": int(steps), "status": status, "stop": stop,
                       "max_abs_dK_vs_lm": float(np.max(np.abs(k - k_ref))),
                       "max_abs_dc_vs_lm_nT": float(np.max(np.abs(c - c_ref)))}
                rows.append(row)
                print(f"{coverage:7s} {start_name:8s} {name:4s}->{solver:4s} {best * 1e3:7.2f} ms "
                      f"(median {median * 1e3:7.2f}) rms {row['rms_nT']:.5f} nT "
                      f"steps {steps:3d} dK {row['max_abs_dK_vs_lm']:.1e} "
                      f"dc {row['max_abs_dc_vs_lm_nT']:.1e} nT  {stop}")
    write_report(args.output, "calib_lm", argv, load_start,
                 packages("numpy", "scipy", "numba"), repeat=args.repeat,
                 steps_mean="hand: iterations; lm, trf: function evaluations", rows=rows)
    return 0


if __name__ == "__main__":
    sys.exit(main())
