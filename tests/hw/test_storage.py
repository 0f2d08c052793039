"""Frames → SDRAM ring → DMA → SD host → card model, with the firmware's driver flushing.

The SDRAM chip model checks every timing rule; the card model checks the SD protocol; the
card image must hold the kept frames bit-exact, in order, and a full ring must drop whole
frames only, as many as the counters say.
"""

import random

import pytest
from amaranth import *
from amaranth.lib import wiring

from maglog.hw.arch import sd as arch_sd
from maglog.hw.arch.sdram import MT48LC4M32B2
from maglog.hw.arbiter import FrameArbiter
from maglog.hw.storage import Storage
from maglog.sim.backends.amaranth import run_simulation
from maglog.sim.models.card_image import CardImage
from maglog.sim.models.sdcard import SdCard
from maglog.sim.models.sdram import SdramChip
from maglog.sim.backends.amaranth import CsrBus, run_card
from maglog.sim.backends.amaranth import run_sdram
from maglog.sw.regmap import RegisterMap
from maglog.sw.sdcard import SdCardDriver
from maglog.sw.storage import RingSource

#: The system clock of the whole chain: the simulation runs at it, the SDRAM controller and
#: the chip model time their rules by it, and the driver is told it. 4 MHz, not the board's
#: 50 MHz, keeps identification (≤ 400 kHz) at 10 system cycles a bit instead of 126.
CLK_FREQ = 4e6
SECTOR = arch_sd.BLOCK_BYTES
FIRST_LBA = 8192


BODY = bytes(b for b in range(0x20, 0x7F) if b != ord("$"))


def frames_of(rng, count, tag=b""):
    return [b"$" + tag + bytes(rng.choice(BODY) for _ in range(rng.randrange(30, 100)))
            + b"\r\n" for _ in range(count)]


class Chain(wiring.Component):
    """The arbiter in front of the storage path, as in the logger."""
    def __init__(self, channels, capacity):
        self.arbiter = FrameArbiter(channels)
        self.storage = Storage(MT48LC4M32B2, clk_freq=CLK_FREQ, capacity=capacity)
        super().__init__({})

    def elaborate(self, platform):
        m = Module()
        m.submodules.arbiter, m.submodules.storage = self.arbiter, self.storage
        m.d.comb += [
            self.storage.i.valid.eq(self.arbiter.o.valid),
            self.storage.i.payload.data.eq(self.arbiter.o.payload.data),
            self.storage.i.payload.last.eq(self.arbiter.o.payload.last),
            self.arbiter.o.ready.eq(self.storage.i.ready),
        ]
        return m


def run(batches, *, capacity, flush_between=True, channels=1):
    """Push each batch of frames (a list per channel when ``channels`` > 1) through the
    arbiter, flushing after each batch (or only at the end)."""
    chain = Chain(channels, capacity)
    storage = chain.storage
    sdram = SdramChip(MT48LC4M32B2, clk_freq=CLK_FREQ)
    card = SdCard(CardImage(1 << 15), seed=3)
    pins = storage.sd
    result = {"flushes": 0}
    strobes = {"dma_done": 0, "ring_overflow": 0, "sd_error": 0}

    pending = [[] for _ in range(channels)]

    def feeder(k):
        async def feed(ctx):
            port = chain.arbiter.i[k]
            while True:
                if not pending[k]:
                    ctx.set(port.valid, 0)
                    await ctx.tick()
                    continue
                frame = pending[k][0]
                for n, byte in enumerate(frame):
                    ctx.set(port.payload, {"data": byte, "last": n == len(frame) - 1})
                    ctx.set(port.valid, 1)
                    await ctx.tick().until(port.ready)
                ctx.set(port.valid, 0)
                pending[k].pop(0)
        return feed

    async def push(ctx, frames):
        per_channel = frames if channels > 1 else [frames]
        for k, channel_frames in enumerate(per_channel):
            pending[k].extend(channel_frames)
        while any(pending):
            await ctx.tick()

    async def firmware(ctx):
        bus = CsrBus(ctx, storage.bus, clock_period=1 / CLK_FREQ)
        sd_regs = RegisterMap(storage.bus.memory_map, window="sdio")
        dma = RegisterMap(storage.bus.memory_map, window="dma")
        driver = SdCardDriver(bus, sd_regs, None, sys_clock_hz=CLK_FREQ)
        await ctx.tick().until(storage.sdram_ready)
        await driver.initialise()
        source = RingSource(bus, dma)
        lba = FIRST_LBA

        async def flush():
            nonlocal lba
            level = await bus.read(dma["level"].address)
            if level == 0:
                return
            sectors = -(-level // SECTOR)
            await driver.write_from(lba, sectors, source)
            result["flushes"] += 1
            full = level // SECTOR
            # Whole sectors are safe on the card: hand them back to the ring. The partial
            # one is written again, with more data, at the next flush.
            await bus.write(dma["release"].address, full)
            lba += full

        for batch in batches:
            await push(ctx, batch)
            if flush_between:
                await flush()
        await flush()
        result["kept"] = await bus.read(dma["kept"].address)
        result["dropped"] = await bus.read(dma["dropped"].address)
        result["high_water"] = await bus.read(dma["high_water"].address)
        result["level"] = await bus.read(dma["level"].address)
        result["lba"] = lba

    async def sdram_side(ctx):
        await run_sdram(ctx, storage.sdram, sdram)

    async def event_monitor(ctx):
        names = list(strobes)
        while True:
            _, _, *values = await ctx.tick().sample(*(getattr(storage, n) for n in names))
            for name, value in zip(names, values):
                strobes[name] += value

    async def card_side(ctx):
        await run_card(ctx, pins, card)

    run_simulation(chain, [firmware],
                   background=[sdram_side, card_side, event_monitor] +
                              [feeder(k) for k in range(channels)],
                   name="storage", clock_period=1 / CLK_FREQ)
    assert sdram.errors == [] and card.errors == []
    # The SoC's event strobes: one DMA done per flush (each one DMA write), one overflow per
    # dropped frame, and no SD error in a clean run.
    assert strobes == {"dma_done": result["flushes"], "ring_overflow": result["dropped"],
                       "sd_error": 0}
    return result, card.image


def image_bytes(image, first, count):
    return b"".join(image.read_block(first + k) for k in range(count))


def test_frames_reach_the_card_bit_exact():
    rng = random.Random(1)
    batches = [frames_of(rng, n) for n in (12, 20, 7)]
    stream = b"".join(f for batch in batches for f in batch)
    result, image = run(batches, capacity=1 << 14)
    assert result["dropped"] == 0 and result["kept"] == sum(map(len, batches))
    sectors = -(-len(stream) // SECTOR)
    data = image_bytes(image, FIRST_LBA, sectors)
    assert data[:len(stream)] == stream
    assert data[len(stream):] == bytes(len(data) - len(stream))
    assert result["level"] == len(stream) % SECTOR


def test_full_ring_drops_whole_frames_and_counts_them():
    rng = random.Random(2)
    capacity = 2048
    frames = frames_of(rng, 60)                     # far more than fits without a flush
    result, image = run([frames], capacity=capacity, flush_between=False)
    fitted, used = [], 0
    for frame in frames:
        if used + len(frame) <= capacity:
            fitted.append(frame)
            used += len(frame)
    assert result["dropped"] == len(frames) - len(fitted) > 0
    assert result["kept"] == len(fitted)
    assert result["high_water"] == used
    stream = b"".join(fitted)
    assert image_bytes(image, FIRST_LBA, -(-len(stream) // SECTOR))[:len(stream)] == stream


def test_frames_of_several_channels_arrive_whole_and_in_order():
    rng = random.Random(3)
    batches = [[frames_of(rng, 8, b"A"), frames_of(rng, 6, b"B")] for _ in range(2)]
    result, image = run(batches, capacity=1 << 14, channels=2)
    total = sum(len(f) for batch in batches for channel in batch for f in channel)
    data = image_bytes(image, FIRST_LBA, -(-total // SECTOR))[:total]
    # The card holds whole frames, each channel's in its own order.
    frames = [b"$" + part for part in data.split(b"$")[1:]]
    assert b"".join(frames) == data
    for k in range(2):
        sent = [f for batch in batches for f in batch[k]]
        assert [f for f in frames if f[1:2] == b"AB"[k:k + 1]] == sent
    assert result["kept"] == sum(len(channel) for batch in batches for channel in batch)


def test_sd_error_strobes_when_a_command_times_out():
    """No card: the CMD line stays high, the response times out, and ``sd_error`` pulses
    once as the command ends (and not again while the error bit stays set)."""
    storage = Storage(MT48LC4M32B2, clk_freq=CLK_FREQ, capacity=1024)
    seen = {}

    async def firmware(ctx):
        bus = CsrBus(ctx, storage.bus, clock_period=1 / CLK_FREQ)
        sd = RegisterMap(storage.bus.memory_map, window="sdio")
        await bus.write(sd["clock"].address, sd["clock"].encode(divisor=0))
        await bus.write(sd["timeouts"].address, sd["timeouts"].encode(response=8))
        pulses = 0
        await bus.write(sd["command"].address, sd["command"].encode(
            index=13, kind=arch_sd.ResponseKind.SHORT.value))
        for _ in range(400):
            _, _, pulse = await ctx.tick().sample(storage.sd_error)
            pulses += pulse
        seen["pulses"] = pulses
        seen["status"] = sd["status"].decode(await bus.read(sd["status"].address))

    run_simulation(storage, [firmware], name="sd_error", clock_period=1 / CLK_FREQ)
    assert seen["status"]["cmd.timeout"] == 1 and seen["status"]["cmd_busy"] == 0
    assert seen["pulses"] == 1
