"""Progress on the long steps (issue 24): the survey's stages and a batch's jobs as they
finish (cli/survey.py, calib/batch.py), the estimate of a run from the rate measured on
this machine (cli/run.py), the Verilator builds timed (sim/backends/fast.py, the demo).
The survey's stage lines on a real flight are checked in tests/calib/test_survey.py."""

import io
import json
import re

import pytest

from maglog.calib.batch import run_batch
from maglog.cli import run as cli_run
from maglog.cli.main import main
from maglog.cli.survey import _StageLines
from maglog.sim.backends import fast


class _Terminal(io.StringIO):
    def isatty(self):
        return True


def test_stage_lines_on_a_terminal_and_in_a_log():
    terminal, log = _Terminal(), io.StringIO()
    for stream in (terminal, log):
        lines = _StageLines(stream)
        lines("gridding", None)
        lines("gridding", 3.52)
        lines("levelling", None)
        lines.close()                           # the stage failed: its line is ended
    # A terminal sees the stage as it starts; a log gets the line whole as it ends.
    assert terminal.getvalue() == ("survey: gridding ... 3.5 s\n"
                                   "survey: levelling ... \n")
    assert log.getvalue() == "survey: gridding: 3.5 s\n"


def _bogus_cards(tmp_path, count):
    cards = []
    for k in range(count):
        card = tmp_path / f"c{k}" / "card.img"
        card.parent.mkdir()
        card.write_bytes(b"not a card")
        cards.append(str(card))
    return cards


def test_a_batch_says_each_job_as_it_finishes_with_the_time_left(tmp_path, capsys):
    cards = _bogus_cards(tmp_path, 3)
    status = main(["survey", *cards, "--serial", "-o", str(tmp_path / "out")])
    err = capsys.readouterr().err.splitlines()
    assert status == 1
    done = [line for line in err if " jobs done " in line]
    assert [line.split(" jobs done")[0] for line in done] == \
        ["survey: 1/3", "survey: 2/3", "survey: 3/3"]
    assert re.search(r"\(c0 failed in \d+ s\); \d+ s so far, about \d+ s left at \d+ s a job$",
                     done[0]), done[0]
    assert "left" not in done[-1]
    # --quiet: the errors only.
    main(["survey", *cards, "--serial", "--quiet", "-o", str(tmp_path / "quiet")])
    err = capsys.readouterr().err.splitlines()
    assert err and all(line.startswith("maglog: error: ") for line in err), err


def test_dask_reports_jobs_as_they_finish_and_keeps_the_jobs_order(tmp_path):
    cards = _bogus_cards(tmp_path, 3)
    jobs = [{"card": card, "name": f"job{k}", "out": str(tmp_path / f"out{k}"),
             "options": {}} for k, card in enumerate(cards)]
    heard = []
    records = run_batch(jobs, workers=2, on_done=lambda r, n, total: heard.append(
        (r["name"], n, total)))
    assert [r["name"] for r in records] == ["job0", "job1", "job2"]
    assert sorted(name for name, _, _ in heard) == ["job0", "job1", "job2"]
    assert [(n, total) for _, n, total in heard] == [(1, 3), (2, 3), (3, 3)]
    assert not any(r["ok"] for r in records)


def test_the_rate_measured_here_is_kept_and_used_for_the_next_estimate(tmp_path):
    from maglog.sim.stimulus.config import load_scenario
    system = load_scenario("short").build().system
    cycles = system.until * system.clk_freq
    # Nothing measured yet: the verilator progress line has the ETA; the others say whose
    # rate the estimate is.
    assert "no rate measured on this machine yet" in cli_run._estimate(system, "verilator",
                                                                         tmp_path)
    assert "of the project's bench machine" in cli_run._estimate(system, "icarus", tmp_path)
    assert cli_run._estimate(system, "model", tmp_path) == ""
    cli_run.record_rate(tmp_path, "verilator", 4e8, 100.0)      # 4e6 cycles/s
    cli_run.record_rate(tmp_path, "model", 4e8, 10.0)           # not an RTL rate: not kept
    cli_run.record_rate(tmp_path, "icarus", 4e3, 0.01)           # too short to time
    rates = json.loads((tmp_path / "rates.json").read_text())
    assert set(rates) == {"verilator"} and rates["verilator"]["cycles_per_s"] == 4e6
    said = cli_run._estimate(system, "verilator", tmp_path)
    seconds = cycles / 4e6
    assert f"estimate {cli_run._duration(seconds)} at 4e+06 cycles/s measured here (" in said
    assert "the run only: a Verilator build, once per design, comes first" in said
    scenario = load_scenario("short")
    assert cli_run.run_size(scenario, "verilator", tmp_path)[2] == pytest.approx(
        scenario.run_seconds() * scenario.clk_freq / 4e6)
    # A damaged record is no rate.
    (tmp_path / "rates.json").write_text('{"verilator": {"cycles_per_s": "fast"}}')
    assert cli_run.measured_rate(tmp_path, "verilator") is None
    (tmp_path / "rates.json").write_text('{"verilator": {"cycles_per_s": -1}}')
    assert cli_run.measured_rate(tmp_path, "verilator") is None


def test_simulate_keeps_the_rate_it_ran_at(tmp_path, capsys, monkeypatch):
    """simulate() says the estimate from the last run's rate, then keeps this run's."""
    from types import SimpleNamespace
    from maglog.sim.runners import system as runners
    stimulus = cli_run.load("short")
    cycles = stimulus.system.until * stimulus.system.clk_freq

    def run_system(system, image, **_):
        return SimpleNamespace(wall_seconds=cycles / 2e6, counters={}, stats={}, led=0,
                               card_errors=[], sdram_errors=[], notes=[], backend="icarus")
    monkeypatch.setattr(runners, "run_system", run_system)
    build = tmp_path / "build"
    cli_run.record_rate(build, "icarus", 1e9, 1000.0)           # 1e6 cycles/s
    cli_run.simulate(stimulus, tmp_path / "card.img", backend="icarus", build_dir=build,
                     card_bytes=512 << 20)
    said = capsys.readouterr().err
    assert f"on icarus; estimate {cli_run._duration(cycles / 1e6)} at 1e+06 cycles/s " \
           "measured here" in said, said
    assert cli_run.measured_rate(build, "icarus")[0] == pytest.approx(2e6)


def test_the_last_harness_build_time_is_read_back(tmp_path):
    assert fast.last_build_seconds(tmp_path) is None
    (tmp_path / fast.BUILD_TIME_FILE).write_text('{"seconds": 95.5}')
    assert fast.last_build_seconds(tmp_path) == 95.5
    for damaged in ("{", '{"seconds": -3}', '{"seconds": "NaN"}', "[]"):
        (tmp_path / fast.BUILD_TIME_FILE).write_text(damaged)
        assert fast.last_build_seconds(tmp_path) is None, damaged


def _demo(backend, out, capsys, seconds="0.5"):
    assert main(["demo", "--backend", backend, "--seconds", seconds, "--out", str(out)]) == 0
    return capsys.readouterr().err


def test_a_demo_estimates_from_the_last_demos_rate(tmp_path, capsys):
    (tmp_path / "timing-amaranth.json").write_text('{"cycles_per_s": 12345.0}')
    said = _demo("amaranth", tmp_path, capsys, seconds="0.2")
    assert re.search(r"about ([\d,]+) cycles, ~\d+ s at 12k cycles/s \(measured here by the "
                     r"last demo\)\n", said), said
    assert "building" not in said                   # Amaranth simulates the design itself
    cycles = int(re.search(r"\[3/3\] ([\d,]+) cycles in ", said)[1].replace(",", ""))
    timing = json.loads((tmp_path / "timing-amaranth.json").read_text())
    assert timing["cycles_per_s"] != 12345.0 and cycles / timing["cycles_per_s"] < 60


@pytest.mark.slow
def test_a_verilator_demo_times_its_build_apart(tmp_path, capsys, external):
    external.simulator("verilator")
    first = _demo("verilator", tmp_path, capsys)
    assert "building the verilator model of the front end (no build timed here yet" in first
    built = re.search(r"\n      built in (\d+) s\n", first)
    assert built, first
    second = _demo("verilator", tmp_path, capsys)
    timing = json.loads((tmp_path / "timing-verilator.json").read_text())
    assert f"(the last build here took {built[1]} s) ..." in second
    assert "(measured here by the last demo)" in second
    assert timing["build_s"] > 0 and timing["cycles_per_s"] > 0


def test_a_runs_stage_times_are_kept_beside_its_rates(tmp_path):
    assert cli_run.last_stage_seconds(tmp_path, "report") is None
    cli_run.record_rate(tmp_path, "verilator", 4e8, 100.0)
    cli_run.record_stages(tmp_path, {"report": 80.5})
    cli_run.record_stages(tmp_path, {"report_quick_papers": 12.0})
    assert cli_run.last_stage_seconds(tmp_path, "report") == 80.5
    assert cli_run.last_stage_seconds(tmp_path, "report_quick_papers") == 12.0
    assert cli_run.measured_rate(tmp_path, "verilator")[0] == 4e6   # the rates kept too
    (tmp_path / "rates.json").write_text('{"stages": {"report": "slow"}}')
    assert cli_run.last_stage_seconds(tmp_path, "report") is None


def test_a_runs_size_says_whose_rate_its_estimate_is(tmp_path, capsys):
    cli_run.load("short", max_seconds=1200, backend="verilator", build_dir=tmp_path)
    assert "on verilator at the bench machine's rate), within" in capsys.readouterr().err
    cli_run.record_rate(tmp_path, "verilator", 4e8, 100.0)
    cli_run.load("short", max_seconds=1200, backend="verilator", build_dir=tmp_path)
    assert "on verilator at the rate measured here), within" in capsys.readouterr().err
