"""What a report figure must be to be read (the figure tests of calib and cli use it):
``problems(fig)`` lists what is wrong with a drawn matplotlib figure, ``Recorder`` keeps
the figures that calib.plotting.save writes.

A figure has no problem when
- every panel's axes have labels (a panel sharing its x axis with the one below, its tick
  labels hidden, needs none), each with a unit ("(nT)", "(deg)", "(s)", seconds ...) or a
  count ("samples per ...", "... number");
- nothing reaches past the figure's edge (the panels' tight boxes, titles and labels);
- tick labels are plain numbers (no mathtext powers such as 2×10⁰);
- two traces that lie on each other (same x, RMS apart under 2 % of the panel's height)
  both show: different colours, and the one drawn on top is dashed or dotted, or thinner
  than three quarters of the one below;
- a panel with labelled traces has a legend;
- a figure that says something is shaded shades something.
"""

import re

import numpy as np

__all__ = ["problems", "Recorder", "UNIT", "COUNT"]

#: A unit in a label: in parentheses (the last word inside), or seconds spelt out.
UNIT = re.compile(r"\((?:[^()]*[\s,;])?(nT|deg|°|s|Hz|m|%|paper C's units[^()]*)\)"
                  r"|\bseconds\b")
#: A count or an index: no unit needed.
COUNT = re.compile(r"\bsamples? per\b|\bnumber\b|\bsample \(in arrival order")


def _labelled(label):
    return bool(UNIT.search(label) or COUNT.search(label))


def _ticks_shown(labels):
    return any(t.get_visible() and t.get_text() for t in labels)


def _inside(box, outer, slack=1.0):
    return (box.x0 >= outer.x0 - slack and box.y0 >= outer.y0 - slack
            and box.x1 <= outer.x1 + slack and box.y1 <= outer.y1 + slack)


def _hidden_traces(ax):
    """Pairs of traces on each other where the upper one hides the lower."""
    # Traces drawn as lines (not the error bars' caps, nor markers alone).
    lines = [line for line in ax.get_lines() if len(line.get_xdata()) > 2
             and line.get_linestyle() not in ("None", "none", "")
             and not str(line.get_label()).startswith("_")]
    order = sorted(range(len(lines)), key=lambda i: (lines[i].get_zorder(), i))
    low, high = ax.get_ylim()
    height = abs(high - low) or 1.0
    found = []
    for a_pos, a in enumerate(order):
        for b in order[a_pos + 1:]:
            under, over = lines[a], lines[b]
            xu, xo = np.asarray(under.get_xdata(), float), np.asarray(over.get_xdata(), float)
            if xu.shape != xo.shape or not np.allclose(xu, xo):
                continue
            yu, yo = np.asarray(under.get_ydata(), float), np.asarray(over.get_ydata(), float)
            apart = np.sqrt(np.nanmean((yu - yo) ** 2))
            if apart >= 0.02 * height:
                continue
            same_colour = under.get_color() == over.get_color()
            shows = (over.get_linestyle() not in ("-", "solid")
                     or over.get_linewidth() < 0.75 * under.get_linewidth())
            if same_colour or not shows:
                found.append(f"{over.get_label()!r} hides {under.get_label()!r}")
    return found


def problems(fig, name="figure"):
    """What makes ``fig`` hard to read (the module docstring's rules), as text; [] if
    nothing. The figure is drawn (its layout applied) first."""
    from matplotlib.patches import Polygon, Rectangle
    fig.draw_without_rendering()
    renderer = fig.canvas.get_renderer()
    edge = fig.bbox
    out = []
    texts = [t.get_text() for t in fig.findobj(lambda a: hasattr(a, "get_text"))
             if isinstance(t.get_text(), str)]
    for k, ax in enumerate(fig.axes):
        where = f"{name} panel {k}"
        is_colorbar = hasattr(ax, "_colorbar") or ax.get_label() == "<colorbar>"
        if not _inside(ax.get_tightbbox(renderer), edge):
            out.append(f"{where}: reaches past the figure's edge (clipped)")
        for axis, label, ticks in (("x", ax.get_xlabel(), ax.get_xticklabels()),
                                   ("y", ax.get_ylabel(), ax.get_yticklabels())):
            if is_colorbar and not label:
                continue
            if not label and not _ticks_shown(ticks):
                continue                # an inner panel of shared axes
            if not label:
                out.append(f"{where}: no {axis} label")
            elif not _labelled(label):
                out.append(f"{where}: {axis} label {label!r} has no unit")
            for tick in ticks:
                text = tick.get_text()
                if tick.get_visible() and re.search(r"\\times|\^|\$|×", text):
                    out.append(f"{where}: {axis} tick label {text!r} is not a plain number")
        out += [f"{where}: {problem}" for problem in _hidden_traces(ax)]
        labelled = [h for h in ax.get_lines() + list(ax.collections)
                    if not str(h.get_label()).startswith("_")]
        if labelled and ax.get_legend() is None:
            out.append(f"{where}: labelled traces and no legend")
    if any("shaded" in text for text in texts):
        spans = [p for ax in fig.axes for p in ax.patches if isinstance(p, (Polygon, Rectangle))]
        if not spans:
            out.append(f"{name}: says something is shaded and shades nothing")
    for text in fig.texts + ([fig._suptitle] if fig._suptitle is not None else []):
        if text.get_text() and not _inside(text.get_window_extent(renderer), edge):
            out.append(f"{name}: text {text.get_text()!r} reaches past the figure's edge")
    return out


class Recorder:
    """Install with ``monkeypatch.setattr(plotting, "save", recorder)``: each figure saved
    is kept (drawn again by :func:`problems`) by its file's name before it is written and
    closed as usual."""

    def __init__(self, save):
        self._save = save
        self.figures = {}

    def __call__(self, plt, fig, path):
        from pathlib import Path
        name = Path(path).name
        # A staged report file is written as ".NAME.png.xxxx": key by the final name.
        match = re.search(r"(\w+)\.png", name)
        self.figures[match.group(1) if match else name] = fig
        fig.draw_without_rendering()
        return self._save(_Keep(plt), fig, path)


class _Keep:
    """pyplot with close() a no-op: the recorder keeps the figure open for the test."""

    def __init__(self, plt):
        self._plt = plt

    def close(self, fig):
        pass
