"""Georeferencing of the cesium samples, the IGRF total field along the track, and the survey
lines found in the track.

- :func:`georeference`: the GGA fixes of a parsed log interpolated to the sample times, as
  latitude, longitude, altitude and local metres (:class:`Track`).
- :func:`igrf_total`: IGRF-14 total intensity (ppigrf) at the track's positions, evaluated
  once a second and interpolated (the field changes by a few nT per kilometre: the
  interpolation error is far below a picotesla).
- :func:`find_lines`: the straight, steady-course, steady-speed stretches of the track,
  sorted into survey lines and tie lines (:class:`Line`).

Local metres are flat-earth metres from an origin (``north = (lat - lat0) * 111_320``,
``east = (lon - lon0) * 111_320 * cos(lat0)``), the same as sim/stimulus/flight.py; the
origin is the first fix unless one is given. Times are seconds on the log's time base
(seconds since 00:00 UTC of ``parsed.date``, :mod:`maglog.calib.logparse`).
"""

from __future__ import annotations

import datetime as _dt
from dataclasses import dataclass

import numpy as np

from .survey_errors import SurveyError

__all__ = [
    "METRES_PER_DEGREE",
    "MAX_FIX_GAP_S",
    "IGRF_STEP_S",
    "Track",
    "Line",
    "georeference",
    "local_metres",
    "igrf_total",
    "find_lines",
    "line_of_sample",
]

#: Metres per degree of latitude of the flat-earth projection (as sim/stimulus/flight.py).
METRES_PER_DEGREE = 111_320.0
#: Fixes further apart than this (seconds) leave the samples between them without a position.
MAX_FIX_GAP_S = 5.0
#: Spacing (seconds) of the times at which ppigrf is evaluated before interpolation.
IGRF_STEP_S = 1.0
#: The dates IGRF-14 (ppigrf's coefficients) defines (as calib.pipeline).
IGRF_DATES = (_dt.date(1900, 1, 1), _dt.date(2030, 1, 1))
#: Share (%) of a stretch's samples whose course must lie within the tolerance of its mean
#: course (the rest may be GPS noise: a single noisy fix swings the course at low speed).
STEADY_PERCENTILE = 90.0
#: GPS altitudes (m) at which IGRF is evaluated; outside, the sample's field is NaN.
ALTITUDE_RANGE_M = (-1_000.0, 100_000.0)


@dataclass(frozen=True, eq=False)
class Track:
    """Positions at the sample times ``t`` (NaN where no fix brackets a sample).

    ``lat``, ``lon`` in degrees, ``alt`` in m above mean sea level (the GGA altitude),
    ``north``, ``east`` in local metres from ``origin`` = (lat0, lon0) in degrees.
    """

    t: np.ndarray
    lat: np.ndarray
    lon: np.ndarray
    alt: np.ndarray
    north: np.ndarray
    east: np.ndarray
    origin: tuple

    @property
    def valid(self) -> np.ndarray:
        """Samples with a horizontal position."""
        return np.isfinite(self.north) & np.isfinite(self.east)

    def as_dict(self) -> dict:
        """A summary for the report (plain JSON values)."""
        valid = self.valid
        return {
            "origin": {"lat_deg": float(self.origin[0]), "lon_deg": float(self.origin[1])},
            "samples": int(self.t.size),
            "with_position": int(np.count_nonzero(valid)),
            "north_range_m": _range(self.north[valid]),
            "east_range_m": _range(self.east[valid]),
            "alt_range_m": _range(self.alt[np.isfinite(self.alt)]),
        }


def _range(values):
    if values.size == 0:
        return None
    return [float(np.min(values)), float(np.max(values))]


def local_metres(lat, lon, origin):
    """``(north, east)`` in flat-earth metres of ``lat``, ``lon`` (degrees) from ``origin``
    = (lat0, lon0)."""
    lat0, lon0 = origin
    north = (np.asarray(lat, float) - lat0) * METRES_PER_DEGREE
    east = (np.asarray(lon, float) - lon0) * METRES_PER_DEGREE * np.cos(np.radians(lat0))
    return north, east


def _interp_with_gaps(t, knots_t, values, max_gap):
    """``values`` (at increasing ``knots_t``) interpolated linearly to ``t``; NaN outside
    the knots' span and between knots more than ``max_gap`` apart."""
    out = np.full(t.shape, np.nan)
    if knots_t.size == 0:
        return out
    finite = np.isfinite(t)
    inside = finite & (t >= knots_t[0]) & (t <= knots_t[-1])
    out[inside] = np.interp(t[inside], knots_t, values)
    if knots_t.size > 1:
        right = np.searchsorted(knots_t, t[inside], side="left")
        right = np.clip(right, 1, knots_t.size - 1)
        wide = (knots_t[right] - knots_t[right - 1]) > max_gap
        on_knot = t[inside] == knots_t[right]
        idx = np.flatnonzero(inside)
        out[idx[wide & ~on_knot]] = np.nan
    return out


def georeference(parsed, t, *, origin=None, max_gap_s=MAX_FIX_GAP_S) -> Track:
    """Positions of the samples at times ``t`` (seconds on the log's time base) from the GGA
    fixes of ``parsed`` (a :class:`~maglog.calib.logparse.ParsedLog`).

    Fixes with quality >= 1, a finite position and a time are used, in time order (a fix
    whose time does not increase is left out); each coordinate is interpolated linearly in
    time between the fixes around a sample. Samples before the first or after the last fix,
    or between two fixes more than ``max_gap_s`` apart, get NaN. The altitude is interpolated
    the same way over the fixes that have one. ``origin`` (lat0, lon0) defaults to the first
    fix. Raises :class:`SurveyError` when the log has no usable fix.
    """
    gga = parsed.gga
    t = np.asarray(t, dtype=float)
    good = (gga.quality >= 1) & np.isfinite(gga.lat) & np.isfinite(gga.lon) & np.isfinite(gga.t)
    if not np.any(good):
        raise SurveyError(f"no position fix in {parsed.name}: the samples cannot be placed")
    order = np.argsort(gga.t[good], kind="stable")
    fix_t = gga.t[good][order]
    lat, lon, alt = (a[good][order] for a in (gga.lat, gga.lon, gga.altitude))
    keep = np.concatenate([[True], np.diff(fix_t) > 0])
    fix_t, lat, lon, alt = fix_t[keep], lat[keep], lon[keep], alt[keep]
    if origin is None:
        origin = (float(lat[0]), float(lon[0]))
    origin = (float(origin[0]), float(origin[1]))
    s_lat = _interp_with_gaps(t, fix_t, lat, max_gap_s)
    s_lon = _interp_with_gaps(t, fix_t, lon, max_gap_s)
    has_alt = np.isfinite(alt)
    s_alt = _interp_with_gaps(t, fix_t[has_alt], alt[has_alt], max_gap_s)
    north, east = local_metres(s_lat, s_lon, origin)
    return Track(t=t, lat=s_lat, lon=s_lon, alt=s_alt, north=north, east=east, origin=origin)


# --- IGRF -----------------------------------------------------------------------------------


def _igrf_when(date):
    if date is None:
        raise SurveyError("the log has no date (no ZDA sentence): IGRF needs one")
    if isinstance(date, _dt.datetime):
        day = date.date()
    elif isinstance(date, _dt.date):
        day = date
    else:
        raise SurveyError(f"IGRF date must be a datetime.date, not {date!r}")
    first, last = IGRF_DATES
    if not first <= day < last:
        raise SurveyError(f"the date {day.isoformat()} is outside IGRF-14's "
                          f"{first.year}-{last.year}")
    if isinstance(date, _dt.datetime):
        return date.replace(tzinfo=None) if date.tzinfo is None else \
            date.astimezone(_dt.timezone.utc).replace(tzinfo=None)
    return _dt.datetime(day.year, day.month, day.day)


def _igrf_direct(when, lat, lon, alt_m):
    import ppigrf
    east, north, up = ppigrf.igrf(lon, lat, alt_m / 1000.0, when)
    return np.sqrt(np.ravel(east) ** 2 + np.ravel(north) ** 2 + np.ravel(up) ** 2)


def igrf_total(date, lat, lon, alt_m, *, t=None, step_s=IGRF_STEP_S) -> np.ndarray:
    """IGRF-14 total intensity (nT, ppigrf) at geodetic ``lat``, ``lon`` (degrees) and
    ``alt_m`` (m) on ``date`` (a :class:`datetime.date`, or a datetime taken as UTC).

    Returns an array shaped like ``lat``; NaN where a coordinate is NaN or the altitude lies
    outside :data:`ALTITUDE_RANGE_M`. ppigrf wants the height above the ellipsoid and GGA
    gives it above mean sea level: the geoid's separation (at most about 100 m) changes the
    field by at most a few nT, nearly the same over a survey's area.

    Speed: ppigrf is evaluated at knots and interpolated linearly in between: with ``t``
    (the samples' times) the knots are the first sample in each ``step_s`` (default 1 s) and
    the ends of every run of valid samples, and the interpolation is in time; without ``t``,
    every tenth valid sample (plus the runs' ends), interpolated in sample number. At 10 m/s
    the knots lie 10 m apart, over which the field's curvature is negligible.
    Raises :class:`SurveyError` without a date or outside IGRF-14's dates.
    """
    when = _igrf_when(date)
    lat = np.asarray(lat, float)
    shape = lat.shape
    lat = lat.ravel()
    lon = np.asarray(lon, float).ravel()
    alt = np.asarray(alt_m, float).ravel()
    if not lat.size == lon.size == alt.size:
        raise SurveyError(f"igrf_total: latitude, longitude and altitude differ in length "
                          f"({lat.size}, {lon.size}, {alt.size})")
    low, high = ALTITUDE_RANGE_M
    with np.errstate(invalid="ignore"):
        valid = np.isfinite(lat) & np.isfinite(lon) & (alt >= low) & (alt <= high)
    axis = np.arange(lat.size, dtype=float)
    if t is not None:
        axis = np.asarray(t, float).ravel()
        if axis.size != lat.size:
            raise SurveyError(f"igrf_total: {axis.size} times for {lat.size} positions")
        valid &= np.isfinite(axis)
    out = np.full(lat.size, np.nan)
    idx = np.flatnonzero(valid)
    if idx.size == 0:
        return out.reshape(shape)
    if t is not None:
        step_key = np.floor(axis[idx] / step_s)
    else:
        step_key = np.floor(np.arange(idx.size) / 10.0)
    knot = np.concatenate([[True], step_key[1:] != step_key[:-1]])
    breaks = np.flatnonzero(np.diff(idx) > 1)     # run ends and starts around invalid samples
    knot[breaks] = True
    knot[breaks + 1] = True
    knot[-1] = True
    k = idx[knot]
    total = _igrf_direct(when, lat[k], lon[k], alt[k])
    x = axis[idx]
    if t is not None and np.any(np.diff(x) <= 0):
        raise SurveyError("igrf_total: the times do not increase")
    out[idx] = np.interp(x, axis[k], total)
    return out.reshape(shape)


# --- lines ------------------------------------------------------------------------------------


@dataclass(frozen=True)
class Line:
    """One straight stretch of the track.

    ``kind`` "line" (survey line) or "tie"; ``index`` counts each kind from 0 in flight
    order; ``start``, ``end`` times (s) of the kept straight part; ``course_deg`` the
    direction flown (0-360, clockwise from north); ``length_m`` the distance from start to
    end; ``speed_m_s`` the mean speed on it.
    """

    kind: str
    index: int
    start: float
    end: float
    course_deg: float
    length_m: float = float("nan")
    speed_m_s: float = float("nan")

    @property
    def name(self) -> str:
        """``L3`` (line 3) or ``T1`` (tie 1)."""
        return f"{'L' if self.kind == 'line' else 'T'}{self.index}"

    def as_dict(self) -> dict:
        return {"kind": self.kind, "index": int(self.index), "name": self.name,
                "start_s": float(self.start), "end_s": float(self.end),
                "course_deg": round(float(self.course_deg), 3),
                "length_m": round(float(self.length_m), 3),
                "speed_m_s": round(float(self.speed_m_s), 3)}


def line_of_sample(lines, t) -> np.ndarray:
    """For each time in ``t``, the position in ``lines`` of the line it lies on
    (``start <= t <= end``), or -1."""
    t = np.asarray(t, float)
    out = np.full(t.shape, -1, dtype=np.int64)
    for k, line in enumerate(lines):
        out[(t >= line.start) & (t <= line.end)] = k
    return out


def _velocity(t, north, east, half_window):
    """Central-difference velocity over ±``half_window`` s along the valid track (positions
    interpolated between 1 Hz fixes are piecewise linear; the window smooths the 0.2 m
    quantisation of GGA's 4-decimal minutes)."""
    tv, nv, ev = t, north, east
    lo = np.maximum(tv - half_window, tv[0])
    hi = np.minimum(tv + half_window, tv[-1])
    span = hi - lo
    span[span <= 0] = np.nan
    vn = (np.interp(hi, tv, nv) - np.interp(lo, tv, nv)) / span
    ve = (np.interp(hi, tv, ev) - np.interp(lo, tv, ev)) / span
    return vn, ve


def _runs(mask):
    """(start, stop) index pairs (stop exclusive) of the True runs of ``mask``."""
    edges = np.diff(np.concatenate([[0], mask.astype(np.int8), [0]]))
    return list(zip(np.flatnonzero(edges == 1), np.flatnonzero(edges == -1)))


def _axial_mean_deg(courses_deg, weights=None):
    """Mean of axes (courses modulo 180°) in degrees [0, 180)."""
    doubled = np.radians(2 * np.asarray(courses_deg, float))
    w = np.ones_like(doubled) if weights is None else np.asarray(weights, float)
    return (np.degrees(np.arctan2(np.sum(w * np.sin(doubled)),
                                  np.sum(w * np.cos(doubled)))) / 2) % 180


def _axial_diff_deg(a, b):
    """Smallest angle between axes ``a`` and ``b`` (degrees, 0-90)."""
    d = (np.asarray(a, float) - b) % 180
    return np.minimum(d, 180 - d)


def _segments_cross(p1, p2, q1, q2):
    """Whether segment p1-p2 crosses segment q1-q2 (2-D points)."""
    def cross(a, b):
        return a[0] * b[1] - a[1] * b[0]
    d = cross(p2 - p1, q2 - q1)
    if d == 0:
        return False
    s = cross(q1 - p1, q2 - q1) / d
    u = cross(q1 - p1, p2 - p1) / d
    return 0 <= s <= 1 and 0 <= u <= 1


def find_lines(t, north, east, *, min_length_m=50.0, peak_fraction=0.5, min_speed_m_s=1.0,
               max_turn_rate_deg_s=5.0, course_tolerance_deg=10.0, min_fraction=0.5,
               min_tie_crossings=2, window_s=1.5, max_sample_gap_s=2.0,
               max_merge_gap_s=30.0) -> list:
    """The survey lines and tie lines in a track (times ``t`` in s, local metres).

    The rule, step by step:

    1. **Moving**: velocity by central differences over ±``window_s``; a sample moves when
       its horizontal speed is at least ``min_speed_m_s`` and its course turns by at most
       ``max_turn_rate_deg_s``. Runs of moving samples (broken by NaN positions and by time
       gaps over ``max_sample_gap_s``) are the candidate stretches. Hovering (the
       calibration box, takeoff, landing, the turns between lines) never moves.
    2. **Steady speed**: in each run, the samples at or above ``peak_fraction`` (default
       50 %) of the run's peak speed are kept, the longest contiguous stretch of them. A
       minimum-jerk move is cut where it accelerates: it keeps the middle 54 % of the move's
       time and 83 % of its length.
    3. **Straight**: the kept stretch's course (axial mean) may differ from its samples'
       courses by at most ``course_tolerance_deg`` (90 % of them: :data:`STEADY_PERCENTILE`),
       and the stretch must be at least
       ``min_length_m`` (default 50 m) long (start to end).
    4. **Gaps**: a stretch broken by a gap in the positions (a GPS outage) is one again when
       the next stretch follows within ``max_merge_gap_s``, on the same course (within
       ``course_tolerance_deg``), ahead and on its line (its start at most
       ``course_tolerance_deg`` off the first part's course as seen from its end). Each part
       was cut at half its own peak speed.
    5. **Kinds**: stretches are grouped by axis (course modulo 180°, within
       ``course_tolerance_deg``); in each group a stretch shorter than ``min_fraction`` of
       the group's longest is a sideways step or a transit, not a line, and is dropped. The
       group with the most stretches left holds the survey lines (on a draw, the group
       flown first), the perpendicular one (±``course_tolerance_deg``) the tie lines; other
       stretches are dropped. A tie line must cross at
       least ``min_tie_crossings`` survey lines (the steps between lines cross none); when
       two or more ties are found, a survey line must cross at least one of them (the steps
       between the ties, on the lines' axis, cross none).

    Returns a list of :class:`Line` in flight order, each kind numbered from 0. Raises
    :class:`SurveyError` when fewer than two survey lines are found.
    """
    t = np.asarray(t, float)
    north = np.asarray(north, float)
    east = np.asarray(east, float)
    if not t.size == north.size == east.size:
        raise SurveyError(f"find_lines: {t.size} times for {north.size} north and "
                          f"{east.size} east positions")
    valid = np.isfinite(t) & np.isfinite(north) & np.isfinite(east)
    idx = np.flatnonzero(valid)
    stretches = []
    if idx.size >= 3:
        tv, nv, ev = t[idx], north[idx], east[idx]
        if np.any(np.diff(tv) <= 0):
            raise SurveyError("find_lines: the times do not increase")
        vn, ve = _velocity(tv, nv, ev, window_s)
        speed = np.hypot(vn, ve)
        course = np.degrees(np.arctan2(ve, vn))
        # turn rate: the velocity's direction change over the same window, per second
        hi = np.minimum(tv + window_s, tv[-1])
        lo = np.maximum(tv - window_s, tv[0])
        a_n = (np.interp(hi, tv, vn) - np.interp(lo, tv, vn))
        a_e = (np.interp(hi, tv, ve) - np.interp(lo, tv, ve))
        span = np.where(hi > lo, hi - lo, np.nan)
        with np.errstate(invalid="ignore", divide="ignore"):
            turn = np.degrees(np.abs(vn * a_e - ve * a_n) / np.maximum(speed, 1e-9) ** 2) / span
        moving = (speed >= min_speed_m_s) & (turn <= max_turn_rate_deg_s)
        # gaps in time break a run
        gap = np.concatenate([[False], np.diff(tv) > max_sample_gap_s])
        for a, b in _runs(moving):
            cuts = a + np.flatnonzero(gap[a + 1:b]) + 1
            for lo_i, hi_i in zip(np.concatenate([[a], cuts]), np.concatenate([cuts, [b]])):
                seg = _steady(tv, nv, ev, speed, course, lo_i, hi_i, peak_fraction,
                              course_tolerance_deg, min_length_m)
                if seg is not None:
                    stretches.append(seg)
    stretches = _merge_gaps(stretches, max_merge_gap_s, course_tolerance_deg)
    lines = _classify(stretches, course_tolerance_deg, min_fraction, min_tie_crossings)
    n_lines = sum(1 for line in lines if line.kind == "line")
    if n_lines < 2:
        where = (f"{np.nanmin(t):.1f}-{np.nanmax(t):.1f} s" if np.any(np.isfinite(t))
                 else "no valid times")
        if n_lines == 0:
            raise SurveyError(f"no survey line found in the track ({where}): no straight "
                              f"stretch of at least {min_length_m:g} m at steady speed")
        raise SurveyError(f"one survey line only (track {where}): a map needs at least two")
    return lines


def _steady(tv, nv, ev, speed, course, a, b, peak_fraction, tolerance, min_length):
    """The steady part of the run a:b as a dict, or None."""
    if b - a < 2:
        return None
    fast = speed[a:b] >= peak_fraction * np.max(speed[a:b])
    runs = _runs(fast)
    lo, hi = max(runs, key=lambda r: r[1] - r[0])
    lo, hi = a + lo, a + hi
    if hi - lo < 2:
        return None
    axis = _axial_mean_deg(course[lo:hi], speed[lo:hi])
    if np.percentile(_axial_diff_deg(course[lo:hi], axis), STEADY_PERCENTILE) > tolerance:
        return None
    length = float(np.hypot(nv[hi - 1] - nv[lo], ev[hi - 1] - ev[lo]))
    if length < min_length:
        return None
    heading = float(np.degrees(np.arctan2(ev[hi - 1] - ev[lo], nv[hi - 1] - nv[lo])) % 360)
    return {"start": float(tv[lo]), "end": float(tv[hi - 1]), "course": heading,
            "axis": axis, "length": length,
            "speed": length / max(float(tv[hi - 1] - tv[lo]), 1e-9),
            "p1": np.array([nv[lo], ev[lo]]), "p2": np.array([nv[hi - 1], ev[hi - 1]])}


def _merge_gaps(stretches, max_gap_s, tolerance):
    """Consecutive stretches joined where a position gap broke one line (step 4 of
    :func:`find_lines`)."""
    out = []
    for s in stretches:
        if out:
            prev = out[-1]
            jump = s["p1"] - prev["p2"]
            bearing = np.degrees(np.arctan2(jump[1], jump[0]))
            turn = abs((s["course"] - prev["course"] + 180) % 360 - 180)
            off = abs((bearing - prev["course"] + 180) % 360 - 180)
            if (s["start"] - prev["end"] <= max_gap_s and turn <= tolerance
                    and np.hypot(*jump) > 0 and off <= tolerance):
                p1, p2 = prev["p1"], s["p2"]
                length = float(np.hypot(*(p2 - p1)))
                course = float(np.degrees(np.arctan2(*(p2 - p1)[::-1])) % 360)
                out[-1] = {**prev, "end": s["end"], "p2": p2, "length": length,
                           "course": course, "axis": course % 180,
                           "speed": length / max(s["end"] - prev["start"], 1e-9)}
                continue
        out.append(s)
    return out


def _classify(stretches, tolerance, min_fraction, min_tie_crossings):
    """Survey lines and ties from the steady stretches (step 4 of :func:`find_lines`)."""
    if not stretches:
        return []
    axes = np.array([s["axis"] for s in stretches])
    lengths = np.array([s["length"] for s in stretches])

    def members(axis):
        """The stretches on ``axis`` that are not steps or transits (short for it)."""
        near = _axial_diff_deg(axes, axis) <= tolerance
        if not np.any(near):
            return near
        return near & (lengths >= min_fraction * np.max(lengths[near]))

    # the biggest group of lines (counted without its short stretches: the steps between
    # lines can outnumber the ties across them); on a draw, the group flown first
    counts = [int(np.count_nonzero(members(a))) for a in axes]
    best = int(np.argmax(counts))
    line_axis = _axial_mean_deg(axes[members(axes[best])])
    tie_axis = (line_axis + 90) % 180

    def group(axis):
        return [s for s, keep in zip(stretches, members(axis)) if keep]

    survey = group(line_axis)
    ties = [s for s in group(tie_axis)
            if sum(_segments_cross(s["p1"], s["p2"], L["p1"], L["p2"]) for L in survey)
            >= min_tie_crossings]
    if len(ties) >= 2:
        # With ties flown, every survey line crosses one; the steps between the ties (on
        # the lines' axis, beyond the outermost line) cross none.
        survey = [s for s in survey
                  if any(_segments_cross(s["p1"], s["p2"], T["p1"], T["p2"]) for T in ties)]
    out = []
    for kind, chosen in (("line", survey), ("tie", ties)):
        for k, s in enumerate(sorted(chosen, key=lambda s: s["start"])):
            out.append(Line(kind, k, s["start"], s["end"], s["course"], s["length"],
                            s["speed"]))
    return sorted(out, key=lambda line: line.start)
