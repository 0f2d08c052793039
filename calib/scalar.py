"""Scalar calibration of a triaxial magnetometer against a total-field reference.

The model of the original paper: the calibrated field is ``K @ b - c`` with ``K`` upper
triangular and ``c`` an offset, nine unknowns, chosen to minimise

    sum_i (|K b_i - c| - r_i)^2

where ``r_i`` is the reference total field (the cesium magnetometer, a constant, or IGRF at
the GPS position). The global search is the standard PSO (``_pso``, numba), the polish
``scipy.optimize.least_squares`` (MINPACK's Levenberg-Marquardt, the bounded trust-region
method when LM leaves the search box) with the analytic Jacobian, which also gives the
parameter uncertainties. The trivial zero-cost solution (K = 0, |c| = r) is excluded by
keeping K's diagonal positive and away from zero.

In the paper's forward form (its Table 1), the sensor reads ``b = P (B_e + o)`` with
``P = K^-1`` and the offset ``o = c`` in the calibrated frame, i.e. ``P @ c`` nT at the
sensor; both are in the result.
"""

from dataclasses import dataclass, field

import numpy as np

from . import _pso
from ._samples import MAX_FIELD_NT, check_samples


__all__ = ["ScalarResult", "calibrate_scalar", "apply_scalar"]

#: Names of the nine parameters, in order.
PARAMETERS = ("k11", "k12", "k13", "k22", "k23", "k33", "c1", "c2", "c3")
#: Search box for PSO: K's diagonal relative to the data's scale, off-diagonals, and c
#: relative to the reference field.
DIAGONAL_RANGE = (0.5, 2.0)
OFF_DIAGONAL = 0.5
OFFSET_FRACTION = 0.5
#: Scaled condition number above which the coverage is reported as not determining the
#: parameters.
POORLY_DETERMINED = 1e6
#: Weight of the constrained fallback's prior, relative to the best-determined direction.
PRIOR_WEIGHT = 1e-3


@dataclass
class ScalarResult:
    """Like ``scipy.optimize.OptimizeResult``: the estimate, its cost and how it went."""
    K: np.ndarray
    c: np.ndarray
    cost: float
    rms: float                 # RMS of |K b - c| - r after calibration
    rms_before: float          # RMS of |b| - r
    success: bool
    message: str
    nit: int                   # PSO iterations + least-squares evaluations
    x: np.ndarray              # the nine parameters
    uncertainties: np.ndarray  # one standard deviation per parameter
    condition: float           # condition number of J^T J at the solution
    warnings: list = field(default_factory=list)
    status: int = 0            # least_squares' status: 1-4 converged, 0 evaluation limit
    solver: str = "lm"         # the polish that gave x: "lm" or "trf" (bounded)
    at_bound: list = field(default_factory=list)   # parameters on the search box

    @property
    def P(self):
        """The paper's forward matrix (K^-1)."""
        return np.linalg.inv(self.K)

    @property
    def offset_sensor(self):
        """The offset as the sensor sees it (P c), nT."""
        return self.P @ self.c

    def as_dict(self):
        return {
            "K": self.K.tolist(), "c": self.c.tolist(), "P": self.P.tolist(),
            "offset_sensor_nT": self.offset_sensor.tolist(),
            "parameters": dict(zip(PARAMETERS, self.x.tolist())),
            "uncertainties": dict(zip(PARAMETERS, self.uncertainties.tolist())),
            "cost": self.cost, "rms_nT": self.rms, "rms_before_nT": self.rms_before,
            "success": self.success, "message": self.message, "iterations": self.nit,
            "status": self.status, "solver": self.solver, "at_bound": list(self.at_bound),
            "condition": self.condition, "warnings": list(self.warnings),
        }


def apply_scalar(K, c, b):
    """Calibrated field of samples ``b`` (N, 3)."""
    return np.asarray(b, float) @ np.asarray(K, float).T - np.asarray(c, float)


def _residuals(p, b, r):
    k, c = _pso.unpack(p)
    u = b @ k.T - c
    norm = np.sqrt(np.einsum("ij,ij->i", u, u))
    return norm - r, u, norm


def _jacobian(u, norm, b):
    d = u / norm[:, None]                       # d|u| / du
    x, y, z = b[:, 0], b[:, 1], b[:, 2]
    return np.column_stack([d[:, 0] * x, d[:, 0] * y, d[:, 0] * z,
                            d[:, 1] * y, d[:, 1] * z, d[:, 2] * z,
                            -d[:, 0], -d[:, 1], -d[:, 2]])


#: What each ``scipy.optimize.least_squares`` status means, as the result's message.
STATUS_MESSAGES = {
    1: "converged: the gradient test (gtol) passed",
    2: "converged: the cost test (ftol) passed",
    3: "converged: the step test (xtol) passed",
    4: "converged: the cost and step tests (ftol, xtol) passed",
    0: "not converged: stopped at the evaluation limit",
    -1: "not converged: improper input to the least-squares solver",
}
#: Tolerances of the polish (scipy's defaults are 1e-8: looser than the noise floor asks).
FTOL = XTOL = 1e-12
GTOL = 1e-10
#: Evaluations allowed per polish, per parameter.
MAX_NFEV_PER_PARAMETER = 200


@dataclass
class _Polish:
    x: np.ndarray
    cost: float                # sum of squares of the data residuals (the prior left out)
    nfev: int
    jac: np.ndarray            # Jacobian of every residual row (prior rows included)
    status: int
    solver: str                # "lm" (MINPACK) or "trf" (bounded)
    active: np.ndarray         # -1 at the lower bound, 1 at the upper, 0 inside


def _polish(p, b, r, lower, upper, *, prior=None, solver="lm"):
    """Least squares from ``p``: MINPACK's Levenberg-Marquardt (``solver="lm"``), or the
    bounded trust-region reflective method (``"trf"``). LM has no bounds: when its solution
    leaves the box, or the start lies on the box's wall, the bounded method is run from the
    same start instead.

    ``prior`` = (A, target): extra residual rows ``A p - target`` (a constrained fit)."""
    from scipy.optimize import least_squares
    n = b.shape[0]

    def fun(q):
        e = _residuals(q, b, r)[0]
        return e if prior is None else np.concatenate([e, prior[0] @ q - prior[1]])

    def jac(q):
        _, u, norm = _residuals(q, b, r)
        j = _jacobian(u, norm, b)
        return j if prior is None else np.vstack([j, prior[0]])

    options = dict(x_scale="jac", ftol=FTOL, xtol=XTOL, gtol=GTOL,
                   max_nfev=max(1, int(MAX_NFEV_PER_PARAMETER * len(p))))
    start = np.clip(p, lower, upper)
    out = None
    # A start on the box's wall (a swarm that settled against it) sends unbounded LM out of
    # the box after many evaluations (bench/calib/lm.py: 220 ms on a near-planar flight
    # against 5 ms for "trf"): the bounded method starts there at once.
    on_wall = np.any(np.isclose(start, lower) | np.isclose(start, upper))
    if solver == "lm" and not on_wall:
        with np.errstate(all="ignore"):
            out = least_squares(fun, start, jac, method="lm", **options)
        inside = np.all(np.isfinite(out.x)) and np.all((out.x >= lower) & (out.x <= upper))
        if not inside:
            out = None
    if out is None:
        solver = "trf"
        with np.errstate(all="ignore"):
            out = least_squares(fun, start, jac, bounds=(lower, upper), method="trf",
                                **options)
    e = out.fun[:n]
    active = np.zeros(len(p), dtype=int)
    if solver == "trf":
        active = np.asarray(out.active_mask, dtype=int)
    return _Polish(x=out.x, cost=float(e @ e), nfev=int(out.nfev), jac=out.jac,
                   status=int(out.status), solver=solver, active=active)


def _check(b, r):
    b = check_samples(b, len(PARAMETERS) + 1, "for nine parameters")
    r = np.asarray(r, dtype=float)
    if r.ndim > 1 or (r.ndim == 1 and r.shape[0] != b.shape[0]):
        raise ValueError(f"The reference must be one value or one per sample ({b.shape[0]}), "
                         f"not shape {r.shape}")
    r = np.broadcast_to(r, (b.shape[0],)).copy()
    if not np.all(np.isfinite(r)) or np.any(r <= 0):
        raise ValueError("The reference field must be finite and positive")
    if np.max(r) > MAX_FIELD_NT:
        raise ValueError(f"The reference field must be below {MAX_FIELD_NT:.0e} nT, not "
                         f"{np.max(r):.3g} nT")
    return b, r


def calibrate_scalar(b, r, *, method="pso", seed=0, particles=40, iterations=300,
                     kernel="numba", pso_samples=2000, solver="lm"):
    """Fit K and c so that |K b_i - c| matches the reference r_i.

    Parameters
    ----------
    b : (N, 3) array
        Magnetometer samples, nT: finite, below 1e8 nT, every axis varying, at least ten
        distinct vectors (``ValueError`` otherwise).
    r : float or (N,) array
        Reference total field, nT.
    method : "pso" or "lm"
        PSO then the least-squares polish, or the polish alone from the identity.
    seed, particles, iterations :
        PSO settings (the swarm is seeded: the same call gives the same result).
    kernel : "numba" or "numpy"
        Which twin evaluates the swarm's cost.
    pso_samples : int
        The swarm searches on at most this many samples, evenly spaced (the polish uses
        them all): a long flight's global search costs no more than a short one's.
    solver : "lm" or "trf"
        The polish: ``scipy.optimize.least_squares`` with MINPACK's Levenberg-Marquardt
        (falling back to the bounded "trf" when its solution leaves the search box), or
        "trf" with the box throughout. bench/calib/lm.py compares them (and the hand-written
        LM they replaced) on the project's flights: "lm" is as fast as the hand-written one
        and 5-40 times faster than "trf".

    The result's ``success`` is True only when the solver's own convergence test passed
    and no parameter ends on the search box; ``status`` is least_squares' (1-4 converged,
    0 evaluation limit), ``message`` says which test, or why not.
    """
    b, r = _check(b, r)
    if method not in ("pso", "lm"):
        raise ValueError(f"Method must be 'pso' or 'lm', not {method!r}")
    if kernel not in ("numba", "numpy"):
        raise ValueError(f"Kernel must be 'numba' or 'numpy', not {kernel!r}")
    if solver not in ("lm", "trf"):
        raise ValueError(f"Solver must be 'lm' or 'trf', not {solver!r}")
    scale = float(np.median(r) / np.median(np.linalg.norm(b, axis=1)))
    reach = OFFSET_FRACTION * float(np.max(r))
    lower = np.array([DIAGONAL_RANGE[0] * scale, -OFF_DIAGONAL * scale, -OFF_DIAGONAL * scale,
                      DIAGONAL_RANGE[0] * scale, -OFF_DIAGONAL * scale,
                      DIAGONAL_RANGE[0] * scale, -reach, -reach, -reach])
    upper = np.array([DIAGONAL_RANGE[1] * scale, OFF_DIAGONAL * scale, OFF_DIAGONAL * scale,
                      DIAGONAL_RANGE[1] * scale, OFF_DIAGONAL * scale,
                      DIAGONAL_RANGE[1] * scale, reach, reach, reach])
    nit = 0
    identity = np.array([scale, 0, 0, scale, 0, scale, 0, 0, 0], dtype=float)
    starts = [identity]
    if method == "pso":
        cost_fn = _pso.cost_numba if kernel == "numba" else _pso.cost_numpy
        step = max(1, b.shape[0] // pso_samples)
        b_s, r_s = b[::step], r[::step]
        best, _, nit, _ = _pso.pso(lambda x: cost_fn(x, b_s, r_s), lower, upper,
                                   particles=particles, iterations=iterations, seed=seed)
        starts.insert(0, best)
    # Polish every start and keep the best: a swarm can settle against the box in a
    # poorly determined direction, where the identity start walks straight to the minimum.
    polished = [_polish(start, b, r, lower, upper, solver=solver) for start in starts]
    best = min(polished, key=lambda p: p.cost if np.isfinite(p.cost) else np.inf)
    nit += best.nfev

    a = best.jac.T @ best.jac
    # Conditioning with the parameters scaled to unit columns (K is ~1, c is ~1e4 nT).
    d = np.sqrt(np.diag(a))
    d = np.where(d > 0, d, 1.0)
    scaled = a / np.outer(d, d)
    values, vectors = np.linalg.eigh(scaled)
    condition = float(values[-1] / max(values[0], 1e-300))
    dof = max(b.shape[0] - len(PARAMETERS), 1)
    warnings = []
    cost = best.cost
    uncertainties = _uncertainties(a, cost, dof)
    if not np.isfinite(condition) or condition > POORLY_DETERMINED:
        # Constrained fallback: the directions the coverage cannot see are held to the
        # isotropic start (K = scale I, c = 0) by a prior that outweighs the data only
        # along them; everything the data determine is fitted as before.
        weak_dirs = vectors[:, values < values[-1] / POORLY_DETERMINED]
        rows = (weak_dirs.T * d) * np.sqrt(values[-1] * PRIOR_WEIGHT)
        best = _polish(best.x, b, r, lower, upper, prior=(rows, rows @ identity),
                       solver=solver)
        nit += best.nfev
        cost = best.cost
        data_jac = best.jac[:b.shape[0]]
        names = [PARAMETERS[i] for i in np.argsort(-np.abs(vectors[:, 0]))[:2]]
        warnings.append("the attitude coverage hardly determines "
                        f"{' against '.join(names)} (scaled condition number "
                        f"{condition:.3g}): constrained fit, that combination held to the "
                        "isotropic prior; its uncertainty reflects the prior, not the data")
        uncertainties = _uncertainties(data_jac.T @ data_jac + rows.T @ rows, cost, dof)
    x = best.x
    at_bound = [name for name, v, lo, hi, act in zip(PARAMETERS, x, lower, upper, best.active)
                if act or np.isclose(v, lo) or np.isclose(v, hi)]
    converged = best.status > 0
    message = STATUS_MESSAGES.get(best.status, f"status {best.status}")
    if not converged:
        warnings.append(f"the least-squares polish ({best.solver}) did not converge: "
                        f"{message} after {best.nfev} evaluations")
    if at_bound:
        warnings.append(f"parameters at the search bound: {', '.join(at_bound)} (the "
                        "minimum lies outside the box the search allows: the data do not "
                        "fit the model there)")
        message += f"; at the search bound: {', '.join(at_bound)}"
    k, c = _pso.unpack(x)
    before = np.linalg.norm(b, axis=1) - r
    success = bool(converged and not at_bound and np.all(np.isfinite(x)))
    return ScalarResult(
        K=k, c=c, cost=cost, rms=float(np.sqrt(cost / b.shape[0])),
        rms_before=float(np.sqrt(np.mean(before ** 2))), success=success,
        message=message, nit=nit, x=x, uncertainties=uncertainties, condition=condition,
        warnings=warnings, status=best.status, solver=best.solver, at_bound=at_bound)


def _uncertainties(a, cost, dof):
    """One standard deviation per parameter from J^T J; infinity where it is singular."""
    try:
        covariance = np.linalg.inv(a) * cost / dof
    except np.linalg.LinAlgError:
        return np.full(len(PARAMETERS), np.inf)
    return np.sqrt(np.clip(np.diag(covariance), 0, None))
