"""The card behind the logger's DMA: block I/O through the DMA's sector buffer, ring writes,
and the flush that moves the ring's committed bytes into a log file.

On the logger the SD host's data streams end at the DMA, not at the processor: read data
fills the DMA's 512-byte sector buffer, and write data comes either from that buffer (one
sector the firmware wrote word by word: FAT, directory, FSInfo) or from the SDRAM ring (the
recording). :class:`DmaBufferPort` makes the buffer a :class:`~maglog.sw.bus.BlockPort`, so
:class:`~maglog.sw.sdcard.SdCardDriver` reads and writes single blocks through it unchanged;
:class:`RingSource` is the driver's source for ring writes; :func:`flush_ring` is the
logger's flush. Registers come by name from the DMA's and the SD host's windows.
"""

import datetime as _dt
from dataclasses import dataclass

from ..hw.arch.sd import BLOCK_BYTES
from .bus import BlockPort, BusTimeout
from .fat32 import BlockDevice, FatFullError
from .regmap import RegisterMap
from .sdcard import SdCardDriver, SdTimeout


__all__ = ["DMA_SOURCE_RING", "DMA_SOURCE_BUFFER", "RingSource", "DmaBufferPort",
           "DmaBlockDevice", "DmaStorage", "FlushResult", "RingError", "flush_ring",
           "last_frame_end"]

#: Values of the DMA's ``control.source`` field (``hw.dma.DmaSource``; the firmware does not
#: import gateware, the tests check that the two agree).
DMA_SOURCE_RING = 0
DMA_SOURCE_BUFFER = 1

WORD_BYTES = 4
BUFFER_WORDS = BLOCK_BYTES // WORD_BYTES
#: How long a single-block read may take to land in the sector buffer: the SD host ends a
#: read at its own read timeout (100 ms for SDHC, PLSS §4.6.2.1); twice that, plus margin.
READ_LIMIT_S = 0.25


class RingSource:
    """The DMA's ring mode as the source of :meth:`SdCardDriver.write_from`: block ``k`` of
    a write is the ring's sector ``base + k`` after its read pointer.

    Parameters
    ----------
    bus : RegisterBus
    regs : RegisterMap
        The DMA's registers (window ``dma``).
    base : int
        The ring sector the write's first block comes from.
    """
    def __init__(self, bus, regs, *, base=0):
        self.bus, self.regs, self.base = bus, regs, base

    async def arm(self, first, count):
        control = self.regs["control"]
        await self.bus.write(control.address, control.encode(
            start=1, source=DMA_SOURCE_RING, sectors=count, first=self.base + first))

    async def cancel(self):
        control = self.regs["control"]
        await self.bus.write(control.address, control.encode(abort=1))


class DmaBufferPort(BlockPort):
    """The DMA's sector buffer as the SD driver's block port (one block at a time).

    :meth:`send` writes the block into the buffer a word at a time (bytes low first) and
    arms a DMA write from it; :meth:`receive` waits for the SD host's read data phase to
    end, reads the block out of the buffer, and points the buffer's fill position back at
    its start for the next read; :meth:`discard` aborts an armed DMA write.

    Parameters
    ----------
    bus : RegisterBus
    dma : RegisterMap
        The DMA's registers (window ``dma``).
    sdio : RegisterMap
        The SD host's registers (window ``sdio``): ``status.dat_busy`` says when read data
        has all arrived.
    """
    def __init__(self, bus, dma, sdio, *, read_limit_s=READ_LIMIT_S):
        self.bus, self.dma, self.sdio = bus, dma, sdio
        self.read_limit_s = read_limit_s

    async def arm_read(self):
        """Point the buffer's fill position at its start: the next read data lands there."""
        control = self.dma["control"]
        await self.bus.write(control.address, control.encode(arm_read=1))

    async def send(self, data):
        if len(data) != BLOCK_BYTES:
            raise ValueError(f"The DMA's sector buffer holds one {BLOCK_BYTES}-byte block, "
                             f"not {len(data)} bytes")
        await self.bus.write(self.dma["buffer_seek"].address, 0)
        address = self.dma["buffer_write"].address
        for offset in range(0, BLOCK_BYTES, WORD_BYTES):
            await self.bus.write(address, int.from_bytes(data[offset:offset + WORD_BYTES],
                                                         "little"))
        control = self.dma["control"]
        await self.bus.write(control.address, control.encode(
            start=1, source=DMA_SOURCE_BUFFER, sectors=1))

    async def discard(self):
        control = self.dma["control"]
        await self.bus.write(control.address, control.encode(abort=1))

    async def receive(self, count):
        if count != BLOCK_BYTES:
            raise ValueError(f"The DMA's sector buffer holds one {BLOCK_BYTES}-byte block, "
                             f"not {count} bytes")
        status = self.sdio["status"]
        busy = status.field("dat_busy")
        try:
            await self.bus.wait_event(status.address, lambda word: not busy.extract(word),
                                      timeout=self.read_limit_s,
                                      what="the end of the read data phase")
        except BusTimeout as error:
            raise SdTimeout(f"read data did not arrive: {error}") from None
        await self.bus.write(self.dma["buffer_seek"].address, 0)
        address = self.dma["buffer_read"].address
        words = [await self.bus.read(address) for _ in range(BUFFER_WORDS)]
        await self.arm_read()           # ready for the next read (or this one's retry)
        return b"".join(word.to_bytes(WORD_BYTES, "little") for word in words)


class DmaBlockDevice(BlockDevice):
    """The card as a FAT32 block device, every block through the DMA's sector buffer.

    ``before_block``, if given, is awaited before each block (the application kicks its
    watchdog there: mounting a large card whose free count must be recounted reads every FAT
    sector, for longer than a watchdog period)."""

    def __init__(self, driver, port, *, before_block=None):
        self.driver, self.port = driver, port
        self.before_block = before_block

    async def read_block(self, lba):
        if self.before_block is not None:
            await self.before_block()
        await self.port.arm_read()
        return await self.driver.read_block(lba)

    async def write_block(self, lba, data):
        if self.before_block is not None:
            await self.before_block()
        await self.driver.write_blocks(lba, bytes(data))


class DmaStorage:
    """The logger's card path built from its memory map: the SD driver over the host's
    registers (window ``sdio``) with the sector buffer as its port, the block device, and
    the ring's registers (window ``dma``). ``before_block``: see :class:`DmaBlockDevice`."""

    def __init__(self, bus, memory_map, *, sys_clock_hz, before_block=None):
        self.bus = bus
        self.sdio = RegisterMap(memory_map, window="sdio")
        self.dma = RegisterMap(memory_map, window="dma")
        self.port = DmaBufferPort(bus, self.dma, self.sdio)
        self.driver = SdCardDriver(bus, self.sdio, self.port, sys_clock_hz=sys_clock_hz)
        self.device = DmaBlockDevice(self.driver, self.port, before_block=before_block)

    def _limit(self, field):
        return 1 << self.dma["control"].field(field).width

    async def read(self, name):
        """A DMA register's only field (``level``, ``kept``, ``dropped``, ...)."""
        register = self.dma[name]
        (field,) = register.fields.values()
        return field.extract(await self.bus.read(register.address))

    async def release(self, sectors):
        """Hand ``sectors`` whole sectors the card holds back to the ring."""
        register = self.dma["release"]
        limit = 1 << register.field("sectors").width
        while sectors:
            step = min(sectors, limit - 1)
            await self.bus.write(register.address, register.encode(sectors=step))
            sectors -= step

    async def clear(self):
        """Empty the ring (only while not recording, the DMA idle, no frame in flight)."""
        control = self.dma["control"]
        await self.bus.write(control.address, control.encode(clear=1))

    async def abort(self):
        control = self.dma["control"]
        await self.bus.write(control.address, control.encode(abort=1))

    async def write_ring(self, lba, first, count):
        """Write ``count`` ring sectors from ring sector ``first`` on to blocks ``lba`` on, in
        DMA commands the ``sectors`` and ``first`` fields can hold; returns the number of
        write commands."""
        most = self._limit("sectors") - 1
        commands = 0
        while count:
            step = min(count, most)
            if first + step > self._limit("first"):
                raise ValueError(f"Ring sector {first + step - 1} is beyond what the DMA's "
                                 f"first field reaches ({self._limit('first') - 1})")
            await self.driver.write_from(lba, step, RingSource(self.bus, self.dma, base=first))
            lba, first, count = lba + step, first + step, count - step
            commands += 1
        return commands


class RingError(Exception):
    """The ring and the file it is flushed into disagree."""


@dataclass(frozen=True)
class FlushResult:
    """What one flush did: ``bytes`` new bytes of the file on the card, ``sectors`` sectors
    written (a partial last sector counts every time it is written again), ``writes`` SD
    write commands, ``released`` ring sectors handed back."""
    bytes: int
    sectors: int
    writes: int
    released: int


async def last_frame_end(device, runs, start, end):
    """Where the last whole frame in bytes ``start .. end`` of a file ends (just after its
    line feed; ``start`` if none ends there), read back from the card: ``runs`` (extents)
    say where the file's sectors from ``start`` on are. Frames end in a line feed and are at
    most :data:`~maglog.hw.arch.frames.MAX_FRAME_LIMIT` bytes long, so at most
    ``MAX_FRAME_LIMIT / 512 + 1`` sectors are read."""
    sector = (end - 1) // BLOCK_BYTES
    while end > start and sector * BLOCK_BYTES + BLOCK_BYTES > start:
        run = next(r for r in runs if r.file_sector <= sector < r.file_sector + r.count)
        data = await device.read_block(run.lba + sector - run.file_sector)
        low = max(start - sector * BLOCK_BYTES, 0)
        high = min(end - sector * BLOCK_BYTES, BLOCK_BYTES)
        found = data.rfind(b"\n", low, high)
        if found >= 0:
            return sector * BLOCK_BYTES + found + 1
        sector -= 1
    return start


async def flush_ring(file, storage, timestamp):
    """Move the ring's committed bytes into ``file`` (a :class:`~maglog.sw.fat32.LogFile`
    fed only from the ring since the ring was cleared): read ``dma.level``, write the
    sectors covering the file from its synced size rounded down to a sector up to
    size - p + level (p: the bytes of its partial last sector, which the ring still holds)
    through the DMA, in the contiguous runs the file's clusters allow, then sync the file to
    the new size (FAT, directory entry, FSInfo) and release the whole sectors. The partial
    last sector stays in the ring and is written again, longer, next time.

    One round reaches as far as the DMA's ``first`` field does; more committed bytes are
    moved in further rounds, each a complete flush. The metadata is written only after
    every data write of its round succeeded (an :class:`~maglog.sw.sdcard.SdError`
    propagates before it). On a full card the file ends at the last whole frame that fitted
    (:func:`last_frame_end`; the clusters after it freed) and
    :class:`~maglog.sw.fat32.FatFullError` says how many bytes it took (``written``)."""
    if not isinstance(timestamp, (_dt.datetime, tuple)):
        raise TypeError(f"Timestamp must be a datetime, not {timestamp!r}")
    level = await storage.read("level")
    start = file.size
    if level < start % BLOCK_BYTES:
        raise RingError(f"the ring holds {level} bytes, fewer than the {start % BLOCK_BYTES} "
                        f"of {file.name}'s partial last sector: ring and file are out of step")
    target = start - start % BLOCK_BYTES + level
    reach = storage._limit("first")
    sectors = writes = released = 0
    written = []                        # every run of this flush (to find its last frame)
    while file.size < target:
        old = file.size
        base = old // BLOCK_BYTES
        wanted = min(target, (base + reach) * BLOCK_BYTES)
        extents = await file.extents(wanted)
        for run in extents.runs:
            writes += await storage.write_ring(run.lba, run.file_sector - base, run.count)
            sectors += run.count
        written += extents.runs
        if extents.size < wanted:
            # The card is full: the file ends at the last whole frame that fitted (its
            # line feed), not inside the frame the last cluster cuts.
            end = await last_frame_end(storage.device, written, start, extents.size)
            await file.end_at(end, timestamp)
            whole = max(end // BLOCK_BYTES - base, 0)
            await storage.release(whole)
            raise FatFullError(f"the card is full: {file.name} took {end - start} of "
                               f"{target - start} bytes (whole frames)", end - start)
        await file.grow(extents.size, timestamp)
        whole = extents.size // BLOCK_BYTES - base
        await storage.release(whole)
        released += whole
    return FlushResult(bytes=file.size - start, sectors=sectors, writes=writes,
                       released=released)
