"""Crossovers of survey and tie lines, and tie-line levelling.

Where a tie line crosses a survey line both measured the same place at different times; the
difference of their values there is the levelling error (diurnal residue, heading effects,
drift). :func:`crossovers` finds the crossings (segment intersection of the two flown
tracks in the plane, the values and times interpolated along each track at the crossing);
:func:`level` solves per-line corrections from the differences by least squares.

The model (documented choice): a survey line ``L`` gets a correction ``a_L`` (order 0) or
``a_L + b_L (t - t_L)`` (order 1, ``t_L`` the line's middle time); a tie line ``T`` gets a
constant ``c_T`` in both orders. The corrected value is ``value - correction``, so a
crossover's corrected difference is ``d - corr_L(t_L) + c_T``, and the sum of their squares is
minimised. Adding one constant to every correction leaves the differences alone; the tie
lines are the reference: their corrections are fixed to a mean of zero, so levelling does not
move the survey's overall level as the ties measured it. The ties still get constants of their
own, so that a tie flown at a different diurnal level is not taken as the truth for the lines
it crosses: the network is adjusted as a whole. With order 1 one more direction is (nearly)
invisible: tie constants rising along the lines, ``c_T = g x_T``, cancel against line slopes
``b_L = g dx/dt`` (exactly at constant speed); the ties' constants are therefore also held
to no trend along the lines (their least-squares slope against the crossing position is
zero). A survey line without crossovers is left alone (correction 0) and listed in the
result. With order 1, a line whose crossovers span less than ``min_slope_span_s`` (or that
has fewer than two) gets a constant only.

The constraints are exact (the least squares is solved in their null space), not weighted
equations.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import NamedTuple

import numpy as np

from .survey_errors import SurveyError

__all__ = ["Crossover", "Levelling", "crossovers", "level"]


class Crossover(NamedTuple):
    """One crossing. ``line`` and ``tie`` are positions in the ``lines`` list given to
    :func:`crossovers`; ``north``, ``east`` the crossing point (local m); ``t_line``,
    ``t_tie`` the times each passed it; ``value_line``, ``value_tie`` the values there;
    ``difference`` = value on the survey line minus value on the tie line (nT), the last
    field (``c[-1]``)."""

    line: int
    tie: int
    north: float
    east: float
    t_line: float
    t_tie: float
    value_line: float
    value_tie: float
    difference: float

    def as_dict(self, lines=None) -> dict:
        out = {"line": int(self.line), "tie": int(self.tie), "north_m": round(self.north, 3),
               "east_m": round(self.east, 3), "difference_nT": round(self.difference, 4),
               "t_line_s": round(self.t_line, 3), "t_tie_s": round(self.t_tie, 3)}
        if lines is not None:
            out["line_name"] = lines[self.line].name
            out["tie_name"] = lines[self.tie].name
        return out


def _track(line, t, north, east, value):
    """The samples of ``line`` (times within start..end) with finite position."""
    sel = (t >= line.start) & (t <= line.end) & np.isfinite(north) & np.isfinite(east)
    idx = np.flatnonzero(sel)
    return t[idx], north[idx], east[idx], value[idx]


def _intersections(pa, pb, qa, qb):
    """Parameters (s, u) in [0, 1] of the crossings of segments pa[i]-pb[i] with
    qa[j]-qb[j]: arrays i, j, s, u."""
    r = (pb - pa)[:, None, :]
    q = (qb - qa)[None, :, :]
    d = r[..., 0] * q[..., 1] - r[..., 1] * q[..., 0]
    w = qa[None, :, :] - pa[:, None, :]
    with np.errstate(divide="ignore", invalid="ignore"):
        s = (w[..., 0] * q[..., 1] - w[..., 1] * q[..., 0]) / d
        u = (w[..., 0] * r[..., 1] - w[..., 1] * r[..., 0]) / d
    ok = (d != 0) & (s >= 0) & (s <= 1) & (u >= 0) & (u <= 1)
    i, j = np.nonzero(ok)
    return i, j, s[i, j], u[i, j]


def _near(points, centre, radius):
    """Indices of the segments (consecutive point pairs) with an end within ``radius``."""
    close = np.hypot(points[:, 0] - centre[0], points[:, 1] - centre[1]) <= radius
    seg = close[:-1] | close[1:]
    return np.flatnonzero(seg)


def crossovers(lines, t, north, east, value, *, search_m=50.0) -> list:
    """The crossings of every tie line with every survey line in ``lines`` (a list of
    :class:`~maglog.calib.georef.Line`), on the track ``t``, ``north``, ``east`` (local m)
    with ``value`` (nT) at each sample.

    For each pair, the lines' chords (start to end point) are intersected first; the flown
    tracks' segments within ``search_m`` of that point are then intersected exactly, and the
    values and times are interpolated linearly along each segment at the crossing. A pair
    whose chords do not cross, or whose tracks do not cross near there, gives no crossover;
    a crossing where either value is NaN is left out. Returns a list of :class:`Crossover`
    ordered by (line, tie).
    """
    t = np.asarray(t, float)
    north = np.asarray(north, float)
    east = np.asarray(east, float)
    value = np.asarray(value, float)
    if not t.size == north.size == east.size == value.size:
        raise SurveyError(f"crossovers: arrays differ in length ({t.size}, {north.size}, "
                          f"{east.size}, {value.size})")
    tracks = [_track(line, t, north, east, value) for line in lines]
    out = []
    for li, line in enumerate(lines):
        if line.kind != "line" or tracks[li][0].size < 2:
            continue
        lt, ln, le, lv = tracks[li]
        lp = np.column_stack([ln, le])
        for ti, tie in enumerate(lines):
            if tie.kind != "tie" or tracks[ti][0].size < 2:
                continue
            tt, tn, te, tv = tracks[ti]
            tp = np.column_stack([tn, te])
            i, j, s, u = _intersections(lp[:1], lp[-1:], tp[:1], tp[-1:])
            # the chords may miss where a track bends past the end: widen by search_m
            centre = lp[0] + s[0] * (lp[-1] - lp[0]) if i.size else None
            if centre is None:
                continue
            a = _near(lp, centre, search_m)
            b = _near(tp, centre, search_m)
            if a.size == 0 or b.size == 0:
                continue
            i, j, s, u = _intersections(lp[a], lp[a + 1], tp[b], tp[b + 1])
            if i.size == 0:
                continue
            k = int(np.argmin(np.hypot(*(lp[a[i]] + s[:, None] * (lp[a[i] + 1] - lp[a[i]])
                                         - centre).T)))
            ia, ib, sk, uk = a[i[k]], b[j[k]], s[k], u[k]
            point = lp[ia] + sk * (lp[ia + 1] - lp[ia])
            v_line = lv[ia] + sk * (lv[ia + 1] - lv[ia])
            v_tie = tv[ib] + uk * (tv[ib + 1] - tv[ib])
            if not (np.isfinite(v_line) and np.isfinite(v_tie)):
                continue
            out.append(Crossover(
                line=li, tie=ti, north=float(point[0]), east=float(point[1]),
                t_line=float(lt[ia] + sk * (lt[ia + 1] - lt[ia])),
                t_tie=float(tt[ib] + uk * (tt[ib + 1] - tt[ib])),
                value_line=float(v_line), value_tie=float(v_tie),
                difference=float(v_line - v_tie)))
    return out


@dataclass(frozen=True, eq=False)
class Levelling:
    """The result of :func:`level`.

    ``values``: the levelled values (``value - correction`` on the lines' samples, unchanged
    elsewhere); ``correction``: the correction subtracted at each sample (0 off the lines);
    ``offsets``: per position in ``lines``, the constant (nT); ``slopes``: per position, the
    slope (nT/s, 0 for ties, order 0 and constant-only lines); ``rms_before``, ``rms_after``:
    RMS of the crossover differences before and after (nT); ``residuals``: the differences
    after; ``unlevelled``: positions of survey lines without a crossover;
    ``crossovers_before``, ``crossovers_after``: the crossovers with their differences before
    and after levelling (:class:`Crossover`, difference last).
    """

    values: np.ndarray
    correction: np.ndarray
    offsets: np.ndarray
    slopes: np.ndarray
    order: int
    rms_before: float
    rms_after: float
    residuals: np.ndarray
    n_crossovers: int
    unlevelled: list = field(default_factory=list)
    lines: list = field(default_factory=list)
    crossovers_before: list = field(default_factory=list)
    crossovers_after: list = field(default_factory=list)

    def as_dict(self) -> dict:
        per_line = [{"name": line.name, "kind": line.kind, "offset_nT": round(float(o), 4),
                     "slope_nT_per_s": float(s)}
                    for line, o, s in zip(self.lines, self.offsets, self.slopes)]
        return {"order": self.order, "crossovers": self.n_crossovers,
                "rms_before_nT": round(self.rms_before, 4),
                "rms_after_nT": round(self.rms_after, 4),
                "corrections": per_line,
                "unlevelled": [self.lines[k].name for k in self.unlevelled]}


def _rms(x):
    return float(np.sqrt(np.mean(np.square(x)))) if len(x) else float("nan")


def _gauge(lines, crossovers, unknowns, sloped):
    """Constraint rows C (C x = 0) fixing the directions the crossovers cannot see: the
    crossed ties' corrections have mean zero, and with slopes also no trend along the survey
    lines (a tilt of the ties along the lines and matching line slopes cancel in every
    crossover)."""
    ties = sorted({c.tie for c in crossovers})
    rows = [np.zeros(unknowns)]
    rows[0][ties] = 1.0 / len(ties)
    if sloped and len(ties) >= 2:
        survey = [line for line in lines if line.kind == "line"]
        doubled = np.radians(2 * np.array([line.course_deg for line in survey]))
        axis = np.arctan2(np.sin(doubled).sum(), np.cos(doubled).sum()) / 2
        along = np.array([np.cos(axis), np.sin(axis)])
        where = {k: np.mean([[c.north, c.east] for c in crossovers if c.tie == k], axis=0)
                 @ along for k in ties}
        mean = np.mean(list(where.values()))
        trend = np.zeros(unknowns)
        for k in ties:
            trend[k] = where[k] - mean
        if np.any(np.abs(trend) > 1e-9):
            rows.append(trend / np.linalg.norm(trend))
    return np.array(rows)


def _solve(rows, d, constraints):
    """Least squares ``rows @ x ≈ d`` subject to ``constraints @ x = 0`` (through the
    constraints' null space), minimum norm where still undetermined (unknowns no crossover
    touches stay 0)."""
    from scipy.linalg import null_space
    basis = null_space(constraints)
    x = basis @ np.linalg.lstsq(rows @ basis, d, rcond=None)[0]
    x[~np.any(rows != 0, axis=0)] = 0.0
    return x


def level(lines, t, value, crossovers, *, order=0, min_slope_span_s=1.0) -> Levelling:
    """Levelled values from the crossover differences (see the module doc for the model).

    ``lines`` and ``crossovers`` as from :func:`crossovers` (positions into ``lines``);
    ``t``, ``value`` the samples. ``order`` 0 (a constant per line) or 1 (a constant and a
    slope in time per survey line). Raises :class:`SurveyError` without crossovers.
    """
    if order not in (0, 1):
        raise SurveyError(f"levelling order must be 0 or 1, not {order!r}")
    t = np.asarray(t, float)
    value = np.asarray(value, float)
    if t.size != value.size:
        raise SurveyError(f"level: {t.size} times for {value.size} values")
    if not crossovers:
        raise SurveyError("no crossover of a tie line with a survey line: nothing to level "
                          "with (fly tie lines across the survey lines)")
    n = len(lines)
    middle = np.array([(line.start + line.end) / 2 for line in lines])
    by_line = {}
    for c in crossovers:
        by_line.setdefault(c.line, []).append(c.t_line)
    sloped = set()
    if order == 1:
        sloped = {k for k, ts in by_line.items()
                  if len(ts) >= 2 and max(ts) - min(ts) >= min_slope_span_s}
    # unknowns: a constant per line (all n positions), then one slope per sloped line
    slope_col = {k: n + m for m, k in enumerate(sorted(sloped))}
    rows = np.zeros((len(crossovers), n + len(slope_col)))
    d = np.array([c.difference for c in crossovers])
    for r, c in enumerate(crossovers):
        # corrected difference = d - a_L - b_L (t - t_L) + c_T  ->  rows @ x ≈ d
        rows[r, c.line] = 1.0
        if c.line in slope_col:
            rows[r, slope_col[c.line]] = c.t_line - middle[c.line]
        rows[r, c.tie] = -1.0
    x = _solve(rows, d, _gauge(lines, crossovers, rows.shape[1], bool(slope_col)))
    residuals = d - rows @ x
    offsets = x[:n].copy()
    slopes = np.zeros(n)
    for k, col in slope_col.items():
        slopes[k] = x[col]
    correction = np.zeros(t.shape)
    for k, line in enumerate(lines):
        sel = (t >= line.start) & (t <= line.end)
        correction[sel] = offsets[k] + slopes[k] * (t[sel] - middle[k])
    unlevelled = [k for k, line in enumerate(lines) if line.kind == "line" and k not in by_line]
    after = [c._replace(value_line=c.value_line - offsets[c.line]
                        - slopes[c.line] * (c.t_line - middle[c.line]),
                        value_tie=c.value_tie - offsets[c.tie], difference=float(r))
             for c, r in zip(crossovers, residuals)]
    return Levelling(values=value - correction, correction=correction, offsets=offsets,
                     slopes=slopes, order=order, rms_before=_rms(d),
                     rms_after=_rms(residuals), residuals=residuals,
                     n_crossovers=len(crossovers), unlevelled=unlevelled, lines=list(lines),
                     crossovers_before=list(crossovers), crossovers_after=after)
