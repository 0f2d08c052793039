"""Standard particle swarm optimisation (Bratton & Kennedy 2007) on the scalar model's cost.

Two twins of the cost kernel: numba (the one used) and plain numpy (the reference); tests
hold them equal on seeded data. The swarm itself is plain numpy: only the cost of every
particle over every sample is heavy.

Ref: D. Bratton and J. Kennedy, "Defining a Standard for Particle Swarm Optimization",
     IEEE Swarm Intelligence Symposium 2007: constriction coefficient chi = 0.72984 with
     c1 = c2 = 2.05, local ring topology (each particle's neighbourhood is itself and its
     two ring neighbours), velocities clamped to the search range, seeded initialisation
     uniform in the search box.

The swarm's random numbers are drawn before it starts, in the order the loop uses them, so
the numba swarm on the moment surrogate (:func:`pso_moments`, the one ``calibrate_scalar``
runs: its whole loop compiled, each evaluation independent of the number of samples) and the
plain numpy swarm (:func:`pso`, any cost function) given the same seed follow the same path.

``topology="gbest"`` replaces the ring by the global best (every particle is drawn towards
the swarm's best), the other topology of that paper, and the one of pyswarms'
``GlobalBestPSO``: the benchmark compares like with like.
"""

import numba
import numpy as np


__all__ = ["unpack", "cost_numpy", "cost_numba", "cost_moments", "pso", "pso_moments",
           "TOPOLOGIES"]

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


def _cost_loop(params, b, r, out):
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


#: The kernel on one thread (the default: a swarm's 40 particles split over threads gained
#: 1.7x on an idle 2-core machine and lost 3-39x on a loaded one) and on numba's threads.
_cost_kernel = numba.njit(parallel=False, fastmath=False, cache=True)(_cost_loop)
_cost_kernel_threads = numba.njit(parallel=True, fastmath=False, cache=True)(_cost_loop)


def cost_numba(params, b, r, *, threads=False):
    """The numba twin of :func:`cost_numpy`: one thread, or with ``threads`` the particles
    split over numba's threads (``numba.set_num_threads``)."""
    params = np.ascontiguousarray(np.atleast_2d(params), dtype=np.float64)
    out = np.empty(params.shape[0])
    kernel = _cost_kernel_threads if threads else _cost_kernel
    kernel(params, np.ascontiguousarray(b, dtype=np.float64),
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
    lower, upper = np.asarray(lower, float), np.asarray(upper, float)
    span = upper - lower
    x, v, draws = _draws(seed, particles, iterations, lower, upper)
    f = cost(x)
    pbest, pcost = x.copy(), f.copy()
    neighbours = ring_neighbours(particles)
    history = []
    it = 0
    for it in range(1, iterations + 1):
        lbest = social_attractors(pbest, pcost, topology, neighbours)
        r1, r2 = draws[it - 1]
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


def _draws(seed, particles, iterations, lower, upper):
    """The swarm's initial positions and velocities, and every iteration's two random
    factors (iterations, 2, particles, 9), from ``numpy.random.default_rng(seed)``."""
    rng = np.random.default_rng(seed)
    span = upper - lower
    x = lower + rng.random((particles, lower.size)) * span
    v = (rng.random((particles, lower.size)) - 0.5) * span
    return x, v, rng.random((iterations, 2, particles, lower.size))


def _theta_rows(params):
    """The squared model's coefficients on the monomials x^2, y^2, z^2, xy, xz, yz, x, y,
    z, 1, then -1 for r^2, per particle (P, 11) (see ``eiv.theta``)."""
    k11, k12, k13, k22, k23, k33, c1, c2, c3 = np.atleast_2d(params).T
    g1 = k11 * c1
    g2 = k12 * c1 + k22 * c2
    g3 = k13 * c1 + k23 * c2 + k33 * c3
    return np.column_stack([k11 * k11, k12 * k12 + k22 * k22,
                            k13 * k13 + k23 * k23 + k33 * k33, 2 * k11 * k12,
                            2 * k11 * k13, 2 * (k12 * k13 + k22 * k23), -2 * g1, -2 * g2,
                            -2 * g3, c1 * c1 + c2 * c2 + c3 * c3, -np.ones_like(k11)])


def cost_moments(params, s):
    """The algebraic surrogate of every particle from the 11x11 moment matrix ``s``:
    sum over samples of (|K b - c|^2 - r^2)^2, without visiting a sample. params: (P, 9)."""
    v = _theta_rows(params)
    return np.einsum("pi,ij,pj->p", v, s, v)


@numba.njit(cache=True, fastmath=False)
def _moment_cost(x, s, v):
    k11, k12, k13, k22, k23, k33 = x[0], x[1], x[2], x[3], x[4], x[5]
    c1, c2, c3 = x[6], x[7], x[8]
    g1 = k11 * c1
    g2 = k12 * c1 + k22 * c2
    g3 = k13 * c1 + k23 * c2 + k33 * c3
    v[0] = k11 * k11
    v[1] = k12 * k12 + k22 * k22
    v[2] = k13 * k13 + k23 * k23 + k33 * k33
    v[3] = 2 * k11 * k12
    v[4] = 2 * k11 * k13
    v[5] = 2 * (k12 * k13 + k22 * k23)
    v[6] = -2 * g1
    v[7] = -2 * g2
    v[8] = -2 * g3
    v[9] = c1 * c1 + c2 * c2 + c3 * c3
    v[10] = -1.0
    total = 0.0
    for i in range(11):
        row = 0.0
        for j in range(11):
            row += s[i, j] * v[j]
        total += v[i] * row
    return total


@numba.njit(cache=True, fastmath=False)
def _swarm_kernel(s, lower, upper, x, v, draws, gbest, history):
    particles, dims = x.shape
    span = upper - lower
    scratch = np.empty(11)
    pbest = x.copy()
    pcost = np.empty(particles)
    for p in range(particles):
        pcost[p] = _moment_cost(x[p], s, scratch)
    attract = np.empty(dims)
    for it in range(draws.shape[0]):
        best = 0
        for p in range(1, particles):
            if pcost[p] < pcost[best]:
                best = p
        chosen = np.empty(particles, dtype=np.int64)
        for p in range(particles):
            if gbest:
                chosen[p] = best
            else:
                left, right = (p - 1) % particles, (p + 1) % particles
                # The ring's order (left, itself, right): the first of equal costs wins, as
                # numpy's argmin does in ``social_attractors``.
                pick = left
                if pcost[p] < pcost[pick]:
                    pick = p
                if pcost[right] < pcost[pick]:
                    pick = right
                chosen[p] = pick
        for p in range(particles):
            for d in range(dims):
                attract[d] = pbest[chosen[p], d]
            for d in range(dims):
                vel = CHI * (v[p, d] + C1 * draws[it, 0, p, d] * (pbest[p, d] - x[p, d])
                             + C2 * draws[it, 1, p, d] * (attract[d] - x[p, d]))
                if vel > span[d]:
                    vel = span[d]
                elif vel < -span[d]:
                    vel = -span[d]
                pos = x[p, d] + vel
                if pos < lower[d]:
                    pos, vel = lower[d], 0.0
                elif pos > upper[d]:
                    pos, vel = upper[d], 0.0
                x[p, d], v[p, d] = pos, vel
        for p in range(particles):
            f = _moment_cost(x[p], s, scratch)
            if f < pcost[p]:
                pcost[p] = f
                for d in range(dims):
                    pbest[p, d] = x[p, d]
        best = 0
        for p in range(1, particles):
            if pcost[p] < pcost[best]:
                best = p
        history[it] = pcost[best]
    best = 0
    for p in range(1, particles):
        if pcost[p] < pcost[best]:
            best = p
    return pbest[best].copy(), pcost[best]


def pso_moments(s, lower, upper, *, particles=40, iterations=300, seed=0, topology="ring"):
    """:func:`pso` on the moment surrogate :func:`cost_moments`, the whole loop compiled.
    Same random numbers, same updates: the same path as ``pso(lambda x: cost_moments(x, s),
    ...)``. Returns (best parameters, best cost, iterations, history of the best cost)."""
    if topology not in TOPOLOGIES:
        raise ValueError(f"Topology must be one of {', '.join(TOPOLOGIES)}, not {topology!r}")
    if not isinstance(particles, (int, np.integer)) or particles < 3:
        raise ValueError(f"Particles must be an integer of at least 3, not {particles!r}")
    lower, upper = np.asarray(lower, float), np.asarray(upper, float)
    x, v, draws = _draws(seed, particles, iterations, lower, upper)
    history = np.empty(iterations)
    best, cost = _swarm_kernel(np.ascontiguousarray(s, dtype=np.float64), lower, upper, x, v,
                               draws, topology == "gbest", history)
    return best, float(cost), iterations, history
