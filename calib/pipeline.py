"""From a card image to calibrated parameters and a report.

card image (or partition image, or plain log) → LOG*.TXT → parsed streams → magnetometer
samples with a reference total field (cesium, IGRF at the GPS position and date, or a
constant) → scalar calibration (PSO + LM, or LM) or an ellipsoid fit → heading (IGRF
declination; alignment to GPS course over ground on straight, level legs; errors against a
known attitude when one is given) → report.
"""

import datetime
import html
import json
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from .card import read_logs
from .ellipsoid import fit_ellipsoid
from .heading import (align_heading, straight_legs, tilt_compensated_heading, true_heading,
                      wrap_degrees)
from .logparse import parse_log, to_arrays
from .noise import allan_deviation
from .scalar import PARAMETERS, apply_scalar, calibrate_scalar


__all__ = ["CalibrationError", "CalibrationRun", "HeadingAnalysis", "calibrate_card",
           "read_attitude", "write_report"]

ATTITUDE_COLUMNS = ("t", "roll_deg", "pitch_deg", "heading_deg")

METHODS = ("pso", "lm", "ellipsoid")


class CalibrationError(Exception):
    """The data cannot be calibrated as asked (said why)."""


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

    @property
    def calibrated(self):
        """|calibrated field|, nT."""
        return np.linalg.norm(self.vectors, axis=1)

    @property
    def residual(self):
        return self.calibrated - self.r

    def summary(self):
        raw = np.linalg.norm(self.b, axis=1) - self.r
        out = {"log": self.log_name, "samples": int(len(self.b)), "reference": self.reference,
               "method": self.method,
               "rms_before_nT": float(np.sqrt(np.mean(raw ** 2))),
               "rms_after_nT": float(np.sqrt(np.mean(self.residual ** 2))),
               "log_report": _jsonable(vars(self.parsed.report))}
        if self.method == "ellipsoid":
            res = self.result
            out.update(fit=res.method, warnings=list(res.warnings),
                       center_nT=res.center.tolist(), W=res.W.tolist(),
                       W_eigenvalues=np.linalg.eigvalsh(res.W).tolist(),
                       coverage=res.coverage.report(), success=res.success,
                       message=res.message)
        else:
            out.update(self.result.as_dict())
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


def _jsonable(value):
    if isinstance(value, dict):
        return {str(k): _jsonable(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [_jsonable(v) for v in value]
    if isinstance(value, (np.integer,)):
        return int(value)
    if isinstance(value, (np.floating,)):
        return float(value)
    if isinstance(value, (datetime.date, datetime.datetime)):
        return value.isoformat()
    return value


def _axis(parsed_t, lines):
    """Times if every one is known, else the line numbers (arrival order)."""
    return parsed_t if np.all(np.isfinite(parsed_t)) else lines.astype(float)


def _reference(parsed, ref, mag_axis, use_time):
    mag = parsed.mag
    if isinstance(ref, (int, float)):
        return np.full(len(mag), float(ref)), f"constant {float(ref):g} nT"
    if ref == "cesium":
        ces = parsed.cesium
        if len(ces) < 2:
            raise CalibrationError("the log has fewer than 2 cesium samples; use --ref igrf "
                                   "or a value")
        if use_time:
            # The parser's interpolation: NaN outside the cesium span and across dropouts.
            return to_arrays(parsed).cesium, "cesium magnetometer"
        return (np.interp(mag_axis, ces.line.astype(float), ces.field, left=np.nan,
                          right=np.nan), "cesium magnetometer (by arrival order: no GPS time)")
    if ref == "igrf":
        import ppigrf
        gga = parsed.gga
        good = gga.quality > 0
        if not np.any(good):
            raise CalibrationError("the log has no GGA with a fix: IGRF needs a position")
        date = parsed.date or datetime.date(2026, 1, 1)
        when = datetime.datetime(date.year, date.month, date.day)
        east, north, up = ppigrf.igrf(gga.lon[good], gga.lat[good],
                                      gga.altitude[good] / 1000.0, when)
        total = np.sqrt(np.ravel(east) ** 2 + np.ravel(north) ** 2 + np.ravel(up) ** 2)
        axis = gga.t[good] if use_time else gga.line[good].astype(float)
        dated = "" if parsed.date else " (no ZDA date: 2026-01-01 assumed)"
        return (np.interp(mag_axis, axis, total),
                f"IGRF-14 at the GPS position, {when:%Y-%m-%d}{dated}")
    raise CalibrationError(f"reference must be cesium, igrf or a field value in nT, "
                           f"not {ref!r}")


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
    good = (gga.quality > 0) & np.isfinite(gga.lat) & np.isfinite(gga.lon)
    if not np.any(good):
        return np.nan, "no GPS fix: headings are magnetic"
    lat, lon = float(np.mean(gga.lat[good])), float(np.mean(gga.lon[good]))
    altitude = float(np.nanmean(gga.altitude[good])) if np.any(
        np.isfinite(gga.altitude[good])) else 0.0
    date = parsed.date or datetime.date(2026, 1, 1)
    east, north, _ = ppigrf.igrf(lon, lat, altitude / 1000.0,
                                 datetime.datetime(date.year, date.month, date.day))
    value = float(np.degrees(np.arctan2(np.ravel(east)[0], np.ravel(north)[0])))
    dated = "" if parsed.date else ", no ZDA date: 2026-01-01 assumed"
    return value, (f"IGRF-14 at {lat:.5f}, {lon:.5f}, {altitude:.0f} m, "
                   f"{date:%Y-%m-%d}{dated}")


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


def calibrate_card(path, *, ref="cesium", method="pso", seed=0, attitude=None):
    """Calibrate the largest log on a card image (or partition image, or plain log).
    ``attitude`` is an optional attitude file (:func:`read_attitude`)."""
    attitude = None if attitude is None else read_attitude(attitude)
    if method not in METHODS:
        raise CalibrationError(f"method must be one of {', '.join(METHODS)}, not {method!r}")
    logs = read_logs(path)
    if not logs:
        raise CalibrationError(f"{path}: no LOG*.TXT file found")
    name, data = max(logs, key=lambda item: len(item[1]))
    parsed = parse_log(data, name=name)
    mag = parsed.mag
    if len(mag) < len(PARAMETERS) + 1:
        raise CalibrationError(f"{name}: only {len(mag)} magnetometer samples; at least "
                               f"{len(PARAMETERS) + 1} are needed")
    use_time = bool(np.all(np.isfinite(mag.t)))
    mag_axis = mag.t if use_time else mag.line.astype(float)
    r, reference = _reference(parsed, ref, mag_axis, use_time)
    keep = np.isfinite(r)
    if keep.sum() < len(PARAMETERS) + 1:
        raise CalibrationError(f"{name}: the reference covers only {int(keep.sum())} "
                               f"magnetometer samples")
    b, r = mag.b[keep], r[keep]
    t = mag.t[keep] if use_time else mag_axis[keep]
    if method == "ellipsoid":
        result = fit_ellipsoid(b, float(np.median(r)))
        if not result.success and result.coverage.complete:
            # The algebraic quadric is not an ellipsoid: the constrained fit always is.
            result = fit_ellipsoid(b, float(np.median(r)), method="constrained")
            result.warnings.append("the algebraic fit gave no ellipsoid: constrained "
                                   "(Li-Griffiths) fit used")
        if not result.success:
            raise CalibrationError(f"{name}: ellipsoid fit refused: {result.message}")
        vectors = (b - result.center) @ result.W.T
    else:
        result = calibrate_scalar(b, r, method=method, seed=seed)
        vectors = apply_scalar(result.K, result.c, b)
    return CalibrationRun(log_name=name, t=t, b=b, r=r, reference=reference, method=method,
                          result=result, parsed=parsed, vectors=vectors,
                          heading=_heading(parsed, t, use_time, vectors, attitude))


def _plots(run, out):
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    files = {}

    def save(fig, key, title):
        fig.axes[0].set_title(title)
        fig.tight_layout()
        files[key] = out / f"{key}.png"
        fig.savefig(files[key], dpi=110)
        plt.close(fig)

    raw = np.linalg.norm(run.b, axis=1)
    fig, ax = plt.subplots(figsize=(9, 4))
    ax.plot(run.t, raw, lw=0.6, label="raw |B|")
    ax.plot(run.t, run.calibrated, lw=0.6, label="compensated |B|")
    ax.plot(run.t, run.r, lw=1.0, label="reference", color="k")
    ax.set_xlabel("time (s)")
    ax.set_ylabel("total field (nT)")
    ax.legend()
    save(fig, "figure7", "Total field before and after calibration")

    unit = run.b - run.b.mean(axis=0)
    unit /= np.linalg.norm(unit, axis=1)[:, None]
    fig, ax = plt.subplots(figsize=(6, 3.5))
    ax.scatter(np.degrees(np.arctan2(unit[:, 1], unit[:, 0])),
               np.degrees(np.arcsin(np.clip(unit[:, 2], -1, 1))), s=1)
    ax.set_xlabel("azimuth of the field in the sensor frame (deg)")
    ax.set_ylabel("elevation (deg)")
    save(fig, "coverage", "Attitude coverage")

    fig, ax = plt.subplots(figsize=(6, 3.5))
    ax.hist(run.residual, bins=80)
    ax.set_xlabel("compensated |B| - reference (nT)")
    save(fig, "residuals", "Residuals")

    if len(run.t) > 20 and np.all(np.isfinite(run.t)):
        rate = 1.0 / float(np.median(np.diff(run.t))) if np.median(np.diff(run.t)) > 0 else 1.0
        allan = allan_deviation(run.residual, rate)
        fig, ax = plt.subplots(figsize=(6, 3.5))
        ax.loglog(allan.taus, allan.deviation)
        ax.set_xlabel("tau (s)")
        ax.set_ylabel("Allan deviation (nT)")
        save(fig, "allan", "Allan deviation of the residual")

    before, after = run.heading.errors() if run.heading is not None else (None, None)
    if before is not None:
        fig, ax = plt.subplots(figsize=(9, 3.5))
        ax.plot(run.t, before, lw=0.6, label="before alignment")
        if run.heading.alignment is not None:
            ax.plot(run.t, after, lw=0.6, label="after alignment to the course over ground")
        for leg in run.heading.legs:
            ax.axvspan(leg.start, leg.end, color="0.9", zorder=0)
        ax.set_xlabel("time (s); straight, level legs shaded")
        ax.set_ylabel("heading error (deg)")
        ax.legend()
        save(fig, "heading_error", "Heading from the calibrated field against the attitude")
    return files


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
        lines += [f"> warning: {w}" for w in align.warnings]
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


def _html(lines):
    """The report's Markdown subset as HTML: headings, lists, tables, code blocks, quotes
    and images."""
    out, table, code = [], [], None

    def cells(row):
        return [html.escape(c.strip()) for c in row.strip().strip("|").split("|")]

    def flush_table():
        if table:
            head, *rows = [r for r in table if not set(r) <= set("|-: ")]
            out.append("<table><tr>" + "".join(f"<th>{c}</th>" for c in cells(head))
                       + "</tr>" + "".join("<tr>" + "".join(f"<td>{c}</td>" for c in cells(r))
                                           + "</tr>" for r in rows) + "</table>")
            table.clear()

    for line in lines:
        if code is not None:
            if line.startswith("```"):
                out.append("<pre>" + html.escape("\n".join(code)) + "</pre>")
                code = None
            else:
                code.append(line)
            continue
        if line.startswith("|"):
            table.append(line)
            continue
        flush_table()
        if line.startswith("```"):
            code = []
        elif line.startswith("#"):
            level = len(line) - len(line.lstrip("#"))
            out.append(f"<h{level}>{html.escape(line[level:].strip())}</h{level}>")
        elif line.startswith("!["):
            out.append(f'<p><img src="{html.escape(line[line.index("(") + 1:-1])}"></p>')
        elif line.startswith("- "):
            out.append(f"<li>{html.escape(line[2:])}</li>")
        elif line.startswith("> "):
            out.append(f"<blockquote>{html.escape(line[2:])}</blockquote>")
        elif line:
            out.append(f"<p>{html.escape(line)}</p>")
    flush_table()
    return "\n".join(out)


def write_report(run, out_dir):
    """Markdown, HTML, PNGs and a JSON of the parameters; returns the paths."""
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    summary = run.summary()
    files = _plots(run, out)
    (out / "parameters.json").write_text(json.dumps(_jsonable(summary), indent=2))
    lines = [f"# Calibration of {run.log_name}", "",
             f"- method: {run.method}; reference: {run.reference}; samples: {len(run.b)}",
             f"- total-field RMS against the reference: {summary['rms_before_nT']:.2f} nT "
             f"before, {summary['rms_after_nT']:.2f} nT after", ""]
    if run.method != "ellipsoid":
        res = run.result
        lines += ["| parameter | value | uncertainty (1 sigma) |", "|---|---:|---:|"]
        lines += [f"| {n} | {v:.6g} | {u:.2g} |"
                  for n, v, u in zip(PARAMETERS, res.x, res.uncertainties)]
        lines += ["", "Paper's Table 1 form: P = K^-1 and the offset P c (nT):", "",
                  "```", np.array2string(res.P, precision=5),
                  np.array2string(res.offset_sensor, precision=2), "```", ""]
        for warning in res.warnings:
            lines.append(f"> warning: {warning}")
    else:
        res = run.result
        values = np.linalg.eigvalsh(res.W)
        lines += ["Ellipsoid: |W (b - centre)| = field. W is the symmetric positive-definite "
                  "root of the fitted quadric (its sign fixed: eigenvalues "
                  f"{', '.join(f'{v:.5f}' for v in values)}, determinant "
                  f"{np.linalg.det(res.W):.5f} > 0, so no axis is reversed); like the "
                  "scalar model it leaves the frame's rotation free.", "",
                  "```", "centre (nT): " + np.array2string(res.center, precision=1),
                  "W:", np.array2string(res.W, precision=6), "```", "",
                  f"Octant coverage: {res.coverage.filled} of 8 octants with at least "
                  f"{res.coverage.min_per_octant} samples ({res.coverage.counts.tolist()}).",
                  ""]
        lines += [f"> warning: {warning}" for warning in res.warnings]
    if run.heading is not None:
        lines += _heading_lines(run.heading, run.t)
    bad = run.parsed.report.bad if hasattr(run.parsed.report, "bad") else {}
    lines += ["", f"Log: {_jsonable(vars(run.parsed.report)).get('lines')} lines; bad lines by "
              f"reason: {bad}", ""]
    lines += [f"![{key}]({path.name})" for key, path in files.items()]
    markdown = "\n".join(lines) + "\n"
    (out / "report.md").write_text(markdown)
    (out / "report.html").write_text(
        "<!doctype html><meta charset=utf-8><title>Calibration</title>"
        "<style>table{border-collapse:collapse}td,th{border:1px solid #bbb;"
        "padding:2px 6px}</style>" + _html(lines))
    return {"markdown": out / "report.md", "html": out / "report.html",
            "json": out / "parameters.json", **files}
