"""Tests for maglog.sim.reference: one case per rule of docs/frame-rules.md, then seeded
random streams checked against a literal byte-by-byte reading of the rules page and against
independent whole-frame regular expressions.
"""

from __future__ import annotations

import datetime as dt
import functools
import operator
import re
from collections.abc import Iterable

import numpy as np
import pytest

from maglog.sim.reference import COUNTER_NAMES, FilterResult, Kind, ReferenceFilter, reference_filter
from maglog.sim.stimulus.sentences import cesium, gga, gsa, gsv, nmea_checksum, nmea_sentence, pmag1, rmc, vtg, zda
from maglog.sim.stimulus.streams import demo_streams
from maglog.sim.stimulus.uart_line import RxEvent

COUNTERS = set(COUNTER_NAMES)
ZDA = zda(dt.datetime(2024, 6, 1, 10, 0, 1))
VTG = vtg(90.0, 29.2)
GGA = gga(36_000.0, 47.5, 8.5)
PMAG = pmag1(1, 20_000.0, -3_000.0, 45_000.0)
CESIUM = cesium(49_895.131, 1249)


def run(kind: Kind, stream: bytes | Iterable[object], **kwargs: int) -> FilterResult:
    result = reference_filter(kind, stream, **kwargs)
    assert set(result.counters) == COUNTERS
    assert result.counters["overflow"] == 0
    return result


def dropped(result: FilterResult) -> dict[str, int]:
    """The non-zero drop counters."""
    return {name: count for name, count in result.counters.items() if count and name != "kept"}


def assert_outcome(
    kind: Kind,
    stream: bytes | Iterable[object],
    kept: list[bytes],
    drops: dict[str, int] | None = None,
    **kw: int,
) -> FilterResult:
    result = run(kind, stream, **kw)
    assert result.frames == kept
    assert result.counters["kept"] == len(kept)
    assert dropped(result) == (drops or {})
    return result


def with_length(sentence_name: str, length: int, eol: bytes = b"\r\n") -> bytes:
    """A valid NMEA sentence of exactly ``length`` bytes (padding in a free field)."""
    overhead = len(nmea_sentence(sentence_name + ",", eol=eol))
    frame = nmea_sentence(sentence_name + "," + "1" * (length - overhead), eol=eol)
    assert len(frame) == length
    return frame


# --- frames -------------------------------------------------------------------------------


@pytest.mark.parametrize("kind", list(Kind))
@pytest.mark.parametrize("empty", [b"$\r\n", b"$\n"])
def test_empty_frame(kind: Kind, empty: bytes) -> None:
    assert_outcome(kind, empty, [], {"not_whitelisted": 1})


def test_bytes_outside_frames_are_ignored() -> None:
    assert_outcome(Kind.NMEA, b"garbage\r\n\x00\xff\r\r*12\n" + ZDA + b"tail\n", [ZDA])


@pytest.mark.parametrize("max_frame", [128, 82, 200])
def test_max_length_kept_and_one_more_overlong(max_frame: int) -> None:
    exact = with_length("GPGGA", max_frame)
    assert_outcome(Kind.NMEA, exact, [exact], max_frame=max_frame)
    assert_outcome(Kind.NMEA, with_length("GPGGA", max_frame + 1), [], {"overlong": 1}, max_frame=max_frame)
    # The bare-LF form of a CR LF frame one byte too long fits.
    bare = with_length("GPVTG", max_frame, eol=b"\n")
    assert_outcome(Kind.NMEA, bare, [bare], max_frame=max_frame)
    # Overlong at the LF itself: rule 5 comes before rule 6.
    at_lf = with_length("GPZDA", max_frame + 1, eol=b"\n")
    assert_outcome(Kind.NMEA, at_lf, [], {"overlong": 1}, max_frame=max_frame)


def test_max_length_pmag() -> None:
    body = "PMAG1," + "0" * (128 - 12)
    exact = nmea_sentence(body)
    assert len(exact) == 128
    assert_outcome(Kind.PMAG, exact, [exact])
    assert_outcome(Kind.PMAG, nmea_sentence(body + "0"), [], {"overlong": 1})


def test_overlong_frame_is_abandoned_until_next_dollar() -> None:
    # After the overlong drop the rest of the long line (a non-printable byte included) is
    # outside any frame and counts nothing.
    long = with_length("GPGGA", 140)
    stream = long[:-10] + b"\x01" + long[-10:] + ZDA
    assert_outcome(Kind.NMEA, stream, [ZDA], {"overlong": 1})


@pytest.mark.parametrize(("kind", "max_frame"), [(Kind.NMEA, 128), (Kind.PMAG, 60)])
def test_overlong_decided_at_the_first_byte_too_many(kind: Kind, max_frame: int) -> None:
    name, good = ("GPGGA", ZDA) if kind is Kind.NMEA else ("PMAG1", PMAG)
    long = with_length(name, max_frame + 20)
    # max_frame bytes then "$": still within the limit, so rule 2 drops it.
    assert_outcome(kind, long[:max_frame] + good, [good], {"bad_byte": 1}, max_frame=max_frame)
    # One byte more and the frame is already overlong when the "$" or an error arrives.
    assert_outcome(kind, long[: max_frame + 1] + good, [good], {"overlong": 1}, max_frame=max_frame)
    events = [(b, False) for b in long[: max_frame + 1]] + [(0, True)]
    assert_outcome(kind, events, [], {"overlong": 1}, max_frame=max_frame)
    # A CR as the last allowed byte is fine; the LF after it is one too many.
    assert_outcome(kind, long[: max_frame - 1] + b"\r\n", [], {"overlong": 1}, max_frame=max_frame)


def test_back_to_back_frames() -> None:
    stream = GGA + ZDA + VTG + GGA
    result = assert_outcome(Kind.NMEA, stream, [GGA, ZDA, VTG, GGA])
    assert result.flushes == [0, 3]
    assert_outcome(Kind.PMAG, PMAG * 5, [PMAG] * 5)
    assert_outcome(Kind.CESIUM, CESIUM * 5, [CESIUM] * 5)


@pytest.mark.parametrize(("kind", "frame"), [(Kind.NMEA, ZDA), (Kind.PMAG, PMAG), (Kind.CESIUM, CESIUM)])
def test_stray_dollar_mid_frame(kind: Kind, frame: bytes) -> None:
    for cut in (1, 4, 9, len(frame) - 2, len(frame) - 1):
        assert_outcome(kind, frame[:cut] + frame, [frame], {"bad_byte": 1})


def test_dollar_right_after_a_drop_starts_a_frame() -> None:
    assert_outcome(Kind.NMEA, b"$GPRMC,1" + ZDA, [ZDA], {"not_whitelisted": 1})


@pytest.mark.parametrize(("kind", "frame"), [(Kind.NMEA, VTG), (Kind.PMAG, PMAG), (Kind.CESIUM, CESIUM)])
def test_cr_without_lf(kind: Kind, frame: bytes) -> None:
    bare = frame[:-2]
    assert_outcome(kind, bare + b"\rX\n" + frame, [frame], {"bad_byte": 1})
    assert_outcome(kind, bare + b"\r\r\n" + frame, [frame], {"bad_byte": 1})
    # The byte after the CR decides even where the position check would also fail.
    assert_outcome(kind, frame[:3] + b"\r" + frame[4:] + frame, [frame], {"bad_byte": 1})


@pytest.mark.parametrize(("kind", "frame"), [(Kind.NMEA, VTG), (Kind.PMAG, PMAG), (Kind.CESIUM, CESIUM)])
def test_cr_then_dollar(kind: Kind, frame: bytes) -> None:
    assert_outcome(kind, frame[:-1] + frame, [frame], {"bad_byte": 1})


@pytest.mark.parametrize("byte", [0x00, 0x09, 0x1B, 0x7F, 0x80, 0xA4, 0xFF])
@pytest.mark.parametrize(("kind", "frame"), [(Kind.NMEA, ZDA), (Kind.PMAG, PMAG), (Kind.CESIUM, CESIUM)])
def test_non_printable_byte(kind: Kind, frame: bytes, byte: int) -> None:
    for at in (1, 5, 8, len(frame) - 2):
        assert_outcome(kind, frame[:at] + bytes([byte]) + frame[at:] + frame, [frame], {"bad_byte": 1})


def test_non_printable_beats_position_check() -> None:
    # Rule 4 before rule 8 at the same byte.
    assert_outcome(Kind.NMEA, b"$GP\x00GA,*00\r\n", [], {"bad_byte": 1})


def test_first_offending_byte_decides() -> None:
    # Position 4 fails the whitelist ("GZ" starts no allowed name); the later bytes are ignored.
    assert_outcome(Kind.NMEA, b"$GPGZ\x00A,\r\r*00\r\n", [], {"not_whitelisted": 1})
    assert_outcome(Kind.NMEA, b"$GPZGA,*00\r\n", [], {"not_whitelisted": 1})
    assert_outcome(Kind.NMEA, b"$GPZD\x00", [], {"bad_byte": 1})
    assert_outcome(Kind.CESIUM, b"$ 4A\x00", [], {"not_whitelisted": 1})


def test_bad_checksum() -> None:
    body = ZDA[1 : ZDA.index(b"*")].decode()
    good = int(ZDA[-4:-2], 16)
    for wrong in (good ^ 1, good ^ 0x80, (good + 1) % 256):
        assert_outcome(Kind.NMEA, nmea_sentence(body, checksum=wrong), [], {"checksum": 1})
    pmag_body = PMAG[1 : PMAG.index(b"*")].decode()
    wrong = nmea_sentence(pmag_body, checksum=int(PMAG[-4:-2], 16) ^ 2)
    assert_outcome(Kind.PMAG, wrong, [], {"checksum": 1})


def test_lower_case_hex_accepted() -> None:
    bodies = (f"GPZDA,{n:06d}.00,01,06,2024,00,00" for n in range(1000))
    body = next(b for b in bodies if re.search(r"[A-F]", f"{nmea_checksum(b):02X}"))
    upper = nmea_sentence(body)
    lower = upper[:-4] + upper[-4:-2].lower() + b"\r\n"
    assert lower != upper
    assert_outcome(Kind.NMEA, lower, [lower])


@pytest.mark.parametrize(
    "ending",
    [b"", b"*", b"*6", b"*6G", b"*G6", b"*6C0", b"6C", b"*6C ", b" *6C"],
)
def test_missing_or_malformed_checksum(ending: bytes) -> None:
    frame = b"$GPZDA,183531.00,23,12,2007,00,00" + ending + b"\r\n"
    assert_outcome(Kind.NMEA, frame, [], {"checksum": 1})
    # The final "*" counts: an earlier "*" is part of the checked bytes.
    starred = nmea_sentence("GPZDA,1*2")
    assert_outcome(Kind.NMEA, starred, [starred])


@pytest.mark.parametrize(
    "frame",
    [
        nmea_sentence("GPRMC,1"),
        nmea_sentence("GPGSA,A,3"),
        nmea_sentence("gpGGA,1"),
        nmea_sentence("G1GGA,1"),
        nmea_sentence("GPGGAX,1"),
        nmea_sentence("GPGGA;1"),
        nmea_sentence("GPGGA*1"),
        nmea_sentence("PGRMZ,1"),
        nmea_sentence("GPGG,1,1"),
        nmea_sentence("GPVTA,1"),
        b"!AIVDM,1,1,,B,13aGhtw0R<OJf=6LgQ?Ad1FF05`L,0*24\r\n$GPXTE,1*00\r\n",
    ],
)
def test_not_whitelisted(frame: bytes) -> None:
    assert_outcome(Kind.NMEA, frame + ZDA, [ZDA], {"not_whitelisted": 1})


def test_any_talker_kept() -> None:
    frames = [gga(0, 1, 2, talker=t) for t in ("GP", "GN", "GL", "GA", "BD", "ZZ")]
    assert_outcome(Kind.NMEA, b"".join(frames), frames)


@pytest.mark.parametrize(
    "frame", [b"$GPGG\r\n", b"$GPGGA\r\n", b"$GPGGA,\r\n", b"$GPGGA,*4\n", b"$PMAG1,*\r\n", b"$GP\n"]
)
def test_cut_short_header(frame: bytes) -> None:
    kind = Kind.PMAG if frame.startswith(b"$PMAG") else Kind.NMEA
    assert_outcome(kind, frame, [], {"not_whitelisted": 1})


def test_shortest_body_kept() -> None:
    for frame in (nmea_sentence("GPZDA,"), nmea_sentence("PMAG1,")):
        assert len(frame) == 1 + 9 + 2
        assert_outcome(Kind.PMAG if b"PMAG" in frame else Kind.NMEA, frame, [frame])


def test_error_flag_inside_a_frame() -> None:
    events = [(b, False) for b in ZDA[:10]] + [(ord("0"), True)] + [(b, False) for b in ZDA[10:]] + list(VTG)
    assert_outcome(Kind.NMEA, events, [VTG], {"uart_error": 1})
    # An error-flagged byte right before the LF.
    events = [(b, False) for b in ZDA[:-1]] + [(ord("\n"), True)]
    assert_outcome(Kind.NMEA, events, [], {"uart_error": 1})
    # An error-flagged "$" inside a frame is an error, not a new frame.
    events = [(b, False) for b in ZDA[:10]] + [(ord("$"), True)] + [(b, False) for b in ZDA[10:]]
    assert_outcome(Kind.NMEA, events, [], {"uart_error": 1})


def test_error_flag_outside_a_frame() -> None:
    events = [RxEvent(0, True), *(RxEvent(b) for b in ZDA), RxEvent(0x55, True), RxEvent(ord("$"), True)]
    events += [RxEvent(b) for b in b"GPVTG,*00\r\n"] + [RxEvent(b) for b in VTG]
    assert_outcome(Kind.NMEA, events, [ZDA, VTG])


@pytest.mark.parametrize(("kind", "frame"), [(Kind.NMEA, ZDA), (Kind.PMAG, PMAG), (Kind.CESIUM, CESIUM)])
def test_bare_lf_endings(kind: Kind, frame: bytes) -> None:
    bare = frame[:-2] + b"\n"
    assert_outcome(kind, bare + frame + bare, [bare, frame, bare])


def test_pmag_rules() -> None:
    assert_outcome(Kind.PMAG, b"$PMAG2,00001*00\r\n" + PMAG, [PMAG], {"not_whitelisted": 1})
    assert_outcome(Kind.PMAG, b"$PMAG1*00\r\n" + PMAG, [PMAG], {"not_whitelisted": 1})
    assert_outcome(Kind.PMAG, ZDA + PMAG, [PMAG], {"not_whitelisted": 1})
    odd = nmea_sentence("PMAG1,anything at all here")
    assert_outcome(Kind.PMAG, odd, [odd])


def test_cesium_rules() -> None:
    high = cesium(149_895.131, 1249)
    assert high == b"$149895.131,1249\r\n"
    assert_outcome(Kind.CESIUM, high, [high])
    cases = [
        b"$ 49895.13,1249\r\n",  # position 10 not a digit
        b"$ 49895.131,124\r\n",  # body 14 bytes
        b"$ 49895.131,12490\r\n",  # position 16 not the end
        b"$ 49895.131,1249 \r\n",
        b"$249895.131,1249\r\n",
        b"$ 4989a.131,1249\r\n",
        b"$ 49895,131,1249\r\n",
        b"$ 49895.131.1249\r\n",
        b"$ 49895.131,1249*00\r\n",
        b"$ 49895\r\n",
        PMAG,
    ]
    for case in cases:
        assert_outcome(Kind.CESIUM, case + CESIUM, [CESIUM], {"not_whitelisted": 1})
    # MAX_FRAME does not apply to cesium frames.
    assert_outcome(Kind.CESIUM, CESIUM, [CESIUM], max_frame=12)


# --- flush event --------------------------------------------------------------------------


@pytest.mark.parametrize("quality", "123456789")
def test_flush_quality_1_to_9(quality: str) -> None:
    frame = nmea_sentence(f"GNGGA,120000.00,4730.0,N,00830.0,E,{quality},08,0.9,100.0,M,45.0,M,,")
    result = assert_outcome(Kind.NMEA, ZDA + frame + VTG, [ZDA, frame, VTG])
    assert result.flushes == [1]


@pytest.mark.parametrize(
    "body",
    [
        "GPGGA,120000.00,4730.0,N,00830.0,E,0,08,0.9,100.0,M,45.0,M,,",
        "GPGGA,120000.00,4730.0,N,00830.0,E,,08,0.9,100.0,M,45.0,M,,",
        "GPGGA,120000.00,4730.0,N,00830.0,E,12,08,0.9,100.0,M,45.0,M,,",
        "GPGGA,120000.00,4730.0,N,00830.0,E, 1,08",
        "GPGGA,120000.00,4730.0,N,00830.0,E",  # fewer fields
        "GPGGA,120000.00,4730.0,N,00830.0,E,",  # item 6 empty and last
        "GPGGA,120000.00,4730.0,N,00830*0,E,1",  # item 6 after the first "*"
        "GPZDA,1,2,3,4,5,1",  # not a GGA
        "GPVTG,1,2,3,4,5,1",
    ],
)
def test_no_flush(body: str) -> None:
    frame = nmea_sentence(body)
    result = assert_outcome(Kind.NMEA, frame, [frame])
    assert result.flushes == []


def test_flush_quality_last_field() -> None:
    frame = nmea_sentence("GPGGA,1,2,3,4,5,6")
    assert run(Kind.NMEA, frame).flushes == [0]


def test_pmag_and_cesium_never_flush() -> None:
    assert run(Kind.PMAG, nmea_sentence("PMAG1,GGA,1,2,3,4,1")).flushes == []


# --- input forms and streaming ------------------------------------------------------------


def test_input_forms_agree() -> None:
    stream = GGA + b"\x00$GPGG\r" + ZDA + b"$ 49895.131,1249\r\n"
    expected = run(Kind.NMEA, stream)
    assert run(Kind.NMEA, bytearray(stream)) == expected
    assert run(Kind.NMEA, list(stream)) == expected
    assert run(Kind.NMEA, [RxEvent(b, False) for b in stream]) == expected
    assert run(Kind.NMEA, [(b, False) for b in stream]) == expected
    assert run("nmea", iter(stream)) == expected


def test_take_frames_hands_over_each_frame_once_and_keeps_none() -> None:
    stream = GGA + VTG[:-3] + ZDA + GGA + VTG + GGA[:20]
    batch = run(Kind.NMEA, stream)
    taker = ReferenceFilter(Kind.NMEA)
    taken = []
    for k in range(0, len(stream), 7):          # chunks that split frames
        taker.feed_all(stream[k:k + 7])
        taken += taker.take_frames()
        assert taker.result.frames == []
    assert taken == batch.frames == [GGA, ZDA, GGA, VTG]
    assert taker.result.counters == batch.counters
    # Flushes number kept frames from the start, taken or not.
    assert taker.result.flushes == batch.flushes == [0, 2]
    taker.feed_all(GGA[20:])
    assert taker.take_frames() == [GGA] and taker.result.flushes == [0, 2, 4]


def test_streaming_equals_batch_and_open_frame_is_pending() -> None:
    stream = GGA + VTG[:-3] + ZDA + GGA[:20]
    incremental = ReferenceFilter(Kind.NMEA)
    for byte in stream:
        incremental.feed(byte)
        incremental.result  # reading in between changes nothing
    assert incremental.result == run(Kind.NMEA, stream)
    assert incremental.result.counters == dict.fromkeys(COUNTER_NAMES, 0) | {"kept": 2, "bad_byte": 1}
    for byte in GGA[20:]:
        incremental.feed(byte)
    assert incremental.result.frames == [GGA, ZDA, GGA]
    assert incremental.result.flushes == [0, 2]


@pytest.mark.parametrize("bad", [256, -1, "a", (1, 2, 3), None])
def test_bad_events(bad: object) -> None:
    with pytest.raises(ValueError):
        reference_filter(Kind.NMEA, [bad])


def test_bad_arguments() -> None:
    with pytest.raises(ValueError, match="Max frame length must be a positive integer, not 0"):
        ReferenceFilter(Kind.NMEA, 0)
    with pytest.raises(ValueError):
        ReferenceFilter("gps")


# --- demo streams -------------------------------------------------------------------------


def test_demo_streams_faults() -> None:
    streams = demo_streams(seconds=2.0, seed=1)
    assert set(streams) == {"mag", "gps", "cesium"}
    assert demo_streams(seconds=2.0, seed=1) == streams
    assert demo_streams(seconds=2.0, seed=2) != streams
    mag = run(Kind.PMAG, streams["mag"])
    assert dropped(mag) == {"checksum": 1} and mag.counters["kept"] == 39
    cs = run(Kind.CESIUM, streams["cesium"])
    assert dropped(cs) == {"bad_byte": 1} and cs.counters["kept"] == 19
    gps = run(Kind.NMEA, streams["gps"])
    # Per second: RMC, GSA and three GSV dropped; GGA, ZDA, VTG kept; one of those cut short.
    assert gps.counters["not_whitelisted"] == 2 * 5
    assert gps.counters["bad_byte"] == 1 and gps.counters["kept"] == 2 * 3 - 1
    assert len(gps.flushes) <= 1  # one GGA has quality 0; the other may be the cut one
    # The epoch without a fix (sentences.gps_epoch): GGA quality 0 with 3 satellites.
    assert sum(b",0,03,99.0," in f for f in gps.frames) == 1


@pytest.mark.parametrize("seed", range(4))
def test_demo_streams_longer(seed: int) -> None:
    streams = demo_streams(seconds=10.0, seed=seed)
    gps = run(Kind.NMEA, streams["gps"])
    assert gps.counters["kept"] == 10 * 3 - 1 and gps.counters["bad_byte"] == 1
    assert len(gps.flushes) in (8, 9)
    assert run(Kind.PMAG, streams["mag"]).counters["kept"] == 199
    assert run(Kind.CESIUM, streams["cesium"]).counters["kept"] == 99


# --- seeded random streams ----------------------------------------------------------------

MAX_FRAME = 96


def literal_rules(kind: Kind, events: list[tuple[int, bool]], max_frame: int) -> FilterResult:
    """docs/frame-rules.md read literally, one byte at a time (independent of the module)."""
    counters = dict.fromkeys(COUNTER_NAMES, 0)
    frames: list[bytes] = []
    flushes: list[int] = []
    limit = 18 if kind is Kind.CESIUM else max_frame
    frame: bytearray | None = None
    after_cr = False
    for byte, error in events:
        if frame is None:
            if not error and byte == ord("$"):
                frame, after_cr = bytearray(b"$"), False
            continue
        cause = None
        if error:
            cause = "uart_error"
        elif byte == ord("$"):
            counters["bad_byte"] += 1
            frame, after_cr = bytearray(b"$"), False
            continue
        elif after_cr and byte != 0x0A:
            cause = "bad_byte"
        elif byte not in (0x0D, 0x0A) and not 0x20 <= byte <= 0x7E:
            cause = "bad_byte"
        elif len(frame) + 1 > limit:
            cause = "overlong"
        elif byte == 0x0A:
            frame.append(byte)
            cause = end_check(kind, bytes(frame))
            if cause == "kept":
                if kind is Kind.NMEA and raises_flush(bytes(frame)):
                    flushes.append(len(frames))
                frames.append(bytes(frame))
        elif byte == 0x0D:
            frame.append(byte)
            after_cr = True
            continue
        else:
            frame.append(byte)
            if not position_ok(kind, bytes(frame)):
                cause = "not_whitelisted"
            else:
                continue
        counters[cause] += 1
        frame = None
    return FilterResult(frames=frames, counters=counters, flushes=flushes)


def position_ok(kind: Kind, frame: bytes) -> bool:
    """The position check of the byte just appended (the last one of ``frame``)."""
    position, char = len(frame) - 1, chr(frame[-1])
    if kind is Kind.PMAG:
        return position > 6 or char == "PMAG1,"[position - 1]
    if kind is Kind.NMEA:
        if position in (1, 2):
            return "A" <= char <= "Z"
        if position in (3, 4, 5):
            name = frame[3 : position + 1].decode("latin-1")
            return any(allowed.startswith(name) for allowed in ("GGA", "ZDA", "VTG"))
        return position != 6 or char == ","
    if position == 1:
        return char in " 1"
    if position in (7, 11):
        return char == ".,"[position == 11]
    return 2 <= position <= 15 and char.isdigit() and char.isascii()


def end_check(kind: Kind, frame: bytes) -> str:
    body = frame[1:-1]
    if body.endswith(b"\r"):
        body = body[:-1]
    if kind is Kind.CESIUM:
        return "kept" if len(body) == 15 else "not_whitelisted"
    if len(body) < 9:
        return "not_whitelisted"
    star = body.rfind(b"*")
    if star != len(body) - 3 or not all(chr(c) in "0123456789abcdefABCDEF" for c in body[-2:]):
        return "checksum"
    return "kept" if functools.reduce(operator.xor, body[:star], 0) == int(body[-2:], 16) else "checksum"


def raises_flush(frame: bytes) -> bool:
    return re.match(rb"\$[A-Z]{2}GGA,(?:[^,*]*,){5}[1-9][,*]", frame) is not None


# Whole frames, from DESIGN.md "Formats" and "Frame rules".
WHOLE_FRAME = {
    Kind.NMEA: re.compile(rb"\$[A-Z]{2}(?:GGA|ZDA|VTG),[\x20-\x7e]*\*(?P<hh>[0-9A-Fa-f]{2})\r?\n"),
    Kind.PMAG: re.compile(rb"\$PMAG1,[\x20-\x7e]*\*(?P<hh>[0-9A-Fa-f]{2})\r?\n"),
    Kind.CESIUM: re.compile(rb"\$[ 1]\d{5}\.\d{3},\d{4}\r?\n"),
}


def valid_frame(kind: Kind, frame: bytes, max_frame: int) -> bool:
    match = WHOLE_FRAME[kind].fullmatch(frame)
    if match is None or b"$" in frame[1:]:
        return False
    if kind is Kind.CESIUM:
        return True
    body = frame[1 : frame.rindex(b"*")]
    return len(frame) <= max_frame and functools.reduce(operator.xor, body, 0) == int(match["hh"], 16)


def random_sentence(rng: np.random.Generator) -> bytes:
    """A valid sentence of any kind (so each kind also sees the others' sentences)."""
    when = dt.datetime(2024, 6, 1) + dt.timedelta(seconds=float(rng.uniform(0, 86_400)))
    lat, lon = float(rng.uniform(-90, 90)), float(rng.uniform(-180, 180))
    eol = b"\n" if rng.random() < 0.2 else b"\r\n"
    talker = "".join(chr(c) for c in rng.integers(ord("A"), ord("Z") + 1, size=2))
    choice = int(rng.integers(9))
    if choice == 0:
        quality = int(rng.integers(0, 10))
        return gga(float(rng.uniform(0, 86_400)), lat, lon, quality=quality, talker=talker, eol=eol)
    if choice == 1:
        return zda(when, talker=talker, eol=eol)
    if choice == 2:
        return vtg(float(rng.uniform(0, 360)), float(rng.uniform(0, 60)), talker=talker, eol=eol)
    if choice == 3:
        distractors = [rmc(when, lat, lon), gsa([1, 2, 3]), gsv([(1, 2, 3, 4), (5, 6, 7, None)])]
        return distractors[int(rng.integers(3))]
    if choice in (4, 5):
        return pmag1(int(rng.integers(0, 10**6)), *rng.uniform(-99_999, 99_999, size=3).tolist(), eol=eol)
    if choice == 6:  # around MAX_FRAME
        name = "PMAG1" if rng.random() < 0.5 else "GPGGA"
        return nmea_sentence(name + "," + ",".join(["1.234567"] * int(rng.integers(8, 14))), eol=eol)
    return cesium(float(rng.uniform(0, 199_999)), int(rng.integers(0, 10_000)), eol=eol)


SPECIAL_BYTES = [ord("$"), 0x0D, 0x0A, ord("*"), ord(","), 0x00, 0x7F, 0xFF, ord(" "), ord("1")]


def mutate(rng: np.random.Generator, sentence: bytes) -> list[tuple[int, bool]]:
    events = [(b, False) for b in sentence]
    for _ in range(int(rng.integers(1, 3))):
        if not events:
            break
        at = int(rng.integers(len(events)))
        what = int(rng.integers(6))
        if what == 0:
            events[at] = (int(rng.integers(256)), False)
        elif what == 1:
            events.insert(at, (SPECIAL_BYTES[int(rng.integers(len(SPECIAL_BYTES)))], False))
        elif what == 2:
            del events[at]
        elif what == 3:
            events = events[:at]
        elif what == 4:
            events[at] = (events[at][0], True)
        else:
            byte = events[at][0]
            events[at] = (byte ^ 0x20 if chr(byte).isalpha() else byte ^ 1, False)
    return events


def random_stream(seed: int, count: int = 250) -> tuple[list[tuple[int, bool]], list[bytes]]:
    """A stream of valid, mutated and noise pieces, and the unmutated sentences in order."""
    rng = np.random.default_rng(seed)
    events: list[tuple[int, bool]] = []
    untouched: list[bytes] = []
    for _ in range(count):
        sentence = random_sentence(rng)
        roll = rng.random()
        if roll < 0.55:
            events += [(b, False) for b in sentence]
            untouched.append(sentence)
        elif roll < 0.9:
            events += mutate(rng, sentence)
        else:
            noise = rng.integers(0, 256, size=int(rng.integers(1, 12))).tolist()
            events += [(b, bool(rng.random() < 0.2)) for b in noise if b != ord("$")]
    return events, untouched


def is_subsequence(items: list[bytes], sequence: list[bytes]) -> bool:
    remaining = iter(sequence)
    return all(any(item == other for other in remaining) for item in items)


@pytest.mark.parametrize("seed", range(12))
@pytest.mark.parametrize("kind", list(Kind))
def test_random_streams_against_literal_rules(kind: Kind, seed: int) -> None:
    events, untouched = random_stream(seed)
    result = run(kind, events, max_frame=MAX_FRAME)
    assert result == literal_rules(kind, events, MAX_FRAME)
    # Every outcome is counted once: each "$" without the error flag starts one frame.
    starts = sum(1 for byte, error in events if byte == ord("$") and not error)
    assert sum(result.counters.values()) in (starts, starts - 1)
    # Whole-frame cross-check: kept frames re-validate, in order, as pieces of the stream.
    for frame in result.frames:
        assert valid_frame(kind, frame, MAX_FRAME), frame
    limit = 18 if kind is Kind.CESIUM else MAX_FRAME
    expected_kept = [s for s in untouched if valid_frame(kind, s, limit)]
    assert is_subsequence(expected_kept, result.frames)
    assert result.flushes == [i for i, f in enumerate(result.frames) if kind is Kind.NMEA and raises_flush(f)]


@pytest.mark.parametrize("seed", range(6))
def test_random_clean_streams_keep_exactly_the_valid_frames(seed: int) -> None:
    # Without mutations, the kept frames are exactly the regex-valid sentences.
    rng = np.random.default_rng(1000 + seed)
    pieces = [random_sentence(rng) for _ in range(300)]
    stream = b"".join(pieces)
    for kind in Kind:
        limit = 18 if kind is Kind.CESIUM else MAX_FRAME
        result = run(kind, stream, max_frame=MAX_FRAME)
        assert result.frames == [p for p in pieces if valid_frame(kind, p, limit)]
