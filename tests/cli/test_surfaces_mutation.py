"""The mutation run of the surfaces issue 23's fuzz reached first (tests/cli/mutants_surfaces.py):
scenario files, ``card format``, ``hdl``, ``replay`` and ``record`` options, as a new user
would meet them, end in a one-line message or a result whose files are there; never a
traceback, a hang, out of memory, or silent nonsense.

A short run (60 inputs: the issue's own 20, then every class) is in the default suite; the
long one (720 inputs) under ``-m slow``. ``bench/cli/surfaces_mutation.py`` runs the long one
and writes its counts.
"""

import importlib
import sys
from pathlib import Path

import pytest

# The helper module beside this file (tests are no package): on sys.path by name, so that
# the run's worker processes import it too.
sys.path.insert(0, str(Path(__file__).parent))
mutants = importlib.import_module("mutants_surfaces")

SHORT_INPUTS = 60
LONG_INPUTS = 720


def _check(results, count):
    assert len(results) == count
    totals, by_class = mutants.counts(results)
    bad = mutants.failures(results)
    listing = "\n".join(f"  #{r['index']} {r['kind']} {r['outcome']}: {r['detail']} -> "
                        f"{r['reason']}" for r in bad)
    assert not bad, f"{len(bad)} of {len(results)} inputs failed ({totals}):\n{listing}"
    assert set(by_class) == set(mutants.CLASSES)
    assert totals["error"] and totals["ok"] and totals["usage"]


def test_short_mutation_run():
    _check(mutants.run(SHORT_INPUTS, seed=10), SHORT_INPUTS)


@pytest.mark.slow
def test_long_mutation_run():
    _check(mutants.run(LONG_INPUTS, seed=20), LONG_INPUTS)


def test_the_issues_inputs_come_first():
    details = [mutants.make_case(i, 1).detail for i in range(20)]
    assert "seed of 5000 digits" in details and "--speed 1e6 into loop://" in details
    assert "an hour on the ground" in details and "--sdram-phase -inf" in details


def test_the_run_finds_each_kind_of_failure(monkeypatch):
    # The classifier itself: an exception escaping main, an input over the time limit,
    # memory exhausted, an error line that repeats a whole value, an exit 0 without its
    # output are each counted as what they are.
    from maglog.cli import main as cli
    case = mutants.make_case(0, 1)
    mutants._worker_init(memory_limit=None)

    def verdict(fake, **kwargs):
        monkeypatch.setattr(cli, "main", fake)
        return mutants.run_case(case, **kwargs)["outcome"]

    def raises(argv):
        raise ZeroDivisionError("boom")
    assert verdict(raises) == "traceback"

    def sleeps(argv):
        import time
        time.sleep(5)
    assert verdict(sleeps, time_limit=1) == "hang"

    def exhausts(argv):
        raise MemoryError()
    assert verdict(exhausts) == "oom"

    def said_oom(argv):
        print("maglog: error: out of memory; try a smaller run", file=sys.stderr)
        return 1
    assert verdict(said_oom) == "oom"

    def echoes(argv):
        print("maglog: error: not " + "x" * 1000, file=sys.stderr)
        return 1
    assert verdict(echoes) == "nonsense"

    def two_lines(argv):
        print("maglog: error: one\nmaglog: error: two", file=sys.stderr)
        return 1
    assert verdict(two_lines) == "nonsense"

    def silent(argv):
        return 0                          # no card image, no truth.json
    assert verdict(silent) == "nonsense"

    def refused(argv):
        print("maglog: error: scenario.toml: [scenario] seed must be ...", file=sys.stderr)
        return 1
    assert verdict(refused) == "error"


def test_a_run_that_passes_an_undetermined_parameter_is_nonsense(monkeypatch):
    # The run judge reads summary.json: a parameter 700 nT off whose sigma made its z small
    # must not pass (issue 23: "PASS parameters ... largest |z| 0.0").
    import json
    from maglog.cli import main as cli
    from maglog.cli.summary import TOLERANCES
    case = mutants.Case(0, "scenario:run", "test", ["run"], "run")
    mutants._worker_init(memory_limit=None)

    def writes(status, determined):
        def fake(argv):
            report = Path.cwd() / "out" / "report"
            report.mkdir(parents=True)
            summary = {"ok": status == "pass", "failed": [] if status == "pass" else
                       ["parameters"], "tolerances": TOLERANCES,
                       "checks": [{"name": "parameters", "status": status, "detail": ""}],
                       "parameters": {"c1": {"difference": 700.0, "sigma": 1e9, "z": 0.0,
                                             "determined": determined}}}
            (report / "summary.json").write_text(json.dumps(summary))
            return 0 if status == "pass" else 1
        return fake
    monkeypatch.setattr(cli, "main", writes("pass", False))
    assert mutants.run_case(case)["outcome"] == "nonsense"
    monkeypatch.setattr(cli, "main", writes("pass", True))
    assert mutants.run_case(case)["outcome"] == "ok"
