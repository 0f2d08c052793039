"""HTML pages of maglog's reports: one stylesheet, one page frame, Markdown made safe.

Every HTML report (``maglog calibrate``'s and ``maglog survey``'s ``report.html``, and the
run's report written by :mod:`maglog.cli.report_html`) is a single file with its
stylesheet embedded: a readable sans-serif at a limited width with margins, ruled tables
that scroll sideways inside the page when they are wider than it, figures centred at
their own size (never wider than the text) with a caption under each, a look that does
not depend on colour alone (every verdict is also a word), and print rules (no width
limit, figures and table rows kept whole). Nothing is fetched from elsewhere: the pages
read the same offline.

``markdown_html(text)`` turns a report's Markdown into an HTML fragment (Python-Markdown
with tables and fenced code; raw HTML in the text is shown as text, never interpreted),
with every image standing alone in a paragraph made a captioned figure;
``page(title, body)`` wraps a fragment into the document; ``markdown_page(text, title)``
does both.
"""

import html
import re
from pathlib import PurePosixPath


__all__ = ["STYLESHEET", "CAPTIONS", "caption", "figure", "markdown_html", "page",
           "markdown_page", "escape"]

escape = html.escape

STYLESHEET = """
:root {
  --ink: #1e2228; --muted: #586070; --rule: #d5dae2; --head: #eef1f5; --stripe: #f8f9fb;
  --accent: #1f4e8c; --pass: #17652f; --pass-bg: #e5f3e8; --fail: #a3161b;
  --fail-bg: #fbe9e8; --skip: #6a5400; --skip-bg: #fdf4d3; --code: #f4f6f8;
}
html { font-size: 16px; -webkit-text-size-adjust: 100%; }
body {
  font-family: "Source Sans 3", "Noto Sans", "DejaVu Sans", "Liberation Sans", Roboto,
    "Segoe UI", "Helvetica Neue", Arial, system-ui, sans-serif;
  color: var(--ink); background: #fff; line-height: 1.55;
  max-width: 62rem; margin: 2.5rem auto 4rem; padding: 0 1.5rem;
  overflow-wrap: break-word;
}
h1 { font-size: 1.9rem; line-height: 1.2; margin: 0 0 .4rem; }
h2 { font-size: 1.4rem; margin: 2.4rem 0 .8rem; padding-bottom: .25rem;
     border-bottom: 2px solid var(--rule); }
h3 { font-size: 1.15rem; margin: 1.8rem 0 .6rem; }
p, ul, ol { margin: .6rem 0; }
li { margin: .2rem 0; }
a { color: var(--accent); }
.subtitle { color: var(--muted); margin: 0 0 1.5rem; }
code, pre { font-family: "DejaVu Sans Mono", "Liberation Mono", Menlo, Consolas, monospace;
            font-size: .88em; }
code { background: var(--code); padding: .05em .3em; border-radius: 3px; }
pre { background: var(--code); padding: .8rem 1rem; overflow-x: auto; border-radius: 4px;
      line-height: 1.4; }
pre code { background: none; padding: 0; }
.wide { overflow-x: auto; margin: 1rem 0; }
table { border-collapse: collapse; font-size: .92rem; font-variant-numeric: tabular-nums;
        margin: 0; }
th, td { border: 1px solid var(--rule); padding: .35rem .65rem; vertical-align: top; }
th { background: var(--head); text-align: left; font-weight: 600; }
tbody tr:nth-child(even) { background: var(--stripe); }
td.num, th.num { text-align: right; white-space: nowrap; }
.wide td:first-child { min-width: 9rem; }
figure { margin: 2rem auto; text-align: center; break-inside: avoid; page-break-inside: avoid; }
figure img { display: block; margin: 0 auto; max-width: 100%; height: auto;
             border: 1px solid var(--rule); border-radius: 3px; }
figcaption { color: var(--muted); font-size: .92rem; max-width: 48rem; margin: .6rem auto 0;
             text-align: center; }
figcaption .name { font-family: "DejaVu Sans Mono", "Liberation Mono", monospace;
                   font-size: .85em; }
.banner { border: 1px solid var(--rule); border-left: .5rem solid var(--muted);
          padding: .8rem 1rem; margin: 1rem 0; border-radius: 3px; font-size: 1.05rem; }
.banner.pass { border-left-color: var(--pass); background: var(--pass-bg); }
.banner.fail { border-left-color: var(--fail); background: var(--fail-bg); }
.banner.skip, .banner.undetermined { border-left-color: var(--skip);
                                     background: var(--skip-bg); }
.status { font-weight: 700; white-space: nowrap; }
.status.pass { color: var(--pass); background: var(--pass-bg); }
.status.fail { color: var(--fail); background: var(--fail-bg); }
.status.skip, .status.undetermined { color: var(--skip); background: var(--skip-bg); }
.note { color: var(--muted); font-size: .92rem; }
.references li { margin: .5rem 0; }
footer { margin-top: 3rem; padding-top: .8rem; border-top: 1px solid var(--rule);
         color: var(--muted); font-size: .85rem; }
@media (max-width: 40rem) {
  body { margin: 1rem auto 2rem; padding: 0 .8rem; }
  h1 { font-size: 1.5rem; }
  table.verdicts thead { display: none; }
  table.verdicts, table.verdicts tbody, table.verdicts tr, table.verdicts td {
    display: block; }
  table.verdicts tr { border: 1px solid var(--rule); margin: 0 0 .6rem; }
  table.verdicts td { border: none; }
  table.verdicts td:last-child::before { content: "tolerance: "; color: var(--muted); }
}
@media print {
  @page { margin: 16mm 14mm; }
  html { font-size: 10.5pt; }
  body { max-width: none; margin: 0; padding: 0; }
  a { color: inherit; text-decoration: none; }
  .wide { overflow: visible; }
  table { font-size: 8pt; }
  th, td { padding: 2px 4px; }
  td.num, th.num { white-space: normal; }
  .wide td:first-child { min-width: 0; }
  h2, h3 { break-after: avoid; page-break-after: avoid; }
  tr, .banner { break-inside: avoid; page-break-inside: avoid; }
  figure img { max-height: 120mm; width: auto; }
  .status, .banner, th, tbody tr:nth-child(even) { -webkit-print-color-adjust: exact;
                                                   print-color-adjust: exact; }
}
"""

_PAGE = """<!DOCTYPE html>
<html lang="en">
<head>
<meta charset="utf-8">
<meta name="viewport" content="width=device-width, initial-scale=1">
<title>{title}</title>
<style>{style}</style>
</head>
<body>
{body}
</body>
</html>
"""

#: What each plot of a report shows, by its file name without ".png" (a plot not named
#: here is captioned with its Markdown alt text).
CAPTIONS = {
    "figure7": "Total field |B| before and after the calibration, with the reference it "
               "was fitted to.",
    "coverage": "Attitude coverage: the directions the field took in the sensor's frame "
                "during the flight, which decide which parameters the flight determines.",
    "residuals": "Residual after the calibration: calibrated |B| minus the reference.",
    "allan": "Allan deviation of the residual, with the noise terms fitted where the "
             "curve has their slope.",
    "heading_error": "Heading error: the magnetometer's tilt-compensated heading against "
                     "the known one, before and after the alignment.",
    "paper_a_figure7": "Paper A, Figure 7 made from this run: raw, compensated and "
                       "reference total field.",
    "paper_b_heading": "Paper B, their Fig. 5 made again: mean heading error against "
                       "samples per octant, and the fit's scatter.",
    "paper_c_allan": "Paper C: Allan deviation of a series made for it, before and after "
                     "the Kalman filter.",
    "map": "Levelled total-field anomaly over the surveyed area, with the flown lines.",
    "compensation": "Tolles–Lawson compensation in the calibration box.",
    "levelling": "Crossover differences before and after levelling.",
}


def caption(src, alt=""):
    """The caption of the image at ``src``: :data:`CAPTIONS` by its stem, else ``alt``."""
    stem = PurePosixPath(src).stem
    return CAPTIONS.get(stem) or alt or stem


def figure(src, alt=None, text=None):
    """A centred figure of the image file ``src`` (a name beside the page) with its caption
    and its file name."""
    src_text = escape(src)
    label = text if text is not None else caption(src, alt or "")
    return (f'<figure><a href="{src_text}"><img src="{src_text}" alt="{escape(alt or label)}"'
            f' loading="eager"></a><figcaption>{escape(label)} '
            f'<span class="name">({escape(PurePosixPath(src).name)})</span></figcaption>'
            '</figure>')


_ALONE = re.compile(r"<p>\s*(<img\b[^>]*>)\s*</p>")
_ATTR = re.compile(r'\b(src|alt)="([^"]*)"')
_HEADING = re.compile(r"<(/?)h([1-6])\b")


def _figures(fragment):
    def one(match):
        attrs = dict(_ATTR.findall(match.group(1)))
        # The attributes are escaped already: unescape before figure() escapes again.
        return figure(html.unescape(attrs.get("src", "")), html.unescape(attrs.get("alt", "")))
    return _ALONE.sub(one, fragment)


def _tables(fragment):
    return fragment.replace("<table>", '<div class="wide"><table>').replace(
        "</table>", "</table></div>")


def markdown_html(text, *, demote=0):
    """Markdown → an HTML fragment: tables (inside a sideways-scrolling box) and fenced code,
    every image alone in its paragraph a captioned figure, headings ``demote`` levels down
    (at most h6). Raw HTML and entities in the text are shown as text."""
    import markdown
    md = markdown.Markdown(extensions=["tables", "fenced_code"], output_format="html")
    md.preprocessors.deregister("html_block")
    md.inlinePatterns.deregister("html")
    md.inlinePatterns.deregister("entity")
    fragment = _tables(_figures(md.convert(text)))
    if demote:
        fragment = _HEADING.sub(lambda m: f"<{m.group(1)}h{min(int(m.group(2)) + demote, 6)}",
                                fragment)
    return fragment


def page(title, body):
    """The whole document: ``title`` (plain text) and the HTML fragment ``body``."""
    return _PAGE.format(title=escape(title), style=STYLESHEET, body=body)


def markdown_page(text, title):
    """A report's Markdown as a styled page (see :func:`markdown_html`)."""
    return page(title, markdown_html(text))
