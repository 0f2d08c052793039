"""SdioHost + SD driver + the protocol-checking card model, on the Amaranth simulator.

The firmware (sw/sdcard.py) runs unchanged over the CSR bus backend; the card model
(sim/models/sdcard.py) sits on the host's pins and records every protocol violation.

The system clock is 4 MHz here, for the simulation and the driver alike (``SYS_CLOCK_HZ``):
the identification clock (≤ 400 kHz) is then 10 system cycles a bit instead of 126 at the
board's 50 MHz, which keeps the test fast; the data clock runs at 2 MHz instead of 25.
"""

import random

import pytest

from maglog.hw.arch import sd as arch
from maglog.hw.arch.sd import CardState
from maglog.hw.sdio.cmd import ResponseKind
from maglog.hw.sdio.host import DataPhase, SdioHost
from maglog.sim.models.card_image import CardImage
from maglog.sim.models.sdcard import Faults, SdCard
from maglog.sim.backends.amaranth import run_driver
from maglog.sw.regmap import RegisterMap
from maglog.sw.sdcard import SdNoCard, SdTimeout, SdWriteError

#: The system clock: the simulation runs at it and the driver is told it.
SYS_CLOCK_HZ = 4e6
#: PLSS §4.2 (f_OD): the identification clock is at most 400 kHz.
IDENT_CLOCK_MAX_HZ = 400e3
CAPACITY = 1 << 16      # blocks (32 MiB), sparse


def run(firmware, card, *, deadline=0.2, extra=()):
    return run_driver(firmware, card, sys_clock_hz=SYS_CLOCK_HZ, deadline=deadline,
                      extra=extra)


def new_card(**kwargs):
    return SdCard(CardImage(CAPACITY), seed=kwargs.pop("seed", 1), **kwargs)


def test_identification():
    card = new_card()
    periods = []            # system cycles between SD clock rising edges in identification

    def clock_meter(host):
        async def meter(ctx):
            last, since = 0, None           # cycles since the last rising edge
            while card.state in (CardState.IDLE, CardState.READY, CardState.IDENT):
                _, _, level = await ctx.tick().sample(host.sd.clk)
                if since is not None:
                    since += 1
                if level and not last:
                    if since is not None:
                        periods.append(since)
                    since = 0
                last = level
        return meter

    async def firmware(driver):
        return await driver.initialise()

    out = run(firmware, card, extra=[clock_meter])
    assert "error" not in out, out.get("error")
    # The identification clock, measured on the SD clock's edges (one system cycle is
    # 1 / SYS_CLOCK_HZ: the simulation runs at the clock the driver was told).
    assert len(periods) > 500
    assert 0.9 * IDENT_CLOCK_MAX_HZ < SYS_CLOCK_HZ / min(periods) <= IDENT_CLOCK_MAX_HZ
    info = out["value"]
    assert info.high_capacity and info.rca == card.rca != 0
    assert info.cid == card.cid >> 1
    assert card.state == arch.CardState.TRAN and card.bus_width == 4
    assert card.errors == []


def test_write_and_read_back():
    card = new_card(seed=3)
    rng = random.Random(3)
    one = rng.randbytes(arch.BLOCK_BYTES)
    many = rng.randbytes(5 * arch.BLOCK_BYTES)

    async def firmware(driver):
        await driver.initialise()
        await driver.write_blocks(100, one)
        await driver.write_blocks(2000, many)
        back = [await driver.read_block(lba) for lba in (100, 2000, 2004)]
        return back

    out = run(firmware, card)
    assert "error" not in out, out.get("error")
    assert out["value"] == [one, many[:512], many[-512:]]
    assert card.image.read_block(100) == one
    assert b"".join(card.image.read_block(2000 + k) for k in range(5)) == many
    assert card.errors == []
    assert out["driver"].retries == 0
    # The five-block write was announced by ACMD23 with its count, and the card applied it
    # to the CMD25 that followed; the single block went out as CMD24 without one.
    commands = [t for t in card.log if hasattr(t, "command")]
    names = [t.command for t in commands]
    multi = names.index("CMD25")
    assert names[multi - 2:multi] == ["CMD55", "ACMD23"]
    assert commands[multi - 1].argument == 5 and commands[multi].argument == 2000
    assert commands[multi].note == "LBA 2000, pre-erase count 5"
    assert names.count("ACMD23") == names.count("CMD25") == 1
    single = names.index("CMD24")
    assert commands[single].argument == 100 and names[single - 1] != "ACMD23"
    assert card.pre_erase_count is None         # used up by that CMD25


@pytest.mark.parametrize("faults", [
    Faults(flip_dat_bit=1, flip_line=2),
    Faults(withhold_token=2),
    Faults(corrupt_response_crc=9),
], ids=["dat-crc", "no-token", "response-crc"])
def test_faults_are_retried_and_nothing_is_silently_lost(faults):
    card = new_card(seed=5, faults=faults)
    data = random.Random(5).randbytes(4 * arch.BLOCK_BYTES)

    async def firmware(driver):
        await driver.initialise()
        written = await driver.write_blocks(500, data)
        return written, [await driver.read_block(500 + k) for k in range(4)]

    out = run(firmware, card)
    assert "error" not in out, out.get("error")
    written, back = out["value"]
    assert written == 4
    assert b"".join(back) == data
    assert out["driver"].retries >= 1
    assert card.errors == []


def test_busy_past_the_timeout_is_reported_with_the_blocks_written():
    card = new_card(seed=6, faults=Faults(busy_past_timeout=1,
                                          busy_past_timeout_clocks=3000))
    data = random.Random(6).randbytes(3 * arch.BLOCK_BYTES)

    async def firmware(driver):
        await driver.initialise()
        # Shorten the busy timeout so that the simulation stays short: 4 ticks of 256 SD
        # clocks (1024 to 1280 clocks), against the card's 3000.
        busy_timeout = driver.regs["busy_timeout"]
        await driver.bus.write(busy_timeout.address, busy_timeout.encode(ticks=4))
        return await driver.write_blocks(700, data)

    out = run(firmware, card)
    # No command reached the card while it was busy programming.
    assert card.errors == []
    error = out.get("error")
    if error is None:
        # Retried once the card was back in tran: every block written, one retry counted.
        assert out["value"] == 3 and out["driver"].retries >= 1
        assert b"".join(card.image.read_block(700 + k) for k in range(3)) == data
    else:
        # Given up: the failure counts the blocks safely on the card, block 0 (block 1's
        # busy outlasted the timeout), and that block is there.
        assert isinstance(error, SdWriteError), error
        assert error.accepted == 1
        assert card.image.read_block(700) == data[:512]


def test_card_that_never_finishes_power_up(monkeypatch):
    monkeypatch.setattr(arch, "ACMD41_LIMIT_S", 0.01)
    card = new_card(acmd41_busy=(10_000, 10_000))

    async def firmware(driver):
        return await driver.initialise()

    out = run(firmware, card)
    assert isinstance(out.get("error"), SdTimeout)
    assert "power-up" in str(out["error"])


def test_no_card():
    card = new_card(faults=Faults(no_card=True))

    async def firmware(driver):
        return await driver.initialise()

    out = run(firmware, card)
    assert isinstance(out.get("error"), SdNoCard)


@pytest.mark.parametrize("gateware, firmware", [(ResponseKind, arch.ResponseKind),
                                                (DataPhase, arch.DataPhase)])
def test_command_fields_take_their_values_from_arch(gateware, firmware):
    # The firmware writes the hw/arch values into the `command` register's fields.
    assert {m.name: m.value for m in gateware} == {m.name: m.value for m in firmware}
    fields = RegisterMap(SdioHost().bus.memory_map)["command"]
    assert fields.field("kind").width == fields.field("data").width == 2


@pytest.mark.parametrize("reset", [False, True])
def test_command_written_in_a_reset_cycle_is_dropped(reset):
    # The CSR bridge runs reset-less and still passes on, one cycle later, a write it took in
    # a reset cycle; the host drops it (as a reset bridge would). The reset comes as the
    # logger's watchdog gives it (a ResetInserter). Without the reset the same write sends
    # the command (CMD0: the CMD line is driven).
    from amaranth import Elaboratable, Module, Signal
    from amaranth.hdl import ResetInserter
    from maglog.sim.backends.amaranth import run_simulation
    host = SdioHost()
    regs = RegisterMap(host.bus.memory_map)
    driven = []

    class Top(Elaboratable):
        rst = Signal()

        def elaborate(self, platform):
            m = Module()
            m.submodules.host = ResetInserter({"sync": self.rst})(host)
            return m

    top = Top()

    async def bench(ctx):
        await ctx.tick().repeat(3)
        ctx.set(host.bus.addr, regs["command"].address)
        ctx.set(host.bus.w_data, regs["command"].encode(
            index=0, kind=ResponseKind.NONE.value, r1b=0, data=DataPhase.NONE.value))
        ctx.set(host.bus.w_stb, 1)
        ctx.set(top.rst, int(reset))
        await ctx.tick()
        ctx.set(host.bus.w_stb, 0)
        ctx.set(top.rst, 0)
        for _ in range(40):
            await ctx.tick()
            driven.append(ctx.get(host.sd.cmd_oe))

    run_simulation(top, [bench], name="sdio_reset_write", deadline=1e-3)
    assert any(driven) != reset
