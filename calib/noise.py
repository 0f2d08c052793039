"""Noise: a scalar Kalman filter per axis, and overlapping Allan deviation with the fits
of quantisation noise and bias instability.

Ref: IEEE Std 952-1997 Annex C (Allan variance: quantisation noise sigma = sqrt(3) Q / tau,
     angle/velocity random walk sigma = N / sqrt(tau), bias instability: the flat part,
     sigma = sqrt(2 ln 2 / pi) B ~ 0.664 B).
"""

from dataclasses import dataclass

import numpy as np


__all__ = ["kalman_filter", "allan_deviation", "AllanResult"]

BIAS_INSTABILITY_FACTOR = np.sqrt(2 * np.log(2) / np.pi)


def kalman_filter(z, *, q, r, x0=None, p0=None):
    """The scalar Kalman filter of the paper on each column of ``z`` (a random walk state,
    B = H = 1): process noise variance ``q``, measurement noise variance ``r``.

    Returns (filtered states, their variances), both shaped like ``z``."""
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
    for k in range(z.shape[0]):
        p = p + q                           # predict (the state is a random walk)
        gain = p / (p + r)                  # update
        x = x + gain * (z[k] - x)
        p = (1 - gain) * p
        states[k], variances[k] = x, p
    if squeeze:
        return states[:, 0], variances[:, 0]
    return states, variances


@dataclass
class AllanResult:
    taus: np.ndarray            # seconds
    deviation: np.ndarray       # overlapping Allan deviation, in the data's unit
    counts: np.ndarray          # number of terms behind each value
    quantisation: float         # Q from the slope -1 region at short tau
    bias_instability: float     # B from the minimum (flat) part
    tau_min: float              # where the minimum is


def allan_deviation(y, rate, *, taus=None):
    """Overlapping Allan deviation of the rate-like series ``y`` sampled at ``rate`` Hz.

    ``taus``: averaging times (s); default about ten per decade up to a third of the span."""
    y = np.asarray(y, dtype=float)
    if y.ndim != 1 or y.size < 4:
        raise ValueError(f"Series must be 1-D with at least 4 samples, not shape {y.shape}")
    if not np.all(np.isfinite(y)):
        raise ValueError("Series must be finite (found NaN or infinity)")
    if not rate > 0:
        raise ValueError(f"Sample rate must be positive, not {rate!r}")
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
    # Quantisation noise: sigma = sqrt(3) Q / tau at the shortest averaging time.
    quantisation = float(deviation[0] * taus_out[0] / np.sqrt(3)) if deviation.size else np.nan
    best = int(np.argmin(deviation)) if deviation.size else 0
    bias = float(deviation[best] / BIAS_INSTABILITY_FACTOR) if deviation.size else np.nan
    return AllanResult(taus=taus_out, deviation=deviation, counts=np.array(counts),
                       quantisation=quantisation, bias_instability=bias,
                       tau_min=float(taus_out[best]) if deviation.size else np.nan)
