"""calib/diurnal.py: the base-station file and the diurnal correction."""

import datetime as dt
import json

import numpy as np
import pytest

from maglog.calib.diurnal import diurnal_correction, read_base_station
from maglog.calib.survey_errors import SurveyError

EPOCH = dt.datetime(2026, 6, 1, tzinfo=dt.timezone.utc)
START = 10 * 3600.0           # the base starts at 10:00:00 UTC
LEVEL = 48_000.0


def variation(seconds):
    """A daily variation and a 600 s pulsation (nT), as the scenarios make them."""
    return (20 * np.cos(2 * np.pi * (seconds - 13 * 3600) / 86_400)
            + 2 * np.sin(2 * np.pi * seconds / 600))


def iso(seconds):
    when = EPOCH + dt.timedelta(seconds=float(seconds))
    return when.strftime("%Y-%m-%dT%H:%M:%S.") + f"{when.microsecond // 1000:03d}Z"


def write_base(path, seconds, values=None, *, header="time_utc,total_nT"):
    if values is None:
        values = LEVEL + variation(np.asarray(seconds))
    rows = [header] + [f"{iso(s)},{v:.3f}" for s, v in zip(seconds, values)]
    path.write_text("\n".join(rows) + "\n")
    return path


def test_correction_follows_the_base_minus_its_median(tmp_path):
    seconds = START + np.arange(0, 3600, 1.0)
    base = read_base_station(write_base(tmp_path / "base.csv", seconds))
    assert len(base) == 3600 and base.name == "base.csv"
    t = START + 100 + np.arange(0, 1800, 0.1)     # a 30 min flight sampled at 10 Hz
    t[5] = np.nan
    correction = diurnal_correction(base, EPOCH, t)
    assert correction.shape == t.shape
    inside = (seconds >= t[0]) & (seconds <= np.nanmax(t))
    reference = np.median(LEVEL + variation(seconds[inside]))
    want = LEVEL + variation(t) - reference
    # 3-decimal file values and linear interpolation of a 2 nT, 600 s pulsation at 1 s
    assert np.nanmax(np.abs(correction - want)) < 2e-3
    assert np.isnan(correction[5])
    report = base.as_dict()
    json.dumps(report)
    assert report["file"] == "base.csv" and report["start_utc"] == "2026-06-01T10:00:00.000Z"


def test_naive_epoch_is_utc_and_other_offsets_convert(tmp_path):
    path = tmp_path / "base.csv"
    path.write_text("time_utc,total_nT\n2026-06-01T12:00:00+02:00,48000\n"
                    "2026-06-01T10:00:10Z,48010\n")
    base = read_base_station(path)
    correction = diurnal_correction(base, dt.datetime(2026, 6, 1), [START, START + 10])
    assert correction.tolist() == [-5.0, 5.0]


@pytest.mark.parametrize("text, message", [
    ("", r"base\.csv: empty base-station file"),
    ("time,total\n", r"base\.csv:1: header must start with time_utc,total_nT"),
    ("time_utc,total_nT\n2026-06-01T10:00:00Z,48000\n", r"base\.csv: 1 reading\(s\)"),
    ("time_utc,total_nT\n2026-06-01T10:00:00Z,48000\n2026-06-01T10:00:01Z\n",
     r"base\.csv:3: 1 column\(s\)"),
    ("time_utc,total_nT\n2026-06-01T10:00:00Z,48000\n\n2026-06-01T25:00:01Z,48000\n",
     r"base\.csv:4: bad time '2026-06-01T25:00:01Z'"),
    ("time_utc,total_nT\n2026-06-01T10:00:00,48000\n", r"base\.csv:2: bad time .*no zone"),
    ("time_utc,total_nT\n2026-06-01T10:00:00Z,48k\n", r"base\.csv:2: bad total field '48k'"),
    ("time_utc,total_nT\n2026-06-01T10:00:00Z,48.0\n", r"base\.csv:2: total field 48\.0 nT "
     r"outside"),
    ("time_utc,total_nT\n2026-06-01T10:00:00Z,nan\n", r"base\.csv:2: total field nan"),
    ("time_utc,total_nT\n2026-06-01T10:00:01Z,48000\n2026-06-01T10:00:01Z,48000\n",
     r"base\.csv:3: time 2026-06-01T10:00:01Z does not increase \(previous "
     r"2026-06-01T10:00:01\.000Z\)"),
])
def test_malformed_base_files_name_file_and_line(tmp_path, text, message):
    path = tmp_path / "base.csv"
    path.write_text(text)
    with pytest.raises(SurveyError, match=message):
        read_base_station(path)


def test_missing_and_binary_files(tmp_path):
    with pytest.raises(SurveyError, match="nothing.csv: base-station file not found"):
        read_base_station(tmp_path / "nothing.csv")
    (tmp_path / "b.csv").write_bytes(b"time_utc,total_nT\n\xff\xfe")
    with pytest.raises(SurveyError, match=r"b\.csv: not UTF-8"):
        read_base_station(tmp_path / "b.csv")


def test_a_gap_inside_the_flight_is_named(tmp_path):
    seconds = START + np.arange(0, 3600, 1.0)
    seconds = seconds[(seconds < START + 1000) | (seconds > START + 1030)]   # a 32 s gap
    base = read_base_station(write_base(tmp_path / "base.csv", seconds))
    t = START + np.arange(500, 2000, 0.1)
    with pytest.raises(SurveyError, match=r"base\.csv: gap of 32\.0 s from "
                       r"2026-06-01T10:16:39\.000Z to 2026-06-01T10:17:11\.000Z inside the "
                       r"flight \(limit 10 s\)"):
        diurnal_correction(base, EPOCH, t)
    # the same gap is fine with a longer limit, or outside the flight
    assert np.all(np.isfinite(diurnal_correction(base, EPOCH, t, max_gap_s=40)))
    assert np.all(np.isfinite(
        diurnal_correction(base, EPOCH, START + np.arange(1100, 2000, 0.1))))


def test_a_base_file_not_covering_the_flight(tmp_path):
    base = read_base_station(write_base(tmp_path / "base.csv", START + np.arange(0, 600.0)))
    with pytest.raises(SurveyError, match=r"base\.csv: covers 2026-06-01T10:00:00\.000Z to "
                       r"2026-06-01T10:09:59\.000Z, the flight 2026-06-01T10:05:00\.000Z to "
                       r"2026-06-01T10:11:39\.000Z: not covered"):
        diurnal_correction(base, EPOCH, START + np.arange(300, 700.0))
    with pytest.raises(SurveyError, match="no date"):
        diurnal_correction(base, None, START + np.arange(100, 200.0))
    with pytest.raises(SurveyError, match="no sample with a time"):
        diurnal_correction(base, EPOCH, [np.nan])
