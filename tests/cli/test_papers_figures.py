"""The papers' figures (cli/papers.py) are readable (tests/support/figures.py's rules):
plain numbers on their log axes, units on every axis, paper A's compensated trace visible
beside the reference, time from the log's first sample."""

import pytest

import figures
from maglog.calib import plotting
from maglog.cli.papers import paper_results


@pytest.fixture(scope="module")
def drawn(flown, tmp_path_factory):
    _, _, _, truth, run, _ = flown
    with pytest.MonkeyPatch.context() as patch:
        recorder = figures.Recorder(plotting.save)
        patch.setattr(plotting, "save", recorder)
        paper_results(run, truth, tmp_path_factory.mktemp("papers"), seed=3, quick=True)
    yield recorder.figures, run
    plotting.pyplot().close("all")


def test_every_figure_is_readable(drawn):
    found, _ = drawn
    assert set(found) == {"paper_a_figure7", "paper_b_heading", "paper_c_allan"}
    for name, fig in found.items():
        assert figures.problems(fig, name) == []


def test_paper_a_time_axis_and_traces(drawn):
    found, run = drawn
    ax = found["paper_a_figure7"].axes[0]
    assert ax.get_xlabel() == (f"seconds from {plotting.clock_of_day(run.t[0])} UTC "
                               "(the first sample)")
    lines = {line.get_label(): line for line in ax.get_lines()}
    assert lines["compensated |B|"].get_xdata()[0] == 0.0
    assert lines["reference (cesium)"].get_zorder() > lines["compensated |B|"].get_zorder()


def test_log_axes_in_plain_numbers(drawn):
    found, _ = drawn
    for name in ("paper_b_heading", "paper_c_allan"):
        ax = found[name].axes[0]
        shown = [t.get_text() for t in ax.get_xticklabels() + ax.get_yticklabels()
                 if t.get_text()]
        assert shown and all(text.replace(".", "").isdigit() for text in shown), shown
    assert "units" in found["paper_c_allan"].axes[0].get_ylabel()
