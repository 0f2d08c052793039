"""Screening of reference readings and magnetometer samples before a calibration: nothing
rejected on clean flights, each fault caught under its reason, the result's shape, edge
cases and bad input."""

import dataclasses
import json
import re

import numpy as np
import pytest

from maglog.calib.logparse import parse_log
from maglog.calib.screen import (EARTH_RANGE_NT, REFERENCE_REASONS, SAMPLE_REASONS,
                                 SPIKE_FLOOR_NT, ScreenResult, screen_reference,
                                 screen_samples)
from maglog.sim.stimulus import errors
from maglog.sim.stimulus.scenario import DEFAULT_ERRORS, make_flight

CESIUM_RATE = 10.0        # readings per second, as Flight.log writes them
CESIUM_NOISE = 0.05       # nT


def error_model(name):
    if name == "paper_a":
        return errors.preset("paper_a")
    return dataclasses.replace(DEFAULT_ERRORS, noise=float(name))


def cesium(flight, seed=0, noise=CESIUM_NOISE):
    """The cesium readings Flight.log would write: the total field at 10 Hz plus noise."""
    t = np.arange(0, flight.t[-1], 1 / CESIUM_RATE)
    rng = np.random.default_rng(seed)
    return t, np.interp(t, flight.t, flight.total) + rng.normal(scale=noise, size=t.size)


def steady(seconds=90.0, value=48395.014, noise=CESIUM_NOISE, seed=0):
    """A 90-s cesium log at one place: readings around ``value``."""
    t = np.arange(0, seconds, 1 / CESIUM_RATE)
    rng = np.random.default_rng(seed)
    return t, value + rng.normal(scale=noise, size=t.size)


def survey_field(n=6000, noise=10.0, seed=0):
    """A survey line's total field at 10 Hz: a regional trend, anomalies of a few hundred
    nT over tens to hundreds of readings, and noise."""
    rng = np.random.default_rng(seed)
    t = np.arange(n) / CESIUM_RATE
    s = t * 60.0                                # metres along the line at 60 m/s
    field = (48_000.0 + 0.02 * s + 400 * np.exp(-((s - 9_000) / 300) ** 2)
             - 250 * np.exp(-((s - 20_000) / 120) ** 2)
             + 150 * np.sin(2 * np.pi * s / 2_500))
    return t, field + rng.normal(scale=noise, size=n)


# --- no false alarms on clean data -----------------------------------------------------

@pytest.mark.parametrize("coverage", ["full", "uav", "planar"])
@pytest.mark.parametrize("model", ["5", "20", "100", "paper_a"])
def test_clean_flights_lose_nothing(coverage, model):
    flight = make_flight(coverage=coverage, seconds=40.0, errors=error_model(model), seed=7)
    t_ces, field = cesium(flight)
    reference = screen_reference(t_ces, field)
    assert reference.n_rejected == 0, reference.summary()
    r = np.interp(flight.t, t_ces, field)
    for screened in (screen_samples(flight.t, flight.b_meas, r),
                     screen_samples(flight.t, flight.b_meas)):
        assert screened.n_rejected == 0, screened.summary()
        assert screened.keep.all() and screened.untested == 0


@pytest.mark.parametrize("seed", range(3))
def test_survey_fields_and_noisy_references_lose_nothing(seed):
    """Anomalies of hundreds of nT over many readings, with 10 nT of noise (200 times a
    cesium's), are not spikes."""
    t, field = survey_field(seed=seed)
    assert screen_reference(t, field).n_rejected == 0


def test_a_day_of_noisy_reference_loses_nothing():
    """A million readings (28 h at 10 Hz) with 10 nT of noise: 50 nT is 4.5 standard
    deviations of a reading's deviation from its neighbours' median, passed a few times;
    the limit's series-wide term (about 5 x 11 nT) keeps them."""
    rng = np.random.default_rng(0)
    field = 48_000.0 + rng.normal(scale=10.0, size=1_000_000)
    out = screen_reference(np.arange(field.size) / CESIUM_RATE, field)
    assert out.n_rejected == 0, out.summary()


def test_steps_and_wide_peaks_are_kept():
    """A step (the field after a turn, a payload switched on) and a 1000-nT peak 3
    readings wide at half height are no isolated spikes."""
    t, field = steady(30.0, value=48_000.0)
    field[150:] += 300.0
    j = np.arange(t.size) - 80
    field += 1000 * np.exp(-j ** 2 / (2 * (3 / 2.355) ** 2))
    assert screen_reference(t, field).n_rejected == 0


# --- faults caught, each under its reason ----------------------------------------------

def test_leading_digit_bit_flip_is_outside_the_earths_range():
    """``$ 48395.014`` read as ``$ 08395.014`` in a 90-s log."""
    t, field = steady()
    field[417] = 8395.014
    out = screen_reference(t, field)
    assert out.rejected_indices.tolist() == [417]
    assert out.counts == {"nonfinite": 0, "earth_range": 1, "spike": 0}
    example = out.examples["earth_range"][0]
    assert (example.index, example.value) == (417, 8395.014)
    assert "8,395.014 nT is outside the Earth's 20,000..75,000 nT" in example.why


def test_tens_digit_bit_flip_is_a_spike_and_units_digit_is_not():
    """48395 read as 48315 (an 80-nT spike) is caught; 48391 (4 nT) is below what any test
    can tell from noise and is left to the fit's robust loss."""
    t, field = steady(noise=0.0)
    field[300] = 48315.014
    field[600] = 48391.014
    out = screen_reference(t, field + np.random.default_rng(3).normal(scale=CESIUM_NOISE,
                                                                      size=t.size))
    assert out.rejected_indices.tolist() == [300]
    assert out.counts["spike"] == 1
    example = out.examples["spike"][0]
    assert example.index == 300 and example.value == pytest.approx(48315.014, abs=0.3)
    assert re.search(r"nT is -(79\.[89]|80\.[01]) nT off the median of its neighbours "
                     rf"\(48,39[45]\.\d+ nT\); limit {SPIKE_FLOOR_NT:,.1f} nT", example.why)


def test_spikes_on_a_survey_field_and_in_pairs_are_caught():
    t, field = survey_field(noise=1.0)
    bad = [1000, 1001, 2500, 4000]              # a pair, then two alone
    field[bad] += [900.0, -700.0, 120.0, -5000.0]
    out = screen_reference(t, field)
    assert out.rejected_indices.tolist() == bad
    assert out.counts["spike"] == 4


def test_the_tens_digit_flip_is_caught_under_10_nT_of_noise_most_of_the_time():
    caught = 0
    for seed in range(20):
        t, field = steady(noise=10.0, seed=seed)
        field[450] -= 80.0
        out = screen_reference(t, field)
        assert set(out.rejected_indices.tolist()) <= {450}
        caught += out.n_rejected
    assert caught >= 16                         # 89 % over 2,000 seeds


def flip_bit(line, column, bit):
    """``line`` with one bit of the character at ``column`` flipped."""
    return line[:column] + bytes([line[column] ^ (1 << bit)]) + line[column + 1:]


def test_bit_flips_in_a_real_log():
    """A 90-s log as the logger writes it (the cesium line has no checksum), parsed: one bit
    flipped in the leading digit of reading 417 (``$ 48395.0xx`` -> ``$ 08395.0xx``), in
    the tens digit of reading 300 (-> ``48315``) and in the units digit of reading 600
    (-> ``48391``)."""
    flight = make_flight(coverage="uav", seconds=90.0, seed=3)
    lines = flight.log(seed=0).split(b"\r\n")
    readings = [i for i, line in enumerate(lines) if line.startswith(b"$ ")]
    assert len(readings) == 900
    exact = [k for k, i in enumerate(readings) if lines[i].startswith(b"$ 48395.")]
    near = {target: min(exact, key=lambda k: abs(k - target)) for target in (300, 417, 600)}
    assert near[417] == 417
    for target, column, bit, text in ((417, 2, 2, b"$ 08395."), (300, 5, 3, b"$ 48315."),
                                      (600, 6, 2, b"$ 48391.")):
        i = readings[near[target]]
        lines[i] = flip_bit(lines[i], column, bit)
        assert lines[i].startswith(text)
    cesium = parse_log(b"\r\n".join(lines)).cesium
    assert np.all(np.diff(cesium.t) > 0)
    out = screen_reference(cesium.t, cesium.field)
    assert out.rejected_indices.tolist() == [near[300], 417]
    assert out.counts == {"nonfinite": 0, "earth_range": 1, "spike": 1}
    assert out.examples["earth_range"][0].value == pytest.approx(8395.0, abs=0.1)
    assert out.examples["spike"][0].value == pytest.approx(48315.0, abs=0.1)


def test_non_numbers_in_the_reference_are_counted():
    t, field = steady(10.0)
    field[[5, 50]] = [np.nan, np.inf]
    out = screen_reference(t, field)
    assert out.rejected_indices.tolist() == [5, 50] and out.counts["nonfinite"] == 2
    assert "nan is not a number" in out.examples["nonfinite"][0].why


def axis_near(flight, value=40_000.0, start=100):
    """A sample (from ``start`` on) with an axis reading about ``value`` nT in magnitude,
    and that axis."""
    near = np.abs(np.abs(flight.b_meas[start:]) - value)
    i, axis = np.unravel_index(np.argmin(near), near.shape)
    return start + int(i), int(axis)


@pytest.mark.parametrize("coverage", ["full", "uav", "planar"])
def test_a_zeroed_axis_is_a_jump_at_any_attitude(coverage):
    """One sample with a valid checksum but an axis read as 0 where it held 40,000 nT."""
    flight = make_flight(coverage=coverage, seconds=20.0, errors=error_model("20"), seed=2)
    b = flight.b_meas.copy()
    i, axis = axis_near(flight)
    assert 38_000 < abs(b[i, axis]) < 43_000        # |b| drops to about 0.55 of 48,000
    b[i, axis] = 0.0
    out = screen_samples(flight.t, b, flight.total)
    assert out.rejected_indices.tolist() == [i]
    assert out.counts == {"nonfinite": 0, "scale": 0, "jump": 1}
    assert out.examples["jump"][0].index == i
    assert "off the median of its neighbours" in out.examples["jump"][0].why


def test_samples_no_calibration_can_map_are_off_scale():
    flight = make_flight(coverage="full", seconds=20.0, errors=error_model("5"), seed=4)
    b = flight.b_meas.copy()
    b[10] = 0.0                                 # a sensor reset: 0, 0, 0
    b[20, 0] = 99_999.9                         # a saturated axis (five digits)
    b[30, 2] = np.nan
    r = flight.total.copy()
    r[40] = 8_395.0                             # the reference at this sample is a flip
    r[50] = np.nan                              # no reference here: the median stands in
    for with_r in (True, False):
        out = screen_samples(flight.t, b, r if with_r else None)
        expect = [10, 20, 30, 40] if with_r else [10, 20, 30]
        assert out.rejected_indices.tolist() == expect
        assert out.counts == {"nonfinite": 1, "scale": len(expect) - 1, "jump": 0}
    assert [ex.index for ex in out.examples["scale"]] == [10, 20]
    assert "0 times the expected" in out.examples["scale"][0].why


def test_one_percent_of_gross_errors_are_all_caught():
    """Zeroed axes where they held more than 40,000 nT, sensor resets and saturated axes on
    1 % of the samples: every one caught, nothing else."""
    flight = make_flight(coverage="uav", seconds=60.0, errors=error_model("paper_a"), seed=5)
    rng = np.random.default_rng(11)
    b = flight.b_meas.copy()
    big = np.abs(b) > 40_000.0
    bad = np.sort(rng.choice(np.flatnonzero(big.any(axis=1)), size=len(b) // 100,
                             replace=False))
    kind = np.arange(bad.size) % 3
    for i, what in zip(bad, kind):
        if what == 0:
            b[i, np.argmax(np.abs(b[i]))] = 0.0
        elif what == 1:
            b[i] = 0.0
        else:
            b[i, rng.integers(0, 3)] = -99_999.9
    out = screen_samples(flight.t, b, flight.total)
    assert out.rejected_indices.tolist() == bad.tolist()
    # A zeroed axis that held more than 87 % of the field leaves |b| under half: off scale.
    assert out.counts["scale"] >= np.count_nonzero(kind > 0)
    assert out.counts["scale"] + out.counts["jump"] == bad.size


# --- the result --------------------------------------------------------------------------

def test_result_counts_examples_summary_and_json():
    t, field = steady()
    field[[10, 20, 30, 40]] = [8395.014, 8395.015, 8395.016, 8395.017]
    field[100] += 500.0
    field[200] = np.nan
    out = screen_reference(t, field)
    assert isinstance(out, ScreenResult) and out.keep.dtype == bool
    assert list(out.counts) == list(REFERENCE_REASONS)
    assert out.counts == {"nonfinite": 1, "earth_range": 4, "spike": 1}
    assert sum(out.counts.values()) == out.n_rejected == 6 and out.n_kept == 894
    assert [ex.index for ex in out.examples["earth_range"]] == [10, 20, 30]   # three kept
    assert out.summary() == (
        "reference readings: 6 of 900 rejected (nonfinite 1, earth_range 4, spike 1); "
        "e.g. #10: 8,395.014 nT is outside the Earth's 20,000..75,000 nT")
    data = json.loads(json.dumps(out.as_dict(), allow_nan=False))
    assert data["counts"] == out.counts and data["rejected"] == 6
    assert data["examples"]["spike"][0]["index"] == 100
    assert data["examples"]["nonfinite"][0] == {"index": 200, "value": None,
                                                "why": "nan is not a number"}
    assert data["limits"]["earth_range_nT"] == list(EARTH_RANGE_NT)
    assert data["limits"]["max_gap_s"] == pytest.approx(0.5)
    assert screen_reference([0.0], [48e3]).as_dict()["limits"]["max_gap_s"] is None
    clean = screen_samples(np.arange(10.0), np.tile([30e3, 20e3, 30e3], (10, 1)))
    assert list(clean.counts) == list(SAMPLE_REASONS)
    assert clean.summary() == "magnetometer samples: 0 of 10 rejected"


# --- edge cases ----------------------------------------------------------------------------

def test_shorter_than_the_window():
    t = np.arange(5.0)
    out = screen_reference(t, [48_000.0, 48_000.1, 49_000.0, 47_999.9, 48_000.0])
    assert out.rejected_indices.tolist() == [2]
    few = screen_reference(t[:3], [48_000.0, 49_000.0, 48_000.0])
    assert few.n_rejected == 0 and few.untested == 3
    assert "3 too isolated to test" in few.summary()
    one = screen_samples([0.0], [[3e4, 2e4, 3e4]])
    assert one.n_rejected == 0 and one.untested == 1


def test_empty_input():
    out = screen_reference([], [])
    assert out.n == 0 and out.n_rejected == 0 and out.summary().startswith(
        "reference readings: 0 of 0")
    assert screen_samples(np.zeros(0), np.zeros((0, 3))).n == 0


def test_all_readings_bad():
    t = np.arange(50.0)
    out = screen_reference(t, np.full(50, 8395.014))
    assert not out.keep.any() and out.counts["earth_range"] == 50
    zeros = screen_samples(t, np.zeros((50, 3)), np.full(50, 48_000.0))
    assert not zeros.keep.any() and zeros.counts["scale"] == 50
    nans = screen_samples(t, np.full((50, 3), np.nan))
    assert not nans.keep.any() and nans.counts["nonfinite"] == 50


def test_neighbours_across_a_gap_are_not_compared():
    """After a dropout the aircraft may be elsewhere: readings 2 s apart at 10 Hz do not
    judge each other, and a 2-reading segment between gaps cannot be judged."""
    t = np.concatenate([np.arange(0, 1, 0.1), [3.0, 3.1], np.arange(6, 7, 0.1)])
    field = np.concatenate([np.full(10, 48_000.0), [48_600.0, 48_600.0],
                            np.full(10, 48_000.0)])
    out = screen_reference(t, field)
    assert out.n_rejected == 0 and out.untested == 2
    joined = screen_reference(t, field, max_gap=10.0)
    assert joined.rejected_indices.tolist() == [10, 11]


def test_a_step_back_in_time_ends_the_neighbourhood():
    """A sensor restart: the sequence-number times start again, and the two readings after
    it cannot be judged by those before (in time order they would be spikes)."""
    field = np.concatenate([np.full(10, 48_000.0), [49_000.0, 49_000.0]])
    forward = np.arange(12) / CESIUM_RATE
    restarted = np.concatenate([forward[:10], forward[:2]])
    assert screen_reference(forward, field).rejected_indices.tolist() == [10, 11]
    out = screen_reference(restarted, field)
    assert out.n_rejected == 0 and out.untested == 2
    samples = np.tile([30_000.0, 20_000.0, 30_000.0], (12, 1))
    samples[10:] *= 0.6
    assert screen_samples(forward, samples).rejected_indices.tolist() == [10, 11]
    assert screen_samples(restarted, samples).n_rejected == 0


def test_settings_change_what_is_caught():
    t, field = steady(noise=0.0)
    field[300] = 48_315.014
    assert screen_reference(t, field, floor_nt=100.0).n_rejected == 0
    assert screen_reference(t, field, earth_range=(50_000, 60_000)).counts["earth_range"] == 900
    flight = make_flight(coverage="uav", seconds=10.0, seed=1)
    b = flight.b_meas.copy()
    b[50] *= 0.85
    assert screen_samples(flight.t, b).n_rejected == 0
    assert screen_samples(flight.t, b, jump_fraction=0.1).rejected_indices.tolist() == [50]
    assert screen_samples(flight.t, b, scale_range=(0.9, 1.1)).counts["scale"] == 1


# --- bad input -----------------------------------------------------------------------------

@pytest.mark.parametrize("call,message", [
    (lambda: screen_reference([0.0, np.nan, 2.0], [1.0, 2.0, 3.0]),
     r"Times must be finite, not NaN or infinite \(1 of 3\); without times, pass the "
     r"readings' line numbers"),
    (lambda: screen_reference(np.zeros((2, 2)), [1.0]), r"Times must be a 1-D array"),
    (lambda: screen_reference([0.0, 1.0], [1.0]),
     r"Reference field must be a 1-D array of 2 values \(one per time\), not shape \(1,\)"),
    (lambda: screen_samples([0.0, 1.0], np.zeros((2, 2))),
     r"Samples must be an \(N, 3\) array with N = 2 \(the times\), not shape \(2, 2\)"),
    (lambda: screen_samples([0.0, 1.0], np.zeros((2, 3)), [1.0]),
     r"Reference must be a 1-D array of 2 values"),
    (lambda: screen_reference([0.0], [1.0], earth_range=(7e4, 2e4)),
     r"Earth range must be a pair 0 < low < high, not \(70000.0, 20000.0\)"),
    (lambda: screen_reference([0.0], [1.0], earth_range=5), r"Earth range must be a pair"),
    (lambda: screen_reference([0.0], [1.0], floor_nt=-1), r"Spike floor must be a number >= 0"),
    (lambda: screen_reference([0.0], [1.0], k=0), r"robust standard deviations k must be a "
                                                  r"positive number, not 0"),
    (lambda: screen_reference([0.0], [1.0], half_window=2.5),
     r"Half window must be an integer >= 1 \(readings on each side\), not 2.5"),
    (lambda: screen_reference([0.0], [1.0], max_gap=0), r"max_gap must be a positive number"),
    (lambda: screen_samples([0.0], np.ones((1, 3)), scale_range=(1.2, 2)),
     r"Scale range must contain 1, not \(1.2, 2\)"),
    (lambda: screen_samples([0.0], np.ones((1, 3)), jump_fraction=True),
     r"Jump fraction must be a positive number, not True"),
])
def test_bad_input_says_what(call, message):
    with pytest.raises(ValueError, match=message):
        call()
