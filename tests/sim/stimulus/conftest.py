"""Shared builds of the stimulus tests: the default scenario (built once per session) and a
short scenario for variations."""

from __future__ import annotations

import pytest

from maglog.sim.stimulus import load_scenario

#: A short flight (about 20 s) for tests that vary a scenario: one calibration heading, no
#: survey lines.
SHORT = """
[scenario]
seed = 3
[flight.ground]
seconds = 6.0
[flight.takeoff]
seconds = 3.0
height_m = 10.0
[flight.calibration]
headings_deg = [0.0]
seconds = 6.0
turn_s = 1.0
[flight.survey]
legs = 0
[flight.landing]
seconds = 3.0
"""


@pytest.fixture(scope="session")
def default_stim():
    return load_scenario().build()
