"""Tests for maglog.sim.stimulus.captures, and every real GPS capture through the reference filter.

The captures are read from the shared data folder beside the repository; when it is absent
the capture tests end through the ``external`` fixture: a skip with the reason on a
developer's machine, a failure under CI=true.
"""

from __future__ import annotations

import functools
import operator
import re
from pathlib import Path

import pytest

from maglog.sim.stimulus import captures
from maglog.sim.stimulus.captures import DATA_ENV_VAR, capture_files, load_capture, shared_data_dir
from maglog.sim.reference import COUNTER_NAMES, Kind, reference_filter

MAX_FRAME = 128

#: A whole kept NMEA frame, from DESIGN.md: no "$" inside, printable ASCII, *hh, line end.
KEEPABLE = re.compile(rb"\$[A-Z]{2}(?:GGA|ZDA|VTG),[\x20-\x23\x25-\x7e]*\*(?P<hh>[0-9A-Fa-f]{2})\r?\n")
FLUSHING_GGA = re.compile(rb"\$[A-Z]{2}GGA,(?:[^,*]*,){5}[1-9][,*]")


def keepable_frames(stream: bytes) -> list[bytes]:
    """The frames the rules keep, found independently: every regex match with a good
    checksum and length (each "$" starts a frame, so matches cannot hide inside others)."""
    kept = []
    for match in KEEPABLE.finditer(stream):
        frame = match.group()
        body = frame[1 : frame.rindex(b"*")]
        if len(frame) <= MAX_FRAME and functools.reduce(operator.xor, body, 0) == int(match["hh"], 16):
            kept.append(frame)
    return kept


# --- the loader ---------------------------------------------------------------------------


def test_load_capture_strips_only_the_leading_header(tmp_path: Path) -> None:
    raw = b"# Name: test\r\n#\n# more\n$GPGGA,1*00\r\n# inside the stream\n\x00\xff$GPZDA*00"
    path = tmp_path / "a.log"
    path.write_bytes(raw)
    assert load_capture(path) == b"$GPGGA,1*00\r\n# inside the stream\n\x00\xff$GPZDA*00"
    assert load_capture(str(path)) == load_capture(path)


@pytest.mark.parametrize(
    ("raw", "stream"),
    [
        (b"", b""),
        (b"$GPZDA*00\n", b"$GPZDA*00\n"),
        (b"# only a header\n", b""),
        (b"# only a header, no line end", b""),
        (b"#\n\n$A\n", b"\n$A\n"),
        (b" # not a header\n", b" # not a header\n"),
    ],
)
def test_load_capture_edge_cases(tmp_path: Path, raw: bytes, stream: bytes) -> None:
    path = tmp_path / "b.log"
    path.write_bytes(raw)
    assert load_capture(path) == stream


def test_shared_data_dir_env_override(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    (tmp_path / "nmea").mkdir()
    for name in ("b.log", "a.log", "notes.txt"):
        (tmp_path / "nmea" / name).write_bytes(b"#\n$X\n")
    monkeypatch.setenv(DATA_ENV_VAR, str(tmp_path))
    assert shared_data_dir() == tmp_path
    assert capture_files() == [tmp_path / "nmea" / "a.log", tmp_path / "nmea" / "b.log"]
    monkeypatch.setenv(DATA_ENV_VAR, str(tmp_path / "missing"))
    assert shared_data_dir() is None
    assert capture_files() == []


def test_default_location_is_beside_the_repository(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.delenv(DATA_ENV_VAR, raising=False)
    repo = Path(__file__).resolve().parents[2]          # tests/sim/ is two levels down
    expected = repo.parent / "shared" / "data"
    assert shared_data_dir() == (expected if expected.is_dir() else None)


# --- the captures through the reference ---------------------------------------------------


def test_captures_present(external) -> None:
    captures = external.captures()
    assert all(path.suffix == ".log" for path in captures)
    assert captures == sorted(captures)


#: One test per capture; without any, one test that ends through ``external.captures()``.
@pytest.mark.parametrize("path", capture_files() or [None],
                         ids=lambda p: p.name if p else "no-data")
def test_capture_through_reference(path: Path | None, external) -> None:
    if path is None:
        external.captures()
        pytest.fail("capture_files() found no captures, external.captures() found some")
    raw = path.read_bytes()
    stream = load_capture(path)
    assert raw.endswith(stream) and not stream.startswith(b"#")
    result = reference_filter(Kind.NMEA, stream, max_frame=MAX_FRAME)
    assert set(result.counters) == set(COUNTER_NAMES)
    # Every "$" starts exactly one frame, counted once (the last one may still be open).
    assert sum(result.counters.values()) in (stream.count(b"$"), stream.count(b"$") - 1)
    # Exactly the frames an independent whole-frame check finds, verbatim and in order.
    assert result.frames == keepable_frames(stream)
    assert result.flushes == [i for i, f in enumerate(result.frames) if FLUSHING_GGA.match(f)]
    # Plausibility: a receiver's output always holds sentences the logger drops.
    assert result.counters["not_whitelisted"] > 0
    assert result.counters["uart_error"] == 0 and result.counters["overflow"] == 0


def test_known_captures(external) -> None:
    def run(name: str):
        return reference_filter(Kind.NMEA, load_capture(external.capture(name)),
                                max_frame=MAX_FRAME)

    navika = run("navika-100-fix.log")  # has a fix: every GGA flushes
    ggas = [f for f in navika.frames if f[3:6] == b"GGA"]
    assert ggas and len(navika.flushes) == len(ggas)
    skytraq = run("skytraq.log")  # cold start, no fix: GGA kept, never a flush
    assert any(f[3:6] == b"GGA" for f in skytraq.frames) and skytraq.flushes == []
    hemi = run("hemi.log")  # no fix at first, a fix later
    ggas = [i for i, f in enumerate(hemi.frames) if f[3:6] == b"GGA"]
    assert 0 < len(hemi.flushes) < len(ggas) and hemi.flushes[0] > ggas[0]
    binary = run("ac12_binary.log")  # binary protocol bytes inside the stream
    assert binary.counters["bad_byte"] > 0 and binary.counters["kept"] > 0
