"""Speed of the system runner: simulated flight seconds per wall second, per backend.

The default scenario (sim/stimulus/default.toml: 180 s of flight at the least system clock
the UARTs allow, 16 x 115,200 = 1.8432 MHz) runs through the system runner
(:func:`maglog.sim.runners.system.run_system`: the firmware, the logger top, the device
models) on each backend, with UART bit timing and SD timing as the hardware sees them:

* ``verilator`` (the C++ harness, sim/backends/fast.py) and ``model``: the whole flight;
* the per-pin backends (``verilator-cocotb``, ``icarus``, ``amaranth``: device models in
  Python on the pins): the flight's first seconds only (``--slice``), which take minutes
  already; their real-time factor is that slice's.

Beside them, the limit: the same Verilog and the same C++ harness with no Python at all
(no firmware: the clock, the UART transmitters and the SDRAM chip only, the serial bytes of
the flight's first ``--limit-seconds`` queued up front) — Verilator's own speed on this
design, which the runner must stay within 1.5x of. And the same flight on the fast harness
at a 50 MHz system clock (its first ``--slice-50mhz`` seconds).

The peak memory of a flight of at least an hour on the ``model`` backend is measured in a
child process (its ``ru_maxrss``): the default scenario with 24 survey lines of 1.4 km
(1.8 h of flight with the turns and the multirotor's speed profile).

Run from the repository root: ``.venv/bin/python bench/system_speed.py`` (``--help``).
"""

import argparse
import json
import os
import re
import resource
import subprocess
import sys
import tempfile
import time
from pathlib import Path

sys.dont_write_bytecode = True
from _machine import command_version, load, packages, write_report

BENCH_DIR = Path(__file__).resolve().parent
DEFAULT_OUTPUT = BENCH_DIR / "results" / "system_speed.json"
#: Real-time factor goal on Verilator, and how far the runner may stay below the limit.
GOAL_RTF = 1.0
GOAL_LIMIT_RATIO = 1.5
#: Peak memory goal of a one-hour flight on the model backend.
GOAL_MEMORY_BYTES = 1 << 30
#: A flight of at least an hour: the default scenario with more and longer survey lines.
HOUR_LEGS, HOUR_LEG_LENGTH_M = 24, 1400.0


def _blank_card(folder):
    from maglog.sim.models.card_image import CardImage
    from maglog.sw.fat32 import format_image
    path = Path(folder) / "blank.img"
    if not path.exists():
        format_image(path, 1 << 30, cluster_bytes=4096, volume_id=0x4D474C47)
    return CardImage.load(path)


def _sliced(system, seconds):
    """The scenario cut at ``seconds`` (the presses after it dropped)."""
    import dataclasses
    return dataclasses.replace(system, until=min(system.until, seconds),
                               presses=[p for p in system.presses if p < seconds])


def run_backend(stimulus, backend, seconds, build_dir, folder):
    """One run: wall seconds, simulated seconds, its result's figures."""
    from maglog.sim.runners.system import run_system
    system = stimulus.system if seconds is None else _sliced(stimulus.system, seconds)
    spikes = [s for s in stimulus.card.get("busy_spikes", ()) if s[0] < system.until]
    if backend not in ("verilator", "model"):
        spikes = []
    image = _blank_card(folder)
    start = time.perf_counter()
    result = run_system(system, image, backend=backend, build_dir=build_dir,
                        busy_spikes=spikes)
    total = time.perf_counter() - start
    return {"backend": backend, "clk_freq_hz": system.clk_freq,
            "simulated_s": system.until, "whole_flight": seconds is None,
            "run_wall_s": result.wall_seconds, "call_wall_s": total,
            "real_time_factor": system.until / result.wall_seconds,
            "cycles_per_s": system.until * system.clk_freq / result.wall_seconds,
            "stats": result.stats, "card_errors": len(result.card_errors),
            "sdram_errors": len(result.sdram_errors)}


def harness_alone(stimulus, seconds, build_dir, folder):
    """The Verilog and the C++ harness with no Python in the loop: Verilator's own speed."""
    from maglog.hw.arch.sdram import MT48LC4M32B2
    from maglog.hw.top import Logger
    from maglog.sim.backends.fast import FastHarness, build_harness, burst_bytes
    from maglog.sim.models.logger_sd import ModelCard
    system = stimulus.system
    logger = Logger(channels=system.channels, clk_freq=system.clk_freq,
                    debounce_s=system.debounce_s, max_frame=system.max_frame,
                    chip=MT48LC4M32B2)
    library = build_harness(logger, MT48LC4M32B2, build_dir)
    clk = system.clk_freq
    harness = FastHarness(library, channels=len(system.channels), clk_freq=clk,
                          chip=MT48LC4M32B2, card=ModelCard(_blank_card(folder)))
    try:
        queued = 0
        for k, channel in enumerate(system.channels):
            starts, values, bits = [], [], []
            for burst in system.channel_bursts(k):
                if burst.start >= seconds:
                    break
                more = burst_bytes(burst, channel.baud, clk)
                starts += more[0]
                values += more[1]
                bits += more[2]
            harness.push_bytes(k, starts, values, bits)
            queued += len(values)
        cycles = round(seconds * clk)
        start = time.perf_counter()
        harness.run(cycles)
        wall = time.perf_counter() - start
    finally:
        harness.close()
    return {"clk_freq_hz": clk, "simulated_s": seconds, "bytes_queued": queued,
            "wall_s": wall, "real_time_factor": seconds / wall, "cycles_per_s": cycles / wall}


def _scenario_text(**changes):
    from maglog.sim.stimulus.config import default_scenario_path
    text = default_scenario_path().read_text()
    for key, value in changes.items():
        text, count = re.subn(rf"(?m)^{key}\s*=.*$", f"{key} = {value}", text)
        if count != 1:
            raise RuntimeError(f"the default scenario has {count} lines for {key}")
    return text


def build_stimulus(text=None):
    from maglog.sim.stimulus.config import load_scenario, loads_scenario
    return (load_scenario(None) if text is None else loads_scenario(text)).build()


_HOUR_CHILD = """
import json, resource, sys, time
sys.path.insert(0, {bench!r})
import system_speed as b
start = time.perf_counter()
stimulus = b.build_stimulus(open({scenario!r}).read())
built = time.perf_counter() - start
figures = b.run_backend(stimulus, "model", None, {build!r}, {folder!r})
figures["build_s"] = built
figures["peak_rss_bytes"] = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * 1024
print(json.dumps(figures))
"""


def hour_on_model(build_dir, folder):
    """A one-hour flight on the model backend in a child process: its peak memory."""
    scenario = Path(folder) / "hour.toml"
    scenario.write_text(_scenario_text(legs=HOUR_LEGS, leg_length_m=HOUR_LEG_LENGTH_M))
    code = _HOUR_CHILD.format(bench=str(BENCH_DIR), scenario=str(scenario),
                              build=str(build_dir), folder=str(folder))
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True)
    if done.returncode != 0:
        raise RuntimeError(f"the one-hour run failed:\n{done.stderr[-2000:]}")
    return json.loads(done.stdout.strip().splitlines()[-1])


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--backends", default="verilator,model,verilator-cocotb,icarus,amaranth",
                        help="backends to run (comma-separated)")
    parser.add_argument("--slice", type=float, default=2.0,
                        help="seconds of the flight the per-pin backends run (2)")
    parser.add_argument("--slice-amaranth", type=float, default=0.25,
                        help="seconds the Amaranth simulator runs (0.25)")
    parser.add_argument("--limit-seconds", type=float, default=60.0,
                        help="seconds of the flight the harness alone runs (60)")
    parser.add_argument("--slice-50mhz", type=float, default=2.0,
                        help="seconds of the flight at 50 MHz on the fast harness (2)")
    parser.add_argument("--no-hour", action="store_true", help="skip the one-hour run")
    parser.add_argument("--build-dir", type=Path, default=Path("build/sim"),
                        help="simulator builds (kept between runs; default build/sim)")
    parser.add_argument("--output", type=Path, default=DEFAULT_OUTPUT)
    args = parser.parse_args(argv)
    # The cocotb runner and Verilator's makefiles find their tools on PATH.
    os.environ["PATH"] = f"{Path(sys.executable).parent}{os.pathsep}{os.environ['PATH']}"
    from amaranth.hdl import UnusedElaboratable
    import warnings
    warnings.filterwarnings("ignore", category=UnusedElaboratable)
    load_start = load()
    folder = Path(tempfile.mkdtemp(prefix="system-speed-"))
    stimulus = build_stimulus()
    runs = []
    for backend in args.backends.split(","):
        seconds = {"verilator": None, "model": None,
                   "amaranth": args.slice_amaranth}.get(backend, args.slice)
        print(f"{backend}: {'the whole flight' if seconds is None else f'{seconds} s'} ...",
              flush=True)
        runs.append(run_backend(stimulus, backend, seconds, args.build_dir, folder))
        print(f"  real-time factor {runs[-1]['real_time_factor']:.3f}", flush=True)
    print("the harness alone ...", flush=True)
    limit = harness_alone(stimulus, args.limit_seconds, args.build_dir, folder)
    print(f"  real-time factor {limit['real_time_factor']:.3f}", flush=True)
    print("verilator at 50 MHz ...", flush=True)
    fast50 = run_backend(build_stimulus(_scenario_text(clk_freq_hz="50_000_000.0")),
                         "verilator", args.slice_50mhz, args.build_dir, folder)
    print(f"  real-time factor {fast50['real_time_factor']:.4f}", flush=True)
    hour = None
    if not args.no_hour:
        print("one hour on the model ...", flush=True)
        hour = hour_on_model(args.build_dir, folder)
        print(f"  peak memory {hour['peak_rss_bytes'] / 2**20:.0f} MiB", flush=True)
    fast = next((r for r in runs if r["backend"] == "verilator"), None)
    verdict = {}
    if fast is not None:
        verdict = {"rtf_goal": GOAL_RTF, "rtf_met": fast["real_time_factor"] >= GOAL_RTF,
                   "limit_ratio": limit["real_time_factor"] / fast["real_time_factor"],
                   "limit_ratio_goal": GOAL_LIMIT_RATIO}
        verdict["limit_ratio_met"] = verdict["limit_ratio"] <= GOAL_LIMIT_RATIO
    if hour is not None:
        verdict["memory_goal_bytes"] = GOAL_MEMORY_BYTES
        verdict["memory_met"] = hour["peak_rss_bytes"] <= GOAL_MEMORY_BYTES
    write_report(args.output, "system_speed", argv, load_start,
                 {**packages("amaranth", "cocotb", "verilator"),
                  "iverilog": command_version("iverilog", "-V"),
                  "c++": command_version("c++", "--version")},
                 scenario="default", runs=runs, harness_alone=limit, verilator_50mhz=fast50,
                 hour_on_model=hour, verdict=verdict)
    return 0


if __name__ == "__main__":
    sys.exit(main())
