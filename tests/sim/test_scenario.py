"""Synthetic flights: the error model's truth and the survey's track, checked against
relations computed here rather than in sim.stimulus.scenario."""

import dataclasses
import hashlib
import io
import json
import re
import tomllib
from pathlib import Path

import numpy as np
import pytest

from maglog.sim.stimulus import ScenarioError, load_scenario
from maglog.sim.stimulus.config import default_scenario_path, scenario_from_dict
from maglog.sim.stimulus.scenario import ErrorModel, make_flight, make_survey


def rot(axis, angle):
    """Right-handed rotation by ``angle`` about axis 0 (x), 1 (y) or 2 (z)."""
    c, s = np.cos(angle), np.sin(angle)
    return {0: np.array([[1, 0, 0], [0, c, -s], [0, s, c]]),
            1: np.array([[c, 0, s], [0, 1, 0], [-s, 0, c]]),
            2: np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]])}[axis]


@pytest.mark.parametrize("mounting", [(0.0, 0.0, 0.0), (1.5, -2.0, 7.0)])
def test_truth_maps_the_noise_free_output_onto_the_rotated_body_field(mounting):
    errors = ErrorModel(noise=0.0, mounting=mounting)
    flight = make_flight(coverage="full", seconds=5, errors=errors, seed=3)
    k, c, q = errors.truth_with_rotation()
    assert np.allclose(np.tril(k, -1), 0) and np.all(np.diag(k) > 0)
    np.testing.assert_allclose(q.T @ q, np.eye(3), atol=1e-12)
    calibrated = flight.b_meas @ k.T - c
    np.testing.assert_allclose(calibrated, flight.b_earth @ q, atol=1e-6)
    # The mounting, built here from elementary rotations (yaw, then pitch, then roll).
    roll, pitch, yaw = np.radians(mounting)
    r_m = rot(2, yaw) @ rot(1, pitch) @ rot(0, roll)
    sensor = flight.b_earth @ r_m
    m = errors.matrix()
    expected = (sensor + errors.hard_iron) @ m.T + errors.bias
    np.testing.assert_allclose(flight.b_meas, expected, atol=1e-6)


def test_survey_track_course_and_crab():
    wind = (4.0, -3.0)
    flight = make_survey(calibration_seconds=20, legs=3, leg_seconds=30, turn_seconds=10,
                         line_course_deg=60.0, airspeed=15.0, wind=wind, turbulence_deg=0.5,
                         seed=2)
    moving = flight.speed > 0
    dt = np.diff(flight.t)[0]
    # Course and speed from the positions' differences (the position after each sample).
    sel = moving[1:] & moving[:-1]
    v_n = (np.diff(flight.north_m) / dt)[sel]
    v_e = (np.diff(flight.east_m) / dt)[sel]
    course = np.degrees(np.arctan2(v_e, v_n))
    diff = (course - np.degrees(flight.course[1:][sel]) + 180) % 360 - 180
    assert np.max(np.abs(diff)) < 1e-6
    np.testing.assert_allclose(np.hypot(v_n, v_e), flight.speed[1:][sel], rtol=1e-9)
    # On a line the heading is the course plus the crab that cancels the cross wind.
    course = flight.course[-1]
    heading = flight.heading[-1]
    air = 15.0 * np.array([np.cos(heading), np.sin(heading)]) + np.array(wind)
    assert np.degrees(abs(np.arctan2(air[1], air[0]) - course)) < 1e-9
    assert abs(np.degrees(heading - course)) > 5            # a real crab angle
    # Lines are level up to the turbulence; the turns are banked.
    assert np.degrees(np.max(np.abs(flight.roll[-400:]))) < 3
    assert np.degrees(np.max(np.abs(flight.roll[moving]))) > 20
    log = flight.log()
    assert log.count(b"VTG,") == int(flight.t[-1]) + 1


def test_survey_rejects_impossible_wind():
    with pytest.raises(ValueError, match="below the airspeed"):
        make_survey(airspeed=10, wind=(8.0, 8.0))



# --- the survey scenario (sim/stimulus/flight.py, geophysics.py, build.py) -----------------

#: The default and short scenarios as they were before the survey features (commit 8c3c925),
#: in tests/sim/data/unchanged_<name>.json: they must not change (new features off, new
#: randomness from new generators). The wire bytes are hashed: they are what the logger
#: receives, promised byte for byte on any machine. The truth and the attitude are floats
#: whose last bits follow the CPU's BLAS kernel and SIMD paths, so they are compared with
#: tolerances. Regenerate deliberately with ``python tests/sim/test_scenario.py``.
UNCHANGED = ("default", "short")
DATA = Path(__file__).parent / "data"
#: Relative and absolute tolerance of the truth's and the attitude's floats.
RTOL, ATOL = 1e-9, 1e-9


def bursts_digest(stim):
    h = hashlib.sha256()
    for burst in stim.system.bursts:
        h.update(repr((burst.channel, burst.start, burst.baud)).encode())
        h.update(bytes(burst.data))
    return h.hexdigest()


def attitude_fingerprint(csv):
    """Row count, per-column sums, sums of squares and extremes, and every 97th row of the
    attitude CSV: a change of any value by more than the tolerances shows in one of them."""
    rows = np.loadtxt(io.BytesIO(csv), delimiter=",", skiprows=1, ndmin=2)
    return {"rows": len(rows), "sum": rows.sum(axis=0).tolist(),
            "sum_sq": (rows ** 2).sum(axis=0).tolist(), "min": rows.min(axis=0).tolist(),
            "max": rows.max(axis=0).tolist(), "every_97th": rows[::97].tolist()}


def snapshot(name):
    stim = load_scenario(name).build()
    return stim, {"bursts_sha256": bursts_digest(stim), "truth": stim.truth,
                  "attitude": attitude_fingerprint(stim.flight.attitude_csv())}


def assert_close_tree(got, want, path=""):
    """Equal structure and non-float leaves; floats within RTOL/ATOL."""
    if isinstance(want, dict):
        assert isinstance(got, dict) and sorted(got) == sorted(want), path
        for key in want:
            assert_close_tree(got[key], want[key], f"{path}.{key}")
    elif isinstance(want, list):
        assert isinstance(got, (list, tuple)) and len(got) == len(want), path
        for i, (g, w) in enumerate(zip(got, want)):
            assert_close_tree(g, w, f"{path}[{i}]")
    elif isinstance(want, float) or isinstance(got, float):
        assert isinstance(got, (int, float)) and not isinstance(got, bool), path
        assert abs(got - want) <= ATOL + RTOL * abs(want), f"{path}: {got!r} != {want!r}"
    else:
        assert got == want, f"{path}: {got!r} != {want!r}"


@pytest.mark.parametrize("name", UNCHANGED)
def test_existing_scenarios_unchanged(name, tmp_path):
    stim, got = snapshot(name)
    want = json.loads((DATA / f"unchanged_{name}.json").read_text())
    assert "survey" not in stim.truth and not stim.files
    assert got["bursts_sha256"] == want["bursts_sha256"]
    # Through JSON, as the truth file is written and read.
    assert_close_tree(json.loads(json.dumps(got["truth"])), want["truth"], "truth")
    assert_close_tree(got["attitude"], want["attitude"], "attitude")
    stim.write_truth(tmp_path)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["attitude.csv", "truth.json"]


def test_the_unchanged_check_sees_a_last_digit_and_a_byte():
    # The comparison itself: a float off by more than the tolerance, or one wire byte
    # changed, is caught; a change in the last bits is not.
    want = {"a": [1.0, 2.0], "b": "x"}
    assert_close_tree({"a": [1.0 + 1e-12, 2.0], "b": "x"}, want)
    with pytest.raises(AssertionError, match=r"\.a\[1\]"):
        assert_close_tree({"a": [1.0, 2.0 + 1e-6], "b": "x"}, want)
    with pytest.raises(AssertionError):
        assert_close_tree({"a": [1.0, 2.0], "b": "y"}, want)
    stim = load_scenario("short").build()
    before = bursts_digest(stim)
    burst = stim.system.bursts[3]
    stim.system.bursts[3] = dataclasses.replace(burst, data=bytes(burst.data[:-1]) + b"#")
    assert bursts_digest(stim) != before


def survey_data():
    """survey.toml as a dict."""
    return tomllib.loads(default_scenario_path().with_name("survey.toml").read_text())


def short_survey():
    """A shorter survey (about 150 s): two calibration headings, three 90 m lines, two tie
    lines; an ideal noise-free vector sensor and a noise-free cesium, so that the tests see
    the field itself."""
    data = survey_data()
    data["flight"].update({"ground": {"seconds": 6.0},
                           "takeoff": {"seconds": 4.0, "height_m": 40.0},
                           "calibration": {"headings_deg": [0.0, 90.0], "seconds": 12.0,
                                           "turn_s": 2.0},
                           "landing": {"seconds": 4.0}})
    data["flight"]["survey"].update(legs=3, leg_length_m=90.0, tie_lines=2)
    data["errors"] = {"preset": "none", "noise_nT": 0.0}
    data["channels"] = {"cesium": {"noise_nT": 0.0}}
    return scenario_from_dict(data, source="survey.toml")


@pytest.fixture(scope="module")
def survey_stim():
    return short_survey().build()


def point_dipole_ned(moment_ned, source_ned, point_ned):
    """A point dipole's field (NED, nT): 100 (3 r̂ (m·r̂) − m) / r³, m in A·m², r in m."""
    r = np.asarray(point_ned, float) - np.asarray(source_ned, float)
    dist = np.linalg.norm(r, axis=-1, keepdims=True)
    rhat = r / dist
    m = np.asarray(moment_ned, float)
    return 100.0 * (3 * rhat * (rhat @ m)[..., None] - m) / dist ** 3


def field_parts(stim, t):
    """The field the sensors should see at ``t``, from formulas here: the IGRF (the track's
    1 Hz grid), the dipoles at the position at ``t``, the diurnal along the IGRF."""
    track, survey = stim.track, stim.truth["survey"]
    igrf = np.column_stack([np.interp(t, track.field_t, track.field_ned[:, k])
                            for k in range(3)])
    point = np.column_stack([np.interp(t, track.t, track.north),
                             np.interp(t, track.t, track.east),
                             -np.interp(t, track.t, track.up)])
    b = sum(point_dipole_ned(d["moment_ned_Am2"], [d["north_m"], d["east_m"], d["depth_m"]],
                             point) for d in survey["dipoles"])
    d = survey["diurnal"]
    daily = d["amplitude_nT"] * np.cos(2 * np.pi * (
        d["start_seconds_of_day"] + t + d["lon_deg"] / 15 * 3600 - 13 * 3600) / 86_400)
    diurnal = daily + d["pulsation_nT"] * np.sin(2 * np.pi * t / d["pulsation_period_s"])
    unit = igrf / np.linalg.norm(igrf, axis=1, keepdims=True)
    return igrf, b, diurnal[:, None] * unit


def to_body(roll, pitch, heading, ned):
    rotations = np.array([rot(2, h) @ rot(1, p) @ rot(0, r)
                          for r, p, h in zip(roll, pitch, heading)])
    return np.einsum("nji,nj->ni", rotations, ned)


def body_at(stim, t):
    """The field in the body frame at ``t`` on the truth's 100 Hz attitude."""
    track = stim.track
    attitude = [np.interp(t, track.t, track.attitude[:, k]) for k in range(3)]
    return to_body(*attitude, sum(field_parts(stim, t)))


def test_survey_vector_sensor_sees_the_total_field_at_its_position(survey_stim):
    flight = survey_stim.flight
    igrf, b, diurnal = field_parts(survey_stim, flight.t)
    body = to_body(flight.roll, flight.pitch, flight.heading, igrf + b + diurnal)
    np.testing.assert_allclose(flight.b_earth, body, atol=1e-6)
    # The sources matter along the track: tens of nT over the first dipole's line.
    anomaly = np.linalg.norm(igrf + b, axis=1) - np.linalg.norm(igrf, axis=1)
    assert anomaly.max() > 50
    # The (ideal, noise-free) vector sensor adds E dB/dt, dB/dt from the 100 Hz attitude
    # (the turbulence makes it rough: a 20 Hz difference would not do).
    track = survey_stim.track
    d_body = np.gradient(body_at(survey_stim, track.t), track.t, axis=0)
    e = np.array(survey_stim.truth["survey"]["interference"]["vector_eddy_s"])
    eddy = np.column_stack([np.interp(flight.t, track.t, d_body[:, k]) for k in range(3)]) @ e.T
    assert np.abs(eddy).max() > 0.2
    np.testing.assert_allclose(flight.b_meas - flight.b_earth, eddy, atol=1e-5)


def test_survey_cesium_reads_total_field_plus_interference(survey_stim):
    """The cesium's lines against the formula evaluated here on the truth's 100 Hz attitude:
    T + Σ c_k term_k(u, T, u') + heading error × u3 (noise-free cesium)."""
    stim, track = survey_stim, survey_stim.track
    inter = stim.truth["survey"]["interference"]
    dense = body_at(stim, track.t)
    du = np.gradient(dense / np.linalg.norm(dense, axis=1, keepdims=True), track.t, axis=0)
    t, reading = cesium_readings(stim)
    body = body_at(stim, t)
    total = np.linalg.norm(body, axis=1)
    u = body / total[:, None]
    u_dot = np.column_stack([np.interp(t, track.t, du[:, k]) for k in range(3)])
    c = np.array(inter["tl_coefficients"])
    permanent = u @ c[:3]
    induced = total * sum(c[3 + k] * u[:, i] * u[:, j] for k, (i, j) in enumerate(
        [(0, 0), (0, 1), (0, 2), (1, 1), (1, 2), (2, 2)]))
    eddy = total * sum(c[9 + 3 * i + j] * u[:, i] * u_dot[:, j]
                       for i in range(3) for j in range(3))
    expected = total + permanent + induced + eddy + inter["heading_error_nT"] * u[:, 2]
    np.testing.assert_allclose(reading, expected, atol=6e-4)     # 0.001 nT resolution
    phase = next(p for p in stim.truth["flight"]["phases"] if p["name"] == "calibration")
    box = (t >= phase["start_s"]) & (t < phase["end_s"])
    assert np.ptp((permanent + induced + eddy)[box]) > 3
    assert np.ptp(eddy[box]) > 0.3


def cesium_readings(stim):
    items = [it for it in stim.items if it.type == "cesium"]
    return (np.array([it.t for it in items]),
            np.array([float(it.data.split(b",")[0][1:]) for it in items]))


def test_survey_lines_and_tie_lines(survey_stim):
    stim, track = survey_stim, survey_stim.track
    survey = stim.scenario.flight.survey           # course 0: lines north, steps east
    lines = stim.truth["survey"]["lines"]
    assert [(x["kind"], x["index"]) for x in lines] == [
        ("line", 0), ("line", 1), ("line", 2), ("tie", 0), ("tie", 1)]
    phases = {p["name"]: p for p in stim.truth["flight"]["phases"]}
    assert list(phases).index("tie") == list(phases).index("survey") + 1
    width = (survey.legs - 1) * survey.spacing_m
    for line in lines:
        inside = (track.t >= line["start_s"]) & (track.t <= line["end_s"])
        north, east = track.north[inside], track.east[inside]
        heading = np.degrees(track.attitude[inside, 2]) % 360
        middle = slice(len(north) // 4, 3 * len(north) // 4)
        phase = phases["survey" if line["kind"] == "line" else "tie"]
        assert phase["start_s"] <= line["start_s"] < line["end_s"] <= phase["end_s"]
        k = line["index"]
        if line["kind"] == "line":
            np.testing.assert_allclose(east, k * survey.spacing_m, atol=1e-6)
            assert sorted([north[0], north[-1]]) == pytest.approx([0.0, survey.leg_length_m])
            course = 0.0 if k % 2 == 0 else 180.0
        else:
            np.testing.assert_allclose(north, survey.leg_length_m * (k + 0.5) / 2, atol=1e-6)
            ends = [-survey.spacing_m, width + survey.spacing_m]
            assert [east[0], east[-1]] == pytest.approx(ends[::-1] if k % 2 == 0 else ends)
            course = 270.0 if k % 2 == 0 else 90.0
        offset = (heading[middle] - course + 180) % 360 - 180
        assert np.abs(offset).max() < 5, line
    # The time base of the log: seconds of day of the timestamp + t.
    time = stim.truth["survey"]["time"]
    assert time["start_seconds_of_day"] == 36_000.0 and "t_log" in time


def test_survey_truth_and_base_station(survey_stim, tmp_path):
    from maglog.sim.stimulus.geophysics import anomaly_total, diurnal_nT
    stim = survey_stim
    truth = json.loads(stim.write_truth(tmp_path).read_text())
    survey = truth["survey"]
    assert survey["origin"]["flight_height_m"] == 40.0
    assert [d["kind"] for d in survey["dipoles"]] == ["induced", "remanent", "induced"]
    assert len(survey["interference"]["tl_coefficients"]) == 18
    assert survey["diurnal"]["base_station"] == "base.csv"
    # anomaly_total: the sources at 40 m against the formula here, with the site's F.
    f = np.array(survey["igrf_site_ned_nT"])
    north, east = np.meshgrid(np.arange(-20.0, 300.0, 40.0), np.arange(-20.0, 230.0, 40.0))
    point = np.column_stack([north.ravel(), east.ravel(), np.full(north.size, -40.0)])
    b = sum(point_dipole_ned(d["moment_ned_Am2"], [d["north_m"], d["east_m"], d["depth_m"]],
                             point) for d in survey["dipoles"])
    np.testing.assert_allclose(anomaly_total(survey, north, east, 40.0).ravel(),
                               np.linalg.norm(f + b, axis=1) - np.linalg.norm(f), atol=1e-6)
    # base.csv: 60 s either side of the run, one row a second, the ground's total + D.
    rows = (tmp_path / "base.csv").read_text().splitlines()
    assert rows[0] == "time_utc,total_nT"
    stamps = [row.split(",")[0] for row in rows[1:]]
    assert all(re.fullmatch(r"2026-06-01T\d\d:\d\d:\d\d\.\d{3}Z", s) for s in stamps)
    assert stamps[0] == "2026-06-01T09:59:00.000Z"
    t = np.arange(len(stamps)) - 60.0
    assert t[-1] >= truth["until_s"] + 59
    values = np.array([float(row.split(",")[1]) for row in rows[1:]])
    residual = values - survey["diurnal"]["base_igrf_total_nT"] - diurnal_nT(survey, t)
    assert np.std(residual) == pytest.approx(survey["diurnal"]["base_noise_nT"], rel=0.3)
    assert abs(np.mean(residual)) < 0.005


@pytest.mark.parametrize("changes, message", [
    ({"anomaly": {"dipole": [{"north_m": 1.0, "east_m": 2.0, "moment_Am2": 5.0}]}},
     "survey.toml: [[anomaly.dipole]] #1 depth_m is required"),
    ({"anomaly": {"dipole": [{"north_m": 1.0, "east_m": 2.0, "depth_m": -5.0,
                              "moment_Am2": 5.0}]}},
     "survey.toml: [[anomaly.dipole]] #1 depth_m must be > 0, not -5.0"),
    ({"anomaly": {"dipole": [{"north_m": 1.0, "east_m": 2.0, "depth_m": 5.0,
                              "moment_Am2": 5.0, "inclination_deg": 30.0}]}},
     "survey.toml: [[anomaly.dipole]] #1 needs both inclination_deg and declination_deg "
     "(remanent) or neither (induced)"),
    ({"anomaly": {"dipole": [{"north_m": 1.0, "east_m": 2.0, "depth_m": 5.0,
                              "moment_Am2": 5.0, "inclination_deg": 95.0,
                              "declination_deg": 0.0}]}},
     "survey.toml: [[anomaly.dipole]] #1 inclination_deg must be within -90..90, not 95.0"),
    ({"anomaly": {"dipole": [{"north_m": 1.0, "east_m": 2.0, "depth_m": 5.0,
                              "moment_Am2": 5.0, "size_m": 3.0}]}},
     "survey.toml: [[anomaly.dipole]] #1 unknown key 'size_m'"),
    ({"anomaly": {"sphere": []}},
     "survey.toml: unknown table [anomaly.sphere] (known: [[anomaly.dipole]])"),
    ({"interference": {"tl_coefficients": [0.0] * 16}},
     "survey.toml: [interference] tl_coefficients must be 18 numbers, not 16"),
    ({"interference": {"vector_eddy_s": [0.0] * 3}},
     "survey.toml: [interference] vector_eddy_s must be 9 numbers, not 3"),
    ({"diurnal": {"phase_h": 3.0}}, "survey.toml: [diurnal] unknown key 'phase_h'"),
    ({"diurnal": {"base_station": "yes"}},
     "survey.toml: [diurnal] base_station must be true or false, not 'yes'"),
    ({"diurnal": {"pulsation_period_s": 0.0}},
     "survey.toml: [diurnal] pulsation_period_s must be > 0, not 0.0"),
    ({"flight": {"survey": {"legs": 1}}},
     "survey.toml: [flight.survey] tie_lines needs legs >= 2 and spacing_m > 0"),
    ({"flight": {"survey": {"tie_lines": -1}}},
     "survey.toml: [flight.survey] tie_lines must be >= 0, not -1"),
])
def test_survey_bad_keys(changes, message):
    data = survey_data()
    for table, values in changes.items():
        if table == "anomaly":
            data[table] = values
        elif table == "flight":
            data["flight"]["survey"].update(values["survey"])
        else:
            data[table].update(values)
    with pytest.raises(ScenarioError) as error:
        scenario_from_dict(data, source="survey.toml")
    assert str(error.value).startswith(message)


def test_survey_preset():
    """survey.toml as the issue asks: 8 lines of 300 m 30 m apart at 40 m, 3 tie lines,
    three sources of 20-200 nT at flight height (one remanent), 10-14 minutes."""
    from maglog.sim.stimulus.flight import survey_seconds
    from maglog.sim.stimulus.geophysics import anomaly_total, survey_truth
    scenario = load_scenario("survey")
    s = scenario.flight.survey
    assert (s.legs, s.leg_length_m, s.spacing_m, s.speed_m_s, s.tie_lines) == (
        8, 300.0, 30.0, 10.0, 3)
    assert scenario.flight.takeoff.height_m == 40.0 and not scenario.faults
    f = scenario.flight
    seconds = (f.ground.seconds + f.takeoff.seconds + f.landing.seconds
               + len(f.calibration.headings_deg) * f.calibration.seconds
               + sum(survey_seconds(s)))
    assert 600 <= seconds <= 840
    truth = survey_truth(scenario, [])
    assert sorted(d["kind"] for d in truth["dipoles"]) == ["induced", "induced", "remanent"]
    north, east = np.meshgrid(np.arange(-30.0, 330.0, 3.0), np.arange(-30.0, 240.0, 3.0))
    for dipole in truth["dipoles"]:
        assert 0 <= dipole["north_m"] <= 300 and 0 <= dipole["east_m"] <= 210
        assert 20 <= dipole["depth_m"] <= 50
        peak = np.abs(anomaly_total(dict(truth, dipoles=[dipole]), north, east, 40.0)).max()
        assert 20 <= peak <= 200
    assert scenario.diurnal.base_station and scenario.diurnal.amplitude_nT == 20.0


if __name__ == "__main__":
    DATA.mkdir(exist_ok=True)
    for scenario in UNCHANGED:
        (DATA / f"unchanged_{scenario}.json").write_text(
            json.dumps(snapshot(scenario)[1], sort_keys=True, indent=1) + "\n")
