"""The SD host's generated Verilog under cocotb (Icarus and Verilator), driven by the same
firmware driver as on the Amaranth simulator, against the card model; the card image it
leaves is checked here byte for byte."""

import os
import random
import shutil

import pytest
from amaranth.back import verilog

from maglog.hw.sdio.host import SdioHost
from maglog.sim.cocotb_run import COCOTB_SIMULATORS, CocotbBuild
from maglog.sim.models.card_image import CardImage

pytestmark = pytest.mark.cocotb

TOPLEVEL = "maglog_sdio"
CAPACITY = 1 << 16
RUNS = [(10, 1), (4096, 3), (CAPACITY - 2, 2)]


@pytest.fixture(scope="module", params=sorted(COCOTB_SIMULATORS))
def build(request, tmp_path_factory):
    tool = COCOTB_SIMULATORS[request.param]
    if shutil.which(tool) is None:
        message = f"{tool} is not on PATH; run `make test`"
        if os.environ.get("CI") == "true":
            pytest.fail(message)
        pytest.skip(message)
    build = CocotbBuild(request.param, tmp_path_factory.mktemp(f"sdio_{request.param}"),
                        TOPLEVEL)
    build.build(verilog.convert(SdioHost(), name=TOPLEVEL))
    return build


@pytest.mark.parametrize("faults", [{}, {"flip_dat_bit": 2, "flip_line": 1}],
                         ids=["clean", "dat-crc"])
def test_random_blocks_written_and_read_back(build, faults):
    seed = 17
    result = build.run("maglog.sim.cocotb_sdio", {
        "capacity": CAPACITY, "seed": seed, "sys_clock_hz": 4e6, "runs": RUNS,
        "faults": faults})
    assert result["mismatches"] == [] and result["card_errors"] == []
    assert (result["retries"] >= 1) == bool(faults)
    # The image file the run left holds exactly the blocks written, the rest is zero.
    image = CardImage.load(build.build_dir / f"run{build._runs}" / "card.img")
    rng = random.Random(seed)
    for lba, count in RUNS:
        data = rng.randbytes(512 * count)
        assert b"".join(image.read_block(lba + k) for k in range(count)) == data
    assert image.read_block(11) == bytes(512)
