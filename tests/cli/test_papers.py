"""cli.papers: the three papers' headline results beside ours (issue 12, the report)."""

import json
import sys
from pathlib import Path

import numpy as np
import pytest

from maglog.calib.ellipsoid import octant_coverage
from maglog.calib.pipeline import calibrate_card
from maglog.cli.papers import (PAPER_A, PAPER_C, STATIC_MIN_SAMPLES, paper_results,
                               select_by_octant)
from maglog.sim.stimulus.scenario import ErrorModel, make_flight

sys.path.insert(0, str(Path(__file__).parent))
from flights import truth_for, write_card


@pytest.fixture(scope="module")
def quick(flown, tmp_path_factory):
    _, _, _, truth, run, _ = flown
    out = tmp_path_factory.mktemp("papers")
    return paper_results(run, truth, out, seed=3, quick=True), out


def test_files(quick):
    result, out = quick
    names = {"papers.md", "papers.json", "paper_a_figure7.png", "paper_b_heading.png",
             "paper_c_allan.png"}
    assert {p.name for p in out.iterdir()} == names
    for name in names:
        assert (out / name).stat().st_size > 0
    assert (out / "paper_a_figure7.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    data = json.loads(result.json.read_text(), parse_constant=lambda c: 1 / 0)
    assert data["seed"] == 3 and data["quick"] is True
    json.dumps(result.as_dict(), allow_nan=False)
    text = result.markdown.read_text()
    for heading in ("## Paper A", "## Paper B", "## Paper C"):
        assert heading in text
    for png in ("paper_a_figure7.png", "paper_b_heading.png", "paper_c_allan.png"):
        assert f"]({png})" in text


def test_paper_a(quick, flown):
    flight, _, _, truth, run, _ = flown
    a = quick[0].data["paper_a"]
    # The sensor-frame offset K^-1 c is what the scalar model fully determines: it is the
    # truth's b within a few nT; the matrix turned onto A by the unseen rotation is A.
    assert a["difference"]["max_abs_O_nT"] < 15.0
    assert a["difference"]["max_abs_P"] < 1e-3
    np.testing.assert_allclose(a["paper"]["P"], PAPER_A["P"])
    raw = np.linalg.norm(flight.b_meas, axis=1)
    assert a["figure7"]["raw_nT"] == pytest.approx(np.ptp(raw), rel=0.05)
    assert a["figure7"]["compensated_nT"] < 0.05 * a["figure7"]["raw_nT"]
    text = quick[0].markdown.read_text()
    assert "| paper, Table 1 (P, O) | 1.0117 | 0.0079 | 0.0184 |" in text
    assert "(paper: 53,700 nT)" in text


def test_paper_b(quick):
    curves = quick[0].data["paper_b"]["curves"]
    assert [c["noise_nT"] for c in curves] == [5.0, 200.0]
    for curve in curves:
        assert all(curve["fits"] == curve["trials"])
        scatter = curve["fit_scatter_deg"]
        # More samples per octant, less scatter of the fit: monotone over the quick counts.
        assert np.all(np.diff(scatter) < 0), scatter
        assert scatter[0] > 3 * scatter[-1]
        assert 0 < curve["unlimited_samples_error_deg"] < 5
        assert curve["claim_holds"] == bool(np.all(curve["mean_error_deg"] < 1.0))
    # The noisier compass scatters more at every count.
    assert np.all(curves[1]["fit_scatter_deg"] > curves[0]["fit_scatter_deg"])
    assert "the claim (mean heading error < 1° at every count)" in \
        quick[0].markdown.read_text()


def test_paper_c(quick):
    c = quick[0].data["paper_c"]
    single_q = c["change_percent"]["single_point.quantisation"]["mean"]
    single_b = c["change_percent"]["single_point.bias_instability"]["mean"]
    assert -100 < single_q < -50 and -100 < single_b < -30
    assert c["variance"][0] == pytest.approx(PAPER_C["before"]["variance"], rel=0.1)
    assert c["variance"][1] < 0.1 * c["variance"][0]
    assert c["on_run"] is None and "no static phase" in c["on_run_reason"]


def test_select_by_octant():
    rng = np.random.default_rng(0)
    b = rng.normal(size=(2000, 3)) * 1000 + [300, -200, 100]
    taken = select_by_octant(b, 7)
    coverage = octant_coverage(b[taken], min_per_octant=7)
    assert coverage.counts.tolist() == [7] * 8           # full, and no octant over-full
    assert np.all(np.diff(taken) > 0)
    assert select_by_octant(b[:20], 7) is None


def test_static_phase_of_the_run(flown, tmp_path):
    """A truth whose flight starts with a static phase long enough: paper C on the run."""
    flight, _, _, truth, run, _ = flown
    truth = dict(truth, timestamp=flight.start.isoformat(),
                 flight=dict(truth["flight"], phases=[
                     {"name": "ground", "start_s": 0.0, "end_s": 40.0},
                     {"name": "calibration", "start_s": 40.0, "end_s": 60.0}]))
    result = paper_results(run, truth, tmp_path, quick=True)
    on_run = result.data["paper_c"]["on_run"]
    assert on_run is not None and on_run["source"].startswith("phase ground")
    assert int(on_run["source"].split(", ")[1].split()[0]) >= STATIC_MIN_SAMPLES
    assert "On the run's data (phase ground" in result.markdown.read_text()


def test_without_a_run(flown, tmp_path):
    _, _, _, truth, _, _ = flown
    result = paper_results(None, truth, tmp_path, quick=True)
    assert "Not computed: the calibration failed" in result.markdown.read_text()
    assert "paper_a_figure7" not in result.plots
    with pytest.raises(ValueError, match="Seed must be a non-negative integer, not -1"):
        paper_results(None, truth, tmp_path, seed=-1)


def test_table_1_recovered(tmp_path):
    """A sensor built from Table 1 (P as A, O as b, as sim/stimulus reads it): the run
    recovers it, and paper A's section says the truth is Table 1."""
    table = ErrorModel(non_orthogonality=PAPER_A["P"], scale=(1, 1, 1),
                       soft_iron=((0, 0, 0),) * 3, hard_iron=(0, 0, 0),
                       bias=tuple(PAPER_A["O_nT"]), noise=5.0)
    flight = make_flight(coverage="full", seconds=60, seed=11, errors=table)
    data = flight.log()
    truth = truth_for(flight, data, scenario="table1")
    truth["errors"]["preset"] = "paper_a"
    run = calibrate_card(write_card(tmp_path / "card.img", data))
    result = paper_results(run, truth, tmp_path / "out", quick=True)
    a = result.data["paper_a"]
    assert a["truth_is_table_1"]
    assert a["difference"]["max_abs_P"] < 1e-4 and a["difference"]["max_abs_O_nT"] < 5
    # P's antisymmetric part is the rotation the scalar check cannot see (~0.8°).
    assert 0.3 < a["ours_rotated"]["rotation_deg"] < 3
    assert "The scenario's sensor is Table 1 itself" in result.markdown.read_text()
