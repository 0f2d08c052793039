"""Does the flight determine the calibration? The coverage gate, judged on the fit itself.

Paper B gates the fit on octants about the running centroid of the raw samples. On a UAV
pattern the centroid sits inside the cap of directions the flight covers, so all eight
octants about it fill although the field never pointed into half of the sphere; on a
tumble, a slow start leaves one octant short. The gate here asks two questions of the fit
instead:

- Observability: each parameter's dilution of precision (its standard deviation, in nT
  of field, per nT of noise per square root of the number of samples; K's entries count
  times the field), from the fit's own information. A parameter whose dilution exceeds
  :data:`~maglog.calib.eiv.UNDETERMINED_DOP` is undetermined by the coverage: the data pin
  it down only slowly, whatever the noise (a full tumble gives 1.7-4 for every parameter;
  a UAV's +-30 deg of roll and pitch about 60-70 for k33 and c3; a level flight leaves some
  parameters with no information at all, held to the prior).
- Directions about the fitted centre: the calibrated field's direction ``K b - c`` counted
  in the eight octants of the calibrated frame; the octants it never reached are attitudes
  the flight never showed the sensor.

The verdict accepts a flight when every parameter is determined. Paper B's check stays
available as :func:`maglog.calib.ellipsoid.octant_coverage`, and is reported beside it as
what the paper did.
"""

from dataclasses import dataclass

import numpy as np

from . import eiv
from .ellipsoid import octant_coverage
from .scalar import PARAMETERS


__all__ = ["CoverageVerdict", "judge_coverage", "octants_about_centre"]

#: An octant of the calibrated directions counts as reached with this many samples.
MIN_PER_OCTANT = 10


def octants_about_centre(vectors, *, min_per_octant=MIN_PER_OCTANT):
    """Samples per octant of the calibrated vectors (index 4 sx + 2 sy + sz, s = 1 where the
    component is >= 0), and how many octants hold ``min_per_octant`` or more."""
    vectors = np.asarray(vectors, dtype=float)
    signs = (vectors >= 0).astype(int)
    counts = np.bincount(4 * signs[:, 0] + 2 * signs[:, 1] + signs[:, 2], minlength=8)
    return counts, int(np.sum(counts >= min_per_octant))


@dataclass
class CoverageVerdict:
    accepted: bool
    dop: np.ndarray              # per parameter
    determined: np.ndarray       # bool per parameter
    held: np.ndarray             # bool per parameter: not determined at all (prior)
    octants: np.ndarray          # calibrated directions per octant about the fitted centre
    octants_reached: int
    paper_octants: np.ndarray    # paper B: raw samples per octant about the running centroid
    paper_filled: int
    min_per_octant: int

    @property
    def undetermined(self):
        return [n for n, d in zip(PARAMETERS, self.determined) if not d]

    @property
    def message(self):
        """One line: the verdict and why."""
        if self.accepted:
            return (f"accepted: the flight determines every parameter (dilution of precision "
                    f"{np.max(self.dop):.2g} at most, limit {eiv.UNDETERMINED_DOP:g}); the "
                    f"field reached {self.octants_reached} of 8 octants about the fitted "
                    "centre")
        held = [n for n, h in zip(PARAMETERS, self.held) if h]
        weak = [n for n in self.undetermined if n not in held]
        parts = []
        if weak:
            parts.append(f"{', '.join(weak)} undetermined (dilution of precision "
                         + ", ".join(f"{self.dop[PARAMETERS.index(n)]:.3g}" for n in weak)
                         + f" > {eiv.UNDETERMINED_DOP:g})")
        if held:
            parts.append(f"{', '.join(held)} not determined at all (held to the prior)")
        return (f"refused: the flight leaves {'; '.join(parts)}; the field reached only "
                f"{self.octants_reached} of 8 octants about the fitted centre: turn the "
                "sensor through more attitudes")

    def as_dict(self):
        return {"accepted": self.accepted, "message": self.message,
                "dilution_of_precision": dict(zip(PARAMETERS, self.dop.tolist())),
                "undetermined": self.undetermined,
                "held_to_prior": [n for n, h in zip(PARAMETERS, self.held) if h],
                "octants_about_fitted_centre": self.octants.tolist(),
                "octants_reached": self.octants_reached,
                "paper_b_octants_about_running_centroid": self.paper_octants.tolist(),
                "paper_b_octants_filled": self.paper_filled,
                "min_per_octant": self.min_per_octant}


def judge_coverage(result, b, *, min_per_octant=MIN_PER_OCTANT):
    """The verdict on a scalar fit ``result`` (``calibrate_scalar``'s) of samples ``b``
    (the samples it fitted are ``result.kept``)."""
    b = np.asarray(b, dtype=float)
    kept = np.ones(len(b), bool) if result.kept is None else result.kept
    vectors = b[kept] @ result.K.T - result.c
    counts, reached = octants_about_centre(vectors, min_per_octant=min_per_octant)
    paper = octant_coverage(b[kept], min_per_octant=min_per_octant)
    determined = np.asarray(result.determined, bool)
    held = np.asarray(result.held, bool)
    return CoverageVerdict(accepted=bool(determined.all() and not held.any()),
                           dop=np.asarray(result.dop, float), determined=determined,
                           held=held, octants=counts, octants_reached=reached,
                           paper_octants=paper.counts, paper_filled=paper.filled,
                           min_per_octant=min_per_octant)
