"""``maglog hdl component`` through its own parser (cli/hdl_component.py's ``register``)."""

import argparse
import re

import pytest

from maglog.cli.hdl_component import register
from maglog.cli.main import CliError
from maglog.hw.platform.component import HEADER_NAME, HW_TCL_NAME, README_NAME, VERILOG_NAME


def parse(argv):
    parser = argparse.ArgumentParser(prog="maglog")
    commands = parser.add_subparsers(dest="command", required=True)
    hdl = commands.add_parser("hdl")
    register(hdl.add_subparsers(dest="hdl_command", required=True))
    return parser.parse_args(argv)


def test_writes_the_component_folder(tmp_path, capsys):
    out = tmp_path / "ip" / "maglog"
    args = parse(["hdl", "component", "-o", str(out), "--channels", "nmea:9600",
                  "--clk-freq", "25e6"])
    args.func(args)
    printed = capsys.readouterr().out
    for name in (HW_TCL_NAME, VERILOG_NAME, HEADER_NAME, README_NAME):
        assert (out / name).is_file() and str(out / name) in printed
    tcl = (out / HW_TCL_NAME).read_text()
    assert re.search(r"^add_interface_port uart uart_rx \w+ Input 1$", tcl, re.M)
    assert re.search(r"^set_interface_property clock clockRate 25000000$", tcl, re.M)


def test_refusals_are_cli_errors(tmp_path):
    blocker = tmp_path / "file"
    blocker.write_text("")
    args = parse(["hdl", "component", "-o", str(blocker / "sub")])
    with pytest.raises(CliError, match="cannot write"):
        args.func(args)
    with pytest.raises(SystemExit):
        parse(["hdl", "component"])           # -o is required
