"""Diurnal correction from a base-station magnetometer file.

The base station records the total field at a fixed place on the ground during the flight;
its changes are the time variations of the external field (the daily variation, pulsations),
the same over a small survey area. The correction at each survey sample is the base reading
at the sample's time minus the base's median over the flight: subtracting it from the
survey's total field removes the time variation and keeps the level.

File format (``base.csv``)::

    time_utc,total_nT
    2026-06-01T10:00:01.000Z,48123.456
    ...

ISO-8601 UTC times with ``Z`` (or an explicit ``+00:00`` offset; another offset is converted,
a time without a zone is an error), strictly increasing; total field in nT. Blank lines are
skipped; extra columns after these two are ignored.
"""

from __future__ import annotations

import csv
import datetime as _dt
import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from .survey_errors import SurveyError

__all__ = ["BaseStation", "read_base_station", "diurnal_correction", "BASE_HEADER",
           "MAX_GAP_S", "BASE_RANGE_NT"]

#: The header's first two columns.
BASE_HEADER = ("time_utc", "total_nT")
#: Default longest gap (s) between base readings inside the flight's span.
MAX_GAP_S = 10.0
#: Total fields (nT) a base station on the Earth reads (the weakest and strongest main field,
#: about 22,000 and 67,000 nT, with a wide margin); outside is a unit mistake or no lock.
BASE_RANGE_NT = (10_000.0, 100_000.0)


@dataclass(frozen=True, eq=False)
class BaseStation:
    """Base-station readings: ``time`` in POSIX seconds (UTC), ``total`` in nT; ``name``
    the file's name (for messages)."""

    name: str
    time: np.ndarray
    total: np.ndarray

    def __len__(self) -> int:
        return len(self.time)

    def as_dict(self) -> dict:
        return {"file": self.name, "readings": int(self.time.size),
                "start_utc": _utc(self.time[0]), "end_utc": _utc(self.time[-1]),
                "median_interval_s": float(np.median(np.diff(self.time)))
                if self.time.size > 1 else None}


def _utc(posix):
    """ISO-8601 UTC with milliseconds and ``Z``."""
    when = _dt.datetime.fromtimestamp(float(posix), tz=_dt.timezone.utc)
    return when.strftime("%Y-%m-%dT%H:%M:%S.") + f"{when.microsecond // 1000:03d}Z"


def _parse_time(text):
    text = text.strip()
    if not text:
        raise ValueError("empty time")
    when = _dt.datetime.fromisoformat(text[:-1] + "+00:00" if text[-1:] in "Zz" else text)
    if when.tzinfo is None:
        raise ValueError(f"time {text!r} has no zone (write it in UTC with Z)")
    return when.timestamp()


def read_base_station(path) -> BaseStation:
    """Read a base-station CSV (see the module doc). Raises :class:`SurveyError` naming the
    file and line for a missing file, a wrong header, a malformed row (time, number, too few
    columns), a field outside :data:`BASE_RANGE_NT`, a time that does not increase, or a
    file without readings."""
    path = Path(path)
    name = path.name
    try:
        text = path.read_bytes().decode("utf-8-sig")
    except FileNotFoundError:
        raise SurveyError(f"{path}: base-station file not found") from None
    except UnicodeDecodeError as error:
        raise SurveyError(f"{name}: not UTF-8 text (byte {error.start})") from None
    except OSError as error:
        raise SurveyError(f"{path}: cannot read the base-station file ({error.strerror})") \
            from None
    times, totals = [], []
    header_seen = False
    previous = -math.inf
    for number, row in enumerate(csv.reader(text.splitlines()), start=1):
        if not row or all(not cell.strip() for cell in row):
            continue
        if not header_seen:
            got = tuple(cell.strip() for cell in row[:2])
            if got != BASE_HEADER:
                raise SurveyError(f"{name}:{number}: header must start with "
                                  f"{','.join(BASE_HEADER)}, not {','.join(row)!r}")
            header_seen = True
            continue
        if len(row) < 2:
            raise SurveyError(f"{name}:{number}: {len(row)} column(s), need time_utc,total_nT")
        try:
            posix = _parse_time(row[0])
        except ValueError as error:
            raise SurveyError(f"{name}:{number}: bad time {row[0].strip()!r} ({error})") \
                from None
        try:
            total = float(row[1])
        except ValueError:
            raise SurveyError(f"{name}:{number}: bad total field {row[1].strip()!r}") from None
        low, high = BASE_RANGE_NT
        if not low <= total <= high:     # also NaN and inf
            raise SurveyError(f"{name}:{number}: total field {row[1].strip()} nT outside "
                              f"{low:,.0f}..{high:,.0f} nT")
        if posix <= previous:
            raise SurveyError(f"{name}:{number}: time {row[0].strip()} does not increase "
                              f"(previous {_utc(previous)})")
        previous = posix
        times.append(posix)
        totals.append(total)
    if not header_seen:
        raise SurveyError(f"{name}: empty base-station file (no header)")
    if len(times) < 2:
        raise SurveyError(f"{name}: {len(times)} reading(s): a base station needs at least two")
    return BaseStation(name=name, time=np.array(times), total=np.array(totals))


def diurnal_correction(base: BaseStation, epoch, t, *, max_gap_s=MAX_GAP_S) -> np.ndarray:
    """The diurnal correction (nT) at the survey times ``t`` (seconds since ``epoch``, the
    log's 00:00 UTC: ``parsed.epoch``, an aware datetime; a naive one is taken as UTC), an
    array shaped like ``t``, NaN where ``t`` is NaN: subtract it from the survey's total field.

    The base readings are interpolated linearly to ``t``; the correction is that minus the
    median of the base readings within the flight's span (the first to the last finite
    ``t``; without a reading inside, the median of the two interpolated at its ends), so
    the survey keeps its level. Raises :class:`SurveyError` when ``epoch`` is None (a log without a date), when
    the base file does not cover the flight's span, or when two consecutive base readings
    overlapping the span lie more than ``max_gap_s`` apart (naming the gap's UTC start and
    end).
    """
    if epoch is None:
        raise SurveyError(f"{base.name}: the log has no date (no ZDA sentence): its times "
                          "cannot be matched to the base station's")
    if epoch.tzinfo is None:
        epoch = epoch.replace(tzinfo=_dt.timezone.utc)
    t = np.asarray(t, float)
    finite = np.isfinite(t)
    if not np.any(finite):
        raise SurveyError(f"{base.name}: the survey has no sample with a time")
    zero = epoch.timestamp()
    first, last = float(np.min(t[finite])), float(np.max(t[finite]))
    start, end = zero + first, zero + last
    if base.time[0] > start or base.time[-1] < end:
        raise SurveyError(f"{base.name}: covers {_utc(base.time[0])} to {_utc(base.time[-1])}, "
                          f"the flight {_utc(start)} to {_utc(end)}: not covered")
    steps = np.diff(base.time)
    overlapping = (base.time[1:] > start) & (base.time[:-1] < end)
    wide = np.flatnonzero((steps > max_gap_s) & overlapping)
    if wide.size:
        k = wide[0]
        more = f" (and {wide.size - 1} more)" if wide.size > 1 else ""
        raise SurveyError(f"{base.name}: gap of {steps[k]:.1f} s from {_utc(base.time[k])} "
                          f"to {_utc(base.time[k + 1])} inside the flight (limit "
                          f"{max_gap_s:g} s){more}")
    inside = (base.time >= start) & (base.time <= end)
    if np.any(inside):
        reference = float(np.median(base.total[inside]))
    else:       # the whole flight between two readings
        reference = float(np.median(np.interp([start, end], base.time, base.total)))
    correction = np.full(t.shape, np.nan)
    correction[finite] = np.interp(zero + t[finite], base.time, base.total) - reference
    return correction
