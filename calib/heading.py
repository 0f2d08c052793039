"""Heading: tilt compensation, IGRF declination, the 2-D circle fit for hard iron, and the
alignment of the heading to GPS course over ground on straight, level legs.

Axes: x forward, y right, z down (the sensor in the aircraft's body frame); roll about x,
pitch about y, both in radians; heading clockwise from north, in degrees 0..360.

Why an alignment: a scalar calibration (or an ellipsoid fit) fixes the field's magnitude,
not its direction: any rotation of the calibrated frame fits equally well. The part of that
rotation about the vertical is a constant heading offset. On straight, level legs the
aircraft's heading is its course over ground plus the wind's crab angle; the crab, and a
small tilt of the calibrated frame, both vary with the course as ``a sin(course) + b
cos(course)``, so with legs in two or more directions (reciprocal lines are enough) the
constant offset separates from them::

    heading_from_field + declination - course = offset + a sin(course) + b cos(course)

Only the constant is applied. The sinusoid mixes wind (this flight's) with frame tilt (the
installation's); course over ground alone cannot tell them apart, so it is reported, not
applied.
"""

from dataclasses import dataclass, field

import numpy as np


__all__ = ["tilt_compensated_heading", "declination", "true_heading", "fit_circle",
           "CircleFit", "Leg", "straight_legs", "HeadingAlignment", "align_heading",
           "wrap_degrees"]


def wrap_degrees(angle):
    """Angles folded into [-180, 180)."""
    return (np.asarray(angle, dtype=float) + 180.0) % 360.0 - 180.0


def _circular_mean_deg(angles):
    rad = np.radians(angles)
    return float(np.degrees(np.arctan2(np.mean(np.sin(rad)), np.mean(np.cos(rad)))) % 360.0)


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


@dataclass
class Leg:
    """A straight, level stretch of the flight found in the GPS records."""
    start: float            # s, on the log's time base
    end: float
    course: float           # degrees true, circular mean of the course over ground
    course_spread: float    # degrees, the largest departure from that mean
    speed: float            # m/s, mean ground speed
    climb: float            # m/s, altitude change over the leg / its duration (NaN: no data)
    records: int            # GPS course records in the leg

    @property
    def duration(self):
        return self.end - self.start


def straight_legs(t, course_deg, speed, *, altitude_t=None, altitude=None, min_seconds=20.0,
                  max_course_spread=3.0, min_speed=3.0, max_climb=0.5, max_gap=3.0,
                  trim=2.0):
    """Straight, level legs in the course-over-ground records (VTG): runs of records with
    ground speed of at least ``min_speed`` whose course stays within
    ``max_course_spread`` degrees of the run's mean, no gap over ``max_gap`` seconds, lasting
    ``min_seconds`` after ``trim`` seconds are cut off each end (to drop the roll-out of the
    turns), and (when GGA altitudes are given) climbing or sinking slower than ``max_climb``
    m/s on average."""
    t = np.asarray(t, float)
    course_deg = np.asarray(course_deg, float)
    speed = np.asarray(speed, float)
    if not (t.shape == course_deg.shape == speed.shape) or t.ndim != 1:
        raise ValueError(f"t, course and speed must be matching 1-D arrays, not shapes "
                         f"{t.shape}, {course_deg.shape} and {speed.shape}")
    usable = np.isfinite(t) & np.isfinite(course_deg) & np.isfinite(speed) & (speed >= min_speed)
    legs = []
    run = []

    def close(run):
        if len(run) < 2:
            return
        idx = np.array(run)
        start, end = t[idx[0]] + trim, t[idx[-1]] - trim
        inside = idx[(t[idx] >= start) & (t[idx] <= end)]
        if end - start < min_seconds or inside.size < 2:
            return
        mean = _circular_mean_deg(course_deg[inside])
        climb = np.nan
        if altitude_t is not None and altitude is not None:
            a_t, alt = np.asarray(altitude_t, float), np.asarray(altitude, float)
            sel = (a_t >= start) & (a_t <= end) & np.isfinite(alt)
            if sel.sum() >= 2:
                climb = float(np.polyfit(a_t[sel], alt[sel], 1)[0])
                if abs(climb) > max_climb:
                    return
        legs.append(Leg(start=float(start), end=float(end), course=mean,
                        course_spread=float(np.max(np.abs(wrap_degrees(course_deg[inside]
                                                                       - mean)))),
                        speed=float(np.mean(speed[inside])), climb=climb,
                        records=int(inside.size)))

    rad = np.radians(course_deg)
    sin_sum = cos_sum = 0.0                         # the run's mean course, kept as it grows
    for i in np.argsort(t, kind="stable"):
        if not usable[i]:
            close(run)
            run = []
            continue
        if run:
            mean = np.degrees(np.arctan2(sin_sum, cos_sum))
            if (t[i] - t[run[-1]] > max_gap
                    or abs(wrap_degrees(course_deg[i] - mean)) > max_course_spread):
                close(run)
                run = []
        if not run:
            sin_sum = cos_sum = 0.0
        run.append(i)
        sin_sum += np.sin(rad[i])
        cos_sum += np.cos(rad[i])
    close(run)
    return legs


@dataclass
class HeadingAlignment:
    """The heading offset found on straight, level legs (see the module docstring)."""
    offset: float               # degrees: subtract from headings computed from the field
    offset_std: float           # degrees, 1 sigma (NaN if it cannot be estimated)
    sinusoid: tuple             # (a, b) degrees: crab and frame tilt, not applied
    legs: list                  # per leg: its Leg and the mean heading - course there
    residual_rms: float         # degrees, of the per-leg means about the model
    warnings: list = field(default_factory=list)

    def apply(self, heading_deg):
        """Headings (degrees) with the offset removed, 0..360."""
        return (np.asarray(heading_deg, float) - self.offset) % 360.0

    def as_dict(self):
        return {"offset_deg": self.offset, "offset_std_deg": self.offset_std,
                "sinusoid_deg": list(self.sinusoid), "residual_rms_deg": self.residual_rms,
                "legs": [{"start": leg.start, "end": leg.end, "course_deg": leg.course,
                          "speed_m_s": leg.speed, "climb_m_s": leg.climb,
                          "heading_minus_course_deg": diff} for leg, diff in self.legs],
                "warnings": list(self.warnings)}


def align_heading(t, heading_deg, legs):
    """Fit ``heading - course = offset + a sin(course) + b cos(course)`` over the legs, from
    true headings computed from the calibrated field (``heading_deg`` at times ``t``; on a
    level leg roll and pitch may be taken as zero: their error is part of the sinusoid).
    Returns None when no leg holds two or more samples."""
    t = np.asarray(t, float)
    heading_deg = np.asarray(heading_deg, float)
    if t.shape != heading_deg.shape or t.ndim != 1:
        raise ValueError(f"t and heading must be matching 1-D arrays, not shapes {t.shape} "
                         f"and {heading_deg.shape}")
    used = []
    for leg in legs:
        sel = (t >= leg.start) & (t <= leg.end) & np.isfinite(heading_deg)
        if sel.sum() >= 2:
            diff = wrap_degrees(_circular_mean_deg(heading_deg[sel] - leg.course))
            used.append((leg, float(diff)))
    if not used:
        return None
    courses = np.radians([leg.course for leg, _ in used])
    diffs = np.array([d for _, d in used])
    # Unwrap the per-leg differences around their circular mean before the linear fit.
    centre = wrap_degrees(_circular_mean_deg(diffs))
    y = centre + wrap_degrees(diffs - centre)
    x = np.column_stack([np.ones_like(courses), np.sin(courses), np.cos(courses)])
    warnings = []
    spread = float(np.hypot(np.mean(np.sin(courses)), np.mean(np.cos(courses))))
    # The offset is determined when the constant column is not a combination of the sine
    # and cosine columns over these legs: legs in two or more directions.
    _, singular, vt = np.linalg.svd(x, full_matrices=True)
    rank = int(np.sum(singular > 1e-9 * singular[0]))
    null = vt[rank:]
    determined = null.size == 0 or float(np.max(np.abs(null[:, 0]))) < 1e-6
    if not determined:
        warnings.append("all legs are flown in one direction: the wind's crab angle cannot "
                        "be told from the heading offset, which is their sum here; fly "
                        "reciprocal lines")
        coef = np.array([float(np.mean(y)), 0.0, 0.0])
    else:
        # With two directions only a sin + b cos along them is determined: lstsq gives
        # the minimum-norm pair, and the offset (orthogonal to the null space) is exact.
        coef = np.linalg.lstsq(x, y, rcond=None)[0]
    residual = y - x @ coef
    dof = len(y) - rank
    offset_std = np.nan
    if dof > 0 and determined:
        sigma2 = float(residual @ residual) / dof
        cov = np.linalg.pinv(x.T @ x) * sigma2
        offset_std = float(np.sqrt(max(cov[0, 0], 0.0)))
    else:
        warnings.append(f"{len(y)} legs in {rank} independent directions leave no degree of "
                        "freedom to estimate the offset's uncertainty; fly more lines")
    if spread > 0.9 and determined:
        warnings.append("the legs' directions are unbalanced: the offset leans on the "
                        "crab model")
    return HeadingAlignment(offset=float(wrap_degrees(coef[0])), offset_std=offset_std,
                            sinusoid=(float(coef[1]), float(coef[2])), legs=used,
                            residual_rms=float(np.sqrt(np.mean(residual ** 2))),
                            warnings=warnings)
