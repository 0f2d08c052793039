"""The Amaranth simulator backend: the simulation runner, line drivers and stream sources
and sinks, the firmware's register buses and block port, the device models on the pins
(SD card, SDRAM chip) and the whole logger's system run.

The building blocks are edge-driven where they can be (a line segment is one `delay`, an
idle output stream is one `changed`), because per-cycle Python is what limits the
simulator's speed. The whole logger (:func:`run_system`): the gateware top (hw/top.py) with
the SDRAM chip model and the SD card model on its pins, the scenario's serial lines and
button on its inputs, and the firmware on its Wishbone port; the firmware is the same code
as on the other backends (:mod:`maglog.sw.app`), only the register bus differs
(:class:`WishboneBus`). Python runs per SDRAM clock (the chip model checks every timing
rule), per SD clock edge, per register access and per pin change.
"""

import contextlib
import os
import time
from pathlib import Path

from amaranth.sim import Simulator

from ...hw.arch.sdram import MT48LC4M32B2
from ...sw.bus import BlockPort, RegisterBus
from ..models.sdcard import SdBus, SdCard
from ..models.sdram import PINS as SDRAM_PINS, SdramChip
from ..runners.result import SystemResult


__all__ = ["CLOCK_HZ", "CLOCK_PERIOD", "CLOCK_NS", "ClockedBus", "run_simulation", "drive_line",
           "feed_stream", "FrameAssembler", "collect_frames", "collect_payloads", "CsrBus",
           "StreamBlockPort", "run_card", "run_driver", "run_sdram", "run_requests",
           "WishboneBus", "run_system"]

#: The simulated system clock of every backend (Amaranth simulator and cocotb): 50 MHz, as
#: the boards' oscillators. Periods below are derived from it, never written again.
CLOCK_HZ = 50_000_000
#: Its period in seconds (Amaranth simulator) ...
CLOCK_PERIOD = 1 / CLOCK_HZ
#: ... and in nanoseconds (cocotb's ``Clock`` and ``Timer``).
CLOCK_NS = 1e9 / CLOCK_HZ

#: Set to a directory to get a VCD of every Amaranth simulation written there.
VCD_ENV = "MAGLOG_VCD_DIR"


def run_simulation(dut, testbenches, *, background=(), name="sim", vcd_dir=None,
                   deadline=None, clock_period=CLOCK_PERIOD):
    """Simulate ``dut`` with the given async testbenches (critical) and background ones.

    The clock runs at ``clock_period`` seconds (default :data:`CLOCK_PERIOD`); a test that
    tells firmware another system clock runs the simulation at that clock too.

    A VCD is written into ``vcd_dir`` (or ``$MAGLOG_VCD_DIR``) when one is given: never into
    the working tree by default. ``deadline`` (seconds of simulated time) turns a hang into
    a ``TimeoutError``.
    """
    sim = Simulator(dut)
    sim.add_clock(clock_period)
    for tb in testbenches:
        sim.add_testbench(tb)
    for tb in background:
        sim.add_testbench(tb, background=True)
    if deadline is not None:
        async def watchdog(ctx):
            await ctx.delay(deadline)
            raise TimeoutError(f"simulation '{name}' did not finish within {deadline} s "
                               f"of simulated time")
        sim.add_testbench(watchdog, background=True)
    vcd_dir = vcd_dir or os.environ.get(VCD_ENV)
    if vcd_dir:
        path = Path(vcd_dir) / f"{name}.vcd"
        path.parent.mkdir(parents=True, exist_ok=True)
        writer = sim.write_vcd(str(path))
    else:
        writer = contextlib.nullcontext()
    with writer:
        sim.run()


class ClockedBus(RegisterBus):
    """A register bus on the Amaranth simulator that keeps time in clock cycles: a
    subclass's accesses add the cycles they take to ``_cycles``; :meth:`wait` jumps (one
    delay, then back onto a clock edge) and :meth:`now` is the cycles times the period."""
    def __init__(self, ctx, *, clock_period):
        self._ctx, self._period = ctx, clock_period
        self._cycles = 0

    async def wait(self, seconds):
        cycles = max(1, round(seconds / self._period))
        await self._ctx.delay((cycles - 1) * self._period)
        await self._ctx.tick()
        self._cycles += cycles

    def now(self):
        return self._cycles * self._period


async def drive_line(ctx, line, segments):
    """Drive a serial line through ``(level, cycles)`` segments (see sim.stimulus.uart_line)."""
    for level, cycles in segments:
        ctx.set(line, level)
        await ctx.delay(cycles * CLOCK_PERIOD)


async def feed_stream(ctx, stream, payloads, *, hold=None):
    """Offer each payload on ``stream`` until it is taken; ``hold(i)`` idle cycles before i."""
    for index, payload in enumerate(payloads):
        if hold is not None:
            for _ in range(hold(index)):
                ctx.set(stream.valid, 0)
                await ctx.tick()
        ctx.set(stream.payload, payload)
        ctx.set(stream.valid, 1)
        # (plain awaits, not tick().until(): an async generator still waiting when the
        # simulation ends is reported by Python as an unraisable exception)
        while True:
            _, _, ready = await ctx.tick().sample(stream.ready)
            if ready:
                break
    ctx.set(stream.valid, 0)


class FrameAssembler:
    """A sink for :func:`collect_payloads` that joins ``last``-marked bytes into frames.

    Each frame is appended to ``frames`` as ``bytes`` when ``fields`` is ``("data",)``,
    otherwise as ``(bytes, {field: value of the frame's last byte})``.
    """
    def __init__(self, frames, fields=("data",)):
        self.frames = frames
        self._fields = [f for f in fields if f != "data"]
        self._current = bytearray()

    def append(self, payload):
        self._current.append(payload.data)
        if payload.last:
            frame = bytes(self._current)
            self._current.clear()
            if self._fields:
                self.frames.append((frame, {f: getattr(payload, f) for f in self._fields}))
            else:
                self.frames.append(frame)


async def collect_frames(ctx, stream, sink, *, fields=("data",), ready=None):
    """Gather frames from a ``last``-marked byte stream into ``sink`` (a list); see
    :class:`FrameAssembler` for the form and :func:`collect_payloads` for ``ready``."""
    await collect_payloads(ctx, stream, FrameAssembler(sink, fields), ready=ready)


async def collect_payloads(ctx, stream, sink, *, ready=None):
    """Append every payload taken from ``stream`` to ``sink``.

    ``ready(cycle)`` gives backpressure; without it the sink is always ready and sleeps
    while the stream is idle (one ``changed`` trigger instead of a tick per cycle).
    """
    cycle = 0
    if ready is None:
        ctx.set(stream.ready, 1)
    while True:
        if ready is None:
            if not ctx.get(stream.valid):
                await ctx.changed(stream.valid)
            rdy = True
        else:
            rdy = bool(ready(cycle))
            ctx.set(stream.ready, rdy)
        _, _, valid, payload = await ctx.tick().sample(stream.valid, stream.payload)
        cycle += 1
        if valid and rdy:
            sink.append(payload)


# -- the SD path: register bus, block port, the card on the pins ------------------------------

class CsrBus(ClockedBus):
    """Register access through a CSR bus (one 32-bit word per address); ``clock_period`` is
    the simulation's (see :func:`~maglog.sim.backends.amaranth.run_simulation`)."""
    def __init__(self, ctx, bus, *, clock_period=CLOCK_PERIOD):
        super().__init__(ctx, clock_period=clock_period)
        self._bus = bus

    async def read(self, address):
        ctx, bus = self._ctx, self._bus
        ctx.set(bus.addr, address)
        ctx.set(bus.r_stb, 1)
        await ctx.tick()
        ctx.set(bus.r_stb, 0)
        self._cycles += 1
        # The data is valid right after the edge on which r_stb was high.
        return ctx.get(bus.r_data)

    async def write(self, address, value):
        ctx, bus = self._ctx, self._bus
        ctx.set(bus.addr, address)
        ctx.set(bus.w_data, value)
        ctx.set(bus.w_stb, 1)
        await ctx.tick()
        ctx.set(bus.w_stb, 0)
        # A field takes the value one cycle after the strobe: wait for it, so that what the
        # firmware does next (read a status, say) sees the write's effect.
        await ctx.tick()
        self._cycles += 2


class StreamBlockPort(BlockPort):
    """The host's byte streams, fed and drained by background testbenches (:meth:`source`,
    :meth:`sink`); the firmware queues and takes bytes (:meth:`attach` its context first).
    ``clock_period`` is the simulation's."""

    #: Cycles between looks at an empty outgoing queue.
    IDLE_POLL = 32

    def __init__(self, host, *, clock_period=CLOCK_PERIOD):
        self._host = host
        self._period = clock_period
        self._outgoing = bytearray()
        self._incoming = bytearray()
        self._ctx = None

    def attach(self, ctx):
        self._ctx = ctx

    async def source(self, ctx):
        stream = self._host.i
        while True:
            if not self._outgoing:
                ctx.set(stream.valid, 0)
                # (a plain delay, not tick().repeat(): an async generator still running when
                # the simulation ends is reported as an unraisable exception)
                await ctx.delay(self.IDLE_POLL * self._period)
                await ctx.tick()
                continue
            ctx.set(stream.payload, self._outgoing[0])
            ctx.set(stream.valid, 1)
            _, _, ready = await ctx.tick().sample(stream.ready)
            if ready and self._outgoing:
                del self._outgoing[0]

    async def sink(self, ctx):
        await collect_payloads(ctx, self._host.o, self._incoming)

    async def send(self, data):
        self._outgoing += data

    async def discard(self):
        self._outgoing.clear()

    async def receive(self, count):
        while len(self._incoming) < count:
            await self._ctx.tick()
        data = bytes(self._incoming[:count])
        del self._incoming[:count]
        return data


async def run_card(ctx, pins, card):
    """Run an :class:`~maglog.sim.models.sdcard.SdCard` on the SD pins ``pins`` (an
    interface of :func:`~maglog.hw.sdio.host.sd_pins_signature`, as ``SdioHost().sd`` or
    ``Storage(...).sd``) through an :class:`~maglog.sim.models.sdcard.SdBus`: the card sees
    the bus at each rising edge of ``clk`` and its outputs reach the host after the falling
    edge, as on the cocotb backend."""
    bus = SdBus(card)
    while True:
        await ctx.posedge(pins.clk)
        cmd, dat = bus.rising_edge(ctx.get(pins.cmd_oe), ctx.get(pins.cmd_o),
                                   ctx.get(pins.dat_oe), ctx.get(pins.dat_o))
        await ctx.negedge(pins.clk)
        ctx.set(pins.cmd_i, cmd)
        ctx.set(pins.dat_i, dat)


def run_driver(firmware, card, *, sys_clock_hz, deadline=0.2, extra=(), name="sdio_host"):
    """The firmware's SD driver on an :class:`~maglog.hw.sdio.host.SdioHost` with ``card``
    on its pins, in the Amaranth simulator at ``sys_clock_hz`` (the driver is told the same
    clock). ``await firmware(driver)`` is the firmware; ``extra`` are functions of the host
    that return more background testbenches (probes). Returns a dict: ``value`` (what the
    firmware returned) or ``error`` (the exception it raised), and ``driver``."""
    from ...hw.sdio.host import SdioHost
    from ...sw.regmap import RegisterMap
    from ...sw.sdcard import SdCardDriver

    host = SdioHost()
    regs = RegisterMap(host.bus.memory_map)
    period = 1 / sys_clock_hz
    port = StreamBlockPort(host, clock_period=period)
    outcome = {}

    async def fw(ctx):
        bus = CsrBus(ctx, host.bus, clock_period=period)
        port.attach(ctx)
        driver = SdCardDriver(bus, regs, port, sys_clock_hz=sys_clock_hz)
        outcome["driver"] = driver
        try:
            outcome["value"] = await firmware(driver)
        except Exception as error:          # reported to the caller, which decides
            outcome["error"] = error

    async def card_side(ctx):
        await run_card(ctx, host.sd, card)

    run_simulation(host, [fw], background=[card_side, port.source, port.sink,
                                           *(make(host) for make in extra)],
                   name=name, deadline=deadline, clock_period=period)
    return outcome


# -- the SDRAM chip on the controller's pins --------------------------------------------------

async def run_sdram(ctx, pins, chip):
    """Run ``chip`` on the controller's ``pins``: at each clock edge the model sees the pin
    values the edge samples, and what it drives appears on ``dq_i`` for the next edge.
    (A per-cycle model: one Python call a clock.)"""
    signals = [getattr(pins, name) for name in SDRAM_PINS] + [pins.dq_o]
    async for _, _, *values in ctx.tick().sample(*signals):
        levels = dict(zip(SDRAM_PINS, values))
        out = chip.edge(**levels, dq=values[-1])
        ctx.set(pins.dq_i, 0 if out is None else out)


def run_requests(chip, requests, *, clk_freq, cas_latency=2, tail=200):
    """Drive word requests ``(write, addr, data, mask)`` into an SdramController with the
    chip model on its pins; returns (read data in order, a dict of figures, the model).

    Figures: ``refreshes``, ``first`` and ``last`` (the cycles of the first request taken
    and of the last read word out, or of the last request when there are no reads)."""
    from ...hw.sdram import SdramController

    dut = SdramController(chip, clk_freq=clk_freq, cas_latency=cas_latency)
    model = SdramChip(chip, clk_freq=clk_freq)
    got, info = [], {"cycle": 0}

    class Sink(list):
        def append(self, value):
            super().append(value)
            info["last"] = info["cycle"]

    sink_list = Sink()

    async def requester(ctx):
        await ctx.tick().until(dut.ready)
        for write, addr, data, mask in requests:
            ctx.set(dut.i.payload, {"write": write, "addr": addr, "data": data, "mask": mask})
            ctx.set(dut.i.valid, 1)
            await ctx.tick().until(dut.i.ready)
            info.setdefault("first", info["cycle"])
            info.setdefault("last", info["cycle"])
            if write:
                info["last"] = max(info["last"], info["cycle"])
        ctx.set(dut.i.valid, 0)
        for _ in range(tail):
            await ctx.tick()
        info["refreshes"] = ctx.get(dut.refreshes)

    async def clock_count(ctx):
        async for _ in ctx.tick():
            info["cycle"] += 1

    async def chip_side(ctx):
        await run_sdram(ctx, dut.pins, model)

    async def sink(ctx):
        await collect_payloads(ctx, dut.o, sink_list)

    run_simulation(dut, [requester], background=[chip_side, sink, clock_count], name="sdram")
    return list(sink_list), info, model


# -- the whole logger -------------------------------------------------------------------------

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
    place). Returns a :class:`~maglog.sim.runners.result.SystemResult`."""
    from ...hw.top import Logger

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
