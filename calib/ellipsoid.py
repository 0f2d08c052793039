"""Ellipsoid fitting with octant-coverage gating.

Samples of a constant field seen from many attitudes lie on an ellipsoid (soft and hard
iron); fitting it gives the centre (hard iron) and the matrix that maps it back onto a
sphere of the field's magnitude (soft iron and scale), up to a rotation.

Two fits of the quadric a x^2 + b y^2 + c z^2 + 2f yz + 2g xz + 2h xy + 2p x + 2q y + 2r z
+ d = 0: the nine-parameter algebraic least-squares fit (d = -1), and the constrained fit
of Li and Griffiths (2004) that always returns an ellipsoid (4J - I^2 = 1).

Coverage gate, two kinds:

- ``gate="centre"`` (the default): the fit is made, then the calibrated directions
  ``W (b - centre)`` are counted in the eight octants about the fitted centre; the fit is
  refused (``success`` False, the fitted centre and W kept for inspection) unless every
  octant holds ``min_per_octant`` samples: a fit from one side of the ellipsoid leaves the
  offset along that side undetermined.
- ``gate="paper"``: paper B's, samples counted in the octants about the running centroid
  of the raw samples, and no fit attempted before all eight hold ``min_per_octant``. On a
  UAV pattern the centroid lies inside the covered cap, so all eight fill although the
  field never pointed into half of the sphere (calib.coverage explains); kept as what the
  paper did.

Samples that cannot determine any fit (a stuck axis, fewer than ten distinct vectors,
values no magnetometer gives) are refused before either gate with a ``ValueError`` that
says so: a stuck axis equal to the running centroid would otherwise count in every octant.

Ref: Q. Li and J. G. Griffiths, "Least squares ellipsoid specific fitting", Geometric
     Modeling and Processing 2004, pp. 335-340.
"""

from dataclasses import dataclass, field

import numpy as np

from ._samples import MAX_FIELD_NT, check_samples


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


GATES = ("centre", "paper")


def fit_ellipsoid(b, field_nt, *, method="algebraic", min_per_octant=10, gate="centre"):
    """Fit the samples' ellipsoid; ``field_nt`` is the field's magnitude (the sphere's
    radius after calibration). ``gate``: "centre" (octants of the calibrated directions
    about the fitted centre, the default; True means it too), "paper" (paper B's octants
    about the running centroid, checked before fitting) or False (no gate). A refused fit
    has ``success`` False and says why; its coverage is in the result."""
    b = check_samples(b, 10, "for an ellipsoid's nine parameters")
    field_nt = float(field_nt)
    if not (np.isfinite(field_nt) and 0 < field_nt <= MAX_FIELD_NT):
        raise ValueError(f"The field must be positive and at most {MAX_FIELD_NT:.0e} nT, not "
                         f"{field_nt!r}")
    if method not in ("algebraic", "constrained"):
        raise ValueError(f"Method must be 'algebraic' or 'constrained', not {method!r}")
    if gate is True:
        gate = "centre"
    if gate not in GATES and gate not in (False, None):
        raise ValueError(f"Gate must be one of {', '.join(GATES)} or False, not {gate!r}")
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
    success, message = True, "fitted"
    if gate == "centre" and not about.complete:
        success = False
        message = (f"coverage: the field reached {about.filled} of 8 octants about the fitted "
                   f"centre with {min_per_octant} samples ({about.counts.tolist()}): the "
                   "offset is undetermined towards the others")
    return EllipsoidResult(center=center, W=w, radii=np.sort(radii),
                           rms=float(np.sqrt(np.mean((calibrated - field_nt) ** 2))),
                           success=success, message=message,
                           coverage=about if gate != "paper" else paper, method=method,
                           paper_coverage=paper)
