"""Card reader: SD card image → MBR partition → FAT32 → the logger's ``LOG*.TXT`` files.

Written from Microsoft's "FAT: General Overview of On-Disk Format" (fatgen103, v1.03) and
the IBM PC master boot record layout, independently of the firmware's FAT writer (``sw/``),
so that each checks the other. No third-party FAT code is used.

The image is read through ``mmap`` (or from a bytes object), never loaded whole: a large,
sparse card image opens in a few milliseconds, and only the sectors a request needs are
touched. Every problem ends in a :class:`CardError` that says where (byte offset, sector,
cluster, directory entry) and what is wrong; oddities that do not stop a read (a cluster
chain longer than the file, a backup boot sector that differs, a dirty volume) are collected
in :attr:`Volume.warnings`.

Decisions beyond the specification's letter:

* MBR partition start addresses (LBA) are counted in 512-byte units, as on SD cards.
* The first partition whose boot sector is a valid FAT32 BPB is used, whatever its type byte
  (a FAT32 volume behind a type other than 0x0B/0x0C gives a warning). Extended (0x05, 0x0F,
  0x85) and GPT protective (0xEE) entries are not followed.
* The FAT type is decided by the cluster count, as fatgen103 says: fewer than 65,525
  clusters is FAT12/16 and is rejected even when the BPB has FAT32 fields.
* Chains are followed in FAT #1, or in the active FAT when ``BPB_ExtFlags`` disables
  mirroring.
* Names are the 8.3 short names as stored (``NAME.EXT``, upper case, OEM code page 850 as
  dosfstools and mtools use); the Windows NT lower-case flags and long names are ignored,
  lookups are case-insensitive.
* A chain that breaks (free, bad or out-of-range cluster, a loop) is an error even past the
  clusters the file size needs; a chain that is merely longer than needed is a warning.
* Times are naive :class:`~datetime.datetime` (FAT has no time zone); an invalid date or
  time gives ``None``.
"""

from __future__ import annotations

import enum
import fnmatch
import mmap
import os
import struct
import warnings as _warnings
from dataclasses import dataclass
from datetime import datetime
from pathlib import Path


__all__ = ["CardError", "TruncatedCardError", "ChainError", "CardFileNotFoundError",
           "CardWarning", "Attr", "BootSector", "DirEntry", "Volume", "open_card",
           "read_logs"]


class CardError(Exception):
    """A card image, partition or FAT32 file system is unusable or inconsistent."""


class TruncatedCardError(CardError):
    """The image ends before the partition or file system does; ``missing`` bytes."""
    def __init__(self, message, missing=None):
        super().__init__(message)
        self.missing = missing


class ChainError(CardError):
    """A cluster chain in the FAT is broken (free, bad or out-of-range cluster, loop) or
    does not match its directory entry."""


class CardFileNotFoundError(CardError):
    """A path names no file or directory on the volume."""


class CardWarning(UserWarning):
    """Something read from the card was skipped (see :func:`read_logs`)."""


# Ref: MBR layout (IBM PC): partition table of four 16-byte entries at 0x1BE, 0x55 0xAA
# at 510.
MBR_TABLE = 0x1BE
MBR_ENTRY = struct.Struct("<B3sB3sII")      # status, CHS first, type, CHS last, LBA, count
MBR_ENTRIES = 4
MBR_SECTOR = 512                            # LBA unit of an SD card's partition table
SIGNATURE_OFFSET = 510
SIGNATURE = b"\x55\xaa"
PARTITION_EXTENDED = (0x05, 0x0F, 0x85)
PARTITION_GPT = 0xEE
PARTITION_FAT32 = (0x0B, 0x0C)

# Ref: fatgen103 "Boot Sector and BPB Structure" and "FAT32 Structure Starting at Offset 36".
BPB = struct.Struct("<3s8sHBHBHHBHHHIIIHHIHH12sBBBI11s8s")   # 90 bytes
BYTES_PER_SECTOR = (512, 1024, 2048, 4096)
SECTORS_PER_CLUSTER = (1, 2, 4, 8, 16, 32, 64, 128)
MEDIA_BYTES = (0xF0,) + tuple(range(0xF8, 0x100))
EXT_BOOT_SIGNATURE = 0x29
EXT_FLAGS_NO_MIRROR = 0x0080                # bit 7: only the active FAT is in use
EXT_FLAGS_ACTIVE = 0x000F                   # bits 0-3: the active FAT
NO_SECTOR = (0, 0xFFFF)                     # BPB_FSInfo / BPB_BkBootSec: "none"

# Ref: fatgen103 "FAT Type Determination": the cluster count alone decides the FAT type.
FAT16_MAX_CLUSTERS = 65524

# Ref: fatgen103 "FAT32 FSInfo Sector Structure and Backup Boot Sector".
FSI_LEAD = (0, 0x41615252)
FSI_STRUC = (484, 0x61417272)
FSI_FREE_COUNT = 488
FSI_NEXT_FREE = 492
FSI_TRAIL = (508, 0xAA550000)
FSI_UNKNOWN = 0xFFFFFFFF

# Ref: fatgen103 "FAT Data Structure": FAT32 entries are 28 bits in 32.
FAT_ENTRY_SIZE = 4
FAT_MASK = 0x0FFFFFFF
FAT_FREE = 0
FAT_BAD = 0x0FFFFFF7
FAT_EOC = 0x0FFFFFF8                        # this and above: end of chain
FIRST_CLUSTER = 2
CLEAN_SHUTDOWN = 0x08000000                 # FAT[1] bit 27: volume cleanly unmounted
NO_HARD_ERROR = 0x04000000                  # FAT[1] bit 26: no disk I/O error seen

# Ref: fatgen103 "FAT Directory Structure" and "FAT Long Directory Entries".
DIR_ENTRY = struct.Struct("<11sBBBHHHHHHHI")  # 32 bytes
DIR_ENTRY_SIZE = DIR_ENTRY.size
DIR_END = 0x00                              # DIR_Name[0]: this and all later entries free
DIR_DELETED = 0xE5                          # DIR_Name[0]: entry free
DIR_KANJI_E5 = 0x05                         # DIR_Name[0]: the name really starts with 0xE5
ATTR_LONG_NAME_MASK = 0x3F
MAX_DIR_BYTES = 65536 * DIR_ENTRY_SIZE      # at most 65,536 entries in a directory
NAME_ENCODING = "cp850"                     # dosfstools' and mtools' default OEM code page
# A path is at most 260 characters where FAT volumes are written (Windows' MAX_PATH), so a
# tree holds at most 130 levels of one-letter folders ("A/A/..."); deeper is a corrupt tree.
MAX_PATH = 260
MAX_DEPTH = MAX_PATH // 2


class Attr(enum.IntFlag):
    """Directory entry attributes (``DIR_Attr``)."""
    READ_ONLY = 0x01
    HIDDEN = 0x02
    SYSTEM = 0x04
    VOLUME_ID = 0x08
    DIRECTORY = 0x10
    ARCHIVE = 0x20
    LONG_NAME = 0x0F


@dataclass(frozen=True)
class BootSector:
    """The FAT32 BPB fields the reader uses, and the layout derived from them."""
    offset: int                 # byte offset of the boot sector in the image
    bytes_per_sector: int
    sectors_per_cluster: int
    reserved_sectors: int
    num_fats: int
    fat_size: int               # sectors per FAT
    root_cluster: int
    total_sectors: int
    fsinfo_sector: int          # 0 when there is none
    backup_boot_sector: int     # 0 when there is none
    hidden_sectors: int
    media: int
    ext_flags: int
    volume_id: int | None
    volume_label: str | None
    oem_name: str

    @property
    def cluster_size(self):
        return self.bytes_per_sector * self.sectors_per_cluster

    @property
    def first_data_sector(self):
        return self.reserved_sectors + self.num_fats * self.fat_size

    @property
    def cluster_count(self):
        return (self.total_sectors - self.first_data_sector) // self.sectors_per_cluster

    @property
    def max_cluster(self):
        """The highest valid cluster number."""
        return self.cluster_count + FIRST_CLUSTER - 1

    @property
    def active_fat(self):
        """The FAT the reader follows: FAT #1 (index 0) unless mirroring is disabled."""
        return self.ext_flags & EXT_FLAGS_ACTIVE if self.ext_flags & EXT_FLAGS_NO_MIRROR else 0

    @property
    def size(self):
        """Bytes of the file system."""
        return self.total_sectors * self.bytes_per_sector


@dataclass(frozen=True)
class DirEntry:
    """One short-name directory entry."""
    name: str                   # "NAME.EXT", or "NAME" without an extension
    size: int
    first_cluster: int
    attributes: Attr
    mtime: datetime | None
    is_dir: bool
    offset: int                 # byte offset of the 32-byte entry in the image


@dataclass(frozen=True)
class FsInfo:
    """The FSInfo sector's hints (``None`` when the sector says "unknown")."""
    free_count: int | None
    next_free: int | None


def _hex(value, digits=1):
    return f"0x{value:0{digits}X}"


def _where(offset):
    """A byte offset in the image, with its 512-byte sector (the card's LBA)."""
    return f"byte {offset} ({_hex(offset)}, image sector {offset // MBR_SECTOR})"


class _Image:
    """Random access to the image bytes: an mmap of a file, or a bytes-like object."""

    def __init__(self, source):
        self._file = None
        if isinstance(source, (bytes, bytearray, memoryview)):
            view = memoryview(source)
            self._buf = view if view.format == "B" and view.ndim == 1 else view.cast("B")
            self.name = "<bytes>"
            self.size = len(self._buf)
            return
        try:
            path = os.fspath(source)
        except TypeError:
            raise CardError(f"expected a path or bytes, not {type(source).__name__}") from None
        self.name = str(path)
        try:
            self._file = open(path, "rb")
            self.size = os.fstat(self._file.fileno()).st_size
            self._buf = (mmap.mmap(self._file.fileno(), 0, access=mmap.ACCESS_READ)
                         if self.size else b"")
        except OSError as exc:
            self.close()
            raise CardError(f"cannot open {self.name}: {exc.strerror or exc}") from None

    def close(self):
        if isinstance(getattr(self, "_buf", None), mmap.mmap):
            self._buf.close()
        self._buf = None
        if self._file is not None:
            self._file.close()
            self._file = None

    def available(self, offset, length):
        return offset + length <= self.size

    def need(self, offset, length, what):
        if self._buf is None:
            raise CardError(f"{self.name}: the volume is closed")
        if not self.available(offset, length):
            missing = offset + length - self.size
            raise TruncatedCardError(
                f"{what} at {_where(offset)} needs bytes up to {offset + length}, but the "
                f"image ends at byte {self.size} ({missing} bytes missing)", missing)

    def read(self, offset, length, what):
        self.need(offset, length, what)
        return bytes(self._buf[offset:offset + length])

    def u32(self, offset, what):
        self.need(offset, 4, what)
        return struct.unpack_from("<I", self._buf, offset)[0]


def _looks_like_boot_sector(sector):
    # Ref: fatgen103 BS_jmpBoot: EB ?? 90 or E9 ?? ??.
    return (sector[0] == 0xEB and sector[2] == 0x90) or sector[0] == 0xE9


def _parse_boot_sector(image, offset, *, check_signature=True):
    """Parse and check the FAT32 BPB at ``offset``; raise :class:`CardError` otherwise."""
    where = f"boot sector at {_where(offset)}"
    sector = image.read(offset, MBR_SECTOR, "boot sector")
    if not _looks_like_boot_sector(sector):
        raise CardError(f"{where}: no FAT boot sector: jump instruction is "
                        f"{sector[:3].hex(' ')}, expected EB xx 90 or E9 xx xx")
    if check_signature and sector[SIGNATURE_OFFSET:SIGNATURE_OFFSET + 2] != SIGNATURE:
        raise CardError(f"{where}: signature at bytes 510-511 is "
                        f"{sector[SIGNATURE_OFFSET:SIGNATURE_OFFSET + 2].hex(' ')}, "
                        f"expected 55 aa")
    (_jump, oem, bps, spc, reserved, nfats, root_entries, tot16, media, fat16, _spt, _heads,
     hidden, tot32, fat32, ext_flags, fs_version, root_cluster, fsinfo, backup, _reserved,
     _drive, _reserved1, boot_sig, vol_id, vol_label, _fs_type) = BPB.unpack_from(sector)

    def bad(field, value, expected):
        raise CardError(f"{where}: {field} is {value}, {expected}")

    if bps not in BYTES_PER_SECTOR:
        bad("bytes per sector (BPB_BytsPerSec, byte 11)", bps,
            "must be 512, 1024, 2048 or 4096")
    if spc not in SECTORS_PER_CLUSTER:
        bad("sectors per cluster (BPB_SecPerClus, byte 13)", spc,
            "must be a power of 2 from 1 to 128")
    if reserved == 0:
        bad("reserved sector count (BPB_RsvdSecCnt, byte 14)", 0, "must be at least 1")
    if nfats == 0:
        bad("number of FATs (BPB_NumFATs, byte 16)", 0, "must be at least 1")
    if root_entries != 0 or fat16 != 0:
        raise CardError(f"{where}: not FAT32: BPB_RootEntCnt is {root_entries} and "
                        f"BPB_FATSz16 is {fat16} (both are 0 on FAT32)")
    if fat32 == 0:
        bad("FAT size (BPB_FATSz32, byte 36)", 0, "must be non-zero on FAT32")
    if tot16 != 0 and tot32 != 0 and tot16 != tot32:
        raise CardError(f"{where}: BPB_TotSec16 ({tot16}) and BPB_TotSec32 ({tot32}) "
                        f"disagree")
    total = tot32 or tot16
    if total == 0:
        bad("total sector count (BPB_TotSec32, byte 32)", 0, "must be non-zero")
    if fs_version != 0:
        bad("FAT32 version (BPB_FSVer, byte 42)", _hex(fs_version), "only version 0.0 exists")
    fsinfo = 0 if fsinfo in NO_SECTOR else fsinfo
    backup = 0 if backup in NO_SECTOR else backup
    for field, value in (("FSInfo sector (BPB_FSInfo, byte 48)", fsinfo),
                         ("backup boot sector (BPB_BkBootSec, byte 50)", backup)):
        if value >= reserved:
            bad(field, value, f"outside the {reserved} reserved sectors")
    bs = BootSector(
        offset=offset, bytes_per_sector=bps, sectors_per_cluster=spc,
        reserved_sectors=reserved, num_fats=nfats, fat_size=fat32, root_cluster=root_cluster,
        total_sectors=total, fsinfo_sector=fsinfo, backup_boot_sector=backup,
        hidden_sectors=hidden, media=media, ext_flags=ext_flags,
        volume_id=vol_id if boot_sig == EXT_BOOT_SIGNATURE else None,
        volume_label=(vol_label.decode(NAME_ENCODING).rstrip()
                      if boot_sig == EXT_BOOT_SIGNATURE else None),
        oem_name=oem.decode(NAME_ENCODING).rstrip())
    if bs.first_data_sector >= total:
        raise CardError(
            f"{where}: the data region would start at sector {bs.first_data_sector} "
            f"({reserved} reserved + {nfats} FATs x {fat32} sectors), beyond the "
            f"{total} sectors of the file system")
    if bs.cluster_count <= FAT16_MAX_CLUSTERS:
        raise CardError(
            f"{where}: only {bs.cluster_count} clusters of {bs.cluster_size} bytes: by the "
            f"FAT specification a volume with fewer than {FAT16_MAX_CLUSTERS + 1} clusters "
            f"is FAT12/16, not FAT32 (use smaller clusters)")
    fat_entries = fat32 * bps // FAT_ENTRY_SIZE
    if fat_entries < bs.max_cluster + 1:
        raise CardError(
            f"{where}: a FAT of {fat32} sectors holds {fat_entries} entries, fewer than the "
            f"{bs.max_cluster + 1} needed for {bs.cluster_count} clusters")
    if not FIRST_CLUSTER <= root_cluster <= bs.max_cluster:
        bad("root cluster (BPB_RootClus, byte 44)", root_cluster,
            f"outside the clusters {FIRST_CLUSTER}..{bs.max_cluster}")
    if ext_flags & EXT_FLAGS_NO_MIRROR and bs.active_fat >= nfats:
        raise CardError(f"{where}: BPB_ExtFlags ({_hex(ext_flags)}) makes FAT "
                        f"#{bs.active_fat + 1} active, but there are only {nfats} FATs")
    return bs


def _is_mbr(sector):
    """The four partition entries, or None when the table is not a plausible MBR."""
    entries = [MBR_ENTRY.unpack_from(sector, MBR_TABLE + i * MBR_ENTRY.size)
               for i in range(MBR_ENTRIES)]
    if any(status not in (0x00, 0x80) for status, *_ in entries):
        return None
    return entries


class Volume:
    """A FAT32 volume in a card image (with an MBR) or a bare partition image.

    ``source`` is a path or a bytes-like object. With ``allow_truncated=True`` an image
    that ends before the file system does is opened anyway (the shortfall is noted in
    :attr:`warnings`), and files whose clusters lie inside the available bytes can be read;
    otherwise such an image raises :class:`TruncatedCardError`.
    """

    def __init__(self, source, *, allow_truncated=False):
        self._image = _Image(source)
        try:
            self._open(allow_truncated)
        except BaseException:
            self._image.close()
            raise

    # -- opening ------------------------------------------------------------------------

    def _open(self, allow_truncated):
        image = self._image
        self.name = image.name
        self.warnings: list[str] = []
        if image.size < MBR_SECTOR:
            raise CardError(f"{image.name}: {image.size} bytes, shorter than one "
                            f"{MBR_SECTOR}-byte sector: not a card or partition image")
        sector0 = image.read(0, MBR_SECTOR, "sector 0")
        self.partition_index = None
        self.partition_type = None
        partition_sectors = None
        if sector0[SIGNATURE_OFFSET:SIGNATURE_OFFSET + 2] != SIGNATURE:
            # Say "bad signature on a good boot sector" rather than "not an image".
            try:
                _parse_boot_sector(image, 0, check_signature=False)
            except CardError:
                raise CardError(
                    f"{image.name}: not a card or partition image: sector 0 has no 55 aa "
                    f"signature at bytes 510-511 (found "
                    f"{sector0[SIGNATURE_OFFSET:SIGNATURE_OFFSET + 2].hex(' ')}), so it is "
                    f"neither an MBR nor a FAT32 boot sector") from None
            raise CardError(
                f"{image.name}: boot sector at {_where(0)}: its BPB is FAT32 but the "
                f"signature at bytes 510-511 is "
                f"{sector0[SIGNATURE_OFFSET:SIGNATURE_OFFSET + 2].hex(' ')}, expected 55 aa")
        try:
            bs = _parse_boot_sector(image, 0)
        except CardError as boot_error:
            bs, partition_sectors = self._from_mbr(sector0, boot_error)
        self.boot = bs
        self.partition_offset = bs.offset
        self._check_extent(partition_sectors, allow_truncated)
        self._check_fsinfo_and_backup()
        self._check_fat_head()

    def _from_mbr(self, sector0, boot_error):
        image = self._image
        entries = _is_mbr(sector0)
        used = [(i, e) for i, e in enumerate(entries or []) if e[2] != 0 and e[5] != 0]
        if not used:
            if _looks_like_boot_sector(sector0) or entries is None:
                raise CardError(f"{image.name}: {boot_error}") from None
            raise CardError(f"{image.name}: the MBR at sector 0 has no partitions, and "
                            f"sector 0 is not a FAT32 boot sector either") from None
        reasons = []
        for index, (_status, _chs0, ptype, _chs1, lba, count) in used:
            label = (f"partition {index + 1} (type {ptype:#04x}, LBA {lba}, {count} "
                     f"sectors)")
            if ptype == PARTITION_GPT:
                reasons.append((label, CardError("a GPT protective entry: GPT disks are "
                                                 "not supported")))
                continue
            if ptype in PARTITION_EXTENDED:
                reasons.append((label, CardError("an extended partition (not followed)")))
                continue
            try:
                bs = _parse_boot_sector(image, lba * MBR_SECTOR)
            except CardError as exc:
                reasons.append((label, exc))
                continue
            if ptype not in PARTITION_FAT32:
                self.warnings.append(f"{label}: the type is not a FAT32 type (0x0B, 0x0C), "
                                     f"but the boot sector is FAT32")
            if bs.hidden_sectors != lba:
                self.warnings.append(f"{label}: the boot sector's hidden sectors "
                                     f"(BPB_HiddSec) is {bs.hidden_sectors}, not the "
                                     f"partition's start LBA {lba}")
            self.partition_index = index
            self.partition_type = ptype
            return bs, count
        if len(reasons) == 1:
            label, exc = reasons[0]
            error = type(exc)(f"{image.name}: {label}: {exc}")
            error.missing = getattr(exc, "missing", None)
            raise error from None
        raise CardError(f"{image.name}: no partition holds a FAT32 file system: "
                        + "; ".join(f"{label}: {exc}" for label, exc in reasons)) from None

    def _check_extent(self, partition_sectors, allow_truncated):
        bs, image = self.boot, self._image
        where = (f"partition {self.partition_index + 1}" if self.partition_index is not None
                 else "the partition image")
        if partition_sectors is not None:
            fs_bytes = bs.total_sectors * bs.bytes_per_sector
            part_bytes = partition_sectors * MBR_SECTOR
            if fs_bytes > part_bytes:
                raise CardError(
                    f"{image.name}: the file system in {where} has {bs.total_sectors} "
                    f"sectors of {bs.bytes_per_sector} bytes ({fs_bytes} bytes, BPB_TotSec32 "
                    f"at {_where(bs.offset + 32)}), more than the partition's "
                    f"{partition_sectors} sectors ({part_bytes} bytes)")
            end, what = bs.offset + part_bytes, f"{where} (MBR entry)"
        else:
            end, what = bs.offset + bs.size, f"the file system (BPB_TotSec32 = {bs.total_sectors})"
        self.truncated = image.size < end
        if self.truncated:
            missing = end - image.size
            message = (f"{image.name}: image is truncated: {what} ends at byte {end}, but the "
                       f"image has only {image.size} bytes ({missing} bytes missing)")
            if not allow_truncated:
                raise TruncatedCardError(message, missing)
            self.warnings.append(message)

    def _check_fsinfo_and_backup(self):
        bs, image = self.boot, self._image
        self.fsinfo = None
        if bs.fsinfo_sector:
            offset = bs.offset + bs.fsinfo_sector * bs.bytes_per_sector
            if image.available(offset, MBR_SECTOR):
                sector = image.read(offset, MBR_SECTOR, "FSInfo sector")
                sigs = [struct.unpack_from("<I", sector, at)[0] == value
                        for at, value in (FSI_LEAD, FSI_STRUC, FSI_TRAIL)]
                if not all(sigs):
                    self.warnings.append(f"FSInfo sector at {_where(offset)}: signatures "
                                         f"missing or wrong; its hints are ignored")
                else:
                    free, nxt = struct.unpack_from("<II", sector, FSI_FREE_COUNT)
                    free = None if free == FSI_UNKNOWN else free
                    nxt = None if nxt == FSI_UNKNOWN else nxt
                    if free is not None and free > bs.cluster_count:
                        self.warnings.append(f"FSInfo free count {free} exceeds the "
                                             f"{bs.cluster_count} clusters")
                    if nxt is not None and not FIRST_CLUSTER <= nxt <= bs.max_cluster:
                        self.warnings.append(f"FSInfo next free cluster {nxt} is outside "
                                             f"{FIRST_CLUSTER}..{bs.max_cluster}")
                    self.fsinfo = FsInfo(free, nxt)
        if bs.backup_boot_sector:
            offset = bs.offset + bs.backup_boot_sector * bs.bytes_per_sector
            if image.available(offset, bs.bytes_per_sector):
                main = image.read(bs.offset, bs.bytes_per_sector, "boot sector")
                backup = image.read(offset, bs.bytes_per_sector, "backup boot sector")
                if main != backup:
                    differ = next(i for i, (a, b) in enumerate(zip(main, backup)) if a != b)
                    self.warnings.append(
                        f"backup boot sector at {_where(offset)} differs from the boot sector "
                        f"(first at byte {differ} of the sector)")

    def _check_fat_head(self):
        bs = self.boot
        self.clean_shutdown = None
        if not self._image.available(self._fat_offset(1), FAT_ENTRY_SIZE):
            return
        fat0 = self._fat_entry(0)
        fat1 = self._image.u32(self._fat_offset(1), "FAT[1]")
        if fat0 & 0xFF != bs.media:
            self.warnings.append(f"FAT[0] is {_hex(fat0, 8)}: its low byte is not the media "
                                 f"byte {_hex(bs.media)}")
        self.clean_shutdown = bool(fat1 & CLEAN_SHUTDOWN)
        if not self.clean_shutdown:
            self.warnings.append("the volume was not cleanly unmounted (FAT[1] bit 27 is 0)")
        if not fat1 & NO_HARD_ERROR:
            self.warnings.append("the volume recorded a disk I/O error (FAT[1] bit 26 is 0)")

    # -- resources ----------------------------------------------------------------------

    def close(self):
        """Release the image (the mmap and the file)."""
        self._image.close()

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()

    def __repr__(self):
        where = (f"partition {self.partition_index + 1}" if self.partition_index is not None
                 else "bare partition")
        return (f"<Volume {self.name} {where} at byte {self.partition_offset}: "
                f"{self.boot.cluster_count} clusters of {self.boot.cluster_size} bytes>")

    # -- layout -------------------------------------------------------------------------

    @property
    def cluster_size(self):
        return self.boot.cluster_size

    @property
    def cluster_count(self):
        return self.boot.cluster_count

    def _fat_offset(self, cluster):
        bs = self.boot
        fat_start = bs.reserved_sectors + bs.active_fat * bs.fat_size
        return bs.offset + fat_start * bs.bytes_per_sector + cluster * FAT_ENTRY_SIZE

    def _fat_entry(self, cluster):
        return self._image.u32(self._fat_offset(cluster),
                               f"FAT #{self.boot.active_fat + 1} entry of cluster {cluster}"
                               ) & FAT_MASK

    def cluster_offset(self, cluster):
        """Byte offset of a data cluster in the image."""
        bs = self.boot
        sector = bs.first_data_sector + (cluster - FIRST_CLUSTER) * bs.sectors_per_cluster
        return bs.offset + sector * bs.bytes_per_sector

    # -- chains -------------------------------------------------------------------------

    def _chain(self, first, what):
        """Every cluster of the chain starting at ``first``, through the end-of-chain mark."""
        bs = self.boot
        if not FIRST_CLUSTER <= first <= bs.max_cluster:
            raise ChainError(f"{what}: first cluster {first} is outside the clusters "
                             f"{FIRST_CLUSTER}..{bs.max_cluster}")
        position = {}
        clusters = []
        cluster = first
        fat = f"FAT #{bs.active_fat + 1}"
        while True:
            position[cluster] = len(clusters)
            clusters.append(cluster)
            try:
                value = self._fat_entry(cluster)
            except TruncatedCardError as exc:
                raise TruncatedCardError(f"{what}: {exc}", exc.missing) from None
            if value >= FAT_EOC:
                return clusters
            entry = f"{fat} entry at {_where(self._fat_offset(cluster))}"
            step = f"cluster {cluster} (number {len(clusters)} of the chain)"
            if value == FAT_FREE:
                raise ChainError(f"{what}: {step} is marked free in the FAT ({entry} is 0): "
                                 f"a free cluster inside the chain")
            if value == FAT_BAD:
                raise ChainError(f"{what}: {step} is marked bad in the FAT ({entry} is "
                                 f"{_hex(FAT_BAD, 8)}): a bad cluster inside the chain")
            if not FIRST_CLUSTER <= value <= bs.max_cluster:
                raise ChainError(f"{what}: {step} links to cluster {value} ({_hex(value, 8)}, "
                                 f"{entry}), outside the clusters "
                                 f"{FIRST_CLUSTER}..{bs.max_cluster}")
            if value in position:
                raise ChainError(f"{what}: {step} links back to cluster {value} (number "
                                 f"{position[value] + 1} of the chain, {entry}): a loop in "
                                 f"the chain")
            cluster = value

    def _warn(self, message):
        if message not in self.warnings:
            self.warnings.append(message)

    def _read_clusters(self, clusters, length, what, *, read=True):
        """``length`` bytes from the start of ``clusters``, one slice per contiguous run
        (``read=False``: only check that they lie in the image; returns None)."""
        size = self.cluster_size
        parts = []
        remaining = length
        i = 0
        while remaining > 0:
            j = i + 1
            while j < len(clusters) and clusters[j] == clusters[j - 1] + 1:
                j += 1
            take = min(remaining, (j - i) * size)
            offset = self.cluster_offset(clusters[i])
            if not self._image.available(offset, take):
                inside = max(0, self._image.size - offset)
                lost = clusters[i + inside // size]
                missing = offset + take - self._image.size
                raise TruncatedCardError(
                    f"{what}: cluster {lost} at {_where(self.cluster_offset(lost))} lies "
                    f"past the end of the image ({self._image.size} bytes, {missing} bytes "
                    f"missing); only the first {length - remaining + min(take, inside)} of "
                    f"{length} bytes are present", missing)
            if read:
                parts.append(self._image.read(offset, take, what))
            remaining -= take
            i = j
        return b"".join(parts) if read else None

    # -- directories --------------------------------------------------------------------

    def _entries(self, cluster, where):
        """The live short-name entries of the directory starting at ``cluster``."""
        clusters = self._chain(cluster, f"directory {where}")
        if len(clusters) * self.cluster_size > MAX_DIR_BYTES:
            raise ChainError(
                f"directory {where}: its chain has {len(clusters)} clusters of "
                f"{self.cluster_size} bytes, more than the {MAX_DIR_BYTES // DIR_ENTRY_SIZE} "
                f"entries a FAT directory may hold")
        data = self._read_clusters(clusters, len(clusters) * self.cluster_size,
                                   f"directory {where}")
        entries = []
        per_cluster = self.cluster_size // DIR_ENTRY_SIZE
        for k in range(len(data) // DIR_ENTRY_SIZE):
            at = k * DIR_ENTRY_SIZE
            raw = data[at:at + DIR_ENTRY_SIZE]
            first = raw[0]
            if first == DIR_END:
                break
            (name, attr, _ntres, _tenth, _ctime, _cdate, _adate, hi, wtime, wdate, lo,
             size) = DIR_ENTRY.unpack(raw)
            if first == DIR_DELETED or attr & ATTR_LONG_NAME_MASK == Attr.LONG_NAME:
                continue
            if attr & Attr.VOLUME_ID:
                continue
            if name[:1] == b".":            # "." and ".." of a subdirectory
                continue
            offset = (self.cluster_offset(clusters[k // per_cluster])
                      + (k % per_cluster) * DIR_ENTRY_SIZE)
            if first == DIR_KANJI_E5:
                name = b"\xe5" + name[1:]
            base = name[:8].decode(NAME_ENCODING).rstrip(" ")
            ext = name[8:].decode(NAME_ENCODING).rstrip(" ")
            if any(c < 0x20 for c in name[1:]) or not base:
                self._warn(f"directory {where}: entry at {_where(offset)} has an invalid "
                           f"8.3 name {name!r}")
            entries.append(DirEntry(
                name=f"{base}.{ext}" if ext else base, size=size,
                first_cluster=(hi << 16) | lo, attributes=Attr(attr & 0x3F),
                mtime=_fat_datetime(wdate, wtime), is_dir=bool(attr & Attr.DIRECTORY),
                offset=offset))
        return entries

    def _resolve(self, path):
        """The entry ``path`` names, or None for the root directory."""
        parts = [p for p in str(path).replace("\\", "/").split("/") if p]
        entry = None
        cluster, where = self.boot.root_cluster, "/"
        for depth, part in enumerate(parts):
            if entry is not None and not entry.is_dir:
                raise CardFileNotFoundError(f"{where} is a file, not a directory "
                                            f"(looking for {path!r})")
            wanted = part.upper()
            found = [e for e in self._entries(cluster, where) if e.name.upper() == wanted]
            if not found:
                raise CardFileNotFoundError(f"{part!r} not found in directory {where} "
                                            f"(looking for {path!r})")
            entry = found[0]
            where = "/" + "/".join(parts[:depth + 1])
            if entry.is_dir:
                if entry.first_cluster == 0:
                    raise ChainError(f"directory {where} (entry at {_where(entry.offset)}) "
                                     f"has first cluster 0")
                cluster = entry.first_cluster
        return entry

    def listdir(self, path="/"):
        """The entries of a directory, in directory order: no deleted entries, volume
        labels, long-name entries, "." or ".."."""
        entry = self._resolve(path)
        if entry is None:
            return self._entries(self.boot.root_cluster, "/")
        if not entry.is_dir:
            raise CardError(f"{path!r} is a file, not a directory")
        return self._entries(entry.first_cluster, "/" + str(path).strip("/"))

    def stat(self, path):
        """The directory entry of ``path``."""
        entry = self._resolve(path)
        if entry is None:
            raise CardError("the root directory has no directory entry")
        return entry

    def clusters(self, path):
        """The cluster chain of a file or directory, as stored in the FAT."""
        entry = self.stat(path)
        if entry.first_cluster == 0:
            return []
        return self._chain(entry.first_cluster, self._describe(path, entry))

    def _describe(self, path, entry):
        kind = "directory" if entry.is_dir else "file"
        return f"{kind} {path!r} (entry at {_where(entry.offset)})"

    # -- files --------------------------------------------------------------------------

    def read(self, path):
        """The contents of a file, following its cluster chain."""
        return self._file(path, read=True)

    def check(self, path):
        """Raise what :meth:`read` would raise for ``path`` (not a file, a broken or short
        chain, clusters past the end of the image), without reading the file's data."""
        self._file(path, read=False)

    def walk(self, path="/"):
        """``(path, entry)`` of everything under the directory ``path``, depth first in
        directory order; ``path`` is relative to the root, ``/``-separated (``DATA/A.BIN``).
        A directory that links back to one above it is a :class:`ChainError`."""
        top = self._resolve(path)
        if top is not None and not top.is_dir:
            raise CardError(f"{path!r} is a file, not a directory")
        prefix = "/".join(p for p in str(path).replace("\\", "/").split("/") if p)
        start = self.boot.root_cluster if top is None else top.first_cluster
        yield from self._walk(start, prefix, {start})

    def _walk(self, cluster, prefix, above):
        if len(above) > MAX_DEPTH:
            raise CardError(f"directory /{prefix}: more than {MAX_DEPTH} levels deep (a path "
                            f"on FAT is at most {MAX_PATH} characters)")
        for entry in self._entries(cluster, "/" + prefix):
            name = f"{prefix}/{entry.name}" if prefix else entry.name
            yield name, entry
            if entry.is_dir:
                if entry.first_cluster == 0 or entry.first_cluster in above:
                    raise ChainError(
                        f"directory /{name} (entry at {_where(entry.offset)}) starts at "
                        f"cluster {entry.first_cluster}, "
                        + ("no chain" if entry.first_cluster == 0 else
                           "a directory above it: a loop in the tree"))
                yield from self._walk(entry.first_cluster, name, above | {entry.first_cluster})

    def _file(self, path, *, read):
        entry = self._resolve(path)
        if entry is None or entry.is_dir:
            raise CardError(f"{path!r} is a directory, not a file")
        what = self._describe(path, entry)
        size, csize = entry.size, self.cluster_size
        capacity = self.cluster_count * csize
        if size > capacity:
            raise CardError(f"{what}: size {size} bytes is larger than the whole data region "
                            f"({self.cluster_count} clusters of {csize} bytes = {capacity})")
        needed = -(-size // csize)
        if entry.first_cluster == 0:
            if size:
                raise ChainError(f"{what}: size {size} bytes but first cluster 0 (no chain): "
                                 f"the chain is shorter than the directory size")
            return b"" if read else None
        chain = self._chain(entry.first_cluster, what)
        if len(chain) < needed:
            raise ChainError(
                f"{what}: size {size} bytes needs {needed} clusters of {csize} bytes, but "
                f"the chain ends after {len(chain)} (at cluster {chain[-1]}): the chain is "
                f"shorter than the directory size")
        if len(chain) > needed:
            self._warn(f"{what}: the chain has {len(chain)} clusters, {len(chain) - needed} "
                       f"more than the {size} bytes need (lost space, not an error)")
        return self._read_clusters(chain, size, what, read=read)

    def log_files(self):
        """Names of the ``LOG*.TXT`` files of the root directory, sorted."""
        return sorted(e.name for e in self.listdir("/")
                      if not e.is_dir and fnmatch.fnmatchcase(e.name.upper(), "LOG*.TXT"))


def _fat_datetime(date, time):
    # Ref: fatgen103 "Date and Time Formats".
    if date == 0:
        return None
    try:
        return datetime(1980 + (date >> 9), (date >> 5) & 0x0F, date & 0x1F,
                        time >> 11, (time >> 5) & 0x3F, (time & 0x1F) * 2)
    except ValueError:
        return None


def open_card(source, *, allow_truncated=False):
    """Open a card image (MBR + FAT32 partition) or a bare FAT32 partition image."""
    return Volume(source, allow_truncated=allow_truncated)


#: How much of a file decides whether it is a text log, and how much must be text.
_TEXT_PROBE = 65536
_TEXT_FRACTION = 0.95
_TEXT_BYTES = frozenset(range(0x20, 0x7F)) | {0x09, 0x0A, 0x0D}


#: Erased flash reads as 0xFF: a log copied from a flash chip or a card's raw blocks may be
#: padded with it (before the first line, after the last, between writes). Such bytes are
#: neither text nor an image's tables: they are left out of the share of text.
ERASED = 0xFF


def _looks_like_text_log(head):
    # A few NUL bytes (a serial glitch the logger kept, a write cut by power loss) do not
    # make a log an image: only the share of text does. An image without the boot
    # signature is mostly zeros and binary tables, far below the share. Erased-flash
    # padding (0xFF) counts for neither.
    head = head.replace(bytes([ERASED]), b"")
    if not head or b"$" not in head:
        return False
    text = len(head) - len(head.translate(None, bytes(_TEXT_BYTES)))
    return text >= _TEXT_FRACTION * len(head)


def read_logs(source, *, allow_truncated=False):
    """Every ``LOG*.TXT`` of a card or partition image as ``[(name, bytes)]``, sorted by
    name; a plain text log (``$`` lines, not an image) as ``[(basename, bytes)]``.

    With ``allow_truncated=True`` a truncated image gives the logs that lie wholly inside
    the available bytes; each one left out is reported with a :class:`CardWarning`.
    """
    if not isinstance(source, (bytes, bytearray, memoryview)):
        try:
            path = Path(os.fspath(source))
            with open(path, "rb") as f:
                head = f.read(_TEXT_PROBE)
        except TypeError:
            raise CardError(f"expected a path or bytes, not {type(source).__name__}") from None
        except OSError as exc:
            raise CardError(f"cannot open {source}: {exc.strerror or exc}") from None
        name = path.name
    else:
        head = bytes(source[:_TEXT_PROBE])
        name = "<bytes>"
    if not head:
        raise CardError(f"{name}: the file is empty: neither a card image nor a text log")
    has_signature = head[SIGNATURE_OFFSET:SIGNATURE_OFFSET + 2] == SIGNATURE
    if not has_signature and _looks_like_text_log(head):
        if isinstance(source, (bytes, bytearray, memoryview)):
            return [(name, bytes(source))]
        return [(name, path.read_bytes())]
    with open_card(source, allow_truncated=allow_truncated) as volume:
        logs = []
        for log in volume.log_files():
            try:
                logs.append((log, volume.read(log)))
            except TruncatedCardError as exc:
                if not allow_truncated:
                    raise
                _warnings.warn(f"{log} left out: {exc}", CardWarning, stacklevel=2)
        return logs
