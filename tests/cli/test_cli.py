"""The maglog command line: outputs, and clear errors for bad arguments."""

import json
import os
import re
import signal
import subprocess
import sys
from pathlib import Path

import pytest

from maglog.cli import main as cli
from maglog.cli.main import main


def test_hdl_verilog_writes_the_logger(tmp_path, capsys):
    out = tmp_path / "logger.v"
    assert main(["hdl", "verilog", "-o", str(out), "--channels", "nmea:9600,pmag:115200"]) == 0
    assert "top module maglog_logger" in capsys.readouterr().err
    text = out.read_text()
    header = re.search(r"^module maglog_logger\(([^)]*)\);", text, re.M)
    ports = {name.strip() for name in header.group(1).split(",")}
    assert {"clk", "rst", "uart_rx", "sd_cmd_oe", "sdram_dq_i", "led", "button", "wb_adr",
            "wb_ack"} <= ports
    assert "module maglog_frontend" not in text
    assert "input [1:0] uart_rx;" in text


def test_hdl_verilog_frontend_writes_the_front_end_alone(tmp_path, capsys):
    out = tmp_path / "fe.v"
    assert main(["hdl", "verilog", "--frontend", "-o", str(out),
                 "--channels", "nmea:9600,pmag:115200"]) == 0
    assert "top module maglog_frontend" in capsys.readouterr().err
    text = out.read_text()
    assert "module maglog_frontend" in text and "module maglog_logger" not in text
    for port in ("clk", "rst", "uart_rx", "o__valid", "counters__r_data"):
        assert port in text


@pytest.mark.parametrize("argv,message", [
    (["hdl", "verilog", "--channels", "gps:9600"], "channel kind must be one of"),
    (["hdl", "verilog", "--channels", "nmea"], "each channel is KIND:BAUD"),
    (["hdl", "verilog", "--max-frame", "zero"], "expected an integer from 1 to 1024"),
    (["demo", "--seconds", "-1"], "expected a number in (0, 3600]"),
    (["hdl", "regmap", "--format", "pdf"], "invalid choice"),
])
def test_bad_arguments_are_usage_errors(argv, message, capsys):
    with pytest.raises(SystemExit) as exit:
        main(argv)
    assert exit.value.code == 2
    err = capsys.readouterr().err
    assert message in err
    assert err.count("\n") == 1, "a usage error is one line"


def test_values_the_design_cannot_take_are_errors(capsys):
    assert main(["hdl", "verilog", "--max-frame", "5"]) == 1
    assert "Maximum frame length must be an integer" in capsys.readouterr().err
    # 1 MHz cannot make 115200 baud within 1 % (divisor 0.54 rounds to 1: -46 %).
    assert main(["hdl", "verilog", "--clk-freq", "1e6"]) == 1
    err = capsys.readouterr().err
    assert err.startswith("maglog: error: Baud rate 115200 from a 1 MHz clock is off by")
    assert err.count("\n") == 1


def test_unwritable_output(tmp_path, capsys):
    blocker = tmp_path / "file"
    blocker.write_text("")
    assert main(["hdl", "regmap", "-o", str(blocker / "x.md")]) == 1
    assert "cannot write" in capsys.readouterr().err


def test_regmap_formats(capsys):
    assert main(["hdl", "regmap"]) == 0
    out = capsys.readouterr().out
    # Every window, registers named window_register.
    assert "| `logger` | 0x40 | 0x43 |" in out
    assert "| 0x07 | `sdio_status` | r |" in out
    assert "| 0x24 | `frontend_ch0_overlong` | r |" in out
    assert "| 0x54 | `events_status` | rw |" in out
    assert main(["hdl", "regmap", "--format", "c"]) == 0
    out = capsys.readouterr().out
    assert "#define MAGLOG_SDIO_COMMAND_ADDR 0x2u" in out
    assert "#define MAGLOG_DMA_CONTROL_CLEAR_SHIFT 28u" in out
    assert "#define MAGLOG_LOGGER_ID_ADDR 0x40u" in out


def test_demo_on_the_amaranth_backend(tmp_path, capsys):
    assert main(["demo", "--backend", "amaranth", "--seconds", "1", "--out",
                 str(tmp_path)]) == 0
    printed = capsys.readouterr().out
    assert "reference filter agrees frame for frame and count for count: yes" in printed
    summary = json.loads((tmp_path / "summary.json").read_text())
    assert summary["reference_agrees"] is True
    assert sum(c["counters"]["kept"] for c in summary["channels"]) > 0
    assert (tmp_path / "frames.txt").read_bytes().startswith(b"$")


# --- bad values, every option: one line, the right status, no traceback, no hang ---------

#: Values no numeric option takes, whatever its range.
NONSENSE = ["", "x", "inf", "-inf", "nan", "1e308", "-1", "1" + "0" * 309, "0x", "1e", "--"]

#: (arguments before the value, option, values beyond the design's range)
OPTIONS = [
    (["hdl", "verilog"], "--clk-freq", ["0", "999", "5.1e8", "1e12"]),
    (["hdl", "verilog"], "--max-frame", ["0", "1025", "1073741824"]),
    (["hdl", "verilog"], "--fifo-depth", ["0", "1", "65536", "1073741824"]),
    (["hdl", "verilog"], "--channels", ["pmag:0", "pmag:-5", "pmag:1e6", "pmag:9600,",
                                        "pmag:10000000000", "nmea:٩٦٠٠"]),
    (["calibrate", "card.img"], "--seed", ["-1", "4294967296", "1.5"]),
    (["calibrate", "card.img"], "--ref", ["0", "5", "999.9", "1e30", "1e308", "-48000",
                                          "inf", "nan", "", "IGRF", "cesium,igrf"]),
    (["demo"], "--seconds", ["0", "3600.5", "1e6", "1e9"]),
    (["demo"], "--seed", ["-1", "4294967296", "2.0"]),
    (["demo"], "--divisor", ["0", "65536", "100000", "1000000000"]),
    (["demo"], "--max-cycles", ["0", "1e3"]),
    (["hdl", "regmap"], "--format", ["pdf", "C"]),
    (["card", "format", "card.img", "--size", "64MiB"], "--cluster-size",
     ["3000", "64KiB", "0", "1GB"]),
    (["card", "format", "card.img"], "--size", ["0", "33GiB", "40GB", "1.5GB", "8 TB",
                                                "64MiB"]),
    (["demo"], "--backend", ["ghdl", "Icarus"]),
    (["calibrate", "card.img"], "--method", ["PSO", "newton"]),
]
CASES = [pytest.param(head + [option, value], id=f"{option}={value[:12]}")
         for head, option, values in OPTIONS
         for value in (values + (NONSENSE if option not in ("--format", "--backend",
                                                            "--method", "--channels")
                                 else []))
         if not (option in ("--seed",) and value in ("1e308",))]


class _Hang(Exception):
    pass


def _alarm(signum, frame):
    raise _Hang()


@pytest.mark.parametrize("argv", CASES)
def test_bad_values_end_in_one_line(argv, capsys, tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    previous = signal.signal(signal.SIGALRM, _alarm)
    signal.alarm(20)
    try:
        try:
            status = main(argv)
        except SystemExit as exit:
            status = exit.code
    except _Hang:
        pytest.fail(f"maglog {' '.join(argv)} ran for 20 s on a bad value")
    finally:
        signal.alarm(0)
        signal.signal(signal.SIGALRM, previous)
    err = capsys.readouterr().err
    assert status in (1, 2), err
    assert "Traceback" not in err
    assert err.startswith("maglog"), err
    assert err.count("\n") == 1, err


def test_demo_refuses_a_run_beyond_its_cycle_budget(tmp_path, capsys):
    # 16-bit divisor at its maximum: valid, but some 10^10 cycles; said before simulating.
    assert main(["demo", "--divisor", "65535", "--out", str(tmp_path)]) == 1
    err = capsys.readouterr().err
    assert "simulated clock cycles" in err and "raise --max-cycles" in err
    assert not (tmp_path / "icarus").exists()


@pytest.mark.parametrize("command", [["demo"], ["calibrate", "CARD"]])
def test_output_folder_the_os_refuses(command, tmp_path, capsys):
    card = tmp_path / "card.img"
    card.write_bytes(b"not a card")
    command = [str(card) if word == "CARD" else word for word in command]
    blocker = tmp_path / "file"
    blocker.write_text("")
    # (the path named is the one the system refused: for /proc/maglog/x, its parent)
    for out, named in ((blocker, blocker), (blocker / "below", blocker / "below"),
                       ("/proc/maglog/x", "/proc/maglog")):
        assert main(command + ["--out", str(out)]) == 1
        err = capsys.readouterr().err
        assert err.startswith("maglog: error: ") and err.count("\n") == 1, err
        assert str(named) in err


def test_unreadable_card_is_one_line(tmp_path, capsys):
    assert main(["calibrate", str(tmp_path)]) == 1
    assert capsys.readouterr().err == (f"maglog: error: {tmp_path}: is a folder without a "
                                       f"card.img (looked for {tmp_path / 'card.img'}, as "
                                       f"maglog run -o and maglog simulate -o leave it)\n")
    assert main(["calibrate", str(tmp_path / "none.img")]) == 1
    assert "no such file" in capsys.readouterr().err


@pytest.mark.parametrize("what", ["verilog", "regmap"])
def test_closed_standard_output(what):
    # The console script's own entry point, with file descriptor 1 closed.
    code = "import sys; from maglog.cli.main import _entry; sys.argv = ['maglog', 'hdl', %r]; _entry()"
    result = subprocess.run(f"{sys.executable} -c \"{code % what}\" >&-", shell=True,
                            capture_output=False, stderr=subprocess.PIPE, text=True,
                            timeout=120)
    assert result.returncode == 1
    assert result.stderr == ("maglog: error: standard output is closed; "
                             "write to a file with -o FILE\n")


@pytest.mark.skipif(not Path("/dev/full").exists(), reason="no /dev/full on this system")
@pytest.mark.parametrize("what", ["verilog", "regmap"])
def test_full_disk_is_one_line(what, capsys):
    assert main(["hdl", what, "-o", "/dev/full"]) == 1
    assert capsys.readouterr().err == ("maglog: error: cannot write /dev/full: "
                                       "no space left on the device\n")


def test_card_format_writes_a_clean_fat32_image(tmp_path, capsys, fat_tools):
    import shutil
    import subprocess
    image = tmp_path / "card.img"
    assert main(["card", "format", str(image), "--size", "64MiB", "--cluster-size", "512",
                 "--volume-id", "7"]) == 0
    out = capsys.readouterr().out
    assert "clusters:  114,688 of 512 bytes" in out and "from sector 8,192" in out
    # The same arguments give the same bytes; an existing image is kept without --force.
    assert main(["card", "format", str(image), "--size", "64MiB"]) == 1
    assert "exists; formatting replaces it" in capsys.readouterr().err
    again = tmp_path / "again.img"
    assert main(["card", "format", str(again), "--size", "64MiB", "--cluster-size", "512",
                 "--volume-id", "7"]) == 0
    assert again.read_bytes() == image.read_bytes()
    # fsck.fat on the partition (it has no offset option): nothing but banner and summary.
    partition = tmp_path / "partition.img"
    with open(image, "rb") as src, open(partition, "wb") as dst:
        src.seek(8192 * 512)
        shutil.copyfileobj(src, dst)
    result = subprocess.run([fat_tools["fsck.fat"], "-n", str(partition)],
                            capture_output=True, text=True)
    lines = [line for line in result.stdout.splitlines()
             if line and not line.startswith("fsck.fat ")]
    assert result.returncode == 0 and len(lines) == 1 and "/114688 clusters" in lines[0], \
        result.stdout + result.stderr
