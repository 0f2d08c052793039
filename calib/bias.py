"""What a bias looks like in the residual of a scalar calibration, tested after the fit.

A calibration leaves the sensor's noise when its inputs agree with the model. Two common
disagreements do not show in the residual's size (the noise estimate grows, no more) but
bias every parameter, and both leave a shape in the residual that noise does not have:

- **A lag.** A magnetometer whose axes pass through a low-pass filter (a first-order lag
  of time constant tau: the sensor's bandwidth, a digital filter) reads the field vector
  late; while the aircraft turns, the lagged vector is shorter than the field by
  tau^2 |du/dt|^2 / (2 |u|) to second order (u the calibrated vector; the first-order term
  vanishes because turning does not change the field's magnitude). A reference (or a
  magnetometer) late by tau as a whole leaves tau times the reference's rate of change,
  d|B_ref|/dt. The residual is regressed on both rates (with an intercept); the
  coefficients give the lag in ms, and their Newey-West standard errors (the residual's
  own autocorrelation counted) their significance.
- **A reference that ignores what the magnetometer sees** (a constant or IGRF reference
  over crustal anomalies, slowly varying interference): the residual holds slow structure
  along the track. Its part that survives a running mean over ``SMOOTH_S`` seconds is
  compared with what the noise leaves there (the noise from the residual's sample-to-sample
  differences, which slow structure does not reach).

Each finding is a warning with the figure that triggered it and what to do. A clean flight
(white noise about the model) triggers neither, by design of the thresholds: see the false
alarm and detection rates measured in ``tests/calib/test_bias.py``.

Ref: W. K. Newey and K. D. West, "A simple, positive semi-definite, heteroskedasticity and
     autocorrelation consistent covariance matrix", Econometrica 55 (1987) 703-708.
"""

from dataclasses import dataclass, field

import numpy as np


__all__ = ["BiasCheck", "check_residual", "LAG_Z", "SMOOTH_S", "SMOOTH_RATIO"]

#: A lag is reported when its coefficient is this many standard errors from zero...
LAG_Z = 6.0
#: ... and the structure it explains is at least this share of the residual's RMS (a
#: significant lag too small to move anything is not worth a warning).
LAG_SHARE = 0.2
#: Window of the running mean that keeps the residual's slow structure, seconds.
SMOOTH_S = 5.0
#: Slow structure is reported when its RMS exceeds this many times what the noise leaves
#: through the running mean (sigma / sqrt(window samples); clean flights gave 0.6-1.5)...
SMOOTH_RATIO = 2.0
#: ... and this share of the noise itself (a few tenths of a nT of slow drift under a nT
#: of noise moves no parameter).
SMOOTH_SHARE = 0.3
#: The memory of the noise itself (a sensor's filter), seconds: what the running mean is
#: compared with counts correlation up to this lag.
MEMORY_S = 0.5
#: Fewest samples, and fewest windows, for either test to say anything.
MIN_SAMPLES = 100
MIN_WINDOWS = 8


@dataclass
class BiasCheck:
    """What :func:`check_residual` found. Lags in seconds (NaN: not estimable)."""
    lag_vector_s: float = float("nan")      # first-order filter on the magnetometer's axes
    lag_vector_z: float = float("nan")      # significance of its coefficient
    lag_vector_share: float = float("nan")  # RMS it explains / residual RMS
    lag_reference_s: float = float("nan")   # delay of the reference (negative: the
    lag_reference_z: float = float("nan")   # magnetometer is the late one)
    lag_reference_share: float = float("nan")
    slow_rms_nT: float = float("nan")       # RMS of the running mean of the residual
    slow_expected_nT: float = float("nan")  # what white noise leaves there
    noise_nT: float = float("nan")          # the residual's sample-to-sample noise
    warnings: list = field(default_factory=list)

    def as_dict(self):
        def num(v):
            return None if not np.isfinite(v) else float(v)
        return {"lag_vector_ms": num(1e3 * self.lag_vector_s),
                "lag_vector_z": num(self.lag_vector_z),
                "lag_reference_ms": num(1e3 * self.lag_reference_s),
                "lag_reference_z": num(self.lag_reference_z),
                "slow_rms_nT": num(self.slow_rms_nT),
                "slow_expected_nT": num(self.slow_expected_nT),
                "noise_nT": num(self.noise_nT), "warnings": list(self.warnings)}


def _derivative(x, t):
    """d x / d t by central differences over two samples each side (the noise of a single
    difference is amplified most), one-sided at the ends."""
    x = np.asarray(x, float)
    n = len(x)
    out = np.empty_like(x)
    lo = np.clip(np.arange(n) - 2, 0, n - 1)
    hi = np.clip(np.arange(n) + 2, 0, n - 1)
    dt = t[hi] - t[lo]
    dt = np.where(dt > 0, dt, np.nan)
    out = (x[hi] - x[lo]) / (dt if x.ndim == 1 else dt[:, None])
    return out


def _newey_west(x, e, lags):
    """OLS of ``e`` on the columns of ``x``: coefficients and their Newey-West standard
    errors with ``lags`` (Bartlett weights)."""
    xtx = x.T @ x
    inv = np.linalg.pinv(xtx)
    beta = inv @ (x.T @ e)
    u = e - x @ beta
    scores = x * u[:, None]
    meat = scores.T @ scores
    for k in range(1, lags + 1):
        w = 1.0 - k / (lags + 1.0)
        gamma = scores[k:].T @ scores[:-k]
        meat += w * (gamma + gamma.T)
    cov = inv @ meat @ inv
    return beta, np.sqrt(np.clip(np.diag(cov), 0, None))


def _running_mean(e, window):
    kernel = np.ones(window) / window
    return np.convolve(e, kernel, mode="valid")


def check_residual(t, vectors, r, keep=None):
    """Test the residual |u| - r of calibrated vectors ``u`` (N, 3) against the reference
    ``r`` (N,) at times ``t`` (s) for a lag and for slow structure, over the samples in
    ``keep`` (the fitted ones). Returns a :class:`BiasCheck` whose ``warnings`` say what
    was found, with the figure and what to do."""
    t = np.asarray(t, float)
    u = np.asarray(vectors, float)
    r = np.asarray(r, float)
    n = len(t)
    keep = np.ones(n, bool) if keep is None else np.asarray(keep, bool)
    out = BiasCheck()
    if n < MIN_SAMPLES or not np.all(np.isfinite(t)) or np.any(np.diff(t) <= 0):
        return out
    norm = np.linalg.norm(u, axis=1)
    e = norm - r
    du = _derivative(u, t)
    dr = _derivative(r, t)
    good = keep & np.isfinite(e) & np.all(np.isfinite(du), axis=1) & np.isfinite(dr)
    # The ends' one-sided differences and the samples next to gaps are left out.
    step = float(np.median(np.diff(t)))
    gaps = np.zeros(n, bool)
    jumps = np.flatnonzero(np.diff(t) > 1.5 * step)
    for j in jumps:
        gaps[max(j - 2, 0):j + 3] = True
    good &= ~gaps
    good[:2] = good[-2:] = False
    if good.sum() < MIN_SAMPLES:
        return out
    e_g = e[good]
    # Noise from sample-to-sample differences of the residual (robust: MAD).
    d = np.diff(e_g)
    noise = 1.4826 * float(np.median(np.abs(d - np.median(d)))) / np.sqrt(2.0)
    out.noise_nT = noise
    explained = _lag_test(out, e_g, du[good], dr[good], norm[good], step)
    # A lag found is not counted again as slow structure: its fitted part is taken out.
    rest = e.copy()
    rest[good] -= explained
    # Slow structure smaller than a lag found is the lag's own (the fit absorbs part of
    # its shape, so taking out the fitted part leaves some): not reported twice.
    _slow_test(out, rest, good, step, noise,
               floor=float(np.sqrt(np.mean(explained ** 2))))
    return out


def _lag_test(out, e, du, dr, norm, step):
    vector_rate = np.einsum("ij,ij->i", du, du) / (2.0 * norm)      # |du/dt|^2 / (2 |u|)
    x = np.column_stack([np.ones(len(e)), vector_rate, dr])
    scale = np.std(x, axis=0)
    scale[0] = 1.0
    usable = scale > 0
    if not np.all(usable[1:]):
        # A regressor that never varies (a constant reference has no rate) is left out.
        x, scale = x[:, usable], scale[usable]
    lags = max(1, int(round(1.0 / step)))       # a second of the residual's memory
    beta, se = _newey_west(x / scale, e, lags)
    beta, se = beta / scale, se / scale
    rms = float(np.sqrt(np.mean((e - np.mean(e)) ** 2)))
    columns = [i for i, ok in enumerate(usable) if ok]
    explained = np.zeros(len(e))
    for k, column in enumerate(columns):
        if column == 0:
            continue
        z = beta[k] / se[k] if se[k] > 0 else np.inf * np.sign(beta[k])
        part = beta[k] * (x[:, k] - np.mean(x[:, k]))
        share = float(np.sqrt(np.mean(part ** 2))) / max(rms, 1e-12)
        if column == 1:
            # e = -tau^2 * rate: only a negative coefficient is a lag.
            out.lag_vector_s = float(np.sqrt(-beta[k])) if beta[k] < 0 else 0.0
            out.lag_vector_z = float(-z)
            out.lag_vector_share = share
            if -z >= LAG_Z and share >= LAG_SHARE:
                explained += part
                out.warnings.append(
                    f"the residual follows the square of the field vector's rate of change "
                    f"({share:.0%} of its RMS, {-z:.0f} standard errors): the magnetometer's "
                    f"axes lag the field by about {1e3 * out.lag_vector_s:.0f} ms (a "
                    "first-order filter: the sensor's bandwidth or a digital filter), which "
                    "biases every parameter; undo it before calibrating (maglog calibrate "
                    f"--mag-lag {1e3 * out.lag_vector_s:.0f}) or fit a flight with slower "
                    "turns")
        else:
            out.lag_reference_s = float(beta[k])
            out.lag_reference_z = float(z)
            out.lag_reference_share = share
            if abs(z) >= LAG_Z and share >= LAG_SHARE:
                explained += part
                late = "reference lags the magnetometer" if beta[k] > 0 else \
                    "magnetometer lags the reference"
                option = "--ref-lag" if beta[k] > 0 else "--mag-lag"
                out.warnings.append(
                    f"the residual follows the reference's rate of change ({share:.0%} of "
                    f"its RMS, {abs(z):.0f} standard errors): the {late} by about "
                    f"{1e3 * abs(beta[k]):.0f} ms, which biases the fit; align the times "
                    f"(maglog calibrate {option} {1e3 * abs(beta[k]):.0f})")
    return explained


def _short_memory(e, step, noise):
    """The noise's level as a running mean sees it (nT). Noise through a sensor's own
    filter is correlated over a few samples: its running mean is larger than white
    noise's, without any structure along the track. The noise's variance s^2 is taken from
    differences :data:`MEMORY_S` apart (past the noise's memory, well within slow
    structure's), its autocorrelation at shorter lags from var(x_(i+k) - x_i) =
    2 s^2 (1 - rho_k), and the level is s times the square root of the long-run variance
    factor 1 + 2 sum w_k rho_k (Bartlett weights). White noise gives ``noise``."""
    lags = max(1, int(round(MEMORY_S / step)))
    if len(e) <= 4 * lags:
        return noise

    def spread(k):
        d = e[k:] - e[:-k]
        return (1.4826 * float(np.median(np.abs(d - np.median(d))))) ** 2

    far = spread(lags)
    if not far > 0:
        return noise
    factor = 1.0
    for k in range(1, lags):
        rho = max(0.0, 1.0 - spread(k) / far)
        factor += 2.0 * (1.0 - k / float(lags)) * rho
    return float(np.sqrt(far / 2.0 * factor))


def _slow_test(out, e, good, step, noise, floor=0.0):
    window = max(2, int(round(SMOOTH_S / step)))
    # Runs of good samples, each smoothed on its own (a gap is no neighbour).
    means = []
    edges = np.flatnonzero(np.diff(np.r_[0, good.astype(int), 0]))
    for start, stop in zip(edges[::2], edges[1::2]):
        if stop - start >= window:
            means.append(_running_mean(e[start:stop], window))
    if not means:
        return
    slow = np.concatenate(means)
    if len(slow) < MIN_WINDOWS * window:
        return
    slow = slow - np.mean(slow)
    out.slow_rms_nT = float(np.sqrt(np.mean(slow ** 2)))
    out.slow_expected_nT = _short_memory(e[good], step, noise) / np.sqrt(window)
    if out.slow_rms_nT > SMOOTH_RATIO * out.slow_expected_nT and \
            out.slow_rms_nT > max(SMOOTH_SHARE * noise, floor):
        out.warnings.append(
            f"the residual holds slow structure along the track: {out.slow_rms_nT:.3g} nT "
            f"RMS over {SMOOTH_S:g} s windows, {out.slow_rms_nT / out.slow_expected_nT:.0f} "
            f"times what the noise ({noise:.3g} nT) leaves there: the reference does not "
            "see what the magnetometer sees (a constant or IGRF reference over crustal "
            "anomalies or a diurnal change, or interference that varies slowly), which "
            "biases the fit; use a measured reference (--ref cesium) or calibrate on a "
            "manoeuvre flown high and away from anomalies")


#: The longest lag that can be undone, seconds (a sensor's filter is tens to hundreds of
#: ms; more than this is a clock error, not a lag).
MAX_LAG_S = 2.0


def check_lag(value, what="lag"):
    """A lag in seconds: finite, 0 to :data:`MAX_LAG_S` (``ValueError`` otherwise)."""
    try:
        value = float(value)
    except (TypeError, ValueError):
        raise ValueError(f"The {what} must be a number of seconds, not {value!r}") from None
    if not (np.isfinite(value) and 0.0 <= value <= MAX_LAG_S):
        raise ValueError(f"The {what} must be 0 to {1e3 * MAX_LAG_S:g} ms, not "
                         f"{1e3 * value:g} ms")
    return value


def undo_lag(x, t, tau):
    """``x`` (N,) or (N, 3) sampled at times ``t`` (s) with a first-order lag of time
    constant ``tau`` (s) undone: the filter ``tau dy/dt + y = x`` inverted, ``x = y +
    tau dy/dt`` (the derivative by the five-point central difference, fourth order, where
    the two samples each side are evenly spaced; by numpy's second-order gradient
    elsewhere: the ends and the edges of gaps)."""
    x = np.asarray(x, float)
    if tau == 0:
        return x.copy()
    t = np.asarray(t, float)
    rate = np.gradient(x, t, axis=0)
    if len(t) >= 5:
        h = np.diff(t)
        even = np.zeros(len(t), bool)
        even[2:-2] = np.all(np.abs(np.column_stack([h[:-3], h[1:-2], h[2:-1], h[3:]])
                                   - h[1:-2, None]) <= 1e-3 * h[1:-2, None], axis=1)
        i = np.flatnonzero(even)
        step = (t[i + 1] - t[i - 1]) / 2
        five = (-x[i + 2] + 8 * x[i + 1] - 8 * x[i - 1] + x[i - 2])
        rate[i] = five / (12 * (step if x.ndim == 1 else step[:, None]))
    return x + tau * rate
