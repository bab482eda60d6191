"""Position fixes whose errors drift: an AR(1) sequence over a straight-line truth, every few held
out -- the case where interpolating the used fixes beats any estimator (shared by the scoring and
the command line's tests) -- and simulated runs with such fixes, modelled as drifting or not (the
drifting model's tests): every few held out, or at their own stamps with a lever arm."""
from __future__ import annotations

from dataclasses import replace

import numpy as np

from datasets.simulate import simulate
from datasets.types import PositionMeasurements, Sensor, Trajectory
from smoother.model.correlated import transitions


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


def drifting_run(seed: int, tau: float | None, duration: float = 60.0, hz: float = 5.0, every: int = 5,
                 sigma: float = 0.5, true_tau: float = 10.0, pose_rate: float | None = None):
    """A simulated run with one position sensor whose errors drift (AR(1), ``sigma`` m, ``true_tau``
    s) at ``hz``, every ``every``-th fix used and the rest held out, modelled with correlation
    time ``tau`` (None: white); with ``pose_rate`` [Hz], the simulator's pose sensor beside it."""
    d = simulate(profile="gentle", duration=duration, seed=seed, pose_rate=pose_rate)
    rng = np.random.default_rng(seed + 100)
    t = np.arange(d.imu.t[0] + 0.5, d.imu.t[-1] - 0.5, 1.0 / hz)
    r = np.stack([np.interp(t, d.truth.t, d.truth.states.r[:, a]) for a in range(3)], axis=1)
    e = np.zeros_like(r)
    e[0] = sigma * rng.standard_normal(3)
    for m, phi in enumerate(transitions(t, true_tau), start=1):
        e[m] = phi * e[m - 1] + sigma * np.sqrt(1 - phi**2) * rng.standard_normal(3)
    fixes = PositionMeasurements(t, r + e, np.broadcast_to(sigma**2 * np.eye(3), (len(t), 3, 3)).copy())
    used = np.arange(len(t)) % every == 0
    gnss = Sensor("gnss", "position", fixes.subset(used), fixes.subset(~used), correlation_time=tau)
    return replace(d, sensors=(*d.sensors, gnss))


def lever_arm_run(hz: float = 5.0, tau: float | None = 3.0, calibrate=None, seed: int = 0, duration: float = 8.0):
    """A simulated run with one position sensor of AR(1) errors (0.3 m, 3 s) at ``hz`` and lever arm
    (0.2, -0.1, 0.3) m, stamps not on the IMU's (measurements attached between keyframes), each
    measurement's covariance its own, modelled with correlation time ``tau`` (None: white) and
    calibrating ``calibrate`` (a :class:`factors.calibration.CalibrationPrior` or None)."""
    d = simulate(profile="gentle", duration=duration, seed=seed, pose_rate=None)
    rng = np.random.default_rng(seed)
    t = np.arange(d.imu.t[0] + 0.013, d.imu.t[-1] - 0.2, 1.0 / hz)
    r = np.stack([np.interp(t, d.truth.t, d.truth.states.r[:, a]) for a in range(3)], axis=1)
    e = np.zeros_like(r)
    e[0] = 0.3 * rng.standard_normal(3)
    for m, phi in enumerate(transitions(t, 3.0), start=1):
        e[m] = phi * e[m - 1] + 0.3 * np.sqrt(1 - phi**2) * rng.standard_normal(3)
    T = np.eye(4)
    T[:3, 3] = [0.2, -0.1, 0.3]
    cov = np.diag([0.09, 0.04, 0.16]) * rng.uniform(0.5, 2.0, (len(t), 1, 1))
    fixes = PositionMeasurements(t, r + e, cov, T_BS=T)
    return replace(d, sensors=(Sensor("gnss", "position", fixes, calibrate=calibrate, correlation_time=tau),))
