"""The errors-in-variables fit: its moments against brute force, its noise correction
against Monte Carlo, its bias against the paper's objective's, its robust loss and its
uncertainties."""

import numpy as np
import pytest

from maglog.calib import _pso, eiv
from maglog.calib.scalar import PARAMETERS, calibrate_scalar
from maglog.sim.stimulus.errors import preset
from maglog.sim.stimulus.scenario import make_flight


def _monomials(b, r):
    x, y, z = b.T
    return np.column_stack([x * x, y * y, z * z, x * y, x * z, y * z, x, y, z,
                            np.ones_like(x), r * r])


def _truth(errors):
    k, c = errors.truth()
    return np.r_[k[np.triu_indices(3)], c]


@pytest.fixture(scope="module")
def samples():
    rng = np.random.default_rng(1)
    b = rng.normal(size=(300, 3)) * 30_000 + [500, -300, 200]
    r = 48_000 + rng.normal(size=300) * 40
    return b, r


def test_moment_matrix_is_the_sum_of_outer_products(samples):
    b, r = samples
    keep = np.arange(len(b)) % 7 != 0
    scale = 48_000.0
    shift = np.array([100.0, -50.0, 25.0])
    m = eiv.moments(b, r, keep, shift=shift, scale=scale)
    z = _monomials((b[keep] - shift) / scale, r[keep] / scale)
    np.testing.assert_allclose(m.matrix(), z.T @ z, rtol=1e-10)
    assert m.count == keep.sum()


def test_objective_and_jacobian_match_their_definitions(samples):
    b, r = samples
    p = np.array([1.02, 0.01, -0.02, 0.97, 0.015, 1.01, 300.0, -150.0, 80.0])
    s = eiv.moments(b, r, shift=np.zeros(3), scale=1.0).matrix()
    k, c = _pso.unpack(p)
    direct = np.sum((np.sum((b @ k.T - c) ** 2, axis=1) - r * r) ** 2)
    assert eiv.objective(p, s) == pytest.approx(direct, rel=1e-9)
    assert _pso.cost_moments(p[None], s)[0] == pytest.approx(direct, rel=1e-9)
    step = 1e-4 * np.maximum(np.abs(p), 1)
    numeric = np.column_stack([(eiv.theta(p + h) - eiv.theta(p - h)) / (2 * h[i])
                               for i, h in enumerate(np.diag(step))])
    np.testing.assert_allclose(eiv.theta_jacobian(p), numeric, rtol=1e-7, atol=1e-9)


def test_noise_correction_is_unbiased():
    # The corrected moments of noisy samples average to the clean samples' moments.
    rng = np.random.default_rng(2)
    clean = rng.normal(size=(50, 3)) * 0.8
    r_clean = 1 + 0.1 * rng.normal(size=50)
    sigma_m, sigma_r = 0.2, 0.05
    target = eiv.moments(clean, r_clean, scale=1.0).matrix()
    draws = np.array([
        eiv.moments(clean + rng.normal(scale=sigma_m, size=clean.shape),
                    r_clean + rng.normal(scale=sigma_r, size=50), scale=1.0
                    ).matrix(sigma_m, sigma_r) for _ in range(3000)])
    standard_error = draws.std(axis=0) / np.sqrt(len(draws))
    assert np.all(np.abs(draws.mean(axis=0) - target) < 5 * standard_error + 1e-12)
    # The uncorrected ones are off by far more (the x^4 terms by 6 s^2 x^2 + 3 s^4 ...).
    plain = np.array([
        eiv.moments(clean + rng.normal(scale=sigma_m, size=clean.shape), r_clean,
                    scale=1.0).matrix() for _ in range(300)])
    plain_error = plain.std(axis=0) / np.sqrt(len(plain)) + 1e-12
    assert np.max(np.abs(plain.mean(axis=0) - target) / plain_error) > 8


@pytest.mark.parametrize("topology", ["ring", "gbest"])
def test_compiled_swarm_follows_the_numpy_swarm(samples, topology):
    b, r = samples
    s = eiv.moments(b, r, shift=np.zeros(3), scale=48_000.0).matrix()
    lower = np.array([0.5, -0.5, -0.5, 0.5, -0.5, 0.5, -0.5, -0.5, -0.5]) * 1.6
    upper = np.array([2.0, 0.5, 0.5, 2.0, 0.5, 2.0, 0.5, 0.5, 0.5]) * 1.6
    ours = _pso.pso_moments(s, lower, upper, seed=3, iterations=80, topology=topology)
    plain = _pso.pso(lambda x: _pso.cost_moments(x, s), lower, upper, seed=3, iterations=80,
                     topology=topology)
    np.testing.assert_allclose(ours[0], plain[0], rtol=1e-9, atol=1e-12)
    np.testing.assert_allclose(ours[3], plain[3], rtol=1e-9)


@pytest.fixture(scope="module")
def long_uav_table1():
    errors = preset("paper_a", noise=100.0)
    flight = make_flight(coverage="uav", seconds=800, rate=20, errors=errors, seed=5)
    return flight, errors


def test_paper_objective_is_biased_where_eiv_is_not(long_uav_table1):
    # 16,000 samples of paper A's Table 1 on a UAV pattern at 100 nT: the paper's
    # objective ends many standard deviations off on the vertical axis; the
    # errors-in-variables fit does not.
    flight, errors = long_uav_table1
    truth = _truth(errors)
    ours = calibrate_scalar(flight.b_meas, flight.total)
    paper = calibrate_scalar(flight.b_meas, flight.total, objective="paper")
    z_ours = (ours.x - truth) / ours.uncertainties
    z_paper = (paper.x - truth) / paper.uncertainties
    assert np.max(np.abs(z_ours)) < 3.5, z_ours
    assert abs(z_paper[PARAMETERS.index("c3")]) > 6, z_paper
    assert abs(z_paper[PARAMETERS.index("k33")]) > 6, z_paper
    # The noise it corrected for is the noise there was.
    assert ours.noise["magnetometer_nT"] == pytest.approx(100.0, rel=0.03)


def test_uncorrected_algebraic_fit_is_biased_too(long_uav_table1):
    # The correction, not the algebraic form, removes the bias.
    flight, errors = long_uav_table1
    truth = _truth(errors)
    fit = eiv.fit_eiv(flight.b_meas, flight.total, correct=False)
    sd = np.sqrt(np.diag(fit.covariance))
    assert abs((fit.x - truth)[PARAMETERS.index("c3")] / sd[PARAMETERS.index("c3")]) > 6


def _held_out_ratio(result, flight, errors, half):
    truth = _truth(errors)
    e, _ = eiv.residuals(result.x, flight.b_meas[half:], flight.total[half:])
    e0, _ = eiv.residuals(truth, flight.b_meas[half:], flight.total[half:])
    return float(np.sqrt(np.mean(e ** 2) / np.mean(e0 ** 2)))


@pytest.mark.parametrize("fault", ["zeroed_axis", "spike", "reference_bit_flip"])
def test_one_percent_of_gross_errors_does_not_move_the_fit(fault):
    errors = preset("paper_a", noise=20.0)
    flight = make_flight(coverage="uav", seconds=200, rate=20, errors=errors, seed=8)
    half = len(flight.t) // 2
    clean = calibrate_scalar(flight.b_meas[:half], flight.total[:half])
    rng = np.random.default_rng(4)
    bad = rng.choice(half, size=half // 100, replace=False)
    b, r = flight.b_meas[:half].copy(), flight.total[:half].copy()
    if fault == "zeroed_axis":
        b[bad, rng.integers(0, 3, size=bad.size)] = 0.0
    elif fault == "spike":
        b[bad] += rng.normal(scale=3000.0, size=(bad.size, 3))
    else:
        r[bad] -= 40_000.0                       # 48395 -> 08395
    fit = calibrate_scalar(b, r)
    # Every bad sample the clean fit puts 10 sigma off is rejected (a zeroed axis that read
    # nearly zero anyway is harmless and may stay), and hardly a good one.
    e, _ = eiv.residuals(clean.x, b[bad], r[bad])
    harmful = bad[np.abs(e) > 10 * 20.0]
    assert harmful.size >= bad.size // 2 and not fit.kept[harmful].any()
    assert fit.rejected <= bad.size + 3
    assert (_held_out_ratio(fit, flight, errors, half)
            <= 1.01 * _held_out_ratio(clean, flight, errors, half))
    # Without the robust loss the same errors wreck it.
    plain = calibrate_scalar(b, r, robust=False)
    assert (_held_out_ratio(plain, flight, errors, half)
            > 1.05 * _held_out_ratio(clean, flight, errors, half))


@pytest.mark.parametrize("coverage", ["full", "uav"])
def test_uncertainties_cover_the_truth(coverage):
    zs = []
    errors = preset("paper_a", noise=20.0)
    for seed in range(12):
        flight = make_flight(coverage=coverage, seconds=60, rate=20, errors=errors,
                             seed=100 + seed)
        fit = calibrate_scalar(flight.b_meas, flight.total)
        zs.append((fit.x - _truth(errors)) / fit.uncertainties)
    rms = np.sqrt(np.mean(np.square(zs), axis=0))
    # 12 seeds: an RMS of one reads 0.6-1.4 by chance; too small uncertainties read 3+.
    assert np.all(rms < 1.6) and np.all(rms > 0.4), rms


def test_screened_samples_are_not_fitted():
    flight = make_flight(coverage="full", seconds=30, rate=20, seed=2)
    keep = np.ones(len(flight.t), bool)
    keep[::10] = False
    b = flight.b_meas.copy()
    b[::10] *= 3.0                                 # what a screening found implausible
    fit = calibrate_scalar(b, flight.total, keep=keep, robust=False)
    assert fit.success and not fit.kept[::10].any() and fit.kept.sum() == keep.sum()
    assert fit.rms < 10
