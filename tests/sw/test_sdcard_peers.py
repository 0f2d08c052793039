"""sw/sdcard.py against cards that behave as other projects' SD card models do.

The card model (sim/models/sdcard.py) has an option for each behaviour, on the SD host in
the Amaranth simulator as in tests/sw/test_sdcard.py:

* a card that answers neither ACMD23 nor CMD13 (ZipCPU's mdl_sdio does so);
* a card that clears ILLEGAL_COMMAND at the next command instead of keeping it until a
  response reports it (litesdcard's emulator does so);
* a Ver1.X card (no answer to CMD8) that sets CCS in its OCR yet takes byte addresses.

Pre-erase (ACMD23) is a hint: no answer to it must not cost a block, it is given up once per
card (until the next initialise) and that is recorded in the driver's status. A CCS bit on
the version-1 path is not believed. Every run also checks the driver's timing margins: the
clocks before the first command, the gap between commands, the wait for a response.
"""

import random

from maglog.hw.arch import sd as arch
from maglog.hw.arch.sd import CardStatus, Response
from maglog.sim.backends.amaranth import run_driver
from maglog.sim.models.card_image import CardImage
from maglog.sim.models.sdcard import Faults, SdCard, Transaction
from maglog.sw import sdcard

SYS_CLOCK_HZ = 4e6
CAPACITY = 1 << 16      # blocks (32 MiB), sparse


class TimedCard(SdCard):
    """An SdCard that notes when each command starts: the clocks before the first one, and
    the idle clocks before every other, with the command (or response) before the gap."""

    def __init__(self, *args, **kwargs):
        super().__init__(*args, **kwargs)
        self.first_command_at = None
        self.gaps = []          # (idle clocks, the Transaction before them)

    def _check_command_spacing(self, now):
        if self.first_command_at is None:
            self.first_command_at = now
        elif self._line_free_since is not None:
            before = next(t for t in reversed(self.log) if isinstance(t, Transaction))
            self.gaps.append((now - self._line_free_since - 1, before))
        super()._check_command_spacing(now)


def new_card(seed, **kwargs):
    # One busy ACMD41 answer (each costs the driver a 1 ms wait): enough, and quicker.
    return TimedCard(CardImage(CAPACITY), seed=seed, acmd41_busy=(1, 1), **kwargs)


def commands(card):
    return [t for t in card.log if isinstance(t, Transaction)]


def run(card, steps, *, seed):
    """Initialise, then for each step: ``"init"`` initialises again, ``(lba, count)``
    writes ``count`` random blocks there (``(lba, count, False)``: without pre-erase).
    Returns the driver, the data written per write
    step, and a snapshot of the driver's status (pre_erase_supported, status_supported,
    fallbacks) taken before each ``"init"`` and at the end."""
    rng = random.Random(seed)
    writes = [step for step in steps if step != "init"]
    data = [rng.randbytes(step[1] * arch.BLOCK_BYTES) for step in writes]

    def snapshot(driver):
        return (driver.pre_erase_supported, driver.status_supported, list(driver.fallbacks))

    async def firmware(driver):
        infos, snapshots = [await driver.initialise()], []
        payloads = iter(data)
        for step in steps:
            if step == "init":
                snapshots.append(snapshot(driver))
                infos.append(await driver.initialise())
                continue
            lba, count, *pre_erase = step
            assert await driver.write_blocks(lba, next(payloads),
                                             pre_erase=all(pre_erase)) == count
        snapshots.append(snapshot(driver))
        return infos, snapshots

    out = run_driver(firmware, card, sys_clock_hz=SYS_CLOCK_HZ)
    assert "error" not in out, out.get("error")
    infos, snapshots = out["value"]
    # Every block where it should be, and block 0 (where block numbers taken as byte
    # addresses land) untouched.
    for (lba, count, *_), payload in zip(writes, data):
        assert b"".join(card.image.read_block(lba + k) for k in range(count)) == payload
    assert all(step[0] > 0 for step in writes) and card.image.read_block(0) == bytes(512)
    assert card.errors == []
    check_margins(card)
    return out["driver"], infos, snapshots


def check_margins(card):
    """More than the PLSS minimums: 74 clocks before the first command, 8 between a
    command or response and the next command, 64 clocks of waiting for a response."""
    assert card.first_command_at >= sdcard.INIT_CLOCKS_SENT >= 2 * arch.INIT_CLOCKS
    assert card.gaps and all(gap >= arch.N_CC + sdcard.COMMAND_GAP_EXTRA_CLOCKS >= 2 * arch.N_CC
                             for gap, _ in card.gaps)
    waited = [gap for gap, before in card.gaps
              if before.response is Response.NONE and before.command != "CMD0"]
    assert all(gap >= sdcard.RESPONSE_TIMEOUT_CLOCKS >= 2 * arch.N_CR_MAX for gap in waited)


def test_card_without_acmd23_and_cmd13():
    """mdl_sdio-like: before, 'writing block 16 failed: CMD13 got no response'. The first
    write (without pre-erase) has a block rejected (a flipped bit) before anything asked
    CMD13: the driver finds no CMD13, waits on DAT0 instead, and writes the block again."""
    card = new_card(3, acmd23=False, cmd13=False, faults=Faults(flip_dat_bit=1))
    steps = [(5, 2, False), (16, 3), (40, 2), "init", (60, 2), (80, 2)]
    driver, _, (first, second) = run(card, steps, seed=3)
    log = commands(card)
    names = [t.command for t in log]
    reinit = max(k for k, name in enumerate(names) if name == "CMD0")
    before, after = names[:reinit], names[reinit:]
    # Per card: one CMD13 (unanswered) and then none, one ACMD23 (taken as CMD23, illegal
    # to this card, unanswered), then CMD25s without it; all forgotten at initialise.
    assert before.count("CMD23") == after.count("CMD23") == 1
    assert before.count("CMD13") == after.count("CMD13") == 1
    assert all(t.response is Response.NONE for t in log if t.command in ("CMD13", "CMD23"))
    assert before.count("CMD25") == before.count("CMD12") == 3          # one to recover
    assert after.count("CMD25") == after.count("CMD12") == 2
    # The first card: CMD13 found missing after the failed write; block 6 written again
    # (CMD24); then pre-erase given up without asking CMD13 again.
    assert names.index("CMD13") < names.index("CMD24") < names.index("CMD23")
    assert first[:2] == (False, False) and len(first[2]) == 2
    assert "after a failed write" in first[2][0] and "waits for DAT0" in first[2][0]
    assert first[2][1].startswith("no pre-erase: ACMD23 got no response, and this card does "
                                  "not answer CMD13")
    # The card initialised again: asked afresh, CMD13 found missing by that probe.
    assert second[:2] == (False, False) and len(second[2]) == 2
    assert "asked why ACMD23 went unanswered" in second[2][0]
    assert "and CMD13 got none either" in second[2][1]
    assert driver.pre_erase_note in second[2][1] and driver.status_note in second[2][0]
    assert driver.retries == 1 and card.blocks_received == 12


def test_card_that_clears_illegal_command_at_the_next_command():
    """litesdcard-like: before, 'ACMD23 got no response twice, and the card does not call it
    illegal'. CMD13 answers, but without the flag: pre-erase off once, no retry."""
    card = new_card(4, acmd23=False, illegal_kept=False)
    driver, _, [(pre_erase, status, fallbacks)] = run(
        card, [(16, 3), (40, 2), (7, 1), (70, 2)], seed=4)
    log = commands(card)
    names = [t.command for t in log]
    assert names.count("CMD23") == 1 and names.count("CMD13") == 1
    probe = names.index("CMD13")
    assert names[probe - 2:probe + 2] == ["CMD55", "CMD23", "CMD13", "CMD25"]
    assert not log[probe].value & CardStatus.ILLEGAL_COMMAND
    assert names.count("CMD25") == names.count("CMD12") == 3
    assert (pre_erase, status) == (False, True) and len(fallbacks) == 1
    assert fallbacks[0] == ("no pre-erase: ACMD23 got no response, and the card status after "
                            "it flags neither ILLEGAL_COMMAND nor COM_CRC_ERROR; multi-block "
                            "writes go without ACMD23")
    assert driver.retries == 0


def test_version_1_card_that_sets_ccs():
    """Before: block numbers as addresses, block 1024 written to block 2 with no error, then
    ADDRESS_ERROR. Now: byte addresses, and the driver says why."""
    card = new_card(5, high_capacity=False, version=1, ocr_ccs=True)
    driver, [info], [(pre_erase, _, fallbacks)] = run(
        card, [(1024, 1), (16, 3), (7, 1)], seed=5)
    assert info.ocr & arch.OCR_CCS and info.version == 1
    assert not info.high_capacity and info.ccs_ignored
    assert fallbacks == ["CCS set in the OCR of a card that did not answer CMD8 (a Ver1.X "
                         "card): ignored, byte addressing"]
    writes = [(t.command, t.argument) for t in commands(card) if t.command in ("CMD24", "CMD25")]
    assert writes == [("CMD24", 1024 * 512), ("CMD25", 16 * 512), ("CMD24", 7 * 512)]
    assert card.image.read_block(2) == bytes(512)
    assert pre_erase is True
