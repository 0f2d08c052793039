"""``maglog hdl build --board BOARD -o DIR``: a complete Quartus project for a board, written
without Quartus (hw/platform/quartus.py; docs/boards.md)."""

import argparse
import math
import os
import re
from pathlib import Path

__all__ = ["register", "check_output_folder"]

#: What argparse reads as a number after an option even with a leading minus: "-3", "-.5",
#: "-1e-3", "-inf", "-nan" (by default only "-3" and "-.5", so ``--sdram-phase -inf`` was
#: taken for an unknown option).
_NEGATIVE_NUMBER = re.compile(r"^-(\d+\.?\d*|\.\d+)([eE][-+]?\d+)?$|^-(inf|infinity|nan)$",
                              re.IGNORECASE)


def check_output_folder(path, *, force=True):
    """Before any elaboration: make the output folder ``path`` (parents too) and check that
    files can be written in it; with ``force`` False it must be new or empty. Returns
    (path, whether it was made here); raises CliError with the reason."""
    from .main import CliError
    path = Path(path)
    if str(path) == "":
        raise CliError("-o: give a folder name, not ''")
    made = False
    try:
        if path.exists() and not path.is_dir():
            raise CliError(f"{path}: exists and is not a folder (give -o a folder)")
        if path.is_dir() and not force and any(path.iterdir()):
            raise CliError(f"{path}: folder is not empty (use --force to write into it)")
        if not path.is_dir():
            path.mkdir(parents=True)
            made = True
        probe = path / f".maglog-write-test-{os.getpid()}"
        probe.write_bytes(b"")
        probe.unlink()
    except OSError as error:
        if made:
            _remove_empty(path)
        raise CliError(f"cannot write {path}: {error.strerror or error}") from None
    return path, made


def _remove_empty(path):
    try:
        path.rmdir()
    except OSError:
        pass


def _phase_arg(text):
    """``--sdram-phase``: a finite number of nanoseconds."""
    try:
        value = float(text)
    except ValueError:
        value = math.nan
    if not math.isfinite(value):
        raise argparse.ArgumentTypeError(f"expected a finite number of ns, not {text[:60]!r}")
    return value


def _cmd_hdl_build(args):
    from .main import CliError
    from ..hw.platform.boards import BOARDS
    from ..hw.platform.quartus import PROJECT_NAME, build_project
    if args.board not in BOARDS:
        raise CliError(f"unknown board {args.board[:60]!r} (boards: {', '.join(BOARDS)})")
    folder, made = check_output_folder(args.output, force=args.force)
    try:
        written = build_project(args.board, folder, force=args.force,
                                sdram_phase_ns=args.sdram_phase)
    except ValueError as error:
        if made:
            _remove_empty(folder)
        raise CliError(str(error)) from None
    print(f"{args.output}: {len(written)} files, Quartus project {PROJECT_NAME} for "
          f"{args.board}; build with {args.output}/build.sh (needs Quartus Prime)")


def register(hdl_subparsers):
    """Add ``build`` to the ``maglog hdl`` subcommands."""
    from ..hw.platform.boards import BOARDS
    build = hdl_subparsers.add_parser(
        "build", help="write a Quartus project for a board (qsf, sdc, Verilog, NIOS II "
                      "system script, build script) without Quartus")
    # "-inf", "-1e-3" after --sdram-phase are values (then refused or taken), not options.
    build._negative_number_matcher = _NEGATIVE_NUMBER
    # Checked in the command (not `choices`) for a one-line error naming the boards.
    build.add_argument("--board", required=True, metavar="BOARD",
                       help=f"the board: {', '.join(BOARDS)}")
    build.add_argument("-o", "--output", required=True, metavar="DIR",
                       help="the project folder (new or empty, or use --force)")
    build.add_argument("--force", action="store_true",
                       help="write into a folder that is not empty")
    build.add_argument("--sdram-phase", type=_phase_arg, default=-3.0, metavar="NS",
                       help="SDRAM clock phase against the system clock, ns (negative "
                            "leads, within a clock period; default: %(default)s)")
    build.set_defaults(func=_cmd_hdl_build)
    return build
