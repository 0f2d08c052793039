"""Tests for maglog.calib.card: FAT32 images built by dosfstools and mtools, read back.

The images are made by independent tools (``mkfs.fat``, ``mcopy``, ``mmd``, ``mdel``) in
``tmp_path``; every corruption is a byte patch at an offset this file computes from the
BPB itself (not from the reader under test). Without the tools the tests skip, and fail
under CI=true (the ``fat_tools`` fixture; ``scripts/setup.sh`` installs them).
"""

from __future__ import annotations

import os
import random
import re
import struct
import subprocess
import time
from datetime import datetime
from pathlib import Path

import pytest

from maglog.calib.card import (
    CardError, CardFileNotFoundError, CardWarning, ChainError, TruncatedCardError, Volume,
    open_card, read_logs,
)


#: name → path of the FAT tools, filled from the ``fat_tools`` fixture (tests/conftest.py:
#: a skip with the reason when one is missing, a failure under CI=true).
TOOLS = {}


@pytest.fixture(autouse=True)
def _fat_tools(fat_tools):
    TOOLS.update(fat_tools)


SECTOR = 512
FS_KIB = 64 * 1024              # 64 MiB file system: with -s 1 a legal FAT32 (> 65524 clusters)
PART_LBA = 2048                 # 1 MiB aligned, as SD cards are formatted
MTIME = datetime(2024, 6, 15, 13, 37, 42)


def _run(*args):
    env = dict(os.environ, MTOOLS_SKIP_CHECK="1")
    result = subprocess.run([TOOLS.get(args[0], args[0]), *map(str, args[1:])], env=env,
                            capture_output=True, text=True)
    assert result.returncode == 0, f"{args}: {result.stderr}"


def _log_lines(rng, n):
    """Random ``$``-lines as the logger writes them (CR LF)."""
    lines = []
    for seq in range(n):
        kind = rng.randrange(3)
        if kind == 0:
            body = (f"PMAG1,{seq % 100000:05d},{rng.uniform(-60000, 60000):+08.1f},"
                    f"{rng.uniform(-60000, 60000):+08.1f},{rng.uniform(-60000, 60000):+08.1f}")
            checksum = 0
            for ch in body.encode():
                checksum ^= ch
            lines.append(f"${body}*{checksum:02X}\r\n")
        elif kind == 1:
            lines.append(f"$ {rng.uniform(40000, 60000):09.3f},{rng.randrange(10000):04d}\r\n")
        else:
            lines.append(f"$GPGGA,{seq:06d}.00,4807.038,N,01131.000,E,1,08,0.9,545.4,M,,,,*47\r\n")
    return "".join(lines).encode()


class Fs:
    """An image with a FAT32 file system at ``offset``, and BPB arithmetic done here (not
    by the reader) for patching."""

    def __init__(self, path, offset=0):
        self.path = Path(path)
        self.offset = offset

    def mtools(self, tool, *args):
        _run(tool, "-i", f"{self.path}@@{self.offset}", *args)

    def put(self, tmp_path, data, name, mtime=None):
        src = tmp_path / f"src-{len(list(tmp_path.iterdir()))}"
        src.write_bytes(data)
        if mtime is not None:
            os.utime(src, (mtime.timestamp(), mtime.timestamp()))
        self.mtools("mcopy", "-m", src, f"::/{name}")
        return data

    def peek(self, at, fmt):
        with open(self.path, "rb") as f:
            f.seek(at)
            raw = f.read(struct.calcsize(fmt))
        return struct.unpack(fmt, raw)

    def poke(self, at, data):
        with open(self.path, "r+b") as f:
            f.seek(at)
            f.write(data)

    @property
    def bpb(self):
        bps, spc, rsvd, nfats = self.peek(self.offset + 11, "<HBHB")
        fatsz, _flags, _ver, root, fsinfo = self.peek(self.offset + 36, "<IHHIH")
        return dict(bps=bps, spc=spc, rsvd=rsvd, nfats=nfats, fatsz=fatsz, root=root,
                    fsinfo=fsinfo)

    def fat_at(self, cluster, fat=0):
        b = self.bpb
        return self.offset + (b["rsvd"] + fat * b["fatsz"]) * b["bps"] + 4 * cluster

    def fat(self, cluster):
        return self.peek(self.fat_at(cluster), "<I")[0] & 0x0FFFFFFF

    def set_fat(self, cluster, value):
        for fat in range(self.bpb["nfats"]):
            self.poke(self.fat_at(cluster, fat), struct.pack("<I", value))

    def cluster_at(self, cluster):
        b = self.bpb
        first_data = b["rsvd"] + b["nfats"] * b["fatsz"]
        return self.offset + (first_data + (cluster - 2) * b["spc"]) * b["bps"]

    @property
    def cluster_size(self):
        return self.bpb["bps"] * self.bpb["spc"]

    def chain(self, first):
        chain = [first]
        while (value := self.fat(chain[-1])) < 0x0FFFFFF8:
            chain.append(value)
        return chain

    def root_entries(self):
        """(offset, raw 32 bytes) of every slot of the root directory, deleted ones too."""
        slots = []
        for cluster in self.chain(self.bpb["root"]):
            at = self.cluster_at(cluster)
            with open(self.path, "rb") as f:
                f.seek(at)
                data = f.read(self.cluster_size)
            slots += [(at + i, data[i:i + 32]) for i in range(0, len(data), 32)]
        return slots

    def entry_at(self, name83):
        """Offset of the root directory entry with the 11-byte short name ``name83``."""
        for at, raw in self.root_entries():
            if raw[:11] == name83 and raw[11] & 0x3F != 0x0F:
                return at
        raise LookupError(name83)

    def first_cluster(self, name83):
        at = self.entry_at(name83)
        hi, = self.peek(at + 20, "<H")
        lo, = self.peek(at + 26, "<H")
        return hi << 16 | lo


def _mkfs(*args):
    _run("mkfs.fat", "-F", "32", "-s", "1", "-n", "MAGLOG", "--invariant", *args)


def make_bare(tmp_path, name="part.img"):
    path = tmp_path / name
    with open(path, "wb") as f:
        f.truncate(FS_KIB * 1024)
    _mkfs(path)
    return Fs(path)


def _mbr(entries):
    sector = bytearray(SECTOR)
    for i, (ptype, lba, count) in enumerate(entries):
        struct.pack_into("<B3sB3sII", sector, 0x1BE + 16 * i, 0x00, b"\xfe\xff\xff", ptype,
                         b"\xfe\xff\xff", lba, count)
    sector[510:512] = b"\x55\xaa"
    return bytes(sector)


def make_card(tmp_path, name="card.img", entries=None, fs_lba=PART_LBA):
    """A card image: our own MBR, then mkfs.fat at ``fs_lba`` (1 MiB aligned)."""
    path = tmp_path / name
    fs_sectors = FS_KIB * 1024 // SECTOR
    with open(path, "wb") as f:
        f.truncate(fs_lba * SECTOR + FS_KIB * 1024)
    _mkfs(f"--offset={fs_lba}", "-h", fs_lba, path, FS_KIB)
    with open(path, "r+b") as f:
        f.write(_mbr(entries or [(0x0C, fs_lba, fs_sectors)]))
    return Fs(path, fs_lba * SECTOR)


# -- a populated card ---------------------------------------------------------------------

@pytest.fixture(scope="module")
def card(tmp_path_factory):
    """A partitioned card with logs (multi-cluster), a fragmented file, a subdirectory,
    long-name files, an empty file and deleted entries; returns (Fs, {path: bytes})."""
    tmp = tmp_path_factory.mktemp("card")
    src = tmp / "src"
    src.mkdir()
    fs = make_card(tmp)
    rng = random.Random(1)
    files = {}
    files["LOG00001.TXT"] = fs.put(src, _log_lines(rng, 400), "LOG00001.TXT", MTIME)
    files["LOG00002.TXT"] = fs.put(src, _log_lines(rng, 3), "LOG00002.TXT")
    # Fragmentation: free a hole of 6 clusters below the allocation hint, make mtools
    # forget the hint (FSInfo next free = unknown), then write a 20-cluster file into it.
    fs.put(src, rng.randbytes(6 * SECTOR), "FILL1.BIN")
    files["A.BIN"] = fs.put(src, rng.randbytes(1500), "A.BIN")
    fs.mtools("mdel", "::/FILL1.BIN")
    fs.poke(fs.offset + fs.bpb["fsinfo"] * SECTOR + 492, b"\xff\xff\xff\xff")
    files["FRAG.BIN"] = fs.put(src, rng.randbytes(20 * SECTOR - 77), "FRAG.BIN")
    fs.mtools("mmd", "::/DATA")
    files["DATA/LOG00099.TXT"] = fs.put(src, _log_lines(rng, 50), "DATA/LOG00099.TXT")
    files["DATA/Long file name log.txt"] = fs.put(src, _log_lines(rng, 30),
                                                  "DATA/Long file name log.txt")
    files["Flight notes 2024.txt"] = fs.put(src, b"survey notes\r\n" * 100,
                                            "Flight notes 2024.txt")
    files["EMPTY.TXT"] = fs.put(src, b"", "EMPTY.TXT")
    fs.put(src, b"gone\r\n" * 300, "DELME.TXT")
    fs.put(src, b"gone too\r\n", "Deleted long name.txt")
    fs.mtools("mdel", "::/DELME.TXT")
    fs.mtools("mdel", "::/Deleted long name.txt")
    return fs, files


def test_card_layout_is_what_the_tests_need(card):
    """The scenario really holds fragmentation, deleted and long-name slots (checked on
    the raw bytes, not through the reader)."""
    fs, _ = card
    chain = fs.chain(fs.first_cluster(b"FRAG    BIN"))
    assert any(b != a + 1 for a, b in zip(chain, chain[1:])), chain
    slots = [raw for _, raw in fs.root_entries()]
    assert any(raw[0] == 0xE5 and raw[11] & 0x3F != 0x0F for raw in slots)   # deleted 8.3
    assert any(raw[0] == 0xE5 and raw[11] & 0x3F == 0x0F for raw in slots)   # deleted LFN
    assert any(raw[0] != 0xE5 and raw[11] & 0x3F == 0x0F for raw in slots)   # live LFN
    assert any(raw[11] == 0x08 for raw in slots)                             # volume label
    assert len(fs.chain(fs.first_cluster(b"LOG00001TXT"))) > 10


def test_card_geometry(card):
    fs, _ = card
    with open_card(fs.path) as vol:
        assert vol.partition_index == 0 and vol.partition_type == 0x0C
        assert vol.partition_offset == PART_LBA * SECTOR
        b = vol.boot
        assert (b.bytes_per_sector, b.sectors_per_cluster) == (SECTOR, 1)
        assert (b.reserved_sectors, b.num_fats, b.fat_size, b.root_cluster) == (
            fs.bpb["rsvd"], 2, fs.bpb["fatsz"], fs.bpb["root"])
        assert b.total_sectors == FS_KIB * 1024 // SECTOR
        assert b.fsinfo_sector == 1 and b.volume_label == "MAGLOG"
        assert vol.cluster_count > 65524
        assert vol.clean_shutdown is True
        assert vol.warnings == []


def test_listdir_root(card):
    fs, _ = card
    with open_card(fs.path) as vol:
        entries = {e.name: e for e in vol.listdir()}
    alias = [n for n in entries if re.fullmatch(r"FLIGHT~\d\.TXT", n)]
    assert len(alias) == 1, sorted(entries)
    assert set(entries) == {"LOG00001.TXT", "LOG00002.TXT", "A.BIN", "FRAG.BIN", "DATA",
                            "EMPTY.TXT", alias[0]}
    data = entries["DATA"]
    assert data.is_dir and data.size == 0 and data.first_cluster >= 2
    log = entries["LOG00001.TXT"]
    assert not log.is_dir and log.size == len(card[1]["LOG00001.TXT"])
    assert log.first_cluster == fs.first_cluster(b"LOG00001TXT")
    assert log.mtime == MTIME
    assert entries["EMPTY.TXT"].size == 0 and entries["EMPTY.TXT"].first_cluster == 0


def test_listdir_subdirectory(card):
    fs, files = card
    with open_card(fs.path) as vol:
        names = [e.name for e in vol.listdir("DATA")]
        assert names == [e.name for e in vol.listdir("/data/")]
    assert names[0] == "LOG00099.TXT"
    assert len(names) == 2 and re.fullmatch(r"LONGFI~\d\.TXT", names[1])


def test_read_matches_sources_byte_for_byte(card):
    fs, files = card
    with open_card(fs.path) as vol:
        alias = {e.name: e for e in vol.listdir()}
        flight = next(n for n in alias if n.startswith("FLIGHT~"))
        sub = {e.name: e for e in vol.listdir("DATA")}
        longname = next(n for n in sub if n.startswith("LONGFI~"))
        for name in ("LOG00001.TXT", "LOG00002.TXT", "A.BIN", "FRAG.BIN", "EMPTY.TXT",
                     "DATA/LOG00099.TXT"):
            assert vol.read(name) == files[name], name
        assert vol.read(flight) == files["Flight notes 2024.txt"]
        assert vol.read(f"/DATA/{longname}") == files["DATA/Long file name log.txt"]
        assert vol.read("log00001.txt") == files["LOG00001.TXT"]
        assert vol.clusters("FRAG.BIN") == fs.chain(fs.first_cluster(b"FRAG    BIN"))
        assert vol.warnings == []


def test_log_files_and_read_logs(card):
    fs, files = card
    with open_card(fs.path) as vol:
        assert vol.log_files() == ["LOG00001.TXT", "LOG00002.TXT"]
    assert read_logs(fs.path) == [("LOG00001.TXT", files["LOG00001.TXT"]),
                                  ("LOG00002.TXT", files["LOG00002.TXT"])]


def test_bare_partition_and_bytes_input(tmp_path):
    fs = make_bare(tmp_path)
    log = fs.put(tmp_path, _log_lines(random.Random(2), 200), "LOG00007.TXT")
    with open_card(fs.path) as vol:
        assert vol.partition_index is None and vol.partition_offset == 0
        assert vol.read("LOG00007.TXT") == log
    with open_card(fs.path.read_bytes()) as vol:
        assert vol.log_files() == ["LOG00007.TXT"]
        assert vol.read("LOG00007.TXT") == log
    assert read_logs(fs.path) == [("LOG00007.TXT", log)]


def test_first_fat32_partition_is_used(tmp_path):
    """Partition 1 is not FAT (zeros); partition 2 is the FAT32 volume."""
    fs_sectors = FS_KIB * 1024 // SECTOR
    fs = make_card(tmp_path, fs_lba=2 * PART_LBA,
                   entries=[(0x83, PART_LBA, PART_LBA), (0x0C, 2 * PART_LBA, fs_sectors)])
    log = fs.put(tmp_path, b"$ 49895.131,1249\r\n" * 50, "LOG00001.TXT")
    with open_card(fs.path) as vol:
        assert vol.partition_index == 1
        assert vol.read("LOG00001.TXT") == log


def test_plain_text_log(tmp_path):
    text = _log_lines(random.Random(3), 40)
    path = tmp_path / "flight.log"
    path.write_bytes(text)
    assert read_logs(path) == [("flight.log", text)]
    with pytest.raises(CardError, match="not a card or partition image"):
        open_card(path)


def test_plain_text_log_with_a_nul_byte_is_still_a_log(tmp_path):
    # One NUL in the first 64 KiB (a glitch on the serial line) was refused as "not a card
    # image" before issue 10; the parser reports that line as bad_byte.
    text = bytearray(_log_lines(random.Random(3), 40))
    text[len(text) // 2] = 0
    path = tmp_path / "LOG00001.TXT"
    path.write_bytes(bytes(text))
    assert read_logs(path) == [("LOG00001.TXT", bytes(text))]
    # An image whose boot signature is gone is mostly zeros: still not a text log.
    with pytest.raises(CardError):
        read_logs(bytes(1024) + text[:200])


def test_sparse_1gib_image_opens_fast(tmp_path):
    path = tmp_path / "big.img"
    with open(path, "wb") as f:
        f.truncate(1 << 30)
    _run("mkfs.fat", "-F", "32", path)
    fs = Fs(path)
    log = fs.put(tmp_path, _log_lines(random.Random(4), 2000), "LOG00001.TXT")
    start = time.perf_counter()
    with open_card(path) as vol:
        assert vol.read("LOG00001.TXT") == log
        assert vol.log_files() == ["LOG00001.TXT"]
    assert time.perf_counter() - start < 0.5
    assert os.stat(path).st_blocks * 512 < 64 << 20    # still sparse: nothing was written


# -- errors -------------------------------------------------------------------------------

@pytest.fixture
def bare(tmp_path):
    """A bare partition with a multi-cluster LOG00001.TXT; returns (Fs, data)."""
    fs = make_bare(tmp_path)
    data = fs.put(tmp_path, _log_lines(random.Random(5), 200), "LOG00001.TXT")
    assert len(data) > 8 * fs.cluster_size
    return fs, data


def test_random_bytes(tmp_path):
    junk = bytearray(random.Random(6).randbytes(1 << 20))
    junk[510:512] = b"\x12\x34"
    path = tmp_path / "junk.img"
    path.write_bytes(bytes(junk))
    with pytest.raises(CardError, match=r"not a card or partition image.*510-511.*12 34"):
        open_card(path)
    with pytest.raises(CardError, match="not a card or partition image"):
        read_logs(path)


@pytest.mark.parametrize("content, message", [
    (b"", "shorter than one 512-byte sector"),
    (b"\x00" * 100, "shorter than one 512-byte sector"),
])
def test_tiny_files(tmp_path, content, message):
    path = tmp_path / "tiny.img"
    path.write_bytes(content)
    with pytest.raises(CardError, match=message):
        open_card(path)


def test_missing_file(tmp_path):
    with pytest.raises(CardError, match="cannot open .*nothing.img"):
        open_card(tmp_path / "nothing.img")
    with pytest.raises(CardError, match="cannot open .*nothing.img"):
        read_logs(tmp_path / "nothing.img")


def test_bad_signature_bare(bare):
    fs, _ = bare
    fs.poke(510, b"\x00\x00")
    with pytest.raises(CardError, match=r"boot sector at byte 0 .*signature at bytes "
                                        r"510-511 is 00 00, expected 55 aa"):
        open_card(fs.path)


def test_bad_signature_partition(tmp_path):
    fs = make_card(tmp_path)
    fs.poke(fs.offset + 510, b"\x55\x55")
    with pytest.raises(CardError, match=r"partition 1 \(type 0x0c, LBA 2048.*boot sector at "
                                        r"byte 1048576 .*signature .* 55 55"):
        open_card(fs.path)


def test_sector_size_zero(bare):
    fs, _ = bare
    fs.poke(11, b"\x00\x00")
    with pytest.raises(CardError, match=r"boot sector at byte 0 .*bytes per sector "
                                        r"\(BPB_BytsPerSec, byte 11\) is 0"):
        open_card(fs.path)


def test_sector_size_zero_in_partition(tmp_path):
    fs = make_card(tmp_path)
    fs.poke(fs.offset + 11, b"\x00\x00")
    with pytest.raises(CardError, match=r"partition 1 .*bytes per sector .* is 0"):
        open_card(fs.path)


def test_sectors_per_cluster_not_power_of_two(bare):
    fs, _ = bare
    fs.poke(13, b"\x03")
    with pytest.raises(CardError, match=r"sectors per cluster .* is 3"):
        open_card(fs.path)


def test_fat16_is_rejected(tmp_path):
    path = tmp_path / "fat16.img"
    with open(path, "wb") as f:
        f.truncate(16 << 20)
    _run("mkfs.fat", "-F", "16", path)
    with pytest.raises(CardError, match="not FAT32: BPB_RootEntCnt"):
        open_card(path)


def test_root_cluster_out_of_range(bare):
    fs, _ = bare
    fs.poke(44, struct.pack("<I", 0x0FFFFFF0))
    with pytest.raises(CardError, match=r"root cluster \(BPB_RootClus, byte 44\) is 268435440"):
        open_card(fs.path)


def test_file_system_larger_than_partition(tmp_path):
    fs = make_card(tmp_path, entries=[(0x0C, PART_LBA, 1000)])
    with pytest.raises(CardError, match=r"131072 sectors .* more than the partition's 1000"):
        open_card(fs.path)


def test_truncated_image(tmp_path):
    fs = make_card(tmp_path)
    rng = random.Random(7)
    first = fs.put(tmp_path, _log_lines(rng, 60), "LOG00001.TXT")
    fs.put(tmp_path, _log_lines(rng, 200), "LOG00002.TXT")
    second = fs.first_cluster(b"LOG00002TXT")
    cut = fs.cluster_at(second + 3) + 100
    full = fs.offset + FS_KIB * 1024
    os.truncate(fs.path, cut)
    with pytest.raises(TruncatedCardError,
                       match=rf"image is truncated: partition 1 .* ends at byte {full}, but "
                             rf"the image has only {cut} bytes \({full - cut} bytes missing"
                       ) as info:
        open_card(fs.path)
    assert info.value.missing == full - cut
    with pytest.raises(TruncatedCardError, match="bytes missing"):
        read_logs(fs.path)

    with Volume(fs.path, allow_truncated=True) as vol:
        assert any("truncated" in w for w in vol.warnings)
        assert vol.read("LOG00001.TXT") == first
        with pytest.raises(TruncatedCardError,
                           match=rf"'LOG00002.TXT'.*cluster {second + 3} at .* past the "
                                 rf"end of the image \({cut} bytes.*only the first "
                                 rf"{3 * SECTOR + 100} of"):
            vol.read("LOG00002.TXT")
    with pytest.warns(CardWarning, match="LOG00002.TXT left out"):
        assert read_logs(fs.path, allow_truncated=True) == [("LOG00001.TXT", first)]


def test_truncated_before_the_partition(tmp_path):
    fs = make_card(tmp_path)
    os.truncate(fs.path, 4096)
    with pytest.raises(TruncatedCardError, match=r"partition 1 .*boot sector at byte 1048576"
                                                  r".*image ends at byte 4096"):
        open_card(fs.path)


def test_chain_loop(bare):
    fs, _ = bare
    chain = fs.chain(fs.first_cluster(b"LOG00001TXT"))
    fs.set_fat(chain[-1], chain[2])
    with open_card(fs.path) as vol:
        with pytest.raises(ChainError, match=rf"'LOG00001.TXT'.*cluster {chain[-1]} \(number "
                                             rf"{len(chain)} of the chain\) links back to "
                                             rf"cluster {chain[2]} .*a loop"):
            vol.read("LOG00001.TXT")


def test_cluster_out_of_range_in_chain(bare):
    fs, _ = bare
    chain = fs.chain(fs.first_cluster(b"LOG00001TXT"))
    fs.set_fat(chain[1], 0x0FFFFFF0)
    with open_card(fs.path) as vol:
        with pytest.raises(ChainError, match=rf"cluster {chain[1]} \(number 2 of the chain\) "
                                             rf"links to cluster 268435440 .*outside the "
                                             rf"clusters 2\.\.{vol.boot.max_cluster}"):
            vol.read("LOG00001.TXT")


def test_free_cluster_in_chain(bare):
    fs, _ = bare
    chain = fs.chain(fs.first_cluster(b"LOG00001TXT"))
    fs.set_fat(chain[3], 0)
    with open_card(fs.path) as vol:
        with pytest.raises(ChainError, match=rf"cluster {chain[3]} \(number 4 of the chain\) "
                                             rf"is marked free .*byte {fs.fat_at(chain[3])} "):
            vol.read("LOG00001.TXT")


def test_bad_cluster_in_chain(bare):
    fs, _ = bare
    chain = fs.chain(fs.first_cluster(b"LOG00001TXT"))
    fs.set_fat(chain[0], 0x0FFFFFF7)
    with open_card(fs.path) as vol:
        with pytest.raises(ChainError, match=rf"cluster {chain[0]} .* is marked bad"):
            vol.read("LOG00001.TXT")


def test_first_cluster_out_of_range(bare):
    fs, _ = bare
    fs.poke(fs.entry_at(b"LOG00001TXT") + 20, struct.pack("<H", 0x0FFF))
    with open_card(fs.path) as vol:
        with pytest.raises(ChainError, match=r"first cluster \d+ is outside the clusters"):
            vol.read("LOG00001.TXT")


def test_size_exceeds_chain(bare):
    fs, data = bare
    at = fs.entry_at(b"LOG00001TXT")
    fs.poke(at + 28, struct.pack("<I", len(data) + 10 * fs.cluster_size))
    n = len(fs.chain(fs.first_cluster(b"LOG00001TXT")))
    with open_card(fs.path) as vol:
        with pytest.raises(ChainError, match=rf"'LOG00001.TXT' \(entry at byte {at} .*needs "
                                             rf"{n + 10} clusters .* ends after {n} .*shorter "
                                             rf"than the directory size"):
            vol.read("LOG00001.TXT")


def test_size_larger_than_partition(bare):
    fs, _ = bare
    fs.poke(fs.entry_at(b"LOG00001TXT") + 28, struct.pack("<I", 0xFFFFFF00))
    with open_card(fs.path) as vol:
        with pytest.raises(CardError, match="larger than the whole data region"):
            vol.read("LOG00001.TXT")


def test_chain_longer_than_size_is_a_warning(bare):
    fs, data = bare
    short = len(data) - 3 * fs.cluster_size
    fs.poke(fs.entry_at(b"LOG00001TXT") + 28, struct.pack("<I", short))
    with open_card(fs.path) as vol:
        assert vol.read("LOG00001.TXT") == data[:short]
        assert any("3 more than" in w for w in vol.warnings), vol.warnings


def test_not_found(bare):
    fs, _ = bare
    with open_card(fs.path) as vol:
        with pytest.raises(CardFileNotFoundError, match=r"'LOG09999.TXT' not found in "
                                                        r"directory /"):
            vol.read("LOG09999.TXT")
        with pytest.raises(CardError, match=r"'NOPE' not found in directory /"):
            vol.listdir("NOPE/")
        with pytest.raises(CardError, match="is a file, not a directory"):
            vol.read("LOG00001.TXT/X")
        with pytest.raises(CardError, match="is a directory, not a file"):
            vol.read("/")


def test_dirty_volume_is_a_warning(bare):
    fs, data = bare
    fs.set_fat(1, 0x0FFFFFFF & ~0x08000000)
    with open_card(fs.path) as vol:
        assert vol.clean_shutdown is False
        assert any("not cleanly unmounted" in w for w in vol.warnings)
        assert vol.read("LOG00001.TXT") == data


def test_active_fat_when_mirroring_is_disabled(bare):
    """BPB_ExtFlags bit 7 with active FAT #2: chains come from FAT #2, FAT #1 is ignored."""
    fs, data = bare
    chain = fs.chain(fs.first_cluster(b"LOG00001TXT"))
    fs.poke(fs.fat_at(chain[1], fat=0), struct.pack("<I", 0))
    with open_card(fs.path) as vol:
        with pytest.raises(ChainError, match="FAT #1 entry .* is 0"):
            vol.read("LOG00001.TXT")
    fs.poke(40, struct.pack("<H", 0x0081))
    with open_card(fs.path) as vol:
        assert vol.read("LOG00001.TXT") == data


def test_4096_byte_sectors(tmp_path):
    path = tmp_path / "4k.img"
    with open(path, "wb") as f:
        f.truncate(300 << 20)
    _run("mkfs.fat", "-F", "32", "-S", "4096", "-s", "1", path)
    fs = Fs(path)
    log = fs.put(tmp_path, _log_lines(random.Random(8), 500), "LOG00003.TXT")
    with open_card(path) as vol:
        assert vol.boot.bytes_per_sector == 4096 and vol.cluster_size == 4096
        assert vol.read("LOG00003.TXT") == log
        assert vol.clusters("LOG00003.TXT") == fs.chain(fs.first_cluster(b"LOG00003TXT"))


def test_closed_volume(bare):
    fs, _ = bare
    vol = open_card(fs.path)
    vol.close()
    with pytest.raises(CardError, match="the volume is closed"):
        vol.read("LOG00001.TXT")


def test_directory_chain_loop(bare):
    fs, _ = bare
    root = fs.bpb["root"]
    fs.set_fat(root, root)
    with open_card(fs.path) as vol:
        with pytest.raises(ChainError, match=rf"directory /: cluster {root} \(number 1 of the "
                                             rf"chain\) links back to cluster {root} .*a loop"):
            vol.log_files()
