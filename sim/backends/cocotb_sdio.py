"""cocotb backends for the SD path, and a bench that runs the firmware's SD driver on the
SD host's generated Verilog against the card model.

Backends: :class:`CsrBus` (the firmware's register bus on the CSR port), :class:`BlockPort`
(the host's byte streams), :func:`run_card` (the card model on an :class:`SdPins`: it samples
at each rising edge of the SD clock and drives after the falling edge, as a default-speed
card; the one loop of every cocotb top, the host's own and the whole logger's).
Python runs per register access, per byte and per SD clock edge, never per system clock.

The stimulus's ``sys_clock_hz`` is the one figure for the system clock: the simulated clock
runs at it and the driver is told it, so every SD clock the driver sets is the one the card
sees. The result reports the fastest SD clock measured during identification.
"""

import json
import logging
import os
import random

import cocotb
from cocotb.clock import Clock
from cocotb.simtime import get_sim_time
from cocotb.triggers import FallingEdge, ReadOnly, RisingEdge, Timer

from ...hw.arch.sd import CardState
from ..models.sdcard import SdBus
from ...sw.bus import BlockPort as _BlockPort
from ...sw.bus import RegisterBus


__all__ = ["CsrBus", "BlockPort", "ClockMeter", "SdPins", "run_card"]

#: The card states of identification mode (PLSS §4.2, at most 400 kHz); it ends with CMD3.
IDENTIFICATION_STATES = (CardState.IDLE, CardState.READY, CardState.IDENT)


class CsrBus(RegisterBus):
    """The firmware's register bus on the Verilog's ``bus__*`` CSR port."""
    def __init__(self, dut, *, clock_period_s):
        self._dut = dut
        self._period = clock_period_s
        self._cycles = 0

    async def read(self, address):
        dut = self._dut
        dut.bus__addr.value = address
        dut.bus__r_stb.value = 1
        await RisingEdge(dut.clk)
        await ReadOnly()
        await FallingEdge(dut.clk)
        # Valid right after the edge that saw r_stb, and still there half a cycle later.
        value = int(dut.bus__r_data.value)
        dut.bus__r_stb.value = 0
        self._cycles += 1
        return value

    async def write(self, address, value):
        dut = self._dut
        dut.bus__addr.value = address
        dut.bus__w_data.value = value
        dut.bus__w_stb.value = 1
        await RisingEdge(dut.clk)
        await FallingEdge(dut.clk)
        dut.bus__w_stb.value = 0
        await RisingEdge(dut.clk)          # the field takes the value a cycle later
        await FallingEdge(dut.clk)
        self._cycles += 2

    async def wait(self, seconds):
        cycles = max(1, round(seconds / self._period))
        await Timer(cycles * round(self._period * 1e12), unit="ps")
        await FallingEdge(self._dut.clk)
        self._cycles += cycles

    def now(self):
        return self._cycles * self._period


class BlockPort(_BlockPort):
    """The host's ``i``/``o`` byte streams, from and to Python queues."""
    def __init__(self, dut):
        self._dut = dut
        self._outgoing = bytearray()
        self._incoming = bytearray()
        self._wake = cocotb.triggers.Event()

    async def source(self):
        dut = self._dut
        dut.i__valid.value = 0
        while True:
            if not self._outgoing:
                dut.i__valid.value = 0
                self._wake.clear()
                await self._wake.wait()
                await FallingEdge(dut.clk)
                continue
            dut.i__payload.value = self._outgoing[0]
            dut.i__valid.value = 1
            # `ready` as the coming edge will see it (settled, this cycle).
            await ReadOnly()
            taken = str(dut.i__ready.value) == "1"
            await RisingEdge(dut.clk)
            if taken:
                del self._outgoing[0]
            await FallingEdge(dut.clk)

    async def sink(self):
        dut = self._dut
        dut.o__ready.value = 1
        while True:
            # What is offered until the next edge, which takes it (ready is always high).
            await ReadOnly()
            if str(dut.o__valid.value) == "1":
                self._incoming.append(int(dut.o__payload.value))
                await RisingEdge(dut.clk)
            else:
                await RisingEdge(dut.o__valid)

    async def send(self, data):
        self._outgoing += data
        self._wake.set()

    async def discard(self):
        self._outgoing.clear()

    async def receive(self, count):
        while len(self._incoming) < count:
            await RisingEdge(self._dut.clk)
        data = bytes(self._incoming[:count])
        del self._incoming[:count]
        await FallingEdge(self._dut.clk)
        return data


class ClockMeter:
    """The shortest SD clock period seen while the card is in identification mode."""
    def __init__(self):
        self.shortest_ns = None
        self._last_ns = None

    def rising_edge(self, card):
        now = get_sim_time(unit="ns")
        if self._last_ns is not None and card.state in IDENTIFICATION_STATES:
            period = now - self._last_ns
            self.shortest_ns = period if self.shortest_ns is None else min(self.shortest_ns,
                                                                           period)
        self._last_ns = now

    @property
    def fastest_hz(self):
        return None if self.shortest_ns is None else 1e9 / self.shortest_ns


class SdPins:
    """The SD pins of a cocotb top, ``{prefix}clk``, ``{prefix}cmd_o`` ... (``sd__`` on the
    SD host's own Verilog): :attr:`clk`, :meth:`host` (what the host drives, read in the
    read-only phase after a rising edge) and :meth:`drive` (the levels the host reads)."""
    def __init__(self, dut, prefix="sd__"):
        self.clk = getattr(dut, prefix + "clk")
        self._outputs = [getattr(dut, prefix + name)
                         for name in ("cmd_oe", "cmd_o", "dat_oe", "dat_o")]
        self._cmd_i = getattr(dut, prefix + "cmd_i")
        self._dat_i = getattr(dut, prefix + "dat_i")

    def host(self):
        """``(cmd_oe, cmd_o, dat_oe, dat_o)``."""
        return tuple(int(pin.value) for pin in self._outputs)

    def drive(self, cmd, dat):
        self._cmd_i.value = cmd
        self._dat_i.value = dat


#: The levels of released lines (pulled up), which the host reads before the card drives.
RELEASED_LEVELS = (1, 0xF)


async def run_card(pins, card, meter=None):
    """The card model on ``pins`` (an :class:`SdPins`) through an
    :class:`~maglog.sim.models.sdcard.SdBus`: the bus resolved at each rising edge of the
    SD clock, the card's levels applied after the falling edge (and only when they change:
    one simulator write fewer an edge). ``meter`` (a :class:`ClockMeter`) sees every rising
    edge."""
    bus = SdBus(card)
    rising, falling, read_only = RisingEdge(pins.clk), FallingEdge(pins.clk), ReadOnly()
    driven = RELEASED_LEVELS
    pins.drive(*driven)
    while True:
        await rising
        if meter is not None:
            meter.rising_edge(card)
        await read_only
        levels = bus.rising_edge(*pins.host())
        await falling
        if levels != driven:
            pins.drive(*levels)
            driven = levels


@cocotb.test()
async def write_read_back(dut):
    """Identify the card, write the stimulus's block runs, read them back."""
    from ...hw.sdio.host import SdioHost
    from ...sw.regmap import RegisterMap
    from ...sw.sdcard import SdCardDriver
    from ..models.card_image import CardImage
    from ..models.sdcard import Faults, SdCard

    logging.getLogger("cocotb").setLevel(logging.WARNING)
    with open(os.environ["MAGLOG_STIMULUS"]) as f:
        stimulus = json.load(f)
    sys_clock_hz = stimulus["sys_clock_hz"]
    Clock(dut.clk, round(1e12 / sys_clock_hz), unit="ps", impl="gpi").start()
    dut.sd__cmd_i.value = 1
    dut.sd__dat_i.value = 0xF
    dut.bus__r_stb.value = 0
    dut.bus__w_stb.value = 0
    dut.rst.value = 1
    for _ in range(4):
        await RisingEdge(dut.clk)
    dut.rst.value = 0
    await FallingEdge(dut.clk)

    image = CardImage(stimulus["capacity"])
    card = SdCard(image, seed=stimulus["seed"], faults=Faults(**stimulus.get("faults", {})))
    port = BlockPort(dut)
    meter = ClockMeter()
    cocotb.start_soon(run_card(SdPins(dut), card, meter))
    cocotb.start_soon(port.source())
    cocotb.start_soon(port.sink())
    bus = CsrBus(dut, clock_period_s=1 / sys_clock_hz)
    driver = SdCardDriver(bus, RegisterMap(SdioHost().bus.memory_map), port,
                          sys_clock_hz=sys_clock_hz)

    result = {"mismatches": []}
    try:
        await driver.initialise()
        rng = random.Random(stimulus["seed"])
        for lba, count in stimulus["runs"]:
            data = rng.randbytes(512 * count)
            await driver.write_blocks(lba, data)
            for k in range(count):
                back = await driver.read_block(lba + k)
                if back != data[512 * k:512 * (k + 1)]:
                    result["mismatches"].append(f"block {lba + k} read back differs")
                if image.read_block(lba + k) != data[512 * k:512 * (k + 1)]:
                    result["mismatches"].append(f"block {lba + k} in the image differs")
    except Exception as error:
        result["mismatches"].append(f"{type(error).__name__}: {error}")
    result.update(card_errors=card.errors, retries=driver.retries,
                  blocks_stored=card.blocks_stored,
                  cycles=round(get_sim_time(unit="ns") * 1e-9 * sys_clock_hz),
                  identification_clock_hz=meter.fastest_hz,
                  commands=[[t.command, t.argument, t.note] for t in card.log
                            if hasattr(t, "command")])
    result["card_image"] = os.path.join(os.path.dirname(os.environ["MAGLOG_RESULT"]),
                                        "card.img")
    image.save(result["card_image"])
    with open(os.environ["MAGLOG_RESULT"], "w") as f:
        json.dump(result, f)
    assert not result["mismatches"] and not card.errors, result
