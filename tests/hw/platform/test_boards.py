"""The board platforms: pins from the resources, the pin tables of docs/boards.md, and what
every used pin must carry (3.3-V LVTTL, SD pull-ups, SDRAM I/O registers)."""

import re
from pathlib import Path

import pytest

from maglog.hw.platform.boards import (BOARDS, EQFP144_CLOCK_INPUTS, EQFP144_CONFIG,
                                       EQFP144_DUAL_PURPOSE, EQFP144_POWER, EQFP144_USER_IO,
                                       LVTTL, pin_table, pin_table_markdown)

DOC = Path(__file__).resolve().parents[3] / "docs" / "boards.md"


def _doc_table(board):
    text = DOC.read_text()
    m = re.search(rf"<!-- pins:{re.escape(board)} -->\n(.*?)\n<!-- /pins -->", text, re.S)
    assert m is not None, f"docs/boards.md has no pin table for {board}"
    return m.group(1)


@pytest.mark.parametrize("board", sorted(BOARDS))
def test_doc_pin_table_is_the_code(board):
    assert _doc_table(board) == pin_table_markdown(BOARDS[board])


def test_doc_table_check_fails_on_drift():
    table = pin_table_markdown(BOARDS["de0nano"])
    assert table.replace("| B4 |", "| B5 |") != table      # the SD CMD row names its ball


@pytest.mark.parametrize("board", sorted(BOARDS))
def test_every_pin_is_lvttl_and_used_once(board):
    rows = pin_table(BOARDS[board])
    pins = [row[2] for row in rows]
    assert len(pins) == len(set(pins))
    for signal, _, pin, direction, attrs in rows:
        assert attrs.split(";")[0] == LVTTL, signal
        if signal.startswith(("sd_card_0_cmd", "sd_card_0_dat")):
            assert "WEAK_PULL_UP_RESISTOR=ON" in attrs, signal
        if signal.startswith("sdram_0_dq["):
            for key in ("FAST_INPUT_REGISTER", "FAST_OUTPUT_REGISTER",
                        "FAST_OUTPUT_ENABLE_REGISTER"):
                assert f"{key}=ON" in attrs, signal


def test_ep4ce6_pins_are_user_io_of_eqfp144():
    # The package is power, configuration, dual-purpose and user I/O, each pin once; user
    # I/O and dual-purpose pins are the device overview's 91 for EP4CE6 in E144.
    groups = (EQFP144_POWER, EQFP144_CONFIG, EQFP144_DUAL_PURPOSE, EQFP144_USER_IO)
    assert sum(len(g) for g in groups) == 144
    assert set().union(*groups) == {str(p) for p in range(1, 145)}
    assert len(EQFP144_USER_IO) + len(EQFP144_DUAL_PURPOSE) == 91
    assert EQFP144_CLOCK_INPUTS <= EQFP144_USER_IO
    rows = pin_table(BOARDS["logger-ep4ce6"])
    for signal, _, pin, direction, _ in rows:
        assert pin in EQFP144_USER_IO, (signal, pin)
        if not direction.startswith("i"):
            # Dedicated clock pins are inputs only.
            assert pin not in EQFP144_CLOCK_INPUTS, (signal, pin)
    # The 32-bit SDRAM: 32 DQ, 12 address, 2 bank, 4 DQM, and CKE.
    names = [row[0] for row in rows]
    assert sum(n.startswith("sdram_0_dq[") for n in names) == 32
    assert sum(n.startswith("sdram_0_a[") for n in names) == 12
    assert sum(n.startswith("sdram_0_dqm[") for n in names) == 4
    assert "sdram_0_clk_en" in names


def test_de0nano_breakout_on_gpio0():
    rows = {row[0]: row for row in pin_table(BOARDS["de0nano"])}
    breakout = {name: row[1] for name, row in rows.items()
                if name.startswith(("sd_card", "sensor_uart"))}
    assert len(breakout) == 3 + 6
    assert all(where.startswith("gpio 0:") for where in breakout.values())
    header_pins = {int(where.split(":")[1]) for where in breakout.values()}
    assert not header_pins & {11, 12, 29, 30}          # 5 V, GND, 3.3 V, GND
    # The DE0-Nano's own SDRAM (IS42S16160): 16 DQ, 13 address lines.
    assert sum(n.startswith("sdram_0_dq[") for n in rows) == 16
    assert sum(n.startswith("sdram_0_a[") for n in rows) == 13
    assert rows["clk50_0"][2] == "R8"
