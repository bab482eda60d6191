"""What every figure shares: Matplotlib's object API on the Agg canvas (no display needed, no
global pyplot state left behind), the resolution and style, each estimator's colour and line,
PNG files written atomically, and plain tick labels on log axes. The figures: a run's
(:mod:`smoother.outputs.plots`), the Monte Carlo consistency (:mod:`smoother.outputs.montecarlo_plot`)
and the Allan deviation (:mod:`smoother.outputs.allan_plot`).
"""
from __future__ import annotations

import math
from pathlib import Path

from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.figure import Figure
from matplotlib.ticker import FuncFormatter

from datasets.atomic import atomic_write
from smoother.confined import inside

#: Resolution of every PNG [dots per inch]; a figure of ``(w, h)`` inches is
#: ``round(w * DPI) x round(h * DPI)`` pixels.
DPI = 120
#: Matplotlib's settings for every figure (``matplotlib.rc_context``).
STYLE = {
    "font.size": 10,
    "axes.titlesize": 11,
    "axes.labelsize": 10,
    "legend.fontsize": 9,
    "xtick.labelsize": 9,
    "ytick.labelsize": 9,
    "axes.grid": True,
    "grid.alpha": 0.3,
    "lines.linewidth": 1.3,
}
#: The estimators' colours (others get the next of :data:`SPARE_COLORS`).
COLORS = {"batch": "tab:blue", "fixed-lag": "tab:orange", "ekf": "tab:green"}
SPARE_COLORS = ("tab:red", "tab:purple", "tab:brown", "tab:pink", "tab:olive", "tab:cyan")
#: Fixed-lag's newest state is close to the EKF's: it is drawn dashed and on top, so both show.
LINESTYLES = {"fixed-lag": (0, (4, 2))}
ZORDER = {"fixed-lag": 3.0}


def estimator_color(name: str, names) -> str:
    """The colour of estimator ``name`` in a figure drawing ``names``: its own, else the spare
    colours in turn among the others."""
    if name in COLORS:
        return COLORS[name]
    others = [n for n in names if n not in COLORS]
    return SPARE_COLORS[others.index(name) % len(SPARE_COLORS)]


def estimator_line(name: str, names, **kwargs) -> dict:
    """Keyword arguments of estimator ``name``'s line among ``names``: colour, line style, drawing
    order and label (``kwargs`` added)."""
    return {"color": estimator_color(name, names), "ls": LINESTYLES.get(name, "-"), "zorder": ZORDER.get(name, 2.0),
            "label": name, **kwargs}


def new_figure(size: tuple) -> Figure:
    """A new figure of ``size`` inches with an Agg canvas (no pyplot)."""
    fig = Figure(figsize=size, dpi=DPI, layout="constrained")
    FigureCanvasAgg(fig)
    return fig


def save_png(fig: Figure, out_dir: Path, stem: str) -> Path:
    """``fig`` as ``out_dir/<stem>.png``, written atomically and only inside ``out_dir``
    (:func:`smoother.confined.inside`); the figure is cleared."""
    path = inside(out_dir, f"{stem}.png")
    with atomic_write(path, "wb") as handle:
        fig.savefig(handle, format="png", dpi=DPI)
    fig.clear()
    return path


def plain_log_labels(ax) -> None:
    """Tick labels like 0.02 instead of 2 x 10^-2 on a log y axis (call after setting the limits);
    minor ticks 2 and 5 are labelled only when the axis spans at most two decades."""
    ax.yaxis.set_major_formatter(FuncFormatter(lambda v, _: f"{v:g}"))
    lo, hi = ax.get_ylim()
    few = lo > 0 and math.log10(hi / lo) <= 2.0
    ax.yaxis.set_minor_formatter(FuncFormatter(
        lambda v, _: f"{v:g}" if few and _leading_digit(v) in (2, 5) else ""))


def _leading_digit(v: float) -> int:
    return int(round(v / 10.0 ** math.floor(math.log10(v)))) if v > 0 else 0
