"""The coverage gate: one rule (1-sigma in nT of field within the noise of one sample, or a
bound the user sets) accepts tumbles and names what a UAV pattern or a level flight leaves
undetermined; paper B's octants about the running centroid do not."""

import numpy as np
import pytest

from maglog.calib.coverage import determine, judge_coverage, octants_about_centre
from maglog.calib.ellipsoid import octant_coverage
from maglog.calib.scalar import PARAMETERS, calibrate_scalar
from maglog.sim.stimulus.errors import preset
from maglog.sim.stimulus.scenario import make_flight


def _verdict(coverage, model, noise, seed, seconds=60):
    flight = make_flight(coverage=coverage, seconds=seconds, rate=20,
                         errors=preset(model, noise=noise), seed=seed)
    result = calibrate_scalar(flight.b_meas, flight.total)
    return judge_coverage(result, flight.b_meas), flight


@pytest.mark.parametrize("model", ["default", "paper_a"])
@pytest.mark.parametrize("noise", [5.0, 100.0])
def test_verdicts_on_the_three_coverages(model, noise):
    for seed in (1, 2):
        full, _ = _verdict("full", model, noise, seed)
        assert full.verdict == "determined" and full.success and full.undetermined == []
        assert full.message.startswith("determined: the flight determines every parameter")
        assert full.octants_reached == 8

        uav, _ = _verdict("uav", model, noise, seed)
        # +-30 deg of roll and pitch for a minute: the vertical axis's scale and offset,
        # about twice the noise of one sample, whatever the noise.
        assert uav.verdict == "undetermined" and not uav.success, uav.message
        assert uav.undetermined == ["k33", "c3"], uav.message
        assert uav.message.startswith("undetermined: the flight does not determine k33, c3")
        d = uav.determination
        assert 1.5 < d.sigma_nT[PARAMETERS.index("c3")] / d.bound_nT < 3
        assert abs(d.bound_nT - noise) < 0.05 * noise      # one sample's noise
        assert uav.octants_reached == 4

        planar, _ = _verdict("planar", model, noise, seed)
        assert planar.verdict == "undetermined" and {"k33", "c3"} <= set(planar.undetermined)


def test_the_uav_pattern_flown_longer_determines_everything():
    # The 1-sigma falls as 1/sqrt(N): ten minutes of the same +-30 deg pattern pin k33 and
    # c3 down within the noise of one sample. Octants do not change (still four).
    long, _ = _verdict("uav", "paper_a", 5.0, 1, seconds=600)
    assert long.verdict == "determined", long.message
    assert long.octants_reached == 4


def test_the_rule():
    sigma = np.array([1e-4, 0, 0, 0, 0, 0, 4.0, 6.0, np.nan])     # K dimensionless, c nT
    d = determine(sigma, 50_000.0, 5.0)
    assert d.sigma_nT[0] == pytest.approx(5.0) and d.bound_nT == 5.0
    assert d.determined.tolist() == [True] * 7 + [False, False]
    assert d.undetermined == ["c2", "c3"] and d.bound_source == "noise"
    held = determine(sigma, 50_000.0, 5.0, held=[False] * 6 + [True, False, False])
    assert held.undetermined == ["c1", "c2", "c3"]        # held: never determined
    user = determine(sigma, 50_000.0, 5.0, bound_nt=10.0)
    assert user.undetermined == ["c3"] and user.bound_source == "user"
    assert "(--determined-nT)" in user.bound_text
    for bad in (0.0, -1.0, float("nan"), 1e6, "x"):
        with pytest.raises(ValueError, match="bound on a determined parameter"):
            determine(sigma, 50_000.0, 5.0, bound_nt=bad)


def test_a_fit_that_failed_is_failed_not_undetermined():
    flight = make_flight(coverage="full", seconds=30, rate=20, seed=1)
    result = calibrate_scalar(flight.b_meas, flight.total)
    result.success, result.message = False, "not converged: test"
    verdict = judge_coverage(result, flight.b_meas)
    assert verdict.verdict == "failed" and not verdict.success
    assert verdict.message == "failed: not converged: test"


def test_paper_b_octants_disagree_with_what_the_fit_can_determine():
    # Paper B's running-centroid octants fill on UAV and level flights, whose fits leave
    # parameters undetermined, and may refuse a tumble whose fit determines everything.
    for coverage in ("uav", "planar"):
        verdict, flight = _verdict(coverage, "paper_a", 20.0, 3)
        assert octant_coverage(flight.b_meas).complete and not verdict.success
        assert verdict.paper_filled == 8
    # A tumble that starts slowly: the first samples' centroid wanders, one octant starves.
    flight = make_flight(coverage="full", seconds=8, rate=20, seed=4)
    order = np.argsort(flight.b_meas[:, 2])
    b, r = flight.b_meas[order], flight.total[order]
    paper = octant_coverage(b)
    verdict = judge_coverage(calibrate_scalar(b, r), b)
    assert verdict.success and not paper.complete


def test_octants_about_the_centre_count_directions():
    vectors = np.array([[1, 1, 1], [-1, 1, 1], [1, -1, -1], [-1, -1, -1]] * 10, float)
    counts, reached = octants_about_centre(vectors)
    assert counts.tolist() == [10, 0, 0, 10, 10, 0, 0, 10] and reached == 4
