"""sw/fat32.py when a file must end short and when power returns: :meth:`LogFile.end_at`
(a full card ends the log at its last whole frame), and the repair of a dirty volume at
mount (:meth:`Volume.mount`), each judged by ``fsck.fat -n`` and the readers.
"""

import os

import pytest

from maglog.calib.card import read_logs
from maglog.hw.arch import fat32 as arch
from maglog.sw.fat32 import ImageFile, Volume, format_image

from .test_fat32 import (MiB, T0, T1, _RECOVERABLE, copy_range_sparse, dma_flush,
                         fsck_findings, fsinfo, mounted, mtype, patch, payload, run)


class Journal(ImageFile):
    """An image file that keeps every block written while ``journal`` is a list."""

    journal = None

    async def write_block(self, lba, data):
        if self.journal is not None:
            self.journal.append((lba, bytes(data)))
        await super().write_block(lba, data)


def judge(image, expected, tmp_path, fat_tools, external):
    """fsck.fat finds nothing; mtools and calib.card read exactly ``expected``."""
    assert fsck_findings(fat_tools["fsck.fat"], image, tmp_path) == []
    logs = dict(read_logs(image))
    for name, data in expected.items():
        assert mtype(external, image, name) == data, f"mtools reads {name} differently"
        assert logs[name] == data, f"calib.card reads {name} differently"


def free_clusters(image):
    with ImageFile(image) as device:
        return run(Volume.mount(device)).free_count


# -- LogFile.end_at ---------------------------------------------------------------------------

@pytest.mark.parametrize("synced, grown, end", [
    (3000, 5000, 4100),         # grows, ends in the last cluster
    (3000, 5000, 3001),         # grows, ends in the synced size's cluster: 3 freed
    (0, 1500, 0),               # nothing kept: every cluster freed, no first cluster
    (5000, 5000, 2900),         # shrinks by 5 clusters (below the synced size)
    (5000, 5000, 0),            # shrinks to nothing
])
def test_end_at_frees_the_clusters_past_the_end(tmp_path, fat_tools, external, synced, grown,
                                                end):
    image = tmp_path / "card.img"
    format_image(image, 40 * MiB, cluster_bytes=512)
    before = free_clusters(image)
    stream = payload(grown, 7)

    async def work(volume):
        log = await volume.create_log(T0)
        if synced:
            await dma_flush(log, stream, synced)
        extents = await log.extents(grown)
        for extent in extents.runs:
            for k in range(extent.count):
                sector = extent.file_sector + k
                data = stream[sector * 512:(sector + 1) * 512]
                await volume.device.write_block(extent.lba + k, data.ljust(512, b"\0"))
        await log.end_at(end, T1)
        assert log.size == end
        await log.close(T1)
        await volume.close()
        return log.name, volume.free_count

    name, free = run(mounted(image, work))
    judge(image, {name: stream[:end]}, tmp_path, fat_tools, external)
    assert free == fsinfo(image)[0] == before - -(-end // 512)


def test_end_at_refuses_an_end_past_the_allocated_clusters(tmp_path):
    image = tmp_path / "card.img"
    format_image(image, 40 * MiB, cluster_bytes=512)

    async def work(volume):
        log = await volume.create_log(T0)
        await log.extents(1000)
        with pytest.raises(ValueError, match=r"^End must be an integer from 0 to 1024 bytes"):
            await log.end_at(1025, T1)

    run(mounted(image, work))


def test_a_power_cut_while_a_file_shrinks_is_recoverable(tmp_path, fat_tools):
    # Cut after each block end_at writes when it shrinks a synced file across FAT sectors:
    # fsck finds nothing worse than lost clusters, and the file reads as before or after.
    image, base = tmp_path / "card.img", tmp_path / "base.img"
    format_image(image, 40 * MiB, cluster_bytes=512)
    stream = payload(140 * 512 + 77, 8)
    end = 100 * 512 + 11                # the chain crosses FAT sectors 0 -> 1; ends in 0

    async def work(device):
        volume = await Volume.mount(device)
        log = await volume.create_log(T0)
        await dma_flush(log, stream, len(stream))
        copy_range_sparse(image, 0, os.path.getsize(image), base)
        device.journal = []
        await log.end_at(end, T1)
        return log.name, device.journal

    with Journal(image) as device:
        name, journal = run(work(device))
    assert len(journal) >= 4            # entry, FAT sector 0 (both FATs), FAT sector 1...
    for cut in range(len(journal) + 1):
        copy_range_sparse(base, 0, os.path.getsize(base), image)
        for lba, data in journal[:cut]:
            patch(image, lba * 512, data)
        findings = fsck_findings(fat_tools["fsck.fat"], image, tmp_path)
        assert [line for line in findings if not _RECOVERABLE.match(line)] == [], cut
        assert dict(read_logs(image))[name] in (stream, stream[:end]), cut


# -- Repair of a dirty volume at mount --------------------------------------------------------

def clean_bit(image, fat=0):
    from .test_fat32 import fat_entries
    return fat_entries(image, 1, fat=fat)[0] & arch.CLEAN_SHUTDOWN_BIT


def test_every_cut_during_a_sync_is_repaired_at_the_next_mount(tmp_path, fat_tools):
    # A sync whose chain crosses FAT sectors, cut after each of its blocks: the next mount
    # repairs what the cut left (chain longer than the file, lost clusters, FATs that
    # differ, a stale free count) and marks the volume clean; fsck then finds nothing and
    # the file holds what was synced.
    image, base = tmp_path / "card.img", tmp_path / "base.img"
    format_image(image, 40 * MiB, cluster_bytes=512)
    old = payload(700, 1)
    new = old + payload(129 * 512, 2)

    async def record(device):
        volume = await Volume.mount(device)
        side = await volume.create_log(T0)
        await side.append(b"a closed file\r\n")
        await side.close(T0)
        log = await volume.create_log(T0)
        await log.append(old)
        await log.sync(T0)
        await log.append(new[len(old):])
        copy_range_sparse(image, 0, os.path.getsize(image), base)
        device.journal = []
        await log.sync(T1)
        return log.name, device.journal

    with Journal(image) as device:
        name, journal = run(record(device))
    kinds = set()
    for cut in range(len(journal) + 1):
        copy_range_sparse(base, 0, os.path.getsize(base), image)
        for lba, data in journal[:cut]:
            patch(image, lba * 512, data)
        before = fsck_findings(fat_tools["fsck.fat"], image, tmp_path)
        kinds.update(line for line in before if not line.startswith(" "))
        synced = dict(read_logs(image))[name]
        with ImageFile(image) as device:
            volume = run(Volume.mount(device))
        assert volume.was_dirty and volume.damage == [] and volume.repaired, cut
        assert fsck_findings(fat_tools["fsck.fat"], image, tmp_path) == [], cut
        assert clean_bit(image) and clean_bit(image, fat=1)
        logs = dict(read_logs(image))
        assert logs[name] == synced and synced in (old, new), cut
        assert logs["LOG00001.TXT"] == b"a closed file\r\n"
    # The cuts left each kind of damage the repair is for.
    assert {"FATs differ but appear to be intact.", "Free cluster summary wrong"} <= {
        line.split(" (")[0] for line in kinds}, kinds
    assert any(line.startswith("/LOG") for line in kinds), kinds
    assert any(line.startswith("Reclaimed") for line in kinds), kinds


def test_damage_a_cut_does_not_cause_keeps_the_volume_dirty(tmp_path, fat_tools):
    # A file whose size needs more clusters than its chain has (the entry written before
    # the FAT: never by this writer): the repair does not guess, writes nothing, and the
    # volume is never marked clean, even after a recording and a close.
    image = tmp_path / "card.img"
    format_image(image, 40 * MiB, cluster_bytes=512)

    async def work(volume):
        log = await volume.create_log(T0)
        await log.append(payload(3000))
        await log.sync(T0)
        # The size says 4 more clusters than the chain holds; the volume stays dirty.
        log.size += 4 * 512
        await log._write_metadata(T0)
        return log.name

    name = run(mounted(image, work))
    assert not clean_bit(image)
    snapshot = image.read_bytes()

    with ImageFile(image) as device:
        volume = run(Volume.mount(device))
    assert volume.was_dirty and volume.repaired is None
    assert volume.damage == ["/LOG00001.TXT: 6 clusters, fewer than its size needs (10)"]
    assert any("not repaired" in note and "stays marked dirty" in note
               for note in volume.notes)
    assert image.read_bytes() == snapshot                    # nothing written

    async def record(volume):
        log = await volume.create_log(T1)
        await log.append(b"$after\r\n")
        await log.close(T1)
        await volume.close()

    run(mounted(image, record))
    assert not clean_bit(image) and not clean_bit(image, fat=1)
