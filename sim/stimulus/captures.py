"""Real GPS receiver captures, read from the shared data folder (never copied into the project).

The captures live in ``<data>/nmea/*.log``, where ``<data>`` is ``shared/data`` beside the
repository (``<repo>/../shared/data``) or the folder named by the ``MAGLOG_SHARED_DATA``
environment variable. Each file starts with ``#`` header lines (capture metadata); everything
after them is the receiver's byte stream, byte-exact (CR LF or bare LF, binary protocol
bytes, truncated sentences and ``#`` comment lines inside the stream included).
"""

from __future__ import annotations

import os
from pathlib import Path

__all__ = ["DATA_ENV_VAR", "shared_data_dir", "capture_files", "load_capture"]

#: Environment variable naming the shared data folder (overrides the location beside the repo).
DATA_ENV_VAR = "MAGLOG_SHARED_DATA"
_CAPTURE_SUBDIR = "nmea"
_CAPTURE_GLOB = "*.log"
_HEADER_MARK = b"#"
_LINE_END = b"\n"
#: This module is sim/stimulus/captures.py: the repository root is two levels up.
_REPO_ROOT = Path(__file__).resolve().parents[2]          # sim/stimulus/captures.py


def shared_data_dir() -> Path | None:
    """The shared data folder, or None when it does not exist."""
    override = os.environ.get(DATA_ENV_VAR)
    candidate = Path(override) if override else _REPO_ROOT.parent / "shared" / "data"
    return candidate if candidate.is_dir() else None


def capture_files() -> list[Path]:
    """The capture files, sorted by path; empty when the data folder is absent."""
    data = shared_data_dir()
    if data is None:
        return []
    return sorted((data / _CAPTURE_SUBDIR).glob(_CAPTURE_GLOB))


def load_capture(path: str | os.PathLike[str]) -> bytes:
    """The byte stream of a capture: the file without its leading ``#`` lines."""
    raw = Path(path).read_bytes()
    position = 0
    while raw.startswith(_HEADER_MARK, position):
        line_end = raw.find(_LINE_END, position)
        if line_end < 0:
            return b""  # the whole file is header
        position = line_end + len(_LINE_END)
    return raw[position:]
