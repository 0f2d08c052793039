"""sw/fat32.py when a file must end short and when power returns: :meth:`LogFile.end_at`
(a full card ends the log at its last whole frame), and the repair of a dirty volume at
mount (:meth:`Volume.mount`), each judged by ``fsck.fat -n`` and the readers.
"""

import os

import pytest

from maglog.calib.card import read_logs
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
