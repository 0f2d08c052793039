"""Synthetic flights: the error model's truth and the survey's track, checked against
relations computed here rather than in sim.stimulus.scenario."""

import numpy as np
import pytest

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
