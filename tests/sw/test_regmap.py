"""RegisterMap: addresses and fields come from the gateware's memory map."""

import pytest

from maglog.hw.sdio.host import SdioHost
from maglog.sw.regmap import RegisterMap


@pytest.fixture(scope="module")
def regs():
    return RegisterMap(SdioHost().bus.memory_map)


def test_addresses_follow_the_memory_map(regs):
    host = SdioHost()
    expected = {"_".join(str(p) for p in info.path[-1]): info.start
                for info in host.bus.memory_map.all_resources()}
    assert {r.name: r.address for r in regs} == expected
    assert len(set(expected.values())) == len(expected)


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


def test_committed_register_page_is_current():
    from pathlib import Path
    from maglog.sw.regmap import to_markdown
    page = Path(__file__).resolve().parents[2] / "docs" / "registers.md"
    expected = to_markdown(RegisterMap(SdioHost().bus.memory_map), title="SD host registers")
    assert page.read_text() == expected, "run `maglog hdl regmap -o docs/registers.md`"


def test_c_header_defines_every_field(regs):
    from maglog.sw.regmap import to_c_header
    header = to_c_header(regs, prefix="sdio")
    for reg in regs:
        assert f"#define SDIO_{reg.name.upper()}_ADDR {reg.address:#x}u" in header
        for field in reg.fields.values():
            assert f"SDIO_{reg.name}_{field.name.replace('.', '_')}_MASK".upper() in header
