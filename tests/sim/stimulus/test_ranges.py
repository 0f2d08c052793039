"""Scenario values range-checked when the file is read (issue 23's fuzz findings): numbers
that overflow, durations that would fill the memory, settings no flight has, fields the
sensors' formats cannot carry; each a one-line ScenarioError naming file, table and key."""

from __future__ import annotations

import pytest

from maglog.sim.stimulus import ScenarioError, load_scenario
from maglog.sim.stimulus.config import MAX_SCENARIO_S, loads_scenario

from .conftest import SHORT


def _error(text, source="fuzz.toml"):
    with pytest.raises(ScenarioError) as error:
        loads_scenario(text, source=source)
    message = str(error.value)
    assert "\n" not in message and message.startswith(f"{source}: ")
    return message


@pytest.mark.parametrize("text, where", [
    ("[scenario]\nseed = " + "9" * 5000 + "\n", "an integer with too many digits"),
    ("[scenario]\nseed = 4294967296\n", "[scenario] seed must be at most 4294967295"),
    ("[flight.ground]\nseconds = 9223372036854775807\n",
     "[flight.ground] seconds must be at most 21600"),
    ("[flight.landing]\nseconds = 1e9\n", "[flight.landing] seconds must be at most 21600"),
    ("[flight.survey]\nlegs = 9223372036854775807\n", "[flight.survey] legs must be at most"),
    ("[flight.takeoff]\nheight_m = 9007199254740993\n",
     "[flight.takeoff] height_m must be at most 10000"),
    ("[recording]\nend_after_stop_s = 2147483648\n",
     "[recording] end_after_stop_s must be at most 3600"),
    ("[flight.dynamics]\nturbulence_deg = 65536\n",
     "[flight.dynamics] turbulence_deg must be at most 30"),
    ("[errors]\nnoise_nT = 9.2e18\n", "[errors] noise_nT must be at most 1000"),
    ("[channels.cesium]\nnoise_nT = 1e300\n", "[channels.cesium] noise_nT must be at most"),
    ("[[anomaly.dipole]]\nnorth_m = 0.0\neast_m = 0.0\ndepth_m = 1.0\nmoment_Am2 = 1e15\n",
     "[[anomaly.dipole]] #1 moment_Am2 must be at most 1e+13"),
    ("[scenario]\nclk_freq_hz = 1e300\n", "[scenario] clk_freq_hz must be within"),
    ("[flight.survey]\nspeed_m_s = 1e-300\n", "[flight.survey] speed_m_s must be within"),
    ("[diurnal]\namplitude_nT = 1" + "0" * 400 + "\n",
     "[diurnal] amplitude_nT must be a finite number, not an integer of 1329 bits"),
    ("[errors]\nmounting_deg = [0, 0, 1" + "0" * 400 + "]\n",
     "[errors] mounting_deg must be a non-empty list of finite numbers"),
])
def test_out_of_range_values_are_refused_when_read(text, where):
    assert where in _error(text)


def test_a_run_longer_than_a_scenario_may_be_names_its_longest_part():
    # Each part within its own limit, the whole over six hours.
    message = _error("[flight.ground]\nseconds = 20000.0\n[flight.landing]\nseconds = 5000.0\n")
    assert f"more than a scenario may ({MAX_SCENARIO_S:,.0f} s)" in message
    assert "the longest part: [flight.ground] seconds (20,000 s)" in message
    message = _error("[flight.survey]\nlegs = 10000\nleg_length_m = 100000.0\n")
    assert "the longest part: [flight.survey] legs, leg_length_m" in message


def test_long_values_and_keys_are_echoed_cut_short():
    for text in ("[gps]\ntalker = '" + "x" * 10_000 + "'\n",
                 "[site]\n" + "k" * 10_000 + " = 1\n",
                 "[" + "t" * 10_000 + "]\na = 1\n",
                 "[scenario]\nseed = [" + ", ".join(["1"] * 5000) + "]\n",
                 "[errors]\nmounting_deg = [" + ", ".join(["1.5"] * 5000) + "]\n"):
        message = _error(text)
        assert len(message) < 300, message
        assert "…" in message or "items" in message, message


def test_run_seconds_estimates_the_built_run():
    # The estimate made before anything is built is within the press search of the run.
    for name in ("short", "default", "survey"):
        scenario = load_scenario(name)
        until = scenario.build().system.until if name == "short" else None
        estimate = scenario.run_seconds()
        assert 0 < estimate
        if until is not None:
            assert until - 5.0 <= estimate <= until
    assert abs(load_scenario("survey").run_seconds() - 797.6) < 5.0


def _built_error(extra):
    with pytest.raises(ScenarioError) as error:
        loads_scenario(SHORT + extra, source="fuzz.toml").build()
    message = str(error.value)
    assert "\n" not in message and message.startswith("fuzz.toml: ")
    return message


@pytest.mark.parametrize("extra, sensor, cause", [
    # A dipole of 1e13 A·m² a metre below the take-off point.
    ("[[anomaly.dipole]]\nnorth_m = 0.0\neast_m = 0.0\ndepth_m = 1.0\nmoment_Am2 = 1e13\n",
     "magnetometer", "[[anomaly.dipole]] #1"),
    # A small one 1 mm below the ground, the flight 1 µm above it.
    ("[[anomaly.dipole]]\nnorth_m = 0.0\neast_m = 0.0\ndepth_m = 0.001\nmoment_Am2 = 1.0\n",
     "magnetometer", "[[anomaly.dipole]] #1"),
    ("[interference]\nvector_eddy_s = [1e6, 0, 0, 0, 0, 0, 0, 0, 0]\n",
     "magnetometer", "[interference] vector_eddy_s"),
    ("[interference]\ntl_coefficients = [1e6" + ", 0" * 17 + "]\n",
     "cesium", "[interference] tl_coefficients"),
])
def test_fields_beyond_the_sensor_formats_name_their_cause(extra, sensor, cause):
    message = _built_error(extra)
    assert f"the {sensor}" in message and "outside its format's" in message
    assert f"the largest cause: {cause}" in message


def test_the_one_micrometre_flight_is_allowed_but_its_field_refused():
    message = _built_error("[[anomaly.dipole]]\nnorth_m = 0.0\neast_m = 0.0\ndepth_m = 0.001\n"
                           "moment_Am2 = 1.0\n").replace("takeoff", "")
    assert "PMAG1" in message
