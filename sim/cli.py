"""The ``maglog`` command line."""

import argparse
import json
import sys
import time
from pathlib import Path

from ..hw.arch import frames as arch_frames


__all__ = ["main"]


class CliError(Exception):
    """A problem the user can fix; printed without a traceback."""


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
        if not sep or not baud.strip().isdigit() or int(baud) <= 0:
            raise argparse.ArgumentTypeError(
                f"each channel is KIND:BAUD with a positive baud rate, not {item!r}")
        configs.append(ChannelConfig(kind, int(baud)))
    return tuple(configs)


def _positive_int(text):
    try:
        value = int(text, 0)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a positive integer, not {text!r}") from None
    if value <= 0:
        raise argparse.ArgumentTypeError(f"expected a positive integer, not {text!r}")
    return value


def _positive_float(text):
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a positive number, not {text!r}") from None
    if not value > 0:
        raise argparse.ArgumentTypeError(f"expected a positive number, not {text!r}")
    return value


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
        sys.stdout.write(text)
        return
    path = Path(output)
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_text(text)
    except OSError as error:
        raise CliError(f"cannot write {path}: {error.strerror}") from None
    print(f"wrote {path} ({what})", file=sys.stderr)


def _cmd_hdl_verilog(args):
    from ..hw.frontend import generate_verilog
    text = generate_verilog(_front_end_from(args))
    _write_output(args.output, text,
                  f"{len(text.splitlines())} lines, top module maglog_frontend")


def _cmd_hdl_regmap(args):
    from ..hw.sdio.host import SdioHost
    from ..sw.regmap import RegisterMap, to_c_header, to_markdown
    regs = RegisterMap(SdioHost().bus.memory_map)
    if args.format == "markdown":
        text = to_markdown(regs, title="SD host registers")
    else:
        text = to_c_header(regs, prefix="sdio")
    _write_output(args.output, text, f"{len(list(regs))} registers")


def _table(header, rows):
    widths = [max(len(str(x)) for x in column) for column in zip(header, *rows)]
    line = lambda cells: "  ".join(str(c).rjust(w) if i else str(c).ljust(w)
                                   for i, (c, w) in enumerate(zip(cells, widths)))
    return "\n".join([line(header), line(["-" * w for w in widths])] + [line(r) for r in rows])


def _cmd_demo(args):
    from ..hw.frontend import DEFAULT_CHANNELS, generate_verilog
    from .frontend_run import ChannelStimulus, FrontEndBench
    from .reference import Kind, reference_filter
    from .streams import demo_streams

    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    channels = DEFAULT_CHANNELS
    names = ("mag", "gps", "cesium")
    streams = demo_streams(seconds=args.seconds, seed=args.seed)
    print(f"[1/3] demo flight: {args.seconds:g} s, seed {args.seed}: "
          + ", ".join(f"{name} {len(streams[name])} bytes" for name in names))

    bench = FrontEndBench(channels, backend=args.backend, build_dir=out / args.backend)
    verilog_path = out / "maglog_frontend.v"
    verilog_path.write_text(generate_verilog(bench.make_dut()))
    print(f"[2/3] front end Verilog: {verilog_path}; simulating on {args.backend} "
          f"(bit time compressed to {16 * args.divisor} clock cycles)")
    stimuli = [ChannelStimulus(divisor=args.divisor, data=streams[name]) for name in names]
    start = time.perf_counter()
    try:
        result = bench.run(stimuli)
    except (RuntimeError, SystemExit) as error:
        raise CliError(f"the {args.backend} simulation failed ({error}); "
                       f"its log is under {out / args.backend}") from None
    elapsed = time.perf_counter() - start

    rows = []
    agree = True
    for k, (config, name) in enumerate(zip(channels, names)):
        counters = result.counters[k]
        ref = reference_filter(Kind(config.kind.value), streams[name])
        agree &= ref.frames == result.frames_of(k) and ref.counters == counters
        rows.append([f"{name} ({config.kind.value})", len(streams[name])] +
                    [counters[c] for c in arch_frames.COUNTER_NAMES])
    print(f"[3/3] {result.cycles} cycles in {elapsed:.1f} s\n")
    print(_table(["channel", "bytes"] + list(arch_frames.COUNTER_NAMES), rows))
    print(f"\nflush events (GGA with a fix): {result.flushes}")
    print(f"reference filter agrees frame for frame and count for count: "
          f"{'yes' if agree else 'NO'}")

    log_path = out / "frames.txt"
    log_path.write_bytes(b"".join(frame for _, frame in result.frames))
    summary = {
        "backend": args.backend, "seconds": args.seconds, "seed": args.seed,
        "cycles": result.cycles,
        "channels": [{"name": n, "kind": c.kind.value, "bytes": len(streams[n]),
                      "counters": result.counters[k]}
                     for k, (c, n) in enumerate(zip(channels, names))],
        "flushes": result.flushes, "reference_agrees": bool(agree),
    }
    (out / "summary.json").write_text(json.dumps(summary, indent=2))
    print(f"kept frames: {log_path}; summary: {out / 'summary.json'}")
    if not agree:
        raise CliError("the gateware and the reference filter disagree")


def _reference_arg(text):
    if text in ("cesium", "igrf"):
        return text
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(
            f"reference must be cesium, igrf or a total field in nT, not {text!r}") from None
    if not value > 0:
        raise argparse.ArgumentTypeError(f"a reference field must be positive, not {text!r}")
    return value


def _cmd_calibrate(args):
    from ..calib.card import CardError
    from ..calib.pipeline import CalibrationError, calibrate_card, write_report
    if not Path(args.card).exists():
        raise CliError(f"{args.card}: no such file")
    print(f"[1/3] reading {args.card}", file=sys.stderr)
    try:
        run = calibrate_card(args.card, ref=args.ref, method=args.method, seed=args.seed,
                             attitude=args.attitude)
    except (CardError, CalibrationError) as error:
        raise CliError(str(error)) from None
    print(f"[2/3] {run.log_name}: {len(run.b)} samples calibrated ({run.method}, "
          f"reference {run.reference})", file=sys.stderr)
    paths = write_report(run, args.out)
    summary = run.summary()
    print(f"[3/3] report: {paths['markdown']}\n")
    rows = [["total-field RMS (nT)", f"{summary['rms_before_nT']:.2f}",
             f"{summary['rms_after_nT']:.2f}"]]
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
    for warning in getattr(run.result, "warnings", []):
        print(f"warning: {warning}")
    print(f"parameters: {paths['json']}")


def _parser():
    from ..hw.frontend import DEFAULT_CHANNELS
    from .frontend_run import BACKENDS

    parser = argparse.ArgumentParser(
        prog="maglog", description="UAV geomagnetic survey logger: gateware, simulation, "
                                   "calibration.")
    commands = parser.add_subparsers(dest="command", metavar="COMMAND", required=True)

    hdl = commands.add_parser("hdl", help="generate hardware description")
    hdl_commands = hdl.add_subparsers(dest="hdl_command", metavar="WHAT", required=True)
    verilog = hdl_commands.add_parser("verilog", help="write the front end's Verilog")
    verilog.add_argument("-o", "--output", default="-",
                         help="output file (default: standard output)")
    verilog.add_argument("--channels", type=_channels_arg, default=DEFAULT_CHANNELS,
                         help="channels in uart_rx order as KIND:BAUD,... with KIND one of "
                              "pmag, nmea, cesium (default: pmag:115200,nmea:9600,cesium:9600)")
    verilog.add_argument("--clk-freq", type=_positive_float, default=50e6,
                         help="system clock in Hz, for the reset baud divisors "
                              "(default: 50e6)")
    verilog.add_argument("--max-frame", type=_positive_int,
                         default=arch_frames.DEFAULT_MAX_FRAME,
                         help="longest NMEA/PMAG frame in bytes (default: %(default)s)")
    verilog.add_argument("--fifo-depth", type=_positive_int, default=1024,
                         help="frame FIFO bytes per channel, a power of two "
                              "(default: %(default)s)")
    verilog.set_defaults(func=_cmd_hdl_verilog)

    regmap = hdl_commands.add_parser(
        "regmap", help="write the register map (from the memory map) as Markdown or a C header")
    regmap.add_argument("--format", choices=("markdown", "c"), default="markdown",
                        help="output format (default: %(default)s)")
    regmap.add_argument("-o", "--output", default="-",
                        help="output file (default: standard output)")
    regmap.set_defaults(func=_cmd_hdl_regmap)

    calibrate = commands.add_parser(
        "calibrate", help="calibrate the magnetometer from a card image or log file")
    calibrate.add_argument("card", help="raw card image, FAT32 partition image, or a "
                                        "plain LOG*.TXT")
    calibrate.add_argument("--ref", type=_reference_arg, default="cesium",
                           help="reference total field: cesium, igrf, or a value in nT "
                                "(default: cesium)")
    calibrate.add_argument("--method", choices=("pso", "lm", "ellipsoid"), default="pso",
                           help="PSO then LM, LM alone, or an ellipsoid fit "
                                "(default: %(default)s)")
    calibrate.add_argument("--seed", type=int, default=0, help="PSO seed (default: 0)")
    calibrate.add_argument("--attitude", metavar="CSV",
                           help="known attitude (t,roll_deg,pitch_deg,heading_deg; t in s "
                                "since 00:00 UTC of the log's date): tilt-compensates the "
                                "headings and plots their error")
    calibrate.add_argument("--out", default="build/calibration",
                           help="report folder (default: %(default)s)")
    calibrate.set_defaults(func=_cmd_calibrate)

    demo = commands.add_parser(
        "demo", help="push the built-in demo flight's serial streams through the front end")
    demo.add_argument("--backend", choices=BACKENDS, default="icarus",
                      help="simulator (default: %(default)s)")
    demo.add_argument("--seconds", type=_positive_float, default=2.0,
                      help="length of the demo flight (default: %(default)s)")
    demo.add_argument("--seed", type=int, default=1, help="stream seed (default: 1)")
    demo.add_argument("--divisor", type=_positive_int, default=1,
                      help="baud divisor in simulation: 16*DIVISOR clock cycles a bit "
                           "(default: %(default)s)")
    demo.add_argument("--out", default="build/demo",
                      help="output folder (default: %(default)s)")
    demo.set_defaults(func=_cmd_demo)
    return parser


def main(argv=None):
    parser = _parser()
    args = parser.parse_args(argv)
    try:
        args.func(args)
    except CliError as error:
        print(f"maglog: error: {error}", file=sys.stderr)
        return 1
    except KeyboardInterrupt:
        print("maglog: interrupted", file=sys.stderr)
        return 130
    return 0


def _entry():
    sys.exit(main())
