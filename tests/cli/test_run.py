"""``maglog simulate`` and ``maglog run``: a scenario through the logger to a card, scored
against the scenario's own truth."""

import json
import re

import pytest

from maglog.cli.main import main
from maglog.sim.stimulus.config import default_scenario_path


def _without_line_faults():
    """The default scenario without its baud-error faults."""
    text = default_scenario_path().read_text()
    return re.sub(r"\[\[faults\.baud_error\]\][^\[]*", "", text)


def test_run_on_the_model_scores_itself(tmp_path, capsys):
    scenario = tmp_path / "scenario.toml"
    scenario.write_text(_without_line_faults())
    out = tmp_path / "run"
    build = tmp_path / "build"
    status = main(["run", str(scenario), "--backend", "model", "-o", str(out),
                   "--quick-papers", "--quiet", "--build-dir", str(build)])
    captured = capsys.readouterr()
    printed = captured.out
    assert status == 0, printed
    assert "=> FAILED" not in printed
    # Each stage said as it starts; their times at the end, the report's kept for the next
    # run's estimate (issue 24).
    stages = [line for line in captured.err.splitlines() if line.startswith(("[", "run:"))]
    assert [line[:5] for line in stages] == ["[1/4]", "[2/4]", "[3/4]", "[4/4]", "run: "]
    assert re.fullmatch(r"run: scenario \d+ s, simulation \d+ s, calibration \d+ s, report and "
                        r"papers \d+ s; \d+ s in all", stages[-1]), stages[-1]
    rates = json.loads((build / "rates.json").read_text())
    assert rates["stages"]["report_quick_papers"] > 0
    for check in ("frames.mag", "frames.gps", "frames.cesium", "log", "residual",
                  "parameters"):
        assert re.search(rf"PASS {re.escape(check)}\b", printed), check
    summary = json.loads((out / "report" / "summary.json").read_text())
    assert summary["ok"] is True
    assert summary["simulation"]["backend"] == "model"
    truth = json.loads((out / "truth.json").read_text())
    counters = json.loads((out / "simulation.json").read_text())["counters"]
    assert counters == {name: {cause: truth["frames"][name][cause] for cause in counted}
                        for name, counted in counters.items()}
    for name in ("card.img", "attitude.csv", "report/report.md", "report/papers.md"):
        assert (out / name).is_file(), name


def test_the_quick_path_passes_with_the_line_faults(tmp_path, capsys):
    """The README's quick path: the default scenario, its cesium line 10 % slow for 0.3 s,
    on the model, whose receivers sample off-rate bytes as the gateware's do: the frames
    and the log agree with the truth."""
    out = tmp_path / "run"
    status = main(["run", "--backend", "model", "-o", str(out), "--quick-papers",
                   "--quiet"])
    captured = capsys.readouterr()
    assert status == 0, captured.out + captured.err
    for check in ("frames.mag", "frames.gps", "frames.cesium", "log"):
        assert re.search(rf"PASS {re.escape(check)}\b", captured.out), check
    truth = json.loads((out / "truth.json").read_text())
    counters = json.loads((out / "simulation.json").read_text())["counters"]
    assert counters["cesium"]["uart_error"] == truth["frames"]["cesium"]["uart_error"] > 0


def test_simulate_rejects_a_bad_scenario_in_one_line(tmp_path, capsys):
    scenario = tmp_path / "bad.toml"
    scenario.write_text(default_scenario_path().read_text().replace(
        "[flight.takeoff]\nseconds = 10.0", "[flight.takeoff]\nseconds = -3.0"))
    status = main(["simulate", str(scenario), "-o", str(tmp_path / "card.img"),
                   "--backend", "model"])
    err = capsys.readouterr().err.strip().splitlines()
    assert status == 1
    assert len(err) == 1 and err[0].startswith("maglog: error: ")
    assert "bad.toml" in err[0] and "takeoff" in err[0] and "seconds" in err[0]
    assert not (tmp_path / "card.img").exists()


def test_simulate_refuses_a_folder_as_the_card(tmp_path, capsys):
    status = main(["simulate", "-o", str(tmp_path), "--backend", "model"])
    assert status == 1
    assert "is a folder" in capsys.readouterr().err


def test_simulate_on_the_model_writes_card_truth_and_counts(tmp_path, capsys):
    card = tmp_path / "out" / "flight.img"
    status = main(["simulate", "-o", str(card), "--backend", "model", "--quiet"])
    printed = capsys.readouterr().out
    assert status == 0
    assert card.is_file() and (card.parent / "truth.json").is_file()
    record = json.loads((card.parent / "simulation.json").read_text())
    assert record["backend"] == "model" and record["simulated_s"] > 100
    # Every counter agrees with the truth, the baud faults' included (the model samples
    # off-rate bytes as the gateware does), so the table names no truth figure beside one.
    assert re.search(r"^gps\s+\d+\s", printed, re.MULTILINE)
    truth = json.loads((card.parent / "truth.json").read_text())
    for name, counted in record["counters"].items():
        assert counted == {cause: truth["frames"][name][cause] for cause in counted}, name
    assert "(truth" not in printed


@pytest.fixture(scope="session")
def rtl_build(tmp_path_factory):
    """One folder for the fast harness's builds per test session."""
    return tmp_path_factory.mktemp("rtl-build")


def test_every_fault_lands_in_the_gateware_counters_as_injected(tmp_path, capsys, external,
                                                                  rtl_build):
    """The short scenario (one fault of each kind, 22 s) through the logger's RTL: every
    counter equals the truth's, and each frame-dropping fault is counted under the cause
    the truth expects, as often as injected."""
    external.simulator("verilator")
    external.tool("c++", "the fast harness is C++")
    card = tmp_path / "card.img"
    status = main(["simulate", "short", "-o", str(card), "--backend", "verilator",
                   "--build-dir", str(rtl_build), "--quiet"])
    capsys.readouterr()
    assert status == 0
    truth = json.loads((tmp_path / "truth.json").read_text())
    counters = json.loads((tmp_path / "simulation.json").read_text())["counters"]
    for name, counted in counters.items():
        assert counted == {cause: truth["frames"][name][cause] for cause in counted}, name
    expected = {}
    for fault in truth["faults"]:
        if fault["expect"] is not None:
            key = (fault["channel"], fault["expect"]["cause"])
            expected[key] = expected.get(key, 0) + fault["expect"]["frames"]
    assert {fault["kind"] for fault in truth["faults"]} >= {
        "noise_burst", "dropped_bytes", "bad_checksum", "baud_error", "gps_outage",
        "card_busy"}
    for (channel, cause), frames in expected.items():
        if cause != "not_whitelisted":      # the GPS distractors are dropped there too
            assert counters[channel][cause] == frames, (channel, cause)
    assert sum(frames for frames in expected.values()) >= 4


@pytest.mark.slow
def test_main_job_on_verilator_matches_the_truth(tmp_path, capsys, external):
    """The README's main command: the default scenario through the logger's RTL (the fast
    harness), every check of the summary passing."""
    external.simulator("verilator")
    external.tool("c++", "the fast harness is C++")
    status = main(["run", "--backend", "verilator", "-o", str(tmp_path / "run"),
                   "--quiet"])
    printed = capsys.readouterr().out
    assert status == 0, printed
    summary = json.loads((tmp_path / "run" / "report" / "summary.json").read_text())
    assert summary["ok"] is True
    # The README shows this run's end as printed.
    from readme import printed_verdicts, readme_verdicts, same_printout
    difference = same_printout(readme_verdicts(), printed_verdicts(printed))
    assert difference is None, "README.md's printed verdicts are stale:\n" + difference


def test_a_run_is_sized_before_it_starts_and_refused_above_max_seconds(tmp_path, capsys):
    # An hour on the ground: estimated before anything is built, refused by default with
    # the estimate on the backend; --max-seconds raises the limit.
    scenario = tmp_path / "hour.toml"
    scenario.write_text("[flight.ground]\nseconds = 3600.0\n")
    for command in (["simulate", str(scenario), "-o", str(tmp_path / "card.img")],
                    ["run", str(scenario), "-o", str(tmp_path / "run")]):
        status = main(command + ["--backend", "verilator"])
        err = capsys.readouterr().err.strip().splitlines()
        assert status == 1 and sum(line.startswith("maglog:") for line in err) == 1, err
        assert err[-1].startswith("maglog: error: hour.toml: this run needs about 3,")
        assert re.search(r"on verilator at (the rate measured here|the bench machine's rate)\), more "
                         r"than --max-seconds 1200", err[-1]), err[-1]
        assert "raise --max-seconds" in err[-1]
    assert not (tmp_path / "card.img").exists() and not (tmp_path / "truth.json").exists()
    status = main(["simulate", "short", "-o", str(tmp_path / "card.img"), "--backend",
                   "model", "--max-seconds", "10", "--quiet"])
    assert status == 1 and "more than --max-seconds 10;" in capsys.readouterr().err
    status = main(["simulate", "short", "-o", str(tmp_path / "card.img"), "--backend",
                   "model", "--max-seconds", "30", "--quiet"])
    err = capsys.readouterr().err
    assert status == 0, err
    # The size is said before the build, within the limit too.
    assert "short.toml: about 21 s of simulated flight (3.87e+07 clock cycles), within " \
           "--max-seconds 30" in err.splitlines()[0]
    assert (tmp_path / "card.img").is_file()


@pytest.mark.parametrize("value", ["0", "-1", "nan", "inf", "1e9", "x"])
def test_max_seconds_is_checked(tmp_path, capsys, value):
    with pytest.raises(SystemExit) as exit_:
        main(["simulate", "short", "-o", str(tmp_path / "card.img"), "--backend", "model",
              f"--max-seconds={value}"])
    status = exit_.value.code
    err = capsys.readouterr().err.strip().splitlines()
    assert status == 2 and len(err) == 1 and "--max-seconds" in err[0]
