"""The IMU stream cut at knot times (keyframes, measurements) into Euler-forward steps.

IMU sample ``k`` is held over ``[t_k, t_{k+1})`` (zero-order hold, the primer's Euler-forward
step). A knot strictly inside such an interval splits it into two steps with the same sample, so
an estimator can stop exactly at the knot. The last IMU sample only marks the end of the stream.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from datasets.types import Dataset, ImuSamples
from factors.errors import InputError


@dataclass(frozen=True)
class Steps:
    """Euler steps: ``acc, gyro (S, 3)``, ``dt (S,)``, start times ``t (S,)``, and for each knot
    the number of steps taken before reaching it, ``knot_step (K,)``."""

    acc: np.ndarray
    gyro: np.ndarray
    dt: np.ndarray
    t: np.ndarray
    knot_step: np.ndarray

    def segments(self):
        """The steps between consecutive knots, padded: ``acc, gyro (J, L, 3)``, ``dt (J, L)``
        with ``J = K - 1`` and padding steps of ``dt = 0`` (the identity step)."""
        starts, stops = self.knot_step[:-1], self.knot_step[1:]
        lengths = stops - starts
        L = max(int(lengths.max(initial=0)), 1)
        idx = starts[:, None] + np.arange(L)[None, :]
        valid = np.arange(L)[None, :] < lengths[:, None]
        safe = np.minimum(idx, max(len(self.dt) - 1, 0))
        dt = np.where(valid, self.dt[safe], 0.0)
        acc = np.where(valid[..., None], self.acc[safe], 0.0)
        gyro = np.where(valid[..., None], self.gyro[safe], 0.0)
        return acc, gyro, dt


def imu_steps(imu: ImuSamples, knots: np.ndarray) -> Steps:
    """Cut the IMU stream at ``knots`` (sorted, within ``[imu.t[0], imu.t[-1]]``)."""
    knots = np.asarray(knots, dtype=float)
    if not np.all(np.isfinite(knots)):  # a NaN passes every comparison below and yields NaN steps
        raise InputError(f"knot times must be finite, got {knots[~np.isfinite(knots)][:3]}")
    if knots.size and (knots[0] < imu.t[0] or knots[-1] > imu.t[-1]):
        raise InputError(
            f"knot times [{knots[0]}, {knots[-1]}] outside the IMU span [{imu.t[0]}, {imu.t[-1]}]"
        )
    if np.any(np.diff(knots) <= 0):
        raise InputError("knot times must increase strictly")
    return steps_between(imu.t, imu.acc, imu.gyro, knots)


def steps_between(t: np.ndarray, acc: np.ndarray, gyro: np.ndarray, knots) -> Steps:
    """:func:`imu_steps` of the samples ``t (N,)``, ``acc, gyro (N, 3)`` (checked by the caller:
    increasing times; ``knots`` increasing, finite, within ``[t[0], t[-1]]``)."""
    bounds = np.union1d(t, knots)
    starts = bounds[:-1]
    sample = np.searchsorted(t, starts, side="right") - 1
    return Steps(
        acc=acc[sample],
        gyro=gyro[sample],
        dt=np.diff(bounds),
        t=starts,
        knot_step=np.searchsorted(bounds, knots),
    )


def interval_steps(t: np.ndarray, acc: np.ndarray, gyro: np.ndarray, t_from: float, t_to: float) -> tuple:
    """The steps of :func:`steps_between` ``(t, acc, gyro, [t_from, t_to])`` from its first knot to its
    second, bit for bit, as ``(acc, gyro, dt)`` (``acc``, ``gyro`` views of the samples'), without
    its sort: one interval of an online smoother, at every keyframe. ``t[0] <= t_from < t_to``,
    the samples checked by the caller."""
    first = int(np.searchsorted(t, t_from, side="right")) - 1  # the sample held at t_from
    stop = int(np.searchsorted(t, t_to, side="left"))  # the samples before t_to
    bounds = np.empty(stop - first + 1)
    bounds[0], bounds[1:-1], bounds[-1] = t_from, t[first + 1:stop], t_to
    return acc[first:stop], gyro[first:stop], np.diff(bounds)


def estimate_times(dataset: Dataset, grid_rate: float | None = None) -> np.ndarray:
    """Where the estimators report states (the smoothers' keyframes, the EKF's knots): every
    measurement time of every sensor (both ends of a relative one), the times of held-out
    measurements (only their times: an evaluation wants estimates there), the start and end of
    the IMU data, and optionally a grid of ``grid_rate`` Hz; all within the IMU span."""
    parts = [dataset.measurement_times(), [dataset.t0, dataset.t1]]
    parts += [s.heldout.t for s in dataset.sensors if s.heldout is not None]
    if grid_rate:
        # Grid times as t0 + k / rate (correctly rounded, like the measurement ticks; arange's
        # accumulated k * step differs by an ulp, e.g. 0.30000000000000004 beside a measurement
        # at 0.3), and none within half an IMU step of another estimate time: a near-duplicate
        # keyframe makes an IMU interval of ~1e-16 s whose factor has a ~0 covariance, and the
        # system becomes indeterminant.
        others = np.unique(np.concatenate([np.asarray(p, dtype=float) for p in parts]))
        grid = dataset.t0 + np.arange(len(np.arange(dataset.t0, dataset.t1, 1.0 / grid_rate))) / grid_rate
        i = np.searchsorted(others, grid)
        gap = np.minimum(np.abs(grid - others[np.maximum(i - 1, 0)]), np.abs(others[np.minimum(i, len(others) - 1)] - grid))
        parts.append(grid[gap >= 0.5 * float(np.median(np.diff(dataset.imu.t)))])
    times = np.unique(np.concatenate([np.asarray(p, dtype=float) for p in parts]))
    return times[(times >= dataset.t0) & (times <= dataset.t1)]
