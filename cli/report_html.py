"""The run's report: one HTML page (``report/report.html``) a person can read and share.

``maglog run -o DIR`` leaves JSON products in ``DIR/report``: summary.json (the verdicts),
parameters.json (the calibration, absent when it failed), papers.md (the papers'
comparison, its figures in papers.json), and the PNGs. :func:`write_run_report` reads them (and
``DIR/truth.json`` for the scenario's name) and writes a single page, replacing the
calibration-only page the calibration wrote there:

1. a title naming the scenario, the backend and the date, and the run's figures in a line;
2. the verdicts first: one banner, then the table of checks (PASS, FAIL or SKIP as words,
   and in colour);
3. the calibration: its figures in a list, the coverage gate's verdict, the warnings, and
   the parameters beside the truth;
4. the papers' comparison, each paper named and cited (:data:`maglog.cli.papers.PAPERS`);
5. every figure of the folder, captioned; the files of the folder.

Everything is read from the JSON products: nothing here judges the run again. The page
uses :mod:`maglog.calib.html`'s stylesheet; it is written with the user's umask
(:mod:`maglog.calib.files`).
"""

import datetime
import json
import math
from pathlib import Path

from ..calib import files
from ..calib.html import escape, figure, markdown_html, page
from .papers import PAPERS, citation


__all__ = ["REPORT_NAME", "write_run_report", "run_report_html"]

#: The page's name inside the report folder (the calibration's own page had this name; a
#: run replaces it with the whole report).
REPORT_NAME = "report.html"
#: The calibration's plots in the order the page shows them.
CALIBRATION_PLOTS = ("figure7", "residuals", "coverage", "heading_error", "allan")
#: The calibration's verdict (parameters.json "verdict") → the banner's look.
_VERDICT_KIND = {"determined": "pass", "undetermined": "undetermined", "failed": "fail"}
_STATUS = {"pass": ("PASS", "✔"), "fail": ("FAIL", "✘"), "skip": ("SKIP", "–"),
           "undetermined": ("UNDETERMINED", "?")}


def _read_json(path):
    try:
        return json.loads(Path(path).read_text(encoding="utf-8"))
    except FileNotFoundError:
        return None


def _number(value, spec):
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value):
        return "–"
    return format(value, spec)


def _table(header, rows, numeric=()):
    """A table; ``rows`` are lists of HTML cells (already escaped); columns in ``numeric``
    are right-aligned."""
    def cells(tag, row):
        return "".join(f'<{tag}{" class=num" if i in numeric else ""}>{c}</{tag}>'
                       for i, c in enumerate(row))
    body = "".join(f"<tr>{cells('td', row)}</tr>" for row in rows)
    return (f'<div class="wide"><table><thead><tr>{cells("th", header)}</tr></thead>'
            f"<tbody>{body}</tbody></table></div>")


def _status_cell(status):
    word, mark = _STATUS.get(status, (str(status).upper(), "?"))
    return f'<td class="status {escape(status)}">{mark} {escape(word)}</td>'


# -- Sections --------------------------------------------------------------------------------

def _title(summary, truth, simulation, when):
    scenario = (truth or {}).get("scenario")
    backend = (summary.get("simulation") or {}).get("backend") or \
        (simulation or {}).get("backend")
    title = "maglog run" + (f": scenario {scenario}" if scenario else "") + \
        (f" on the {backend} backend" if backend else "") + f", {when:%Y-%m-%d}"
    facts = [f"run {when:%Y-%m-%d %H:%M} UTC"]
    seed = (summary.get("papers") or {}).get("seed")
    if seed is not None:
        facts.append(f"seed {seed}")
    sim = summary.get("simulation") or {}
    if isinstance(sim.get("simulated_s"), (int, float)):
        facts.append(f"{sim['simulated_s']:.1f} s of flight simulated in "
                     f"{_number(sim.get('wall_s'), '.1f')} s")
    if isinstance(summary.get("wall_s"), (int, float)):
        facts.append(f"{summary['wall_s']:.0f} s in all")
    if (summary.get("papers") or {}).get("quick"):
        facts.append("papers B and C on quick (small) scenarios")
    stamp = (truth or {}).get("timestamp")
    if stamp:
        facts.append(f"flight dated {str(stamp)[:10]}")
    return title, (f"<h1>{escape(title)}</h1>"
                   f'<p class="subtitle">{escape("; ".join(facts))}</p>')


def _verdicts(summary):
    checks = summary.get("checks") or []
    failed = summary.get("failed") or [c["name"] for c in checks if c.get("status") == "fail"]
    skipped = [c["name"] for c in checks if c.get("status") == "skip"]
    if failed:
        kind = "fail"
    elif summary.get("ok") is False:
        kind = "undetermined"
    else:
        kind = "pass"
    verdict = summary.get("verdict")
    if isinstance(verdict, str) and verdict:
        word, colon, rest = verdict.partition(":")
        text = f"<strong>{escape(word)}</strong>{escape(colon + rest)}"
    elif failed:
        text = (f"<strong>FAIL</strong>: {len(failed)} of {len(checks)} checks failed "
                f"({escape(', '.join(failed))}).")
    elif kind == "pass":
        text = "<strong>PASS</strong>: every check made agrees with the scenario's truth."
    else:
        text = "<strong>NOT PASSED</strong>: see the checks below."
    if skipped and not verdict:
        text += f" Not checked: {escape(', '.join(skipped))}."
    body = "".join(
        f"<tr>{_status_cell(c.get('status', ''))}<td><code>{escape(c.get('name', ''))}</code>"
        f"</td><td>{escape(c.get('detail', ''))}</td><td>{escape(c.get('tolerance', ''))}"
        "</td></tr>" for c in checks)
    table = ('<div class="wide"><table class="verdicts"><thead><tr><th>verdict</th>'
             "<th>check</th><th>what was found</th><th>tolerance</th></tr></thead>"
             f"<tbody>{body}</tbody></table></div>")
    return ('<section id="verdicts"><h2>Verdicts</h2>'
            f'<p class="banner {kind}" id="verdict">{text}</p>{table}'
            '<p class="note">Each check compares the run with the truth of the scenario it '
            "was made from: the gateware's frame counters, the log file on the card, the "
            "residual after the calibration against the injected noise, and the recovered "
            "parameters against the injected errors.</p></section>")


def _calibration(parameters, summary, names):
    out = ['<section id="calibration"><h2>Calibration</h2>']
    if parameters is None:
        why = next((c.get("detail") for name in ("calibration", "residual", "parameters")
                    for c in summary.get("checks") or []
                    if c.get("name") == name and c.get("detail")), None)
        why = (why or "it failed (see the verdicts)").removeprefix("no calibration: ")
        out.append(f"<p>No calibration: {escape(why)}.</p>")
        return "".join(out) + "</section>"
    p = parameters
    facts = [f"log {p.get('log', '?')}, {p.get('samples', '?')} samples; method "
             f"{p.get('method', '?')}; reference: {p.get('reference', '?')}",
             f"total-field RMS against the reference: {_number(p.get('rms_before_nT'), '.2f')}"
             f" nT before, {_number(p.get('rms_after_nT'), '.2f')} nT after"]
    if p.get("message"):
        facts.append(f"fit: {p['message']}")
    held = p.get("held_out")
    if isinstance(held, dict) and held.get("message"):
        facts.append(f"held out: {held['message']}")
    elif p.get("held_out_note"):
        facts.append(f"held out: not scored ({p['held_out_note']})")
    out.append("<ul>" + "".join(f"<li>{escape(f)}</li>" for f in facts) + "</ul>")
    gate = p.get("coverage_gate") if isinstance(p.get("coverage_gate"), dict) else {}
    message = p.get("verdict_message") or gate.get("message")
    if message:
        verdict = p.get("verdict") or gate.get("verdict")
        kind = _VERDICT_KIND.get(verdict) or \
            {True: "pass", False: "fail"}.get(gate.get("accepted"), "undetermined")
        out.append(f'<p class="banner {kind}" id="calibration-verdict"><strong>Calibration '
                   f"verdict</strong>: {escape(str(message))}</p>")
    warnings = p.get("warnings") or []
    if warnings:
        out.append("<h3>Warnings</h3><ul>"
                   + "".join(f"<li>{escape(str(w))}</li>" for w in warnings) + "</ul>")
    out.append(_parameter_table(p, summary.get("parameters") or {}))
    for key in CALIBRATION_PLOTS:
        if f"{key}.png" in names:
            out.append(figure(f"{key}.png"))
            names.discard(f"{key}.png")
    return "".join(out) + "</section>"


def _parameter_table(p, truths):
    values = p.get("parameters")
    if not isinstance(values, dict) or not values:
        return ""
    sigma = p.get("uncertainties") or {}
    held = set(p.get("held_to_prior") or [])
    rule = p.get("determination") if isinstance(p.get("determination"), dict) else {}
    if isinstance(rule.get("sigma_nT"), dict):       # 1σ in nT of field, and the verdict
        spread, spread_name = rule["sigma_nT"], "1σ in nT of field"
        determined = rule.get("determined") or {}
    else:                                            # an older parameters.json
        spread, spread_name = p.get("dilution_of_precision") or {}, "dilution of precision"
        determined = {n: n not in set(p.get("undetermined") or []) for n in values}
    rows = []
    for name, value in values.items():
        truth = truths.get(name) if isinstance(truths.get(name), dict) else {}
        spec = ".6g" if name.startswith("k") else ".2f"
        state = "no: held to the prior" if name in held else \
            "yes" if determined.get(name) else "no" if name in determined else "–"
        rows.append([f"<code>{escape(name)}</code>", _number(value, spec),
                     _number(sigma.get(name), ".2g"), _number(spread.get(name), ".3g"),
                     escape(state), _number(truth.get("truth"), spec),
                     _number(truth.get("difference"), "+.2g"),
                     _number(truth.get("z"), "+.1f")])
    header = ["parameter", "recovered", "1σ", spread_name, "determined", "truth",
              "difference", "z"]
    note = ("K (k11…k33, the upper triangle) scales and shears the sensor's axes; c "
            "(c1…c3) is its offset in nT; truth, difference and z (difference over 1σ) "
            "come from the scenario.")
    if rule.get("rule"):
        note += f" Determined: {rule['rule']}."
    return ("<h3>Parameters</h3>" + _table(header, rows, numeric={1, 2, 3, 5, 6, 7})
            + f'<p class="note">{escape(note)}</p>')


def _papers(papers_md, names):
    out = ['<section id="papers"><h2>The papers\' results beside ours</h2>']
    if papers_md is not None:
        # papers.md names the papers in its first lines and cites them under References.
        text = papers_md.split("\n", 1)[1] if papers_md.startswith("# ") else papers_md
        out.append(markdown_html(text, demote=1))
        for name in list(names):
            if f'src="{name}"' in out[-1]:
                names.discard(name)
    else:
        out.append("<p>Not computed in this run.</p><h3>References</h3><ul>"
                   + "".join(f"<li>Paper {key}: {escape(citation(key))}</li>"
                             for key in PAPERS) + "</ul>")
    return "".join(out) + "</section>"


def _files(folder, present):
    described = {"summary.json": "the verdicts and the figures behind them",
                 "summary.txt": "the verdicts as the run printed them",
                 "parameters.json": "the calibration's parameters and figures",
                 "report.md": "the calibration report in Markdown",
                 "papers.md": "the papers' comparison in Markdown",
                 "papers.json": "the papers' comparison's figures"}
    items = [f'<li><a href="{escape(n)}">{escape(n)}</a>: {escape(d)}</li>'
             for n, d in described.items() if n in present]
    if not items:
        return ""
    return ('<section id="files"><h2>Files of this report</h2><ul>' + "".join(items)
            + "</ul></section>")


def _calibration_failed(summary):
    """summary.json says the calibration failed: a "calibration" check and no figures."""
    return "calibration" not in summary and any(
        c.get("name") == "calibration" and c.get("status") == "fail"
        for c in summary.get("checks") or [])


def run_report_html(folder, *, when=None):
    """The run's report page (HTML text) from the products in report folder ``folder``
    (``when``: the run's date, a datetime; default now)."""
    folder = Path(folder)
    summary = _read_json(folder / "summary.json")
    if not isinstance(summary, dict):
        raise FileNotFoundError(f"{folder / 'summary.json'}: no run summary to report")
    parameters = _read_json(folder / "parameters.json")
    truth = _read_json(folder.parent / "truth.json")
    simulation = _read_json(folder.parent / "simulation.json")
    try:
        papers_md = (folder / "papers.md").read_text(encoding="utf-8")
    except FileNotFoundError:
        papers_md = None
    when = when or datetime.datetime.now(datetime.timezone.utc)
    present = {p.name for p in folder.iterdir() if p.is_file()}
    names = {n for n in present if n.endswith(".png")}
    plots = (summary.get("papers") or {}).get("plots")
    if isinstance(plots, dict):
        # This run's figures: the calibration's and those summary.json lists for the papers
        # (a PNG an earlier run left in the folder is not this run's).
        names &= {f"{key}.png" for key in CALIBRATION_PLOTS} | \
            {Path(str(path)).name for path in plots.values()}
    if _calibration_failed(summary):
        # What an earlier run left in the folder is not this run's calibration.
        parameters = None
        names -= {f"{key}.png" for key in CALIBRATION_PLOTS}
    title, header = _title(summary, truth if isinstance(truth, dict) else None,
                           simulation if isinstance(simulation, dict) else None, when)
    body = [header, _verdicts(summary),
            _calibration(parameters if isinstance(parameters, dict) else None, summary,
                         names),
            _papers(papers_md, names)]
    if names:
        body.append('<section id="figures"><h2>Other figures</h2>'
                    + "".join(figure(n) for n in sorted(names)) + "</section>")
    body.append(_files(folder, present))
    body.append(f"<footer>Written by maglog from the JSON products in this folder "
                f"({when:%Y-%m-%d %H:%M} UTC). Open it from this folder: the figures are "
                "the PNG files beside it.</footer>")
    return page(title, "\n".join(body))


def write_run_report(folder, *, when=None):
    """Write the run's report page into ``folder`` (see :func:`run_report_html`), whole or
    not at all, with the user's umask; returns its path."""
    folder = Path(folder)
    return files.write_text(folder / REPORT_NAME, run_report_html(folder, when=when))
