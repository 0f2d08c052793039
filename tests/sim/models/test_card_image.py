"""CardImage: sparse block store, sparse raw image files, clear errors."""

import os

import pytest

from maglog.sim.models import CardImage
from maglog.sim.models.card_image import BLOCK_BYTES


def block(fill: int, seed: int = 0) -> bytes:
    return bytes((fill + seed * i) & 0xFF for i in range(BLOCK_BYTES))


def test_unwritten_blocks_read_as_zeros_and_writes_stick():
    image = CardImage(100)
    assert image.capacity_blocks == 100 and image.capacity_bytes == 100 * BLOCK_BYTES
    assert image.read_block(0) == image.read_block(99) == bytes(BLOCK_BYTES)
    image.write_block(7, block(1, 3))
    image.write_block(8, bytearray(block(2, 5)))
    image.write_block(9, memoryview(block(3, 7)))
    assert image.read_block(7) == block(1, 3) and image.read_block(8) == block(2, 5)
    assert image.is_written(9) and not image.is_written(10)
    assert [lba for lba, _ in image.blocks()] == [7, 8, 9] and len(image) == 3
    image.write_block(8, bytes(BLOCK_BYTES))                 # zeros are a hole again
    assert not image.is_written(8) and len(image) == 2


@pytest.mark.parametrize("lba", [-1, 100, 1.0, "3", True, None])
def test_bad_lba(lba):
    image = CardImage(100)
    with pytest.raises(ValueError, match=r"LBA must be an integer in 0\.\.99"):
        image.read_block(lba)
    with pytest.raises(ValueError, match="LBA must be"):
        image.write_block(lba, bytes(BLOCK_BYTES))


@pytest.mark.parametrize("data, message", [
    (bytes(511), "512 bytes, not 511"), (bytes(513), "512 bytes, not 513"),
    (b"", "512 bytes, not 0"), (3.5, "bytes-like"),
])
def test_bad_block_data(data, message):
    with pytest.raises(ValueError, match=message):
        CardImage(10).write_block(0, data)


@pytest.mark.parametrize("capacity", [0, -5, 2.0, None, True])
def test_bad_capacity(capacity):
    with pytest.raises(ValueError, match="Capacity must be a positive number of blocks"):
        CardImage(capacity)


def test_sparse_save_load_round_trip(tmp_path):
    capacity = 1 << 17                                       # 64 MiB
    image = CardImage(capacity)
    written = {0: block(0xEB, 1), 1: block(0x11, 2), 8191: block(0x22, 3),
               capacity - 1: block(0x55, 1)}
    for lba, data in written.items():
        image.write_block(lba, data)
    path = tmp_path / "card.img"
    image.save(path)
    stat = os.stat(path)
    assert stat.st_size == capacity * BLOCK_BYTES
    if hasattr(stat, "st_blocks"):
        assert stat.st_blocks * 512 < 4 << 20, "holes must not be written"
    loaded = CardImage.load(path)
    assert loaded == image and loaded.capacity_blocks == capacity
    assert {lba: data for lba, data in loaded.blocks()} == written
    with open(path, "rb") as f:
        f.seek(8191 * BLOCK_BYTES)
        assert f.read(BLOCK_BYTES) == written[8191]
        f.seek(5000 * BLOCK_BYTES)
        assert f.read(BLOCK_BYTES) == bytes(BLOCK_BYTES)


def test_load_dense_file_and_overwrite(tmp_path):
    path = tmp_path / "dense.img"
    raw = bytearray(16 * BLOCK_BYTES)
    raw[3 * BLOCK_BYTES + 10] = 0x42
    raw[-1] = 0x99
    path.write_bytes(bytes(raw))
    image = CardImage.load(path)
    assert image.capacity_blocks == 16 and [lba for lba, _ in image.blocks()] == [3, 15]
    assert image.read_block(3)[10] == 0x42 and image.read_block(15)[-1] == 0x99
    # Saving over an existing, larger file leaves exactly the image.
    path.write_bytes(bytes([0xFF]) * (32 * BLOCK_BYTES))
    image.save(path)
    assert path.read_bytes() == bytes(raw)


@pytest.mark.parametrize("size", [0, 100, BLOCK_BYTES + 1])
def test_load_rejects_partial_blocks(tmp_path, size):
    path = tmp_path / "bad.img"
    path.write_bytes(bytes(size))
    with pytest.raises(ValueError, match=f"whole number of {BLOCK_BYTES}-byte blocks, not {size}"):
        CardImage.load(path)


def test_equality():
    a, b = CardImage(10), CardImage(10)
    assert a == b
    a.write_block(1, block(1, 1))
    assert a != b
    b.write_block(1, block(1, 1))
    assert a == b and a != CardImage(11) and a != "image"
