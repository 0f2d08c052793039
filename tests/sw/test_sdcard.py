"""sw/sdcard.py: the SD driver needs hw/arch only, and meets cards as they are."""

import random
import subprocess
import sys

import pytest

from maglog.hw.arch import sd as arch
from maglog.hw.arch.sd import CardState, CardStatus, Response
from maglog.sim.models.card_image import CardImage
from maglog.sim.models.sdcard import Faults, SdCard, Transaction
from maglog.sim.backends.amaranth import run_driver


def test_the_driver_imports_without_amaranth():
    # A fresh interpreter: the firmware's SD driver must not pull in Amaranth (nor any
    # gateware module) on its way in.
    code = ("import sys, maglog.sw.sdcard\n"
            "assert 'amaranth' not in sys.modules, 'amaranth imported'\n"
            "gateware = sorted(name for name in sys.modules if name.startswith('maglog.hw.')"
            " and not name.startswith('maglog.hw.arch'))\n"
            "assert not gateware, gateware\n")
    result = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True)
    assert result.returncode == 0, result.stderr


# -- the driver against the card model, on the SD host in the Amaranth simulator ------------------
# (The host's own tests, with faults and timeouts, are in tests/hw/sdio/test_host.py.)

#: The system clock of the simulation and of the driver (4 MHz keeps identification short).
SYS_CLOCK_HZ = 4e6
CAPACITY = 1 << 16      # blocks (32 MiB), sparse


def new_card(seed, **kwargs):
    return SdCard(CardImage(CAPACITY), seed=seed, **kwargs)


def commands(card):
    return [t for t in card.log if isinstance(t, Transaction)]


def write_and_read_back(card, runs, *, seed, check=None):
    """Initialise, write each (lba, count) run with random data and read every block back
    through the driver; ``check(driver, card)`` runs after each write returns. Returns the
    driver and the data written per run."""
    rng = random.Random(seed)
    data = [rng.randbytes(count * arch.BLOCK_BYTES) for _, count in runs]

    async def firmware(driver):
        info = await driver.initialise()
        back = []
        for (lba, count), payload in zip(runs, data):
            assert await driver.write_blocks(lba, payload) == count
            if check is not None:
                check(driver, card)
            back.append(b"".join([await driver.read_block(lba + k) for k in range(count)]))
        return info, back

    out = run_driver(firmware, card, sys_clock_hz=SYS_CLOCK_HZ)
    assert "error" not in out, out.get("error")
    info, back = out["value"]
    assert back == data
    for (lba, count), payload in zip(runs, data):
        assert b"".join(card.image.read_block(lba + k) for k in range(count)) == payload
    assert card.errors == []
    return out["driver"], info


def test_sdhc_card():
    card = new_card(1)
    driver, info = write_and_read_back(card, [(7, 1), (CAPACITY - 3, 3)], seed=1)
    assert info.high_capacity and info.version == 2 and driver.retries == 0
    assert driver.pre_erase_supported is True
    writes = [(t.command, t.argument) for t in commands(card) if t.command in ("CMD24", "CMD25")]
    assert writes == [("CMD24", 7), ("CMD25", CAPACITY - 3)]      # block addresses


@pytest.mark.parametrize("version", [2, 1])
def test_standard_capacity_card(version):
    card = new_card(2, high_capacity=False, version=version)
    driver, info = write_and_read_back(card, [(5, 1), (1000, 3), (CAPACITY - 1, 1)], seed=2)
    assert not info.high_capacity and info.version == version
    assert not info.ocr & arch.OCR_CCS
    log = commands(card)
    # Byte addresses on the bus, block numbers at the driver.
    data_commands = [(t.command, t.argument) for t in log
                     if t.command in ("CMD17", "CMD24", "CMD25")]
    assert ("CMD24", 5 * arch.BLOCK_BYTES) in data_commands
    assert ("CMD25", 1000 * arch.BLOCK_BYTES) in data_commands
    assert ("CMD17", (CAPACITY - 1) * arch.BLOCK_BYTES) in data_commands
    # The block length is 512 from power-up (PLSS Table 4-22): no CMD16.
    assert "CMD16" not in [t.command for t in log]
    acmd41 = [t.argument for t in log if t.command == "ACMD41"]
    assert all(bool(a & arch.ACMD41_HCS) == (version == 2) for a in acmd41)
    if version == 1:
        assert next(t for t in log if t.command == "CMD8").response is Response.NONE


def test_card_without_acmd23_gets_its_multi_block_writes():
    card = new_card(3, acmd23=False)
    driver, _ = write_and_read_back(card, [(100, 3), (200, 2), (300, 1)], seed=3)
    assert driver.pre_erase_supported is False
    log = commands(card)
    names = [t.command for t in log]
    # Tried once: CMD55 then 23, taken by the card as CMD23, which it lacks too (no
    # response: an illegal command); told apart by CMD13, never sent again.
    tried = names.index("CMD23")
    assert names.count("CMD23") == 1 and "ACMD23" not in names
    assert names[tried - 1] == "CMD55" and log[tried].response is Response.NONE
    assert names[tried + 1] == "CMD13" and log[tried + 1].value & CardStatus.ILLEGAL_COMMAND
    assert names.count("CMD25") == names.count("CMD12") == 2
    assert all("pre-erase" not in t.note for t in log if t.command == "CMD25")


def test_card_that_takes_acmd23_for_cmd23():
    """A card without ACMD23 but with CMD23: the R1 has APP_CMD clear and the block count is
    set, so that CMD25 ends by itself (no CMD12, illegal in tran)."""
    card = new_card(5, acmd23=False, cmd23=True)
    driver, _ = write_and_read_back(card, [(100, 3), (200, 2)], seed=5)
    assert driver.pre_erase_supported is False
    log = commands(card)
    names = [t.command for t in log]
    tried = names.index("CMD23")
    assert names.count("CMD23") == 1 and names[tried - 1] == "CMD55"
    assert not log[tried].value & CardStatus.APP_CMD
    first, second = [k for k, name in enumerate(names) if name == "CMD25"]
    assert log[first].note == "LBA 100, block count 3"
    assert "CMD12" not in names[first:second] and names[second:].count("CMD12") == 1


@pytest.mark.parametrize("delay", sorted({0, 1, 2, 3, 5, arch.BUSY_START_CLOCKS}))
def test_late_busy_start(delay):
    """The card pulls DAT0 low ``delay`` clocks after the CRC status token (and after CMD12's
    R1b): the host waits for it, and no write is reported done before the card has
    programmed every block."""
    card = new_card(4, busy_start_delay=delay, busy_clocks=(30, 60))

    def finished(driver, card):
        assert not card.busy, "the write was reported done while the card was busy"
        assert card.state is CardState.TRAN

    driver, _ = write_and_read_back(card, [(40, 1), (50, 3)], seed=4, check=finished)
    assert driver.retries == 0 and card.blocks_stored == 4


@pytest.mark.parametrize("response, acmd", [(7, "ACMD6"), (9, "ACMD23")])
def test_app_command_with_a_response_crc_error_is_sent_again_with_its_cmd55(response, acmd):
    """Responses with a CRC7, counted from 0: CMD8, CMD55, CMD55 (ACMD41 is R3), CMD2, CMD3,
    CMD7, CMD55, ACMD6 (7), then CMD55, ACMD23 (9). Sent again alone, ACMD6 would reach the
    card as CMD6 (SWITCH_FUNC) and ACMD23 as CMD23 (SET_BLOCK_COUNT)."""
    card = new_card(6, acmd41_busy=(1, 1), faults=Faults(corrupt_response_crc=response))
    driver, _ = write_and_read_back(card, [(30, 2)], seed=6)
    log = commands(card)
    names = [t.command for t in log]
    corrupted = next(k for k, t in enumerate(log) if "corrupted" in t.note)
    assert names[corrupted] == acmd
    assert names[corrupted - 1:corrupted + 3] == ["CMD55", acmd, "CMD55", acmd]
    assert driver.retries == 1 and driver.pre_erase_supported is True
    assert names.count("CMD6") == names.count("CMD23") == 0


def test_a_single_block_the_card_rejected_gets_no_cmd12():
    """After CMD24's block is answered with a CRC error token the card is back in tran,
    where CMD12 is an illegal command: the driver asks CMD13 and sends the block again."""
    card = new_card(7, acmd41_busy=(1, 1), faults=Faults(flip_dat_bit=0))
    driver, _ = write_and_read_back(card, [(9, 1)], seed=7)
    names = [t.command for t in commands(card)]
    assert names[names.index("CMD24"):] == ["CMD24", "CMD13", "CMD24", "CMD17"]
    assert driver.retries == 1 and card.blocks_received == 2
