"""Heading: tilt compensation against a rotation built independently, declination, circle."""

import datetime

import numpy as np
import pytest

from maglog.calib.heading import (declination, fit_circle, tilt_compensated_heading,
                                  true_heading)


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
