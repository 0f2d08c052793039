"""Checks that magnetometer samples can determine a calibration at all, shared by the
fitting methods (scalar, ellipsoid). Each raises ``ValueError`` saying what is wrong."""

import numpy as np


__all__ = ["MAX_FIELD_NT", "STUCK_AXIS_NT", "check_samples"]

#: Largest magnitude accepted for a sample or a reference, nT (0.1 T: far beyond any
#: magnetometer flown for a survey; above it the sums of squares lose their precision).
MAX_FIELD_NT = 1e8
#: An axis whose peak-to-peak is below this (nT) is stuck: a working sensor's noise alone
#: moves it more.
STUCK_AXIS_NT = 1.0


def check_samples(b, distinct, purpose=""):
    """``b`` as a float (N, 3) array, or ValueError: the shape, at least ``distinct``
    distinct vectors, finite values below :data:`MAX_FIELD_NT`, every axis varying.
    ``purpose`` ends the count messages ("for nine parameters")."""
    purpose = f" {purpose}" if purpose else ""
    b = np.asarray(b, dtype=float)
    if b.ndim != 2 or b.shape[1] != 3:
        raise ValueError(f"Samples must be an (N, 3) array, not shape {b.shape}")
    if b.shape[0] < distinct:
        raise ValueError(f"At least {distinct} samples are needed{purpose}, not "
                         f"{b.shape[0]}")
    if not np.all(np.isfinite(b)):
        raise ValueError("Samples must be finite (found NaN or infinity)")
    largest = float(np.max(np.abs(b)))
    if largest > MAX_FIELD_NT:
        raise ValueError(f"Samples must be below {MAX_FIELD_NT:.0e} nT in magnitude, not "
                         f"{largest:.3g} nT: not a magnetometer reading in nT")
    span = np.ptp(b, axis=0)
    for axis, s, value in zip("xyz", span, b[0]):
        if s < STUCK_AXIS_NT:
            raise ValueError(f"Axis {axis} does not change (peak-to-peak {s:.3g} nT, "
                             f"about {value:.6g} nT): a stuck or disconnected axis, or a "
                             "sensor that was not turned, cannot be calibrated")
    count = _distinct(b, distinct)
    if count < distinct:
        raise ValueError(f"Only {count} distinct vectors among {len(b)} samples; at least "
                         f"{distinct} are needed{purpose}")
    return b


def _distinct(b, wanted):
    """The number of distinct rows of ``b``, counted on a growing prefix until ``wanted``
    are found (sorting a day's samples to learn that the first hundred differ took 0.2 s
    of a one-hour flight's 0.5 s); exact whenever it is below ``wanted``."""
    size = max(16 * wanted, 256)
    while True:
        count = len(np.unique(b[:size], axis=0))
        if count >= wanted or size >= len(b):
            return count
        size *= 16
