"""The three papers' headline results beside ours, for the report (:data:`PAPERS` cites them).

- Paper A (Li et al. 2018): Table 1, the estimated P and O, beside the scenario's truth and
  the run's recovered parameters read the same way; Figure 7 (raw magnitude, the cesium
  reference, the compensated magnitude) from the run's data, with the raw peak-to-peak
  beside their 53,700 nT.
- Paper B (Guan and Wang): the mean heading error against the number of samples per octant
  (their Fig. 5; they claim under 1°), on flights made for it: samples taken by their
  octant strategy from a tumbling flight, an ellipsoid fit (calib.ellipsoid), headings of a
  separate level flight from the calibrated field (calib.heading) against its true heading.
- Paper C (Li, Zhang and Yang): scalar Kalman filter, Allan analysis before and after, the
  change in quantisation noise and bias instability beside their −82.8 % and −77.9 %, on
  series made for it (the approach of bench/calib/allan_paper_c.py) and, when the run's
  flight has a static phase long enough, on the run's data.

``paper_results(run, truth, out_dir)`` writes papers.md, papers.json and the PNGs into
``out_dir`` and returns a :class:`PapersResult`. Everything is seeded.
"""

import dataclasses
import datetime
import json
import math
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from ..calib.ellipsoid import fit_ellipsoid
from ..calib.pipeline import jsonable as _jsonable
from ..calib.heading import declination, tilt_compensated_heading, wrap_degrees
from ..calib.noise import BIAS_INSTABILITY_FACTOR, allan_deviation, kalman_filter, \
    simulate_noise
from ..sim.stimulus.scenario import DEFAULT_ERRORS, ErrorModel, make_flight
from .summary import recovered_kc


__all__ = ["PAPERS", "citation", "PAPER_A", "PAPER_B", "PAPER_C", "PapersResult",
           "paper_results", "select_by_octant", "paper_a", "paper_b", "paper_c"]

#: The three papers as the reports cite them. Paper A prints its reference on its first
#: page. The copies of papers B and C the project holds begin at the authors' names and
#: affiliations: their title, journal and year are not in them, so none is given here and
#: the citation says what the paper is about instead of inventing them.
PAPERS = {
    "A": {"short": "Li et al. 2018",
          "authors": "Li C.L., Wang S.C., Li T., Zhang Z.Y.",
          "title": "UAV based regional geomagnetic field test and correction technology",
          "venue": "Electronics Optics & Control 25(7):14–18", "year": 2018,
          "doi": "10.3969/j.issn.1671-637X.2018.07.003",
          "affiliation": "Rocket Force University of Engineering, Xi'an",
          "subject": "a UAV's data logger (FPGA, SDRAM buffer, SD card, FAT32) and a "
                     "particle-swarm calibration of a strapdown three-axis magnetometer "
                     "against an optically pumped scalar magnetometer"},
    "B": {"short": "Guan and Wang",
          "authors": "Guan Q.P., Wang T.M.", "title": None, "venue": None, "year": None,
          "doi": None,
          "affiliation": "Department of Mechanical Engineering and Automation, Beihang "
                         "University, Beijing",
          "subject": "ellipsoid-fit calibration of a small UAV's magnetic compass, with a "
                     "dynamic check of the calibration's progress by octant coverage"},
    "C": {"short": "Li, Zhang and Yang",
          "authors": "Li R., Zhang Y.F., Yang W.W.", "title": None, "venue": None,
          "year": None, "doi": None,
          "affiliation": "Huainan Vocational and Technical College, and Anhui University "
                         "of Science and Technology, Huainan",
          "subject": "LS-KF compensation of an electronic compass (a least-squares circle "
                     "fit for the hard iron, then a scalar Kalman filter), judged by Allan "
                     "variance"},
}


def citation(key):
    """Paper ``key``'s (A, B or C) reference as one line of plain text."""
    paper = PAPERS[key]
    if paper["title"]:
        text = (f"{paper['authors']} \u201c{paper['title']}.\u201d {paper['venue']}, "
                f"{paper['year']}.")
        return text + (f" doi:{paper['doi']}." if paper["doi"] else "")
    return (f"{paper['authors']} ({paper['affiliation']}): {paper['subject']}. Title, "
            "journal and year are not printed in the copy this project holds.")

#: Paper A's Table 1 (P row by row, O in nT) and Figure 7's raw peak-to-peak.
PAPER_A = {"P": [[1.0117, 0.0079, 0.0184], [0.0028, 1.0010, -0.0119],
                 [-0.0067, -0.0166, 0.9972]],
           "O_nT": [1576.1, -604.3794, -41.7471], "raw_peak_to_peak_nT": 53_700.0}
#: Paper B's claim: mean heading error under 1° with octant coverage.
PAPER_B = {"claim_mean_heading_error_deg": 1.0}
#: Paper C's figures (X axis, 0.1 s sampling).
PAPER_C = {"rate_hz": 10.0,
           "before": {"mean": 0.0022, "variance": 1.3717, "quantisation": 0.000935,
                      "bias_instability": 0.160291},
           "after": {"mean": -0.0075, "variance": 0.0129, "quantisation": 0.000161,
                     "bias_instability": 0.035448},
           "change_percent": {"quantisation": -82.8, "bias_instability": -77.9}}

#: Paper B: samples per octant on the curve, trials per point, seconds of the level flight
#: whose headings are scored; the noise levels: the scenario's magnetometer, and a
#: HMC5883L-class compass (its datasheet's noise floor, 2 mG = 200 nT), the kind paper B
#: calibrates.
B_COUNTS = (2, 3, 5, 8, 12, 20, 30, 50, 100)
B_COUNTS_QUICK = (2, 5, 12, 30)
B_TRIALS, B_TRIALS_QUICK = 30, 8
B_SCORE_SECONDS, B_SCORE_SECONDS_QUICK = 120.0, 20.0
B_COMPASS_NOISE_NT = 200.0
B_RATE_HZ = 20.0
#: Paper C: minutes per synthetic series and series (seeds) per figure.
C_MINUTES, C_MINUTES_QUICK = 60.0, 10.0
C_SEEDS, C_SEEDS_QUICK = 10, 1
#: Phases of the run's flight taken as static (sitting on the ground), and the shortest
#: static stretch worth an Allan analysis (at 20 Hz: 30 s, a decade and a half of tau).
#: (a name containing any of these words)
STATIC_PHASES = ("ground", "static", "idle", "preflight", "standby", "warm", "power", "fix")
STATIC_MIN_SAMPLES = 600


@dataclass
class PapersResult:
    markdown: Path              # papers.md
    json: Path                  # papers.json
    plots: dict                 # name -> Path of each PNG
    data: dict = field(default_factory=dict)

    def as_dict(self):
        return _jsonable({"markdown": str(self.markdown), "json": str(self.json),
                          "plots": {k: str(v) for k, v in self.plots.items()}, **self.data})


def _figure(size):
    """(plt, fig, ax): one panel at a report figure's size, dpi and layout."""
    from ..calib.plotting import figure
    return figure(size)


def _save(plt, fig, path):
    from ..calib.plotting import save
    return save(plt, fig, path)


def _matrix_rows(m, fmt):
    return " / ".join(" ".join(format(v, fmt) for v in row) for row in np.asarray(m))


# -- Paper A --------------------------------------------------------------------------------

def _nearest_rotation(m, target):
    """The rotation X minimising |m X - target| (orthogonal Procrustes, det +1)."""
    u, _, vt = np.linalg.svd(m.T @ target)
    d = np.sign(np.linalg.det(u @ vt))
    return u @ np.diag([1.0, 1.0, d]) @ vt


def paper_a(run, truth, out_dir):
    """Table 1 and Figure 7 (see the module docstring). The scalar model recovers
    ``A^-1 = U K`` only up to the rotation U (paper A, eq. 6-9): the sensor-frame offset
    ``b = K^-1 c`` is fully determined, the matrix only as ``K^-1 U^T``; ours is shown with
    U = I (upper triangular, what calib reports as P) and with the U that brings it nearest
    the truth's A (U taken from the truth, said so)."""
    out = {"paper": PAPER_A}
    lines = [f"## Paper A ({PAPERS['A']['short']}): Table 1 and Figure 7", ""]
    if run is None:
        lines += ["Not computed: the calibration failed (see the summary).", ""]
        return out, lines, {}
    k, c, sigma = recovered_kc(run)
    p_ours = np.linalg.inv(k)
    o_ours = p_ours @ c
    rows = [("paper, Table 1 (P, O)", np.array(PAPER_A["P"]), np.array(PAPER_A["O_nT"]))]
    errors = (truth or {}).get("errors") or {}
    a_true = b_true = None
    if "A" in errors and "b" in errors:
        a_true, b_true = np.array(errors["A"], float), np.array(errors["b"], float)
        rows.append((f"truth: the scenario's A, b (preset {errors.get('preset', '?')})",
                     a_true, b_true))
    rows.append(("ours: K^-1, K^-1 c (U = I)", p_ours, o_ours))
    if a_true is not None:
        rot = _nearest_rotation(p_ours, a_true)
        p_turned = p_ours @ rot
        angle = float(np.degrees(np.arccos(np.clip((np.trace(rot) - 1) / 2, -1, 1))))
        rows.append((f"ours: K^-1 U^T, U from the truth ({angle:.2f}° rotation)",
                     p_turned, o_ours))
        rows.append(("ours - truth", p_turned - a_true, o_ours - b_true))
        out["truth"] = {"A": a_true, "b_nT": b_true, "preset": errors.get("preset")}
        out["ours_rotated"] = {"P": p_turned, "rotation_deg": angle}
        out["difference"] = {"P": p_turned - a_true, "O_nT": o_ours - b_true,
                             "max_abs_P": float(np.max(np.abs(p_turned - a_true))),
                             "max_abs_O_nT": float(np.max(np.abs(o_ours - b_true)))}
        out["paper_minus_truth"] = {"P": np.array(PAPER_A["P"]) - a_true,
                                    "O_nT": np.array(PAPER_A["O_nT"]) - b_true}
    out["ours"] = {"P": p_ours, "O_nT": o_ours, "K": k, "c_nT": c,
                   "method": run.method}
    if a_true is not None:
        same = max(float(np.max(np.abs(np.array(PAPER_A["P"]) - a_true))),
                   float(np.max(np.abs(np.array(PAPER_A["O_nT"]) - b_true))) / 1000.0)
        out["truth_is_table_1"] = same < 1e-6
        note = ("The scenario's sensor is Table 1 itself (preset paper_a reads P as A and O "
                "as b: sim/stimulus/errors.py), so its row repeats the paper's." if same < 1e-6
                else "The scenario's sensor is not Table 1 (preset "
                     f"{errors.get('preset', '?')}): compare the reading, not the numbers.")
    else:
        note = "The truth gives no A and b: ours is shown beside the paper's only."
    header = "| | " + " | ".join(f"P{i}{j}" for i in range(1, 4) for j in range(1, 4)) + \
        " | O1 (nT) | O2 (nT) | O3 (nT) |"
    lines += ["The sensor reads `b = P B_e + O` (our reading of Table 1: P = A, O = b of "
              "eq. 1-5; the scalar check recovers A only up to a rotation, so ours is shown "
              "as K⁻¹ and turned onto the truth's A by the rotation U the check cannot see).",
              "", note, "", header, "|---|" + "---:|" * 12]
    for label, p, o in rows:
        lines.append(f"| {label} | " + " | ".join(f"{v:.4f}" for v in np.ravel(p)) + " | "
                     + " | ".join(f"{v:.1f}" for v in o) + " |")
    lines.append("")
    raw = np.linalg.norm(run.b, axis=1)
    comp = run.calibrated
    ptp = {"raw_nT": float(np.ptp(raw)), "compensated_nT": float(np.ptp(comp)),
           "reference_nT": float(np.ptp(run.r)),
           "residual_rms_nT": float(np.sqrt(np.mean(run.residual ** 2)))}
    out["figure7"] = ptp
    lines += [f"Figure 7 from the run ({run.log_name}, {len(raw)} samples, reference: "
              f"{run.reference}): raw |B| peak-to-peak {ptp['raw_nT']:,.0f} nT (paper: "
              f"{PAPER_A['raw_peak_to_peak_nT']:,.0f} nT), compensated "
              f"{ptp['compensated_nT']:,.1f} nT, reference {ptp['reference_nT']:,.1f} nT; "
              f"compensated − reference {ptp['residual_rms_nT']:.2f} nT RMS. Theirs includes "
              "the strong interference the paper reports; the scenario's sensor has only "
              "the constant A and b of eq. 1-5, so ours is the hard and soft iron seen as "
              "the aircraft turns.", "",
              "![Figure 7](paper_a_figure7.png)", ""]
    from ..calib.plotting import WIDE, log_time_axis
    plt, fig, ax = _figure(WIDE)
    x, time_label = log_time_axis(run.t, bool(np.all(np.isfinite(run.parsed.mag.t))))
    ax.plot(x, raw, lw=0.6, color="tab:green", label="raw |B| (triaxial)")
    # The paper's colours; the compensated trace wide below, the reference thin and
    # dashed on top, so that both show where they coincide.
    ax.plot(x, comp, lw=2.0, color="tab:blue", label="compensated |B|")
    ax.plot(x, run.r, lw=0.9, ls="--", color="tab:red", label="reference (cesium)", zorder=3)
    ax.set_xlabel(time_label)
    ax.set_ylabel("total field (nT)")
    ax.set_title("Paper A, Figure 7 style: the run's data")
    ax.legend(loc="upper right", fontsize=8)
    plots = {"paper_a_figure7": _save(plt, fig, Path(out_dir) / "paper_a_figure7.png")}
    return out, lines, plots


# -- Paper B --------------------------------------------------------------------------------

def select_by_octant(b, per_octant):
    """Paper B's coverage strategy: the samples in order, each placed in its octant about
    the centroid of the samples taken so far (as calib.ellipsoid.octant_coverage counts);
    an octant holding ``per_octant`` takes no more. Returns the indices taken when all
    eight are full, or None when the samples ran out first."""
    b = np.asarray(b, dtype=float)
    counts = np.zeros(8, dtype=int)
    taken = []
    total = np.zeros(3)
    for i, sample in enumerate(b):
        centroid = total / len(taken) if taken else sample
        s = sample >= centroid
        octant = 4 * int(s[0]) + 2 * int(s[1]) + int(s[2])
        if counts[octant] >= per_octant:
            continue
        counts[octant] += 1
        taken.append(i)
        total += sample
        if np.all(counts >= per_octant):
            return np.array(taken)
    return None


def _error_model(truth, noise):
    """The scenario's sensor errors (A, b; no mounting: paper B calibrates the sensor) at
    ``noise`` nT, or the project's default model when there is no truth."""
    errors = (truth or {}).get("errors") or {}
    if "A" in errors and "b" in errors:
        return ErrorModel(non_orthogonality=tuple(map(tuple, errors["A"])), scale=(1, 1, 1),
                          soft_iron=((0, 0, 0),) * 3, hard_iron=(0, 0, 0),
                          bias=tuple(errors["b"]), noise=float(noise))
    return dataclasses.replace(DEFAULT_ERRORS, noise=float(noise), mounting=(0.0, 0.0, 0.0))


def _sqrtm_spd(m):
    values, vectors = np.linalg.eigh(m)
    return (vectors * np.sqrt(values)) @ vectors.T


def _heading_errors(model, counts, trials, score_seconds, seed):
    """Per count and trial: the mean |heading error| against the true heading, and the
    mean |difference| from the headings of the ellipsoid an unlimited number of noiseless
    samples would give (W = (A^-T A^-1)^(1/2), the true offset): the part of the error
    that comes from the fit's scatter (NaN where no fit)."""
    score = make_flight(coverage="uav", seconds=score_seconds, rate=B_RATE_HZ, errors=model,
                        seed=seed * 7919 + 1)
    decl = declination(score.lat, score.lon, score.altitude_m, score.start)
    field_nt = float(np.mean(score.total))
    truth_deg = np.degrees(score.heading) % 360.0
    a = model.matrix()
    offset = a @ np.array(model.hard_iron) + np.array(model.bias)
    inverse = np.linalg.inv(a)
    w_limit = _sqrtm_spd(inverse.T @ inverse)
    limit = tilt_compensated_heading((score.b_meas - offset) @ w_limit.T, score.roll,
                                     score.pitch) + decl
    limit_error = float(np.mean(np.abs(wrap_degrees(limit - truth_deg))))
    total = np.full((len(counts), trials), np.nan)
    scatter = np.full((len(counts), trials), np.nan)
    for trial in range(trials):
        longest = max(counts)
        pool = make_flight(coverage="full", seconds=(8 * longest * 4 + 400) / B_RATE_HZ,
                           rate=B_RATE_HZ, errors=model, seed=seed * 7919 + 100 + trial)
        for i, n in enumerate(counts):
            taken = select_by_octant(pool.b_meas, n)
            if taken is None:
                continue
            fit = fit_ellipsoid(pool.b_meas[taken], field_nt, min_per_octant=n,
                                gate="paper")
            if not fit.success:
                fit = fit_ellipsoid(pool.b_meas[taken], field_nt, method="constrained",
                                    min_per_octant=n, gate="paper")
            if not fit.success:
                continue
            calibrated = (score.b_meas - fit.center) @ fit.W.T
            heading = tilt_compensated_heading(calibrated, score.roll, score.pitch) + decl
            total[i, trial] = float(np.mean(np.abs(wrap_degrees(heading - truth_deg))))
            scatter[i, trial] = float(np.mean(np.abs(wrap_degrees(heading - limit))))
    return total, scatter, limit_error


def _stats(values):
    """Mean and standard deviation over the trials per count (NaN: no fit at all)."""
    with np.errstate(all="ignore"):
        good = np.isfinite(values)
        n = good.sum(axis=1)
        mean = np.where(n > 0, np.nansum(values, axis=1) / np.maximum(n, 1), np.nan)
        std = np.array([np.std(row[ok]) if ok.any() else np.nan
                        for row, ok in zip(values, good)])
    return mean, std, n


def paper_b(truth, out_dir, *, seed=0, quick=False):
    counts = B_COUNTS_QUICK if quick else B_COUNTS
    trials = B_TRIALS_QUICK if quick else B_TRIALS
    seconds = B_SCORE_SECONDS_QUICK if quick else B_SCORE_SECONDS
    errors = (truth or {}).get("errors") or {}
    scenario_noise = float(errors.get("noise_nT", DEFAULT_ERRORS.noise))
    levels = [("scenario magnetometer", scenario_noise),
              ("HMC5883L-class compass", B_COMPASS_NOISE_NT)]
    claim = PAPER_B["claim_mean_heading_error_deg"]
    curves = []
    for k, (label, noise) in enumerate(levels):
        total, scatter, limit = _heading_errors(_error_model(truth, noise), counts, trials,
                                                seconds, seed * 10 + k)
        mean, std, fits = _stats(total)
        scatter_mean, scatter_std, _ = _stats(scatter)
        holds = bool(np.all(np.isfinite(mean)) and np.all(mean < claim))
        curves.append({"label": label, "noise_nT": noise, "counts": list(counts),
                       "mean_error_deg": mean, "std_error_deg": std,
                       "fit_scatter_deg": scatter_mean, "fit_scatter_std_deg": scatter_std,
                       "unlimited_samples_error_deg": limit,
                       "fits": fits, "trials": trials, "claim_holds": holds})
    source = "the scenario's A, b" if "A" in errors else "the project's default error model"
    lines = [f"## Paper B ({PAPERS['B']['short']}): mean heading error against samples per "
             "octant (their Fig. 5)", "",
             f"Flights made for it (sim.stimulus.scenario.make_flight, seed {seed}): samples "
             "taken by the paper's octant strategy (each octant about the running centroid "
             "takes at most n, fit when all eight are full) from a tumbling flight (full sphere, "
             f"{B_RATE_HZ:g} Hz), an algebraic ellipsoid fit (calib.ellipsoid, gated on the "
             "same count), then the tilt-compensated true heading (calib.heading, IGRF "
             f"declination) of a separate {seconds:g} s level flight (±30° roll and pitch, "
             f"four turns) against its true heading. Sensor errors: {source}, no mounting "
             f"rotation; {trials} trials per point (independent tumbling flights).", "",
             "Two figures per point: the mean |heading error| against the true heading "
             "(the paper's measure), and the fit's scatter: the mean |difference| from the "
             "headings of the ellipsoid unlimited noiseless samples would give (what more "
             "samples can still improve).", "",
             "| samples per octant | " + " | ".join(str(n) for n in counts) + " |",
             "|---|" + "---:|" * len(counts)]
    for curve in curves:
        for key, what in (("mean_error_deg", "heading error"),
                          ("fit_scatter_deg", "fit scatter")):
            spread = curve["std_error_deg" if key == "mean_error_deg" else
                           "fit_scatter_std_deg"]
            cells = [f"{m:.3f} ± {s:.3f}" if np.isfinite(m) else "no fit"
                     for m, s in zip(curve[key], spread)]
            lines.append(f"| {curve['label']} ({curve['noise_nT']:g} nT), {what} (°) | "
                         + " | ".join(cells) + " |")
    lines.append("")
    for curve in curves:
        verdict = "holds" if curve["claim_holds"] else "does not hold"
        lines.append(f"- {curve['label']} ({curve['noise_nT']:g} nT noise): the claim "
                     f"(mean heading error < {claim:g}° at every count) {verdict}: "
                     f"{curve['mean_error_deg'][0]:.3f}° at {counts[0]} per octant, "
                     f"{curve['mean_error_deg'][-1]:.3f}° at {counts[-1]}; the fit's "
                     f"scatter {curve['fit_scatter_deg'][0]:.3f}° → "
                     f"{curve['fit_scatter_deg'][-1]:.3f}°; with unlimited samples "
                     f"{curve['unlimited_samples_error_deg']:.3f}°.")
    a = _error_model(truth, 0.0).matrix()
    u, _, vt = np.linalg.svd(a)
    rotation = float(np.degrees(np.arccos(np.clip((np.trace(u @ vt) - 1) / 2, -1, 1))))
    lines += ["- What unlimited samples leave is the ellipsoid method's own limit: its "
              "symmetric W cannot undo the rotation part of A (the axes' non-orthogonality; "
              f"here a rotation of {rotation:.2f}°), and a noisy compass's single readings "
              "scatter too.", "",
              "![Paper B](paper_b_heading.png)", ""]
    from ..calib.plotting import NARROW, plain_log_axis
    plt, fig, ax = _figure(NARROW)
    plotted = [c for c in curves if np.isfinite(c["mean_error_deg"]).any()]
    for curve in plotted:
        line = ax.errorbar(counts, curve["mean_error_deg"], yerr=curve["std_error_deg"],
                           marker="o", capsize=3, lw=1,
                           label=f"{curve['label']} ({curve['noise_nT']:g} nT)")
        ax.plot(counts, curve["fit_scatter_deg"], ls=":", marker=".",
                color=line[0].get_color(), label=f"{curve['label']}: fit scatter")
    ax.axhline(claim, color="k", ls="--", lw=0.8, label="paper B's claim (1°)")
    ax.set_xscale("log")
    if plotted:
        ax.set_yscale("log")
    else:
        ax.text(0.5, 0.5, "no fit at any count", transform=ax.transAxes, ha="center")
    plain_log_axis(ax, "both" if plotted else "x")
    ax.set_xlabel("samples per octant")
    ax.set_ylabel("mean heading error (deg)")
    ax.set_title("Paper B, Fig. 5 style: heading error vs samples per octant")
    ax.legend(fontsize=8)
    plots = {"paper_b_heading": _save(plt, fig, Path(out_dir) / "paper_b_heading.png")}
    return {"paper": PAPER_B, "curves": curves, "seed": seed, "error_model": source,
            "unseen_rotation_deg": rotation}, \
        lines, plots


# -- Paper C --------------------------------------------------------------------------------

def _single_point(result):
    """The reads a reduction like the paper's comes from: Q from the first point of the
    curve, B from its minimum, whatever the slope there."""
    best = int(np.argmin(result.deviation))
    return {"quantisation": float(result.deviation[0] * result.taus[0] / np.sqrt(3)),
            "bias_instability": float(result.deviation[best] / BIAS_INSTABILITY_FACTOR)}


def _slope_regions(result):
    """The terms where the curve has their slope (NaN: not resolved)."""
    return {name: result.terms[name].value for name in ("quantisation", "bias_instability")}


def _change(before, after):
    if not (np.isfinite(before) and np.isfinite(after)) or before == 0:
        return math.nan
    return 100.0 * (after - before) / before


def _paper_c_signal(n, rate):
    """The paper's "before" Q and B, plus white noise bringing the variance to theirs
    (bench/calib/allan_paper_c.py's ``paper_coefficients``)."""
    q, b = PAPER_C["before"]["quantisation"], PAPER_C["before"]["bias_instability"]
    tau0 = 1 / rate
    k = np.arange(1, n)
    h = np.concatenate(([1.0], np.cumprod((k - 0.5) / k)))
    rest = b ** 2 * np.sum(h ** 2) + 2 * q ** 2 / tau0 ** 2
    white = math.sqrt(max(PAPER_C["before"]["variance"] - rest, 0.0) * tau0)
    return {"quantisation": q, "random_walk": white, "bias_instability": b}


def _filter_and_analyse(y, rate, q_over_r):
    r = float(np.var(y))
    filtered, _ = kalman_filter(y, q=q_over_r * r, r=r, p0=1.0)
    before, after = allan_deviation(y, rate), allan_deviation(filtered, rate)
    return {"variance": (float(np.var(y)), float(np.var(filtered))),
            "single_point": (_single_point(before), _single_point(after)),
            "slope_regions": (_slope_regions(before), _slope_regions(after))}, before, after


def _static_series(run, truth):
    """The run's calibrated x component over its static phase, or (None, why)."""
    if run is None:
        return None, "the calibration failed"
    phases = ((truth or {}).get("flight") or {}).get("phases") or []
    static = [p for p in phases
              if any(word in str(p.get("name", "")).lower() for word in STATIC_PHASES)]
    if not static:
        names = ", ".join(str(p.get("name")) for p in phases) or "none"
        return None, f"the run's flight has no static phase (phases: {names})"
    try:
        start = datetime.datetime.fromisoformat(str(truth.get("timestamp")))
    except ValueError:
        return None, "the truth gives no timestamp of t = 0 to place the phases in the log"
    midnight = start.replace(hour=0, minute=0, second=0, microsecond=0)
    t = run.t - (start - midnight).total_seconds()      # the log's seconds of day
    found = []
    for phase in static:
        inside = (t >= phase["start_s"]) & (t <= phase["end_s"])
        if inside.sum() >= STATIC_MIN_SAMPLES:
            return run.vectors[inside, 0], f"phase {phase['name']}, {int(inside.sum())} samples"
        found.append(f"{phase['name']} {phase['start_s']:g}-{phase['end_s']:g} s: "
                     f"{int(inside.sum())}")
    return None, (f"logged samples in the static phases ({'; '.join(found)}) are fewer than "
                  f"the {STATIC_MIN_SAMPLES} an Allan analysis needs")


def paper_c(run, truth, out_dir, *, seed=0, quick=False):
    rate = PAPER_C["rate_hz"]
    minutes = C_MINUTES_QUICK if quick else C_MINUTES
    seeds = C_SEEDS_QUICK if quick else C_SEEDS
    ratio = PAPER_C["after"]["variance"] / PAPER_C["before"]["variance"]
    gain = 2 * ratio / (1 + ratio)              # steady state: g / (2 - g) = ratio
    q_over_r = gain ** 2 / (1 - gain)
    n = int(round(minutes * 60 * rate))
    truth_terms = _paper_c_signal(n, rate)
    runs, first = [], None
    for k in range(seeds):
        y = simulate_noise(n, rate, rng=seed * 1000 + k, **truth_terms)
        figures, before, after = _filter_and_analyse(y, rate, q_over_r)
        runs.append(figures)
        if first is None:
            first = (before, after)
    changes = {}
    for method in ("single_point", "slope_regions"):
        for term in ("quantisation", "bias_instability"):
            values = np.array([_change(r[method][0][term], r[method][1][term]) for r in runs])
            good = values[np.isfinite(values)]
            changes[f"{method}.{term}"] = {
                "mean": float(np.mean(good)) if good.size else math.nan,
                "std": float(np.std(good)) if good.size else math.nan,
                "resolved_in": int(good.size), "of": seeds}
    variance = (float(np.mean([r["variance"][0] for r in runs])),
                float(np.mean([r["variance"][1] for r in runs])))
    resolved = {term: tuple(int(sum(np.isfinite(r["slope_regions"][stage][term])
                                    for r in runs)) for stage in (0, 1))
                for term in ("quantisation", "bias_instability")}
    static, why = _static_series(run, truth)
    on_run = None
    if static is not None:
        step = float(np.median(np.diff(run.t)))
        run_rate = 1.0 / step if step > 0 else rate
        figures, _, _ = _filter_and_analyse(static - np.mean(static), run_rate, q_over_r)
        on_run = {"source": why, "rate_hz": run_rate, **figures,
                  "change_percent": {
                      f"{m}.{t}": _change(figures[m][0][t], figures[m][1][t])
                      for m in ("single_point", "slope_regions")
                      for t in ("quantisation", "bias_instability")}}

    def cell(key):
        ch = changes[key]
        if not ch["resolved_in"]:
            return "not resolved"
        spread = f" ± {ch['std']:.1f}" if seeds > 1 else ""
        part = "" if ch["resolved_in"] == ch["of"] else f" ({ch['resolved_in']} of {ch['of']})"
        return f"{ch['mean']:+.1f} %{spread}{part}"

    paper = PAPER_C["change_percent"]
    lines = [f"## Paper C ({PAPERS['C']['short']}): Kalman filter and Allan deviation", "",
             f"Series made for it ({seeds} × {minutes:g} min at {rate:g} Hz, seeds "
             f"{seed * 1000}..{seed * 1000 + seeds - 1}; calib.noise.simulate_noise): the "
             f"paper's \"before\" quantisation noise {truth_terms['quantisation']:g} and bias "
             f"instability {truth_terms['bias_instability']:g}, plus white noise "
             f"{truth_terms['random_walk']:.3g} bringing the variance to their 1.3717 "
             "(the approach of bench/calib/allan_paper_c.py). Filter: calib.noise."
             "kalman_filter, B = H = 1, P0 = 1, R = the series' variance, Q chosen so that "
             "the steady-state gain lowers white noise's variance by their ratio "
             f"0.0129 / 1.3717 (Q/R = {q_over_r:.3g}, time constant "
             f"{(1 - gain) / gain / rate:.1f} s).", "",
             "| change through the filter | quantisation noise | bias instability |",
             "|---|---:|---:|",
             f"| paper C | {paper['quantisation']:+.1f} % | {paper['bias_instability']:+.1f} % |",
             f"| ours, read as the paper likely did (Q from the first point, B from the "
             f"minimum) | {cell('single_point.quantisation')} | "
             f"{cell('single_point.bias_instability')} |",
             f"| ours, each term where the curve has its slope (IEEE 952) | "
             f"{cell('slope_regions.quantisation')} | "
             f"{cell('slope_regions.bias_instability')} |", "",
             f"Variance before → after: {variance[0]:.4g} → {variance[1]:.4g} (paper: "
             "1.3717 → 0.0129). The filter (unity gain at DC) lowers the Allan curve only "
             f"below its time constant ({(1 - gain) / gain / rate:.1f} s). The single-point reads take "
             "Q at the first point (0.1 s) and B at the minimum, both where the filter acts, "
             "so the filter shows in them fully. Fitted only where its slope holds, the "
             f"quantisation noise is resolved in {resolved['quantisation'][0]} of {seeds} "
             f"series before the filter and {resolved['quantisation'][1]} after"
             + (" (the paper's 0.000935 lies under the white noise that makes its variance)"
                if not resolved["quantisation"][0] else "") + ", and the bias "
             f"instability in {resolved['bias_instability'][0]} and "
             f"{resolved['bias_instability'][1]}, read on the long-τ floor that a filter "
             "with unity gain at DC leaves in place (expected change at τ ≫ T: 0 %).", ""]
    if on_run is None:
        lines += [f"On the run's data: not computed ({why}).", ""]
    else:
        ch = on_run["change_percent"]
        lines += [f"On the run's data ({on_run['source']}, calibrated x component, "
                  f"{on_run['rate_hz']:.3g} Hz): single-point reads "
                  f"{ch['single_point.quantisation']:+.1f} % quantisation, "
                  f"{ch['single_point.bias_instability']:+.1f} % bias instability.", ""]
    lines += ["![Paper C](paper_c_allan.png)", ""]
    from ..calib.plotting import NARROW, plain_log_axis
    plt, fig, ax = _figure(NARROW)
    before, after = first
    ax.errorbar(before.taus, before.deviation, yerr=before.error, lw=0.8, elinewidth=0.5,
                label="before the Kalman filter")
    ax.errorbar(after.taus, after.deviation, yerr=after.error, lw=0.8, elinewidth=0.5,
                label="after")
    ax.set_xscale("log")
    ax.set_yscale("log")
    plain_log_axis(ax)
    ax.set_xlabel("averaging time τ (s)")
    # The paper's figures carry no unit: the series is in its units (an HMC5883L's output).
    ax.set_ylabel("Allan deviation (paper C's units;\nthe paper states none)")
    ax.set_title(f"Paper C: Allan deviation, synthetic series (seed {seed * 1000})")
    ax.legend(fontsize=8)
    plots = {"paper_c_allan": _save(plt, fig, Path(out_dir) / "paper_c_allan.png")}
    return {"paper": PAPER_C, "signal": truth_terms, "minutes": minutes, "seeds": seeds,
            "filter": {"q_over_r": q_over_r, "steady_state_gain": gain,
                       "time_constant_s": (1 - gain) / gain / rate},
            "change_percent": changes, "variance": variance, "runs": runs,
            "slope_regions_resolved": resolved,
            "on_run": on_run, "on_run_reason": None if on_run else why}, lines, plots


# -- All three ------------------------------------------------------------------------------

def paper_results(run, truth, out_dir, *, seed=0, quick=False):
    """The three papers' results beside ours, written into folder ``out_dir`` (created when
    missing): papers.md (a Markdown section for the report), papers.json and the PNGs.
    ``run``: the calibration (None when it failed: paper A is then not computed);
    ``truth``: truth.json's dict (or None: the default error model); ``quick``: small
    made-up scenarios (a few seconds in all)."""
    if not isinstance(seed, (int, np.integer)) or isinstance(seed, bool) or seed < 0:
        raise ValueError(f"Seed must be a non-negative integer, not {seed!r}")
    if truth is not None and not isinstance(truth, dict):
        raise ValueError(f"Truth must be the dict of a truth.json or None, not "
                         f"{type(truth).__name__}")
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    data, plots = {"seed": seed, "quick": quick}, {}
    lines = ["# The papers' results beside ours", "",
             f"Seed {seed}; {'quick (small made-up scenarios)' if quick else 'full'} run. "
             "Paper A is computed on this run's data; papers B and C on scenarios made for "
             "them (stated in each section). The papers: "
             + ", ".join(f"{key} ({paper['short']})" for key, paper in PAPERS.items())
             + ", cited in full under References at the end; the figures quoted from them "
             "are theirs.", ""]
    for name, (section, section_lines, section_plots) in (
            ("paper_a", paper_a(run, truth, out)),
            ("paper_b", paper_b(truth, out, seed=seed, quick=quick)),
            ("paper_c", paper_c(run, truth, out, seed=seed, quick=quick))):
        data[name] = section
        lines += section_lines
        plots.update(section_plots)
    data["citations"] = {key: {**PAPERS[key], "text": citation(key)} for key in PAPERS}
    lines += ["## References", ""] + [f"- Paper {key}: {citation(key)}" for key in PAPERS]
    lines.append("")
    markdown = out / "papers.md"
    markdown.write_text("\n".join(lines) + "\n", encoding="utf-8")
    result = PapersResult(markdown=markdown, json=out / "papers.json", plots=plots, data=data)
    result.json.write_text(json.dumps(_jsonable(data), indent=2, allow_nan=False) + "\n")
    return result
