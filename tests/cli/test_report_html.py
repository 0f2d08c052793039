"""The HTML reports in a real browser: headless Chromium (Debian's ``chromium``) loads the
run's ``report/report.html`` and the calibrate command's, and a script in the page reports
what it sees: every image loaded (``naturalWidth`` > 0), nothing wider than the window
(outside the boxes that scroll sideways on purpose), the stylesheet applied (a sans-serif
body at a limited width, figures centred at a readable size).

The same checks run on pages broken on purpose (an image removed, the stylesheet removed, a
line that cannot wrap) and must find each fault. Without Chromium the tests skip (fail
under ``CI=true``: scripts/setup.sh installs it). One quick run on the model backend
(about 10 s) serves the whole module.

``MAGLOG_REPORT_SCREENSHOT=DIR`` saves a full-page screenshot of each page checked there,
to look at.
"""

import json
import os
import re
import shutil
import subprocess
from pathlib import Path

import pytest

from maglog.calib.files import default_mode, umask
from maglog.calib.html import STYLESHEET
from maglog.calib.pipeline import write_report
from maglog.cli.main import main
from maglog.cli.papers import PAPERS
from maglog.cli.report_html import REPORT_NAME, write_run_report

#: Window widths the pages are checked at: a laptop, and a phone held sideways (500 px is
#: the narrowest window headless Chromium makes).
WIDE, NARROW = 1280, 500

#: Put into a copy of the page: on load, write what the page looks like into the DOM,
#: where --dump-dom prints it.
PROBE = """<script>
window.addEventListener("load", function () {
  var view = document.documentElement.clientWidth, body = document.body;
  var style = getComputedStyle(body), box = body.getBoundingClientRect();
  var out = {view: view, scroll_width: document.documentElement.scrollWidth,
             font: style.fontFamily, max_width: style.maxWidth,
             body: {left: box.left, right: box.right, width: box.width},
             images: [], overflow: []};
  document.querySelectorAll("img").forEach(function (img) {
    var r = img.getBoundingClientRect();
    out.images.push({src: img.getAttribute("src"), complete: img.complete,
                     natural: img.naturalWidth, left: r.left, right: r.right,
                     width: r.width});
  });
  function check(node, el, r) {     /* a box or a run of text beyond the window's sides */
    if (!r.width || (r.right <= view + 1 && r.left >= -1)) return;
    for (var p = el.parentElement; p && p !== body; p = p.parentElement) {
      var o = getComputedStyle(p).overflowX;
      if (o === "auto" || o === "scroll") return;      /* scrolls inside the page */
    }
    out.overflow.push(el.tagName.toLowerCase() + " " + Math.round(r.right) + " px: " +
                      (node.textContent || "").trim().slice(0, 60));
  }
  body.querySelectorAll("*").forEach(function (el) {
    check(el, el, el.getBoundingClientRect());
  });
  var walk = document.createTreeWalker(body, NodeFilter.SHOW_TEXT), text, range;
  while ((text = walk.nextNode())) {
    if (!text.textContent.trim()) continue;
    range = document.createRange();
    range.selectNodeContents(text);
    check(text, text.parentElement, range.getBoundingClientRect());
  }
  var pre = document.createElement("pre");
  pre.id = "maglog-probe";
  pre.textContent = JSON.stringify(out);
  body.appendChild(pre);
});
</script>"""


def probe(chromium, page, width, screenshots=None):
    """What the page at ``page`` looks like in Chromium at ``width`` px (PROBE's dict)."""
    text = page.read_text(encoding="utf-8")
    copy = page.with_name(f".probe-{width}-{page.name}")
    copy.write_text(text.replace("</body>", PROBE + "</body>"), encoding="utf-8")
    command = [chromium, "--headless", "--no-sandbox", "--disable-gpu",
               "--hide-scrollbars", "--run-all-compositor-stages-before-draw",
               "--virtual-time-budget=10000", f"--window-size={width},900"]
    try:
        done = subprocess.run(command + ["--dump-dom", copy.as_uri()], capture_output=True,
                              text=True, timeout=60)
        if screenshots:
            shot = Path(screenshots) / f"{page.parent.name}-{page.stem}-{width}.png"
            subprocess.run(command[:-1] + [f"--window-size={width},12000",
                                           f"--screenshot={shot}", page.as_uri()],
                           capture_output=True, timeout=60)
    finally:
        copy.unlink()
    found = re.search(r'<pre id="maglog-probe">(.*?)</pre>', done.stdout, re.S)
    assert found, f"chromium printed no probe (exit {done.returncode}): {done.stderr[-500:]}"
    return json.loads(found.group(1).replace("&lt;", "<").replace("&gt;", ">")
                      .replace("&quot;", '"').replace("&amp;", "&"))


def problems(seen):
    """What is wrong with a page as Chromium saw it (``probe``'s dict): [] when nothing."""
    found = []
    for img in seen["images"]:
        if not img["complete"] or img["natural"] <= 0:
            found.append(f"image not loaded: {img['src']}")
    if seen["scroll_width"] > seen["view"] + 1:
        found.append(f"the page is {seen['scroll_width']} px wide in a {seen['view']} px "
                     "window")
    found += [f"overflows the window: {what}" for what in seen["overflow"][:5]]
    families = [f.strip().strip('"').lower() for f in seen["font"].split(",")]
    if "sans-serif" not in families or families[0] in ("serif", "times new roman", "times"):
        found.append(f"unstyled text: body font {seen['font']!r}")
    if seen["max_width"] in ("none", ""):
        found.append("no width limit on the text (max-width none)")
    body = seen["body"]
    if seen["view"] >= 1000:
        if body["width"] > 1100 or body["left"] < 100:
            found.append(f"text spans {body['width']:.0f} px from {body['left']:.0f} px: "
                         "no margins")
        centre = (body["left"] + body["right"]) / 2
        for img in seen["images"]:
            if img["natural"] <= 0:
                continue
            if img["width"] < min(img["natural"], 500):
                found.append(f"image shown at {img['width']:.0f} px: {img['src']}")
            if img["right"] > body["right"] + 1 or img["left"] < body["left"] - 1:
                found.append(f"image outside the text's width: {img['src']}")
            if abs((img["left"] + img["right"]) / 2 - centre) > 2:
                found.append(f"image not centred: {img['src']}")
    return found


@pytest.fixture(scope="module")
def chromium(external):
    return external.tool("chromium", why="the HTML reports' browser test")


@pytest.fixture(scope="module")
def run_folder(tmp_path_factory):
    """A quick run on the model backend (its report folder)."""
    out = tmp_path_factory.mktemp("html") / "run"
    main(["run", "--backend", "model", "--quick-papers", "--quiet", "-o", str(out)])
    report = out / "report"
    assert (report / REPORT_NAME).is_file()
    return report


def _screenshots():
    return os.environ.get("MAGLOG_REPORT_SCREENSHOT")


@pytest.mark.parametrize("width", [WIDE, NARROW])
def test_the_run_report_reads_in_a_browser(chromium, run_folder, width):
    seen = probe(chromium, run_folder / REPORT_NAME, width, _screenshots())
    assert problems(seen) == []
    # Every figure of the folder is in the page.
    pngs = {p.name for p in run_folder.glob("*.png")}
    assert len(pngs) >= 6
    assert {img["src"] for img in seen["images"]} == pngs


def test_the_run_report_holds_verdicts_calibration_and_the_papers(run_folder):
    import html5lib
    page = html5lib.HTMLParser(strict=True).parse((run_folder / REPORT_NAME).read_bytes())
    ns = "{http://www.w3.org/1999/xhtml}"
    text = lambda el: "".join(el.itertext())                            # noqa: E731
    title = page.find(f"{ns}head/{ns}title").text
    truth = json.loads((run_folder.parent / "truth.json").read_text())
    assert f"scenario {truth['scenario']}" in title and "model backend" in title
    assert re.search(r"\d{4}-\d\d-\d\d", title)
    headings = [text(h) for h in page.iter(f"{ns}h2")]
    assert headings[:3] == ["Verdicts", "Calibration", "The papers' results beside ours"]
    # The verdicts table: one row per check of summary.json, the verdict as a word.
    summary = json.loads((run_folder / "summary.json").read_text())
    table = page.find(f".//{ns}table")
    rows = [[text(td).strip() for td in tr.iter(f"{ns}td")]
            for tr in table.find(f"{ns}tbody")]
    assert [(r[0].split()[-1], r[1]) for r in rows] == [
        (c["status"].upper(), c["name"]) for c in summary["checks"]]
    banner = text(page.find(f".//{ns}p[@id='verdict']"))
    if "verdict" in summary:
        assert banner.strip() == summary["verdict"]
    else:
        assert banner.startswith("PASS" if summary["ok"] else "FAIL")
    # The calibration: the gate's message and the parameters as parameters.json has them.
    parameters = json.loads((run_folder / "parameters.json").read_text())
    body = text(page.find(f"{ns}body"))
    assert parameters["coverage_gate"]["message"] in body
    assert all(w in body for w in parameters["warnings"])
    for name in parameters["parameters"]:
        assert any(r and r[0] == name for r in (
            [text(td).strip() for td in tr.iter(f"{ns}td")] for tr in page.iter(f"{ns}tr")))
    # Each paper named and cited; no link leaves the folder.
    for key, paper in PAPERS.items():
        assert f"Paper {key} ({paper['short']})" in body
        assert paper["authors"] in body
    assert PAPERS["A"]["title"] in body and "2018" in body
    links = [a.get("href") for a in page.iter(f"{ns}a")] + \
        [img.get("src") for img in page.iter(f"{ns}img")]
    assert links and all("/" not in link and ":" not in link for link in links), links
    assert "../shared" not in (run_folder / "papers.md").read_text()
    assert STYLESHEET in (run_folder / REPORT_NAME).read_text()


def test_the_calibrate_report_reads_in_a_browser(chromium, flown, tmp_path):
    _, _, _, _, run, _ = flown
    paths = write_report(run, tmp_path / "calibration")
    page = Path(paths["html"])
    assert STYLESHEET in page.read_text()
    seen = probe(chromium, page, WIDE, _screenshots())
    assert problems(seen) == []
    assert {img["src"] for img in seen["images"]} == \
        {p.name for p in page.parent.glob("*.png")}


def _broken_copy(run_folder, tmp_path, edit):
    folder = tmp_path / "broken"
    shutil.copytree(run_folder, folder)
    page = folder / REPORT_NAME
    page.write_text(edit(page.read_text()))
    return folder, page


def test_a_missing_image_is_found(chromium, run_folder, tmp_path):
    folder, page = _broken_copy(run_folder, tmp_path, lambda text: text)
    (folder / "residuals.png").unlink()
    assert problems(probe(chromium, page, WIDE)) == ["image not loaded: residuals.png"]


def test_an_unstyled_page_is_found(chromium, run_folder, tmp_path):
    _, page = _broken_copy(run_folder, tmp_path,
                           lambda text: re.sub(r"<style>.*?</style>", "", text, flags=re.S))
    found = problems(probe(chromium, page, WIDE))
    assert any(p.startswith("unstyled text") for p in found), found
    assert "no width limit on the text (max-width none)" in found
    assert any("no margins" in p for p in found), found


def test_text_wider_than_the_window_is_found(chromium, run_folder, tmp_path):
    _, page = _broken_copy(run_folder, tmp_path, lambda text: text.replace(
        "</h1>", "</h1><p style='white-space:nowrap'>" + "a-very-long-line " * 40 + "</p>"))
    found = problems(probe(chromium, page, NARROW))
    assert any(p.startswith("overflows the window: p") for p in found), found


# -- Files written with the user's umask ------------------------------------------------------

@pytest.mark.parametrize("mask", [0o022, 0o077])
def test_reports_take_the_umask(flown, tmp_path, mask):
    _, _, _, _, run, _ = flown
    old = os.umask(mask)
    try:
        assert umask() == mask and default_mode() == 0o666 & ~mask
        out = tmp_path / "calibration"
        write_report(run, out)
        (out / "summary.json").write_text(json.dumps({"ok": True, "checks": []}))
        write_run_report(out)
        modes = {p.name: p.stat().st_mode & 0o777 for p in out.iterdir()}
    finally:
        os.umask(old)
    assert modes and set(modes.values()) == {0o666 & ~mask}, modes
    assert not [p for p in out.iterdir() if p.name.startswith(".")]


def test_the_run_writes_with_the_umask(run_folder):
    want = 0o666 & ~umask()
    modes = {p.name: p.stat().st_mode & 0o777 for p in run_folder.iterdir()}
    assert set(modes.values()) == {want}, modes


def test_a_run_without_calibration_still_gets_its_page(run_folder, tmp_path):
    # The calibration failed: no papers.md, and what an earlier run left (its
    # parameters.json and plots) is not shown; markup in a detail is text.
    report = tmp_path / "report"
    report.mkdir()
    checks = [{"name": "log", "status": "fail", "detail": "no <b>log</b> file on the card",
               "tolerance": "equal bytes"},
              {"name": "residual", "status": "skip", "detail": "no calibration",
               "tolerance": ""},
              {"name": "calibration", "status": "fail",
               "detail": "no calibration: too few samples", "tolerance": ""}]
    (report / "summary.json").write_text(json.dumps({
        "ok": False, "failed": ["log", "calibration"], "checks": checks,
        "papers": {"plots": {"paper_b_heading": str(report / "paper_b_heading.png")}}}))
    (report / "paper_b_heading.png").write_bytes((run_folder / "paper_b_heading.png")
                                                 .read_bytes())
    (report / "paper_a_figure7.png").write_bytes(b"an earlier run's plot")
    (report / "parameters.json").write_text(json.dumps({"parameters": {"k11": 1.0}}))
    (report / "figure7.png").write_bytes(b"an earlier run's plot")
    import html5lib
    ns = "{http://www.w3.org/1999/xhtml}"
    page = html5lib.HTMLParser(strict=True).parse(write_run_report(report).read_bytes())
    body = "".join(page.find(f"{ns}body").itertext())
    assert "FAIL: 2 of 3 checks failed (log, calibration). Not checked: residual." in body
    assert "No calibration: too few samples." in body and "k11" not in body
    assert "no <b>log</b> file on the card" in body and page.find(f".//{ns}b") is None
    assert all(PAPERS[key]["authors"] in body for key in PAPERS)
    assert [img.get("src") for img in page.iter(f"{ns}img")] == ["paper_b_heading.png"]
