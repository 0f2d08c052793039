"""Magnetometer error-model presets: ``default``, ``paper_a`` and ``none``.

The error model is DESIGN.md's, ``B̂ = C_NO C_SF (I + C_SI)(B_e + B_HI) + b0 + w``
(:class:`maglog.sim.stimulus.scenario.ErrorModel`), so ``B̂ = A B_e + b + w`` with
``A = C_NO C_SF (I + C_SI)`` and ``b = A B_HI + b0`` (paper A, eq. 1-5).

- ``default``: :data:`maglog.sim.stimulus.scenario.DEFAULT_ERRORS`, this project's representative
  values.
- ``none``: an ideal sensor (A = I, b = 0) with its white noise only.
- ``paper_a``: built from paper A's Table 1 (PAPERS.md, section A).

How ``paper_a`` reads Table 1. The paper prints a full 3×3 "P" and an offset "O" (nT) without
saying whether P is the calibration's K (upper triangular, so it cannot be: P is full), K⁻¹,
or the error model's A. We read **P as A, the forward error matrix, and O as b, the total
offset in the sensor frame**: ``B̂ = P B_e + O``. Why:

1. Table 1 is titled the estimated parameters of the error model, and eq. 1-5 define the
   model by A and b; P ≈ I with off-diagonal terms of 0.3-1.8 % and O of hundreds to
   thousands of nT are what a forward matrix and a hard-iron offset look like.
2. ``maglog.calib`` already reports its result this way: ``ScalarResult.P = K⁻¹`` ("the
   paper's forward matrix") and ``offset_sensor = P c``, which is b. Reading Table 1 the same
   way puts the paper's numbers and ours side by side with no conversion.
3. The scalar calibration sees A only up to a rotation (``A = K⁻¹ Uᵀ``): what it recovers is
   ``K⁻¹``, the triangular factor of P, and the offset b = O exactly. The truth file gives
   both A (= P) and the K, c the calibration should find. P's antisymmetric part (P13 − P31
   = 0.025) is a rotation of about 0.8° that no scalar method can see, so the recovered K⁻¹
   and P differ by up to ~0.02 off the diagonal while their products with any field have the
   same magnitude.

The other reading (P = A⁻¹, the correction of eq. 6, ``B_e = P (B̂ − O)``) differs from this
one by terms of second order in P − I (about 4·10⁻⁴ here), below what a short flight
determines; the choice is therefore one of naming, not of numbers.

To express A as the ErrorModel's physical factors, the scale factors C_SF are taken as A's
diagonal, C_SI symmetric, and the non-orthogonality angles β, α, γ of C_NO solved so that
``C_SF⁻¹ C_NO⁻¹ A`` is symmetric (three equations, three unknowns); the product equals P to
rounding. All of O goes to the bias b0 (hard iron B_HI = 0): the split between the two is not
observable and the paper does not make it.
"""

from __future__ import annotations

import numpy as np
from scipy.optimize import least_squares

from .scenario import DEFAULT_ERRORS, ErrorModel

__all__ = ["PAPER_A_P", "PAPER_A_O", "PRESETS", "preset", "from_forward", "forward", "c_no"]

#: Paper A, Table 1: the printed matrix P (read as the forward error matrix A).
PAPER_A_P = ((1.0117, 0.0079, 0.0184),
             (0.0028, 1.0010, -0.0119),
             (-0.0067, -0.0166, 0.9972))
#: Paper A, Table 1: the printed offset O, nT (read as b, the sensor-frame offset).
PAPER_A_O = (1576.1, -604.3794, -41.7471)

#: White noise of the presets, nT per axis (the paper's w is "neglected after low-pass
#: filtering"; a magnetoresistive sensor of this class is a few nT).
PRESET_NOISE_NT = DEFAULT_ERRORS.noise

_RECONSTRUCTION_TOLERANCE = 1e-12


def c_no(beta, alpha, gamma):
    """Paper A's non-orthogonality matrix C_NO (angles in radians)."""
    return np.array([[1.0, 0.0, 0.0],
                     [np.sin(beta), np.cos(beta), 0.0],
                     [np.sin(gamma), np.sin(alpha) * np.cos(gamma),
                      np.cos(alpha) * np.cos(gamma)]])


def from_forward(a, b, *, noise=PRESET_NOISE_NT, mounting=(0.0, 0.0, 0.0)):
    """An :class:`ErrorModel` whose matrix is ``a`` and whose total offset is ``b`` (nT):
    scale factors ``diag(a)``, C_NO solved so that the soft iron is symmetric, all of the
    offset in the bias."""
    a = np.asarray(a, float)
    if a.shape != (3, 3) or not np.all(np.isfinite(a)):
        raise ValueError(f"The error matrix must be a finite 3x3 matrix, not {a.tolist()!r}")
    scale = np.diag(a).copy()
    if np.any(scale <= 0):
        raise ValueError(f"The error matrix's diagonal must be positive, not {scale.tolist()}")

    def asymmetry(angles):
        s = np.diag(1 / scale) @ np.linalg.solve(c_no(*angles), a)
        return [s[0, 1] - s[1, 0], s[0, 2] - s[2, 0], s[1, 2] - s[2, 1]]

    angles = least_squares(asymmetry, np.zeros(3), xtol=1e-15, ftol=1e-15, gtol=1e-15).x
    non_orth = c_no(*angles)
    soft = np.diag(1 / scale) @ np.linalg.solve(non_orth, a) - np.eye(3)
    soft = (soft + soft.T) / 2
    model = ErrorModel(non_orthogonality=tuple(map(tuple, non_orth.tolist())),
                       scale=tuple(scale.tolist()), soft_iron=tuple(map(tuple, soft.tolist())),
                       hard_iron=(0.0, 0.0, 0.0), bias=tuple(np.asarray(b, float).tolist()),
                       noise=float(noise), mounting=tuple(float(m) for m in mounting))
    if np.max(np.abs(model.matrix() - a)) > _RECONSTRUCTION_TOLERANCE:
        raise ValueError("The error matrix has no non-orthogonality, scale and symmetric "
                         "soft-iron decomposition near the identity")
    return model


def _default(noise, mounting):
    return ErrorModel(non_orthogonality=DEFAULT_ERRORS.non_orthogonality,
                      scale=DEFAULT_ERRORS.scale, soft_iron=DEFAULT_ERRORS.soft_iron,
                      hard_iron=DEFAULT_ERRORS.hard_iron, bias=DEFAULT_ERRORS.bias,
                      noise=noise, mounting=mounting)


def _paper_a(noise, mounting):
    return from_forward(PAPER_A_P, PAPER_A_O, noise=noise, mounting=mounting)


def _none(noise, mounting):
    return ErrorModel(non_orthogonality=((1.0, 0.0, 0.0), (0.0, 1.0, 0.0), (0.0, 0.0, 1.0)),
                      scale=(1.0, 1.0, 1.0), soft_iron=((0.0,) * 3,) * 3,
                      hard_iron=(0.0, 0.0, 0.0), bias=(0.0, 0.0, 0.0), noise=noise,
                      mounting=mounting)


#: Preset name -> builder(noise_nT, mounting_deg).
PRESETS = {"default": _default, "paper_a": _paper_a, "none": _none}


def preset(name, *, noise=None, mounting=(0.0, 0.0, 0.0)):
    """The error model of preset ``name``; ``noise`` (nT per axis) overrides its noise."""
    if name not in PRESETS:
        raise ValueError(f"Error preset must be one of {', '.join(PRESETS)}, not {name!r}")
    noise = DEFAULT_ERRORS.noise if noise is None else float(noise)
    return PRESETS[name](noise, tuple(float(m) for m in mounting))


def forward(model):
    """``(A, b)`` of an ErrorModel: ``B̂ = A R_mᵀ B_body + b`` (b in nT, sensor frame)."""
    a = model.matrix()
    return a, a @ np.array(model.hard_iron) + np.array(model.bias)
