"""The mutation run of ``maglog calibrate`` (tests/calib/mutants.py): bad card images, logs
and option values, as a new user would meet them, end in a message or in a result whose
problems the report states; never a traceback, a hang, or silent nonsense.

A short run (55 inputs, every class) is in the default suite; the long one (1,210 inputs)
under ``-m slow``. ``bench/calib/mutation.py`` runs the long one and writes its counts.
"""

import importlib
import sys
from pathlib import Path

import pytest

# The helper module beside this file (tests are no package): on sys.path by name, so that
# the run's worker processes import it too.
sys.path.insert(0, str(Path(__file__).parent))
mutants = importlib.import_module("mutants")


def _check(results):
    totals, by_class = mutants.counts(results)
    bad = mutants.failures(results)
    listing = "\n".join(f"  #{r['index']} {r['kind']} {r['outcome']}: {r['detail']} -> "
                        f"{r['reason']}" for r in bad)
    assert not bad, f"{len(bad)} of {len(results)} inputs failed ({totals}):\n{listing}"
    # Every class was tried, and the run saw both refusals and calibrations.
    assert set(by_class) == set(mutants.CLASSES)
    assert totals["error"] and totals["ok"] and totals["usage"]


def test_short_mutation_run(fat_tools):
    results, with_images = mutants.run(55, seed=10, tools=fat_tools)
    assert with_images and len(results) == 55
    _check(results)


@pytest.mark.slow
def test_long_mutation_run(fat_tools):
    results, with_images = mutants.run(1210, seed=20, tools=fat_tools)
    assert with_images and len(results) == 1210
    _check(results)


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
