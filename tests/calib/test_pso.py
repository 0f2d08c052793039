"""The standard PSO of calib/_pso.py: its cost twins, and its two topologies."""

import numpy as np
import pytest

from maglog.calib import _pso


FIELD = 50_000.0


def flight(seed, n=400):
    """Seeded samples of a field of magnitude FIELD seen through a known K and c."""
    rng = np.random.default_rng(seed)
    u = rng.normal(size=(n, 3))
    u /= np.linalg.norm(u, axis=1)[:, None]
    k = np.array([[1.02, 0.01, -0.02], [0.0, 0.97, 0.015], [0.0, 0.0, 1.05]])
    c = np.array([300.0, -150.0, 80.0])
    b = np.linalg.solve(k, (FIELD * u + c).T).T
    return b, np.full(n, FIELD), np.r_[k[np.triu_indices(3)], c]


def box(truth):
    lower = truth - np.r_[np.full(6, 0.2), np.full(3, 2000.0)]
    upper = truth + np.r_[np.full(6, 0.2), np.full(3, 2000.0)]
    return lower, upper


def sphere(x):
    """A simple function with its minimum 0 at (1, 2, ..., 9)."""
    return np.sum((np.atleast_2d(x) - np.arange(1, 10)) ** 2, axis=1)


def test_cost_twins_agree():
    b, r, truth = flight(1)
    params = truth + np.random.default_rng(2).normal(scale=[0.05] * 6 + [100.0] * 3,
                                                       size=(24, 9))
    np.testing.assert_allclose(_pso.cost_numba(params, b, r), _pso.cost_numpy(params, b, r),
                               rtol=1e-12)
    np.testing.assert_allclose(_pso.cost_numba(params, b, r, threads=True),
                               _pso.cost_numpy(params, b, r), rtol=1e-12)


@pytest.mark.parametrize("topology", _pso.TOPOLOGIES)
def test_swarms_on_the_twins_agree(topology):
    b, r, truth = flight(3)
    lower, upper = box(truth)
    runs = [_pso.pso(lambda x, cost=cost: cost(x, b, r), lower, upper, particles=20,
                     iterations=40, seed=5, topology=topology)
            for cost in (_pso.cost_numba, _pso.cost_numpy)]
    np.testing.assert_allclose(runs[0][0], runs[1][0], rtol=1e-9)
    np.testing.assert_allclose(runs[0][3], runs[1][3], rtol=1e-9)


@pytest.mark.parametrize("topology", _pso.TOPOLOGIES)
def test_both_topologies_find_the_optimum(topology):
    lower, upper = np.full(9, -10.0), np.full(9, 10.0)
    best, cost, iterations, history = _pso.pso(sphere, lower, upper, particles=30,
                                               iterations=300, seed=1, topology=topology)
    np.testing.assert_allclose(best, np.arange(1, 10), atol=1e-3)
    assert cost < 1e-6
    assert iterations == 300 and len(history) == 300
    assert np.all(np.diff(history) <= 0)                # the best never gets worse


@pytest.mark.parametrize("topology", _pso.TOPOLOGIES)
def test_both_topologies_find_the_calibration(topology):
    b, r, truth = flight(4)
    lower, upper = box(truth)
    best, cost, _, _ = _pso.pso(lambda x: _pso.cost_numba(x, b, r), lower, upper,
                                particles=40, iterations=300, seed=2, topology=topology)
    assert cost < 1e-3 * _pso.cost_numpy(truth + (upper - lower) / 20, b, r)[0]
    np.testing.assert_allclose(best[6:], truth[6:], atol=5.0)


def test_gbest_attracts_every_particle_to_the_swarms_best():
    rng = np.random.default_rng(6)
    pbest, pcost = rng.normal(size=(12, 9)), rng.random(12)
    attractors = _pso.social_attractors(pbest, pcost, "gbest")
    assert np.all(attractors == pbest[np.argmin(pcost)])


def test_ring_attracts_each_particle_to_its_neighbourhoods_best():
    pbest = np.arange(6 * 9, dtype=float).reshape(6, 9)
    pcost = np.array([5.0, 1.0, 4.0, 3.0, 6.0, 2.0])
    attractors = _pso.social_attractors(pbest, pcost, "ring")
    # Neighbourhoods (i-1, i, i+1 around the ring) and their best: 0 -> {5, 0, 1} -> 1,
    # 1 -> {0, 1, 2} -> 1, 2 -> {1, 2, 3} -> 1, 3 -> {2, 3, 4} -> 3, 4 -> {3, 4, 5} -> 5,
    # 5 -> {4, 5, 0} -> 5.
    assert [int(a[0] // 9) for a in attractors] == [1, 1, 1, 3, 5, 5]


def test_the_topologies_differ_in_a_run():
    lower, upper = np.full(9, -10.0), np.full(9, 10.0)
    ring = _pso.pso(sphere, lower, upper, particles=20, iterations=10, seed=3,
                    topology="ring")
    gbest = _pso.pso(sphere, lower, upper, particles=20, iterations=10, seed=3,
                     topology="gbest")
    assert not np.allclose(ring[3], gbest[3])


def test_ring_is_the_default():
    lower, upper = np.full(9, -10.0), np.full(9, 10.0)
    default = _pso.pso(sphere, lower, upper, particles=20, iterations=10, seed=3)
    ring = _pso.pso(sphere, lower, upper, particles=20, iterations=10, seed=3,
                    topology="ring")
    np.testing.assert_array_equal(default[3], ring[3])


def test_unknown_topology_is_refused():
    with pytest.raises(ValueError, match="Topology must be one of ring, gbest, not 'star'"):
        _pso.pso(sphere, np.zeros(9), np.ones(9), topology="star")
