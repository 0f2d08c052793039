"""``maglog survey``: card images (or scenario seeds flown through the logger) to compensated,
levelled, gridded anomaly maps with a report (calib/survey.py), one or many at once on Dask
(calib/batch.py).

One card: the products go into ``-o DIR``. Several cards, or ``--scenario`` with
``--seeds``: each goes into ``DIR/<card's folder or file name>`` (``DIR/seed-N``), and
``DIR/batch.json`` lists every job's figures, digest and error.
"""

import argparse
import json
import re
import sys
import time
from pathlib import Path

__all__ = ["register"]

_TOD = re.compile(r"^(\d{1,2}):(\d{2}):(\d{2}(?:\.\d+)?)$")


def _seconds_of_day(text):
    match = _TOD.match(text)
    if not match:
        raise argparse.ArgumentTypeError(f"expected a UTC time HH:MM:SS, not {text!r}")
    h, m, s = int(match[1]), int(match[2]), float(match[3])
    if h > 23 or m > 59 or s >= 60:
        raise argparse.ArgumentTypeError(f"expected a UTC time HH:MM:SS, not {text!r}")
    return 3600 * h + 60 * m + s


def _box_arg(text):
    start, sep, end = text.partition("-")
    if not sep:
        raise argparse.ArgumentTypeError(f"expected START-END in UTC (10:01:20-10:02:40), "
                                         f"not {text!r}")
    a, b = _seconds_of_day(start), _seconds_of_day(end)
    if not b > a:
        raise argparse.ArgumentTypeError(f"the box must end after it starts, not {text!r}")
    return (a, b)


def _band_arg(text):
    try:
        low, high = (float(x) for x in text.split(","))
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected LOW,HIGH in Hz (0.05,0.5), not "
                                         f"{text!r}") from None
    if not 0 < low < high < 1e3:
        raise argparse.ArgumentTypeError(f"expected 0 < LOW < HIGH in Hz, not {text!r}")
    return (low, high)


def _ridge_arg(text):
    from ..calib.survey import RIDGE_RANGE
    if text == "auto":
        return text
    try:
        value = float(text)
    except ValueError:
        value = -1.0
    if not RIDGE_RANGE[0] <= value <= RIDGE_RANGE[1]:
        raise argparse.ArgumentTypeError(
            f"expected auto or a number from {RIDGE_RANGE[0]:g} to {RIDGE_RANGE[1]:g} (the "
            f"range auto searches), not {text[:40]!r}")
    return value


def _seeds_arg(text):
    seeds = []
    try:
        for part in text.split(","):
            first, sep, last = part.partition("-")
            a = int(first)
            b = int(last) if sep else a
            if a < 0 or b < a or b - a > 10_000:
                raise ValueError
            seeds.extend(range(a, b + 1))
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected seeds like 1-4 or 1,5,9, not {text!r}") \
            from None
    return seeds


def _options(args):
    return {"terms": args.terms, "band": args.band, "ridge": args.ridge,
            "max_base_gap_s": args.max_base_gap, "box": args.box, "spacing_m": args.spacing,
            "grid_method": args.grid, "level_order": args.level, "seed": args.seed,
            "lag_s": args.lag,
            "compare_deinterf": not args.no_deinterf}


def _jobs(args, out):
    from ..calib.batch import _beside, _is_survey_truth
    from .main import CliError
    options = _options(args)
    jobs = []
    if args.scenario is not None:
        if args.cards:
            raise CliError("give card images or --scenario with --seeds, not both")
        # base.csv and truth.json of each flight are used unless told otherwise.
        if args.no_base or args.base is not None:
            options["base_station"] = None if args.no_base else str(Path(args.base).resolve())
        if args.no_truth or args.truth is not None:
            options["truth"] = None if args.no_truth else str(Path(args.truth).resolve())
        scenario = args.scenario
        if Path(scenario).exists():
            scenario = str(Path(scenario).resolve())
        # Read once here: a scenario that cannot be read is one error, not one per seed.
        from ..sim.stimulus.config import ScenarioError, load_scenario
        try:
            load_scenario(scenario)
        except (ScenarioError, OSError) as error:
            raise CliError(str(error)) from None
        for seed in args.seeds or [0]:
            jobs.append({"scenario": scenario, "seed": seed, "name": f"seed-{seed}",
                         "out": str((out / f"seed-{seed}").resolve()),
                         "options": dict(options)})
        return jobs
    if not args.cards:
        raise CliError("give at least one card image (or --scenario NAME --seeds N-M)")
    if args.seeds:
        raise CliError("--seeds goes with --scenario")
    from .card import RUN_CARD, card_of
    cards = [card_of(card) for card in args.cards]      # a run's folder: its card.img
    names = [card.resolve().parent.name if card.name == RUN_CARD else card.stem
             for card in cards]
    if len(set(names)) != len(names):
        names = [f"{k + 1}-{name}" for k, name in enumerate(names)]
    for path, name in zip(cards, names):
        values = dict(options)
        base = _beside(path, "base.csv", args.base, args.no_base)
        values["base_station"] = None if base is None else str(Path(base).resolve())
        truth = _beside(path, "truth.json", args.truth, args.no_truth)
        if truth is not None and args.truth is None and not _is_survey_truth(truth):
            truth = None                      # a truth beside the card, not a survey's
        values["truth"] = None if truth is None else str(Path(truth).resolve())
        target = out if len(args.cards) == 1 else out / name
        # Absolute paths: a worker of a remote scheduler starts in its own folder.
        jobs.append({"card": str(path.resolve()), "name": name, "out": str(target.resolve()),
                     "options": values})
    return jobs


def _row(record):
    figures = record["figures"] or {}
    comp = figures.get("compensation", {})
    ours = next((v for k, v in comp.items() if k.startswith("maglog")), {})
    lev = figures.get("levelling", {})
    peak = figures.get("peak", {})
    truth = figures.get("truth", {})
    return [record["name"],
            f"{ours.get('improvement_ratio', float('nan')):.1f}",
            f"{lev['rms_before_nT']:.2f} -> {lev['rms_after_nT']:.2f}"
            if lev.get("crossovers") else "none",
            f"{peak.get('amplitude_nT', peak.get('value_nT', float('nan'))):.1f}",
            f"{truth['grid_rms_nT']:.2f}" if truth else "-",
            f"{record['wall_s']:.0f}"]


class _StageLines:
    """A job's stages on ``stream``, one line each with its time. On a terminal the line is
    written as the stage starts and its time added when it ends; elsewhere (a log, a pipe)
    it is written whole as the stage ends."""

    def __init__(self, stream):
        self.stream = stream
        self.tty = bool(getattr(stream, "isatty", lambda: False)())
        self.open = False

    def __call__(self, label, seconds):
        if seconds is None:
            if self.tty:
                self._write(f"survey: {label} ... ")
                self.open = True
            return
        if self.open:
            self._write(f"{seconds:.1f} s\n")
        else:
            self._write(f"survey: {label}: {seconds:.1f} s\n")
        self.open = False

    def close(self):
        """End a line left open by a stage that failed."""
        if self.open:
            self._write("\n")
            self.open = False

    def _write(self, text):
        self.stream.write(text)
        self.stream.flush()


def _job_lines(started):
    """``run_batch``'s ``on_done``: a line per finished job, with the time left at the rate
    the jobs have finished so far."""

    def rounded(seconds):
        return f"{seconds / 60:.0f} min" if seconds >= 90 else f"{seconds:.0f} s"

    def done_line(record, done, total):
        elapsed = time.perf_counter() - started
        line = (f"survey: {done}/{total} jobs done ({record['name']} "
                f"{'ok' if record['ok'] else 'failed'} in {record.get('wall_s', 0):.0f} s); "
                f"{elapsed:.0f} s so far")
        if done < total:
            line += (f", about {rounded(elapsed / done * (total - done))} left at "
                     f"{elapsed / done:.0f} s a job")
        print(line, file=sys.stderr, flush=True)
    return done_line


def _cmd_survey(args):
    from ..calib.batch import run_batch
    from ..calib.survey_errors import SurveyError
    from .main import CliError, _out_dir, _progress, _table
    out = Path(args.output)
    _out_dir(out)
    jobs = _jobs(args, out)
    serial = args.serial or (len(jobs) == 1 and args.scheduler is None)
    where = ("in this process" if serial else
             f"on the Dask scheduler {args.scheduler}" if args.scheduler else
             f"on a local Dask cluster of {args.workers} workers")
    stages = None
    if not args.quiet:
        _progress(f"survey: {len(jobs)} job{'s' * (len(jobs) != 1)} {where}")
        # One job: its stages; several: a line per job as it finishes.
        stages = _StageLines(sys.stderr) if len(jobs) == 1 else None
    try:
        records = run_batch(jobs, scheduler=args.scheduler, workers=args.workers,
                            serial=serial, stages=stages,
                            on_done=(_job_lines(time.perf_counter())
                                     if len(jobs) > 1 and not args.quiet else None))
    except SurveyError as error:
        raise CliError(str(error)) from None
    finally:
        if stages is not None:
            stages.close()
    if len(jobs) > 1:
        (out / "batch.json").write_text(json.dumps(
            {"jobs": records, "where": where}, indent=1, default=str) + "\n")
    good = [r for r in records if r["ok"]]
    if good:
        print(_table(["job", "improvement ratio", "crossovers (nT RMS)", "peak (nT)",
                      "grid vs truth (nT RMS)", "wall (s)"], [_row(r) for r in good]))
    for record in records:
        if record["ok"]:
            print(f"{record['name']}: report {Path(record['out']) / 'report.md'}, map "
                  f"{Path(record['out']) / 'map.png'}")
            # What makes the result untrustworthy, as the report says it.
            for warning in (record["figures"] or {}).get("warnings", []):
                print(f"warning: {record['name']}: {warning}")
    failed = [r for r in records if not r["ok"]]
    if failed and len(jobs) == 1:
        raise CliError(failed[0]["error"])
    for record in failed:
        print(f"maglog: error: {record['name']}: {record['error']}", file=sys.stderr)
    if len(jobs) > 1:
        print(f"batch: {out / 'batch.json'}")
    if failed:
        raise CliError(f"{len(failed)} of {len(records)} jobs failed (see above)")


def register(commands):
    """Add ``maglog survey``."""
    from .main import SEED_MAX, _float_in, _int_in
    survey = commands.add_parser(
        "survey", help="card images to a compensated, levelled, gridded anomaly map and "
                       "report (many at once on Dask)")
    survey.add_argument("cards", nargs="*", metavar="CARD",
                        help="card images (or partition images, plain logs, or a run's "
                             "folders: their card.img); truth.json and base.csv beside a "
                             "card are used")
    survey.add_argument("-o", "--output", required=True, metavar="DIR",
                        help="the products' folder (one per job under it for several)")
    survey.add_argument("--scenario", metavar="NAME|TOML", default=None,
                        help="fly this scenario (e.g. survey) through the logger (model "
                             "backend) for each of --seeds, then survey the cards")
    survey.add_argument("--seeds", type=_seeds_arg, default=None, metavar="N-M",
                        help="the scenario's seeds: 1-4, or 1,5,9 (default: 0)")
    survey.add_argument("--base", metavar="CSV", default=None,
                        help="base-station file (time_utc,total_nT) for the diurnal "
                             "correction (default: base.csv beside the card, if any)")
    survey.add_argument("--no-base", action="store_true",
                        help="no diurnal correction even if base.csv is beside the card")
    survey.add_argument("--max-base-gap", type=_float_in(0, 86400, low_open=True),
                        default=10.0, metavar="S",
                        help="the longest gap allowed in the base station's record during "
                             "the flight (default: %(default)s s)")
    survey.add_argument("--truth", metavar="JSON", default=None,
                        help="a simulated flight's truth.json: score the result against it "
                             "(default: truth.json beside the card, if it is a survey's)")
    survey.add_argument("--no-truth", action="store_true", help="do not score")
    survey.add_argument("--terms", type=int, choices=(16, 18), default=18,
                        help="Tolles–Lawson terms applied (both are fitted and reported; "
                             "default: %(default)s)")
    survey.add_argument("--band", type=_band_arg, default=None, metavar="LOW,HIGH",
                        help="the compensation's band-pass in Hz (default: from the "
                             "manoeuvres' frequencies); LOW at least 0.02 Hz, HIGH at most "
                             "0.45 x the cesium's rate and at least 1.5 x LOW, the box at "
                             "least two periods of LOW long")
    survey.add_argument("--ridge", type=_ridge_arg, default="auto",
                        help="ridge parameter from 1e-06 to 1e+06 (the range auto "
                             "searches), or auto (blocked cross-validation; default)")
    survey.add_argument("--box", type=_box_arg, default=None, metavar="HH:MM:SS-HH:MM:SS",
                        help="the calibration box in UTC (default: found from the hovering "
                             "manoeuvres)")
    survey.add_argument("--spacing", type=_float_in(0, 1e5, low_open=True), default=None,
                        metavar="M", help="grid spacing (default: a third of the line spacing)")
    survey.add_argument("--grid", choices=("spline", "eqs"), default="spline",
                        help="gridder: verde's spline or harmonica's equivalent sources "
                             "(default: %(default)s)")
    survey.add_argument("--level", type=int, choices=(0, 1), default=0,
                        help="levelling: 0 a constant per line, 1 a linear drift per line "
                             "(default: %(default)s)")
    survey.add_argument("--lag", type=_float_in(-10, 10), default=None, metavar="S",
                        help="the positions' lag behind the samples' times, s: at most what "
                             "moves a sample half the line spacing along its line (default: "
                             "estimated from the crossovers within +-1 s; at the scan's edge "
                             "it is reported as not found)")
    survey.add_argument("--seed", type=_int_in(0, SEED_MAX), default=0,
                        help="the vector calibration's PSO seed (default: 0)")
    survey.add_argument("--no-deinterf", action="store_true",
                        help="leave out the comparison with deinterf")
    survey.add_argument("--workers", type=_int_in(1, 256), default=2,
                        help="local Dask workers for several jobs (default: %(default)s)")
    survey.add_argument("--scheduler", metavar="ADDRESS", default=None,
                        help="a running Dask scheduler (tcp://host:8786) instead of a local "
                             "cluster")
    survey.add_argument("--serial", action="store_true",
                        help="run the jobs one after another in this process (no Dask)")
    survey.add_argument("--quiet", action="store_true",
                        help="no progress lines (one job: each stage and its time; several: "
                             "each job as it finishes, with the time left)")
    survey.set_defaults(func=_cmd_survey)
    return survey
