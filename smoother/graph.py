"""Building the factor graph of a dataset: keyframes, IMU factors, measurement factors, priors
and initial values.

Keyframes sit at :func:`smoother.timeline.estimate_times`: every measurement time, held-out fix
times, the start and end of the IMU data, and optionally a fixed grid (``keyframe_rate``). Keyframe 0 carries a joint prior from ``dataset.initial`` and
``dataset.initial_cov``. Consecutive keyframes are joined by an IMU factor
(:class:`factors.imu_factor.ImuFactor`); every interval is preintegrated in one batched call.

Initial values come from dead reckoning and the measurements: keyframe ``k`` starts as the IMU
prediction from keyframe ``k-1``; a measured position or attitude then replaces the predicted one
and, where positions are measured, the velocity is taken from their finite differences. The same
initial trajectory is the reference along which each IMU factor's noise covariance is computed.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import gtsam
import numpy as np

from datasets.types import Dataset
from factors import imu, preintegration
from factors import measurements as meas
from factors.imu_factor import ImuFactor
from factors.keys import KeyframeKeys, keyframe_keys
from smoother.timeline import estimate_times, imu_steps

#: Robust kernels selectable per measurement type.
ROBUST_KERNELS = {
    "huber": (gtsam.noiseModel.mEstimator.Huber, 1.345),
    "cauchy": (gtsam.noiseModel.mEstimator.Cauchy, 2.385),
    "tukey": (gtsam.noiseModel.mEstimator.Tukey, 4.685),
}


def robust_spec(text: str | None):
    """Parse ``none``, ``huber``, ``cauchy[:k]``, ``tukey:4.0`` into ``(name, threshold)`` or None."""
    if text is None or text == "none":
        return None
    name, _, value = text.partition(":")
    if name not in ROBUST_KERNELS:
        raise ValueError(f"robust kernel {name!r}: expected one of none, {', '.join(ROBUST_KERNELS)}")
    try:
        threshold = float(value) if value else ROBUST_KERNELS[name][1]
    except ValueError:
        raise ValueError(f"robust kernel threshold {value!r}: expected a number") from None
    if not threshold > 0:
        raise ValueError(f"robust kernel threshold must be positive, got {threshold}")
    return name, threshold


def noise_model(cov: np.ndarray, robust=None):
    """A Gaussian model of ``cov``, wrapped in a robust kernel ``(name, threshold)`` if given."""
    base = meas.covariance_model(cov)
    if robust is None:
        return base
    kernel, _ = ROBUST_KERNELS[robust[0]]
    return gtsam.noiseModel.Robust.Create(kernel.Create(robust[1]), base)


@dataclass
class Problem:
    """A dataset's factor graph: keyframe times and keys, the graph, initial values, and the
    factors grouped by the keyframe at which they become available (for fixed-lag smoothing)."""

    times: np.ndarray
    keys: list[KeyframeKeys]
    graph: gtsam.NonlinearFactorGraph
    initial: gtsam.Values
    initial_states: imu.ImuState
    imu_factors: list[ImuFactor]
    factors_at: list[list] = field(default_factory=list)
    gravity: np.ndarray = field(default_factory=lambda: imu.DEFAULT_GRAVITY.copy())


def _match(times: np.ndarray, t: np.ndarray) -> np.ndarray:
    """Keyframe index of each time in ``t`` (which must all be keyframe times), -1 if outside."""
    i = np.searchsorted(times, t)
    ok = (i < len(times)) & (times[np.minimum(i, len(times) - 1)] == t)
    return np.where(ok, i, -1)


def insert_state(values: gtsam.Values, keys: KeyframeKeys, state: imu.ImuState) -> None:
    """Insert one state's variables (Rot3, Point3, velocity, bias) under ``keys``."""
    values.insert(keys.rot, gtsam.Rot3(state.C))
    values.insert(keys.pos, gtsam.Point3(*state.r))
    values.insert(keys.vel, np.array(state.v, dtype=float))
    values.insert(keys.bias, gtsam.imuBias.ConstantBias(state.b_f, state.b_w))


def read_state(values: gtsam.Values, keys: KeyframeKeys) -> imu.ImuState:
    """The state of one keyframe from GTSAM values."""
    b = values.atConstantBias(keys.bias).vector()
    return imu.ImuState(
        r=values.atPoint3(keys.pos), v=values.atVector(keys.vel), C=values.atRot3(keys.rot).matrix(),
        b_f=b[:3], b_w=b[3:],
    )


def _initial_states(dataset: Dataset, times: np.ndarray, pre: preintegration.Preintegrated) -> imu.ImuState:
    """Dead reckoning from keyframe to keyframe, reset by measured positions and attitudes."""
    n = len(times)
    measured_r = np.full((n, 3), np.nan)
    measured_C = np.full((n, 3, 3), np.nan)
    for m in (dataset.position, dataset.pose):
        if m is not None:
            idx = _match(times, m.t)
            measured_r[idx[idx >= 0]] = m.position[idx >= 0]
    for m in (dataset.orientation, dataset.pose):
        if m is not None:
            idx = _match(times, m.t)
            measured_C[idx[idx >= 0]] = m.C[idx >= 0]
    has_r = np.isfinite(measured_r[:, 0])
    world_v = None
    if has_r.sum() >= 2:
        tr, rr = times[has_r], measured_r[has_r]
        gradient = np.gradient(rr, tr, axis=0)
        world_v = np.stack([np.interp(times, tr, gradient[:, a]) for a in range(3)], axis=-1)
    states = [dataset.initial]
    for k in range(1, n):
        x = preintegration.predict(pre[k - 1], states[-1], dataset.gravity)
        if np.isfinite(measured_C[k, 0, 0]):
            x = x.replace(C=measured_C[k])
        if has_r[k]:
            x = x.replace(r=measured_r[k])
        if world_v is not None:
            x = x.replace(v=x.C.T @ world_v[k])
        states.append(x)
    return imu.ImuState.stack(states)


def build_problem(dataset: Dataset, keyframe_rate: float | None = None, robust: dict | None = None) -> Problem:
    """The factor graph of ``dataset`` (see the module docstring).

    ``robust`` maps a measurement type (``"pose"``, ``"position"``, ``"orientation"``,
    ``"relative_pose"``) to a kernel spec ``(name, threshold)`` from :func:`robust_spec`.
    """
    robust = robust or {}
    times = estimate_times(dataset, keyframe_rate)
    if len(times) < 2:
        raise ValueError("the dataset spans less than one keyframe interval")
    keys = [keyframe_keys(k) for k in range(len(times))]
    steps = imu_steps(dataset.imu, times)
    acc, gyro, dt = steps.segments()
    b_w0 = np.broadcast_to(dataset.initial.b_w, (len(times) - 1, 3))
    pre = preintegration.integrate(acc, gyro, dt, b_w0)
    initial_states = _initial_states(dataset, times, pre)
    pre.cov = preintegration.noise_covariance(pre.samples, initial_states[:-1], dataset.noise, dataset.gravity)

    factors_at: list[list] = [[] for _ in times]
    factors_at[0].append(meas.state_prior_factor(keys[0], dataset.initial, dataset.initial_cov))
    imu_factors = []
    for k in range(1, len(times)):
        f = ImuFactor(pre[k - 1], keys[k - 1], keys[k], dataset.gravity)
        imu_factors.append(f)
        factors_at[k].append(f.factor)
    if dataset.pose is not None:
        m = dataset.pose
        for i, k in enumerate(_match(times, m.t)):
            if k >= 0:
                model = noise_model(m.cov[i], robust.get("pose"))
                factors_at[k].append(meas.pose_factor(keys[k].pos, keys[k].rot, m.position[i], m.C[i], model))
    if dataset.position is not None:
        m = dataset.position
        for i, k in enumerate(_match(times, m.t)):
            if k >= 0:
                model = noise_model(m.cov[i], robust.get("position"))
                factors_at[k].append(meas.position_factor(keys[k].pos, m.position[i], model))
    if dataset.orientation is not None:
        m = dataset.orientation
        for i, k in enumerate(_match(times, m.t)):
            if k >= 0:
                model = noise_model(m.cov[i], robust.get("orientation"))
                factors_at[k].append(meas.orientation_factor(keys[k].rot, m.C[i], model))
    if dataset.relative_pose is not None:
        m = dataset.relative_pose
        ki, kj = _match(times, m.t_from), _match(times, m.t_to)
        for i in range(len(m)):
            if ki[i] >= 0 and kj[i] >= 0:
                model = noise_model(m.cov[i], robust.get("relative_pose"))
                a, b = keys[ki[i]], keys[kj[i]]
                factors_at[kj[i]].append(
                    meas.relative_pose_factor(a.rot, a.pos, b.rot, b.pos, m.dr[i], m.dC[i], model)
                )
    graph = gtsam.NonlinearFactorGraph()
    for group in factors_at:
        for f in group:
            graph.add(f)
    values = gtsam.Values()
    for k, kk in enumerate(keys):
        insert_state(values, kk, initial_states[k])
    return Problem(times, keys, graph, values, initial_states, imu_factors, factors_at, dataset.gravity)
