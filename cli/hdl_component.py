"""``maglog hdl component -o DIR``: the logger as a Platform Designer (Qsys) component for a
NIOS II system: ``_hw.tcl``, Verilog, C register header and README (hw/platform/component.py;
docs/platform-designer.md)."""

__all__ = ["register"]


def _cmd_hdl_component(args):
    from .main import CliError, _os_message
    from .hdl_build import _remove_empty, check_output_folder
    from ..hw.platform.component import write_component
    from ..hw.arch.units import hertz
    kwargs = {"channels": args.channels, "clk_freq": args.clk_freq,
              "max_frame": args.max_frame, "fifo_depth": args.fifo_depth}
    folder, made = check_output_folder(args.output)     # before the elaboration
    try:
        written = write_component(folder, kwargs)
    except (TypeError, ValueError) as error:
        if made:
            _remove_empty(folder)
        raise CliError(str(error)) from None
    except OSError as error:
        raise CliError(f"cannot write {_os_message(error)}") from None
    for path in written:
        print(path)
    print(f"{args.output}: Platform Designer component maglog_logger_avalon "
          f"({hertz(args.clk_freq)} clock); add the folder to the IP search path")


def register(hdl_subparsers):
    """Add ``component`` to the ``maglog hdl`` subcommands; returns its parser."""
    from .main import _add_logger_options
    component = hdl_subparsers.add_parser(
        "component", help="write the logger as a Platform Designer component for a NIOS II "
                          "system (_hw.tcl, Verilog, C register header, README)")
    component.add_argument("-o", "--output", required=True, metavar="DIR",
                           help="the component folder (made if needed; its files replaced)")
    _add_logger_options(component)
    component.set_defaults(func=_cmd_hdl_component)
    return component
