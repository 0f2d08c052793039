"""A sparse SD card image: 512-byte blocks addressed by LBA, unwritten blocks read as zeros.

Only written blocks are held in memory, so a simulated 32 GB card costs what was written to
it. :meth:`CardImage.save` writes a raw image of the full capacity as a sparse file (it seeks
over the holes), which ``fsck.fat``, ``mtools`` or the calib reader open like a card dump;
:meth:`CardImage.load` reads one back, skipping holes where the file system reports them.
"""

from __future__ import annotations

import errno
import os
from collections.abc import Iterator
from pathlib import Path

from ...hw.arch.sd import BLOCK_BYTES

__all__ = ["CardImage", "TracingImage", "BLOCK_BYTES"]

_ZERO_BLOCK = bytes(BLOCK_BYTES)
#: Bytes read at a time by :meth:`CardImage.load`.
_LOAD_CHUNK = 1 << 20


class CardImage:
    """Sparse block store of ``capacity_blocks`` blocks of :data:`BLOCK_BYTES` bytes.

    Blocks written with all zeros are forgotten (they read back the same), so two images with
    the same contents compare equal however they were produced.
    """

    def __init__(self, capacity_blocks: int):
        if (not isinstance(capacity_blocks, int) or isinstance(capacity_blocks, bool)
                or capacity_blocks < 1):
            raise ValueError(f"Capacity must be a positive number of blocks, not "
                             f"{capacity_blocks!r}")
        self._capacity = capacity_blocks
        self._blocks: dict[int, bytes] = {}

    @property
    def capacity_blocks(self) -> int:
        """Capacity in blocks."""
        return self._capacity

    @property
    def capacity_bytes(self) -> int:
        return self._capacity * BLOCK_BYTES

    def _check_lba(self, lba) -> int:
        if not isinstance(lba, int) or isinstance(lba, bool) or not 0 <= lba < self._capacity:
            raise ValueError(f"LBA must be an integer in 0..{self._capacity - 1}, not {lba!r}")
        return lba

    def read_block(self, lba: int) -> bytes:
        """The 512 bytes of block ``lba`` (zeros if it was never written)."""
        return self._blocks.get(self._check_lba(lba), _ZERO_BLOCK)

    def write_block(self, lba: int, data) -> None:
        """Store 512 bytes (``bytes``, ``bytearray`` or ``memoryview``) at block ``lba``."""
        self._check_lba(lba)
        try:
            data = bytes(data)
        except TypeError:
            raise ValueError(f"Block data must be bytes-like, not {type(data).__name__}") \
                from None
        if len(data) != BLOCK_BYTES:
            raise ValueError(f"Block data must be {BLOCK_BYTES} bytes, not {len(data)}")
        if data == _ZERO_BLOCK:
            self._blocks.pop(lba, None)
        else:
            self._blocks[lba] = data

    def is_written(self, lba: int) -> bool:
        """Whether block ``lba`` holds anything but zeros."""
        return self._check_lba(lba) in self._blocks

    def blocks(self) -> Iterator[tuple[int, bytes]]:
        """``(lba, data)`` of every non-zero block, in LBA order."""
        for lba in sorted(self._blocks):
            yield lba, self._blocks[lba]

    def __len__(self) -> int:
        """Number of non-zero blocks."""
        return len(self._blocks)

    def __eq__(self, other) -> bool:
        if not isinstance(other, CardImage):
            return NotImplemented
        return self._capacity == other._capacity and self._blocks == other._blocks

    def __repr__(self) -> str:
        return f"CardImage(capacity_blocks={self._capacity}, written={len(self._blocks)})"

    def save(self, path) -> None:
        """Write a raw image of the full capacity; holes are left unwritten (sparse)."""
        path = Path(path)
        with open(path, "wb") as f:
            for lba, data in self.blocks():
                f.seek(lba * BLOCK_BYTES)
                f.write(data)
            f.truncate(self.capacity_bytes)

    @classmethod
    def load(cls, path) -> CardImage:
        """Read a raw image; its size must be a whole, non-zero number of blocks."""
        path = Path(path)
        size = path.stat().st_size
        if size == 0 or size % BLOCK_BYTES:
            raise ValueError(f"Card image {str(path)!r} must be a non-empty whole number of "
                             f"{BLOCK_BYTES}-byte blocks, not {size} bytes")
        image = cls(size // BLOCK_BYTES)
        with open(path, "rb") as f:
            for start, end in _data_extents(f, size):
                # Extents from SEEK_DATA/SEEK_HOLE are aligned to file-system blocks, which
                # may be smaller than a card block: widen to whole card blocks.
                offset = start - start % BLOCK_BYTES
                end = min(size, -(-end // BLOCK_BYTES) * BLOCK_BYTES)
                f.seek(offset)
                while offset < end:
                    chunk = f.read(min(_LOAD_CHUNK, end - offset))
                    if not chunk:
                        break
                    for pos in range(0, len(chunk) - BLOCK_BYTES + 1, BLOCK_BYTES):
                        block = chunk[pos:pos + BLOCK_BYTES]
                        if block != _ZERO_BLOCK:
                            image._blocks[(offset + pos) // BLOCK_BYTES] = block
                    offset += len(chunk)
        return image


def _data_extents(f, size: int) -> Iterator[tuple[int, int]]:
    """``(start, end)`` byte ranges that may hold data: the whole file where the file system
    cannot tell holes apart."""
    seek_data = getattr(os, "SEEK_DATA", None)
    seek_hole = getattr(os, "SEEK_HOLE", None)
    if seek_data is None or seek_hole is None:
        yield 0, size
        return
    fd = f.fileno()
    offset = 0
    while offset < size:
        try:
            start = os.lseek(fd, offset, seek_data)
            end = os.lseek(fd, start, seek_hole)
        except OSError as error:
            if error.errno != errno.ENXIO:      # holes not reported: read the rest
                yield offset, size
            return                              # ENXIO: no data after offset
        yield start, min(end, size)
        offset = end


class TracingImage(CardImage):
    """A :class:`CardImage` that also keeps every block stored, in order, as ``(lba,
    data)`` in :attr:`writes` (for power-cut campaigns and write counts)."""

    def __init__(self, capacity_blocks: int):
        super().__init__(capacity_blocks)
        self.writes: list[tuple[int, bytes]] = []

    def write_block(self, lba: int, data) -> None:
        super().write_block(lba, data)
        self.writes.append((lba, bytes(data)))

    @property
    def lbas(self) -> list[int]:
        """The LBA of every block stored, in order."""
        return [lba for lba, _ in self.writes]
