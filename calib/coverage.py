"""Does the flight determine the calibration? One definition, used by every verdict.

A parameter is **determined** when its 1-sigma, expressed in nT of field, is at most a
bound:

- the 1-sigma in nT of field: K's entries times the field (a change dK moves a calibrated
  field of magnitude F by up to F dK), c's as they are (nT);
- the bound: by default the noise of one sample, the RMS of the fit's own total-field
  residual. A parameter within it adds less to any calibrated sample than the sensor's
  own noise does; one beyond it is known less well than a single sample measures the
  field, and what it adds grows with the attitudes the flight did not show. The user may
  set a fixed accuracy target in nT instead (``maglog calibrate --determined-nT``).

The uncertainty falls as 1/sqrt(N), so a weak pattern flown longer can determine what a
short one cannot; the noise bound makes the rule independent of the noise level (with the
default bound it is: dilution of precision at most sqrt(N)). A parameter held to a prior
(no information at all) is never determined.

:func:`determine` applies the rule; :func:`judge_coverage` gives the verdict on a fit (the
scalar fit's or the ellipsoid's: both give K, c and their 1-sigma in the canonical form),
which the pipeline's ``success`` and ``verdict``, its report, ``maglog calibrate``'s printed
verdict and ``maglog run``'s parameters check all take from here. The calibrated field's
octants about the fitted centre and paper B's octants about the running centroid are
reported beside it as information only: octants do not say how well a parameter is known.
"""

from dataclasses import dataclass

import numpy as np

from .scalar import PARAMETERS


__all__ = ["RULE", "BOUND_RANGE_NT", "Determination", "check_bound", "field_sigma",
           "determine", "CoverageVerdict", "judge_coverage", "octants_about_centre"]

#: An octant of the calibrated directions counts as reached with this many samples.
MIN_PER_OCTANT = 10
#: The bounds a user may set, nT (inclusive): below 0.001 nT no magnetometer of this kind
#: resolves, above 10,000 nT a "calibration" is a fifth of the Earth's field off.
BOUND_RANGE_NT = (0.001, 10_000.0)
#: The rule, as the report states it.
RULE = ("a parameter is determined when its 1-sigma, in nT of field (K's entries times the "
        "field, c's in nT), is at most the bound: by default the noise of one sample (the "
        "RMS of the fit's total-field residual), so that no parameter adds more to a "
        "calibrated sample than the sensor's own noise; --determined-nT sets a fixed "
        "accuracy target instead. A parameter held to the prior is never determined")

#: Verdicts of a calibration.
DETERMINED, UNDETERMINED, FAILED = "determined", "undetermined", "failed"


def check_bound(value):
    """A user's bound in nT: a finite number within :data:`BOUND_RANGE_NT` (or None: the
    noise of one sample). Raises ValueError saying why not."""
    if value is None:
        return None
    try:
        number = float(value)
    except (TypeError, ValueError):
        raise ValueError(f"the bound on a determined parameter must be a number of nT, not "
                         f"{value!r}") from None
    low, high = BOUND_RANGE_NT
    if not low <= number <= high:        # NaN fails too
        raise ValueError(f"the bound on a determined parameter must be {low:g}..{high:,.0f} "
                         f"nT, not {value!r}")
    return number


def field_sigma(uncertainties, field_nt):
    """Each parameter's 1-sigma in nT of field: K's six entries times ``field_nt``, c's three
    as they are; infinite where there is none (not finite, or negative)."""
    sigma = np.asarray(uncertainties, dtype=float) * np.array([field_nt] * 6 + [1.0] * 3)
    return np.where(np.isfinite(sigma) & (sigma >= 0), sigma, np.inf)


@dataclass
class Determination:
    """Which parameters a fit determines, by :data:`RULE`."""
    sigma_nT: np.ndarray         # 1-sigma per parameter in nT of field (inf: none)
    held: np.ndarray             # bool per parameter: held to a prior (never determined)
    bound_nT: float
    bound_source: str            # "noise" (one sample's, from the fit) or "user"
    noise_nT: float              # the fit's residual RMS

    @property
    def determined(self):
        return np.isfinite(self.sigma_nT) & (self.sigma_nT <= self.bound_nT) & ~self.held

    @property
    def undetermined(self):
        return [n for n, d in zip(PARAMETERS, self.determined) if not d]

    @property
    def complete(self):
        return bool(self.determined.all())

    @property
    def bound_text(self):
        if self.bound_source == "user":
            return f"{self.bound_nT:.3g} nT (--determined-nT)"
        return f"{self.bound_nT:.3g} nT (one sample's noise: the fit's residual RMS)"

    def figures(self, names):
        """``name 1-sigma`` for each of ``names``, in nT of field."""
        return ", ".join(f"{n} " + ("none (held to the prior)" if self.held[i] else
                                    "none" if not np.isfinite(self.sigma_nT[i]) else
                                    f"{self.sigma_nT[i]:.3g} nT")
                         for n in names for i in [PARAMETERS.index(n)])

    def as_dict(self):
        return {"rule": RULE, "bound_nT": self.bound_nT, "bound_source": self.bound_source,
                "noise_nT": self.noise_nT,
                "sigma_nT": dict(zip(PARAMETERS, self.sigma_nT.tolist())),
                "determined": dict(zip(PARAMETERS, self.determined.tolist())),
                "undetermined": self.undetermined,
                "held_to_prior": [n for n, h in zip(PARAMETERS, self.held) if h]}


def determine(uncertainties, field_nt, noise_nt, *, held=None, bound_nt=None):
    """The :class:`Determination` of a fit whose canonical parameters (k11..c3) have 1-sigma
    ``uncertainties`` (K's dimensionless, c's in nT), for a field of ``field_nt`` and a
    residual RMS of ``noise_nt``; ``bound_nt`` a fixed bound (None: ``noise_nt``)."""
    bound = check_bound(bound_nt)
    held = np.zeros(len(PARAMETERS), bool) if held is None else np.asarray(held, bool)
    sigma = np.where(held, np.inf, field_sigma(uncertainties, field_nt))
    noise = float(noise_nt)
    return Determination(sigma_nT=sigma, held=held,
                         bound_nT=noise if bound is None else bound,
                         bound_source="noise" if bound is None else "user", noise_nT=noise)


def octants_about_centre(vectors, *, min_per_octant=MIN_PER_OCTANT):
    """Samples per octant of the calibrated vectors (index 4 sx + 2 sy + sz, s = 1 where the
    component is >= 0), and how many octants hold ``min_per_octant`` or more."""
    vectors = np.asarray(vectors, dtype=float)
    signs = (vectors >= 0).astype(int)
    counts = np.bincount(4 * signs[:, 0] + 2 * signs[:, 1] + signs[:, 2], minlength=8)
    return counts, int(np.sum(counts >= min_per_octant))


@dataclass
class CoverageVerdict:
    """The verdict on one calibration: ``verdict`` is "determined" (the fit converged and
    determines every parameter: ``success``), "undetermined" (it converged; the parameters
    in ``undetermined`` are not determined) or "failed" (the fit itself did not succeed:
    ``fit_message`` says why)."""
    determination: Determination
    fit_ok: bool
    fit_message: str
    octants: np.ndarray          # calibrated directions per octant about the fitted centre
    octants_reached: int
    paper_octants: np.ndarray    # paper B: raw samples per octant about the running centroid
    paper_filled: int
    min_per_octant: int

    @property
    def verdict(self):
        if not self.fit_ok:
            return FAILED
        return DETERMINED if self.determination.complete else UNDETERMINED

    @property
    def success(self):
        return self.verdict == DETERMINED

    accepted = success

    @property
    def undetermined(self):
        return self.determination.undetermined

    @property
    def determined(self):
        return self.determination.determined

    @property
    def held(self):
        return self.determination.held

    @property
    def message(self):
        """One line: the verdict and why."""
        d = self.determination
        if self.verdict == FAILED:
            return f"failed: {self.fit_message}"
        if self.verdict == DETERMINED:
            return (f"determined: the flight determines every parameter (1-sigma "
                    f"{np.max(d.sigma_nT):.2g} nT of field at most, bound {d.bound_text})")
        return (f"undetermined: the flight does not determine {', '.join(d.undetermined)} "
                f"(1-sigma {d.figures(d.undetermined)}; bound {d.bound_text}): not scored as "
                "calibrated; turn the sensor through more attitudes (about every axis) or "
                "fly the pattern longer")

    def as_dict(self):
        return {"verdict": self.verdict, "accepted": self.success, "message": self.message,
                "undetermined": self.undetermined,
                "held_to_prior": [n for n, h in zip(PARAMETERS, self.held) if h],
                **{k: v for k, v in self.determination.as_dict().items()
                   if k not in ("undetermined", "held_to_prior")},
                "octants_about_fitted_centre": self.octants.tolist(),
                "octants_reached": self.octants_reached,
                "paper_b_octants_about_running_centroid": self.paper_octants.tolist(),
                "paper_b_octants_filled": self.paper_filled,
                "min_per_octant": self.min_per_octant}


def judge_coverage(result, b, *, field_nt=None, bound_nt=None,
                   min_per_octant=MIN_PER_OCTANT):
    """The verdict on a fit ``result`` of samples ``b``: a scalar fit
    (``calibrate_scalar``'s; ``field_nt`` the field K's entries are judged against, by
    default the calibrated field's median magnitude) or an ellipsoid fit
    (``fit_ellipsoid``'s, which carries its own determination). The samples it fitted are
    ``result.kept`` when it says."""
    from .ellipsoid import EllipsoidResult, octant_coverage
    b = np.asarray(b, dtype=float)
    kept = getattr(result, "kept", None)
    kept = np.ones(len(b), bool) if kept is None else kept
    if isinstance(result, EllipsoidResult):
        determination = result.determination
        if bound_nt is not None or determination is None:
            determination = determine(result.uncertainties, result.field_nt, result.noise_nT,
                                      bound_nt=bound_nt)
        fit_ok = bool(np.all(np.isfinite(result.W)))
        fit_message = result.message
        vectors = (b[kept] - result.center) @ result.W.T
    else:
        vectors = b[kept] @ np.asarray(result.K).T - result.c
        if field_nt is None:        # the calibrated field's own magnitude
            field_nt = float(np.median(np.linalg.norm(vectors, axis=1)))
        held = getattr(result, "held", None)
        determination = determine(result.uncertainties, field_nt, result.rms, held=held,
                                  bound_nt=bound_nt)
        fit_ok = bool(result.success)
        fit_message = result.message
    counts, reached = octants_about_centre(vectors, min_per_octant=min_per_octant)
    paper = octant_coverage(b[kept], min_per_octant=min_per_octant)
    return CoverageVerdict(determination=determination, fit_ok=fit_ok,
                           fit_message=fit_message, octants=counts, octants_reached=reached,
                           paper_octants=paper.counts, paper_filled=paper.filled,
                           min_per_octant=min_per_octant)
