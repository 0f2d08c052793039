"""FAT32 on-disk constants: MBR, boot sector (BPB), FSInfo, FAT entries, directory entries,
and the SD Association's format parameters for SDHC cards.

# Ref: Microsoft Extensible Firmware Initiative FAT32 File System Specification, "FAT:
#      General Overview of On-Disk Format", v1.03 (2000; republished 2005), cited as "FAT".
# Ref: SD Specifications Part 2, File System Specification, Version 3.00 (SD Association,
#      2009), cited as "SDFS".
# Ref: IBM PC master boot record layout (partition table at byte 446), as SDFS §5.1 uses it.
"""

import enum as _enum

SECTOR_BYTES = 512
BOOT_SIGNATURE = b"\x55\xAA"          # bytes 510-511 of the MBR, boot sector and FSInfo
BOOT_SIGNATURE_OFFSET = 510

# -- Master boot record ---------------------------------------------------------------------
# Ref: SDFS §5.1 "Master Boot Record and Partition Table": four 16-byte entries at 446.
MBR_PARTITION_TABLE = 446
MBR_PARTITION_ENTRY_BYTES = 16
MBR_PARTITIONS = 4
MBR_DISK_ID = 440
#: Offsets inside one partition entry.
PART_STATUS = 0
PART_CHS_FIRST = 1
PART_TYPE = 4
PART_CHS_LAST = 5
PART_LBA_FIRST = 8
PART_SECTORS = 12
#: CHS geometry that LBA-only hosts assume, and the CHS value meaning "beyond 1024 cylinders".
CHS_HEADS = 255
CHS_SECTORS = 63
CHS_MAX_CYLINDER = 1023


class PartitionType(_enum.IntEnum):
    """MBR system ID (SDFS §5.1 Table 5-2 lists FAT12/16/32 and exFAT)."""
    EMPTY = 0x00
    FAT12 = 0x01
    FAT16_SMALL = 0x04
    EXTENDED = 0x05
    FAT16 = 0x06
    EXFAT = 0x07                        # also NTFS; told apart by the boot sector's OEM name
    FAT32_CHS = 0x0B
    FAT32_LBA = 0x0C                    # what SDFS gives an SDHC card
    FAT16_LBA = 0x0E
    EXTENDED_LBA = 0x0F
    GPT_PROTECTIVE = 0xEE


FAT32_PARTITION_TYPES = (PartitionType.FAT32_CHS, PartitionType.FAT32_LBA)

# -- Boot sector and BIOS parameter block ----------------------------------------------------
# Ref: FAT §3.1 "Boot Sector and BPB Structure" and §3.3 "FAT32 Structure Starting at Offset 36".
BS_JMP_BOOT = 0                        # EB xx 90 or E9 xx xx
JMP_SHORT = 0xEB
JMP_NEAR = 0xE9
NOP = 0x90
BS_OEM_NAME = 3                        # 8 bytes
BPB_BYTS_PER_SEC = 11                  # u16
BPB_SEC_PER_CLUS = 13                  # u8, a power of two 1..128
BPB_RSVD_SEC_CNT = 14                  # u16
BPB_NUM_FATS = 16                      # u8
BPB_ROOT_ENT_CNT = 17                  # u16, 0 on FAT32
BPB_TOT_SEC16 = 19                     # u16, 0 on FAT32
BPB_MEDIA = 21                         # u8
BPB_FAT_SZ16 = 22                      # u16, 0 on FAT32
BPB_SEC_PER_TRK = 24                   # u16
BPB_NUM_HEADS = 26                     # u16
BPB_HIDD_SEC = 28                      # u32: sectors before the partition
BPB_TOT_SEC32 = 32                     # u32
BPB_FAT_SZ32 = 36                      # u32
BPB_EXT_FLAGS = 40                     # u16: bit 7 set = only FAT number bits 0-3 is active
BPB_FS_VER = 42                        # u16, 0:0
BPB_ROOT_CLUS = 44                     # u32
BPB_FS_INFO = 48                       # u16
BPB_BK_BOOT_SEC = 50                   # u16
BS_DRV_NUM = 64                        # u8
BS_BOOT_SIG = 66                       # u8, 0x29: the next three fields are present
BS_VOL_ID = 67                         # u32
BS_VOL_LAB = 71                        # 11 bytes
BS_FIL_SYS_TYPE = 82                   # 8 bytes, informative only (FAT §3.5)
BS16_FIL_SYS_TYPE = 54                 # the same field in a FAT12/16 boot sector (FAT §3.2)

EXT_FLAGS_NO_MIRROR = 0x0080
EXTENDED_BOOT_SIGNATURE = 0x29
DRIVE_NUMBER_HARD_DISK = 0x80
FIL_SYS_TYPE_FAT32 = b"FAT32   "
NO_NAME_LABEL = b"NO NAME    "
#: An exFAT boot sector has this OEM name at byte 3 (exFAT specification §3.1.2).
EXFAT_OEM_NAME = b"EXFAT   "
#: Media descriptor of fixed media (FAT §3.1, BPB_Media); FAT[0] repeats it.
MEDIA_FIXED = 0xF8
MEDIA_VALUES = (0xF0,) + tuple(range(0xF8, 0x100))
#: Standard FAT32 reserved-region layout (FAT §3.3: BPB_FSInfo "usually 1", BPB_BkBootSec
#: "6; no value other than 6 is recommended"); the backup FSInfo follows the backup boot.
FSINFO_SECTOR = 1
BACKUP_BOOT_SECTOR = 6
BACKUP_FSINFO_SECTOR = 7
MIN_RESERVED_SECTORS = 32               # FAT §3.1: "typically 32 for FAT32"
NUM_FATS = 2
ROOT_CLUSTER = 2
MAX_SECTORS_PER_CLUSTER = 128
#: FAT §3.1 BPB_SecPerClus: more than 32 KiB a cluster is not supported by many systems.
MAX_CLUSTER_BYTES = 32 * 1024

# -- FSInfo ----------------------------------------------------------------------------------
# Ref: FAT §5 "FAT32 FSInfo Sector Structure and Backup Boot Sector".
FSI_LEAD_SIG_OFFSET = 0
FSI_LEAD_SIG = 0x41615252              # "RRaA"
FSI_STRUC_SIG_OFFSET = 484
FSI_STRUC_SIG = 0x61417272             # "rrAa"
FSI_FREE_COUNT = 488                   # u32, 0xFFFFFFFF = unknown
FSI_NXT_FREE = 492                     # u32, 0xFFFFFFFF = no hint
FSI_TRAIL_SIG_OFFSET = 508
FSI_TRAIL_SIG = 0xAA550000
FSI_UNKNOWN = 0xFFFFFFFF

# -- File allocation table -------------------------------------------------------------------
# Ref: FAT §3.5 "Determination of FAT type when mounting the volume" (cluster counts) and
#      §4 "FAT Data Structure" (entry values; FAT32 entries are 28 bits in a u32).
FAT_ENTRY_BYTES = 4
FAT_ENTRIES_PER_SECTOR = SECTOR_BYTES // FAT_ENTRY_BYTES       # 128
FAT_ENTRY_MASK = 0x0FFFFFFF            # the high 4 bits are reserved and preserved
FAT_FREE = 0x00000000
FAT_BAD = 0x0FFFFFF7
FAT_EOC = 0x0FFFFFFF                   # what this writer stores at a chain's end
FAT_EOC_MIN = 0x0FFFFFF8               # any value >= this ends a chain
FIRST_DATA_CLUSTER = 2
#: FAT[0] holds the media byte in its low 8 bits, the other bits set (FAT §4).
FAT0_HIGH = 0x0FFFFF00
#: FAT[1]: bit 27 set = volume clean (cleared while mounted, set at a clean dismount);
#: bit 26 set = no disk I/O error was met (FAT §4, "ClnShutBitMask" and "HrdErrBitMask").
CLEAN_SHUTDOWN_BIT = 0x08000000
HARD_ERROR_BIT = 0x04000000
#: Fewer clusters than this is FAT12 (< 4085) or FAT16 (FAT §3.5).
FAT16_MAX_CLUSTERS = 4084
FAT32_MIN_CLUSTERS = 65525
#: The largest cluster number a FAT32 entry can address below the reserved values.
FAT32_MAX_CLUSTER = 0x0FFFFFF6

# -- Directory entries -----------------------------------------------------------------------
# Ref: FAT §6 "Directory Structure" and §7 "Long File Name Implementation".
DIR_ENTRY_BYTES = 32
DIR_ENTRIES_PER_SECTOR = SECTOR_BYTES // DIR_ENTRY_BYTES       # 16
DIR_NAME = 0                           # 11 bytes, 8.3 space padded
DIR_ATTR = 11
DIR_NT_RES = 12
DIR_CRT_TIME_TENTH = 13
DIR_CRT_TIME = 14
DIR_CRT_DATE = 16
DIR_LST_ACC_DATE = 18
DIR_FST_CLUS_HI = 20
DIR_WRT_TIME = 22
DIR_WRT_DATE = 24
DIR_FST_CLUS_LO = 26
DIR_FILE_SIZE = 28
DIR_NAME_BYTES = 11
DIR_END = 0x00                         # this and every later entry is free
DIR_DELETED = 0xE5
DIR_KANJI_E5 = 0x05                    # a name whose first byte really is 0xE5
#: FAT §6: a directory holds at most 65,536 32-byte entries (2 MiB).
DIR_MAX_ENTRIES = 65536


class Attr(_enum.IntFlag):
    """DIR_Attr bits (FAT §6)."""
    READ_ONLY = 0x01
    HIDDEN = 0x02
    SYSTEM = 0x04
    VOLUME_ID = 0x08
    DIRECTORY = 0x10
    ARCHIVE = 0x20
    LONG_NAME = 0x0F                   # READ_ONLY|HIDDEN|SYSTEM|VOLUME_ID: an LFN entry


ATTR_LONG_NAME_MASK = 0x3F

# -- Date and time ---------------------------------------------------------------------------
# Ref: FAT §6.1 "Date and Time Formats": date = (year-1980)<<9 | month<<5 | day;
#      time = hour<<11 | minute<<5 | seconds/2.
FAT_EPOCH_YEAR = 1980
FAT_LAST_YEAR = 2107

# -- SD Association format parameters --------------------------------------------------------
# Ref: SDFS §5.2 / Annex C "Format Parameters", Table C-1/C-2: by card capacity the table gives
# the file system type, sectors a cluster and the boundary unit (BU, the erase-block
# alignment that the partition start and the first data sector are rounded to). For SDHC
# (more than 2 GB up to 32 GB) it gives FAT32, 64 sectors a cluster (32 KiB) and a BU of
# 8,192 sectors (4 MiB). SDSC cards (up to 2 GB) are given FAT12/16 and SDXC cards (above
# 32 GB) exFAT by the same tables, so FAT32 outside the SDHC range is not an SDA format.
SDHC_MIN_BYTES = 2 * 1024 ** 3 + 1     # capacities above 2 GiB
SDHC_MAX_BYTES = 32 * 1024 ** 3
SDHC_SECTORS_PER_CLUSTER = 64
SDHC_BOUNDARY_SECTORS = 8192
