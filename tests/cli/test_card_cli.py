"""``maglog card ls`` and ``maglog card extract``, judged by mtools; and ``calibrate`` and
``survey`` given a run's folder.

The judged images are made by dosfstools and mtools (``mkfs.fat``, ``mcopy -m``, ``mmd``,
``mattrib``), or by the logger's own FAT32 writer (tests/cli/flights.py); what ``ls`` lists
is compared with ``mdir`` and ``mattrib``, what ``extract`` copies with ``mcopy``. Without
the tools the judged tests skip, and fail under CI=true (the ``external`` fixture:
scripts/setup.sh installs mtools and dosfstools). Corruptions are byte patches at offsets
computed here from the BPB, not by the reader under test.
"""

import errno
import json
import os
import re
import struct
import subprocess
from datetime import datetime
from pathlib import Path

import pytest

from flights import write_card
from maglog.cli.main import main

SECTOR = 512
PART_LBA = 2048                     # 1 MiB, as SD cards are formatted
FS_KIB = 64 * 1024                  # with one-sector clusters a legal FAT32 (> 65,524 clusters)
MTIME = datetime(2024, 6, 15, 13, 37, 42)
#: The files of the judged card: card path -> bytes (a long name, a subfolder, a file of
#: many clusters, an empty file).
FILES = {
    "LOG00001.TXT": b"$PMAG1,00001,+01234.5,-00012.0,+40000.1*00\r\n" * 300,
    "LOG00002.TXT": bytes(range(256)) * 9 + b"\xff" * 7,
    "NOTES.MD": b"",
    "Long name here.txt": b"a long name\n",
    "DATA/BIG.BIN": os.urandom(123_457),
    "DATA/SUB/DEEP.TXT": b"deep\n",
}
TOOLS = ("mkfs.fat", "mcopy", "mmd", "mdir", "mattrib")


def _mtools_env():
    return dict(os.environ, MTOOLS_SKIP_CHECK="1")


def _run(*args, **kw):
    return subprocess.run([str(a) for a in args], capture_output=True, text=True, check=True,
                          env=_mtools_env(), timeout=60, **kw).stdout


def _partition_offset(image):
    """Byte offset of the first MBR partition, read here (not by the reader under test)."""
    with open(image, "rb") as f:
        sector = f.read(SECTOR)
    lba, = struct.unpack_from("<I", sector, 0x1BE + 8)
    return lba * SECTOR


@pytest.fixture(scope="module")
def tools(external):
    return external.tools(*TOOLS, why="mtools judges what maglog card lists and extracts")


@pytest.fixture(scope="module")
def judged_card(tools, tmp_path_factory):
    """A card image (an MBR, FAT32 at 1 MiB by mkfs.fat) filled by mtools with FILES; the
    logs read-only and hidden, LOG00001.TXT with a known time."""
    folder = tmp_path_factory.mktemp("judged")
    image = folder / "card.img"
    with open(image, "wb") as f:
        f.truncate((PART_LBA + FS_KIB * 2) * SECTOR)
        f.seek(0x1BE)
        f.write(struct.pack("<B3sB3sII", 0, b"\0\0\0", 0x0C, b"\0\0\0", PART_LBA, FS_KIB * 2))
        f.seek(510)
        f.write(b"\x55\xaa")
    _run(tools["mkfs.fat"], "-F", "32", "-s", "1", "-n", "JUDGED", "-i", "1234ABCD",
         "--offset", PART_LBA, "-h", PART_LBA, image, FS_KIB)
    drive = f"{image}@@{PART_LBA * SECTOR}"
    _run(tools["mmd"], "-i", drive, "::/DATA", "::/DATA/SUB")
    sources = folder / "sources"
    sources.mkdir()
    for k, (name, data) in enumerate(FILES.items()):
        source = sources / str(k)
        source.write_bytes(data)
        os.utime(source, (MTIME.timestamp(), MTIME.timestamp()))
        _run(tools["mcopy"], "-m", "-i", drive, source, f"::/{name}")
    _run(tools["mattrib"], "-i", drive, "+r", "+h", "::/LOG00002.TXT")
    return image


def _mdir(tools, image, folder="/"):
    """mdir's entries of ``folder`` as {short name: (size or None, "YYYY-MM-DD HH:MM")},
    and its total bytes."""
    text = _run(tools["mdir"], "-a", "-i", f"{image}@@{_partition_offset(image)}",
                f"::{folder}")
    entries = {}
    for line in text.splitlines():
        match = re.match(r"^(\S.{7}) (.{3}) +(\d+|<DIR>) +(\d{4}-\d\d-\d\d) +(\d\d:\d\d)", line)
        if match and match[1].strip() not in (".", ".."):
            name = match[1].strip() + ("." + match[2].strip() if match[2].strip() else "")
            entries[name] = (None if match[3] == "<DIR>" else int(match[3]),
                             f"{match[4]} {match[5]}")
    total = re.search(r"files +([\d ]+) bytes", text)
    return entries, int(total[1].replace(" ", ""))


def _mattrib(tools, image, path):
    """The attribute letters mattrib shows for ``path`` (R, H, S, A)."""
    line = _run(tools["mattrib"], "-i", f"{image}@@{_partition_offset(image)}", f"::/{path}")
    return set(line.split("::")[0].replace(" ", ""))


def _cli(argv, capsys):
    """``maglog`` in process: (exit status, stdout, stderr)."""
    try:
        status = main(argv)
    except SystemExit as exit_:
        status = exit_.code
    captured = capsys.readouterr()
    return status, captured.out, captured.err


def _one_line_error(status, err, *fragments):
    assert status in (1, 2), err
    assert err.startswith("maglog") and err.count("\n") == 1 and "Traceback" not in err, err
    for fragment in fragments:
        assert fragment in err, err


# -- ls ----------------------------------------------------------------------------------

@pytest.mark.parametrize("folder", ["/", "/DATA", "data/sub"])
def test_ls_lists_what_mdir_lists(judged_card, tools, folder, capsys):
    status, out, err = _cli(["card", "ls", str(judged_card), folder, "--json"], capsys)
    assert status == 0, err
    listing = json.loads(out)
    expected, total = _mdir(tools, judged_card, "/" + folder.strip("/").upper())
    ours = {e["name"]: (e["size"], e["modified"][:16].replace("T", " "))
            for e in listing["entries"]}
    assert ours == expected
    assert listing["total"]["bytes"] == total
    assert listing["volume"] == {"partition": 1, "partition_type": 0x0C,
                                 "offset": PART_LBA * SECTOR, "label": "JUDGED",
                                 "id": 0x1234ABCD, "cluster_size": 512,
                                 "clusters": listing["volume"]["clusters"], "clean": True}
    for entry in listing["entries"]:
        path = f"{folder.strip('/')}/{entry['name']}".lstrip("/")
        assert set(entry["attributes"]) - {"D", "-"} == _mattrib(tools, judged_card, path), path


def test_ls_table_and_total(judged_card, capsys):
    status, out, err = _cli(["card", "ls", str(judged_card)], capsys)
    assert status == 0, err
    lines = out.splitlines()
    assert re.fullmatch(re.escape(f"{judged_card}: FAT32 volume JUDGED (id 1234-ABCD) in "
                                  f"partition 1 (type 0x0C) at byte {PART_LBA * SECTOR}, ")
                        + r"\d+ clusters of 512 bytes", lines[0]), lines[0]
    assert lines[1].split() == ["name", "size", "modified", "attributes"]
    rows = {line.split()[0]: line.split()[1:] for line in lines[3:-1]}
    assert rows["LOG00001.TXT"] == [str(len(FILES["LOG00001.TXT"])), "2024-06-15",
                                    "13:37:42", "A"]
    assert rows["LOG00002.TXT"][-1] == "RHA"
    assert rows["DATA"][0] == "<DIR>" and rows["DATA"][-1] == "D"
    assert "LONGNA~1.TXT" in rows                      # the 8.3 name, as stored
    root_bytes = sum(len(d) for n, d in FILES.items() if "/" not in n)
    assert lines[-1] == f"4 files, {root_bytes} bytes; 1 folder"


def test_ls_of_a_bare_partition_and_of_the_firmware_card(tools, tmp_path, capsys):
    bare = tmp_path / "part.img"
    with open(bare, "wb") as f:
        f.truncate(FS_KIB * 1024)
    _run(tools["mkfs.fat"], "-F", "32", "-s", "1", bare)
    (tmp_path / "x").write_bytes(b"x" * 1000)
    _run(tools["mcopy"], "-i", bare, tmp_path / "x", "::/LOG00007.TXT")
    status, out, err = _cli(["card", "ls", str(bare)], capsys)
    assert status == 0, err
    assert "in a bare partition image at byte 0" in out
    assert out.splitlines()[-1] == "1 file, 1000 bytes"
    (tmp_path / "run").mkdir()
    card = write_card(tmp_path / "run" / "card.img", b"$ 48000.000,0001\r\n" * 50)
    # A run's folder stands for its card.img.
    status, out, err = _cli(["card", "ls", str(tmp_path / "run")], capsys)
    assert status == 0, err
    assert out.startswith(f"{card}: FAT32 volume")
    assert out.splitlines()[-1] == "1 file, 900 bytes"


# -- extract -----------------------------------------------------------------------------

def _mcopy_tree(tools, image, dest):
    """Every file of the card copied out by mcopy, each to its 8.3 path under ``dest``
    (the list of files from mdir's listing, not from maglog)."""
    drive = f"{image}@@{_partition_offset(image)}"
    files, folders = [], [""]
    while folders:
        folder = folders.pop()
        entries, _ = _mdir(tools, image, "/" + folder)
        for name, (size, _when) in entries.items():
            path = f"{folder}/{name}".lstrip("/")
            (folders if size is None else files).append(path)
    for path in files:
        target = dest / path
        target.parent.mkdir(parents=True, exist_ok=True)
        _run(tools["mcopy"], "-n", "-i", drive, f"::/{path}", target)
    return sorted(files)


def _tree(folder):
    return {p.relative_to(folder).as_posix(): p.read_bytes()
            for p in sorted(folder.rglob("*")) if p.is_file()}


def test_extract_all_matches_mcopy_byte_for_byte(judged_card, tools, tmp_path, capsys):
    theirs = tmp_path / "mcopy"
    files = _mcopy_tree(tools, judged_card, theirs)
    assert len(files) == len(FILES)
    status, out, err = _cli(["card", "extract", str(judged_card), "--all",
                             "-o", str(tmp_path / "ours")], capsys)
    assert status == 0, err
    assert _tree(tmp_path / "ours") == _tree(theirs)
    assert _tree(theirs)["DATA/BIG.BIN"] == FILES["DATA/BIG.BIN"]
    assert out.splitlines()[-1] == (f"{len(FILES)} files, {sum(map(len, FILES.values()))} "
                                    f"bytes, extracted to {tmp_path / 'ours'}")


def test_extract_takes_the_logs_by_default(judged_card, tmp_path, capsys):
    out_dir = tmp_path / "logs"
    status, out, err = _cli(["card", "extract", str(judged_card), "-o", str(out_dir)], capsys)
    assert status == 0, err
    assert _tree(out_dir) == {"LOG00001.TXT": FILES["LOG00001.TXT"],
                              "LOG00002.TXT": FILES["LOG00002.TXT"]}
    assert out.splitlines()[0] == (f"LOG00001.TXT  {len(FILES['LOG00001.TXT'])} bytes -> "
                                   f"{out_dir / 'LOG00001.TXT'}")


def test_extract_named_files_in_any_case(judged_card, tmp_path, capsys):
    status, out, err = _cli(["card", "extract", str(judged_card), "data/big.bin",
                             "Log00002.txt", "LOG00002.TXT", "-o", str(tmp_path)], capsys)
    assert status == 0, err
    assert _tree(tmp_path) == {"DATA/BIG.BIN": FILES["DATA/BIG.BIN"],
                               "LOG00002.TXT": FILES["LOG00002.TXT"]}


def test_extract_of_the_firmware_card_matches_mcopy(tools, tmp_path, capsys):
    data = b"".join(b"$PMAG1,%05d,+00001.0,+00002.0,+00003.0*00\r\n" % k for k in range(3000))
    (tmp_path / "run").mkdir()
    card = write_card(tmp_path / "run" / "card.img", data)
    status, out, err = _cli(["card", "extract", str(tmp_path / "run"), "-o",
                             str(tmp_path / "logs")], capsys)
    assert status == 0, err
    theirs = tmp_path / "theirs.txt"
    _run(tools["mcopy"], "-n", "-i", f"{card}@@{_partition_offset(card)}", "::/LOG00001.TXT",
         theirs)
    assert (tmp_path / "logs" / "LOG00001.TXT").read_bytes() == theirs.read_bytes() == data


def test_extract_writes_with_the_users_umask(judged_card, tmp_path, capsys):
    previous = os.umask(0o027)
    try:
        status, _, err = _cli(["card", "extract", str(judged_card), "-o",
                               str(tmp_path / "x")], capsys)
    finally:
        os.umask(previous)
    assert status == 0, err
    assert (tmp_path / "x" / "LOG00001.TXT").stat().st_mode & 0o777 == 0o640


def test_extract_refuses_to_overwrite_without_force(judged_card, tmp_path, capsys):
    (tmp_path / "LOG00002.TXT").write_bytes(b"mine")
    status, _, err = _cli(["card", "extract", str(judged_card), "-o", str(tmp_path)], capsys)
    _one_line_error(status, err, "LOG00002.TXT: exists", "--force")
    # Nothing was written: not even the first log, which did not exist.
    assert sorted(p.name for p in tmp_path.iterdir()) == ["LOG00002.TXT"]
    assert (tmp_path / "LOG00002.TXT").read_bytes() == b"mine"
    status, _, err = _cli(["card", "extract", str(judged_card), "-o", str(tmp_path),
                           "--force"], capsys)
    assert status == 0, err
    assert (tmp_path / "LOG00002.TXT").read_bytes() == FILES["LOG00002.TXT"]


@pytest.mark.parametrize("argv, fragments", [
    (["NOPE.TXT"], ["NOPE.TXT: no such file on the card", "maglog card ls"]),
    (["DATA/NOPE.BIN"], ["DATA/NOPE.BIN: no such file on the card"]),
    (["LOG00001.TXT/X"], ["no such file on the card"]),
    (["DATA"], ["DATA: is a folder on the card", "--all"]),
    (["LOG00001.TXT", "--all"], ["give file names or --all, not both"]),
])
def test_extract_errors_are_one_line_and_write_nothing(judged_card, tmp_path, capsys, argv,
                                                       fragments):
    out_dir = tmp_path / "out"
    status, out, err = _cli(["card", "extract", str(judged_card), *argv, "-o", str(out_dir)],
                            capsys)
    _one_line_error(status, err, *fragments)
    assert out == "" and not out_dir.exists()


def _bpb(image, offset):
    """FAT geometry read here from the BPB: (bytes per sector, sectors per cluster, reserved
    sectors, FATs, sectors per FAT, root cluster)."""
    with open(image, "rb") as f:
        f.seek(offset)
        sector = f.read(SECTOR)
    bps, spc, reserved, nfats = struct.unpack_from("<HBHB", sector, 11)
    fat_size, = struct.unpack_from("<I", sector, 36)
    root, = struct.unpack_from("<I", sector, 44)
    return bps, spc, reserved, nfats, fat_size, root


def _break_chain(image, name83):
    """Mark the second cluster of file ``name83``'s chain free in every FAT (root folder)."""
    offset = _partition_offset(image)
    bps, spc, reserved, nfats, fat_size, root = _bpb(image, offset)
    data = offset + (reserved + nfats * fat_size) * bps
    with open(image, "r+b") as f:
        f.seek(data + (root - 2) * spc * bps)
        folder = f.read(spc * bps)
        at = next(k for k in range(0, len(folder), 32) if folder[k:k + 11] == name83)
        hi, = struct.unpack_from("<H", folder, at + 20)
        lo, = struct.unpack_from("<H", folder, at + 26)
        first = hi << 16 | lo
        f.seek(offset + reserved * bps + 4 * first)
        second, = struct.unpack("<I", f.read(4))
        for fat in range(nfats):
            f.seek(offset + (reserved + fat * fat_size) * bps + 4 * (second & 0x0FFFFFFF))
            f.write(struct.pack("<I", 0))


def test_a_broken_chain_stops_extract_before_anything_is_written(judged_card, tmp_path,
                                                                  capsys):
    image = tmp_path / "card.img"
    with open(judged_card, "rb") as src, open(image, "wb") as dst:
        dst.write(src.read())
    _break_chain(image, b"LOG00002TXT")
    out_dir = tmp_path / "out"
    status, _, err = _cli(["card", "extract", str(image), "-o", str(out_dir)], capsys)
    _one_line_error(status, err, str(image), "LOG00002.TXT", "marked free")
    assert not out_dir.exists()          # LOG00001.TXT, before it, was not written either
    status, _, err = _cli(["card", "extract", str(image), "LOG00001.TXT", "-o",
                           str(out_dir)], capsys)
    assert status == 0, err


def test_a_write_refused_midway_leaves_no_partial_file(judged_card, tmp_path, capsys,
                                                       monkeypatch):
    from maglog.cli import card as cli_card
    replace = os.replace
    calls = []

    def full_disk(src, dst):
        calls.append(dst)
        if len(calls) == 2:
            raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC), str(src))
        replace(src, dst)

    monkeypatch.setattr(cli_card.os, "replace", full_disk)
    status, _, err = _cli(["card", "extract", str(judged_card), "-o", str(tmp_path)], capsys)
    _one_line_error(status, err, "no space left on the device",
                    f"(1 of 2 files already written to {tmp_path})")
    assert _tree(tmp_path) == {"LOG00001.TXT": FILES["LOG00001.TXT"]}
    assert [p.name for p in tmp_path.iterdir()] == ["LOG00001.TXT"]


@pytest.mark.parametrize("command", ["ls", "extract"])
def test_images_that_are_not_fat32_are_one_line_errors(tools, tmp_path, capsys, command,
                                                       judged_card):
    fat16 = tmp_path / "fat16.img"
    with open(fat16, "wb") as f:
        f.truncate(32 << 20)
    _run(tools["mkfs.fat"], "-F", "16", fat16)
    truncated = tmp_path / "truncated.img"
    with open(judged_card, "rb") as src, open(truncated, "wb") as dst:
        dst.write(src.read((PART_LBA + 4096) * SECTOR))
    (tmp_path / "empty.img").write_bytes(b"")
    (tmp_path / "LOG00001.TXT").write_bytes(FILES["LOG00001.TXT"])
    (tmp_path / "folder").mkdir()
    cases = {
        fat16: "not FAT32",
        truncated: "image is truncated",
        tmp_path / "empty.img": "shorter than one 512-byte sector",
        tmp_path / "LOG00001.TXT": "not a card or partition image",
        tmp_path / "none.img": "none.img: no such file",
        tmp_path / "folder": f"is a folder without a card.img (looked for "
                             f"{tmp_path / 'folder' / 'card.img'}",
    }
    for image, fragment in cases.items():
        out_dir = tmp_path / "out"
        argv = ["card", command, str(image)] + (["-o", str(out_dir)] if command == "extract"
                                                else [])
        status, out, err = _cli(argv, capsys)
        _one_line_error(status, err, fragment)
        assert out == "" and not out_dir.exists(), image


def test_extract_into_a_file_is_refused(judged_card, tmp_path, capsys):
    blocker = tmp_path / "file"
    blocker.write_text("")
    status, _, err = _cli(["card", "extract", str(judged_card), "-o", str(blocker)], capsys)
    _one_line_error(status, err, f"{blocker}: exists and is not a folder")


# -- calibrate and survey given a run's folder ------------------------------------------

@pytest.fixture(scope="module")
def run_folder(tmp_path_factory):
    """A run's folder as maglog run leaves it: card.img (the firmware's writer) and
    attitude.csv beside it."""
    from maglog.sim.stimulus.scenario import make_flight
    folder = tmp_path_factory.mktemp("run")
    flight = make_flight(coverage="uav", seconds=60, seed=5)
    write_card(folder / "card.img", flight.log())
    (folder / "attitude.csv").write_bytes(flight.attitude_csv())
    return folder


def test_calibrate_takes_a_run_folder_and_its_attitude(run_folder, tmp_path, capsys):
    status, out, err = _cli(["calibrate", str(run_folder), "--method", "lm", "--out",
                             str(tmp_path / "a")], capsys)
    assert status == 0, err
    assert out.splitlines()[0] == f"attitude: {run_folder / 'attitude.csv'} (beside the card)"
    assert "heading error vs attitude" in out
    assert f"reading {run_folder / 'card.img'}" in err
    # --no-attitude leaves it out; --attitude names another.
    status, out, err = _cli(["calibrate", str(run_folder / "card.img"), "--method", "lm",
                             "--no-attitude", "--out", str(tmp_path / "b")], capsys)
    assert status == 0, err
    assert not out.startswith("attitude:") and "heading error vs attitude" not in out
    other = tmp_path / "other.csv"
    other.write_bytes((run_folder / "attitude.csv").read_bytes())
    status, out, err = _cli(["calibrate", str(run_folder), "--method", "lm", "--attitude",
                             str(other), "--out", str(tmp_path / "c")], capsys)
    assert status == 0, err
    assert "beside the card" not in out and "heading error vs attitude" in out
    status, _, err = _cli(["calibrate", str(run_folder), "--attitude", str(other),
                           "--no-attitude"], capsys)
    _one_line_error(status, err, "not allowed with argument")


def test_calibrate_a_folder_without_a_card(tmp_path, capsys):
    (tmp_path / "LOG00001.TXT").write_bytes(b"$ 48000.000,0001\r\n")
    status, _, err = _cli(["calibrate", str(tmp_path), "--out", str(tmp_path / "r")], capsys)
    _one_line_error(status, err, f"{tmp_path}: is a folder without a card.img",
                    str(tmp_path / "card.img"))
    assert not (tmp_path / "r").exists()


def test_survey_takes_a_run_folder(run_folder, tmp_path, capsys, monkeypatch):
    import maglog.calib.batch as batch
    seen = []
    monkeypatch.setattr(batch, "run_batch", lambda jobs, **kw: seen.extend(jobs) or [])
    (run_folder / "base.csv").write_text("time_utc,total_nT\n")
    try:
        status, _, err = _cli(["survey", str(run_folder), "-o", str(tmp_path / "p")], capsys)
    finally:
        (run_folder / "base.csv").unlink()
    assert status == 0, err
    assert [job["card"] for job in seen] == [str((run_folder / "card.img").resolve())]
    assert seen[0]["options"]["base_station"] == str((run_folder / "base.csv").resolve())
    # Two run folders: each job named after its folder.
    seen.clear()
    status, _, err = _cli(["survey", str(run_folder), str(run_folder / "card.img"), "-o",
                           str(tmp_path / "q")], capsys)
    assert status == 0, err
    assert [job["name"] for job in seen] == [f"1-{run_folder.name}", f"2-{run_folder.name}"]
    status, _, err = _cli(["survey", str(tmp_path / "p"), "-o", str(tmp_path / "q")], capsys)
    _one_line_error(status, err, "is a folder without a card.img")
