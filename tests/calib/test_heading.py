"""Heading: tilt compensation against a rotation built independently, declination, circle."""

import datetime

import numpy as np
import pytest

from maglog.calib.heading import (align_heading, declination, fit_circle, straight_legs,
                                  tilt_compensated_heading, true_heading)
from maglog.calib.logparse import parse_log
from maglog.calib.scalar import apply_scalar, calibrate_scalar
from maglog.sim.stimulus.scenario import ErrorModel, make_survey


def body_field(field_ned, heading, pitch, roll):
    """The NED field seen in the body frame: b = R_x(roll)^T R_y(pitch)^T R_z(heading)^T f."""
    def rz(a):
        return np.array([[np.cos(a), -np.sin(a), 0], [np.sin(a), np.cos(a), 0], [0, 0, 1]])

    def ry(a):
        return np.array([[np.cos(a), 0, np.sin(a)], [0, 1, 0], [-np.sin(a), 0, np.cos(a)]])

    def rx(a):
        return np.array([[1, 0, 0], [0, np.cos(a), -np.sin(a)], [0, np.sin(a), np.cos(a)]])
    return (rz(heading) @ ry(pitch) @ rx(roll)).T @ field_ned


@pytest.mark.parametrize("heading,pitch,roll", [(0, 0, 0), (90, 10, -5), (225, -30, 30),
                                                (359, 25, 20), (135, 0, 45)])
def test_tilt_compensation_recovers_the_heading(heading, pitch, roll):
    field = np.array([21_000.0, 1_600.0, 44_000.0])          # north, east, down (nT)
    magnetic_north = np.degrees(np.arctan2(field[1], field[0]))
    b = body_field(field, np.radians(heading), np.radians(pitch), np.radians(roll))
    got = tilt_compensated_heading(b[None, :], np.radians(roll), np.radians(pitch))[0]
    expected = (heading - magnetic_north) % 360
    assert min(abs(got - expected), 360 - abs(got - expected)) < 1e-9


def test_declination_and_true_heading():
    d = declination(48.1, 11.5, 500.0, datetime.datetime(2026, 11, 21))
    assert 3.0 < d < 6.0                                      # central Europe, 2026: ~4.4°
    assert true_heading(358.0, d) == pytest.approx((358.0 + d) % 360)


def test_circle_fit_recovers_the_hard_iron_offset():
    rng = np.random.default_rng(1)
    angle = rng.uniform(0, np.pi, 200)                        # half a turn is enough
    x = 350.0 + 21_000.0 * np.cos(angle) + rng.normal(scale=5, size=200)
    y = -120.0 + 21_000.0 * np.sin(angle) + rng.normal(scale=5, size=200)
    fit = fit_circle(x, y)
    np.testing.assert_allclose(fit.center, [350.0, -120.0], atol=5.0)
    assert fit.radius == pytest.approx(21_000.0, abs=5.0)
    assert fit.rms < 10


def test_bad_input():
    with pytest.raises(ValueError, match="at least 3 points"):
        fit_circle([1, 2], [1, 2])
    with pytest.raises(ValueError, match="do not lie on a circle"):
        fit_circle([0, 1, 2, 3], [0, 1, 2, 3])
    with pytest.raises(ValueError, match="three components"):
        tilt_compensated_heading(np.zeros((4, 2)), 0, 0)


def vtg_series(segments, rate=1.0):
    """Course-over-ground records: (seconds, course at the start, course at the end, speed)
    segments joined end to end."""
    t, course, speed = [], [], []
    now = 0.0
    for seconds, c0, c1, v in segments:
        n = int(seconds * rate)
        t.append(now + np.arange(n) / rate)
        course.append((c0 + (c1 - c0) * np.arange(n) / n) % 360)
        speed.append(np.full(n, v))
        now += n / rate
    return np.concatenate(t), np.concatenate(course), np.concatenate(speed)


def test_straight_legs_are_found_between_turns():
    t, course, speed = vtg_series([(60, 30, 30, 15), (12, 30, 210, 15), (60, 210, 210, 12),
                                   (12, 210, 390, 15), (10, 30, 30, 15), (40, 30, 30, 1.0),
                                   (50, 120, 120, 14)])
    legs = straight_legs(t, course, speed)
    assert [round(leg.course) for leg in legs] == [30, 210, 120]
    # Each turn's first record still has the old course: 61 s of records less 2 s at each end.
    assert [round(leg.duration) for leg in legs] == [56, 56, 45]
    assert legs[1].speed == pytest.approx(12)
    # The 10 s line after the second turn is too short; the slow stretch does not count.
    assert all(leg.start > 0 for leg in legs)


def test_straight_legs_rejects_climbs_and_splits_at_gaps():
    t, course, speed = vtg_series([(60, 90, 90, 15), (60, 90, 90, 15)])
    altitude = np.where(t < 60, 300.0, 300.0 + 2.0 * (t - 60))    # the second half climbs
    legs = straight_legs(t, course, speed, altitude_t=t, altitude=altitude, min_seconds=20,
                         max_course_spread=3.0)
    assert len(legs) == 0            # one run across both halves: its climb is 1 m/s
    gap = t.copy()
    gap[60:] += 10                   # a 10 s hole in the records splits the run
    legs = straight_legs(gap, course, speed, altitude_t=gap, altitude=altitude)
    assert len(legs) == 1 and legs[0].end < 60 and abs(legs[0].climb) < 1e-9
    with pytest.raises(ValueError, match="matching 1-D"):
        straight_legs(t, course[:-1], speed)


def legs_with_headings(courses, offset, a, b, seconds=50, noise=0.3, seed=0):
    rng = np.random.default_rng(seed)
    segments = []
    for course in courses:
        segments += [(seconds, course, course, 15), (12, course, course + 90, 15)]
    t, course, speed = vtg_series(segments)
    legs = straight_legs(t, course, speed)
    c = np.radians(course)
    heading = (course + offset + a * np.sin(c) + b * np.cos(c)
               + rng.normal(scale=noise, size=t.size)) % 360
    return t, heading, legs


def test_alignment_separates_the_offset_from_the_crab():
    t, heading, legs = legs_with_headings([30, 210, 30, 210], offset=4.0, a=12.0, b=-5.0)
    fit = align_heading(t, heading, legs)
    assert fit.offset == pytest.approx(4.0, abs=0.15)
    assert fit.offset_std < 0.2
    corrected = fit.apply(heading)
    assert np.all(np.abs((corrected - heading + 180) % 360 - 180 + 4.0) < 0.15)
    # With three directions the sinusoid itself is determined too.
    t, heading, legs = legs_with_headings([0, 120, 240, 60, 180, 300], offset=-2.5, a=8.0,
                                          b=3.0, seed=1)
    fit = align_heading(t, heading, legs)
    assert fit.offset == pytest.approx(-2.5, abs=0.1)
    np.testing.assert_allclose(fit.sinusoid, (8.0, 3.0), atol=0.2)
    assert not fit.warnings


def test_alignment_across_north_and_one_direction():
    t, heading, legs = legs_with_headings([359, 179, 359, 179], offset=1.5, a=0.0, b=0.0)
    assert align_heading(t, heading, legs).offset == pytest.approx(1.5, abs=0.15)
    t, heading, legs = legs_with_headings([90, 90, 90], offset=1.0, a=6.0, b=0.0)
    fit = align_heading(t, heading, legs)
    assert any("one direction" in w for w in fit.warnings)
    assert fit.offset == pytest.approx(7.0, abs=0.2)        # the sum: nothing to separate
    assert align_heading(t, heading, []) is None


def test_survey_alignment_recovers_the_mounting_yaw():
    """End to end on a survey flight with the sensor yawed 5° in the airframe: calibrate the
    magnitude, then align the heading on the lines from the log's own VTG, assuming level
    flight; the offset must match the constant part of the true heading error."""
    flight = make_survey(errors=ErrorModel(mounting=(0.5, -0.3, 5.0)), seed=4)
    parsed = parse_log(flight.log())
    ces = parsed.cesium
    r = np.interp(parsed.mag.t, ces.t, ces.field)
    fit = calibrate_scalar(parsed.mag.b, r)
    vectors = apply_scalar(fit.K, fit.c, parsed.mag.b)
    decl = declination(flight.lat, flight.lon, flight.altitude_m, flight.start)
    level = true_heading(tilt_compensated_heading(vectors, 0.0, 0.0), decl)
    vtg = parsed.vtg
    legs = straight_legs(vtg.t, vtg.course, vtg.speed, altitude_t=parsed.gga.t,
                         altitude=parsed.gga.altitude)
    assert len(legs) == 6
    alignment = align_heading(parsed.mag.t, level, legs)
    # The truth: the heading error with the true attitude, averaged over the two directions.
    with_attitude = true_heading(tilt_compensated_heading(vectors, flight.roll, flight.pitch),
                                 decl)
    error = (with_attitude - np.degrees(flight.heading) + 180) % 360 - 180
    per_direction = []
    for course in (30.0, 210.0):
        sel = np.zeros(len(error), bool)
        for leg in legs:
            if abs((leg.course - course + 180) % 360 - 180) < 5:
                sel |= (parsed.mag.t >= leg.start) & (parsed.mag.t <= leg.end)
        per_direction.append(error[sel].mean())
    constant = float(np.mean(per_direction))
    assert abs(constant) > 2                                  # there is something to find
    assert alignment.offset == pytest.approx(constant, abs=0.4)
    aligned = (alignment.apply(with_attitude) - np.degrees(flight.heading) + 180) % 360 - 180
    on_legs = np.zeros(len(error), bool)
    for leg in legs:
        on_legs |= (parsed.mag.t >= leg.start) & (parsed.mag.t <= leg.end)
    assert np.sqrt(np.mean(aligned[on_legs] ** 2)) < 0.6 < np.sqrt(np.mean(error[on_legs] ** 2))
