"""Scenario files: every key checked, every error one line naming the file, table and key."""

from __future__ import annotations

import datetime as _dt
import tomllib

import pytest

from maglog.sim.stimulus import ScenarioError, default_scenario_path, load_scenario
from maglog.sim.stimulus.config import SCHEMA, loads_scenario, scenario_from_dict

from .conftest import SHORT


def _load(tmp_path, text):
    path = tmp_path / "scenario.toml"
    path.write_text(text)
    return load_scenario(path)


@pytest.mark.parametrize("text, message", [
    ("[flight.calibration]\nseconds = -3\n",
     "scenario.toml: [flight.calibration] seconds must be > 0, not -3"),
    ("[site]\nlatitude = 3\n",
     "scenario.toml: [site] unknown key 'latitude' (known: lat_deg, lon_deg, ground_alt_m)"),
    ("[sitex]\na = 1\n",
     "scenario.toml: unknown table [sitex] (known: anomaly, channels, diurnal, errors, "
     "faults, flight, gps, interference, recording, scenario, site)"),
    ("[flight.hover]\nseconds = 3\n",
     "scenario.toml: unknown table [flight.hover] (known: flight.ground, flight.takeoff, "
     "flight.calibration, flight.survey, flight.landing, flight.dynamics)"),
    ("[scenario]\nseed = 'a'\n", "scenario.toml: [scenario] seed must be an integer, not 'a'"),
    ("[scenario]\nseed = -1\n", "scenario.toml: [scenario] seed must be >= 0, not -1"),
    ("[scenario]\nstart = 3\n", "scenario.toml: [scenario] start must be a TOML date-time "
     "(e.g. 2026-06-01T10:00:00Z), not 3"),
    ("[channels.mag]\nrate_hz = 60\n",
     "scenario.toml: [channels.mag] rate_hz must be within 10..50, not 60"),
    ("[channels.gps]\ntiming = 'often'\n",
     "scenario.toml: [channels.gps] timing must be one of rate, groups, stream, not 'often'"),
    ("[errors]\npreset = 'paper_b'\n",
     "scenario.toml: [errors] preset must be one of default, paper_a, none, not 'paper_b'"),
    ("[errors]\nmounting_deg = [1, 2]\n", "scenario.toml: [errors] mounting_deg must be "
     "three angles (roll, pitch, yaw), not [1.0, 2.0]"),
    ("[gps]\ntalker = 'gp'\n", "scenario.toml: [gps] talker must be two upper-case letters, "
     "not 'gp'"),
    ("[gps]\ndistractors = 1\n", "scenario.toml: [gps] distractors must be true or false, "
     "not 1"),
    ("[flight.calibration]\nheadings_deg = []\n", "scenario.toml: [flight.calibration] "
     "headings_deg must be a non-empty list of finite numbers, not []"),
    ("[[faults.noise_burst]]\nchannel = 'mag'\nend_s = 3\n",
     "scenario.toml: [[faults.noise_burst]] #1 start_s is required"),
    ("[[faults.noise_burst]]\nchannel = 'imu'\nstart_s = 1\nend_s = 3\n",
     "scenario.toml: [[faults.noise_burst]] #1 channel must be one of mag, gps, cesium, "
     "not 'imu'"),
    ("[[faults.dropped_bytes]]\nchannel = 'mag'\nstart_s = 1\nend_s = 3\n"
     "[[faults.dropped_bytes]]\nchannel = 'mag'\nstart_s = 5\nend_s = 4\n",
     "scenario.toml: [[faults.dropped_bytes]] #2 end_s must be > start_s (5), not 4.0"),
    ("[[faults.bad_checksum]]\nchannel = 'cesium'\nstart_s = 1\nend_s = 3\n",
     "scenario.toml: [[faults.bad_checksum]] #1 channel must be mag or gps (cesium lines "
     "have no checksum), not 'cesium'"),
    ("[[faults.baud_error]]\nchannel = 'gps'\nstart_s = 1\nend_s = 3\nerror = 0.3\n",
     "scenario.toml: [[faults.baud_error]] #1 error must be within -0.25..0.25, not 0.3"),
    ("[[faults.card_busy]]\nstart_s = 1\nend_s = 3\nbusy_s = 0.1\nchannel = 'mag'\n",
     "scenario.toml: [[faults.card_busy]] #1 unknown key 'channel' (known: start_s, end_s, "
     "busy_s)"),
    ("[[faults.lightning]]\nstart_s = 1\n", "scenario.toml: unknown fault kind "
     "[[faults.lightning]] (known: noise_burst, dropped_bytes, bad_checksum, baud_error, "
     "gps_outage, card_busy)"),
    ("[faults]\nnoise_burst = 3\n", "scenario.toml: faults.noise_burst must be an array of "
     "tables ([[faults.noise_burst]]), not 3"),
])
def test_errors_name_file_table_and_key(tmp_path, text, message):
    with pytest.raises(ScenarioError) as error:
        _load(tmp_path, text)
    assert str(error.value) == message


def test_bad_toml_and_missing_file(tmp_path):
    with pytest.raises(ScenarioError, match=r"^scenario.toml: not valid TOML: "):
        _load(tmp_path, "[site\n")
    with pytest.raises(ScenarioError, match=r"nope.toml: cannot read the scenario"):
        load_scenario(tmp_path / "nope.toml")


@pytest.mark.parametrize("text, message", [
    ("[recording]\nstart_s = 7\n", "[recording] start_s must be before take-off at 6 s "
     "([flight.ground] seconds), not 7.0"),
    ("[channels.gps]\nbaud = 1000000\n", "[channels.gps] baud must be reachable from the "
     "1.8432 MHz clock"),
    ("[[faults.noise_burst]]\nchannel = 'mag'\nstart_s = 10\nend_s = 10.2\ncount = 9\n",
     "[[faults.noise_burst]] #1 count must be at most the 4 mag frames the filter would keep "
     "in 10-10.2 s, not 9"),
    ("[channels.gps]\ncapture = 'absent.log'\n", "[channels.gps] capture must name a "
     "readable file, not 'absent.log'"),
])
def test_build_errors_name_the_key(tmp_path, text, message):
    scenario = _load(tmp_path, SHORT + text)
    with pytest.raises(ScenarioError) as error:
        scenario.build()
    assert str(error.value).startswith("scenario.toml: " + message)


def test_default_file_spells_out_every_default():
    """default.toml sets every key of the schema, to the schema's default (so the file is
    the documentation of the defaults and the code cannot drift from it)."""
    data = tomllib.loads(default_scenario_path().read_text())
    for table, keys in SCHEMA.items():
        given = data
        for part in table.split("."):
            given = given[part]
        assert set(given) == set(keys), table
        for name, key in keys.items():
            value = given[name]
            if isinstance(value, _dt.datetime):
                value = value.astimezone(_dt.timezone.utc)
            if table == "scenario" and name in ("name", "seed"):
                continue            # the default scenario's own name and seed
            assert value == key.default, f"[{table}] {name}"


def test_defaults_apply_and_datetimes_are_utc():
    scenario = loads_scenario("[scenario]\nstart = 2026-06-01T12:00:00+02:00\n")
    assert scenario.start == _dt.datetime(2026, 6, 1, 10, tzinfo=_dt.timezone.utc)
    assert scenario.channels["mag"].baud == 115_200 and scenario.errors.preset == "paper_a"
    assert scenario.flight.calibration.headings_deg == [0.0, 90.0, 180.0, 270.0]
    assert scenario_from_dict({}).clk_freq == 1_843_200.0


def test_every_key_is_documented():
    """docs/scenarios.md names every table and key of the schema and every fault key."""
    from pathlib import Path
    from maglog.sim.stimulus.config import FAULT_SCHEMA
    doc = (Path(__file__).resolve().parents[3] / "docs" / "scenarios.md").read_text()
    for table, keys in SCHEMA.items():
        assert f"[{table}]" in doc or f"[{table.split('.')[0]}.<" in doc, table
        for name in keys:
            assert f"`{name}`" in doc, f"[{table}] {name}"
    for kind, keys in FAULT_SCHEMA.items():
        assert f"`{kind}`" in doc
        for name in keys:
            assert f"`{name}`" in doc, f"{kind} {name}"
