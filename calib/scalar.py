"""Scalar calibration of a triaxial magnetometer against a total-field reference.

The model of the original paper: the calibrated field is ``K @ b - c`` with ``K`` upper
triangular and ``c`` an offset, nine unknowns. Two objectives:

- ``objective="eiv"`` (the default): errors in variables, by adjusted least squares on the
  samples' sufficient statistics (:mod:`.eiv`): unbiased when the magnetometer itself is
  noisy, with a robust loss, sandwich uncertainties and each parameter's dilution of
  precision. It is the default because the paper's objective is biased by the
  magnetometer's noise wherever the coverage is weak (c3 by about 100 nT on a UAV pattern
  with paper A's Table 1 at 100 nT, whatever the number of samples), and a survey applies
  the parameters to attitudes the fit did not see.
- ``objective="paper"``: the paper's own, ``sum_i (|K b_i - c| - r_i)^2``, with the
  reference ``r_i`` taken as the only noisy quantity (the same robust loss around it).

``r_i`` is the reference total field (the cesium magnetometer, a constant, or IGRF at the
GPS position). The global search is the standard PSO (``_pso``): by default on the moment
surrogate, whose evaluation does not visit the samples (the whole swarm compiled with
numba, about 2 ms for 40 particles and 300 iterations whatever the flight's length); the
paper's polish is ``scipy.optimize.least_squares`` (MINPACK's Levenberg-Marquardt, the bounded trust-region
method when LM leaves the search box) with the analytic Jacobian, which also gives the
parameter uncertainties. The trivial zero-cost solution (K = 0, |c| = r) is excluded by
keeping K's diagonal positive and away from zero.

In the paper's forward form (its Table 1), the sensor reads ``b = P (B_e + o)`` with
``P = K^-1`` and the offset ``o = c`` in the calibrated frame, i.e. ``P @ c`` nT at the
sensor; both are in the result.
"""

import contextlib
from dataclasses import dataclass, field

import numpy as np

from . import _pso, eiv
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
    objective: str = "eiv"     # "eiv" (errors in variables) or "paper"
    dop: np.ndarray = None     # dilution of precision per parameter (nT per nT / sqrt(N))
    determined: np.ndarray = None  # bool per parameter: dop within eiv.UNDETERMINED_DOP
    held: np.ndarray = None    # bool per parameter: held to the isotropic prior
    kept: np.ndarray = None    # bool per sample: fitted (not screened out, not rejected)
    robust_cut_nT: float = float("inf")   # Talwar's cut-off on the residual
    noise: dict = field(default_factory=dict)   # estimated noise: magnetometer, reference
    covariance: np.ndarray = None  # the sandwich covariance (plus the prior's spread)
    #: The combinations of parameters the coverage leaves to the isotropic prior: unit
    #: vectors in the dilution's units (K's entries times the field, c in nT), (m, 9).
    held_directions: np.ndarray = field(default_factory=lambda: np.zeros((0, 9)))

    @property
    def rejected(self):
        """Samples the robust loss left out (not counting those ``keep`` excluded)."""
        return 0 if self.kept is None else int(np.count_nonzero(~self.kept))

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
            "objective": self.objective,
            "dilution_of_precision": None if self.dop is None else
            dict(zip(PARAMETERS, np.asarray(self.dop).tolist())),
            "undetermined": [] if self.determined is None else
            [n for n, d in zip(PARAMETERS, self.determined) if not d],
            "held_to_prior": [] if self.held is None else
            [n for n, h in zip(PARAMETERS, self.held) if h],
            "held_combinations": [combination(v) for v in self.held_directions],
            "samples_fitted": None if self.kept is None else int(self.kept.sum()),
            "rejected_by_robust_loss": self.rejected,
            "robust_cut_nT": self.robust_cut_nT,
            "noise_estimate_nT": dict(self.noise),
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


OBJECTIVES = ("eiv", "paper")
KERNELS = ("moments", "numba", "numpy")


def _box(b, r):
    """The search box (lower, upper) and the data's scale (median r / median |b|)."""
    scale = float(np.median(r) / np.median(np.linalg.norm(b, axis=1)))
    reach = OFFSET_FRACTION * float(np.max(r))
    lower = np.array([DIAGONAL_RANGE[0] * scale, -OFF_DIAGONAL * scale, -OFF_DIAGONAL * scale,
                      DIAGONAL_RANGE[0] * scale, -OFF_DIAGONAL * scale,
                      DIAGONAL_RANGE[0] * scale, -reach, -reach, -reach])
    upper = np.array([DIAGONAL_RANGE[1] * scale, OFF_DIAGONAL * scale, OFF_DIAGONAL * scale,
                      DIAGONAL_RANGE[1] * scale, OFF_DIAGONAL * scale,
                      DIAGONAL_RANGE[1] * scale, reach, reach, reach])
    return lower, upper, scale


def _swarm(b, r, lower, upper, *, kernel, seed, particles, iterations, pso_samples):
    """The swarm's best parameters (nT units) and its iterations. ``kernel="moments"``
    searches the algebraic surrogate from the samples' power sums (no sample visited per
    evaluation); "numba" and "numpy" search the exact cost on at most ``pso_samples``
    evenly spaced samples."""
    if kernel == "moments":
        field_nt = float(np.median(r))
        s = eiv.moments(b, r, shift=np.zeros(3), scale=field_nt).matrix()
        units = np.array([1.0] * 6 + [field_nt] * 3)
        best, _, nit, _ = _pso.pso_moments(s, lower / units, upper / units,
                                           particles=particles, iterations=iterations,
                                           seed=seed)
        # The swarm ends near the surrogate's minimum, not on it, and often against the box
        # in a weak direction. The search is finished on the same surrogate, still without
        # visiting a sample: Gauss-Newton from the swarm's best and from the surrogate's
        # linear solution, and the plausible end with the lowest surrogate cost wins (the
        # swarm's best itself when none is plausible).
        scale = float(np.median(r) / np.median(np.linalg.norm(b, axis=1)))
        root = eiv._root(s)
        ends = [(not eiv._plausible(best, scale), eiv.objective(best, s), best)]
        for start in (best, eiv._linear_start(s, scale)):
            if start is not None and eiv._plausible(start, scale):
                end, steps, _ = eiv._gauss_newton(start, root, scale=scale)
                nit += steps
                inside = np.all((end > lower / units) & (end < upper / units))
                ends.append((not (inside and eiv._plausible(end, scale)),
                             eiv.objective(end, s), end))
        best = min(ends, key=lambda item: item[:2])[2]
        return best * units, nit
    cost_fn = _pso.cost_numba if kernel == "numba" else _pso.cost_numpy
    step = max(1, b.shape[0] // pso_samples)
    b_s, r_s = b[::step], r[::step]
    best, _, nit, _ = _pso.pso(lambda x: cost_fn(x, b_s, r_s), lower, upper,
                               particles=particles, iterations=iterations, seed=seed)
    return best, nit


_CONTROLLER = None


def _blas_threads(threads):
    """A context limiting the BLAS (numpy's and scipy's OpenBLAS) to ``threads`` threads,
    or leaving it alone when ``threads`` is None. The fit's matrices are small (9 or 11
    columns): on 2 cores another thread gained nothing, and on a loaded machine the
    paper objective's polish once took 1.4 s instead of 45 ms with the default threads."""
    global _CONTROLLER
    if threads is None:
        return contextlib.nullcontext()
    if _CONTROLLER is None:
        # scipy's own OpenBLAS first: the controller sees only the libraries loaded now.
        import scipy.linalg  # noqa: F401
        import scipy.optimize  # noqa: F401
        from threadpoolctl import ThreadpoolController
        _CONTROLLER = ThreadpoolController()
    return _CONTROLLER.limit(limits=threads, user_api="blas")


def calibrate_scalar(b, r, *, objective="eiv", method="pso", seed=0, particles=40,
                     iterations=300, kernel="moments", pso_samples=2000, solver="lm",
                     robust=True, keep=None, reference_noise=None, threads=1):
    """Fit K and c so that |K b_i - c| matches the reference r_i.

    Parameters
    ----------
    b : (N, 3) array
        Magnetometer samples, nT: finite, below 1e8 nT, every axis varying, at least ten
        distinct vectors (``ValueError`` otherwise).
    r : float or (N,) array
        Reference total field, nT.
    objective : "eiv" or "paper"
        Errors in variables (unbiased under the magnetometer's noise; :mod:`.eiv`), or the
        paper's ``sum (|K b - c| - r)^2``.
    method : "pso" or "lm"
        The swarm's best as the start, or the deterministic start alone (the linear
        solution of the moment problem for "eiv", the identity for "paper").
    seed, particles, iterations :
        PSO settings (the swarm is seeded: the same call gives the same result).
    kernel : "moments", "numba" or "numpy"
        What the swarm evaluates: the moment surrogate (default; independent of N), or the
        exact cost on at most ``pso_samples`` samples (numba or numpy twin).
    solver : "lm" or "trf"
        The paper objective's polish: ``scipy.optimize.least_squares`` with MINPACK's
        Levenberg-Marquardt (falling back to the bounded "trf" when its solution leaves the
        search box), or "trf" with the box throughout.
    robust : bool
        Talwar's loss: samples more than ``eiv.ROBUST_K`` robust standard deviations off the
        fit are left out (counted in ``rejected``), and the fit repeated.
    keep : (N,) bool array or None
        Samples allowed at all (a screening's verdict); the others are not fitted.
    reference_noise : float or None
        The reference's noise, nT (None: estimated from its second differences).
    threads : int or None
        BLAS threads during the fit (default one: the matrices are small; None leaves the
        library's default). The compiled swarm and the moments run on one thread anyway.

    The result's ``success`` is True only when the solver converged and no parameter ends
    on the search box. ``determined`` says which parameters the attitude coverage
    determines (dilution of precision ``dop`` within ``eiv.UNDETERMINED_DOP``); a parameter
    in ``held`` is not determined by the data at all and was held to the isotropic prior:
    its uncertainty is infinite.
    """
    b, r = _check(b, r)
    if objective not in OBJECTIVES:
        raise ValueError(f"Objective must be one of {', '.join(OBJECTIVES)}, not "
                         f"{objective!r}")
    if method not in ("pso", "lm"):
        raise ValueError(f"Method must be 'pso' or 'lm', not {method!r}")
    if kernel not in KERNELS:
        raise ValueError(f"Kernel must be one of {', '.join(KERNELS)}, not {kernel!r}")
    if solver not in ("lm", "trf"):
        raise ValueError(f"Solver must be 'lm' or 'trf', not {solver!r}")
    if keep is not None:
        keep = np.asarray(keep, dtype=bool)
        if keep.shape != (b.shape[0],):
            raise ValueError(f"keep must be one bool per sample ({b.shape[0]}), not shape "
                             f"{keep.shape}")
        if keep.sum() < len(PARAMETERS) + 1:
            raise ValueError(f"Only {int(keep.sum())} samples kept; at least "
                             f"{len(PARAMETERS) + 1} are needed for nine parameters")
    if threads is not None and (not isinstance(threads, (int, np.integer)) or threads < 1):
        raise ValueError(f"Threads must be a positive integer or None, not {threads!r}")
    with _blas_threads(threads):
        return _calibrate(b, r, objective, method, seed, particles, iterations, kernel,
                          pso_samples, solver, robust, keep, reference_noise)


def _calibrate(b, r, objective, method, seed, particles, iterations, kernel, pso_samples,
               solver, robust, keep, reference_noise):
    lower, upper, scale = _box(b, r)
    nit = 0
    start = None
    if method == "pso":
        allowed = slice(None) if keep is None else keep
        start, nit = _swarm(b[allowed], r[allowed], lower, upper, kernel=kernel, seed=seed,
                            particles=particles, iterations=iterations,
                            pso_samples=pso_samples)
    used = objective
    if objective == "eiv":
        result = _fit_eiv(b, r, start, keep, robust, reference_noise)
        low = _collapsing(result.x, lower)
        if low:
            # The algebraic objective's trivial minimum (K -> 0, |c| = r) is the lowest when
            # the reference hardly varies and the model leaves a large misfit: the bounded
            # fit of the paper objective cannot reach it.
            nit += result.nit
            result = _fit_paper(b, r, start, keep, robust, lower, upper, scale, solver,
                                reference_noise)
            used = "paper"
            result.warnings.insert(0, (
                f"the errors-in-variables fit slid towards the trivial solution (K's "
                f"diagonal {', '.join(low)}, below {DIAGONAL_RANGE[0]:g} times the data's "
                "scale: K -> 0 with |c| = the reference fits a reference that hardly "
                "varies): the paper objective's bounded fit is reported instead"))
    else:
        result = _fit_paper(b, r, start, keep, robust, lower, upper, scale, solver,
                            reference_noise)
    result.nit += nit
    result.objective = used
    _check_bounds(result, lower, upper)
    return result


def _collapsing(x, lower):
    """K's diagonal elements below the search box's floor, as "k11 0.047" (empty: none)."""
    return [f"{PARAMETERS[i]} {x[i]:.3g}" for i in eiv.DIAGONAL
            if not x[i] > lower[i] or np.isclose(x[i], lower[i])]


def _check_bounds(result, lower, upper):
    """Parameters on (or beyond) the search box make the fit unsuccessful, and say so."""
    x = result.x
    at_bound = sorted(set(result.at_bound) | {
        name for name, v, lo, hi in zip(PARAMETERS, x, lower, upper)
        if v <= lo or v >= hi or np.isclose(v, lo) or np.isclose(v, hi)})
    at_bound = [name for name in PARAMETERS if name in at_bound]
    if at_bound and "at the search bound" not in result.message:
        result.warnings.append(f"parameters at the search bound: {', '.join(at_bound)} (the "
                               "minimum lies outside the box the search allows: the data "
                               "do not fit the model there)")
        result.message += f"; at the search bound: {', '.join(at_bound)}"
    result.at_bound = at_bound
    result.success = bool(result.success and not at_bound and np.all(np.isfinite(x)))


def _names(mask):
    return [name for name, m in zip(PARAMETERS, mask) if m]


def combination(direction, smallest=0.1):
    """A held direction as text: "0.64 k33 + 0.6 c3 - 0.31 k22" (its components of at
    least ``smallest``, largest first; K's entries in units of the field)."""
    order = np.argsort(-np.abs(direction))
    terms = [(direction[i], PARAMETERS[i]) for i in order if abs(direction[i]) >= smallest]
    text = ""
    for k, (value, name) in enumerate(terms):
        sign = "-" if value < 0 else "+"
        text += (f"{'-' if value < 0 else ''}" if k == 0 else f" {sign} ") + \
            f"{abs(value):.2g} {name}"
    return text


def _coverage_warnings(dop, determined, held, directions=()):
    warnings = []
    weak = [n for n, d, h in zip(PARAMETERS, determined, held) if not d and not h]
    if weak:
        figures = ", ".join(f"{n} {dop[PARAMETERS.index(n)]:.3g}" for n in weak)
        warnings.append(f"the attitude coverage leaves {', '.join(weak)} undetermined "
                        f"(dilution of precision {figures}, above {eiv.UNDETERMINED_DOP:g}: "
                        "each one's 1-sigma is that many times the noise / sqrt(N)); fitted "
                        "from the data with their large uncertainties: turn the sensor "
                        "further about its other axes to determine them")
    if len(directions):
        combos = "; ".join(combination(v) for v in directions)
        what = (f"{', '.join(_names(held))} mostly lie along it: held to the isotropic "
                "prior, no uncertainty given" if np.any(held) else
                "no parameter lies mostly along it")
        warnings.append(f"the attitude coverage does not determine the combination "
                        f"{combos} (K's entries in units of the field) at all (a level "
                        "flight never turns that axis against the field): that combination "
                        f"is held to the isotropic prior; {what}; the other parameters are "
                        "fitted from the data, their uncertainties including what the "
                        "prior's error can move them by")
    return warnings


def _fit_eiv(b, r, start, keep, robust, reference_noise):
    fit = eiv.fit_eiv(b, r, start=start, sigma_r=reference_noise, robust=robust, keep=keep)
    x = fit.x
    k, c = _pso.unpack(x)
    sd = np.sqrt(np.clip(np.diag(fit.covariance), 0, None))
    sd = np.where(fit.held, np.inf, sd)
    e, _ = eiv.residuals(x, b, r)
    kept = fit.keep
    before = np.linalg.norm(b[kept], axis=1) - r[kept]
    cost = float(e[kept] @ e[kept])
    directions = eiv.held_directions(fit.weak, float(np.median(r[kept])))
    warnings = _coverage_warnings(fit.dop, fit.determined, fit.held, directions) + \
        list(fit.warnings)
    message = ("converged: adjusted least squares (errors in variables)" if fit.converged
               else "not converged: the adjusted least squares reached its iteration limit")
    if not fit.converged:
        warnings.append(f"the errors-in-variables fit did not converge in {fit.nit} "
                        "iterations")
    return ScalarResult(
        K=k, c=c, cost=cost, rms=float(np.sqrt(cost / kept.sum())),
        rms_before=float(np.sqrt(np.mean(before ** 2))), success=fit.converged,
        message=message, nit=fit.nit, x=x, uncertainties=sd,
        condition=float(np.max(fit.dop) / max(np.min(fit.dop), 1e-300)),
        warnings=warnings, status=1 if fit.converged else 0, solver="eiv",
        at_bound=[], dop=fit.dop, determined=fit.determined, held=fit.held,
        kept=kept, robust_cut_nT=fit.scale_cut,
        noise={"magnetometer_nT": fit.sigma_m, "reference_nT": fit.sigma_r},
        covariance=fit.covariance, held_directions=directions)


def _robust_keep(e, allowed):
    """Talwar's loss as a mask: samples within ``eiv.ROBUST_K`` robust standard
    deviations of the median residual; and the cut-off (nT)."""
    inside = e[allowed]
    centre = float(np.median(inside))
    spread = 1.4826 * float(np.median(np.abs(inside - centre)))
    if spread <= 0:
        return allowed.copy(), np.inf
    cut = eiv.ROBUST_K * spread
    return allowed & (np.abs(e - centre) <= cut), cut


def _on_box(x, lower, upper):
    return bool(np.any(np.isclose(x, lower) | np.isclose(x, upper)))


def _fit_paper(b, r, start, keep, robust, lower, upper, scale, solver, reference_noise):
    allowed = np.ones(len(b), bool) if keep is None else keep.copy()
    identity = np.array([scale, 0, 0, scale, 0, scale, 0, 0, 0], dtype=float)
    starts = [identity] if start is None else [start, identity]
    kept = allowed.copy()
    cut = np.inf
    nit = 0
    for _ in range(eiv.MAX_ROUNDS):
        bk, rk = b[kept], r[kept]
        # The swarm's best first; the identity too when that ends on the box or fails (a
        # swarm can settle against the box in a poorly determined direction, where the
        # identity walks straight to the minimum), and the better kept.
        polished = [_polish(starts[0], bk, rk, lower, upper, solver=solver)]
        if len(starts) > 1 and (polished[0].status <= 0 or np.any(polished[0].active)
                                or _on_box(polished[0].x, lower, upper)
                                or not np.isfinite(polished[0].cost)):
            polished.append(_polish(starts[1], bk, rk, lower, upper, solver=solver))
        best = min(polished, key=lambda p: p.cost if np.isfinite(p.cost) else np.inf)
        nit += sum(p.nfev for p in polished)
        best, fallback, nit = _constrained(best, bk, rk, lower, upper, identity, solver, nit)
        e, _ = eiv.residuals(best.x, b, r)
        new_kept, cut = _robust_keep(e, allowed) if robust else (allowed, np.inf)
        if np.array_equal(new_kept, kept):
            break
        kept = new_kept
        starts = [best.x]
    bk, rk = b[kept], r[kept]
    x = best.x
    e, u = eiv.residuals(x, bk, rk)
    info = eiv.information(x, bk, rk)
    dop = eiv.dilution(info, float(np.median(rk)))
    covariance, held = eiv._sandwich(info, fallback, float(np.median(rk)))
    determined = (dop <= eiv.UNDETERMINED_DOP) & ~held
    dof = max(bk.shape[0] - len(PARAMETERS), 1)
    uncertainties = np.sqrt(np.clip(np.diag(covariance), 0, None))
    uncertainties = np.where(held, np.inf, uncertainties)
    directions = eiv.held_directions(fallback, float(np.median(rk)))
    warnings = _coverage_warnings(dop, determined, held, directions)
    converged = best.status > 0
    message = STATUS_MESSAGES.get(best.status, f"status {best.status}")
    if not converged:
        warnings.append(f"the least-squares polish ({best.solver}) did not converge: "
                        f"{message} after {best.nfev} evaluations")
    at_bound = [name for name, act in zip(PARAMETERS, best.active) if act]
    k, c = _pso.unpack(x)
    before = np.linalg.norm(bk, axis=1) - rk
    sigma_r = eiv.reference_noise(rk) if reference_noise is None else reference_noise
    sigma = float(np.sqrt(max(best.cost / dof - sigma_r ** 2, 0.0)))
    return ScalarResult(
        K=k, c=c, cost=best.cost, rms=float(np.sqrt(best.cost / bk.shape[0])),
        rms_before=float(np.sqrt(np.mean(before ** 2))), success=converged,
        message=message, nit=nit, x=x, uncertainties=uncertainties,
        condition=float(np.max(dop) / max(np.min(dop), 1e-300)), warnings=warnings,
        status=best.status, solver=best.solver, at_bound=at_bound, dop=dop,
        determined=determined, held=held, kept=kept, robust_cut_nT=cut,
        noise={"magnetometer_nT": sigma, "reference_nT": sigma_r},
        covariance=covariance, held_directions=directions)


def _constrained(best, b, r, lower, upper, identity, solver, nit):
    """The constrained fallback of the paper objective: the directions the coverage
    cannot see (scaled condition above :data:`POORLY_DETERMINED`) are held to the
    isotropic start by a prior that outweighs the data only along them. Returns the polish,
    the prior's rows (the held directions; None when there is no prior) and the
    evaluations so far."""
    a = best.jac.T @ best.jac
    d = np.sqrt(np.diag(a))
    d = np.where(d > 0, d, 1.0)
    values, vectors = np.linalg.eigh(a / np.outer(d, d))
    condition = float(values[-1] / max(values[0], 1e-300))
    if np.isfinite(condition) and condition <= POORLY_DETERMINED:
        return best, None, nit
    weak = vectors[:, values < values[-1] / POORLY_DETERMINED]
    rows = (weak.T * d) * np.sqrt(values[-1] * PRIOR_WEIGHT)
    best = _polish(best.x, b, r, lower, upper, prior=(rows, rows @ identity), solver=solver)
    return best, rows, nit + best.nfev
