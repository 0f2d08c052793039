"""What every figure of the reports shares: the size, resolution and layout they are drawn
at, plain numbers on logarithmic axes, and the time axis of a log.

Every report PNG is drawn with constrained layout (labels, ticks and titles make room for
themselves, so nothing is clipped at the figure's edge) at :data:`DPI`, in one of two sizes:
:data:`WIDE` for a series against time, :data:`NARROW` for the rest; a report's figures
then show at one scale side by side. The figures are made with pyplot on the Agg backend
(no display needed) and closed once saved.
"""

import datetime
import math

import numpy as np

__all__ = ["DPI", "WIDE", "NARROW", "pyplot", "figure", "save", "plain_log_axis",
           "plain_number", "clock_of_day", "log_time_axis"]

#: Dots per inch of every report PNG; with :data:`WIDE` a figure is 990 pixels across.
DPI = 110
#: Figure sizes in inches: (width, height) of a series against time, and of the others;
#: a second panel adds :data:`PANEL` inches of height.
WIDE = (9.0, 4.0)
NARROW = (7.0, 4.0)
PANEL = 2.2


def pyplot():
    """matplotlib.pyplot on the Agg backend."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    return plt


def figure(size=NARROW, rows=1, *, height_ratios=None, sharex=True):
    """A new figure of ``size`` with ``rows`` panels stacked (each extra one
    :data:`PANEL` inches high), constrained layout; returns (plt, fig, axes) where axes is
    one Axes for one row, else a list."""
    plt = pyplot()
    width, height = size
    height += PANEL * (rows - 1)
    fig, axes = plt.subplots(rows, 1, figsize=(width, height), layout="constrained",
                             sharex=sharex if rows > 1 else False,
                             gridspec_kw={"height_ratios": height_ratios}
                             if height_ratios else None)
    return plt, fig, (list(axes) if rows > 1 else axes)


def save(plt, fig, path):
    """Write ``fig`` as a PNG at :data:`DPI` to ``path`` and close it; returns ``path``."""
    try:
        fig.savefig(path, dpi=DPI, format="png")
    finally:
        plt.close(fig)
    return path


def plain_number(value, _position=None):
    """A tick label as a plain decimal: 0.002, 0.1, 2, 30, 1000 (never 2×10⁰)."""
    if value == 0 or not math.isfinite(value):
        return "0" if value == 0 else ""
    digits = max(0, -int(math.floor(math.log10(abs(value)) + 1e-9)))
    text = f"{value:.{digits}f}"
    return text.rstrip("0").rstrip(".") if "." in text else text


def plain_log_axis(ax, which="both", *, minor_labels=False):
    """Put a logarithmic axis's tick labels in plain numbers: labels on 1, 2 and 5 times
    the powers of ten when the axis spans less than two decades (so a short axis still has
    labels), on the powers of ten only when it spans more; minor ticks unlabelled unless
    ``minor_labels``."""
    from matplotlib.ticker import FuncFormatter, LogLocator, NullFormatter
    for axis in (("x", "y") if which == "both" else (which,)):
        target = ax.xaxis if axis == "x" else ax.yaxis
        low, high = (ax.get_xlim() if axis == "x" else ax.get_ylim())
        low, high = min(low, high), max(low, high)
        decades = math.log10(high / low) if low > 0 and high > 0 else 10.0
        subs = (1.0, 2.0, 5.0) if decades < 2 else (1.0,)
        target.set_major_locator(LogLocator(base=10, subs=subs))
        target.set_major_formatter(FuncFormatter(plain_number))
        target.set_minor_locator(LogLocator(base=10, subs=np.arange(2, 10) * 1.0))
        target.set_minor_formatter(FuncFormatter(plain_number) if minor_labels
                                   else NullFormatter())


def clock_of_day(seconds):
    """Seconds since 00:00 UTC as HH:MM:SS (the day wrapped)."""
    seconds = float(seconds) % 86400.0
    return (datetime.datetime(2000, 1, 1) + datetime.timedelta(seconds=seconds)) \
        .strftime("%H:%M:%S")


def log_time_axis(t, timed=True):
    """The x values and label for a series on a log's time base: ``t`` (seconds since
    00:00 UTC when ``timed``, else the samples' arrival numbers) becomes seconds from the
    first sample, labelled with that sample's UTC clock time; untimed, the arrival order.
    Returns (x, label)."""
    t = np.asarray(t, dtype=float)
    if not timed or t.size == 0 or not np.isfinite(t[0]):
        return t, "magnetometer sample (in arrival order: the log has no GPS time)"
    return t - t[0], f"seconds from {clock_of_day(t[0])} UTC (the first sample)"
