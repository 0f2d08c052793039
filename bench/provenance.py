"""The generated parts of bench/RESULTS.md: every table (and the sentences with figures
next to it) rendered from the benchmark JSON it came from, closed by that JSON's provenance
line.

In RESULTS.md a generated block starts with a marker line ``<!-- generated: NAME -->`` and
ends with its provenance line, ``Provenance (bench/results/X.json): ...``
(:func:`_machine.provenance_line`). Everything between is what :data:`BLOCKS` ``[NAME]``
renders from that JSON; nothing in a block is written by hand.

    .venv/bin/python bench/provenance.py            # rewrite the blocks from the JSONs
    .venv/bin/python bench/provenance.py --check    # only compare; exit 1 on a difference

A table outside a block, a block with an unknown name or a provenance line that does not
close a block is an error as well (tests/bench/test_provenance.py runs the check).
"""

import argparse
import difflib
import json
import re
import statistics
import sys
from pathlib import Path

sys.dont_write_bytecode = True
sys.path.insert(0, str(Path(__file__).resolve().parent))

from _machine import REPO, provenance_line


RESULTS_MD = REPO / "bench" / "RESULTS.md"
MARKER = re.compile(r"^<!-- generated: ([\w-]+) -->$")
PROVENANCE = re.compile(r"^Provenance \((bench/results/[\w.-]+\.json)\): ")


# --- formatting -------------------------------------------------------------------------

def thousands(n):
    return f"{n:,}"


def ms(seconds, digits=0):
    return f"{seconds * 1e3:.{digits}f} ms"


def pct(x, digits=1):
    return f"{100 * x:.{digits}f}"


def table(head, rows, align):
    """A Markdown table; ``align`` is one of 'l' / 'r' per column."""
    lines = ["| " + " | ".join(head) + " |",
             "|" + "|".join("---" if a == "l" else "---:" for a in align) + "|"]
    lines += ["| " + " | ".join(str(cell) for cell in row) + " |" for row in rows]
    return lines


# --- synth.json -------------------------------------------------------------------------

def _design(r):
    what, _, note = r["design"].partition("#")
    what = f"`{what.strip()}`"
    if note.strip():
        what += f" ({note.strip()})"
    return ("part: " if r["part"] else "") + what


def _synth_table(report, modules):
    les = report["device"]["les"]
    by_module = {r["module"]: r for r in report["results"]}
    rows = []
    for module in modules:
        r = by_module[module]
        low, high = 100 * r["le_min"] / les, 100 * r["le_max"] / les
        share = f"{low:.1f}" if f"{low:.1f}" == f"{high:.1f}" else f"{low:.1f}–{high:.1f}"
        rows.append([_design(r), r["lut4"], r["ff"], r["m9k"], r.get("depth", "–"),
                     f"{r['le_min']}..{r['le_max']}", share])
    return table(["block", "LUT4", "FF", "M9K", "depth", "LE range",
                  f"% of {report['device']['name']} LEs"], rows, "lrrrrrr")


def synth_frontend(report):
    by = {r["module"]: r for r in report["results"]}
    lines = _synth_table(report, ["uart_rx", "channel_nmea", "channel_pmag", "channel_cesium",
                                  "maglog_frontend", "frame_fifo", "frame_arbiter",
                                  "channel_pmag_w32"])
    front, pmag, wide = by["maglog_frontend"], by["channel_pmag"], by["channel_pmag_w32"]
    channels = [by[k] for k in ("channel_nmea", "channel_pmag", "channel_cesium")]
    glue_lut = front["lut4"] - sum(c["lut4"] for c in channels) - by["frame_arbiter"]["lut4"]
    glue_ff = front["ff"] - sum(c["ff"] for c in channels) - by["frame_arbiter"]["ff"]
    seconds = [r["synth_seconds"] for r in report["results"]]
    lines += [
        "",
        f"- Memories: the front end uses {front['m9k']} M9K "
        f"({pct(front['m9k'] / report['device']['m9k'], 0)} % of an "
        f"{report['device']['name']}'s {report['device']['m9k']}); the script found "
        f"{len(report['problems'])} problem(s) (memory left to flip-flops, flip-flops added "
        f"by `memory_libmap` to emulate a port, unmapped cells) in all blocks together.",
        f"- Counters: a PMAG channel with its own seven 32-bit counters (as before issue 14) "
        f"takes {wide['lut4']}/{wide['ff']} LUT4/FF; as the front end builds it, its "
        f"counters in the front end's one shared counter bank (a block RAM), "
        f"{pmag['lut4']}/{pmag['ff']}: {wide['lut4'] - pmag['lut4']} LUT4 and "
        f"{wide['ff'] - pmag['ff']} FF less per channel.",
        f"- The front end minus its three channels and the arbiter: {glue_lut} LUT4, "
        f"{glue_ff} FF.",
        f"- Yosys time per block: {min(seconds):.1f}–{max(seconds):.1f} s.",
    ]
    return lines


def synth_sd(report):
    by = {r["module"]: r for r in report["results"]}
    lines = _synth_table(report, ["sdio_host", "sd_cmd", "sd_dat_writer", "sd_dat_reader"])
    total = by["sdio_host"]["lut4"] + by["maglog_frontend"]["lut4"]
    lines += ["", f"The SD host and the front end together: {total} LUT4 "
              f"({pct(total / report['device']['les'])} % of an {report['device']['name']}'s "
              f"{thousands(report['device']['les'])} LEs, counting LUT4 alone)."]
    return lines


def synth_sdram(report):
    return _synth_table(report, ["sdram_mt48lc4m32b2", "sdram_is42s16160", "ring_buffer",
                                 "dma"])


def synth_logger(report):
    """The whole logger (flattened) and its split by block (not flattened)."""
    by = {r["module"]: r for r in report["results"]}
    logger = by["maglog_logger"]
    device = report["device"]
    lines = _synth_table(report, ["maglog_logger"])
    blocks = [b for b in logger["blocks"] if b["lut4"] or b["ff"] or b["m9k"]]
    total = {k: sum(b[k] for b in blocks) for k in ("lut4", "ff", "m9k")}
    rows = [[f"`{b['block']}`", b["lut4"], b["ff"], b["m9k"], b.get("depth", "–"),
             pct(b["lut4"] / total["lut4"], 1)] for b in blocks]
    rows.append(["all blocks (not flattened)", total["lut4"], total["ff"], total["m9k"], "",
                 "100"])
    lines += ["", *table(["block", "LUT4", "FF", "M9K", "depth", "% of the LUT4"], rows,
                         "lrrrrr")]
    fits = logger["le_min"] <= device["les"]
    lines += ["", f"The whole logger needs at least {thousands(logger['le_min'])} LEs (LUT4 "
              f"alone), {pct(logger['le_min'] / device['les'], 0)} % of an {device['name']}'s "
              f"{thousands(device['les'])}: it {'fits' if fits else 'does not fit'}. Flattened, "
              f"Yosys optimises across blocks, so the flattened total "
              f"({thousands(logger['lut4'])} LUT4) differs from the blocks' sum "
              f"({thousands(total['lut4'])}). Yosys time: {logger['synth_seconds']:.0f} s for "
              f"both runs."]
    return lines


#: Issue 14's budget for the whole logger top, and the NIOS II/e beside it on an EP4CE6.
LOGGER_LUT4_BUDGET = 4000
LOGGER_M9K_BUDGET = 20
NIOS2E_LES = 700
FIT_SHARE = 0.80


def synth_cut(report):
    """The logger before and after issue 14's cuts: per block, and the whole top."""
    base = report["baseline"]
    before = next(r for r in base["results"] if r["module"] == "maglog_logger")
    after = next(r for r in report["results"] if r["module"] == "maglog_logger")
    old = {b["block"]: b for b in before["blocks"]}
    new = {b["block"]: b for b in after["blocks"]}
    names = sorted(set(old) | set(new), key=lambda n: (-old.get(n, new.get(n))["lut4"], n))
    rows = []
    for name in names:
        o, n = old.get(name), new.get(name)
        if not any((o or {}).get(k) for k in ("lut4", "ff", "m9k")) and \
                not any((n or {}).get(k) for k in ("lut4", "ff", "m9k")):
            continue

        def pair(key):
            return f"{o[key] if o else '–'} → {n[key] if n else '–'}"
        rows.append([f"`{name}`", pair("lut4"), pair("ff"), pair("m9k"), pair("depth")])

    def whole(key):
        return f"**{before[key]} → {after[key]}**"
    rows.append(["whole top (flattened)", whole("lut4"), whole("ff"), whole("m9k"),
                 whole("depth")])
    device = report["device"]
    les = max(after["lut4"], after["ff"])
    share = (les + NIOS2E_LES) / device["les"]
    met = after["lut4"] <= LOGGER_LUT4_BUDGET and after["m9k"] <= LOGGER_M9K_BUDGET
    deep = [f"`{b['block']}` {b['depth']}" for b in after["blocks"] if b["depth"] > 10]
    tree = base.get("work_tree") or {}
    return table(["block", "LUT4", "FF", "M9K", "depth (LUT levels)"], rows, "lrrrr") + [
        "", f"Budget: the whole top ≤ {thousands(LOGGER_LUT4_BUDGET)} LUT4 and ≤ "
            f"{LOGGER_M9K_BUDGET} M9K: {'met' if met else '**not met**'} "
            f"({thousands(after['lut4'])} LUT4, {after['m9k']} M9K). With a NIOS II/e of about "
            f"{NIOS2E_LES} LEs, at least {thousands(les + NIOS2E_LES)} of the "
            f"{device['name']}'s {thousands(device['les'])} LEs: {pct(share, 0)} % (goal ≤ "
            f"{pct(FIT_SHARE, 0)} %: {'met' if share <= FIT_SHARE else '**not met**'}, "
            f"counting one LE per LUT4 with the flip-flops packed beside them; with no "
            f"flip-flop packed beside a LUT, {thousands(after['lut4'] + after['ff'] + NIOS2E_LES)}"
            f" LEs, {pct((after['lut4'] + after['ff'] + NIOS2E_LES) / device['les'], 0)} %).",
        f"Depth goal ≤ 10 levels per block: "
        + ("met." if not deep else "not met in " + ", ".join(deep) + "."),
        f"Before: `{base['path']}`, commit `{str(tree.get('commit', '?'))[:7]}` "
        f"({'clean' if not tree.get('status_porcelain') else 'not clean'}), "
        f"{base.get('date')}, `{base.get('command')}`."]


# --- sim_throughput.json ----------------------------------------------------------------

BACKEND_NAMES = {"amaranth": "Amaranth simulator", "icarus": "cocotb + Icarus",
                 "verilator": "cocotb + Verilator"}


def sim_throughput(report):
    rows = []
    for r in report["results"]:
        m = r["main"]
        steady, overhead = r["steady_cycles_per_second"], r["overhead_seconds"]
        rows.append([BACKEND_NAMES.get(r["backend"], r["backend"]), f"{r['build_seconds']:.2f}",
                     m["sentences"], thousands(m["cycles"]), f"{m['seconds']:.2f}",
                     thousands(m["cycles_per_second"]),
                     "–" if steady is None else thousands(steady),
                     "–" if overhead is None else f"{overhead:.2f}",
                     r["slowdown_vs_hardware"]])
    lines = table(["backend", "build s", "sentences", "cycles", "run s", "cycles/s",
                   "steady cycles/s", "overhead s", "× slower"], rows, "lrrrrrrrr")
    lines += ["", f"Stimulus: {report['stimulus']}; design `{report['design']}`. Tools: "
              + ", ".join(f"{k} {v}" for k, v in report["tools"].items()) + "."]
    by = {r["backend"]: r for r in report["results"]}
    if "icarus" in by and "verilator" in by:
        icarus, verilator = by["icarus"], by["verilator"]
        lines.append(f"- cocotb + Verilator runs "
                     f"{verilator['main']['cycles_per_second'] / icarus['main']['cycles_per_second']:.1f}× "
                     f"as many cycles a second as cocotb + Icarus.")
        extra_build = verilator["build_seconds"] - icarus["build_seconds"]
        gain = 1 / icarus["main"]["cycles_per_second"] - 1 / verilator["main"]["cycles_per_second"]
        if gain > 0:
            cycles = extra_build / gain
            lines.append(f"- Verilator's longer build ({extra_build:.1f} s more than Icarus's) "
                         f"pays off after {cycles / 1e6:.1f} M simulated cycles "
                         f"({cycles / icarus['main']['cycles_per_second']:.0f} s of Icarus run "
                         f"time) at these rates.")
    return lines


# --- sdio_throughput.json ---------------------------------------------------------------

def sdio_throughput(report):
    r = report["result"]
    lines = table(["blocks", "SD clocks outside busy", "4-bit bus limit (1024 a block)",
                   "efficiency", "clocks a block"],
                  [[r["blocks"], thousands(r["clocks_excluding_busy"]),
                    thousands(r["bus_limit_clocks"]), f"**{pct(r['efficiency'], 2)} %** "
                    "(goal ≥ 95 %)", f"{r['clocks_per_block']:.1f}"]], "rrrrr")
    pauses = r["clock_pauses"]
    where = "; ".join(
        f"block {p['block']}, SD clock {thousands(p['edge'])} of the data phase, "
        f"{p['edges_since_host_released_dat']} clocks after the host released DAT, "
        f"card {'busy' if p['card_busy'] else 'not busy'}, {p['extra_cycles']} system "
        f"cycles" for p in r["pauses"])
    lines += [
        "",
        f"Clock pauses (an SD clock period longer than the divisor's "
        f"{r['sd_clock_period_cycles']} system cycles at {r['sd_clock_hz'] / 1e6:g} MHz from "
        f"{r['sys_clock_hz'] / 1e6:g} MHz) over the {thousands(r['sd_clock_periods_checked'])} "
        f"periods of the data phase: {pauses}"
        + (f" ({where})" if pauses else "")
        + f"; while the host drove DAT (sending a block): "
          f"{r['pauses_while_host_drives_dat']}. Busy clocks excluded: "
          f"{thousands(r['busy_clocks'])}; clocks a block beyond the 1024 of data: "
          f"{r['clocks_per_block'] - r['bus_limit_clocks'] / r['blocks']:.1f}.",
    ]
    return lines


# --- sdram_bandwidth.json ---------------------------------------------------------------

def sdram_bandwidth(report):
    rows = [[r["chip"], r["direction"], thousands(r["clocks"]), r["refreshes"],
             f"**{pct(r['efficiency'])} %**", f"{r['bytes_per_second'] / 1e6:.1f} MB/s"]
            for r in report["results"]]
    return table(["chip", "direction", "clocks", "refreshes", "efficiency", "at 50 MHz"],
                 rows, "llrrrr") + ["", f"Words per run: {thousands(report['results'][0]['words'])}."]


# --- write_amplification.json -----------------------------------------------------------

WA_SCHEMES = {"firmware": "the firmware's (FSInfo on allocation)",
              "fsinfo_every_sync": "FSInfo every sync",
              "whole_sectors_preallocated": "whole sectors, clusters preallocated"}


def write_amplification(report):
    goal = report["goal"]
    results = report["results"]
    head = ["cluster", "flushes", "bytes a flush", "data", "FAT 1", "FAT 2", "directory",
            "FSInfo", "blocks a flush", "WA (recording)", "WA (flushes)", "floor (the "
            "firmware's scheme)"]
    rows = []
    for r in results:
        pf = r["per_flush"]

        def cell(name):
            c = pf[name]
            return f"{c['mean']:.2f} ({c['min']}–{c['max']})"

        wa = r["write_amplification"]
        rows.append([f"{r['cluster_bytes'] // 1024} KiB", r["flushes"],
                     f"{r['bytes_per_flush']:.0f}", cell("data"), cell("fat1"), cell("fat2"),
                     cell("directory"), cell("fsinfo"), f"{r['blocks_per_flush']:.2f}",
                     f"**{wa:.2f}**", f"{r['write_amplification_flushes']:.2f}",
                     f"{r['floor']['firmware']['write_amplification']:.2f}"])
    lines = table(head, rows, "lrrrrrrrrrrr")
    first = results[0]
    floors = "; ".join(
        f"{r['cluster_bytes'] // 1024} KiB clusters: " + ", ".join(
            f"{WA_SCHEMES[name]} {f['write_amplification']:.2f} (goal reached with a flush "
            f"every {f['flush_period_for_goal_s']:g} s)"
            for name, f in r["floor"].items())
        for r in results)
    missed = [f"{r['cluster_bytes'] // 1024} KiB" for r in results
              if r["write_amplification"] > goal]
    verdict = (f"The goal (≤ {goal}) is met." if not missed else
               f"The goal (≤ {goal}) is missed with {' and '.join(missed)} clusters.")
    if missed:
        reach = sorted({WA_SCHEMES[name] for r in results
                        for name, f in r["floor"].items()
                        if f["write_amplification"] <= goal})
        periods = ", ".join(f"{r['floor']['firmware']['flush_period_for_goal_s']:g} s "
                            f"({r['cluster_bytes'] // 1024} KiB clusters)" for r in results)
        verdict += (f" At one flush a second only {' and '.join(reach) or 'no scheme'} gets "
                    f"below it; the firmware's scheme needs a flush every {periods}.")
    lines += [
        "",
        f"A {first['flight_seconds']:g} s flight, {thousands(first['bytes_logged'])} bytes "
        f"logged ({first['bytes_per_second']:.0f} B/s); block writes a flush by region: mean "
        f"(least–most); WA: bytes the card stored per byte of the log, over the whole "
        f"recording (the file's creation and close included: "
        f"{first['blocks_before_first_flush']} and {first['blocks_of_close']} blocks) and "
        f"over the flushes alone. {verdict}",
        "",
        f"Floors: {report['formula']}. Per scheme: {floors}.",
    ]
    return lines


# --- system_speed.json / main_command.json ------------------------------------------------

SYSTEM_BACKENDS = {"verilator": "verilator (the C++ harness, Python per command)",
                   "model": "model (transaction level, no RTL)",
                   "verilator-cocotb": "verilator-cocotb (models on the pins)",
                   "icarus": "icarus (cocotb, models on the pins)",
                   "amaranth": "amaranth (models on the pins)"}


def system_speed(report):
    rows = []
    for r in report["runs"]:
        rows.append([SYSTEM_BACKENDS.get(r["backend"], r["backend"]),
                     f"{r['clk_freq_hz'] / 1e6:g}",
                     f"{r['simulated_s']:g}" + ("" if r["whole_flight"] else " (first)"),
                     f"{r['run_wall_s']:.1f}", f"**{r['real_time_factor']:.3g}**",
                     thousands(round(r["cycles_per_s"])) if r["backend"] != "model" else "–"])
    limit, fast50 = report["harness_alone"], report["verilator_50mhz"]
    rows.append(["the harness alone (Verilator, no Python): the limit",
                 f"{limit['clk_freq_hz'] / 1e6:g}", f"{limit['simulated_s']:g} (first)",
                 f"{limit['wall_s']:.1f}", f"**{limit['real_time_factor']:.3g}**",
                 thousands(round(limit["cycles_per_s"]))])
    rows.append([SYSTEM_BACKENDS["verilator"] + " at 50 MHz", f"{fast50['clk_freq_hz'] / 1e6:g}",
                 f"{fast50['simulated_s']:g} (first)", f"{fast50['run_wall_s']:.1f}",
                 f"**{fast50['real_time_factor']:.3g}**",
                 thousands(round(fast50["cycles_per_s"]))])
    lines = table(["backend", "clock MHz", "flight s", "wall s", "real-time factor",
                   "clocks/s"], rows, "lrrrrr")
    v = report["verdict"]
    lines.append("")
    if "rtf_met" in v:
        fast = next(r for r in report["runs"] if r["backend"] == "verilator")
        lines.append(f"- Goal: a real-time factor of at least {v['rtf_goal']:g} on Verilator "
                     f"at {fast['clk_freq_hz'] / 1e6:g} MHz: "
                     + ("met." if v["rtf_met"] else
                        f"**missed** ({fast['real_time_factor']:.2f}); the harness alone "
                        f"reaches {limit['real_time_factor']:.2f}: the design's own "
                        f"evaluation sets the pace."))
        lines.append(f"- The runner against the limit: {v['limit_ratio']:.2f}x slower (goal "
                     f"within {v['limit_ratio_goal']:g}x: "
                     + ("met)." if v["limit_ratio_met"] else "**missed**)."))
    hour = report.get("hour_on_model")
    if hour is not None:
        lines.append(f"- A flight of {hour['simulated_s'] / 3600:.1f} h ({hour['simulated_s']:.0f} s; "
                     f"the goal is stated for one hour) on the model: peak "
                     f"memory {hour['peak_rss_bytes'] / 2**20:.0f} MiB (goal ≤ "
                     f"{v['memory_goal_bytes'] / 2**30:g} GiB: "
                     + ("met" if v["memory_met"] else "**missed**")
                     + f"), {hour['build_s']:.0f} s to build its streams and "
                     f"{hour['run_wall_s']:.0f} s to run.")
    return lines


def main_command(report):
    r = report["result"]
    lines = table(["step", "command", "wall s", "exit"],
                  [["set-up", "`make setup`", f"{r['setup_s']:.0f}", r["setup_exit"]],
                   ["the main job", "`make run`", f"{r['run_s']:.0f}", r["run_exit"]]],
                  "llrr")
    lines += ["", f"On a fresh clone of commit `{r['commit'][:7]}` ({r['clone']}); the "
                  f"summary's verdict: {r['verdict']}."]
    return lines


# --- calib.json -------------------------------------------------------------------------

COVERAGE_NAMES = {"full": "full sphere", "uav": "UAV ±30°", "planar": "near-planar ±5°"}


def _coverage(name):
    return COVERAGE_NAMES.get(name, name)


def calib_accuracy(report):
    rows = []
    for r in report["accuracy"]:
        scipy = f"{r['scipy_ratio']:.4f}"
        if r["scipy_ratio"] < 0.5:
            scipy = (f"**{scipy}** (K diagonal ≤ {max(r['scipy_k_diagonal']):.2g}, \\|c\\| = "
                     f"{r['scipy_c_norm_nT']:.0f} nT against a reference of "
                     f"{r['reference_median_nT']:.0f} nT)")
        rows.append([_coverage(r["coverage"]), f"{r['noise_nT']:g}",
                     f"{r['maglog_ratio']:.4f}", ms(r["maglog_timing"]["best"]),
                     ms(r["maglog_timing"]["median"]), scipy, ms(r["scipy_timing"]["best"]),
                     ms(r["scipy_timing"]["median"])])
    lines = table(["coverage", "noise (nT)", "maglog PSO+LM ratio", "best", "median",
                   "scipy `least_squares` (lm) ratio", "best", "median"], rows, "lrrrrrrr")
    full_uav = [r["maglog_ratio"] for r in report["accuracy"] if r["coverage"] != "planar"]
    planar = [r["maglog_ratio"] for r in report["accuracy"] if r["coverage"] == "planar"]
    repeats = report["accuracy"][0]["maglog_timing"]["repeats"]
    warned = [r for r in report["accuracy"]
              if any("hardly determines" in w for w in r["maglog_warnings"])]
    collapsed = [r for r in report["accuracy"] if r["scipy_ratio"] < 0.5]

    def met(ok):
        return "met" if ok else "**not met**"
    lines += ["", f"Times: best and median of {repeats} repeats each. maglog's ratio: "
              f"{min(full_uav):.4f}–{max(full_uav):.4f} on full and UAV coverage (goal ≤ 1.01: "
              f"{met(max(full_uav) <= 1.01)}), {min(planar):.4f}–{max(planar):.4f} on "
              f"near-planar (goal ≤ 1.10: {met(max(planar) <= 1.10)}); fits maglog reports "
              f"unsuccessful: {sum(1 for r in report['accuracy'] if not r['maglog_success'])} "
              f"of {len(report['accuracy'])}. maglog warns that the coverage hardly determines "
              f"a combination of parameters (and holds it to the isotropic prior) in "
              f"{len(warned)} case(s): "
              + (", ".join(f"{_coverage(r['coverage'])} {r['noise_nT']:g} nT" for r in warned)
                 or "none")
              + f". scipy's ratio is below 0.5 (a collapse towards the trivial K = 0, \\|c\\| = r "
                f"solution) in {len(collapsed)} case(s)."]
    return lines


PSO_NAMES = {"maglog_gbest": "maglog gbest", "maglog_ring": "maglog ring",
             "pyswarms_gbest": "pyswarms GlobalBestPSO", "pyswarms_ring": "pyswarms LocalBestPSO"}


def calib_pso(report):
    c = report["pso_comparison"]
    runs = c["runs"]
    rows = []
    for key, run in runs.items():
        name = PSO_NAMES[key.rsplit("_", 1)[0]]
        s = run["seconds"]
        rows.append([name, run["kernel"], ms(s["best"]), ms(s["median"]), ms(s["worst"]),
                     f"{statistics.median(run['best_costs']):.4g}"])
    lines = table(["optimiser", "cost kernel", "best", "median", "worst",
                   "median best cost"], rows, "llrrrr")
    like = [p for p in c["pairings"] if p["like_for_like"]]
    lines += ["", "Like for like (pyswarms' time / maglog's, same topology and cost kernel):", ""]
    lines += table(["maglog", "pyswarms", "speed-up (median)", "speed-up (best)"],
                   [[f"{PSO_NAMES[p['maglog'].rsplit('_', 1)[0]]}, "
                     f"{p['maglog'].rsplit('_', 1)[1]}",
                     f"{PSO_NAMES[p['pyswarms'].rsplit('_', 1)[0]]}, "
                     f"{p['pyswarms'].rsplit('_', 1)[1]}",
                     f"**{p['speedup_median']:.2f}×**", f"{p['speedup_best']:.2f}×"]
                    for p in like], "llrr")
    medians = [p["speedup_median"] for p in like]
    numba_over_numpy = [p["speedup_median"] for p in c["pairings"]
                        if p["maglog"].endswith("_numba") and p["pyswarms"].endswith("_numpy")]
    lines += ["", f"The earlier goal, ≥ 10× pyswarms: like for like the median speed-up is "
              f"{min(medians):.2f}–{max(medians):.2f}×: "
              f"{'met' if min(medians) >= 10 else '**not met**'}. maglog on the numba cost "
              f"against pyswarms on the numpy cost (the pairing of the earlier table, not like "
              f"for like) gives {min(numba_over_numpy):.1f}–{max(numba_over_numpy):.1f}×."]
    keys = list(runs)
    ours = [k for k in keys if k.startswith("maglog_")]
    theirs = [k for k in keys if k.startswith("pyswarms_")]
    by_pair = {(p["maglog"], p["pyswarms"]): p for p in c["pairings"]}
    lines += ["", "Every pairing (median speed-up; rows maglog, columns pyswarms):", ""]
    lines += table(["maglog \\ pyswarms"] + [f"{PSO_NAMES[t.rsplit('_', 1)[0]]}, "
                                             f"{t.rsplit('_', 1)[1]}" for t in theirs],
                   [[f"{PSO_NAMES[o.rsplit('_', 1)[0]]}, {o.rsplit('_', 1)[1]}"] +
                    [f"{by_pair[(o, t)]['speedup_median']:.2f}×" for t in theirs]
                    for o in ours], "l" + "r" * len(theirs))
    st = c["startup"]
    pys = c["pyswarms_settings"]
    lines += [
        "",
        f"Each run: {c['particles']} particles × {c['iterations']} iterations × "
        f"{thousands(c['samples'])} samples, {c['repeats']} repeats (seeds 0..{c['repeats'] - 1}), "
        f"numba on {c['numba_threads']} thread(s) "
        f"({report['numba_threading']['threading_layer']} layer); pyswarms "
        f"{c['pyswarms']} with w = {pys['options']['w']:.5f}, c1 = c2 = "
        f"{pys['options']['c1']:.5f} (maglog: χ = {c['maglog_settings']['chi']}, c1 = c2 = "
        f"{c['maglog_settings']['c1']} in the constriction form, the same update), "
        f"LocalBestPSO k = {pys['ring']['k']} (the particle itself and "
        f"{pys['ring']['k'] - 1} neighbours), "
        f"p = {pys['ring']['p']}, static = {pys['static']}.",
        f"- Velocity clamp: both ± the search range per dimension. Initial velocities: maglog "
        f"{c['maglog_settings']['initial_velocity']}, pyswarms {pys['initial_velocity']}. "
        f"Walls: maglog {c['maglog_settings']['walls']}; pyswarms {pys['walls']}. Neighbourhoods: "
        f"maglog {c['maglog_settings']['neighbourhood']}; pyswarms {pys['neighbourhood']}. Cost evaluations "
        f"per run: maglog {runs[ours[0]]['cost_evaluations']} (the start and every "
        f"iteration), pyswarms {runs[theirs[0]]['cost_evaluations']}.",
    ]
    if c.get("thread_scaling"):
        lines.append("- Threads: maglog ring on the numba cost with " + ", ".join(
            f"{t['threads']} thread(s) {ms(t['seconds']['median'])} (median of "
            f"{t['seconds']['repeats']})" for t in c["thread_scaling"]) + ".")
    lines += [
        f"- Start-up, timed apart in fresh interpreters: `import pyswarms` "
        f"{st['pyswarms_import_seconds']:.2f} s; importing maglog's PSO (numba) "
        f"{st['maglog_pso_import_seconds_cold_cache']:.2f} s; the numba kernel's first call "
        f"with an empty cache (JIT compile) {st['numba_first_call_seconds_cold_cache']:.2f} s, "
        f"with the cache filled {st['numba_first_call_seconds_warm_cache']:.2f} s.",
    ]
    return lines


def calib_timing(report):
    lm = report["lm_2000_timing"]
    hour = report["hour_flight"]
    total = hour["stages"]["total"]
    fastest = hour["fastest_run_stages"]
    lines = table(["timing", "best", "median", "worst", "repeats", "goal"], [
        ["deterministic fit of 2,000 samples (`method=\"lm\"`, no PSO)", ms(lm["best"], 2), ms(lm["median"], 2),
         ms(lm["worst"], 2), lm["repeats"], "≤ 2 ms"],
        [f"one-hour 50 Hz flight ({thousands(hour['samples'])} samples): log file → parameters",
         f"{total['best']:.2f} s", f"{total['median']:.2f} s", f"{total['worst']:.2f} s",
         total["repeats"], "≤ 2 s"]], "lrrrrr")
    names = {"read": "read the file", "parse": "parse", "align": "align the cesium reference",
             "pso": "PSO", "polish_and_rest": "polish, uncertainties and checks"}
    rows = []
    for key, label in names.items():
        s = hour["stages"][key]
        if s is None:
            rows.append([label, "not measured", "", "", ""])
            continue
        rows.append([label, f"{fastest[key]:.3f} s", pct(fastest[key] / fastest["total"], 0)
                     + " %", f"{s['median']:.3f} s", f"{s['best']:.3f}–{s['worst']:.3f} s"])
    lines += ["", f"Goals: LM fit ≤ 2 ms (best: {'met' if lm['best'] <= 2e-3 else 'not met'}), "
              f"hour flight ≤ 2 s (best: {'met' if total['best'] <= 2 else 'not met'}; "
              f"worst: {'met' if total['worst'] <= 2 else 'not met'})."]
    lines += ["", f"The hour flight by stage ({hour['log_bytes'] / 2**20:.1f} MiB log, "
              f"{thousands(hour['samples_fitted'])} samples fitted, RMS "
              f"{hour['rms_nT']:.2f} nT):", ""]
    lines += table(["stage", "in the fastest run", "share", "median", "range"], rows,
                   "lrrrr")
    return lines


def calib_ellipsoid(report):
    rows = []
    methods = ["maglog_algebraic", "maglog_constrained", "magyc_ellipsoid_fit",
               "magyc_ellipsoid_fit_fang"]

    def cell(m):
        if m is None:
            return "not run"
        if "ratio" not in m:
            return str(next(iter(m.values())))
        return f"{m['ratio']:.3f} / {m['direction_rms_deg']:.2f}°"
    for row in report["ellipsoid"]:
        coverage, _, noise = row["case"].rpartition("_")
        rows.append([_coverage(coverage), noise] + [cell(row.get(k)) for k in methods])
    lines = table(["coverage", "noise (nT)", "maglog algebraic",
                   "maglog constrained (Li–Griffiths)", "magyc `ellipsoid_fit`",
                   "magyc `ellipsoid_fit_fang`"], rows, "lrllll")
    times = {k: [row[k]["seconds"] for row in report["ellipsoid"]
                 if isinstance(row.get(k), dict) and "seconds" in row[k]] for k in methods}
    lines += ["", "Times per fit (best of 3): " + "; ".join(
        f"{k.replace('_', ' ', 1)} {min(v) * 1e3:.2f}–{ms(max(v), 2)}" for k, v in times.items()
        if v) + "."]
    magyc = [(row["case"], name, row[name]) for row in report["ellipsoid"]
             for name in methods[2:] if isinstance(row.get(name), dict) and "ratio" in row[name]]
    if magyc:
        own = sum(1 for *_, m in magyc if m["returned_field_matches_parameters"])
        reshaped = sum(1 for *_, m in magyc if m["returned_field_matches_reshaped_input"])
        direct = [m["soft_iron_used_directly_ratio"] for _, name, m in magyc
                  if name == "magyc_ellipsoid_fit"]
        lines += [
            f"- The calibrated field magyc returns matches its own parameters applied to the "
            f"samples in {own} of {len(magyc)} fits, and the same parameters applied to the "
            f"(N, 3) samples reshaped (not transposed) to 3 × N in {reshaped} of "
            f"{len(magyc)}; the table uses its parameters (calibrated = soft_iron⁻¹ (b − "
            f"hard_iron)).",
            f"- `ellipsoid_fit`'s soft-iron matrix used directly instead of inverted: ratio "
            f"{min(direct):.2f}–{max(direct):.2f}.",
        ]
    tally = {"equal": 0, "magyc Fang": 0, "maglog algebraic": 0}
    for row in report["ellipsoid"]:
        ours, fang = row.get("maglog_algebraic"), row.get("magyc_ellipsoid_fit_fang")
        if not (isinstance(ours, dict) and "ratio" in ours and isinstance(fang, dict)
                and "ratio" in fang):
            continue
        a, b = round(abs(ours["ratio"] - 1), 3), round(abs(fang["ratio"] - 1), 3)
        tally["equal" if a == b else "magyc Fang" if b < a else "maglog algebraic"] += 1
    lines += [f"- magyc's Fang fit against maglog's algebraic fit, ratio's distance from 1 at "
              f"the table's precision: equal in {tally['equal']} cases, Fang closer in "
              f"{tally['magyc Fang']}, maglog closer in {tally['maglog algebraic']}."]
    ours = [row[k] for row in report["ellipsoid"] for k in methods[:2]
            if isinstance(row.get(k), dict) and "ratio" in row[k]]
    lines += [f"- maglog matrices symmetric positive definite: "
              f"{sum(1 for m in ours if m['positive_definite'])} of {len(ours)}."]
    return lines


def calib_ellipsoid_gate(report):
    rows = []
    for r in report["cases"]:
        now = "accepts" if r["accepted"] else \
            f"refuses: {', '.join(r['undetermined'])} undetermined"
        rows.append([_coverage(r["coverage"]), f"{r['seconds']:.0f} s", f"{r['noise_nT']:g}",
                     r["method"], f"{r['ratio']:.4f}",
                     f"{r['octants_about_centre']} of 8: "
                     + ("accepts" if r["centre_gate_accepts"] else "refuses"),
                     now, f"{r['worst_sigma_over_noise']:.2f}",
                     f"{r['worst_error_nT']:.3g}"])
    lines = table(["coverage", "flight", "noise (nT)", "fit", "ratio (no gate)",
                   "octant gate (issue 14)", "gate on what the fit determines",
                   "worst 1σ / noise", "worst error (nT of field)"], rows, "llrlrllrr")
    fits = [r for r in report["cases"] if r["ratio"] <= 1.0074 and r["coverage"] != "full"]
    accepted = [r for r in fits if r["accepted"]]
    refused = [r for r in fits if not r["accepted"]]
    if refused:
        lines += ["", f"- UAV and near-planar fits that match the samples to a ratio of 1.0074 "
                      f"or better: {len(fits)}. The octant gate refused all {len(fits)}; the "
                      f"gate on what the fit determines accepts {len(accepted)} and refuses "
                      f"{len(refused)}, each naming the parameters whose 1σ exceeds one "
                      f"sample's noise ({min(r['worst_sigma_over_noise'] for r in refused):.2f}"
                      f"–{max(r['worst_sigma_over_noise'] for r in refused):.2f} × the noise; "
                      f"their worst errors against the truth "
                      f"{min(r['worst_error_nT'] for r in refused):.3g}–"
                      f"{max(r['worst_error_nT'] for r in refused):.3g} nT)."]
    return lines


def calib_heading(report):
    rows = [[f"{r['mounting_yaw_deg']:+.0f}°", r["legs"], f"{r['true_offset_deg']:+.2f}°",
             f"{r['found_offset_deg']:+.2f}° ± {r['found_std_deg']:.2f}°"]
            for r in report["heading"]]
    return table(["mounting yaw", "legs", "true offset", "found"], rows, "rrrr")


def calib_lm(report):
    rows = []
    for r in report["rows"]:
        polish = {"hand": "hand-written LM (removed)", "lm": "`least_squares` lm",
                  "trf": "`least_squares` trf"}[r["polish"]]
        if r["solver_used"] != r["polish"]:
            polish += f" (ran {r['solver_used']})"
        rows.append([r["coverage"], r["start"], polish,
                     f"{r['seconds_best'] * 1e3:.2f}", f"{r['seconds_median'] * 1e3:.2f}",
                     f"{r['rms_nT']:.4f}", r["steps"], r["stop"],
                     f"{r['max_abs_dK_vs_lm']:.1e} / {r['max_abs_dc_vs_lm_nT']:.1e}"])
    samples = sorted({r["samples"] for r in report["rows"]})
    return table(["flight", "start", "polish", "best ms", "median ms", "RMS (nT)", "steps",
                  "stop", "max \\|ΔK\\| / \\|Δc\\| (nT) vs lm"], rows, "lllrrrrll") + [
        "", f"{', '.join(map(str, samples))} samples; best and median of {report['repeat']} "
            f"repeats; steps: {report['steps_mean']}."]


def calib_mutation(report):
    outcomes = list(report["counts"])
    rows = [[name] + [counts[o] for o in outcomes] for name, counts in
            sorted(report["by_class"].items())]
    for part in ("calibrate", "survey"):
        if f"{part}_counts" in report:
            rows.append([f"**all {part}** ({report[f'{part}_inputs']:,})"]
                        + [f"**{report[f'{part}_counts'][o]}**" for o in outcomes])
    rows.append(["**all**"] + [f"**{report['counts'][o]}**" for o in outcomes])
    survey = (f", the {report['survey_inputs']:,} survey inputs {report['survey_seconds']:.0f} s "
              f"of worker time" if "survey_inputs" in report else "")
    return table(["class"] + outcomes, rows, "l" + "r" * len(outcomes)) + [
        "", f"{report['inputs']:,} inputs (seed {report['seed']}, card images "
            f"{'built' if report['images'] else 'not built: no FAT tools'}, "
            f"at most {report['time_limit_s']} s an input) in {report['seconds']:.0f} s"
            f"{survey}: {report['failures_total']} tracebacks, hangs or nonsense results."]


def surfaces_mutation(report):
    outcomes = list(report["counts"])
    rows = [[name] + [counts[o] for o in outcomes] for name, counts in
            sorted(report["by_class"].items())]
    rows.append(["**all**"] + [f"**{report['counts'][o]}**" for o in outcomes])
    return table(["class"] + outcomes, rows, "l" + "r" * len(outcomes)) + [
        "", f"{report['inputs']:,} inputs (seed {report['seed']}, scenarios run with "
            f"--max-seconds {report['max_seconds']}, at most {report['time_limit_s']} s and "
            f"{report['memory_limit_bytes'] / 2**30:.0f} GiB an input) in "
            f"{report['seconds']:.0f} s: {report['failures_total']} tracebacks, hangs, "
            f"out-of-memory exits or nonsense results."]



# --- calib_heldout.json -------------------------------------------------------------------

HELDOUT_NAMES = {"maglog_eiv": "maglog eiv (default)", "maglog_paper": "maglog paper",
                 "scipy_lm": "scipy lm", "scipy_trf": "scipy trf (boxed)",
                 "pyswarms_gbest": "pyswarms gbest + polish", "magyc_fang": "magyc Fang"}
HELDOUT_ERRORS = {"default": "default", "paper_a": "Table 1"}


def _heldout_cell(e):
    if "not_run" in e:
        return "not run"
    if e["heldout_worst"] is None:
        cell = "–"
    else:
        cell = f"{e['heldout_worst']:.4f} / {e['heldout_median']:.4f}"
    marks = []
    if e["collapses"]:
        marks.append(f"{e['collapses']} collapsed")
    if e["reflections"]:
        marks.append(f"{e['reflections']} reflected")
    if e["shrunk"]:
        marks.append(f"{e['shrunk']} below 0.9")
    if e["errors"]:
        marks.append(f"{e['errors']} failed")
    return cell + (f" ({', '.join(marks)})" if marks else "")


def calib_heldout(report):
    cases, settings = report["cases"], report["settings"]
    names = [n for n in HELDOUT_NAMES if n in cases[0]["estimators"]]
    rows = [[_coverage(c["coverage"]), HELDOUT_ERRORS.get(c["errors"], c["errors"]),
             f"{c['noise_nT']:g}"] + [_heldout_cell(c["estimators"][n]) for n in names]
            for c in cases]
    lines = table(["coverage", "errors", "noise (nT)"] + [HELDOUT_NAMES[n] for n in names],
                  rows, "llr" + "r" * len(names))
    summary = []
    for n in names:
        got = [c["estimators"][n] for c in cases]
        if any("not_run" in e for e in got):
            summary.append([HELDOUT_NAMES[n], f"not run: {got[0]['not_run']}", "", "", "", "",
                            ""])
            continue

        def worst(key, coverages):
            values = [c["estimators"][n][key] for c in cases if c["coverage"] in coverages
                      and c["estimators"][n][key] is not None]
            return f"{max(values):.4f}" if values else "–"
        summary.append([HELDOUT_NAMES[n], worst("heldout_worst", ("full", "uav")),
                        worst("heldout_worst", ("planar",)),
                        worst("insample_worst", ("full", "uav", "planar")),
                        sum(e["collapses"] for e in got), sum(e["reflections"] for e in got),
                        sum(e["shrunk"] for e in got)])
    per_case = cases[0]["seeds"]
    lines += ["", f"Each cell: worst / median held-out ratio over {per_case} seeds "
              f"({settings['flight_seconds']:g} s flights at {settings['rate_hz']:g} Hz, fitted "
              f"on the first half, scored on the second against the true field; ratio = "
              f"RMS(\\|K b − c\\| − \\|B_true\\|) / the same with the true K and c). "
              f"Collapsed fits (a diagonal element of K below "
              f"{settings['collapse_diagonal']:g} in size) are left out of the ratios and "
              f"counted: the simulated field is constant over a flight, so a "
              f"collapse scores near 0 and a shrunk K below 1 (counted as \"below "
              f"{settings['shrunk_ratio']:g}\"). Reflected: det K < 0.", ""]
    lines += table(["estimator", "worst held-out, full and UAV",
                    "worst held-out, near-planar",
                    "worst in-sample", "collapses", "reflections",
                    f"below {settings['shrunk_ratio']:g}"], summary, "lrrrrrr")
    total = len(cases) * per_case
    n = settings["fit_samples"]
    lines += ["", f"Over all {total} fits per estimator ({len(cases)} cases × {per_case} "
              f"seeds). Goals (issue 13): held-out ≤ {settings['floor_goal']:g} on full and UAV "
              f"coverage, ≤ 1.05 on near-planar. For scale: an unbiased, efficient fit of 9 "
              f"parameters to {thousands(n)} samples leaves on average about √(1 + 9/{n}) = "
              f"{(1 + 9 / n) ** 0.5:.4f} × the floor on new samples and √(1 − 9/{n}) = "
              f"{(1 - 9 / n) ** 0.5:.4f} × on its own; the worst of {per_case} seeds lies above "
              f"that."]
    if report.get("magyc_not_run"):
        lines += ["", f"magyc: not run: {report['magyc_not_run']}."]
    return lines


def calib_heldout_systematic(report):
    cases = report["cases"]
    names = [n for n in HELDOUT_NAMES if n in cases[0]["estimators"]
             and "not_run" not in cases[0]["estimators"][n]]

    def cell(e):
        if e.get("systematic_worst_nT") is None:
            return "–"
        return f"{e['systematic_worst_nT']:.3g} / {e['systematic_median_nT']:.3g}"
    rows = [[_coverage(c["coverage"]), HELDOUT_ERRORS.get(c["errors"], c["errors"]),
             f"{c['noise_nT']:g}"] + [cell(c["estimators"][n]) for n in names] for c in cases]
    return table(["coverage", "errors", "noise (nT)"] + [HELDOUT_NAMES[n] for n in names],
                 rows, "llr" + "r" * len(names)) + [
        "", f"Each cell: worst / median over {cases[0]['seeds']} seeds of RMS(\\|K b − c\\| − "
            "\\|B_true\\|) in nT on the held-out half's attitudes with the sensor's noise left "
            "out (the same error model applied to the true body field without noise): the "
            "error the fitted parameters themselves make where the flight went next, which "
            "a survey line does not average away. Collapsed fits are left out, as above."]


def calib_heldout_z(report):
    cases = report["cases"]
    params = ("k11", "k12", "k13", "k22", "k23", "k33", "c1", "c2", "c3")
    rows = []
    for c in cases:
        for n in ("maglog_eiv", "maglog_paper"):
            e = c["estimators"][n]
            cells = []
            for j in range(9):
                if e["z_rms"][j] is None:
                    cells.append("held" if e["held"][j] else "–")
                else:
                    z = f"{e['z_rms'][j]:.2f}"
                    cells.append(f"**{z}**" if e["z_rms"][j] > 1.3 else z)
            rows.append([_coverage(c["coverage"]), HELDOUT_ERRORS.get(c["errors"], c["errors"]),
                         f"{c['noise_nT']:g}", HELDOUT_NAMES[n].split(" (")[0]] + cells
                        + [sum(e["held"])])
    lines = table(["coverage", "errors", "noise (nT)", "objective"] + list(params)
                  + ["held"], rows, "llrl" + "r" * 10)
    over = [(c, n, p, c["estimators"][n]["z_rms"][j]) for c in cases
            for n in ("maglog_eiv", "maglog_paper") for j, p in enumerate(params)
            if c["estimators"][n]["z_rms"][j] is not None]
    for n in ("maglog_eiv", "maglog_paper"):
        mine = [z for c, m, p, z in over if m == n]
        bad = sum(1 for z in mine if z > 1.3)
        lines += ["", f"{HELDOUT_NAMES[n]}: z-score RMS {min(mine):.2f}–{max(mine):.2f} over "
                  f"{len(mine)} (case, parameter) pairs; above 1.3 (goal ≤ 1.3, bold): {bad}; "
                  f"held to the prior and left out: "
                  f"{sum(sum(c['estimators'][n]['held']) for c in cases)} parameter fits."]
    lines += ["", "z = (estimate − truth) / reported 1σ, RMS over the seeds of a case; a "
              "parameter is counted in a seed when it was not held to the prior (held: its "
              "uncertainty is infinite). The coverage gate's verdict (fits with the parameter "
              "reported not determined / held, of all fits of the coverage):", ""]
    gate = report["gate"]
    rows = []
    for coverage, g in gate.items():
        for n in ("maglog_eiv", "maglog_paper"):
            cells = [f"{g[n]['undetermined'][p]} / {g[n]['held'][p]}" for p in params]
            rows.append([_coverage(coverage), HELDOUT_NAMES[n].split(" (")[0], g["fits"]]
                        + cells)
    lines += table(["coverage", "objective", "fits"] + list(params), rows, "llr" + "r" * 9)
    return lines


HELDOUT_TIMING_NAMES = {"maglog_eiv": "maglog `calibrate_scalar` (default: moments swarm + "
                                      "eiv fit)",
                        "maglog_paper": "maglog `objective=\"paper\"` (moments swarm + "
                                        "least_squares polish)",
                        "pyswarms_gbest": "pyswarms GlobalBestPSO on `cost_numba` + polish",
                        "pyswarms_lbest": "pyswarms LocalBestPSO (k = 3) on `cost_numba` + "
                                          "polish"}


def calib_heldout_timing(report):
    rows, swarm_rows = [], []
    for t in report["timing"]:
        for name, run in t["runs"].items():
            s = run["seconds"]
            stages = run["stages"]
            split = ("" if stages is None else
                     f"{ms(stages['swarm']['median'])} + {ms(stages['polish']['median'])}")
            rows.append([thousands(t["samples"]), HELDOUT_TIMING_NAMES[name], ms(s["best"], 1),
                         ms(s["median"], 1), ms(s["worst"], 1), split,
                         f"{max(run['insample_ratios']):.4f} "
                         f"({'at the floor' if run['at_floor'] else '**not at the floor**'})"])
    lines = table(["samples", "fit", "best", "median", "worst", "swarm + polish (median)",
                   "worst in-sample ratio"], rows, "llrrrrl")
    speed = []
    for t in report["timing"]:
        for s in t["speedups"]:
            speed.append([thousands(t["samples"]), HELDOUT_TIMING_NAMES[s["maglog"]],
                          HELDOUT_TIMING_NAMES[s["pyswarms"]].split(" on ")[0],
                          f"**{s['median']:.1f}×**", f"{s['best']:.1f}×"])
        alone = t["swarm_alone"]["maglog_moments_swarm"]
        for s in t["swarm_speedups"]:
            speed.append([thousands(t["samples"]),
                          f"the swarm alone: maglog's on the moments "
                          f"({ms(alone['median'], 1)} median)",
                          HELDOUT_TIMING_NAMES[s["pyswarms"]].split(" on ")[0] + ", swarm alone",
                          f"{s['median']:.1f}×", f"{s['best']:.1f}×"])
    lines += ["", "Ratios (pyswarms' time / maglog's), **not like for like**: maglog's swarm "
              "searches the moment surrogate, whose cost does not visit the samples, "
              "pyswarms' the exact cost on every sample; the ratios are what the surrogate "
              "buys. The two swarms on the same objective: the next section.", ""]
    lines += table(["samples", "maglog", "pyswarms", "median", "best"], speed, "lllrr")
    first = report["timing"][0]
    verdicts = "; ".join(
        f"{HELDOUT_TIMING_NAMES[ours]}: "
        + ("met" if all(t["goal_met_median"][ours] for t in report["timing"]) else
           "**not met**")
        for ours in ("maglog_eiv", "maglog_paper"))
    st = report["startup"]
    calls = st["first_calls_in_process"]
    settings = report["settings"]
    blas = report["blas_threads"]["default_against_one"]
    lines += ["", f"The earlier goal, ≥ {first['goal_speedup']:g}× (median ratio of the whole "
              f"fit against both pyswarms swarms, at both sizes): {verdicts} (what the ratio "
              f"measures is the surrogate, not the swarm). "
              f"{first['repeats']} repeats each, "
              f"numba on {report['numba_threading']['threads']} thread "
              f"({report['numba_threading']['threading_layer']} layer); swarm "
              f"{settings['particles']} particles × {settings['iterations']} iterations, "
              f"pyswarms w = {settings['pyswarms_options']['w']:g}, c1 = "
              f"{settings['pyswarms_options']['c1']:.5f}, c2 = "
              f"{settings['pyswarms_options']['c2']:.5f}, LocalBestPSO k = "
              f"{settings['pyswarms_ring']['k']}, p = {settings['pyswarms_ring']['p']}; "
              f"pyswarms' swarm searches `calibrate_scalar`'s box on every sample; the polish "
              f"after it is maglog's paper polish (least_squares from the swarm's best, and "
              f"from the identity too when that ends on the box or fails; Talwar's robust "
              f"rounds). Flight: UAV "
              f"coverage, default errors, {first['flight']['rate']:g} Hz, seed "
              f"{first['flight']['seed']}, reference = true field + N(0, "
              f"{settings['reference_noise_nT']:g} nT); \"at the floor\": in-sample ratio ≤ "
              f"{settings['floor_goal']:g} in every repeat; the bench runs with "
              f"OMP_NUM_THREADS={report['blas_threads']['variables']['OMP_NUM_THREADS']} "
              f"(OpenBLAS under numpy and scipy on one thread).",
              "- The BLAS threads left to their default (fresh interpreters, numba on one "
              "thread, 2,000 samples, median): " + "; ".join(
                  f"`objective=\"{o}\"` {ms(blas['default'][o]['median'], 1)} against "
                  f"{ms(blas['one'][o]['median'], 1)} on one BLAS thread "
                  f"({blas['default'][o]['median'] / blas['one'][o]['median']:.1f}×)"
                  for o in ("eiv", "paper")) + ".",
              f"- Start-up, timed apart: `import pyswarms` {st['pyswarms_import_seconds']:.2f} "
              f"s, maglog's PSO module {st['maglog_pso_import_seconds_warm_cache']:.2f} s, "
              f"numba kernel's first call {st['numba_first_call_seconds_cold_cache']:.2f} s "
              f"(empty cache) / {st['numba_first_call_seconds_warm_cache']:.2f} s (cache "
              f"filled), each in a fresh interpreter; first calls in this process: " + ", ".join(
                  f"{k.replace('_', ' ')} {v:.2f} s" for k, v in calls.items()) + "."]
    return lines


SWARM_NAMES = {"maglog_gbest": "maglog gbest", "maglog_ring": "maglog ring",
               "pyswarms_gbest": "pyswarms GlobalBestPSO",
               "pyswarms_lbest": "pyswarms LocalBestPSO (k = 3)"}
SWARM_OBJECTIVES = {"eiv": "`eiv` (default)", "paper": "`paper`"}
#: A difference between the fits with and without the swarm larger than this many of the
#: fit's own 1 sigma (in any parameter), or a different verdict, is a changed result.
SWARM_CHANGED_SIGMA = 0.01


def _swarm_changed(case, objective):
    entry = case[objective]
    if "dK" not in entry:
        return True
    return (entry["pso"].get("success") != entry["lm"].get("success")
            or not entry["dz"] <= SWARM_CHANGED_SIGMA)


def calib_swarm(report):
    settings = report["settings"]
    rows = []
    for t in report["timing"]:
        runs = t["runs"]
        for p in t["pairs"]:
            ours, theirs = runs[p["maglog"]], runs[p["pyswarms"]]
            rows.append([thousands(t["samples"]), SWARM_NAMES[p["maglog"]],
                         SWARM_NAMES[p["pyswarms"]],
                         f"{ms(ours['swarm']['median'])} / {ms(theirs['swarm']['median'])}",
                         f"**{p['swarm_median']:.2f}×**", f"{p['swarm_best']:.2f}×",
                         f"{ms(ours['swarm_and_polish']['median'])} / "
                         f"{ms(theirs['swarm_and_polish']['median'])}",
                         f"{p['swarm_and_polish_median']:.2f}×",
                         f"{max(ours['insample_ratios']):.4f} / "
                         f"{max(theirs['insample_ratios']):.4f}"])
    lines = ["Like for like: the same objective (the paper's exact cost on every sample, "
             "`_pso.cost_numba`), box, swarm, seeds and polish (medians; speed-up = "
             "pyswarms' time / maglog's):", ""]
    lines += table(["samples", "maglog", "pyswarms", "swarm, median (maglog / pyswarms)",
                    "speed-up (median)", "speed-up (best)", "swarm + polish, median",
                    "speed-up (median)", "worst in-sample ratio"], rows, "lllrrrrrr")
    medians = [p["swarm_median"] for t in report["timing"] for p in t["pairs"]]
    bests = [p["swarm_best"] for t in report["timing"] for p in t["pairs"]]
    load = report["load_average"]
    lines += ["", f"Like for like the swarm runs {min(medians):.2f}–{max(medians):.2f}× "
              f"pyswarms' speed (median; best of the repeats {min(bests):.2f}–"
              f"{max(bests):.2f}×), and both end at the same floor after the polish. (Load "
              f"average {load['start'][0]:g} at the start, {load['end'][0]:g} at the end, on "
              f"{report['machine'].get('nproc', '?')} CPUs: the absolute times are a loaded "
              "machine's; the repeats interleave the four swarms, so the load falls on all "
              "of them alike.)", "",
              "What the surrogate buys, maglog against maglog (not a comparison with "
              "pyswarms; medians):", ""]
    rows = []
    for t in report["timing"]:
        s = t["surrogate"]
        rows.append([thousands(t["samples"]), ms(s["swarm_moments"]["median"], 1),
                     ms(s["swarm_numba"]["median"], 1),
                     f"{s['swarm_numba']['median'] / s['swarm_moments']['median']:.0f}×",
                     ms(s["calibrate_scalar_moments"]["median"], 1),
                     ms(s["calibrate_scalar_exact"]["median"], 1),
                     f"{s['calibrate_scalar_exact']['median'] / s['calibrate_scalar_moments']['median']:.0f}×",
                     f"{s['result_difference']['K']:.1e} / {s['result_difference']['c_nT']:.1e} nT"])
    lines += table(["samples", "ring swarm on the moments", "the same swarm on the exact cost",
                    "ratio", "`calibrate_scalar` (moments)", "`calibrate_scalar` "
                    "(`kernel=\"numba\"`, every sample)", "ratio",
                    "their results differ by (K / c)"], rows, "lrrrrrrr")
    lines += ["", "Does the swarm change the result? `calibrate_scalar` with the swarm "
              "(`method=\"pso\"`, the default) against the deterministic start alone "
              "(`method=\"lm\"`: the moment problem's linear solution for `eiv`, the "
              "identity for `paper`):", ""]
    rows = []
    for part, label in (("grid", "held-out grid"), ("poor", "poor starts")):
        for objective, v in report["results"][part].items():
            changed = sum(_swarm_changed(c, objective) for c in report["cases"][part])
            rows.append([label, SWARM_OBJECTIVES[objective], str(v["compared"]),
                         str(v["differ"]), str(changed), f"{v['max_dK']:.1e}",
                         f"{v['max_dc_nT']:.1e}",
                         "–" if v["max_dz"] is None else f"{v['max_dz']:.1e}",
                         f"{v['success_pso']} / {v['success_lm']}"])
    lines += table(["cases", "objective", "fits", f"differ (> {settings['same']:g})",
                    f"changed (> {SWARM_CHANGED_SIGMA:g} σ or verdict)", "largest \\|ΔK\\|", "largest \\|Δc\\| (nT)", "largest \\|Δ\\| / 1σ",
                    "successful (swarm / start alone)"], rows, "llrrrrrrr")
    rows = []
    for name in [p["name"] for p in settings["poor"]]:
        for coverage in ("full", "uav"):
            cases = [c for c in report["cases"]["poor"]
                     if c["errors"] == name and c["coverage"] == coverage]
            cells = []
            for objective in ("eiv", "paper"):
                differ = sum(_swarm_changed(c, objective) for c in cases)
                worst = lambda m: max(c[objective][m].get("heldout", float("inf"))
                                      for c in cases)
                ok = sum(c[objective]["pso"].get("success", False) for c in cases)
                cells.append(f"{worst('pso'):.3g} / {worst('lm'):.3g}; {differ} changed; "
                             f"{ok} successful")
            rows.append([name, {"full": "full sphere", "uav": "UAV ±30°"}[coverage],
                         *cells])
    lines += ["", "Poor starts, per case (worst held-out ratio over the seeds with the swarm "
              "/ from the start alone; fits the swarm changed, as above; fits reported "
              "successful with the swarm):", ""]
    lines += table(["errors", "coverage", "`eiv`", "`paper`"], rows, "llll")
    grid = report["results"]["grid"]
    lines += ["", f"Each timing: {settings['repeats']} repeats (seeds 0..{settings['repeats'] - 1}), "
              f"{settings['particles']} particles × {settings['iterations']} iterations, numba on "
              f"{report['numba_threading']['threads']} thread, OMP_NUM_THREADS="
              f"{settings['omp_num_threads']}; flight: UAV coverage, default errors, "
              f"{settings['timing_flight']['rate']:g} Hz, seed {settings['timing_flight']['seed']}, "
              f"reference = true field + N(0, {settings['reference_noise_nT']:g} nT); pyswarms "
              f"w = {settings['pyswarms_options']['w']:g}, c1 = c2 = "
              f"{settings['pyswarms_options']['c1']:.5f}; the polish: maglog's paper polish "
              "(heldout.py's `paper_polish`). Held-out grid: as the held-out section above, "
              f"{settings['seeds']} seeds per case, {grid['eiv']['fits']} cases; poor starts: "
              f"the errors named, noise 5 nT, {settings['seeds']} seeds each, full sphere and "
              "UAV; \"differ\": |ΔK| or |Δc| / field above "
              f"{settings['same']:g}; the 1σ is the swarm's fit's reported uncertainty."]
    return lines


HOUR_STAGES = {"read": "read the file", "parse_log": "`parse_log`",
               "screen_reference": "screen the cesium (`screen_reference`)",
               "align": "align the cesium to the samples", "screen_samples":
               "screen the samples (`screen_samples`)", "calibrate_scalar": "`calibrate_scalar`"}


def calib_heldout_hours(report):
    runs = report["log_to_parameters"]
    head = ["stage"] + [f"{r['hours']} h: best" for r in runs] \
        + [f"{r['hours']} h: median" for r in runs]
    rows = []
    for key, label in list(HOUR_STAGES.items()) + [("total", "**log text → parameters**")]:
        cells = []
        for field in ("best", "median"):
            for r in runs:
                s = r["stages"][key]
                cells.append("not run" if s is None else f"{s[field]:.3f} s")
        if key == "total":
            cells = [f"**{c}**" for c in cells]
        rows.append([label] + cells)
    lines = table(head, rows, "l" + "r" * (len(head) - 1))
    notes = []
    for r in runs:
        total = r["stages"]["total"]
        goal = ("" if r["goal_seconds"] is None else
                f"; goal ≤ {r['goal_seconds']:g} s: best "
                f"{'met' if r['goal_met_best'] else '**not met**'}, median "
                f"{'met' if r['goal_met_median'] else '**not met**'}")
        screened = (f"rejected {thousands(r['rejected_by_screen'])} samples"
                    if r["screening"] else "not available")
        notes.append(f"- {r['hours']} h: {thousands(r['samples'])} samples, "
                     f"{r['log_bytes'] / 2**20:.1f} MiB of log, best and median of "
                     f"{total['repeats']} repeats"
                     f"{goal}; screening "
                     f"{screened}; "
                     f"fit `{r['objective']}`, RMS {r['rms_nT']:.2f} nT, "
                     f"{'successful' if r['success'] else '**unsuccessful**'}.")
    return lines + [""] + notes


def _allan_cell(entry):
    if entry.get("before") is None and entry.get("after") is None:
        return "not resolved"
    def one(value, span):
        if value is None:
            return "not resolved"
        return f"{value:.4g}" + (f" [{span[0]:.3g}–{span[1]:.3g} s]" if span else "")
    cell = (f"{one(entry['before'], entry.get('before_tau_range_s'))} → "
            f"{one(entry['after'], entry.get('after_tau_range_s'))}")
    if entry.get("reduction_percent") is not None:
        cell += f" ({entry['reduction_percent']:+.1f} %"
        seeds = entry.get("reduction_percent_over_seeds") or {}
        if seeds.get("mean") is not None:
            cell += (f"; {seeds['mean']:+.1f} ± {seeds['std']:.1f} % over "
                     f"{seeds['resolved_in']} of {seeds['of']} seeds")
        cell += ")"
    return cell


def allan_paper_c(report):
    methods = [("slope_regions", "slope regions"),
               ("slope_regions_beyond_10_time_constants", "slope regions, τ ≥ 10 T"),
               ("sum_model", "sum model"), ("single_point", "single-point read (old)")]
    rows = []
    for scenario, terms in report["comparison"].items():
        for term, entry in terms.items():
            paper = entry["paper"]
            rows.append([scenario.replace("_", " "), term.replace("_", " "),
                         f"{entry['truth']:.4g}",
                         f"{paper['before']:.4g} → {paper['after']:.4g} "
                         f"({paper['reduction_percent']:+.1f} %)"]
                        + [_allan_cell(entry[key]) for key, _ in methods])
    f = report["filter"]
    return table(["signal", "term", "truth", "paper C (before → after)"]
                 + [label for _, label in methods], rows, "llrl" + "l" * len(methods)) + [
        "", f"{report['samples']:,} samples at {report['rate_hz']:g} Hz, {report['seeds']} "
            f"seeds (the table's values are the first seed's). Kalman filter: {f['ours']}; "
            f"steady-state gain {f['steady_state_gain']:.4f}, time constant T = "
            f"{f['time_constant_s']:.2f} s."]


# --- machines ---------------------------------------------------------------------------

def machine(report):
    m = report["machine"]
    return table(["", ""], [
        ["CPU", f"`nproc` {m['nproc']}, \"{m['cpu_model']}\""],
        ["memory", m["memory_total"]], ["OS", m["platform"]], ["Python", m["python"]]],
        "ll") + ["", "Tools: " + ", ".join(f"{k} {v}" for k, v in report["tools"].items()) + "."]


def calib_parse(report):
    rows = []
    for key, label in (("one_hour", "one hour"), ("long", f"{report['linearity']['hours']} hours")):
        r = report[key]
        rows.append([label, thousands(r["samples"]), f"{r['log_bytes'] / 2**20:.1f} MiB",
                     f"{r['wall']['best']:.3f} s", f"{r['wall']['median']:.3f} s",
                     f"{r['cpu']['best']:.3f} s", str(r["bad_lines"])])
    reference = report["per_line_reference_one_hour"]
    goals = report["goals"]
    lin = report["linearity"]
    return table(["log", "samples", "size", "best", "median", "CPU (best)", "bad lines"], rows,
                 "lrrrrrr") + [
        "", f"The per-line reader on the hour: {reference['wall']['best']:.3f} s best "
            f"({reference['speedup_best']:.1f}× slower), its result "
            f"{'identical' if reference['identical_to_bulk'] else '**different**'}. "
            f"{lin['hours']} hours take {lin['best_over_hour_best_times_hours']:.2f}× "
            f"{lin['hours']} times the hour (best). Goals: the hour ≤ "
            f"{goals['hour_seconds']:g} s "
            f"({'met' if goals['hour_met_best'] else '**not met**'}), {lin['hours']} hours ≤ "
            f"{goals['ten_hours_seconds']:g} s "
            f"({'met' if goals['ten_hours_met_median'] else '**not met**'}, median); "
            f"{report['one_hour']['wall']['repeats']} repeats each."]


def _survey_rows(report, key):
    return [f["figures"]["compensation"][key] for f in report["flights"]
            if key in f["figures"]["compensation"]]


def survey_compensation(report):
    flights = report["flights"]
    names = list(flights[0]["figures"]["compensation"])
    truth_key = {"uncompensated": "box_residual_raw_nT",
                 "maglog TL18": "box_residual_compensated_nT",
                 "deinterf TL18": "box_residual_deinterf_nT"}
    rows = []
    for name in names:
        cells = _survey_rows(report, name)
        ir = [c["improvement_ratio"] for c in cells]
        fom = [c["fom_nT"] for c in cells]
        key = truth_key.get(name)
        res = [f["figures"]["truth"][key] for f in flights] if key else None
        rows.append([name, f"{statistics.median(ir):.1f} ({min(ir):.1f}–{max(ir):.1f})",
                     f"{statistics.median(fom):.2f}",
                     f"{statistics.median(res):.3f} ({min(res):.3f}–{max(res):.3f})"
                     if res else "–"])
    floor = flights[0]["figures"]["truth"]["noise_floor_nT"]
    return table(["series", "improvement ratio, median (range)", "figure of merit (nT), median",
                  "residual against the truth in the box (nT), median (range)"], rows,
                 "lrrr") + [
        "", f"{len(flights)} flights (seeds {', '.join(str(f['seed']) for f in flights)}); "
            f"noise floor (the cesium's own noise) {floor:g} nT. The band of every figure is "
            "maglog's (chosen from the manoeuvres: "
            + ", ".join(f"{f['figures']['tolles_lawson']['band_hz'][0]:.3g}–"
                        f"{f['figures']['tolles_lawson']['band_hz'][1]:.3g} Hz"
                        for f in flights)
            + "); deinterf fits in its own fixed 0.1–0.6 Hz band with RidgeCV."]


def survey_map(report):
    rows = []
    for f in report["flights"]:
        fig = f["figures"]
        truth, lev, lag = fig["truth"], fig["levelling"], fig.get("lag") or {}
        rows.append([str(f["seed"]), f"{lag.get('lag_s', float('nan')):.3f} s",
                     f"{lev['rms_before_nT']:.3f} → {lev['rms_after_nT']:.3f}",
                     f"{truth['line_anomaly_rms_nT']:.2f}", f"{truth['grid_rms_nT']:.2f}",
                     f"{truth['peak']['recovered_nT']:.1f} / {truth['peak']['true_nT']:.1f}",
                     f"{truth['peak']['distance_m']:.1f} m"])
    return table(["seed", "lag", "crossovers (nT RMS)", "lines vs truth (nT RMS)",
                  "grid vs truth (nT RMS)", "peak: recovered / true (nT)", "peak distance"],
                 rows, "lrrrrrr")


def survey_speed(report):
    per, batch = report["per_hour"], report["batch"]
    steps = {}
    for f in report["flights"]:
        for k, v in f["steps_s"].items():
            steps.setdefault(k, []).append(v)
    step_text = ", ".join(f"{k.removesuffix('_s').replace('_', ' ')} "
                          f"{statistics.median(v):.1f} s" for k, v in steps.items())
    return table(["what", "figure"], [
        ["card to products (reduce), per flight-hour", f"{per['reduce_s_per_flight_hour']:.0f} s"],
        ["scenario build + model backend (fly), per flight-hour",
         f"{per['fly_s_per_flight_hour']:.0f} s"],
        ["one 13.3-min flight reduced, median", f"{per['median_reduce_s']:.1f} s"],
        [f"{batch['jobs']} seeds flown and reduced serially",
         f"{batch['serial_fly_reduce_wall_s']:.1f} s"],
        [f"the same on Dask, {batch['workers']} local workers",
         f"{batch['dask_fly_reduce_wall_s']:.1f} s"],
        ["speed-up of the whole batch path", f"{batch['fly_reduce_speedup']:.2f}×"],
        [f"{batch['jobs']} cards reduced serially", f"{batch['serial_wall_s']:.1f} s"],
        [f"the same on Dask, {batch['workers']} local workers",
         f"{batch['dask_wall_s']:.1f} s"],
        ["speed-up of the reduction alone", f"{batch['speedup']:.2f}×"],
        ["Dask maps and samples identical to the serial ones (digests)",
         "yes" if batch["identical"] else "**no**"],
    ], "lr") + ["", f"Median per step of one reduction: {step_text}. The Dask wall includes "
                    "starting the cluster and each worker's first imports and numba compiles; "
                    f"{report['machine']['nproc']} cores."]


#: name -> (JSON, renderer)
BLOCKS = {
    "machine": ("bench/results/synth.json", machine),
    "synth-frontend": ("bench/results/synth.json", synth_frontend),
    "synth-sd": ("bench/results/synth.json", synth_sd),
    "synth-sdram": ("bench/results/synth.json", synth_sdram),
    "synth-logger": ("bench/results/synth.json", synth_logger),
    "synth-cut": ("bench/results/synth.json", synth_cut),
    "sim-throughput": ("bench/results/sim_throughput.json", sim_throughput),
    "sim-throughput-div27": ("bench/results/sim_throughput_div27.json", sim_throughput),
    "sdio-throughput": ("bench/results/sdio_throughput.json", sdio_throughput),
    "sdram-bandwidth": ("bench/results/sdram_bandwidth.json", sdram_bandwidth),
    "write-amplification": ("bench/results/write_amplification.json", write_amplification),
    "system-speed": ("bench/results/system_speed.json", system_speed),
    "main-command": ("bench/results/main_command.json", main_command),
    "calib-accuracy": ("bench/results/calib.json", calib_accuracy),
    "calib-timing": ("bench/results/calib.json", calib_timing),
    "calib-pso": ("bench/results/calib.json", calib_pso),
    "calib-ellipsoid": ("bench/results/calib.json", calib_ellipsoid),
    "calib-ellipsoid-gate": ("bench/results/calib_ellipsoid_gate.json", calib_ellipsoid_gate),
    "calib-heading": ("bench/results/calib.json", calib_heading),
    "calib-lm": ("bench/results/calib_lm.json", calib_lm),
    "calib-mutation": ("bench/results/calib_mutation.json", calib_mutation),
    "surfaces-mutation": ("bench/results/surfaces_mutation.json", surfaces_mutation),
    "allan-paper-c": ("bench/results/allan_paper_c.json", allan_paper_c),
    "calib-heldout": ("bench/results/calib_heldout.json", calib_heldout),
    "calib-heldout-systematic": ("bench/results/calib_heldout.json",
                                 calib_heldout_systematic),
    "calib-heldout-z": ("bench/results/calib_heldout.json", calib_heldout_z),
    "calib-heldout-timing": ("bench/results/calib_heldout.json", calib_heldout_timing),
    "calib-heldout-hours": ("bench/results/calib_heldout.json", calib_heldout_hours),
    "calib-swarm": ("bench/results/calib_swarm.json", calib_swarm),
    "calib-parse": ("bench/results/calib_parse.json", calib_parse),
    "survey-compensation": ("bench/results/survey.json", survey_compensation),
    "survey-map": ("bench/results/survey.json", survey_map),
    "survey-speed": ("bench/results/survey.json", survey_speed),
}


def render(name, root=REPO):
    """The lines of block ``name``: its content and, last, its provenance line."""
    source, renderer = BLOCKS[name]
    report = json.loads((Path(root) / source).read_text())
    return renderer(report) + ["", provenance_line(report, source)]


def regenerate(text, root=REPO):
    """(the text with every block rendered again, list of problems that are no mere
    difference: unknown blocks, unclosed blocks, tables or provenance lines outside one)."""
    lines = text.split("\n")
    out, problems = [], []
    k = 0
    while k < len(lines):
        line = lines[k]
        marker = MARKER.match(line)
        if marker is None:
            if line.startswith("|"):
                problems.append(f"line {k + 1}: a table outside a generated block "
                                f"(no provenance): {line[:60]}")
            if PROVENANCE.match(line):
                problems.append(f"line {k + 1}: a provenance line that closes no block")
            out.append(line)
            k += 1
            continue
        name = marker.group(1)
        end = next((j for j in range(k + 1, len(lines)) if PROVENANCE.match(lines[j])
                    or MARKER.match(lines[j])), None)
        if end is None or MARKER.match(lines[end]):
            problems.append(f"line {k + 1}: block {name!r} has no provenance line")
            out.append(line)
            k += 1
            continue
        if name not in BLOCKS:
            problems.append(f"line {k + 1}: unknown block {name!r}")
            out += lines[k:end + 1]
        else:
            source = PROVENANCE.match(lines[end]).group(1)
            if source != BLOCKS[name][0]:
                problems.append(f"line {end + 1}: block {name!r} comes from "
                                f"{BLOCKS[name][0]}, its provenance names {source}")
            out += [line] + render(name, root)
        k = end + 1
    return "\n".join(out), problems


def check(path=RESULTS_MD, root=REPO):
    """Problems of ``path`` against the JSONs: [] when every block is as rendered."""
    text = Path(path).read_text()
    new, problems = regenerate(text, root)
    if new != text:
        diff = difflib.unified_diff(text.split("\n"), new.split("\n"), "RESULTS.md",
                                    "from the JSONs", lineterm="", n=0)
        problems.append("blocks differ from their JSONs:\n" + "\n".join(diff))
    return problems


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--check", action="store_true",
                        help="only compare RESULTS.md with the JSONs (exit 1 on a difference)")
    parser.add_argument("--file", type=Path, default=RESULTS_MD)
    args = parser.parse_args(argv)
    if args.check:
        problems = check(args.file)
        for problem in problems:
            print(problem)
        return 1 if problems else 0
    new, problems = regenerate(args.file.read_text())
    args.file.write_text(new)
    for problem in problems:
        print(problem)
    print(f"rewrote the generated blocks of {args.file}")
    return 1 if problems else 0


if __name__ == "__main__":
    sys.exit(main())
