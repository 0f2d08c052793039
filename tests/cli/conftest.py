"""Fixtures of the summary and papers tests: a one-minute calibration flight on a card
image, calibrated, with its truth (tests/cli/flights.py builds them)."""

import sys
from pathlib import Path

import pytest

from maglog.calib.pipeline import calibrate_card
from maglog.cli.summary import CAUSES
from maglog.sim.stimulus.scenario import make_flight

# Tests are no package: the folder goes on the path for the helper module.
sys.path.insert(0, str(Path(__file__).parent))
from flights import truth_for, write_card


@pytest.fixture(scope="session")
def flown(tmp_path_factory):
    """(flight, log bytes, card image path, truth, calibration run, counters) for a one-
    minute calibration flight: the counters are the truth's (a gateware that agrees). The
    sensor is turned over the whole sphere, so the flight determines every parameter and the
    run can pass (a minute of a UAV's +-30 deg leaves k33 and c3 undetermined: issue 24)."""
    folder = tmp_path_factory.mktemp("flown")
    flight = make_flight(coverage="full", seconds=60, seed=5)
    data = flight.log()
    image = write_card(folder / "card.img", data)
    truth = truth_for(flight, data)
    run = calibrate_card(image, ref="cesium")
    counters = {ch: {cause: truth["frames"][ch][cause] for cause in CAUSES}
                for ch in truth["frames"]}
    return flight, data, image, truth, run, counters
