"""Heading: tilt compensation, IGRF declination, and the 2-D circle fit for hard iron.

Axes: x forward, y right, z down (the sensor in the aircraft's body frame); roll about x,
pitch about y, both in radians; heading clockwise from north, in degrees 0..360.
"""

from dataclasses import dataclass

import numpy as np


__all__ = ["tilt_compensated_heading", "declination", "true_heading", "fit_circle",
           "CircleFit"]


def tilt_compensated_heading(b, roll, pitch):
    """Magnetic heading (degrees) from calibrated body-frame samples ``b`` (N, 3) and the
    attitude: the field is rotated back to the horizontal plane first."""
    b = np.atleast_2d(np.asarray(b, dtype=float))
    if b.shape[-1] != 3:
        raise ValueError(f"Samples must have three components, not shape {b.shape}")
    roll, pitch = np.asarray(roll, float), np.asarray(pitch, float)
    bx, by, bz = b[:, 0], b[:, 1], b[:, 2]
    x_h = (bx * np.cos(pitch) + by * np.sin(roll) * np.sin(pitch)
           + bz * np.cos(roll) * np.sin(pitch))
    y_h = by * np.cos(roll) - bz * np.sin(roll)
    return np.degrees(np.arctan2(-y_h, x_h)) % 360.0


def declination(lat, lon, altitude_m, date):
    """IGRF declination (degrees, east positive) at the position and date (ppigrf)."""
    import ppigrf
    east, north, _ = ppigrf.igrf(lon, lat, altitude_m / 1000.0, date)
    return float(np.degrees(np.arctan2(np.ravel(east)[0], np.ravel(north)[0])))


def true_heading(magnetic_deg, declination_deg):
    """True heading from magnetic heading and declination, degrees 0..360."""
    return (np.asarray(magnetic_deg) + declination_deg) % 360.0


@dataclass
class CircleFit:
    center: np.ndarray      # (x, y): the hard-iron offset in the horizontal plane
    radius: float           # the horizontal field
    rms: float              # RMS distance of the points from the circle


def fit_circle(x, y):
    """Least-squares circle through the points (algebraic fit, Kasa): minimises
    sum (x^2 + y^2 + D x + E y + F)^2; well posed for points on an arc of any length."""
    x, y = np.asarray(x, float), np.asarray(y, float)
    if x.shape != y.shape or x.ndim != 1 or x.size < 3:
        raise ValueError(f"Need matching 1-D x and y with at least 3 points, not shapes "
                         f"{x.shape} and {y.shape}")
    a = np.column_stack([x, y, np.ones_like(x)])
    rhs = -(x * x + y * y)
    (d, e, f), _, rank, _ = np.linalg.lstsq(a, rhs, rcond=None)
    if rank < 3:
        raise ValueError("The points do not lie on a circle (collinear or degenerate)")
    center = np.array([-d / 2, -e / 2])
    radius_sq = center @ center - f
    if not radius_sq > 0:
        raise ValueError("The points do not lie on a circle (collinear or degenerate)")
    radius = float(np.sqrt(radius_sq))
    distance = np.hypot(x - center[0], y - center[1]) - radius
    return CircleFit(center=center, radius=radius, rms=float(np.sqrt(np.mean(distance ** 2))))
