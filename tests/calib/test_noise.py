"""Kalman filter and Allan deviation; allantools is the reference for the deviation."""

import allantools
import numpy as np
import pytest

from maglog.calib.noise import allan_deviation, kalman_filter


def test_allan_deviation_matches_allantools():
    rng = np.random.default_rng(1)
    y = rng.normal(scale=3.0, size=20_000) + np.cumsum(rng.normal(scale=0.01, size=20_000))
    rate = 50.0
    ours = allan_deviation(y, rate)
    taus, dev, _, _ = allantools.oadev(y, rate=rate, data_type="freq", taus=ours.taus)
    common = np.isin(np.round(ours.taus, 9), np.round(taus, 9))
    np.testing.assert_allclose(ours.deviation[common], dev, rtol=1e-9)


def test_white_noise_slope_and_quantisation():
    rng = np.random.default_rng(2)
    sigma, rate = 2.0, 100.0
    result = allan_deviation(rng.normal(scale=sigma, size=50_000), rate)
    # White noise: sigma(tau) = sigma * sqrt(tau0 / tau), slope -1/2.
    slope = np.polyfit(np.log(result.taus[:20]), np.log(result.deviation[:20]), 1)[0]
    assert slope == pytest.approx(-0.5, abs=0.05)
    assert result.deviation[0] == pytest.approx(sigma, rel=0.03)


def test_bias_instability_from_the_flat_part():
    rng = np.random.default_rng(3)
    n, rate = 100_000, 10.0
    # White noise plus a slow random walk: the deviation has a minimum.
    y = rng.normal(scale=1.0, size=n) + np.cumsum(rng.normal(scale=0.002, size=n))
    result = allan_deviation(y, rate)
    assert result.deviation.min() == pytest.approx(result.bias_instability * 0.664, rel=1e-2)
    assert result.taus[0] < result.tau_min < result.taus[-1]


def test_kalman_filter_reduces_noise_and_tracks():
    rng = np.random.default_rng(4)
    truth = 48_000 + np.cumsum(rng.normal(scale=0.5, size=5000))
    z = np.column_stack([truth, truth + 10]) + rng.normal(scale=20.0, size=(5000, 2))
    states, variances = kalman_filter(z, q=0.25, r=400.0)
    error_raw = np.std(z[:, 0] - truth)
    error_filtered = np.std(states[100:, 0] - truth[100:])
    assert error_filtered < error_raw / 3
    assert np.all(variances[-1] < 400.0)
    single, _ = kalman_filter(z[:, 1], q=0.25, r=400.0)
    np.testing.assert_allclose(single, states[:, 1])


def test_kalman_filter_scalar_recursion_by_hand():
    z = np.array([1.0, 2.0, 3.0])
    states, variances = kalman_filter(z, q=1.0, r=1.0, x0=0.0, p0=1.0)
    # p: 2 -> gain 2/3 -> x = 2/3, p = 2/3; p 5/3 -> gain 5/8 -> x = 2/3 + 5/8 (4/3) ...
    assert states[0] == pytest.approx(2 / 3)
    assert variances[0] == pytest.approx(2 / 3)
    assert states[1] == pytest.approx(2 / 3 + 5 / 8 * (2 - 2 / 3))


@pytest.mark.parametrize("call,message", [
    (lambda: kalman_filter(np.zeros((0, 3)), q=1, r=1), "non-empty"),
    (lambda: kalman_filter(np.zeros(3), q=-1, r=1), "Noise variances must be"),
    (lambda: allan_deviation(np.zeros(3), 10), "at least 4 samples"),
    (lambda: allan_deviation(np.array([0, 1, np.nan, 2, 3]), 10), "finite"),
    (lambda: allan_deviation(np.zeros(10), 0), "Sample rate must be positive"),
])
def test_bad_input(call, message):
    with pytest.raises(ValueError, match=message):
        call()
