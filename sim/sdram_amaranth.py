"""Amaranth-simulator adapter for the SDRAM chip model (sim/models/sdram.py)."""

__all__ = ["run_sdram"]

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
