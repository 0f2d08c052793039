"""``maglog card ls`` and ``maglog card extract``: the files of a card image, listed or copied
out byte for byte; and :func:`card_of`, the card a ``CARD`` argument of ``calibrate`` and
``survey`` names (a run's folder stands for its ``card.img``).

The image is read by :mod:`maglog.calib.card` (an MBR and its first FAT32 partition, or a
bare partition image); nothing here parses FAT. ``extract`` checks every file it will copy
(its cluster chain and that its clusters lie inside the image) before it writes any, and
writes each one to a temporary name in the target folder that is renamed when complete: a
corrupt card or a refused write leaves no partial file behind.
"""

import json
import os
from pathlib import Path, PurePosixPath

__all__ = ["card_of", "register", "RUN_CARD"]

#: The card image in a run's output folder (``maglog run -o DIR``, ``maglog simulate -o
#: DIR/card.img``).
RUN_CARD = "card.img"
#: Attribute letters in the order ``ls`` prints them (``DIR_Attr`` bits).
_ATTR_LETTERS = (("READ_ONLY", "R"), ("HIDDEN", "H"), ("SYSTEM", "S"), ("DIRECTORY", "D"),
                 ("ARCHIVE", "A"))


def card_of(text):
    """The card image or log a ``CARD`` argument names: the file itself, or a run's folder's
    ``card.img``. Raises :class:`CliError` (one line) when there is neither."""
    from .main import CliError
    path = Path(text)
    if path.is_dir():
        card = path / RUN_CARD
        if not card.is_file():
            raise CliError(f"{path}: is a folder without a {RUN_CARD} (looked for {card}, as "
                           f"maglog run -o and maglog simulate -o leave it)")
        return card
    if not path.exists():
        raise CliError(f"{path}: no such file")
    return path


def _open(image):
    from ..calib.card import CardError, open_card
    from .main import CliError
    try:
        return open_card(image)
    except CardError as error:
        raise CliError(_located(error, image)) from None


def _located(error, image):
    """A reader's message, with the image named once."""
    message = str(error)
    return message if message.startswith(str(image)) else f"{image}: {message}"


def _attributes(attr):
    from ..calib.card import Attr
    return "".join(letter for name, letter in _ATTR_LETTERS if attr & Attr[name]) or "-"


def _volume_line(image, volume):
    boot = volume.boot
    where = (f"partition {volume.partition_index + 1} (type 0x{volume.partition_type:02X})"
             if volume.partition_index is not None else "a bare partition image")
    label = f" {boot.volume_label}" if boot.volume_label else ""
    serial = (f" (id {boot.volume_id >> 16:04X}-{boot.volume_id & 0xFFFF:04X})"
              if boot.volume_id is not None else "")
    return (f"{image}: FAT32 volume{label}{serial} in {where} at byte "
            f"{volume.partition_offset}, {boot.cluster_count} clusters of "
            f"{boot.cluster_size} bytes")


def _cmd_ls(args):
    from ..calib.card import CardError
    from .main import CliError, _table
    image = card_of(args.image)
    with _open(image) as volume:
        try:
            entries = volume.listdir(args.folder)
        except CardError as error:
            raise CliError(_located(error, image)) from None
        warnings = list(volume.warnings)
        header = _volume_line(image, volume)
        boot = volume.boot
        volume_info = {
            "partition": (None if volume.partition_index is None
                          else volume.partition_index + 1),
            "partition_type": volume.partition_type, "offset": volume.partition_offset,
            "label": boot.volume_label, "id": boot.volume_id,
            "cluster_size": boot.cluster_size, "clusters": boot.cluster_count,
            "clean": volume.clean_shutdown}
    folder = "/" + "/".join(p for p in args.folder.replace("\\", "/").split("/") if p)
    files = [e for e in entries if not e.is_dir]
    folders = [e for e in entries if e.is_dir]
    total = sum(e.size for e in files)
    if args.json:
        record = {
            "image": str(image), "volume": volume_info, "folder": folder,
            "entries": [{"name": e.name, "size": None if e.is_dir else e.size,
                         "modified": e.mtime.isoformat() if e.mtime else None,
                         "attributes": _attributes(e.attributes), "folder": e.is_dir}
                        for e in entries],
            "total": {"files": len(files), "folders": len(folders), "bytes": total},
            "warnings": warnings}
        print(json.dumps(record, indent=1))
        return
    print(header)
    if folder != "/":
        print(f"folder {folder}")
    if entries:
        print(_table(["name", "size", "modified", "attributes"],
                     [[e.name, "<DIR>" if e.is_dir else e.size,
                       e.mtime.strftime("%Y-%m-%d %H:%M:%S") if e.mtime else "-",
                       _attributes(e.attributes)] for e in entries]))
    line = f"{len(files)} file{'s' * (len(files) != 1)}, {total} bytes"
    if folders:
        line += f"; {len(folders)} folder{'s' * (len(folders) != 1)}"
    print(line)
    for warning in warnings:
        print(f"warning: {warning}")


def _host_path(card_path, image):
    """The relative path a file of the card is written to: its card path, refused when a
    part could leave the target folder or name no file here (a corrupt directory entry)."""
    from .main import CliError
    parts = card_path.split("/")
    for part in parts:
        if part in ("", ".", "..") or "\0" in part or os.sep in part:
            raise CliError(f"{image}: the card's entry {card_path!r} cannot be a file name "
                           f"here (a corrupt directory entry?)")
    return PurePosixPath(*parts)


def _chosen(args, volume, image):
    """``[(card path, entry)]`` to extract, every one checked readable."""
    from ..calib.card import CardError, CardFileNotFoundError
    from .main import CliError
    try:
        if args.all:
            chosen = [(path, e) for path, e in volume.walk() if not e.is_dir]
            if not chosen:
                raise CliError(f"{image}: the card holds no files")
        elif args.names:
            chosen, seen = [], set()
            for name in args.names:
                parts = [p for p in name.replace("\\", "/").split("/") if p]
                try:
                    entry = volume.stat(name) if parts else None
                except CardFileNotFoundError:
                    entry = None
                if entry is None:
                    raise CliError(f"{name}: no such file on the card {image} (maglog card ls "
                                   f"{image} lists them)")
                if entry.is_dir:
                    raise CliError(f"{name}: is a folder on the card; name its files "
                                   f"({name.rstrip('/')}/FILE) or give --all")
                path = "/".join([p.upper() for p in parts[:-1]] + [entry.name])
                if path not in seen:
                    seen.add(path)
                    chosen.append((path, entry))
        else:
            names = volume.log_files()
            if not names:
                others = sum(1 for e in volume.listdir("/") if not e.is_dir)
                raise CliError(f"{image}: no LOG*.TXT in the card's root ({others} other "
                               f"file{'s' * (others != 1)}); name files or give --all")
            chosen = [(name, volume.stat(name)) for name in names]
        for path, _entry in chosen:
            volume.check(path)
    except CardError as error:
        raise CliError(_located(error, image)) from None
    return chosen


def _write_new(target, data):
    """``data`` into ``target`` through a temporary name beside it (renamed when written)."""
    temporary = target.with_name(f".{target.name}.maglog-{os.getpid()}.part")
    try:
        with open(temporary, "xb") as f:
            f.write(data)
        os.replace(temporary, target)
    except BaseException:
        temporary.unlink(missing_ok=True)
        raise


def _cmd_extract(args):
    from ..calib.card import CardError
    from .main import CliError, _os_message, _out_dir
    if args.all and args.names:
        raise CliError("give file names or --all, not both")
    image = card_of(args.image)
    out = Path(args.output)
    if out.exists() and not out.is_dir():
        raise CliError(f"{out}: exists and is not a folder (give -o a folder)")
    with _open(image) as volume:
        chosen = _chosen(args, volume, image)
        targets = [(path, entry, out / _host_path(path, image)) for path, entry in chosen]
        for path, _entry, target in targets:
            if target.is_dir():
                raise CliError(f"{target}: is a folder; {path} cannot be written there")
            if (target.exists() or target.is_symlink()) and not args.force:
                raise CliError(f"{target}: exists; extracting replaces it (give --force to "
                               f"do so)")
        _out_dir(out)
        written = 0
        for k, (path, entry, target) in enumerate(targets):
            try:
                data = volume.read(path)
                target.parent.mkdir(parents=True, exist_ok=True)
                _write_new(target, data)
            except CardError as error:
                raise CliError(_located(error, image)
                               + _so_far(k, len(targets), out)) from None
            except OSError as error:
                # The target's name, not the temporary one the system may name.
                error = OSError(error.errno, error.strerror)
                raise CliError(f"cannot write {_os_message(error, target)}"
                               + _so_far(k, len(targets), out)) from None
            written += len(data)
            print(f"{path}  {len(data)} bytes -> {target}")
        warnings = list(volume.warnings)
    print(f"{len(targets)} file{'s' * (len(targets) != 1)}, {written} bytes, extracted to "
          f"{out}")
    for warning in warnings:
        print(f"warning: {warning}")


def _so_far(done, total, out):
    return f" ({done} of {total} files already written to {out})" if done else ""


def register(card_commands):
    """Add ``maglog card ls`` and ``maglog card extract`` to ``maglog card``'s commands."""
    ls = card_commands.add_parser(
        "ls", help="list the files of a card image's FAT32 volume: name, size, date and "
                   "time, attributes")
    ls.add_argument("image", metavar="IMAGE",
                    help="raw card image (with an MBR), FAT32 partition image, or a run's "
                         f"folder (its {RUN_CARD})")
    ls.add_argument("folder", nargs="?", default="/", metavar="FOLDER",
                    help="folder on the card to list (default: the root)")
    ls.add_argument("--json", action="store_true",
                    help="print the listing as JSON (sizes in bytes, times ISO 8601, no time "
                         "zone: FAT keeps none)")
    ls.set_defaults(func=_cmd_ls)

    extract = card_commands.add_parser(
        "extract", help="copy files out of a card image, byte for byte (default: every "
                        "LOG*.TXT of its root)")
    extract.add_argument("image", metavar="IMAGE",
                         help="raw card image (with an MBR), FAT32 partition image, or a "
                              f"run's folder (its {RUN_CARD})")
    extract.add_argument("names", nargs="*", metavar="NAME",
                         help="files to copy (case does not matter; FOLDER/NAME below the "
                              "root; default: every LOG*.TXT of the root)")
    extract.add_argument("-o", "--output", required=True, metavar="DIR",
                         help="folder to copy into (made if missing); files below the root "
                              "keep their folders")
    extract.add_argument("--all", action="store_true",
                         help="every file on the card, its folders recreated under DIR")
    extract.add_argument("--force", action="store_true",
                         help="replace files that exist in DIR")
    extract.set_defaults(func=_cmd_extract)
