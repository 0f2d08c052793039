"""Stimulus: flight scenarios (TOML), the truth they imply, and the sensor byte streams.

::

    from maglog.sim.stimulus import load_scenario
    stim = load_scenario().build()      # the built-in default (default.toml)
    stim.system                         # SystemScenario: channels, bursts, presses, until
    stim.flight                         # Flight: attitude, Earth field, magnetometer output
    stim.truth                          # truth.json's content
    stim.card                           # card-model options ({"busy_spikes": [...]})
    stim.write_truth(folder)            # truth.json and attitude.csv

The keys of a scenario file: docs/scenarios.md.
"""

from .build import Stimulus
from .config import (ScenarioError, SurveyScenario, default_scenario_path, load_scenario,
                     loads_scenario)
from .errors import PRESETS, preset

__all__ = ["load_scenario", "loads_scenario", "default_scenario_path", "Stimulus",
           "SurveyScenario", "ScenarioError", "PRESETS", "preset"]
