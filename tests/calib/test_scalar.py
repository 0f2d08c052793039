"""Scalar calibration on seeded synthetic data with known parameters."""

import numpy as np
import pytest

from maglog.calib import _pso
from maglog.calib.scalar import apply_scalar, calibrate_scalar

FIELD = 50_000.0


def synthetic(seed, n=2000, noise=5.0, tilt=None):
    """Samples of the paper's model b = P (B_e + o) + w over attitudes: the full sphere, or
    directions within ``tilt`` degrees of the horizontal plane (near-planar flight)."""
    rng = np.random.default_rng(seed)
    if tilt is None:
        v = rng.normal(size=(n, 3))
    else:
        heading = rng.uniform(0, 2 * np.pi, n)
        dip = np.radians(rng.uniform(-tilt, tilt, n))
        v = np.column_stack([np.cos(dip) * np.cos(heading), np.cos(dip) * np.sin(heading),
                             np.sin(dip)])
    v /= np.linalg.norm(v, axis=1)[:, None]
    be = FIELD * v
    p = (np.array([[1.05, 0.02, -0.03], [0.0, 0.97, 0.01], [0.0, 0.0, 1.02]])
         @ np.array([[1, 0, 0], [0.01, 1, 0], [-0.02, 0.015, 1]]))
    o = np.array([300.0, -200.0, 150.0])
    b = (be + o) @ p.T + rng.normal(scale=noise, size=(n, 3))
    return b, p, o


def canonical(p, o):
    """The truth in the fitted form: K upper triangular with a positive diagonal."""
    q, r = np.linalg.qr(np.linalg.inv(p))
    signs = np.sign(np.diag(r))
    return r * signs[:, None], (q * signs).T @ o


@pytest.mark.parametrize("method", ["pso", "lm"])
def test_recovers_known_parameters_at_the_noise_floor(method):
    b, p, o = synthetic(1)
    result = calibrate_scalar(b, FIELD, method=method)
    k_true, c_true = canonical(p, o)
    floor = np.sqrt(np.mean((np.linalg.norm(apply_scalar(k_true, c_true, b), axis=1)
                             - FIELD) ** 2))
    assert result.success, result.message
    assert result.rms <= 1.01 * floor
    assert result.rms_before > 100 * result.rms
    np.testing.assert_allclose(result.K, k_true, atol=2e-4)
    np.testing.assert_allclose(result.c, c_true, atol=3.0)
    # The uncertainties are honest: the errors are within a few standard deviations.
    assert np.all(np.abs(result.x - np.r_[k_true[np.triu_indices(3)], c_true])
                  < 6 * result.uncertainties + 1e-9)


def test_numba_and_numpy_twins_agree():
    b, _, _ = synthetic(2, n=500)
    r = np.full(len(b), FIELD)
    params = np.random.default_rng(3).uniform(-1, 1, size=(16, 9)) + np.r_[
        1, 0, 0, 1, 0, 1, 0, 0, 0]
    np.testing.assert_allclose(_pso.cost_numba(params, b, r), _pso.cost_numpy(params, b, r),
                               rtol=1e-12)
    pso_numba = calibrate_scalar(b, FIELD, kernel="numba", iterations=50)
    pso_numpy = calibrate_scalar(b, FIELD, kernel="numpy", iterations=50)
    np.testing.assert_allclose(pso_numba.x, pso_numpy.x, rtol=1e-9, atol=1e-6)


def test_seeded_runs_repeat():
    b, _, _ = synthetic(4, n=300)
    first = calibrate_scalar(b, FIELD, seed=7, iterations=40)
    again = calibrate_scalar(b, FIELD, seed=7, iterations=40)
    assert np.array_equal(first.x, again.x)


def test_never_the_trivial_solution():
    # A constant reference lets K = 0, |c| = r reach zero cost; K's diagonal stays away.
    b, _, _ = synthetic(5, n=400)
    result = calibrate_scalar(b, FIELD)
    assert np.all(np.diag(result.K) > 0.4)
    assert result.rms < 10


@pytest.mark.parametrize("noise", [5.0, 100.0])
@pytest.mark.parametrize("coverage,limit", [("full", 1.01), ("uav", 1.01), ("planar", 1.10)])
def test_flight_coverages_reach_the_noise_floor(coverage, limit, noise):
    from maglog.sim.scenario import ErrorModel, make_flight
    flight = make_flight(coverage=coverage, seconds=100, seed=3, errors=ErrorModel(noise=noise))
    k_true, c_true = flight.errors.truth()
    floor = np.sqrt(np.mean((np.linalg.norm(apply_scalar(k_true, c_true, flight.b_meas),
                                            axis=1) - flight.total) ** 2))
    result = calibrate_scalar(flight.b_meas, flight.total)
    assert np.all(np.isfinite(result.x))
    assert result.rms <= limit * floor
    if coverage == "planar":
        # A level flight cannot separate the vertical axis's scale from its offset: said,
        # and fitted with that combination held to the prior instead of fitting noise.
        assert result.warnings and "k33" in result.warnings[0] and "c3" in result.warnings[0]
        assert "constrained fit" in result.warnings[0]
        assert result.rms >= 0.98 * floor
    else:
        assert result.warnings == []


@pytest.mark.parametrize("b,r,message", [
    (np.zeros((20, 2)), FIELD, r"Samples must be an \(N, 3\) array, not shape \(20, 2\)"),
    (np.zeros((5, 3)), FIELD, "At least 10 samples are needed for nine parameters, not 5"),
    (np.full((20, 3), np.nan), FIELD, "Samples must be finite"),
    (np.ones((20, 3)), -1.0, "The reference field must be finite and positive"),
])
def test_bad_input(b, r, message):
    with pytest.raises(ValueError, match=message):
        calibrate_scalar(b, r)


def test_bad_options():
    b, _, _ = synthetic(7, n=50)
    with pytest.raises(ValueError, match="Method must be 'pso' or 'lm', not 'ga'"):
        calibrate_scalar(b, FIELD, method="ga")
    with pytest.raises(ValueError, match="Kernel must be 'numba' or 'numpy'"):
        calibrate_scalar(b, FIELD, kernel="cuda")
