"""The report figures (calib/plotting.py and the plots of calib/pipeline.py and
calib/survey.py) are readable: labels with units, nothing clipped, plain tick labels,
traces that lie on each other both visible, legs shaded where the text says so
(tests/support/figures.py holds the rules). The survey report's grid and CRS sentences
read as text."""

import re
from types import SimpleNamespace

import numpy as np
import pytest

import figures
from maglog.calib import plotting
from maglog.calib import survey as sv
from maglog.calib.pipeline import calibrate_card, write_report
from maglog.sim.stimulus.scenario import ErrorModel, make_flight, make_survey


@pytest.fixture
def recorder(monkeypatch):
    recorder = figures.Recorder(plotting.save)
    monkeypatch.setattr(plotting, "save", recorder)
    yield recorder
    plotting.pyplot().close("all")


# -- the helpers ----------------------------------------------------------------------------

@pytest.mark.parametrize("value, text", [(2.0, "2"), (30.0, "30"), (0.1, "0.1"),
                                         (0.002, "0.002"), (1000.0, "1000"), (0.5, "0.5"),
                                         (0.0, "0")])
def test_plain_number(value, text):
    assert plotting.plain_number(value) == text


def test_a_log_axis_reads_in_plain_numbers():
    plt, fig, ax = plotting.figure()
    ax.loglog([2, 5, 12, 30], [0.011, 0.005, 0.003, 0.0017])
    ax.set_xlabel("samples per octant")
    ax.set_ylabel("error (deg)")
    fig.draw_without_rendering()
    # matplotlib's own labels on a short log axis: 2×10⁰ ... 3×10¹ (mathtext).
    assert any("$" in t.get_text() for t in ax.get_xticklabels(minor=True))
    assert figures.problems(fig)
    plotting.plain_log_axis(ax)
    assert figures.problems(fig) == []
    shown = [t.get_text() for t in ax.get_xticklabels() if t.get_text()]
    assert "2" in shown and "10" in shown and "20" in shown
    plt.close(fig)


def test_the_layout_makes_room_for_long_labels():
    def draw(fixed_margins):
        if fixed_margins:           # what the reports did before: margins set by hand
            plt = plotting.pyplot()
            fig, ax = plt.subplots(figsize=plotting.NARROW)
            fig.subplots_adjust(left=0.9 / 7, bottom=0.6 / 4)
        else:
            plt, fig, ax = plotting.figure()
        ax.plot([0, 1], [0, 40000])
        ax.set_xlabel("seconds from 10:00:04 UTC (the first sample)\nsecond line")
        ax.set_ylabel("band-passed\ntotal field (nT)")
        found = figures.problems(fig)
        plt.close(fig)
        return found

    assert draw(False) == []
    assert draw(True) == ["figure panel 0: reaches past the figure's edge (clipped)"]


def test_time_axis_from_the_first_sample():
    x, label = plotting.log_time_axis(np.array([36004.5, 36005.0, 36010.5]))
    assert x.tolist() == [0.0, 0.5, 6.0]
    assert label == "seconds from 10:00:04 UTC (the first sample)"
    x, label = plotting.log_time_axis(np.array([1.0, 2.0]), timed=False)
    assert x.tolist() == [1.0, 2.0] and "no GPS time" in label


# -- the calibration report's figures -------------------------------------------------------

@pytest.fixture(scope="module")
def survey_run(tmp_path_factory):
    """A calibration with straight, level legs (a survey flight) and its attitude; the
    sensor turned in the airframe so that the alignment's offset is a hundredth of a
    degree: the headings before and after it lie on each other."""
    folder = tmp_path_factory.mktemp("legs")
    flight = make_survey(errors=ErrorModel(mounting=(0.0, 0.0, 2.2)), seed=6)
    (folder / "LOG00002.TXT").write_bytes(flight.log())
    (folder / "attitude.csv").write_bytes(flight.attitude_csv())
    return calibrate_card(folder / "LOG00002.TXT", attitude=folder / "attitude.csv")


@pytest.fixture(scope="module")
def tumble_run(tmp_path_factory):
    """A calibration flight without a straight leg, with its attitude."""
    folder = tmp_path_factory.mktemp("nolegs")
    flight = make_flight(coverage="uav", seconds=40, seed=2)
    (folder / "LOG00001.TXT").write_bytes(flight.log())
    (folder / "attitude.csv").write_bytes(flight.attitude_csv())
    return calibrate_card(folder / "LOG00001.TXT", attitude=folder / "attitude.csv")


@pytest.fixture(scope="module")
def drawn(survey_run, tumble_run, tmp_path_factory):
    """The report figures of each run, kept open: name of the run -> name -> Figure."""
    out, save = {}, plotting.save
    with pytest.MonkeyPatch.context() as patch:
        for name, run in (("survey_run", survey_run), ("tumble_run", tumble_run)):
            recorder = figures.Recorder(save)
            patch.setattr(plotting, "save", recorder)
            folder = tmp_path_factory.mktemp(name)
            write_report(run, folder)
            assert (folder / "figure7.png").stat().st_size > 0
            out[name] = recorder.figures
    yield out
    plotting.pyplot().close("all")


@pytest.mark.parametrize("which", ["survey_run", "tumble_run"])
def test_report_figures_are_readable(which, drawn):
    assert set(drawn[which]) == {"figure7", "coverage", "residuals", "allan",
                                 "heading_error"}
    for name, fig in drawn[which].items():
        assert figures.problems(fig, name) == []


def test_figure7_shows_the_compensated_trace_and_says_its_clock(survey_run, drawn):
    fig = drawn["survey_run"]["figure7"]
    top, low = fig.axes
    first = plotting.clock_of_day(survey_run.t[0])
    assert low.get_xlabel() == f"seconds from {first} UTC (the first sample)"
    lines = {line.get_label(): line for line in top.get_lines()}
    compensated = lines["compensated |B|"]
    assert compensated.get_xdata()[0] == 0.0
    reference = next(line for label, line in lines.items() if label.startswith("reference"))
    # The reference on top, dashed; the compensated trace below it wider.
    assert reference.get_zorder() > compensated.get_zorder()
    assert reference.get_linestyle() == "--"
    # The difference panel: compensated - reference, on its own scale.
    assert np.allclose(low.get_lines()[0].get_ydata(), survey_run.residual)


def test_legs_are_shaded_when_there_are_legs(survey_run, tumble_run, drawn):
    assert survey_run.heading.legs and not tumble_run.heading.legs
    assert abs(survey_run.heading.alignment.offset) < 0.05
    ax = drawn["survey_run"]["heading_error"].axes[0]
    assert len(ax.patches) == len(survey_run.heading.legs)
    assert "straight, level legs" in [t.get_text() for t in ax.get_legend().get_texts()]
    fig = drawn["tumble_run"]["heading_error"]
    assert not fig.axes[0].patches
    assert "no straight, level leg found" in fig._suptitle.get_text()


# -- the survey's figures -------------------------------------------------------------------

def _survey_result(seed=1, deinterf=True, crossovers=24):
    """What the survey's plots read of a result: a 90 s box at 10 Hz whose raw signal
    swings by nT, compensated to a few hundredths, deinterf's a few thousandths away."""
    rng = np.random.default_rng(seed)
    t = 36000.0 + np.arange(0, 120, 0.1)
    raw = 2.0 * np.sin(2 * np.pi * 0.3 * t) + rng.normal(0, 0.3, t.size)
    ours = rng.normal(0, 0.03, t.size)
    theirs = ours + rng.normal(0, 0.005, t.size)
    before = [(k, k, rng.normal(0, 0.07)) for k in range(crossovers)]
    after = [(k, k, rng.normal(0, 0.05)) for k in range(crossovers)]
    levelling = SimpleNamespace(
        crossovers_before=before, crossovers_after=after,
        as_dict=lambda: {"crossovers": crossovers, "rms_before_nT": 0.07,
                         "rms_after_nT": 0.05})
    return SimpleNamespace(t=t, box=(36010.0, 36100.0), raw=raw, compensated=ours,
                           deinterf={"compensated": theirs} if deinterf else None,
                           timing=SimpleNamespace(rate_hz=10.0),
                           tl=SimpleNamespace(band=(0.12, 1.5), terms=18),
                           levelling=levelling)


@pytest.mark.parametrize("deinterf", [True, False])
def test_survey_figures_are_readable(deinterf, recorder, tmp_path):
    result = _survey_result(deinterf=deinterf)
    sv._plot_compensation(result, tmp_path / "compensation.png")
    sv._plot_levelling(result, tmp_path / "levelling.png")
    for name in ("compensation", "levelling"):
        assert figures.problems(recorder.figures[name], name) == []
    labels = [line.get_label() for ax in recorder.figures["compensation"].axes
              for line in ax.get_lines()]
    assert any(label.startswith("deinterf") for label in labels) == deinterf


def test_deinterf_drawn_beside_ours_on_a_zoomed_panel(recorder, tmp_path):
    sv._plot_compensation(_survey_result(), tmp_path / "compensation.png")
    top, low = recorder.figures["compensation"].axes
    ours, theirs = low.get_lines()
    assert ours.get_label().startswith("maglog") and theirs.get_label().startswith("deinterf")
    # Zoomed on the compensated traces: their range fills the panel, not the raw one's.
    assert np.ptp(low.get_ylim()) < 0.5 * np.ptp(top.get_ylim())
    assert "nT RMS" in theirs.get_label()


def test_levelling_with_no_crossover(recorder, tmp_path):
    sv._plot_levelling(_survey_result(crossovers=0), tmp_path / "levelling.png")
    fig = recorder.figures["levelling"]
    assert figures.problems(fig, "levelling") == []
    assert fig.axes[0].get_title() == "No crossovers: not levelled"


# -- the survey report's text ---------------------------------------------------------------

GRID = {"method": "spline", "spacing_m": 10.0, "shape": (26, 23), "damping": None,
        "misfit_rms_nT": 0.3115408304157012, "line_spacing_m": 30.002382311271063,
        "block_m": 10.000794103757022, "mask_m": 30.002382311271063, "n_data": 3263,
        "n_blocks": 245, "coverage": 1.0, "crs": "local"}


def _unreadable(line):
    """What a printed line must not hold: a dict's braces, Python's None, an exponent, a
    float printed to all its digits."""
    return re.findall(r"[{}]|\bNone\b|\de[+-]\d|\d\.\d{6,}", line)


def test_grid_sentences_read_as_text():
    lines = sv._grid_lines(GRID, (47.3769, 8.5417))
    text = "\n".join(lines)
    assert [_unreadable(line) for line in lines] == [[]] * len(lines)
    assert "undamped" in text and "10 m spacing (26 × 23 nodes)" in text
    assert "misfit 0.31 nT RMS" in text and "lines 30 m apart" in text
    assert "local metres north and east of the first fix (47.37690° N, 8.54170° E)" in text
    assert "WGS 84 / UTM zone 32N (EPSG:32632)" in text
    damped = "\n".join(sv._grid_lines({**GRID, "damping": 1e-3, "method": "eqs",
                                       "eqs_depth_m": 45.0}, (-33.9, 18.4)))
    assert "damping 0.001" in damped and "equivalent sources at 45 m depth" in damped
    assert "UTM zone 34S (EPSG:32734)" in damped


@pytest.mark.parametrize("key, value, text", [
    ("band_hz", [0.1, 0.6], "band 0.1-0.6 Hz"),
    ("sampling_rate_hz", 10, "sampling rate 10 Hz"),
    ("terms", 18, "terms 18"),
    ("filter", "butter(4) filtfilt", "filter butter(4) filtfilt"),
    ("box_samples", 908, "box samples 908"),
])
def test_settings_read_as_text(key, value, text):
    assert sv._setting_text(key, value) == text
