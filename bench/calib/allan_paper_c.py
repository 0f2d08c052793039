"""Paper C's Allan analysis (Li, Zhang and Yang: LS-KF compensation of an electronic
compass; docs/papers.md section C) reproduced on synthetic 0.1 s signals whose noise
terms are known.

The paper: HMC5883L at 0.1 s; X axis before the Kalman filter mean 0.0022, variance
1.3717, after mean -0.0075, variance 0.0129; Allan fit before -> after: quantisation noise
0.000935 -> 0.000161 (-82.8 %), bias instability 0.160291 -> 0.035448 (-77.9 %). It gives
B = H = 1 and Kg, P initialised to 1, not Q and R, nor the units, nor the log's length.

Signals (``maglog.calib.noise.simulate_noise``, IEEE 952 coefficients, tau in s):

- ``paper_coefficients``: the paper's "before" Q and B as they stand, plus white noise N
  chosen so that the sample variance is the paper's 1.3717 (a variance that large at 0.1 s
  is white noise: Q and B alone give less than 0.1);
- ``resolvable_quantisation``: the paper's B with a Q large enough (0.2) to dominate below
  about 1 s, so that a slope -1 region exists at 0.1 s sampling, and no white noise.

Filter: ``maglog.calib.noise.kalman_filter`` with the paper's B = H = 1, P0 = 1, x0 the
first sample (the gain follows from P, so "Kg = 1" needs no setting). R is the sample
variance of the series (the measurement noise of a static sensor); Q is chosen so that the
steady-state gain g lowers white noise's variance by the paper's ratio 0.0129 / 1.3717:
g / (2 - g) = ratio, Q / R = g^2 / (1 - g). The same Q / R serves both signals.

Analysis before and after: ``allan_deviation`` (terms where their slope holds, "not
resolved" otherwise; the NNLS sum model beside) and, for comparison, the single-point
reads that calib/noise.py made before issue 10 (Q from the first point, B from the
minimum), which are what a reduction like the paper's comes from.

Run from the repository root: ``.venv/bin/python bench/calib/allan_paper_c.py``
(writes bench/results/allan_paper_c.json).
"""

import argparse
import sys
import time
from pathlib import Path

import numpy as np

BENCH = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(BENCH))

from _machine import load, packages, write_report

from maglog.calib.noise import (BIAS_INSTABILITY_FACTOR, allan_deviation, kalman_filter,
                                simulate_noise)

DEFAULT_OUTPUT = BENCH / "results" / "allan_paper_c.json"
RATE = 10.0                                        # 0.1 s sampling
PAPER = {
    "before": {"mean": 0.0022, "variance": 1.3717, "quantisation": 0.000935,
               "bias_instability": 0.160291},
    "after": {"mean": -0.0075, "variance": 0.0129, "quantisation": 0.000161,
              "bias_instability": 0.035448},
    "reduction_percent": {"quantisation": -82.8, "bias_instability": -77.9},
}
TERMS_SHOWN = ("quantisation", "random_walk", "bias_instability")


def gain_for_variance_ratio(ratio):
    """Steady-state gain g of x += g (z - x) whose output variance for white input is
    ``ratio`` times the input's: g / (2 - g) = ratio."""
    return 2 * ratio / (1 + ratio)


def signals(n):
    q, b = PAPER["before"]["quantisation"], PAPER["before"]["bias_instability"]
    tau0 = 1 / RATE
    # Variance of the rest at this length (Kasdin flicker: B^2 sum h_k^2; white phase
    # noise: 2 Q^2 / tau0^2), so that the total is the paper's.
    k = np.arange(1, n)
    h = np.concatenate(([1.0], np.cumprod((k - 0.5) / k)))
    rest = b ** 2 * np.sum(h ** 2) + 2 * q ** 2 / tau0 ** 2
    white = np.sqrt(max(PAPER["before"]["variance"] - rest, 0.0) * tau0)
    return {
        "paper_coefficients": dict(quantisation=q, random_walk=float(white),
                                   bias_instability=b),
        "resolvable_quantisation": dict(quantisation=0.2, bias_instability=b),
    }


def single_point_reads(result):
    """What calib/noise.py reported before issue 10: Q from the first point, B from the
    minimum, whatever the slope there."""
    best = int(np.argmin(result.deviation))
    return {"quantisation": float(result.deviation[0] * result.taus[0] / np.sqrt(3)),
            "bias_instability": float(result.deviation[best] / BIAS_INSTABILITY_FACTOR),
            "tau_of_minimum": float(result.taus[best])}


def term_fields(term):
    return {"resolved": term.resolved,
            "value": term.value if term.resolved else None,
            "error": term.error if term.resolved else None,
            "tau_range_s": list(term.tau_range) if term.resolved else None,
            "message": term.message}


def analyse(y, shortest=0.0):
    taus = allan_deviation(y, RATE).taus
    result = allan_deviation(y, RATE, taus=taus[taus >= shortest])
    return result, {
        "shortest_tau_s": float(result.taus[0]),
        "mean": float(np.mean(y)), "variance": float(np.var(y)),
        "slope_regions": {name: term_fields(result.terms[name]) for name in TERMS_SHOWN},
        "sum_model": {name: term_fields(result.model[name]) for name in TERMS_SHOWN},
        "single_point": single_point_reads(result),
    }


def reduction(before, after):
    if before is None or after is None:
        return None
    return round(100 * (after - before) / before, 1)


def run_one(truth, n, seed, q_over_r):
    y = simulate_noise(n, RATE, rng=seed, **truth)
    r = float(np.var(y))
    filtered, variances = kalman_filter(y, q=q_over_r * r, r=r, p0=1.0)
    gain = float(variances[-1] / r)
    time_constant = (1 - gain) / gain / RATE
    _, before = analyse(y)
    _, after = analyse(filtered)
    # Beyond ten time constants, where the filtered curve has rejoined the unfiltered one
    # (the first-order low-pass leaves ~T / tau of its effect at tau).
    _, beyond = analyse(filtered, 10 * time_constant)
    reductions = {}
    for method in ("slope_regions", "sum_model"):
        reductions[method] = {name: reduction(before[method][name]["value"],
                                              after[method][name]["value"])
                              for name in ("quantisation", "bias_instability")}
        reductions[method + "_beyond_10_time_constants"] = {
            name: reduction(before[method][name]["value"], beyond[method][name]["value"])
            for name in ("quantisation", "bias_instability")}
    reductions["single_point"] = {name: reduction(before["single_point"][name],
                                                  after["single_point"][name])
                                  for name in ("quantisation", "bias_instability")}
    return {"seed": seed, "filter": {"q": q_over_r * r, "r": r, "p0": 1.0,
                                     "steady_state_gain": gain,
                                     "time_constant_s": time_constant},
            "before": before, "after": after, "after_beyond_10_time_constants": beyond,
            "reduction_percent": reductions}


def summary(runs, path):
    """Mean, standard deviation and count of a figure over the seeds (None: unresolved)."""
    values = []
    for run in runs:
        value = run
        for key in path:
            value = value[key]
        if value is not None:
            values.append(value)
    if not values:
        return {"mean": None, "std": None, "resolved_in": 0, "of": len(runs)}
    return {"mean": float(np.mean(values)), "std": float(np.std(values)),
            "resolved_in": len(values), "of": len(runs)}


def compare(truth, expected, first, stats):
    """The paper's Q and B beside ours: truth, each method's before and after (first seed,
    with tau ranges) and the reductions (first seed; mean and std over the seeds)."""
    rows = {}
    for term in ("quantisation", "bias_instability"):
        row = {"paper": {"before": PAPER["before"][term], "after": PAPER["after"][term],
                         "reduction_percent": PAPER["reduction_percent"][term]},
               "truth": truth.get(term), "expected_after_at_long_tau": expected[term]}
        for method in ("slope_regions", "sum_model"):
            for stage, key in (("after", method),
                               ("after_beyond_10_time_constants",
                                method + "_beyond_10_time_constants")):
                b, a = first["before"][method][term], first[stage][method][term]
                row[key] = {"before": b["value"], "before_tau_range_s": b["tau_range_s"],
                            "after": a["value"], "after_tau_range_s": a["tau_range_s"],
                            "reduction_percent": first["reduction_percent"][key][term],
                            "reduction_percent_over_seeds":
                                stats[f"reduction_percent.{key}.{term}"]}
        b, a = first["before"]["single_point"][term], first["after"]["single_point"][term]
        row["single_point"] = {
            "before": b, "after": a,
            "reduction_percent": first["reduction_percent"]["single_point"][term],
            "reduction_percent_over_seeds": stats[f"reduction_percent.single_point.{term}"]}
        rows[term] = row
    return rows


def fmt(value, digits=4):
    return "-" if value is None else f"{value:.{digits}g}"


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--minutes", type=float, default=60.0,
                        help="length of each series (default: 60)")
    parser.add_argument("--seeds", type=int, default=10,
                        help="series per signal; the first is shown in full (default: 10)")
    parser.add_argument("--output", type=Path, default=DEFAULT_OUTPUT)
    args = parser.parse_args(argv)
    load_start = load()
    n = int(round(args.minutes * 60 * RATE))
    ratio = PAPER["after"]["variance"] / PAPER["before"]["variance"]
    gain = gain_for_variance_ratio(ratio)
    q_over_r = gain ** 2 / (1 - gain)
    started = time.perf_counter()
    scenarios, comparison = {}, {}
    for name, truth in signals(n).items():
        runs = [run_one(truth, n, seed, q_over_r) for seed in range(args.seeds)]
        stats = {}
        for stage in ("before", "after", "after_beyond_10_time_constants"):
            for method in ("slope_regions", "sum_model"):
                for term in TERMS_SHOWN:
                    stats[f"{stage}.{method}.{term}"] = summary(
                        runs, (stage, method, term, "value"))
            for term in ("quantisation", "bias_instability"):
                stats[f"{stage}.single_point.{term}"] = summary(
                    runs, (stage, "single_point", term))
        for method in ("slope_regions", "sum_model", "single_point",
                       "slope_regions_beyond_10_time_constants",
                       "sum_model_beyond_10_time_constants"):
            for term in ("quantisation", "bias_instability"):
                stats[f"reduction_percent.{method}.{term}"] = summary(
                    runs, ("reduction_percent", method, term))
        # What the steady-state filter (x += g (z - x), unity gain at DC) should leave at
        # tau >> its time constant: white phase noise comes out white with variance
        # g / (2 - g) of the input's, white and flicker rate noise unchanged.
        expected = {"quantisation": truth.get("quantisation", 0.0) * np.sqrt(gain / (2 - gain)),
                    "random_walk": truth.get("random_walk", 0.0),
                    "bias_instability": truth.get("bias_instability", 0.0)}
        scenarios[name] = {"truth": truth, "expected_after_at_long_tau": expected,
                           "first_seed": runs[0], "over_seeds": stats}
        comparison[name] = compare(truth, expected, runs[0], stats)
    elapsed = time.perf_counter() - started

    print(f"0.1 s sampling, {args.minutes:g} min series, {args.seeds} seeds; filter "
          f"Q/R = {q_over_r:.3g} (steady-state gain {gain:.4f}, time constant "
          f"{(1 - gain) / gain / RATE:.1f} s)")
    for name, scenario in scenarios.items():
        first, truth, stats = (scenario["first_seed"], scenario["truth"],
                               scenario["over_seeds"])
        print(f"\n{name}: truth " + ", ".join(f"{k} {v:.4g}" for k, v in truth.items()))
        print(f"  {'term, method':34s}{'truth':>10s}{'before':>11s}{'after':>11s}"
              f"{'>=10T':>11s}{'chg %':>8s}{'>=10T %':>8s}  {'chg % over seeds':>19s}"
              f"{'>=10T % over seeds':>20s}  tau ranges (s)")
        stages = ("before", "after", "after_beyond_10_time_constants")
        for method in ("slope_regions", "sum_model"):
            for term in TERMS_SHOWN:
                fields = [first[stage][method][term] for stage in stages]
                changes = [reduction(fields[0]["value"], f["value"]) for f in fields[1:]]
                overs = []
                for key in (method, method + "_beyond_10_time_constants"):
                    over = stats.get(f"reduction_percent.{key}.{term}")
                    overs.append("" if over is None or over["mean"] is None else
                                 f"{over['mean']:+.1f}+-{over['std']:.1f} "
                                 f"({over['resolved_in']})")
                ranges = " | ".join("-" if f["tau_range_s"] is None else
                                    "%.3g-%.3g" % tuple(f["tau_range_s"]) for f in fields)
                print(f"  {term + ', ' + method:34s}{fmt(truth.get(term)):>10s}"
                      + "".join(f"{fmt(f['value']):>11s}" for f in fields)
                      + "".join(f"{fmt(c, 3):>8s}" for c in changes)
                      + f"  {overs[0]:>19s}{overs[1]:>20s}  {ranges}")
        for term in ("quantisation", "bias_instability"):
            b, a = first["before"]["single_point"][term], first["after"]["single_point"][term]
            over = stats[f"reduction_percent.single_point.{term}"]
            over = f"{over['mean']:+.1f}+-{over['std']:.1f} ({over['resolved_in']})"
            print(f"  {term + ', single point':34s}{fmt(truth.get(term)):>10s}{fmt(b):>11s}"
                  f"{fmt(a):>11s}{'':>11s}{fmt(reduction(b, a), 3):>8s}{'':>8s}  {over:>19s}")
        print(f"  {'mean':34s}{'0':>10s}{fmt(first['before']['mean']):>11s}"
              f"{fmt(first['after']['mean']):>11s}")
        print(f"  {'variance':34s}{'':>10s}{fmt(first['before']['variance']):>11s}"
              f"{fmt(first['after']['variance']):>11s}")
        print("  expected at tau >> T after the filter: "
              + ", ".join(f"{k} {v:.4g}" for k, v in scenario["expected_after_at_long_tau"]
                          .items() if v))
    print(f"\npaper: Q {PAPER['before']['quantisation']} -> {PAPER['after']['quantisation']}"
          f" (-82.8 %), B {PAPER['before']['bias_instability']} -> "
          f"{PAPER['after']['bias_instability']} (-77.9 %), variance 1.3717 -> 0.0129")

    write_report(args.output, "allan_paper_c", argv, load_start,
                 packages("numpy", "scipy"),
                 paper=PAPER, rate_hz=RATE, samples=n, seeds=args.seeds,
                 filter={"paper": "B = H = 1, Kg and P initialised to 1, Q and R not given",
                         "ours": "P0 = 1, x0 = first sample, R = sample variance, "
                                 "Q = R g^2 / (1 - g) with g / (2 - g) = 0.0129 / 1.3717",
                         "q_over_r": q_over_r, "steady_state_gain": gain,
                         "time_constant_s": (1 - gain) / gain / RATE},
                 comparison=comparison, scenarios=scenarios, elapsed_s=round(elapsed, 2))


if __name__ == "__main__":
    main()
