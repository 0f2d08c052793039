"""FAT32 writer for the logger: a host-side formatter, and a mount / create / append / sync
driver over any 512-byte block device.

Written from the FAT specification and the SD Association's file system specification (see
:mod:`maglog.hw.arch.fat32`), independently of :mod:`maglog.calib.card`, which reads what
this module writes.

Decisions beyond the specification's letter:

* New directory entries always go after the last used entry of the root directory (at its
  end marker); deleted (0xE5) slots are never reused, so no long-file-name chain can be
  broken. A full directory grows by one zeroed cluster.
* FSInfo is trusted when it is plausible (free count at most the cluster count, hint inside
  the data clusters). An unknown or implausible free count is recounted from the FAT and an
  implausible hint is replaced by cluster 2, each with a line in :attr:`Volume.notes`. An
  FSInfo sector with bad signatures is noted, the free count recounted, and the sector is
  never written: what was not understood is not overwritten.
* A volume whose clean-shutdown bit is clear mounts (with a note) and is repaired as
  ``fsck.fat`` would (:meth:`Volume.repair`: chains trimmed to their files' sizes, lost
  clusters freed, FAT 2 made equal to FAT 1, the free count recounted), then marked clean.
  Damage no power cut causes is not guessed at: the volume mounts, the logger keeps
  recording, and it is never marked clean (:attr:`Volume.damage`).
* Only the primary FSInfo is kept up to date; the backup (sector 7) is the format-time copy.
* At most ``fat_cache_sectors`` FAT sectors stay in memory (least recently used evicted
  first), so a long recording does not accumulate the FAT: a sector with changes not yet on
  the card is never evicted before the next sync writes it.
* Data can reach a file two ways: :meth:`LogFile.append` (the writer stores the bytes), or
  the ring path for data someone else writes (the logger's DMA): :meth:`LogFile.extents`
  allocates the clusters and says where the sectors go, the caller writes them,
  :meth:`LogFile.grow` then commits the new size in the same safe order as a sync.
* Sync writes data sectors, then the changed FAT sectors (all of FAT 1, then FAT 2), then the
  directory entry, then FSInfo. Within each FAT the sector that links a chain already on the
  card to the new clusters goes last, so a cut at any point leaves at worst lost clusters,
  a chain longer than the file, FATs that differ, or a stale FSInfo (the tests cut after
  every block and check with ``fsck.fat``).
"""

import abc
import collections
import datetime as _dt
import os
import re
from dataclasses import dataclass

from ..hw.arch import fat32 as arch


__all__ = ["FatError", "FatFullError", "FatNoNumberError", "BlockDevice", "ImageFile",
           "FormatPlan", "plan_format", "format_image", "Volume", "LogFile", "Extent", "Extents",
           "FAT_CACHE_SECTORS"]

SECTOR = arch.SECTOR_BYTES
_LOG_NAME = re.compile(rb"LOG(\d{5})TXT")
LOG_MAX_NUMBER = 99999
#: FAT sectors a mounted volume keeps in memory by default (least recently used go first;
#: sectors with changes not yet on the card stay until the next sync writes them).
FAT_CACHE_SECTORS = 8


class FatError(Exception):
    """The card is not a sane FAT32 volume, or an operation on it failed."""


class FatNoNumberError(FatError):
    """Every LOG file number is taken (``LOG99999.TXT`` exists)."""


class FatFullError(FatError):
    """No free cluster (or directory entry) is left; ``written`` bytes were taken first."""

    def __init__(self, message, written=0):
        super().__init__(message)
        self.written = written


# -- Block devices ---------------------------------------------------------------------------

class BlockDevice(abc.ABC):
    """512-byte blocks addressed by LBA, as an SDHC card is."""

    @abc.abstractmethod
    async def read_block(self, lba):
        """The 512 bytes of block ``lba``."""

    @abc.abstractmethod
    async def write_block(self, lba, data):
        """Store 512 bytes at block ``lba``."""


class ImageFile(BlockDevice):
    """A raw card image on the host as a block device (for the formatter's tests and the
    CLI). Blocks beyond the end of the file read as zeros. Writes are unbuffered: each block
    is in the file when :meth:`write_block` returns, as on a card."""

    def __init__(self, path):
        self.path = os.fspath(path)
        self._file = open(self.path, "r+b", buffering=0)

    def close(self):
        self._file.close()

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()

    @property
    def blocks(self):
        return os.fstat(self._file.fileno()).st_size // SECTOR

    async def read_block(self, lba):
        self._file.seek(lba * SECTOR)
        return self._file.read(SECTOR).ljust(SECTOR, b"\0")

    async def write_block(self, lba, data):
        if len(data) != SECTOR:
            raise ValueError(f"A block is {SECTOR} bytes, not {len(data)}")
        self._file.seek(lba * SECTOR)
        self._file.write(data)


# -- Little helpers --------------------------------------------------------------------------

def _u16(buf, offset):
    return int.from_bytes(buf[offset:offset + 2], "little")


def _u32(buf, offset):
    return int.from_bytes(buf[offset:offset + 4], "little")


def _put16(buf, offset, value):
    buf[offset:offset + 2] = value.to_bytes(2, "little")


def _put32(buf, offset, value):
    buf[offset:offset + 4] = value.to_bytes(4, "little")


def _ceil_div(a, b):
    return -(-a // b)


def _round_up(value, unit):
    return _ceil_div(value, unit) * unit


def fat_date_time(timestamp):
    """``(date, time)`` FAT fields of a :class:`datetime.datetime` or of a ``(date, time)``
    pair of :class:`datetime.date` and :class:`datetime.time`."""
    if isinstance(timestamp, _dt.datetime):
        date, time = timestamp.date(), timestamp.time()
    else:
        date, time = timestamp
    if not arch.FAT_EPOCH_YEAR <= date.year <= arch.FAT_LAST_YEAR:
        raise FatError(f"Year {date.year} cannot be stored in a FAT date "
                       f"({arch.FAT_EPOCH_YEAR}..{arch.FAT_LAST_YEAR})")
    fat_date = ((date.year - arch.FAT_EPOCH_YEAR) << 9) | (date.month << 5) | date.day
    fat_time = (time.hour << 11) | (time.minute << 5) | (time.second // 2)
    return fat_date, fat_time


FAT_EPOCH = _dt.datetime(arch.FAT_EPOCH_YEAR, 1, 1)


# -- Formatter -------------------------------------------------------------------------------

class FormatPlan:
    """Where everything goes on a card of ``total_sectors``: partition, reserved region,
    FATs, data region (all in sectors)."""

    def __init__(self, total_sectors, sectors_per_cluster, boundary):
        self.total_sectors = total_sectors
        self.sectors_per_cluster = sectors_per_cluster
        self.boundary = boundary
        self.partition_start = boundary
        self.partition_sectors = total_sectors - boundary
        self.fat_sectors, self.reserved_sectors = self._layout()
        data_sectors = self.partition_sectors - self.data_offset
        self.cluster_count = data_sectors // sectors_per_cluster

    @property
    def data_offset(self):
        """First data sector, counted from the partition start."""
        return self.reserved_sectors + arch.NUM_FATS * self.fat_sectors

    def _layout(self):
        # SDFS's FAT32 layout puts the first data sector on a boundary unit; the reserved
        # region absorbs the difference. The FAT size depends on the cluster count and that
        # on the FAT size, so iterate until the FAT is just large enough.
        fat_sectors = 1
        while True:
            reserved = self._reserved_for(fat_sectors)
            data = self.partition_sectors - reserved - arch.NUM_FATS * fat_sectors
            clusters = max(data // self.sectors_per_cluster, 0)
            needed = _ceil_div((clusters + arch.FIRST_DATA_CLUSTER) * arch.FAT_ENTRY_BYTES,
                               SECTOR)
            if needed <= fat_sectors:
                return fat_sectors, reserved
            fat_sectors = needed

    def _reserved_for(self, fat_sectors):
        fats_end = (self.partition_start + arch.MIN_RESERVED_SECTORS
                    + arch.NUM_FATS * fat_sectors)
        data_start = _round_up(fats_end, self.boundary)
        return data_start - self.partition_start - arch.NUM_FATS * fat_sectors


def plan_format(size_bytes, cluster_bytes=None):
    """The :class:`FormatPlan` for a card of ``size_bytes``: the SDA parameters for an SDHC
    capacity, or FAT32 with an explicit ``cluster_bytes`` when that gives a legal FAT32."""
    if size_bytes <= 0 or size_bytes % SECTOR:
        raise FatError(f"Card size must be a positive multiple of {SECTOR} bytes, "
                       f"not {size_bytes!r}")
    sdhc = arch.SDHC_MIN_BYTES <= size_bytes <= arch.SDHC_MAX_BYTES
    if cluster_bytes is None:
        if not sdhc:
            raise FatError(
                f"A card of {size_bytes} bytes is not SDHC (above 2 GiB up to 32 GiB): the "
                f"SD Association formats it as FAT12/16 or exFAT; give a cluster size to "
                f"format it as FAT32 anyway")
        cluster_bytes = arch.SDHC_SECTORS_PER_CLUSTER * SECTOR
    sectors_per_cluster, rest = divmod(cluster_bytes, SECTOR)
    if (rest or not 1 <= sectors_per_cluster <= arch.MAX_SECTORS_PER_CLUSTER
            or sectors_per_cluster & (sectors_per_cluster - 1)
            or cluster_bytes > arch.MAX_CLUSTER_BYTES):
        raise FatError(f"Cluster size must be a power of two from {SECTOR} to "
                       f"{arch.MAX_CLUSTER_BYTES} bytes, not {cluster_bytes!r}")
    total = size_bytes // SECTOR
    if total <= 2 * arch.SDHC_BOUNDARY_SECTORS:
        raise FatError(f"A card of {size_bytes} bytes is too small for FAT32")
    plan = FormatPlan(total, sectors_per_cluster, arch.SDHC_BOUNDARY_SECTORS)
    if not arch.FAT32_MIN_CLUSTERS <= plan.cluster_count <= arch.FAT32_MAX_CLUSTER - 1:
        raise FatError(f"{size_bytes} bytes with {cluster_bytes}-byte clusters gives "
                       f"{plan.cluster_count} clusters; FAT32 needs at least "
                       f"{arch.FAT32_MIN_CLUSTERS}")
    return plan


def _chs(lba):
    cylinder, rest = divmod(lba, arch.CHS_HEADS * arch.CHS_SECTORS)
    head, sector = divmod(rest, arch.CHS_SECTORS)
    if cylinder > arch.CHS_MAX_CYLINDER:
        cylinder, head, sector = arch.CHS_MAX_CYLINDER, arch.CHS_HEADS - 1, arch.CHS_SECTORS - 1
    return bytes([head, ((cylinder >> 2) & 0xC0) | (sector + 1), cylinder & 0xFF])


def _mbr(plan, disk_id):
    mbr = bytearray(SECTOR)
    _put32(mbr, arch.MBR_DISK_ID, disk_id)
    entry = arch.MBR_PARTITION_TABLE
    mbr[entry + arch.PART_STATUS] = 0x00
    mbr[entry + arch.PART_CHS_FIRST:entry + arch.PART_CHS_FIRST + 3] = _chs(plan.partition_start)
    mbr[entry + arch.PART_TYPE] = arch.PartitionType.FAT32_LBA
    last = plan.partition_start + plan.partition_sectors - 1
    mbr[entry + arch.PART_CHS_LAST:entry + arch.PART_CHS_LAST + 3] = _chs(last)
    _put32(mbr, entry + arch.PART_LBA_FIRST, plan.partition_start)
    _put32(mbr, entry + arch.PART_SECTORS, plan.partition_sectors)
    mbr[arch.BOOT_SIGNATURE_OFFSET:] = arch.BOOT_SIGNATURE
    return bytes(mbr)


#: Characters a volume label may not hold besides controls (FAT specification §6.1).
_LABEL_FORBIDDEN = '*?.,;:/\\|+=<>[]"'


def _label_bytes(label):
    """The 11 label bytes of ``label``: upper-cased, padded with spaces. A FAT label is 11
    bytes of the OEM code page, which the card does not record: only printable ASCII is
    accepted, so that every computer shows the same label."""
    if label is None:
        return arch.NO_NAME_LABEL
    upper = label.upper()
    if (not upper or len(upper) > arch.DIR_NAME_BYTES
            or any(not " " <= c <= "~" or c in _LABEL_FORBIDDEN for c in upper)):
        raise FatError(f"Volume label must be 1 to {arch.DIR_NAME_BYTES} printable ASCII "
                       f"characters (letters A-Z, digits, space and punctuation other than "
                       f"{_LABEL_FORBIDDEN}), not {label!r}")
    return upper.encode("ascii").ljust(arch.DIR_NAME_BYTES)


def _boot_sector(plan, label, volume_id):
    bs = bytearray(SECTOR)
    bs[0:3] = bytes([arch.JMP_SHORT, 0x58, arch.NOP])
    bs[arch.BS_OEM_NAME:arch.BS_OEM_NAME + 8] = b"MAGLOG  "
    _put16(bs, arch.BPB_BYTS_PER_SEC, SECTOR)
    bs[arch.BPB_SEC_PER_CLUS] = plan.sectors_per_cluster
    _put16(bs, arch.BPB_RSVD_SEC_CNT, plan.reserved_sectors)
    bs[arch.BPB_NUM_FATS] = arch.NUM_FATS
    bs[arch.BPB_MEDIA] = arch.MEDIA_FIXED
    _put16(bs, arch.BPB_SEC_PER_TRK, arch.CHS_SECTORS)
    _put16(bs, arch.BPB_NUM_HEADS, arch.CHS_HEADS)
    _put32(bs, arch.BPB_HIDD_SEC, plan.partition_start)
    _put32(bs, arch.BPB_TOT_SEC32, plan.partition_sectors)
    _put32(bs, arch.BPB_FAT_SZ32, plan.fat_sectors)
    _put32(bs, arch.BPB_ROOT_CLUS, arch.ROOT_CLUSTER)
    _put16(bs, arch.BPB_FS_INFO, arch.FSINFO_SECTOR)
    _put16(bs, arch.BPB_BK_BOOT_SEC, arch.BACKUP_BOOT_SECTOR)
    bs[arch.BS_DRV_NUM] = arch.DRIVE_NUMBER_HARD_DISK
    bs[arch.BS_BOOT_SIG] = arch.EXTENDED_BOOT_SIGNATURE
    _put32(bs, arch.BS_VOL_ID, volume_id)
    bs[arch.BS_VOL_LAB:arch.BS_VOL_LAB + 11] = label
    bs[arch.BS_FIL_SYS_TYPE:arch.BS_FIL_SYS_TYPE + 8] = arch.FIL_SYS_TYPE_FAT32
    bs[arch.BOOT_SIGNATURE_OFFSET:] = arch.BOOT_SIGNATURE
    return bytes(bs)


def _fsinfo_sector(free_count, next_free):
    fsi = bytearray(SECTOR)
    _put32(fsi, arch.FSI_LEAD_SIG_OFFSET, arch.FSI_LEAD_SIG)
    _put32(fsi, arch.FSI_STRUC_SIG_OFFSET, arch.FSI_STRUC_SIG)
    _put32(fsi, arch.FSI_FREE_COUNT, free_count)
    _put32(fsi, arch.FSI_NXT_FREE, next_free)
    _put32(fsi, arch.FSI_TRAIL_SIG_OFFSET, arch.FSI_TRAIL_SIG)
    return bytes(fsi)


def _first_fat_sector(media):
    fat = bytearray(SECTOR)
    _put32(fat, 0, arch.FAT0_HIGH | media)
    _put32(fat, 4, arch.FAT_EOC)        # clean-shutdown and no-hard-error bits set
    _put32(fat, arch.ROOT_CLUSTER * arch.FAT_ENTRY_BYTES, arch.FAT_EOC)
    return bytes(fat)


def _root_cluster(plan, label):
    root = bytearray(plan.sectors_per_cluster * SECTOR)
    if label != arch.NO_NAME_LABEL:
        root[arch.DIR_NAME:arch.DIR_NAME + 11] = label
        root[arch.DIR_ATTR] = arch.Attr.VOLUME_ID
    return bytes(root)


def format_image(path, size_bytes, *, cluster_bytes=None, label="MAGLOG", volume_id=None):
    """Write a blank, sparse card image of ``size_bytes`` at ``path``: an MBR with one FAT32
    partition (type 0x0C) laid out as the SD Association formats cards, boot sector and
    FSInfo with their backups, two FATs and an empty root directory. Returns the
    :class:`FormatPlan`. ``label=None`` leaves the volume unlabelled ("NO NAME")."""
    plan = plan_format(size_bytes, cluster_bytes)
    label = _label_bytes(label)
    volume_id = (int.from_bytes(os.urandom(4), "little") if volume_id is None
                 else volume_id & 0xFFFFFFFF)
    boot = _boot_sector(plan, label, volume_id)
    fsinfo = _fsinfo_sector(plan.cluster_count - 1, arch.ROOT_CLUSTER + 1)
    part = plan.partition_start
    writes = [(0, _mbr(plan, volume_id)),
              (part, boot), (part + arch.FSINFO_SECTOR, fsinfo),
              (part + arch.BACKUP_BOOT_SECTOR, boot),
              (part + arch.BACKUP_FSINFO_SECTOR, fsinfo)]
    for fat in range(arch.NUM_FATS):
        fat_start = part + plan.reserved_sectors + fat * plan.fat_sectors
        writes.append((fat_start, _first_fat_sector(arch.MEDIA_FIXED)))
    writes.append((part + plan.data_offset, _root_cluster(plan, label)))
    with open(path, "wb") as f:
        f.truncate(size_bytes)
        for lba, data in writes:
            f.seek(lba * SECTOR)
            f.write(data)
    return plan


# -- Mount -----------------------------------------------------------------------------------

class _Layout:
    """The geometry a mounted volume's BPB gives, in absolute sectors."""

    def __init__(self, partition_start, bs):
        self.partition_start = partition_start
        self.sectors_per_cluster = bs[arch.BPB_SEC_PER_CLUS]
        self.reserved_sectors = _u16(bs, arch.BPB_RSVD_SEC_CNT)
        self.num_fats = bs[arch.BPB_NUM_FATS]
        self.total_sectors = _u32(bs, arch.BPB_TOT_SEC32)
        self.fat_sectors = _u32(bs, arch.BPB_FAT_SZ32)
        self.root_cluster = _u32(bs, arch.BPB_ROOT_CLUS)
        self.fsinfo_sector = _u16(bs, arch.BPB_FS_INFO)
        self.backup_boot_sector = _u16(bs, arch.BPB_BK_BOOT_SEC)
        self.fat_start = partition_start + self.reserved_sectors
        data_offset = self.reserved_sectors + self.num_fats * self.fat_sectors
        self.data_start = partition_start + data_offset
        self.cluster_count = max(self.total_sectors - data_offset, 0) // max(
            self.sectors_per_cluster, 1)
        self.max_cluster = self.cluster_count + 1

    @property
    def cluster_bytes(self):
        return self.sectors_per_cluster * SECTOR

    def cluster_lba(self, cluster):
        return self.data_start + (cluster - arch.FIRST_DATA_CLUSTER) * self.sectors_per_cluster


def _find_partition(mbr):
    """``(index, type, first LBA, sectors)`` of the first used MBR entry."""
    if mbr[arch.BOOT_SIGNATURE_OFFSET:] != arch.BOOT_SIGNATURE:
        raise FatError(f"sector 0: no MBR: bytes 510-511 are {mbr[510:512].hex()}, not 55aa")
    if mbr[arch.BS_OEM_NAME:arch.BS_OEM_NAME + 8] == arch.EXFAT_OEM_NAME:
        raise FatError("sector 0: an exFAT boot sector without a partition table; "
                       "exFAT is not supported, only FAT32 in an MBR partition")
    if (mbr[arch.BS_FIL_SYS_TYPE:arch.BS_FIL_SYS_TYPE + 8] == arch.FIL_SYS_TYPE_FAT32
            or mbr[arch.BS16_FIL_SYS_TYPE:arch.BS16_FIL_SYS_TYPE + 3] == b"FAT"):
        raise FatError("sector 0: a FAT boot sector without a partition table; only a card "
                       "with an MBR partition (as SD cards are formatted) is supported")
    for index in range(arch.MBR_PARTITIONS):
        entry = arch.MBR_PARTITION_TABLE + index * arch.MBR_PARTITION_ENTRY_BYTES
        kind = mbr[entry + arch.PART_TYPE]
        if kind == arch.PartitionType.EMPTY:
            continue
        status = mbr[entry + arch.PART_STATUS]
        if status not in (0x00, 0x80):
            raise FatError(f"sector 0: no MBR: partition entry {index + 1} has status "
                           f"0x{status:02x} (a boot sector without a partition table?)")
        return (index, kind, _u32(mbr, entry + arch.PART_LBA_FIRST),
                _u32(mbr, entry + arch.PART_SECTORS))
    raise FatError("sector 0: the MBR has no partition")


def _check_partition_type(index, kind, boot):
    where = f"partition {index + 1}"
    if boot[arch.BS_OEM_NAME:arch.BS_OEM_NAME + 8] == arch.EXFAT_OEM_NAME:
        raise FatError(f"{where}: the boot sector is exFAT (OEM name 'EXFAT'); "
                       f"only FAT32 is supported")
    if kind not in arch.FAT32_PARTITION_TYPES:
        name = (arch.PartitionType(kind).name if kind in arch.PartitionType._value2member_map_
                else "unknown")
        raise FatError(f"{where}: type 0x{kind:02x} ({name}) is not FAT32 (0x0b or 0x0c)")


def _check_bpb(where, bs, partition_sectors):
    """Raise :class:`FatError` unless ``bs`` is a sane FAT32 boot sector."""
    def bad(what):
        raise FatError(f"{where}: {what}")

    if bs[arch.BOOT_SIGNATURE_OFFSET:] != arch.BOOT_SIGNATURE:
        bad(f"boot sector signature is {bs[510:512].hex()}, not 55aa")
    if not (bs[0] == arch.JMP_SHORT and bs[2] == arch.NOP or bs[0] == arch.JMP_NEAR):
        bad(f"no boot sector: jump instruction is {bs[0:3].hex()}")
    if _u16(bs, arch.BPB_BYTS_PER_SEC) != SECTOR:
        bad(f"BPB_BytsPerSec is {_u16(bs, arch.BPB_BYTS_PER_SEC)}, only {SECTOR} is supported")
    spc = bs[arch.BPB_SEC_PER_CLUS]
    if spc == 0 or spc & (spc - 1):
        bad(f"BPB_SecPerClus is {spc}, not a power of two")
    if _u16(bs, arch.BPB_ROOT_ENT_CNT) or _u16(bs, arch.BPB_FAT_SZ16):
        bad(f"FAT12/FAT16, not FAT32: BPB_RootEntCnt is {_u16(bs, arch.BPB_ROOT_ENT_CNT)} "
            f"and BPB_FATSz16 is {_u16(bs, arch.BPB_FAT_SZ16)}")
    if _u16(bs, arch.BPB_TOT_SEC16):
        bad(f"BPB_TotSec16 is {_u16(bs, arch.BPB_TOT_SEC16)}, not 0 as on FAT32")
    if bs[arch.BPB_NUM_FATS] not in (1, 2):
        bad(f"BPB_NumFATs is {bs[arch.BPB_NUM_FATS]}, not 1 or 2")
    if bs[arch.BPB_MEDIA] not in arch.MEDIA_VALUES:
        bad(f"BPB_Media is 0x{bs[arch.BPB_MEDIA]:02x}, not a media descriptor")
    if _u16(bs, arch.BPB_FS_VER):
        bad(f"BPB_FSVer is 0x{_u16(bs, arch.BPB_FS_VER):04x}, only version 0:0 is known")
    if _u16(bs, arch.BPB_EXT_FLAGS) & arch.EXT_FLAGS_NO_MIRROR:
        bad("BPB_ExtFlags turns FAT mirroring off; only mirrored FATs are supported")
    layout = _Layout(0, bs)
    if not 0 < layout.total_sectors <= partition_sectors:
        bad(f"BPB_TotSec32 is {layout.total_sectors}, outside the partition's "
            f"{partition_sectors} sectors")
    reserved = layout.reserved_sectors
    for field, value in (("BPB_FSInfo", layout.fsinfo_sector),
                         ("BPB_BkBootSec", layout.backup_boot_sector)):
        if not 0 < value < reserved:
            bad(f"{field} is {value}, outside the {reserved} reserved sectors")
    if layout.cluster_count < arch.FAT32_MIN_CLUSTERS:
        bad(f"{layout.cluster_count} clusters is FAT12/FAT16, not FAT32 (which needs at "
            f"least {arch.FAT32_MIN_CLUSTERS})")
    needed = _ceil_div((layout.max_cluster + 1) * arch.FAT_ENTRY_BYTES, SECTOR)
    if layout.fat_sectors < needed:
        bad(f"BPB_FATSz32 is {layout.fat_sectors} sectors, the {layout.cluster_count} "
            f"clusters need {needed}")
    if not arch.FIRST_DATA_CLUSTER <= layout.root_cluster <= layout.max_cluster:
        bad(f"BPB_RootClus is {layout.root_cluster}, outside clusters 2..{layout.max_cluster}")


class Volume:
    """A mounted FAT32 volume on a :class:`BlockDevice`; use :meth:`mount`."""

    def __init__(self, device, layout, notes, *, fat_cache_sectors=FAT_CACHE_SECTORS):
        if (not isinstance(fat_cache_sectors, int) or isinstance(fat_cache_sectors, bool)
                or fat_cache_sectors < 1):
            raise ValueError(f"FAT cache size must be a positive number of sectors, not "
                             f"{fat_cache_sectors!r}")
        self.device = device
        self.layout = layout
        #: What mount found odd but not fatal (dirty bit, implausible FSInfo, ...).
        self.notes = notes
        self.free_count = None
        self.next_free = None
        self.fsinfo_valid = False
        self.fat_cache_sectors = fat_cache_sectors
        #: The clean-shutdown bit was clear at mount: the volume was not closed cleanly.
        self.was_dirty = False
        #: FAT sectors read from the card so far (a measure of the cache's work).
        self.fat_reads = 0
        self._fsinfo = None
        self._fsinfo_on_card = None             # the FSInfo sector as the card holds it
        # FAT sector index -> bytearray (FAT 1's view), least recently used first.
        self._fat = collections.OrderedDict()
        self._fat_dirty = set()
        self._fresh = set()             # clusters allocated since the last FAT flush
        self._anchors = set()           # FAT sectors linking synced chains to fresh clusters
        self._dirty_marked = False
        self._files = []
        #: Damage a dirty volume's repair found and did not repair (see :meth:`repair`):
        #: while it is not empty the volume is never marked clean.
        self.damage = []
        #: What the repair did: ``trimmed`` chains, ``freed`` lost clusters, ``fat_copied``
        #: FAT sectors made equal to FAT 1's, ``free_was``/``free_count`` (None: no repair).
        self.repaired = None

    # -- mounting ---------------------------------------------------------------------------

    @classmethod
    async def mount(cls, device, *, fat_cache_sectors=FAT_CACHE_SECTORS, repair=True):
        """Find the FAT32 partition, check it, and return the mounted :class:`Volume`
        (keeping at most ``fat_cache_sectors`` FAT sectors in memory). A dirty volume is
        repaired (:meth:`repair`) unless ``repair`` is false. Raises :class:`FatError`
        naming the problem when the card is not a sane FAT32."""
        mbr = await device.read_block(0)
        index, kind, start, sectors = _find_partition(mbr)
        where = f"partition {index + 1} (sector {start})"
        if start == 0 or sectors == 0:
            raise FatError(f"{where}: starts at sector {start} with {sectors} sectors")
        boot = await device.read_block(start)
        _check_partition_type(index, kind, boot)
        _check_bpb(f"{where} boot sector", boot, sectors)
        volume = cls(device, _Layout(start, boot), [], fat_cache_sectors=fat_cache_sectors)
        await volume._check_backup_boot(boot)
        await volume._read_fsinfo()
        await volume._check_fat_head()
        if volume.was_dirty and repair:
            await volume.repair()
        return volume

    async def _check_backup_boot(self, boot):
        lba = self.layout.partition_start + self.layout.backup_boot_sector
        if await self.device.read_block(lba) != boot:
            self.notes.append(f"the backup boot sector (sector {lba}) differs from the "
                              f"boot sector")

    async def _read_fsinfo(self):
        lba = self.layout.partition_start + self.layout.fsinfo_sector
        fsi = await self.device.read_block(lba)
        signatures = (_u32(fsi, arch.FSI_LEAD_SIG_OFFSET) == arch.FSI_LEAD_SIG
                      and _u32(fsi, arch.FSI_STRUC_SIG_OFFSET) == arch.FSI_STRUC_SIG
                      and _u32(fsi, arch.FSI_TRAIL_SIG_OFFSET) == arch.FSI_TRAIL_SIG)
        if not signatures:
            self.notes.append(f"FSInfo (sector {lba}) has bad signatures: ignored and "
                              f"never written; free clusters counted from the FAT")
            self.free_count = await self._count_free()
            self.next_free = arch.FIRST_DATA_CLUSTER
            return
        self.fsinfo_valid = True
        self._fsinfo = bytearray(fsi)
        self._fsinfo_on_card = bytes(fsi)
        free, hint = _u32(fsi, arch.FSI_FREE_COUNT), _u32(fsi, arch.FSI_NXT_FREE)
        if free > self.layout.cluster_count:
            if free != arch.FSI_UNKNOWN:
                self.notes.append(f"FSInfo free count {free} exceeds the "
                                  f"{self.layout.cluster_count} clusters: recounted")
            free = await self._count_free()
        if not arch.FIRST_DATA_CLUSTER <= hint <= self.layout.max_cluster:
            if hint != arch.FSI_UNKNOWN:
                self.notes.append(f"FSInfo next-free hint {hint} is outside clusters "
                                  f"2..{self.layout.max_cluster}: ignored")
            hint = arch.FIRST_DATA_CLUSTER
        self.free_count, self.next_free = free, hint

    async def _check_fat_head(self):
        fat1 = await self._fat_entry(1)
        if not fat1 & arch.CLEAN_SHUTDOWN_BIT:
            self.was_dirty = True
            self.notes.append("the volume is dirty (clean-shutdown bit of FAT[1] clear): it "
                              "was not closed cleanly; lost clusters are possible")
        if not fat1 & arch.HARD_ERROR_BIT:
            self.notes.append("the hard-error bit of FAT[1] is clear: a disk error was met")

    async def _count_free(self):
        free = 0
        for cluster in range(arch.FIRST_DATA_CLUSTER, self.layout.max_cluster + 1):
            if await self._fat_entry(cluster) == arch.FAT_FREE:
                free += 1
        return free

    # -- repair of a dirty volume -----------------------------------------------------------

    async def repair(self):
        """Repair what a power cut can leave on a dirty volume, as ``fsck.fat -a`` would, or
        find damage it does not repair and leave the volume dirty (:attr:`damage`).

        1. Walk every directory from the root (volume label, deleted and long-name entries
           skipped) and follow every chain, marking each cluster reached in a bitmap. A
           file's chain longer than its size is trimmed to it (its clusters past the size
           are not marked); a size-0 file with a first cluster loses it. Damage a cut does
           not cause (a chain shorter than its size or running into a free, bad or
           out-of-range cluster, two chains meeting, a directory loop) is recorded in
           :attr:`damage` and nothing is written.
        2. Write the directory entries that lose their first cluster, then the FAT sectors
           that end the trimmed chains (every FAT).
        3. Sweep the FAT once, sector by sector: an allocated cluster no chain reached (a
           lost cluster, a trimmed tail) is freed; FAT 1's sector is written when it changed,
           then every other FAT's when it differs from FAT 1 (FAT 1 is written first by the
           writer, so it is the newer); the free clusters are counted.
        4. FSInfo gets the count (and the first free cluster as its hint), then the
           clean-shutdown bit is set.

        Every step leaves at worst lost clusters, FATs that differ or a stale count, with
        the volume still dirty, so a cut during the repair is repaired at the next mount.

        Bounds: memory, a bitmap of one bit per cluster (128 KiB for the 1 M clusters of a
        32 GB card) and the FAT cache; block reads, every directory sector once, every FAT
        sector of every FAT once in the sweep, and while following chains one FAT sector
        read each time a chain moves to a FAT sector not in the cache (a contiguous chain
        reads each of its FAT sectors once; at most one read per allocated cluster); block
        writes, the entries and trimmed chains' sectors twice (every FAT), at most every FAT
        sector once per FAT, FSInfo and the FAT's first sector. So the time is linear in the
        size of the FAT and the directories: no chain is followed twice, and a full card of
        contiguous files costs about three reads per FAT sector. On the logger (model
        timing, ~0.8 ms a block read through the DMA's buffer): 0.9 s for an empty 40 MiB
        card of 512-byte clusters (2 x 513 FAT sectors); 1.6 s for a nearly full 40 MiB card
        that mkfs.fat formatted (about 2 x 620) and mtools filled."""
        layout = self.layout
        free_was = self.free_count
        reached = bytearray((layout.max_cluster >> 3) + 1)
        damage, trims, unlink = [], [], []

        def seen(cluster):
            return reached[cluster >> 3] >> (cluster & 7) & 1

        def mark(cluster):
            reached[cluster >> 3] |= 1 << (cluster & 7)

        def valid(cluster):
            return arch.FIRST_DATA_CLUSTER <= cluster <= layout.max_cluster

        async def follow(first, need, what):
            """Mark ``first``'s chain (``need`` clusters; None: a directory, all of it);
            return its clusters, or None after recording damage."""
            chain, cluster = [], first
            while True:
                if need is not None and len(chain) == need:
                    trims.append(chain[-1])         # the clusters from `cluster` on: lost
                    return chain
                if seen(cluster):
                    damage.append(f"{what}: its chain meets another (cluster {cluster})")
                    return None
                mark(cluster)
                chain.append(cluster)
                following = await self._fat_entry(cluster)
                if following >= arch.FAT_EOC_MIN:
                    if need is not None and len(chain) < need:
                        damage.append(f"{what}: {len(chain)} clusters, fewer than its size "
                                      f"needs ({need})")
                        return None
                    return chain
                if not valid(following):
                    damage.append(f"{what}: its chain breaks at cluster {cluster} (FAT entry "
                                  f"0x{following:08x})")
                    return None
                cluster = following

        directories = [(layout.root_cluster, "the root directory")]
        while directories and not damage:
            first, where = directories.pop()
            chain = await follow(first, None, where)
            if chain is None:
                break
            async for lba, index, entry in self._slots_of(chain):
                if entry[0] == arch.DIR_END:
                    break
                attr = entry[arch.DIR_ATTR]
                if (entry[0] == arch.DIR_DELETED or attr & arch.Attr.LONG_NAME
                        == arch.Attr.LONG_NAME or attr & arch.Attr.VOLUME_ID
                        or entry[:2] == b". " or entry[:3] == b".. "):
                    continue
                base, ext = (entry[:8].decode("latin-1").rstrip(),
                             entry[8:arch.DIR_NAME_BYTES].decode("latin-1").rstrip())
                name = f"{base}.{ext}" if ext else base
                what = f"{where}/{name}" if where != "the root directory" else f"/{name}"
                start = (_u16(entry, arch.DIR_FST_CLUS_HI) << 16
                         | _u16(entry, arch.DIR_FST_CLUS_LO))
                size = _u32(entry, arch.DIR_FILE_SIZE)
                if attr & arch.Attr.DIRECTORY:
                    if not valid(start):
                        damage.append(f"{what}: a directory starting at cluster {start}")
                    else:
                        directories.append((start, what))
                    continue
                if start == 0:
                    if size:
                        damage.append(f"{what}: {size} bytes but no cluster")
                    continue
                if not valid(start):
                    damage.append(f"{what}: starts at cluster {start}, outside 2.."
                                  f"{layout.max_cluster}")
                    continue
                if size == 0:
                    unlink.append((lba, index))     # its clusters are lost clusters
                    continue
                await follow(start, _ceil_div(size, layout.cluster_bytes), what)
        if damage:
            self.damage = damage
            self.notes.append(f"the dirty volume was not repaired: {damage[0]}"
                              + (f" (and {len(damage) - 1} more)" if len(damage) > 1 else "")
                              + "; it stays marked dirty")
            return
        for lba, index in unlink:
            sector = bytearray(await self.device.read_block(lba))
            offset = index * arch.DIR_ENTRY_BYTES
            _put16(sector, offset + arch.DIR_FST_CLUS_HI, 0)
            _put16(sector, offset + arch.DIR_FST_CLUS_LO, 0)
            await self.device.write_block(lba, bytes(sector))
        for cluster in trims:
            await self._set_fat_entry(cluster, arch.FAT_EOC)
        await self._flush_fat()
        freed, copied, free, hint = await self._sweep(seen)
        self.free_count = free
        self.next_free = hint if hint is not None else arch.FIRST_DATA_CLUSTER
        await self._write_fsinfo()
        await self._set_clean_bit(True)
        self.repaired = {"trimmed": len(trims), "freed": freed, "fat_copied": copied,
                         "unlinked": len(unlink), "free_was": free_was, "free_count": free}
        self.notes.append(f"the dirty volume was repaired: {len(trims)} chains trimmed to "
                          f"their files' sizes, {freed} lost clusters freed, {copied} FAT "
                          f"sectors made equal to FAT 1, free count {free} (was {free_was})")

    async def _slots_of(self, chain):
        """``(lba, index, entry)`` of each directory slot in the clusters ``chain``."""
        for cluster in chain:
            lba = self.layout.cluster_lba(cluster)
            for sector in range(self.layout.sectors_per_cluster):
                data = await self.device.read_block(lba + sector)
                for index in range(arch.DIR_ENTRIES_PER_SECTOR):
                    offset = index * arch.DIR_ENTRY_BYTES
                    yield lba + sector, index, data[offset:offset + arch.DIR_ENTRY_BYTES]

    async def _sweep(self, reached):
        """Free every allocated cluster for which ``reached(cluster)`` is false and make
        every FAT equal to FAT 1, a FAT sector at a time (FAT 1's first); returns ``(freed,
        FAT sectors copied, free clusters, first free cluster or None)``."""
        layout = self.layout
        last_sector = layout.max_cluster // arch.FAT_ENTRIES_PER_SECTOR
        freed = copied = free = 0
        hint = None
        for index in range(last_sector + 1):
            sector = bytearray(await self.device.read_block(layout.fat_start + index))
            changed = False
            for slot in range(arch.FAT_ENTRIES_PER_SECTOR):
                cluster = index * arch.FAT_ENTRIES_PER_SECTOR + slot
                if not arch.FIRST_DATA_CLUSTER <= cluster <= layout.max_cluster:
                    continue
                offset = slot * arch.FAT_ENTRY_BYTES
                value = _u32(sector, offset) & arch.FAT_ENTRY_MASK
                if value != arch.FAT_FREE and value != arch.FAT_BAD and not reached(cluster):
                    _put32(sector, offset, _u32(sector, offset) & ~arch.FAT_ENTRY_MASK
                           & 0xFFFFFFFF)
                    value, changed = arch.FAT_FREE, True
                    freed += 1
                if value == arch.FAT_FREE:
                    free += 1
                    if hint is None:
                        hint = cluster
            if changed:
                await self.device.write_block(layout.fat_start + index, bytes(sector))
            for fat in range(1, layout.num_fats):
                lba = layout.fat_start + fat * layout.fat_sectors + index
                if await self.device.read_block(lba) != sector:
                    await self.device.write_block(lba, bytes(sector))
                    copied += 1
            if index in self._fat:
                self._fat[index] = sector
        return freed, copied, free, hint

    # -- the FAT ----------------------------------------------------------------------------

    @property
    def cached_fat_sectors(self):
        """How many FAT sectors are in memory now."""
        return len(self._fat)

    async def _fat_sector(self, index):
        sector = self._fat.get(index)
        if sector is None:
            sector = bytearray(await self.device.read_block(self.layout.fat_start + index))
            self.fat_reads += 1
            self._fat[index] = sector
            self._trim_fat_cache(keep=index)
        else:
            self._fat.move_to_end(index)
        return sector

    def _trim_fat_cache(self, keep=None):
        """Evict least recently used clean FAT sectors down to the bound; changed sectors
        wait for the next flush, and ``keep`` (the sector in use) stays."""
        excess = len(self._fat) - self.fat_cache_sectors
        for index in list(self._fat):
            if excess <= 0:
                break
            if index != keep and index not in self._fat_dirty:
                del self._fat[index]
                excess -= 1

    async def _fat_entry(self, cluster):
        index, slot = divmod(cluster, arch.FAT_ENTRIES_PER_SECTOR)
        sector = await self._fat_sector(index)
        return _u32(sector, slot * arch.FAT_ENTRY_BYTES) & arch.FAT_ENTRY_MASK

    async def _set_fat_entry(self, cluster, value):
        index, slot = divmod(cluster, arch.FAT_ENTRIES_PER_SECTOR)
        sector = await self._fat_sector(index)
        offset = slot * arch.FAT_ENTRY_BYTES
        reserved = _u32(sector, offset) & ~arch.FAT_ENTRY_MASK & 0xFFFFFFFF
        _put32(sector, offset, reserved | (value & arch.FAT_ENTRY_MASK))
        self._fat_dirty.add(index)

    async def _write_fat_sectors(self, indices):
        for fat in range(self.layout.num_fats):
            base = self.layout.fat_start + fat * self.layout.fat_sectors
            for index in indices:
                await self.device.write_block(base + index, bytes(self._fat[index]))

    async def _flush_fat(self):
        # The sectors that link a chain already on the card to fresh clusters go last: a cut
        # before them leaves the fresh clusters lost (recoverable), never a chain that runs
        # into a free cluster.
        order = (sorted(self._fat_dirty - self._anchors)
                 + sorted(self._fat_dirty & self._anchors))
        await self._write_fat_sectors(order)
        self._fat_dirty.clear()
        self._fresh.clear()
        self._anchors.clear()
        self._trim_fat_cache()

    async def _set_clean_bit(self, clean):
        if clean and self.damage:
            return                      # damage the repair left: the volume stays dirty
        fat1 = await self._fat_entry(1)
        value = fat1 | arch.CLEAN_SHUTDOWN_BIT if clean else fat1 & ~arch.CLEAN_SHUTDOWN_BIT
        await self._set_fat_entry(1, value)
        self._fat_dirty.discard(0)
        await self._write_fat_sectors([0])

    async def _mark_dirty(self):
        """Clear the clean-shutdown bit on both FATs before the first write after mount."""
        if not self._dirty_marked:
            await self._set_clean_bit(False)
            self._dirty_marked = True

    async def _allocate(self, previous):
        """A free cluster, found from the hint onwards (wrapping), marked end of chain and
        linked after ``previous`` (0: none). Raises :class:`FatFullError`."""
        first, last = arch.FIRST_DATA_CLUSTER, self.layout.max_cluster
        if self.free_count == 0:
            raise FatFullError("the card is full: no free cluster")
        start = min(max(self.next_free, first), last)
        cluster = start
        while await self._fat_entry(cluster) != arch.FAT_FREE:
            cluster = cluster + 1 if cluster < last else first
            if cluster == start:
                self.free_count = 0
                raise FatFullError("the card is full: no free cluster")
        await self._set_fat_entry(cluster, arch.FAT_EOC)
        if previous:
            await self._set_fat_entry(previous, cluster)
            if previous not in self._fresh:
                self._anchors.add(previous // arch.FAT_ENTRIES_PER_SECTOR)
        self._fresh.add(cluster)
        self.free_count -= 1
        self.next_free = cluster + 1 if cluster < last else first
        return cluster

    async def _free_clusters(self, clusters):
        """Mark ``clusters`` free (in the cache; the next FAT flush writes them)."""
        for cluster in clusters:
            await self._set_fat_entry(cluster, arch.FAT_FREE)
            self._fresh.discard(cluster)
            self.free_count += 1
            self.next_free = min(self.next_free, cluster)

    async def _write_fsinfo(self):
        """Write FSInfo when its free count or next-free hint changed (an allocation): a
        sync that allocated nothing leaves the sector as it is, a block write saved."""
        if not self.fsinfo_valid:
            return
        _put32(self._fsinfo, arch.FSI_FREE_COUNT, self.free_count)
        _put32(self._fsinfo, arch.FSI_NXT_FREE, self.next_free)
        if self._fsinfo == self._fsinfo_on_card:
            return
        await self.device.write_block(self.layout.partition_start + self.layout.fsinfo_sector,
                                      bytes(self._fsinfo))
        self._fsinfo_on_card = bytes(self._fsinfo)

    # -- the root directory -----------------------------------------------------------------

    async def _chain(self, first):
        chain, cluster = [], first
        while arch.FIRST_DATA_CLUSTER <= cluster <= self.layout.max_cluster:
            if len(chain) > self.layout.cluster_count:
                raise FatError(f"the cluster chain from cluster {first} loops")
            chain.append(cluster)
            cluster = await self._fat_entry(cluster)
        if cluster < arch.FAT_EOC_MIN:
            raise FatError(f"the cluster chain from cluster {first} breaks at cluster "
                           f"{chain[-1]} (FAT entry 0x{cluster:08x})")
        return chain

    async def _root_slots(self):
        """Yield ``(lba, index, entry)`` for each directory slot of the root, in order."""
        async for slot in self._slots_of(await self._chain(self.layout.root_cluster)):
            yield slot

    async def _scan_root(self):
        """The highest LOG file number in the root (0: none), the first free slot at the
        end of the directory (``None`` when the directory is full) and its slot count."""
        highest, end, slots = 0, None, 0
        async for lba, index, entry in self._root_slots():
            slots += 1
            if entry[0] == arch.DIR_END:
                end = (lba, index)
                break
            if entry[0] == arch.DIR_DELETED or entry[arch.DIR_ATTR] == arch.Attr.LONG_NAME:
                continue
            match = _LOG_NAME.fullmatch(entry[:arch.DIR_NAME_BYTES])
            if match:
                highest = max(highest, int(match.group(1)))
        return highest, end, slots

    async def _grow_root(self):
        """Append a zeroed cluster to the root directory; return its first slot."""
        chain = await self._chain(self.layout.root_cluster)
        if (len(chain) + 1) * self.layout.cluster_bytes > (arch.DIR_MAX_ENTRIES
                                                           * arch.DIR_ENTRY_BYTES):
            raise FatFullError(f"the root directory is full ({arch.DIR_MAX_ENTRIES} entries)")
        cluster = await self._allocate(chain[-1])
        lba = self.layout.cluster_lba(cluster)
        for sector in range(self.layout.sectors_per_cluster):
            await self.device.write_block(lba + sector, bytes(SECTOR))
        await self._flush_fat()
        await self._write_fsinfo()
        return lba, 0

    # -- files ------------------------------------------------------------------------------

    async def create_log(self, timestamp=None):
        """Create ``LOGnnnnn.TXT`` with the number after the highest LOG file in the root
        directory (created at ``timestamp``, default the FAT epoch); return its
        :class:`LogFile`. Never overwrites; raises :class:`FatError` after LOG99999."""
        highest, slot, _ = await self._scan_root()
        if highest >= LOG_MAX_NUMBER:
            raise FatNoNumberError(f"no free LOG file number: LOG{LOG_MAX_NUMBER:05d}.TXT "
                                   f"exists and is the last one the 8.3 name LOGnnnnn.TXT "
                                   f"allows")
        number = highest + 1
        name = f"LOG{number:05d}TXT".encode("ascii")
        await self._mark_dirty()
        if slot is None:
            slot = await self._grow_root()
        date, time = fat_date_time(FAT_EPOCH if timestamp is None else timestamp)
        entry = bytearray(arch.DIR_ENTRY_BYTES)
        entry[arch.DIR_NAME:arch.DIR_NAME + arch.DIR_NAME_BYTES] = name
        entry[arch.DIR_ATTR] = arch.Attr.ARCHIVE
        for field, value in ((arch.DIR_CRT_TIME, time), (arch.DIR_CRT_DATE, date),
                             (arch.DIR_LST_ACC_DATE, date), (arch.DIR_WRT_TIME, time),
                             (arch.DIR_WRT_DATE, date)):
            _put16(entry, field, value)
        log = LogFile(self, f"LOG{number:05d}.TXT", slot, entry)
        await log._write_entry()
        self._files.append(log)
        return log

    async def sync(self, timestamp):
        """Sync every open file (see :meth:`LogFile.sync`)."""
        for log in self._files:
            await log.sync(timestamp)

    async def close(self, timestamp=None):
        """Sync every open file and mark the volume clean (clean-shutdown bit set)."""
        for log in list(self._files):
            await log.close(timestamp)
        if self._dirty_marked:
            await self._flush_fat()
            await self._write_fsinfo()
            await self._set_clean_bit(True)
            self._dirty_marked = False


@dataclass(frozen=True)
class Extent:
    """``count`` consecutive sectors of a file from its sector ``file_sector`` on, stored
    from block ``lba`` on."""
    lba: int
    file_sector: int
    count: int


@dataclass(frozen=True)
class Extents:
    """Where the sectors of a file's growth go (:meth:`LogFile.extents`): ``runs`` of
    contiguous blocks, in file order, covering the file up to ``size`` bytes. ``size`` is
    less than the size asked for only when the card is full: the file then ends at the end
    of its last cluster."""
    runs: tuple
    size: int

    @property
    def sectors(self):
        return sum(run.count for run in self.runs)


class LogFile:
    """An open log file. Host data: :meth:`append`, :meth:`sync`. Data written by someone
    else (the DMA from the ring): :meth:`extents`, then :meth:`grow`. Then :meth:`close`."""

    def __init__(self, volume, name, slot, entry):
        self.volume = volume
        self.name = name
        #: Bytes of the file: appended whole sectors, or the size :meth:`grow` committed.
        self.size = 0
        self._slot = slot               # (lba, index) of the directory entry
        self._entry = entry
        self._first = 0
        # The file's clusters from its cluster number `_base` on: the one its end lies in
        # and any allocated after it (earlier ones are never written again).
        self._clusters = []
        self._base = 0
        self._tail = bytearray()        # bytes of the last, partial sector (append path)
        self._closed = False

    @property
    def first_cluster(self):
        return self._first

    @property
    def closed(self):
        return self._closed

    def _check_open(self):
        if self._closed:
            raise FatError(f"{self.name} is closed")

    async def _cluster_at(self, index):
        """The cluster holding the file's cluster number ``index``, allocating and linking
        clusters up to it. Raises :class:`FatFullError`."""
        while self._base + len(self._clusters) <= index:
            previous = self._clusters[-1] if self._clusters else 0
            cluster = await self.volume._allocate(previous)
            if not self._first:
                self._first = cluster
            self._clusters.append(cluster)
        return self._clusters[index - self._base]

    def _forget_before(self, index):
        """Drop the clusters before the file's cluster number ``index``, keeping the last
        one (the next allocation links after it)."""
        drop = min(index - self._base, len(self._clusters) - 1)
        if drop > 0:
            del self._clusters[:drop]
            self._base += drop

    async def _sector_lba(self, file_sector):
        layout = self.volume.layout
        index, offset = divmod(file_sector, layout.sectors_per_cluster)
        return layout.cluster_lba(await self._cluster_at(index)) + offset

    async def append(self, data):
        """Add ``data`` to the file: whole sectors are written now, the partial last one at
        the next :meth:`sync`. Raises :class:`FatFullError` (with ``written``) when the card
        fills; what fitted is kept."""
        self._check_open()
        await self.volume._mark_dirty()
        view, written = memoryview(bytes(data)), 0
        cluster_bytes = self.volume.layout.cluster_bytes
        while written < len(view):
            if self.size % cluster_bytes == 0 and not self._tail:
                try:
                    await self._cluster_at(self.size // cluster_bytes)
                except FatFullError as full:
                    raise FatFullError(f"{full}: {self.name} took {written} of {len(view)} "
                                       f"bytes", written) from None
            take = min(SECTOR - len(self._tail), len(view) - written)
            self._tail += view[written:written + take]
            written += take
            if len(self._tail) == SECTOR:
                lba = await self._sector_lba(self.size // SECTOR)
                await self.volume.device.write_block(lba, bytes(self._tail))
                self._tail.clear()
                self.size += SECTOR
        return written

    async def extents(self, new_size):
        """Allocate the clusters for the file to reach ``new_size`` bytes and return the
        :class:`Extents` of its sectors from the one its end lies in (a partial last sector
        is written again, longer) up to ``new_size``. Nothing is written: the caller writes
        the data there, then calls :meth:`grow`. On a full card the extents stop at the last
        cluster that could be allocated (``size`` says where)."""
        self._check_open()
        if self._tail:
            raise FatError(f"{self.name} holds {len(self._tail)} appended bytes not yet "
                           f"synced: sync before handing the file to the ring path")
        if not isinstance(new_size, int) or new_size < self.size:
            raise ValueError(f"New size must be an integer of at least {self.size} bytes, "
                             f"not {new_size!r}")
        await self.volume._mark_dirty()
        layout = self.volume.layout
        per_cluster = layout.sectors_per_cluster
        sector, end = self.size // SECTOR, _ceil_div(new_size, SECTOR)
        runs = []
        while sector < end:
            index, offset = divmod(sector, per_cluster)
            try:
                cluster = await self._cluster_at(index)
            except FatFullError:
                break
            lba = layout.cluster_lba(cluster) + offset
            count = min(per_cluster - offset, end - sector)
            if runs and runs[-1].lba + runs[-1].count == lba:
                runs[-1] = Extent(runs[-1].lba, runs[-1].file_sector, runs[-1].count + count)
            else:
                runs.append(Extent(lba, sector, count))
            sector += count
        return Extents(tuple(runs), min(new_size, max(sector * SECTOR, self.size)))

    async def grow(self, new_size, timestamp):
        """Commit ``new_size`` (the ``size`` of the last :meth:`extents`, whose sectors the
        caller has written): the FAT sectors (every FAT), the directory entry (size, first
        cluster, write time from ``timestamp``), then FSInfo, as :meth:`sync` does. Call it
        only once the data is on the card: it makes the file point at it."""
        self._check_open()
        if self._tail:
            raise FatError(f"{self.name} holds {len(self._tail)} appended bytes not yet "
                           f"synced: sync before handing the file to the ring path")
        cluster_bytes = self.volume.layout.cluster_bytes
        allocated = self._base + len(self._clusters)
        if (not isinstance(new_size, int) or new_size < self.size
                or _ceil_div(new_size, cluster_bytes) != allocated):
            raise ValueError(f"New size must be at least {self.size} bytes and end in the "
                             f"file's last allocated cluster (cluster {allocated} of "
                             f"{cluster_bytes} bytes), not {new_size!r}")
        self.size = new_size
        await self.sync(timestamp)

    async def end_at(self, size, timestamp):
        """End the file at ``size`` bytes (ring path, nothing appended pending): anywhere
        from 0 up to the end of its last allocated cluster, below its synced size too (the
        logger ends a file on a full card at its last whole frame). The clusters after the
        one ``size`` ends in are freed. Safe order at any cut: growing, the FAT (fresh
        clusters past the end were never on the card) then the entry, as :meth:`sync`;
        shrinking, the entry first (the chain is then at worst longer than the file: lost
        clusters), then the FAT sector that ends the chain, then the ones that free its
        tail, then FSInfo."""
        self._check_open()
        if self._tail:
            raise FatError(f"{self.name} holds {len(self._tail)} appended bytes not yet "
                           f"synced: sync before ending it")
        volume = self.volume
        cluster_bytes = volume.layout.cluster_bytes
        allocated = self._base + len(self._clusters)
        if (not isinstance(size, int) or isinstance(size, bool)
                or not 0 <= size <= allocated * cluster_bytes):
            raise ValueError(f"End must be an integer from 0 to {allocated * cluster_bytes} "
                             f"bytes (the file's allocated clusters), not {size!r}")
        keep = _ceil_div(size, cluster_bytes)
        if keep > self._base or not self._first:
            clusters, base = list(self._clusters), self._base
        else:                           # the last kept cluster was forgotten: walk the chain
            clusters, base = await volume._chain(self._first), 0
        last = clusters[keep - 1 - base] if keep else None
        tail = clusters[keep - base:]
        shrinking = size < self.size
        self.size = size
        if not keep:
            self._first = 0
        self._clusters = [last] if keep else []
        self._base = keep - 1 if keep else 0
        if shrinking:
            await self._write_metadata(timestamp)
        if last is not None:
            await volume._set_fat_entry(last, arch.FAT_EOC)
            if shrinking:
                index = last // arch.FAT_ENTRIES_PER_SECTOR
                await volume._write_fat_sectors([index])
                volume._fat_dirty.discard(index)
        await volume._free_clusters(tail)
        if shrinking:
            await volume._flush_fat()
            await volume._write_fsinfo()
        else:
            await self.sync(timestamp)

    async def _write_metadata(self, timestamp):
        """The directory entry: size, first cluster, write time from ``timestamp``."""
        date, time = fat_date_time(timestamp)
        _put16(self._entry, arch.DIR_WRT_DATE, date)
        _put16(self._entry, arch.DIR_WRT_TIME, time)
        _put16(self._entry, arch.DIR_LST_ACC_DATE, date)
        _put16(self._entry, arch.DIR_FST_CLUS_HI, self._first >> 16)
        _put16(self._entry, arch.DIR_FST_CLUS_LO, self._first & 0xFFFF)
        _put32(self._entry, arch.DIR_FILE_SIZE, self.size + len(self._tail))
        await self._write_entry()

    async def sync(self, timestamp):
        """Make the file on the card hold everything appended so far, in the safe order:
        the partial data sector, the FAT sectors (every FAT), the directory entry (size,
        first cluster, write time from ``timestamp``), then FSInfo."""
        self._check_open()
        volume = self.volume
        if self._tail:
            await volume.device.write_block(await self._sector_lba(self.size // SECTOR),
                                            bytes(self._tail.ljust(SECTOR, b"\0")))
        await volume._flush_fat()
        await self._write_metadata(timestamp)
        await volume._write_fsinfo()
        self._forget_before(self.size // volume.layout.cluster_bytes)

    async def _write_entry(self):
        lba, index = self._slot
        sector = bytearray(await self.volume.device.read_block(lba))
        offset = index * arch.DIR_ENTRY_BYTES
        sector[offset:offset + arch.DIR_ENTRY_BYTES] = self._entry
        await self.volume.device.write_block(lba, bytes(sector))

    async def close(self, timestamp=None):
        """Final sync (at ``timestamp``, default the last write time) and close; the volume
        is marked clean when no other file is open."""
        if self._closed:
            return
        if timestamp is None:
            date, time = _u16(self._entry, arch.DIR_WRT_DATE), _u16(self._entry,
                                                                     arch.DIR_WRT_TIME)
            timestamp = (_dt.date(1980 + (date >> 9), (date >> 5) & 0xF, date & 0x1F),
                         _dt.time(time >> 11, (time >> 5) & 0x3F, (time & 0x1F) * 2))
        await self.sync(timestamp)
        self._closed = True
        volume = self.volume
        volume._files.remove(self)
        if not volume._files and volume._dirty_marked:
            await volume._set_clean_bit(True)
            volume._dirty_marked = False
