"""Card images for the calibration tests, made by independent FAT tools.

One builder for every test that needs a whole card: an MBR with one FAT32 (LBA) partition
at 1 MiB, as SD cards are formatted, formatted by ``mkfs.fat`` and filled by ``mcopy``
(dosfstools and mtools, not maglog's own code). The tests get the tools from the
``fat_tools`` fixture of ``tests/conftest.py``; a script outside pytest (the mutation
benchmark) finds them with :func:`find_fat_tools`.
"""

import os
import shutil
import struct
import subprocess

SECTOR = 512
FS_LBA = 2048                         # 1 MiB aligned, as SD cards are formatted
FS_SECTORS = 131072                   # 64 MiB: a legal FAT32 with one-sector clusters
#: MBR partition type: FAT32 with LBA addressing.
FAT32_LBA = 0x0C


def find_fat_tools():
    """mkfs.fat and mcopy, name -> path, or None when either is missing."""
    search = os.pathsep.join([os.environ.get("PATH", os.defpath), "/usr/sbin", "/sbin"])
    found = {name: shutil.which(name, path=search) for name in ("mkfs.fat", "mcopy")}
    return found if all(found.values()) else None


def card_image(tools, path, files):
    """Write a raw card image to ``path`` holding ``files`` (name -> bytes) in its root."""
    with open(path, "wb") as f:
        f.truncate((FS_LBA + FS_SECTORS) * SECTOR)
        entry = struct.pack("<B3sB3sII", 0x00, b"\0\0\0", FAT32_LBA, b"\0\0\0", FS_LBA,
                            FS_SECTORS)
        f.seek(0x1BE)
        f.write(entry)
        f.seek(0x1FE)
        f.write(b"\x55\xAA")
    subprocess.run([tools["mkfs.fat"], "-F", "32", "-s", "1", "--offset", str(FS_LBA),
                    "-h", str(FS_LBA), str(path), str(FS_SECTORS // 2)],
                   check=True, capture_output=True)
    for name, data in files.items():
        source = path.parent / name
        source.write_bytes(data)
        subprocess.run([tools["mcopy"], "-i", f"{path}@@{FS_LBA * SECTOR}", str(source),
                        f"::{name}"], check=True, capture_output=True)
