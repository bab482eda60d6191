"""``montecarlo_nees.png`` of ``smoother montecarlo``: the Monte Carlo runs' consistency."""
from __future__ import annotations

from pathlib import Path

from smoother.outputs.canvas import LINESTYLES, STYLE, estimator_color, new_figure, save_png

#: The figure's size [inch].
FIGSIZE = (11.0, 5.0)


def plot_montecarlo(summary, out_dir) -> Path:
    """``montecarlo_nees.png``: the pose NEES per dimension at each keyframe, averaged over the
    Monte Carlo runs, per estimator, with the 95% chi-square interval of that average (a
    :class:`smoother.evaluation.montecarlo.Summary`)."""
    import matplotlib

    low, high = summary.nees_interval_95
    with matplotlib.rc_context(STYLE):
        fig = new_figure(FIGSIZE)
        ax = fig.add_subplot()
        ax.axhspan(low, high, color="0.85", label=f"95% interval ({summary.runs} runs)")
        ax.axhline(1.0, color="0.3", lw=0.8, ls="--")
        for name, e in summary.estimators.items():
            ax.plot(e["t"], e["nees_per_keyframe"], color=estimator_color(name, summary.estimators), lw=1.2,
                    ls=LINESTYLES.get(name, "-"),
                    label=f"{name} (mean {e['nees_mean']:.2f}, {100 * e['nees_share_inside_95']:.0f}% inside)")
        ax.set_xlabel("time [s]")
        ax.set_ylabel("pose NEES / 6, mean over runs")
        ax.set_title(f"Monte Carlo consistency: {summary.runs} runs")
        ax.legend(loc="upper right", fontsize=9)
        return save_png(fig, out_dir, "montecarlo_nees")
