"""cli.summary: the run scored against the truth (issue 12, `maglog run`'s printed summary)."""

import copy
import json

import numpy as np
import pytest

from maglog.calib.card import read_logs
from maglog.calib.pipeline import CalibrationError
from maglog.calib.scalar import PARAMETERS
from maglog.cli.summary import (C_ABS_NT, RESIDUAL_RATIO, Z_MAX, canonical_kc, log_frames,
                                summarize)


def strict(summary):
    """as_dict() through a JSON round trip that refuses NaN."""
    return json.loads(json.dumps(summary.as_dict(), allow_nan=False))


def test_all_equal_is_ok(flown):
    flight, data, image, truth, run, counters = flown
    summary = summarize(truth, counters, read_logs(image), run)
    assert summary.ok, summary.text
    assert summary.failed == []
    assert [c.status for c in summary.checks] == ["pass"] * 6
    assert "*" not in summary.text.split("Verdicts")[0].replace("(* = they differ)", "")
    assert "ALL CHECKS PASS" in summary.text
    assert "matches the truth's" in summary.text
    out = strict(summary)
    assert out["ok"] and out["log"]["sha256_match"]
    assert out["tolerances"]["z_max"] == Z_MAX
    assert out["frames"]["mag"]["kept"] == {"gateware": 1200, "truth": 1200}


def test_counter_mismatch_is_marked(flown):
    _, _, image, truth, run, counters = flown
    changed = copy.deepcopy(counters)
    changed["gps"]["kept"] -= 1
    changed["gps"]["checksum"] += 1
    summary = summarize(truth, changed, read_logs(image), run)
    assert not summary.ok
    assert summary.failed == ["frames.gps"]
    row = next(line for line in summary.text.splitlines() if line.strip().startswith("gps"))
    assert "119/120 *" in row and "1/0 *" in row
    assert "kept 119 vs 120, checksum 1 vs 0" in summary.text
    assert "FAILED: frames.gps" in summary.text


def test_missing_counters(flown):
    _, _, image, truth, run, counters = flown
    summary = summarize(truth, None, read_logs(image), run)
    assert summary.ok                      # nothing to compare is no failure, but said
    assert [c.status for c in summary.checks[:3]] == ["skip"] * 3
    assert "ALL CHECKS PASS (3 skipped: nothing to check against)" in summary.text
    assert "-/1200" in summary.text
    partial = {k: v for k, v in counters.items() if k != "cesium"}
    summary = summarize(truth, partial, read_logs(image), run)
    assert summary.failed == ["frames.cesium"]


def test_log_differs(flown):
    _, data, image, truth, run, counters = flown
    cut = data[:data.rindex(b"$")]         # the last frame lost
    summary = summarize(truth, counters, [("LOG00001.TXT", cut)], run)
    assert summary.failed == ["log"]
    check = summary.checks[3]
    assert "bytes" in check.detail and "frames 1919 vs 1920" in check.detail
    assert "differs from" in summary.text
    assert summarize(truth, counters, [], run).failed == ["log"]
    counts, tail = log_frames(data + b"$PMAG1,12")
    assert tail == 9 and counts == truth["recorded"]["per_channel"]


@pytest.mark.parametrize("factor, status", [(1.0, "pass"), (0.5, "fail"), (2.0, "fail")])
def test_residual_verdict(flown, factor, status):
    _, _, image, truth, run, counters = flown
    truth = dict(truth, noise_floor_nT=truth["noise_floor_nT"] * factor)
    summary = summarize(truth, counters, read_logs(image), run)
    check = next(c for c in summary.checks if c.name == "residual")
    assert check.status == status
    ratio = summary.data["residual"]["ratio_after"]
    assert (RESIDUAL_RATIO[0] <= ratio <= RESIDUAL_RATIO[1]) == (status == "pass")
    if factor == 0.5:
        assert "above the floor" in check.detail
    if factor == 2.0:
        assert "below the floor" in check.detail


def test_parameters_against_truth(flown):
    _, _, image, truth, run, counters = flown
    wrong = copy.deepcopy(truth)
    wrong["errors"]["c"][1] += 10 * C_ABS_NT
    summary = summarize(wrong, counters, read_logs(image), run)
    assert summary.failed == ["parameters"]
    assert "c2 off by" in summary.checks[-1].detail
    row = next(line for line in summary.text.splitlines() if line.strip().startswith("c2"))
    assert row.endswith("*")
    # A truth given as any rotation of K (Q K, Q c) reads the same.
    q = np.linalg.qr(np.random.default_rng(1).normal(size=(3, 3)))[0]
    turned = copy.deepcopy(truth)
    turned["errors"]["K"] = (q @ np.array(truth["errors"]["K"])).tolist()
    turned["errors"]["c"] = (q @ np.array(truth["errors"]["c"])).tolist()
    assert summarize(turned, counters, read_logs(image), run).ok
    k, c = canonical_kc(turned["errors"]["K"], turned["errors"]["c"])
    np.testing.assert_allclose(k, truth["errors"]["K"], atol=1e-12)


def test_calibration_failed(flown):
    _, _, image, truth, _, counters = flown
    why = CalibrationError("LOG00001.TXT: fewer than 2 cesium samples")
    summary = summarize(truth, counters, read_logs(image), why)
    assert summary.failed == ["calibration"]
    assert "Calibration failed: LOG00001.TXT: fewer than 2 cesium samples" in summary.text
    summary = summarize(truth, counters, read_logs(image), None)
    assert "no result given" in summary.text
    strict(summary)


def test_bad_input(flown):
    _, _, image, truth, run, counters = flown
    with pytest.raises(ValueError, match="truth.json of version 1"):
        summarize({"version": 2}, counters, [], run)
    with pytest.raises(ValueError, match="CalibrationRun or None, not str"):
        summarize(truth, counters, [], "run")
    with pytest.raises(ValueError, match="counters must be a dict"):
        summarize(truth, [1], [], run)


def test_faults_listed(flown):
    _, _, image, truth, run, counters = flown
    truth = copy.deepcopy(truth)
    truth["frames"]["mag"]["checksum"] = 3
    truth["frames"]["mag"]["kept"] -= 3
    truth["faults"] = [
        {"kind": "bad_checksum", "channel": "mag", "start_s": 30.0, "end_s": 50.0,
         "count": 2, "expect": {"cause": "checksum", "frames": 2}},
        {"kind": "dropped_bytes", "channel": "mag", "start_s": 60.0, "end_s": 80.0,
         "count": 1, "expect": {"cause": "checksum", "frames": 1}},
        {"kind": "card_busy", "channel": None, "start_s": 90.0, "end_s": 92.0, "count": 1,
         "expect": None}]
    summary = summarize(truth, counters, read_logs(image), run)
    text = summary.text
    assert "bad_checksum  mag       30.00-50.00    x2: expect 2 frame(s) dropped as checksum" \
        in text
    assert "card_busy     all" in text and "no frame dropped" in text
    # The gateware (counters of a clean run) missed the three: marked, and frames.mag fails.
    assert "mag checksum             faults expect 3, truth 3, gateware 0 *" in text
    assert summary.data["faults"]["mag.checksum"] == {"faults_expect": 3, "truth": 3,
                                                      "gateware": 0}
    assert "frames.mag" in summary.failed


def test_default_scenario_log_scores_clean(tmp_path):
    """The default scenario's own expected log (what the truth says the card holds, before
    any RTL): the calibration recovers the paper_a preset within the stated tolerances, the
    residual is at the noise floor, and the summary says so."""
    from maglog.calib.pipeline import calibrate_card
    from maglog.sim.stimulus import load_scenario
    stim = load_scenario(None).build()
    stim.write_truth(tmp_path)
    log = b"".join(stim.system.recorded_frames())
    (tmp_path / "LOG00001.TXT").write_bytes(log)
    run = calibrate_card(tmp_path / "LOG00001.TXT",
                         attitude=tmp_path / stim.truth["flight"]["attitude_csv"])
    counters = {ch: {cause: n for cause, n in counts.items()}
                for ch, counts in stim.truth["frames"].items()}
    summary = summarize(stim.truth, counters, [("LOG00001.TXT", log)], run)
    assert summary.ok, summary.text
    assert stim.truth["errors"]["preset"] == "paper_a"
    ratio = summary.data["residual"]["ratio_after"]
    assert RESIDUAL_RATIO[0] <= ratio <= RESIDUAL_RATIO[1]
    assert "=> ALL CHECKS PASS" in summary.text
    assert len(stim.truth["faults"]) >= 6 and "Faults injected" in summary.text


@pytest.mark.parametrize("sigma", [np.inf, 1e4])
def test_parameters_the_flight_does_not_determine_are_not_scored(flown, sigma):
    # A flight that does not turn an axis against the field leaves its parameters with a
    # huge (or infinite) 1 sigma: z rounds to 0 however far off they are. The calibration's
    # verdict (calib.coverage) calls them undetermined; the run does not score them, and
    # ends UNDETERMINED naming them, never ALL CHECKS PASS.
    import dataclasses
    from maglog.calib.coverage import judge_coverage
    _, _, image, truth, run, counters = flown
    result = dataclasses.replace(run.result, uncertainties=np.full(9, sigma))
    loose = dataclasses.replace(run, result=result,
                                coverage=judge_coverage(result, run.b,
                                                        field_nt=float(np.median(run.r))))
    assert loose.verdict == "undetermined"
    wrong = copy.deepcopy(truth)
    wrong["errors"]["c"][0] += 700.0               # c1 off by 700 nT: z ~ 0 with this sigma
    summary = summarize(wrong, counters, read_logs(image), loose)
    check = summary.checks[-1]
    assert check.name == "parameters" and check.status == "undetermined", check.line()
    assert check.detail.startswith("the flight does not determine k11, k12, k13, k22, k23, "
                                   "k33, c1, c2, c3")
    assert not summary.ok and summary.failed == [] and "ALL CHECKS PASS" not in summary.text
    assert summary.undetermined == list(PARAMETERS)
    assert "=> UNDETERMINED: the flight does not determine k11" in summary.text
    assert strict(summary)["verdict"].startswith("UNDETERMINED")
    # The same with a truth the fit recovered: still undetermined, not a pass.
    exact = copy.deepcopy(truth)
    exact["errors"]["K"] = np.asarray(run.result.K).tolist()
    exact["errors"]["c"] = np.asarray(run.result.c).tolist()
    assert not summarize(exact, counters, read_logs(image), loose).ok
    # A determined parameter (the fit's own sigma) 700 nT off fails as not recovered.
    summary = summarize(wrong, counters, read_logs(image), run)
    assert summary.checks[-1].status == "fail" and summary.failed == ["parameters"]
    assert "not recovered: c1" in summary.checks[-1].detail
    assert "not determined" not in summary.checks[-1].detail
    # Failed and undetermined together: both named.
    changed = copy.deepcopy(counters)
    changed["gps"]["kept"] -= 1
    summary = summarize(truth, changed, read_logs(image), loose)
    assert "=> FAILED: frames.gps; UNDETERMINED: the flight does not determine" in \
        summary.text


