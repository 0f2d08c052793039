"""A seeded mutation run of ``maglog calibrate`` and ``maglog survey``: card images, logs,
truth and base-station files and option values changed as a new user would meet them, each
run through ``maglog.cli.main.main`` in process, in worker processes (one per core) with an
alarm per input, and classified. (``survey`` exits 0 are judged by :func:`_judge_survey`:
survey.json strict JSON, report.html valid HTML, and an improvement ratio in
:data:`PLAUSIBLE_IR` and a map within :data:`PLAUSIBLE_GRID_RMS_NT` of the truth, or
warnings saying why not.)

Outcomes (:data:`OUTCOMES`):

``ok``
    exit 0, ``parameters.json`` strict JSON, ``report.html`` valid HTML, the parameters
    finite and the residual plausible (below the raw one and below
    :data:`PLAUSIBLE_RMS_NT`, the fit converged inside its box);
``warned``
    exit 0 with a result that is not all of that, and the report's warnings say why;
``error``
    exit 1 and a last line ``maglog: error: ...`` (no traceback);
``usage``
    the argument parser's exit 2 with its one-line message;
``traceback``
    an exception escaped ``main``;
``hang``
    no answer within the time limit;
``nonsense``
    exit 0 with no usable result and no warning saying why, or output that is not strict
    JSON / valid HTML, or an exit status other than 0, 1, 2.

Used by ``tests/calib/test_mutation.py`` (a short run by default, the long one under
``-m slow``) and ``bench/calib/mutation.py`` (the long run, its counts as JSON).
"""

import contextlib
import io
import json
import math
import multiprocessing
import os
import shutil
import signal
import struct
import tempfile
import time
import traceback
from collections import Counter
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from cards import FS_LBA, SECTOR, card_image

#: Input classes, in the order a run cycles through them.
CLASSES = ("image", "log:field", "log:bytes", "log:lines", "log:values", "option:ref",
           "option:seed", "option:method", "option:out", "option:attitude", "option:card")
OUTCOMES = ("ok", "warned", "error", "usage", "traceback", "hang", "nonsense")
#: The failures the run exists to find.
FAILURES = ("traceback", "hang", "nonsense")
#: A calibrated total field further than this (RMS) from the reference is no calibration.
PLAUSIBLE_RMS_NT = 1000.0
#: Seconds an input may take (a PSO fit and a report take a few on a loaded machine).
TIME_LIMIT = 120


#: Field values a new user's files and fingers produce.
WEIRD_FIELDS = ("", "0", "-0", "00000", "9" * 309, "1e308", "-1e308", "1e-308", "nan", "inf",
                "-inf", str(2**63), "9999999999999999999", "+99999.9", "-99999.9", "100000.0",
                "0.0001", "abc", " ", "1.2.3", "+", "-", ".", "3000", "9999", "235960.99",
                "240000", "0000", "1" * 5000, "\x00", "\u00e9", "$", "*", "-1", "2", "61",
                "0001", "99", "13")
REFS = ("5", "0", "-1", "1e30", "1e308", "nan", "inf", "-inf", "999", "1000", "1000000",
        "1000001", "50000", "48000.5", "abc", "", "CESIUM", "Igrf", "0x10", "1e-300", "1_000",
        " 50000", "5e4", "cesium", "igrf")
SEEDS = ("-1", "0", "1", str(2**128 - 1), str(2**128), "1.5", "x", "1e3", str(10**50), "",
         "0x10", "-0", "+3", "9" * 5000, "007")
METHODS = ("pso", "lm", "ellipsoid", "PSO", "ga", "", "ellipsoid ", "-m")


@dataclass
class Case:
    """One input: files to create in a fresh folder, the image's patches, the argv
    (``{work}`` is that folder, ``{base}`` the base material's)."""
    index: int
    kind: str
    detail: str
    argv: list
    files: dict = field(default_factory=dict)
    image: list = None            # None: no image; else [(offset, bytes)] patches
    image_size: int = None        # truncate the image to this many bytes
    out: str = "{work}/report"


# --- base material ------------------------------------------------------------------------

def make_base(folder, tools):
    """Logs, an attitude file and (with ``tools``) a card image the mutants start from;
    returns facts about them (image regions) for the generator."""
    from maglog.sim.stimulus.scenario import make_flight
    folder = Path(folder)
    uav = make_flight(coverage="uav", seconds=20, seed=3)
    full = make_flight(coverage="full", seconds=20, seed=4)
    (folder / "uav.log").write_bytes(uav.log())
    (folder / "full.log").write_bytes(full.log())
    (folder / "attitude.csv").write_bytes(uav.attitude_csv())
    facts = {"image": None}
    if tools:
        image = folder / "card.img"
        card_image(tools, image, {"LOG00001.TXT": uav.log(), "NOTES.TXT": b"notes\r\n"})
        facts["image"] = _image_facts(image)
    return facts


def _image_facts(path):
    """Byte ranges of the image's structures, read from its boot sector."""
    data = path.read_bytes()
    boot = FS_LBA * SECTOR
    per_sector, per_cluster, reserved, fats = struct.unpack_from("<HBHB", data, boot + 11)
    fat_size, = struct.unpack_from("<I", data, boot + 36)
    root_cluster, = struct.unpack_from("<I", data, boot + 44)
    fat = boot + reserved * per_sector
    clusters = fat + fats * fat_size * per_sector
    cluster_bytes = per_cluster * per_sector
    root = clusters + (root_cluster - 2) * cluster_bytes
    return {"size": len(data), "boot": boot, "fat": fat, "fat_bytes": fat_size * per_sector,
            "root": root, "cluster_bytes": cluster_bytes, "data": root + cluster_bytes}


def _sparse_copy(source, target, size):
    """Copy an image, its holes left holes (a 64 MiB image holds a few hundred KiB)."""
    with open(source, "rb") as src, open(target, "wb") as dst:
        dst.truncate(size)
        end = os.fstat(src.fileno()).st_size
        offset = 0
        while offset < min(end, size):
            try:
                start = os.lseek(src.fileno(), offset, os.SEEK_DATA)
                stop = os.lseek(src.fileno(), start, os.SEEK_HOLE)
            except OSError:          # no more data (ENXIO), or no SEEK_DATA here
                break
            stop = min(stop, size)
            if start >= stop:
                break
            src.seek(start)
            dst.seek(start)
            dst.write(src.read(stop - start))
            offset = stop


# --- mutations ------------------------------------------------------------------------------

def _lines(log):
    return log.splitlines(keepends=True)


def _kind(line):
    if line.startswith(b"$PMAG1,"):
        return "pmag"
    if line[1:2] in (b" ", b"1"):
        return "cesium"
    return line[3:6].decode("ascii", "replace").lower()


def _nmea(body):
    checksum = 0
    for byte in body:
        checksum ^= byte
    return b"$" + body + b"*%02X\r\n" % checksum


def _set_field(line, index, value, rng):
    """``line`` with comma field ``index`` replaced; the checksum recomputed mostly."""
    text = line.rstrip(b"\r\n")
    star = text.rfind(b"*")
    body = text[1:star] if star > 0 else text[1:]
    fields = body.split(b",")
    fields[index % len(fields)] = value
    body = b",".join(fields)
    if star > 0 and rng.random() < 0.8:
        return _nmea(body)
    return b"$" + body + (text[star:] if star > 0 else b"") + b"\r\n"


def _rewrite(log, kind, edit):
    """Every line of ``kind`` through ``edit(k, fields) -> fields or None`` (text fields;
    NMEA and PMAG checksums recomputed)."""
    out, k = [], 0
    for line in _lines(log):
        if _kind(line) != kind:
            out.append(line)
            continue
        text = line.rstrip(b"\r\n").decode("ascii")
        if kind == "cesium":
            new = edit(k, text[1:].split(","))
            if new is not None:
                out.append(("$" + ",".join(new) + "\r\n").encode())
        else:
            new = edit(k, text[1:text.index("*")].split(","))
            if new is not None:
                out.append(_nmea(",".join(new).encode()))
        k += 1
    return b"".join(out)


def _axes(values):
    def edit(k, fields):
        x, y, z = (float(f) for f in fields[2:5])
        return fields[:2] + [v if isinstance(v, str) else f"{v:+.1f}" for v in values(k, x, y, z)]
    return edit


def _mutate_field(log, rng):
    lines = _lines(log)
    weird = WEIRD_FIELDS[rng.integers(len(WEIRD_FIELDS))].encode("utf-8")
    kinds = sorted({_kind(line) for line in lines})
    if rng.random() < 0.3:                      # every line of one kind
        kind = kinds[rng.integers(len(kinds))]
        index = int(rng.integers(1, 12))
        lines = [_set_field(line, index, weird, rng) if _kind(line) == kind else line
                 for line in lines]
        return b"".join(lines), f"field {index} of every {kind} = {weird[:20]!r}"
    picks = rng.choice(len(lines), size=int(rng.integers(1, 4)), replace=False)
    index = int(rng.integers(1, 12))
    for p in picks:
        lines[p] = _set_field(lines[p], index, weird, rng)
    return b"".join(lines), f"field {index} of lines {sorted(picks.tolist())} = {weird[:20]!r}"


def _mutate_bytes(log, rng):
    data = bytearray(log)
    op = int(rng.integers(10))
    n = len(data)
    where = int(rng.integers(0, max(n, 1)))
    if op == 0:
        for p in rng.integers(0, n, size=int(rng.integers(1, 20))):
            data[p] ^= int(rng.integers(1, 256))
        return bytes(data), "bytes flipped"
    if op == 1:
        data[where:where] = b"\x00"
        return bytes(data), f"NUL inserted at {where}"
    if op == 2:
        span = int(rng.integers(1, 5000))
        del data[where:where + span]
        return bytes(data), f"{span} bytes deleted at {where}"
    if op == 3:
        junk = rng.integers(0, 256, size=int(rng.integers(1, 2000)), dtype=np.uint8).tobytes()
        data[where:where] = junk
        return bytes(data), f"{len(junk)} random bytes inserted at {where}"
    if op == 4:
        return bytes(data[:where]), f"truncated to {where} bytes"
    if op == 5:
        span = int(rng.integers(1, 20000))
        data[where:where] = data[where:where + span]
        return bytes(data), f"{span} bytes repeated at {where}"
    if op == 6:
        return log.replace(b"\r\n", b"\n"), "bare LF line ends"
    if op == 7:
        return log.replace(b"\n", b"\r"), "CR line ends"
    if op == 8:
        junk = rng.integers(0, 256, size=512, dtype=np.uint8).tobytes()
        return junk + log, "512 random bytes before the log"
    return log + rng.integers(0, 256, size=4096, dtype=np.uint8).tobytes(), "junk appended"


def _mutate_lines(log, rng):
    lines = _lines(log)
    op = int(rng.integers(9))
    kinds = ("pmag", "cesium", "gga", "zda")
    kind = kinds[rng.integers(len(kinds))]
    if op == 0:
        return b"".join(l for l in lines if _kind(l) != kind), f"every {kind} line dropped"
    if op == 1:
        n = int(rng.integers(0, 60))
        return b"".join(lines[:n]), f"first {n} lines only"
    if op == 2:
        order = rng.permutation(len(lines))
        return b"".join(lines[i] for i in order), "lines shuffled"
    if op == 3:
        return b"".join(reversed(lines)), "lines reversed"
    if op == 4:
        return b"".join(l + l for l in lines), "every line twice"
    if op == 5:
        return b"".join(sorted(lines)), "lines sorted"
    if op == 6:
        return b"".join(lines[::2]), "every other line"
    if op == 7:
        return b"".join(l for l in lines if _kind(l) == kind), f"{kind} lines only"
    keep = [l for l in lines if _kind(l) != "cesium"]
    one = [l for l in lines if _kind(l) == "cesium"][:1]
    return b"".join(one + keep), "one cesium line"


def _mutate_values(log, rng):
    op = int(rng.integers(20))
    axis = int(rng.integers(3))
    if op == 0:
        return _rewrite(log, "pmag", _axes(lambda k, x, y, z: (20000.0, 3000.0, 40000.0))), \
            "samples identical"
    if op == 1:
        return _rewrite(log, "pmag", _axes(
            lambda k, x, y, z: (20000.0, 3000.0, 40000.0) if k % 2 else (-9e3, 25e3, 35e3))), \
            "two distinct vectors"
    if op == 2:
        count = int(rng.integers(3, 14))
        table = rng.uniform(-40000, 40000, size=(count, 3))
        return _rewrite(log, "pmag", _axes(lambda k, x, y, z: tuple(table[k % count]))), \
            f"{count} distinct vectors"
    if op == 3:
        value = (0.0, 99999.9, -99999.9, float(rng.uniform(-9e4, 9e4)))[rng.integers(4)]

        def stuck(k, x, y, z):
            v = [x, y, z]
            v[axis] = value
            return tuple(v)
        return _rewrite(log, "pmag", _axes(stuck)), f"axis {'xyz'[axis]} stuck at {value:g}"
    if op == 4:
        return _rewrite(log, "pmag", _axes(lambda k, x, y, z: (0.0, 0.0, 0.0))), "all axes 0"
    if op == 5:
        factor = (1e-6, 1e-3, 0.1, 1.9, 10.0)[rng.integers(5)]
        return _rewrite(log, "pmag", _axes(
            lambda k, x, y, z: tuple(f"{v * factor:+.1f}" if abs(v * factor) < 1e5
                                     else f"{v * factor:+.4g}" for v in (x, y, z)))), \
            f"axes scaled by {factor:g}"
    if op == 6:
        return _rewrite(log, "pmag", _axes(lambda k, x, y, z: (x, y, -z))), "z reversed"
    if op == 7:
        return _rewrite(log, "pmag", _axes(
            lambda k, x, y, z: (x + rng.uniform(-5e4, 5e4), y, z))), "x noise of 50,000 nT"
    if op == 8:
        value = ("00000.000", "00000.001", "00500.000", "00005.000", "99999.999", "48000.000")[
            rng.integers(6)]
        prefix = "1" if rng.random() < 0.2 else " "
        return _rewrite(log, "cesium", lambda k, f: [prefix + value, f[1]]), \
            f"cesium all {prefix.strip()}{value}"
    if op == 9:
        return _rewrite(log, "cesium", lambda k, f: [
            f" {rng.uniform(0, 99999.999):09.3f}", f[1]]), "cesium random"
    if op == 10:
        year = ("1899", "1900", "2029", "2030", "3000", "9999", "0001")[rng.integers(7)]
        return _rewrite(log, "zda", lambda k, f: f[:4] + [year] + f[5:]), f"ZDA year {year}"
    if op == 11:
        return _rewrite(log, "zda", lambda k, f: f[:2] + ["31", "02"] + f[4:]), "ZDA 31 Feb"
    if op == 12:
        altitude = ("100000000.0", "-100000.0", "", "0.0", "99999.0", "1e308")[rng.integers(6)]
        return _rewrite(log, "gga", lambda k, f: f[:9] + [altitude] + f[10:]), \
            f"GGA altitude {altitude!r}"
    if op == 13:
        return _rewrite(log, "gga", lambda k, f: f[:6] + ["0"] + f[7:]), "GGA without a fix"
    if op == 14:
        return _rewrite(log, "gga", lambda k, f: [f[0], f"{235959 - k * 7:06d}.00"] + f[2:]), \
            "GGA time going back"
    if op == 15:
        place = (("9000.00000", "N", "00000.00000", "E"), ("9000.00000", "S", "18000.00000", "W"),
                 ("0000.00000", "N", "18000.00000", "E"))[rng.integers(3)]
        return _rewrite(log, "gga", lambda k, f: f[:2] + list(place) + f[6:]), \
            f"GGA at {place[0]}{place[1]} {place[2]}{place[3]}"
    if op == 16:
        return _rewrite(log, "pmag", lambda k, f: f[:1] + [f"{rng.integers(0, 100000):05d}"]
                        + f[2:]), "random sequence numbers"
    if op == 17:
        return _rewrite(log, "pmag", lambda k, f: f[:1] + ["00007"] + f[2:]), \
            "one sequence number"
    if op == 18:
        return _rewrite(log, "pmag", _axes(lambda k, x, y, z: (y, x, z))), "x and y swapped"
    return _rewrite(log, "pmag", _axes(lambda k, x, y, z: (x + 60000.0 if x < 39999 else x,
                                                           y, z))), "x offset by 60,000 nT"


def _image_patches(facts, rng):
    """Patches of the card image's structures: [(offset, bytes)], a size, a description."""
    boot, fat, root = facts["boot"], facts["fat"], facts["root"]
    size = facts["size"]
    op = int(rng.integers(8))
    if op == 0:
        region = ((0, SECTOR), (boot, 3 * SECTOR), (fat, 4 * SECTOR), (root, SECTOR),
                  (facts["data"], 4 * SECTOR))[rng.integers(5)]
        patches = [(int(region[0] + rng.integers(region[1])),
                    bytes([int(rng.integers(256))])) for _ in range(int(rng.integers(1, 9)))]
        return patches, size, f"{len(patches)} bytes changed from {region[0]}"
    if op == 1:
        name, offset, fmt = [("BytsPerSec", 11, "<H"), ("SecPerClus", 13, "<B"),
                             ("RsvdSecCnt", 14, "<H"), ("NumFATs", 16, "<B"),
                             ("TotSec32", 32, "<I"), ("FATSz32", 36, "<I"),
                             ("RootClus", 44, "<I"), ("FSInfo", 48, "<H"),
                             ("signature", 510, "<H")][rng.integers(9)]
        limit = 1 << (8 * struct.calcsize(fmt))
        value = (0, 1, limit - 1, int(rng.integers(limit)))[rng.integers(4)]
        return [(boot + offset, struct.pack(fmt, value))], size, f"BPB {name} = {value}"
    if op == 2:
        name, offset, fmt = [("type", 4, "<B"), ("LBA", 8, "<I"), ("count", 12, "<I")][
            rng.integers(3)]
        limit = 1 << (8 * struct.calcsize(fmt))
        value = (0, 1, limit - 1, int(rng.integers(limit)))[rng.integers(4)]
        return [(0x1BE + offset, struct.pack(fmt, value))], size, f"MBR {name} = {value}"
    if op == 3:
        cut = int(rng.integers(0, size))
        return [], cut, f"image truncated to {cut} bytes"
    if op == 4:
        where = (0, boot, boot + SECTOR, fat, root)[rng.integers(5)]
        return [(where, bytes(SECTOR))], size, f"sector at {where} zeroed"
    if op == 5:
        cluster = int(rng.integers(2, 40))
        value = (0, 0x0FFFFFF7, cluster, 0x0FFFFFFF, int(rng.integers(1 << 32)))[rng.integers(5)]
        return [(fat + 4 * cluster, struct.pack("<I", value))], size, \
            f"FAT entry {cluster} = {value:#x}"
    if op == 6:
        entry = root + 32 * int(rng.integers(0, 4))
        name, offset, fmt = [("size", 28, "<I"), ("cluster", 26, "<H"), ("attr", 11, "<B"),
                             ("name", 0, "<B")][rng.integers(4)]
        limit = 1 << (8 * struct.calcsize(fmt))
        value = (0, limit - 1, int(rng.integers(limit)))[rng.integers(3)]
        return [(entry + offset, struct.pack(fmt, value))], size, \
            f"directory entry at {entry}: {name} = {value}"
    junk = rng.integers(0, 256, size=SECTOR, dtype=np.uint8).tobytes()
    where = (facts["data"] + SECTOR * int(rng.integers(0, 64)))
    return [(where, junk)], size, f"log data sector at {where} replaced by noise"


def _attitude_case(rng, base_csv):
    header = b"t,roll_deg,pitch_deg,heading_deg\n"
    rows = base_csv.split(b"\n", 1)[1]
    options = [
        (None, "missing"), (b"", "empty"),
        (rng.integers(0, 256, size=3000, dtype=np.uint8).tobytes(), "binary"),
        (header, "header only"), (header + b"1,0,0,nan\n2,0,0,1\n", "NaN"),
        (header + b"1,0,0,10\n2,0,0,10\n", "times not overlapping"),
        (base_csv, "good"), (header + b"1,0,0,1e400\n2,0,0,1\n", "infinite"),
        (b"heading_deg,t,pitch_deg,roll_deg\n" + rows, "columns reordered (values not)"),
        (header + b"9" * 5000 + b",0,0,1\n", "5000 digits"),
        ("dir", "a folder"), (header + rows.replace(b",", b";"), "semicolons"),
        (header + rows[:len(rows) // 3], "cut short"),
    ]
    return options[rng.integers(len(options))]


def _known(log, full):
    """The inputs issue 10's own run found failing, one each: every run starts with them."""
    zda_day = lambda k, f: f[:2] + ["9999999999999999999"] + f[3:]
    cases = [
        ("log:field", "ZDA day of 19 digits", _rewrite(log, "zda", zda_day), []),
        ("log:field", "ZDA 9999-12-31 at the leap second",
         _rewrite(log, "zda", lambda k, f: [f[0], "235960.50", "31", "12", "9999"] + f[5:]), []),
        ("log:field", "GGA fix quality 2**63",
         _rewrite(log, "gga", lambda k, f: f[:6] + [str(2**63)] + f[7:]), []),
        ("log:field", "x axis of 309 digits",
         _rewrite(log, "pmag", _axes(lambda k, x, y, z: ("9" * 309, y, z))), []),
        ("log:values", "cesium all 0 nT",
         _rewrite(log, "cesium", lambda k, f: [" 00000.000", f[1]]), []),
        ("log:values", "samples identical",
         _rewrite(log, "pmag", _axes(lambda k, x, y, z: (2e4, 3e3, 4e4))), []),
        ("log:values", "two distinct vectors", _rewrite(log, "pmag", _axes(
            lambda k, x, y, z: (2e4, 3e3, 4e4) if k % 2 else (-9e3, 2.5e4, 3.5e4))), []),
        ("log:values", "z stuck at 99999.9, ellipsoid",
         _rewrite(full, "pmag", _axes(lambda k, x, y, z: (x, y, 99999.9))),
         ["--method", "ellipsoid"]),
        ("log:values", "all axes 0", _rewrite(log, "pmag", _axes(lambda k, x, y, z: (0., 0., 0.))),
         []),
        ("log:values", "sub-nT axes", _rewrite(log, "pmag", _axes(
            lambda k, x, y, z: tuple(f"{v * 1e-5:+.4f}" for v in (x, y, z)))), []),
        ("log:values", "IGRF in the year 3000",
         _rewrite(log, "zda", lambda k, f: f[:4] + ["3000"] + f[5:]), ["--ref", "igrf"]),
        ("log:values", "IGRF at 1e8 m",
         _rewrite(log, "gga", lambda k, f: f[:9] + ["100000000.0"] + f[10:]), ["--ref", "igrf"]),
        ("log:bytes", "one NUL in the first 64 KiB", log[:5000] + b"\x00" + log[5000:], []),
        ("option:ref", "--ref 5", log, ["--ref", "5"]),
        ("option:ref", "--ref 1e30", log, ["--ref", "1e30"]),
        ("option:ref", "--ref 1e308", log, ["--ref", "1e308"]),
    ]
    return cases


def make_case(index, seed, facts):
    """Input number ``index`` of the run seeded ``seed``: first the issue's own failing
    inputs (:func:`_known`), then classes cycling through :data:`CLASSES` (without an
    image the image class becomes a log class)."""
    rng = np.random.default_rng([seed, index])
    base = Path(facts["base"])
    known = _known((base / "uav.log").read_bytes(), (base / "full.log").read_bytes())
    if index < len(known):
        kind, detail, data, args = known[index]
        return Case(index, kind, detail, ["calibrate", "{work}/LOG00001.TXT", *args,
                                          "--out", "{work}/report"], {"LOG00001.TXT": data})
    kind = CLASSES[index % len(CLASSES)]
    if kind == "image" and facts.get("image") is None:
        kind = "log:bytes"
    base = Path(facts["base"])
    log = (base / "uav.log").read_bytes()
    card = "{work}/LOG00001.TXT"
    argv = ["calibrate", card]
    files, image, image_size = {}, None, None
    method = ("pso", "lm", "lm", "ellipsoid")[rng.integers(4)]
    if kind == "image":
        image, image_size, detail = _image_patches(facts["image"], rng)
        argv = ["calibrate", "{work}/card.img", "--method", "lm"]
    elif kind.startswith("log:"):
        if method == "ellipsoid":
            log = (base / "full.log").read_bytes()
        mutate = {"log:field": _mutate_field, "log:bytes": _mutate_bytes,
                  "log:lines": _mutate_lines, "log:values": _mutate_values}[kind]
        data, detail = mutate(log, rng)
        files["LOG00001.TXT"] = data
        ref = ("cesium", "cesium", "igrf", "50000")[rng.integers(4)]
        argv += ["--method", method, "--ref", ref]
        detail += f" (--method {method} --ref {ref})"
    else:
        files["LOG00001.TXT"] = log
        if kind == "option:ref":
            value = REFS[rng.integers(len(REFS))]
            argv += ["--ref", value, "--method", "lm"]
            detail = f"--ref {value!r}"
        elif kind == "option:seed":
            value = SEEDS[rng.integers(len(SEEDS))]
            argv += ["--seed", value]
            detail = f"--seed {value[:40]!r}"
        elif kind == "option:method":
            value = METHODS[rng.integers(len(METHODS))]
            argv += ["--method", value]
            detail = f"--method {value!r}"
        elif kind == "option:out":
            files["blocker"] = b"a file where a folder should be"
            outs = ["{work}/blocker", "{work}/blocker/sub", "/proc/maglog-report", "/proc",
                    "/dev/null", "", "{work}/" + "n" * 300, "{work}/a/b/c", "{work}/stale",
                    "{work}/with space", "."]
            value = outs[rng.integers(len(outs))]
            if value == "{work}/stale":
                files["stale/heading_error.png"] = b"an earlier run's plot"
                files["stale/mine.txt"] = b"the user's own file"
            argv += ["--method", "lm"]
            detail = f"--out {value[:60]!r}"
            return Case(index, kind, detail, argv + ["--out", value], files, out=value)
        elif kind == "option:attitude":
            content, what = _attitude_case(rng, (base / "attitude.csv").read_bytes())
            if content == "dir":
                files["attitude/keep"] = b""
            elif content is not None:
                files["attitude.csv"] = content
            target = "{work}/attitude" if content == "dir" else "{work}/attitude.csv"
            argv += ["--attitude", target, "--method", "lm"]
            detail = f"--attitude: {what}"
        else:
            choices = [("{work}/missing.img", "missing"), ("{work}", "a folder"),
                       ("{work}/empty.img", "empty"), ("/dev/null", "/dev/null"),
                       ("/proc/version", "/proc/version"), ("{base}/attitude.csv", "a CSV"),
                       ("{work}/zeros.img", "1 GiB of zeros (sparse)"),
                       ("{work}/LOG00001.TXT", "good log"), ("", "empty name")]
            path, detail = choices[rng.integers(len(choices))]
            files["empty.img"] = b""
            if path.endswith("zeros.img"):
                files["zeros.img"] = 1 << 30             # a sparse file of this size
            argv = ["calibrate", path, "--method", "lm"]
            detail = f"card: {detail}"
    return Case(index, kind, detail, argv + ["--out", "{work}/report"], files, image,
                image_size)


# --- running --------------------------------------------------------------------------------

class _Timeout(BaseException):
    """Raised by the alarm: not an Exception, so no handler in the code under test eats it."""


def _alarm(signum, frame):
    raise _Timeout()


def _worker_init():
    import numba
    numba.set_num_threads(1)              # one worker per core already
    signal.signal(signal.SIGALRM, _alarm)


def _materialise(case, work, base):
    for name, content in case.files.items():
        path = work / name
        path.parent.mkdir(parents=True, exist_ok=True)
        if isinstance(content, int):
            with open(path, "wb") as f:
                f.truncate(content)
        else:
            path.write_bytes(content)
    if case.image is not None:
        image = work / "card.img"
        size = case.image_size
        _sparse_copy(base / "card.img", image, size)
        with open(image, "r+b") as f:
            for offset, data in case.image:
                if offset < size:
                    f.seek(offset)
                    f.write(data[:size - offset])


def run_case(case, base, time_limit=TIME_LIMIT):
    """Run one input through ``maglog.cli.main.main`` in this process; its outcome."""
    from maglog.cli.main import main
    base = Path(base)
    work = Path(tempfile.mkdtemp(prefix=f"mutant{case.index}-"))
    here = os.getcwd()
    subst = lambda text: text.replace("{work}", str(work)).replace("{base}", str(base))
    argv = [subst(a) for a in case.argv]
    out, err = io.StringIO(), io.StringIO()
    result = {"index": case.index, "kind": case.kind, "detail": case.detail}
    start = time.perf_counter()
    try:
        _materialise(case, work, base)
        os.chdir(work)                    # a relative --out lands in the scratch folder
        signal.alarm(time_limit)
        try:
            with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
                status = main(argv)
        except SystemExit as exit_:
            status = exit_.code
        finally:
            signal.alarm(0)
        result.update(_classify(status, err.getvalue(), Path(subst(case.out))
                                if case.out else work, survey=case.kind.startswith("survey:")))
    except _Timeout:
        result.update(outcome="hang", reason=f"no answer within {time_limit} s")
    except Exception as error:           # what escaped main: the failure counted here
        frames = traceback.extract_tb(error.__traceback__)
        where = frames[-1] if frames else None
        at = f" at {Path(where.filename).name}:{where.lineno}" if where else ""
        result.update(outcome="traceback",
                      reason=f"{type(error).__name__}: {str(error)[:160]}{at}")
    finally:
        signal.alarm(0)
        os.chdir(here)
        shutil.rmtree(work, ignore_errors=True)
    result["seconds"] = round(time.perf_counter() - start, 3)
    return result


def _classify(status, err, out, survey=False):
    last = err.strip().splitlines()[-1] if err.strip() else ""
    if status == 1:
        if last.startswith("maglog: error: ") and "Traceback" not in err:
            return {"outcome": "error", "reason": last[len("maglog: error: "):][:200]}
        return {"outcome": "nonsense", "reason": f"exit 1 without a message: {last[:200]!r}"}
    if status == 2:
        return {"outcome": "usage", "reason": last[:200]}
    if status not in (0, None):
        return {"outcome": "nonsense", "reason": f"exit status {status!r}: {last[:160]!r}"}
    return _judge_survey(out) if survey else _judge_report(out)


def _judge_report(out):
    import html5lib

    def refuse(name):
        raise ValueError(f"{name} is not JSON")
    try:
        summary = json.loads((out / "parameters.json").read_text(), parse_constant=refuse)
    except (OSError, ValueError) as error:
        return {"outcome": "nonsense", "reason": f"parameters.json: {error}"[:200]}
    try:
        html5lib.HTMLParser(strict=True).parse((out / "report.html").read_bytes())
    except Exception as error:            # html5lib's ParseError, or the file missing
        return {"outcome": "nonsense", "reason": f"report.html: {error}"[:200]}
    if summary.get("method") == "ellipsoid":
        numbers = [summary.get("center_nT"), summary.get("W")]
    else:
        numbers = [summary.get("K"), summary.get("c")]
    finite = all(v is not None and np.all(np.isfinite(np.asarray(v, dtype=float)))
                 for v in numbers)
    before, after = summary.get("rms_before_nT"), summary.get("rms_after_nT")
    plausible = (finite and before is not None and after is not None and after < before
                 and after < PLAUSIBLE_RMS_NT and summary.get("success") is True)
    warnings = summary.get("warnings") or []
    if plausible and not warnings:
        return {"outcome": "ok", "reason": f"{after:.3g} nT RMS after"}
    if warnings:
        return {"outcome": "warned", "reason": warnings[0][:200]}
    return {"outcome": "nonsense", "reason": f"exit 0: finite {finite}, RMS {before} -> "
                                             f"{after} nT, success {summary.get('success')}, "
                                             "no warning"}


def run(count, *, seed=10, tools=None, processes=None, time_limit=TIME_LIMIT, progress=None,
        survey=0):
    """Generate and run ``count`` inputs of ``maglog calibrate`` and ``survey`` of ``maglog
    survey`` (numbered after them); the results (one dict per input) in input order.

    ``tools`` are the FAT tools (name -> path) the card images are built with: the tests
    pass the ``fat_tools`` fixture's; without them the card-image classes are left out."""
    with tempfile.TemporaryDirectory(prefix="maglog-mutants-") as folder:
        facts = make_base(folder, tools)
        facts["base"] = folder
        cases = [make_case(i, seed, facts) for i in range(count)]
        if survey:
            facts["survey"] = make_survey_base(folder)
            cases += [make_survey_case(count + j, seed, facts, j) for j in range(survey)]
        processes = processes or min(2, os.cpu_count() or 1)
        context = multiprocessing.get_context("spawn")
        results = []
        with context.Pool(processes, initializer=_worker_init) as pool:
            jobs = [pool.apply_async(run_case, (case, folder, time_limit)) for case in cases]
            for case, job in zip(cases, jobs):
                try:
                    result = job.get(timeout=time_limit + 60)
                except multiprocessing.TimeoutError:
                    result = {"index": case.index, "kind": case.kind, "detail": case.detail,
                              "outcome": "hang", "reason": "the worker did not answer"}
                results.append(result)
                if progress:
                    progress(result)
        return results, tools is not None


def is_survey(result):
    return result["kind"].startswith("survey:")


def counts(results):
    """Totals by outcome, and by class and outcome."""
    total = Counter(r["outcome"] for r in results)
    by_class = {}
    for r in results:
        by_class.setdefault(r["kind"], Counter())[r["outcome"]] += 1
    return ({o: total.get(o, 0) for o in OUTCOMES},
            {k: {o: c.get(o, 0) for o in OUTCOMES} for k, c in sorted(by_class.items())})


def failures(results):
    return [r for r in results if r["outcome"] in FAILURES]


# --- maglog survey --------------------------------------------------------------------------
#
# A short survey flight (the built-in ``survey`` scenario cut to four 200-m lines and two tie
# lines, as tests/calib/test_survey.py flies it) is built once per run; its log, truth.json
# and base.csv are the base material. Survey inputs are numbered after the calibrate ones and
# cycle through SURVEY_SCHEDULE: most end before the reduction (a truth, base station,
# option or address refused when read), a few go through it (about 10 s each).

SURVEY_CLASSES = ("survey:truth", "survey:base", "survey:option", "survey:card",
                  "survey:scheduler", "survey:log")
#: The order survey inputs take their classes in (a quarter are mutated logs, each a whole
#: reduction: about a second in a warm worker, against a hundredth for a refusal).
SURVEY_SCHEDULE = ("survey:truth", "survey:option", "survey:log", "survey:base",
                   "survey:truth", "survey:log", "survey:option", "survey:card",
                   "survey:scheduler", "survey:option", "survey:base", "survey:log")
#: A survey that exits 0 without a warning must have mapped the truth's anomaly to within
#: this RMS on the grid's nodes (the short flight gives 1.5 nT; the fuzz's --ridge 0 gave 31).
PLAUSIBLE_GRID_RMS_NT = 10.0
#: ... and an improvement ratio in this range (a compensation that removed the reading
#: itself gave 1.7e10).
PLAUSIBLE_IR = (1.5, 1000.0)


def make_survey_base(folder):
    """The short survey flight's log, truth and base station in ``folder/survey``; facts:
    the index of a cesium reading in the middle of the calibration box."""
    import tomllib
    from maglog.calib.logparse import parse_log
    from maglog.calib.survey import cesium_times
    from maglog.sim.stimulus.config import default_scenario_path, scenario_from_dict
    data = tomllib.loads(default_scenario_path().with_name("survey.toml").read_text())
    data["flight"]["survey"].update({"legs": 4, "leg_length_m": 200.0, "tie_lines": 2})
    stimulus = scenario_from_dict(data, source="short-survey.toml").build()
    target = Path(folder) / "survey"
    target.mkdir()
    stimulus.write_truth(target)
    log = b"".join(stimulus.system.recorded_frames())
    (target / "LOG00001.TXT").write_bytes(log)
    truth = json.loads((target / "truth.json").read_text())
    phase = next(p for p in truth["flight"]["phases"] if p["name"] == "calibration")
    day = truth["timestamp"][11:19]
    offset = sum(int(x) * f for x, f in zip(day.split(":"), (3600, 60, 1)))
    times = cesium_times(parse_log(log)).t
    box = np.flatnonzero((times > offset + phase["start_s"] + 5)
                         & (times < offset + phase["end_s"] - 5))
    return {"box_reading": int(box[len(box) // 2])}


def _cesium_values(log, edit):
    """The log with cesium reading ``k`` (nT) replaced by ``edit(k, value)``."""
    return _rewrite(log, "cesium", lambda k, f: [f" {edit(k, float(f[0])):09.3f}", f[1]])


def _swap_positions(log):
    def swap(k, f):
        if not (f[2] and f[4]):
            return f
        lat = float(f[2][:2]) + float(f[2][2:]) / 60
        lon = float(f[4][:3]) + float(f[4][3:]) / 60
        return f[:2] + [f"{int(lon):02d}{(lon - int(lon)) * 60:08.5f}", f[3],
                        f"{int(lat):03d}{(lat - int(lat)) * 60:08.5f}"] + f[5:]
    return _rewrite(log, "gga", swap)


def _shift_lines(truth, seconds):
    for line in truth["survey"]["lines"]:
        line["start_s"] += seconds
        line["end_s"] += seconds


def _survey_known(base, facts):
    """The survey findings of issue 23, one input each: every survey run starts with them
    (the first few, which end quickly, are the default suite's)."""
    folder = base / "survey"
    log = (folder / "LOG00001.TXT").read_bytes()
    truth = json.loads((folder / "truth.json").read_text())
    card = "{base}/survey/LOG00001.TXT"

    def truth_file(edit):
        value = json.loads(json.dumps(truth))
        edit(value)
        return json.dumps(value).encode()
    spike = facts["box_reading"]
    return [
        ("survey:truth", "truth.json with survey null",
         [card, "--truth", "{work}/truth.json"],
         {"truth.json": truth_file(lambda t: t.update(survey=None))}),
        ("survey:truth", "truth.json without origin", [card, "--truth", "{work}/truth.json"],
         {"truth.json": truth_file(lambda t: t["survey"].pop("origin"))}),
        ("survey:option", "--ridge 0", [card, "--ridge", "0"], {}),
        ("survey:scheduler", "--scheduler inproc://x", [card, "--scheduler", "inproc://x"],
         {}),
        ("survey:base", "--base /dev/null", [card, "--base", "/dev/null"], {}),
        ("survey:base", "--base a folder", [card, "--base", "{work}"], {}),
        ("survey:option", "--ridge -0", [card, "--ridge", "-0"], {}),
        ("survey:option", "--ridge 1e-300", [card, "--ridge", "1e-300"], {}),
        ("survey:option", "--band 4.9,5", [card, "--band", "4.9,5"], {}),
        ("survey:option", "--lag 5", [card, "--lag", "5"], {}),
        ("survey:option", "--lag 10", [card, "--lag", "10"], {}),
        ("survey:option", "--spacing 99999", [card, "--spacing", "99999"], {}),
        ("survey:truth", "a truth of another flight (lines 300 s later)",
         [card, "--truth", "{work}/truth.json"],
         {"truth.json": truth_file(lambda t: _shift_lines(t, 300.0))}),
        ("survey:log", "latitude and longitude swapped in every GGA",
         ["{work}/LOG00001.TXT"], {"LOG00001.TXT": _swap_positions(log)}),
        ("survey:log", "one cesium reading of 99,999.999 nT in the calibration box",
         ["{work}/LOG00001.TXT"],
         {"LOG00001.TXT": _cesium_values(log, lambda k, v: 99999.999 if k == spike else v)}),
        ("survey:log", "cesium stuck at 48,400.000 nT", ["{work}/LOG00001.TXT"],
         {"LOG00001.TXT": _cesium_values(log, lambda k, v: 48400.0)}),
    ]


#: Values a new user's truth.json holds where a number, list or table belongs.
WEIRD_JSON = (None, "", "47.3", [], {}, True, -1, 0, 1e308, -1e308, "NaN", [1, 2], {"a": 1},
              "x" * 5000, 10**30)
TRUTH_KEYS = (("survey",), ("survey", "origin"), ("survey", "origin", "lat_deg"),
              ("survey", "origin", "lon_deg"), ("survey", "origin", "ground_alt_m"),
              ("survey", "dipoles"), ("survey", "dipoles", 0), ("survey", "dipoles", 0,
                                                                "moment_ned_Am2"),
              ("survey", "dipoles", 0, "depth_m"), ("survey", "igrf_site_ned_nT"),
              ("survey", "diurnal"), ("survey", "diurnal", "pulsation_period_s"),
              ("survey", "lines"), ("survey", "lines", 0), ("survey", "lines", 0, "start_s"),
              ("survey", "lines", 0, "kind"), ("timestamp",), ("reference",),
              ("reference", "cesium_noise_nT"))


def _truth_case(truth, rng):
    op = int(rng.integers(8))
    if op < 4:                                   # one value replaced or removed
        keys = TRUTH_KEYS[rng.integers(len(TRUTH_KEYS))]
        value = json.loads(json.dumps(truth))
        parent = value
        for key in keys[:-1]:
            parent = parent[key]
        if rng.random() < 0.25:
            del parent[keys[-1]]
            return json.dumps(value).encode(), f"truth without {'.'.join(map(str, keys))}"
        weird = WEIRD_JSON[rng.integers(len(WEIRD_JSON))]
        parent[keys[-1]] = weird
        text = json.dumps(value)
        if weird == "NaN":
            text = text.replace('"NaN"', "NaN")
        return text.encode(), f"truth {'.'.join(map(str, keys))} = {str(weird)[:20]!r}"
    if op == 4:
        what = ("", "{", "[1, 2]", "null", '"survey"', "\xff\xfe", "{\"survey\": {}}",
                "{\"survey\": 1}", "[" * 100000)[rng.integers(9)]
        return what.encode("utf-8", "surrogateescape"), f"truth.json is {what[:20]!r}"
    if op == 5:
        value = json.loads(json.dumps(truth))
        seconds = float((-3600.0, -300.0, 300.0, 86400.0)[rng.integers(4)])
        _shift_lines(value, seconds)
        return json.dumps(value).encode(), f"the truth's lines {seconds:+g} s"
    if op == 6:
        value = json.loads(json.dumps(truth))
        stamp = ("2026-06-02T10:00:00+00:00", "2025-06-01T10:00:00+00:00",
                 "2026-06-01T10:00:00", "2026-06-01T10:00:00+05:00", "10:00")[rng.integers(5)]
        value["timestamp"] = stamp
        return json.dumps(value).encode(), f"the truth's timestamp {stamp!r}"
    value = json.loads(json.dumps(truth))
    shift = float((0.02, 0.5, 90.0, -180.0)[rng.integers(4)])
    value["survey"]["origin"]["lat_deg"] = max(-90.0, min(90.0, value["survey"]["origin"][
        "lat_deg"] + shift))
    return json.dumps(value).encode(), f"the truth's site {shift:+g} degrees north"


def _base_case(base_csv, rng):
    header, rows = base_csv.split(b"\n", 1)
    rows = rows.splitlines(keepends=True)
    options = [
        (None, "missing"), (b"", "empty"), (header + b"\n", "header only"),
        ("dir", "a folder"), ("/dev/null", "/dev/null"), ("/proc/version", "/proc/version"),
        (rng.integers(0, 256, size=4000, dtype=np.uint8).tobytes(), "binary"),
        (b"time,field\n" + b"".join(rows), "another header"),
        (header + b"\n" + b"".join(rows[::-1]), "rows reversed"),
        (header + b"\n" + b"".join(rows[:len(rows) // 3]), "cut short"),
        (header + b"\n" + b"".join(rows[len(rows) // 3:]), "starting late"),
        (header + b"\n" + b"".join(r.replace(b"Z,", b",") for r in rows), "no time zone"),
        (header + b"\n" + b"".join(r.replace(b",", b";") for r in rows), "semicolons"),
        (header + b"\n" + b"".join(r.replace(b"2026-06-01", b"2026-06-02") for r in rows),
         "another day"),
        (header + b"\n" + b"".join(rows[:200] + rows[260:]), "a 60-s gap"),
        (header + b"\n" + b"".join(rows[:100]) + b"2026-06-01T10:00:40.000Z,nan\n"
         + b"".join(rows[100:]), "a NaN row"),
        (header + b"\n" + b"".join(r.split(b",")[0] + b",1e400\n" for r in rows), "inf"),
        (header + b"\n" + b"".join(r.split(b",")[0] + b",48000.0\n" for r in rows), "constant"),
        (header + b"\n" + b"".join(r.split(b",")[0] + b",4.8e-5\n" for r in rows), "in tesla"),
        (header + b"\n" + b"9" * 5000 + b",48000\n", "5000 digits"),
        (base_csv, "good"),
    ]
    return options[rng.integers(len(options))]


SURVEY_OPTIONS = {
    "--ridge": ("0", "-0", "1e-300", "1e-7", "1e-6", "1", "1e6", "2e6", "inf", "nan", "auto",
                "AUTO", "", "x", "-1"),
    "--band": ("4.9,5", "0.1,0.5", "0.01,0.02", "1,4", "0.05,4.5", "0.5,0.1", "0,1", "1,1",
               "nan,1", "0.1", "0.1,0.2,0.3", "1e-300,1", "0.2,999", "-1,1", ""),
    "--lag": ("5", "10", "-10", "10.0001", "0.25", "1.5", "-1.5", "nan", "inf", "", "x",
              "1e-300", "0"),
    "--box": ("10:00:20-10:00:25", "00:00:00-23:59:59", "10:01:00-10:00:00", "25:00:00-26:00:00",
              "10:00:15-10:01:40", "x", "10:00-10:01", "10:00:20.5-10:01:44.9"),
    "--spacing": ("0", "-5", "0.001", "99999", "100", "40", "10", "1e5", "nan", "x"),
    "--grid": ("spline", "eqs", "kriging", ""),
    "--level": ("0", "1", "2", "-1", "x"),
    "--terms": ("16", "18", "17", "0", "x"),
    "--max-base-gap": ("0", "0.001", "1e9", "86400", "nan", "-1", "x"),
    "--seed": ("-1", "0", str(2**128), "x", "1.5"),
    "--workers": ("0", "1", "257", "x"),
    "--seeds": ("1-2", "4-1", "x", "1,2", "0-99999"),
    "--scenario": ("nosuch", "{work}", "{base}/survey/truth.json"),
}

SCHEDULERS = ("inproc://x", "tcp://127.0.0.1:1", "tcp://127.0.0.1", "tcp://:8786", "x",
              "", "tcp://127.0.0.1:99999", "http://127.0.0.1:8786", "ucx://127.0.0.1:8786",
              "tcp://nonexistent.invalid:8786", "tcp://[::1]:1", "tcp://127.0.0.1:0",
              "tcp://127.0.0.1:-1", "127.0.0.1:1", "tcp://" + "h" * 300 + ":1",
              "tcp://127.0.0.1:1/x")


def make_survey_case(index, seed, facts, number):
    """Survey input ``number`` (counted from 0 among the survey inputs) of the run seeded
    ``seed``, numbered ``index`` in the whole run."""
    base = Path(facts["base"])
    if "survey_known" not in facts:
        facts["survey_known"] = _survey_known(base, facts["survey"])
        folder = base / "survey"
        facts["survey_files"] = {name: (folder / name).read_bytes()
                                 for name in ("LOG00001.TXT", "truth.json", "base.csv")}
    known = facts["survey_known"]
    out = ["-o", "{work}/out"]
    if number < len(known):
        kind, detail, argv, files = known[number]
        return Case(index, kind, detail, ["survey", *argv, *out], files, out="{work}/out")
    rng = np.random.default_rng([seed, index, 23])
    kind = SURVEY_SCHEDULE[number % len(SURVEY_SCHEDULE)]
    original = facts["survey_files"]
    card = "{base}/survey/LOG00001.TXT"
    files, argv = {}, [card]
    if kind == "survey:truth":
        truth = json.loads(original["truth.json"])
        files["truth.json"], detail = _truth_case(truth, rng)
        argv += ["--truth", "{work}/truth.json", "--no-deinterf"]
    elif kind == "survey:base":
        content, what = _base_case(original["base.csv"], rng)
        target = "{work}/base.csv"
        if content == "dir":
            files["base.csv/keep"] = b""
        elif isinstance(content, str):
            target = content
        elif content is not None:
            files["base.csv"] = content
        argv += ["--base", target, "--no-deinterf"]
        detail = f"--base: {what}"
    elif kind == "survey:option":
        name = sorted(SURVEY_OPTIONS)[rng.integers(len(SURVEY_OPTIONS))]
        values = SURVEY_OPTIONS[name]
        value = values[rng.integers(len(values))]
        argv += [name, value, "--no-deinterf"]
        detail = f"{name} {value[:40]!r}"
        if name in ("--seeds", "--scenario"):
            argv = ["--scenario", value if name == "--scenario" else "nosuch",
                    *(["--seeds", value] if name == "--seeds" else [])]
    elif kind == "survey:scheduler":
        value = SCHEDULERS[rng.integers(len(SCHEDULERS))]
        argv += ["--scheduler", value]
        detail = f"--scheduler {value[:40]!r}"
    elif kind == "survey:card":
        choices = [("{work}/missing.img", "missing"), ("{work}", "a folder"),
                   ("{work}/empty.img", "empty"), ("/dev/null", "/dev/null"),
                   ("/proc/version", "/proc/version"), ("{base}/survey/base.csv", "a CSV"),
                   ("{base}/survey/truth.json", "the truth"), ("{base}/uav.log",
                                                                "a calibration log"),
                   ("{work}/zeros.img", "1 GiB of zeros (sparse)"), ("", "empty name")]
        path, what = choices[rng.integers(len(choices))]
        files["empty.img"] = b""
        if path.endswith("zeros.img"):
            files["zeros.img"] = 1 << 30
        argv = [path, "--no-deinterf"]
        detail = f"card: {what}"
    else:
        mutate = (_mutate_field, _mutate_bytes, _mutate_lines, _mutate_values)[
            rng.integers(4)]
        files["LOG00001.TXT"], detail = mutate(original["LOG00001.TXT"], rng)
        files["truth.json"] = original["truth.json"]
        files["base.csv"] = original["base.csv"]
        argv = ["{work}/LOG00001.TXT", "--no-deinterf"]
    return Case(index, kind, detail, ["survey", *argv, *out], files, out="{work}/out")


def _judge_survey(out):
    """An exit 0 of ``maglog survey``: strict JSON and valid HTML, finite figures, and a
    plausible result (against the truth, when there was one) or warnings saying why not."""
    import html5lib

    def refuse(name):
        raise ValueError(f"{name} is not JSON")
    try:
        figures = json.loads((out / "survey.json").read_text(), parse_constant=refuse)
    except (OSError, ValueError) as error:
        return {"outcome": "nonsense", "reason": f"survey.json: {error}"[:200]}
    try:
        html5lib.HTMLParser(strict=True).parse((out / "report.html").read_bytes())
    except Exception as error:            # html5lib's ParseError, or the file missing
        return {"outcome": "nonsense", "reason": f"report.html: {error}"[:200]}
    ours = next((v for k, v in figures.get("compensation", {}).items()
                 if k.startswith("maglog TL")), {})
    ratio = ours.get("improvement_ratio")
    peak = figures.get("peak", {}).get("amplitude_nT")
    rms = figures.get("truth", {}).get("grid_rms_nT")
    warnings = figures.get("warnings") or []
    plausible = (ratio is not None and PLAUSIBLE_IR[0] <= ratio <= PLAUSIBLE_IR[1]
                 and peak is not None and math.isfinite(peak)
                 and (rms is None or rms < PLAUSIBLE_GRID_RMS_NT))
    if warnings:
        return {"outcome": "warned", "reason": warnings[0][:200]}
    if plausible:
        return {"outcome": "ok", "reason": f"IR {ratio:.3g}, grid {rms} nT off the truth"}
    return {"outcome": "nonsense", "reason": f"exit 0: IR {ratio}, peak {peak} nT, grid "
                                             f"{rms} nT RMS off the truth, no warning"}
