"""Noise: a scalar Kalman filter per axis; the overlapping Allan deviation with its
confidence per averaging time, and the noise terms it resolves.

Ref: IEEE Std 952-1997 Annex C (Allan variance of a rate-like signal). With sigma^2(tau)
     the Allan variance at averaging time tau, and the IEEE two-sided rate spectra:

     term                      sigma^2(tau)              slope of log sigma vs log tau
     quantisation noise Q      3 Q^2 / tau^2             -1
     angle/velocity r.w. N     N^2 / tau                 -1/2
     bias instability B        (2 ln 2 / pi) B^2         0  (sigma ~ 0.664 B, the floor)
     rate random walk K        K^2 tau / 3               +1/2
     rate ramp R               R^2 tau^2 / 2             +1

Each term is fitted only where the curve has that term's slope (``allan_deviation``'s
``terms``); where no such region exists the term is reported as not resolved, never read
from a single point. A weighted non-negative least-squares fit of the sum of the five
terms (``model``) is the cross-check. ``simulate_noise`` makes a series with known terms.

Quantisation noise in this sense (slope -1) is white noise of the integrated signal, as
when a gyro's angle is counted in steps S (Q = S / sqrt(12)). Rounding each sample of a
magnetometer's field to its LSB is white noise of the signal itself: a random-walk term,
N = LSB sqrt(tau0 / 12), not Q.
"""

from dataclasses import dataclass, field

import numba
import numpy as np
from scipy.optimize import nnls


__all__ = ["kalman_filter", "allan_deviation", "AllanResult", "NoiseTerm", "simulate_noise",
           "TERMS", "BIAS_INSTABILITY_FACTOR"]

BIAS_INSTABILITY_FACTOR = np.sqrt(2 * np.log(2) / np.pi)

# name: (slope in log sigma vs log tau, sigma^2 per coefficient^2 as a function of tau).
TERMS = {
    "quantisation": (-1.0, lambda tau: 3.0 / tau ** 2),
    "random_walk": (-0.5, lambda tau: 1.0 / tau),
    "bias_instability": (0.0, lambda tau: np.full_like(tau, BIAS_INSTABILITY_FACTOR ** 2)),
    "rate_random_walk": (0.5, lambda tau: tau / 3.0),
    "rate_ramp": (1.0, lambda tau: tau ** 2 / 2.0),
}


#: The Kalman filter's twins: the numba kernel (used) and the plain loop (its reference).
KALMAN_KERNELS = ("numba", "numpy")


def kalman_filter(z, *, q, r, x0=None, p0=None, kernel="numba"):
    """The scalar Kalman filter of the paper on each column of ``z`` (a random walk state,
    B = H = 1): process noise variance ``q``, measurement noise variance ``r``; the state
    starts at ``x0`` (default: the first measurement) with variance ``p0`` (default ``r``).

    ``kernel`` is ``"numba"`` (a compiled loop over the samples) or ``"numpy"`` (the same
    recursion as a Python loop, vectorised over the columns: the reference the tests hold
    the kernel to). Returns (filtered states, their variances), both shaped like ``z``."""
    if kernel not in KALMAN_KERNELS:
        raise ValueError(f"Kernel must be one of {', '.join(KALMAN_KERNELS)}, not {kernel!r}")
    z = np.asarray(z, dtype=float)
    squeeze = z.ndim == 1
    if squeeze:
        z = z[:, None]
    if z.ndim != 2 or z.shape[0] == 0:
        raise ValueError(f"Measurements must be a non-empty (N,) or (N, axes) array, not "
                         f"shape {z.shape}")
    if not (q >= 0 and r > 0):
        raise ValueError(f"Noise variances must be q >= 0 and r > 0, not q={q!r}, r={r!r}")
    x = np.array(z[0] if x0 is None else np.broadcast_to(x0, z.shape[1]), dtype=float)
    p = np.full(z.shape[1], r if p0 is None else p0, dtype=float)
    states = np.empty_like(z)
    variances = np.empty_like(z)
    if kernel == "numba":
        _kalman_kernel(np.ascontiguousarray(z), float(q), float(r), x, p, states, variances)
    else:
        _kalman_loop(z, q, r, x, p, states, variances)
    if squeeze:
        return states[:, 0], variances[:, 0]
    return states, variances


def _kalman_loop(z, q, r, x, p, states, variances):
    for k in range(z.shape[0]):
        p = p + q                           # predict (the state is a random walk)
        gain = p / (p + r)                  # update
        x = x + gain * (z[k] - x)
        p = (1 - gain) * p
        states[k], variances[k] = x, p


@numba.njit(cache=True)
def _kalman_kernel(z, q, r, x0, p0, states, variances):
    # The same operations in the same order as _kalman_loop, column by column.
    for j in range(z.shape[1]):
        x, p = x0[j], p0[j]
        for k in range(z.shape[0]):
            p = p + q
            gain = p / (p + r)
            x = x + gain * (z[k, j] - x)
            p = (1 - gain) * p
            states[k, j] = x
            variances[k, j] = p


@dataclass
class NoiseTerm:
    """One noise term of the Allan curve: its coefficient where it was resolved."""
    name: str
    slope: float                # of log sigma vs log tau
    resolved: bool
    value: float                # coefficient (Q, N, B, K or R); NaN when not resolved
    error: float                # 1-sigma uncertainty of value; NaN when not resolved
    tau_range: tuple            # (first, last) tau (s) of the points used; () if none
    points: int                 # points of the curve used
    message: str


@dataclass
class AllanResult:
    """Overlapping Allan deviation and the noise terms it resolves.

    ``terms`` are the slope-region fits (the answer); ``model`` the weighted NNLS fit of
    the sum of the five terms, with each term's range where it is at least half the model
    variance and the curve's slope agrees with the model's. ``quantisation`` and
    ``bias_instability`` are the slope-region values (NaN when not resolved); ``tau_min``
    is where the curve is lowest."""
    taus: np.ndarray            # seconds
    deviation: np.ndarray       # overlapping Allan deviation, in the data's unit
    counts: np.ndarray          # number of (overlapping) second differences per tau
    clusters: np.ndarray        # N / m: non-overlapping clusters of m samples
    rel_error: np.ndarray       # 1-sigma relative error of deviation, 1/sqrt(2 (N/m - 1))
    slopes: np.ndarray          # local slope of log deviation vs log tau (NaN: too few)
    slope_errors: np.ndarray    # its standard error (points taken as independent)
    terms: dict                 # name -> NoiseTerm, slope-region fits
    model: dict                 # name -> NoiseTerm, NNLS sum-model fit
    tau_min: float              # where the deviation is lowest
    status: int                 # number of resolved terms
    message: str
    cost: float = np.nan        # weighted sum of squares of the sum model
    options: dict = field(default_factory=dict)

    @property
    def error(self):
        """1-sigma absolute error of ``deviation``."""
        return self.deviation * self.rel_error

    @property
    def quantisation(self):
        return self.terms["quantisation"].value

    @property
    def bias_instability(self):
        return self.terms["bias_instability"].value


def allan_deviation(y, rate, *, taus=None, slope_tolerance=0.1, slope_z=1.0, min_span=0.5,
                    min_clusters=10, window=0.5):
    """Overlapping Allan deviation of the rate-like series ``y`` sampled at ``rate`` Hz and
    the noise terms it resolves.

    ``taus``: averaging times (s); default 60 log-spaced cluster sizes (fewer after
    rounding to whole samples) up to a third of the span.
    A term is resolved where the local slope (a weighted line over ``window`` decades of
    tau) stays within ``slope_tolerance`` plus ``slope_z`` standard errors of that local
    slope of the term's slope, over at least ``min_span`` decades, using only points with
    at least ``min_clusters`` clusters; its coefficient is the weighted mean of
    log(sigma tau^-slope) over the longest such region. Near a neighbouring term that mean
    carries its leakage (the tolerance 0.1 admits up to a fifth of the variance from it, so
    up to ~10 % on the coefficient at the region's edge): ``model``, the sum of all terms
    fitted at once, does not.

    On 100 seeded synthetic series each of white noise, white noise plus rate random walk,
    and quantisation noise plus flicker, the defaults resolved an absent term in 0, 1 and
    2 of them: a curve going from slope -1 to 0 passes through -1/2 and can, rarely, be
    taken for a short random-walk region."""
    y = np.asarray(y, dtype=float)
    if y.ndim != 1 or y.size < 4:
        raise ValueError(f"Series must be 1-D with at least 4 samples, not shape {y.shape}")
    if not np.all(np.isfinite(y)):
        raise ValueError("Series must be finite (found NaN or infinity)")
    if not rate > 0:
        raise ValueError(f"Sample rate must be positive, not {rate!r}")
    if not (slope_tolerance > 0 and slope_z >= 0 and min_span >= 0 and min_clusters >= 2
            and window > 0):
        raise ValueError(f"Fit options must be slope_tolerance > 0, slope_z >= 0, "
                         f"min_span >= 0, min_clusters >= 2 and window > 0, not "
                         f"{slope_tolerance!r}, {slope_z!r}, {min_span!r}, {min_clusters!r}, "
                         f"{window!r}")
    tau0 = 1.0 / rate
    n = y.size
    if taus is None:
        ms = np.unique(np.round(np.logspace(0, np.log10(max(n // 3, 1)), 60)).astype(int))
    else:
        ms = np.unique(np.round(np.asarray(taus, dtype=float) / tau0).astype(int))
    ms = ms[(ms >= 1) & (2 * ms < n)]
    x = np.concatenate(([0.0], np.cumsum(y))) * tau0          # phase
    deviation, counts = [], []
    for m in ms:
        d = x[2 * m:] - 2 * x[m:-m] + x[:-2 * m]
        deviation.append(np.sqrt(np.sum(d * d) / (2 * (m * tau0) ** 2 * d.size)))
        counts.append(d.size)
    taus_out = ms * tau0
    deviation = np.array(deviation)
    clusters = n / ms
    # Chi-square with N/m - 1 degrees of freedom (Allan's simple estimate; the overlapping
    # estimator is somewhat better, so this is conservative).
    rel_error = 1.0 / np.sqrt(2.0 * np.maximum(clusters - 1.0, 1.0))
    usable = (clusters >= min_clusters) & (deviation > 0)
    slopes, slope_errors = _local_slopes(taus_out, deviation, rel_error, usable, window)
    allowed = slope_tolerance + slope_z * slope_errors
    model, cost, coef = _fit_sum_model(taus_out, deviation, rel_error, slopes, allowed, usable,
                                       min_span)
    terms = _fit_slope_regions(taus_out, deviation, rel_error, slopes, allowed, usable,
                               slope_tolerance, min_span, coef)
    resolved = [name for name, term in terms.items() if term.resolved]
    message = ("resolved: " + ", ".join(resolved)) if resolved else "no noise term resolved"
    best = int(np.argmin(deviation)) if deviation.size else 0
    return AllanResult(
        taus=taus_out, deviation=deviation, counts=np.array(counts), clusters=clusters,
        rel_error=rel_error, slopes=slopes, terms=terms, model=model,
        tau_min=float(taus_out[best]) if deviation.size else np.nan,
        status=len(resolved), message=message, cost=cost,
        slope_errors=slope_errors,
        options=dict(slope_tolerance=slope_tolerance, slope_z=slope_z, min_span=min_span,
                     min_clusters=min_clusters, window=window))


def _local_slopes(taus, deviation, rel_error, usable, window):
    """Weighted least-squares slope of log sigma vs log tau within +-window/2 decades."""
    lt = np.log10(taus)
    ld = np.log10(np.where(deviation > 0, deviation, 1.0))
    w = (np.log(10) / rel_error) ** 2       # 1 / variance of log10 sigma
    slopes = np.full(taus.size, np.nan)
    errors = np.full(taus.size, np.nan)
    for i in np.flatnonzero(usable):
        distance = np.where(usable, np.abs(lt - lt[i]), np.inf)
        near = distance <= window / 2 + 1e-12
        if near.sum() < 3:                  # the first points: the three nearest
            near = distance <= np.sort(distance)[2]
        if near.sum() < 3 or not np.all(np.isfinite(distance[near])):
            continue
        wi, xi, yi = w[near], lt[near], ld[near]
        xm = np.sum(wi * xi) / wi.sum()
        ym = np.sum(wi * yi) / wi.sum()
        sxx = np.sum(wi * (xi - xm) ** 2)
        slopes[i] = np.sum(wi * (xi - xm) * (yi - ym)) / sxx
        errors[i] = 1.0 / np.sqrt(sxx)
    return slopes, errors


def _runs(mask):
    """(start, stop) index pairs of the runs of True in ``mask``."""
    edges = np.diff(np.concatenate(([0], mask.astype(np.int8), [0])))
    return list(zip(np.flatnonzero(edges == 1), np.flatnonzero(edges == -1)))


def _coefficient(name, c):
    """Term coefficient from sigma = c tau^slope (c of the term alone)."""
    _, basis = TERMS[name]
    return c / np.sqrt(basis(np.array([1.0]))[0])


def _fit_slope_regions(taus, deviation, rel_error, slopes, allowed, usable, tolerance,
                       min_span, coef):
    terms = {}
    lt = np.log10(taus)
    basis = np.column_stack([TERMS[name][1](taus) for name in TERMS])
    total = np.maximum(basis @ coef, np.finfo(float).tiny)
    for j, (name, (slope, _)) in enumerate(TERMS.items()):
        inside = usable & np.isfinite(slopes) & (np.abs(slopes - slope) <= allowed)
        best, best_span = None, -1.0
        for start, stop in _runs(inside):
            span = lt[stop - 1] - lt[start]
            if span > best_span:
                best, best_span = (start, stop), span
        if best is None or best_span < min_span or best[1] - best[0] < 3:
            found = ("no region" if best is None else
                     f"longest region {best_span:.2f} decades, {best[1] - best[0]} points")
            terms[name] = NoiseTerm(
                name, slope, False, np.nan, np.nan, (), 0,
                f"not resolved: slope {slope:+g} +- {tolerance:g} over >= {min_span:g} "
                f"decades not found ({found})")
            continue
        start, stop = best
        w = 1.0 / rel_error[start:stop] ** 2
        level = np.log(deviation[start:stop]) - slope * np.log(taus[start:stop])
        mean = np.sum(w * level) / w.sum()
        # Neighbouring points share data, so their errors are taken as fully correlated
        # (the weighted mean of the points' errors); the scatter about the fixed slope and
        # the other terms' share of the sum model's variance in the region (1 - f: the
        # coefficient would be sqrt(f) of the value) show neighbours leaking in.
        statistical = np.sum(w * rel_error[start:stop]) / w.sum()
        spread = np.sqrt(np.sum(w * (level - mean) ** 2) / w.sum())
        own = np.sum(w * basis[start:stop, j] * coef[j] / total[start:stop]) / w.sum()
        leakage = 1.0 - np.sqrt(np.clip(own, 0.0, 1.0)) if coef.any() else 0.0
        rel = np.sqrt(statistical ** 2 + spread ** 2 + leakage ** 2)
        value = float(_coefficient(name, np.exp(mean)))
        terms[name] = NoiseTerm(
            name, slope, True, value, value * rel,
            (float(taus[start]), float(taus[stop - 1])), int(stop - start),
            f"slope {slope:+g} +- {tolerance:g} over {best_span:.2f} decades")
    return terms


def _fit_sum_model(taus, deviation, rel_error, slopes, allowed, usable, min_span):
    """NNLS of sigma^2 = sum_j c_j^2 basis_j(tau), each row weighted by 1 / (2 rel sigma^2).

    A term is resolved where it is at least half the model's variance and the model's slope
    (sum of the terms' shares times their slopes) matches the curve's local slope, over at
    least ``min_span`` decades: a curve that is no sum of these terms (a filtered series
    below the filter's time constant) is not read as one.

    Returns the terms, the weighted sum of squares and the c_j^2."""
    names = list(TERMS)
    t, var, rel = taus[usable], deviation[usable] ** 2, rel_error[usable]
    slopes, allowed = slopes[usable], allowed[usable]
    if t.size < len(names):
        return ({name: NoiseTerm(name, TERMS[name][0], False, np.nan, np.nan, (), 0,
                                 "not resolved: too few points for the sum model")
                 for name in names}, np.nan, np.zeros(len(names)))
    basis = np.column_stack([TERMS[name][1](t) for name in names])
    scale = 2.0 * rel * var
    a, b = basis / scale[:, None], var / scale
    coef, residual = nnls(a, b)
    active = coef > 0
    cov = np.full((len(names), len(names)), np.nan)
    if active.any():
        cov[np.ix_(active, active)] = np.linalg.pinv(a[:, active].T @ a[:, active])
    # The points overlap in data and in tau: counted as one independent point per octave.
    octaves = max(np.log2(t[-1] / t[0]), 1.0)
    cov *= max(t.size / octaves, 1.0)
    share = basis * coef / np.maximum(basis @ coef, np.finfo(float).tiny)[:, None]
    model_slope = share @ np.array([TERMS[name][0] for name in names])
    agrees = np.isfinite(slopes) & (np.abs(slopes - model_slope) <= allowed)
    lt = np.log10(t)
    model = {}
    for j, name in enumerate(names):
        slope = TERMS[name][0]
        runs = _runs((share[:, j] >= 0.5) & agrees)
        start, stop = max(runs, key=lambda r: lt[r[1] - 1] - lt[r[0]]) if runs else (0, 0)
        span = lt[stop - 1] - lt[start] if runs else -1.0
        if coef[j] <= 0 or span < min_span or stop - start < 3:
            why = ("coefficient 0" if coef[j] <= 0 else
                   f"at least half the model variance, with the curve's slope, over only "
                   f"{max(span, 0):.2f} decades")
            model[name] = NoiseTerm(name, slope, False, np.nan, np.nan, (), 0,
                                    f"not resolved: {why}")
            continue
        value = float(np.sqrt(coef[j]))
        error = float(np.sqrt(cov[j, j]) / (2 * value))      # d sqrt(c) = dc / (2 sqrt(c))
        model[name] = NoiseTerm(
            name, slope, True, value, error, (float(t[start]), float(t[stop - 1])),
            int(stop - start),
            f"at least half the model variance, with the curve's slope, over {span:.2f} decades")
    return model, float(residual ** 2), coef


def simulate_noise(n, rate, *, quantisation=0.0, random_walk=0.0, bias_instability=0.0,
                   rate_random_walk=0.0, rate_ramp=0.0, rng=None):
    """A rate-like series of ``n`` samples at ``rate`` Hz with the given IEEE 952
    coefficients (same meaning and units as ``AllanResult.terms``; tau0 = 1 / rate):

    - quantisation Q: white phase noise e of std Q, y_k = (e_k - e_(k-1)) / tau0, whose
      Allan variance is 3 Q^2 / tau^2 exactly at tau = m tau0 (the second difference of
      the phase has variance 6 Q^2). Quantising the integral with step S gives Q = S/sqrt(12).
    - random walk N: white noise of std N / sqrt(tau0) (two-sided spectrum N^2).
    - bias instability B: flicker noise by Kasdin's method (Kasdin and Walter 1992):
      white noise of std B through the filter (1 - z^-1)^(-1/2), coefficients
      h_0 = 1, h_k = h_(k-1) (k - 1/2) / k. Its two-sided spectrum is
      B^2 tau0 / |2 sin(pi f tau0)| ~ B^2 / (2 pi f), IEEE's B^2 / (2 pi f): so the std of
      the white input is B itself, and the Allan floor 0.664 B.
    - rate random walk K: the cumulative sum of white noise of std K sqrt(tau0).
    - rate ramp R: R t.
    """
    if not (isinstance(n, (int, np.integer)) and n >= 2):
        raise ValueError(f"Length must be an integer >= 2, not {n!r}")
    if not rate > 0:
        raise ValueError(f"Sample rate must be positive, not {rate!r}")
    coefficients = (quantisation, random_walk, bias_instability, rate_random_walk, rate_ramp)
    if not all(np.isfinite(c) and c >= 0 for c in coefficients):
        raise ValueError(f"Noise coefficients must be finite and >= 0, not {coefficients!r}")
    rng = np.random.default_rng(rng)
    tau0 = 1.0 / rate
    y = np.zeros(n)
    if quantisation:
        e = rng.normal(scale=quantisation, size=n + 1)
        y += np.diff(e) / tau0
    if random_walk:
        y += rng.normal(scale=random_walk / np.sqrt(tau0), size=n)
    if bias_instability:
        y += _flicker(n, bias_instability, rng)
    if rate_random_walk:
        y += np.cumsum(rng.normal(scale=rate_random_walk * np.sqrt(tau0), size=n))
    if rate_ramp:
        y += rate_ramp * tau0 * np.arange(n)
    return y


def _flicker(n, scale, rng):
    """Kasdin's 1/f noise: white noise of std ``scale`` through (1 - z^-1)^(-1/2), as a
    linear convolution by FFTs of twice the length."""
    k = np.arange(1, n)
    h = np.concatenate(([1.0], np.cumprod((k - 0.5) / k)))
    w = rng.normal(scale=scale, size=n)
    size = 2 * n
    return np.fft.irfft(np.fft.rfft(w, size) * np.fft.rfft(h, size), size)[:n]
