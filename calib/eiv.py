"""The scalar model fitted with errors in variables: unbiased when the magnetometer is noisy.

The paper's objective, ``sum (|K b_i - c| - r_i)^2``, treats the samples ``b_i`` as exact and
only the reference ``r_i`` as noisy. The magnetometer's own noise then biases the fit by a
term of order sigma^2, and where the attitude coverage determines a combination poorly (a
UAV's tilt of +-30 deg hardly moves the vertical axis) the bias is multiplied by the
inverse of that weak direction: with paper A's Table 1 and 100 nT of noise, c3 came out
100 nT off, whatever the number of samples.

This module fits the same nine parameters by adjusted least squares (Kukush, Markovsky and
Van Huffel 2004): the squared model ``|K b - c|^2 - r^2`` is linear in the monomials of
``b`` up to degree two, so the objective is a quadratic form in an 11x11 moment matrix built
from power sums of the samples up to degree four (the sufficient statistics: an
evaluation costs the same for 100 samples or a day's flight). Each power sum is replaced by
its unbiased counterpart under Gaussian noise of variance sigma_m^2 per axis (Hermite
polynomials: E[x~^2 - s^2] = x^2, E[x~^4 - 6 s^2 x~^2 + 3 s^4] = x^4, ...), and the
reference's square by ``r~^2 - sigma_r^2``; the minimiser of the corrected objective is
consistent. sigma_m is estimated from the fit's own residual (the residual's variance is
sigma_m^2 |K^T n|^2 + sigma_r^2, with n the calibrated field's direction), sigma_r is given
or estimated from the reference's own second differences.

Robust loss: Talwar's (quadratic within ``ROBUST_K`` robust standard deviations of the
residual, constant outside), solved by reweighting with weights 0 or 1: a sample far off the
fit does not move it, and the inliers keep weight one so the bias correction stays exact.

Uncertainties: the sandwich estimator (the spread of the per-sample estimating equations
between the curvature), which holds when the noise is not what the model assumes.
Observability: the dilution of precision of each parameter (its standard deviation in nT,
K's entries times the field, per nT of noise per square root of the number of samples), a
property of the attitude coverage alone; a parameter whose dilution exceeds
``UNDETERMINED_DOP`` is reported as undetermined and held to the isotropic prior.

Ref: A. Kukush, I. Markovsky and S. Van Huffel, "Consistent least squares fitting of
     ellipsoids", Numerische Mathematik 98 (2004) 177-194.
     R. A. Maronna, R. D. Martin and V. J. Yohai, "Robust Statistics", Wiley 2006 (Talwar's
     loss, the MAD scale).
"""

import itertools
from dataclasses import dataclass, field

import numba
import numpy as np


__all__ = ["Moments", "moments", "theta", "theta_jacobian", "objective", "Fit", "fit_eiv",
           "residuals", "Information", "information", "dilution", "EXPONENTS", "ROBUST_K",
           "UNDETERMINED_DOP"]

#: Exponents (x, y, z) of the monomials of b in the squared model, in order:
#: x^2, y^2, z^2, xy, xz, yz, x, y, z, 1 (then r^2 as the eleventh column).
EXPONENTS = ((2, 0, 0), (0, 2, 0), (0, 0, 2), (1, 1, 0), (1, 0, 1), (0, 1, 1),
             (1, 0, 0), (0, 1, 0), (0, 0, 1), (0, 0, 0))
#: Power sums kept: every exponent triple of total degree four or less (35).
_POWERS = tuple(e for e in itertools.product(range(5), repeat=3) if sum(e) <= 4)
_POWER_INDEX = {e: i for i, e in enumerate(_POWERS)}
#: Probabilists' Hermite polynomials with variance s^2, as {power of x: coefficient of
#: s^(n - power)}: E[He_n(x + w)] = x^n for w ~ N(0, s^2).
_HERMITE = ({0: 1.0}, {1: 1.0}, {2: 1.0, 0: -1.0}, {3: 1.0, 1: -3.0},
            {4: 1.0, 2: -6.0, 0: 3.0})
#: Talwar's cut-off, in robust standard deviations (1.4826 MAD) of the residual: Gaussian
#: noise passes it with probability 1 - 6e-7, so the inliers' weights are one.
ROBUST_K = 5.0
#: Reweighting rounds at most (each one refits on the kept samples).
MAX_ROUNDS = 12
#: Levenberg-Marquardt iterations at most per fit of the moment problem.
MAX_ITERATIONS = 50
#: A parameter whose dilution of precision exceeds this is reported as undetermined by the
#: coverage: its standard deviation exceeds this many times the noise divided by sqrt(N)
#: (a full-sphere tumble gives 1.7-4 for every parameter; a +-30 deg UAV pattern ~70 for
#: k33 and c3, the vertical axis it hardly turns; a level turn 10^4 and more). It is still
#: fitted from the data, with its (large) uncertainty.
UNDETERMINED_DOP = 30.0
#: A direction whose dilution exceeds this is not fitted at all: the data cannot tell it
#: from the trivial solution (K -> 0, |c| = r), so a prior holds it to the isotropic start.
DEGENERATE_DOP = 1000.0
#: Strength of that prior relative to the strongest direction of the data.
PRIOR_STRENGTH = 1.0
#: How wrong the isotropic start may be, for the parameters the prior holds: K's entries
#: by this much (scale factors and soft iron of a few %, misalignment of a few degrees)...
PRIOR_ERROR_K = 0.1
#: ... and the offset by this share of the field (paper A's Table 1: 3.5 %).
PRIOR_ERROR_C = 0.05
#: A parameter is reported as held (its value the prior's, no uncertainty) when at least
#: this share of it lies along the held directions (in the dilution's units: the squared
#: component of its unit vector on them). A parameter that only takes a small part in a
#: held combination is fitted by the data: its uncertainty then includes what the prior's
#: plausible error moves it by.
HELD_SHARE = 0.25


@dataclass
class Moments:
    """Power sums of the kept samples: ``P[i]`` = sum x^a y^b z^c for ``_POWERS[i]``,
    ``Pr[j]`` = sum monomial_j * r^2 for the ten model monomials, ``r4`` = sum r^4, and the
    count. Samples and reference are centred and scaled first (``shift``, ``scale``) so the
    sums keep their precision."""
    P: np.ndarray
    Pr: np.ndarray
    r2: float
    r4: float
    count: int
    shift: np.ndarray
    scale: float

    def matrix(self, sigma_m=0.0, sigma_r=0.0):
        """The 11x11 moment matrix, corrected for noise of ``sigma_m`` per axis (nT) in the
        samples and ``sigma_r`` (nT) in the reference; unbiased for the noise-free one."""
        s2 = (sigma_m / self.scale) ** 2
        q2 = (sigma_r / self.scale) ** 2

        def corrected(e):
            total = 0.0
            for px, cx in _HERMITE[e[0]].items():
                for py, cy in _HERMITE[e[1]].items():
                    for pz, cz in _HERMITE[e[2]].items():
                        order = (e[0] - px) + (e[1] - py) + (e[2] - pz)
                        total += cx * cy * cz * s2 ** (order // 2) * \
                            self.P[_POWER_INDEX[(px, py, pz)]]
            return total

        s = np.empty((11, 11))
        for j, ej in enumerate(EXPONENTS):
            for k in range(j, 10):
                s[j, k] = s[k, j] = corrected(tuple(a + b for a, b in zip(ej, EXPONENTS[k])))
            # sum m_j (r^2 - q^2): the reference's noise is independent of the samples'.
            s[j, 10] = s[10, j] = self._corrected_r(j, s2) - q2 * corrected(ej)
        s[10, 10] = self.r4 - 6 * q2 * self.r2 + 3 * q2 * q2 * self.count
        return s

    def _corrected_r(self, j, s2):
        e = EXPONENTS[j]
        # m_j has degree <= 2 and at most one squared axis: He_2 = x^2 - s^2.
        if sum(e) == 2 and max(e) == 2:
            return self.Pr[j] - s2 * self.Pr[9]
        return self.Pr[j]


#: Each power sum as a product of two model monomials (every monomial of degree four or
#: less in three variables is one): its place in the 11x11 matrix of their products.
_POWER_PLACE = {}
for _j, _ej in enumerate(EXPONENTS):
    for _k, _ek in enumerate(EXPONENTS):
        _POWER_PLACE.setdefault(tuple(a + b for a, b in zip(_ej, _ek)), (_j, _k))
_POWER_ROWS = np.array([_POWER_PLACE[e][0] for e in _POWERS])
_POWER_COLUMNS = np.array([_POWER_PLACE[e][1] for e in _POWERS])
#: Samples per block of the moment and information sums (their arrays stay in cache).
BLOCK = 1 << 16


def _monomial_block(b, r, shift, scale):
    """The model monomials and r^2 of a block of samples, centred and scaled (n, 11)."""
    x = (b - shift) / scale
    z = np.empty((len(x), 11))
    z[:, 0:3] = x * x
    z[:, 3] = x[:, 0] * x[:, 1]
    z[:, 4] = x[:, 0] * x[:, 2]
    z[:, 5] = x[:, 1] * x[:, 2]
    z[:, 6:9] = x
    z[:, 9] = 1.0
    z[:, 10] = (r / scale) ** 2
    return z


def moments(b, r, keep=None, *, shift=None, scale=None):
    """The power sums of samples ``b`` (N, 3) and reference ``r`` (N,) over ``keep``: the
    products of the model monomials summed block by block with BLAS (about 10 ms for a
    one-hour flight at 50 Hz)."""
    b = np.asarray(b, dtype=np.float64)
    r = np.asarray(r, dtype=np.float64)
    shift = np.zeros(3) if shift is None else np.asarray(shift, dtype=np.float64)
    if scale is None:
        scale = float(np.median(r if keep is None else r[keep]))
    scale = float(scale)
    products = np.zeros((11, 11))
    count = 0
    for start in range(0, len(b), BLOCK):
        block = slice(start, start + BLOCK)
        z = _monomial_block(b[block], r[block], shift, scale)
        if keep is not None:
            z = z[keep[block]]
        products += z.T @ z
        count += len(z)
    return Moments(P=products[_POWER_ROWS, _POWER_COLUMNS], Pr=products[:10, 10].copy(),
                   r2=float(products[9, 10]), r4=float(products[10, 10]), count=count,
                   shift=shift, scale=scale)


@numba.njit(cache=True)
def _residual_kernel(p, b, r, u, e):
    for i in range(b.shape[0]):
        x, y, z = b[i, 0], b[i, 1], b[i, 2]
        u0 = p[0] * x + p[1] * y + p[2] * z - p[6]
        u1 = p[3] * y + p[4] * z - p[7]
        u2 = p[5] * z - p[8]
        u[i, 0], u[i, 1], u[i, 2] = u0, u1, u2
        e[i] = np.sqrt(u0 * u0 + u1 * u1 + u2 * u2) - r[i]


def theta(p):
    """Coefficients of the squared model on the monomials (ten) for parameters ``p`` (9):
    |K b - c|^2 = theta . monomials(b)."""
    k11, k12, k13, k22, k23, k33, c1, c2, c3 = p
    g1 = k11 * c1
    g2 = k12 * c1 + k22 * c2
    g3 = k13 * c1 + k23 * c2 + k33 * c3
    return np.array([k11 * k11, k12 * k12 + k22 * k22, k13 * k13 + k23 * k23 + k33 * k33,
                     2 * k11 * k12, 2 * k11 * k13, 2 * (k12 * k13 + k22 * k23),
                     -2 * g1, -2 * g2, -2 * g3, c1 * c1 + c2 * c2 + c3 * c3])


def theta_jacobian(p):
    """d theta / d p (10, 9)."""
    k11, k12, k13, k22, k23, k33, c1, c2, c3 = p
    j = np.zeros((10, 9))
    j[0, 0] = 2 * k11
    j[1, 1], j[1, 3] = 2 * k12, 2 * k22
    j[2, 2], j[2, 4], j[2, 5] = 2 * k13, 2 * k23, 2 * k33
    j[3, 0], j[3, 1] = 2 * k12, 2 * k11
    j[4, 0], j[4, 2] = 2 * k13, 2 * k11
    j[5, 1], j[5, 2], j[5, 3], j[5, 4] = 2 * k13, 2 * k12, 2 * k23, 2 * k22
    j[6, 0], j[6, 6] = -2 * c1, -2 * k11
    j[7, 1], j[7, 3], j[7, 6], j[7, 7] = -2 * c1, -2 * c2, -2 * k12, -2 * k22
    j[8, 2], j[8, 4], j[8, 5] = -2 * c1, -2 * c2, -2 * c3
    j[8, 6], j[8, 7], j[8, 8] = -2 * k13, -2 * k23, -2 * k33
    j[9, 6:9] = 2 * np.array([c1, c2, c3])
    return j


def objective(p, s):
    """The algebraic objective: sum (|K b - c|^2 - r^2)^2 from the moment matrix ``s``."""
    v = np.append(theta(p), -1.0)
    return float(v @ s @ v)


def _to_unit(p, shift, scale):
    """Parameters for samples in nT -> parameters for the centred, scaled samples."""
    k = np.array([[p[0], p[1], p[2]], [0, p[3], p[4]], [0, 0, p[5]]])
    c = (np.asarray(p[6:9]) - k @ shift) / scale
    return np.array([p[0], p[1], p[2], p[3], p[4], p[5], *c])


def _from_unit(q, shift, scale):
    k = np.array([[q[0], q[1], q[2]], [0, q[3], q[4]], [0, 0, q[5]]])
    c = np.asarray(q[6:9]) * scale + k @ shift
    return np.array([q[0], q[1], q[2], q[3], q[4], q[5], *c])


def _linear_start(s, scale_guess):
    """Parameters from the linear solution of the moment problem (ten free coefficients,
    the relation between them not enforced); None when it is no ellipsoid. (It was the
    isotropic start about the origin of ``s``'s coordinates, which for the centred moments
    of :func:`fit_eiv` put the centre on the samples' mean: no start at all.)"""
    a, g = s[:10, :10], s[:10, 10]
    try:
        t = np.linalg.lstsq(a, g, rcond=1e-14)[0]
        m = np.array([[t[0], t[3] / 2, t[4] / 2], [t[3] / 2, t[1], t[5] / 2],
                      [t[4] / 2, t[5] / 2, t[2]]])
        k = np.linalg.cholesky(m).T                 # M = K^T K, K upper triangular
        c = np.linalg.solve(k.T, -t[6:9] / 2)       # K^T c = -theta[6:9] / 2
        return np.array([k[0, 0], k[0, 1], k[0, 2], k[1, 1], k[1, 2], k[2, 2], *c])
    except np.linalg.LinAlgError:
        return None


def _root(s):
    """L with L^T L = s (s clipped to positive semi-definite)."""
    values, vectors = np.linalg.eigh((s + s.T) / 2)
    return np.sqrt(np.clip(values, 0, None))[:, None] * vectors.T


#: K's diagonal in the parameter vector (k11, k22, k33).
DIAGONAL = (0, 3, 5)


def canonical(p):
    """The same model with K's diagonal positive: |K b - c| is unchanged when a row of K
    and the matching entry of c change sign together (D K, D c with D = diag(+-1)), so
    each row whose diagonal element is negative is flipped. A zero diagonal element has
    no such twin (it is the collapsed model): ``ValueError``."""
    p = np.array(p, dtype=float)
    diag = p[list(DIAGONAL)]
    if not np.all(np.isfinite(diag)) or np.any(diag == 0):
        raise ValueError(f"K's diagonal must be finite and non-zero, not {diag.tolist()}")
    rows = ((0, 1, 2, 6), (3, 4, 7), (5, 8))
    for d, row in zip(diag, rows):
        if d < 0:
            p[list(row)] *= -1
    return p


#: The errors-in-variables solver's range for K's diagonal, as a factor of the data's scale
#: either way (the swarm's box, ``scalar.DIAGONAL_RANGE``): the collapse K -> 0 lies outside.
DIAGONAL_FACTOR = 2.0
#: How close to that range's edge a start is put when it lies outside (as a share of it).
_EDGE = 0.999


def to_log(q, scale=None):
    """Solver coordinates: K's diagonal as its logarithm (so no step of any solver can
    make it zero or negative), the other parameters as they are. With ``scale`` (the
    data's scale), the logarithm of diagonal / scale is further mapped by atanh onto the
    whole line from the range within :data:`DIAGONAL_FACTOR` of it: a step cannot leave
    that range either."""
    z = np.array(q, dtype=float)
    d = list(DIAGONAL)
    z[d] = np.log(z[d])
    if scale is not None:
        width = np.log(DIAGONAL_FACTOR)
        z[d] = np.arctanh(np.clip((z[d] - np.log(scale)) / width, -_EDGE, _EDGE))
    return z


def from_log(z, scale=None):
    q = np.array(z, dtype=float)
    d = list(DIAGONAL)
    if scale is not None:
        q[d] = np.log(scale) + np.log(DIAGONAL_FACTOR) * np.tanh(q[d])
    q[d] = np.exp(q[d])
    return q


def _chain(z, q, scale=None):
    """d q / d z of :func:`from_log` (diagonal)."""
    chain = np.ones(len(q))
    d = list(DIAGONAL)
    chain[d] = q[d]
    if scale is not None:
        chain[d] *= np.log(DIAGONAL_FACTOR) * (1.0 - np.tanh(z[d]) ** 2)
    return chain


def _gauss_newton(q, root, prior=None, *, iterations=None, scale=None):
    """Levenberg-Marquardt on the 11 residuals ``root @ [theta(q), -1]`` (plus prior rows
    ``A q - target``). K's diagonal is stepped as its logarithm (:func:`to_log`): it stays
    positive by construction (a start with a negative diagonal is first replaced by its
    twin, :func:`canonical`), and with ``scale`` within :data:`DIAGONAL_FACTOR` of it, so
    the collapsed minimum (K -> 0, |c| = r, the lowest when the reference hardly varies) is
    out of reach. Returns (q, iterations, converged)."""
    def residual(z):
        x = from_log(z, scale)
        e = root @ np.append(theta(x), -1.0)
        return e if prior is None else np.concatenate([e, prior[0] @ x - prior[1]])

    def jacobian(z):
        x = from_log(z, scale)
        chain = _chain(z, x, scale)
        j = root[:, :10] @ theta_jacobian(x) * chain[None, :]
        return j if prior is None else np.vstack([j, prior[0] * chain[None, :]])

    iterations = MAX_ITERATIONS if iterations is None else iterations
    z = to_log(canonical(q), scale)
    e = residual(z)
    cost = e @ e
    damping = 1e-6
    for it in range(1, iterations + 1):
        j = jacobian(z)
        a = j.T @ j
        g = j.T @ e
        d = np.diag(a).copy()
        d[d <= 0] = 1.0
        while True:
            try:
                step = np.linalg.solve(a + damping * np.diag(d), -g)
            except np.linalg.LinAlgError:
                step = np.zeros_like(z)
            trial = z + step
            with np.errstate(over="ignore", invalid="ignore"):
                diagonal = from_log(trial, scale)[list(DIAGONAL)]
                e_trial = residual(trial)
                c_trial = e_trial @ e_trial
            # A diagonal element that the exponential rounds to zero or infinity is no
            # model (the collapse K -> 0 is approached, never reached).
            if (np.isfinite(c_trial) and c_trial <= cost
                    and np.all((diagonal > 0) & np.isfinite(diagonal))):
                break
            damping *= 10
            if damping > 1e12:
                return from_log(z, scale), it, True     # no descent left: at the minimum
        z, e, change = trial, e_trial, cost - c_trial
        cost = c_trial
        damping = max(damping / 10, 1e-12)
        if change <= 1e-15 * max(cost, 1e-300) or np.max(np.abs(step)) <= 1e-13 * (
                1 + np.max(np.abs(z))):
            return from_log(z, scale), it, True
    return from_log(z, scale), iterations, False


@numba.njit(cache=True)
def _talwar(p, u, e, allowed, centre, cut, kept):
    """Marks the allowed samples within ``cut`` of ``centre`` in ``kept``; returns their
    count, their sum of squared residuals and their sum of |K^T n|^2 (n the calibrated
    field's direction: how the sensor's noise reaches the residual)."""
    count = 0
    square_sum = 0.0
    gain_sum = 0.0
    for i in range(e.shape[0]):
        kept[i] = allowed[i] and abs(e[i] - centre) <= cut
        if not kept[i]:
            continue
        norm = np.sqrt(u[i, 0] ** 2 + u[i, 1] ** 2 + u[i, 2] ** 2)
        n0, n1, n2 = u[i, 0] / norm, u[i, 1] / norm, u[i, 2] / norm
        g0 = p[0] * n0
        g1 = p[1] * n0 + p[3] * n1
        g2 = p[2] * n0 + p[4] * n1 + p[5] * n2
        gain_sum += g0 * g0 + g1 * g1 + g2 * g2
        square_sum += e[i] * e[i]
        count += 1
    return count, square_sum, gain_sum


def residuals(p, b, r):
    """|K b - c| - r per sample, and the calibrated vectors K b - c."""
    b = np.ascontiguousarray(b, dtype=np.float64)
    r = np.broadcast_to(np.asarray(r, dtype=np.float64), (len(b),))
    u = np.empty_like(b)
    e = np.empty(len(b))
    _residual_kernel(np.asarray(p, dtype=np.float64), b, np.ascontiguousarray(r), u, e)
    return e, u


def _field_gradient(p, b, u):
    """d|K b - c| / dp per sample (N, 9)."""
    d = u / np.linalg.norm(u, axis=1)[:, None]
    x, y, z = b[:, 0], b[:, 1], b[:, 2]
    return np.column_stack([d[:, 0] * x, d[:, 0] * y, d[:, 0] * z, d[:, 1] * y,
                            d[:, 1] * z, d[:, 2] * z, -d[:, 0], -d[:, 1], -d[:, 2]])


@dataclass
class Information:
    """Sums over the fitted samples: ``h`` = sum g g^T of the field's gradient g (9), and
    ``spread`` = the scatter of the scores g e about their mean (e the residual), ``count``
    the samples."""
    h: np.ndarray
    spread: np.ndarray
    count: int


def information(p, b, r, keep=None):
    """The :class:`Information` of parameters ``p`` on samples ``b``, ``r`` (over ``keep``),
    block by block."""
    h = np.zeros((9, 9))
    outer = np.zeros((9, 9))
    total = np.zeros(9)
    count = 0
    for start in range(0, len(b), BLOCK):
        block = slice(start, start + BLOCK)
        bb, rr = b[block], r[block]
        if keep is not None:
            bb, rr = bb[keep[block]], rr[keep[block]]
        e, u = residuals(p, bb, rr)
        g = _field_gradient(p, bb, u)
        scores = g * e[:, None]
        h += g.T @ g
        outer += scores.T @ scores
        total += scores.sum(axis=0)
        count += len(bb)
    mean = total / max(count, 1)
    return Information(h=h, spread=outer - count * np.outer(mean, mean), count=count)


def dilution(info, field_nt):
    """Per-parameter dilution of precision from an :class:`Information`: each parameter's
    standard deviation in nT (K's entries times ``field_nt``) per nT of noise per
    1/sqrt(N); infinity where the information is singular."""
    units = np.array([field_nt] * 6 + [1.0] * 3)
    try:
        cov = np.linalg.inv(info.h / max(info.count, 1))
    except np.linalg.LinAlgError:
        return np.full(9, np.inf)
    diag = np.diag(cov)
    return np.where(diag > 0, np.sqrt(np.abs(diag)) * units, np.inf)


@dataclass
class Fit:
    """What :func:`fit_eiv` found (parameters in nT units, as ``calibrate_scalar``'s)."""
    x: np.ndarray
    keep: np.ndarray            # samples the robust loss kept
    sigma_m: float              # the magnetometer's noise per axis, estimated (nT)
    sigma_r: float              # the reference's noise, given or estimated (nT)
    covariance: np.ndarray      # sandwich, 9x9 (parameters as x)
    dop: np.ndarray             # dilution of precision per parameter
    determined: np.ndarray      # bool per parameter
    held: np.ndarray            # bool per parameter: moved along a direction the prior holds
    weak: np.ndarray            # (m, 9) the directions held to the prior (reported parameters)
    rounds: int                 # reweighting rounds
    nit: int                    # Gauss-Newton iterations in all
    converged: bool
    scale_cut: float            # the robust loss's cut-off (nT)
    warnings: list = field(default_factory=list)


def reference_noise(r):
    """The reference's own noise (nT), from the MAD of its second differences: a total
    field along a flight is smooth from one sample to the next, its sensor's noise is not.
    (A reference interpolated between readings is smoother than its readings: this gives a
    lower bound, which is the conservative side for the correction.)"""
    r = np.asarray(r, float)
    if len(r) < 5:
        return 0.0
    d2 = np.diff(r, 2)
    return float(1.4826 * np.median(np.abs(d2 - np.median(d2))) / np.sqrt(6.0))


def _plausible(q, scale_guess):
    """A start worth polishing: K's diagonal within the calibration's range of the data's
    scale, small off-diagonals, the centre within half the field."""
    diag = np.array([q[0], q[3], q[5]]) / scale_guess
    off = np.array([q[1], q[2], q[4]]) / scale_guess
    return bool(np.all(np.isfinite(q)) and np.all((diag > 0.5) & (diag < 2.0))
                and np.all(np.abs(off) < 0.5) and np.linalg.norm(q[6:9]) < 0.5)


def _weak_prior(root, q, target, count, shift, field_nt):
    """The directions the data cannot tell from the trivial solution, and prior rows
    holding them to ``target``. The information per sample is taken from the moment
    problem at ``q`` and expressed in the reported parameters, K's entries times the field
    and c in nT (the dilution's units); a direction whose dilution exceeds
    :data:`DEGENERATE_DOP` is held. Returns (rows in the reported parameters (m, 9), the
    prior in the moment problem's parameters (rows, target)), or (None, None)."""
    j = root[:, :10] @ theta_jacobian(q)
    jtj = j.T @ j
    d = _unit_jacobian(shift, field_nt)
    units = np.array([field_nt] * 6 + [1.0] * 3)
    info = field_nt ** 2 * d.T @ jtj @ d / (4.0 * count) / np.outer(units, units)
    values, vectors = np.linalg.eigh((info + info.T) / 2)
    weak = values < 1.0 / DEGENERATE_DOP ** 2
    if not np.any(weak):
        return None, None
    rows_x = vectors[:, weak].T * units[None, :]
    rows_q = rows_x @ np.linalg.inv(d)
    rows_q /= np.linalg.norm(rows_q, axis=1)[:, None]
    # As strong as the strongest direction of the data: the prior decides only along the
    # held directions, which the data leave free (they are the information's own
    # eigenvectors, so holding them does not move the others).
    rows_q *= np.sqrt(PRIOR_STRENGTH * np.linalg.eigvalsh(jtj)[-1])
    return rows_x, (rows_q, rows_q @ target)


def fit_eiv(b, r, *, start=None, sigma_r=None, robust=True, keep=None, correct=True):
    """Fit the nine parameters by adjusted least squares with Talwar's robust loss.

    ``start``: parameters to start from (else the linear solution when it is plausible,
    else the isotropic K = s I, c = 0); ``sigma_r``: the reference's noise (nT; None:
    :func:`reference_noise`); ``keep``: samples allowed at all (a screening's mask);
    ``correct`` False gives the uncorrected algebraic fit (the noise taken as zero)."""
    n = len(b)
    allowed = np.ones(n, bool) if keep is None else np.asarray(keep, bool).copy()
    field_nt = float(np.median(r[allowed]))
    shift = np.mean(b[allowed], axis=0)
    if sigma_r is None:
        sigma_r = reference_noise(r[allowed])
    scale_guess = field_nt / float(np.median(np.linalg.norm(b[allowed], axis=1)))
    isotropic = np.array([scale_guess, 0, 0, scale_guess, 0, scale_guess, 0, 0, 0])
    target = _to_unit(isotropic, shift, field_nt)
    kept = allowed.copy()
    sigma_m = 0.0
    q = None if start is None else _to_unit(np.asarray(start, float), shift, field_nt)
    warnings = []
    for rounds in range(1, MAX_ROUNDS + 1):
        mom = moments(b, r, kept, shift=shift, scale=field_nt)
        s = mom.matrix(sigma_m if correct else 0.0, sigma_r if correct else 0.0)
        root = _root(s)
        if rounds == 1:
            q, nit, converged = _best_start(q, root, s, target, mom.count, shift, field_nt,
                                            scale_guess)
        # The directions the coverage leaves to the prior, judged where the fit stands.
        held_rows, prior = _weak_prior(root, q, target, mom.count, shift, field_nt)
        q, it, converged = _gauss_newton(q, root, prior, scale=scale_guess)
        nit += it
        new_kept, cut, new_sigma = _reweight(_from_unit(q, shift, field_nt), b, r, kept,
                                             allowed, robust, sigma_r)
        stable = np.array_equal(new_kept, kept) and (
            not correct or abs(new_sigma - sigma_m) <= 1e-3 * max(new_sigma, 1e-9))
        kept, sigma_m = new_kept, new_sigma
        if stable:
            break
    else:
        warnings.append(f"the robust reweighting had not settled after {MAX_ROUNDS} rounds")
    x = _from_unit(q, shift, field_nt)
    info = information(x, b, r, kept)
    dop = dilution(info, field_nt)
    covariance, held = _sandwich(info, held_rows, field_nt)
    determined = (dop <= UNDETERMINED_DOP) & ~held
    return Fit(x=x, keep=kept, sigma_m=sigma_m, sigma_r=sigma_r, covariance=covariance,
               dop=dop, determined=determined, held=held,
               weak=np.zeros((0, 9)) if held_rows is None else held_rows, rounds=rounds,
               nit=nit, converged=converged, scale_cut=cut, warnings=warnings)


def _best_start(given, root, s, target, count, shift, field_nt, scale_guess):
    """Every plausible start (the given one, the linear solution, the isotropic one)
    polished; the best plausible end wins: the algebraic objective has a collapsed minimum
    (K -> 0) that a start far off may slide into. Returns (q, iterations, converged)."""
    def plausible(q):
        # Judged on the reported parameters (c in the field's units), not the centred ones:
        # a survey flight's mean vector is most of the field, so its centred offset is too.
        x = _from_unit(q, shift, field_nt)
        return _plausible(np.r_[x[:6], x[6:9] / field_nt], scale_guess)

    candidates = [target.copy()]
    linear = _linear_start(s, scale_guess)
    if linear is not None and plausible(linear):
        candidates.insert(0, linear)
    if given is not None and plausible(given):
        candidates.insert(0, given)
    ends, nit = [], 0
    for candidate in candidates:
        _, prior = _weak_prior(root, candidate, target, count, shift, field_nt)
        end, it, ok = _gauss_newton(candidate, root, prior, scale=scale_guess)
        nit += it
        ends.append((not plausible(end), objective(end, s), end, ok))
    _, _, q, converged = min(ends, key=lambda item: item[:2])
    return q, nit, converged


def _reweight(x, b, r, kept, allowed, robust, sigma_r):
    """Talwar's loss as a mask about the median residual of the ``kept`` samples (cut at
    :data:`ROBUST_K` robust standard deviations), and the magnetometer's noise from the
    residual of those it keeps. Returns (new mask, cut-off in nT, noise in nT)."""
    e, u = residuals(x, b, r)
    inside = e[kept]
    centre = float(np.median(inside))
    spread = 1.4826 * float(np.median(np.abs(inside - centre)))
    cut = ROBUST_K * spread if robust and spread > 0 else np.inf
    new_kept = np.empty(len(b), dtype=np.bool_)
    count, square_sum, gain_sum = _talwar(x, u, e, allowed, centre, cut, new_kept)
    gain = gain_sum / max(count, 1)
    variance = square_sum / max(count - 9, 1)
    return new_kept, cut, float(np.sqrt(max(variance - sigma_r ** 2, 0.0) / gain))


def _unit_jacobian(shift, field_nt):
    """d q / d x: the centred, scaled parameters against the reported ones (K the same,
    c_unit = (c - K shift) / field)."""
    d = np.eye(9)
    d[6:9, 6:9] /= field_nt
    d[6, 0:3] = -shift / field_nt
    d[7, 3:5] = -shift[1:] / field_nt
    d[8, 5] = -shift[2] / field_nt
    return d


def held_directions(rows, field_nt):
    """The held directions as unit vectors in the dilution's units (K's entries times the
    field, c in nT), largest component positive: (m, 9)."""
    if rows is None or len(rows) == 0:
        return np.zeros((0, 9))
    units = np.array([field_nt] * 6 + [1.0] * 3)
    v = np.asarray(rows, float) / units[None, :]
    v /= np.linalg.norm(v, axis=1)[:, None]
    signs = np.sign(v[np.arange(len(v)), np.argmax(np.abs(v), axis=1)])
    return v * signs[:, None]


def _sandwich(info, rows, field_nt):
    """Covariance of the parameters and which of them the prior holds.

    The data's part: H^-1 B H^-1 (H the information of the field's gradient, B the spread
    of the per-sample scores, gradient times residual), within the directions the data
    determine when a prior holds others (``rows``: the held directions, in the reported
    parameters). The prior's part: the constrained estimate moves by (I - basis inner
    basis^T H) times the isotropic start's error, which is plausibly K's entries by
    :data:`PRIOR_ERROR_K` and c by :data:`PRIOR_ERROR_C` of the field (one standard
    deviation); that spread is added. A parameter is held when :data:`HELD_SHARE` of it or
    more lies along the held directions: the data cannot move it on its own."""
    h, spread = info.h, info.spread
    if rows is None:
        basis = np.eye(9)
    else:
        _, _, vt = np.linalg.svd(rows)
        basis = vt[rows.shape[0]:].T                # the directions the data determine
    try:
        inner = np.linalg.inv(basis.T @ h @ basis)
    except np.linalg.LinAlgError:
        return np.full((9, 9), np.inf), np.ones(9, bool)
    covariance = basis @ inner @ (basis.T @ spread @ basis) @ inner @ basis.T
    if rows is None:
        return covariance, np.zeros(9, bool)
    reach = np.eye(9) - basis @ inner @ basis.T @ h
    error = np.array([PRIOR_ERROR_K] * 6 + [PRIOR_ERROR_C * field_nt] * 3)
    covariance = covariance + (reach * error ** 2) @ reach.T
    share = np.sum(held_directions(rows, field_nt) ** 2, axis=0)
    return covariance, share >= HELD_SHARE
