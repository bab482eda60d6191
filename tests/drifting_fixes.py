"""Position fixes whose errors drift: an AR(1) sequence over a straight-line truth, every few held
out -- the case where interpolating the used fixes beats any estimator (shared by the scoring and
the command line's tests)."""
from __future__ import annotations

from dataclasses import replace

import numpy as np

from datasets.simulate import simulate
from datasets.types import PositionMeasurements, Sensor, Trajectory


def fixes_with_noise(phi: float, n: int = 2000, every: int = 4):
    """``(dataset, truth)``: the truth a straight line at 1 m/s (the simulator's first state's
    attitude, velocity and biases), fixes of it at 10 Hz with AR(1) errors (``phi`` the
    correlation from one fix to the next, 0.5 m), every ``every``-th used and the rest held out;
    the dataset's IMU a simulated one (the fixes are all it is judged by), without a truth."""
    t = np.arange(n) * 0.1
    rng = np.random.default_rng(5)
    e = np.zeros((n, 3))
    for k in range(1, n):
        e[k] = phi * e[k - 1] + np.sqrt(1 - phi**2) * rng.normal(scale=0.5, size=3)
    data = simulate(profile="gentle", duration=t[-1] + 0.1, seed=0, imu_rate=100.0, pose_rate=None)
    truth = Trajectory(t, data.truth.states[np.zeros(n, dtype=int)].replace(r=np.outer(t, [1.0, 0.2, 0.0])))
    fixes = PositionMeasurements(t, truth.states.r + e, 0.25 * np.eye(3))
    used = np.arange(n) % every == 0
    gps = Sensor("gps", "position", fixes.subset(used), fixes.subset(~used))
    return replace(data, sensors=(gps,), truth=None), truth
