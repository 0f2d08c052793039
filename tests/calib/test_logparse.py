"""Tests for maglog.calib.logparse: synthetic logs built with maglog.sim.stimulus.sentences, with
known arrival times, and one test per kind of bad line and per error path."""

from __future__ import annotations

import dataclasses
import datetime as dt
import math
import re
from dataclasses import dataclass

import numpy as np
import pytest

from maglog.calib import logparse
from maglog.calib.logparse import BAD_REASONS, SEQ_MODULUS, ParsedLog, parse_log, to_arrays
from maglog.sim.stimulus.sentences import (
    CRLF,
    LF,
    cesium,
    gga,
    gsa,
    gsv,
    nmea_checksum,
    nmea_sentence,
    pmag1,
    rmc,
    vtg,
    zda,
)

MAG_BAUD = 115_200
GPS_BAUD = 9_600
CESIUM_BAUD = 9_600
BITS_PER_BYTE = 10  # 8N1
GPS_LATENCY = 0.12  # s from a GGA's epoch to the arrival of its last byte
DAY = dt.datetime(2024, 3, 31)
MIDNIGHT = 86_400.0
MAG_PERIOD = 1 / 20
# Tolerances, from the method (module docstring of logparse):
# - magnetometer, timed by sequence numbers: one bracket is good to ± half a period (25 ms at
#   20 Hz); a 30-anchor fit averages that down to ~10 ms at worst, a 120-anchor fit to ~2 ms.
MAG_TOL_30S = MAG_PERIOD / 4
MAG_TOL_120S = 0.005
# - lines timed by line position between 1 Hz anchors: the GPS burst (GGA, ZDA, VTG, RMC, GSA,
#   ~0.3 s at 9600 baud) puts five lines into a third of a second, which skews the even
#   spread by up to ~0.2 s.
LINE_TOL = 0.25


@dataclass
class Event:
    arrival: float  # s since midnight of DAY, when the line's last byte arrived
    kind: str
    line: bytes
    truth: object  # per kind: mag (seq, x, y, z), cesium field, GPS epoch


def transmit(line: bytes, baud: int) -> float:
    return len(line) * BITS_PER_BYTE / baud


def position(epoch: float) -> tuple[float, float, float]:
    k = epoch - 86_385.0
    return 47.0 + 1e-4 * k, 8.0 + 2e-4 * k, 100.0 + 0.5 * k


def mag_field(ts: float) -> tuple[float, float, float]:
    return 20_000.0 + 300.0 * math.sin(ts), -3_000.0 + 50.0 * math.cos(ts), 45_000.0


def cesium_field(ts: float) -> float:
    return 49_895.0 + 0.02 * (ts - 86_385.0)


def build(
    *,
    duration: float = 30.0,
    start: float = 86_385.0,
    mag_rate: float = 20 * (1 - 0.003),
    seq0: int = 99_950,
    eol: bytes = CRLF,
    seed: int = 1,
    distractors: bool = True,
    with_zda: bool = True,
    gps: bool = True,
) -> list[Event]:
    """Events of a survey log: 20 Hz magnetometer (its own clock 0.3 % slow), 10 Hz cesium,
    1 Hz GPS (GGA, ZDA, VTG and the distractors RMC, GSA), sorted by arrival."""
    rng = np.random.default_rng(seed)
    events = []
    t_mag = start + rng.uniform(0.0, 1.0)
    for i in range(int(duration * mag_rate)):
        ts = t_mag + i / mag_rate
        x, y, z = mag_field(ts)
        line = pmag1(seq0 + i, x, y, z, eol=eol)
        events.append(Event(ts + transmit(line, MAG_BAUD), "mag", line, (seq0 + i, x, y, z)))
    t_cs = start + rng.uniform(0.0, 0.1)
    for j in range(int(duration * 10)):
        ts = t_cs + j / 10
        line = cesium(cesium_field(ts), 1200 + j % 7, eol=eol)
        events.append(
            Event(ts + transmit(line, CESIUM_BAUD), "cesium", line, round(cesium_field(ts), 3))
        )
    for k in range(int(duration) + 1 if gps else 0):
        epoch = math.floor(start) + k
        when = DAY + dt.timedelta(seconds=epoch)
        lat, lon, alt = position(epoch)
        burst = [("gga", gga(epoch, lat, lon, altitude_m=alt, satellites=9, hdop=0.8, eol=eol))]
        if with_zda:
            burst.append(("zda", zda(when, eol=eol)))
        burst.append(("vtg", vtg(45.0, 29.0, eol=eol)))
        if distractors:
            burst += [("rmc", rmc(when, lat, lon, eol=eol)), ("gsa", gsa([1, 5, 9], eol=eol))]
        arrival = epoch + GPS_LATENCY
        for index, (kind, line) in enumerate(burst):
            if index:
                arrival += transmit(line, GPS_BAUD)
            events.append(Event(arrival, kind, line, epoch))
    events.sort(key=lambda event: event.arrival)
    return events


def log_of(events: list[Event]) -> bytes:
    return b"".join(event.line for event in events)


def of_kind(events: list[Event], kind: str) -> list[Event]:
    return [event for event in events if event.kind == kind]


def arrivals(events: list[Event], kind: str) -> np.ndarray:
    return np.array([event.arrival for event in of_kind(events, kind)])


def parse(events: list[Event], **kw) -> ParsedLog:
    return parse_log(log_of(events), gps_latency=GPS_LATENCY, **kw)


@pytest.fixture(scope="module")
def survey() -> tuple[list[Event], ParsedLog]:
    events = build()
    return events, parse(events, name="LOG00001.TXT")


# --- the synthetic survey -----------------------------------------------------------------


def test_survey_counts_and_no_bad_lines(survey):
    events, parsed = survey
    report = parsed.report
    assert parsed.bad == []
    assert report.bad == {reason: 0 for reason in BAD_REASONS}
    assert report.counts == {
        "mag": len(of_kind(events, "mag")),
        "cesium": 300,
        "gga": 31,
        "zda": 31,
        "vtg": 31,
    }
    assert report.ignored == {"GPRMC": 31, "GPGSA": 31}
    assert [address for _, address in parsed.ignored] == ["GPRMC", "GPGSA"] * 31
    assert report.lines == len(events)
    assert report.bytes == len(log_of(events))
    assert report.line_endings == {"CRLF": len(events), "LF": 0}
    # Line numbers are the events' positions, from 1.
    kinds = [event.kind for event in events]
    assert [kinds[line - 1] for line in parsed.mag.line] == ["mag"] * len(parsed.mag)
    assert [kinds[line - 1] for line in parsed.cesium.line] == ["cesium"] * len(parsed.cesium)
    assert [kinds[line - 1] for line, _ in parsed.ignored] == ["rmc", "gsa"] * 31


def test_survey_values(survey):
    events, parsed = survey
    truth = np.array([event.truth for event in of_kind(events, "mag")])
    np.testing.assert_allclose(parsed.mag.b, truth[:, 1:], atol=0.05)
    assert parsed.mag.b.shape == (len(truth), 3) and parsed.mag.b.dtype == np.float64
    np.testing.assert_allclose(
        parsed.cesium.field, [event.truth for event in of_kind(events, "cesium")], atol=5e-4
    )
    assert parsed.cesium.signal.dtype == np.int64
    assert list(parsed.cesium.signal[:8]) == [1200, 1201, 1202, 1203, 1204, 1205, 1206, 1200]
    epochs = np.array([event.truth for event in of_kind(events, "gga")], dtype=float)
    np.testing.assert_allclose(parsed.gga.time_of_day, epochs % MIDNIGHT)
    lat, lon, alt = np.array([position(epoch) for epoch in epochs]).T
    np.testing.assert_allclose(parsed.gga.lat, lat, atol=2e-7)
    np.testing.assert_allclose(parsed.gga.lon, lon, atol=2e-7)
    np.testing.assert_allclose(parsed.gga.altitude, np.round(alt, 1))
    assert set(parsed.gga.quality) == {1} and set(parsed.gga.satellites) == {9}
    np.testing.assert_allclose(parsed.gga.hdop, 0.8)
    assert parsed.zda.datetime == [DAY + dt.timedelta(seconds=epoch) for epoch in epochs]
    np.testing.assert_allclose(parsed.vtg.course, 45.0)
    np.testing.assert_allclose(parsed.vtg.speed, 29.0 * 1852 / 3600)


def test_survey_sequence_unwrapped_across_the_wrap(survey):
    events, parsed = survey
    sent = np.array([event.truth[0] for event in of_kind(events, "mag")])
    assert parsed.mag.seq[0] == 99_950
    assert parsed.mag.seq[-1] > SEQ_MODULUS  # it crossed 99999 -> 00000
    np.testing.assert_array_equal(parsed.mag.seq, sent)
    np.testing.assert_array_equal(np.diff(parsed.mag.seq), 1)
    assert parsed.mag.seq.dtype == np.int64
    assert (parsed.mag.seq_gaps, parsed.mag.seq_missing, parsed.mag.seq_repeats) == (0, 0, 0)


def test_survey_date_and_midnight(survey):
    events, parsed = survey
    assert parsed.date == dt.date(2024, 3, 31)
    assert parsed.epoch == dt.datetime(2024, 3, 31, tzinfo=dt.timezone.utc)
    assert parsed.report.midnight_rollovers == 1
    epochs = np.array([event.truth for event in of_kind(events, "gga")], dtype=float)
    assert epochs[0] < MIDNIGHT < epochs[-1]
    np.testing.assert_allclose(parsed.gga.t, epochs, atol=1e-9)  # the fixes' own epochs


def test_survey_times(survey):
    events, parsed = survey
    report = parsed.report
    assert report.time_aligned and report.anchors == 31 and report.mag_timing == "sequence"
    mag_error = parsed.mag.t - arrivals(events, "mag")
    assert np.max(np.abs(mag_error)) < MAG_TOL_30S
    assert report.mag_rate_hz == pytest.approx(20 * (1 - 0.003), rel=5e-4)
    assert report.mag_outliers == 0 and report.mag_brackets == 30
    assert report.mag_fit_rms_s < MAG_PERIOD / 2
    for kind, records in (("cesium", parsed.cesium), ("zda", parsed.zda), ("vtg", parsed.vtg)):
        assert np.max(np.abs(records.t - arrivals(events, kind))) < LINE_TOL, kind
    assert np.all(np.diff(parsed.mag.t) > 0) and np.all(np.diff(parsed.cesium.t) > 0)
    assert report.line_rate_hz == pytest.approx(len(events) / 30, rel=0.05)


def test_longer_log_times_the_magnetometer_within_5_ms():
    events = build(duration=120.0, seed=3)
    parsed = parse(events)
    assert np.max(np.abs(parsed.mag.t - arrivals(events, "mag"))) < MAG_TOL_120S
    assert np.max(np.abs(parsed.cesium.t - arrivals(events, "cesium"))) < LINE_TOL


def test_gps_latency_shifts_every_time_but_the_fixes(survey):
    events, parsed = survey
    late = parse_log(log_of(events), gps_latency=0.0)
    np.testing.assert_allclose(late.mag.t, parsed.mag.t - GPS_LATENCY, atol=1e-9)
    np.testing.assert_allclose(late.cesium.t, parsed.cesium.t - GPS_LATENCY, atol=1e-9)
    np.testing.assert_allclose(late.gga.t, parsed.gga.t, atol=1e-9)


def test_bare_lf_gives_the_same_result(survey):
    events, parsed = survey
    bare = parse_log(log_of(events).replace(CRLF, LF), gps_latency=GPS_LATENCY)
    assert bare.bad == [] and bare.report.line_endings == {"CRLF": 0, "LF": len(events)}
    for attribute in ("line", "seq", "b", "t"):
        np.testing.assert_array_equal(getattr(bare.mag, attribute), getattr(parsed.mag, attribute))
    np.testing.assert_array_equal(bare.cesium.field, parsed.cesium.field)
    np.testing.assert_array_equal(bare.cesium.t, parsed.cesium.t)
    np.testing.assert_array_equal(bare.gga.lat, parsed.gga.lat)


def test_mixed_line_ends():
    events = build(duration=5.0)
    for index in range(0, len(events), 2):
        events[index].line = events[index].line.replace(CRLF, LF)
    parsed = parse(events)
    assert parsed.bad == []
    assert parsed.report.line_endings == {
        "CRLF": len(events) // 2,
        "LF": len(events) - len(events) // 2,
    }
    assert len(parsed.mag) == len(of_kind(events, "mag"))


# --- gaps, bursts, restarts ---------------------------------------------------------------


def test_sequence_gaps_stay_visible_and_do_not_disturb_time():
    events = build()
    mags = of_kind(events, "mag")
    dropped = {id(event) for event in mags[100:103] + mags[400:401]}  # 3 + 1 samples lost
    repeated = mags[200]
    kept = []
    for event in events:
        if id(event) in dropped:
            continue
        kept.append(event)
        if event is repeated:
            kept.append(Event(event.arrival, "mag", event.line, event.truth))
    parsed = parse(kept)
    assert (parsed.mag.seq_gaps, parsed.mag.seq_missing, parsed.mag.seq_repeats) == (2, 4, 1)
    assert (parsed.report.seq_gaps, parsed.report.seq_missing, parsed.report.seq_repeats) == (
        2,
        4,
        1,
    )
    sent = [event.truth[0] for event in kept if event.kind == "mag"]
    np.testing.assert_array_equal(parsed.mag.seq, sent)
    assert np.all(np.diff(parsed.mag.seq) >= 0)
    assert np.max(np.abs(parsed.mag.t - arrivals(kept, "mag"))) < MAG_TOL_30S
    assert "2 gaps, 4 samples missing, 1 repeats" in str(parsed.report)


def test_bursts_in_arrival_order_do_not_distort_magnetometer_time():
    events = build()
    expected = arrivals(events, "mag")
    mags = of_kind(events, "mag")
    # The samples of the half second around a GGA are held back and released together, in
    # order, just before the next sample: their line positions are wrong, their sequence
    # numbers are not.
    gga_arrival = of_kind(events, "gga")[10].arrival
    held = [event for event in mags if gga_arrival - 0.5 < event.arrival < gga_arrival + 0.1]
    release = mags[mags.index(held[-1]) + 1].arrival - 1e-4
    for offset, event in enumerate(reversed(held)):
        event.arrival = release - offset * 1e-5
    events.sort(key=lambda event: event.arrival)
    parsed = parse(events)
    np.testing.assert_array_equal(np.diff(parsed.mag.seq), 1)
    assert np.max(np.abs(parsed.mag.t - expected)) < MAG_TOL_30S
    assert parsed.report.mag_outliers == 1  # the anchor the burst straddles is left out
    # Timing by line position would have been off by most of the hold.
    line_times = logparse._line_times(
        parsed.mag.line, parsed.gga.line.astype(float), parsed.gga.t + GPS_LATENCY
    )
    assert np.max(np.abs(line_times - expected)) > 0.3


@pytest.mark.parametrize("restart_at", [450, 150, 300], ids=["late", "early", "middle"])
def test_sensor_restart(restart_at):
    events = build()
    mags = of_kind(events, "mag")
    for i, event in enumerate(mags[restart_at:]):
        x, y, z = event.truth[1:]
        event.line = pmag1(i, x, y, z)  # the sensor restarted at 00000
    parsed = parse(events)
    report = parsed.report
    assert parsed.mag.seq_gaps == 1  # the restart looks like a jump forward
    error = np.abs(parsed.mag.t - arrivals(events, "mag"))
    messages = " ".join(report.messages)
    if restart_at == 300:
        # Half and half: no rate to trust, all by line position.
        assert report.mag_timing == "line" and "do not agree on a sample rate" in messages
        assert np.max(error) < LINE_TOL
        return
    # The side of the restart with most anchors is timed by sequence, the other by line.
    major, minor = (slice(0, restart_at), slice(restart_at, None))[
        :: 1 if restart_at > 300 else -1
    ]
    assert report.mag_timing == "sequence" and report.mag_outliers > 0.1 * report.anchors
    assert "disagree with the magnetometer sequence" in messages
    assert np.max(error[major]) < MAG_TOL_30S
    assert report.mag_line_timed == len(mags[minor])
    assert "timed by line position instead" in messages
    assert np.max(error[minor]) < LINE_TOL


def test_magnetometer_falls_back_to_line_timing_without_brackets():
    events = [
        event for event in build(duration=10.0) if event.kind != "mag" or event.arrival > 86_395.2
    ]
    parsed = parse(events)  # all magnetometer lines after the last GGA: nothing to bracket
    assert parsed.report.mag_timing == "line"
    assert math.isnan(parsed.report.mag_rate_hz)
    assert any(
        "magnetometer timed by line position" in message for message in parsed.report.messages
    )
    assert np.all(np.isfinite(parsed.mag.t)) and np.all(np.diff(parsed.mag.t) > 0)
    assert parsed.mag.t[0] > parsed.gga.t[-1]  # extrapolated after the last anchor


@pytest.mark.parametrize(
    ("seq", "anchor_t"),
    [
        # After the rough first pass, fewer than two brackets remain near any one line.
        (
            [30, 63, 102, 122, 143, 183, 204, 212],
            [1.5608291696739993, 6.271938763985025, 7.069802663668563],
        ),
        # The fit converges, but on fewer brackets than it leaves out.
        (
            [42, 105, 130, 144, 163, 197, 234, 236, 279, 290, 332, 391],
            [
                1.0665709313393614,
                2.010693592261099,
                2.563895004497276,
                2.7539176432187817,
                2.7734555547192494,
            ],
        ),
        # Fewer than two brackets with different sequence numbers.
        ([5] * 8, [1.0, 2.0, 3.0]),
        ([1, 2], [1.0]),
    ],
    ids=["no line", "minority", "one sequence number", "one anchor"],
)
def test_fit_gives_up_on_brackets_that_fit_no_line(seq, anchor_t):
    seq = np.array(seq)
    mag_line = np.arange(len(seq)) * 2  # magnetometer lines 0, 2, 4, ...
    anchor_line = np.arange(len(anchor_t)) * 4 + 3  # GGAs on lines 3, 7, 11, ...
    assert logparse._fit_mag(mag_line, seq, anchor_line, np.array(anchor_t)) is None


def test_fit_needs_brackets_at_different_sequence_numbers():
    # Two GGAs between the same two magnetometer lines: one bracket twice, no slope.
    mag_line, seq = np.array([1, 10]), np.array([4, 5])
    assert logparse._fit_mag(mag_line, seq, np.array([3, 7]), np.array([1.0, 2.0])) is None


# --- anchors ------------------------------------------------------------------------------


def test_no_gps_gives_nan_times_and_says_so():
    events = build(gps=False)
    parsed = parse(events)
    assert len(parsed.mag) and len(parsed.cesium) and len(parsed.gga) == 0
    assert np.all(np.isnan(parsed.mag.t)) and np.all(np.isnan(parsed.cesium.t))
    report = parsed.report
    assert not report.time_aligned and report.anchors == 0 and report.mag_timing == "none"
    assert parsed.date is None and parsed.epoch is None
    assert any(
        "no GGA with a fix and a time: all times are NaN" in message for message in report.messages
    )
    assert str(report).endswith("time: not aligned (0 GPS anchors), all times are NaN")
    arrays = to_arrays(parsed)
    assert (
        np.all(np.isnan(arrays.t))
        and np.all(np.isnan(arrays.cesium))
        and np.all(np.isnan(arrays.lat))
    )


def test_one_anchor_is_not_enough():
    events = [
        event for event in build(duration=3.0) if event.kind != "gga" or event.truth == 86_386
    ]
    parsed = parse(events)
    assert parsed.report.anchors == 1 and not parsed.report.time_aligned
    assert np.all(np.isnan(parsed.mag.t)) and np.all(np.isnan(parsed.gga.t))
    assert any("only one GGA" in message for message in parsed.report.messages)


def test_gga_without_fix_is_no_anchor():
    lines = [
        gga(36_000.0, 47.0, 8.0, quality=0),
        pmag1(5, 1.0, 2.0, 3.0),
        gga(36_001.0, 47.0, 8.0, quality=0),
        nmea_sentence(
            "GPGGA,,,,,,0,00,99.99,,,,,,"
        ),  # a receiver without any fix, from a real capture
    ]
    parsed = parse_log(b"".join(lines))
    assert parsed.bad == [] and parsed.report.anchors == 0
    assert list(parsed.gga.quality) == [0, 0, 0]
    assert (
        math.isnan(parsed.gga.time_of_day[2])
        and math.isnan(parsed.gga.lat[2])
        and math.isnan(parsed.gga.lon[2])
    )
    assert parsed.gga.satellites[2] == 0 and parsed.gga.hdop[2] == pytest.approx(99.99)
    assert math.isnan(parsed.gga.altitude[2])


def test_empty_gga_fields_are_missing_values():
    parsed = parse_log(nmea_sentence("GNGGA,123519.00,,,,,1,,,,M,,M,,"))
    assert parsed.bad == []
    assert parsed.gga.quality[0] == 1 and parsed.gga.satellites[0] == -1
    assert all(
        math.isnan(getattr(parsed.gga, name)[0]) for name in ("lat", "lon", "hdop", "altitude")
    )
    assert parsed.gga.time_of_day[0] == pytest.approx(12 * 3600 + 35 * 60 + 19)


def test_midnight_without_zda():
    events = build(with_zda=False, distractors=False)
    parsed = parse(events)
    assert parsed.date is None and parsed.epoch is None and len(parsed.zda) == 0
    assert parsed.report.midnight_rollovers == 1
    np.testing.assert_allclose(parsed.gga.t, [event.truth for event in of_kind(events, "gga")])
    assert np.max(np.abs(parsed.mag.t - arrivals(events, "mag"))) < MAG_TOL_30S
    assert any("no ZDA: the date is unknown" in message for message in parsed.report.messages)


def test_date_from_a_zda_after_midnight():
    # ZDA only after midnight: the first anchor (before midnight) is still on March 31.
    events = [event for event in build() if event.kind != "zda" or event.truth >= MIDNIGHT + 5]
    parsed = parse(events)
    assert parsed.zda.datetime[0] == dt.datetime(2024, 4, 1, 0, 0, 5)
    assert parsed.date == dt.date(2024, 3, 31)
    assert parsed.gga.t[0] < MIDNIGHT < parsed.gga.t[-1]


def test_date_from_zda_without_anchors():
    parsed = parse_log(zda(dt.datetime(2024, 6, 1, 10, 0, 1)))
    assert parsed.date == dt.date(2024, 6, 1) and not parsed.report.time_aligned
    empty = parse_log(nmea_sentence("GPZDA,,,,,,"))
    assert empty.bad == [] and empty.zda.datetime == [None] and empty.date is None


def test_a_date_carried_off_the_calendar_is_unknown_and_said():
    # The only ZDA is just after midnight of 0001-01-01; the first fix, before midnight,
    # would fall on a day before the calendar starts (OverflowError before issue 10).
    events = [event for event in build() if event.kind != "zda" or event.truth >= MIDNIGHT + 5]
    first = next(event for event in events if event.kind == "zda")
    first.line = zda(dt.datetime(1, 1, 1) + dt.timedelta(seconds=first.truth - MIDNIGHT))
    events = [event for event in events if event.kind != "zda" or event is first]
    parsed = parse(events)
    assert parsed.date is None and parsed.report.time_aligned
    assert any("falls outside the calendar" in message for message in parsed.report.messages)


def test_leap_second_in_zda():
    parsed = parse_log(nmea_sentence("GPZDA,235960.00,31,12,2016,00,00"))
    assert parsed.zda.datetime == [dt.datetime(2017, 1, 1)]


def test_gga_times_that_do_not_increase_are_left_out():
    events = build(duration=10.0, distractors=False)
    ggas = of_kind(events, "gga")
    stale = ggas[5]
    stale.line = gga(ggas[3].truth, *position(ggas[3].truth)[:2])  # repeats an older time
    parsed = parse(events)
    assert parsed.report.anchors == len(ggas) - 1 and parsed.report.anchors_not_increasing == 1
    assert any("did not increase" in message for message in parsed.report.messages)
    truth = arrivals(events, "mag")
    assert np.max(np.abs(parsed.mag.t - truth)) < MAG_TOL_30S


# --- bad lines ----------------------------------------------------------------------------

PMAG_BODY = "PMAG1,00001,+00001.0,+00002.0,+00003.0"
GGA_GOOD = gga(36_000.0, 47.5, 8.5)
GGA_BODY = GGA_GOOD[1 : GGA_GOOD.index(b"*")].decode()

BAD_CASES = [
    # checksum
    ("pmag wrong checksum", nmea_sentence(PMAG_BODY, checksum=0x00), "checksum"),
    ("pmag no checksum", f"${PMAG_BODY}\r\n".encode(), "checksum"),
    ("pmag non-hex checksum", f"${PMAG_BODY}*G1\r\n".encode(), "checksum"),
    ("gga wrong checksum", GGA_GOOD.replace(b"4730.00000", b"4730.00001"), "checksum"),
    ("rmc wrong checksum", rmc(DAY, 47.0, 8.0).replace(b",A,", b",V,", 1), "checksum"),
    # field count
    ("pmag four fields", nmea_sentence("PMAG1,00001,+00001.0,+00002.0"), "field_count"),
    ("pmag six fields", nmea_sentence(PMAG_BODY + ",+1.0"), "field_count"),
    ("gga short", nmea_sentence("GPGGA,120000.00,4730.00000,N"), "field_count"),
    ("zda short", nmea_sentence("GPZDA,120000.00,01,06,2024"), "field_count"),
    ("vtg short", nmea_sentence("GPVTG,045.0,T,,M,29.0,N"), "field_count"),
    ("cesium three fields", b"$ 49895.131,1249,1\r\n", "field_count"),
    ("cesium one field", b"$ 49895.131\r\n", "field_count"),
    # unparsable numbers and out-of-range fields
    ("pmag seq letters", nmea_sentence("PMAG1,0000A,+00001.0,+00002.0,+00003.0"), "number"),
    ("pmag seq too big", nmea_sentence("PMAG1,100000,+00001.0,+00002.0,+00003.0"), "number"),
    ("pmag seq empty", nmea_sentence("PMAG1,,+00001.0,+00002.0,+00003.0"), "number"),
    ("pmag x letters", nmea_sentence("PMAG1,00001,+0000x.0,+00002.0,+00003.0"), "number"),
    ("pmag y nan", nmea_sentence("PMAG1,00001,+00001.0,nan,+00003.0"), "number"),
    ("pmag z empty", nmea_sentence("PMAG1,00001,+00001.0,+00002.0,"), "number"),
    ("gga hour 24", nmea_sentence(GGA_BODY.replace("100000.00", "240000.00")), "number"),
    ("gga time letters", nmea_sentence(GGA_BODY.replace("100000.00", "10ab00.00")), "number"),
    ("gga minute 60", nmea_sentence(GGA_BODY.replace("100000.00", "106000.00")), "number"),
    ("gga latitude form", nmea_sentence(GGA_BODY.replace("4730.00000", "47.3")), "number"),
    (
        "gga latitude minutes",
        nmea_sentence(GGA_BODY.replace("4730.00000", "4775.00000")),
        "number",
    ),
    ("gga latitude 91", nmea_sentence(GGA_BODY.replace("4730.00000", "9100.00000")), "number"),
    ("gga hemisphere", nmea_sentence(GGA_BODY.replace(",N,", ",X,")), "number"),
    ("gga east west", nmea_sentence(GGA_BODY.replace(",E,", ",N,")), "number"),
    ("gga longitude form", nmea_sentence(GGA_BODY.replace("00830.00000", "830.00000")), "number"),
    (
        "gga quality letter",
        nmea_sentence(GGA_BODY.replace(",N,00830.00000,E,1,", ",N,00830.00000,E,A,")),
        "number",
    ),
    ("gga hdop", nmea_sentence(GGA_BODY.replace(",0.9,", ",0.9.1,")), "number"),
    ("zda month 13", nmea_sentence("GPZDA,120000.00,01,13,2024,00,00"), "number"),
    ("zda 31 april", nmea_sentence("GPZDA,120000.00,31,04,2024,00,00"), "number"),
    ("zda day letters", nmea_sentence("GPZDA,120000.00,x1,04,2024,00,00"), "number"),
    ("vtg speed", nmea_sentence("GPVTG,045.0,T,,M,fast,N,53.7,K,A"), "number"),
    ("vtg course", nmea_sentence("GPVTG,north,T,,M,29.0,N,53.7,K,A"), "number"),
    ("cesium field letters", b"$ 4989x.131,1249\r\n", "number"),
    ("cesium field short", b"$ 4989.131,1249\r\n", "number"),
    ("cesium signal letters", b"$ 49895.131,12a4\r\n", "number"),
    ("cesium prefix 2", b"$249895.131,1249\r\n", "number"),
    # values that overflowed a C int, an int64, the calendar or a double (OverflowError or
    # ValueError, and infinities, before issue 10)
    ("zda day of 19 digits", nmea_sentence("GPZDA,120000.00,9999999999999999999,04,2024,00,00"),
     "number"),
    ("zda leap second after 9999", nmea_sentence("GPZDA,235960.50,31,12,9999,00,00"), "number"),
    ("zda year of 5 digits", nmea_sentence("GPZDA,120000.00,01,04,20240,00,00"), "number"),
    (
        "gga quality 2^63",
        nmea_sentence(GGA_BODY.replace(",N,00830.00000,E,1,", f",N,00830.00000,E,{2**63},")),
        "number",
    ),
    ("gga satellites of 5000 digits", nmea_sentence(GGA_BODY.replace(",1,08,", ",1," + "9" * 5000
                                                                      + ",")), "number"),
    ("gga altitude of 400 digits", nmea_sentence(GGA_BODY.replace(",100.0,M,", ",1" + "0" * 400
                                                                      + ",M,")), "number"),
    ("pmag axis of 309 digits", nmea_sentence("PMAG1,00001," + "9" * 309 + ",+00002.0,+00003.0"),
     "number"),
    ("pmag axis at 100000", nmea_sentence("PMAG1,00001,+100000.0,+00002.0,+00003.0"), "number"),
    ("pmag seq of 5000 digits", nmea_sentence("PMAG1," + "1" * 5000 + ",+1.0,+2.0,+3.0"),
     "number"),
    # unknown sentences
    ("no dollar", b"hello world\r\n", "unknown_sentence"),
    ("lower case", b"$hello,world*00\r\n", "unknown_sentence"),
    ("lone dollar", b"$\r\n", "unknown_sentence"),
    ("pmag2", nmea_sentence("PMAG2,00001,+00001.0,+00002.0,+00003.0"), "unknown_sentence"),
    ("no address comma", nmea_sentence("GPGGA"), "unknown_sentence"),
    # bytes outside printable ASCII
    ("non-ascii degree sign", b"$GPGGA,12\xb000,*00\r\n", "bad_byte"),
    ("nul", b"$ 49895.131,1\x00249\r\n", "bad_byte"),
    ("stray cr", b"$ 49895.131\r,1249\r\n", "bad_byte"),
    ("tab", b"\t$ 49895.131,1249\r\n", "bad_byte"),
    ("cr cr lf", b"$ 49895.131,1249\r\r\n", "bad_byte"),
]


@pytest.mark.parametrize(
    ("line", "reason"), [case[1:] for case in BAD_CASES], ids=[case[0] for case in BAD_CASES]
)
def test_bad_line_is_reported_with_its_line_number(line, reason):
    good = build(duration=3.0)
    where = 17  # the bad line becomes line 17
    data = log_of(good[: where - 1]) + line + log_of(good[where - 1 :])
    parsed = parse_log(data, name="LOG00042.TXT", gps_latency=GPS_LATENCY)
    assert parsed.bad == [(where, reason)]
    assert parsed.report.bad[reason] == 1 and sum(parsed.report.bad.values()) == 1
    assert any(
        message.startswith(f"LOG00042.TXT:{where}: {reason}: ")
        for message in parsed.report.messages
    )
    # Everything else is still there.
    assert len(parsed.mag) == len(of_kind(good, "mag")) and len(parsed.cesium) == len(
        of_kind(good, "cesium")
    )
    assert parsed.report.time_aligned


def test_every_reason_has_a_case():
    assert {case[2] for case in BAD_CASES} | {"truncated"} == set(BAD_REASONS)


def test_many_bad_lines_counted_by_reason():
    lines = [case[1] for case in BAD_CASES]
    parsed = parse_log(b"".join(lines))
    assert [line for line, _ in parsed.bad] == list(range(1, len(lines) + 1))
    assert [reason for _, reason in parsed.bad] == [case[2] for case in BAD_CASES]
    for reason in BAD_REASONS:
        assert parsed.report.bad[reason] == sum(case[2] == reason for case in BAD_CASES)
    assert "checksum 5" in str(parsed.report)


def test_messages_say_what_is_wrong():
    parsed = parse_log(
        nmea_sentence(PMAG_BODY, checksum=0x00)
        + b"$ 49895.131,1\x00249\r\n"
        + nmea_sentence("GPZDA,120000.00,01,13,2024,00,00")
        + nmea_sentence("PMAG1,00001,+00001.0,+00002.0")
    )
    messages = parsed.report.messages
    assert (
        messages[0]
        == f"log:1: checksum: checksum 00 does not match the computed {0x00 ^ _xor(PMAG_BODY):02X}"
    )
    assert (
        messages[1] == "log:2: bad_byte: byte 0x00 at column 14 (only printable ASCII is allowed)"
    )
    assert messages[2].startswith("log:3: number: date 01,13,2024: month must be in 1..12")
    assert messages[3] == "log:4: field_count: $PMAG1 has 4 fields, not 5"


def _xor(text: str) -> int:
    value = 0
    for byte in text.encode():
        value ^= byte
    return value


@pytest.mark.parametrize(
    "cut", [1, 10, -3, -2, -1], ids=["after $", "mid", "before *hh", "before CR", "before LF"]
)
def test_truncated_final_line(cut):
    events = build(duration=3.0)
    data = log_of(events)
    last = events[-1].line
    assert len(last) > 12
    end = len(data) - len(last) + (cut if cut > 0 else len(last) + cut)
    parsed = parse_log(data[:end], gps_latency=GPS_LATENCY)
    assert parsed.bad == [(len(events), "truncated")]
    assert parsed.report.lines == len(events) and parsed.report.bad["truncated"] == 1
    assert any("the last line has no line end" in message for message in parsed.report.messages)
    whole = parse_log(data, gps_latency=GPS_LATENCY)
    kind = events[-1].kind
    if kind in ("mag", "cesium", "gga", "zda", "vtg"):
        assert len(getattr(parsed, kind)) == len(getattr(whole, kind)) - 1
    np.testing.assert_array_equal(parsed.mag.line, whole.mag.line[: len(parsed.mag)])
    np.testing.assert_array_equal(parsed.mag.b, whole.mag.b[: len(parsed.mag)])


def test_cut_exactly_at_a_line_end_is_not_truncated():
    events = build(duration=3.0)
    parsed = parse_log(log_of(events[:50]))
    assert parsed.bad == [] and parsed.report.lines == 50


def test_frame_cut_short_by_a_dollar():
    cut = pmag1(7, 1.0, 2.0, 3.0)[:15]
    line = cut + GGA_GOOD
    parsed = parse_log(pmag1(6, 1.0, 2.0, 3.0) + line + b"xx" + cesium(49_895.131, 1249))
    assert parsed.bad == [(2, "truncated"), (3, "truncated")]
    assert "before the '$' at column 16 is a cut frame" in parsed.report.messages[0]
    assert (
        list(parsed.gga.line) == [2]
        and list(parsed.cesium.line) == [3]
        and list(parsed.mag.line) == [1]
    )


def test_blank_lines_are_counted_not_bad():
    parsed = parse_log(b"\r\n" + pmag1(1, 1.0, 2.0, 3.0) + b"\n\r\n")
    assert parsed.bad == [] and parsed.report.blank_lines == 3 and len(parsed.mag) == 1
    assert list(parsed.mag.line) == [2] and parsed.report.lines == 4


def test_dropped_sentences_are_ignored_not_bad():
    lines = [
        rmc(DAY, 47.0, 8.0),
        gsa([1, 2, 3]),
        gsv(
            [(1, 40, 100, 30), (2, 10, 200, None), (3, 80, 300, 45), (4, 5, 10, 20), (5, 6, 7, 8)]
        ),
        nmea_sentence("PGRME,15.0,M,45.0,M,25.0,M"),
        nmea_sentence("GNTXT,01,01,02,u-blox AG"),
    ]
    parsed = parse_log(b"".join(lines))
    assert parsed.bad == []
    assert parsed.ignored == [
        (1, "GPRMC"),
        (2, "GPGSA"),
        (3, "GPGSV"),
        (4, "GPGSV"),
        (5, "PGRME"),
        (6, "GNTXT"),
    ]
    assert parsed.report.ignored == {"GPRMC": 1, "GPGSA": 1, "GPGSV": 2, "PGRME": 1, "GNTXT": 1}


# --- formats ------------------------------------------------------------------------------


def test_any_talker_and_lower_case_checksum():
    body = "BDGGA,010001.00,3330.00000,S,07015.00000,W,2,12,0.7,-4.0,M,20.0,M,,"
    assert any(c in "abcdef" for c in f"{nmea_checksum(body):02x}")
    lines = [
        gga(3600.0, -33.5, -70.25, talker="GN", quality=4, altitude_m=-12.5),
        zda(dt.datetime(2024, 1, 2, 3, 4, 5), talker="GL"),
        vtg(270.0, 10.0, talker="GA"),
        f"${body}*{nmea_checksum(body):02x}\r\n".encode(),
    ]
    parsed = parse_log(b"".join(lines))
    assert (
        parsed.bad == [] and len(parsed.gga) == 2 and len(parsed.zda) == 1 and len(parsed.vtg) == 1
    )
    np.testing.assert_allclose(parsed.gga.lat, [-33.5, -33.5])
    np.testing.assert_allclose(parsed.gga.lon, [-70.25, -70.25])
    assert list(parsed.gga.quality) == [4, 2]
    assert parsed.gga.altitude[0] == -12.5
    assert parsed.vtg.course[0] == 270.0


def test_vtg_speed_from_kmh_and_old_form():
    parsed = parse_log(
        nmea_sentence("GPVTG,054.7,T,034.4,M,,N,010.2,K,A")  # no knots: km/h
        + nmea_sentence("GPVTG,054.7,T,034.4,M,005.5,N,010.2,K")  # before NMEA 2.3: no mode
        + nmea_sentence("GPVTG,,T,,M,,N,,K,N")  # no fix
    )
    assert parsed.bad == []
    np.testing.assert_allclose(parsed.vtg.speed[:2], [10.2 / 3.6, 5.5 * 1852 / 3600])
    assert math.isnan(parsed.vtg.speed[2]) and math.isnan(parsed.vtg.course[2])


def test_cesium_high_range():
    parsed = parse_log(b"$149895.131,0001\r\n$ 00000.000,0000\n")
    np.testing.assert_allclose(parsed.cesium.field, [149_895.131, 0.0])
    assert list(parsed.cesium.signal) == [1, 0]


def test_empty_log():
    parsed = parse_log(b"")
    assert parsed.bad == [] and parsed.ignored == [] and parsed.date is None
    for records in (parsed.mag, parsed.cesium, parsed.gga, parsed.zda, parsed.vtg):
        assert (
            len(records) == 0 and records.t.dtype == np.float64 and records.line.dtype == np.int64
        )
    assert parsed.mag.b.shape == (0, 3) and parsed.mag.seq.dtype == np.int64
    report = parsed.report
    assert report.lines == 0 and report.bytes == 0 and not report.time_aligned
    assert report.counts == {"mag": 0, "cesium": 0, "gga": 0, "zda": 0, "vtg": 0}
    assert report.messages[0] == "log: the log is empty"
    assert len(to_arrays(parsed)) == 0


def test_accepts_bytearray_and_memoryview():
    data = pmag1(1, 1.0, 2.0, 3.0) + pmag1(2, 1.0, 2.0, 3.0)
    for form in (bytearray(data), memoryview(data)):
        assert list(parse_log(form).mag.seq) == [1, 2]


@pytest.mark.parametrize(
    ("kwargs", "error", "message"),
    [
        ({"data": "$ 49895.131,1249\n"}, TypeError, "Log data must be bytes, not str"),
        ({"name": 3}, TypeError, "Log name must be a str, not int"),
        (
            {"gps_latency": -0.1},
            ValueError,
            "GPS latency must be a finite number of seconds >= 0, not -0.1",
        ),
        (
            {"gps_latency": math.nan},
            ValueError,
            "GPS latency must be a finite number of seconds >= 0, not nan",
        ),
        (
            {"gps_latency": True},
            ValueError,
            "GPS latency must be a finite number of seconds >= 0, not True",
        ),
        (
            {"gps_latency": "0.1"},
            ValueError,
            "GPS latency must be a finite number of seconds >= 0, not '0.1'",
        ),
    ],
)
def test_parse_log_checks_its_arguments(kwargs, error, message):
    arguments = {"data": b""} | kwargs
    data = arguments.pop("data")
    with pytest.raises(error, match=f"^{re.escape(message)}$"):
        parse_log(data, **arguments)


def test_report_text(survey):
    _, parsed = survey
    text = str(parsed.report)
    assert text.startswith("LOG00001.TXT: 1053 lines")
    assert "ignored: GPGSA 31, GPRMC 31" in text
    assert "31 GGA anchors" in text and "magnetometer by sequence at 19.94" in text
    assert "0 of 30 brackets rejected, 0 samples by line" in text
    fallback = parse(
        [
            event
            for event in build(duration=10.0)
            if event.kind != "mag" or event.arrival > 86_395.2
        ]
    )
    assert str(fallback.report).endswith("magnetometer by line")


# --- to_arrays ----------------------------------------------------------------------------


def test_to_arrays_interpolates_references_to_magnetometer_times(survey):
    events, parsed = survey
    arrays = to_arrays(parsed)
    n = len(parsed.mag)
    assert arrays.b.shape == (
        n,
        3,
    ) and arrays.t.shape == arrays.cesium.shape == arrays.lat.shape == (n,)
    np.testing.assert_array_equal(arrays.t, parsed.mag.t)
    np.testing.assert_array_equal(arrays.seq, parsed.mag.seq)
    np.testing.assert_array_equal(arrays.line, parsed.mag.line)
    assert arrays.date == parsed.date
    inside = (arrays.t >= parsed.cesium.t[0]) & (arrays.t <= parsed.cesium.t[-1])
    assert np.all(np.isnan(arrays.cesium[~inside])) and np.all(np.isfinite(arrays.cesium[inside]))
    assert np.count_nonzero(inside) > 0.9 * n
    # The cesium truth is a ramp of 0.02 nT/s: timing errors of a few tenths of a second
    # stay below 0.01 nT, and the line-timing's arrival offset (~19 ms) is negligible.
    expected = np.array([cesium_field(t) for t in arrays.t[inside]])
    np.testing.assert_allclose(arrays.cesium[inside], expected, atol=0.01)
    fix = (arrays.t >= parsed.gga.t[0]) & (arrays.t <= parsed.gga.t[-1])
    assert np.all(np.isnan(arrays.lat[~fix]))
    lat, lon, alt = position(arrays.t[fix])
    np.testing.assert_allclose(arrays.lat[fix], lat, atol=2e-7)
    np.testing.assert_allclose(arrays.lon[fix], lon, atol=2e-7)
    np.testing.assert_allclose(arrays.alt[fix], alt, atol=0.06)


def test_to_arrays_leaves_gaps_empty():
    events = build(distractors=False)
    events = [
        event
        for event in events
        if event.kind != "cesium" or not 86_395.0 < event.arrival < 86_400.0
    ]
    parsed = parse(events)
    arrays = to_arrays(parsed)
    in_gap = (arrays.t > 86_395.2) & (arrays.t < 86_399.8)
    assert np.count_nonzero(in_gap) > 50 and np.all(np.isnan(arrays.cesium[in_gap]))
    assert np.all(np.isfinite(arrays.cesium[(arrays.t > 86_387.0) & (arrays.t < 86_394.0)]))
    bridged = to_arrays(parsed, max_gap=10.0)
    assert np.all(np.isfinite(bridged.cesium[in_gap]))


def test_to_arrays_interpolates_longitude_across_the_date_line():
    lines = [
        gga(0.0, 10.0, 179.9999),
        pmag1(0, 1.0, 2.0, 3.0),
        pmag1(1, 1.0, 2.0, 3.0),
        gga(1.0, 10.0, -179.9999),
        pmag1(2, 1.0, 2.0, 3.0),
        pmag1(3, 1.0, 2.0, 3.0),
        gga(2.0, 10.0, -179.9997),
    ]
    arrays = to_arrays(parse_log(b"".join(lines)))
    inside = np.isfinite(arrays.lon)
    assert np.count_nonzero(inside) >= 2
    assert np.all(np.abs(arrays.lon[inside]) > 179.999)


def test_interpolate_edge_cases():
    t_src = np.array([0.0, 1.0, 2.0, 10.0, 11.0])
    y_src = t_src * 2
    out = logparse._interpolate(
        t_src, y_src, np.array([-1.0, 0.0, 0.5, 2.0, 5.0, 10.0, 11.0, 12.0, math.nan]), 1.5
    )
    np.testing.assert_array_equal(out[[1, 2, 3, 5, 6]], [0.0, 1.0, 4.0, 20.0, 22.0])
    assert np.all(np.isnan(out[[0, 4, 7, 8]]))
    assert np.all(
        np.isnan(logparse._interpolate(np.array([1.0]), np.array([1.0]), np.array([1.0]), None))
    )


@pytest.mark.parametrize(
    ("argument", "error", "message"),
    [
        ({"parsed": "log"}, TypeError, "Expected a ParsedLog from parse_log, not str"),
        (
            {"max_gap": 0.0},
            ValueError,
            "Maximum gap must be a positive number of seconds, not 0.0",
        ),
        ({"max_gap": -1}, ValueError, "Maximum gap must be a positive number of seconds, not -1"),
        (
            {"max_gap": True},
            ValueError,
            "Maximum gap must be a positive number of seconds, not True",
        ),
        (
            {"max_gap": math.nan},
            ValueError,
            "Maximum gap must be a positive number of seconds, not nan",
        ),
    ],
)
def test_to_arrays_checks_its_arguments(argument, error, message):
    arguments = {"parsed": parse_log(b"")} | argument
    with pytest.raises(error, match=f"^{re.escape(message)}$"):
        to_arrays(arguments.pop("parsed"), **arguments)


# --- bulk reading ---------------------------------------------------------------------------
# parse_log reads the lines in the logger's own forms with array operations and every other
# line on its own; logparse._parse(..., per_line=True) reads every line on its own. Both must
# give the same ParsedLog, bit for bit.


def assert_identical(fast, slow, where: str = "parsed") -> None:
    """Equal values of equal types, arrays equal in dtype, shape and bytes (-0.0, NaN)."""
    if dataclasses.is_dataclass(fast):
        assert type(fast) is type(slow), where
        for member in dataclasses.fields(fast):
            assert_identical(
                getattr(fast, member.name), getattr(slow, member.name), f"{where}.{member.name}"
            )
    elif isinstance(fast, np.ndarray):
        assert isinstance(slow, np.ndarray), where
        assert (fast.dtype, fast.shape) == (slow.dtype, slow.shape), where
        assert fast.tobytes() == slow.tobytes(), where
    elif isinstance(fast, (list, tuple)):
        assert type(fast) is type(slow) and len(fast) == len(slow), where
        for index, (one, other) in enumerate(zip(fast, slow)):
            assert_identical(one, other, f"{where}[{index}]")
    elif isinstance(fast, dict):
        assert type(slow) is dict and list(fast) == list(slow), where
        for key in fast:
            assert_identical(fast[key], slow[key], f"{where}[{key!r}]")
    elif isinstance(fast, float) and math.isnan(fast):
        assert type(slow) is float and math.isnan(slow), where
    else:
        assert type(fast) is type(slow) and fast == slow, (where, fast, slow)


def _lower_hex(body: str) -> bytes:
    """A sentence whose checksum is written in lower case (a letter in it)."""
    assert re.search("[a-f]", f"{nmea_checksum(body):02x}")
    return f"${body}*{nmea_checksum(body):02x}\r\n".encode()


#: Good lines in or near the logger's forms and in other forms, lines one byte away from the
#: forms, and every bad line of BAD_CASES: mixed into a survey by test_bulk_and_per_line_agree.
EDGE_LINES = [
    _lower_hex("PMAG1,00001,+00001.0,+00002.0,+00001.0"),
    nmea_sentence("PMAG1,00002,-00000.0,+99999.9,-99999.9"),  # -0.0 and the form's limits
    nmea_sentence("PMAG1,99999,-12345.6,+00000.0,-00000.1"),
    nmea_sentence("PMAG1,7,1.5,-2,+3.25"),  # good, not the logger's form
    nmea_sentence("PMAG1,00003,+000001.0,+0002.0,+00003.0"),  # good, fields of other widths
    nmea_sentence("PMAG1,00001, 00001.0,+00002.0,+00003.0"),  # space for the sign: number
    nmea_sentence("PMAG1,0000:,+00001.0,+00002.0,+00003.0"),  # ':' follows '9': number
    nmea_sentence("PMAG1,0000/,+00001.0,+00002.0,+00003.0"),  # '/' precedes '0': number
    nmea_sentence("PMAG1;00001,+00001.0,+00002.0,+00003.0"),  # no address comma
    nmea_sentence("PMAG1,00001,+00001.0,+00002.0,+00003.0").replace(b"*", b"#"),
    nmea_sentence("PMAG1,00001,+00001.0,+00002.0,+00003.0").replace(b"$", b"!"),
    b"$PMAG1,00001,+00001.0,+00002.0,+00003.0*g0\r\n",
    b"xx" + pmag1(5, 1.0, 2.0, 3.0),  # a cut frame before a good one
    b"$PMAG1,00001,+0$" + pmag1(6, -1.0, -2.0, -3.0),
    b"xx" + cesium(49_895.2, 1249),
    b"$149895.131,0001\r\n",  # cesium, high range
    b"$100000.000,9999\r\n",
    b"$ 00000.000,0000\r\n",
    b"$ 49895.131,1249\n",  # bare LF in a CR LF log
    b"$ 49895.1311249\r\n",
    b"$ 49895.131;1249\r\n",
    b"$ 49895.131,124\r\n",
    b"$ 49895.131,12490\r\n",
    b"$049895.131,1249\r\n",  # a digit, not the range: number
    b"$ 4989\x005.131,1249\r\n",
    b"$ 49895,131,1249\r\n",
    b"$ 49895.131,1249 \r\n",
    b"\r\n",
    b"\n",
    rmc(DAY, 47.0, 8.0),
    gsa([1, 2, 3]),
    nmea_sentence("GPGGA,,,,,,0,00,,,M,,M,,"),  # a receiver without a fix
    _lower_hex(GGA_BODY.replace(",E,1,08,", ",E,1,12,")),
    *[
        nmea_sentence(GGA_BODY.replace(old, new))
        for old, new in [
            ("100000.00", "235960.99"),  # a leap second
            ("100000.00", "100000"),
            ("100000.00", "100000."),
            ("100000.00", "1000000.00"),  # number
            ("100000.00", "10000.00"),  # number
            ("100000.00", ""),
            ("4730.00000", "4730"),
            ("4730.00000", "4759.99999"),
            ("4730.00000", "9000.00000"),
            ("4730.00000", "9000.00001"),  # number
            ("4730.00000", "47.30"),  # number
            ("4730.00000,N", ","),
            ("4730.00000,N", "4730.00000,"),  # number
            ("4730.00000,N", ",N"),  # number
            (",N,", ",NN,"),  # number
            (",N,", ",n,"),  # number
            (",N,", ",S,"),
            ("00830.00000,E", "18000.0000,W"),
            ("00830.00000,E", "18000.0001,W"),  # number
            (",E,1,08,", ",E,9,999,"),
            (",E,1,08,", ",E,10,08,"),  # number
            (",E,1,08,", ",E,1,1000,"),  # number
            (",E,1,08,", ",E,01,0008,"),
            (",E,1,08,", ",E,,,"),
            (",0.9,", ",.5,"),
            (",0.9,", ",5.,"),
            (",0.9,", ",+0.9,"),
            (",0.9,", ",.,"),  # number
            (",0.9,", ",+,"),  # number
            (",0.9,", ",1e5,"),  # number
            (",0.9,", ",0.9.,"),  # number
            (",0.9,", ",1234567890.12345,"),  # 15 digits
            (",0.9,", ",12345678901.12345,"),  # 16 digits
            (",0.9,", ",1234567890123456,"),
            (",100.0,", ",-0.0,"),
            (",100.0,", ",-12.25,"),
            (",M,45.0,M,,", ",M,45.0,M,*,"),  # a '*' in a field: read line by line
            (",M,45.0,M,,", ",M,45.0,M,,,"),  # field_count
            ("GPGGA", "G1GGA"),  # unknown_sentence
            ("GPGGA", "gpGGA"),  # unknown_sentence
        ]
    ],
    b"$GPGGA,10$" + GGA_GOOD,
    *[
        nmea_sentence("GPZDA," + fields)
        for fields in [
            "235960.50,31,12,2024,00,00",
            "120000.00,29,02,2023,00,00",  # number
            "120000.00,1,2,0001,00,00",
            "120000.00,01,01,0000,00,00",  # number
            "120000.00,01,01,10000,00,00",  # number
            ",,,,00,00",
            "120000.00,,,,,",
            "120000.00,01,01,2024,+01,x",
            "120000.00,01,01,2024,00",  # field_count
            "120000.00,01,02,2024,00,*",  # a '*' in a field: read line by line
        ]
    ],
    b"xx" + zda(DAY + dt.timedelta(hours=5)),
    gga(36_000.0, -33.5, -70.25, talker="GN", quality=4, altitude_m=-12.5),
    vtg(270.0, 10.0, talker="GA"),
    *[
        nmea_sentence("GPVTG," + fields)
        for fields in [
            "045.0,T,,M,29.0,N,53.7,K",  # NMEA before 2.3: no mode
            "045.0,T,,M,,N,53.7,K,A",  # speed from km/h
            ",T,,M,,N,,K,N",
            "-0.0,T,,M,-0.0,N,53.7,K,A",
            "045.0,T,,M,29.0,N,53.7,K,A,",  # field_count
            "045.0,T,,M,29.0,N,5*3.7,K,A",  # a '*' in a field: number, line by line
            "045.0,T,,M,29,N,53.7,K,*",  # a '*' in a field: read line by line
        ]
    ],
    *[case[1] for case in BAD_CASES],
]


@pytest.mark.parametrize(
    ("seed", "eol", "block"),
    [(1, CRLF, None), (2, LF, None), (3, CRLF, None), (4, CRLF, 37), (5, LF, 1)],
    ids=["crlf", "lf", "crlf-cut", "blocks-of-37", "blocks-of-1"],
)
def test_bulk_and_per_line_agree(seed, eol, block, monkeypatch):
    if block is not None:  # many blocks of lines (see logparse._BULK_BLOCK_LINES)
        monkeypatch.setattr(logparse, "_BULK_BLOCK_LINES", block)
    rng = np.random.default_rng(seed)
    lines = [event.line for event in build(duration=20.0, seed=seed, eol=eol)]
    for line in EDGE_LINES:
        lines.insert(int(rng.integers(0, len(lines) + 1)), line)
    data = b"".join(lines)
    if seed in (3, 5):
        data += lines[int(rng.integers(0, len(lines)))][:-1]  # a last line without its end
    fast = parse_log(data, name="LOG00007.TXT", gps_latency=GPS_LATENCY)
    slow = logparse._parse(data, "LOG00007.TXT", GPS_LATENCY, per_line=True)
    assert_identical(fast, slow)
    # Not vacuous: every reason occurs, most samples were read in bulk and some line by line.
    assert all(fast.report.bad.values())
    reader = logparse._Reader(data, "log")
    reader.read()
    for kind in ("mag", "cesium", "gga", "zda", "vtg"):
        in_bulk = sum(len(block[0]) for block in reader.bulk[kind])
        assert in_bulk > 0.9 * len(getattr(fast, kind)), kind
        assert getattr(reader, kind), kind


def test_bulk_and_per_line_agree_on_a_clean_survey(survey):
    events, parsed = survey
    data = log_of(events)
    slow = logparse._parse(data, "LOG00001.TXT", GPS_LATENCY, per_line=True)
    assert_identical(parsed, slow)


#: Bytes a mutation writes: the ones the forms are made of and some they exclude.
MUTATION_BYTES = b"0123456789+-., *$:/AaFfGgNSEWMKTnx\r\n\x00\x7f\xb0"


@pytest.mark.parametrize("seed", range(4))
def test_bulk_and_per_line_agree_on_mutated_logs(seed):
    """Random bytes written over a short survey, many times: whatever a line becomes, both
    readings agree."""
    rng = np.random.default_rng(seed)
    clean = bytearray(log_of(build(duration=4.0, seed=seed, eol=(CRLF, LF)[seed % 2])))
    for _ in range(60):
        data = bytearray(clean)
        for where in rng.integers(0, len(data), size=int(rng.integers(1, 40))):
            data[where] = MUTATION_BYTES[int(rng.integers(0, len(MUTATION_BYTES)))]
        data = bytes(data[: int(rng.integers(len(data) // 2, len(data) + 1))])
        assert_identical(
            parse_log(data, gps_latency=GPS_LATENCY),
            logparse._parse(data, "log", GPS_LATENCY, per_line=True),
        )
