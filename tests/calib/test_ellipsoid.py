"""Ellipsoid fits against known soft and hard iron, and the gate on what they determine."""

import numpy as np
import pytest

from maglog.calib.ellipsoid import fit_ellipsoid, octant_coverage

FIELD = 50_000.0


def samples(seed, n=2000, noise=5.0, hemisphere=False):
    rng = np.random.default_rng(seed)
    v = rng.normal(size=(n, 3))
    if hemisphere:
        v[:, 2] = np.abs(v[:, 2])
    v /= np.linalg.norm(v, axis=1)[:, None]
    soft = np.array([[1.10, 0.05, -0.02], [0.05, 0.92, 0.03], [-0.02, 0.03, 1.04]])
    hard = np.array([400.0, -250.0, 120.0])
    return FIELD * v @ soft.T + hard + rng.normal(scale=noise, size=(n, 3)), soft, hard


@pytest.mark.parametrize("method", ["algebraic", "constrained"])
def test_recovers_hard_and_soft_iron(method):
    b, soft, hard = samples(1)
    result = fit_ellipsoid(b, FIELD, method=method)
    assert result.success and result.coverage.complete
    np.testing.assert_allclose(result.center, hard, atol=5.0)
    # W undoes the soft iron up to a rotation: W soft is orthogonal.
    q = result.W @ soft
    np.testing.assert_allclose(q @ q.T, np.eye(3), atol=3e-4)
    assert result.rms < 10


def test_paper_gate_refuses_until_every_octant_is_filled():
    b, _, hard = samples(2)
    early = fit_ellipsoid(b[:30], FIELD, min_per_octant=10, gate="paper")   # too few yet
    assert not early.success and early.coverage.filled < 8
    assert "octants" in early.message
    later = fit_ellipsoid(b, FIELD, min_per_octant=10, gate="paper")
    assert later.success and later.coverage.filled == 8
    assert later.coverage.about == "running centroid"


def test_the_gate_accepts_what_the_samples_determine_whatever_the_octants():
    # A hemisphere of directions: four octants about the fitted centre, yet every parameter
    # is pinned down well within one sample's noise. The old gate on octants about the
    # centre refused it; the gate on what the fit determines accepts it.
    b, soft, hard = samples(5, n=3000, hemisphere=True)
    fit = fit_ellipsoid(b, FIELD)
    assert fit.success, fit.message
    assert fit.coverage.filled == 4 and fit.coverage.about == "fitted centre"
    assert fit.determination.complete and fit.message.startswith("fitted; every parameter")
    np.testing.assert_allclose(fit.center, hard, atol=10.0)
    # The canonical form is the scalar model's, and within its 1-sigma of the truth.
    q, r = np.linalg.qr(np.linalg.inv(soft))
    k = r * np.sign(np.diag(r))[:, None]
    truth = np.concatenate([k[np.triu_indices(3)], k @ hard])
    assert np.all(np.abs(fit.x - truth) < 5 * fit.uncertainties)
    with pytest.raises(ValueError, match="Gate must be one of determined, paper or False, "
                                         "not 'x'"):
        fit_ellipsoid(b, FIELD, gate="x")


@pytest.mark.parametrize("coverage, missing", [("uav", {"k33", "c3"}), ("planar", None)])
def test_the_gate_refuses_what_the_samples_leave_undetermined(coverage, missing):
    # The same flights the scalar fit calls undetermined (calib.coverage): a minute of a
    # UAV's +-30 deg leaves k33 and c3 at about twice the noise; a near-level flight leaves
    # most parameters free. They fit the samples (the RMS is the noise) and are refused,
    # naming what the samples leave free; the fit is kept for inspection.
    from maglog.sim.stimulus.scenario import make_flight
    flight = make_flight(coverage=coverage, seconds=60, rate=20, seed=3)
    fit = fit_ellipsoid(flight.b_meas, float(np.median(flight.total)))
    assert fit.rms < 1.1 * flight.errors.noise
    assert not fit.success and fit.message.startswith("undetermined: the samples do not "
                                                      "determine")
    found = set(fit.determination.undetermined)
    assert found == missing if missing else {"k33", "c3"} < found, fit.message
    assert np.all(np.isfinite(fit.W)) and np.all(np.isfinite(fit.center))
    # A bound as loose as the user likes accepts it; ungated, it is a fit like any other.
    assert fit_ellipsoid(flight.b_meas, float(np.median(flight.total)),
                         determined_nt=1e4).success
    assert fit_ellipsoid(flight.b_meas, float(np.median(flight.total)), gate=False).success
    with pytest.raises(ValueError, match="bound on a determined parameter"):
        fit_ellipsoid(flight.b_meas, 5e4, determined_nt=-1)


def test_coverage_counts_every_octant():
    b, _, _ = samples(3, n=4000)
    coverage = octant_coverage(b, min_per_octant=50)
    assert coverage.complete and coverage.counts.sum() == 4000
    assert coverage.report()["octants_filled"] == 8


def test_bad_input():
    with pytest.raises(ValueError, match="At least 10 samples are needed for an ellipsoid"):
        fit_ellipsoid(np.zeros((5, 3)), FIELD)
    with pytest.raises(ValueError, match="Method must be"):
        fit_ellipsoid(samples(4)[0], FIELD, method="magic")
    with pytest.raises(ValueError, match="The field must be positive"):
        fit_ellipsoid(samples(4)[0], 0.0)


def test_samples_that_determine_no_ellipsoid_are_refused_before_the_gate():
    b, _, _ = samples(6)
    # A stuck z axis equal to the running centroid counts in every octant (>=): it passed
    # the gate and "fitted". Now it is named.
    stuck = b.copy()
    stuck[:, 2] = 99999.9
    with pytest.raises(ValueError, match=r"Axis z does not change .*about 99999.9 nT"):
        fit_ellipsoid(stuck, FIELD)
    with pytest.raises(ValueError, match="Only 2 distinct vectors"):
        fit_ellipsoid(np.vstack([b[:2]] * 20), FIELD)
    # Scaled by 1e300 the normal equations overflowed (LinAlgError).
    with pytest.raises(ValueError, match="Samples must be below 1e\\+08 nT"):
        fit_ellipsoid(b * 1e300, FIELD)
    with pytest.raises(ValueError, match="Axis x does not change"):
        fit_ellipsoid(np.zeros((50, 3)), FIELD)


def hyperboloid(n=3000, seed=5):
    """Points on x^2 + y^2 - z^2 / 4 = 1 (scaled): every octant, but no ellipsoid."""
    rng = np.random.default_rng(seed)
    angle = rng.uniform(0, 2 * np.pi, n)
    height = rng.uniform(-1, 1, n)
    radius = np.sqrt(1 + height ** 2 / 4)
    return FIELD * np.column_stack([radius * np.cos(angle), radius * np.sin(angle), height])


def test_no_ellipsoid_from_the_algebraic_fit_but_always_from_the_constrained_one():
    b = hyperboloid()
    algebraic = fit_ellipsoid(b, FIELD)
    assert not algebraic.success and "not an ellipsoid" in algebraic.message
    constrained = fit_ellipsoid(b, FIELD, method="constrained")
    assert constrained.success
    assert np.all(np.linalg.eigvalsh(constrained.W) > 0)


@pytest.mark.parametrize("method", ["algebraic", "constrained"])
def test_calibration_matrix_sign_is_fixed(method):
    """W is the positive-definite root whichever overall sign the quadric came out with:
    the same samples reflected through the centre give the same W."""
    b, soft, hard = samples(6)
    result = fit_ellipsoid(b, FIELD, method=method)
    mirrored = fit_ellipsoid(2 * hard - b, FIELD, method=method)
    assert np.all(np.linalg.eigvalsh(result.W) > 0) and np.linalg.det(result.W) > 0
    np.testing.assert_allclose(mirrored.W, result.W, rtol=1e-6, atol=1e-9)
    # And the calibrated field keeps the sensor's sense: no axis reversed.
    calibrated = (b - result.center) @ result.W.T
    true = (b - hard) @ np.linalg.inv(soft).T
    cos = np.sum(calibrated * true, axis=1) / (np.linalg.norm(calibrated, axis=1)
                                                * np.linalg.norm(true, axis=1))
    assert np.min(cos) > 0.99
