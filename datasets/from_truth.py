"""Synthetic pose and position measurements drawn from a ground-truth :class:`Trajectory`
(``pose_from_truth``, ``gps_from_truth``; any kind of sensor with its extrinsic:
:mod:`datasets.simulated_sensors`).

The one place where measurements are generated from a truth (EuRoC's ``pose_from_truth`` /
``gps_from_truth`` and any dataset with a ground truth use it).

Times: a measurement is taken at a truth sample, never interpolated, so its value is exactly
the truth plus noise. For a rate ``f`` the ticks are ``t_0 + k / f`` (``t_0`` the first truth
time) and each tick takes the first truth sample at or after it (a tolerance of 1e-6 of the
median truth step absorbs round-off in the ticks); a truth sample is used at most once. A rate
above the truth's own rate is refused (it could not be delivered).

Noise, in the primer's convention (docs/design.md, section 7): position ``r_meas = r + n_r``,
``n_r ~ N(0, pos_sigma^2 I)``; attitude ``C_meas = exp(n) C``, ``n ~ N(0, rot_sigma^2 I)`` in WORLD
coordinates (the left perturbation of eq. 63). The covariance stored with the measurements is
exactly that of the noise drawn. ``seed`` is anything ``numpy.random.default_rng`` accepts; the
same seed gives the same measurements. Pose and position measurements of one dataset come from
:func:`measurements_from_truth`, which gives each its own stream (one seed for both would draw the
same position noise twice: GPS fixes perfectly correlated with the pose sensor's positions).
"""
from __future__ import annotations

import numpy as np

from datasets.types import PoseMeasurements, PositionMeasurements, Trajectory
from factors import so3


def _positive(name: str, value) -> float:
    try:
        value = float(value)
    except (TypeError, ValueError):
        raise ValueError(f"{name}: expected a number > 0, got {value!r}") from None
    if not np.isfinite(value) or value <= 0:
        raise ValueError(f"{name}: expected a finite number > 0, got {value!r}")
    return value


def measurement_indices(t: np.ndarray, rate_hz: float) -> np.ndarray:
    """Indices into the truth times ``t`` (strictly increasing) of measurements at ``rate_hz``."""
    rate_hz = _positive("rate_hz", rate_hz)
    t = np.asarray(t, dtype=float)
    if t.size == 0:
        return np.zeros(0, dtype=int)
    if t.size == 1:
        return np.zeros(1, dtype=int)
    step = float(np.median(np.diff(t)))
    if rate_hz * step > 1.0 + 1e-6:
        raise ValueError(
            f"rate_hz: {rate_hz:g} Hz is above the rate of the ground truth ({1.0 / step:g} Hz); "
            "measurements are taken at truth samples"
        )
    count = int(np.floor((t[-1] - t[0]) * rate_hz + 1e-9)) + 1
    ticks = t[0] + np.arange(count) / rate_hz
    index = np.searchsorted(t, ticks - 1e-6 * step, side="left")
    index = index[index < t.size]
    return np.unique(index)


def pose_measurements_from_truth(truth: Trajectory, rate_hz: float, pos_sigma: float, rot_sigma: float,
                                 seed=0) -> PoseMeasurements:
    """Pose readings (position and attitude) at ``rate_hz`` with the noise of the module
    docstring; covariance ``diag(pos_sigma^2 I3, rot_sigma^2 I3)``."""
    pos_sigma = _positive("pos_sigma", pos_sigma)
    rot_sigma = _positive("rot_sigma", rot_sigma)
    k = measurement_indices(truth.t, rate_hz)
    rng = np.random.default_rng(seed)
    position = truth.position[k] + pos_sigma * rng.standard_normal((len(k), 3))
    C = so3.boxplus(truth.C[k], rot_sigma * rng.standard_normal((len(k), 3)))
    cov = np.diag(np.repeat([pos_sigma**2, rot_sigma**2], 3))
    return PoseMeasurements(truth.t[k], position, C, cov)


def position_measurements_from_truth(truth: Trajectory, rate_hz: float, pos_sigma: float,
                                     seed=0) -> PositionMeasurements:
    """GPS-like position fixes at ``rate_hz``; covariance ``pos_sigma^2 I3``."""
    pos_sigma = _positive("pos_sigma", pos_sigma)
    k = measurement_indices(truth.t, rate_hz)
    rng = np.random.default_rng(seed)
    position = truth.position[k] + pos_sigma * rng.standard_normal((len(k), 3))
    return PositionMeasurements(truth.t[k], position, pos_sigma**2 * np.eye(3))


def measurements_from_truth(truth: Trajectory, pose_from_truth=None, gps_from_truth=None, seed=0):
    """``(pose, position)`` measurements drawn from ``truth``: ``pose_from_truth = (rate_hz,
    pos_sigma, rot_sigma)`` and ``gps_from_truth = (rate_hz, pos_sigma)`` (None: none of that
    kind), with independent noise streams spawned from ``seed`` (an integer >= 0). A ValueError
    names which of the two is wrong."""
    pose_seed, gps_seed = np.random.SeedSequence(seed).spawn(2)
    pose = position = None
    try:
        if pose_from_truth is not None:
            pose = pose_measurements_from_truth(truth, *pose_from_truth, seed=pose_seed)
    except ValueError as error:
        raise ValueError(f"pose_from_truth: {error}") from None
    try:
        if gps_from_truth is not None:
            position = position_measurements_from_truth(truth, *gps_from_truth, seed=gps_seed)
    except ValueError as error:
        raise ValueError(f"gps_from_truth: {error}") from None
    return pose, position
