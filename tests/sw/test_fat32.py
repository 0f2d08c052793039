"""sw/fat32.py: the formatter, mount checks, LOG file creation, append and sync.

Every image the writer leaves is judged by four independent readers: ``fsck.fat -n`` (no
finding), mtools (``mtype``), pyfatfs and :mod:`maglog.calib.card`; each must read back
exactly the bytes written.
"""

import asyncio
import datetime as dt
import os
import re
import subprocess

import pytest

from maglog.calib.card import open_card, read_logs
from maglog.hw.arch import fat32 as arch
from maglog.sw import fat32
from maglog.sw.fat32 import FatError, FatFullError, ImageFile, Volume, format_image


MiB = 1024 * 1024
T0 = dt.datetime(2024, 5, 6, 7, 8, 10)
T1 = dt.datetime(2024, 5, 6, 9, 30, 44)


def run(coro):
    return asyncio.run(coro)


def partition(path):
    """``(byte offset, byte length)`` of the first MBR partition of an image."""
    with open(path, "rb") as f:
        mbr = f.read(512)
    entry = arch.MBR_PARTITION_TABLE
    first = int.from_bytes(mbr[entry + 8:entry + 12], "little")
    sectors = int.from_bytes(mbr[entry + 12:entry + 16], "little")
    return first * 512, sectors * 512


def copy_range_sparse(src, offset, length, dst):
    """Copy bytes ``offset .. offset+length`` of ``src`` to ``dst``, reading only the data
    extents (holes stay holes, so a 2 GiB sparse partition copies in milliseconds)."""
    with open(src, "rb") as s, open(dst, "wb") as d:
        d.truncate(length)
        fd, position, end = s.fileno(), offset, offset + length
        while position < end:
            try:
                start = os.lseek(fd, position, os.SEEK_DATA)
            except OSError:                 # no data after position
                break
            if start >= end:
                break
            stop = min(os.lseek(fd, start, os.SEEK_HOLE), end)
            s.seek(start)
            d.seek(start - offset)
            for chunk in range(start, stop, 1 << 20):
                d.write(s.read(min(1 << 20, stop - chunk)))
            position = stop


_FSCK_BANNER = re.compile(r"^fsck\.fat \d+\.\d+ \(.*\)$")
_FSCK_SUMMARY = re.compile(r"^.*: \d+ files, \d+/\d+ clusters$")


def fsck_findings(fsck, image, tmp_path):
    """The finding lines of ``fsck.fat -n`` on a copy of the image's partition: every line
    but the banner and the summary, plus the exit status when it is not 0."""
    offset, length = partition(image)
    copy = tmp_path / "fsck-partition.img"
    copy_range_sparse(image, offset, length, copy)
    result = subprocess.run([fsck, "-n", str(copy)], capture_output=True, text=True,
                            timeout=60)
    copy.unlink()
    lines = [line for line in (result.stdout + result.stderr).splitlines()
             if line.strip() and not _FSCK_BANNER.match(line) and not _FSCK_SUMMARY.match(line)]
    if result.returncode:
        lines.append(f"exit status {result.returncode}")
    return lines


def mtools_env():
    return dict(os.environ, MTOOLS_SKIP_CHECK="1", MTOOLS_NO_VFAT="0")


def mtype(external, image, name):
    offset, _ = partition(image)
    result = subprocess.run([external.tool("mtype"), "-i", f"{image}@@{offset}", f"::{name}"],
                            capture_output=True, env=mtools_env(), check=True, timeout=60)
    return result.stdout


def mtools(tool, image, *args):
    offset, _ = partition(image)
    subprocess.run([tool, "-i", f"{image}@@{offset}", *args], capture_output=True,
                   env=mtools_env(), check=True, timeout=60)


def pyfatfs_read(image, names):
    from pyfatfs.PyFatFS import PyFatFS
    offset, _ = partition(image)
    fs = PyFatFS(str(image), offset=offset, read_only=True)
    try:
        return {name: fs.readbytes("/" + name) for name in names}
    finally:
        fs.close()


def judge(image, expected, tmp_path, fat_tools, external):
    """Every reader agrees the image is clean and holds exactly ``expected`` (name→bytes)."""
    assert fsck_findings(fat_tools["fsck.fat"], image, tmp_path) == []
    for name, data in expected.items():
        assert mtype(external, image, name) == data, f"mtools reads {name} differently"
    assert pyfatfs_read(image, expected) == expected
    logs = dict(read_logs(image))
    for name, data in expected.items():
        assert logs[name] == data, f"calib.card reads {name} differently"
    with open_card(image) as card:
        assert card.warnings == []


async def mounted(image, work):
    """Mount ``image`` and run ``await work(volume)``; returns its result."""
    with ImageFile(image) as device:
        volume = await Volume.mount(device)
        return await work(volume)


async def write_logs(volume, contents, *, chunk=1000, timestamp=T1):
    """Create one LOG file per entry of ``contents``, appended in chunks with a sync after
    each; returns the names."""
    names = []
    for data in contents:
        log = await volume.create_log(T0)
        for start in range(0, len(data), chunk):
            await log.append(data[start:start + chunk])
            await log.sync(timestamp)
        await log.close(timestamp)
        names.append(log.name)
    await volume.close()
    return names


def payload(n, seed=0):
    line = f"$GPGGA,{seed:06d},5230.0000,N,01323.0000,E,1,08,0.9,545.4,M,46.9,M,,*47\r\n"
    return (line.encode() * (n // len(line) + 1))[:n]


def fat_entries(image, cluster, count=1, fat=0):
    with open(image, "rb") as f:
        offset, _ = partition(image)
        f.seek(offset)
        bs = f.read(512)
        reserved = int.from_bytes(bs[14:16], "little")
        fat_sectors = int.from_bytes(bs[36:40], "little")
        f.seek(offset + (reserved + fat * fat_sectors) * 512 + cluster * 4)
        raw = f.read(4 * count)
    return [int.from_bytes(raw[i:i + 4], "little") for i in range(0, len(raw), 4)]


def fsinfo(image):
    offset, _ = partition(image)
    with open(image, "rb") as f:
        f.seek(offset + 512)
        sector = f.read(512)
    return (int.from_bytes(sector[488:492], "little"), int.from_bytes(sector[492:496], "little"))


# -- Formatter --------------------------------------------------------------------------------

@pytest.mark.parametrize("size, cluster_bytes", [(64 * MiB, 512), (512 * MiB, 4096),
                                                 (2200 * MiB, None)])
def test_format_layout(tmp_path, fat_tools, size, cluster_bytes):
    image = tmp_path / "card.img"
    plan = format_image(image, size, cluster_bytes=cluster_bytes)
    assert os.path.getsize(image) == size
    assert os.stat(image).st_blocks * 512 < 2 * MiB + plan.sectors_per_cluster * 512
    with open(image, "rb") as f:
        mbr = f.read(512)
        f.seek(plan.partition_start * 512)
        reserved = f.read(8 * 512)
    assert mbr[446 + 4] == 0x0C and mbr[510:] == b"\x55\xaa"
    assert plan.partition_start % 8192 == 0
    assert (plan.partition_start + plan.data_offset) % 8192 == 0     # SDA: data on a BU
    assert reserved[6 * 512:7 * 512] == reserved[:512]              # backup boot sector
    assert reserved[7 * 512:8 * 512] == reserved[512:1024]          # backup FSInfo
    expected_spc = 64 if cluster_bytes is None else cluster_bytes // 512
    assert plan.sectors_per_cluster == expected_spc
    assert fat_entries(image, 0, 3) == [0x0FFFFFF8, 0x0FFFFFFF, 0x0FFFFFFF]
    assert fat_entries(image, 0, 3, fat=1) == [0x0FFFFFF8, 0x0FFFFFFF, 0x0FFFFFFF]
    assert fsinfo(image) == (plan.cluster_count - 1, 3)
    assert fsck_findings(fat_tools["fsck.fat"], image, tmp_path) == []
    volume = run(mounted(image, lambda v: asyncio.sleep(0, v)))
    assert volume.notes == [] and volume.free_count == plan.cluster_count - 1


def test_format_refuses_what_is_not_fat32(tmp_path):
    image = tmp_path / "card.img"
    with pytest.raises(FatError, match="not SDHC.*give a cluster size"):
        format_image(image, 1024 * MiB)
    with pytest.raises(FatError, match="gives 63488 clusters; FAT32 needs at least 65525"):
        format_image(image, 256 * MiB, cluster_bytes=4096)
    with pytest.raises(FatError, match="power of two"):
        format_image(image, 64 * MiB, cluster_bytes=1536)
    with pytest.raises(FatError, match="multiple of 512"):
        format_image(image, 64 * MiB + 1, cluster_bytes=512)
    assert not image.exists()


# -- Writing and reading back -----------------------------------------------------------------

@pytest.mark.parametrize("size, cluster_bytes", [(64 * MiB, 512), (512 * MiB, 4096),
                                                 (2200 * MiB, None)])
def test_logs_read_back_by_every_judge(tmp_path, fat_tools, external, size, cluster_bytes):
    image = tmp_path / "card.img"
    plan = format_image(image, size, cluster_bytes=cluster_bytes)
    cluster = plan.sectors_per_cluster * 512
    # Empty, partial sector, exactly one cluster, one byte past a cluster, several clusters.
    contents = [b"", payload(100, 1), payload(cluster, 2), payload(cluster + 1, 3),
                payload(3 * cluster + 777, 4)]
    names = run(mounted(image, lambda v: write_logs(v, contents, chunk=cluster // 3 + 5)))
    assert names == [f"LOG{n:05d}.TXT" for n in range(1, 6)]
    expected = dict(zip(names, contents))
    judge(image, expected, tmp_path, fat_tools, external)
    assert os.stat(image).st_blocks * 512 < 4 * MiB            # still sparse
    with open_card(image) as card:
        entry = card.stat("LOG00005.TXT")
        assert entry.mtime == T1
        assert len(card.clusters("LOG00005.TXT")) == -(-len(contents[4]) // cluster)
    used = sum(-(-len(c) // cluster) for c in contents)
    assert fsinfo(image)[0] == plan.cluster_count - 1 - used


def test_fat_sector_boundary(tmp_path, fat_tools, external):
    # 512-byte clusters: 128 FAT entries a sector; a 300-cluster file's chain spans the
    # FAT sectors 0, 1 and 2 (clusters 3..302).
    image = tmp_path / "card.img"
    format_image(image, 64 * MiB, cluster_bytes=512)
    data = payload(300 * 512 - 3)
    names = run(mounted(image, lambda v: write_logs(v, [data], chunk=4096)))
    judge(image, {names[0]: data}, tmp_path, fat_tools, external)
    with open_card(image) as card:
        chain = card.clusters(names[0])
    assert chain == list(range(3, 303))
    assert fat_entries(image, 127, 2) == [128, 129]
    assert fat_entries(image, 127, 2, fat=1) == [128, 129]


def test_directory_grows_past_one_cluster(tmp_path, fat_tools, external):
    # 512-byte clusters hold 16 entries; the label takes one, so 40 files need 3 clusters.
    image = tmp_path / "card.img"
    plan = format_image(image, 64 * MiB, cluster_bytes=512)
    # Free clusters need not be zero: junk where the directory will grow must not show up
    # as entries.
    patch(image, (plan.partition_start + plan.data_offset + 16) * 512, b"\xaa" * 64 * 512)
    contents = [payload(10 + n, n) for n in range(40)]
    names = run(mounted(image, lambda v: write_logs(v, contents, chunk=64)))
    judge(image, dict(zip(names, contents)), tmp_path, fat_tools, external)
    with open_card(image) as card:
        assert card.log_files() == [f"LOG{n:05d}.TXT" for n in range(1, 41)]
    # The root chain is 2 -> 3 -> (after LOG00001..15's clusters) another cluster.
    root = [2]
    while True:
        nxt = fat_entries(image, root[-1])[0]
        if nxt >= 0x0FFFFFF8:
            break
        root.append(nxt)
    assert len(root) == 3


def test_existing_files_are_kept(tmp_path, fat_tools, external):
    image = tmp_path / "card.img"
    format_image(image, 64 * MiB, cluster_bytes=512)
    files = {"LOG00002.TXT": payload(900, 2), "LOG00007.TXT": payload(2000, 7),
             "A long file name.csv": b"x,y\n1,2\n" * 300}
    for name, data in {"Deleted long name.txt": b"gone\n", **files}.items():
        source = tmp_path / name
        source.write_bytes(data)
        mtools(fat_tools["mcopy"], image, str(source), f"::{name}")
    mtools(fat_tools["mmd"], image, "::Flight notes")
    (tmp_path / "note.txt").write_bytes(b"calibration pattern at 12:00\n")
    mtools(fat_tools["mcopy"], image, str(tmp_path / "note.txt"), "::Flight notes/note.txt")
    mtools(fat_tools["mdel"], image, "::Deleted long name.txt")   # leaves 0xE5 entries
    with open_card(image) as card:
        root_offset = card.cluster_offset(2)
    with open(image, "rb") as f:
        f.seek(root_offset)
        root_before = f.read(512)
    used = root_before.rstrip(b"\0")
    assert used.count(b"\xe5") >= 2 and used.count(b"\x0f\x00") >= 3   # deleted, LFN

    new = payload(5000, 8)
    names = run(mounted(image, lambda v: write_logs(v, [new])))
    assert names == ["LOG00008.TXT"]
    judge(image, {"LOG00008.TXT": new, "LOG00007.TXT": files["LOG00007.TXT"]},
          tmp_path, fat_tools, external)
    for name, data in files.items():
        assert mtype(external, image, name) == data
    assert mtype(external, image, "Flight notes/note.txt") == b"calibration pattern at 12:00\n"
    with open(image, "rb") as f:
        f.seek(root_offset)
        assert f.read(len(used)) == used               # LFN and other entries untouched


def test_mkfs_made_image_mounts(tmp_path, fat_tools, external):
    image = tmp_path / "card.img"
    format_image(image, 64 * MiB, cluster_bytes=512)      # for its MBR
    offset, length = partition(image)
    subprocess.run([fat_tools["mkfs.fat"], "-F", "32", "-s", "1", "-S", "512",
                    "-h", str(offset // 512), f"--offset={offset // 512}", str(image), str(length // 1024)],
                   check=True, capture_output=True)
    data = payload(70_000, 3)
    names = run(mounted(image, lambda v: write_logs(v, [data], chunk=3000)))
    judge(image, {names[0]: data}, tmp_path, fat_tools, external)


def test_log_numbers_run_out(tmp_path, fat_tools):
    image = tmp_path / "card.img"
    format_image(image, 64 * MiB, cluster_bytes=512)
    source = tmp_path / "x"
    source.write_bytes(b"old\n")
    mtools(fat_tools["mcopy"], image, str(source), "::LOG99998.TXT")
    names = run(mounted(image, lambda v: write_logs(v, [b"last\n"])))
    assert names == ["LOG99999.TXT"]
    with pytest.raises(FatError, match=r"^no free LOG file number: LOG99999\.TXT exists"):
        run(mounted(image, lambda v: v.create_log(T0)))
    assert fsck_findings(fat_tools["fsck.fat"], image, tmp_path) == []


# -- Sync order, dirty bit, card full ---------------------------------------------------------

class Recorder(ImageFile):
    """An image file that records every block written."""

    def __init__(self, path):
        super().__init__(path)
        self.writes = []

    async def write_block(self, lba, data):
        self.writes.append(lba)
        await super().write_block(lba, data)


def test_sync_writes_in_the_safe_order(tmp_path):
    image = tmp_path / "card.img"
    plan = format_image(image, 64 * MiB, cluster_bytes=512)
    part = plan.partition_start
    fat1 = part + plan.reserved_sectors
    fat2 = fat1 + plan.fat_sectors
    data = part + plan.data_offset
    root = data                                             # cluster 2

    def kind(lba):
        if lba == part + 1:
            return "fsinfo"
        if fat1 <= lba < fat2:
            return "fat1"
        if fat2 <= lba < data:
            return "fat2"
        return "dir" if lba == root else "data"

    async def work(device):
        volume = await Volume.mount(device)
        log = await volume.create_log(T0)
        await log.append(payload(129 * 512 + 100))     # crosses FAT sectors 0 -> 1
        device.writes.clear()
        await log.append(b"tail")
        await log.sync(T1)
        return [kind(lba) for lba in device.writes]

    with Recorder(image) as device:
        kinds = run(work(device))
    assert kinds == ["data", "fat1", "fat1", "fat2", "fat2", "dir", "fsinfo"]


#: What ``fsck.fat -n`` may say after a power cut during a sync: a dirty volume, FATs that
#: differ (FAT 2 not yet written), lost clusters and a chain longer than the size (the entry
#: not yet written), a stale FSInfo free count; the lines that go with those, nothing else.
_RECOVERABLE = re.compile(
    r"^(Dirty bit is set\. Fs was not properly unmounted and some data may be corrupt\.|"
    r" Automatically removing dirty bit\.|FATs differ but appear to be intact\.|"
    r"  Using first FAT\.|/LOG\d{5}\.TXT|"
    r"  File size is (\d+) bytes, cluster chain length is > \d+ bytes\.|"
    r"  Truncating file to \d+ bytes\.|Free cluster summary wrong \(\d+ vs\. really \d+\)|"
    r"  Auto-correcting\.|Leaving filesystem unchanged\.|exit status 1|"
    r"Reclaimed \d+ unused clusters \(\d+ bytes\)\.)$")


class Journal(ImageFile):
    """An image file that keeps every block written while ``journal`` is a list."""

    journal = None

    async def write_block(self, lba, data):
        if self.journal is not None:
            self.journal.append((lba, bytes(data)))
        await super().write_block(lba, data)


def test_power_cut_during_a_sync_is_recoverable(tmp_path, fat_tools):
    # Cut the power after each block write of a sync: fsck finds nothing worse than lost
    # clusters, a dirty bit or a stale hint, and the file reads as before or after the sync.
    image, base = tmp_path / "card.img", tmp_path / "base.img"
    format_image(image, 64 * MiB, cluster_bytes=512)
    old = payload(700, 1)
    new = old + payload(129 * 512, 2)

    async def record(device):
        volume = await Volume.mount(device)
        log = await volume.create_log(T0)
        await log.append(old)
        await log.sync(T0)
        await log.append(new[len(old):])               # whole sectors: written already
        copy_range_sparse(image, 0, os.path.getsize(image), base)
        device.journal = []
        await log.sync(T1)
        return log.name, device.journal

    with Journal(image) as device:
        name, journal = run(record(device))
    assert len(journal) == 7        # tail sector, 2 FAT sectors in each FAT, entry, FSInfo
    for cut in range(len(journal) + 1):
        copy_range_sparse(base, 0, os.path.getsize(base), image)
        for lba, data in journal[:cut]:
            patch(image, lba * 512, data)
        findings = fsck_findings(fat_tools["fsck.fat"], image, tmp_path)
        assert [line for line in findings if not _RECOVERABLE.match(line)] == [], cut
        assert dict(read_logs(image))[name] in (old, new), cut


def test_dirty_while_recording_clean_after_close(tmp_path, fat_tools):
    image = tmp_path / "card.img"
    format_image(image, 64 * MiB, cluster_bytes=512)

    async def record(device):
        volume = await Volume.mount(device)
        log = await volume.create_log(T0)
        await log.append(payload(3000))
        await log.sync(T1)
        during = [fat_entries(image, 1)[0], fat_entries(image, 1, fat=1)[0]]
        second = await Volume.mount(device)
        await log.close(T1)
        await volume.close()
        return during, second

    with ImageFile(image) as device:
        during, second = run(record(device))
    notes = second.notes
    assert [value & arch.CLEAN_SHUTDOWN_BIT for value in during] == [0, 0]
    assert any("dirty" in note for note in notes) and second.was_dirty
    assert fat_entries(image, 1)[0] == fat_entries(image, 1, fat=1)[0] == 0x0FFFFFFF
    clean = run(mounted(image, lambda v: asyncio.sleep(0, v)))
    assert clean.notes == [] and not clean.was_dirty
    assert fsck_findings(fat_tools["fsck.fat"], image, tmp_path) == []


def test_card_full(tmp_path, fat_tools, external):
    image = tmp_path / "card.img"
    plan = format_image(image, 40 * MiB, cluster_bytes=512)
    capacity = (plan.cluster_count - 1) * 512               # all but the root cluster
    data = payload(capacity + 5000)

    async def fill(volume):
        log = await volume.create_log(T0)
        with pytest.raises(FatFullError, match="card is full") as full:
            await log.append(data)
        await log.close(T1)
        await volume.close()
        return log.name, full.value.written, volume.free_count

    name, written, free = run(mounted(image, fill))
    assert written == capacity and free == 0
    assert fsinfo(image)[0] == 0
    assert fsck_findings(fat_tools["fsck.fat"], image, tmp_path) == []
    assert dict(read_logs(image))[name] == data[:capacity]
    assert mtype(external, image, name) == data[:capacity]


# -- Mount refusals and notes -----------------------------------------------------------------

def patch(image, offset, data):
    with open(image, "r+b") as f:
        f.seek(offset)
        f.write(data)


@pytest.fixture
def card(tmp_path):
    image = tmp_path / "card.img"
    format_image(image, 64 * MiB, cluster_bytes=512)
    return image


def refusal(image):
    with pytest.raises(FatError) as error:
        run(mounted(image, lambda v: asyncio.sleep(0)))
    message = str(error.value)
    assert "\n" not in message
    return message


def test_refuses_zeroed_mbr(card):
    patch(card, 0, bytes(512))
    assert refusal(card) == "sector 0: no MBR: bytes 510-511 are 0000, not 55aa"


@pytest.mark.parametrize("fat", ["16", "32"])
def test_refuses_a_card_without_partition_table(tmp_path, fat_tools, fat):
    image = tmp_path / "superfloppy.img"
    image.write_bytes(b"")
    os.truncate(image, 64 * MiB)
    subprocess.run([fat_tools["mkfs.fat"], "-F", fat, str(image)], check=True,
                   capture_output=True)
    assert refusal(image) == ("sector 0: a FAT boot sector without a partition table; only "
                              "a card with an MBR partition (as SD cards are formatted) is "
                              "supported")


def test_refuses_mbr_without_partition(card):
    patch(card, 446, bytes(64))
    assert refusal(card) == "sector 0: the MBR has no partition"


def test_refuses_exfat(card):
    offset, _ = partition(card)
    patch(card, offset, b"\xeb\x76\x90EXFAT   " + bytes(53))
    assert "exFAT" in refusal(card)


def test_refuses_fat16(card, fat_tools):
    offset, _ = partition(card)
    subprocess.run([fat_tools["mkfs.fat"], "-F", "16", f"--offset={offset // 512}", str(card),
                    str(60 * 1024)], check=True, capture_output=True)
    assert "FAT12/FAT16, not FAT32" in refusal(card)
    patch(card, 446 + 4, b"\x06")
    assert "type 0x06 (FAT16) is not FAT32" in refusal(card)


def test_refuses_too_few_clusters_for_fat32(card):
    offset, _ = partition(card)
    patch(card, offset + arch.BPB_SEC_PER_CLUS, b"\x02")       # 57,000 clusters
    assert "clusters is FAT12/FAT16, not FAT32" in refusal(card)


def test_refuses_corrupt_boot_sector(card):
    offset, _ = partition(card)
    patch(card, offset + 510, b"\0\0")
    assert "boot sector signature is 0000, not 55aa" in refusal(card)
    patch(card, offset + 510, b"\x55\xaa")
    patch(card, offset + arch.BPB_BYTS_PER_SEC, (4096).to_bytes(2, "little"))
    assert "BPB_BytsPerSec is 4096" in refusal(card)


def test_bad_fsinfo_signature_is_a_note(card, tmp_path):
    offset, _ = partition(card)
    patch(card, offset + 512, b"XXXX")
    data = payload(2000)
    names = run(mounted(card, lambda v: write_logs(v, [data])))
    notes = run(mounted(card, lambda v: asyncio.sleep(0, v.notes)))
    assert notes == [f"FSInfo (sector {offset // 512 + 1}) has bad signatures: ignored and "
                     f"never written; free clusters counted from the FAT"]
    with open(card, "rb") as f:
        f.seek(offset + 512)
        assert f.read(4) == b"XXXX"                         # never written
    assert dict(read_logs(card))[names[0]] == data


def test_implausible_fsinfo_is_recounted(card, tmp_path, fat_tools):
    offset, _ = partition(card)
    patch(card, offset + 512 + 488, (10 ** 9).to_bytes(4, "little") + (7).to_bytes(4, "little"))
    patch(card, offset + 512 + 492, (10 ** 9).to_bytes(4, "little"))
    volume = run(mounted(card, lambda v: asyncio.sleep(0, v)))
    assert len(volume.notes) == 2 and "recounted" in volume.notes[0]
    assert volume.free_count == volume.layout.cluster_count - 1
    assert volume.next_free == 2
    run(mounted(card, lambda v: write_logs(v, [payload(600)])))
    assert fsck_findings(fat_tools["fsck.fat"], card, tmp_path) == []


def test_allocation_wraps_from_the_hint(card, tmp_path, fat_tools, external):
    volume = run(mounted(card, lambda v: asyncio.sleep(0, v)))
    last = volume.layout.max_cluster
    offset, _ = partition(card)
    patch(card, offset + 512 + 492, (last - 1).to_bytes(4, "little"))
    data = payload(3 * 512)
    names = run(mounted(card, lambda v: write_logs(v, [data])))
    with open_card(card) as reader:
        assert reader.clusters(names[0]) == [last - 1, last, 3]
    assert fsinfo(card)[1] == 4
    # From the hint again: last-1 and last are taken, so the search wraps to 4 and 5.
    patch(card, offset + 512 + 492, (last - 1).to_bytes(4, "little"))
    more = payload(2 * 512, 9)
    names += run(mounted(card, lambda v: write_logs(v, [more])))
    with open_card(card) as reader:
        assert reader.clusters(names[1]) == [4, 5]
    judge(card, {names[0]: data, names[1]: more}, tmp_path, fat_tools, external)


# -- The fsck judge itself --------------------------------------------------------------------

def test_fsck_helper_reports_findings(tmp_path, fat_tools):
    image = tmp_path / "card.img"
    format_image(image, 64 * MiB, cluster_bytes=512)
    run(mounted(image, lambda v: write_logs(v, [payload(5000)])))
    assert fsck_findings(fat_tools["fsck.fat"], image, tmp_path) == []
    offset, _ = partition(image)
    patch(image, offset + 512 + 488, (1234).to_bytes(4, "little"))   # wrong free count
    findings = fsck_findings(fat_tools["fsck.fat"], image, tmp_path)
    assert findings and any("ree cluster" in line for line in findings)


def test_timestamp_is_a_datetime_or_a_date_time_pair():
    assert fat32.fat_date_time(T1) == fat32.fat_date_time((T1.date(), T1.time()))
    date, time = fat32.fat_date_time(T1)
    assert date == (44 << 9) | (5 << 5) | 6 and time == (9 << 11) | (30 << 5) | 22
    with pytest.raises(FatError, match="Year 1979"):
        fat32.fat_date_time(dt.datetime(1979, 12, 31))


# -- The ring path: data written by someone else (the DMA) ------------------------------------

async def dma_flush(log, stream, committed, timestamp=T1):
    """Do what the logger's flush does with ``stream[:committed]``: ask the file where its
    sectors from the tail sector on go, write them as the DMA writes them from the ring (a
    partial last sector padded with zeros), then grow the file. Returns the extents."""
    extents = await log.extents(committed)
    for run in extents.runs:
        for k in range(run.count):
            sector = run.file_sector + k
            end = min((sector + 1) * 512, committed)
            await log.volume.device.write_block(
                run.lba + k, stream[sector * 512:end].ljust(512, b"\0"))
    await log.grow(extents.size, timestamp)
    return extents


def check_runs(runs, chain, sectors_per_cluster, first_sector, end_sector):
    """The runs are in file order, each contiguous on the card, cover the sectors
    ``first_sector .. end_sector - 1`` once, and lie where the file's chain puts them."""
    expected, sector = [], first_sector
    for run in runs:
        assert run.file_sector == sector
        for k in range(run.count):
            index, offset = divmod(sector + k, sectors_per_cluster)
            expected.append((chain[index], offset, run.lba + k))
        sector += run.count
    assert sector == end_sector
    return expected


@pytest.mark.parametrize("size, cluster_bytes", [(512 * MiB, 4096), (2200 * MiB, None)])
def test_ring_path_across_cluster_and_fat_sector_boundaries(tmp_path, fat_tools, external,
                                                            size, cluster_bytes):
    # Flush sizes that end mid-sector, on a sector, on a cluster; another file appended
    # between flushes makes the chain fragmented, so some flushes need several runs. Past
    # 128 clusters the chain crosses into the FAT's second sector.
    image = tmp_path / "card.img"
    plan = format_image(image, size, cluster_bytes=cluster_bytes)
    spc = plan.sectors_per_cluster
    cluster = spc * 512
    total = 130 * cluster + 1000
    stream = payload(total, 5)
    other = payload(cluster * 3 + 17, 6)
    steps = [100, 512, 700, cluster, cluster + 1, 3 * cluster - 5, 3 * cluster + 512,
             40 * cluster + 100, 129 * cluster, total]

    async def work(volume):
        log = await volume.create_log(T0)
        side = await volume.create_log(T0)
        seen, multi = [], 0
        synced = 0
        for n, committed in enumerate(steps):
            extents = await dma_flush(log, stream, committed)
            assert extents.size == committed == log.size
            multi += len(extents.runs) > 1
            seen.append((synced // 512, -(-committed // 512), extents.runs))
            synced = committed
            if n % 3 == 1:
                await side.append(other[:cluster])      # takes the next free cluster
                await side.sync(T1)
        await side.close(T1)
        await log.close(T1)
        await volume.close()
        return log.name, side.name, seen, multi

    name, side_name, seen, multi = run(mounted(image, work))
    assert multi >= 2                                   # fragmented: several runs a flush
    judge(image, {name: stream, side_name: other[:cluster] * 3}, tmp_path, fat_tools,
          external)
    with open_card(image) as card:
        chain = card.clusters(name)
        data_lba = card.cluster_offset(2) // 512
    assert len(chain) == -(-total // cluster) and chain[-1] // 128 >= 1
    for first, end, runs in seen:
        for cluster_number, offset, lba in check_runs(runs, chain, spc, first, end):
            assert lba == data_lba + (cluster_number - 2) * spc + offset


def test_ring_path_timestamp_and_refusals(tmp_path):
    image = tmp_path / "card.img"
    format_image(image, 64 * MiB, cluster_bytes=512)

    async def work(volume):
        log = await volume.create_log(T0)
        with pytest.raises(ValueError, match=r"^New size must be an integer of at least 0 "
                                             r"bytes, not -1$"):
            await log.extents(-1)
        extents = await log.extents(1500)               # three 512-byte clusters
        with pytest.raises(ValueError, match="end in the file's last allocated cluster"):
            await log.grow(600, T1)                     # would leave a cluster past its end
        await log.grow(extents.size, T1)
        await log.append(b"host")
        with pytest.raises(FatError, match="appended bytes not yet synced"):
            await log.extents(2000)
        await log.close(T1)
        with pytest.raises(FatError, match="is closed"):
            await log.extents(2000)
        await volume.close()
        return log.name

    name = run(mounted(image, work))
    with open_card(image) as card:
        assert card.stat(name).mtime == T1 and card.stat(name).size == 1504


def test_ring_path_card_full(tmp_path, fat_tools, external):
    image = tmp_path / "card.img"
    plan = format_image(image, 40 * MiB, cluster_bytes=512)
    capacity = (plan.cluster_count - 1) * 512               # all but the root cluster
    stream = payload(capacity + 5000, 3)

    async def fill(volume):
        log = await volume.create_log(T0)
        await dma_flush(log, stream, capacity - 700)
        extents = await dma_flush(log, stream, len(stream) - 10)
        await log.close(T1)
        await volume.close()
        return log.name, extents.size, volume.free_count

    name, fitted, free = run(mounted(image, fill))
    assert fitted == capacity and free == 0
    assert fsinfo(image)[0] == 0
    assert fsck_findings(fat_tools["fsck.fat"], image, tmp_path) == []
    assert dict(read_logs(image))[name] == stream[:capacity]
    assert mtype(external, image, name) == stream[:capacity]


def test_fat_cache_keeps_at_most_n_sectors(tmp_path, fat_tools, external):
    # 512-byte clusters: 128 FAT entries a sector, so 700 clusters cross 6 FAT sectors.
    image = tmp_path / "card.img"
    format_image(image, 64 * MiB, cluster_bytes=512)
    stream = payload(700 * 512 + 300, 4)

    async def work(volume):
        log = await volume.create_log(T0)
        sizes = []
        for committed in range(5000, 300 * 512, 5000):
            await dma_flush(log, stream, committed)
            sizes.append(volume.cached_fat_sectors)
        await dma_flush(log, stream, len(stream))       # 4 FAT sectors changed at once
        sizes.append(volume.cached_fat_sectors)
        await log.close(T1)
        await volume.close()
        return log.name, sizes, volume.fat_reads

    class Sampler(ImageFile):
        """Samples the cache's size at every block access."""
        volume, samples = None, []

        async def read_block(self, lba):
            if self.volume is not None:
                self.samples.append(self.volume.cached_fat_sectors)
            return await super().read_block(lba)

    with Sampler(image) as device:
        volume = run(Volume.mount(device, fat_cache_sectors=2))
        device.volume = volume
        name, sizes, reads = run(work(volume))
    assert max(sizes) == 2                  # after each sync
    # Between syncs sectors with unwritten changes may add to the bound.
    assert max(device.samples) <= 5
    assert reads >= 6                       # each FAT sector was read at least once
    judge(image, {name: stream}, tmp_path, fat_tools, external)
    # An unknown free count is recounted through every FAT sector at mount: the cache
    # still holds two.
    offset, _ = partition(image)
    patch(image, offset + 512 + 488, (0xFFFFFFFF).to_bytes(4, "little"))
    with ImageFile(image) as device:
        volume = run(Volume.mount(device, fat_cache_sectors=2))
        assert volume.fat_reads > 500 and volume.cached_fat_sectors == 2
    with ImageFile(image) as device:
        with pytest.raises(ValueError, match=r"^FAT cache size must be a positive number of "
                                             r"sectors, not 0$"):
            run(Volume.mount(device, fat_cache_sectors=0))


# -- Volume label -----------------------------------------------------------------------------

@pytest.mark.parametrize("label", ["ÄÖÜ", "café", "LOG\x7f", "TAB\tX", "A.B", "TWELVE CHARS", ""])
def test_a_label_that_is_not_plain_ascii_is_refused_in_one_line(tmp_path, label):
    path = tmp_path / "c.img"
    with pytest.raises(FatError, match=r"^Volume label must be 1 to 11 printable ASCII "
                                       r"characters \(letters A-Z, digits, space and "
                                       r"punctuation other than .*\), not ") as error:
        format_image(path, 4_000_000_000, label=label)
    assert "\n" not in str(error.value)
    assert not path.exists()                 # refused before anything was written


def test_a_plain_label_is_stored_upper_case(tmp_path):
    path = tmp_path / "c.img"
    format_image(path, 64 * MiB, cluster_bytes=512, label="log-2024 #1")
    with open(path, "rb") as f:
        f.seek(8192 * 512 + arch.BS_VOL_LAB)
        assert f.read(11) == b"LOG-2024 #1"


def test_cli_card_format_refuses_a_non_ascii_label(tmp_path, capsys):
    from maglog.cli.main import main
    path = tmp_path / "c.img"
    assert main(["card", "format", str(path), "--size", "4GB", "--label", "ÄÖÜ"]) == 1
    captured = capsys.readouterr()
    assert captured.out == "" and captured.err.count("\n") == 1
    assert captured.err.startswith("maglog: error: Volume label must be 1 to 11 printable "
                                   "ASCII characters")
    assert not path.exists()
