"""``maglog simulate`` and ``maglog run``: a scenario through the whole logger to a card
image, and the main job (that card calibrated, scored against the scenario's truth, and
reported beside the papers' results).

Files a run leaves in its folder (``maglog run -o DIR``; ``maglog simulate -o CARD`` puts
them beside the card image):

``card.img``            the card (sparse), as the firmware left it at the scenario's end
``truth.json``          the scenario's truth (frames per channel and cause, faults, error
                        model, noise floor, phases), ``attitude.csv`` the attitude
``simulation.json``     backend, clock, simulated and wall seconds, the front end's
                        counters, the backend's own figures

Each simulation on an RTL backend keeps the rate it ran at (simulated clock cycles per
wall-clock second) in ``rates.json`` in the build folder (``--build-dir``, by default
``build/sim``); the next run's estimate is made from it: a rate measured on this machine.
``report/``             (run) report.html, the one page to read and share (verdicts,
                        calibration, the papers' comparison, every figure:
                        cli/report_html.py), and what it is made from: summary.json and
                        summary.txt (the verdicts), parameters.json and report.md (the
                        calibration), papers.json and papers.md, the PNGs
"""

import json
import os
import sys
import time
import warnings
from pathlib import Path


__all__ = ["simulate", "main_job", "load", "run_size", "DEFAULT_CARD_BYTES",
           "DEFAULT_CLUSTER_BYTES", "DEFAULT_MAX_SECONDS"]

#: The blank card each run starts from: 1 GiB, 4 KiB clusters (a sparse file; a few MB on
#: disk), formatted with the scenario's seed as volume id (a reproducible image).
DEFAULT_CARD_BYTES = 1 << 30
DEFAULT_CLUSTER_BYTES = 4096
#: Simulated seconds (power-up to the run's end) a run or simulation takes on by default
#: before it refuses; ``--max-seconds`` raises it (up to the scenario limit, six hours).
#: The built-in survey scenario is 800 s; an hour of flight is about 70 minutes on
#: Verilator and days on Icarus.
DEFAULT_MAX_SECONDS = 1200.0
#: The build folder's record of the rates measured here (module docstring).
RATES_FILE = "rates.json"
#: Runs shorter than this (wall-clock seconds) are not timed into RATES_FILE.
MIN_TIMED_S = 1.0


class RunError(Exception):
    """What the command line reports as ``maglog: error: ...``."""


def _quiet_amaranth():
    # amaranth-soc leaves unused action objects behind while it builds registers: noise
    # for a user.
    from amaranth.hdl import UnusedElaboratable
    warnings.filterwarnings("ignore", category=UnusedElaboratable)


def _say(text):
    print(text, file=sys.stderr, flush=True)


def _duration(seconds):
    """A rough duration in the unit that reads best."""
    if seconds >= 3600:
        return f"{seconds / 3600:.3g} h"
    if seconds >= 60:
        return f"{seconds / 60:.3g} min"
    return f"{max(seconds, 1):.0f} s"


def run_size(scenario, backend=None, build_dir=None):
    """A run's size before anything is built: (simulated seconds, simulated clock cycles,
    wall-clock seconds on ``backend`` or None where no rate is known). The rate is the one
    measured here by the last run with ``build_dir`` (:func:`measured_rate`), or without
    one the bench machine's (:data:`~maglog.sim.runners.system.CLOCKS_PER_SECOND`)."""
    from ..sim.runners.system import CLOCKS_PER_SECOND
    seconds = scenario.run_seconds()
    cycles = seconds * scenario.clk_freq
    measured = measured_rate(build_dir, backend) if build_dir is not None else None
    rate = measured[0] if measured else CLOCKS_PER_SECOND.get(backend)
    return seconds, cycles, (cycles / rate if rate else None)


def measured_rate(build_dir, backend):
    """(simulated clock cycles per second, when) that the last run on ``backend`` with
    ``build_dir`` measured on this machine, or None (none yet, or unreadable)."""
    import math
    try:
        entry = json.loads((Path(build_dir) / RATES_FILE).read_text())[backend]
        rate = float(entry["cycles_per_s"])
        when = str(entry.get("measured", "?"))
    except (OSError, ValueError, KeyError, TypeError):
        return None
    return (rate, when) if math.isfinite(rate) and rate > 0 else None


def record_rate(build_dir, backend, cycles, wall_s):
    """Keep the rate a run measured (:data:`RATES_FILE`) for the next estimate; a run too
    short to time, the model backend or a build folder that cannot be written keeps
    nothing."""
    import datetime
    if backend == "model" or not wall_s or wall_s < MIN_TIMED_S:
        return
    rates = _read_rates(build_dir)
    rates[backend] = {"cycles_per_s": cycles / wall_s, "cycles": cycles, "wall_s": wall_s,
                      "measured": datetime.datetime.now(datetime.timezone.utc)
                      .isoformat(timespec="seconds")}
    _write_rates(build_dir, rates)


def _read_rates(build_dir):
    """What :data:`RATES_FILE` holds, or an empty dict for a file missing or not ours."""
    try:
        rates = json.loads((Path(build_dir) / RATES_FILE).read_text())
    except (OSError, ValueError):
        return {}
    return rates if isinstance(rates, dict) else {}


def _write_rates(build_dir, rates):
    """Keep ``rates``; a build folder that cannot be written keeps nothing."""
    path = Path(build_dir) / RATES_FILE
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_text(json.dumps(rates, indent=1) + "\n")
    except OSError:
        pass


def last_stage_seconds(build_dir, name):
    """Wall-clock seconds the stage ``name`` of the last run with ``build_dir`` took here,
    or None."""
    import math
    try:
        seconds = float(json.loads((Path(build_dir) / RATES_FILE).read_text())
                        ["stages"][name])
    except (OSError, ValueError, KeyError, TypeError):
        return None
    return seconds if math.isfinite(seconds) and seconds >= 0 else None


def record_stages(build_dir, stages):
    """Keep a run's stage times (``{name: seconds}``) in :data:`RATES_FILE` for the next
    run's estimates; a build folder that cannot be written keeps nothing."""
    rates = _read_rates(build_dir)
    if not isinstance(rates.get("stages"), dict):
        rates["stages"] = {}
    rates["stages"].update(stages)
    _write_rates(build_dir, rates)


def _estimate(system, backend, build_dir):
    """What simulate() says of the time a run will take: from the rate measured here by
    the last run, or what stands in for it."""
    from ..sim.runners.system import CLOCKS_PER_SECOND
    if backend == "model":
        return ""
    cycles = system.until * system.clk_freq
    build = " (the run only: a Verilator build, once per design, comes first)" \
        if backend == "verilator" else ""
    measured = measured_rate(build_dir, backend)
    if measured:
        return (f"; estimate {_duration(cycles / measured[0])} at {measured[0]:.3g} cycles/s "
                f"measured here ({Path(build_dir) / RATES_FILE}, {measured[1]}){build}")
    if backend == "verilator":
        return ("; no rate measured on this machine yet: the progress line gives the time "
                "left from the simulator's own rate")
    rate = CLOCKS_PER_SECOND[backend]
    return (f"; about {_duration(cycles / rate)} at the {rate:.3g} cycles/s of the project's "
            "bench machine (no rate measured here yet; this run's is kept for the next)")


def load(path, *, max_seconds=None, backend=None, build_dir=None):
    """The scenario at ``path`` (None: the built-in default), built; RunError if bad, or
    (with ``max_seconds``) if its run is estimated to be longer than that (``build_dir``:
    see :func:`run_size`)."""
    from ..sim.stimulus.config import MAX_SCENARIO_S, ScenarioError, load_scenario
    try:
        scenario = load_scenario(path)
    except ScenarioError as error:
        raise RunError(str(error)) from None
    except OSError as error:
        raise RunError(f"{path}: {error.strerror or error}") from None
    seconds, cycles, wall = run_size(scenario, backend, build_dir)
    on = ""
    if wall and backend != "model":
        whose = ("the rate measured here" if build_dir is not None
                 and measured_rate(build_dir, backend) else "the bench machine's rate")
        on = f", ~{_duration(wall)} on {backend} at {whose}"
    if max_seconds is not None and seconds > max_seconds:
        raise RunError(f"{scenario.source}: this run needs about {seconds:,.0f} s of simulated "
                       f"flight ({cycles:.3g} clock cycles{on}), more than --max-seconds "
                       f"{max_seconds:g}; shorten the scenario or raise --max-seconds (up to "
                       f"{MAX_SCENARIO_S:g})")
    if max_seconds is not None:
        _say(f"{scenario.source}: about {seconds:,.0f} s of simulated flight ({cycles:.3g} "
             f"clock cycles{on}), within --max-seconds {max_seconds:g}")
    try:
        return scenario.build()
    except ScenarioError as error:
        raise RunError(str(error)) from None
    except ValueError as error:         # a combination of keys the flight cannot take
        raise RunError(f"{scenario.source}: cannot build the scenario: {error}") from None


def simulate(stimulus, card_path, *, backend, build_dir, card_bytes=DEFAULT_CARD_BYTES,
             progress=True):
    """Run a built scenario (a :class:`~maglog.sim.stimulus.build.Stimulus`) on
    ``backend`` into a fresh card image at ``card_path``; write the truth and
    simulation.json beside it. Returns the :class:`~maglog.sim.runners.result.SystemResult`."""
    from ..sim.models.card_image import CardImage
    from ..sim.runners.system import BackendUnavailable, run_system
    from ..sim.backends.fast import FastBuildError, FastSimulationError
    from ..sw.fat32 import FatError, format_image
    from ..hw.arch.units import hertz
    _quiet_amaranth()
    card_path = Path(card_path)
    folder = card_path.parent
    folder.mkdir(parents=True, exist_ok=True)
    truth = stimulus.truth
    try:
        format_image(card_path, card_bytes, cluster_bytes=DEFAULT_CLUSTER_BYTES,
                     volume_id=truth.get("seed", 0) + 0x4D470000)
    except FatError as error:
        raise RunError(str(error)) from None
    image = CardImage.load(card_path)
    stimulus.write_truth(folder)
    system = stimulus.system
    _say(f"simulating {system.until:.1f} s of flight at {hertz(system.clk_freq)} on "
         f"{backend}" + _estimate(system, backend, build_dir))
    try:
        result = run_system(system, image, backend=backend, build_dir=build_dir,
                            busy_spikes=stimulus.card.get("busy_spikes", ()),
                            progress=sys.stderr if progress else None, log=_say)
    except (BackendUnavailable, FastBuildError, FastSimulationError, ValueError) as error:
        raise RunError(str(error)) from None
    image.save(card_path)
    record_rate(build_dir, backend, system.until * system.clk_freq, result.wall_seconds)
    record = {"backend": result.backend, "clk_freq_hz": system.clk_freq,
              "simulated_s": system.until, "wall_s": result.wall_seconds,
              "real_time_factor": (system.until / result.wall_seconds
                                   if result.wall_seconds else None),
              "counters": result.counters, "stats": result.stats, "led": result.led,
              "card_errors": result.card_errors, "sdram_errors": result.sdram_errors,
              "notes": result.notes}
    (folder / "simulation.json").write_text(json.dumps(record, indent=1) + "\n")
    _say(f"card image: {card_path} ({result.wall_seconds:.1f} s for {system.until:.1f} s "
         f"simulated: real-time factor {record['real_time_factor'] or 0:.2f})")
    for problem in result.card_errors + result.sdram_errors:
        _say(f"warning: device model: {problem}")
    for note in result.notes:
        _say(f"note: {note}")
    return result


def main_job(scenario_path, out_dir, *, backend, build_dir, seed=0, quick_papers=False,
             progress=True, max_seconds=None):
    """The main job: scenario → logger RTL → card → calibration → summary and report.
    Returns the :class:`~maglog.cli.summary.Summary` (printed by the caller)."""
    from ..calib.card import CardError, read_logs
    from ..calib.pipeline import CalibrationError, calibrate_card, write_report
    from .papers import paper_results
    from .summary import summarize
    out = Path(out_dir)
    started = time.perf_counter()
    laps = {}

    def lap(name):
        laps[name] = time.perf_counter() - started - sum(laps.values())

    _say("[1/4] building the scenario")
    stimulus = load(scenario_path, max_seconds=max_seconds, backend=backend,
                    build_dir=build_dir)
    lap("scenario")
    _say(f"[2/4] the logger's RTL on {backend}")
    card = out / "card.img"
    result = simulate(stimulus, card, backend=backend, build_dir=build_dir,
                      progress=progress)
    lap("simulation")
    _say("[3/4] calibrating the card's log")
    run, failure = None, None
    try:
        logs = read_logs(card)
    except CardError as error:
        raise RunError(f"{card}: {error}") from None
    try:
        run = calibrate_card(card, ref="cesium", method="pso", seed=seed,
                             attitude=out / stimulus.truth["flight"]["attitude_csv"])
    except (CardError, CalibrationError) as error:
        failure = error
    lap("calibration")
    papers_key = "report_quick_papers" if quick_papers else "report"
    last = last_stage_seconds(build_dir, papers_key)
    _say("[4/4] report and the papers' results"
         + (f" (the last run here: {_duration(last)})" if last is not None else ""))
    report = out / "report"
    if run is not None:
        try:
            paths = write_report(run, report)
        except CalibrationError as error:
            raise RunError(str(error)) from None
    else:
        report.mkdir(parents=True, exist_ok=True)
        paths = {}
    papers = paper_results(run, stimulus.truth, report, seed=seed, quick=quick_papers)
    summary = summarize(stimulus.truth, result.counters, logs, run,
                        calibration_error=failure, seed=seed)
    record = summary.as_dict()
    record["papers"] = papers.as_dict()
    record["simulation"] = {"backend": result.backend, "wall_s": result.wall_seconds,
                            "simulated_s": stimulus.system.until}
    record["wall_s"] = time.perf_counter() - started
    (report / "summary.json").write_text(json.dumps(record, indent=1, default=str) + "\n")
    (report / "summary.txt").write_text(summary.text + "\n")
    if "markdown" in paths:
        _link_papers(Path(paths["markdown"]), report / "papers.md")
    from .report_html import write_run_report        # the one page: verdicts, calibration,
    try:                                             # papers, figures (from the JSONs)
        page = write_run_report(report)
    except OSError as error:
        raise RunError(f"{report}: cannot write the report page: "
                       f"{error.strerror or error}") from None
    summary.files = {"card": card, "report": page, "markdown": paths.get("markdown"),
                     "papers": report / "papers.md", "summary": report / "summary.json"}
    lap("report and papers")
    record_stages(build_dir, {papers_key: laps["report and papers"]})
    _say("run: " + ", ".join(f"{name} {_duration(seconds)}" for name, seconds in laps.items())
         + f"; {_duration(time.perf_counter() - started)} in all")
    return summary


def _link_papers(report_md, papers_md):
    """Point the calibration report at the papers' page."""
    if papers_md.exists():
        text = report_md.read_text()
        if "papers.md" not in text:
            report_md.write_text(text.rstrip() + "\n\n## The papers' results beside ours\n\n"
                                 "See [papers.md](papers.md).\n")


def default_build_dir():
    """Where simulator builds are kept between runs: ``$MAGLOG_BUILD_DIR`` or
    ``build/sim`` under the current folder."""
    return Path(os.environ.get("MAGLOG_BUILD_DIR", "build/sim"))
