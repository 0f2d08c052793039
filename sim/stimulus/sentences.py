"""Serial sentence builders for the three sensor channels.

Every builder returns the exact bytes an instrument puts on its serial line, line end
included, with a correct checksum where the format has one:

- NMEA 0183 sentences of the GPS receiver: :func:`gga`, :func:`zda`, :func:`vtg` (the ones the
  logger keeps) and the distractors :func:`rmc`, :func:`gsa`, :func:`gsv` (the ones it drops);
- the magnetometer's proprietary ``$PMAG1`` sentence: :func:`pmag1`;
- the Geometrics G-882 style cesium line: :func:`cesium`;
- one second of a GPS receiver's output, the sentences above in its order: :func:`gps_epoch`
  (the one source of GPS epochs for the scenarios and the demo streams).

:func:`nmea_sentence` wraps any body as ``$`` body ``*hh`` line end and lets tests force a
wrong checksum. The formats are those of ``docs/architecture.md`` ("What is on the wire and on the card").

Ref: NMEA 0183 v4.10 §5.2 (sentence structure, checksum), §6.3 (GGA, GSA, GSV, RMC, VTG,
ZDA field layouts).
"""

from __future__ import annotations

import datetime as _dt
import math
import re
from collections.abc import Sequence

__all__ = [
    "CRLF",
    "LF",
    "nmea_checksum",
    "nmea_sentence",
    "pmag1",
    "cesium",
    "gga",
    "zda",
    "vtg",
    "rmc",
    "gsa",
    "gsv",
    "gps_epoch",
]

#: Line end the instruments send.
CRLF = b"\r\n"
#: Bare line end (some captures and adapters).
LF = b"\n"

_START = "$"
_CHECKSUM_DELIMITER = "*"
_FIELD_SEPARATOR = ","
_CHECKSUM_MAX = 0xFF
_TALKER_PATTERN = re.compile(r"[A-Z]{2}")

# $PMAG1: sequence 00000-99999 wrapping; each axis ±XXXXX.X in nT.
_PMAG_ID = "PMAG1"
_PMAG_SEQUENCE_MODULUS = 100_000
_PMAG_FIELD_DECIMALS = 1
#: Smallest magnitude that no longer fits ±XXXXX.X once rounded to one decimal.
PMAG_FIELD_LIMIT_NT = 99_999.95

# Cesium: a space or "1" (+100000 nT), five digits, ".", three digits, ",", four digits.
_CESIUM_MILLI = 1000
_CESIUM_HIGH_RANGE_NT = 100_000
_CESIUM_FIELD_LIMIT_NT = 200_000
_CESIUM_LOW_PREFIX = " "
_CESIUM_HIGH_PREFIX = "1"
CESIUM_SIGNAL_MAX = 9999

# Time and position encodings of NMEA 0183.
_SECONDS_PER_DAY = 86_400
_SECONDS_PER_HOUR = 3600
_SECONDS_PER_MINUTE = 60
_CENTI = 100
_MINUTES_PER_DEGREE = 60
_MINUTE_DECIMALS = 5
_MINUTE_SCALE = 10**_MINUTE_DECIMALS
_LAT_LIMIT_DEG = 90.0
_LON_LIMIT_DEG = 180.0
_FULL_CIRCLE_DEG = 360.0
_KNOTS_TO_KMH = 1.852
_TWO_DIGIT_MAX = 99
_GGA_QUALITY_MAX = 9
_GSA_PRN_SLOTS = 12
_GSA_FIX_MODES = (1, 2, 3)
_GSA_SELECTION_MODES = ("A", "M")
_GSV_SATELLITES_PER_SENTENCE = 4
_GSV_ELEVATION_MAX_DEG = 90
_GSV_AZIMUTH_MAX_DEG = 359
_GSV_MAX_SENTENCES = 9
_FAA_MODE_AUTONOMOUS = "A"
_FAA_MODE_NOT_VALID = "N"


def _as_ascii(text: bytes | str, what: str) -> bytes:
    if isinstance(text, str):
        try:
            return text.encode("ascii")
        except UnicodeEncodeError as error:
            raise ValueError(f"{what} must be ASCII, not {text!r}") from error
    if isinstance(text, (bytes, bytearray, memoryview)):
        return bytes(text)
    raise TypeError(f"{what} must be str or bytes, not {type(text).__name__}")


def nmea_checksum(body: bytes | str) -> int:
    """XOR of the bytes of ``body`` (the bytes between ``$`` and ``*``)."""
    checksum = 0
    for byte in _as_ascii(body, "Sentence body"):
        checksum ^= byte
    return checksum


def nmea_sentence(body: str, *, eol: bytes = CRLF, checksum: int | None = None) -> bytes:
    """``$`` + ``body`` + ``*HH`` + ``eol``, HH the checksum in upper-case hex.

    ``checksum`` overrides the computed value (to make deliberately bad sentences).
    """
    raw = _as_ascii(body, "Sentence body")
    if checksum is None:
        checksum = nmea_checksum(raw)
    elif isinstance(checksum, bool) or not isinstance(checksum, int) or not 0 <= checksum <= _CHECKSUM_MAX:
        raise ValueError(f"Checksum must be an integer 0..{_CHECKSUM_MAX}, not {checksum!r}")
    return (
        _START.encode()
        + raw
        + f"{_CHECKSUM_DELIMITER}{checksum:02X}".encode()
        + _check_eol(eol)
    )


def _check_eol(eol: bytes) -> bytes:
    if not isinstance(eol, (bytes, bytearray)):
        raise TypeError(f"Line end must be bytes, not {type(eol).__name__}")
    return bytes(eol)


def _check_talker(talker: str) -> str:
    if not isinstance(talker, str) or not _TALKER_PATTERN.fullmatch(talker):
        raise ValueError(f"Talker must be two upper-case letters A-Z, not {talker!r}")
    return talker


def _check_finite(value: float, what: str) -> float:
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value):
        raise ValueError(f"{what} must be a finite number, not {value!r}")
    return float(value)


def _check_int(value: int, what: str, low: int, high: int) -> int:
    if isinstance(value, bool) or not isinstance(value, int) or not low <= value <= high:
        raise ValueError(f"{what} must be an integer {low}..{high}, not {value!r}")
    return value


# --- magnetometer -------------------------------------------------------------------------


def _pmag_field(value: float, axis: str) -> str:
    value = _check_finite(value, f"Field {axis}")
    if abs(value) >= PMAG_FIELD_LIMIT_NT:
        raise ValueError(
            f"Field {axis} must be within ±{PMAG_FIELD_LIMIT_NT} nT to fit ±XXXXX.X, not {value!r}"
        )
    text = f"{value:+08.{_PMAG_FIELD_DECIMALS}f}"
    if float(text) == 0.0:
        text = f"{0.0:+08.{_PMAG_FIELD_DECIMALS}f}"  # no "-00000.0"
    return text


def pmag1(seq: int, x: float, y: float, z: float, *, eol: bytes = CRLF) -> bytes:
    """``$PMAG1,SSSSS,±XXXXX.X,±YYYYY.Y,±ZZZZZ.Z*hh`` + ``eol``.

    ``seq`` is a non-negative sample counter, written modulo 100000 as five digits; x, y, z
    are the field components in nT.
    """
    if isinstance(seq, bool) or not isinstance(seq, int) or seq < 0:
        raise ValueError(f"Sequence number must be a non-negative integer, not {seq!r}")
    fields = [
        _PMAG_ID,
        f"{seq % _PMAG_SEQUENCE_MODULUS:05d}",
        _pmag_field(x, "x"),
        _pmag_field(y, "y"),
        _pmag_field(z, "z"),
    ]
    return nmea_sentence(_FIELD_SEPARATOR.join(fields), eol=eol)


# --- cesium -------------------------------------------------------------------------------


def cesium(field_nt: float, signal: int, *, eol: bytes = CRLF) -> bytes:
    """Geometrics G-882 style ``$ 49895.131,1249`` + ``eol`` (no checksum).

    A field of 100000 nT or more is written with a leading ``1`` in place of the space and
    the five digits of ``field_nt - 100000``.
    """
    field_nt = _check_finite(field_nt, "Cesium field")
    if not 0 <= field_nt < _CESIUM_FIELD_LIMIT_NT:
        raise ValueError(
            f"Cesium field must be 0 <= field < {_CESIUM_FIELD_LIMIT_NT} nT, not {field_nt!r}"
        )
    _check_int(signal, "Signal level", 0, CESIUM_SIGNAL_MAX)
    milli = round(field_nt * _CESIUM_MILLI)
    high_range_milli = _CESIUM_HIGH_RANGE_NT * _CESIUM_MILLI
    if milli >= _CESIUM_FIELD_LIMIT_NT * _CESIUM_MILLI:
        raise ValueError(f"Cesium field {field_nt!r} nT rounds to {_CESIUM_FIELD_LIMIT_NT} nT")
    prefix = _CESIUM_LOW_PREFIX
    if milli >= high_range_milli:
        prefix = _CESIUM_HIGH_PREFIX
        milli -= high_range_milli
    whole, fraction = divmod(milli, _CESIUM_MILLI)
    text = f"{_START}{prefix}{whole:05d}.{fraction:03d}{_FIELD_SEPARATOR}{signal:04d}"
    return text.encode("ascii") + _check_eol(eol)


# --- NMEA field encodings -----------------------------------------------------------------


def _hhmmss_centi(seconds_of_day: float) -> str:
    centis = round(seconds_of_day * _CENTI) % (_SECONDS_PER_DAY * _CENTI)
    seconds, centi = divmod(centis, _CENTI)
    hours, rest = divmod(seconds, _SECONDS_PER_HOUR)
    minutes, seconds = divmod(rest, _SECONDS_PER_MINUTE)
    return f"{hours:02d}{minutes:02d}{seconds:02d}.{centi:02d}"


def _datetime_utc(value: _dt.datetime) -> _dt.datetime:
    if not isinstance(value, _dt.datetime):
        raise ValueError(f"Time must be a datetime.datetime, not {value!r}")
    if value.tzinfo is not None:
        value = value.astimezone(_dt.timezone.utc).replace(tzinfo=None)
    return value  # naive datetimes are taken as UTC


def _time_of_datetime(value: _dt.datetime) -> str:
    centi = value.microsecond // (1_000_000 // _CENTI)  # truncate, never round into the next second
    return f"{value:%H%M%S}.{centi:02d}"


def _angle(
    value_deg: float, limit: float, degree_digits: int, hemispheres: str, what: str
) -> tuple[str, str]:
    value_deg = _check_finite(value_deg, what)
    if not -limit <= value_deg <= limit:
        raise ValueError(f"{what} must be within ±{limit:g}°, not {value_deg!r}")
    hemisphere = hemispheres[0] if value_deg >= 0 else hemispheres[1]
    units = round(abs(value_deg) * _MINUTES_PER_DEGREE * _MINUTE_SCALE)
    degrees, minute_units = divmod(units, _MINUTES_PER_DEGREE * _MINUTE_SCALE)
    minutes, fraction = divmod(minute_units, _MINUTE_SCALE)
    return f"{degrees:0{degree_digits}d}{minutes:02d}.{fraction:0{_MINUTE_DECIMALS}d}", hemisphere


def _latitude(lat_deg: float) -> tuple[str, str]:
    return _angle(lat_deg, _LAT_LIMIT_DEG, 2, "NS", "Latitude")


def _longitude(lon_deg: float) -> tuple[str, str]:
    return _angle(lon_deg, _LON_LIMIT_DEG, 3, "EW", "Longitude")


def _sentence(talker: str, name: str, fields: Sequence[str], eol: bytes) -> bytes:
    return nmea_sentence(_FIELD_SEPARATOR.join([_check_talker(talker) + name, *fields]), eol=eol)


# --- kept sentences -----------------------------------------------------------------------


def gga(
    t_utc_seconds: float,
    lat_deg: float,
    lon_deg: float,
    *,
    quality: int = 1,
    satellites: int = 8,
    hdop: float = 0.9,
    altitude_m: float = 100.0,
    geoid_m: float = 45.0,
    talker: str = "GP",
    eol: bytes = CRLF,
) -> bytes:
    """GGA fix data: ``$GPGGA,hhmmss.ss,ddmm.mmmmm,N,dddmm.mmmmm,E,q,ss,h.h,a.a,M,g.g,M,,*hh``.

    ``t_utc_seconds`` is taken modulo one day (seconds since midnight or since an epoch
    that starts at midnight both work). The DGPS age and station fields are empty.
    """
    t_utc_seconds = _check_finite(t_utc_seconds, "Time")
    lat, ns = _latitude(lat_deg)
    lon, ew = _longitude(lon_deg)
    _check_int(quality, "Fix quality", 0, _GGA_QUALITY_MAX)
    _check_int(satellites, "Satellite count", 0, _TWO_DIGIT_MAX)
    fields = [
        _hhmmss_centi(t_utc_seconds),
        lat,
        ns,
        lon,
        ew,
        str(quality),
        f"{satellites:02d}",
        f"{_check_finite(hdop, 'HDOP'):.1f}",
        f"{_check_finite(altitude_m, 'Altitude'):.1f}",
        "M",
        f"{_check_finite(geoid_m, 'Geoid separation'):.1f}",
        "M",
        "",  # age of DGPS data
        "",  # DGPS station id
    ]
    return _sentence(talker, "GGA", fields, eol)


def zda(datetime_utc: _dt.datetime, *, talker: str = "GP", eol: bytes = CRLF) -> bytes:
    """ZDA time and date: ``$GPZDA,hhmmss.ss,dd,mm,yyyy,00,00*hh``.

    A naive datetime is taken as UTC; an aware one is converted to UTC.
    """
    when = _datetime_utc(datetime_utc)
    fields = [_time_of_datetime(when), f"{when:%d}", f"{when:%m}", f"{when.year:04d}", "00", "00"]
    return _sentence(talker, "ZDA", fields, eol)


def vtg(
    course_deg: float,
    speed_knots: float,
    *,
    magnetic_course_deg: float | None = None,
    talker: str = "GP",
    eol: bytes = CRLF,
) -> bytes:
    """VTG course and speed: ``$GPVTG,ccc.c,T,[mmm.m],M,s.s,N,k.k,K,A*hh`` (FAA mode A)."""
    course = _check_finite(course_deg, "Course") % _FULL_CIRCLE_DEG
    speed = _check_finite(speed_knots, "Speed")
    if speed < 0:
        raise ValueError(f"Speed must be non-negative, not {speed_knots!r}")
    magnetic = ""
    if magnetic_course_deg is not None:
        magnetic = f"{_check_finite(magnetic_course_deg, 'Magnetic course') % _FULL_CIRCLE_DEG:05.1f}"
    fields = [
        f"{course:05.1f}",
        "T",
        magnetic,
        "M",
        f"{speed:.1f}",
        "N",
        f"{speed * _KNOTS_TO_KMH:.1f}",
        "K",
        _FAA_MODE_AUTONOMOUS,
    ]
    return _sentence(talker, "VTG", fields, eol)


# --- distractors --------------------------------------------------------------------------


def rmc(
    datetime_utc: _dt.datetime,
    lat_deg: float,
    lon_deg: float,
    *,
    speed_knots: float = 0.0,
    course_deg: float = 0.0,
    valid: bool = True,
    talker: str = "GP",
    eol: bytes = CRLF,
) -> bytes:
    """RMC recommended minimum data (dropped by the logger):
    ``$GPRMC,hhmmss.ss,A,ddmm.mmmmm,N,dddmm.mmmmm,E,s.s,c.c,ddmmyy,,,A*hh``."""
    when = _datetime_utc(datetime_utc)
    lat, ns = _latitude(lat_deg)
    lon, ew = _longitude(lon_deg)
    speed = _check_finite(speed_knots, "Speed")
    if speed < 0:
        raise ValueError(f"Speed must be non-negative, not {speed_knots!r}")
    fields = [
        _time_of_datetime(when),
        "A" if valid else "V",
        lat,
        ns,
        lon,
        ew,
        f"{speed:.1f}",
        f"{_check_finite(course_deg, 'Course') % _FULL_CIRCLE_DEG:.1f}",
        f"{when:%d%m%y}",
        "",  # magnetic variation
        "",  # variation direction
        _FAA_MODE_AUTONOMOUS if valid else _FAA_MODE_NOT_VALID,
    ]
    return _sentence(talker, "RMC", fields, eol)


def gsa(
    prns: Sequence[int],
    *,
    selection: str = "A",
    fix: int = 3,
    pdop: float = 1.6,
    hdop: float = 0.9,
    vdop: float = 1.3,
    talker: str = "GP",
    eol: bytes = CRLF,
) -> bytes:
    """GSA DOP and active satellites (dropped by the logger):
    ``$GPGSA,A,3,p1,...,p12,p.p,h.h,v.v*hh`` with up to 12 PRNs, unused slots empty."""
    if selection not in _GSA_SELECTION_MODES:
        raise ValueError(f"Selection mode must be one of {_GSA_SELECTION_MODES}, not {selection!r}")
    if fix not in _GSA_FIX_MODES:
        raise ValueError(f"Fix mode must be one of {_GSA_FIX_MODES}, not {fix!r}")
    prns = list(prns)
    if len(prns) > _GSA_PRN_SLOTS:
        raise ValueError(f"GSA holds at most {_GSA_PRN_SLOTS} satellites, not {len(prns)}")
    slots = [f"{_check_int(prn, 'PRN', 1, _TWO_DIGIT_MAX):02d}" for prn in prns]
    slots += [""] * (_GSA_PRN_SLOTS - len(slots))
    fields = [
        selection,
        str(fix),
        *slots,
        f"{_check_finite(pdop, 'PDOP'):.1f}",
        f"{_check_finite(hdop, 'HDOP'):.1f}",
        f"{_check_finite(vdop, 'VDOP'):.1f}",
    ]
    return _sentence(talker, "GSA", fields, eol)


def gsv(
    satellites: Sequence[tuple[int, int, int, int | None]],
    *,
    talker: str = "GP",
    eol: bytes = CRLF,
) -> bytes:
    """GSV satellites in view (dropped by the logger), all messages of one cycle concatenated.

    ``satellites`` holds ``(prn, elevation_deg, azimuth_deg, snr_db or None)``; four per
    sentence: ``$GPGSV,total,index,in_view,prn,el,az,snr,...*hh``. An empty list gives one
    sentence with zero satellites in view.
    """
    entries = list(satellites)
    count = len(entries)
    total = max(1, math.ceil(count / _GSV_SATELLITES_PER_SENTENCE))
    if total > _GSV_MAX_SENTENCES:
        raise ValueError(
            f"GSV holds at most {_GSV_MAX_SENTENCES * _GSV_SATELLITES_PER_SENTENCE} satellites, not {count}"
        )
    out = bytearray()
    for index in range(total):
        fields = [str(total), str(index + 1), f"{count:02d}"]
        start = index * _GSV_SATELLITES_PER_SENTENCE
        for prn, elevation, azimuth, snr in entries[start : start + _GSV_SATELLITES_PER_SENTENCE]:
            fields += [
                f"{_check_int(prn, 'PRN', 1, _TWO_DIGIT_MAX):02d}",
                f"{_check_int(elevation, 'Elevation', 0, _GSV_ELEVATION_MAX_DEG):02d}",
                f"{_check_int(azimuth, 'Azimuth', 0, _GSV_AZIMUTH_MAX_DEG):03d}",
                "" if snr is None else f"{_check_int(snr, 'SNR', 0, _TWO_DIGIT_MAX):02d}",
            ]
        out += _sentence(talker, "GSV", fields, eol)
    return bytes(out)


#: GGA's satellite count and HDOP while the receiver has no fix.
NO_FIX_SATELLITES = 3
NO_FIX_HDOP = 99.0


def gps_epoch(
    when: _dt.datetime,
    lat_deg: float,
    lon_deg: float,
    *,
    course_deg: float,
    speed_knots: float,
    sky: Sequence[tuple[int, int, int, int | None]],
    fix: bool = True,
    hdop: float = 0.9,
    altitude_m: float = 100.0,
    geoid_m: float = 45.0,
    distractors: bool = True,
    talker: str = "GP",
) -> list[tuple[str, bytes]]:
    """One second of a GPS receiver's output at ``when``, as ``(type, sentence)`` pairs in the
    order it sends them: RMC, VTG, GGA, GSA, one GSV per line, ZDA (RMC, GSA and GSV only
    with ``distractors``). ``sky``: the satellites in view, ``(prn, elevation, azimuth,
    snr)``, all of them used for the fix. Without a ``fix``: RMC void, GGA quality 0 with
    :data:`NO_FIX_SATELLITES` satellites and HDOP :data:`NO_FIX_HDOP`, GSA fix 1 with no
    PRNs."""
    seconds_of_day = when.hour * 3600 + when.minute * 60 + when.second + when.microsecond / 1e6
    sky = list(sky)
    epoch = []
    if distractors:
        epoch.append(("RMC", rmc(when, lat_deg, lon_deg, speed_knots=speed_knots,
                                 course_deg=course_deg, valid=fix, talker=talker)))
    epoch.append(("VTG", vtg(course_deg, speed_knots, talker=talker)))
    epoch.append(("GGA", gga(seconds_of_day, lat_deg, lon_deg, quality=1 if fix else 0,
                             satellites=len(sky) if fix else NO_FIX_SATELLITES,
                             hdop=hdop if fix else NO_FIX_HDOP, altitude_m=altitude_m,
                             geoid_m=geoid_m, talker=talker)))
    if distractors:
        epoch.append(("GSA", gsa([prn for prn, *_ in sky] if fix else [], fix=3 if fix else 1,
                                 talker=talker)))
        epoch += [("GSV", line) for line in gsv(sky, talker=talker).splitlines(keepends=True)]
    epoch.append(("ZDA", zda(when, talker=talker)))
    return epoch
