"""Screening before a calibration: reject, count and explain the readings and samples that no
aircraft over the Earth could have measured.

Two screens, each returning a :class:`ScreenResult` (a ``keep`` mask, counts per reason and
a few examples of each):

- :func:`screen_reference`: the reference's total-field readings (a cesium magnetometer's
  time series). A reading is rejected when it is not a number (``"nonfinite"``), outside the
  Earth's range (``"earth_range"``), or an isolated spike (``"spike"``).
- :func:`screen_samples`: the vector magnetometer's samples, optionally with the reference
  at each sample. A sample is rejected when a component is not a number (``"nonfinite"``),
  when its magnitude is beyond what any calibration can map onto the reference
  (``"scale"``), or when its magnitude jumps from its neighbours' (``"jump"``).

Each rejected reading gets the first reason that applies, in the order above, so the counts
add up to the number rejected; the spike and jump tests compare a reading only with
neighbours that passed the earlier tests.

**The Earth's range.** The main field at the Earth's surface runs from about 22,000 nT (the
South Atlantic Anomaly) to about 67,000 nT (near the south magnetic pole): IGRF (ppigrf) on
a 1° grid gives 22,229..66,987 nT in 2020 and 22,039..66,937 nT in 2026.
:data:`EARTH_RANGE_NT` is 20,000..75,000 nT: 2,000 nT below the minimum covers decades of
the Anomaly's deepening (about 30 nT a year) and the decrease with height (the dipole falls
as ``(R / (R + h))^3``: 0.5 % at 10 km); 8,000 nT above the maximum covers the strong
crustal anomalies seen at survey height (iron formations give a few thousand nT). A bit
flip in the leading digit of a cesium reading (``$ 48395.014`` read as ``$ 08395.014``)
lands far outside. The extreme surface anomalies over iron ore (Kursk) exceed the range:
pass ``earth_range`` for a survey there.

**Spikes (Hampel's test).** A reading is compared with the median of its neighbours: the
valid readings within ``half_window`` readings on each side (itself left out; fewer at the
ends of a segment). It is a spike when it deviates from that median by more than both

- ``k`` robust standard deviations (1.4826 × the median absolute deviation): of the
  neighbours about their median, or of every reading's deviation over the whole series,
  whichever is larger, and
- a physical floor, ``floor_nt`` (:data:`SPIKE_FLOOR_NT`, 50 nT).

The statistical part passes every real anomaly, whatever its amplitude, as long as it spans
a few readings: with the defaults (3 readings each side, k = 5) a peak whose width at half
height is 3 readings or more stays below half the limit, because the neighbours' spread
grows with it; one 2 readings wide or less is flagged. The total-field anomaly of a source
at distance z is about z wide at half height, so a real one spans ``z f / v`` readings at
speed v and reading rate f: a fixed wing at 70 m/s with a 10-Hz cesium would have to pass
within 21 m of the source to make one narrower than 3 readings, below any survey clearance
(60-120 m for fixed wings; helicopters and drones fly lower but slower, and span more
readings). A calibration flown at altitude sees no anomaly at all.

The floor keeps noise and small sharp effects (the cesium's heading error and the
aircraft's manoeuvre noise, a few nT) from being called spikes: it is five times the noise
of the noisiest reference considered (10 nT; a cesium magnetometer's is 0.01-0.05 nT), and
the series-wide term raises the limit with noisier references (at 10 nT of noise, about
5 × 11 nT: one false alarm in 8 million readings measured). A bit flip in the tens digit
(``48395`` read as ``48315``, an 80-nT spike) is caught (at 10 nT of noise, 9 times in 10).
One in the units digit (``48391``, 4 nT) is not: it is no larger than what manoeuvres and
heading error make, and hidden in 10 nT of noise; the calibration's robust loss takes care
of it. A spike smaller than the field's local variation (on the steep flank of a survey
anomaly) also passes, for the same reason.

**Magnetometer samples.** A rotation leaves the field's magnitude unchanged, so tests on
``|b|`` hold for any attitude, a tumbling calibration included (whose attitude may change
completely between samples); the sensor's errors make ``|b|`` vary with attitude by a few
percent only (scale factors and soft iron: the error ellipsoid's radii differ by a few %;
hard iron: its offset, 3.5 % of the field in paper A's Table 1).

- Scale: the calibration searches K's diagonal within :data:`SCALE_RANGE` (0.5..2) of the
  data's scale (``median(r) / median(|b|)``, as ``calib.scalar.DIAGONAL_RANGE``), so a
  sample whose ``|b| / r``, relative to the median of that ratio, is outside 0.5..2 cannot
  be mapped onto its reference by any calibration the fit considers: a sensor reading zero,
  a saturated or bit-flipped leading digit. Without ``r``, ``|b|`` is compared with the
  median ``|b|``.
- Jump: Hampel's test on ``|b|`` (as for spikes above) with a floor relative to the
  neighbours' median, :data:`JUMP_FRACTION` (20 %): four times the few % a rotation can
  change ``|b|`` by through the error ellipsoid, so that an installation with ten times the
  hard iron of paper A's passes too. An axis read as zero with a valid checksum is caught
  when that axis held more than about 60 % of the field (``|b|`` then drops by more than
  20 %); ``b_z = 0`` where the vertical field reads 40,000 nT of 48,000 drops ``|b|`` by
  45 %. Smaller faults are left to the fit's robust loss.

Readings more than ``max_gap`` seconds apart (by default 5 × the median interval) are not
neighbours: the test restarts after a dropout, where the aircraft may have moved on, and
after a step back in time (a sensor restart in the log). Times must be finite; a log
without times can pass its line numbers. A
reading with fewer than 3 valid neighbours cannot be judged and is kept (counted in
``untested``).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import NamedTuple

import numpy as np
from numpy.lib.stride_tricks import sliding_window_view


__all__ = ["EARTH_RANGE_NT", "SPIKE_FLOOR_NT", "JUMP_FRACTION", "SCALE_RANGE", "HALF_WINDOW",
           "SIGMAS", "GAP_INTERVALS", "REFERENCE_REASONS", "SAMPLE_REASONS", "Example",
           "ScreenResult", "screen_reference", "screen_samples"]

#: The Earth's total field anywhere a survey flies, with margins (see the module's doc), nT.
EARTH_RANGE_NT = (20_000.0, 75_000.0)
#: Smallest deviation from the neighbours' median called a spike, nT.
SPIKE_FLOOR_NT = 50.0
#: Smallest jump of |b| from the neighbours' median, as a fraction of that median.
JUMP_FRACTION = 0.20
#: |b| / r relative to its median: the range a calibration can map (calib.scalar's
#: DIAGONAL_RANGE).
SCALE_RANGE = (0.5, 2.0)
#: Readings on each side of the one tested.
HALF_WINDOW = 3
#: Robust standard deviations a spike or jump must exceed.
SIGMAS = 5.0
#: An interval longer than this many median intervals ends a segment.
GAP_INTERVALS = 5.0
#: Fewest valid neighbours for a test (their median stays good with one of them bad).
MIN_NEIGHBOURS = 3
#: Examples kept per reason.
EXAMPLES = 3
#: Median absolute deviation to standard deviation, for normal noise.
_MAD_TO_SIGMA = 1.4826

REFERENCE_REASONS = ("nonfinite", "earth_range", "spike")
SAMPLE_REASONS = ("nonfinite", "scale", "jump")


class Example(NamedTuple):
    """One rejected reading: its index in the input, the value tested (nT) and why."""
    index: int
    value: float
    why: str


@dataclass
class ScreenResult:
    """What a screen kept and rejected, like ``scipy.optimize.OptimizeResult``.

    ``keep`` is True for each reading kept; ``counts`` maps every reason of the screen to
    the readings it rejected (zero included); ``examples`` maps each reason to at most
    :data:`EXAMPLES` :class:`Example` s (the first in the input); ``untested`` counts the
    readings kept without a spike or jump test (too few neighbours); ``limits`` holds the
    settings used."""
    what: str
    keep: np.ndarray
    counts: dict
    examples: dict
    untested: int = 0
    limits: dict = field(default_factory=dict)

    @property
    def n(self):
        return int(self.keep.size)

    @property
    def n_kept(self):
        return int(np.count_nonzero(self.keep))

    @property
    def n_rejected(self):
        return self.n - self.n_kept

    @property
    def rejected_indices(self):
        """Indices of the rejected readings."""
        return np.flatnonzero(~self.keep)

    def summary(self):
        """One line: how many were rejected, per reason, and the first example."""
        line = f"{self.what}: {self.n_rejected} of {self.n} rejected"
        reasons = [f"{reason} {count}" for reason, count in self.counts.items() if count]
        if reasons:
            line += f" ({', '.join(reasons)})"
            first = min((ex for exs in self.examples.values() for ex in exs),
                        key=lambda ex: ex.index)
            line += f"; e.g. #{first.index}: {first.why}"
        if self.untested:
            line += f"; {self.untested} too isolated to test"
        return line

    def as_dict(self):
        """For JSON: the counts, examples (a value that is not a number as None) and settings;
        not the mask, which is as long as the log."""
        return {"what": self.what, "n": self.n, "kept": self.n_kept,
                "rejected": self.n_rejected, "counts": dict(self.counts),
                "examples": {reason: [{"index": ex.index,
                                       "value": ex.value if math.isfinite(ex.value) else None,
                                       "why": ex.why} for ex in exs]
                             for reason, exs in self.examples.items()},
                "untested": self.untested, "limits": dict(self.limits),
                "summary": self.summary()}


def screen_reference(t, field_nt, *, earth_range=EARTH_RANGE_NT, floor_nt=SPIKE_FLOOR_NT,
                     k=SIGMAS, half_window=HALF_WINDOW, max_gap=None):
    """Screen a reference's total-field readings ``field_nt`` (nT) at times ``t`` (s,
    finite): reject those not finite, outside ``earth_range`` (nT) or spiking from their
    neighbours (see the module's doc). Returns a :class:`ScreenResult`."""
    t = _check_times(t)
    values = _check_series(field_nt, t.size, "Reference field")
    low, high = _check_range(earth_range, "Earth range", positive=True)
    floor_nt = _check_nonnegative(floor_nt, "Spike floor")
    k = _check_positive(k, "Number of robust standard deviations k")
    half_window = _check_half_window(half_window)
    gap = _gap_seconds(t, max_gap)
    segment = _segments(t, gap)

    reason = np.full(t.size, -1)
    finite = np.isfinite(values)
    reason[~finite] = 0
    with np.errstate(invalid="ignore"):
        outside = finite & ((values < low) | (values > high))
    reason[outside] = 1
    hampel = _hampel(values, reason < 0, segment, half_window, k,
                     lambda median: np.full(median.shape, floor_nt))
    reason[hampel.flagged] = 2

    def why(code, i):
        v = values[i]
        if code == 0:
            return f"{v} is not a number"
        if code == 1:
            return f"{v:,.3f} nT is outside the Earth's {low:,.0f}..{high:,.0f} nT"
        return (f"{v:,.3f} nT is {v - hampel.median[i]:+,.1f} nT off the median of its "
                f"neighbours ({hampel.median[i]:,.3f} nT); limit {hampel.limit[i]:,.1f} nT")

    limits = {"earth_range_nT": [low, high], "spike_floor_nT": floor_nt, "k": k,
              "half_window": half_window, "max_gap_s": gap if math.isfinite(gap) else None}
    return _result("reference readings", reason, REFERENCE_REASONS, values, why,
                   hampel.untested, limits)


def screen_samples(t, b, r=None, *, scale_range=SCALE_RANGE, jump_fraction=JUMP_FRACTION,
                   k=SIGMAS, half_window=HALF_WINDOW, max_gap=None):
    """Screen magnetometer samples ``b`` ((N, 3), nT) at times ``t`` (s, finite), with the
    reference total field ``r`` at each sample if known (nT; NaN where there is none):
    reject those with a component not finite, a magnitude outside ``scale_range`` of the
    data's scale, or a magnitude jumping from its neighbours' (see the module's doc).
    Returns a :class:`ScreenResult` whose examples' values are ``|b|``."""
    t = _check_times(t)
    b = np.asarray(b, dtype=float)
    if b.shape != (t.size, 3):
        raise ValueError(f"Samples must be an (N, 3) array with N = {t.size} (the times), "
                         f"not shape {b.shape}")
    low, high = _check_range(scale_range, "Scale range", positive=True)
    if not low < 1 < high:
        raise ValueError(f"Scale range must contain 1, not {scale_range!r}")
    jump_fraction = _check_positive(jump_fraction, "Jump fraction")
    k = _check_positive(k, "Number of robust standard deviations k")
    half_window = _check_half_window(half_window)
    gap = _gap_seconds(t, max_gap)
    segment = _segments(t, gap)
    if r is not None:
        r = _check_series(r, t.size, "Reference")

    magnitude = np.linalg.norm(b, axis=1)
    reason = np.full(t.size, -1)
    finite = np.all(np.isfinite(b), axis=1)
    reason[~finite] = 0
    ratio, expected = _scale_ratio(magnitude, finite, r)
    with np.errstate(invalid="ignore"):
        off_scale = finite & ~((ratio >= low) & (ratio <= high))
    reason[off_scale] = 1
    hampel = _hampel(magnitude, reason < 0, segment, half_window, k,
                     lambda median: jump_fraction * median)
    reason[hampel.flagged] = 2

    def why(code, i):
        v = magnitude[i]
        if code == 0:
            return f"b = {b[i].tolist()} is not a number"
        if code == 1:
            return (f"|b| {v:,.1f} nT is {ratio[i]:.3g} times the expected {expected[i]:,.1f} nT "
                    f"(a calibration maps {low:g}..{high:g})")
        deviation = v - hampel.median[i]
        return (f"|b| {v:,.1f} nT is {deviation:+,.1f} nT ({deviation / hampel.median[i]:+.0%}) "
                f"off the median of its neighbours ({hampel.median[i]:,.1f} nT); limit "
                f"{hampel.limit[i]:,.1f} nT")

    limits = {"scale_range": [low, high], "jump_fraction": jump_fraction, "k": k,
              "half_window": half_window, "max_gap_s": gap if math.isfinite(gap) else None,
              "with_reference": r is not None}
    return _result("magnetometer samples", reason, SAMPLE_REASONS, magnitude, why,
                   hampel.untested, limits)


# --- the tests -------------------------------------------------------------------------

class _Hampel(NamedTuple):
    flagged: np.ndarray     # bool: tested and beyond the limit
    median: np.ndarray      # the window's median (NaN where untested)
    limit: np.ndarray       # the limit on |value - median| (NaN where untested)
    untested: int           # valid readings with too few valid neighbours


def _hampel(x, valid, segment, half, k, floor):
    """Hampel's test on the ``valid`` readings of ``x``: the window is the valid readings
    of the same segment within ``half`` on each side; ``floor(median)`` is the physical
    floor of the limit (see the module's doc)."""
    n = x.size
    if n == 0:
        empty = np.zeros(0)
        return _Hampel(np.zeros(0, bool), empty, empty, 0)
    # Each row: the readings half before and half after (padded past the ends), a
    # neighbour only if valid and in the same segment.
    sides = np.r_[0:half, half + 1:2 * half + 1]
    around = sliding_window_view(np.pad(np.where(valid, x, np.nan), half,
                                        constant_values=np.nan), 2 * half + 1)[:, sides]
    same = sliding_window_view(np.pad(segment, half, constant_values=-1),
                               2 * half + 1)[:, sides] == segment[:, None]
    member = same & ~np.isnan(around) & valid[:, None]
    window = np.where(member, around, np.nan)
    count = member.sum(axis=1)
    tested = valid & (count >= MIN_NEIGHBOURS)
    median = _row_median(window, count)
    deviation = x - median
    spread = _MAD_TO_SIGMA * _row_median(np.abs(window - median[:, None]), count)
    overall = (_MAD_TO_SIGMA * float(np.median(np.abs(deviation[tested])))
               if np.any(tested) else 0.0)
    limit = np.maximum(floor(median), k * np.maximum(spread, overall))
    with np.errstate(invalid="ignore"):
        flagged = tested & (np.abs(deviation) > limit)
    median = np.where(tested, median, np.nan)
    limit = np.where(tested, limit, np.nan)
    return _Hampel(flagged, median, limit, int(np.count_nonzero(valid & ~tested)))


def _row_median(rows, count):
    """The median of each row's first ``count`` values once sorted (NaN sorts last); NaN
    for an empty row."""
    ordered = np.sort(rows, axis=1)
    at = np.arange(rows.shape[0])
    low = ordered[at, np.maximum(count - 1, 0) // 2]
    high = ordered[at, np.minimum(count // 2, rows.shape[1] - 1)]
    return np.where(count > 0, 0.5 * (low + high), np.nan)


def _scale_ratio(magnitude, finite, r):
    """``|b|`` over what it should be (the data's scale times the reference, or the median
    ``|b|`` without one), and that expected ``|b|``."""
    reference = np.ones(magnitude.size)
    if r is not None:
        known = np.isfinite(r) & (r > 0)
        if np.any(known):
            reference = np.where(known, r, np.median(r[known]))
    usable = finite & np.isfinite(magnitude)
    scale = float(np.median(magnitude[usable] / reference[usable])) if np.any(usable) else 0.0
    expected = scale * reference
    with np.errstate(invalid="ignore", divide="ignore"):
        ratio = magnitude / expected if scale > 0 else np.full(magnitude.size, np.nan)
    return ratio, expected


def _result(what, reason, names, values, why, untested, limits):
    counts = {name: int(np.count_nonzero(reason == code)) for code, name in enumerate(names)}
    examples = {name: [Example(int(i), float(values[i]), why(code, int(i)))
                       for i in np.flatnonzero(reason == code)[:EXAMPLES]]
                for code, name in enumerate(names)}
    return ScreenResult(what=what, keep=reason < 0, counts=counts, examples=examples,
                        untested=untested, limits=limits)


# --- segments and input checks ---------------------------------------------------------

def _gap_seconds(t, max_gap):
    """The largest interval between neighbours: ``max_gap``, or :data:`GAP_INTERVALS` times
    the median forward interval (infinite when no time moves forward)."""
    if max_gap is not None:
        return _check_positive(max_gap, "Largest gap max_gap")
    steps = np.diff(t)
    steps = steps[steps > 0]
    return GAP_INTERVALS * float(np.median(steps)) if steps.size else math.inf


def _segments(t, gap):
    """Segment number of each reading: a new one after each interval over ``gap`` and at
    each step back in time."""
    steps = np.diff(t)
    return np.concatenate([[0], np.cumsum((steps > gap) | (steps < 0))]).astype(int)


def _check_times(t):
    t = np.asarray(t, dtype=float)
    if t.ndim != 1:
        raise ValueError(f"Times must be a 1-D array, not shape {t.shape}")
    if not np.all(np.isfinite(t)):
        raise ValueError(f"Times must be finite, not NaN or infinite "
                         f"({int(np.count_nonzero(~np.isfinite(t)))} of {t.size}); without "
                         "times, pass the readings' line numbers")
    return t


def _check_series(values, n, name):
    values = np.asarray(values, dtype=float)
    if values.shape != (n,):
        raise ValueError(f"{name} must be a 1-D array of {n} values (one per time), not "
                         f"shape {values.shape}")
    return values


def _check_range(pair, name, *, positive):
    try:
        low, high = (float(v) for v in pair)
    except (TypeError, ValueError):
        raise ValueError(f"{name} must be a pair (low, high), not {pair!r}") from None
    if not (math.isfinite(low) and math.isfinite(high) and low < high
            and (low > 0 or not positive)):
        raise ValueError(f"{name} must be a pair 0 < low < high, not {pair!r}")
    return low, high


def _check_positive(value, name):
    if isinstance(value, bool) or not isinstance(value, (int, float, np.number)) \
            or not math.isfinite(value) or value <= 0:
        raise ValueError(f"{name} must be a positive number, not {value!r}")
    return float(value)


def _check_nonnegative(value, name):
    if isinstance(value, bool) or not isinstance(value, (int, float, np.number)) \
            or not math.isfinite(value) or value < 0:
        raise ValueError(f"{name} must be a number >= 0, not {value!r}")
    return float(value)


def _check_half_window(value):
    if isinstance(value, bool) or not isinstance(value, (int, np.integer)) or value < 1:
        raise ValueError(f"Half window must be an integer >= 1 (readings on each side), "
                         f"not {value!r}")
    return int(value)
