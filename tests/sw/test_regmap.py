"""RegisterMap: addresses and fields come from the gateware's memory map.

The expected addresses, windows and field offsets are written here literally, from the
register documentation (docs/registers.md, DESIGN.md), not derived from the memory map under
test: a register that moves must fail this file until it and the page are updated together.
"""

import re
from pathlib import Path

import pytest

from maglog.hw.arch.sdram import MT48LC4M32B2
from maglog.hw.dma import Dma
from maglog.hw.sdio.host import SdioHost
from maglog.hw.storage import Storage
from maglog.hw.top import Logger
from maglog.sw.regmap import RegisterMap, windows

#: The SD host's registers: name → word address.
SDIO_REGISTERS = {
    "clock": 0x00, "argument": 0x01, "command": 0x02, "blocks": 0x03, "timeouts": 0x04,
    "busy_timeout": 0x05, "read_timeout": 0x06, "status": 0x07, "accepted": 0x08,
    "response0": 0x09, "response1": 0x0A, "response2": 0x0B, "response3": 0x0C,
}
#: The DMA's registers, at their offsets within its own map (its window in Storage).
DMA_REGISTERS = {
    "control": 0x0, "release": 0x1, "status": 0x2, "level": 0x3, "high_water": 0x4,
    "kept": 0x5, "dropped": 0x6, "buffer_seek": 0x7, "buffer_write": 0x8, "buffer_read": 0x9,
}
#: Storage's windows: name → base word address.
STORAGE_WINDOWS = {"sdio": 0x00, "dma": 0x10}
#: The logger's windows: name → base word address (on the CSR bus and on Wishbone alike).
LOGGER_WINDOWS = {
    "sdio": 0x00, "dma": 0x10, "frontend": 0x20, "logger": 0x40, "leds": 0x44,
    "button": 0x46, "rtc": 0x48, "watchdog": 0x4C, "gps": 0x50, "events": 0x54,
}
#: The front end's registers: 8 per channel (divisor, kept, then drops by cause).
FRONTEND_REGISTERS = {
    f"ch{k}_{name}": 8 * k + offset
    for k in range(3)
    for offset, name in enumerate(("divisor", "kept", "checksum", "not_whitelisted",
                                   "overlong", "bad_byte", "uart_error", "overflow"))
}
#: Each window's registers at their offsets in the window.
WINDOW_REGISTERS = {
    "sdio": SDIO_REGISTERS,
    "dma": DMA_REGISTERS,
    "frontend": FRONTEND_REGISTERS,
    "logger": {"id": 0, "control": 1, "status": 2, "fw_status": 3},
    "leds": {"value": 0},
    "button": {"status": 0},
    "rtc": {"seconds": 0, "subsec": 1},
    "watchdog": {"control": 0, "kick": 1, "status": 2},
    "gps": {"time": 0, "date": 1, "status": 2},
    "events": {"status": 0},
}
#: Fields of the registers the firmware's application loop uses, beyond the SD host's.
LOGGER_FIELDS = {
    "dma_control": {"start": (0, 1), "source": (1, 1), "arm_read": (2, 1), "sectors": (3, 12),
                    "first": (15, 12), "abort": (27, 1), "clear": (28, 1)},
    "frontend_ch1_divisor": {"value": (0, 16)},
    "frontend_ch2_overflow": {"count": (0, 32)},
    "logger_id": {"magic": (0, 32)},
    "logger_control": {"record": (0, 1)},
    "logger_status": {"in_frame": (0, 1), "sdram_ready": (1, 1), "button": (2, 1)},
    "logger_fw_status": {"state": (0, 4), "error": (4, 8), "file": (12, 17)},
    "leds_value": {"value": (0, 4)},
    "button_status": {"level": (0, 1)},
    "rtc_seconds": {"value": (0, 32)},
    "rtc_subsec": {"millis": (0, 10)},
    "watchdog_control": {"enable": (0, 1), "timeout_ms": (1, 16)},
    "watchdog_kick": {"kick": (0, 1)},
    "watchdog_status": {"reset_cause": (0, 1)},
    "gps_time": {"second": (0, 6), "minute": (6, 6), "hour": (12, 5)},
    "gps_date": {"day": (0, 5), "month": (5, 4), "year": (9, 12)},
    "gps_status": {"valid": (0, 1)},
    "events_status": {"fix": (0, 1), "dma_done": (1, 1), "sd_error": (2, 1),
                      "ring_overflow": (3, 1), "button": (4, 1), "zda": (5, 1)},
}
#: Fields of the SD host's registers: name → {field: (bit offset, width)}.
SDIO_FIELDS = {
    "clock": {"divisor": (0, 10), "run": (10, 1)},
    "command": {"index": (0, 6), "kind": (6, 2), "r1b": (8, 1), "data": (9, 2)},
    "blocks": {"count": (0, 16)},
    "timeouts": {"response": (0, 16)},
    "busy_timeout": {"ticks": (0, 16)},
    "read_timeout": {"ticks": (0, 16)},
    "status": {
        "cmd_busy": (0, 1), "dat_busy": (1, 1),
        "cmd.timeout": (2, 1), "cmd.crc_error": (3, 1), "cmd.format_error": (4, 1),
        "cmd.end_error": (5, 1),
        "write.crc_rejected": (6, 1), "write.write_error": (7, 1), "write.no_token": (8, 1),
        "write.bad_token_end": (9, 1), "write.busy_timeout": (10, 1),
        "read.timeout": (11, 1), "read.crc_error": (12, 1), "read.end_error": (13, 1),
        "busy_timeout": (14, 1), "dat_level": (15, 4),
    },
    "accepted": {"count": (0, 16)},
    **{name: {"value": (0, 32)} for name in ("argument", "response0", "response1",
                                             "response2", "response3")},
}


@pytest.fixture(scope="module")
def regs():
    return RegisterMap(SdioHost().bus.memory_map)


def test_sd_host_addresses(regs):
    assert {r.name: r.address for r in regs} == SDIO_REGISTERS


def test_sd_host_fields(regs):
    assert {r.name: {f.name: (f.offset, f.width) for f in r.fields.values()}
            for r in regs} == SDIO_FIELDS


def test_dma_addresses():
    assert {r.name: r.address for r in RegisterMap(Dma().bus.memory_map)} == DMA_REGISTERS


def test_storage_windows():
    memory_map = Storage(MT48LC4M32B2, clk_freq=50e6).bus.memory_map
    for window, registers in (("sdio", SDIO_REGISTERS), ("dma", DMA_REGISTERS)):
        found = RegisterMap(memory_map, window=window)
        assert {r.name: r.address for r in found} == {
            name: STORAGE_WINDOWS[window] + offset for name, offset in registers.items()}
    # Nothing else in the map: every resource sits in one of the two windows.
    assert {info.path[0][0] for info in memory_map.all_resources()} == set(STORAGE_WINDOWS)


@pytest.fixture(scope="module")
def logger():
    return Logger()


def test_logger_windows_and_offsets(logger):
    # The firmware's view: one RegisterMap per window, over the Wishbone slave's map.
    for window, registers in WINDOW_REGISTERS.items():
        found = RegisterMap(logger.bus.memory_map, window=window)
        assert {r.name: r.address for r in found} == {
            name: LOGGER_WINDOWS[window] + offset for name, offset in registers.items()}, window
    # Nothing outside these windows, on either map.
    for memory_map in (logger.bus.memory_map, logger.csr_memory_map):
        assert {info.path[0][0] for info in memory_map.all_resources()} == set(LOGGER_WINDOWS)
    assert {name: first for name, (first, _) in windows(logger.csr_memory_map).items()} \
        == LOGGER_WINDOWS


def test_logger_whole_map_names_and_fields(logger):
    regs = RegisterMap(logger.csr_memory_map)
    assert {r.name: r.address for r in regs} == {
        f"{window}_{name}": LOGGER_WINDOWS[window] + offset
        for window, registers in WINDOW_REGISTERS.items() for name, offset in registers.items()}
    for name, fields in LOGGER_FIELDS.items():
        assert {f.name: (f.offset, f.width) for f in regs[name].fields.values()} == fields, name


def test_struct_fields_are_flattened(regs):
    status = regs["status"]
    names = list(status.fields)
    assert names[:3] == ["cmd_busy", "dat_busy", "cmd.timeout"]
    assert "write.crc_rejected" in names and "read.crc_error" in names
    # Fields tile the register without overlap.
    offsets = sorted((f.offset, f.width) for f in status.fields.values())
    for (a, w), (b, _) in zip(offsets, offsets[1:]):
        assert a + w == b


def test_encode_decode_round_trip(regs):
    command = regs["command"]
    word = command.encode(index=25, kind=1, r1b=0, data=1)
    assert command.decode(word) == {"index": 25, "kind": 1, "r1b": 0, "data": 1}
    status = regs["status"]
    word = status.encode(cmd__crc_error=1, dat_level=0b1010)
    assert status.decode(word)["cmd.crc_error"] == 1
    assert status.decode(word)["dat_level"] == 0b1010


def test_errors_name_what_exists(regs):
    with pytest.raises(KeyError, match="No register 'nope'; there are clock, argument"):
        regs["nope"]
    with pytest.raises(KeyError, match="Register command has no field 'speed'"):
        regs["command"].field("speed")
    with pytest.raises(ValueError, match="Field index is 6 bits wide; 64 does not fit"):
        regs["command"].encode(index=64)


PAGE = Path(__file__).resolve().parents[2] / "docs" / "registers.md"


def test_committed_register_page_is_current(logger):
    from maglog.sw.regmap import to_markdown
    expected = to_markdown(RegisterMap(logger.csr_memory_map), title="Logger registers",
                           memory_map=logger.csr_memory_map)
    assert PAGE.read_text() == expected, "run `maglog hdl regmap -o docs/registers.md`"


def test_register_page_lists_the_documented_addresses():
    text = PAGE.read_text()
    rows = re.findall(r"^\| (0x[0-9a-f]+) \| `(\w+)` \|", text, re.M)
    assert {name: int(address, 16) for address, name in rows} == {
        f"{window}_{name}": LOGGER_WINDOWS[window] + offset
        for window, registers in WINDOW_REGISTERS.items() for name, offset in registers.items()}
    bases = re.findall(r"^\| `(\w+)` \| (0x[0-9a-f]+) \|", text, re.M)
    assert {name: int(first, 16) for name, first in bases} == LOGGER_WINDOWS


def test_c_header_defines_every_field(regs):
    from maglog.sw.regmap import to_c_header
    header = to_c_header(regs, prefix="sdio")
    for reg in regs:
        assert f"#define SDIO_{reg.name.upper()}_ADDR {reg.address:#x}u" in header
        for field in reg.fields.values():
            assert f"SDIO_{reg.name}_{field.name.replace('.', '_')}_MASK".upper() in header
