"""From a card image to calibrated parameters and a report.

card image (or partition image, or plain log) → LOG*.TXT → parsed streams → magnetometer
samples with a reference total field (cesium, IGRF at the GPS position and date, or a
constant) → scalar calibration (PSO + LM, or LM) or an ellipsoid fit → report.
"""

import datetime
import html
import json
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from .card import read_logs
from .ellipsoid import fit_ellipsoid
from .logparse import parse_log, to_arrays
from .noise import allan_deviation
from .scalar import PARAMETERS, apply_scalar, calibrate_scalar


__all__ = ["CalibrationError", "CalibrationRun", "calibrate_card", "write_report"]

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
    calibrated: np.ndarray     # |calibrated field|, nT
    parsed: object

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
            out.update(center_nT=res.center.tolist(), W=res.W.tolist(),
                       coverage=res.coverage.report(), success=res.success,
                       message=res.message)
        else:
            out.update(self.result.as_dict())
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


def calibrate_card(path, *, ref="cesium", method="pso", seed=0):
    """Calibrate the largest log on a card image (or partition image, or plain log)."""
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
        if not result.success:
            raise CalibrationError(f"{name}: ellipsoid fit refused: {result.message}")
        calibrated = np.linalg.norm((b - result.center) @ result.W.T, axis=1)
    else:
        result = calibrate_scalar(b, r, method=method, seed=seed)
        calibrated = np.linalg.norm(apply_scalar(result.K, result.c, b), axis=1)
    return CalibrationRun(log_name=name, t=t, b=b, r=r, reference=reference, method=method,
                          result=result, calibrated=calibrated, parsed=parsed)


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
    return files


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
    bad = run.parsed.report.bad if hasattr(run.parsed.report, "bad") else {}
    lines += ["", f"Log: {_jsonable(vars(run.parsed.report)).get('lines')} lines; bad lines by "
              f"reason: {bad}", ""]
    lines += [f"![{key}]({path.name})" for key, path in files.items()]
    markdown = "\n".join(lines) + "\n"
    (out / "report.md").write_text(markdown)
    body = "".join(f"<p>{html.escape(line)}</p>" if not line.startswith("![") else
                   f'<img src="{line[line.index("(") + 1:-1]}">' for line in lines if line)
    (out / "report.html").write_text(f"<!doctype html><meta charset=utf-8>"
                                     f"<title>Calibration</title>{body}")
    return {"markdown": out / "report.md", "html": out / "report.html",
            "json": out / "parameters.json", **files}
