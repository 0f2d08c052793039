"""The calibration on data it has not seen: the grid of the issue (three coverages, two error
models including paper A's Table 1, three noise levels, many seeds), fitted on the first
half of each flight and scored on the second half against the true field.

The full grid is in the slow suite; the default suite runs a short version of it."""

import numpy as np
import pytest

from maglog.calib import eiv
from maglog.calib.scalar import PARAMETERS, calibrate_scalar
from maglog.sim.stimulus.errors import preset
from maglog.sim.stimulus.scenario import make_flight

COVERAGES = ("full", "uav", "planar")
MODELS = ("default", "paper_a")
NOISES = (5.0, 20.0, 100.0)
#: Held-out ratio limits (median over seeds; a single seed's excess scatters with 9 / N).
LIMITS = {"full": 1.01, "uav": 1.01, "planar": 1.05}
SINGLE_SEED_LIMIT = {"full": 1.025, "uav": 1.025, "planar": 1.06}


def _truth(errors):
    k, c = errors.truth()
    return np.r_[k[np.triu_indices(3)], c]


def run_case(coverage, model, noise, seed, seconds=100.0):
    """One flight: fit the first half (cesium-like reference, 0.05 nT of noise), score the
    second against the true field. Returns (held-out ratio, z-scores (NaN where held),
    the result)."""
    errors = preset(model, noise=noise)
    flight = make_flight(coverage=coverage, seconds=seconds, rate=20, errors=errors,
                         seed=5000 + seed)
    half = len(flight.t) // 2
    reference = flight.total + np.random.default_rng(seed).normal(scale=0.05,
                                                                  size=len(flight.t))
    result = calibrate_scalar(flight.b_meas[:half], reference[:half])
    truth = _truth(errors)
    e, _ = eiv.residuals(result.x, flight.b_meas[half:], flight.total[half:])
    floor, _ = eiv.residuals(truth, flight.b_meas[half:], flight.total[half:])
    ratio = float(np.sqrt(np.mean(e ** 2) / np.mean(floor ** 2)))
    z = (result.x - truth) / result.uncertainties
    z[result.held] = np.nan
    return ratio, z, result


def check_case(coverage, model, noise, seeds):
    ratios, zs = [], []
    for seed in range(seeds):
        ratio, z, result = run_case(coverage, model, noise, seed)
        k = result.K
        # No collapse (K -> 0, |c| = r) and no reflection (a reversed axis).
        assert np.all(np.diag(k) > 0.5) and np.linalg.det(k) > 0, (coverage, seed)
        assert result.success, (coverage, model, noise, seed, result.message)
        ratios.append(ratio)
        zs.append(z)
    ratios = np.array(ratios)
    assert np.median(ratios) <= LIMITS[coverage], (coverage, model, noise, ratios)
    assert np.max(ratios) <= SINGLE_SEED_LIMIT[coverage], (coverage, model, noise, ratios)
    return np.array(zs)


def z_rms(zs):
    """RMS of the z-scores per parameter over the seeds (NaN where always held), and over
    every parameter and seed that was not held."""
    with np.errstate(invalid="ignore"):
        counts = np.sum(np.isfinite(zs), axis=0)
        per = np.sqrt(np.nansum(zs ** 2, axis=0) / np.maximum(counts, 1))
    per[counts == 0] = np.nan
    pooled = float(np.sqrt(np.nanmean(zs ** 2)))
    return per, pooled, counts


def check_z(coverage, zs, limit):
    per, pooled, counts = z_rms(zs)
    if coverage == "planar":
        # A level flight leaves most parameters held or weakly determined, each reported
        # in only some seeds: judged pooled.
        assert pooled <= limit, (coverage, pooled, per, counts)
    else:
        assert np.all(counts == len(zs))        # every parameter reported, every seed
        assert np.all(per <= limit), (coverage, dict(zip(PARAMETERS, per.round(2))))


@pytest.mark.parametrize("coverage", COVERAGES)
def test_short_grid(coverage):
    # The default suite's share: Table 1 at every noise level, 8 seeds.
    zs = np.concatenate([check_case(coverage, "paper_a", noise, 8) for noise in NOISES])
    check_z(coverage, zs, 1.5)


@pytest.mark.slow
@pytest.mark.parametrize("model", MODELS)
@pytest.mark.parametrize("noise", NOISES)
@pytest.mark.parametrize("coverage", COVERAGES)
def test_grid(coverage, model, noise):
    zs = check_case(coverage, model, noise, 40)
    check_z(coverage, zs, 1.3)


def test_table1_recovered_within_the_reported_uncertainties():
    # Paper A's Table 1 as the truth, a tumbling calibration at 20 nT: every parameter
    # determined, and within three of its reported standard deviations.
    errors = preset("paper_a", noise=20.0)
    flight = make_flight(coverage="full", seconds=120, rate=20, errors=errors, seed=11)
    result = calibrate_scalar(flight.b_meas, flight.total)
    z = (result.x - _truth(errors)) / result.uncertainties
    assert result.determined.all() and not result.held.any()
    assert np.all(np.abs(z) < 3.0), dict(zip(PARAMETERS, z.round(2)))
    # In the paper's forward form (P = K^-1, offset P c at the sensor), the rotation the
    # scalar model cannot see taken out.
    k_true, c_true, q = errors.truth_with_rotation()
    np.testing.assert_allclose(result.P, np.linalg.inv(k_true), atol=5 * np.max(
        result.uncertainties[:6]))
