"""bench/RESULTS.md against the benchmark JSONs: every table is generated from its JSON and
carries that JSON's provenance line (bench/provenance.py). No benchmark runs here."""

import importlib.util
import json
import re
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[2]
BENCH = REPO / "bench"


def _load(name):
    sys.path.insert(0, str(BENCH))
    try:
        spec = importlib.util.spec_from_file_location(f"bench_{name}", BENCH / f"{name}.py")
        module = importlib.util.module_from_spec(spec)
        spec.loader.exec_module(module)
        return module
    finally:
        sys.path.remove(str(BENCH))


provenance = _load("provenance")
machine = _load("_machine")


@pytest.fixture
def copy(tmp_path):
    """A copy of RESULTS.md and the JSONs to break."""
    (tmp_path / "bench").mkdir()
    shutil.copytree(BENCH / "results", tmp_path / "bench" / "results")
    shutil.copy(BENCH / "RESULTS.md", tmp_path / "bench" / "RESULTS.md")
    return tmp_path


def test_results_md_is_as_generated_from_the_jsons():
    problems = provenance.check()
    assert problems == [], "\n".join(problems) + \
        "\n(rerun `.venv/bin/python bench/provenance.py` after a benchmark)"


def test_every_block_is_in_results_md():
    text = (BENCH / "RESULTS.md").read_text()
    names = [m.group(1) for m in map(provenance.MARKER.match, text.splitlines()) if m]
    assert sorted(names) == sorted(provenance.BLOCKS)


def test_every_json_in_results_md_records_its_provenance():
    for source in {source for source, _ in provenance.BLOCKS.values()}:
        report = json.loads((REPO / source).read_text())
        tree = report["work_tree"]
        assert len(tree["commit"]) == 40, source
        assert isinstance(tree["status_porcelain"], list), source
        assert len(tree["source_sha256"]) == 64, source
        assert re.search(r"\.venv/bin/python bench/\S+\.py", report["command"]), source
        assert report["machine"]["nproc"] >= 1, source
        assert len(report["load_average"]["start"]) == 3, source
        assert len(report["load_average"]["end"]) == 3, source


def test_an_edited_provenance_line_fails(copy):
    path = copy / "bench" / "RESULTS.md"
    text = path.read_text()
    line = next(line for line in text.splitlines() if line.startswith("Provenance ("))
    path.write_text(text.replace(line, line.replace("commit `", "commit `0", 1), 1))
    assert any("differ" in p for p in provenance.check(path, copy))


def test_an_edited_figure_fails(copy):
    path = copy / "bench" / "RESULTS.md"
    text = path.read_text()
    row = next(line for line in text.splitlines() if line.startswith("| `UartRx()`"))
    path.write_text(text.replace(row, row.replace("|", "| 1", 2)[:-1] + "|", 1))
    assert any("differ" in p for p in provenance.check(path, copy))


def test_a_changed_json_fails(copy):
    path = copy / "bench" / "results" / "sdram_bandwidth.json"
    report = json.loads(path.read_text())
    report["load_average"]["end"][0] += 1.0
    path.write_text(json.dumps(report))
    assert any("differ" in p for p in provenance.check(copy / "bench" / "RESULTS.md", copy))


def test_a_table_without_provenance_fails(copy):
    path = copy / "bench" / "RESULTS.md"
    path.write_text(path.read_text() + "\n| a | b |\n|---|---|\n| 1 | 2 |\n")
    assert any("table outside" in p for p in provenance.check(path, copy))


def test_a_block_without_its_provenance_line_fails(copy):
    path = copy / "bench" / "RESULTS.md"
    lines = path.read_text().split("\n")
    k = lines.index("<!-- generated: sdram-bandwidth -->")
    end = next(j for j in range(k, len(lines)) if lines[j].startswith("Provenance ("))
    del lines[end]
    path.write_text("\n".join(lines))
    assert provenance.check(path, copy)


def test_a_provenance_line_naming_another_json_fails(copy):
    path = copy / "bench" / "RESULTS.md"
    text = path.read_text()
    k = text.index("<!-- generated: synth-sdram -->")
    head, tail = text[:k], text[k:]
    tail = tail.replace("Provenance (bench/results/synth.json)",
                        "Provenance (bench/results/sdram_bandwidth.json)", 1)
    path.write_text(head + tail)
    assert any("its provenance names" in p for p in provenance.check(path, copy))


def test_provenance_line_says_what_the_json_holds():
    report = {
        "date": "2026-11-24T01:00:00+00:00", "command": ".venv/bin/python bench/x.py",
        "load_average": {"start": [0.5, 0.4, 0.3], "end": [1.25, 0.5, 0.4]},
        "work_tree": {"commit": "0123456789abcdef" * 2 + "01234567",
                      "status_porcelain": [" M a.py", "?? b.py"],
                      "source_sha256": "ab" * 32,
                      "end": {"commit": "fedcba98" * 5, "changed_during_run": ["a.py"]}}}
    line = machine.provenance_line(report, "bench/results/x.json")
    assert line == ("Provenance (bench/results/x.json): commit `0123456`, 2 uncommitted source "
                    "paths, "
                    "source sha256 abababababab (1 path changed during the run; HEAD moved "
                    "to `fedcba9` during the run); 2026-11-24T01:00:00+00:00; load 0.50→1.25; "
                    "`.venv/bin/python bench/x.py`")
    report["work_tree"].update(status_porcelain=[], end={})
    assert "commit `0123456`, clean, source sha256" in machine.provenance_line(report)
    # Earlier benchmarks' results are outside the source hash, and said apart.
    report["work_tree"].update(status_porcelain=[" M bench/results/a.json",
                                                 "?? bench/results/b.json"])
    assert ("commit `0123456`, clean but for 2 result files (bench/results/), source sha256"
            in machine.provenance_line(report))
    report["work_tree"]["status_porcelain"].append(" M hw/uart.py")
    assert ("commit `0123456`, 1 uncommitted source path and 2 result files, source sha256"
            in machine.provenance_line(report))


def test_the_source_hash_covers_tracked_and_untracked_files(tmp_path, monkeypatch):
    def git(*args):
        subprocess.run(["git", "-c", "user.name=t", "-c", "user.email=t@t", *args],
                       cwd=tmp_path, check=True, capture_output=True)
    git("init", "-q")
    (tmp_path / ".gitignore").write_text("ignored.txt\n")
    (tmp_path / "tracked.py").write_text("a = 1\n")
    git("add", ".gitignore", "tracked.py")
    git("commit", "-q", "-m", "start")
    (tmp_path / "untracked.py").write_text("b = 2\n")
    (tmp_path / "ignored.txt").write_text("x\n")
    (tmp_path / "bench" / "results").mkdir(parents=True)
    (tmp_path / "bench" / "results" / "out.json").write_text("{}\n")
    monkeypatch.setattr(machine, "REPO", tmp_path)

    tree = machine.work_tree()
    assert sorted(tree["_digests"]) == [".gitignore", "tracked.py", "untracked.py"]
    assert tree["status_porcelain"] == ["?? bench/results/out.json", "?? untracked.py"]
    before = tree["source_sha256"]
    (tmp_path / "ignored.txt").write_text("y\n")
    (tmp_path / "bench" / "results" / "out.json").write_text("[]\n")
    assert machine.work_tree()["source_sha256"] == before
    (tmp_path / "untracked.py").write_text("b = 3\n")
    after_untracked = machine.work_tree()["source_sha256"]
    assert after_untracked != before
    (tmp_path / "tracked.py").write_text("a = 2\n")
    assert machine.work_tree()["source_sha256"] != after_untracked
