"""Amaranth-simulator backends for the SD path: the firmware's register bus and block port
on an :class:`~maglog.hw.sdio.host.SdioHost`, and the SD card model on its pins."""

from ..sw.bus import BlockPort
from .models.sdcard import SdBus
from .amaranth_tb import CLOCK_PERIOD, ClockedBus, collect_payloads, run_simulation


__all__ = ["CsrBus", "StreamBlockPort", "run_card", "run_driver"]


class CsrBus(ClockedBus):
    """Register access through a CSR bus (one 32-bit word per address); ``clock_period`` is
    the simulation's (see :func:`~maglog.sim.amaranth_tb.run_simulation`)."""
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
    from ..hw.sdio.host import SdioHost
    from ..sw.regmap import RegisterMap
    from ..sw.sdcard import SdCardDriver

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
