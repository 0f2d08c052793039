"""From a card image to a survey product: the data reduction of airborne magnetics.

card → the largest ``LOG*.TXT`` → parsed streams → the vector magnetometer calibrated
(:func:`~maglog.calib.pipeline.calibrate_card`, cesium reference) → cesium samples timed →
direction cosines at the cesium samples → Tolles–Lawson compensation fitted on the
calibration box (:mod:`.tolles_lawson`) → georeferencing from GGA, IGRF removed
(:mod:`.georef`) → diurnal correction from a base station (:mod:`.diurnal`, optional) →
lines found and levelled on the tie lines (:mod:`.levelling`) → gridded with verde, NetCDF,
GeoTIFF, map (:mod:`.gridding`) → report (Markdown, HTML, PNGs, ``survey.json``).

Timing the cesium samples
-------------------------
The log has no timestamps; :mod:`.logparse` times the magnetometer by its sequence numbers
(good to milliseconds) but the cesium only by its place between GPS lines (errors up to
0.2 s). Tolles–Lawson needs the two sensors on one time base to a few milliseconds: the
interference changes by up to ~20 nT/s in the manoeuvres. So each cesium line is first
timed by the magnetometer lines around it in the log (interpolated in line number: ± half a
magnetometer period, 25 ms at 20 Hz), then, since the cesium samples at a steady rate, its
sample count is unrolled (each step rounded to whole periods, so drops are counted) and a
straight line ``t = t0 + k / rate`` fitted to those times by least squares. Both sensors'
lines arrive after their sample instant by their own transmission time, so the cesium
times are moved back by the difference (:data:`CESIUM_BAUD`, :data:`MAG_BAUD`, the lines'
own lengths). If the straight line leaves residuals above a third of a period (a sensor
restart, a rate change) the bracketed times are used and the report says so.

The calibration box
-------------------
Tolles–Lawson is fitted on the calibration box: the hovering manoeuvres (rolls, pitches and
yaws on four headings) before the lines. It is found as the longest stretch in which the
aircraft hovers (GPS speed below :data:`HOVER_SPEED` m/s, :data:`HOVER_HEIGHT` m above the
lowest fix) and the direction cosines move (their band-passed RMS over 4 s above
:data:`ACTIVE_COSINE`), gaps up to :data:`BOX_GAP_S` closed (the turns between headings).
``box=(start, end)`` (seconds of day, UTC) overrides it. The figure of merit sums the
band-passed peak-to-peak over the box's twelve equal parts (four headings of roll, pitch and
yaw, as the scenario flies them).

What the data allow, and what the result is checked against
-------------------------------------------------------------
Given settings are checked against the flight: ``ridge`` within :data:`RIDGE_RANGE` (the
range "auto" searches; below it the 18 terms' diagonal induced terms, which sum to the
cesium's own reading, reproduce the measurement and the "compensation" removes the
survey); ``band`` from tolles_lawson.BAND_FLOOR_HZ to BAND_CEILING x the cesium's rate, its
high edge at least :data:`BAND_MIN_RATIO` x its low one; ``lag_s`` at most what moves a
sample half the line spacing along its line; ``spacing_m`` leaving at least
:data:`MIN_GRID_NODES` nodes a side. The cesium's spikes and readings outside the Earth's
range are screened out (:mod:`.screen`), a cesium stuck in the box is refused. The result
carries ``warnings`` (printed, at the top of the report, in survey.json) where its own
diagnostics contradict it: a box residual below :data:`NOISE_FLOOR_FRACTION` of the
cesium's own noise in the band (the noise from its third differences), a cesium repeating
readings, a lag at the edge of its scan (not found: none applied), a given lag the
crossovers contradict, a field :data:`IGRF_MISFIT_NT` off IGRF, a grid coarser than the
lines. A ``truth`` must be this flight's (date, site, lines) or it is refused.
"""

from __future__ import annotations

import dataclasses
import datetime as _dt
import json
import math
import os
import warnings as _warnings
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from .survey_errors import SurveyError

__all__ = ["SurveyOptions", "SurveyResult", "survey_card", "write_products", "cesium_times",
           "find_box", "SURVEY_FILES", "HOVER_SPEED", "HOVER_HEIGHT", "ACTIVE_COSINE",
           "BOX_GAP_S", "CESIUM_BAUD", "MAG_BAUD"]

#: The sensors' line rates (the scenario's and the original design's), for the
#: transmission-time correction of the cesium times.
CESIUM_BAUD = 9_600
MAG_BAUD = 115_200
UART_BITS = 10
HOVER_SPEED = 1.0
HOVER_HEIGHT = 5.0
ACTIVE_COSINE = 0.02
BOX_GAP_S = 15.0
MIN_BOX_S = 20.0
#: A given ridge parameter must lie in the range ``ridge="auto"`` searches
#: (tolles_lawson.RIDGE_GRID): below it the 18-term set's diagonal induced terms
#: (u1² + u2² + u3² = 1 times the cesium's own reading) reproduce the measurement itself,
#: noise, anomaly and all, and the "compensation" removes the survey.
RIDGE_RANGE = (1e-6, 1e6)
#: A given band's high edge at most this fraction of the cesium's rate (the automatic band's
#: ceiling, tolles_lawson.BAND_CEILING), its low edge at least tolles_lawson.BAND_FLOOR_HZ,
#: and high / low at least BAND_MIN_RATIO (half an octave of manoeuvres).
BAND_MIN_RATIO = 1.5
#: Diagnostics (:func:`_diagnose`): the compensated box's band RMS below this fraction of
#: the cesium's own noise in that band is not a compensation; this share of consecutive
#: cesium readings identical is a stuck reference (refused), this share a suspect one
#: (warned); a median |compensated - IGRF| above this is not this place or date.
NOISE_FLOOR_FRACTION = 0.3
#: A box whose band holds more than UNCOMPENSATED_NOISE x the cesium's noise there (the
#: interference to remove) and an improvement ratio below UNCOMPENSATED_IR: not compensated.
UNCOMPENSATED_NOISE = 5.0
UNCOMPENSATED_IR = 1.2
STUCK_REFUSE = 0.5
STUCK_WARN = 0.05
IGRF_MISFIT_NT = 2000.0
#: A --truth must describe this flight: its origin within this of the first GPS fix.
TRUTH_ORIGIN_M = 1000.0
#: Files :func:`write_products` writes.
SURVEY_FILES = ("report.md", "report.html", "survey.json", "samples.csv", "anomaly.nc",
                "anomaly.tif", "map.png", "compensation.png", "levelling.png")


@dataclass
class SurveyOptions:
    """Settings of one survey reduction (the command line's options)."""
    terms: int = 18                 # Tolles–Lawson terms: 16 or 18
    band: tuple | None = None       # (low, high) Hz; None: from the manoeuvres
    ridge: object = "auto"          # "auto" or a non-negative float
    base_station: object = None     # path of a base-station CSV, or None
    max_base_gap_s: float = 10.0
    box: tuple | None = None        # (start, end) seconds of day UTC; None: found
    spacing_m: float | None = None  # grid spacing; None: a third of the line spacing
    grid_method: str = "spline"     # "spline" or "eqs"
    level_order: int = 0            # 0: a constant per line, 1: linear in time
    lag_s: float | None = None      # positions' lag behind the samples; None: estimated
    seed: int = 0                   # the vector calibration's swarm seed
    truth: object = None            # truth.json of a simulated flight (scores the result)
    compare_deinterf: bool = True

    def check(self):
        if self.terms not in (16, 18):
            raise SurveyError(f"terms must be 16 or 18, not {self.terms!r}")
        if self.band is not None:
            low, high = self.band
            if not (0 < low < high):
                raise SurveyError(f"band must be two frequencies 0 < low < high (Hz), not "
                                  f"{low:g},{high:g}")
        if self.ridge != "auto" and not (isinstance(self.ridge, (int, float))
                                         and not isinstance(self.ridge, bool)
                                         and RIDGE_RANGE[0] <= self.ridge <= RIDGE_RANGE[1]):
            raise SurveyError(f"ridge must be 'auto' or a number from {RIDGE_RANGE[0]:g} to "
                              f"{RIDGE_RANGE[1]:g} (the range the automatic choice searches: "
                              "below it the 18 terms reproduce the cesium's own reading and "
                              f"the compensation removes the survey), not {self.ridge!r}")
        if self.spacing_m is not None and not self.spacing_m > 0:
            raise SurveyError(f"grid spacing must be > 0 m, not {self.spacing_m!r}")
        if self.grid_method not in ("spline", "eqs"):
            raise SurveyError(f"grid method must be spline or eqs, not {self.grid_method!r}")
        if self.level_order not in (0, 1):
            raise SurveyError(f"levelling order must be 0 or 1, not {self.level_order!r}")
        if not self.max_base_gap_s > 0:
            raise SurveyError(f"the base station's largest gap must be > 0 s, not "
                              f"{self.max_base_gap_s!r}")
        if self.lag_s is not None and not (isinstance(self.lag_s, (int, float))
                                           and math.isfinite(self.lag_s)
                                           and abs(self.lag_s) <= 10):
            raise SurveyError(f"the lag must be a number of seconds within -10..10, not "
                              f"{self.lag_s!r}")
        if self.box is not None and not self.box[0] < self.box[1]:
            raise SurveyError(f"the calibration box must end after it starts, not "
                              f"{self.box[0]:g}-{self.box[1]:g}")
        return self


# --- timing --------------------------------------------------------------------------------

@dataclass
class CesiumTiming:
    t: np.ndarray               # sample times (seconds of day)
    method: str                 # "rate" or "bracketed"
    rate_hz: float
    residual_s: float           # RMS of the bracketed times about the straight line
    drops: int                  # samples the count says are missing
    lag_s: float                # transmission-time correction applied

    def as_dict(self):
        return {"method": self.method, "rate_hz": self.rate_hz,
                "residual_ms": 1e3 * self.residual_s, "drops": self.drops,
                "lag_ms": 1e3 * self.lag_s}


def _line_seconds(length, baud):
    return length * UART_BITS / baud


def cesium_times(parsed, *, cesium_baud=CESIUM_BAUD, mag_baud=MAG_BAUD):
    """The cesium samples' times (module docstring): :class:`CesiumTiming`."""
    mag, ces = parsed.mag, parsed.cesium
    ok = np.isfinite(mag.t)
    if ok.sum() < 2:
        raise SurveyError(f"{parsed.name}: no GPS fix in the log (no GGA with a fix and a "
                          "time): the samples have no time and no position")
    if len(ces) < 10:
        raise SurveyError(f"{parsed.name}: only {len(ces)} cesium readings")
    bracket = np.interp(ces.line, mag.line[ok], mag.t[ok], left=np.nan, right=np.nan)
    inside = np.isfinite(bracket)
    if inside.sum() < 10:
        raise SurveyError(f"{parsed.name}: only {int(inside.sum())} cesium readings lie "
                          "between timed magnetometer samples")
    # Both lines arrive one transmission time after their sample; the cesium's is longer.
    ces_len, mag_len = 18, 45        # "$ 49895.131,1249\r\n", "$PMAG1,...*hh\r\n"
    lag = _line_seconds(ces_len, cesium_baud) - _line_seconds(mag_len, mag_baud)
    tb = bracket[inside]
    steps = np.diff(tb)
    period = float(np.median(steps))
    if not period > 0:
        raise SurveyError(f"{parsed.name}: the cesium readings are not in time order")
    k = np.concatenate([[0], np.cumsum(np.maximum(1, np.round(steps / period)))])
    t = np.full(len(ces), np.nan)
    for _ in range(3):
        a = np.vstack([np.ones_like(k), k]).T
        coef, *_ = np.linalg.lstsq(a, tb, rcond=None)
        fitted = a @ coef
        residual = float(np.sqrt(np.mean((tb - fitted) ** 2)))
        if not coef[1] > 0:
            break
        # Unroll the count again against the refined line (a step misrounded against the
        # first, median period is put right), as long as it stays increasing.
        again = np.round((tb - coef[0]) / coef[1])
        again = again - again[0]
        if np.all(np.diff(again) >= 1):
            k = again
    period = float(coef[1])
    drops = int(k[-1] + 1 - len(k))
    if period > 0 and residual < period / 3:
        t[inside] = fitted - lag
        method = "rate"
    else:
        t[inside] = tb - lag
        method = "bracketed"
        period = float(np.median(steps))
    return CesiumTiming(t=t, method=method, rate_hz=1.0 / period, residual_s=residual,
                        drops=drops, lag_s=lag)


# --- the calibration box -------------------------------------------------------------------

def _runs(mask):
    """(start, stop) index pairs of the True runs of ``mask``."""
    edges = np.diff(np.concatenate([[0], mask.astype(np.int8), [0]]))
    return list(zip(np.flatnonzero(edges == 1), np.flatnonzero(edges == -1)))


def _moving_rms(x, width):
    width = max(1, int(width))
    kernel = np.ones(width) / width
    return np.sqrt(np.convolve(x ** 2, kernel, mode="same"))


def find_box(t, cosines, speed, height, rate_hz):
    """The calibration box (module docstring): (start, end) seconds, or SurveyError."""
    from .tolles_lawson import bandpass
    good = np.isfinite(speed) & np.isfinite(height) & np.all(np.isfinite(cosines), axis=1)
    moving = np.zeros(len(t))
    if good.sum() > 10 * rate_hz:
        filled = np.where(np.isfinite(cosines), cosines, 0.0)
        moved = bandpass(filled, rate_hz, (0.05, min(1.0, 0.45 * rate_hz)))
        moving = _moving_rms(np.linalg.norm(moved, axis=1), 4 * rate_hz)
    with np.errstate(invalid="ignore"):
        hover = good & (speed < HOVER_SPEED) & (height > HOVER_HEIGHT) & (moving > ACTIVE_COSINE)
    runs = _runs(hover)
    # Close the gaps of up to BOX_GAP_S between runs (the turns).
    merged = []
    for start, stop in runs:
        if merged and t[start] - t[merged[-1][1] - 1] <= BOX_GAP_S:
            merged[-1] = (merged[-1][0], stop)
        else:
            merged.append((start, stop))
    if not merged:
        raise SurveyError("no calibration box found (no hovering manoeuvres: rolls, pitches, "
                          "yaws); give it with --box START-END")
    start, stop = max(merged, key=lambda r: t[r[1] - 1] - t[r[0]])
    if t[stop - 1] - t[start] < MIN_BOX_S:
        raise SurveyError(f"the calibration box found is only {t[stop - 1] - t[start]:.0f} s "
                          f"long (at least {MIN_BOX_S:.0f} s needed); give it with --box")
    return float(t[start]), float(t[stop - 1])


def _segments(start, end, parts=12):
    edges = np.linspace(start, end, parts + 1)
    return list(zip(edges[:-1], edges[1:]))


# --- the reduction -------------------------------------------------------------------------

@dataclass
class SurveyResult:
    """Everything :func:`survey_card` computed; :meth:`summary` gives the report's figures."""
    log_name: str
    date: _dt.date | None
    options: SurveyOptions
    timing: CesiumTiming
    t: np.ndarray               # cesium sample times (seconds of day)
    raw: np.ndarray             # cesium total field, nT
    cosines: np.ndarray         # (n, 3) calibrated field direction in the body frame
    box: tuple
    box_source: str
    tl: object                  # tolles_lawson.TLFit applied
    tl_other: object            # the other term count's fit (16 or 18)
    compensated: np.ndarray
    deinterf: dict | None       # deinterf's compensated series and settings
    track: object               # georef.Track at t
    igrf: np.ndarray
    diurnal: np.ndarray | None
    anomaly: np.ndarray         # compensated - IGRF (- diurnal)
    lines: list
    levelling: object
    levelled: np.ndarray
    grid: object                # xarray.Dataset (local metres)
    grid_info: dict
    calibration: object         # pipeline.CalibrationRun of the vector magnetometer
    notes: list = field(default_factory=list)
    scores: dict = field(default_factory=dict)   # against the truth, when given
    times: dict = field(default_factory=dict)    # seconds per step
    lag: dict = field(default_factory=dict)      # the lag correction (estimate_lag)
    warnings: list = field(default_factory=list)  # why the result is not to be trusted
    noise: dict = field(default_factory=dict)    # the cesium's noise (_diagnose)

    def on_lines(self):
        mask = np.zeros(len(self.t), bool)
        for line in self.lines:
            mask |= (self.t >= line.start) & (self.t <= line.end)
        return mask


def _check_path(path, what):
    """``path`` a regular file (a folder, a device or a missing file said as such)."""
    import stat
    path = Path(path)
    try:
        mode = path.stat().st_mode
    except FileNotFoundError:
        raise SurveyError(f"{path}: no such {what}") from None
    except OSError as error:
        raise SurveyError(f"{path}: cannot read the {what} ({error.strerror or error})") \
            from None
    if stat.S_ISDIR(mode):
        raise SurveyError(f"{path}: is a folder, not a {what}")
    if not stat.S_ISREG(mode):
        raise SurveyError(f"{path}: not a regular file (a device or a pipe), not a {what}")
    return path


def survey_card(path, options=None, *, progress=None):
    """Reduce the largest log on a card image (or partition image, or plain log) to a
    levelled, gridded anomaly (module docstring). Bad input ends in a :class:`SurveyError`
    (or the card reader's and calibration's own errors, which the caller reports the same
    way). Nothing is printed: ``progress``, if given, is told of each of :data:`STAGES` as
    ``progress(label, None)`` when it starts and ``progress(label, seconds)`` when it
    ends."""
    from threadpoolctl import threadpool_limits
    options = (options or SurveyOptions()).check()
    # One BLAS thread: a threaded BLAS sums in an order that depends on its thread count,
    # and a Dask worker runs with one; the same card must give the same map anywhere.
    with _warnings.catch_warnings(), np.errstate(all="ignore"), threadpool_limits(1):
        _warnings.simplefilter("ignore")
        return _survey(Path(path), options, progress)


def _clock():
    import time
    return time.perf_counter()


#: The reduction's stages in order: (key, what it does). A key ending in ``_s`` is also the
#: stage's entry in :attr:`SurveyResult.times` (survey.json's ``times_s``).
STAGES = (("vector_calibration_s", "reading the log, calibrating the vector magnetometer"),
          ("timing_georef_s", "timing the cesium, georeferencing"),
          ("tolles_lawson_s", "compensating (Tolles–Lawson)"),
          ("igrf_diurnal_s", "IGRF and the diurnal correction"),
          ("lag_s", "the positions' lag"),
          ("levelling_s", "levelling"),
          ("gridding_s", "gridding"),
          ("checks", "checks and scores"))


class _Stages:
    """Times each of :data:`STAGES` into ``times`` and tells ``progress`` (if any) of its
    start and end (:func:`survey_card`)."""

    def __init__(self, times, progress):
        self.times, self.progress = times, progress
        self.labels = dict(STAGES)
        self.key = None

    def start(self, key):
        self.key, self.mark = key, _clock()
        if self.progress is not None:
            self.progress(self.labels[key], None)

    def end(self):
        seconds = _clock() - self.mark
        if self.key.endswith("_s"):
            self.times[self.key] = seconds
        if self.progress is not None:
            self.progress(self.labels[self.key], seconds)


def _survey(path, options, progress=None):
    from . import tolles_lawson as tl
    from .diurnal import diurnal_correction, read_base_station
    from .georef import find_lines, georeference, igrf_total
    from .gridding import grid_anomaly, grid_summary
    from .levelling import Levelling, crossovers, level
    from .pipeline import calibrate_card
    from .scalar import apply_scalar

    times = {}
    stage = _Stages(times, progress)
    stage.start("vector_calibration_s")
    # The base station and the truth are read before the long work: their errors come first.
    base = None
    if options.base_station is not None:
        base = read_base_station(_check_path(options.base_station, "base-station file"))
    truth = None
    if options.truth is not None:
        truth = read_truth(_check_path(options.truth, "truth file"))
    run = calibrate_card(path, ref="cesium", method="pso", seed=options.seed)
    if run.parsed.date is None:
        raise SurveyError(f"{run.parsed.name}: no ZDA date in the log: IGRF needs the date")
    stage.end()
    parsed = run.parsed
    notes = list(run.warnings)

    stage.start("timing_georef_s")
    timing = cesium_times(parsed)
    ces = parsed.cesium
    warnings = []
    untrusted = _vector_calibration_warning(run)
    if untrusted:
        warnings.append(untrusted)
    valid = _screen_cesium(timing.t, ces.field, notes)
    t, raw = timing.t[valid], ces.field[valid]
    if timing.method != "rate":
        notes.append(f"cesium samples timed by the magnetometer lines around them (their "
                     f"steady rate left {1e3 * timing.residual_s:.0f} ms RMS)")
    mag = parsed.mag
    ok = np.isfinite(mag.t)
    vectors = apply_scalar(run.result.K, run.result.c, mag.b[ok])
    vt = mag.t[ok]
    if not np.all(np.diff(vt) > 0):
        raise SurveyError(f"{parsed.name}: the magnetometer's times do not increase (a "
                          "sensor restart?): its samples cannot be matched to the cesium's")
    vec = np.column_stack([np.interp(t, vt, vectors[:, k], left=np.nan, right=np.nan)
                           for k in range(3)])
    # No direction across a gap in the magnetometer's samples (more than 3 periods).
    right = np.clip(np.searchsorted(vt, t), 1, len(vt) - 1)
    vec[vt[right] - vt[right - 1] > 3 * float(np.median(np.diff(vt)))] = np.nan
    cosines = vec / np.linalg.norm(vec, axis=1, keepdims=True)
    keep = np.all(np.isfinite(cosines), axis=1)
    t, raw, cosines = t[keep], raw[keep], cosines[keep]
    rate = timing.rate_hz

    track = georeference(parsed, t)
    stage.end()

    # The calibration box and Tolles–Lawson.
    stage.start("tolles_lawson_s")
    if options.box is not None:
        box, box_source = tuple(map(float, options.box)), "given"
    else:
        speed = _speed(track)
        height = track.alt - np.nanmin(track.alt)
        box, box_source = find_box(t, cosines, speed, height, rate), "found"
    in_box = (t >= box[0]) & (t <= box[1])
    if in_box.sum() < 20 * rate:
        raise SurveyError(f"the calibration box {_tod(box[0])}-{_tod(box[1])} holds only "
                          f"{int(in_box.sum())} cesium samples")
    _check_stuck(raw[in_box], box, warnings)
    if options.band is not None:
        _check_band(options.band, rate)
    fits = {}
    for terms in (16, 18):
        fits[terms] = tl.fit(t[in_box], cosines[in_box], raw[in_box], raw[in_box],
                             terms=terms, band=options.band, ridge=options.ridge)
    chosen = fits[options.terms]
    other = fits[34 - options.terms]
    compensated = raw - chosen.predict(t, cosines, raw)
    deinterf = None
    if options.compare_deinterf:
        try:
            deinterf = tl.deinterf_compensate(t, cosines, raw, raw, in_box, options.terms)
        except Exception as error:      # noqa: BLE001 - the comparison is optional
            notes.append(f"deinterf could not run on this flight ({type(error).__name__}: "
                         f"{error}); left out of the comparison")
    stage.end()

    # Georeferenced anomaly: IGRF, diurnal.
    stage.start("igrf_diurnal_s")
    date = parsed.date
    if date is None:
        raise SurveyError(f"{parsed.name}: no ZDA date in the log: IGRF needs the date")
    igrf = igrf_total(date, track.lat, track.lon, track.alt)
    anomaly = compensated - igrf
    diurnal = None
    if base is not None:
        epoch = _dt.datetime(date.year, date.month, date.day, tzinfo=_dt.timezone.utc)
        diurnal = diurnal_correction(base, epoch, t, max_gap_s=options.max_base_gap_s)
        anomaly = anomaly - diurnal
    stage.end()

    # Lines, the lag correction, levelling, grid.
    stage.start("lag_s")
    lines = find_lines(t, track.north, track.east)
    if options.lag_s is None:
        lag, lag_table = estimate_lag(parsed, t, lines, anomaly, track.origin)
        lag_source = "crossovers" if lag is not None else "none"
        if lag is not None and abs(lag) >= LAG_RANGE_S - 1e-9:
            warnings.append(
                f"the positions' lag was not found: the crossovers are least at the edge of "
                f"the {-LAG_RANGE_S:g}..{LAG_RANGE_S:g} s scan ({lag:+.3f} s), not inside "
                "it; the map is made without a lag correction (give it with --lag if you "
                "know it; a compensation that removed the anomaly pins it there too)")
            lag, lag_source = None, "not found"
        lag = lag or 0.0
    else:
        lag, lag_table, lag_source = float(options.lag_s), [], "given"
        _check_lag(lag, lines, t, track)
        best, scan = estimate_lag(parsed, t, lines, anomaly, track.origin)
        if best is not None and abs(best) < LAG_RANGE_S - 1e-9:
            given_rms = crossover_rms(parsed, t, lines, anomaly, track.origin, lag)[0]
            best_rms = min(row[1] for row in scan)
            if given_rms > LAG_WORSE * best_rms and given_rms > best_rms + LAG_WORSE_NT:
                warnings.append(
                    f"the lag given ({lag:g} s) leaves the crossovers {given_rms:.2f} nT RMS "
                    f"apart, against {best_rms:.2f} nT at {best:+.3f} s (the lag they "
                    "indicate): the map is smeared across the lines by the lag given")
    if lag:
        track = dataclasses.replace(georeference(parsed, t + lag, origin=track.origin), t=t)
        anomaly = anomaly + igrf
        igrf = igrf_total(date, track.lat, track.lon, track.alt)
        anomaly = anomaly - igrf
        lines = find_lines(t, track.north, track.east)
    stage.end()
    stage.start("levelling_s")
    cross = crossovers(lines, t, track.north, track.east, anomaly)
    if cross:
        levelling = level(lines, t, anomaly, cross, order=options.level_order)
    else:
        # No tie line crosses the lines: the map is made unlevelled, and says so.
        levelling = Levelling(values=anomaly.copy(), correction=np.zeros(len(t)),
                              offsets=np.zeros(len(lines)), slopes=np.zeros(len(lines)),
                              order=options.level_order, rms_before=math.nan,
                              rms_after=math.nan, residuals=np.zeros(0), n_crossovers=0,
                              unlevelled=[k for k, line in enumerate(lines)
                                          if line.kind == "line"], lines=list(lines))
        notes.append("no tie line crosses the survey lines: the map is not levelled"
                     + (" (the lag is not corrected either)" if options.lag_s is None else ""))
    levelled = levelling.values
    stage.end()
    stage.start("gridding_s")
    on = np.zeros(len(t), bool)
    for line in lines:
        on |= (t >= line.start) & (t <= line.end)
    on &= np.isfinite(levelled) & np.isfinite(track.north)
    if options.spacing_m is not None and on.any():
        _check_spacing(options.spacing_m, track.north[on], track.east[on], warnings)
    grid = grid_anomaly(track.north[on], track.east[on], levelled[on],
                        spacing_m=options.spacing_m, method=options.grid_method)
    stage.end()
    stage.start("checks")
    lag_record = {"lag_s": lag, "source": lag_source, "scan": lag_table}
    result = SurveyResult(
        log_name=parsed.name, date=date, options=options, timing=timing, t=t, raw=raw,
        cosines=cosines, box=box, box_source=box_source, tl=chosen, tl_other=other,
        compensated=compensated, deinterf=deinterf, track=track, igrf=igrf, diurnal=diurnal,
        anomaly=anomaly, lines=lines, levelling=levelling, levelled=levelled, grid=grid,
        grid_info=grid_summary(grid),
        calibration=run, notes=notes, times=times, lag=lag_record)
    result.warnings = warnings + _diagnose(result)
    if truth is not None:
        _check_truth_flight(truth, options.truth, result)
        result.scores = score_against_truth(result, options.truth)
        result.warnings += _truth_misfit(result.scores)
    stage.end()
    return result


#: A map further than this fraction of the true anomaly's largest |value| (RMS on the grid's
#: nodes, and at least TRUTH_MISFIT_NT) from the truth is warned about.
TRUTH_MISFIT_FRACTION = 0.15
TRUTH_MISFIT_NT = 2.0


def _truth_misfit(scores):
    """A warning when the map and the truth disagree by much more than a reduction's error:
    the map is wrong, or the truth (its sources, heights) is not this flight's."""
    rms = scores.get("grid_rms_nT")
    span = max(abs(v) for v in scores.get("true_anomaly_range_nT", [0.0]))
    if rms is None or not math.isfinite(rms):
        return []
    if rms > max(TRUTH_MISFIT_NT, TRUTH_MISFIT_FRACTION * span):
        return [f"the map is {rms:.1f} nT RMS off the truth's anomaly (its largest "
                f"|value| {span:.1f} nT): either the map is wrong or the truth (its sources, "
                "site or heights) is not this flight's; its scores are not a measure of "
                "this reduction"]
    return []


#: The compensation is built on the calibrated vector's direction cosines: a calibration
#: that leaves the field's direction uncertain by more than this share of the field (its
#: residual against the cesium, or an undetermined parameter's 1 sigma in nT of field)
#: makes the compensation and the map untrustworthy. The built-in survey's +-30 deg box
#: leaves k33 and c3 at about 11 nT of a 49,000 nT field: 2e-4, far below.
DIRECTION_SHARE = 0.01


def _vector_calibration_warning(run):
    """A warning when the vector calibration the compensation rests on failed, does not fit
    the cesium, or leaves a parameter undetermined by more than :data:`DIRECTION_SHARE` of
    the field; None otherwise."""
    from .coverage import PARAMETERS
    field_nt = float(np.median(run.r))
    rms = float(np.sqrt(np.mean(run.residual ** 2)))
    reasons = []
    coverage = getattr(run, "coverage", None)
    if coverage is not None and coverage.verdict == "failed":
        reasons.append(f"its fit failed ({coverage.fit_message})")
    if rms > DIRECTION_SHARE * field_nt:
        reasons.append(f"it leaves {rms:.3g} nT RMS against the cesium "
                       f"({rms / field_nt:.1%} of the field)")
    if coverage is not None and coverage.verdict == "undetermined":
        sigma = coverage.determination.sigma_nT
        loose = [n for n in coverage.undetermined
                 if not sigma[PARAMETERS.index(n)] <= DIRECTION_SHARE * field_nt]
        if loose:
            reasons.append(f"it leaves {', '.join(loose)} undetermined beyond "
                           f"{DIRECTION_SHARE:.0%} of the field "
                           f"({coverage.determination.figures(loose)})")
    if not reasons:
        return None
    return ("the vector magnetometer's calibration is not to be trusted: "
            + "; ".join(reasons) + ": the compensation is built on its direction cosines, "
            "so the compensation and the map rest on it (fly a calibration box that turns "
            "the sensor about every axis, or check the vector sensor's data)")


def _screen_cesium(t, field, notes):
    """The cesium readings to use: timed, and passed by the reference screen (the Earth's
    range, isolated spikes such as a bit flip: :func:`~maglog.calib.screen.screen_reference`);
    what it left out said in ``notes``."""
    from .screen import screen_reference
    valid = np.isfinite(t) & np.isfinite(field)
    if valid.sum() < 10:
        raise SurveyError(f"only {int(valid.sum())} timed cesium readings")
    screen = screen_reference(t[valid], field[valid])
    if screen.n_rejected:
        notes.append(f"cesium {screen.summary()}: left out")
    keep = np.zeros(len(t), bool)
    keep[np.flatnonzero(valid)[screen.keep]] = True
    if keep.sum() < 10:
        raise SurveyError(f"only {int(keep.sum())} plausible cesium readings "
                          f"({screen.summary()})")
    return keep


def _check_stuck(raw, box, warnings):
    """A cesium that repeats its reading in the calibration box (where the manoeuvres change
    the interference by nT every tenth of a second, and a reading has 0.001 nT steps) is
    stuck: refused from STUCK_REFUSE of consecutive readings identical, warned from
    STUCK_WARN."""
    if raw.size < 2:
        return
    same = float(np.mean(np.diff(raw) == 0))
    values, counts = np.unique(raw, return_counts=True)
    common = float(values[np.argmax(counts)])
    where = f"the calibration box {_tod(box[0])}-{_tod(box[1])}"
    if same >= STUCK_REFUSE:
        raise SurveyError(f"the cesium is stuck: {100 * same:.0f} % of its consecutive "
                          f"readings in {where} are identical ({common:,.3f} nT most "
                          "often): it measured no field to compensate or map")
    if same >= STUCK_WARN:
        warnings.append(f"the cesium repeats its reading in {100 * same:.0f} % of "
                        f"consecutive samples in {where} ({common:,.3f} nT most often; a "
                        "working one repeats in well under 1 %): a stuck or frozen "
                        "reference; the compensation and the map are not to be trusted")


def _check_band(band, rate):
    """A given band against what the cesium's rate allows (the rule of --band)."""
    from .tolles_lawson import BAND_CEILING, BAND_FLOOR_HZ
    low, high = (float(b) for b in band)
    ceiling = BAND_CEILING * rate
    if not (BAND_FLOOR_HZ <= low and high <= ceiling and high >= BAND_MIN_RATIO * low):
        raise SurveyError(
            f"the band {low:g}-{high:g} Hz is not one this flight allows: it must run from at "
            f"least {BAND_FLOOR_HZ:g} Hz to at most {BAND_CEILING:g} x the cesium's "
            f"{rate:.4g} Hz ({ceiling:.3g} Hz), its high edge at least {BAND_MIN_RATIO:g} x "
            "its low one")


def _check_lag(lag, lines, t, track):
    """A given lag against the flight: moving each sample by lag x speed along its line
    must keep it nearer its own line than the next (the rule of --lag)."""
    from .gridding import line_spacing
    survey = [line for line in lines if line.kind == "line"]
    if not survey or lag == 0:
        return
    on = np.zeros(len(t), bool)
    for line in survey:
        on |= (t >= line.start) & (t <= line.end)
    on &= np.isfinite(track.north) & np.isfinite(track.east)
    speeds = [line.speed_m_s for line in survey if math.isfinite(line.speed_m_s)]
    if not speeds or on.sum() < 10:
        return
    speed = float(np.median(speeds))
    try:
        spacing = float(line_spacing(track.north[on], track.east[on])[0])
    except (ValueError, SurveyError):
        return
    if not math.isfinite(spacing) or spacing <= 0:
        return
    limit = spacing / 2 / speed
    if abs(lag) > limit:
        raise SurveyError(f"the lag {lag:g} s is more than this flight allows: at "
                          f"{speed:.3g} m/s it moves every sample {abs(lag) * speed:.0f} m "
                          f"along its line, past half the {spacing:.0f} m line spacing "
                          f"(at most {limit:.2f} s here)")


#: A given grid spacing must leave at least this many nodes along each side of the survey.
MIN_GRID_NODES = 3


def _check_spacing(spacing, north, east, warnings):
    """A given grid spacing against the survey: refused when it leaves fewer than
    MIN_GRID_NODES nodes along a side (one node is no map), warned when it is coarser than
    the line spacing (the map no longer resolves what the lines measured)."""
    from .gridding import line_spacing
    extent = min(float(np.ptp(north)), float(np.ptp(east)))
    nodes = int(extent // spacing) + 1
    if nodes < MIN_GRID_NODES:
        raise SurveyError(f"grid spacing {spacing:g} m leaves {nodes} node"
                          f"{'s' * (nodes != 1)} across the survey's {extent:.0f} m: at most "
                          f"{extent / (MIN_GRID_NODES - 1):.3g} m here (a map needs "
                          f"{MIN_GRID_NODES} nodes a side)")
    try:
        lines = float(line_spacing(north, east)[0])
    except SurveyError:
        return
    if math.isfinite(lines) and spacing > lines:
        warnings.append(f"the grid spacing {spacing:g} m is coarser than the {lines:.0f} m "
                        "line spacing: the map does not resolve what the lines measured "
                        "(its peak is smoothed away)")


def _noise_nT(t, raw):
    """The cesium's own white noise (nT RMS) from its third differences (robust: their
    median absolute deviation; smooth signals, the interference and anomalies at a 10-Hz
    rate, hardly reach them), on gap-free stretches."""
    period = float(np.median(np.diff(t)))
    pieces = np.split(raw, np.flatnonzero(np.diff(t) > 2.5 * period) + 1)
    d3 = np.concatenate([np.diff(p, 3) for p in pieces if p.size > 3] or [np.zeros(0)])
    if d3.size < 10:
        return math.nan
    return float(1.4826 * np.median(np.abs(d3 - np.median(d3))) / math.sqrt(20.0))


def _diagnose(result):
    """Warnings where the result is implausible against its own diagnostics: a compensation
    that removes more than the cesium's own noise (it reproduced the measurement, not the
    interference: improvement ratios of thousands), and an anomaly thousands of nT off
    IGRF (the positions or the date are not this flight's)."""
    from .tolles_lawson import bandpass
    out = []
    box = (result.t >= result.box[0]) & (result.t <= result.box[1])
    band, rate = result.tl.band, result.timing.rate_hz
    noise = _noise_nT(result.t, result.raw)
    try:
        before = float(np.std(bandpass(result.raw[box], rate, band)))
        after = float(np.std(bandpass(result.compensated[box], rate, band)))
    except SurveyError:
        before = after = math.nan
    expected = noise * math.sqrt(2 * (band[1] - band[0]) / rate)
    result.noise = {"cesium_noise_nT": noise, "band_noise_nT": expected}
    if math.isfinite(expected) and expected > 0 and after < NOISE_FLOOR_FRACTION * expected:
        ratio = before / after if after > 0 else math.inf
        out.append(f"the compensation is implausible: in the calibration box it leaves "
                   f"{after:.3g} nT RMS in the {band[0]:.3g}-{band[1]:.3g} Hz band "
                   f"(improvement ratio {ratio:.3g}), below the cesium's own noise there "
                   f"({expected:.3g} nT, from {noise:.3g} nT white noise): the model "
                   "reproduced the measurement itself, not the interference, and the map "
                   "lost the anomaly with it (a ridge, band or box that does not "
                   "determine the terms)")
    elif (math.isfinite(expected) and before > UNCOMPENSATED_NOISE * expected
          and after > before / UNCOMPENSATED_IR):
        out.append(f"the compensation removed next to nothing: in the calibration box the "
                   f"{band[0]:.3g}-{band[1]:.3g} Hz band holds {before:.3g} nT RMS, "
                   f"{before / max(expected, 1e-300):.0f} times the cesium's own noise "
                   f"there, and {after:.3g} nT are left (improvement ratio "
                   f"{before / after:.3g}): the platform's interference stays in the map "
                   f"(a ridge of {result.tl.ridge_alpha:.3g} holds the terms at zero, or the "
                   "band misses the manoeuvres)")
    misfit = float(np.nanmedian(np.abs(result.compensated - result.igrf)))
    if misfit > IGRF_MISFIT_NT:
        out.append(f"the field is {misfit:,.0f} nT (median) off IGRF at the GPS positions "
                   "and date: the positions (latitude and longitude swapped? a wrong "
                   "hemisphere?), the date or the reference are not this flight's, and the "
                   "anomaly map is not one")
    return out


def _check_truth_flight(truth, path, result):
    """A --truth must describe this flight: the same date, an origin at the first GPS fix,
    and every line found inside one of the truth's lines of the same kind."""
    when = _dt.datetime.fromisoformat(truth["timestamp"]).astimezone(_dt.timezone.utc)
    if result.date is not None and when.date() != result.date:
        raise SurveyError(f"{path}: the truth is of a flight on {when.date()}, the log's is "
                          f"on {result.date}: not this flight's truth")
    origin = truth["survey"]["origin"]
    lat0, lon0 = result.track.origin
    north = (origin["lat_deg"] - lat0) * METRES_PER_DEGREE
    east = (origin["lon_deg"] - lon0) * METRES_PER_DEGREE * math.cos(math.radians(lat0))
    distance = math.hypot(north, east)
    if not distance <= TRUTH_ORIGIN_M:
        raise SurveyError(f"{path}: the truth's site is {distance / 1e3:,.1f} km from the "
                          f"log's first GPS fix: not this flight's truth")
    start = when - when.replace(hour=0, minute=0, second=0, microsecond=0)
    offset = start.total_seconds()
    spans = [(line["kind"], line["start_s"] + offset, line["end_s"] + offset)
             for line in truth["survey"]["lines"]]
    for line in result.lines:
        middle = (line.start + line.end) / 2
        if not any(kind == line.kind and a - 5 <= middle <= b + 5 for kind, a, b in spans):
            raise SurveyError(f"{path}: the log's {line.kind} {line.index + 1} "
                              f"({_tod(line.start)}-{_tod(line.end)} UTC) is not one of the "
                              f"truth's {sum(k == line.kind for k, _, _ in spans)} "
                              f"{line.kind}s: not this flight's truth")


#: The lags :func:`estimate_lag` tries (s): coarse steps over +-LAG_RANGE_S, then fine ones.
LAG_RANGE_S = 1.0
LAG_STEP_S = 0.05
LAG_FINE_S = 0.005


def estimate_lag(parsed, t, lines, anomaly, origin):
    """The lag correction of airborne magnetics: the time by which the positions must be
    taken later than the samples' times so that lines flown in opposite directions agree.

    The log's times are GGA line arrival times with ``gps_latency`` 0, so every sample's
    time is early by the GPS receiver's latency (its fix's age when the GGA line ends);
    a sample is then placed ``speed × latency`` back along its line, in opposite senses on
    neighbouring lines, and the anomaly's gradients turn that into crossover differences.
    The lag is the one that minimises the crossover RMS of the (unlevelled) anomaly: a scan
    in LAG_STEP_S over +-LAG_RANGE_S, then LAG_FINE_S steps around the best. Returns
    (lag_s, [(lag_s, rms_nT, crossovers)]); (None, ...) when fewer than three crossovers
    leave no RMS to minimise. A lag at the scan's edge (+-LAG_RANGE_S) is returned as it is,
    not refined: the minimum lies outside the scan, and the caller reports it as not found."""
    def rms(lag):
        return crossover_rms(parsed, t, lines, anomaly, origin, lag)

    scan = []
    for lag in np.arange(-LAG_RANGE_S, LAG_RANGE_S + LAG_STEP_S / 2, LAG_STEP_S):
        scan.append((round(float(lag), 6), *rms(float(lag))))
    best = min(scan, key=lambda row: row[1])
    if not math.isfinite(best[1]):
        return None, scan
    if abs(best[0]) >= LAG_RANGE_S - 1e-9:
        return best[0], scan              # at the edge: the caller says "not found"
    for lag in np.arange(best[0] - LAG_STEP_S, best[0] + LAG_STEP_S + LAG_FINE_S / 2,
                         LAG_FINE_S):
        if abs(lag) <= LAG_RANGE_S + 1e-9:
            scan.append((round(float(lag), 6), *rms(float(lag))))
    best = min(scan, key=lambda row: row[1])
    return best[0], sorted(scan)


def crossover_rms(parsed, t, lines, anomaly, origin, lag):
    """(RMS about their mean of the crossover differences, their number) with the positions
    taken ``lag`` s later; the RMS is inf below three crossovers."""
    from .georef import georeference
    from .levelling import crossovers
    shifted = georeference(parsed, t + lag, origin=origin)
    cross = crossovers(lines, t, shifted.north, shifted.east, anomaly)
    d = np.asarray([c[-1] for c in cross], float)
    d = d - d.mean() if d.size else d
    return (float(np.sqrt(np.mean(d ** 2))) if d.size > 2 else math.inf), int(d.size)


#: A given lag whose crossover RMS exceeds the best lag's by this factor (and by
#: LAG_WORSE_NT) is warned about.
LAG_WORSE = 2.0
LAG_WORSE_NT = 0.5


def _speed(track):
    """Ground speed (m/s) at the samples from the georeferenced track."""
    t = track.t
    good = np.isfinite(track.north) & np.isfinite(track.east)
    speed = np.full(len(t), np.nan)
    if good.sum() > 2:
        vn = np.gradient(track.north[good], t[good])
        ve = np.gradient(track.east[good], t[good])
        speed[good] = np.hypot(vn, ve)
    return speed


def _tod(seconds):
    seconds = float(seconds) % 86400
    h, rest = divmod(seconds, 3600)
    m, s = divmod(rest, 60)
    return f"{int(h):02d}:{int(m):02d}:{s:04.1f}"


# --- scores against a simulated flight's truth ---------------------------------------------

METRES_PER_DEGREE = 111_320.0


def read_truth(path):
    """``truth.json`` of a simulated survey flight (it must hold a ``survey`` section)."""
    path = Path(path)
    try:
        truth = json.loads(path.read_text(encoding="utf-8"))
    except OSError as error:
        raise SurveyError(f"{path}: cannot read the truth ({error.strerror or error})") \
            from None
    except (UnicodeDecodeError, json.JSONDecodeError) as error:
        raise SurveyError(f"{path}: not a truth file ({error})") from None
    if not isinstance(truth, dict) or "survey" not in truth:
        raise SurveyError(f"{path}: the truth has no survey section (not a survey scenario)")
    _check_truth(truth, path)
    return truth


def _truth_value(truth, path, keys, kind="number", low=-math.inf, high=math.inf, size=None):
    """``truth[k0][k1]...`` checked: a finite number within [low, high] (``kind`` "number"),
    a list of ``size`` such numbers ("vector"), a dict, a list or a string; else a
    SurveyError naming the file and the key."""
    value, where = truth, []
    for key in keys:
        if where and not isinstance(value, (dict, list)):
            raise SurveyError(f"{path}: the truth's {'.'.join(where)} must be a "
                              f"{'list' if isinstance(key, int) else 'table'}, not "
                              f"{type(value).__name__}")
        where.append(str(key))
        if isinstance(key, int):
            ok = isinstance(value, list) and -len(value) <= key < len(value)
        else:
            ok = isinstance(value, dict) and key in value
        if not ok:
            raise SurveyError(f"{path}: the truth has no {'.'.join(where)} (not the truth of "
                              "a survey scenario, or a damaged one)")
        value = value[key]
    name = ".".join(where)

    def number(v):
        return (isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v)
                and low <= v <= high)
    if kind == "number" and not number(value):
        raise SurveyError(f"{path}: the truth's {name} must be a number"
                          + (f" within {low:g}..{high:g}" if math.isfinite(low) or
                             math.isfinite(high) else "") + f", not {str(value)[:40]!r}")
    if kind == "vector" and not (isinstance(value, list) and len(value) == size
                                 and all(number(v) for v in value)):
        raise SurveyError(f"{path}: the truth's {name} must be {size} numbers, not "
                          f"{str(value)[:60]!r}")
    for wanted, python in (("dict", dict), ("list", list), ("string", str)):
        if kind == wanted and not isinstance(value, python):
            raise SurveyError(f"{path}: the truth's {name} must be a {wanted}, not "
                              f"{type(value).__name__}")
    return value


def _check_truth(truth, path):
    """Every value :func:`score_against_truth` and :func:`_check_truth_flight` read, of the
    right type and range (a damaged or hand-edited truth.json ends in one line)."""
    value = lambda *keys, **kw: _truth_value(truth, path, keys, **kw)
    stamp = value("timestamp", kind="string")
    try:
        when = _dt.datetime.fromisoformat(stamp)
    except ValueError:
        raise SurveyError(f"{path}: the truth's timestamp {stamp[:40]!r} is not an ISO date "
                          "and time") from None
    if when.tzinfo is None:
        raise SurveyError(f"{path}: the truth's timestamp {stamp[:40]!r} has no time zone")
    value("reference", "cesium_noise_nT", low=0)
    value("survey", kind="dict")
    value("survey", "origin", kind="dict")
    value("survey", "origin", "lat_deg", low=-90, high=90)
    value("survey", "origin", "lon_deg", low=-180, high=180)
    value("survey", "origin", "ground_alt_m", low=-1e4, high=1e5)
    value("survey", "igrf_site_ned_nT", kind="vector", size=3)
    for k in range(len(value("survey", "dipoles", kind="list"))):
        for key in ("north_m", "east_m"):
            value("survey", "dipoles", k, key, low=-1e7, high=1e7)
        value("survey", "dipoles", k, "depth_m", low=0, high=1e7)      # buried
        value("survey", "dipoles", k, "moment_ned_Am2", kind="vector", size=3)
    for key in ("start_seconds_of_day", "lon_deg", "amplitude_nT", "pulsation_nT"):
        value("survey", "diurnal", key, low=-1e6, high=1e6)
    value("survey", "diurnal", "pulsation_period_s", low=1e-3, high=1e9)
    for k in range(len(value("survey", "lines", kind="list"))):
        kind = value("survey", "lines", k, "kind", kind="string")
        if kind not in ("line", "tie"):
            raise SurveyError(f"{path}: the truth's survey.lines.{k}.kind must be line or "
                              f"tie, not {kind[:20]!r}")
        start = value("survey", "lines", k, "start_s", low=-1e6, high=1e7)
        value("survey", "lines", k, "end_s", low=start, high=1e7)


def _truth_local(survey, lat, lon, alt):
    origin = survey["origin"]
    north = (lat - origin["lat_deg"]) * METRES_PER_DEGREE
    east = (lon - origin["lon_deg"]) * METRES_PER_DEGREE * math.cos(
        math.radians(origin["lat_deg"]))
    return north, east, alt - origin["ground_alt_m"]


def score_against_truth(result, truth_path):
    """The result against the scenario's truth: the compensated scalar's residual in the box
    (against the noise floor), the levelled anomaly along the lines, and the grid and its
    peak against the true anomaly on the same nodes."""
    from ..sim.stimulus.geophysics import anomaly_total, diurnal_nT
    truth = read_truth(truth_path)
    survey = truth["survey"]
    start = _dt.datetime.fromisoformat(truth["timestamp"])
    day = start.replace(hour=0, minute=0, second=0, microsecond=0)
    offset = (start - day).total_seconds()            # t_log = offset + t_truth
    track = result.track
    north, east, up = _truth_local(survey, track.lat, track.lon, track.alt)
    true_anomaly = anomaly_total(survey, north, east, up)
    true_diurnal = diurnal_nT(survey, result.t - offset)
    if not (np.all(np.isfinite(true_anomaly[np.isfinite(north)]))
            and np.all(np.isfinite(true_diurnal))):
        raise SurveyError(f"{truth_path}: the truth's sources or diurnal give no finite field "
                          "along the flight (a source on the track?): cannot score against it")
    scalar = result.igrf + true_anomaly + true_diurnal
    box = (result.t >= result.box[0]) & (result.t <= result.box[1]) & np.isfinite(scalar)
    noise = float(truth["reference"]["cesium_noise_nT"])

    def rms_about_mean(x):
        x = x[np.isfinite(x)]
        return float(np.sqrt(np.mean((x - x.mean()) ** 2))) if x.size else math.nan

    scores = {"noise_floor_nT": noise,
              "box_residual_raw_nT": rms_about_mean((result.raw - scalar)[box]),
              "box_residual_compensated_nT": rms_about_mean((result.compensated - scalar)[box])}
    if result.deinterf is not None:
        scores["box_residual_deinterf_nT"] = rms_about_mean(
            (result.deinterf["compensated"] - scalar)[box])
    scores["box_residual_over_floor"] = (scores["box_residual_compensated_nT"] / noise
                                         if noise > 0 else None)
    on = result.on_lines()
    scores["line_anomaly_rms_nT"] = rms_about_mean((result.levelled - true_anomaly)[on])
    scores["line_anomaly_unlevelled_rms_nT"] = rms_about_mean(
        (result.anomaly - true_anomaly)[on])
    scores["true_anomaly_range_nT"] = [float(np.nanmin(true_anomaly[on])),
                                       float(np.nanmax(true_anomaly[on]))]
    # The grid against the truth on its own nodes at the lines' mean height.
    grid = result.grid
    values = grid["anomaly"].values
    gn, ge = np.meshgrid(grid["northing"].values, grid["easting"].values, indexing="ij")
    lat0, lon0 = track.origin
    lat = lat0 + gn / METRES_PER_DEGREE
    lon = lon0 + ge / (METRES_PER_DEGREE * math.cos(math.radians(lat0)))
    height = float(np.nanmean(track.alt[on]))
    tn, te, tu = _truth_local(survey, lat, lon, np.full(lat.shape, height))
    truth_grid = anomaly_total(survey, tn.ravel(), te.ravel(), tu.ravel()).reshape(gn.shape)
    inside = np.isfinite(values) & np.isfinite(truth_grid)
    if not inside.any():
        raise SurveyError(f"{truth_path}: the truth's sources give no finite field on the "
                          "map's nodes: cannot score against it")
    diff = values[inside] - truth_grid[inside]
    scores["grid_rms_nT"] = float(np.sqrt(np.mean((diff - diff.mean()) ** 2)))
    scores["grid_offset_nT"] = float(diff.mean())
    k = np.nanargmax(np.abs(np.where(inside, values, np.nan)))
    j = np.nanargmax(np.abs(np.where(inside, truth_grid, np.nan)))
    # A map's level is a datum (the base station's median, the box's mean interference):
    # the peak is measured above the grid's mean offset from the truth.
    offset = scores["grid_offset_nT"]
    scores["peak"] = {
        "recovered_nT": float(values.flat[k] - offset), "true_nT": float(truth_grid.flat[j]),
        "amplitude_ratio": float((values.flat[k] - offset) / truth_grid.flat[j]),
        "recovered_at_m": [float(gn.flat[k]), float(ge.flat[k])],
        "true_at_m": [float(gn.flat[j]), float(ge.flat[j])],
        "distance_m": float(math.hypot(gn.flat[k] - gn.flat[j], ge.flat[k] - ge.flat[j]))}
    # The sources in the map's frame (from the first GPS fix, not the scenario's site).
    site = survey["origin"]
    shift_n = (site["lat_deg"] - lat0) * METRES_PER_DEGREE
    shift_e = (site["lon_deg"] - lon0) * METRES_PER_DEGREE * math.cos(math.radians(lat0))
    scores["sources_local_m"] = [[float(d["north_m"]) + shift_n, float(d["east_m"]) + shift_e]
                                 for d in survey["dipoles"]]
    result.truth_grid = truth_grid
    return scores


# --- products and report -------------------------------------------------------------------

def _band_rms(result, series, mask):
    from .tolles_lawson import bandpass
    filtered = bandpass(series[mask], result.timing.rate_hz, result.tl.band)
    return float(np.sqrt(np.mean(filtered ** 2)))


def _compensation_figures(result):
    """Improvement ratio and figure of merit in the box, ours (both term counts) and
    deinterf's, on the same samples and the same band."""
    from .tolles_lawson import figure_of_merit, improvement_ratio
    box = (result.t >= result.box[0]) & (result.t <= result.box[1])
    t = result.t[box]
    band = result.tl.band
    segments = _segments(*result.box)
    rows = {}

    def row(name, compensated):
        rows[name] = {"improvement_ratio": float(improvement_ratio(
                          t, result.raw[box], compensated[box], band)),
                      "fom_nT": float(figure_of_merit(t, compensated[box], segments, band)),
                      "band_rms_nT": _band_rms(result, compensated, box)}
    row("uncompensated", result.raw)
    row(f"maglog TL{result.tl.terms}", result.compensated)
    other = result.raw - result.tl_other.predict(result.t, result.cosines, result.raw)
    row(f"maglog TL{result.tl_other.terms}", other)
    if result.deinterf is not None:
        row(f"deinterf TL{result.tl.terms}", result.deinterf["compensated"])
    return rows


def summary(result):
    """The report's figures as plain JSON values (on one BLAS thread, as :func:`survey_card`,
    so that they are the same everywhere)."""
    from threadpoolctl import threadpool_limits
    with threadpool_limits(1):
        return _summary(result)


def _summary(result):
    from .pipeline import jsonable
    on = result.on_lines()
    out = {"log": result.log_name, "date": result.date,
           "samples": int(len(result.t)), "samples_on_lines": int(on.sum()),
           "cesium_timing": result.timing.as_dict(),
           "box": {"start_utc": _tod(result.box[0]), "end_utc": _tod(result.box[1]),
                   "seconds": result.box[1] - result.box[0], "source": result.box_source},
           "tolles_lawson": result.tl.as_dict(),
           "tolles_lawson_other": result.tl_other.as_dict(),
           "compensation": _compensation_figures(result),
           "deinterf": None if result.deinterf is None else {
               k: v for k, v in result.deinterf.items() if k != "compensated"},
           "lines": [_line_dict(line) for line in result.lines],
           "lag": {k: v for k, v in result.lag.items() if k != "scan"},
           "levelling": result.levelling.as_dict(),
           "diurnal": None if result.diurnal is None else {
               "base_station": str(result.options.base_station),
               "range_nT": [float(np.nanmin(result.diurnal)),
                            float(np.nanmax(result.diurnal))]},
           "anomaly_nT": {"min": float(np.nanmin(result.levelled[on])),
                          "max": float(np.nanmax(result.levelled[on]))},
           "grid": result.grid_info,
           "vector_calibration": {
               "rms_before_nT": result.calibration.summary()["rms_before_nT"],
               "rms_after_nT": result.calibration.summary()["rms_after_nT"]},
           "warnings": list(result.warnings), "notes": list(result.notes),
           "cesium_noise": dict(result.noise), "times_s": result.times,
           "options": {k: (str(v) if isinstance(v, Path) else v)
                       for k, v in vars(result.options).items()}}
    from .gridding import peak
    out["peak"] = peak(result.grid).as_dict()
    if result.scores:
        out["truth"] = result.scores
    return jsonable(out)


def _line_dict(line):
    return {"kind": line.kind, "index": line.index, "start_utc": _tod(line.start),
            "end_utc": _tod(line.end), "seconds": line.end - line.start,
            "course_deg": getattr(line, "course_deg", None)}


def write_products(result, out_dir):
    """The products and the report into folder ``out_dir`` (:data:`SURVEY_FILES`); returns
    their paths by name. Files are written under temporary names and moved into place when
    all are written, so a failure leaves an earlier product as it was."""
    from .gridding import map_plot, to_utm, write_geotiff, write_netcdf
    from .pipeline import _discard, _html, _stage, check_output_dir
    out = check_output_dir(out_dir)
    staged = {}
    try:
        with _warnings.catch_warnings(), np.errstate(all="ignore"):
            _warnings.simplefilter("ignore")
            figures = summary(result)
            lat0, lon0 = result.track.origin
            utm = to_utm(result.grid, lat0, lon0)
            write_netcdf(utm, _stage(staged, out / "anomaly.nc"))
            write_geotiff(utm, _stage(staged, out / "anomaly.tif"))
            sources = figures.get("truth", {}).get("sources_local_m")
            map_plot(result.grid, _flown(result), _stage(staged, out / "map.png"),
                     sources=sources, title=f"Levelled total-field anomaly, {result.log_name}")
            _plot_compensation(result, _stage(staged, out / "compensation.png"))
            _plot_levelling(result, _stage(staged, out / "levelling.png"))
            _write_samples(result, _stage(staged, out / "samples.csv"))
            _stage(staged, out / "survey.json").write_text(
                json.dumps(figures, indent=1, allow_nan=False) + "\n")
            text = "\n".join(_report_lines(result, figures)) + "\n"
            _stage(staged, out / "report.md").write_text(text, encoding="utf-8")
            _stage(staged, out / "report.html").write_text(
                _html(text, f"Survey of {result.log_name}"), encoding="utf-8")
        for final, temp in staged.items():
            os.replace(temp, final)
    except OSError as error:
        raise SurveyError(f"{out}: cannot write the products: "
                          f"{error.strerror or error}") from None
    finally:
        _discard(staged)
    return {name: out / name for name in SURVEY_FILES}


def _flown(result):
    """The flown lines as (north, east) arrays for the map."""
    return [(result.track.north[(result.t >= line.start) & (result.t <= line.end)],
             result.track.east[(result.t >= line.start) & (result.t <= line.end)])
            for line in result.lines]


def _write_samples(result, path):
    on = result.on_lines()
    line_of = np.full(len(result.t), "", dtype=object)
    for line in result.lines:
        line_of[(result.t >= line.start) & (result.t <= line.end)] = \
            f"{line.kind}{line.index}"
    tr = result.track
    with open(path, "w", encoding="utf-8") as f:
        f.write("t_utc_s,lat_deg,lon_deg,alt_m,north_m,east_m,raw_nT,compensated_nT,"
                "igrf_nT,anomaly_nT,levelled_nT,line\n")
        for i in range(len(result.t)):
            f.write(f"{result.t[i]:.3f},{tr.lat[i]:.7f},{tr.lon[i]:.7f},{tr.alt[i]:.2f},"
                    f"{tr.north[i]:.2f},{tr.east[i]:.2f},{result.raw[i]:.3f},"
                    f"{result.compensated[i]:.3f},{result.igrf[i]:.3f},"
                    f"{result.anomaly[i]:.3f},{result.levelled[i]:.3f},"
                    f"{line_of[i] if on[i] else ''}\n")


def _plot_compensation(result, path):
    from .plotting import WIDE, figure, save
    from .tolles_lawson import bandpass
    box = (result.t >= result.box[0]) & (result.t <= result.box[1])
    t = result.t[box] - result.box[0]
    rate, band = result.timing.rate_hz, result.tl.band
    ours = bandpass(result.compensated[box], rate, band)
    theirs = (bandpass(result.deinterf["compensated"][box], rate, band)
              if result.deinterf is not None else None)
    name = f"maglog TL{result.tl.terms}"
    # Two panels: at the uncompensated signal's scale the compensated traces are a flat
    # line on top of each other; the lower panel zooms on them, ours wide and light below,
    # deinterf's thin and dashed on top, so that each shows where they agree.
    plt, fig, (ax, low) = figure(WIDE, 2, height_ratios=(3, 2))
    ax.plot(t, bandpass(result.raw[box], rate, band), lw=0.7, color="tab:blue",
            label="uncompensated")
    ax.plot(t, ours, lw=0.9, color="k", label=name)
    ax.set_ylabel("band-passed\ntotal field (nT)")
    ax.legend(loc="upper right", fontsize="small")
    ax.set_title("uncompensated against compensated", fontsize="medium")
    low.plot(t, ours, lw=2.2, color="0.6", label=f"{name}: {np.sqrt(np.mean(ours ** 2)):.3f} nT RMS")
    if theirs is not None:
        low.plot(t, theirs, lw=0.8, ls="--", color="tab:orange", zorder=3,
                 label=f"deinterf TL{result.tl.terms}: {np.sqrt(np.mean(theirs ** 2)):.3f} nT "
                       f"RMS; differs from ours by "
                       f"{np.sqrt(np.mean((theirs - ours) ** 2)):.3f} nT RMS")
    low.set_ylabel("compensated,\nzoomed (nT)")
    low.set_title("compensated only" + (": maglog and deinterf" if theirs is not None else ""),
                  fontsize="medium")
    low.legend(loc="upper right", fontsize="small")
    low.set_xlabel(f"seconds into the calibration box (from {_tod(result.box[0])} UTC)")
    fig.suptitle(f"Tolles–Lawson compensation in the calibration box "
                 f"(band-passed {band[0]:.2g}-{band[1]:.2g} Hz)")
    save(plt, fig, path)


def _plot_levelling(result, path):
    from .plotting import NARROW, figure, save
    lev = result.levelling.as_dict()
    plt, fig, ax = figure(NARROW)
    before = np.asarray([c[-1] for c in result.levelling.crossovers_before], float) \
        if hasattr(result.levelling, "crossovers_before") else None
    after = np.asarray([c[-1] for c in result.levelling.crossovers_after], float) \
        if hasattr(result.levelling, "crossovers_after") else None
    if before is not None and before.size:
        ax.plot(np.arange(1, before.size + 1), before, "o", label="before levelling")
    if after is not None and after.size:
        ax.plot(np.arange(1, after.size + 1), after, "x", label="after levelling")
    ax.axhline(0.0, color="k", lw=0.6)
    ax.set_xlabel("crossover number (one per line × tie line crossing)")
    ax.set_ylabel("line minus tie line (nT)")
    if lev["crossovers"]:
        ax.set_title(f"Crossovers: RMS {lev['rms_before_nT']:.2f} nT before levelling, "
                     f"{lev['rms_after_nT']:.2f} nT after")
        ax.legend(loc="upper right", fontsize="small")
    else:
        ax.set_title("No crossovers: not levelled")
    save(plt, fig, path)


def _report_lines(result, figures):
    comp = figures["compensation"]
    tlf = figures["tolles_lawson"]
    lines_ = [line for line in result.lines if line.kind == "line"]
    ties = [line for line in result.lines if line.kind == "tie"]
    out = [f"# Survey of {result.log_name}", "",
           f"- date {figures['date']}; {figures['samples']} cesium samples "
           f"({figures['samples_on_lines']} on lines), timed by "
           f"{result.timing.method} at {result.timing.rate_hz:.4f} Hz",
           f"- {len(lines_)} lines and {len(ties)} tie lines found",
           f"- calibration box {figures['box']['start_utc']}-{figures['box']['end_utc']} UTC "
           f"({figures['box']['seconds']:.0f} s, {result.box_source})",
           f"- vector magnetometer calibrated against the cesium: "
           f"{figures['vector_calibration']['rms_before_nT']:.1f} -> "
           f"{figures['vector_calibration']['rms_after_nT']:.2f} nT RMS", ""]
    if result.warnings:
        out += ["## Warnings: this result is not to be trusted", ""] + \
            [f"- **{warning}**" for warning in result.warnings] + [""]
    if result.notes:
        out += ["## Notes", ""] + [f"- {note}" for note in result.notes] + [""]
    out += ["## Tolles–Lawson compensation", "",
            f"Fitted on the calibration box with {tlf.get('terms')} terms, band "
            f"{result.tl.band[0]:.3g}-{result.tl.band[1]:.3g} Hz "
            f"({'given' if result.options.band else 'chosen from the manoeuvres'}), ridge "
            f"{tlf['ridge_alpha']:.3g} "
            f"({'by blocked cross-validation' if tlf['ridge_auto'] else 'given'}). "
            "Figures on the box's samples, band-passed in that band; the figure of merit "
            "sums the peak-to-peak over the box's twelve parts (four headings × roll, pitch, "
            "yaw).", ""]
    scores = figures.get("truth", {})
    head = "| series | improvement ratio | figure of merit (nT) | band RMS (nT) |"
    rule = "|---|---:|---:|---:|"
    if scores:
        head += " residual against the truth (nT) |"
        rule += "---:|"
    out += [head, rule]
    for name, row in comp.items():
        cells = (f"| {name} | {row['improvement_ratio']:.2f} | {row['fom_nT']:.2f} | "
                 f"{row['band_rms_nT']:.3f} |")
        if scores:
            key = {"uncompensated": "box_residual_raw_nT",
                   f"maglog TL{result.tl.terms}": "box_residual_compensated_nT",
                   f"deinterf TL{result.tl.terms}": "box_residual_deinterf_nT"}.get(name)
            value = scores.get(key) if key else None
            cells += f" {value:.3f} |" if value is not None else " |"
        out.append(cells)
    out.append("")
    if result.deinterf is not None:
        settings = result.deinterf.get("settings", {})
        text = "; ".join(_setting_text(k, v) for k, v in settings.items()) \
            if isinstance(settings, dict) else str(settings)
        out += [f"deinterf ({result.deinterf.get('version', '')}) on the same samples: "
                f"{text}.", ""]
    if scores and scores.get("box_residual_over_floor") is not None:
        out += [f"The noise floor (the cesium's own noise) is {scores['noise_floor_nT']:.3f} nT: "
                f"the compensated residual is {scores['box_residual_over_floor']:.1f} times it.",
                ""]
    lev = figures["levelling"]
    out += ["## Georeferencing, IGRF, diurnal, levelling", "",
            "Positions and altitudes from the GGA fixes interpolated to the cesium samples; "
            "the IGRF total field at each removed.",
            ("Diurnal: the base station's field (minus its median) removed, range "
             f"{figures['diurnal']['range_nT'][0]:.2f} to {figures['diurnal']['range_nT'][1]:.2f}"
             " nT." if figures["diurnal"] else
             "Diurnal: no base-station file; levelling takes out what it can."
             if lev["crossovers"] else
             "Diurnal: no base-station file and no tie lines: it stays in the map."),
            (f"Lag correction: positions taken {result.lag['lag_s']:.3f} s after the "
             "samples' times (" + ("given" if result.lag["source"] == "given" else
                                   "the lag that minimises the crossovers; the GGA line "
                                   "arrives after its fix") + ")."
             if result.lag["source"] not in ("none", "not found") else
             "Lag correction: none (not found: the crossovers are least at the edge of "
             "the scan)." if result.lag["source"] == "not found" else
             "Lag correction: none (no crossovers to estimate it from)."),
            (f"Levelling on {lev['crossovers']} crossovers: RMS "
             f"{lev['rms_before_nT']:.2f} nT before, {lev['rms_after_nT']:.2f} nT after."
             if lev["crossovers"] else "Not levelled: no tie line crosses the lines."), "",
            "![levelling](levelling.png)", "", "![compensation](compensation.png)", ""]
    pk = figures["peak"]
    out += ["## Map", "", "![map](map.png)", "",
            f"Anomaly along the lines {figures['anomaly_nT']['min']:.1f} to "
            f"{figures['anomaly_nT']['max']:.1f} nT.", "",
            *_grid_lines(figures["grid"], result.track.origin),
            f"Largest |anomaly| on the grid: {pk['amplitude_nT']:.1f} nT at "
            f"{pk['northing']:.0f} m north, {pk['easting']:.0f} m east of the first fix.", ""]
    if scores:
        p = scores["peak"]
        out += ["## Against the scenario's truth", "",
                f"- along the lines: levelled anomaly RMS {scores['line_anomaly_rms_nT']:.2f} nT "
                f"about its mean (before levelling {scores['line_anomaly_unlevelled_rms_nT']:.2f} "
                f"nT); true anomaly {scores['true_anomaly_range_nT'][0]:.1f} to "
                f"{scores['true_anomaly_range_nT'][1]:.1f} nT",
                f"- grid: RMS {scores['grid_rms_nT']:.2f} nT against the true anomaly on its "
                f"nodes (offset {scores['grid_offset_nT']:.2f} nT)",
                f"- peak (above the grid's offset): {p['recovered_nT']:.1f} nT recovered against {p['true_nT']:.1f} nT "
                f"true (ratio {p['amplitude_ratio']:.3f}), {p['distance_m']:.1f} m apart", ""]
    utm = _utm_name(result.track.origin)
    out += ["## Files", "", f"anomaly.nc (NetCDF) and anomaly.tif (GeoTIFF): the grid "
            f"resampled onto {utm}; map.png, samples.csv (every cesium sample through each "
            "step: latitude and longitude in WGS 84, north and east in local metres) and "
            "survey.json (these figures): local metres from the first fix.", ""]
    return out


_UNITS = {"_hz": "Hz", "_m": "m", "_s": "s", "_nT": "nT", "_deg": "°"}


def _setting_text(key, value):
    """One setting as words: ``band_hz [0.1, 0.6]`` reads "band 0.1-0.6 Hz"."""
    unit = next((u for suffix, u in _UNITS.items() if key.endswith(suffix)), "")
    name = key[:len(key) - len(next(s for s in _UNITS if key.endswith(s)))] if unit else key
    if isinstance(value, (list, tuple)):
        value = "-".join(f"{v:g}" if isinstance(v, (int, float)) else str(v) for v in value)
    elif isinstance(value, float):
        value = f"{value:g}"
    return f"{name.replace('_', ' ')} {value}" + (f" {unit}" if unit else "")


def _utm_name(origin):
    """The UTM zone the products are written in, e.g. "WGS 84 / UTM zone 32N (EPSG:32632)"."""
    from .gridding import utm_epsg
    try:
        epsg = utm_epsg(*origin)
    except SurveyError:
        return "UTM (no zone at the first fix)"
    zone, hemisphere = epsg % 100, "N" if epsg < 32700 else "S"
    return f"WGS 84 / UTM zone {zone}{hemisphere} (EPSG:{epsg})"


def _grid_lines(grid, origin):
    """The grid's description (:func:`~maglog.calib.gridding.grid_summary`) as sentences
    with units: how it was made, how well it fits, and which coordinates it is in."""
    method = {"spline": "verde's bi-harmonic spline",
              "eqs": "harmonica's equivalent sources"}.get(grid.get("method"),
                                                        str(grid.get("method")))
    if grid.get("eqs_depth_m") is not None:
        method += f" at {grid['eqs_depth_m']:.0f} m depth"
    damping = grid.get("damping")
    rows, columns = grid.get("shape", (0, 0))
    lat0, lon0 = origin
    crs = grid.get("crs", "local")
    where = (f"local metres north and east of the first fix ({abs(lat0):.5f}° "
             f"{'N' if lat0 >= 0 else 'S'}, {abs(lon0):.5f}° {'E' if lon0 >= 0 else 'W'}), "
             "on a flat earth" if crs == "local" else crs)
    return [f"Grid: {method}, {'undamped' if damping is None else f'damping {damping:.3g}'}, "
            f"{grid['spacing_m']:.3g} m spacing ({rows} × {columns} nodes), from "
            f"{grid['n_data']:,} samples reduced to {grid['n_blocks']:,} block medians of "
            f"{grid['block_m']:.3g} m; lines {grid['line_spacing_m']:.3g} m apart; nodes "
            f"farther than {grid['mask_m']:.3g} m from a sample blanked "
            f"({grid['coverage']:.0%} kept); misfit {grid['misfit_rms_nT']:.2f} nT RMS at "
            "the samples.",
            f"The grid, the map and the peak below are in {where}; anomaly.nc and "
            f"anomaly.tif hold it resampled onto {_utm_name(origin)}.", ""]
