"""``allan.png`` of ``smoother allan``: the Allan deviation of a static IMU recording."""
from __future__ import annotations

from pathlib import Path

import numpy as np

from datasets.allan import WALK_TAU, WHITE_TAU
from smoother.outputs.canvas import STYLE, new_figure, save_png

#: The figure's size [inch].
FIGSIZE = (12.0, 5.0)
#: The colours of the x, y and z axes.
AXIS_COLORS = ("tab:blue", "tab:orange", "tab:green")


def plot_allan(result, out_dir) -> Path:
    """``allan.png``: the Allan deviation of each accelerometer and gyro axis (a
    :class:`datasets.allan.AllanResult`), log-log, with the fitted white-noise (slope -1/2) and
    random-walk (slope +1/2) lines of each axis and the points where they are read (1 s, 3 s)."""
    import matplotlib

    with matplotlib.rc_context(STYLE):
        fig = new_figure(FIGSIZE)
        panels = (("accelerometer", result.acc_adev, result.acc_white, result.acc_walk, "m/s$^2$"),
                  ("gyro", result.gyro_adev, result.gyro_white, result.gyro_walk, "rad/s"))
        tau = result.tau
        for j, (name, adev, white, walk, unit) in enumerate(panels):
            ax = fig.add_subplot(1, 2, j + 1)
            for k, axis in enumerate("xyz"):
                color = AXIS_COLORS[k]
                known = f"{walk[k]:.3g}" if np.isfinite(walk[k]) else "not estimated"
                shown = np.where(adev[:, k] > 0, adev[:, k], np.nan)  # an axis of one value has zeros: no line
                ax.loglog(tau, shown, color=color, label=f"{axis}: N {white[k]:.3g}, K {known}")
                ax.loglog(tau, white[k] / np.sqrt(tau / WHITE_TAU), color=color, lw=0.8, ls="--")
                ax.loglog(tau, walk[k] * np.sqrt(tau / WALK_TAU), color=color, lw=0.8, ls=":")
                ax.plot([WHITE_TAU, WALK_TAU], [white[k], walk[k]], "o", color=color, ms=4)
            values = np.concatenate([adev.ravel(), white, walk])
            values = values[np.isfinite(values) & (values > 0)]  # NaN: not estimated; 0: an axis of one value
            if values.size:  # the fitted lines run far beyond the data: keep them in view
                ax.set_ylim(values.min() / 3, values.max() * 3)
            ax.set_xlabel("cluster time $\\tau$ [s]")
            ax.set_ylabel(f"Allan deviation [{unit}]")
            ax.set_title(f"{name}: white noise N (--, read at 1 s), random walk K (:, read at 3 s)")
            ax.legend(loc="upper center")
        return save_png(fig, out_dir, "allan")
