"""Files written whole or not at all, with the mode the user's umask gives.

A report, a survey's products and a run's HTML page are written under temporary names
beside their final ones and moved into place (``os.replace``) when every one is written,
so a failure leaves the earlier files as they were. The temporary files are created the
way ``open(path, "w")`` creates a file (mode 0o666 masked by the umask): what the user
gets is what their umask says, never the 0600 of :func:`tempfile.mkstemp`.

``stage(staged, final)`` makes a temporary file beside ``final`` and records it in the
dict ``staged``; ``commit(staged)`` moves every one into place; ``discard(staged)`` removes
what was not moved (call it in a ``finally``). ``write_text(path, text)`` does all three
for one file.
"""

import os
import secrets
from pathlib import Path


__all__ = ["stage", "commit", "discard", "write_text", "umask", "default_mode"]

#: Tries at a free temporary name before giving up (each name has 64 random bits).
_TRIES = 16


def umask():
    """The process's umask (read without changing it where the OS allows)."""
    try:
        with open("/proc/self/status", encoding="ascii") as status:
            for line in status:
                if line.startswith("Umask:"):
                    return int(line.split()[1], 8)
    except (OSError, ValueError, IndexError):
        pass
    mask = os.umask(0o022)
    os.umask(mask)
    return mask


def default_mode():
    """The mode ``open(path, "w")`` gives a new file: 0o666 less the umask."""
    return 0o666 & ~umask()


def stage(staged, final):
    """A new, empty temporary file beside ``final`` (same folder, a hidden name), created
    with the mode a plain ``open()`` would give; recorded in ``staged`` (final → temporary
    path) and returned. OSError when the folder refuses."""
    final = Path(final)
    for _ in range(_TRIES):
        temp = final.parent / f".{final.name}.{secrets.token_hex(8)}.tmp"
        try:
            fd = os.open(temp, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o666)
        except FileExistsError:
            continue
        os.close(fd)
        staged[final] = temp
        return temp
    raise FileExistsError(f"{final.parent}: no free temporary name for {final.name}")


def commit(staged):
    """Move every staged file over its final name (each move is atomic)."""
    for final, temp in list(staged.items()):
        os.replace(temp, final)
        del staged[final]


def discard(staged):
    """Remove the staged temporary files that were not moved into place."""
    for temp in staged.values():
        try:
            Path(temp).unlink(missing_ok=True)
        except OSError:
            pass
    staged.clear()


def write_text(path, text, encoding="utf-8"):
    """Write ``text`` to ``path`` whole or not at all (the user's umask decides the mode);
    returns the path."""
    path = Path(path)
    staged = {}
    try:
        stage(staged, path).write_text(text, encoding=encoding)
        commit(staged)
    finally:
        discard(staged)
    return path
