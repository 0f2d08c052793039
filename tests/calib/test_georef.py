"""calib/georef.py: positions from GGA, IGRF along the track, survey lines from the track.

The tracks are built here: a multirotor survey as the scenarios fly it (ground, hover, a
calibration box in place, minimum-jerk lines joined by sideways steps, tie lines back and
forth, landing), sampled at 10 Hz, its positions sent as 1 Hz GGA with 4-decimal minutes.
"""

import datetime as dt
import json

import numpy as np
import pytest

from maglog.calib.georef import (METRES_PER_DEGREE, Line, find_lines, georeference,
                                 igrf_total, line_of_sample, local_metres)
from maglog.calib.logparse import parse_log
from maglog.calib.survey_errors import SurveyError
from maglog.sim.stimulus.sentences import cesium, nmea_sentence, zda

LAT0, LON0 = 47.5, 8.5
DAY = dt.datetime(2026, 6, 1)
T0 = 10 * 3600.0            # the flight starts at 10:00:00 UTC
#: One unit of GGA's 4-decimal minutes, in metres of latitude.
GGA_QUANTUM_M = METRES_PER_DEGREE / 600_000


def min_jerk(x):
    x = np.clip(x, 0.0, 1.0)
    return x ** 3 * (10 - 15 * x + 6 * x ** 2)


def survey_track(*, lines=6, length=300.0, spacing=30.0, course_deg=30.0, speed=10.0, ties=3,
                 step_s=10.0, rate=10.0, box_s=120.0, seed=0):
    """(t, north, east, moves): a survey at 10 Hz from t = 0; ``moves`` lists (kind, start,
    end) of every line and tie move (whole moves, accelerations included). The calibration
    box hovers with 0.1 m of random drift."""
    c = np.radians(course_deg)
    along = np.array([np.cos(c), np.sin(c)])
    across = np.array([np.cos(c + np.pi / 2), np.sin(c + np.pi / 2)])
    moves = [(20.0, np.zeros(2), "ground"), (box_s, np.zeros(2), "box")]
    for k in range(lines):
        moves.append((1.875 * length / speed, along * length * (1 if k % 2 == 0 else -1),
                      "line"))
        if k + 1 < lines:
            moves.append((step_s, across * spacing, "step"))
    at_along = length if lines % 2 else 0.0
    at_across = (lines - 1) * spacing
    tie_length = (lines + 1) * spacing
    places = [length * (j + 1) / (ties + 1) for j in range(ties)]
    if at_along > length / 2:
        places = places[::-1]
    far, near = at_across + spacing, -spacing          # the ties' ends, past the lines
    for j, place in enumerate(places):
        start, end = (far, near) if j % 2 == 0 else (near, far)
        moves.append((step_s + 10.0, along * (place - at_along) + across * (start - at_across),
                      "transit"))
        moves.append((1.875 * tie_length / speed, across * (end - start), "tie"))
        at_along, at_across = place, end
    moves.append((60.0, np.zeros(2), "landing"))
    total = sum(m[0] for m in moves)
    t = np.arange(0.0, total, 1.0 / rate)
    north, east = np.zeros_like(t), np.zeros_like(t)
    pos, now, out = np.zeros(2), 0.0, []
    for seconds, delta, kind in moves:
        sel = (t >= now) & (t < now + seconds)
        s = min_jerk((t[sel] - now) / seconds)
        north[sel], east[sel] = pos[0] + delta[0] * s, pos[1] + delta[1] * s
        out.append((kind, now, now + seconds))
        pos, now = pos + delta, now + seconds
    north[t >= now], east[t >= now] = pos
    rng = np.random.default_rng(seed)
    box = (t >= moves[0][0]) & (t < moves[0][0] + box_s)
    north[box] += 0.1 * rng.standard_normal(box.sum())
    east[box] += 0.1 * rng.standard_normal(box.sum())
    return t, north, east, out


def as_gga_track(t, north, east):
    """What georeferencing sees: positions at whole seconds rounded to GGA's 4-decimal
    minutes, interpolated back to ``t``."""
    whole = np.round(t) == t
    lat = np.round((LAT0 + north[whole] / METRES_PER_DEGREE) * 600_000) / 600_000
    lon = np.round((LON0 + east[whole] / (METRES_PER_DEGREE * np.cos(np.radians(LAT0))))
                   * 600_000) / 600_000
    n, e = local_metres(lat, lon, (LAT0, LON0))
    return np.interp(t, t[whole], n), np.interp(t, t[whole], e)


def expected_cut(start, end, fraction=0.5):
    """The part of a minimum-jerk move from ``start`` to ``end`` at or above ``fraction`` of
    its peak speed (speed ∝ x²(1-x)², peak at x = 1/2)."""
    x = 0.5 - np.sqrt(0.25 - np.sqrt(fraction / 16))
    return start + x * (end - start), end - x * (end - start)


# --- GGA → positions ---------------------------------------------------------------------


def _minutes(value, degree_digits):
    hemi = value < 0
    value = abs(value)
    degrees = int(value)
    minutes = round((value - degrees) * 60, 4)
    if minutes >= 60:
        degrees, minutes = degrees + 1, 0.0
    return f"{degrees:0{degree_digits}d}{minutes:07.4f}", hemi


def gga4(seconds_of_day, lat, lon, *, quality=1, altitude=540.0):
    """A GGA with 4-decimal minutes (as the survey receivers send)."""
    h, rest = divmod(seconds_of_day, 3600)
    m, s = divmod(rest, 60)
    la, south = _minutes(lat, 2)
    lo, west = _minutes(lon, 3)
    body = (f"GPGGA,{int(h):02d}{int(m):02d}{s:05.2f},{la},{'S' if south else 'N'},{lo},"
            f"{'W' if west else 'E'},{quality},08,0.9,{altitude:.1f},M,47.0,M,,")
    return nmea_sentence(body)


def make_log(t, north, east, *, no_fix=(), up=None):
    """A log: ZDA, then each second a GGA (quality 0 in the ``no_fix`` seconds) and ten
    cesium lines. Returns the bytes."""
    out = [zda(DAY + dt.timedelta(seconds=T0))]
    whole = np.flatnonzero(np.round(t * 10) % 10 == 0)
    for i in whole:
        second = int(round(t[i]))
        lat = LAT0 + north[i] / METRES_PER_DEGREE
        lon = LON0 + east[i] / (METRES_PER_DEGREE * np.cos(np.radians(LAT0)))
        alt = 500.0 + (0.0 if up is None else up[i])
        out.append(gga4(T0 + second, lat, lon, quality=0 if second in no_fix else 1,
                        altitude=alt))
        out.extend(cesium(48_000.0 + k, 1249) for k in range(10))
    return b"".join(out)


def test_georeference_matches_the_track_and_leaves_gaps_empty():
    t, north, east, _ = survey_track(lines=2, ties=0, box_s=10.0)
    t, north, east = t[t < 120], north[t < 120], east[t < 120]
    up = 0.05 * t
    gap = set(range(60, 70))                     # ten seconds without a fix: a 11 s gap
    parsed = parse_log(make_log(t, north, east, no_fix=gap, up=up), name="LOG00007.TXT")
    track = georeference(parsed, parsed.cesium.t)
    assert track.origin == pytest.approx((LAT0, LON0), abs=1e-6)
    ts = track.t - T0
    truth_n = np.interp(ts, t, north)
    truth_e = np.interp(ts, t, east)
    inside_gap = (ts > 59) & (ts < 70)
    outside = ~inside_gap & (ts >= 0) & (ts <= 119)      # after the last fix: NaN
    assert np.all(np.isnan(track.north[inside_gap])) and np.all(np.isnan(track.lat[inside_gap]))
    assert np.all(np.isnan(track.north[ts > 119]))
    assert np.all(np.isfinite(track.north[outside]))
    # 4-decimal minutes (0.19 m) plus linear interpolation of a 0.5 m/s² move between fixes
    # (the hovering box's 10 Hz jitter is left out: 1 Hz fixes cannot follow it)
    flying = outside & (ts >= 30)
    assert np.max(np.abs(track.north[flying] - truth_n[flying])) < 0.2
    assert np.max(np.abs(track.east[flying] - truth_e[flying])) < 0.2
    assert np.nanmax(np.abs(track.alt - 500.0 - 0.05 * ts)) < 0.06
    summary = track.as_dict()
    json.dumps(summary)
    assert summary["with_position"] == int(np.count_nonzero(np.isfinite(track.north)))


def test_georeference_without_a_fix_names_the_log():
    t, north, east, _ = survey_track(lines=2, ties=0, box_s=10.0)
    t, north, east = t[t < 5], north[t < 5], east[t < 5]
    parsed = parse_log(make_log(t, north, east, no_fix=set(range(10))), name="LOG00012.TXT")
    with pytest.raises(SurveyError, match=r"no position fix in LOG00012\.TXT"):
        georeference(parsed, parsed.cesium.t)


# --- IGRF --------------------------------------------------------------------------------


def test_igrf_total_against_a_published_value():
    # NOAA NCEI magnetic field calculator, IGRF-14, Ulaanbaatar (47.9 N, 106.9 E, 1300 m),
    # 2026-06-01: north 21568.1, east -2104.8, down 55327.5 nT (as listed in harmonica's
    # tests/test_igrf.py), so F = 59420.08 nT.
    published = np.sqrt(21568.1 ** 2 + 2104.8 ** 2 + 55327.5 ** 2)
    value = igrf_total(dt.date(2026, 6, 1), 47.9, 106.9, 1300.0)
    assert value.shape == ()
    assert float(value) == pytest.approx(published, abs=0.5)


def test_igrf_total_on_knots_equals_the_direct_evaluation():
    import ppigrf
    t, north, east, _ = survey_track(lines=3, ties=0, box_s=10.0)
    lat = LAT0 + north / METRES_PER_DEGREE
    lon = LON0 + east / (METRES_PER_DEGREE * np.cos(np.radians(LAT0)))
    alt = 540.0 + 10 * np.sin(t / 30)
    lat[500:530] = np.nan                     # a gap
    alt[700] = 1e6                            # an impossible altitude
    e, n, u = ppigrf.igrf(lon, lat, alt / 1000, DAY)
    direct = np.sqrt(e ** 2 + n ** 2 + u ** 2).ravel()
    for times in (t, None):
        fast = igrf_total(DAY.date(), lat, lon, alt, t=times)
        assert np.all(np.isnan(fast[500:530])) and np.isnan(fast[700])
        ok = np.isfinite(direct) & (alt < 1e5)
        assert np.all(np.isfinite(fast[ok]))
        assert np.max(np.abs(fast[ok] - direct[ok])) < 1e-3


def test_igrf_total_needs_a_date_inside_igrf():
    with pytest.raises(SurveyError, match="no date"):
        igrf_total(None, [47.5], [8.5], [500.0])
    with pytest.raises(SurveyError, match="2031-01-01 is outside IGRF-14"):
        igrf_total(dt.date(2031, 1, 1), [47.5], [8.5], [500.0])


# --- lines ---------------------------------------------------------------------------------


@pytest.mark.parametrize("course", [0.0, 30.0, 135.0])
def test_find_lines_keeps_the_steady_middle_of_each_line_and_tie(course):
    t, north, east, moves = survey_track(course_deg=course)
    n, e = as_gga_track(t, north, east)
    lines = find_lines(t, n, e, min_length_m=50.0)
    want = [m for m in moves if m[0] in ("line", "tie")]
    assert [line.kind for line in lines] == [m[0] for m in want]
    assert [line.index for line in lines] == [0, 1, 2, 3, 4, 5, 0, 1, 2]
    for line, (kind, start, end) in zip(lines, want):
        cut_start, cut_end = expected_cut(start, end)
        assert line.start == pytest.approx(cut_start, abs=0.5)
        assert line.end == pytest.approx(cut_end, abs=0.5)
        axis = course if kind == "line" else course + 90
        assert min(abs((line.course_deg - axis + 90) % 180 - 90), 90) < 1.0
        assert line.speed_m_s > 5.0
    json.dumps([line.as_dict() for line in lines])
    # the cut keeps 83 % of a minimum-jerk move's length
    assert lines[0].length_m == pytest.approx(0.833 * 300, abs=1.5)


@pytest.mark.parametrize("sigma", [0.5, 1.0])
def test_find_lines_through_gps_noise(sigma):
    # white noise of sigma metres on every 1 Hz fix (real GNSS noise is slower and smoother)
    t, north, east, moves = survey_track(course_deg=30.0)
    whole = np.round(t) == t
    rng = np.random.default_rng(7)
    n = np.interp(t, t[whole], north[whole] + sigma * rng.standard_normal(whole.sum()))
    e = np.interp(t, t[whole], east[whole] + sigma * rng.standard_normal(whole.sum()))
    lines = find_lines(t, n, e)
    want = [m for m in moves if m[0] in ("line", "tie")]
    assert [line.kind for line in lines] == [m[0] for m in want]
    for line, (_, start, end) in zip(lines, want):
        cut_start, cut_end = expected_cut(start, end)
        assert line.start == pytest.approx(cut_start, abs=3.0)
        assert line.end == pytest.approx(cut_end, abs=3.0)


def test_a_line_broken_by_a_gps_outage_is_one_line():
    t, north, east, moves = survey_track(course_deg=30.0)
    n, e = as_gga_track(t, north, east)
    start, end = moves[4][1:]                          # the second line
    outage = (t > start + 25) & (t < start + 33)       # 8 s without a position mid-line
    n[outage] = e[outage] = np.nan
    lines = find_lines(t, n, e)
    assert [line.kind for line in lines].count("line") == 6
    cut_start, cut_end = expected_cut(start, end)
    assert lines[1].start == pytest.approx(cut_start, abs=0.5)
    assert lines[1].end == pytest.approx(cut_end, abs=0.5)
    # each part is cut at half its own peak: the first part's peak lies before the move's
    assert lines[1].length_m == pytest.approx(0.833 * 300, abs=4.0)
    assert lines[1].course_deg == pytest.approx(210.0, abs=1.0)


def test_find_lines_never_takes_the_box_or_the_steps():
    # long, fast steps (60 m in 4 s: 28 m/s peak) and no ties: the steps are the only
    # stretches across the lines and cross none of them
    t, north, east, moves = survey_track(spacing=60.0, step_s=4.0, ties=0, box_s=300.0)
    n, e = as_gga_track(t, north, east)
    lines = find_lines(t, n, e, min_length_m=40.0)
    assert [line.kind for line in lines] == ["line"] * 6
    box_end = moves[1][2]
    assert all(line.start > box_end for line in lines)


def test_steps_outnumbering_the_ties_do_not_make_the_ties_lines():
    # five lines 100 m apart: four 100 m steps and three ties across, seven stretches
    # across the lines against five along them
    t, north, east, _ = survey_track(lines=5, spacing=100.0, step_s=15.0, ties=3)
    n, e = as_gga_track(t, north, east)
    lines = find_lines(t, n, e, min_length_m=65.0)
    assert [line.kind for line in lines] == ["line"] * 5 + ["tie"] * 3
    assert all(abs((line.course_deg - 30.0 + 90) % 180 - 90) < 1 for line in lines[:5])


def test_find_lines_drops_transits_between_ties():
    # transits along the lines between ties are 75 m: shorter than half the lines
    t, north, east, _ = survey_track(ties=3)
    n, e = as_gga_track(t, north, east)
    lines = find_lines(t, n, e, min_length_m=30.0)
    assert sum(line.kind == "line" for line in lines) == 6


def test_line_of_sample():
    lines = [Line("line", 0, 10.0, 20.0, 0.0), Line("tie", 0, 30.0, 40.0, 90.0)]
    which = line_of_sample(lines, np.array([5.0, 10.0, 15.0, 20.0, 25.0, 35.0, np.nan]))
    assert which.tolist() == [-1, 0, 0, 0, -1, 1, -1]


def test_find_lines_one_line_only():
    t, north, east, _ = survey_track(lines=1, ties=0)
    with pytest.raises(SurveyError, match="one survey line only .*a map needs at least two"):
        find_lines(t, north, east, min_length_m=50.0)
    hover = np.zeros_like(t)
    with pytest.raises(SurveyError, match="no survey line found"):
        find_lines(t, hover, hover, min_length_m=50.0)
