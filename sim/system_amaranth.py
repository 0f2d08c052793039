"""The whole logger on the Amaranth simulator: the gateware top (hw/top.py) with the SDRAM
chip model and the SD card model on its pins, the scenario's serial lines and button on its
inputs, and the firmware on its Wishbone port.

The firmware is the same code as on the other backends (:mod:`maglog.sw.app`); only the
register bus differs (:class:`WishboneBus`). Python runs per SDRAM clock (the chip model
checks every timing rule), per SD clock edge, per register access and per pin change.
"""

import time

from ..hw.arch.sdram import MT48LC4M32B2
from ..hw.top import Logger
from .amaranth_tb import ClockedBus, run_simulation
from .models.sdcard import SdCard
from .models.sdram import SdramChip
from .sdio_amaranth import run_card
from .sdram_amaranth import run_sdram
from .system import SystemResult


__all__ = ["WishboneBus", "run_system"]


class WishboneBus(ClockedBus):
    """The firmware's register bus on a Wishbone (classic, 32-bit, word-addressed) slave:
    one cycle with ``cyc`` and ``stb`` held until ``ack``; ``clock_period`` is the
    simulation's."""

    #: An access that is not acknowledged within this many cycles is a gateware fault.
    ACK_LIMIT = 64

    def __init__(self, ctx, wb, *, clock_period):
        super().__init__(ctx, clock_period=clock_period)
        self._wb = wb
        self._sel = (1 << len(wb.sel)) - 1

    async def _cycle(self, address, write, value=0):
        ctx, wb = self._ctx, self._wb
        ctx.set(wb.adr, address)
        ctx.set(wb.we, int(write))
        ctx.set(wb.dat_w, value)
        ctx.set(wb.sel, self._sel)
        ctx.set(wb.cyc, 1)
        ctx.set(wb.stb, 1)
        for _ in range(self.ACK_LIMIT):
            await ctx.tick()
            self._cycles += 1
            if ctx.get(wb.ack):
                break
        else:
            raise TimeoutError(f"Wishbone {'write' if write else 'read'} at {address:#x} not "
                               f"acknowledged within {self.ACK_LIMIT} cycles")
        data = ctx.get(wb.dat_r)
        ctx.set(wb.cyc, 0)
        ctx.set(wb.stb, 0)
        ctx.set(wb.we, 0)
        return data

    async def read(self, address):
        return await self._cycle(address, False)

    async def write(self, address, value):
        await self._cycle(address, True, value)
        # A CSR field takes the value one cycle after the strobe the bridge gives with its
        # acknowledgement: what the firmware does next sees the write's effect.
        await self._ctx.tick()
        self._cycles += 1


def run_system(scenario, firmware, image, *, chip=MT48LC4M32B2, card_seed=0,
               ring_capacity=None, vcd_dir=None):
    """Run ``scenario`` on the gateware with ``firmware(bus, memory_map, sys_clock_hz)`` (a
    coroutine function; it never needs to return) until ``scenario.until``; the SD card
    model holds ``image`` (a :class:`~maglog.sim.models.card_image.CardImage`, changed in
    place). Returns a :class:`SystemResult`."""
    clk_freq = scenario.clk_freq
    period = 1 / clk_freq
    logger = Logger(channels=scenario.channels, clk_freq=clk_freq,
                    debounce_s=scenario.debounce_s, max_frame=scenario.max_frame,
                    ring_capacity=ring_capacity, chip=chip)
    sdram = SdramChip(chip, clk_freq=clk_freq)
    card = SdCard(image, seed=card_seed)

    async def pins(ctx):
        now = 0
        for cycle, uart_rx, button in scenario.pin_changes():
            if cycle > now:
                await ctx.delay((cycle - now) * period)
                now = cycle
            ctx.set(logger.uart_rx, uart_rx)
            ctx.set(logger.button, button)

    async def software(ctx):
        bus = WishboneBus(ctx, logger.bus, clock_period=period)
        await firmware(bus, logger.csr_memory_map, clk_freq)

    async def sdram_side(ctx):
        await run_sdram(ctx, logger.sdram, sdram)

    async def card_side(ctx):
        await run_card(ctx, logger.sd, card)

    final = {}

    async def until(ctx):
        await ctx.delay(scenario.until)
        final["led"] = ctx.get(logger.led)

    start = time.perf_counter()
    run_simulation(logger, [until], background=[pins, software, sdram_side, card_side],
                   name="system", clock_period=period, vcd_dir=vcd_dir)
    return SystemResult(image=image, led=final["led"], seconds=scenario.until,
                        wall_seconds=time.perf_counter() - start,
                        sdram_errors=list(sdram.errors), card_errors=list(card.errors))
