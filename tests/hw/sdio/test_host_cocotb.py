"""The SD host's generated Verilog under cocotb (Icarus and Verilator), driven by the same
firmware driver as on the Amaranth simulator, against the card model; the card image it
leaves is checked here byte for byte.

The simulated system clock and the driver's idea of it are one figure, ``SYS_CLOCK_HZ``
(the board's 50 MHz): identification runs at the ≤ 400 kHz it asks for, data at 25 MHz.
"""

import random

import pytest
from amaranth.back import verilog

from maglog.hw.sdio.host import SdioHost
from maglog.sim.backends.amaranth import CLOCK_HZ
from maglog.sim.backends.cocotb import COCOTB_SIMULATORS, CocotbBuild
from maglog.sim.models.card_image import CardImage

pytestmark = pytest.mark.cocotb

TOPLEVEL = "maglog_sdio"
CAPACITY = 1 << 16
RUNS = [(10, 1), (4096, 3), (CAPACITY - 2, 2)]
#: The system clock the simulation runs at and the driver is told.
SYS_CLOCK_HZ = CLOCK_HZ
#: PLSS §4.2 (f_OD): the identification clock is at most 400 kHz; the driver asks for that
#: with a divisor, so it may be a little slower, never faster.
IDENT_CLOCK_MAX_HZ = 400e3


@pytest.fixture(scope="module", params=sorted(COCOTB_SIMULATORS))
def build(request, external, tmp_path_factory):
    external.simulator(request.param)
    build = CocotbBuild(request.param, tmp_path_factory.mktemp(f"sdio_{request.param}"),
                        TOPLEVEL)
    build.build(verilog.convert(SdioHost(), name=TOPLEVEL))
    return build


@pytest.mark.parametrize("faults", [{}, {"flip_dat_bit": 2, "flip_line": 1}],
                         ids=["clean", "dat-crc"])
def test_random_blocks_written_and_read_back(build, faults):
    seed = 17
    result = build.run("maglog.sim.backends.cocotb_sdio", {
        "capacity": CAPACITY, "seed": seed, "sys_clock_hz": SYS_CLOCK_HZ, "runs": RUNS,
        "faults": faults})
    assert result["mismatches"] == [] and result["card_errors"] == []
    assert (result["retries"] >= 1) == bool(faults)
    # Measured on the SD clock's edges while the card was in identification mode.
    assert 0.9 * IDENT_CLOCK_MAX_HZ < result["identification_clock_hz"] <= IDENT_CLOCK_MAX_HZ
    # Each multi-block run was announced by ACMD23 with its block count, and the CMD25
    # that followed carried it (the card model notes the pre-erase count it applied).
    commands = result["commands"]
    for lba, count in RUNS:
        writes = [k for k, (name, argument, _) in enumerate(commands)
                  if name in ("CMD24", "CMD25") and argument == lba]
        assert writes, f"no write command for block {lba}"
        for k in writes:
            name, _, note = commands[k]
            if count == 1:
                assert name == "CMD24" and commands[k - 1][0] != "ACMD23"
            else:
                assert name == "CMD25"
                assert commands[k - 2][0] == "CMD55" and commands[k - 1][:2] == ["ACMD23", count]
                assert note.endswith(f"pre-erase count {count}")
    # The image file the run left holds exactly the blocks written, the rest is zero.
    image = CardImage.load(result["card_image"])
    rng = random.Random(seed)
    for lba, count in RUNS:
        data = rng.randbytes(512 * count)
        assert b"".join(image.read_block(lba + k) for k in range(count)) == data
    assert image.read_block(11) == bytes(512)
