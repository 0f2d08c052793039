"""Tests for maglog.sim.stimulus.sentences: checksums, exact formats, argument checks."""

from __future__ import annotations

import datetime as dt
import functools
import operator
import re

import numpy as np
import pytest

from maglog.sim.stimulus import sentences
from maglog.sim.stimulus.sentences import cesium, gga, gsa, gsv, nmea_checksum, nmea_sentence, pmag1, rmc, vtg, zda

# The formats of docs/architecture.md ("What is on the wire and on the card"), written out as regular expressions.
PMAG_RE = re.compile(
    rb"\$PMAG1,\d{5},[+-]\d{5}\.\d,[+-]\d{5}\.\d,[+-]\d{5}\.\d\*(?P<hh>[0-9A-F]{2})\r\n"
)
CESIUM_RE = re.compile(rb"\$[ 1]\d{5}\.\d{3},\d{4}\r\n")
NMEA_RE = re.compile(rb"\$(?P<body>[A-Z]{2}[A-Z]{3},[\x20-\x7e]*)\*(?P<hh>[0-9A-F]{2})\r\n")

# Sentences from real receivers (shared/data/nmea captures), checksums as the receivers sent them.
REAL_SENTENCES = [
    b"$GPZDA,183531.00,23,12,2007,00,00*6C",
    b"$GPGGA,183530.00,2037.76012,N,08704.07373,W,1,03,2.2,072.35,M,-13.9,M,,*6B",
    b"$GPGGA,,,,,,0,00,99.99,,,,,,*48",
    b"$GPVTG,338.51,T,0.00,M,0.068,N,0.126,K,A*24",
    b"$GNGGA,003956.00,4552.65403,S,17030.00668,E,1,12,0.64,14.2,M,1.8,M,,*56",
    b"$GPGSA,A,3,07,30,19,11,15,,,,,,,,2.88,1.20,2.62,1*10",
]


def xor_of(data: bytes) -> int:
    return functools.reduce(operator.xor, data, 0)


def checksum_ok(sentence: bytes) -> bool:
    body, _, tail = sentence.partition(b"*")
    return xor_of(body[1:]) == int(tail[:2], 16)


def nmea_fields(sentence: bytes) -> list[str]:
    match = NMEA_RE.fullmatch(sentence)
    assert match, sentence
    return match["body"].decode().split(",")


# --- checksums ----------------------------------------------------------------------------


@pytest.mark.parametrize("sentence", REAL_SENTENCES)
def test_checksum_matches_real_receivers(sentence: bytes) -> None:
    body, _, hh = sentence[1:].partition(b"*")
    assert nmea_checksum(body) == int(hh, 16)
    assert nmea_checksum(body.decode()) == int(hh, 16)
    assert nmea_sentence(body.decode()) == sentence + b"\r\n"


def test_checksum_against_independent_xor() -> None:
    rng = np.random.default_rng(7)
    for _ in range(200):
        body = bytes(rng.integers(0x20, 0x7F, size=int(rng.integers(0, 90))).tolist())
        assert nmea_checksum(body) == xor_of(body)


def test_nmea_sentence_override_and_eol() -> None:
    assert nmea_sentence("GPZDA,", checksum=0xAB, eol=b"\n") == b"$GPZDA,*AB\n"
    assert nmea_sentence("A", eol=b"") == b"$A*41"
    with pytest.raises(ValueError, match="Checksum must be an integer 0..255, not 256"):
        nmea_sentence("A", checksum=256)
    with pytest.raises(ValueError, match="must be ASCII"):
        nmea_sentence("GPGGA,\u00b0")


# --- $PMAG1 -------------------------------------------------------------------------------


def test_pmag1_exact() -> None:
    frame = pmag1(7, 123.4, -48000, 0.0)
    assert frame.startswith(b"$PMAG1,00007,+00123.4,-48000.0,+00000.0*")
    assert PMAG_RE.fullmatch(frame) and checksum_ok(frame)


def test_pmag1_sequence_wraps_and_rounding() -> None:
    assert pmag1(123_456, 0, 0, 0).startswith(b"$PMAG1,23456,")
    assert pmag1(99_999, 0, 0, 0).startswith(b"$PMAG1,99999,")
    assert pmag1(100_000, 0, 0, 0).startswith(b"$PMAG1,00000,")
    assert b",+99999.9," in pmag1(0, 99_999.94, 0, 0)
    assert b",-99999.9," in pmag1(0, -99_999.94, 0, 0)
    assert b",+00000.0," in pmag1(0, -0.04, 0, 0)  # no negative zero


def test_pmag1_random_frames_match_format() -> None:
    rng = np.random.default_rng(3)
    for seq in rng.integers(0, 10**6, size=200):
        x, y, z = rng.uniform(-99_999.9, 99_999.9, size=3)
        frame = pmag1(int(seq), float(x), float(y), float(z), eol=b"\r\n")
        assert PMAG_RE.fullmatch(frame), frame
        assert checksum_ok(frame)
        fields = frame[1 : frame.index(b"*")].split(b",")
        assert int(fields[1]) == seq % 100_000
        assert [float(f) for f in fields[2:]] == pytest.approx([x, y, z], abs=0.05 + 1e-9)


@pytest.mark.parametrize("value", [99_999.95, -99_999.95, 1e6, float("nan"), float("inf")])
def test_pmag1_out_of_range(value: float) -> None:
    with pytest.raises(ValueError, match="Field y"):
        pmag1(0, 0.0, value, 0.0)


def test_pmag1_bad_sequence() -> None:
    with pytest.raises(ValueError, match="Sequence number must be a non-negative integer, not -1"):
        pmag1(-1, 0, 0, 0)


# --- cesium -------------------------------------------------------------------------------


def test_cesium_exact() -> None:
    assert cesium(49_895.131, 1249) == b"$ 49895.131,1249\r\n"
    assert cesium(149_895.131, 1249) == b"$149895.131,1249\r\n"
    assert cesium(0, 0, eol=b"\n") == b"$ 00000.000,0000\n"
    assert cesium(99_999.9996, 9999) == b"$100000.000,9999\r\n"  # rounds into the high range
    assert cesium(199_999.999, 5) == b"$199999.999,0005\r\n"
    assert len(cesium(12_345.6789, 12)) == 18


def test_cesium_random_frames_match_format() -> None:
    rng = np.random.default_rng(5)
    for field_nt, signal in zip(rng.uniform(0, 199_999.999, size=200), rng.integers(0, 10_000, size=200)):
        frame = cesium(float(field_nt), int(signal))
        assert CESIUM_RE.fullmatch(frame), frame
        value = float(frame[2:11]) + (100_000 if frame[1:2] == b"1" else 0)
        assert value == pytest.approx(field_nt, abs=0.0005 + 1e-9)
        assert int(frame[12:16]) == signal


@pytest.mark.parametrize("field_nt", [-0.001, 200_000, 199_999.9996, float("nan")])
def test_cesium_bad_field(field_nt: float) -> None:
    with pytest.raises(ValueError, match="Cesium field"):
        cesium(field_nt, 1)


@pytest.mark.parametrize("signal", [12345, -1, 10_000, 12.5, True])
def test_cesium_bad_signal(signal: object) -> None:
    message = f"Signal level must be an integer 0..9999, not {signal!r}"
    with pytest.raises(ValueError, match=re.escape(message)):
        cesium(49_000.0, signal)  # type: ignore[arg-type]


# --- NMEA ---------------------------------------------------------------------------------


def test_gga_exact() -> None:
    frame = gga(10 * 3600 + 30 * 60 + 1.234, 47.5, -8.25)
    assert frame == nmea_sentence("GPGGA,103001.23,4730.00000,N,00815.00000,W,1,08,0.9,100.0,M,45.0,M,,")
    fields = nmea_fields(frame)
    assert len(fields) == 15  # name + 14 fields
    assert fields[6] == "1"


def test_gga_positions_and_options() -> None:
    frame = gga(
        86_400 * 3 + 59.999,  # modulo one day; 59.999 s rounds to the next minute
        -33.8688,
        151.2093,
        quality=4,
        satellites=12,
        hdop=0.64,
        altitude_m=14.25,
        geoid_m=-1.8,
        talker="GN",
        eol=b"\n",
    )
    assert frame.endswith(b"\n") and not frame.endswith(b"\r\n")
    fields = frame[1 : frame.index(b"*")].decode().split(",")
    assert fields == [
        "GNGGA", "000100.00", "3352.12800", "S", "15112.55800", "E", "4", "12", "0.6", "14.2", "M",
        "-1.8", "M", "", "",
    ]
    assert checksum_ok(frame)


def test_gga_minutes_carry() -> None:
    assert b",4800.00000,N," in gga(0, 47.99999999, 0)
    assert b",4759.99999,N," in gga(0, 47.9999999, 0)
    assert b",17959.99999,W," in gga(0, 0, -179.9999999)


@pytest.mark.parametrize(
    ("kwargs", "message"),
    [
        ({"lat_deg": 90.1}, "Latitude"),
        ({"lon_deg": -180.5}, "Longitude"),
        ({"quality": 10}, "Fix quality must be an integer 0..9, not 10"),
        ({"satellites": 100}, "Satellite count"),
        ({"hdop": float("nan")}, "HDOP"),
    ],
)
def test_gga_bad_arguments(kwargs: dict, message: str) -> None:
    args = {"t_utc_seconds": 0.0, "lat_deg": 0.0, "lon_deg": 0.0} | kwargs
    with pytest.raises(ValueError, match=message):
        gga(**args)


@pytest.mark.parametrize("talker", ["gp", "G", "GPS", "G1", "", 12])
def test_talker_checked(talker: object) -> None:
    for build in (
        lambda: gga(0, 0, 0, talker=talker),
        lambda: zda(dt.datetime(2024, 1, 1), talker=talker),
        lambda: vtg(0, 0, talker=talker),
        lambda: rmc(dt.datetime(2024, 1, 1), 0, 0, talker=talker),
        lambda: gsa([1], talker=talker),
        lambda: gsv([], talker=talker),
    ):
        with pytest.raises(ValueError, match="Talker must be two upper-case letters"):
            build()


def test_zda_exact_and_timezones() -> None:
    when = dt.datetime(2007, 12, 23, 18, 35, 31, 999_999)
    assert zda(when) == nmea_sentence("GPZDA,183531.99,23,12,2007,00,00")
    aware = dt.datetime(2024, 1, 1, 1, 0, 0, tzinfo=dt.timezone(dt.timedelta(hours=2)))
    assert zda(aware, talker="GN") == nmea_sentence("GNZDA,230000.00,31,12,2023,00,00")


def test_vtg_exact() -> None:
    assert vtg(338.51, 0.068) == nmea_sentence("GPVTG,338.5,T,,M,0.1,N,0.1,K,A")
    assert vtg(-10, 10, magnetic_course_deg=367.5) == nmea_sentence("GPVTG,350.0,T,007.5,M,10.0,N,18.5,K,A")
    with pytest.raises(ValueError, match="Speed must be non-negative"):
        vtg(0, -1)


def test_distractors_are_valid_nmea() -> None:
    when = dt.datetime(2016, 4, 21, 22, 32, 51)
    frame = rmc(when, 37.9654422, -122.5323, speed_knots=0.068, course_deg=338.51)
    assert frame == nmea_sentence("GPRMC,223251.00,A,3757.92653,N,12231.93800,W,0.1,338.5,210416,,,A")
    assert nmea_fields(rmc(when, 0, 0, valid=False))[2] == "V"
    frame = gsa([7, 30, 19, 11, 15], pdop=2.88, hdop=1.2, vdop=2.62)
    assert frame == nmea_sentence("GPGSA,A,3,07,30,19,11,15,,,,,,,,2.9,1.2,2.6")
    with pytest.raises(ValueError, match="at most 12"):
        gsa(range(1, 14))


def test_gsv_splits_four_per_sentence() -> None:
    satellites = [(prn, 10 + prn, 20 * prn, None if prn % 3 == 0 else 30 + prn) for prn in range(1, 11)]
    out = gsv(satellites, talker="GL")
    lines = out.split(b"\r\n")[:-1]
    assert len(lines) == 3
    for index, line in enumerate(lines, start=1):
        sentence = line + b"\r\n"
        fields = nmea_fields(sentence)
        assert fields[:4] == ["GLGSV", "3", str(index), "10"]
        assert checksum_ok(sentence)
    assert nmea_fields(lines[2] + b"\r\n")[4:] == ["09", "19", "180", "", "10", "20", "200", "40"]
    assert gsv([]) == nmea_sentence("GPGSV,1,1,00")


def test_all_builders_end_in_eol() -> None:
    when = dt.datetime(2024, 6, 1, 12)
    for frame in (gga(0, 1, 2), zda(when), vtg(1, 2), rmc(when, 1, 2), gsa([1]), gsv([(1, 2, 3, 4)])):
        assert NMEA_RE.fullmatch(frame), frame
        assert checksum_ok(frame)
    assert sentences.CRLF == b"\r\n"


# --- one second of a GPS receiver ---------------------------------------------------------


def test_gps_epoch_is_one_receiver_second_in_order_with_and_without_a_fix() -> None:
    when = dt.datetime(2024, 6, 1, 10, 0, 1, 500_000, tzinfo=dt.timezone.utc)
    sky = [(2, 40, 100, 30), (5, 20, 200, None), (12, 60, 10, 45), (13, 5, 300, 25),
           (15, 85, 0, 41)]
    where = dict(course_deg=90.0, speed_knots=10.0, sky=sky, altitude_m=120.0, geoid_m=47.4)
    fixed = sentences.gps_epoch(when, 47.5, 8.25, **where)
    assert [kind for kind, _ in fixed] == ["RMC", "VTG", "GGA", "GSA", "GSV", "GSV", "ZDA"]
    assert b"".join(s for kind, s in fixed if kind == "GSV") == gsv(sky)
    assert fixed[0][1] == rmc(when, 47.5, 8.25, speed_knots=10.0, course_deg=90.0)
    assert fixed[2][1] == gga(36001.5, 47.5, 8.25, satellites=5, altitude_m=120.0,
                              geoid_m=47.4)
    assert fixed[3][1] == gsa([2, 5, 12, 13, 15])
    assert fixed[-1][1] == zda(when)
    lost = dict(sentences.gps_epoch(when, 47.5, 8.25, fix=False, **where))
    assert lost["RMC"] == rmc(when, 47.5, 8.25, speed_knots=10.0, course_deg=90.0, valid=False)
    assert lost["GGA"] == gga(36001.5, 47.5, 8.25, quality=0, satellites=3, hdop=99.0,
                              altitude_m=120.0, geoid_m=47.4)
    assert lost["GSA"] == gsa([], fix=1)
    bare = sentences.gps_epoch(when, 47.5, 8.25, distractors=False, talker="GN", **where)
    assert [kind for kind, _ in bare] == ["VTG", "GGA", "ZDA"]
    assert all(s.startswith(b"$GN") for _, s in bare)
