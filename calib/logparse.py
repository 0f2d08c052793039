"""Log parser: the text of a ``LOGnnnnn.TXT`` → per-instrument arrays on one time base.

The log holds the kept ``$``-frames verbatim in arrival order (``docs/architecture.md``,
"What is on the wire and on the card"): magnetometer
``$PMAG1,SSSSS,±XXXXX.X,±YYYYY.Y,±ZZZZZ.Z*hh``, cesium
``$ 49895.131,1249`` / ``$149895.131,0001``, and NMEA GGA, ZDA and VTG of any talker. Line
ends are CR LF or a bare LF. :func:`parse_log` reads every line, never raises on content,
and returns a :class:`ParsedLog`; :func:`to_arrays` gives what calibration needs.

Lines
-----
Lines are numbered from 1, as a text editor numbers them. A line that is not a good frame
goes to :attr:`ParsedLog.bad` as ``(line_number, reason)`` with one of the reasons of
:data:`BAD_REASONS`:

``truncated``
    the last line of the file has no line end (a cut write), or a ``$`` inside a line cut the
    frame before it short (the part before the last ``$`` is reported, the rest is parsed);
``bad_byte``
    a byte outside printable ASCII 0x20-0x7E (non-ASCII, NUL, a stray CR);
``unknown_sentence``
    not one of the three frame forms (no ``$``, ``$hello``, ``$PMAG2``, ...);
``checksum``
    ``$PMAG1`` or NMEA without a final ``*hh``, or with a wrong XOR;
``field_count``
    the wrong number of comma-separated fields for the sentence;
``number``
    a field that does not parse or is out of range (time ``246000``, month 13, hemisphere
    ``X``, a ``$PMAG1`` axis at or beyond the form's ±100,000 nT, a fix quality above 9, a
    ZDA year of five digits or a date past 9999-12-31, a number beyond a double's range).

Well-formed NMEA sentences with a good checksum that the logger would have dropped (RMC,
GSA, GSV, proprietary ``$P...``) are not bad: they are counted in ``report.ignored`` and
listed in :attr:`ParsedLog.ignored`. Blank lines are counted and skipped. Empty NMEA fields
(a receiver without a fix) give NaN (floats) or -1 (integers), not errors.

Speed: the lines in the plain forms (``$PMAG1`` and cesium in the logger's fixed widths, GGA,
ZDA and VTG with a good checksum and plain numbers of up to 15 digits: nearly every line of a
real log) are read in bulk with array operations; every other line, good or bad, is read on
its own, and both readings give the same results bit for bit (tests/calib/test_logparse.py).
A one-hour 50 Hz log (8.6 MiB) takes about 0.1 s on one thread, ten times as long a log ten
times as long (bench/calib/parse_speed.py).

Time alignment
--------------
The log has no timestamps of its own; times come from GPS. All times ``t`` are seconds
since 00:00:00 UTC of :attr:`ParsedLog.date`, the UTC date at the first anchor (taken from
ZDA); without ZDA the date is ``None`` and ``t`` counts from midnight of that unknown day.

1. **Anchors.** Every GGA with a fix (quality 1-9) and a time of day is an anchor. Its time
   of day is unrolled over midnight (a step back of more than 12 h adds a day), and the
   calendar day comes from the first ZDA with a date: it gives the day of the anchor nearest
   to it in the log, hence of the first anchor. Anchors whose time does not increase are
   left out. A GGA line arrives some time after its epoch (receiver
   latency plus 9600 baud transmission); ``gps_latency`` (default 0) says how long, and the
   anchor's line is placed at ``epoch + gps_latency``.
2. **Lines between anchors** (cesium, ZDA, VTG): the time of a line is interpolated
   linearly in its line number between the surrounding anchors: the lines that arrived
   between two GGAs are spread evenly between those two times. Before the first and after
   the last anchor, times are extrapolated at the mean line rate of the whole log (lines
   per second between the first and last anchor). These are arrival times; the GPS burst
   after each GGA (several long lines within a few tenths of a second) skews the even
   spread, so expect errors up to about 0.2 s.
3. **Magnetometer**: its samples are timed by their own sequence numbers, ``t = t0 +
   seq / rate``, so that bursts in the arrival order do not distort time. For each anchor,
   the magnetometer lines just before and just after the GGA line bracket its time: the
   unwrapped sequence number "at" the anchor lies between theirs, and their mean is taken.
   A straight line ``anchor time = t0 + seq_mid / rate`` is fitted to these pairs: first
   robustly (Theil-Sen: the median of the slopes between all pairs of brackets, then the
   median intercept), then by least squares weighted by 1 / bracket width², leaving out
   anchors further from the line than their bracket allows, until nothing changes. One
   bracket is only good to ± half a sample period, but the sensor and GPS clocks are not
   locked, so the phase between them moves and the fit averages the brackets down (at
   20 Hz: about 10 ms over 30 s of log, 2 ms over two minutes; clocks that stayed locked
   would leave ± half a period). These too are arrival times. One rate holds for the whole
   log: a sensor clock that changes its rate during the flight, or a sensor restart, shows
   as rejected anchors and a large fit residual in the report. With fewer than two usable
   brackets, or more rejected than kept, the magnetometer falls back to step 2; so does
   any sample whose sequence time is more than 2 s from its line time (plus 10 % of the
   time by which it lies beyond the first or last anchor): the minority side of a restart.
4. **No GPS**: with fewer than two anchors every ``t`` is NaN and the report says so.

GGA records keep their own epoch (``gga.t``): the anchor's time without ``gps_latency``, or
for a GGA that is no anchor, its line time minus ``gps_latency``.
"""

from __future__ import annotations

import datetime as _dt
import math
import re
from collections import Counter
from dataclasses import dataclass, field

import numpy as np

__all__ = [
    "BAD_REASONS",
    "SEQ_MODULUS",
    "MagData",
    "CesiumData",
    "GgaData",
    "ZdaData",
    "VtgData",
    "LogReport",
    "ParsedLog",
    "CalibrationArrays",
    "parse_log",
    "to_arrays",
]

# --- reasons ------------------------------------------------------------------------------

TRUNCATED = "truncated"
BAD_BYTE = "bad_byte"
UNKNOWN_SENTENCE = "unknown_sentence"
CHECKSUM = "checksum"
FIELD_COUNT = "field_count"
NUMBER = "number"
#: Every reason a line can be bad for, in the order they are checked.
BAD_REASONS = (TRUNCATED, BAD_BYTE, UNKNOWN_SENTENCE, CHECKSUM, FIELD_COUNT, NUMBER)

# --- formats ------------------------------------------------------------------------------
# Ref: docs/architecture.md and docs/frame-rules.md; NMEA 0183 v4.11 §5.2 (sentence, checksum), §6.3 (GGA, VTG,
# ZDA fields); Geometrics G-882 manual, RS-232 output.

#: The magnetometer's sequence counter runs 00000..99999 and wraps.
SEQ_MODULUS = 100_000
_PMAG_ADDRESS = "PMAG1"
_PMAG_FIELDS = 5  # PMAG1, seq, x, y, z
_CESIUM_FIELD_RE = re.compile(r"[ 1]\d{5}\.\d{3}\Z")
_CESIUM_SIGNAL_RE = re.compile(r"\d{4}\Z")
_CESIUM_HIGH_RANGE_NT = 100_000.0
_ADDRESS_RE = re.compile(r"\$(?:PMAG1|[A-Z]{5}),")
_NMEA_KEPT = ("GGA", "ZDA", "VTG")
_CHECKSUM_RE = re.compile(r"\*([0-9A-Fa-f]{2})\Z")
_GGA_FIELDS = (15,)  # address + 14 data fields
_ZDA_FIELDS = (7,)  # address, time, day, month, year, zone hours, zone minutes
_VTG_FIELDS = (9, 10)  # address + 8 data fields, NMEA 2.3 and later add the mode
_BAD_BYTE_RE = re.compile(rb"[^\x20-\x7e]")
_DECIMAL_RE = re.compile(r"[+-]?(?:\d+(?:\.\d*)?|\.\d+)\Z")
_UINT_RE = re.compile(r"\d+\Z")
_TIME_RE = re.compile(r"(\d{2})(\d{2})(\d{2}(?:\.\d*)?)\Z")
_LAT_RE = re.compile(r"(\d{2})(\d{2}(?:\.\d*)?)\Z")
_LON_RE = re.compile(r"(\d{3})(\d{2}(?:\.\d*)?)\Z")
_HOURS_PER_DAY = 24
_MINUTES_PER_HOUR = 60
_SECONDS_PER_MINUTE = 60
_MAX_SECOND = 61  # exclusive; a leap second is 60
_SECONDS_PER_DAY = 86_400.0
_HALF_DAY = _SECONDS_PER_DAY / 2
_LAT_LIMIT = 90.0
_LON_LIMIT = 180.0
_KNOT_M_S = 1852.0 / 3600.0
_KMH_M_S = 1000.0 / 3600.0
_MISSING_INT = -1
#: The $PMAG1 form is ±XXXXX.X: anything at or beyond 100,000 nT is not a reading.
_PMAG_LIMIT_NT = 100_000.0
#: Largest values of the integer fields (NMEA 0183 §6.3): the GGA fix quality is one digit,
#: the satellite count at most two (three allowed), ZDA's day and month two digits (the
#: calendar itself is checked by datetime), the year four.
_MAX_QUALITY = 9
_MAX_SATELLITES = 999
_MAX_DAY = 99
_MAX_MONTH = 99
_MAX_YEAR = 9999

# --- alignment ----------------------------------------------------------------------------

#: Fit iterations of the magnetometer rate before giving up on convergence.
_FIT_ITERATIONS = 10
#: Brackets used for the robust start of the magnetometer fit (all pairs of them).
_THEIL_SEN_POINTS = 600
#: Residual allowed in the first pass of the fit, in bracket widths (later passes: one).
_FIRST_PASS_WIDTHS = 4.0
#: A report message when more than this share of the magnetometer brackets are rejected.
_OUTLIER_WARNING_SHARE = 0.1
#: Seconds a magnetometer sample's sequence time may differ from its line time (which is good
#: to a few tenths of a second) before the line time is taken instead.
_MAX_SEQUENCE_LINE_DISAGREEMENT = 2.0
#: ... plus this share of the time by which the line time lies beyond the first or last anchor.
_DISAGREEMENT_GROWTH = 0.1
#: Default interpolation gap in :func:`to_arrays`, in median sample intervals of the source.
_GAP_INTERVALS = 5.0


class _BadLine(Exception):
    def __init__(self, reason: str, detail: str):
        super().__init__(detail)
        self.reason = reason
        self.detail = detail


# --- result types -------------------------------------------------------------------------


@dataclass(frozen=True, eq=False)
class MagData:
    """``$PMAG1`` samples in log order."""

    line: np.ndarray  #: int64 line numbers (from 1)
    seq: np.ndarray  #: int64 sequence numbers, unwrapped: ``seq % SEQ_MODULUS`` is the sent value
    b: np.ndarray  #: float64 (N, 3) field in nT
    t: np.ndarray  #: float64 seconds (see the module docstring), NaN without GPS
    seq_gaps: int  #: places where the sequence skips forward (samples lost)
    seq_missing: int  #: samples lost in those gaps
    seq_repeats: int  #: places where a sequence number repeats

    def __len__(self) -> int:
        return len(self.line)


@dataclass(frozen=True, eq=False)
class CesiumData:
    """Cesium readings in log order."""

    line: np.ndarray  #: int64 line numbers
    field: np.ndarray  #: float64 total field in nT
    signal: np.ndarray  #: int64 signal level 0..9999
    t: np.ndarray  #: float64 arrival times

    def __len__(self) -> int:
        return len(self.line)


@dataclass(frozen=True, eq=False)
class GgaData:
    """GGA fixes in log order; empty fields are NaN (floats) or -1 (integers)."""

    line: np.ndarray  #: int64
    time_of_day: np.ndarray  #: float64 UTC seconds since midnight as sent
    lat: np.ndarray  #: float64 degrees, north positive
    lon: np.ndarray  #: float64 degrees, east positive
    quality: np.ndarray  #: int64 fix quality (0 = no fix)
    satellites: np.ndarray  #: int64
    hdop: np.ndarray  #: float64
    altitude: np.ndarray  #: float64 m above mean sea level
    t: np.ndarray  #: float64 the fix's epoch on the log's time base

    def __len__(self) -> int:
        return len(self.line)


@dataclass(frozen=True, eq=False)
class ZdaData:
    """ZDA date and time sentences in log order."""

    line: np.ndarray  #: int64
    datetime: list  #: naive UTC :class:`datetime.datetime`, or None for empty fields
    t: np.ndarray  #: float64 arrival times

    def __len__(self) -> int:
        return len(self.line)


@dataclass(frozen=True, eq=False)
class VtgData:
    """VTG course and speed in log order."""

    line: np.ndarray  #: int64
    course: np.ndarray  #: float64 degrees true
    speed: np.ndarray  #: float64 m/s (from the knots field, else the km/h field)
    t: np.ndarray  #: float64 arrival times

    def __len__(self) -> int:
        return len(self.line)


@dataclass
class LogReport:
    """What was in the log and how well it could be timed."""

    name: str
    lines: int = 0  #: lines, the truncated last one included
    bytes: int = 0
    line_endings: dict = field(default_factory=lambda: {"CRLF": 0, "LF": 0})
    blank_lines: int = 0
    counts: dict = field(default_factory=dict)  #: records per channel: mag, cesium, gga, zda, vtg
    bad: dict = field(default_factory=dict)  #: bad lines per reason (every reason present)
    ignored: dict = field(default_factory=dict)  #: well-formed sentences not used, per address
    seq_gaps: int = 0
    seq_missing: int = 0
    seq_repeats: int = 0
    time_aligned: bool = False  #: False: no (or one) GPS anchor, every time is NaN
    anchors: int = 0  #: GGA anchors used
    anchors_not_increasing: int = 0  #: GGA times left out because they did not increase
    midnight_rollovers: int = 0
    line_rate_hz: float = math.nan  #: lines per second between the first and last anchor
    mag_timing: str = "none"  #: "sequence", "line" (fallback) or "none"
    mag_rate_hz: float = math.nan  #: the magnetometer's own sample rate, estimated
    mag_brackets: int = 0  #: anchors bracketed by magnetometer lines and used in the fit
    mag_outliers: int = 0  #: brackets left out of the fit
    #: RMS residual (s) of the used bracket midpoints: about period / sqrt(12) when sequence
    #: numbers and arrival order agree, more when the sensor clock wanders.
    mag_fit_rms_s: float = math.nan
    #: Samples timed by line position although the fit succeeded (sequence time more than
    #: 2 s from the line time: the minority side of a sensor restart)
    mag_line_timed: int = 0
    messages: list = field(default_factory=list)  #: "name:line: reason: detail" and notes

    def __str__(self) -> str:
        counts = ", ".join(f"{key} {value}" for key, value in self.counts.items())
        bad = ", ".join(f"{key} {value}" for key, value in self.bad.items() if value) or "none"
        ignored = (
            ", ".join(f"{key} {value}" for key, value in sorted(self.ignored.items())) or "none"
        )
        lines = [
            f"{self.name}: {self.lines} lines, {self.bytes} bytes ({counts})",
            f"  bad lines: {bad}; ignored: {ignored}; blank: {self.blank_lines}",
            f"  magnetometer sequence: {self.seq_gaps} gaps, {self.seq_missing} samples missing, "
            f"{self.seq_repeats} repeats",
        ]
        if not self.time_aligned:
            lines.append(f"  time: not aligned ({self.anchors} GPS anchors), all times are NaN")
        elif self.mag_timing == "sequence":
            lines.append(
                f"  time: {self.anchors} GGA anchors, {self.line_rate_hz:.2f} lines/s, "
                f"magnetometer by sequence at {self.mag_rate_hz:.4f} Hz ({self.mag_outliers} of "
                f"{self.mag_brackets + self.mag_outliers} brackets rejected, "
                f"{self.mag_line_timed} samples by line)"
            )
        else:
            lines.append(
                f"  time: {self.anchors} GGA anchors, {self.line_rate_hz:.2f} lines/s, "
                f"magnetometer by {self.mag_timing}"
            )
        return "\n".join(lines)


@dataclass(frozen=True, eq=False)
class ParsedLog:
    """The result of :func:`parse_log`."""

    name: str
    mag: MagData
    cesium: CesiumData
    gga: GgaData
    zda: ZdaData
    vtg: VtgData
    bad: list  #: ``(line_number, reason)`` in line order
    ignored: list  #: ``(line_number, address)`` of well-formed sentences not used
    date: _dt.date | None  #: UTC date of the first anchor (from ZDA), or None
    report: LogReport

    @property
    def epoch(self) -> _dt.datetime | None:
        """00:00:00 UTC of :attr:`date` (aware), the zero of every ``t``; None without ZDA."""
        if self.date is None:
            return None
        return _dt.datetime(
            self.date.year, self.date.month, self.date.day, tzinfo=_dt.timezone.utc
        )


@dataclass(frozen=True, eq=False)
class CalibrationArrays:
    """Magnetometer samples with the references at their times (see :func:`to_arrays`)."""

    t: np.ndarray  #: (N,) magnetometer times
    b: np.ndarray  #: (N, 3) nT
    seq: np.ndarray  #: (N,) unwrapped sequence numbers
    line: np.ndarray  #: (N,) line numbers
    cesium: np.ndarray  #: (N,) cesium total field at ``t``, NaN outside its span and gaps
    lat: np.ndarray  #: (N,) degrees
    lon: np.ndarray  #: (N,) degrees
    alt: np.ndarray  #: (N,) m
    date: _dt.date | None

    def __len__(self) -> int:
        return len(self.t)


# --- field parsers ------------------------------------------------------------------------


def _float(text: str, what: str) -> float:
    if not text:
        return math.nan
    if not _DECIMAL_RE.match(text):
        raise _BadLine(NUMBER, f"{what} {_clip(text)!r} is not a number")
    value = float(text)
    if not math.isfinite(value):
        raise _BadLine(NUMBER, f"{what} {_clip(text)!r} is beyond a double's range")
    return value


def _uint(text: str, what: str, maximum: int) -> int:
    if not text:
        return _MISSING_INT
    if not _UINT_RE.match(text):
        raise _BadLine(NUMBER, f"{what} {_clip(text)!r} is not an unsigned integer")
    # Compare digits before converting: a field of thousands of digits is no integer to
    # build (Python refuses beyond 4,300 digits) and no int64 to store.
    digits = text.lstrip("0") or "0"
    if len(digits) > len(str(maximum)) or int(digits) > maximum:
        raise _BadLine(NUMBER, f"{what} {_clip(text)!r} is out of range (0..{maximum})")
    return int(digits)


def _time_of_day(text: str) -> float:
    if not text:
        return math.nan
    match = _TIME_RE.match(text)
    if match is None:
        raise _BadLine(NUMBER, f"time {text!r} is not hhmmss.ss")
    hours, minutes, seconds = int(match[1]), int(match[2]), float(match[3])
    if hours >= _HOURS_PER_DAY or minutes >= _MINUTES_PER_HOUR or seconds >= _MAX_SECOND:
        raise _BadLine(NUMBER, f"time {text!r} is out of range")
    return (hours * _MINUTES_PER_HOUR + minutes) * _SECONDS_PER_MINUTE + seconds


def _angle(
    text: str, hemisphere: str, pattern: re.Pattern, signs: str, limit: float, what: str
) -> float:
    if not text and not hemisphere:
        return math.nan
    match = pattern.match(text)
    if match is None:
        raise _BadLine(
            NUMBER, f"{what} {text!r} is not {'dd' if limit == _LAT_LIMIT else 'ddd'}mm.mmmm"
        )
    degrees, minutes = int(match[1]), float(match[2])
    value = degrees + minutes / _MINUTES_PER_HOUR
    if minutes >= _MINUTES_PER_HOUR or value > limit:
        raise _BadLine(NUMBER, f"{what} {text!r} is out of range")
    if hemisphere == signs[0]:
        return value
    if hemisphere == signs[1]:
        return -value
    raise _BadLine(NUMBER, f"{what} hemisphere {hemisphere!r} is not {signs[0]} or {signs[1]}")


def _check_count(fields: list[str], allowed: tuple[int, ...], what: str) -> None:
    if len(fields) not in allowed:
        wanted = " or ".join(str(n) for n in allowed)
        raise _BadLine(FIELD_COUNT, f"{what} has {len(fields)} fields, not {wanted}")


def _parse_pmag(payload: str) -> tuple[int, float, float, float]:
    fields = payload.split(",")
    _check_count(fields, (_PMAG_FIELDS,), "$PMAG1")
    if not _UINT_RE.match(fields[1]) or len(fields[1].lstrip("0")) > len(str(SEQ_MODULUS)) \
            or int(fields[1]) >= SEQ_MODULUS:
        raise _BadLine(NUMBER, f"sequence number {_clip(fields[1])!r} is not "
                               f"0..{SEQ_MODULUS - 1}")
    seq = int(fields[1])
    values = [_float(text, f"field {axis}") for text, axis in zip(fields[2:], "xyz")]
    for value, axis, text in zip(values, "xyz", fields[2:]):
        if math.isnan(value):
            raise _BadLine(NUMBER, f"field {axis} {text!r} is empty")
        if abs(value) >= _PMAG_LIMIT_NT:
            raise _BadLine(NUMBER, f"field {axis} {_clip(text)!r} is beyond the $PMAG1 "
                                   f"form's ±{_PMAG_LIMIT_NT - 0.1:.1f} nT")
    return seq, values[0], values[1], values[2]


def _parse_cesium(body: str) -> tuple[float, int]:
    fields = body.split(",")
    _check_count(fields, (2,), "cesium line")
    reading, signal = fields
    if not _CESIUM_FIELD_RE.match(reading):
        raise _BadLine(NUMBER, f"cesium field {reading!r} is not ' ddddd.ddd' or '1ddddd.ddd'")
    if not _CESIUM_SIGNAL_RE.match(signal):
        raise _BadLine(NUMBER, f"cesium signal {signal!r} is not four digits")
    value = float(reading[1:]) + (_CESIUM_HIGH_RANGE_NT if reading[0] == "1" else 0.0)
    return value, int(signal)


def _parse_gga(fields: list[str]) -> tuple:
    _check_count(fields, _GGA_FIELDS, "GGA")
    tod = _time_of_day(fields[1])
    lat = _angle(fields[2], fields[3], _LAT_RE, "NS", _LAT_LIMIT, "latitude")
    lon = _angle(fields[4], fields[5], _LON_RE, "EW", _LON_LIMIT, "longitude")
    quality = _uint(fields[6], "fix quality", _MAX_QUALITY)
    satellites = _uint(fields[7], "satellite count", _MAX_SATELLITES)
    hdop = _float(fields[8], "HDOP")
    altitude = _float(fields[9], "altitude")
    return tod, lat, lon, quality, satellites, hdop, altitude


def _parse_zda(fields: list[str]) -> _dt.datetime | None:
    _check_count(fields, _ZDA_FIELDS, "ZDA")
    tod = _time_of_day(fields[1])
    day, month, year = (
        _uint(text, what, maximum)
        for text, what, maximum in zip(
            fields[2:5], ("day", "month", "year"), (_MAX_DAY, _MAX_MONTH, _MAX_YEAR)
        )
    )
    if math.isnan(tod) or _MISSING_INT in (day, month, year):
        return None
    try:
        midnight = _dt.datetime(year, month, day)
        return midnight + _dt.timedelta(seconds=tod)
    except (ValueError, OverflowError) as error:
        # OverflowError: a leap second at the end of 9999-12-31 is past the calendar.
        raise _BadLine(NUMBER, f"date {fields[2]},{fields[3]},{fields[4]}: {error} "
                               f"(time {fields[1]})") from None


def _parse_vtg(fields: list[str]) -> tuple[float, float]:
    _check_count(fields, _VTG_FIELDS, "VTG")
    course = _float(fields[1], "course")
    knots = _float(fields[5], "speed in knots")
    kmh = _float(fields[7], "speed in km/h")
    speed = knots * _KNOT_M_S if not math.isnan(knots) else kmh * _KMH_M_S
    return course, speed


# --- the bulk readers ---------------------------------------------------------------------
# The logger writes $PMAG1 and cesium frames in fixed forms. Lines in exactly those forms
# (and, for $PMAG1, with a matching checksum) are read with array operations; every other
# line, good or bad, goes to _Reader.read_line. The forms accept no line that read_line would
# refuse or read differently: each field is one read_line accepts, and a value of n decimals
# is its digits as an integer divided by 10**n, the correctly rounded double that float()
# gives for its text too.

#: The forms, one byte class per column: "d" a digit, "s" a sign, "c" the cesium range (" "
#: or "1"), "h" a hex digit; any other byte stands for itself.
_PMAG_FORM = b"$PMAG1,ddddd,sddddd.d,sddddd.d,sddddd.d*hh"
_CESIUM_FORM = b"$cddddd.ddd,dddd"
_LF = ord("\n")
_CR = ord("\r")
#: The byte classes of the forms, each as inclusive byte ranges.
_DIGIT = (b"09",)
_BYTE_CLASSES = {
    ord("d"): _DIGIT,
    ord("s"): (b"++", b"--"),
    ord("c"): (b"  ", b"11"),
    ord("h"): (b"09", b"AF", b"af"),
}
_UPPER = (b"AZ",)
_PRINTABLE = (b" ~",)
_HEX_VALUE = np.zeros(256, dtype=np.int64)
_HEX_VALUE[list(b"0123456789")] = range(10)
_HEX_VALUE[list(b"ABCDEF")] = range(10, 16)
_HEX_VALUE[list(b"abcdef")] = range(10, 16)


def _in_class(cells: np.ndarray, ranges: tuple[bytes, ...]) -> np.ndarray:
    """Whether each byte lies in one of the inclusive ``ranges``."""
    low, high = ranges[0]
    inside = (cells - np.uint8(low)) <= high - low  # bytes below ``low`` wrap round to 255
    for low, high in ranges[1:]:
        inside |= (cells - np.uint8(low)) <= high - low
    return inside


def _rows_in_form(
    data: np.ndarray, starts: np.ndarray, length: np.ndarray, form: bytes
) -> tuple[np.ndarray, np.ndarray]:
    """The indices of the lines (``length`` bytes from ``starts``, line end excluded) that are
    exactly in ``form``, and their bytes, one row per line."""
    template = np.frombuffer(form, dtype=np.uint8)
    lines = np.flatnonzero(length == len(form))
    if not len(lines):
        return lines, np.empty((0, len(form)), dtype=np.uint8)
    rows = np.lib.stride_tricks.sliding_window_view(data, len(form))[starts[lines]]
    ok = np.ones(len(lines), dtype=bool)
    literal = np.ones(len(form), dtype=bool)
    for byte_class, ranges in _BYTE_CLASSES.items():
        columns = np.flatnonzero(template == byte_class)
        literal[columns] = False
        if len(columns):
            ok &= _in_class(rows[:, columns], ranges).all(axis=1)
    ok &= (rows[:, literal] == template[literal]).all(axis=1)
    return lines[ok], rows[ok]


def _digits(rows: np.ndarray, first: int, count: int) -> np.ndarray:
    """The unsigned integers written in columns ``first`` to ``first + count - 1``."""
    value = np.zeros(len(rows), dtype=np.int64)
    for column in range(first, first + count):
        value = value * 10 + (rows[:, column] - ord("0"))
    return value


def _bulk_pmag(data, starts, length) -> tuple[np.ndarray, tuple[np.ndarray, ...]]:
    """``$PMAG1`` lines in :data:`_PMAG_FORM` with a good checksum: their indices, and
    sequence number and x, y, z as :func:`_parse_pmag` reads them."""
    lines, rows = _rows_in_form(data, starts, length, _PMAG_FORM)
    star = _PMAG_FORM.index(b"*")
    sent = _HEX_VALUE[rows[:, star + 1]] * 16 + _HEX_VALUE[rows[:, star + 2]]
    good = np.bitwise_xor.reduce(rows[:, 1:star], axis=1) == sent
    lines, rows = lines[good], rows[good]
    seq = _digits(rows, _PMAG_FORM.index(b"d"), len(str(SEQ_MODULUS - 1)))
    axes = []
    for sign in (index for index, byte in enumerate(_PMAG_FORM) if byte == ord("s")):
        # ±XXXXX.X: five digits, the point, one digit.
        tenths = _digits(rows, sign + 1, 5) * 10 + _digits(rows, sign + 7, 1)
        value = tenths / 10.0
        axes.append(np.where(rows[:, sign] == ord("-"), -value, value))
    return lines, (seq, *axes)


def _bulk_cesium(data, starts, length) -> tuple[np.ndarray, tuple[np.ndarray, ...]]:
    """Cesium lines in :data:`_CESIUM_FORM`: their indices, and field and signal as
    :func:`_parse_cesium` reads them."""
    lines, rows = _rows_in_form(data, starts, length, _CESIUM_FORM)
    # [ 1]ddddd.ddd,dddd from column 1.
    value = (_digits(rows, 2, 5) * 1000 + _digits(rows, 8, 3)) / 1000.0
    field = value + np.where(rows[:, 1] == ord("1"), _CESIUM_HIGH_RANGE_NT, 0.0)
    return lines, (field, _digits(rows, 12, 4))


# NMEA sentences have fields of varying width. A GGA, ZDA or VTG line is read in bulk when it
# is in the plain form of _nmea_fields and each field it uses is a plain number that
# _plain_number reads exactly; any other line goes to _Reader.read_line.

#: Widest number field read in bulk, and most digits in it (below 2**53: the digits and the
#: power of ten are exact doubles, and their quotient is the correctly rounded value).
_BULK_FIELD_WIDTH = 16
_BULK_DIGITS = 15
_POWERS_OF_TEN = np.array([float(10**k) for k in range(_BULK_FIELD_WIDTH + 1)])


def _gather(data: np.ndarray, starts: np.ndarray, length: np.ndarray):
    """The bytes of some lines end to end, then ``_BULK_FIELD_WIDTH`` zeros (so that there is
    a byte after the last line for a field's window to end on), and where each line starts."""
    offsets = np.zeros(len(starts), dtype=np.int64)
    np.cumsum(length[:-1], out=offsets[1:])
    index = np.arange(int(length.sum()), dtype=np.int64) + np.repeat(starts - offsets, length)
    return np.concatenate([data[index], np.zeros(_BULK_FIELD_WIDTH, np.uint8)]), offsets


def _nmea_fields(data, starts, length, sentence: bytes, field_count: int):
    """Lines of one NMEA sentence in the plain form: ``$``, a two-capital talker, the
    sentence, ``field_count`` comma-separated fields (the address included) of printable
    bytes other than ``$`` and ``*``, and ``*hh`` with a good checksum. Returns their
    indices, their bytes end to end (``chunk``, see :func:`_gather`), and where each data
    field starts and stops in ``chunk`` (column ``k - 1`` for field ``k``)."""
    lines = np.flatnonzero(length >= len(b"$ccGGA,*hh"))
    at = starts[lines]
    ok = (data[at] == ord("$")) & _in_class(data[at + 1], _UPPER) & _in_class(data[at + 2], _UPPER)
    for column, byte in enumerate(sentence + b",", start=3):
        ok &= data[at + column] == byte
    lines = lines[ok & (data[at + length[lines] - 3] == ord("*"))]
    chunk, offsets = _gather(data, starts[lines], length[lines])
    row = np.repeat(np.arange(len(lines)), length[lines])
    star = offsets + length[lines] - 3

    def per_line(flags):
        return np.bincount(row[flags[: len(row)]], minlength=len(lines))

    hex_digit = _BYTE_CLASSES[ord("h")]
    ok = _in_class(chunk[star + 1], hex_digit) & _in_class(chunk[star + 2], hex_digit)
    ok &= (per_line(~_in_class(chunk, _PRINTABLE)) == 0) & (per_line(chunk == ord("$")) == 1)
    ok &= (per_line(chunk == ord("*")) == 1) & (per_line(chunk == ord(",")) == field_count - 1)
    prefix = np.zeros(len(chunk) + 1, dtype=np.uint8)
    np.bitwise_xor.accumulate(chunk, out=prefix[1:])
    sent = _HEX_VALUE[chunk[star + 1]] * 16 + _HEX_VALUE[chunk[star + 2]]
    ok &= (prefix[offsets + 1] ^ prefix[star]) == sent
    lines = lines[ok]
    chunk, offsets = _gather(data, starts[lines], length[lines])
    commas = np.flatnonzero(chunk == ord(",")).reshape(len(lines), field_count - 1)
    return lines, chunk, commas + 1, np.column_stack([commas[:, 1:], offsets + length[lines] - 3])


def _plain_number(chunk: np.ndarray, first: np.ndarray, stop: np.ndarray):
    """Fields ``chunk[first:stop]`` of the form ``\\d*(\\.\\d*)?`` (at most
    ``_BULK_DIGITS`` digits): ``(ok, value, digits before the point, digits, has a point)``."""
    width = stop - first
    columns = np.arange(_BULK_FIELD_WIDTH)
    cells = chunk[np.minimum(first[:, None] + columns, len(chunk) - 1)]
    inside = columns < width[:, None]
    digit = inside & _in_class(cells, _DIGIT)
    point = inside & (cells == ord("."))
    mantissa = np.zeros(len(first), dtype=np.int64)
    for column in range(_BULK_FIELD_WIDTH):
        mantissa = np.where(
            digit[:, column], mantissa * 10 + (cells[:, column] - ord("0")), mantissa
        )
    whole = np.count_nonzero(digit & (np.cumsum(point, axis=1) == 0), axis=1)
    digits = np.count_nonzero(digit, axis=1)
    ok = (width <= _BULK_FIELD_WIDTH) & ((digit | point) == inside).all(axis=1)
    ok &= (np.count_nonzero(point, axis=1) <= 1) & (digits <= _BULK_DIGITS)
    value = mantissa / _POWERS_OF_TEN[np.minimum(digits - whole, _BULK_FIELD_WIDTH)]
    return ok, value, whole, digits, point.any(axis=1)


def _bulk_float(chunk, first, stop):
    """:func:`_float` in bulk: (ok, value or NaN for an empty field)."""
    empty = stop == first
    sign = ~empty & ((chunk[first] == ord("+")) | (chunk[first] == ord("-")))
    ok, value, _, digits, _ = _plain_number(chunk, first + sign, stop)
    value = np.where(sign & (chunk[first] == ord("-")), -value, value)
    return empty | (ok & (digits > 0)), np.where(empty, math.nan, value)


def _bulk_uint(chunk, first, stop, maximum: int):
    """:func:`_uint` in bulk: (ok, value or -1 for an empty field)."""
    empty = stop == first
    ok, value, _, _, point = _plain_number(chunk, first, stop)
    ok = empty | (ok & ~point & (value <= maximum))
    return ok, np.where(empty | ~ok, _MISSING_INT, value).astype(np.int64)


def _bulk_whole_then_number(chunk, first, stop, whole_digits: int):
    """Fields of ``whole_digits`` digits then ``\\d{2}(\\.\\d*)?``: (ok, the integer, the
    number)."""
    ok, head, head_whole, _, _ = _plain_number(chunk, first, first + whole_digits)
    ok_rest, rest, rest_whole, _, _ = _plain_number(chunk, first + whole_digits, stop)
    ok &= ok_rest & (head_whole == whole_digits) & (rest_whole == 2)
    return ok & (stop - first >= whole_digits + 2), head.astype(np.int64), rest


def _bulk_time_of_day(chunk, first, stop):
    """:func:`_time_of_day` in bulk: (ok, seconds or NaN for an empty field)."""
    empty = stop == first
    ok, hours_minutes, seconds = _bulk_whole_then_number(chunk, first, stop, 4)
    hours, minutes = np.divmod(hours_minutes, 100)
    ok &= (hours < _HOURS_PER_DAY) & (minutes < _MINUTES_PER_HOUR) & (seconds < _MAX_SECOND)
    tod = (hours * _MINUTES_PER_HOUR + minutes) * _SECONDS_PER_MINUTE + seconds
    return empty | ok, np.where(empty, math.nan, tod)


def _bulk_angle(chunk, first, stop, hemisphere, degree_digits, signs: bytes, limit: float):
    """:func:`_angle` in bulk (``hemisphere``: the start and stop of its field): (ok, degrees
    or NaN when both fields are empty)."""
    empty = (stop == first) & (hemisphere[1] == hemisphere[0])
    ok, degrees, minutes = _bulk_whole_then_number(chunk, first, stop, degree_digits)
    value = degrees + minutes / _MINUTES_PER_HOUR
    ok &= (minutes < _MINUTES_PER_HOUR) & (value <= limit)
    one = hemisphere[1] - hemisphere[0] == 1
    positive = one & (chunk[hemisphere[0]] == signs[0])
    negative = one & (chunk[hemisphere[0]] == signs[1])
    value = np.where(negative, -value, value)
    return empty | (ok & (positive | negative)), np.where(empty, math.nan, value)


def _bulk_gga(data, starts, length) -> tuple[np.ndarray, tuple[np.ndarray, ...]]:
    """GGA lines in the plain form whose fields :func:`_parse_gga` accepts: their indices
    and the values it gives."""
    lines, chunk, first, stop = _nmea_fields(data, starts, length, b"GGA", _GGA_FIELDS[0])

    def field(k):
        return chunk, first[:, k - 1], stop[:, k - 1]

    found = [
        _bulk_time_of_day(*field(1)),
        _bulk_angle(*field(2), field(3)[1:], 2, b"NS", _LAT_LIMIT),
        _bulk_angle(*field(4), field(5)[1:], 3, b"EW", _LON_LIMIT),
        _bulk_uint(*field(6), _MAX_QUALITY),
        _bulk_uint(*field(7), _MAX_SATELLITES),
        _bulk_float(*field(8)),
        _bulk_float(*field(9)),
    ]
    good = np.logical_and.reduce([ok for ok, _ in found])
    return lines[good], tuple(value[good] for _, value in found)


def _bulk_zda(data, starts, length) -> tuple[np.ndarray, tuple[np.ndarray, ...]]:
    """ZDA lines in the plain form whose fields :func:`_parse_zda` accepts: their indices and
    the date and time it gives (an object array of datetimes or None)."""
    lines, chunk, first, stop = _nmea_fields(data, starts, length, b"ZDA", _ZDA_FIELDS[0])
    ok, tod = _bulk_time_of_day(chunk, first[:, 0], stop[:, 0])
    parts = []
    for k, maximum in ((2, _MAX_DAY), (3, _MAX_MONTH), (4, _MAX_YEAR)):
        ok_part, value = _bulk_uint(chunk, first[:, k - 1], stop[:, k - 1], maximum)
        ok &= ok_part
        parts.append(value)
    when = np.full(len(lines), None, dtype=object)
    days, months, years, seconds_of_day = (values.tolist() for values in (*parts, tod))
    for index in np.flatnonzero(ok).tolist():
        day, month, year, seconds = days[index], months[index], years[index], seconds_of_day[index]
        if math.isnan(seconds) or _MISSING_INT in (day, month, year):
            continue
        try:
            when[index] = _dt.datetime(year, month, day) + _dt.timedelta(seconds=seconds)
        except (ValueError, OverflowError):
            ok[index] = False  # _parse_zda reports it
    return lines[ok], (when[ok],)


def _bulk_vtg(data, starts, length) -> tuple[np.ndarray, tuple[np.ndarray, ...]]:
    """VTG lines (of either field count) in the plain form whose fields :func:`_parse_vtg`
    accepts: their indices and the course and speed it gives."""
    lines, course, speed = [], [], []
    for field_count in _VTG_FIELDS:
        found, chunk, first, stop = _nmea_fields(data, starts, length, b"VTG", field_count)
        (ok, degrees), (ok_knots, knots), (ok_kmh, kmh) = (
            _bulk_float(chunk, first[:, k - 1], stop[:, k - 1]) for k in (1, 5, 7)
        )
        good = ok & ok_knots & ok_kmh
        lines.append(found[good])
        course.append(degrees[good])
        speed.append(np.where(np.isnan(knots), kmh * _KMH_M_S, knots * _KNOT_M_S)[good])
    order = np.argsort(np.concatenate(lines), kind="stable")
    return np.concatenate(lines)[order], (np.concatenate(course)[order],
                                          np.concatenate(speed)[order])


#: The bulk readers in turn, each on the lines the ones before did not take: the fixed forms
#: a block of lines at a time, then the NMEA sentences.
_FIXED_FORM_READERS = (("mag", _bulk_pmag), ("cesium", _bulk_cesium))
_BULK_BLOCK_LINES = 1 << 15
_NMEA_READERS = (("gga", _bulk_gga), ("zda", _bulk_zda), ("vtg", _bulk_vtg))


# --- the line reader ----------------------------------------------------------------------


class _Reader:
    """Reads the lines of one log into lists of records, bad lines and ignored sentences."""

    def __init__(self, data: bytes, name: str):
        self.data = data
        self.name = name
        self.report = LogReport(name=name, bytes=len(data))
        self.bad: list[tuple[int, str]] = []
        self.ignored: list[tuple[int, str]] = []
        self.mag: list[tuple] = []
        self.cesium: list[tuple] = []
        self.gga: list[tuple] = []
        self.zda: list[tuple] = []
        self.vtg: list[tuple] = []
        #: Records read in bulk (:meth:`read`), per channel: per block of lines, one array per
        #: column.
        self.bulk: dict[str, list[tuple[np.ndarray, ...]]] = {}
        #: The bytes the ``start`` of :meth:`read_line` counts in (see :attr:`prefix`).
        self.xor_source = data
        self._prefix: bytes | None = None

    @property
    def prefix(self) -> bytes:
        """``prefix[i]`` is the XOR of ``xor_source[:i]``: the XOR of ``xor_source[a:b]`` is
        ``prefix[a] ^ prefix[b]`` (computed when a line first needs it)."""
        if self._prefix is None:
            source = np.frombuffer(self.xor_source, dtype=np.uint8)
            prefix = np.zeros(len(source) + 1, dtype=np.uint8)
            np.bitwise_xor.accumulate(source, out=prefix[1:])
            self._prefix = prefix.tobytes()
        return self._prefix

    def fail(self, line: int, reason: str, detail: str) -> None:
        self.bad.append((line, reason))
        self.report.messages.append(f"{self.name}:{line}: {reason}: {detail}")

    def read(self) -> None:
        """Read every line: the lines the bulk readers (:data:`_FIXED_FORM_READERS`,
        :data:`_NMEA_READERS`) take, every other line with :meth:`read_line`, with the same
        results as :meth:`read_per_line`."""
        data = np.frombuffer(self.data, dtype=np.uint8)
        ends = np.flatnonzero(data == _LF)
        starts = np.zeros(len(ends), dtype=np.int64)
        starts[1:] = ends[:-1] + 1
        tail = self.data[int(ends[-1]) + 1 if len(ends) else 0 :]
        self.report.lines = len(ends) + (1 if tail else 0)
        crlf = (ends > starts) & (data[ends - 1] == _CR)
        stops = ends - crlf
        self.report.line_endings["CRLF"] = int(np.count_nonzero(crlf))
        self.report.line_endings["LF"] = len(ends) - self.report.line_endings["CRLF"]
        lines = np.arange(len(ends))
        # The fixed forms (nearly all of a log) a block of lines at a time: the arrays of a
        # block stay in the processor's cache, which keeps the time linear in the log's size.
        rest = [
            self.read_bulk(_FIXED_FORM_READERS, lines[first : first + _BULK_BLOCK_LINES],
                           data, starts, stops)
            for first in range(0, len(ends), _BULK_BLOCK_LINES)
        ]
        rest = self.read_bulk(_NMEA_READERS, np.concatenate([lines[:0], *rest]), data, starts,
                              stops).tolist()
        pieces = [self.data[starts[index] : stops[index]] for index in rest]
        # The checksums of the rest are computed on their bytes alone.
        self.xor_source = b"".join(pieces)
        offset = 0
        for index, raw in zip(rest, pieces):
            self.read_line(index + 1, offset, raw)
            offset += len(raw)
        if tail:
            self.fail(
                len(ends) + 1, TRUNCATED, f"the last line has no line end ({len(tail)} bytes)"
            )

    def read_bulk(self, readers, lines: np.ndarray, data, starts, stops) -> np.ndarray:
        """Let the bulk ``readers`` take what they can of ``lines`` in turn; the lines left."""
        for kind, bulk_reader in readers:
            taken, columns = bulk_reader(data, starts[lines], stops[lines] - starts[lines])
            # Line numbers count from 1.
            self.bulk.setdefault(kind, []).append((lines[taken] + 1, *columns))
            lines = np.delete(lines, taken)
        return lines

    def columns(self, kind: str, dtypes: tuple) -> list[np.ndarray]:
        """The records of one channel, line by line and in bulk, merged in line order:
        one array per column (the first is the line number)."""
        rows = getattr(self, kind)
        columns = [_column(rows, index, dtype) for index, dtype in enumerate(dtypes)]
        blocks = self.bulk.get(kind, [])
        if not blocks:
            return columns
        columns = [
            np.concatenate([column, *(block[index] for block in blocks)])
            for index, column in enumerate(columns)
        ]
        if rows:
            order = np.argsort(columns[0], kind="stable")
            columns = [column[order] for column in columns]
        return columns

    def read_per_line(self) -> None:
        """Read every line with :meth:`read_line` (the reference :meth:`read` agrees with)."""
        pieces = self.data.split(b"\n")
        self.report.lines = len(pieces) - (1 if pieces[-1] == b"" else 0)
        offset = 0
        last = len(pieces) - 1
        for index, raw in enumerate(pieces):
            number = index + 1
            start = offset
            offset += len(raw) + 1
            if index == last:
                if raw:
                    self.fail(
                        number, TRUNCATED, f"the last line has no line end ({len(raw)} bytes)"
                    )
                break
            if raw.endswith(b"\r"):
                raw = raw[:-1]
                self.report.line_endings["CRLF"] += 1
            else:
                self.report.line_endings["LF"] += 1
            self.read_line(number, start, raw)

    def read_line(self, number: int, start: int, raw: bytes) -> None:
        if not raw:
            self.report.blank_lines += 1
            return
        bad_byte = _BAD_BYTE_RE.search(raw)
        if bad_byte is not None:
            byte = raw[bad_byte.start()]
            self.fail(
                number,
                BAD_BYTE,
                f"byte 0x{byte:02X} at column {bad_byte.start() + 1} "
                "(only printable ASCII is allowed)",
            )
            return
        text = raw.decode("ascii")
        frame_start = text.rfind("$")
        if frame_start < 0:
            self.fail(number, UNKNOWN_SENTENCE, f"no '$' frame start in {_clip(text)!r}")
            return
        if frame_start > 0:
            self.fail(
                number,
                TRUNCATED,
                f"{_clip(text[:frame_start])!r} before the '$' at column {frame_start + 1} "
                "is a cut frame",
            )
        try:
            self.read_frame(number, start + frame_start, text[frame_start:])
        except _BadLine as bad:
            self.fail(number, bad.reason, bad.detail)

    def checked_payload(self, frame: str, offset: int) -> str:
        """The bytes between ``$`` and a final ``*hh`` whose XOR matches."""
        match = _CHECKSUM_RE.search(frame)
        if match is None:
            raise _BadLine(CHECKSUM, "no '*hh' checksum at the end")
        star = match.start()
        sent = int(match[1], 16)
        computed = self.prefix[offset + 1] ^ self.prefix[offset + star]
        if sent != computed:
            raise _BadLine(
                CHECKSUM, f"checksum {match[1]} does not match the computed {computed:02X}"
            )
        return frame[1:star]

    def read_frame(self, number: int, offset: int, frame: str) -> None:
        first = frame[1:2]
        if first == " " or first.isdigit():
            self.cesium.append((number, *_parse_cesium(frame[1:])))
            return
        if not _ADDRESS_RE.match(frame):
            raise _BadLine(
                UNKNOWN_SENTENCE, f"{_clip(frame)!r} is no $PMAG1, NMEA or cesium frame"
            )
        payload = self.checked_payload(frame, offset)
        address = frame[1:6]
        if address == _PMAG_ADDRESS:
            self.mag.append((number, *_parse_pmag(payload)))
            return
        sentence = address[2:]
        if sentence not in _NMEA_KEPT:
            self.ignored.append((number, address))
            return
        fields = payload.split(",")
        if sentence == "GGA":
            self.gga.append((number, *_parse_gga(fields)))
        elif sentence == "ZDA":
            self.zda.append((number, _parse_zda(fields)))
        else:
            self.vtg.append((number, *_parse_vtg(fields)))


def _clip(text: str, limit: int = 40) -> str:
    return text if len(text) <= limit else text[:limit] + "..."


def _column(rows: list[tuple], index: int, dtype) -> np.ndarray:
    return np.array([row[index] for row in rows], dtype=dtype)


# --- time alignment -----------------------------------------------------------------------


@dataclass
class _Anchors:
    line: np.ndarray  # line numbers of the anchor GGAs
    epoch: np.ndarray  # their epochs, seconds since midnight of `date`
    gga_index: np.ndarray  # index into the GGA records
    date: _dt.date | None
    rollovers: int
    not_increasing: int
    beyond_calendar: bool = False  # the ZDA's day, moved to the first fix's, is off the calendar


def _find_anchors(gga_line, tod, quality, zda_line, zda_datetimes) -> _Anchors:
    usable = np.flatnonzero((quality >= 1) & np.isfinite(tod))
    steps_back = np.diff(tod[usable]) < -_HALF_DAY  # past midnight
    days = np.concatenate([np.zeros(min(len(usable), 1)), np.cumsum(steps_back)]).astype(np.int64)
    epoch = tod[usable] + days * _SECONDS_PER_DAY
    keep = []
    latest = -math.inf
    for position, value in enumerate(epoch):
        if value > latest:
            keep.append(position)
            latest = value
    keep = np.array(keep, dtype=np.int64)
    index = usable[keep]
    epoch = epoch[keep]
    line = gga_line[index]
    date = None
    beyond_calendar = False
    dated = [(zl, when) for zl, when in zip(zda_line, zda_datetimes) if when is not None]
    if dated and len(line):
        # The first dated ZDA gives the calendar day of the anchor nearest to it in the log
        # (they are less than half a day apart), hence the day of the first anchor.
        zl, when = dated[0]
        nearest = int(np.argmin(np.abs(line - zl)))
        zda_tod = (when - _dt.datetime(when.year, when.month, when.day)).total_seconds()
        shift = round((zda_tod - epoch[nearest]) / _SECONDS_PER_DAY)
        try:
            date = when.date() + _dt.timedelta(days=shift)
        except OverflowError:
            # The first fix falls on a day before 0001-01-01 or after 9999-12-31.
            date = None
            beyond_calendar = True
    elif dated:
        date = dated[0][1].date()
    rollovers = int(days[keep][-1]) if len(keep) else 0
    return _Anchors(
        line, epoch, index, date, rollovers, len(usable) - len(keep), beyond_calendar
    )


def _line_times(position: np.ndarray, anchor_pos: np.ndarray, anchor_t: np.ndarray) -> np.ndarray:
    """Times of lines at ``position``: linear between anchors, the mean rate outside."""
    position = np.asarray(position, dtype=np.float64)
    if len(anchor_pos) < 2:
        return np.full(position.shape, math.nan)
    seconds_per_line = (anchor_t[-1] - anchor_t[0]) / (anchor_pos[-1] - anchor_pos[0])
    t = np.interp(position, anchor_pos, anchor_t)
    before = position < anchor_pos[0]
    after = position > anchor_pos[-1]
    t[before] = anchor_t[0] - (anchor_pos[0] - position[before]) * seconds_per_line
    t[after] = anchor_t[-1] + (position[after] - anchor_pos[-1]) * seconds_per_line
    return t


@dataclass
class _MagFit:
    t_ref: float  # time of sequence number s_ref
    s_ref: float
    period: float  # seconds per sample
    used: int
    outliers: int
    rms: float  # RMS residual of the used brackets' midpoints

    def times(self, seq: np.ndarray) -> np.ndarray:
        return self.t_ref + (seq - self.s_ref) * self.period


def _fit_mag(mag_line, seq, anchor_line, anchor_t) -> _MagFit | None:
    """Fit ``anchor time = t_ref + (seq - s_ref) * period`` to the magnetometer brackets."""
    after = np.searchsorted(mag_line, anchor_line, side="right")
    inside = (after > 0) & (after < len(mag_line))
    low, high = seq[after[inside] - 1].astype(np.float64), seq[after[inside]].astype(np.float64)
    times = anchor_t[inside]
    ok = high > low
    low, high, times = low[ok], high[ok], times[ok]
    if len(times) < 2:
        return None
    s_ref, t_ref = low[0], times[0]
    mid = (low + high) / 2.0 - s_ref
    times = times - t_ref
    width = high - low
    # Robust start (Theil-Sen): the median slope over all pairs of brackets (of at most
    # _THEIL_SEN_POINTS of them, evenly spread), then the median intercept. Pairs within one
    # stretch of good samples agree, so a restart or a burst does not move the medians.
    pick = np.unique(
        np.linspace(0, len(mid) - 1, min(len(mid), _THEIL_SEN_POINTS)).astype(np.int64)
    )
    first, second = np.triu_indices(len(pick), k=1)
    d_seq = mid[pick[second]] - mid[pick[first]]
    d_t = times[pick[second]] - times[pick[first]]
    slopes = d_t[d_seq > 0] / d_seq[d_seq > 0]
    if len(slopes) == 0:
        return None
    period = float(np.median(slopes))
    offset = float(np.median(times - period * mid))
    used = None
    for iteration in range(_FIT_ITERATIONS):
        # A bracket is good to ± half its width: keep those within a full width (at least one
        # sample) of the line. The robust start is rougher, so the first pass allows more.
        allowed = _FIRST_PASS_WIDTHS if iteration == 0 else 1.0
        keep = np.abs(times - offset - period * mid) <= allowed * np.maximum(width, 1.0) * abs(
            period
        )
        if len(np.unique(mid[keep])) < 2:
            return None  # the brackets disagree with any one line
        if used is not None and np.array_equal(keep, used):
            break
        used = keep
        sqrt_w = 1.0 / width[used]
        design = np.column_stack([np.ones(np.count_nonzero(used)), mid[used]]) * sqrt_w[:, None]
        (offset, period), *_ = np.linalg.lstsq(design, times[used] * sqrt_w, rcond=None)
        offset, period = float(offset), float(period)
    used_count = int(np.count_nonzero(used))
    if not period > 0 or used_count < len(used) - used_count:
        return None  # most brackets disagree with the line: no rate to trust
    residual = times[used] - (offset + period * mid[used])
    rms = float(np.sqrt(np.mean(residual**2)))
    return _MagFit(t_ref + offset, s_ref, period, used_count, len(used) - used_count, rms)


def _unwrap_seq(raw: np.ndarray) -> tuple[np.ndarray, int, int, int]:
    if len(raw) == 0:
        return raw.astype(np.int64), 0, 0, 0
    step = np.diff(raw) % SEQ_MODULUS
    seq = raw[0] + np.concatenate([[0], np.cumsum(step)]).astype(np.int64)
    gaps = step > 1
    return (
        seq,
        int(np.count_nonzero(gaps)),
        int(np.sum(step[gaps] - 1)),
        int(np.count_nonzero(step == 0)),
    )


# --- public API ---------------------------------------------------------------------------


def parse_log(data: bytes, *, name: str = "log", gps_latency: float = 0.0) -> ParsedLog:
    """Parse a log file's bytes into per-instrument arrays with times (see the module doc).

    ``name`` prefixes the report's messages (``"LOG00003.TXT:17: checksum: ..."``);
    ``gps_latency`` is the time in seconds from a GGA's epoch to the arrival of its line.
    Malformed lines never raise: they are listed in ``bad`` and counted in ``report``.
    """
    if not isinstance(data, (bytes, bytearray, memoryview)):
        raise TypeError(f"Log data must be bytes, not {type(data).__name__}")
    if not isinstance(name, str):
        raise TypeError(f"Log name must be a str, not {type(name).__name__}")
    if (
        isinstance(gps_latency, bool)
        or not isinstance(gps_latency, (int, float))
        or not math.isfinite(gps_latency)
        or gps_latency < 0
    ):
        raise ValueError(
            f"GPS latency must be a finite number of seconds >= 0, not {gps_latency!r}"
        )
    return _parse(bytes(data), name, float(gps_latency))


def _parse(data: bytes, name: str, gps_latency: float, *, per_line: bool = False) -> ParsedLog:
    """:func:`parse_log` after its checks. ``per_line`` reads every line on its own
    (:meth:`_Reader.read_per_line`), the reference the bulk reading must agree with."""
    reader = _Reader(data, name)
    if per_line:
        reader.read_per_line()
    else:
        reader.read()
    report = reader.report
    mag_line, raw_seq, *axes = reader.columns("mag", (np.int64, np.int64) + (np.float64,) * 3)
    seq, report.seq_gaps, report.seq_missing, report.seq_repeats = _unwrap_seq(raw_seq)
    gga_columns = reader.columns("gga", (np.int64,) + (np.float64,) * 3 + (np.int64,) * 2
                                 + (np.float64,) * 2)
    gga_line, tod, quality = gga_columns[0], gga_columns[1], gga_columns[4]
    zda_line, zda_datetimes = reader.columns("zda", (np.int64, object))
    zda_datetimes = zda_datetimes.tolist()

    anchors = _find_anchors(gga_line, tod, quality, zda_line, zda_datetimes)
    anchor_t = anchors.epoch + gps_latency
    anchor_pos = anchors.line.astype(np.float64)
    _report_anchors(report, anchors, anchor_pos, anchor_t)
    mag_t = _line_times(mag_line, anchor_pos, anchor_t)
    if report.time_aligned and len(mag_line):
        mag_t = _time_mag(report, mag_line, seq, mag_t, anchors, anchor_t)
    gga_t = _line_times(gga_line, anchor_pos, anchor_t) - gps_latency
    gga_t[anchors.gga_index] = anchors.epoch
    if not report.time_aligned:
        gga_t[:] = math.nan

    mag = MagData(mag_line, seq, np.column_stack(axes), mag_t, report.seq_gaps,
                  report.seq_missing, report.seq_repeats)
    cs_line, cs_field, cs_signal = reader.columns("cesium", (np.int64, np.float64, np.int64))
    cesium = CesiumData(cs_line, cs_field, cs_signal, _line_times(cs_line, anchor_pos, anchor_t))
    gga = GgaData(*gga_columns, gga_t)
    zda = ZdaData(zda_line, zda_datetimes, _line_times(zda_line, anchor_pos, anchor_t))
    vtg_line, course, speed = reader.columns("vtg", (np.int64, np.float64, np.float64))
    vtg = VtgData(vtg_line, course, speed, _line_times(vtg_line, anchor_pos, anchor_t))
    report.counts = {"mag": len(mag), "cesium": len(cesium), "gga": len(gga), "zda": len(zda),
                     "vtg": len(vtg)}
    found = Counter(reason for _, reason in reader.bad)
    report.bad = {reason: found.get(reason, 0) for reason in BAD_REASONS}
    report.ignored = dict(Counter(address for _, address in reader.ignored))
    if not data:
        report.messages.insert(0, f"{name}: the log is empty")
    return ParsedLog(name=name, mag=mag, cesium=cesium, gga=gga, zda=zda, vtg=vtg,
                     bad=reader.bad, ignored=reader.ignored, date=anchors.date, report=report)


def _report_anchors(report: LogReport, anchors: _Anchors, anchor_pos, anchor_t) -> None:
    """The report's anchor figures and notes."""
    name = report.name
    report.anchors = len(anchors.line)
    report.anchors_not_increasing = anchors.not_increasing
    report.midnight_rollovers = anchors.rollovers
    report.time_aligned = report.anchors >= 2
    if report.anchors == 0:
        report.messages.append(f"{name}: no GGA with a fix and a time: all times are NaN")
    elif report.anchors == 1:
        report.messages.append(
            f"{name}: only one GGA with a fix and a time (two are needed): all times are NaN"
        )
    else:
        report.line_rate_hz = float(
            (anchor_pos[-1] - anchor_pos[0]) / (anchor_t[-1] - anchor_t[0])
        )
    if anchors.beyond_calendar:
        report.messages.append(
            f"{name}: the ZDA date, carried to the first fix, falls outside the calendar "
            "(0001-01-01..9999-12-31): the date is unknown"
        )
    if report.time_aligned and anchors.date is None:
        report.messages.append(
            f"{name}: no ZDA: the date is unknown, "
            "times count from midnight of the first fix's day"
        )
    if anchors.not_increasing:
        report.messages.append(
            f"{name}: {anchors.not_increasing} GGA times did not increase and were left out"
        )


def _time_mag(report: LogReport, mag_line, seq, line_t, anchors: _Anchors, anchor_t):
    """Magnetometer times by sequence number (step 3 of the module doc), or ``line_t``, the
    times by line position, where the fit fails; the report says which."""
    name = report.name
    fit = _fit_mag(mag_line, seq, anchors.line, anchor_t)
    if fit is None:
        report.mag_timing = "line"
        report.messages.append(
            f"{name}: GGA anchors and magnetometer sequence numbers do not agree on a "
            "sample rate (too few anchors between magnetometer lines, or most disagree): "
            "magnetometer timed by line position"
        )
        return line_t
    mag_t = fit.times(seq)
    # A sample whose sequence time is far from its line time is not on the fitted line
    # (a sensor restart): it keeps its line time. Line times extrapolated beyond the
    # anchors get less certain with distance, so the limit grows there.
    beyond = np.maximum(0.0, np.maximum(anchor_t[0] - line_t, line_t - anchor_t[-1]))
    limit = _MAX_SEQUENCE_LINE_DISAGREEMENT + _DISAGREEMENT_GROWTH * beyond
    astray = np.abs(mag_t - line_t) > limit
    mag_t[astray] = line_t[astray]
    report.mag_line_timed = int(np.count_nonzero(astray))
    if report.mag_line_timed:
        report.messages.append(
            f"{name}: {report.mag_line_timed} magnetometer samples are more than "
            f"{_MAX_SEQUENCE_LINE_DISAGREEMENT:g} s from where their lines arrived "
            "(sensor restart?): timed by line position instead"
        )
    report.mag_timing = "sequence"
    report.mag_rate_hz = 1.0 / fit.period
    report.mag_brackets = fit.used
    report.mag_outliers = fit.outliers
    report.mag_fit_rms_s = fit.rms
    if fit.outliers > _OUTLIER_WARNING_SHARE * (fit.used + fit.outliers):
        report.messages.append(
            f"{name}: {fit.outliers} of {fit.used + fit.outliers} GGA anchors "
            "disagree with the magnetometer sequence (sensor restart or clock change?)"
        )
    return mag_t


def _interpolate(
    t_src, y_src, t_dst, max_gap: float | None, *, period: float | None = None
) -> np.ndarray:
    """Linear interpolation of ``y_src(t_src)`` at ``t_dst``: NaN outside the source span and
    inside source gaps longer than ``max_gap`` (None: five median source intervals).
    ``period`` unwraps a cyclic quantity (longitude) first."""
    t_dst = np.asarray(t_dst, dtype=np.float64)
    out = np.full(t_dst.shape, math.nan)
    good = np.isfinite(t_src) & np.isfinite(y_src)
    t_src, y_src = np.asarray(t_src, np.float64)[good], np.asarray(y_src, np.float64)[good]
    t_src, first = np.unique(t_src, return_index=True)
    y_src = y_src[first]
    if len(t_src) < 2:
        return out
    if period is not None:
        y_src = np.unwrap(y_src, period=period)
    if max_gap is None:
        max_gap = _GAP_INTERVALS * float(np.median(np.diff(t_src)))
    inside = np.isfinite(t_dst) & (t_dst >= t_src[0]) & (t_dst <= t_src[-1])
    right = np.clip(np.searchsorted(t_src, t_dst[inside], side="left"), 1, len(t_src) - 1)
    gap = t_src[right] - t_src[right - 1]
    exact = (t_src[right] == t_dst[inside]) | (t_src[right - 1] == t_dst[inside])
    values = np.interp(t_dst[inside], t_src, y_src)
    values[(gap > max_gap) & ~exact] = math.nan
    if period is not None:
        values = (values + period / 2) % period - period / 2
    out[inside] = values
    return out


def to_arrays(parsed: ParsedLog, *, max_gap: float | None = None) -> CalibrationArrays:
    """The magnetometer samples with the references calibration needs at their times.

    The cesium field and the GPS position (from GGAs with a fix, at their epochs) are
    interpolated linearly to the magnetometer times; NaN outside the source's span, where
    the magnetometer time is NaN, and inside source gaps longer than ``max_gap`` seconds
    (default: five median sample intervals of that source).
    """
    if not isinstance(parsed, ParsedLog):
        raise TypeError(f"Expected a ParsedLog from parse_log, not {type(parsed).__name__}")
    if max_gap is not None and (
        isinstance(max_gap, bool) or not isinstance(max_gap, (int, float)) or not max_gap > 0
    ):
        raise ValueError(f"Maximum gap must be a positive number of seconds, not {max_gap!r}")
    mag, gga = parsed.mag, parsed.gga
    fix = gga.quality >= 1
    return CalibrationArrays(
        t=mag.t.copy(),
        b=mag.b.copy(),
        seq=mag.seq.copy(),
        line=mag.line.copy(),
        cesium=_interpolate(parsed.cesium.t, parsed.cesium.field, mag.t, max_gap),
        lat=_interpolate(gga.t[fix], gga.lat[fix], mag.t, max_gap),
        lon=_interpolate(gga.t[fix], gga.lon[fix], mag.t, max_gap, period=2 * _LON_LIMIT),
        alt=_interpolate(gga.t[fix], gga.altitude[fix], mag.t, max_gap),
        date=parsed.date,
    )
