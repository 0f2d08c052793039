"""The coverage gate: judged on the fit, it accepts tumbles and names what a UAV pattern or
a level flight leaves undetermined; paper B's octants about the running centroid do not."""

import numpy as np
import pytest

from maglog.calib.coverage import judge_coverage, octants_about_centre
from maglog.calib.ellipsoid import octant_coverage
from maglog.calib.scalar import calibrate_scalar
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
        assert full.accepted and full.undetermined == [], full.message
        assert full.octants_reached == 8 and full.message.startswith("accepted")

        uav, _ = _verdict("uav", model, noise, seed)
        # +-30 deg of roll and pitch: the vertical axis's scale and offset, exactly.
        assert not uav.accepted and uav.undetermined == ["k33", "c3"], uav.message
        assert not uav.held.any() and uav.octants_reached == 4
        assert "leaves k33, c3 undetermined" in uav.message

        planar, _ = _verdict("planar", model, noise, seed)
        held = [n for n, h in zip(("k11", "k12", "k13", "k22", "k23", "k33", "c1", "c2", "c3"),
                                  planar.held) if h]
        assert not planar.accepted and {"k33", "c3"} <= set(held), planar.message
        assert set(held) <= set(planar.undetermined)
        assert "not determined at all (held to the prior)" in planar.message


def test_paper_b_octants_disagree_with_what_the_fit_can_determine():
    # Paper B's running-centroid octants fill on UAV and level flights, whose fits leave
    # parameters undetermined, and may refuse a tumble whose fit determines everything.
    for coverage in ("uav", "planar"):
        verdict, flight = _verdict(coverage, "paper_a", 20.0, 3)
        assert octant_coverage(flight.b_meas).complete and not verdict.accepted
        assert verdict.paper_filled == 8
    # A tumble that starts slowly: the first samples' centroid wanders, one octant starves.
    flight = make_flight(coverage="full", seconds=8, rate=20, seed=4)
    order = np.argsort(flight.b_meas[:, 2])
    b, r = flight.b_meas[order], flight.total[order]
    paper = octant_coverage(b)
    verdict = judge_coverage(calibrate_scalar(b, r), b)
    assert verdict.accepted and not paper.complete


def test_octants_about_the_centre_count_directions():
    vectors = np.array([[1, 1, 1], [-1, 1, 1], [1, -1, -1], [-1, -1, -1]] * 10, float)
    counts, reached = octants_about_centre(vectors)
    assert counts.tolist() == [10, 0, 0, 10, 10, 0, 0, 10] and reached == 4
