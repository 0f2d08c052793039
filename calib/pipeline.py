"""From a card image to calibrated parameters and a report.

card image (or partition image, or plain log) → LOG*.TXT → parsed streams → magnetometer
samples with a reference total field (cesium, IGRF at the GPS position and date, or a
constant) → scalar calibration (PSO + LM, or LM) or an ellipsoid fit → heading (IGRF
declination; alignment to GPS course over ground on straight, level legs; errors against a
known attitude when one is given) → report.
"""

import dataclasses
import datetime
import json
import math
import numbers
import os
import shutil
import tempfile
import warnings as _warnings
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from .card import read_logs
from . import scalar as _scalar
from .coverage import RULE, check_bound, judge_coverage
from .ellipsoid import fit_ellipsoid
from .heading import (align_heading, straight_legs, tilt_compensated_heading, true_heading,
                      wrap_degrees)
from .logparse import parse_log, to_arrays
from .holdout import held_out
from .noise import allan_deviation
from .scalar import OBJECTIVES, PARAMETERS, apply_scalar, calibrate_scalar
from .screen import screen_reference, screen_samples


__all__ = ["CalibrationError", "ReportError", "CalibrationRun", "HeadingAnalysis",
           "REFERENCE_RANGE_NT", "SEED_RANGE", "IGRF_DATES", "ALTITUDE_RANGE_M",
           "check_reference", "check_seed", "check_output_dir", "calibrate_card",
           "read_attitude", "write_report", "report_files"]

ATTITUDE_COLUMNS = ("t", "roll_deg", "pitch_deg", "heading_deg")

METHODS = ("pso", "lm", "ellipsoid")

#: The total fields the design calibrates against, nT (inclusive). Earth's field is about
#: 20,000-70,000 nT at the surface; the range is generous (a survey near a strong anomaly,
#: a laboratory coil) but physical: below it a "field" is an offset or a unit mistake
#: (``--ref 5`` gave K ~ 1e-4 and "converged"), above it no magnetometer of this kind
#: reads and the squares lose precision (``--ref 1e308`` ended in LinAlgError).
REFERENCE_RANGE_NT = (1_000.0, 1_000_000.0)
#: PSO seeds accepted (inclusive). numpy's ``default_rng`` takes any non-negative integer
#: (it raises ValueError for negative ones); the cap keeps a seed to 39 digits, printable
#: in a report and comparable between runs.
SEED_RANGE = (0, 2**128 - 1)
#: The dates IGRF-14 (ppigrf's coefficients) defines: its models start in 1900 and its
#: secular variation ends in 2030. Outside it the field is an extrapolation nobody made.
IGRF_DATES = (datetime.date(1900, 1, 1), datetime.date(2030, 1, 1))
#: GPS altitudes (m above mean sea level) at which IGRF is used for an airborne survey:
#: the deepest land and sea surface to the top of a sounding balloon's flight. A fix outside
#: is a receiver's error, not a place to evaluate a main-field model.
ALTITUDE_RANGE_M = (-1_000.0, 100_000.0)
#: The magnetometer's median |B| may differ from the reference's by at most this factor
#: (a strong hard iron moves it, a unit mistake moves it by 1000).
SCALE_MISMATCH = 10.0
#: A residual RMS above this share of the field is reported as a poor fit.
POOR_FIT_FRACTION = 0.01
#: A sample whose residual is this many robust standard deviations (1.4826 MAD) from the
#: median, and at least OUTLIER_FLOOR_NT, is reported as an outlier.
OUTLIER_SIGMAS = 10.0
OUTLIER_FLOOR_NT = 10.0
#: Free space a report needs: its plots and text (a few hundred KiB) with a margin.
REPORT_SPACE_BYTES = 4 << 20


class CalibrationError(Exception):
    """The data cannot be calibrated as asked (said why)."""


class ReportError(CalibrationError):
    """The report folder cannot be written (said where and why, one line)."""


def check_reference(value):
    """The reference as :func:`calibrate_card` takes it: ``"cesium"``, ``"igrf"``, or a
    total field in nT (a number, or its text) within :data:`REFERENCE_RANGE_NT`.
    Returns the name or the float; raises :class:`CalibrationError` saying why not."""
    if isinstance(value, str):
        if value in ("cesium", "igrf"):
            return value
        try:
            number = float(value)
        except ValueError:
            raise CalibrationError(f"reference must be cesium, igrf or a total field in nT, "
                                   f"not {value!r}") from None
    elif isinstance(value, numbers.Real) and not isinstance(value, bool):
        number = float(value)
    else:
        raise CalibrationError(f"reference must be cesium, igrf or a total field in nT, not "
                               f"{value!r}")
    low, high = REFERENCE_RANGE_NT
    if not low <= number <= high:       # NaN fails too
        raise CalibrationError(f"a reference field must be {low:,.0f}..{high:,.0f} nT (Earth's "
                               f"field is about 20,000-70,000 nT), not {value!r}")
    return number


def check_seed(value):
    """The PSO seed: an integer (or its text) within :data:`SEED_RANGE`; raises
    :class:`CalibrationError` saying why not."""
    low, high = SEED_RANGE
    if isinstance(value, str):
        text = value.strip()
        digits = text.lstrip("+-")
        if not digits.isdigit() or len(digits) > len(str(high)):
            raise CalibrationError(f"a seed must be an integer {low}..2**128-1, not {value!r}")
        number = int(text)
    elif isinstance(value, numbers.Integral) and not isinstance(value, bool):
        number = int(value)
    else:
        raise CalibrationError(f"a seed must be an integer {low}..2**128-1, not {value!r}")
    if not low <= number <= high:
        raise CalibrationError(f"a seed must be an integer {low}..2**128-1, not {value!r}")
    return number


def check_output_dir(path):
    """Make sure a report can be written into folder ``path`` before any work is done:
    creates it (and its parents) when missing, writes and removes a probe file, and checks
    the free space. Returns the folder as a Path; raises :class:`ReportError` (one line)."""
    out = Path(path)
    try:
        out.mkdir(parents=True, exist_ok=True)
    except FileExistsError:
        raise ReportError(f"{out}: exists and is not a folder (the report needs a folder)") \
            from None
    except OSError as error:
        raise ReportError(f"{out}: cannot create the report folder: "
                          f"{_reason(error)}") from None
    if not out.is_dir():
        raise ReportError(f"{out}: is not a folder (the report needs a folder)")
    try:
        with tempfile.NamedTemporaryFile(dir=out, prefix=".maglog-probe-") as probe:
            probe.write(b"maglog")
            probe.flush()
        free = shutil.disk_usage(out).free
    except OSError as error:
        raise ReportError(f"{out}: cannot write into the report folder: "
                          f"{_reason(error)}") from None
    if free < REPORT_SPACE_BYTES:
        raise ReportError(f"{out}: only {free // 1024} KiB free; a report needs about "
                          f"{REPORT_SPACE_BYTES >> 20} MiB")
    return out


def _reason(error):
    return error.strerror or str(error) or type(error).__name__


@dataclass
class CalibrationRun:
    log_name: str
    t: np.ndarray
    b: np.ndarray
    r: np.ndarray
    reference: str
    method: str
    result: object
    parsed: object
    vectors: np.ndarray        # calibrated field vectors (N, 3), nT
    heading: "HeadingAnalysis"
    notes: list = field(default_factory=list)   # what the pipeline left out or assumed
    screens: dict = field(default_factory=dict)  # name -> calib.screen.ScreenResult
    fitted: np.ndarray = None  # bool per sample: screened in and kept by the robust loss
    held_out: object = None    # calib.holdout.HeldOut, or None (``held_out_note`` says why)
    held_out_note: str = ""
    coverage: object = None    # calib.coverage.CoverageVerdict: the one verdict

    @property
    def verdict(self):
        """"determined", "undetermined" or "failed" (:mod:`.coverage`)."""
        return self.coverage.verdict

    @property
    def success(self):
        """True only when the fit succeeded and determines every parameter."""
        return self.coverage.success

    @property
    def calibrated(self):
        """|calibrated field|, nT."""
        return np.linalg.norm(self.vectors, axis=1)

    @property
    def residual(self):
        return self.calibrated - self.r

    @property
    def warnings(self):
        """Everything the user must know about this result: the pipeline's notes (samples
        left out, dates assumed), then the fit's warnings (not converged, at a bound, poorly
        determined)."""
        fit = list(getattr(self.result, "warnings", []))
        if self.coverage is not None:
            # The verdict on what the flight determines is calib.coverage's alone: the
            # scalar fit's own wording of it (by its dilution of precision) is left out.
            words = getattr(_scalar, "_coverage_warnings", None)
            res = self.result
            if words is not None and getattr(res, "dop", None) is not None:
                own = set(words(res.dop, res.determined, res.held))
                fit = [w for w in fit if w not in own]
            if self.coverage.verdict != "determined":
                fit.insert(0, self.coverage.message)
        return list(self.notes) + fit

    def summary(self):
        raw = np.linalg.norm(self.b, axis=1) - self.r
        fitted = np.ones(len(self.b), bool) if self.fitted is None else self.fitted
        out = {"log": self.log_name, "samples": int(len(self.b)), "reference": self.reference,
               "method": self.method,
               "rms_before_nT": float(np.sqrt(np.mean(raw ** 2))),
               "rms_after_nT": float(np.sqrt(np.mean(self.residual ** 2))),
               "samples_fitted": int(fitted.sum()),
               "rms_after_fitted_nT": float(np.sqrt(np.mean(self.residual[fitted] ** 2))),
               "held_out": None if self.held_out is None else self.held_out.as_dict(),
               "held_out_note": self.held_out_note or None,
               "screening": {name: screen.as_dict() for name, screen in self.screens.items()},
               "log_report": jsonable(vars(self.parsed.report))}
        if self.method == "ellipsoid":
            res = self.result
            out.update(fit=res.method, center_nT=res.center.tolist(), W=res.W.tolist(),
                       W_eigenvalues=np.linalg.eigvalsh(res.W).tolist(),
                       K=res.K.tolist(), c=res.c.tolist(),
                       parameters=dict(zip(PARAMETERS, res.x.tolist())),
                       uncertainties=dict(zip(PARAMETERS, res.uncertainties.tolist())),
                       coverage=res.coverage.report(), message=res.message)
        else:
            out.update(self.result.as_dict())
        if self.coverage is not None:
            # One verdict: success, verdict, the gate and the undetermined parameters all
            # from calib.coverage (the scalar fit's own "success" is its convergence).
            gate = self.coverage.as_dict()
            out["fit_converged"] = bool(self.coverage.fit_ok)
            out.update(success=self.coverage.success, verdict=self.coverage.verdict,
                       verdict_message=self.coverage.message, coverage_gate=gate,
                       undetermined=gate["undetermined"],
                       held_to_prior=gate["held_to_prior"],
                       determination={k: gate[k] for k in (
                           "rule", "bound_nT", "bound_source", "noise_nT", "sigma_nT",
                           "determined")})
        out["warnings"] = self.warnings
        if self.heading is not None:
            out["heading"] = self.heading.as_dict(self.t)
        return out


@dataclass
class HeadingAnalysis:
    """Headings from the calibrated field, and how well they are known."""
    declination: float          # degrees east (NaN: no GPS position, headings magnetic)
    declination_source: str
    heading: np.ndarray         # degrees 0..360 per sample, before alignment
    attitude: bool              # True: tilt-compensated with a known attitude
    legs: list                  # straight, level legs (heading.Leg)
    alignment: object           # heading.HeadingAlignment or None
    reference: np.ndarray = None    # the attitude file's heading per sample (degrees)
    messages: list = field(default_factory=list)

    @property
    def aligned(self):
        return self.heading if self.alignment is None else self.alignment.apply(self.heading)

    def errors(self):
        """Heading error against the known attitude, before and after the alignment."""
        if self.reference is None:
            return None, None
        return (wrap_degrees(self.heading - self.reference),
                wrap_degrees(self.aligned - self.reference))

    def on_legs(self, t):
        """Which samples (at times ``t``) lie on the straight, level legs."""
        inside = np.zeros(len(t), dtype=bool)
        for leg in self.legs:
            inside |= (t >= leg.start) & (t <= leg.end)
        return inside

    def as_dict(self, t=None):
        out = {"declination_deg": None if np.isnan(self.declination) else self.declination,
               "declination_source": self.declination_source,
               "attitude_known": self.attitude, "legs_found": len(self.legs),
               "alignment": None if self.alignment is None else self.alignment.as_dict(),
               "messages": list(self.messages)}
        before, after = self.errors()
        if before is not None:
            good = np.isfinite(before)
            out["error_rms_deg"] = {
                "before_alignment": float(np.sqrt(np.mean(before[good] ** 2))),
                "after_alignment": float(np.sqrt(np.mean(after[good] ** 2))),
                "samples": int(good.sum())}
            if t is not None and self.legs:
                legs = good & self.on_legs(t)
                out["error_rms_deg"].update(
                    legs_before_alignment=float(np.sqrt(np.mean(before[legs] ** 2))),
                    legs_after_alignment=float(np.sqrt(np.mean(after[legs] ** 2))),
                    legs_samples=int(legs.sum()))
        return out


def jsonable(value):
    """Plain JSON values: NaN and infinities become null (JSON has neither; a bare NaN
    made parameters.json unreadable to strict parsers)."""
    if isinstance(value, dict):
        return {str(k): jsonable(v) for k, v in value.items()}
    if isinstance(value, (list, tuple, np.ndarray)):
        return [jsonable(v) for v in value]
    if isinstance(value, (bool, np.bool_)):
        return bool(value)
    if isinstance(value, (np.integer,)):
        return int(value)
    if isinstance(value, (float, np.floating)):
        return float(value) if math.isfinite(value) else None
    if isinstance(value, (datetime.date, datetime.datetime)):
        return value.isoformat()
    return value


def _axis(parsed_t, lines):
    """Times if every one is known, else the line numbers (arrival order)."""
    return parsed_t if np.all(np.isfinite(parsed_t)) else lines.astype(float)


def _igrf_date(parsed):
    """The date IGRF is evaluated at, and what the report says about it; CalibrationError
    when the log's date lies outside :data:`IGRF_DATES`."""
    date = parsed.date or datetime.date(2026, 1, 1)
    first, last = IGRF_DATES
    if not first <= date < last:
        raise CalibrationError(f"the log's date {date.isoformat()} (from its ZDA) is outside "
                               f"IGRF-14's {first.year}-{last.year}")
    dated = "" if parsed.date else " (no ZDA date: 2026-01-01 assumed)"
    return datetime.datetime(date.year, date.month, date.day), dated


def _igrf_fixes(parsed, notes):
    """GGA fixes IGRF may be evaluated at: a fix, a finite position and an altitude within
    :data:`ALTITUDE_RANGE_M` (the others are left out, and said)."""
    gga = parsed.gga
    fixed = (gga.quality > 0) & np.isfinite(gga.lat) & np.isfinite(gga.lon)
    low, high = ALTITUDE_RANGE_M
    with np.errstate(invalid="ignore"):
        plausible = (gga.altitude >= low) & (gga.altitude <= high)
    good = fixed & plausible
    dropped = int(np.count_nonzero(fixed & ~plausible))
    if dropped:
        notes.append(f"{dropped} of {int(fixed.sum())} GPS fixes have no altitude or one "
                     f"outside {low:,.0f}..{high:,.0f} m: left out of IGRF")
    return good


def _cesium_in_range(parsed, notes):
    """The parsed log with the cesium readings outside :data:`REFERENCE_RANGE_NT` left out
    (0 nT: the sensor had no lock), said in ``notes``."""
    ces = parsed.cesium
    low, high = REFERENCE_RANGE_NT
    good = (ces.field >= low) & (ces.field <= high)
    if np.all(good):
        return parsed
    bad = ces.field[~good]
    values = ", ".join(f"{v:g}" for v in np.unique(bad)[:3])
    if not np.any(good):
        raise CalibrationError(f"{parsed.name}: every cesium reading is outside "
                               f"{low:,.0f}..{high:,.0f} nT ({values} nT: no lock?); use "
                               "--ref igrf or a value")
    notes.append(f"{int(bad.size)} of {len(ces)} cesium readings outside "
                 f"{low:,.0f}..{high:,.0f} nT ({values} nT: no lock?) left out of the "
                 "reference")
    kept = type(ces)(ces.line[good], ces.field[good], ces.signal[good], ces.t[good])
    return dataclasses.replace(parsed, cesium=kept)


def _screen_cesium(parsed, screens):
    """The parsed log with the cesium readings :func:`~maglog.calib.screen.screen_reference`
    finds implausible left out (outside the Earth's range, isolated spikes such as a bit
    flip); the screen's result goes into ``screens``."""
    ces = parsed.cesium
    if len(ces) == 0:
        return parsed
    times = ces.t if np.all(np.isfinite(ces.t)) else ces.line.astype(float)
    screen = screen_reference(times, ces.field)
    screens["reference"] = screen
    if screen.n_rejected == 0:
        return parsed
    good = screen.keep
    kept = type(ces)(ces.line[good], ces.field[good], ces.signal[good], ces.t[good])
    return dataclasses.replace(parsed, cesium=kept)


def _reference(parsed, ref, mag_axis, use_time, notes, screens):
    mag = parsed.mag
    if not isinstance(ref, str):
        value = check_reference(ref)
        return np.full(len(mag), value), f"constant {value:g} nT"
    if ref == "cesium":
        parsed = _cesium_in_range(parsed, notes)
        parsed = _screen_cesium(parsed, screens)
        ces = parsed.cesium
        if len(ces) < 2:
            raise CalibrationError(f"{parsed.name}: fewer than 2 cesium samples; use --ref "
                                   "igrf or a value")
        if use_time:
            # The parser's interpolation: NaN outside the cesium span and across dropouts.
            return to_arrays(parsed).cesium, "cesium magnetometer"
        return (np.interp(mag_axis, ces.line.astype(float), ces.field, left=np.nan,
                          right=np.nan), "cesium magnetometer (by arrival order: no GPS time)")
    if ref == "igrf":
        import ppigrf
        gga = parsed.gga
        if not np.any(gga.quality > 0):
            raise CalibrationError(f"{parsed.name}: no GGA with a fix: IGRF needs a position")
        try:
            when, dated = _igrf_date(parsed)
        except CalibrationError as error:
            raise CalibrationError(f"{parsed.name}: {error}; use --ref cesium or a value") \
                from None
        good = _igrf_fixes(parsed, notes)
        if not np.any(good):
            raise CalibrationError(f"{parsed.name}: no GPS fix with a position and a plausible "
                                   "altitude "
                                   f"({ALTITUDE_RANGE_M[0]:,.0f}..{ALTITUDE_RANGE_M[1]:,.0f} m): "
                                   "IGRF needs one")
        east, north, up = ppigrf.igrf(gga.lon[good], gga.lat[good],
                                      gga.altitude[good] / 1000.0, when)
        total = np.sqrt(np.ravel(east) ** 2 + np.ravel(north) ** 2 + np.ravel(up) ** 2)
        axis = gga.t[good] if use_time else gga.line[good].astype(float)
        # np.interp needs increasing abscissae: fixes whose time went back are left out.
        axis, first = np.unique(axis, return_index=True)
        return (np.interp(mag_axis, axis, total[first]),
                f"IGRF-14 at the GPS position, {when:%Y-%m-%d}{dated}")
    return check_reference(ref), None       # raises: not a reference


def read_attitude(path):
    """An attitude file: CSV with a header naming at least ``t, roll_deg, pitch_deg,
    heading_deg`` (any order, more columns ignored); ``t`` in seconds on the log's time
    base (since 00:00 UTC of the log's date), strictly increasing; true heading. Returns a
    dict of arrays (roll and pitch in radians, heading in degrees)."""
    path = Path(path)
    try:
        text = path.read_text(encoding="ascii")
    except FileNotFoundError:
        raise CalibrationError(f"{path}: no such attitude file") from None
    except (OSError, UnicodeDecodeError) as error:
        raise CalibrationError(f"{path}: cannot read the attitude file: {error}") from None
    lines = [(n, line.strip()) for n, line in enumerate(text.splitlines(), 1) if line.strip()]
    if not lines:
        raise CalibrationError(f"{path}: the attitude file is empty")
    header = [name.strip() for name in lines[0][1].split(",")]
    missing = [name for name in ATTITUDE_COLUMNS if name not in header]
    if missing:
        raise CalibrationError(f"{path}:{lines[0][0]}: the header lacks "
                               f"{', '.join(missing)} (need {', '.join(ATTITUDE_COLUMNS)})")
    index = [header.index(name) for name in ATTITUDE_COLUMNS]
    rows = []
    for n, line in lines[1:]:
        cells = line.split(",")
        if len(cells) != len(header):
            raise CalibrationError(f"{path}:{n}: {len(cells)} fields, the header has "
                                   f"{len(header)}")
        try:
            values = [float(cells[i]) for i in index]
        except ValueError:
            raise CalibrationError(f"{path}:{n}: not a number in {line!r}") from None
        if not all(np.isfinite(values)):
            raise CalibrationError(f"{path}:{n}: not a finite number in {line!r}")
        rows.append(values)
    if len(rows) < 2:
        raise CalibrationError(f"{path}: the attitude file needs at least 2 rows")
    data = np.array(rows)
    bad = np.flatnonzero(np.diff(data[:, 0]) <= 0)
    if bad.size:
        raise CalibrationError(f"{path}: t must increase (row {bad[0] + 2} of the data is "
                               f"not after the one before)")
    return {"t": data[:, 0], "roll": np.radians(data[:, 1]),
            "pitch": np.radians(data[:, 2]), "heading": data[:, 3] % 360.0}


def _declination(parsed):
    import ppigrf
    gga = parsed.gga
    fixed = (gga.quality > 0) & np.isfinite(gga.lat) & np.isfinite(gga.lon)
    if not np.any(fixed):
        return np.nan, "no GPS fix: headings are magnetic"
    try:
        when, dated = _igrf_date(parsed)
    except CalibrationError as error:
        return np.nan, f"{error}: headings are magnetic"
    notes = []
    plausible = _igrf_fixes(parsed, notes)
    lat, lon = float(np.mean(gga.lat[fixed])), float(np.mean(gga.lon[fixed]))
    # The declination hardly depends on the altitude: without a plausible one, sea level.
    altitude = float(np.mean(gga.altitude[plausible])) if np.any(plausible) else 0.0
    east, north, _ = ppigrf.igrf(lon, lat, altitude / 1000.0, when)
    value = float(np.degrees(np.arctan2(np.ravel(east)[0], np.ravel(north)[0])))
    dated = dated.replace(" (", ", ").rstrip(")")
    left_out = f"; {notes[0]}" if notes else ""
    return value, (f"IGRF-14 at {lat:.5f}, {lon:.5f}, {altitude:.0f} m, "
                   f"{when:%Y-%m-%d}{dated}{left_out}")


def _heading(parsed, t, use_time, vectors, attitude):
    """Heading analysis of the calibrated vectors at times ``t``."""
    decl, source = _declination(parsed)
    messages = []
    reference = None
    if attitude is not None:
        if not use_time:
            raise CalibrationError("an attitude file needs GPS time in the log, which has "
                                   "none")
        inside = (t >= attitude["t"][0]) & (t <= attitude["t"][-1])
        if not np.any(inside):
            raise CalibrationError(
                f"the attitude file's times ({attitude['t'][0]:.1f}..{attitude['t'][-1]:.1f} "
                f"s) do not overlap the log's ({t[0]:.1f}..{t[-1]:.1f} s since 00:00 UTC)")
        roll = np.where(inside, np.interp(t, attitude["t"], attitude["roll"]), np.nan)
        pitch = np.where(inside, np.interp(t, attitude["t"], attitude["pitch"]), np.nan)
        unwrapped = np.degrees(np.unwrap(np.radians(attitude["heading"])))
        reference = np.where(inside, np.interp(t, attitude["t"], unwrapped) % 360.0, np.nan)
        if not np.all(inside):
            messages.append(f"{int((~inside).sum())} samples lie outside the attitude file's "
                            "time span: no heading for them")
    else:
        roll = pitch = np.zeros(len(t))
        messages.append("no attitude given: headings assume level flight (roll = pitch = 0), "
                        "good on straight, level legs only")
    magnetic = tilt_compensated_heading(vectors, roll, pitch)
    heading = magnetic if np.isnan(decl) else true_heading(magnetic, decl)
    legs, alignment = [], None
    vtg = parsed.vtg
    if not use_time:
        messages.append("no GPS time: no alignment to the course over ground")
    elif len(vtg) < 2:
        messages.append("no VTG course over ground in the log: heading not aligned")
    elif np.isnan(decl):
        messages.append("no declination: heading not aligned to the (true) course")
    else:
        legs = straight_legs(vtg.t, vtg.course, vtg.speed, altitude_t=parsed.gga.t,
                             altitude=parsed.gga.altitude)
        alignment = align_heading(t, heading, legs)
        if alignment is None:
            messages.append("no straight, level leg found: heading not aligned")
    return HeadingAnalysis(declination=decl, declination_source=source, heading=heading,
                           attitude=attitude is not None, legs=legs, alignment=alignment,
                           reference=reference, messages=messages)


def calibrate_card(path, *, ref="cesium", method="pso", seed=0, attitude=None,
                   objective="eiv", determined_nt=None, mag_lag=0.0, ref_lag=0.0):
    """Calibrate the largest log on a card image (or partition image, or plain log).
    ``mag_lag`` and ``ref_lag`` (seconds) undo a first-order lag of the magnetometer's
    axes or of the reference before the fit (:func:`~maglog.calib.bias.undo_lag`).
    ``attitude`` is an optional attitude file (:func:`read_attitude`); ``objective`` is the
    scalar fit's (:func:`~maglog.calib.scalar.calibrate_scalar`: "eiv" or "paper");
    ``determined_nt`` the bound on a determined parameter's 1-sigma in nT of field (None:
    the noise of one sample; :mod:`.coverage`). The run's :attr:`CalibrationRun.verdict`
    says whether the flight determines every parameter.

    Bad input ends in a :class:`CalibrationError` (or :class:`~maglog.calib.card.CardError`
    from the card reader) that says what is wrong and where; a result that is usable but
    doubtful (not converged, samples left out, a date assumed) lists why in
    :attr:`CalibrationRun.warnings`. Nothing is printed."""
    ref = check_reference(ref)
    seed = check_seed(seed)
    if method not in METHODS:
        raise CalibrationError(f"method must be one of {', '.join(METHODS)}, not {method!r}")
    if objective not in OBJECTIVES:
        raise CalibrationError(f"objective must be one of {', '.join(OBJECTIVES)}, not "
                               f"{objective!r}")
    try:
        determined_nt = check_bound(determined_nt)
    except ValueError as error:
        raise CalibrationError(str(error)) from None
    from .bias import check_lag
    try:
        lags = (check_lag(mag_lag, "magnetometer's lag"), check_lag(ref_lag, "reference's lag"))
    except ValueError as error:
        raise CalibrationError(str(error)) from None
    attitude = None if attitude is None else read_attitude(attitude)
    with _warnings.catch_warnings(), np.errstate(all="ignore"):
        # Library warnings (numpy on a degenerate stretch, matplotlib) are not the user's
        # business: whatever matters is in the result's warnings.
        _warnings.simplefilter("ignore")
        return _calibrate(path, ref, method, seed, attitude, objective, determined_nt,
                          lags)


def _calibrate(path, ref, method, seed, attitude, objective, determined_nt=None,
               lags=(0.0, 0.0)):
    logs = read_logs(path)
    if not logs:
        raise CalibrationError(f"{path}: no LOG*.TXT file found")
    name, data = max(logs, key=lambda item: len(item[1]))
    notes = []
    data = _skip_erased(data, notes)
    parsed = parse_log(data, name=name)
    mag = parsed.mag
    if len(mag) < len(PARAMETERS) + 1:
        raise CalibrationError(f"{name}: only {len(mag)} magnetometer samples; at least "
                               f"{len(PARAMETERS) + 1} are needed")
    notes += _saturation(name, mag.b)
    use_time = bool(np.all(np.isfinite(mag.t)))
    mag_axis = mag.t if use_time else mag.line.astype(float)
    screens = {}
    r, reference = _reference(parsed, ref, mag_axis, use_time, notes, screens)
    keep = np.isfinite(r)
    if keep.sum() < len(PARAMETERS) + 1:
        raise CalibrationError(f"{name}: the reference covers only {int(keep.sum())} "
                               f"magnetometer samples")
    b, r = mag.b[keep], r[keep]
    t = mag.t[keep] if use_time else mag_axis[keep]
    if any(lags):
        from .bias import undo_lag
        if not use_time:
            raise CalibrationError(f"{name}: undoing a lag needs the samples' times, and "
                                   "this log has no GPS time")
        b, r = undo_lag(b, t, lags[0]), undo_lag(r, t, lags[1])
        notes.append(f"lags undone before the fit: magnetometer {1e3 * lags[0]:g} ms, "
                     f"reference {1e3 * lags[1]:g} ms (first-order)")
    _check_scale(name, b, r)
    screen = screen_samples(t, b, r)
    screens["samples"] = screen
    allowed = screen.keep
    if allowed.sum() < len(PARAMETERS) + 1:
        raise CalibrationError(f"{name}: only {int(allowed.sum())} plausible magnetometer "
                               f"samples ({screen.summary()})")
    try:
        fit = _fitter(b, r, method, seed, objective)
        result, residual_of = fit(allowed)
        if method == "ellipsoid":
            vectors = (b - result.center) @ result.W.T
            fitted = allowed
        else:
            vectors = apply_scalar(result.K, result.c, b)
            fitted = result.kept
    except ValueError as error:
        # The fits' own checks of what samples can determine (a stuck axis, too few
        # distinct vectors): said with the log's name.
        raise CalibrationError(f"{name}: {error}") from None
    except np.linalg.LinAlgError as error:
        raise CalibrationError(f"{name}: the {method} fit is numerically singular ({error}): "
                               "the samples do not determine it") from None
    if not np.all(np.isfinite(vectors)):
        raise CalibrationError(f"{name}: the {method} fit gave no finite calibration")
    run = CalibrationRun(log_name=name, t=t, b=b, r=r, reference=reference, method=method,
                         result=result, parsed=parsed, vectors=vectors,
                         heading=_heading(parsed, t, use_time, vectors, attitude), notes=notes,
                         screens=screens, fitted=fitted)
    for screen in screens.values():
        if screen.n_rejected:
            notes.append(f"screening: {screen.summary()}")
    run.coverage = judge_coverage(result, b, field_nt=float(np.median(r[fitted])),
                                  bound_nt=determined_nt)
    if method != "ellipsoid":
        if result.rejected - int(np.count_nonzero(~allowed)):
            notes.append(f"robust loss: {result.rejected - int(np.count_nonzero(~allowed))} "
                         f"samples more than {result.robust_cut_nT:.3g} nT off the fit left "
                         "out of it")
    def half(mask):
        result, residual_of = fit(mask)
        if method == "ellipsoid":
            # A half whose ellipsoid the samples do not determine says nothing of the fit.
            verdict = judge_coverage(result, b[mask], bound_nt=determined_nt)
            if not verdict.success:
                raise ValueError(f"its ellipsoid is {verdict.message}")
        return residual_of
    run.held_out, run.held_out_note = held_out(t, b, r, fitted, half, run.residual)
    before = float(np.sqrt(np.mean((np.linalg.norm(b, axis=1) - r) ** 2)))
    after = float(np.sqrt(np.mean(run.residual ** 2)))
    field_nt = float(np.median(r))
    if not after < before:
        notes.append(f"the calibration did not reduce the total-field RMS ({before:.3g} nT "
                     f"before, {after:.3g} nT after): the model does not fit these data")
    elif after > POOR_FIT_FRACTION * field_nt:
        notes.append(f"the calibrated field is still {after:.3g} nT RMS from the reference "
                     f"({100 * after / field_nt:.2g} % of it; a calibration reaches the "
                     "sensor's noise, a few nT): the model does not fit these data (strong "
                     "interference, bad samples, or not this field)")
    residual = run.residual - np.median(run.residual)
    spread = max(OUTLIER_SIGMAS * 1.4826 * float(np.median(np.abs(residual))),
                 OUTLIER_FLOOR_NT)
    outliers = int(np.count_nonzero(np.abs(residual) > spread))
    if outliers:
        notes.append(f"{outliers} of {len(residual)} samples lie more than {spread:.3g} nT "
                     f"({OUTLIER_SIGMAS:g} robust standard deviations) off the fit: spikes "
                     "or bad samples in the log; the residual RMS is mostly theirs")
    if use_time:
        # What a bias looks like in the residual (calib.bias): a lag, or slow structure.
        from .bias import check_residual
        notes += check_residual(t, vectors, r, fitted).warnings
    return run


#: Runs of at least this many 0xFF bytes are erased flash (padding), not data.
ERASED_RUN = 16
_ERASED_RE = None


def _skip_erased(data, notes):
    """``data`` without its runs of erased flash (0xFF, at least ERASED_RUN of them: a log
    copied from flash or raw card blocks, padded before, after or between its writes), said
    in ``notes``; a lone 0xFF inside a line stays (the parser counts that line as bad)."""
    import re
    global _ERASED_RE
    if b"\xff" * ERASED_RUN not in data:
        return data
    if _ERASED_RE is None:
        _ERASED_RE = re.compile(b"\xff{%d,}" % ERASED_RUN)
    runs = _ERASED_RE.findall(data)
    skipped = sum(len(run) for run in runs)
    notes.append(f"{skipped:,} bytes of erased flash (0xFF) in {len(runs)} run"
                 f"{'s' * (len(runs) != 1)} skipped: padding, not data")
    return _ERASED_RE.sub(b"", data)


#: The PMAG line's largest magnitude (±99999.9 nT): a sample there is the sensor's or the
#: format's limit, not a measurement. An axis with this share of its samples there (or
#: at a value it never leaves) is saturated or stuck, and the log is refused.
SATURATED_NT = 99999.9
SATURATED_REFUSE = 0.5


def _saturation(name, b):
    """Refuse a log whose axis is saturated (SATURATED_REFUSE of its samples at the format's
    limit ±SATURATED_NT); note the saturated samples of one that is not (the screen leaves
    them out: their magnitude is no field's)."""
    notes = []
    if len(b) == 0:
        return notes
    at_limit = np.abs(b) >= SATURATED_NT - 0.05
    for axis in range(3):
        count = int(np.count_nonzero(at_limit[:, axis]))
        if not count:
            continue
        share = count / len(b)
        what = (f"axis {'xyz'[axis]} reads the format's limit ±{SATURATED_NT:,.1f} nT in "
                f"{count:,} of {len(b):,} samples ({100 * share:.0f} %)")
        if share >= SATURATED_REFUSE:
            raise CalibrationError(f"{name}: {what}: the sensor is saturated on that axis "
                                   "(or its range is set wrong), so the log holds no "
                                   "field to calibrate; no result can be trusted")
        notes.append(f"{what}: saturated samples, not measurements (left out by the "
                     "screen)")
    return notes


def _fitter(b, r, method, seed, objective):
    """``fit(mask) -> (result, residual_of)``: the chosen fit of the samples in ``mask``,
    and a function giving its total-field residual on the samples of another mask."""
    def fit(mask):
        if method == "ellipsoid":
            # No gate here: what the flight determines is the run's verdict (judged by
            # calib.coverage as for the scalar fit), not a refusal.
            result = fit_ellipsoid(b[mask], float(np.median(r[mask])), gate=False)
            if not np.all(np.isfinite(result.W)):
                # The algebraic quadric is not an ellipsoid: the constrained fit always is.
                result = fit_ellipsoid(b[mask], float(np.median(r[mask])),
                                       method="constrained", gate=False)
                result.warnings.append("the algebraic fit gave no ellipsoid: constrained "
                                       "(Li-Griffiths) fit used")
            if not np.all(np.isfinite(result.W)):
                raise ValueError(f"ellipsoid fit failed: {result.message}")

            def residual_of(other):
                return np.linalg.norm((b[other] - result.center) @ result.W.T,
                                      axis=1) - r[other]
        else:
            result = calibrate_scalar(b, r, method=method, seed=seed, objective=objective,
                                      keep=mask)

            def residual_of(other):
                return np.linalg.norm(apply_scalar(result.K, result.c, b[other]),
                                      axis=1) - r[other]
        return result, residual_of
    return fit


def _check_scale(name, b, r):
    """The magnetometer and the reference must measure the same field in the same unit."""
    raw = float(np.median(np.linalg.norm(b, axis=1)))
    field_nt = float(np.median(r))
    if not raw > 0:
        raise CalibrationError(f"{name}: the magnetometer reads 0 nT (median |B|): "
                               "disconnected?")
    ratio = raw / field_nt
    if not 1 / SCALE_MISMATCH <= ratio <= SCALE_MISMATCH:
        raise CalibrationError(
            f"{name}: the magnetometer's median |B| ({raw:.4g} nT) is {ratio:.3g} times the "
            f"reference's ({field_nt:.4g} nT), more than {SCALE_MISMATCH:g} times off: not "
            "in nT, or not the same field")


#: Units of the noise terms of a residual in nT sampled in seconds (sigma in nT).
_NOISE_UNITS = {"quantisation": "nT s", "random_walk": "nT s^1/2", "bias_instability": "nT",
                "rate_random_walk": "nT s^-1/2", "rate_ramp": "nT s^-1"}


def _allan(run):
    """The Allan analysis of the calibrated residual, or None when it is too short or its
    times are not usable."""
    if len(run.t) <= 20 or not np.all(np.isfinite(run.t)):
        return None
    step = float(np.median(np.diff(run.t)))
    return allan_deviation(run.residual, 1.0 / step if step > 0 else 1.0)


def _allan_lines(allan):
    """The noise terms of the residual: each where its slope holds, or not resolved."""
    lines = ["## Noise of the residual (Allan deviation)", "",
             "Each term is fitted only over the τ range where the curve has its slope "
             "(IEEE 952); where no such range exists it is not resolved.", "",
             "| term | slope | value | 1 sigma | τ range (s) |", "|---|---:|---:|---:|---|"]
    for name, term in allan.terms.items():
        label = name.replace("_", " ")
        if term.resolved:
            low, high = term.tau_range
            lines.append(f"| {label} | {term.slope:+g} | {term.value:.4g} "
                         f"{_NOISE_UNITS[name]} | {term.error:.2g} | {low:.3g}–{high:.3g} |")
        else:
            lines.append(f"| {label} | {term.slope:+g} | not resolved | | |")
    return lines + [""]


def _allan_dict(allan):
    return {name: {"resolved": term.resolved, "value": term.value, "error": term.error,
                   "unit": _NOISE_UNITS[name], "tau_range_s": list(term.tau_range)}
            for name, term in allan.terms.items()}


def _plots(run, out, staged, allan):
    from .plotting import WIDE, NARROW, figure, log_time_axis, plain_log_axis, save

    files = {}

    def done(plt, fig, key, title):
        fig.suptitle(title)
        files[key] = out / f"{key}.png"
        save(plt, fig, _stage(staged, files[key]))

    timed = bool(np.all(np.isfinite(run.parsed.mag.t)))
    x, time_label = log_time_axis(run.t, timed)
    raw = np.linalg.norm(run.b, axis=1)
    plt, fig, (ax, low) = figure(WIDE, 2, height_ratios=(2, 1))
    ax.plot(x, raw, lw=0.6, color="tab:blue", label="raw |B|")
    ax.plot(x, run.calibrated, lw=1.4, color="tab:orange", label="compensated |B|")
    # The reference on top, thin and dashed: the compensated trace shows beside it.
    ax.plot(x, run.r, lw=0.9, ls="--", color="k", label=f"reference ({run.reference})",
            zorder=3)
    ax.set_ylabel("total field (nT)")
    ax.legend(loc="upper right", fontsize="small")
    rms = float(np.sqrt(np.mean(run.residual ** 2)))
    low.plot(x, run.residual, lw=0.5, color="tab:orange")
    low.axhline(0.0, color="k", lw=0.6)
    low.set_ylabel("compensated −\nreference (nT)")
    low.set_title(f"compensated |B| − reference: {rms:.2f} nT RMS", fontsize="medium")
    low.set_xlabel(time_label)
    done(plt, fig, "figure7", "Total field before and after calibration")

    unit = run.b - run.b.mean(axis=0)
    unit /= np.linalg.norm(unit, axis=1)[:, None]
    plt, fig, ax = figure(NARROW)
    ax.scatter(np.degrees(np.arctan2(unit[:, 1], unit[:, 0])),
               np.degrees(np.arcsin(np.clip(unit[:, 2], -1, 1))), s=1)
    ax.set_xlabel("azimuth of the field in the sensor frame (deg)")
    ax.set_ylabel("elevation of the field (deg)")
    done(plt, fig, "coverage", "Attitude coverage")

    plt, fig, ax = figure(NARROW)
    _, edges, _ = ax.hist(run.residual, bins=80)
    ax.set_xlabel("compensated |B| − reference (nT)")
    ax.set_ylabel(f"samples per {edges[1] - edges[0]:.2g} nT bin")
    done(plt, fig, "residuals", f"Residuals: {rms:.2f} nT RMS, {len(run.residual)} samples")

    if allan is not None:
        plt, fig, ax = figure(NARROW)
        ax.errorbar(allan.taus, allan.deviation, yerr=allan.error, lw=0.8, elinewidth=0.5)
        ax.set_xscale("log")
        ax.set_yscale("log")
        plain_log_axis(ax)
        ax.set_xlabel("averaging time τ (s)")
        ax.set_ylabel("Allan deviation (nT)")
        done(plt, fig, "allan", "Allan deviation of the residual")

    before, after = run.heading.errors() if run.heading is not None else (None, None)
    if before is not None:
        plt, fig, ax = figure(WIDE)
        aligned = run.heading.alignment
        # An offset of a fraction of a degree puts one trace on the other: the one before
        # the alignment wide below, the one after thin on top, so that both show.
        ax.plot(x, before, lw=1.4 if aligned is not None else 0.6, color="tab:blue",
                label="before alignment")
        if aligned is not None:
            ax.plot(x, after, lw=0.5, color="tab:orange",
                    label=f"after alignment to the course over ground (offset "
                          f"{aligned.offset:+.2f}°)")
        origin = run.t[0] - x[0] if len(x) else 0.0
        for k, leg in enumerate(run.heading.legs if timed else ()):
            ax.axvspan(leg.start - origin, leg.end - origin, color="0.85", zorder=0,
                       label="straight, level legs" if k == 0 else None)
        ax.set_xlabel(time_label)
        ax.set_ylabel("heading error (deg)")
        ax.legend(loc="upper right", fontsize="small")
        title = "Heading from the calibrated field against the attitude"
        if not run.heading.legs:
            title += " (no straight, level leg found)"
        done(plt, fig, "heading_error", title)
    return files


def _coverage_lines(verdict, result):
    lines = ["## Coverage gate: what the flight determines", "",
             f"Verdict: {verdict.message}.", "",
             f"The rule (one for the gate, `success` and `verdict` in parameters.json, this "
             f"report, the printed verdict and `maglog run`'s parameters check): {RULE}.",
             "", "Octants, for information only (they do not say how well a parameter is "
             "known):", "",
             f"- the calibrated field's octants about the fitted centre reached (≥ "
             f"{verdict.min_per_octant} samples): {verdict.octants_reached} of 8 "
             f"({verdict.octants.tolist()})",
             f"- paper B's check, octants about the running centroid of the raw samples: "
             f"{verdict.paper_filled} of 8 filled ({verdict.paper_octants.tolist()}); it "
             "counts octants of a centroid inside the covered cap, so it fills on flights "
             "that leave parameters undetermined"]
    if getattr(result, "rejected", 0):
        lines.append(f"- samples not fitted: {result.rejected}")
    return lines + [""]


def _parameter_lines(run):
    """The parameters (canonical k11..c3 for every method), each with its 1-sigma, in nT of
    field, and whether the flight determines it (:mod:`.coverage`)."""
    res, d = run.result, run.coverage.determination
    lines = [f"Determined: 1-sigma in nT of field at most {d.bound_text}.", "",
             "| parameter | value | 1 sigma | 1 sigma in nT of field | determined |",
             "|---|---:|---:|---:|---|"]
    for i, (n, v, u) in enumerate(zip(PARAMETERS, res.x, res.uncertainties)):
        if d.held[i]:
            sigma, field_sigma, state = "none", "none", "no: held to the prior"
        else:
            sigma = f"{u:.2g}" if np.isfinite(u) else "none"
            field_sigma = f"{d.sigma_nT[i]:.3g}" if np.isfinite(d.sigma_nT[i]) else "none"
            state = "yes" if d.determined[i] else "**no: undetermined**"
        lines.append(f"| {n} | {v:.6g} | {sigma} | {field_sigma} | {state} |")
    return lines + [""]


def _screening_lines(run):
    lines = ["## Screening and robust loss", ""]
    if not run.screens:
        lines.append("- no screening (the reference is not a cesium series)")
    for screen in run.screens.values():
        lines.append(f"- {screen.summary()}")
        for reason, examples in screen.examples.items():
            lines += [f"  - {reason}, #{ex.index}: {ex.why}" for ex in examples]
    res = run.result
    if run.method != "ellipsoid":
        allowed = run.screens["samples"].keep if "samples" in run.screens else \
            np.ones(len(run.b), bool)
        robust = int(np.count_nonzero(allowed & ~res.kept))
        cut = "none" if not np.isfinite(res.robust_cut_nT) else f"{res.robust_cut_nT:.3g} nT"
        lines.append(f"- robust loss (Talwar's, cut-off {cut} from the median residual): "
                     f"{robust} samples left out of the fit")
    return lines + [""]


def _heading_lines(analysis, t):
    lines = ["## Heading", ""]
    if np.isnan(analysis.declination):
        lines.append(f"- declination: none ({analysis.declination_source})")
    else:
        lines.append(f"- declination {analysis.declination:+.2f}° ({analysis.declination_source})")
    align = analysis.alignment
    lines.append(f"- straight, level legs in the GPS course over ground: {len(analysis.legs)}")
    if align is not None:
        std = "unknown" if np.isnan(align.offset_std) else f"{align.offset_std:.2f}°"
        a, b = align.sinusoid
        lines += [f"- heading offset {align.offset:+.2f}° (1 sigma {std}), removed from the "
                  f"aligned headings; a sin(course) + b cos(course) = {a:+.2f}°, {b:+.2f}° "
                  "(wind crab and frame tilt, not separable from the course: not applied); "
                  f"residual {align.residual_rms:.2f}° RMS", "",
                  "| leg start (s) | duration (s) | course (°) | ground speed (m/s) | "
                  "heading - course (°) |", "|---:|---:|---:|---:|---:|"]
        lines += [f"| {leg.start:.1f} | {leg.duration:.0f} | {leg.course:.1f} | "
                  f"{leg.speed:.1f} | {diff:+.2f} |" for leg, diff in align.legs]
        lines.append("")
        lines += [f"- warning: {w}" for w in align.warnings]
    before, after = analysis.errors()
    if before is not None:
        good = np.isfinite(before)
        lines.append(f"- against the attitude file ({int(good.sum())} samples): heading error "
                     f"{np.sqrt(np.mean(before[good] ** 2)):.2f}° RMS before the alignment, "
                     f"{np.sqrt(np.mean(after[good] ** 2)):.2f}° after")
        legs = good & analysis.on_legs(t)
        if legs.any():
            lines.append(f"- on the legs ({int(legs.sum())} samples): "
                         f"{np.sqrt(np.mean(before[legs] ** 2)):.2f}° RMS before, "
                         f"{np.sqrt(np.mean(after[legs] ** 2)):.2f}° after; what is left "
                         "off the legs is mostly the frame's tilt, which the course over "
                         "ground cannot see")
    lines += [f"- {message}" for message in analysis.messages]
    return lines + [""]


#: The plots a report may hold (heading_error and allan only when there is data for them).
PLOTS = ("figure7", "coverage", "residuals", "allan", "heading_error")
#: The text files of a report.
TEXT_FILES = ("report.md", "report.html", "parameters.json")


def report_files():
    """Every file name :func:`write_report` may write into its folder (and the only ones it
    removes when a rerun does not write them again)."""
    return TEXT_FILES + tuple(f"{key}.png" for key in PLOTS)


def _html(markdown_text, title):
    """The report's Markdown as a full HTML document (Python-Markdown, tables and fenced
    code). Raw HTML in the text (a log name, a bad line's bytes quoted in a message) is
    shown as text, never interpreted."""
    from .html import markdown_page
    return markdown_page(markdown_text, title)


def _discard(staged):
    """Remove the staged temporary files that were not moved into place."""
    for temp in staged.values():
        try:
            temp.unlink(missing_ok=True)
        except OSError:
            pass


def _stage(staged, final):
    """A temporary file beside ``final`` to write into; moved over ``final`` when the whole
    report is written (see :func:`write_report`)."""
    from .files import stage
    return stage(staged, final)      # created with the user's umask, not mkstemp's 0600


def _report_lines(run, summary, files, allan=None):
    lines = [f"# Calibration of {run.log_name}", "",
             f"- method: {run.method}; reference: {run.reference}; samples: {len(run.b)}",
             f"- total-field RMS against the reference: {summary['rms_before_nT']:.2f} nT "
             f"before, {summary['rms_after_nT']:.2f} nT after"]
    res = run.result
    if run.method != "ellipsoid" and res.objective == "eiv":
        noise = res.noise
        lines.append(f"- fit: {res.message}; objective: errors in variables (the "
                     "magnetometer's noise corrected for: estimated "
                     f"{noise['magnetometer_nT']:.3g} nT per axis, the reference's "
                     f"{noise['reference_nT']:.2g} nT); {res.nit} swarm and "
                     "Gauss-Newton iterations in all")
    elif run.method != "ellipsoid":
        lines.append(f"- fit: {res.message}; objective: the paper's (polish: least_squares "
                     f"{res.solver}; {res.nit} swarm iterations and function evaluations "
                     "in all)")
    else:
        lines.append(f"- fit: {res.method} ellipsoid, {res.message}")
    fitted = summary["samples_fitted"]
    if fitted != len(run.b):
        lines.append(f"- fitted {fitted} of {len(run.b)} samples (the others screened out "
                     "or rejected by the robust loss: see below); their RMS after: "
                     f"{summary['rms_after_fitted_nT']:.2f} nT")
    if run.held_out is not None:
        lines.append(f"- held out: {run.held_out.message}")
    else:
        lines.append(f"- held out: not scored ({run.held_out_note})")
    lines.insert(2, f"- **verdict: {run.coverage.verdict.upper()}** — {run.coverage.message}")
    lines.append("")
    others = [w for w in run.warnings if w != run.coverage.message]   # the verdict: above
    if others:
        lines += ["## Warnings", ""] + [f"- {warning}" for warning in others] + [""]
    lines += ["## Parameters", ""] + _parameter_lines(run)
    if run.method != "ellipsoid":
        lines += ["Paper's Table 1 form: P = K^-1 and the offset P c (nT):", "",
                  "```", np.array2string(res.P, precision=5),
                  np.array2string(res.offset_sensor, precision=2), "```", ""]
    else:
        values = np.linalg.eigvalsh(res.W)
        lines += ["Ellipsoid: |W (b - centre)| = field. W is the symmetric positive-definite "
                  "root of the fitted quadric (its sign fixed: eigenvalues "
                  f"{', '.join(f'{v:.5f}' for v in values)}, determinant "
                  f"{np.linalg.det(res.W):.5f} > 0, so no axis is reversed); like the "
                  "scalar model it leaves the frame's rotation free.", "",
                  "```", "centre (nT): " + np.array2string(res.center, precision=1),
                  "W:", np.array2string(res.W, precision=6), "```", "",
                  "The table gives the same fit in the scalar model's form (K the "
                  "upper-triangular factor of W, c = K centre).", ""]
    lines += _coverage_lines(run.coverage, res)
    lines += _screening_lines(run)
    if run.heading is not None:
        lines += _heading_lines(run.heading, run.t)
    if allan is not None:
        lines += _allan_lines(allan)
    report = run.parsed.report
    bad = ", ".join(f"{k} {v}" for k, v in report.bad.items() if v) or "none"
    lines += ["## Log", "", f"{report.lines} lines; bad lines by reason: {bad}.", ""]
    lines += ["## Plots", ""]
    for key, path in files.items():
        lines += [f"![{key}]({path.name})", ""]
    return lines


def write_report(run, out_dir):
    """Markdown, HTML, PNGs and a JSON of the parameters into folder ``out_dir``; returns
    the paths (keys markdown, html, json and one per plot).

    Every file is written beside its final name first and moved into place when all are
    written; files of an earlier report (:func:`report_files`: only those names) that this
    one does not write again are then removed, so a rerun leaves no stale plot behind and
    a failed write leaves the earlier report as it was. When the OS refuses (no such
    folder and none can be made, a file in the way, no permission, a full disk) a
    :class:`ReportError` says where and why in one line. Nothing is printed."""
    out = check_output_dir(out_dir)
    staged = {}
    try:
        with _warnings.catch_warnings(), np.errstate(all="ignore"):
            _warnings.simplefilter("ignore")
            summary = run.summary()
            allan = _allan(run)
            if allan is not None:
                summary["allan"] = _allan_dict(allan)
            files = _plots(run, out, staged, allan)
            _stage(staged, out / "parameters.json").write_text(
                json.dumps(jsonable(summary), indent=2, allow_nan=False) + "\n")
            markdown_text = "\n".join(_report_lines(run, summary, files, allan)) + "\n"
            _stage(staged, out / "report.md").write_text(markdown_text, encoding="utf-8")
            _stage(staged, out / "report.html").write_text(
                _html(markdown_text, f"Calibration of {run.log_name}"), encoding="utf-8")
        for final, temp in staged.items():
            os.replace(temp, final)
        for name in report_files():
            stale = out / name
            if stale not in staged and (stale.is_file() or stale.is_symlink()):
                stale.unlink()
    except OSError as error:
        where = Path(error.filename).parent if error.filename else out
        raise ReportError(f"{where}: cannot write the report: {_reason(error)}") from None
    finally:
        _discard(staged)
    return {"markdown": out / "report.md", "html": out / "report.html",
            "json": out / "parameters.json", **files}
