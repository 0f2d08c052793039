"""The survey's geophysics (sim/stimulus/geophysics.py) against formulas written here: the
point dipole's field, the Tolles–Lawson terms, the diurnal sinusoid, and the base station's
file."""

import datetime as _dt
import re

import numpy as np
import pytest

from maglog.sim.stimulus.geophysics import (TL_TERM_NAMES, anomaly_total, anomaly_vector,
                                            base_station_csv, diurnal_nT, dipole_moment_ned,
                                            tl_features)

#: μ0 / 4π in nT·m/A: B = 100 (3 r̂ (m·r̂) − m) / r³ nT with m in A·m², r in m.
MU0_4PI_NT = 100.0
F_SITE = np.array([21_500.0, 750.0, 43_100.0])          # an IGRF-like NED vector, nT


def point_dipole_ned(moment_ned, source_ned, point_ned):
    """The field (NED, nT) of a point dipole: the textbook formula, no library."""
    r = np.asarray(point_ned, float) - np.asarray(source_ned, float)
    dist = np.linalg.norm(r, axis=-1, keepdims=True)
    rhat = r / dist
    m = np.asarray(moment_ned, float)
    return MU0_4PI_NT * (3 * rhat * (rhat @ m)[..., None] - m) / dist ** 3


def survey(dipoles, **diurnal):
    d = {"amplitude_nT": 0.0, "pulsation_nT": 0.0, "pulsation_period_s": 600.0,
         "lon_deg": 8.5, "start_seconds_of_day": 36_000.0, "base_igrf_total_nT": 48_000.0,
         "base_rate_hz": 1.0, "base_noise_nT": 0.0}
    d.update(diurnal)
    return {"igrf_site_ned_nT": list(F_SITE), "dipoles": dipoles, "diurnal": d}


DIPOLES = [
    {"north_m": 90.0, "east_m": 55.0, "depth_m": 20.0,
     "moment_ned_Am2": list(dipole_moment_ned(1.5e5, None, None, F_SITE))},
    {"north_m": 200.0, "east_m": 150.0, "depth_m": 35.0,
     "moment_ned_Am2": list(dipole_moment_ned(1.2e5, -30.0, 120.0, F_SITE))},
]


def test_moments_induced_along_the_field_remanent_by_angles():
    induced = np.array(DIPOLES[0]["moment_ned_Am2"])
    np.testing.assert_allclose(induced, 1.5e5 * F_SITE / np.linalg.norm(F_SITE))
    remanent = np.array(DIPOLES[1]["moment_ned_Am2"])
    # inclination −30° (pointing up), declination 120° (south-east)
    assert remanent[2] == pytest.approx(-1.2e5 * 0.5)
    horizontal = 1.2e5 * np.cos(np.radians(30))
    assert remanent[0] == pytest.approx(horizontal * -0.5)
    assert remanent[1] == pytest.approx(horizontal * np.sqrt(3) / 2)


def test_anomaly_against_the_point_dipole_formula():
    rng = np.random.default_rng(4)
    north, east = rng.uniform(-50, 300, 200), rng.uniform(-50, 250, 200)
    up = rng.uniform(5, 80, 200)
    point = np.column_stack([north, east, -up])
    expected = sum(point_dipole_ned(d["moment_ned_Am2"],
                                    [d["north_m"], d["east_m"], d["depth_m"]], point)
                   for d in DIPOLES)
    np.testing.assert_allclose(anomaly_vector(DIPOLES, north, east, up), expected,
                               rtol=1e-9, atol=1e-9)
    total = np.linalg.norm(F_SITE + expected, axis=1) - np.linalg.norm(F_SITE)
    np.testing.assert_allclose(anomaly_total(survey(DIPOLES), north, east, up), total,
                               rtol=1e-9, atol=1e-9)
    # Over an induced source the total-field anomaly is positive and of the expected size:
    # mostly the field's component along F, 2 m / r³ on the axis at high inclination.
    above = anomaly_total(survey(DIPOLES[:1]), 90.0, 55.0, 40.0)
    assert isinstance(above, float) and 90 < above < 2 * MU0_4PI_NT * 1.5e5 / 60 ** 3
    # Broadcasting: a grid against a scalar height.
    grid = anomaly_total(survey(DIPOLES), *np.meshgrid([0.0, 100.0], [0.0, 50.0, 90.0]), 40.0)
    assert grid.shape == (3, 2)
    assert np.all(anomaly_total(survey([]), north, east, up) == 0)


def test_tl_features_term_by_term():
    rng = np.random.default_rng(7)
    u = rng.normal(size=(50, 3))
    u /= np.linalg.norm(u, axis=1, keepdims=True)
    du = rng.normal(size=(50, 3))
    total = rng.uniform(40_000, 50_000, 50)
    got = tl_features(u, total, du)
    assert got.shape == (50, 18) and len(TL_TERM_NAMES) == 18
    for k, name in enumerate(TL_TERM_NAMES):
        # Evaluate the name itself: "T*u1*u2'" is T · u1 · du2/dt.
        factors = name.split("*")
        value = np.ones(50)
        for f in factors:
            if f == "T":
                value = value * total
            elif f.endswith("'"):
                value = value * du[:, int(f[1]) - 1]
            else:
                value = value * u[:, int(f[1]) - 1]
        np.testing.assert_allclose(got[:, k], value, rtol=1e-12, err_msg=name)
    assert TL_TERM_NAMES[:3] == ("u1", "u2", "u3")
    assert TL_TERM_NAMES[3 + 3] == "T*u2*u2" and TL_TERM_NAMES[9 + 4] == "T*u2*u2'"


def test_diurnal_peaks_at_13_local_solar_time_and_pulsates():
    lon = 8.5
    s = survey([], amplitude_nT=20.0, lon_deg=lon, start_seconds_of_day=0.0)
    t = np.arange(0.0, 86_400.0, 60.0)
    d = diurnal_nT(s, t)
    peak_utc_h = t[np.argmax(d)] / 3600
    assert peak_utc_h == pytest.approx(13.0 - lon / 15, abs=1 / 60)
    assert d.max() == pytest.approx(20.0, abs=1e-3) and d.min() == pytest.approx(-20.0, abs=1e-3)
    p = survey([], pulsation_nT=2.0, pulsation_period_s=600.0, start_seconds_of_day=36_000.0)
    assert diurnal_nT(p, 150.0) == pytest.approx(2.0)
    assert diurnal_nT(p, 450.0) == pytest.approx(-2.0)
    # The start's time of day moves the daily term only.
    later = survey([], amplitude_nT=20.0, lon_deg=lon, start_seconds_of_day=3600.0)
    assert diurnal_nT(later, 0.0) == pytest.approx(diurnal_nT(s, 3600.0))


def test_base_station_csv_format():
    s = survey([], amplitude_nT=20.0, base_rate_hz=2.0, base_noise_nT=0.0)
    start = _dt.datetime(2026, 6, 1, 10, 0, 0, tzinfo=_dt.timezone.utc)
    text = base_station_csv(s, start, 10.0, np.random.default_rng(0)).decode("ascii")
    lines = text.splitlines()
    assert lines[0] == "time_utc,total_nT" and text.endswith("\n")
    rows = [line.split(",") for line in lines[1:]]
    assert all(re.fullmatch(r"\d{4}-\d\d-\d\dT\d\d:\d\d:\d\d\.\d{3}Z", r[0]) for r in rows)
    assert rows[0][0] == "2026-06-01T09:59:00.000Z"
    assert rows[1][0] == "2026-06-01T09:59:00.500Z"
    assert rows[-1][0] == "2026-06-01T10:01:10.000Z"
    t = np.arange(-60.0, 70.0 + 1e-9, 0.5)
    values = np.array([float(r[1]) for r in rows])
    np.testing.assert_allclose(values, 48_000.0 + diurnal_nT(s, t), atol=5e-4)
