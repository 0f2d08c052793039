"""Standard particle swarm optimisation (Bratton & Kennedy 2007) on the scalar model's cost.

Two twins of the cost kernel: numba (the one used) and plain numpy (the reference); tests
hold them equal on seeded data. The swarm itself is plain numpy: only the cost of every
particle over every sample is heavy.

Ref: D. Bratton and J. Kennedy, "Defining a Standard for Particle Swarm Optimization",
     IEEE Swarm Intelligence Symposium 2007: constriction coefficient chi = 0.72984 with
     c1 = c2 = 2.05, local ring topology (each particle's neighbourhood is itself and its
     two ring neighbours), velocities clamped to the search range, seeded initialisation
     uniform in the search box.

``topology="gbest"`` replaces the ring by the global best (every particle is drawn towards
the swarm's best), the other topology of that paper, and the one of pyswarms'
``GlobalBestPSO``: the benchmark compares like with like.
"""

import numba
import numpy as np


__all__ = ["unpack", "cost_numpy", "cost_numba", "pso", "TOPOLOGIES"]

#: Parameter vector: K's upper triangle (k11, k12, k13, k22, k23, k33), then c (3).
N_PARAMS = 9
CHI = 0.72984
C1 = C2 = 2.05
#: Neighbourhoods: "ring" (itself and its two neighbours by index, fixed) or "gbest" (the
#: whole swarm).
TOPOLOGIES = ("ring", "gbest")


def unpack(p):
    """(K, c) from a parameter vector."""
    k = np.array([[p[0], p[1], p[2]],
                  [0.0,  p[3], p[4]],
                  [0.0,  0.0,  p[5]]])
    return k, np.asarray(p[6:9], dtype=float)


def cost_numpy(params, b, r):
    """Cost of each particle: sum over samples of (|K b - c| - r)^2. params: (P, 9)."""
    params = np.atleast_2d(params)
    k11, k12, k13, k22, k23, k33, c1, c2, c3 = params.T[:, :, None]
    x, y, z = b[:, 0][None, :], b[:, 1][None, :], b[:, 2][None, :]
    u1 = k11 * x + k12 * y + k13 * z - c1
    u2 = k22 * y + k23 * z - c2
    u3 = k33 * z - c3
    e = np.sqrt(u1 * u1 + u2 * u2 + u3 * u3) - r[None, :]
    return np.sum(e * e, axis=1)


@numba.njit(parallel=True, fastmath=False, cache=True)
def _cost_kernel(params, b, r, out):
    for j in numba.prange(params.shape[0]):
        k11, k12, k13 = params[j, 0], params[j, 1], params[j, 2]
        k22, k23, k33 = params[j, 3], params[j, 4], params[j, 5]
        c1, c2, c3 = params[j, 6], params[j, 7], params[j, 8]
        total = 0.0
        for i in range(b.shape[0]):
            x, y, z = b[i, 0], b[i, 1], b[i, 2]
            u1 = k11 * x + k12 * y + k13 * z - c1
            u2 = k22 * y + k23 * z - c2
            u3 = k33 * z - c3
            e = np.sqrt(u1 * u1 + u2 * u2 + u3 * u3) - r[i]
            total += e * e
        out[j] = total


def cost_numba(params, b, r):
    """The numba twin of :func:`cost_numpy`."""
    params = np.ascontiguousarray(np.atleast_2d(params), dtype=np.float64)
    out = np.empty(params.shape[0])
    _cost_kernel(params, np.ascontiguousarray(b, dtype=np.float64),
                 np.ascontiguousarray(r, dtype=np.float64), out)
    return out


def ring_neighbours(particles):
    """(P, 3) indices of each particle's ring neighbourhood: i - 1, i, i + 1 (wrapping)."""
    ring = np.arange(particles)
    return np.stack([np.roll(ring, 1), ring, np.roll(ring, -1)], axis=1)


def social_attractors(pbest, pcost, topology, neighbours=None):
    """The position each particle is drawn towards besides its own best: the best personal
    best of its ring neighbourhood, or the swarm's best for "gbest"."""
    if topology == "gbest":
        return np.broadcast_to(pbest[np.argmin(pcost)], pbest.shape)
    if neighbours is None:
        neighbours = ring_neighbours(len(pcost))
    rows = np.arange(len(pcost))
    return pbest[neighbours[rows, np.argmin(pcost[neighbours], axis=1)]]


def pso(cost, lower, upper, *, particles=40, iterations=300, seed=0, threshold=None,
        topology="ring"):
    """Minimise ``cost(params (P, 9)) -> (P,)`` in the box [lower, upper].

    ``topology`` is "ring" (Bratton and Kennedy's standard: each particle follows the best of
    itself and its two index neighbours) or "gbest" (every particle follows the swarm's
    best).

    Returns (best parameters, best cost, iterations run, history of the best cost)."""
    if topology not in TOPOLOGIES:
        raise ValueError(f"Topology must be one of {', '.join(TOPOLOGIES)}, not {topology!r}")
    if not isinstance(particles, (int, np.integer)) or particles < 3:
        raise ValueError(f"Particles must be an integer of at least 3, not {particles!r}")
    rng = np.random.default_rng(seed)
    lower, upper = np.asarray(lower, float), np.asarray(upper, float)
    span = upper - lower
    x = lower + rng.random((particles, lower.size)) * span
    v = (rng.random((particles, lower.size)) - 0.5) * span
    f = cost(x)
    pbest, pcost = x.copy(), f.copy()
    neighbours = ring_neighbours(particles)
    history = []
    it = 0
    for it in range(1, iterations + 1):
        lbest = social_attractors(pbest, pcost, topology, neighbours)
        r1, r2 = rng.random(x.shape), rng.random(x.shape)
        v = CHI * (v + C1 * r1 * (pbest - x) + C2 * r2 * (lbest - x))
        np.clip(v, -span, span, out=v)
        x = x + v
        # Particles that leave the box are held at its wall with their velocity zeroed.
        outside = (x < lower) | (x > upper)
        x = np.clip(x, lower, upper)
        v[outside] = 0.0
        f = cost(x)
        better = f < pcost
        pbest[better], pcost[better] = x[better], f[better]
        best = np.argmin(pcost)
        history.append(pcost[best])
        if threshold is not None and pcost[best] <= threshold:
            break
    best = np.argmin(pcost)
    return pbest[best], pcost[best], it, np.array(history)
