"""The whole logger under cocotb (sim/backends/cocotb_system.py): the generated Verilog with
the SDRAM and SD card models on its pins and the firmware on its Wishbone port.

The application's recording of the short scenario must leave a card that ``fsck.fat -n``
finds clean and whose LOG file holds exactly the frames the reference filter keeps between
the two presses (``SystemScenario.recorded_frames``), read back by calib.card.
"""

import re

import pytest

from maglog.calib.card import read_logs
from maglog.hw.top import Logger, generate_verilog
from maglog.sim.models.card_image import CardImage
from maglog.sim.models.sdram import PINS as SDRAM_PINS
from maglog.sim.stimulus.system import short_scenario
from maglog.sim.backends.cocotb_system import (RESET_CYCLES, SDRAM_PACKED, TOPLEVEL,
                                               run_system_cocotb, settings_to_json,
                                               system_verilog)
from maglog.sw.app import AppSettings
from maglog.sw.fat32 import format_image

from ..sw.test_fat32 import fsck_findings

MiB = 1 << 20
VOLUME_ID = 0x4D474C47


def blank_card(path):
    """A freshly formatted card (40 MiB, 512-byte clusters, as the firmware's own tests
    use: 256 MiB with 4 KiB clusters has too few clusters for FAT32)."""
    format_image(path, 40 * MiB, cluster_bytes=512, volume_id=VOLUME_ID)
    return CardImage.load(path)


@pytest.fixture(scope="module")
def build_dir(tmp_path_factory):
    # One folder for the module: each backend builds the logger once.
    return tmp_path_factory.mktemp("system_cocotb")


# -- without a simulator ------------------------------------------------------------------------

def _module_ports(text, name):
    header = text[text.index(f"module {name}("):]
    return re.findall(r"\w+", header[header.index("(") + 1:header.index(");")])


def test_the_wrapper_has_the_loggers_ports_and_the_packed_sdram_and_sd_pins():
    scenario = short_scenario()
    verilog = generate_verilog(Logger(channels=scenario.channels, clk_freq=scenario.clk_freq))
    text = system_verilog(verilog)
    assert text.startswith(verilog)
    logger_ports = _module_ports(verilog, "maglog_logger")
    ports = _module_ports(text, TOPLEVEL)
    assert ports[-3:] == ["sim_sdram", "sim_sd", "sim_sdram_command"]
    assert sorted(ports[:-3]) == sorted(set(logger_ports) - {"rst"})
    wrapper = text[text.index(f"module {TOPLEVEL}("):]
    for name in logger_ports:
        assert f".{name}({name})" in wrapper
        assert (f" {name} /*verilator public_flat_rw*/;" in wrapper) == (name != "rst")
    # rst from the power-on reset: high for the first RESET_CYCLES clocks.
    assert f"wire rst = por_count != 3'd{RESET_CYCLES};" in wrapper
    # 1 + 1 + 1 + 1 + 1 + 1 (cke .. dq_oe) + 2 (ba) + 12 (a) + 4 (dqm) + 32 (dq_o) bits.
    assert "output [55:0] sim_sdram /*verilator public_flat_rw*/;" in wrapper
    assert ("assign sim_sdram = {sdram_dq_o, sdram_dqm, sdram_a, sdram_ba, sdram_dq_oe, "
            "sdram_we_n, sdram_cas_n, sdram_ras_n, sdram_cs_n, sdram_cke};") in wrapper
    assert tuple(SDRAM_PACKED[:6]) == ("cke", "cs_n", "ras_n", "cas_n", "we_n", "dq_oe")
    # Every pin the chip model takes, and only those (dq_o is its dq).
    assert sorted(SDRAM_PACKED) == sorted((*SDRAM_PINS, "dq_o"))
    assert "assign sim_sd = {sd_dat_o, sd_dat_oe, sd_cmd_o, sd_cmd_oe};" in wrapper


def test_a_logger_without_sdram_pins_is_refused():
    with pytest.raises(ValueError, match="module maglog_logger has no port sdram_cke, "):
        system_verilog("module maglog_logger(clk, rst);\n  input clk;\n  input rst;\n"
                       "endmodule\n")


def test_settings_cross_as_their_plain_fields():
    settings = AppSettings(poll_s=0.001, watchdog_timeout_ms=500, resume=False)
    plain = settings_to_json(settings)
    assert plain["poll_s"] == 0.001 and plain["watchdog_timeout_ms"] == 500
    assert plain["resume"] is False
    assert "fault" not in plain and "patterns" not in plain
    assert AppSettings(**plain) == AppSettings(poll_s=0.001, watchdog_timeout_ms=500,
                                               resume=False)


def test_settings_that_cannot_cross_are_refused():
    async def hang(app, point):
        pass
    with pytest.raises(ValueError, match=r"AppSettings.fault cannot be passed to a cocotb "
                                         r"run \(only plain numbers and flags can\), not "):
        settings_to_json(AppSettings(fault=hang))
    with pytest.raises(TypeError, match="Settings must be an AppSettings, not {}"):
        settings_to_json({})


def test_bad_arguments_are_refused(tmp_path):
    image = CardImage(1024)
    with pytest.raises(ValueError, match="backend must be one of icarus, verilator, not "
                                         "'amaranth'"):
        run_system_cocotb(short_scenario(), image, backend="amaranth", build_dir=tmp_path)
    with pytest.raises(ValueError, match="Firmware must be one of app, card_check, not 'x'"):
        run_system_cocotb(short_scenario(), image, backend="icarus", build_dir=tmp_path,
                          firmware="x")


# -- on the simulators ---------------------------------------------------------------------------

@pytest.mark.cocotb
@pytest.mark.slow
@pytest.mark.parametrize("backend", ["verilator", "icarus"])
def test_the_card_check_firmware_writes_a_block_through_the_dma(backend, build_dir, external,
                                                               tmp_path):
    external.simulator(backend)
    scenario = short_scenario()
    scenario.until = 0.05
    image = blank_card(tmp_path / "card.img")
    before = dict(image.blocks())
    result = run_system_cocotb(scenario, image, backend=backend, build_dir=build_dir,
                               firmware="card_check")
    assert result.sdram_errors == [] and result.card_errors == []
    after = dict(image.blocks())
    assert set(after) == set(before) | {1}          # the block came back into the image
    assert after[1] != before.get(1)


@pytest.mark.cocotb
@pytest.mark.slow
@pytest.mark.parametrize("backend", ["verilator", "icarus"])
def test_a_recording_of_the_short_scenario(backend, build_dir, external, fat_tools, tmp_path):
    external.simulator(backend)
    scenario = short_scenario()
    image = blank_card(tmp_path / "card.img")
    result = run_system_cocotb(scenario, image, backend=backend, build_dir=build_dir)
    assert result.sdram_errors == [] and result.card_errors == []
    assert result.seconds == pytest.approx(scenario.until, abs=1e-6)
    out = tmp_path / "out.img"
    image.save(out)
    assert fsck_findings(fat_tools["fsck.fat"], out, tmp_path) == []
    logs = read_logs(out)
    assert [name for name, _ in logs] == ["LOG00001.TXT"]
    assert logs[0][1] == b"".join(scenario.recorded_frames())


@pytest.mark.cocotb
@pytest.mark.slow
def test_the_sdram_model_skipping_quiet_clocks_sees_what_it_sees_every_clock(build_dir,
                                                                             external,
                                                                             tmp_path):
    # The same recording with a simulator callback every clock and with SkippingChip (the
    # DMA reads the ring back from the SDRAM for every flush): the same card, no finding,
    # and (checked by the test itself) every clock edge seen by the model.
    external.simulator("verilator")
    scenario = short_scenario()
    images = []
    for every_clock in (True, False):
        image = blank_card(tmp_path / f"card{int(every_clock)}.img")
        result = run_system_cocotb(scenario, image, backend="verilator", build_dir=build_dir,
                                   sdram_every_clock=every_clock)
        assert result.sdram_errors == [] and result.card_errors == []
        images.append(image)
    assert images[0] == images[1]
    assert any(data != bytes(512) for _, data in images[0].blocks())
