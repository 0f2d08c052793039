"""calib/levelling.py: crossovers and tie-line levelling on a survey built here (straight lines
at constant speed, known per-line offsets and drifts, a known smooth field)."""

import json

import numpy as np
import pytest

from maglog.calib.georef import Line, find_lines, line_of_sample
from maglog.calib.levelling import crossovers, level
from maglog.calib.survey_errors import SurveyError

SPACING = 30.0
LENGTH = 300.0
SPEED = 10.0
RATE = 10.0
TIE_NORTH = (75.0, 150.0, 225.0)


def field(north, east):
    """A smooth anomaly (nT)."""
    return 80 * np.exp(-((north - 140) ** 2 + (east - 70) ** 2) / 90 ** 2) + 0.02 * north


def grid_survey(n_lines=8, tie_north=TIE_NORTH, wobble=0.0, surge=0.0):
    """Lines north-south at east = k·SPACING flown back and forth, then ties east-west at
    ``tie_north`` from beyond the last line to beyond the first; a 10 s hover between moves.
    ``surge`` varies the speed along each move by that share (1 ± surge, as the middle of a
    minimum-jerk move does); ``wobble`` (m) bends the tracks.
    Returns t, north, east, lines (the :class:`Line` list, as find_lines gives it)."""
    ts, ns, es, lines = [], [], [], []
    now = 0.0

    def fly(p, q, kind, index):
        nonlocal now
        seconds = np.hypot(*(np.subtract(q, p))) / SPEED
        tau = np.arange(0, seconds * RATE + 1) / (seconds * RATE)
        x = tau - surge * np.sin(2 * np.pi * tau) / (2 * np.pi)
        ts.append(now + tau * seconds)
        ns.append(p[0] + x * (q[0] - p[0]) + wobble * np.sin(7 * x))
        es.append(p[1] + x * (q[1] - p[1]) + wobble * np.cos(5 * x))
        course = np.degrees(np.arctan2(q[1] - p[1], q[0] - p[0])) % 360
        lines.append(Line(kind, index, now, now + seconds, course, seconds * SPEED, SPEED))
        now += seconds + 10.0
    for k in range(n_lines):
        ends = ((0.0, k * SPACING), (LENGTH, k * SPACING))
        fly(*(ends if k % 2 == 0 else ends[::-1]), "line", k)
    far = n_lines * SPACING
    for j, north in enumerate(tie_north):
        ends = ((north, far), (north, -SPACING))
        fly(*(ends if j % 2 == 0 else ends[::-1]), "tie", j)
    return np.concatenate(ts), np.concatenate(ns), np.concatenate(es), lines


def with_errors(t, north, east, lines, offsets, slopes=None, noise=0.0, seed=0):
    value = field(north, east)
    which = line_of_sample(lines, t)
    for k, line in enumerate(lines):
        sel = which == k
        value[sel] += offsets[k]
        if slopes is not None:
            value[sel] += slopes[k] * (t[sel] - (line.start + line.end) / 2)
    return value + noise * np.random.default_rng(seed).standard_normal(t.size), which


def test_crossovers_are_where_the_tracks_cross():
    t, north, east, lines = grid_survey(wobble=0.7)
    offsets = np.arange(len(lines), dtype=float)
    value, _ = with_errors(t, north, east, lines, offsets)
    found = crossovers(lines, t, north, east, value)
    assert len(found) == 8 * 3
    assert [(c.line, c.tie) for c in found] == [(k, 8 + j) for k in range(8) for j in range(3)]
    for c in found:
        assert c.east == pytest.approx(lines[c.line].start * 0 + c.line * SPACING, abs=1.0)
        assert c.north == pytest.approx(TIE_NORTH[c.tie - 8], abs=1.0)
        # the value differences are the offsets' differences (same place, same field)
        assert c.difference == pytest.approx(offsets[c.line] - offsets[c.tie], abs=0.05)
        assert lines[c.line].start <= c.t_line <= lines[c.line].end
        assert lines[c.tie].start <= c.t_tie <= lines[c.tie].end
    json.dumps([c.as_dict(lines) for c in found])
    assert found[0].as_dict(lines)["tie_name"] == "T0"


def test_order_0_recovers_the_line_offsets():
    t, north, east, lines = grid_survey()
    rng = np.random.default_rng(3)
    offsets = rng.normal(0, 5, len(lines))
    ties = [k for k, line in enumerate(lines) if line.kind == "tie"]
    offsets[ties] -= offsets[ties].mean()            # the reference: ties' mean is zero
    value, which = with_errors(t, north, east, lines, offsets, noise=0.05)
    found = crossovers(lines, t, north, east, value)
    result = level(lines, t, value, found)
    # a crossover difference carries ~0.06 nT of the 0.05 nT sample noise; a line's offset
    # rests on three of them and the ties': 0.15 nT is about four standard deviations
    assert result.offsets == pytest.approx(offsets, abs=0.15)
    assert result.rms_before > 3.0
    assert result.rms_after < 0.1
    on = which >= 0
    assert np.max(np.abs(result.values[on] - field(north, east)[on])) < 0.3
    assert np.all(result.values[~on] == value[~on])
    report = result.as_dict()
    json.dumps(report)
    assert report["corrections"][0]["name"] == "L0" and report["unlevelled"] == []
    after = np.array([c[-1] for c in result.crossovers_after])
    assert after == pytest.approx(result.residuals)
    assert [c[-1] for c in result.crossovers_before] == [c.difference for c in found]
    assert all(c.value_line - c.value_tie == pytest.approx(c.difference)
               for c in result.crossovers_after)


def test_order_1_recovers_drifts():
    # a speed that varies along the lines: without the no-trend gauge the ties' tilt along
    # the lines and the lines' slopes are nearly one unknown (ill-conditioned)
    t, north, east, lines = grid_survey(tie_north=(60.0, 120.0, 180.0, 240.0), surge=0.5)
    rng = np.random.default_rng(4)
    offsets = rng.normal(0, 5, len(lines))
    slopes = rng.normal(0, 0.1, len(lines))          # nT/s: ±3 nT over a 30 s line
    ties = np.array([k for k, line in enumerate(lines) if line.kind == "tie"])
    slopes[ties] = 0.0
    # tie offsets with mean zero and no trend along the lines (what levelling cannot see)
    along = np.array([60.0, 120.0, 180.0, 240.0])
    tie_offsets = offsets[ties] - offsets[ties].mean()
    a = along - along.mean()
    offsets[ties] = tie_offsets - a * (tie_offsets @ a) / (a @ a)
    value, which = with_errors(t, north, east, lines, offsets, slopes, noise=0.05)
    found = crossovers(lines, t, north, east, value)
    flat = level(lines, t, value, found, order=0)
    result = level(lines, t, value, found, order=1)
    assert result.slopes == pytest.approx(slopes, abs=0.01)
    assert result.offsets == pytest.approx(offsets, abs=0.1)
    assert result.rms_after < 0.1 < flat.rms_after
    on = which >= 0
    assert np.max(np.abs(result.values[on] - field(north, east)[on])) < 0.5


def test_a_line_without_crossovers_is_left_alone():
    t, north, east, lines = grid_survey()
    # a ninth line east of the ties' reach
    t9 = t[-1] + 20 + np.arange(0, 301) / RATE
    lines = lines + [Line("line", 8, t9[0], t9[-1], 0.0)]
    t = np.concatenate([t, t9])
    north = np.concatenate([north, np.linspace(0, LENGTH, 301)])
    east = np.concatenate([east, np.full(301, 400.0)])
    value, _ = with_errors(t, north, east, lines, np.ones(len(lines)))
    result = level(lines, t, value, crossovers(lines, t, north, east, value))
    assert result.unlevelled == [len(lines) - 1]
    assert result.offsets[-1] == 0.0
    assert result.as_dict()["unlevelled"] == ["L8"]


def test_levelling_errors():
    t, north, east, lines = grid_survey()
    value, _ = with_errors(t, north, east, lines, np.zeros(len(lines)))
    with pytest.raises(SurveyError, match="no crossover of a tie line"):
        level(lines, t, value, [])
    found = crossovers(lines, t, north, east, value)
    with pytest.raises(SurveyError, match="order must be 0 or 1, not 2"):
        level(lines, t, value, found, order=2)
    with pytest.raises(SurveyError, match="differ in length"):
        crossovers(lines, t, north, east, value[:-1])


def test_found_lines_levelled_end_to_end():
    # the lines as find_lines sees them (hovers between constant-speed moves), then levelled
    t, north, east, flown = grid_survey()
    hover_t = np.arange(0, t[-1], 1 / RATE)
    n = np.interp(hover_t, t, north)
    e = np.interp(hover_t, t, east)
    lines = find_lines(hover_t, n, e, min_length_m=100.0)
    assert [line.kind for line in lines] == [line.kind for line in flown]
    offsets = np.random.default_rng(5).normal(0, 4, len(lines))
    value, which = with_errors(hover_t, n, e, lines, offsets, noise=0.05)
    result = level(lines, hover_t, value, crossovers(lines, hover_t, n, e, value))
    assert result.rms_after < 0.1 < 2.0 < result.rms_before
    on = which >= 0
    level_error = result.values[on] - field(n, e)[on]
    tie_mean = np.mean([offsets[k] for k, line in enumerate(lines) if line.kind == "tie"])
    assert np.max(np.abs(level_error - tie_mean)) < 0.3
