"""sw/storage.py: block I/O through the DMA's sector buffer, ring writes and the flush.

On the storage gateware (ring, SDRAM, DMA, SD host; Amaranth simulator, SDRAM and card
models): the card is mounted through the sector buffer, a log file is created, frames go
into the ring and are flushed into the file several times, the file is closed; the image
must then pass ``fsck.fat -n`` and hold exactly the frames (calib.card reads it back).
"""

import asyncio
import datetime as dt
import random

import pytest

from maglog.calib.card import read_logs
from maglog.hw.dma import DmaSource
from maglog.sw import storage as sw_storage
from maglog.sw.fat32 import ImageFile, Volume, format_image
from maglog.sw.regmap import RegisterMap
from maglog.sw.storage import DmaStorage, RingError, flush_ring

from .test_fat32 import fsck_findings

MiB = 1 << 20
T0 = dt.datetime(2026, 11, 24, 12, 0, 0)


def test_dma_source_values_are_the_gateware_s():
    assert sw_storage.DMA_SOURCE_RING == DmaSource.RING.value
    assert sw_storage.DMA_SOURCE_BUFFER == DmaSource.BUFFER.value


def test_flush_refuses_a_timestamp_that_is_not_a_datetime():
    with pytest.raises(TypeError, match=r"^Timestamp must be a datetime, not 12$"):
        asyncio.run(flush_ring(None, None, 12))


def frames_of(rng, count):
    body = bytes(b for b in range(0x20, 0x7F) if b != ord("$"))
    return [b"$" + bytes(rng.choice(body) for _ in range(rng.randrange(30, 120))) + b"\r\n"
            for _ in range(count)]


def gateware_run(image_path, batches, *, capacity=1 << 14):
    """On the storage gateware: mount the card image at ``image_path`` through the DMA,
    create a LOG file, flush after each batch of frames pushed into the ring, close; returns
    the card image and what the firmware saw (flush results, file name, ring drops)."""
    from amaranth.lib import wiring

    from maglog.hw.arch.sdram import MT48LC4M32B2
    from maglog.hw.storage import Storage
    from maglog.sim.backends.amaranth import run_simulation
    from maglog.sim.models.card_image import CardImage
    from maglog.sim.models.sdcard import SdCard
    from maglog.sim.models.sdram import SdramChip
    from maglog.sim.backends.amaranth import CsrBus, run_card
    from maglog.sim.backends.amaranth import run_sdram

    clk_freq = 4e6
    storage = Storage(MT48LC4M32B2, clk_freq=clk_freq, capacity=capacity)
    sdram = SdramChip(MT48LC4M32B2, clk_freq=clk_freq)
    card = SdCard(CardImage.load(image_path), seed=5)
    pending = []
    result = {}

    async def feed(ctx):
        port = storage.i
        while True:
            if not pending:
                ctx.set(port.valid, 0)
                await ctx.tick()
                continue
            frame = pending[0]
            for n, byte in enumerate(frame):
                ctx.set(port.payload, {"data": byte, "last": n == len(frame) - 1})
                ctx.set(port.valid, 1)
                await ctx.tick().until(port.ready)
            ctx.set(port.valid, 0)
            pending.pop(0)

    async def firmware(ctx):
        bus = CsrBus(ctx, storage.bus, clock_period=1 / clk_freq)
        disk = DmaStorage(bus, storage.bus.memory_map, sys_clock_hz=clk_freq)
        await ctx.tick().until(storage.sdram_ready)
        await disk.driver.initialise()
        volume = await Volume.mount(disk.device)
        log = await volume.create_log(T0)
        flushes = []
        for batch in batches:
            pending.extend(batch)
            while pending:
                await ctx.tick()
            await ctx.tick().repeat(64)             # the last frame committed
            flushes.append(await flush_ring(log, disk, T0))
        await log.close(T0)
        result["flushes"], result["name"] = flushes, log.name
        result["dropped"] = await disk.read("dropped")

    async def sdram_side(ctx):
        await run_sdram(ctx, storage.sdram, sdram)

    async def card_side(ctx):
        await run_card(ctx, storage.sd, card)

    run_simulation(storage, [firmware], background=[sdram_side, card_side, feed],
                   name="sw_storage", clock_period=1 / clk_freq)
    assert sdram.errors == [] and card.errors == []
    return card.image, result


@pytest.mark.slow
def test_flushes_through_the_storage_gateware(tmp_path, fat_tools):
    # 512-byte clusters: the flushes cross cluster boundaries every sector, and a partial
    # sector is written again at every flush.
    image_path = tmp_path / "card.img"
    format_image(image_path, 40 * MiB, cluster_bytes=512, volume_id=1)
    rng = random.Random(4)
    batches = [frames_of(rng, n) for n in (9, 1, 14)]
    image, result = gateware_run(image_path, batches)
    assert result["dropped"] == 0
    stream = b"".join(frame for batch in batches for frame in batch)
    flushes = result["flushes"]
    assert sum(f.bytes for f in flushes) == len(stream)
    ends = [sum(len(f) for batch in batches[:k + 1] for f in batch) for k in range(3)]
    assert [f.bytes for f in flushes] == [ends[0], ends[1] - ends[0], ends[2] - ends[1]]
    assert [f.released for f in flushes] == [ends[0] // 512, ends[1] // 512 - ends[0] // 512,
                                             ends[2] // 512 - ends[1] // 512]
    # Each flush writes from the sector its last one left partial.
    assert [f.sectors for f in flushes] == [-(-ends[0] // 512),
                                            -(-ends[1] // 512) - ends[0] // 512,
                                            -(-ends[2] // 512) - ends[1] // 512]
    out = tmp_path / "out.img"
    image.save(out)
    assert fsck_findings(fat_tools["fsck.fat"], out, tmp_path) == []
    assert dict(read_logs(out))[result["name"]] == stream


def test_flush_refuses_a_ring_out_of_step_with_the_file(tmp_path):
    # The file ends 188 bytes into a sector, which the ring should still hold; a ring with
    # fewer committed bytes (emptied behind the file's back) is refused before any write.
    image = tmp_path / "card.img"
    format_image(image, 40 * MiB, cluster_bytes=512)

    class RingLevel:
        async def read(self, name):
            assert name == "level"
            return 100

    async def work():
        with ImageFile(image) as device:
            volume = await Volume.mount(device)
            log = await volume.create_log(T0)
            extents = await log.extents(700)
            for run in extents.runs:
                for k in range(run.count):
                    await device.write_block(run.lba + k, b"x" * 512)
            await log.grow(700, T0)
            with pytest.raises(RingError, match=r"^the ring holds 100 bytes, fewer than the "
                                                r"188 of LOG00001\.TXT's partial last sector"):
                await flush_ring(log, RingLevel(), T0)
            return log.size

    assert asyncio.run(work()) == 700


class NarrowDma(DmaStorage):
    """The DMA as if its ``first`` field reached 8 ring sectors and ``sectors`` held 4: a
    flush of more must go in rounds, and a run in several write commands."""

    def _limit(self, field):
        return {"first": 8, "sectors": 5}[field]


def test_flush_rounds_and_split_writes_on_the_logger_model(tmp_path, fat_tools):
    from maglog.sim.stimulus import sentences
    from maglog.sim.models.card_image import CardImage
    from maglog.sim.models.logger import LoggerModel
    from maglog.sim.stimulus.system import Burst, SystemScenario, short_scenario

    # 300 magnetometer frames back to back (about 13 KB in 0.57 s); flushes at 0.3 s and
    # at the end, each more than 8 sectors.
    frames = b"".join(sentences.pmag1(n, 100.0 * n, -2000.0, 3000.5) for n in range(300))
    base = short_scenario()
    scenario = SystemScenario(channels=base.channels, clk_freq=base.clk_freq,
                              bursts=[Burst(0, 0.05, frames)], presses=[], until=0.7)
    card = tmp_path / "card.img"
    format_image(card, 80 * MiB, cluster_bytes=1024, volume_id=1)
    model = LoggerModel(CardImage.load(card), clk_freq=scenario.clk_freq,
                        channels=scenario.channels)
    for burst in scenario.bursts:
        model.feed(burst.channel, burst.data, start=burst.start)
    logger = RegisterMap(model.memory_map, window="logger")

    async def main():
        disk = NarrowDma(model.bus, model.memory_map, sys_clock_hz=scenario.clk_freq)
        await disk.driver.initialise()
        volume = await Volume.mount(disk.device)
        log = await volume.create_log(T0)
        control = logger["control"]
        await model.bus.write(control.address, control.encode(record=1))
        flushes = []
        for until in (0.3, 0.68):
            await model.bus.wait(until - model.bus.now())
            flushes.append(await flush_ring(log, disk, T0))
        await model.bus.write(control.address, control.encode(record=0))
        await log.close(T0)
        return log.name, flushes, await disk.read("level")

    name, flushes, level = model.call(main())
    expected = b"".join(scenario.log_frames(0.0, scenario.until))
    assert len(expected) == len(frames)
    assert sum(f.bytes for f in flushes) == len(expected) and level == len(expected) % 512
    # More than 8 sectors a flush: rounds; no command over 4 sectors.
    assert all(f.sectors > 8 for f in flushes)
    assert all(f.writes >= -(-f.sectors // 4) for f in flushes)
    out = tmp_path / "out.img"
    model.image.save(out)
    assert fsck_findings(fat_tools["fsck.fat"], out, tmp_path) == []
    assert dict(read_logs(out)) == {name: expected}
