"""What ``maglog run`` prints: the run scored against the scenario's truth.

Four scores, each with a one-line verdict:

- frames: the gateware's front-end counters (kept, and dropped per cause) for each channel
  against ``truth["frames"]`` (the reference filter fed with the decoded line). Both count
  the same bytes with the same rules, so they must be equal: any difference is a failure.
- log: the log file read from the card against ``truth["recorded"]`` (frames per channel,
  bytes, SHA-256). The logger writes the kept frames verbatim, so the file must be equal.
- residual: the total-field RMS after calibration against ``truth["noise_floor_nT"]``, the
  residual a perfect calibration leaves (see :data:`RESIDUAL_RATIO`).
- parameters: the recovered K and c against the truth's, with the fit's 1σ and z (see
  :data:`Z_MAX`, :data:`K_ABS`, :data:`C_ABS_NT`). Only the parameters the flight determines
  are scored, by the calibration's own verdict (:mod:`maglog.calib.coverage`: 1-sigma in nT
  of field within the noise of one sample, or the bound given); a flight that leaves any
  undetermined ends UNDETERMINED, naming them, never ALL CHECKS PASS.

``summarize(truth, counters, logs, run)`` returns a :class:`Summary`; nothing is printed.
"""

import hashlib
from dataclasses import dataclass, field

import numpy as np

from ..calib.pipeline import CalibrationRun
from ..calib.pipeline import jsonable as _jsonable
from ..calib.scalar import PARAMETERS


__all__ = ["CAUSES", "RESIDUAL_RATIO", "Z_MAX", "K_ABS", "C_ABS_NT", "TOLERANCES", "Check",
           "Summary", "summarize", "log_frames", "canonical_kc", "recovered_kc"]

#: The front end's counters per channel, in the order the table shows them (``kept`` then
#: the drop causes of DESIGN.md's frame rules; ``overflow``: no room in the frame FIFO).
CAUSES = ("kept", "checksum", "not_whitelisted", "overlong", "bad_byte", "uart_error",
          "overflow")
#: The channels in uart_rx bit order (spec: FLIGHT_CHANNELS).
CHANNELS = ("mag", "gps", "cesium")

#: Residual after calibration ÷ noise floor must lie in this range. A least-squares fit of
#: 9 parameters to N samples leaves sqrt(1 - 9/N) of the noise (> 0.99 for any flight), and
#: the RMS of N noise samples scatters by 1/sqrt(2N) (< 1 % for N > 5000): so a correct
#: calibration gives 0.98-1.02. The range is wider for what the floor's formula leaves out
#: (interpolating the 10 Hz cesium to the magnetometer's times while the aircraft moves
#: through the field's gradient, the PMAG1 format's 0.1 nT rounding): up to 25 % above.
#: Far below the floor (< 0.8) the data are not the truth's (less noise than injected).
RESIDUAL_RATIO = (0.8, 1.25)
#: A recovered parameter passes when it is within Z_MAX of the fit's 1σ of the truth
#: (5σ: one of nine parameters beyond 3σ happens in 2 % of honest runs; beyond 5σ is a
#: model error, not chance) ...
Z_MAX = 5.0
#: ... or when its difference cannot matter: K off by 1e-4 moves a 50,000 nT field by
#: 5 nT, and c off by 5 nT moves it by 5 nT, about one magnetometer noise sigma
#: (DESIGN.md's error model: 5 nT). Also the only test when the method gives no 1σ
#: (the ellipsoid fit).
K_ABS = 1e-4
C_ABS_NT = 5.0
#: Which parameters are scored at all: those the calibration's verdict calls determined
#: (calib.coverage.RULE). An undetermined one is not scored (a small z on a huge 1σ says
#: nothing) and the check is UNDETERMINED, naming it.
DETERMINED = "determined by the flight (calib.coverage): 1 sigma in nT of field within the " \
             "noise of one sample (or the bound given)"
#: Every tolerance, as Summary.as_dict() reports it.
TOLERANCES = {"frames": "equal (0 difference)", "log": "equal bytes (SHA-256)",
              "residual_ratio": list(RESIDUAL_RATIO), "z_max": Z_MAX, "k_abs": K_ABS,
              "c_abs_nT": C_ABS_NT, "scored": DETERMINED}

PASS, FAIL, SKIP, UNDETERMINED = "pass", "fail", "skip", "undetermined"


@dataclass(frozen=True)
class Check:
    """One verdict: ``status`` is pass, fail or skip (nothing to check it against)."""
    name: str
    status: str
    detail: str
    tolerance: str = ""

    def line(self):
        tol = f" [tolerance: {self.tolerance}]" if self.tolerance else ""
        return f"{self.status.upper():4s} {self.name}: {self.detail}{tol}"


@dataclass
class Summary:
    text: str                   # the block ``maglog run`` prints
    checks: list                # Check, in the order printed
    data: dict = field(default_factory=dict)   # the figures behind the text (JSON-able)

    @property
    def failed(self):
        """Names of the checks that failed."""
        return [c.name for c in self.checks if c.status == FAIL]

    @property
    def undetermined(self):
        """The parameters the flight does not determine (not scored)."""
        return list(self.data.get("undetermined") or [])

    @property
    def ok(self):
        return not self.failed and not any(c.status == UNDETERMINED for c in self.checks)

    @property
    def verdict(self):
        """The run's verdict line (after "=> ")."""
        parts = []
        if self.failed:
            parts.append(f"FAILED: {', '.join(self.failed)}")
        if any(c.status == UNDETERMINED for c in self.checks):
            parts.append(f"UNDETERMINED: the flight does not determine "
                         f"{', '.join(self.undetermined)} (not scored)")
        text = "; ".join(parts) or "ALL CHECKS PASS"
        skipped = sum(c.status == SKIP for c in self.checks)
        if skipped:
            text += f" ({skipped} skipped: nothing to check against)"
        return text

    def as_dict(self):
        return _jsonable({"ok": self.ok, "failed": self.failed,
                          "undetermined": self.undetermined, "verdict": self.verdict,
                          "tolerances": TOLERANCES,
                          "checks": [{"name": c.name, "status": c.status, "detail": c.detail,
                                      "tolerance": c.tolerance} for c in self.checks],
                          **self.data})


# -- Frames ---------------------------------------------------------------------------------

def _frames(truth, counters):
    expected = truth.get("frames")
    if not isinstance(expected, dict):
        raise ValueError(f"truth['frames'] must be a dict per channel, not {expected!r}")
    channels = [c["name"] for c in truth.get("channels", [])] or \
        [c for c in CHANNELS if c in expected]
    if counters is not None and not isinstance(counters, dict):
        raise ValueError(f"counters must be a dict per channel or None, not {counters!r}")
    lines = ["Frames per channel and cause: gateware / truth (* = they differ)"]
    checks, table, rows = [], {}, []
    for name in channels:
        want = expected.get(name)
        if not isinstance(want, dict):
            raise ValueError(f"truth['frames'] has no counts for channel {name!r}")
        got = None if counters is None else counters.get(name)
        cells, row, differ = [], {}, []
        for cause in CAUSES:
            w = want.get(cause)
            g = None if got is None else got.get(cause)
            row[cause] = {"gateware": g, "truth": w}
            if g is None:
                cells.append(f"-/{w}")
            elif g == w:
                cells.append(f"{g}")
            else:
                cells.append(f"{g}/{w} *")
                differ.append(f"{cause} {g} vs {w}")
        table[name] = row
        rows.append([name] + cells)
        check = f"frames.{name}"
        if counters is None:
            checks.append(Check(check, SKIP, "the backend gave no counters"))
        elif got is None:
            checks.append(Check(check, FAIL, f"no counters for channel {name}", "equal"))
        elif differ:
            checks.append(Check(check, FAIL, "gateware differs from truth: " +
                                ", ".join(differ), "equal"))
        else:
            checks.append(Check(check, PASS, f"kept {got['kept']}, dropped "
                                f"{sum(got[c] for c in CAUSES[1:])}, as the truth says",
                                "equal"))
    header = ["channel", *CAUSES]
    widths = [max(len(r[i]) for r in [header] + rows) + 2 for i in range(len(header))]
    for r in [header] + rows:
        lines.append("  " + r[0].ljust(widths[0])
                     + "".join(cell.rjust(w) for cell, w in zip(r[1:], widths[1:])))
    lines.append("  (kept, then dropped by cause; a cell with one number: both agree)")
    return lines, checks, table


def _faults(truth, counters):
    """The injected faults (truth) and the counters their frames land in: per channel and
    cause, what the faults expect, the truth's total (the faults plus everything else that
    drops frames there, such as the GPS's distractor sentences) and the gateware's."""
    faults = truth.get("faults") or []
    if not faults:
        return [], {}
    lines = ["Faults injected (truth) and the counters they land in"]
    expected = {}
    for fault in faults:
        where = fault.get("channel") or "all"
        expect = fault.get("expect")
        what = (f"expect {expect['frames']} frame(s) dropped as {expect['cause']}"
                if expect else "no frame dropped (expect: none)")
        lines.append(f"  {fault.get('kind', '?'):13s} {where:7s} "
                     f"{fault.get('start_s', float('nan')):7.2f}-"
                     f"{fault.get('end_s', float('nan')):<8.2f} x{fault.get('count', '?')}: "
                     f"{what}")
        if expect and fault.get("channel"):
            key = (fault["channel"], expect["cause"])
            expected[key] = expected.get(key, 0) + int(expect["frames"])
    table = {}
    for (channel, cause), n in sorted(expected.items()):
        total = (truth.get("frames") or {}).get(channel, {}).get(cause)
        got = None if counters is None else (counters.get(channel) or {}).get(cause)
        table[f"{channel}.{cause}"] = {"faults_expect": n, "truth": total, "gateware": got}
        lines.append(f"  {channel + ' ' + cause:24s} faults expect {n}, truth {total}, "
                     f"gateware {'-' if got is None else got}"
                     + ("" if got is None or got == total else " *"))
    return lines, table


# -- The log file ---------------------------------------------------------------------------

def _channel_of(frame):
    """Which channel a kept frame came from, by its form (DESIGN.md "Formats")."""
    if frame.startswith(b"$PMAG1,"):
        return "mag"
    if len(frame) > 2 and frame[1:2] in (b" ", b"1") and frame[2:3].isdigit():
        return "cesium"
    return "gps"


def log_frames(data):
    """Frames of a log file per channel (``$`` through LF), and the bytes after the last
    LF (a cut frame: 0 on a cleanly closed log)."""
    counts = dict.fromkeys(CHANNELS, 0)
    lines = data.split(b"\n")
    for line in lines[:-1]:
        counts[_channel_of(line)] += 1
    return counts, len(lines[-1])


def _log(truth, logs):
    recorded = truth.get("recorded")
    if not isinstance(recorded, dict):
        raise ValueError(f"truth['recorded'] must be a dict, not {recorded!r}")
    lines = ["Log file on the card against the truth"]
    if not logs:
        return (lines + ["  no LOG*.TXT on the card"],
                [Check("log", FAIL, "no log file on the card", "equal bytes")], {})
    digests = [(name, data, hashlib.sha256(data).hexdigest()) for name, data in logs]
    match = [d for d in digests if d[2] == recorded.get("sha256")]
    name, data, digest = match[0] if match else max(digests, key=lambda d: len(d[1]))
    counts, tail = log_frames(data)
    total = sum(counts.values())
    want = recorded.get("per_channel", {})
    lines.append(f"  {name} ({len(logs)} log file{'s' if len(logs) != 1 else ''} on the card)")
    lines.append(f"  {'':10s}{'card':>12s}{'truth':>12s}")
    rows = [("frames", total, recorded.get("frames"))]
    rows += [(f"  {ch}", counts[ch], want.get(ch)) for ch in CHANNELS]
    rows.append(("bytes", len(data), recorded.get("bytes")))
    for label, got, expected in rows:
        mark = "" if got == expected else " *"
        lines.append(f"  {label:10s}{got:>12}{str(expected):>12s}{mark}")
    same = digest == recorded.get("sha256")
    lines.append(f"  sha256 {digest[:16]}… {'matches' if same else 'differs from'} the "
                 f"truth's {str(recorded.get('sha256'))[:16]}…")
    info = {"name": name, "files": len(logs), "frames": total, "per_channel": counts,
            "bytes": len(data), "sha256": digest, "cut_tail_bytes": tail, "sha256_match": same}
    if same:
        check = Check("log", PASS, f"{name}: {total} frames, {len(data)} bytes, identical to "
                      "the truth's", "equal bytes")
    else:
        diffs = [f"{label.strip()} {got} vs {expected}" for label, got, expected in rows
                 if got != expected]
        more = f"; {tail} bytes after the last line end" if tail else ""
        check = Check("log", FAIL, f"{name} differs from the truth: " +
                      (", ".join(diffs) or "same counts, other bytes") + more, "equal bytes")
    return lines, [check], info


# -- Calibration ----------------------------------------------------------------------------

def canonical_kc(k, c):
    """The scalar model's (K, c) in its canonical form: K upper triangular with a positive
    diagonal. Any K' with |K' b - c'| = |B| is Q K for a rotation Q (QR), and then
    c = Q^T c'; an upper-triangular K with a positive diagonal comes back unchanged."""
    k, c = np.asarray(k, dtype=float), np.asarray(c, dtype=float)
    if k.shape != (3, 3) or c.shape != (3,):
        raise ValueError(f"K must be 3x3 and c 3 long, not shapes {k.shape} and {c.shape}")
    q, r = np.linalg.qr(k)
    signs = np.where(np.diag(r) < 0, -1.0, 1.0)
    return r * signs[:, None], (q * signs).T @ c


def recovered_kc(run):
    """The run's K, c (canonical) and 1σ per parameter. The ellipsoid fit gives them in
    this form too (|W (b - centre)| = field: W = Q K, c = K centre)."""
    res = run.result
    k, c = canonical_kc(res.K, res.c)
    return k, c, np.asarray(res.uncertainties, dtype=float)


def _residual(truth, run):
    floor = truth.get("noise_floor_nT")
    raw = np.linalg.norm(run.b, axis=1) - run.r
    before = float(np.sqrt(np.mean(raw ** 2)))
    after = float(np.sqrt(np.mean(run.residual ** 2)))
    lines = ["Total-field residual |B| - reference, RMS",
             f"  before {before:10.2f} nT", f"  after  {after:10.2f} nT"]
    info = {"rms_before_nT": before, "rms_after_nT": after, "noise_floor_nT": floor}
    low, high = RESIDUAL_RATIO
    tol = f"{low:g}..{high:g} x floor"
    if not isinstance(floor, (int, float)) or not floor > 0:
        lines.append("  noise floor: not in the truth")
        return lines, [Check("residual", SKIP, "the truth gives no noise floor")], info
    ratio = after / floor
    info.update(ratio_after=ratio, ratio_before=before / floor)
    lines.append(f"  floor  {floor:10.2f} nT  (after / floor = {ratio:.3f}, before / floor "
                 f"= {before / floor:.3g})")
    detail = f"{after:.2f} nT RMS after, {ratio:.3f} x the noise floor {floor:.2f} nT " \
             f"(before: {before:.4g} nT)"
    status = PASS if low <= ratio <= high else FAIL
    if status == FAIL:
        detail += "; above the floor" if ratio > high else "; below the floor: not the " \
                                                           "truth's noise"
    return lines, [Check("residual", status, detail, tol)], info


def _parameters(truth, run):
    errors = truth.get("errors") or {}
    if "K" not in errors or "c" not in errors:
        return ["Parameters: the truth gives no K and c"], \
            [Check("parameters", SKIP, "the truth gives no K and c")], {}
    k_true, c_true = canonical_kc(errors["K"], errors["c"])
    k, c, sigma = recovered_kc(run)
    iu = np.triu_indices(3)
    ours = np.concatenate([k[iu], c])
    true = np.concatenate([k_true[iu], c_true])
    diff = ours - true
    with np.errstate(invalid="ignore", divide="ignore"):
        z = np.where(np.isfinite(sigma) & (sigma > 0), diff / np.where(sigma > 0, sigma, 1),
                     np.nan)
    verdict = run.coverage
    determined = np.asarray(verdict.determined, bool)
    field_sigma = verdict.determination.sigma_nT
    lines = [f"Recovered parameters ({run.method}) against the truth; scored only where the "
             f"flight determines them (1 sigma in nT of field <= "
             f"{verdict.determination.bound_text})",
             f"  {'':5s}{'recovered':>14s}{'truth':>14s}{'difference':>13s}{'1 sigma':>11s}"
             f"{'z':>8s}{'1 sigma nT':>12s}  determined"]
    bad, undetermined, rows = [], [], {}
    for i, name in enumerate(PARAMETERS):
        absolute = C_ABS_NT if name.startswith("c") else K_ABS
        small = abs(diff[i]) <= absolute
        within = bool(np.isfinite(z[i])) and abs(z[i]) <= Z_MAX
        fmt = ".2f" if name.startswith("c") else ".6f"
        s = f"{sigma[i]:.2g}" if np.isfinite(sigma[i]) else "none"
        zs = f"{z[i]:+.1f}" if np.isfinite(z[i]) else ""
        fs = f"{field_sigma[i]:.3g}" if np.isfinite(field_sigma[i]) else "none"
        if not determined[i]:
            mark, state = "", "no: not scored"
            undetermined.append(name)
        else:
            mark, state = ("", "yes") if (small or within) else (" *", "yes")
            if not (small or within):
                bad.append(f"{name} off by {diff[i]:+.3g} (z {z[i]:+.1f})")
        lines.append(f"  {name:5s}{ours[i]:>14{fmt}}{true[i]:>14{fmt}}{diff[i]:>+13{fmt}}"
                     f"{s:>11s}{zs:>8s}{fs:>12s}  {state}{mark}")
        rows[name] = {"recovered": ours[i], "truth": true[i], "difference": diff[i],
                      "sigma": sigma[i], "z": z[i], "sigma_nT": field_sigma[i],
                      "determined": bool(determined[i])}
    tol = (f"scored where determined (1 sigma <= {verdict.determination.bound_nT:.3g} nT of "
           f"field); there |z| <= {Z_MAX:g}, or |dK| <= {K_ABS:g} and |dc| <= {C_ABS_NT:g} nT")
    scored = np.abs(z)[determined & np.isfinite(z)]
    worst = f", largest |z| {np.max(scored):.1f}" if scored.size else ""
    if verdict.verdict == "failed":
        check = Check("parameters", FAIL, f"the fit failed: {verdict.fit_message}", tol)
    elif bad:
        check = Check("parameters", FAIL, "not recovered: " + ", ".join(bad) + (
            f"; not determined by this flight (not scored): {', '.join(undetermined)}"
            if undetermined else ""), tol)
    elif undetermined:
        kept = [n for n, d in zip(PARAMETERS, determined) if d]
        check = Check("parameters", UNDETERMINED,
                      f"the flight does not determine {', '.join(undetermined)} (1 sigma "
                      f"{verdict.determination.figures(undetermined)}; bound "
                      f"{verdict.determination.bound_text}): not scored"
                      + (f"; the {len(kept)} determined within tolerance{worst}" if kept
                         else ""), tol)
    else:
        check = Check("parameters", PASS, f"every parameter determined; K within "
                      f"{np.max(np.abs(diff[:6])):.2g}, c within "
                      f"{np.max(np.abs(diff[6:])):.2g} nT of the truth{worst}", tol)
    rows["undetermined"] = undetermined
    return lines, [check], rows


# -- The whole ------------------------------------------------------------------------------

def summarize(truth, counters, logs, run, *, calibration_error=None, seed=None):
    """Score a run against the scenario's truth (see the module docstring).

    ``truth``: the dict of truth.json (version 1); ``counters``: the gateware's counters
    per channel and cause, or None when the backend gives none; ``logs``: ``[(name,
    bytes)]`` read from the card; ``run``: the :class:`~maglog.calib.pipeline.CalibrationRun`,
    or None (or the exception) when the calibration failed; ``calibration_error``: why it
    failed (an exception or text), said in the summary; ``seed``: the PSO's and papers'
    seed (``maglog run --seed``), named in the title beside the scenario's own seed."""
    if not isinstance(truth, dict):
        raise ValueError(f"truth must be the dict of a truth.json of version 1, not "
                         f"{type(truth).__name__}")
    if truth.get("version") != 1:
        raise ValueError(f"truth must be the dict of a truth.json of version 1, not version "
                         f"{truth.get('version')!r}")
    if isinstance(run, BaseException):
        run, calibration_error = None, run
    if run is not None and not isinstance(run, CalibrationRun):
        raise ValueError(f"run must be a CalibrationRun or None, not {type(run).__name__}")
    title = (f"maglog run: scenario {truth.get('scenario', '?')} (scenario seed "
             f"{truth.get('seed', '?')})" + ("" if seed is None else
                                            f", PSO and papers' seed {seed} (--seed)"))
    blocks, checks, data = [[title, "=" * len(title)]], [], {}
    lines, found, data["frames"] = _frames(truth, counters)
    blocks.append(lines)
    checks += found
    lines, data["faults"] = _faults(truth, counters)
    if lines:
        blocks.append(lines)
    lines, found, data["log"] = _log(truth, logs or [])
    blocks.append(lines)
    checks += found
    if run is None:
        why = str(calibration_error) if calibration_error is not None else "no result given"
        blocks.append([f"Calibration failed: {why}"])
        checks.append(Check("calibration", FAIL, f"no calibration: {why}"))
    else:
        data["calibration"] = {"log": run.log_name, "method": run.method,
                               "reference": run.reference, "samples": int(len(run.b)),
                               "warnings": list(run.warnings)}
        lines, found, data["residual"] = _residual(truth, run)
        blocks.append([f"Calibration of {run.log_name}: {run.method} against the "
                       f"{run.reference}, {len(run.b)} samples"])
        blocks.append(lines)
        checks += found
        lines, found, data["parameters"] = _parameters(truth, run)
        data["undetermined"] = data["parameters"].pop("undetermined", [])
        blocks.append(lines)
        checks += found
        if run.warnings:
            blocks.append(["Calibration warnings"] + [f"  - {w}" for w in run.warnings])
    summary = Summary(text="", checks=checks, data=data)
    blocks.append(["Verdicts"] + [f"  {c.line()}" for c in checks]
                  + [f"  => {summary.verdict}"])
    summary.text = "\n\n".join("\n".join(block) for block in blocks) + "\n"
    return summary
