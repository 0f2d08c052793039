"""Amaranth-simulator adapter for the SDRAM chip model (sim/models/sdram.py)."""

__all__ = ["run_sdram", "run_requests"]

_PINS = ("cke", "cs_n", "ras_n", "cas_n", "we_n", "ba", "a", "dqm", "dq_oe")


async def run_sdram(ctx, pins, chip):
    """Run ``chip`` on the controller's ``pins``: at each clock edge the model sees the pin
    values the edge samples, and what it drives appears on ``dq_i`` for the next edge.
    (A per-cycle model: one Python call a clock.)"""
    signals = [getattr(pins, name) for name in _PINS] + [pins.dq_o]
    async for _, _, *values in ctx.tick().sample(*signals):
        levels = dict(zip(_PINS, values))
        out = chip.edge(**levels, dq=values[-1])
        ctx.set(pins.dq_i, 0 if out is None else out)


def run_requests(chip, requests, *, clk_freq, cas_latency=2, tail=200):
    """Drive word requests ``(write, addr, data, mask)`` into an SdramController with the
    chip model on its pins; returns (read data in order, a dict of figures, the model).

    Figures: ``refreshes``, ``first`` and ``last`` (the cycles of the first request taken
    and of the last read word out, or of the last request when there are no reads)."""
    from ..hw.sdram import SdramController
    from .amaranth_tb import collect_payloads, run_simulation
    from .models.sdram import SdramChip

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
