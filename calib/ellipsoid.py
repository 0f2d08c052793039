"""Ellipsoid fitting, gated on what the flight determines.

Samples of a constant field seen from many attitudes lie on an ellipsoid (soft and hard
iron); fitting it gives the centre (hard iron) and the matrix that maps it back onto a
sphere of the field's magnitude (soft iron and scale), up to a rotation.

Two fits of the quadric a x^2 + b y^2 + c z^2 + 2f yz + 2g xz + 2h xy + 2p x + 2q y + 2r z
+ d = 0: the nine-parameter algebraic least-squares fit (d = -1), and the constrained fit
of Li and Griffiths (2004) that always returns an ellipsoid (4J - I^2 = 1).

The fit's own uncertainty: the geometric residual ``|W (b - centre)| - field`` linearised
about the fit (W's six entries and the centre), its covariance scaled by the residual's
variance, carried to the scalar model's canonical form (K = the upper-triangular factor of
W with a positive diagonal, c = K centre) so that its parameters are named and judged as
the scalar fit's are (k11..c3, :mod:`.coverage`).

Coverage gate, two kinds:

- ``gate="determined"`` (the default): the fit is made, and refused (``success`` False, the
  fitted centre and W kept for inspection) unless :func:`maglog.calib.coverage.determine`
  finds every parameter determined: its 1-sigma in nT of field within the noise of one
  sample (the fit's residual RMS) or the bound given. A flight that fits and pins every
  parameter down is accepted whatever octants its samples fill; one that fits as well but
  leaves the offset along an axis free (a level flight, a UAV's +-30 deg over too few
  samples) is refused, and the message names the parameters and their 1-sigma.
- ``gate="paper"``: paper B's, samples counted in the octants about the running centroid
  of the raw samples, and no fit attempted before all eight hold ``min_per_octant``. On a
  UAV pattern the centroid lies inside the covered cap, so all eight fill although the
  field never pointed into half of the sphere (calib.coverage explains); kept as what the
  paper did.

The octants of the calibrated directions about the fitted centre are counted in every
result (``coverage``), as information: a UAV's +-30 deg reaches four of them and may
still determine every parameter when flown long enough.

Samples that cannot determine any fit (a stuck axis, fewer than ten distinct vectors,
values no magnetometer gives) are refused before either gate with a ``ValueError`` that
says so: a stuck axis equal to the running centroid would otherwise count in every octant.

Ref: Q. Li and J. G. Griffiths, "Least squares ellipsoid specific fitting", Geometric
     Modeling and Processing 2004, pp. 335-340.
"""

from dataclasses import dataclass, field

import numpy as np

from ._samples import MAX_FIELD_NT, check_samples
from .coverage import check_bound, determine


__all__ = ["Coverage", "octant_coverage", "EllipsoidResult", "fit_ellipsoid"]


@dataclass
class Coverage:
    counts: np.ndarray          # samples per octant (index = 4 sx + 2 sy + sz, s = 1 if >=)
    centroid: np.ndarray        # the point the octants are about
    min_per_octant: int
    about: str = "running centroid"     # or "fitted centre"

    @property
    def filled(self):
        return int(np.sum(self.counts >= self.min_per_octant))

    @property
    def complete(self):
        return self.filled == 8

    def report(self):
        return {"octants_filled": self.filled, "counts": self.counts.tolist(),
                "min_per_octant": self.min_per_octant, "about": self.about,
                "centroid": self.centroid.tolist()}


def octant_coverage(b, *, min_per_octant=10):
    """Samples per octant around the running centroid (each sample is placed against the
    centroid of the samples before it, as a logger would count during a flight)."""
    b = np.asarray(b, dtype=float)
    running = np.cumsum(b, axis=0) / np.arange(1, len(b) + 1)[:, None]
    reference = np.vstack([b[:1], running[:-1]])
    signs = (b >= reference).astype(int)
    octant = 4 * signs[:, 0] + 2 * signs[:, 1] + signs[:, 2]
    return Coverage(counts=np.bincount(octant, minlength=8), centroid=running[-1],
                    min_per_octant=min_per_octant)


@dataclass
class EllipsoidResult:
    center: np.ndarray          # hard-iron offset, nT
    W: np.ndarray               # symmetric: |W (b - center)| = field
    radii: np.ndarray           # semi-axes, nT
    rms: float                  # RMS of |W (b - center)| - field
    success: bool
    message: str
    coverage: Coverage          # the gate's: about the fitted centre, or paper B's
    method: str
    warnings: list = field(default_factory=list)
    paper_coverage: Coverage = None     # paper B's octants about the running centroid
    field_nt: float = float("nan")      # the sphere's radius the fit was made for
    K: np.ndarray = None        # canonical form: upper triangular, positive diagonal
    c: np.ndarray = None        # K centre, nT: calibrated = K b - c (up to a rotation)
    x: np.ndarray = None        # k11, k12, k13, k22, k23, k33, c1, c2, c3
    uncertainties: np.ndarray = None    # 1-sigma of x (K's dimensionless, c's nT)
    noise_nT: float = float("nan")      # RMS of the geometric residual (as ``rms``)
    determination: object = None        # calib.coverage.Determination


def _design(b):
    x, y, z = b[:, 0], b[:, 1], b[:, 2]
    return np.column_stack([x * x, y * y, z * z, 2 * y * z, 2 * x * z, 2 * x * y,
                            2 * x, 2 * y, 2 * z, np.ones_like(x)])


def _algebraic(d):
    v, *_ = np.linalg.lstsq(d[:, :9], np.ones(len(d)), rcond=None)
    return np.append(v, -1.0)


def _li_griffiths(d, k=4.0):
    s = d.T @ d
    s11, s12, s22 = s[:6, :6], s[:6, 6:], s[6:, 6:]
    c1 = np.zeros((6, 6))
    c1[:3, :3] = k / 2 - 1
    np.fill_diagonal(c1[:3, :3], -1)
    c1[3:, 3:] = -k * np.eye(3)
    reduced = s11 - s12 @ np.linalg.solve(s22, s12.T)
    values, vectors = np.linalg.eig(np.linalg.solve(c1, reduced))
    values, vectors = values.real, vectors.real
    v1 = vectors[:, int(np.argmax(values))]
    v2 = -np.linalg.solve(s22, s12.T @ v1)
    return np.concatenate([v1, v2])


def _to_geometry(v, field_nt):
    a, b_, c, f, g, h, p, q, r, dd = v
    quad = np.array([[a, h, g], [h, b_, f], [g, f, c]])
    lin = np.array([p, q, r])
    center = -np.linalg.solve(quad, lin)
    scale = center @ quad @ center - dd
    m = quad / scale
    values, vectors = np.linalg.eigh(m)
    if np.all(values < 0):                     # the quadric's overall sign is free
        values = -values
    if np.any(values <= 0):
        return center, None, None
    w = field_nt * (vectors * np.sqrt(values)) @ vectors.T
    return center, w, 1.0 / np.sqrt(values)


_UPPER = np.triu_indices(3)


def _canonical(w, center):
    """The scalar model's form of ``|W (b - centre)|``: K the upper-triangular factor of W
    (W = Q K, K's diagonal positive) and c = K centre; as one vector k11..c3."""
    q, r = np.linalg.qr(w)
    k = r * np.where(np.diag(r) < 0, -1.0, 1.0)[:, None]
    return np.concatenate([k[_UPPER], k @ center])


def _uncertainties(b, w, center, field_nt):
    """1-sigma of the canonical parameters (k11..c3) of the fit (W, centre): the geometric
    residual linearised about it in (W's entries times the field, centre), its covariance
    scaled by the residual's variance, carried through :func:`_canonical`. Infinite where
    the samples leave a direction of the fit free."""
    d = b - center
    v = d @ w.T
    norm = np.linalg.norm(v, axis=1)
    u = v / norm[:, None]
    e = norm - field_nt
    jac = np.empty((len(b), 9))
    for j, (p, q) in enumerate(zip(*_UPPER)):
        jac[:, j] = (u[:, p] * d[:, q] + (u[:, q] * d[:, p] if p != q else 0.0)) / field_nt
    jac[:, 6:] = -(u @ w)
    variance = float(e @ e) / max(len(b) - 9, 1)
    info = jac.T @ jac
    scale = np.sqrt(np.diag(info))
    if not np.all(scale > 0):
        return np.full(9, np.inf)
    try:
        cov = np.linalg.inv(info / np.outer(scale, scale)) / np.outer(scale, scale)
    except np.linalg.LinAlgError:
        return np.full(9, np.inf)
    if not np.all(np.isfinite(cov)) or np.any(np.diag(cov) < 0):
        return np.full(9, np.inf)
    cov *= variance
    # Carry to the canonical form: central differences of _canonical in (W F, centre).
    p0 = np.concatenate([w[_UPPER] * field_nt, center])

    def canonical(p):
        m = np.zeros((3, 3))
        m[_UPPER] = p[:6] / field_nt
        m = m + np.triu(m, 1).T
        return _canonical(m, p[6:])
    grad = np.empty((9, 9))
    for j in range(9):
        h = 1e-6 * max(abs(p0[j]), 1.0)
        up, down = p0.copy(), p0.copy()
        up[j] += h
        down[j] -= h
        grad[:, j] = (canonical(up) - canonical(down)) / (2 * h)
    out = np.diag(grad @ cov @ grad.T)
    return np.where(np.isfinite(out) & (out >= 0), np.sqrt(np.abs(out)), np.inf)


GATES = ("determined", "paper")


def fit_ellipsoid(b, field_nt, *, method="algebraic", min_per_octant=10, gate="determined",
                  determined_nt=None):
    """Fit the samples' ellipsoid; ``field_nt`` is the field's magnitude (the sphere's
    radius after calibration). ``gate``: "determined" (every parameter determined by the
    flight, :func:`maglog.calib.coverage.determine`, the default; True means it too),
    "paper" (paper B's octants about the running centroid, checked before fitting) or False
    (no gate). ``determined_nt``: the bound on a determined parameter's 1-sigma in nT of
    field (None: the noise of one sample, the fit's residual RMS). A refused fit has
    ``success`` False and says why; its determination and coverage are in the result."""
    b = check_samples(b, 10, "for an ellipsoid's nine parameters")
    field_nt = float(field_nt)
    if not (np.isfinite(field_nt) and 0 < field_nt <= MAX_FIELD_NT):
        raise ValueError(f"The field must be positive and at most {MAX_FIELD_NT:.0e} nT, not "
                         f"{field_nt!r}")
    if method not in ("algebraic", "constrained"):
        raise ValueError(f"Method must be 'algebraic' or 'constrained', not {method!r}")
    if gate is True:
        gate = "determined"
    if gate not in GATES and gate not in (False, None):
        raise ValueError(f"Gate must be one of {', '.join(GATES)} or False, not {gate!r}")
    check_bound(determined_nt)
    paper = octant_coverage(b, min_per_octant=min_per_octant)
    nan3 = np.full(3, np.nan)
    if gate == "paper" and not paper.complete:
        return EllipsoidResult(center=nan3, W=np.full((3, 3), np.nan), radii=nan3,
                               rms=np.nan, success=False,
                               message=f"coverage: {paper.filled} of 8 octants have "
                                       f"{min_per_octant} samples",
                               coverage=paper, method=method, paper_coverage=paper)
    # Normalise for conditioning; undo afterwards.
    mean = b.mean(axis=0)
    spread = float(np.sqrt(np.mean(np.sum((b - mean) ** 2, axis=1))))
    unit = (b - mean) / spread
    d = _design(unit)
    try:
        v = _algebraic(d) if method == "algebraic" else _li_griffiths(d)
        center_u, w_u, _ = _to_geometry(v, 1.0)
    except np.linalg.LinAlgError:
        center_u, w_u = None, None          # a singular quadric: no centre, no ellipsoid
    if w_u is None:
        return EllipsoidResult(center=nan3, W=np.full((3, 3), np.nan), radii=nan3,
                               rms=np.nan, success=False,
                               message="the fitted quadric is not an ellipsoid (the "
                                       "constrained method always gives one)",
                               coverage=paper, method=method, paper_coverage=paper)
    center = mean + spread * center_u
    w = field_nt * w_u / spread
    vectors = (b - center) @ w.T
    calibrated = np.linalg.norm(vectors, axis=1)
    radii = field_nt / np.linalg.eigvalsh(w)
    signs = (vectors >= 0).astype(int)
    about = Coverage(counts=np.bincount(4 * signs[:, 0] + 2 * signs[:, 1] + signs[:, 2],
                                        minlength=8),
                     centroid=center, min_per_octant=min_per_octant, about="fitted centre")
    rms = float(np.sqrt(np.mean((calibrated - field_nt) ** 2)))
    x = _canonical(w, center)
    k = np.zeros((3, 3))
    k[_UPPER] = x[:6]
    uncertainties = _uncertainties(b, w, center, field_nt)
    determination = determine(uncertainties, field_nt, rms, bound_nt=determined_nt)
    success, message = True, "fitted"
    if gate == "determined" and not determination.complete:
        success = False
        names = determination.undetermined
        message = (f"undetermined: the samples do not determine {', '.join(names)} (1-sigma "
                   f"{determination.figures(names)}; bound {determination.bound_text})")
    elif gate == "determined":
        message = (f"fitted; every parameter determined (1-sigma "
                   f"{np.max(determination.sigma_nT):.2g} nT of field at most, bound "
                   f"{determination.bound_text})")
    return EllipsoidResult(center=center, W=w, radii=np.sort(radii), rms=rms,
                           success=success, message=message,
                           coverage=about if gate != "paper" else paper, method=method,
                           paper_coverage=paper, field_nt=field_nt, K=k, c=x[6:], x=x,
                           uncertainties=uncertainties, noise_nT=rms,
                           determination=determination)
