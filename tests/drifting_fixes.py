"""Position fixes whose errors drift, beside the truth they measure: what the scoring tests
(``tests/smoother/evaluation/test_scoring.py``) and the command line's note on interpolation
(``tests/cli/test_run_cli.py``) judge."""
from __future__ import annotations

from dataclasses import replace

import numpy as np

from datasets.simulate import simulate
from datasets.types import PositionMeasurements, Sensor, Trajectory
from factors.imu import ImuState


def fixes_with_noise(phi: float, n: int = 2000, every: int = 4):
    """``(dataset, truth)``: the truth (level, at 1 m/s along x and 0.2 m/s along y, 10 Hz), to be
    taken as the estimate, and fixes of it with AR(1) errors (``phi`` the correlation from one fix
    to the next, 0.5 m), every ``every``-th used and the rest held out, the dataset's only sensor
    (``gps``, a position sensor at the IMU); no truth in the dataset."""
    t = np.arange(n) * 0.1
    rng = np.random.default_rng(5)
    e = np.zeros((n, 3))
    for k in range(1, n):
        e[k] = phi * e[k - 1] + np.sqrt(1 - phi**2) * rng.normal(scale=0.5, size=3)
    zeros = np.zeros((n, 3))
    truth = Trajectory(t, ImuState(np.outer(t, [1.0, 0.2, 0.0]), zeros, np.tile(np.eye(3), (n, 1, 1)), zeros, zeros))
    fixes = PositionMeasurements(t, truth.states.r + e, 0.25 * np.eye(3))
    used = np.arange(n) % every == 0
    data = simulate(profile="gentle", duration=t[-1] + 0.1, seed=0, imu_rate=100.0, pose_rate=None)
    gps = Sensor("gps", "position", fixes.subset(used), fixes.subset(~used))
    return replace(data, sensors=(gps,), truth=None), truth
