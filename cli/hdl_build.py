"""``maglog hdl build --board BOARD -o DIR``: a complete Quartus project for a board, written
without Quartus (hw/platform/quartus.py; docs/boards.md)."""

__all__ = ["register"]


def _cmd_hdl_build(args):
    from .main import CliError
    from ..hw.platform.boards import BOARDS
    from ..hw.platform.quartus import PROJECT_NAME, build_project
    if args.board not in BOARDS:
        raise CliError(f"unknown board {args.board!r} (boards: {', '.join(BOARDS)})")
    try:
        written = build_project(args.board, args.output, force=args.force,
                                sdram_phase_ns=args.sdram_phase)
    except ValueError as error:
        raise CliError(str(error)) from None
    print(f"{args.output}: {len(written)} files, Quartus project {PROJECT_NAME} for "
          f"{args.board}; build with {args.output}/build.sh (needs Quartus Prime)")


def register(hdl_subparsers):
    """Add ``build`` to the ``maglog hdl`` subcommands."""
    from ..hw.platform.boards import BOARDS
    build = hdl_subparsers.add_parser(
        "build", help="write a Quartus project for a board (qsf, sdc, Verilog, NIOS II "
                      "system script, build script) without Quartus")
    # Checked in the command (not `choices`) for a one-line error naming the boards.
    build.add_argument("--board", required=True, metavar="BOARD",
                       help=f"the board: {', '.join(BOARDS)}")
    build.add_argument("-o", "--output", required=True, metavar="DIR",
                       help="the project folder (new or empty, or use --force)")
    build.add_argument("--force", action="store_true",
                       help="write into a folder that is not empty")
    build.add_argument("--sdram-phase", type=float, default=-3.0, metavar="NS",
                       help="SDRAM clock phase against the system clock, ns (negative "
                            "leads; default: %(default)s)")
    build.set_defaults(func=_cmd_hdl_build)
    return build
