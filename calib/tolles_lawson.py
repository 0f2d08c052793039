"""Tolles–Lawson compensation of the scalar (cesium) channel from the vector's direction cosines.

The platform's magnetic interference at the scalar sensor is modelled as a linear function of
the unit Earth-field direction ``u`` in the body frame, the total field ``T`` and the rate
``u' = du/dt`` (per second, ``np.gradient(u, t)``): 18 terms in this order (issue 15's plan)

- permanent ``u1 u2 u3`` (coefficients in nT),
- induced ``T*(u1u1, u1u2, u1u3, u2u2, u2u3, u3u3)`` (dimensionless),
- eddy ``T*(u1u1', u1u2', u1u3', u2u1', u2u2', u2u3', u3u1', u3u2', u3u3')`` (seconds),

or 16 terms, the same without induced ``u2u2`` and eddy ``u2u2'`` (deinterf's choice). The
18-term set is rank-deficient: ``u·u' = 0`` makes the three diagonal eddy terms sum to zero
exactly, and ``u1² + u2² + u3² = 1`` makes the three diagonal induced terms sum to T, which
the band-pass removes wherever T is steady (a hover). Only differences of the diagonal
coefficients are determined; the ridge picks the smallest-norm split. The 16-term set's
diagonal coefficients are those differences (``c11 - c22``, ``c33 - c22``), full rank.

The fit (:func:`fit`) is made on the calibration box (hovering rolls, pitches and yaws on four
headings). Slow signals in the scalar (the anomaly under the aircraft, the diurnal variation,
IGRF along the track) are not interference; both sides are band-passed with the same
zero-phase Butterworth filter (:func:`bandpass`) before the fit, which is exact for a linear
model: ``bpf(X) @ c = bpf(X @ c)``. The band comes from the manoeuvres' own spectrum
(:func:`choose_band`). The coefficients are a ridge solution on standardised band-passed
features, the ridge parameter chosen by cross-validation on contiguous blocks
(``ridge="auto"``): adjacent samples of a 10-Hz record are strongly correlated, so shuffled
folds would reward over-fitting.

The constant part of the interference is not identifiable from band-passed data (the band-pass
removes it, along with anything constant over the box); :meth:`TLFit.predict` therefore
returns the interference minus its mean over the box, as deinterf does (deinterf removes the
mean over whatever it predicts; here it is the box mean, fixed at fit time, so the whole
flight's compensated level does not depend on which part of the flight is predicted).

:func:`deinterf_compensate` does the same job through the `deinterf` package (1.2) for the
report's comparison; its differences are listed there.

Every check raises :class:`~maglog.calib.survey_errors.SurveyError` with a one-line message.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from scipy import signal

from .survey_errors import SurveyError


__all__ = ["TERM_NAMES", "TLFit", "features", "bandpass", "choose_band",
           "fit", "improvement_ratio", "figure_of_merit", "deinterf_compensate"]


_NAMES_18 = (
    "perm_u1", "perm_u2", "perm_u3",
    "ind_u1u1", "ind_u1u2", "ind_u1u3", "ind_u2u2", "ind_u2u3", "ind_u3u3",
    "eddy_u1u1'", "eddy_u1u2'", "eddy_u1u3'", "eddy_u2u1'", "eddy_u2u2'", "eddy_u2u3'",
    "eddy_u3u1'", "eddy_u3u2'", "eddy_u3u3'",
)
#: Columns of the 18-term set dropped in the 16-term set (induced u2u2, eddy u2u2').
_DROP_16 = (6, 13)
_KEEP_16 = tuple(k for k in range(18) if k not in _DROP_16)

#: Names of the terms, in the order of :func:`features`' columns, for 16 and 18 terms.
TERM_NAMES = {18: _NAMES_18, 16: tuple(_NAMES_18[k] for k in _KEEP_16)}

#: The band is kept within these limits: below 0.02 Hz the diurnal variation and the anomaly
#: along a line are as large as the interference; above 0.45 × rate the filter is too
#: close to Nyquist.
BAND_FLOOR_HZ = 0.02
BAND_CEILING = 0.45
#: choose_band: a frequency is "strong" when the rate spectrum there reaches this fraction of
#: its maximum; the band runs from BAND_MARGIN below the lowest strong frequency to
#: BAND_MARGIN above the highest (a factor, i.e. an octave each side).
STRONG_FRACTION = 0.1
BAND_MARGIN = 2.0
#: Least samples per term for a fit, and least box length in periods of the band's low edge
#: (the filter's transients at the box's ends must not dominate).
SAMPLES_PER_TERM = 10
BOX_PERIODS = 2.0
#: Ridge "auto": the grid of ridge parameters (on standardised features, penalty
#: alpha * |c|² against the residual sum of squares) and the number of contiguous blocks.
RIDGE_GRID = np.logspace(-6, 6, 25)
CV_BLOCKS = 5
#: Direction cosines must be unit vectors to within this (they come normalised).
UNIT_TOLERANCE = 0.05
#: A gap longer than this many sample intervals splits the record into pieces filtered apart.
GAP_SAMPLES = 2.5


# ---------------------------------------------------------------------------------------
# input checks

def _where(t, k):
    return f"t={t[k]:.3f} s" if t is not None and 0 <= k < len(t) else f"sample {k}"


def _check_t(t, what):
    t = np.asarray(t, dtype=float)
    if t.ndim != 1:
        raise SurveyError(f"{what}: times must be a 1-D array, not shape {t.shape}")
    bad = np.flatnonzero(~np.isfinite(t))
    if bad.size:
        raise SurveyError(f"{what}: time is NaN or infinite at sample {bad[0]}")
    if t.size >= 2:
        step = np.diff(t)
        bad = np.flatnonzero(step <= 0)
        if bad.size:
            raise SurveyError(f"{what}: times not increasing at t={t[bad[0]]:.3f} s")
    return t


def _check_inputs(t, cosines, total, scalar, what, allow_nan=False):
    t = _check_t(t, what)
    n = t.size
    cosines = np.asarray(cosines, dtype=float)
    if cosines.shape != (n, 3):
        raise SurveyError(f"{what}: cosines must have shape ({n}, 3) like the times, "
                          f"not {cosines.shape}")
    total = np.asarray(total, dtype=float)
    if total.ndim == 0:
        total = np.full(n, float(total))
    if total.shape != (n,):
        raise SurveyError(f"{what}: total must have shape ({n},) like the times, "
                          f"not {total.shape}")
    arrays = [("cosines", cosines), ("total", total)]
    if scalar is not None:
        scalar = np.asarray(scalar, dtype=float)
        if scalar.shape != (n,):
            raise SurveyError(f"{what}: scalar must have shape ({n},) like the times, "
                              f"not {scalar.shape}")
        arrays.append(("scalar", scalar))
    for name, a in arrays:
        finite = np.isfinite(a) if a.ndim == 1 else np.isfinite(a).all(axis=1)
        if not allow_nan and not finite.all():
            k = int(np.flatnonzero(~finite)[0])
            raise SurveyError(f"{what}: {name} is NaN or infinite at {_where(t, k)}")
    with np.errstate(invalid="ignore"):
        norm = np.linalg.norm(cosines, axis=1)
        bad = np.flatnonzero(np.abs(norm - 1.0) > UNIT_TOLERANCE)
        if bad.size:
            k = int(bad[0])
            raise SurveyError(f"{what}: cosines are not unit vectors (norm {norm[k]:.4g} at "
                              f"{_where(t, k)}); pass the field's direction, not the field")
        bad = np.flatnonzero(total <= 0)
        if bad.size:
            k = int(bad[0])
            raise SurveyError(f"{what}: total field must be > 0 nT, not {total[k]:g} at "
                              f"{_where(t, k)}")
    return t, cosines, total, scalar


def _check_terms(terms):
    if terms not in TERM_NAMES:
        raise SurveyError(f"terms must be 16 or 18, not {terms!r}")
    return terms


def _rate(t, what):
    if t.size < 2:
        raise SurveyError(f"{what}: too few samples ({t.size}) to tell the sampling rate")
    return 1.0 / float(np.median(np.diff(t)))


def _check_band(band, rate_hz, what):
    try:
        lo, hi = (float(b) for b in band)
    except (TypeError, ValueError):
        raise SurveyError(f"{what}: band must be (low_hz, high_hz), not {band!r}") from None
    nyquist = rate_hz / 2
    if not (0 < lo < hi < nyquist):
        raise SurveyError(f"{what}: band must satisfy 0 < low < high < {nyquist:g} Hz "
                          f"(half the {rate_hz:g}-Hz rate), not ({lo:g}, {hi:g})")
    return lo, hi


def _pieces(t, rate_hz):
    """Slices of ``t`` without a gap longer than GAP_SAMPLES sample intervals."""
    cuts = np.flatnonzero(np.diff(t) > GAP_SAMPLES / rate_hz) + 1
    edges = np.concatenate(([0], cuts, [t.size]))
    return [slice(int(a), int(b)) for a, b in zip(edges[:-1], edges[1:])]


# ---------------------------------------------------------------------------------------
# features and filters

def features(t, cosines, total, terms=18):
    """The Tolles–Lawson features, shape ``(n, terms)``, columns in :data:`TERM_NAMES` order.

    ``t`` in s, ``cosines`` (n, 3) the unit field direction in the body frame, ``total``
    (n,) in nT (or a scalar). ``u'`` is ``np.gradient(u, t)`` per second (second-order
    central differences, one-sided at the ends), computed separately on each piece of the
    record between gaps. NaN inputs give NaN rows (and NaN rates next to them).
    """
    _check_terms(terms)
    t, u, T, _ = _check_inputs(t, cosines, total, None, "features", allow_nan=True)
    if t.size < 2:
        raise SurveyError(f"features: too few samples ({t.size}); at least 2 are needed "
                          "for the rates")
    du = np.empty_like(u)
    for sl in _pieces(t, _rate(t, "features")):
        if sl.stop - sl.start >= 2:
            du[sl] = np.gradient(u[sl], t[sl], axis=0)
        else:
            du[sl] = 0.0
    i, j = np.triu_indices(3)
    induced = T[:, None] * u[:, i] * u[:, j]
    eddy = T[:, None] * (u[:, :, None] * du[:, None, :]).reshape(-1, 9)
    X = np.column_stack((u, induced, eddy))
    return X if terms == 18 else X[:, _KEEP_16]


def bandpass(x, rate_hz, band, order=4):
    """Zero-phase Butterworth band-pass of ``x`` along its first axis.

    ``order`` is the design order (scipy's; the band-pass has twice as many poles) and the
    forward-backward pass (``sosfiltfilt``, odd padding) squares the magnitude response and
    cancels the phase.
    """
    x = np.asarray(x, dtype=float)
    lo, hi = _check_band(band, float(rate_hz), "bandpass")
    sos = signal.butter(order, (lo, hi), btype="bandpass", fs=float(rate_hz), output="sos")
    if x.shape[0] < _min_piece(order):
        raise SurveyError(f"bandpass: too few samples ({x.shape[0]}) for an order-{order} "
                          f"filter (at least {_min_piece(order)})")
    return signal.sosfiltfilt(sos, x, axis=0)


def _min_piece(order=4):
    """Least samples of a piece the order-``order`` band-pass can filter (its padding)."""
    return 3 * (2 * order + 1) + 1


def _long_pieces(t, rate_hz, order=4):
    return [sl for sl in _pieces(t, rate_hz) if sl.stop - sl.start >= _min_piece(order)]


def _bandpass_pieces(t, x, rate_hz, band, order=4):
    """:func:`bandpass` applied to each gap-free piece of the record; pieces too short to
    filter are NaN."""
    out = np.full(np.shape(x), np.nan)
    for sl in _long_pieces(t, rate_hz, order):
        out[sl] = bandpass(x[sl], rate_hz, band, order)
    return out


def choose_band(t, cosines, rate_hz=None):
    """The band-pass band ``(low_hz, high_hz)`` from the manoeuvres' frequencies.

    Rule: the power spectrum of the direction cosines' rates ``du/dt`` (the three axes
    summed; each axis linearly detrended, one Hann-windowed periodogram over the box) is
    taken between 0.02 Hz and 0.45 × rate. The rate rather than the cosine itself, because
    the heading changes between the box's legs put most of the cosines' power at the lowest
    frequencies, while the swings are what excites the eddy and induced terms. Frequencies
    whose power reaches 10 % of the maximum are "strong"; the band runs from half the lowest
    strong frequency to twice the highest (an octave of margin each side, so the Butterworth
    skirts do not cut the manoeuvres), clipped to (0.02 Hz, 0.45 × rate).

    For the calibration box of sim/stimulus/flight.py at 10 Hz (rolls and pitches of two
    swings and yaws of one swing, each over 5.3 s, on four headings: 80 s) this gives about
    0.08–0.13 Hz to 1.5 Hz (deinterf's fixed band: 0.1–0.6 Hz).
    """
    t, u, _, _ = _check_inputs(t, cosines, np.ones(np.shape(t)), None, "choose_band")
    if rate_hz is None:
        rate_hz = _rate(t, "choose_band")
    rate_hz = float(rate_hz)
    n = t.size
    if n < 16:
        raise SurveyError(f"choose_band: too few samples ({n}) for a spectrum")
    du = np.gradient(signal.detrend(u, axis=0), t, axis=0)
    f, p = signal.periodogram(du, fs=rate_hz, window="hann", detrend="linear", axis=0)
    p = p.sum(axis=1)
    floor, ceiling = BAND_FLOOR_HZ, BAND_CEILING * rate_hz
    inside = (f >= floor) & (f <= ceiling)
    if not inside.any() or not np.any(p[inside] > 0):
        raise SurveyError(f"choose_band: no manoeuvre between {floor:g} and {ceiling:g} Hz "
                          f"in {t[-1] - t[0]:.1f} s from t={t[0]:.3f} s")
    fi, pi = f[inside], p[inside]
    strong = fi[pi >= STRONG_FRACTION * pi.max()]
    lo = max(floor, strong.min() / BAND_MARGIN)
    hi = min(ceiling, strong.max() * BAND_MARGIN)
    if hi <= lo * 1.5:         # a single line: widen to at least half an octave
        lo, hi = max(floor, lo / 1.2), min(ceiling, hi * 1.2)
    return float(lo), float(hi)


# ---------------------------------------------------------------------------------------
# fit

@dataclass
class TLFit:
    """A Tolles–Lawson fit.

    Attributes: ``coefficients`` (terms,) in physical units (permanent nT, induced
    dimensionless, eddy s) in :data:`TERM_NAMES` order; ``terms`` (16 or 18); ``names``;
    ``band`` (low_hz, high_hz) of the band-pass used; ``ridge_alpha`` (on standardised
    band-passed features); ``ridge_auto`` (whether it was chosen by cross-validation);
    ``cv_alphas`` and ``cv_errors`` (the grid and the held-out RMS in nT, empty when not
    auto); ``rate_hz``; ``offset_nT`` (the box mean of the raw-feature interference,
    subtracted by :meth:`predict`); ``n_samples`` and ``box_s`` (samples and seconds of the
    box used: pieces between gaps too short to filter are left out); ``before_nT`` and
    ``after_nT`` (std of the band-passed scalar in the box before and after compensation);
    ``condition`` (condition number of the standardised band-passed features: large means
    some terms are not determined by the manoeuvres and lean on the ridge; about 25 for 16
    terms on the four-heading box, thousands for 18, which are rank-deficient).
    """
    coefficients: np.ndarray
    terms: int
    band: tuple
    ridge_alpha: float
    ridge_auto: bool
    rate_hz: float
    offset_nT: float
    n_samples: int
    box_s: float
    before_nT: float
    after_nT: float
    condition: float
    cv_alphas: np.ndarray = field(default_factory=lambda: np.empty(0))
    cv_errors: np.ndarray = field(default_factory=lambda: np.empty(0))

    @property
    def names(self):
        return TERM_NAMES[self.terms]

    def predict(self, t, cosines, total):
        """The interference (nT) at ``t``, minus its box mean (``offset_nT``): subtract it
        from the scalar. The constant is not identifiable (the band-pass removed it). NaN
        inputs give NaN outputs (and NaN next to them, through the rates)."""
        X = features(t, cosines, total, self.terms)
        return X @ self.coefficients - self.offset_nT

    def as_dict(self):
        """Plain JSON values (floats, ints, lists, a dict of named coefficients)."""
        return {
            "terms": int(self.terms),
            "coefficients": {name: float(c) for name, c in zip(self.names, self.coefficients)},
            "units": {"permanent": "nT", "induced": "1", "eddy": "s"},
            "band_hz": [float(self.band[0]), float(self.band[1])],
            "ridge_alpha": float(self.ridge_alpha),
            "ridge_auto": bool(self.ridge_auto),
            "cv_alphas": [float(a) for a in self.cv_alphas],
            "cv_rms_nT": [float(e) for e in self.cv_errors],
            "rate_hz": float(self.rate_hz),
            "offset_nT": float(self.offset_nT),
            "n_samples": int(self.n_samples),
            "box_s": float(self.box_s),
            "box_std_before_nT": float(self.before_nT),
            "box_std_after_nT": float(self.after_nT),
            "box_improvement_ratio": float(self.before_nT / self.after_nT)
            if self.after_nT > 0 else None,
            "condition": float(self.condition),
        }


def _ridge_solve(U, s, Vt, y, alphas):
    """Ridge solutions for each alpha from the SVD of X: columns of shape (p, len(alphas))."""
    uty = U.T @ y
    d = s[:, None] / (s[:, None] ** 2 + np.asarray(alphas)[None, :])
    return Vt.T @ (d * uty[:, None])


def _cv_ridge(X, y, alphas, blocks):
    """Held-out RMS per alpha, over ``blocks`` contiguous blocks (each block's training set
    solved through its Gram matrix: the whole record's minus the block's)."""
    n, p = X.shape
    edges = np.linspace(0, n, blocks + 1).astype(int)
    G, b = X.T @ X, X.T @ y
    sse = np.zeros(len(alphas))
    for lo, hi in zip(edges[:-1], edges[1:]):
        Xk, yk = X[lo:hi], y[lo:hi]
        w, V = np.linalg.eigh(G - Xk.T @ Xk)
        w = np.clip(w, 0.0, None)
        vb = V.T @ (b - Xk.T @ yk)
        C = V @ (vb[:, None] / (w[:, None] + np.asarray(alphas)[None, :]))
        sse += ((Xk @ C - yk[:, None]) ** 2).sum(axis=0)
    return np.sqrt(sse / n)


def fit(t, cosines, total, scalar, *, terms=18, band=None, ridge="auto"):
    """Fit the Tolles–Lawson coefficients on the calibration box.

    ``t`` (n,) s, ``cosines`` (n, 3) unit field direction (body frame), ``total`` (n,) nT,
    ``scalar`` (n,) the scalar sensor's reading (nT). ``band``: (low_hz, high_hz) or None for
    :func:`choose_band`. ``ridge``: "auto" (cross-validated on CV_BLOCKS contiguous blocks
    over RIDGE_GRID, the alpha with the least held-out RMS), or a number >= 0 (0 = least
    squares). Both sides are band-passed, each gap-free piece apart (a gap is longer than
    GAP_SAMPLES sample intervals; pieces shorter than the filter's padding, 28 samples, are
    left out), the band-passed
    features standardised by their RMS, the ridge solved by SVD and the coefficients scaled
    back to physical units. Returns a :class:`TLFit`.
    """
    _check_terms(terms)
    t, u, T, y = _check_inputs(t, cosines, total, scalar, "Tolles-Lawson fit")
    n = t.size
    if n < SAMPLES_PER_TERM * terms:
        raise SurveyError(f"Tolles-Lawson fit: too few samples ({n}) for {terms} terms "
                          f"(at least {SAMPLES_PER_TERM * terms})")
    rate_hz = _rate(t, "Tolles-Lawson fit")
    band = choose_band(t, u, rate_hz) if band is None else _check_band(
        band, rate_hz, "Tolles-Lawson fit")
    pieces = _long_pieces(t, rate_hz)
    used = np.zeros(n, dtype=bool)
    for sl in pieces:
        used[sl] = True
    if used.sum() < SAMPLES_PER_TERM * terms:
        raise SurveyError(f"Tolles-Lawson fit: too few samples ({int(used.sum())}) in pieces "
                          f"of at least {_min_piece()} between gaps for {terms} terms (at least "
                          f"{SAMPLES_PER_TERM * terms})")
    box_s = float(sum(t[sl.stop - 1] - t[sl.start] + 1 / rate_hz for sl in pieces))
    if box_s < BOX_PERIODS / band[0]:
        raise SurveyError(f"Tolles-Lawson fit: calibration box too short ({box_s:.1f} s "
                          f"from t={t[0]:.3f} s) for a {band[0]:.3g}-Hz band edge (at least "
                          f"{BOX_PERIODS / band[0]:.1f} s)")
    X = features(t, u, T, terms)
    Xf = _bandpass_pieces(t, X, rate_hz, band)[used]
    yf = _bandpass_pieces(t, y, rate_hz, band)[used]
    scale = np.sqrt(np.mean(Xf ** 2, axis=0))
    if np.any(scale == 0):
        k = int(np.flatnonzero(scale == 0)[0])
        raise SurveyError(f"Tolles-Lawson fit: term {TERM_NAMES[terms][k]} is constant in "
                          f"the box from t={t[0]:.3f} s (no manoeuvre excites it)")
    Xs = Xf / scale
    U, s, Vt = np.linalg.svd(Xs, full_matrices=False)
    condition = float(s[0] / s[-1]) if s[-1] > 0 else float("inf")
    cv_alphas = cv_errors = np.empty(0)
    if isinstance(ridge, str):
        if ridge != "auto":
            raise SurveyError(f"Tolles-Lawson fit: ridge must be 'auto' or a number >= 0, "
                              f"not {ridge!r}")
        cv_alphas = RIDGE_GRID.copy()
        cv_errors = _cv_ridge(Xs, yf, cv_alphas, CV_BLOCKS)
        alpha = float(cv_alphas[int(np.argmin(cv_errors))])
        auto = True
    else:
        try:
            alpha = float(ridge)
        except (TypeError, ValueError):
            raise SurveyError(f"Tolles-Lawson fit: ridge must be 'auto' or a number >= 0, "
                              f"not {ridge!r}") from None
        if not alpha >= 0 or not np.isfinite(alpha):
            raise SurveyError(f"Tolles-Lawson fit: ridge must be 'auto' or a number >= 0, "
                              f"not {ridge!r}")
        auto = False
    if alpha == 0:
        keep = s > s[0] * max(Xs.shape) * np.finfo(float).eps
        c_std = Vt[keep].T @ ((U[:, keep].T @ yf) / s[keep])
    else:
        c_std = _ridge_solve(U, s, Vt, yf, [alpha])[:, 0]
    coefficients = c_std / scale
    offset = float(np.mean(X[used] @ coefficients))
    residual = yf - Xf @ coefficients
    return TLFit(coefficients=coefficients, terms=terms, band=(float(band[0]), float(band[1])),
                 ridge_alpha=alpha, ridge_auto=auto, rate_hz=rate_hz, offset_nT=offset,
                 n_samples=int(used.sum()), box_s=box_s, before_nT=float(np.std(yf)),
                 after_nT=float(np.std(residual)), condition=condition,
                 cv_alphas=cv_alphas, cv_errors=cv_errors)


# ---------------------------------------------------------------------------------------
# quality measures

def _finite_series(t, x, what):
    t = _check_t(t, what)
    x = np.asarray(x, dtype=float)
    if x.shape != t.shape:
        raise SurveyError(f"{what}: signal must have shape {t.shape} like the times, "
                          f"not {x.shape}")
    bad = np.flatnonzero(~np.isfinite(x))
    if bad.size:
        raise SurveyError(f"{what}: signal is NaN or infinite at {_where(t, int(bad[0]))}")
    return t, x


def improvement_ratio(t, uncompensated, compensated, band):
    """Standard deviation of the band-passed scalar before compensation over that after
    (the same band as the fit's, normally ``fit.band``)."""
    t, before = _finite_series(t, uncompensated, "improvement_ratio")
    _, after = _finite_series(t, compensated, "improvement_ratio")
    rate_hz = _rate(t, "improvement_ratio")
    band = _check_band(band, rate_hz, "improvement_ratio")
    sb = np.nanstd(_bandpass_pieces(t, before, rate_hz, band))
    sa = np.nanstd(_bandpass_pieces(t, after, rate_hz, band))
    if not np.isfinite(sa):
        raise SurveyError(f"improvement_ratio: no piece of at least {_min_piece()} samples "
                          "between gaps")
    if sa == 0:
        raise SurveyError("improvement_ratio: the compensated signal is constant in the band")
    return float(sb / sa)


def figure_of_merit(t, compensated, segments, band):
    """The figure of merit: the sum over the manoeuvre segments ``[(start_s, end_s), ...]``
    of the peak-to-peak of the band-passed signal within each (classically the 12
    manoeuvres: 4 headings × roll, pitch, yaw). The whole record is band-passed first (each
    gap-free piece apart), then cut into the segments, so the filter's end transients fall
    outside the segments when the record extends beyond them."""
    t, x = _finite_series(t, compensated, "figure_of_merit")
    rate_hz = _rate(t, "figure_of_merit")
    band = _check_band(band, rate_hz, "figure_of_merit")
    xf = _bandpass_pieces(t, x, rate_hz, band)
    segments = list(segments)
    if not segments:
        raise SurveyError("figure_of_merit: no manoeuvre segments")
    total = 0.0
    for start, end in segments:
        sel = (t >= start) & (t <= end) & np.isfinite(xf)
        if sel.sum() < 2:
            raise SurveyError(f"figure_of_merit: segment {start:.3f}-{end:.3f} s has fewer "
                              f"than 2 filtered samples (data {t[0]:.3f}-{t[-1]:.3f} s)")
        total += float(np.ptp(xf[sel]))
    return total


# ---------------------------------------------------------------------------------------
# comparison through deinterf

def deinterf_compensate(t, cosines_or_vectors, total, scalar, box_mask, terms=16):
    """Compensate ``scalar`` with deinterf's ``TollesLawson`` fitted on ``box_mask``.

    ``cosines_or_vectors`` (n, 3): unit directions (then ``total`` (n,) is the total field,
    given to deinterf as its ``MagIntensity``), or field vectors in nT (told apart by their
    norm; deinterf then takes direction and intensity from the vectors, and ``total`` may be
    None; if given, it overrides the intensity). Fed as ``DataIoC().with_data(
    DirectionalCosine(...), MagIntensity(...))`` or ``with_data(MagVector(...))``, the scalar
    as ``Tmi``. How deinterf 1.2 differs from :func:`fit`:

    - a fixed 0.1–0.6 Hz band (order-4 Butterworth, ``filtfilt`` in b/a form), whatever the
      manoeuvres;
    - u' by ``np.gradient(u)`` per sample, not per second (its eddy features are 1/rate
      times ours; the sampling times are not used at all, so gaps are not seen);
    - features standardised (``StandardScaler`` on the unfiltered features) before the
      band-pass, and ``RidgeCV(alphas=logspace(-6, 6, 13), cv=10, fit_intercept=False)``:
      ten unshuffled (contiguous) folds scored by R², alpha on the standardised unfiltered
      scale (the penalty is stronger relative to the band-passed data than ours);
    - the box is filtered as one record even if ``box_mask`` selects separate pieces;
    - the prediction's mean is removed over the record predicted (here the whole flight),
      not over the box.

    The coefficients therefore differ from :class:`TLFit`'s in scale and, where the
    manoeuvres do not determine a term, in value; the compensated signals agree where the
    fit is well determined.

    Returns a dict: ``"compensated"`` (n,) the scalar minus deinterf's interference (its
    mean over the whole record removed), nT; and plain JSON values: ``"version"``
    ("deinterf 1.2.0"), ``"alpha"`` (RidgeCV's choice), ``"coefficients_standardised"``
    (deinterf's, on its standardised unfiltered features: not comparable with
    :class:`TLFit`'s), ``"settings"`` (a dict: terms, band, filter, rate, derivative,
    estimator, normalisation, input, box samples).
    """
    _check_terms(terms)
    t = _check_t(t, "deinterf_compensate")
    n = t.size
    v = np.asarray(cosines_or_vectors, dtype=float)
    if v.shape != (n, 3):
        raise SurveyError(f"deinterf_compensate: cosines or vectors must have shape ({n}, 3), "
                          f"not {v.shape}")
    y = np.asarray(scalar, dtype=float)
    if y.shape != (n,):
        raise SurveyError(f"deinterf_compensate: scalar must have shape ({n},), not {y.shape}")
    mask = np.asarray(box_mask, dtype=bool)
    if mask.shape != (n,):
        raise SurveyError(f"deinterf_compensate: box_mask must have shape ({n},), "
                          f"not {mask.shape}")
    for name, a in (("cosines or vectors", v), ("scalar", y)):
        bad = np.flatnonzero(~np.isfinite(a.reshape(n, -1)).all(axis=1))
        if bad.size:
            raise SurveyError(f"deinterf_compensate: {name} is NaN or infinite at "
                              f"{_where(t, int(bad[0]))}")
    if mask.sum() < SAMPLES_PER_TERM * terms:
        raise SurveyError(f"deinterf_compensate: too few box samples ({int(mask.sum())}) "
                          f"for {terms} terms (at least {SAMPLES_PER_TERM * terms})")
    rate = _rate(t, "deinterf_compensate")
    rate_int = int(round(rate))
    if rate_int < 2 or abs(rate - rate_int) > 0.01 * rate:
        raise SurveyError(f"deinterf_compensate: deinterf needs a whole sampling rate of at "
                          f"least 2 Hz, not {rate:.4g} Hz")
    norm = np.median(np.linalg.norm(v, axis=1))
    as_vectors = norm > 2.0
    if not as_vectors:
        if total is None:
            raise SurveyError("deinterf_compensate: total is needed with direction cosines")
        _, v, total, _ = _check_inputs(t, v, total, None, "deinterf_compensate")
    elif total is not None:
        total = np.asarray(total, dtype=float)
        if total.ndim == 0:
            total = np.full(n, float(total))
        if total.shape != (n,) or not np.isfinite(total).all():
            raise SurveyError(f"deinterf_compensate: total must be ({n},) and finite")

    from deinterf import __version__ as version
    from deinterf.compensator.tmi.linear import Terms, TollesLawson
    from deinterf.foundation.sensors import (DirectionalCosine, MagIntensity, MagVector,
                                             Tmi)
    from deinterf.utils.data_ioc import DataIoC

    def container(sel):
        data = []
        if as_vectors:
            data.append(MagVector(*v[sel].T))
        else:
            data.append(DirectionalCosine(*v[sel].T))
        if total is not None:
            data.append(MagIntensity(total[sel]))
        return DataIoC().with_data(*data)

    model = TollesLawson(terms=Terms.Terms_16 if terms == 16 else Terms.Terms_18,
                         sampling_rate=rate_int)
    model.fit(container(mask), Tmi(y[mask]))
    interference = np.asarray(model.predict(container(slice(None))), dtype=float)
    settings = {"terms": int(terms),
                "band_hz": [0.1, 0.6], "filter": "butter(4) filtfilt",
                "sampling_rate_hz": rate_int, "derivative": "np.gradient per sample",
                "estimator": "RidgeCV(alphas=logspace(-6, 6, 13), cv=10, "
                             "fit_intercept=False)",
                "norm": "StandardScaler before the band-pass",
                "input": "MagVector" if as_vectors else "DirectionalCosine + MagIntensity",
                "box_samples": int(mask.sum())}
    return {"compensated": y - interference, "version": f"deinterf {version}",
            "alpha": float(model.model_.alpha_),
            "coefficients_standardised": [float(c) for c in
                                          np.asarray(model.model_.coef_, dtype=float).ravel()],
            "settings": settings}
