"""Ellipsoid fits against known soft and hard iron, and the coverage gate."""

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


def test_gate_refuses_until_every_octant_is_filled():
    b, _, hard = samples(2)
    early = fit_ellipsoid(b[:30], FIELD, min_per_octant=10)   # too few samples yet
    assert not early.success and early.coverage.filled < 8
    assert "octants" in early.message
    later = fit_ellipsoid(b, FIELD, min_per_octant=10)
    assert later.success and later.coverage.filled == 8


def test_coverage_counts_every_octant():
    b, _, _ = samples(3, n=4000)
    coverage = octant_coverage(b, min_per_octant=50)
    assert coverage.complete and coverage.counts.sum() == 4000
    assert coverage.report()["octants_filled"] == 8


def test_bad_input():
    with pytest.raises(ValueError, match="N >= 10"):
        fit_ellipsoid(np.zeros((5, 3)), FIELD)
    with pytest.raises(ValueError, match="Method must be"):
        fit_ellipsoid(samples(4)[0], FIELD, method="magic")
