"""The same scenario and the same firmware on every backend give the same card, byte for
byte (DESIGN.md, Simulation): the transaction-level model, the Amaranth simulator on the
gateware, and cocotb on the generated Verilog. The card holds what the reference filter
keeps of the recording, and every FAT reader agrees it is clean."""

import pytest

from maglog.sim.models.card_image import CardImage
from maglog.sim.models import logger as model_backend
from maglog.sim.stimulus.system import short_scenario
from maglog.sw.app import AppSettings, LoggerApp
from maglog.sw.fat32 import format_image

from ..sw.test_fat32 import judge

#: The app's settings on every backend: a short poll so that the HDL runs stay short.
SETTINGS = dict(poll_s=0.5e-3)
VOLUME_ID = 0x4D474C47


async def firmware(bus, memory_map, sys_clock_hz):
    await LoggerApp(bus, memory_map, sys_clock_hz=sys_clock_hz,
                    settings=AppSettings(**SETTINGS)).run()


@pytest.fixture(scope="module")
def blank(tmp_path_factory):
    path = tmp_path_factory.mktemp("card") / "blank.img"
    format_image(path, 300 << 20, cluster_bytes=4096, volume_id=VOLUME_ID)
    return path


@pytest.fixture(scope="module")
def model_card(blank):
    image = CardImage.load(blank)
    model_backend.run_system(short_scenario(), firmware, image)
    return image


def differing_blocks(a, b):
    lbas = {lba for lba, _ in a.blocks()} | {lba for lba, _ in b.blocks()}
    return sorted(lba for lba in lbas if a.read_block(lba) != b.read_block(lba))


def test_model_card_holds_the_recording(model_card, tmp_path, fat_tools, external):
    path = tmp_path / "model.img"
    model_card.save(path)
    expected = b"".join(short_scenario().recorded_frames())
    judge(path, {"LOG00001.TXT": expected}, tmp_path, fat_tools, external)


def test_model_is_deterministic(blank, model_card):
    again = CardImage.load(blank)
    model_backend.run_system(short_scenario(), firmware, again)
    assert differing_blocks(again, model_card) == []


@pytest.mark.slow
def test_amaranth_gives_the_models_card(blank, model_card):
    from maglog.sim.backends.amaranth import run_system
    image = CardImage.load(blank)
    result = run_system(short_scenario(), firmware, image)
    assert result.sdram_errors == [] and result.card_errors == []
    assert differing_blocks(image, model_card) == []


@pytest.mark.slow
@pytest.mark.cocotb
@pytest.mark.parametrize("backend", ["verilator", "icarus"])
def test_cocotb_gives_the_models_card(backend, blank, model_card, external, tmp_path):
    from maglog.sim.backends.cocotb_system import run_system_cocotb
    external.simulator(backend)
    image = CardImage.load(blank)
    result = run_system_cocotb(short_scenario(), image, backend=backend,
                               build_dir=tmp_path / "build", settings=AppSettings(**SETTINGS))
    assert result.sdram_errors == [] and result.card_errors == []
    assert differing_blocks(image, model_card) == []


@pytest.fixture(scope="session")
def fast_build(tmp_path_factory):
    """One build folder for the fast harness per test session (a build takes ~20 s)."""
    return tmp_path_factory.mktemp("fast-build")


def test_fast_harness_gives_the_models_card(blank, model_card, external, fast_build):
    """The fast path (Verilator with the C++ harness, the command-level card) gives the
    card the model gives, and its front end counted what the reference filter counts."""
    from maglog.sim.backends.fast import CHANNEL_NAMES, run_system_fast
    from maglog.sim.reference import Kind, reference_filter
    external.simulator("verilator")
    external.tool("c++", "the fast harness is C++")
    scenario = short_scenario()
    image = CardImage.load(blank)
    result = run_system_fast(scenario, image, build_dir=fast_build,
                             settings=AppSettings(**SETTINGS))
    assert result.card_errors == []
    assert differing_blocks(image, model_card) == []
    kinds = {"pmag": Kind.PMAG, "nmea": Kind.NMEA, "cesium": Kind.CESIUM}
    for k, channel in enumerate(scenario.channels):
        expected = reference_filter(kinds[channel.kind.value], scenario.channel_bytes(k),
                                    max_frame=scenario.max_frame).counters
        assert result.counters[CHANNEL_NAMES[k]] == expected, CHANNEL_NAMES[k]
