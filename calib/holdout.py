"""Held-out scoring: how a calibration does on samples it did not fit.

A least-squares fit can hardly end above the noise on the samples it fitted; a survey
applies its parameters to the rest of the flight and to the next one. :func:`held_out`
splits a flight in two halves in time, fits each half and scores the other, and compares
the total-field RMS on unseen samples with the in-sample RMS of the fit of the whole flight
on the same samples. A ratio near one says the parameters carry over; a large one says
one half's attitudes do not determine what the other half needs (a calibration pattern
in one half, level survey lines in the other).
"""

from dataclasses import dataclass, field

import numpy as np


__all__ = ["HeldOut", "held_out"]


@dataclass
class HeldOut:
    rms_held_out: float          # nT, over both halves, each scored by the other's fit
    rms_in_sample: float         # nT, the whole flight's fit on the same samples
    samples: int                 # samples scored
    halves: list = field(default_factory=list)   # per half: span, fitted, scored, rms
    message: str = ""

    @property
    def ratio(self):
        return self.rms_held_out / self.rms_in_sample if self.rms_in_sample > 0 else np.nan

    def as_dict(self):
        return {"rms_held_out_nT": self.rms_held_out, "rms_in_sample_nT": self.rms_in_sample,
                "ratio": self.ratio, "samples": self.samples, "halves": self.halves,
                "message": self.message}


def held_out(t, b, r, keep, fit, full_residual):
    """Two-fold held-out scoring in time. ``fit(train_mask)`` fits the samples of the mask
    and returns a function ``residual(index_mask) -> |calibrated| - r`` on those samples
    (or raises ``ValueError`` saying why it cannot fit); ``full_residual`` is the residual
    of the whole flight's fit per sample; ``keep`` the samples that count (screened in and
    not rejected by the robust loss). Returns a :class:`HeldOut`, or None with the reason
    when a half has too few samples to fit."""
    n = len(b)
    order = np.argsort(t, kind="stable") if np.all(np.isfinite(t)) else np.arange(n)
    first = np.zeros(n, bool)
    first[order[: n // 2]] = True
    squares, in_squares, scored, halves = 0.0, 0.0, 0, []
    for train, test, name in ((first, ~first, "first"), (~first, first, "second")):
        train_mask, test_mask = train & keep, test & keep
        if train_mask.sum() < 10 or test_mask.sum() < 1:
            return None, f"the {name} half has too few samples to fit ({int(train_mask.sum())})"
        try:
            residual = fit(train_mask)
        except (ValueError, np.linalg.LinAlgError) as error:
            return None, f"the {name} half alone cannot be fitted: {error}"
        e = residual(test_mask)
        if not np.all(np.isfinite(e)):
            return None, f"the {name} half's fit gives no finite calibration of the other"
        e_full = full_residual[test_mask]
        squares += float(e @ e)
        in_squares += float(e_full @ e_full)
        scored += int(test_mask.sum())
        span = t[train] if np.all(np.isfinite(t)) else np.flatnonzero(train)
        halves.append({"fitted": name, "fitted_span": [float(np.min(span)), float(np.max(span))],
                       "fitted_samples": int(train_mask.sum()),
                       "scored_samples": int(test_mask.sum()),
                       "rms_held_out_nT": float(np.sqrt(e @ e / test_mask.sum())),
                       "rms_in_sample_nT": float(np.sqrt(e_full @ e_full / test_mask.sum()))})
    result = HeldOut(rms_held_out=float(np.sqrt(squares / scored)),
                     rms_in_sample=float(np.sqrt(in_squares / scored)), samples=scored,
                     halves=halves)
    first_half, second_half = halves
    result.message = (
        f"fitted on one half of the flight, scored on the other (both ways): "
        f"{result.rms_held_out:.3g} nT RMS on samples the fit did not see, "
        f"{result.rms_in_sample:.3g} nT in-sample (ratio {result.ratio:.3f}); the first "
        f"half's fit on the second {first_half['rms_held_out_nT']:.3g} nT, the second's on "
        f"the first {second_half['rms_held_out_nT']:.3g} nT")
    return result, ""
