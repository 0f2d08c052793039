"""Scalar calibration of a triaxial magnetometer against a total-field reference.

The model of the original paper: the calibrated field is ``K @ b - c`` with ``K`` upper
triangular and ``c`` an offset, nine unknowns, chosen to minimise

    sum_i (|K b_i - c| - r_i)^2

where ``r_i`` is the reference total field (the cesium magnetometer, a constant, or IGRF at
the GPS position). The global search is the standard PSO (``_pso``, numba), the polish a
bounded Levenberg-Marquardt (``_lm``) with the analytic Jacobian, which also gives the
parameter uncertainties. The trivial zero-cost solution (K = 0, |c| = r) is excluded by
keeping K's diagonal positive and away from zero.

In the paper's forward form (its Table 1), the sensor reads ``b = P (B_e + o)`` with
``P = K^-1`` and the offset ``o = c`` in the calibrated frame, i.e. ``P @ c`` nT at the
sensor; both are in the result.
"""

from dataclasses import dataclass, field

import numpy as np

from . import _pso


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
    nit: int                   # PSO iterations + LM iterations
    x: np.ndarray              # the nine parameters
    uncertainties: np.ndarray  # one standard deviation per parameter
    condition: float           # condition number of J^T J at the solution
    warnings: list = field(default_factory=list)

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


def _lm(p, b, r, lower, upper, *, max_iter=200, tol=1e-12, prior=None):
    """Bounded Levenberg-Marquardt: damped Gauss-Newton steps projected into the box.

    ``prior`` = (A, target): extra residual rows ``A p - target`` (a constrained fit)."""
    if prior is not None:
        rows, target = prior
        plain = _residuals

        def _residuals_with_prior(q, b_, r_):
            e_, u_, n_ = plain(q, b_, r_)
            return np.concatenate([e_, rows @ q - target]), u_, n_
        residuals = _residuals_with_prior

        def jacobian(u_, n_, b_):
            return np.vstack([_jacobian(u_, n_, b_), rows])
    else:
        residuals, jacobian = _residuals, _jacobian
    e, u, norm = residuals(p, b, r)
    cost = float(e @ e)
    lam = 1e-3
    it = 0
    for it in range(1, max_iter + 1):
        j = jacobian(u, norm, b)
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
            e_t, u_t, n_t = residuals(trial, b, r)
            cost_t = float(e_t @ e_t)
            if cost_t < cost:
                improved = True
                decrease = cost - cost_t
                p, e, u, norm, cost = trial, e_t, u_t, n_t, cost_t
                lam = max(lam / 10, 1e-12)
                break
            lam *= 10
        if not improved or decrease <= tol * max(cost, 1e-300):
            break
    return p, cost, it, e, jacobian(u, norm, b)


def _check(b, r):
    b = np.asarray(b, dtype=float)
    if b.ndim != 2 or b.shape[1] != 3:
        raise ValueError(f"Samples must be an (N, 3) array, not shape {b.shape}")
    if b.shape[0] < len(PARAMETERS) + 1:
        raise ValueError(f"At least {len(PARAMETERS) + 1} samples are needed for nine "
                         f"parameters, not {b.shape[0]}")
    if not np.all(np.isfinite(b)):
        raise ValueError("Samples must be finite (found NaN or infinity)")
    r = np.broadcast_to(np.asarray(r, dtype=float), (b.shape[0],)).copy()
    if not np.all(np.isfinite(r)) or np.any(r <= 0):
        raise ValueError("The reference field must be finite and positive")
    return b, r


def calibrate_scalar(b, r, *, method="pso", seed=0, particles=40, iterations=300,
                     kernel="numba", pso_samples=2000):
    """Fit K and c so that |K b_i - c| matches the reference r_i.

    Parameters
    ----------
    b : (N, 3) array
        Magnetometer samples, nT.
    r : float or (N,) array
        Reference total field, nT.
    method : "pso" or "lm"
        PSO then LM, or LM alone from the identity.
    seed, particles, iterations :
        PSO settings (the swarm is seeded: the same call gives the same result).
    kernel : "numba" or "numpy"
        Which twin evaluates the swarm's cost.
    pso_samples : int
        The swarm searches on at most this many samples, evenly spaced (the LM polish uses
        them all): a long flight's global search costs no more than a short one's.
    """
    b, r = _check(b, r)
    if method not in ("pso", "lm"):
        raise ValueError(f"Method must be 'pso' or 'lm', not {method!r}")
    if kernel not in ("numba", "numpy"):
        raise ValueError(f"Kernel must be 'numba' or 'numpy', not {kernel!r}")
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
    polished = [_lm(start, b, r, lower, upper) for start in starts]
    x, cost, lm_it, e, j = min(polished, key=lambda p: p[1])
    nit += lm_it

    a = j.T @ j
    # Conditioning with the parameters scaled to unit columns (K is ~1, c is ~1e4 nT).
    d = np.sqrt(np.diag(a))
    scaled = a / np.outer(d, d)
    values, vectors = np.linalg.eigh(scaled)
    condition = float(values[-1] / max(values[0], 1e-300))
    dof = max(b.shape[0] - len(PARAMETERS), 1)
    warnings = []
    try:
        covariance = np.linalg.inv(a) * cost / dof
        uncertainties = np.sqrt(np.clip(np.diag(covariance), 0, None))
    except np.linalg.LinAlgError:
        uncertainties = np.full(len(PARAMETERS), np.inf)
    if not np.isfinite(condition) or condition > POORLY_DETERMINED:
        # Constrained fallback: the directions the coverage cannot see are held to the
        # isotropic start (K = scale I, c = 0) by a prior that outweighs the data only
        # along them; everything the data determine is fitted as before.
        weak_dirs = vectors[:, values < values[-1] / POORLY_DETERMINED]
        rows = (weak_dirs.T * d) * np.sqrt(values[-1] * PRIOR_WEIGHT)
        x, cost_prior, more, e, j_full = _lm(x, b, r, lower, upper,
                                             prior=(rows, rows @ identity))
        nit += more
        e = e[:b.shape[0]]
        cost = float(e @ e)
        a = j_full[:b.shape[0]].T @ j_full[:b.shape[0]]
        names = [PARAMETERS[i] for i in np.argsort(-np.abs(vectors[:, 0]))[:2]]
        warnings.append("the attitude coverage hardly determines "
                        f"{' against '.join(names)} (scaled condition number "
                        f"{condition:.3g}): constrained fit, that combination held to the "
                        "isotropic prior; its uncertainty reflects the prior, not the data")
        try:
            prior_a = a + rows.T @ rows
            uncertainties = np.sqrt(np.clip(np.diag(np.linalg.inv(prior_a) * cost / dof),
                                            0, None))
        except np.linalg.LinAlgError:
            pass
    at_bound = [name for name, v, lo, hi in zip(PARAMETERS, x, lower, upper)
                if np.isclose(v, lo) or np.isclose(v, hi)]
    if at_bound:
        warnings.append(f"parameters at the search bound: {', '.join(at_bound)}")

    k, c = _pso.unpack(x)
    before = np.linalg.norm(b, axis=1) - r
    success = bool(np.all(np.isfinite(x)) and not at_bound)
    return ScalarResult(
        K=k, c=c, cost=cost, rms=float(np.sqrt(cost / b.shape[0])),
        rms_before=float(np.sqrt(np.mean(before ** 2))), success=success,
        message="converged" if success else "; ".join(warnings) or "failed",
        nit=nit, x=x, uncertainties=uncertainties, condition=condition, warnings=warnings)
