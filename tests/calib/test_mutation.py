"""The mutation run of ``maglog calibrate`` and ``maglog survey`` (tests/calib/mutants.py):
bad card images, logs, truth and base-station files and option values, as a new user would
meet them, end in a message or in a result whose problems the report states; never a
traceback, a hang, or silent nonsense.

A short run (55 calibrate inputs, every class, and the first 6 survey inputs: issue 23's
findings that are refused in a second) is in the default suite; the long one (1,210
calibrate and 420 survey inputs, every class) under ``-m slow``. ``bench/calib/mutation.py``
runs the long one and writes its counts.
"""

import importlib
import json
import sys
from pathlib import Path

import pytest

# The helper module beside this file (tests are no package): on sys.path by name, so that
# the run's worker processes import it too.
sys.path.insert(0, str(Path(__file__).parent))
mutants = importlib.import_module("mutants")


def _check(results, survey_classes):
    totals, by_class = mutants.counts(results)
    bad = mutants.failures(results)
    listing = "\n".join(f"  #{r['index']} {r['kind']} {r['outcome']}: {r['detail']} -> "
                        f"{r['reason']}" for r in bad)
    assert not bad, f"{len(bad)} of {len(results)} inputs failed ({totals}):\n{listing}"
    # Every class was tried, and the run saw both refusals and calibrations.
    assert set(by_class) == set(mutants.CLASSES) | set(survey_classes)
    assert totals["error"] and totals["ok"] and totals["usage"]


def test_short_mutation_run(fat_tools):
    results, with_images = mutants.run(55, seed=10, tools=fat_tools, survey=6)
    assert with_images and len(results) == 61
    _check(results, {"survey:truth", "survey:option", "survey:scheduler", "survey:base"})


@pytest.mark.slow
def test_long_mutation_run(fat_tools):
    results, with_images = mutants.run(1210, seed=20, tools=fat_tools, survey=420)
    assert with_images and len(results) == 1630
    _check(results, mutants.SURVEY_CLASSES)
    survey = [r for r in results if mutants.is_survey(r)]
    totals, _ = mutants.counts(survey)
    # Survey runs that mapped, warned and were refused were all seen.
    assert totals["ok"] and totals["warned"] and totals["error"] and totals["usage"]


def test_the_run_finds_a_traceback_a_hang_and_nonsense(tmp_path, monkeypatch):
    # The classifier itself: an exception escaping main, an input over the time limit, and
    # an exit 0 whose parameters.json holds NaN are each counted as what they are.
    from maglog.cli import main as cli
    case = mutants.Case(0, "log:values", "test", ["calibrate", "{work}/LOG00001.TXT"],
                        {"LOG00001.TXT": b"$ 49895.131,1249\r\n"})
    mutants._worker_init()

    def raises(argv):
        raise ZeroDivisionError("boom")
    monkeypatch.setattr(cli, "main", raises)
    assert mutants.run_case(case, tmp_path)["outcome"] == "traceback"

    def sleeps(argv):
        import time
        time.sleep(5)
    monkeypatch.setattr(cli, "main", sleeps)
    assert mutants.run_case(case, tmp_path, time_limit=1)["outcome"] == "hang"

    def nan_report(argv):
        out = Path.cwd() / "report"         # run_case works in the scratch folder
        out.mkdir()
        (out / "parameters.json").write_text('{"K": NaN}')
        return 0
    monkeypatch.setattr(cli, "main", nan_report)
    result = mutants.run_case(case, tmp_path)
    assert result["outcome"] == "nonsense" and "NaN is not JSON" in result["reason"]


def test_a_survey_map_without_its_warning_is_nonsense(tmp_path):
    # The classifier of survey exits: --ridge 0's map (improvement ratio 1.7e10, 30.8 nT
    # off the truth) without a warning is silent nonsense; with one it is a warned result.
    figures = {"compensation": {"uncompensated": {"improvement_ratio": 1.0},
                                "maglog TL18": {"improvement_ratio": 1.7e10}},
               "peak": {"amplitude_nT": 33.9}, "truth": {"grid_rms_nT": 30.8},
               "warnings": []}
    out = tmp_path / "out"
    out.mkdir()
    (out / "report.html").write_text("<!DOCTYPE html><html><head><title>t</title></head>"
                                     "<body><p>map</p></body></html>")
    (out / "survey.json").write_text(json.dumps(figures))
    assert mutants._classify(0, "", out, survey=True)["outcome"] == "nonsense"
    figures["warnings"] = ["the compensation is implausible: ..."]
    (out / "survey.json").write_text(json.dumps(figures))
    assert mutants._classify(0, "", out, survey=True)["outcome"] == "warned"
    figures.update(warnings=[], compensation={"maglog TL18": {"improvement_ratio": 41.0}})
    figures["truth"]["grid_rms_nT"] = 1.9
    (out / "survey.json").write_text(json.dumps(figures))
    assert mutants._classify(0, "", out, survey=True)["outcome"] == "ok"
