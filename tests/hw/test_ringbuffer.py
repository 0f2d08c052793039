"""RingBuffer over the SDRAM controller and the timing-checking chip model.

Frames go in as the arbiter sends them; sectors come out committed bytes first, zero
padding after; a full ring drops whole frames and counts them, and never overwrites bytes
that were not released.
"""

import random

import pytest
from amaranth import *
from amaranth.lib import wiring
from amaranth.lib.wiring import In, Out

from maglog.hw.arch.sdram import IS42S16160, MT48LC4M32B2
from maglog.hw.ringbuffer import RingBuffer
from maglog.hw.sdram import SdramController
from maglog.sim.backends.amaranth import CLOCK_HZ, run_simulation
from maglog.sim.models.sdram import SdramChip
from maglog.sim.backends.amaranth import run_sdram

#: The simulated clock, which the controller and the chip model time their rules by.
CLK_FREQ = CLOCK_HZ
SECTOR = 512


class Harness(wiring.Component):
    def __init__(self, chip, capacity):
        self.ctrl = SdramController(chip, clk_freq=CLK_FREQ)
        self.ring = RingBuffer(chip.geometry, capacity=capacity)
        super().__init__({})

    def elaborate(self, platform):
        m = Module()
        m.submodules.ctrl, m.submodules.ring = self.ctrl, self.ring
        wiring.connect(m, self.ring.mem, self.ctrl.i)
        wiring.connect(m, self.ctrl.o, self.ring.mem_data)
        return m


def frames_of(rng, count, *, low=20, high=90):
    return [b"$" + bytes(rng.randrange(0x20, 0x7F) for _ in range(rng.randrange(low, high)))
            + b"\r\n" for _ in range(count)]


def run(chip, capacity, script):
    """``script(ctx, ring, ops)``: an async function using the helpers in ``ops``."""
    dut = Harness(chip, capacity)
    ring = dut.ring
    model = SdramChip(chip, clk_freq=CLK_FREQ)

    async def push(ctx, frame):
        for k, byte in enumerate(frame):
            ctx.set(ring.i.payload, {"data": byte, "last": k == len(frame) - 1})
            ctx.set(ring.i.valid, 1)
            await ctx.tick().until(ring.i.ready)
        ctx.set(ring.i.valid, 0)

    async def read_sector(ctx, index):
        ctx.set(ring.dma.read_sector, index)
        ctx.set(ring.dma.read_start, 1)
        await ctx.tick()
        ctx.set(ring.dma.read_start, 0)
        ctx.set(ring.dma.data.ready, 1)
        data = bytearray()
        while len(data) < SECTOR:
            _, _, valid, byte = await ctx.tick().sample(ring.dma.data.valid, ring.dma.data.payload)
            if valid:
                data.append(byte)
        ctx.set(ring.dma.data.ready, 0)
        return bytes(data)

    async def release(ctx, sectors):
        ctx.set(ring.dma.release_sectors, sectors)
        ctx.set(ring.dma.release, 1)
        await ctx.tick()
        ctx.set(ring.dma.release, 0)

    class Ops:
        pass
    ops = Ops()
    ops.push, ops.read_sector, ops.release = push, read_sector, release
    result = {}

    async def main(ctx):
        await ctx.tick().until(dut.ctrl.ready)
        result["value"] = await script(ctx, ring, ops)

    async def chip_side(ctx):
        await run_sdram(ctx, dut.ctrl.pins, model)

    run_simulation(dut, [main], background=[chip_side], name="ring")
    assert model.errors == []
    return result["value"]


@pytest.mark.parametrize("chip", [MT48LC4M32B2, IS42S16160], ids=lambda c: c.name)
def test_frames_come_out_as_sectors_with_padding(chip):
    frames = frames_of(random.Random(1), 30)
    stream = b"".join(frames)

    async def script(ctx, ring, ops):
        for frame in frames:
            await ops.push(ctx, frame)
        level = ctx.get(ring.dma.level)
        sectors = [await ops.read_sector(ctx, k) for k in range(-(-level // SECTOR))]
        return level, sectors, ctx.get(ring.dma.kept), ctx.get(ring.dma.dropped)

    level, sectors, kept, dropped = run(chip, 1 << 14, script)
    assert level == len(stream) and kept == 30 and dropped == 0
    data = b"".join(sectors)
    assert data[:level] == stream
    assert data[level:] == bytes(len(data) - level)


def test_full_ring_drops_whole_frames_and_keeps_unreleased_bytes():
    chip = MT48LC4M32B2
    capacity = 2048
    rng = random.Random(2)
    first = frames_of(rng, 60)
    later = frames_of(rng, 30)          # more than the two released sectors hold

    async def script(ctx, ring, ops):
        for frame in first:
            await ops.push(ctx, frame)
        level_full = ctx.get(ring.dma.level)
        before = [await ops.read_sector(ctx, k) for k in range(capacity // SECTOR)]
        dropped = ctx.get(ring.dma.dropped)
        # The card took two sectors: they are released and new frames fit again.
        await ops.release(ctx, 2)
        for frame in later:
            await ops.push(ctx, frame)
        after = [await ops.read_sector(ctx, k) for k in range(capacity // SECTOR)]
        return (level_full, b"".join(before), dropped, ctx.get(ring.dma.level), b"".join(after),
                ctx.get(ring.dma.kept), ctx.get(ring.dma.dropped), ctx.get(ring.dma.high_water))

    (level_full, before, dropped, level, after, kept, dropped_total,
     high_water) = run(chip, capacity, script)
    # Frames were kept while they fitted whole; the rest were dropped whole.
    fitted, used = [], 0
    for frame in first:
        if used + len(frame) <= capacity:
            fitted.append(frame)
            used += len(frame)
    kept_first = [f for f in first if f in fitted]
    assert level_full == used
    assert before[:used] == b"".join(kept_first)
    assert dropped == len(first) - len(kept_first) > 0
    # After the release, the unreleased bytes are untouched and the new frames follow them,
    # each kept whole if it fits in what is free then, else dropped whole (the same rule).
    tail = b"".join(kept_first)[2 * SECTOR:]
    kept_later, free = [], capacity - len(tail)
    for frame in later:
        if len(frame) <= free:
            kept_later.append(frame)
            free -= len(frame)
    assert 0 < len(kept_later) < len(later)     # the release made room, but not for all
    assert after[:len(tail)] == tail
    assert after[len(tail):level] == b"".join(kept_later)
    assert level == len(tail) + sum(map(len, kept_later))
    assert kept == len(kept_first) + len(kept_later)
    assert dropped_total == dropped + len(later) - len(kept_later)
    assert high_water == max(level_full, level)


def test_capacity_is_checked():
    with pytest.raises(ValueError, match="Capacity must be a power of two of whole sectors"):
        RingBuffer(MT48LC4M32B2.geometry, capacity=1000)


def test_clear_empties_the_ring_and_the_counters_keep_counting():
    chip = MT48LC4M32B2
    rng = random.Random(4)
    before = frames_of(rng, 12)
    after = frames_of(rng, 5)

    async def script(ctx, ring, ops):
        for frame in before:
            await ops.push(ctx, frame)
        await ops.release(ctx, 1)
        high_water = ctx.get(ring.dma.high_water)
        ctx.set(ring.dma.clear, 1)
        await ctx.tick()
        ctx.set(ring.dma.clear, 0)
        cleared = ctx.get(ring.dma.level)
        for frame in after:
            await ops.push(ctx, frame)
        level = ctx.get(ring.dma.level)
        sector = await ops.read_sector(ctx, 0)
        return (high_water, cleared, level, sector, ctx.get(ring.dma.kept),
                ctx.get(ring.dma.high_water))

    high_water, cleared, level, sector, kept, high_water_after = run(chip, 1 << 14, script)
    stream = b"".join(after)
    assert high_water == len(b"".join(before)) > SECTOR
    assert cleared == 0
    # The new frames start at the ring's start, the read pointer there too.
    assert level == len(stream)
    assert sector[:level] == stream and sector[level:] == bytes(SECTOR - level)
    assert kept == len(before) + len(after)
    assert high_water_after == high_water


def test_ring_port_width_is_checked():
    from maglog.hw.ringbuffer import RingPort
    with pytest.raises(ValueError, match="Level width must be a positive integer, not 0"):
        RingPort(0)
    assert RingPort(15) == RingPort(15) != RingPort(16)


def test_a_reset_zeroes_the_figures_high_water_included():
    """The high-water mark has no reset of its own: it takes the level (zero) the clock
    after a reset, as a watchdog reset of the logger does."""
    class Top(Elaboratable):
        def __init__(self):
            self.cd = ClockDomain("sync")
            self.ring = RingBuffer(MT48LC4M32B2.geometry, capacity=1 << 14)

        def elaborate(self, platform):
            m = Module()
            m.domains.sync = self.cd
            m.submodules.ring = self.ring
            return m

    top = Top()
    ring = top.ring
    frame = frames_of(random.Random(5), 1)[0]
    result = {}

    async def main(ctx):
        ctx.set(ring.mem.ready, 1)                # writes are taken at once
        for k, byte in enumerate(frame):
            ctx.set(ring.i.payload, {"data": byte, "last": k == len(frame) - 1})
            ctx.set(ring.i.valid, 1)
            await ctx.tick().until(ring.i.ready)
        ctx.set(ring.i.valid, 0)
        await ctx.tick().repeat(2)
        result["before"] = [ctx.get(v) for v in (ring.dma.level, ring.dma.high_water,
                                                   ring.dma.kept)]
        ctx.set(top.cd.rst, 1)
        await ctx.tick()
        ctx.set(top.cd.rst, 0)
        await ctx.tick().repeat(2)
        result["after"] = [ctx.get(v) for v in (ring.dma.level, ring.dma.high_water,
                                                  ring.dma.kept, ring.dma.dropped)]

    run_simulation(top, [main], name="ring_reset")
    assert result["before"] == [len(frame), len(frame), 1]
    assert result["after"] == [0, 0, 0, 0]
