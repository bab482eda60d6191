"""The initial state of a recording without ground truth, from the IMU and the sensors alone.

The estimate starts at the first measurement that fixes a position (a pose, position or GNSS
sensor's; without any, at the first IMU sample, with the world origin there). At that time ``t_s``:

* **attitude**: from the pose or orientation measurement nearest to ``t_s`` (``C_IB = Z R_BS^T``,
  carried to ``t_s`` through the gyro readings in between); otherwise roll and pitch from the
  mean specific force of the first :data:`LEVEL_WINDOW_S` seconds (at rest ``f = -C^T g``) and the
  heading from the course over ground: the first two position fixes at least
  :data:`COURSE_DISTANCE_M` apart, against the body's direction of travel (a velocity sensor's
  measured direction, else the body x axis), carried back to ``t_s`` through the gyro;
* **position**: the first fix minus its lever arm, ``r = z - C p_BS``;
* **velocity**: zero when the IMU is at rest at ``t_s`` (angular rate below
  :data:`REST_RATE` and specific force within :data:`REST_FORCE` of ``|g|``); else from the
  velocity sensor's measurement nearest ``t_s`` or from the fixes' finite differences;
* **biases**: zero, with the prior sigmas given.

Each part comes with the uncertainty of how it was found (:func:`initial_state`'s covariance).
When the data cannot fix the attitude, one :class:`InitialisationError` says what is missing.
"""
from __future__ import annotations

import numpy as np

from datasets.types import ImuSamples, Sensor
from factors import preintegration, so3
from factors.imu import STATE_DIM, ImuState
from factors.sensor_models import extrinsic_parts

#: Seconds of IMU data averaged for roll and pitch.
LEVEL_WINDOW_S = 0.5
#: A fix pair at least this far apart [m] gives the course over ground.
COURSE_DISTANCE_M = 5.0
#: At rest: angular rate below this [rad/s] and specific force within this of |g| [m/s^2].
REST_RATE = 0.05
REST_FORCE = 0.3
#: 1-sigma of the parts found from the IMU: level (roll, pitch) [rad], course heading [rad],
#: velocity from finite differences [m/s], a resting velocity [m/s].
LEVEL_SIGMA = np.deg2rad(2.0)
COURSE_SIGMA = np.deg2rad(10.0)
MOVING_VELOCITY_SIGMA = 1.0
REST_VELOCITY_SIGMA = 0.05

_POSITION_KINDS = ("pose", "position", "gnss")
_ATTITUDE_KINDS = ("pose", "orientation")


class InitialisationError(ValueError):
    """The data cannot fix the initial state; the message says what is missing."""


def start_time(imu: ImuSamples, sensors: list[Sensor]) -> float:
    """``t_s``: the first position measurement's time (module docstring), or the IMU's first."""
    firsts = [float(s.data.t[0]) for s in sensors if s.kind in _POSITION_KINDS and len(s.data)]
    return max(min(firsts), float(imu.t[0])) if firsts else float(imu.t[0])


def _attitude_change(imu: ImuSamples, t_a: float, t_b: float, b_w: np.ndarray) -> np.ndarray:
    """``dC`` with ``C(t_b) = C(t_a) dC``: the gyro readings between the two times (each held to
    the next sample, as the estimators step) integrated by the preintegration's recursion."""
    lo, hi = min(t_a, t_b), max(t_a, t_b)
    bounds = np.union1d(imu.t[(imu.t > lo) & (imu.t < hi)], [lo, hi])
    held = np.clip(np.searchsorted(imu.t, bounds[:-1], side="right") - 1, 0, len(imu) - 1)
    dt = np.diff(bounds)
    if dt.size == 0:
        return np.eye(3)
    dC = preintegration.integrate(imu.acc[held][None], imu.gyro[held][None], dt[None], b_w[None]).dC[0]
    return dC if t_b >= t_a else dC.T


def _nearest(t: np.ndarray, time: float) -> int:
    return int(np.argmin(np.abs(t - time)))


def _window(imu: ImuSamples, t_s: float):
    inside = (imu.t >= t_s) & (imu.t <= t_s + LEVEL_WINDOW_S)
    if inside.sum() < 2:
        inside = np.zeros(len(imu), bool)
        inside[:2] = True
    return imu.acc[inside], imu.gyro[inside]


def _level(imu: ImuSamples, t_s: float, gravity: np.ndarray) -> np.ndarray:
    """An attitude with the right roll and pitch (heading 0): the body's ``up`` is the mean
    specific force's direction (at rest ``f = -C^T g``)."""
    acc, _ = _window(imu, t_s)
    up_body = acc.mean(axis=0)
    up_body /= np.linalg.norm(up_body)
    up_world = -gravity / np.linalg.norm(gravity)
    # the rotation taking up_body to up_world (C up_body = up_world) by the shortest arc
    axis = np.cross(up_body, up_world)
    s, c = np.linalg.norm(axis), float(up_body @ up_world)
    if s < 1e-12:
        return np.eye(3) if c > 0 else so3.exp(np.array([np.pi, 0.0, 0.0]))
    return so3.exp(axis / s * np.arctan2(s, c))


def _travel_direction(sensors: list[Sensor]) -> np.ndarray:
    """The body-frame direction of travel: a velocity sensor's mean measured direction (while
    faster than 0.5 m/s) rotated into the body, else the body x axis. The IMU may be mounted in
    any orientation: whether the direction is horizontal is judged in the world frame, by
    :func:`_heading_from_course`."""
    for s in sensors:
        if s.kind == "velocity" and len(s.data):
            R, _ = extrinsic_parts(s.data.T_BS)
            fast = np.linalg.norm(s.data.velocity, axis=1) > 0.5
            if fast.any():
                d = R @ s.data.velocity[fast].mean(axis=0)
                return d / np.linalg.norm(d)
    return np.array([1.0, 0.0, 0.0])


def _course(sensors: list[Sensor]):
    """``(t_a, t_b, world direction)`` of the first fix pair at least COURSE_DISTANCE_M apart
    (horizontal), or None."""
    for s in sensors:
        if s.kind not in ("position", "gnss") or len(s.data) < 2:
            continue
        z = s.data.position
        moved = np.linalg.norm(z[:, :2] - z[0, :2], axis=1) >= COURSE_DISTANCE_M
        if moved.any():
            b = int(np.argmax(moved))
            a = max(b - 1, 0)
            while a > 0 and np.linalg.norm(z[b, :2] - z[a, :2]) < COURSE_DISTANCE_M:
                a -= 1
            d = z[b] - z[a]
            return float(s.data.t[a]), float(s.data.t[b]), d / np.linalg.norm(d)
    return None


def _heading_from_course(level: np.ndarray, imu: ImuSamples, t_s: float, sensors: list[Sensor]):
    """The level attitude turned about the vertical so that the body's direction of travel,
    midway through the course's fix pair, points along the course (carried back to ``t_s``)."""
    course = _course(sensors)
    if course is None:
        return None
    t_a, t_b, d_world = course
    t_mid = 0.5 * (t_a + t_b)
    C_mid = level @ _attitude_change(imu, t_s, t_mid, np.zeros(3))  # heading 0 at t_s
    d_body_world = C_mid @ _travel_direction(sensors)
    if np.linalg.norm(d_body_world[:2]) < 0.5:  # travelling along the IMU's x axis would go up or down
        raise InitialisationError(
            "cannot fix the initial heading from the course over ground: the direction of travel in the IMU frame "
            "(a velocity sensor's, else the IMU's x axis) is not horizontal; add a velocity sensor (wheel "
            "odometry) or a pose or orientation sensor")
    yaw = np.arctan2(d_world[1], d_world[0]) - np.arctan2(d_body_world[1], d_body_world[0])
    return so3.exp(np.array([0.0, 0.0, yaw])) @ level


def _at_rest(imu: ImuSamples, t_s: float, gravity: np.ndarray) -> bool:
    acc, gyro = _window(imu, t_s)
    return bool(np.linalg.norm(gyro, axis=1).max() < REST_RATE
                and np.abs(np.linalg.norm(acc, axis=1) - np.linalg.norm(gravity)).max() < REST_FORCE)


def initial_state(imu: ImuSamples, sensors: list[Sensor], gravity, bias_sigma=(0.1, 0.01)):
    """``(t_s, state, cov)``: the start time, the state there and its 15x15 covariance
    (error-state order) found as the module docstring says. ``bias_sigma = (accelerometer
    [m/s^2], gyro [rad/s])`` is the biases' prior."""
    gravity = np.asarray(gravity, dtype=float)
    t_s = start_time(imu, sensors)
    sigma = np.zeros(STATE_DIM)
    sigma[9:12], sigma[12:15] = bias_sigma

    # attitude
    attitude = [s for s in sensors if s.kind in _ATTITUDE_KINDS and len(s.data)]
    if attitude:
        s = min(attitude, key=lambda s: abs(s.data.t[_nearest(s.data.t, t_s)] - t_s))
        k = _nearest(s.data.t, t_s)
        R, _ = extrinsic_parts(s.data.T_BS)
        C = s.data.C[k] @ R.T @ _attitude_change(imu, float(s.data.t[k]), t_s, np.zeros(3))
        block = slice(3, 6) if s.kind == "pose" else slice(0, 3)
        sigma[6:9] = np.sqrt(np.diag(s.data.cov[k])[block]) + bias_sigma[1] * abs(float(s.data.t[k]) - t_s)
    else:
        level = _level(imu, t_s, gravity)
        C = _heading_from_course(level, imu, t_s, sensors)
        if C is None:
            raise InitialisationError(
                "cannot fix the initial heading: no pose or orientation sensor, and no position/GNSS fixes "
                f"{COURSE_DISTANCE_M:g} m apart to take the course over ground from (add a pose or orientation "
                "sensor, or record the vehicle moving)")
        sigma[6:9] = [LEVEL_SIGMA, LEVEL_SIGMA, COURSE_SIGMA]

    # position
    fixes = [s for s in sensors if s.kind in _POSITION_KINDS and len(s.data)]
    r = np.zeros(3)
    sigma[0:3] = 1e-3  # without fixes the world origin is the start
    if fixes:
        s = min(fixes, key=lambda s: float(s.data.t[0]))
        _, p = extrinsic_parts(s.data.T_BS)
        r = s.data.position[0] - C @ p
        sigma[0:3] = np.sqrt(np.diag(s.data.cov[0])[:3]) + np.linalg.norm(p) * sigma[6:9].max()

    # velocity
    v = np.zeros(3)
    sigma[3:6] = REST_VELOCITY_SIGMA
    if not _at_rest(imu, t_s, gravity):
        sigma[3:6] = MOVING_VELOCITY_SIGMA
        velocity = [s for s in sensors if s.kind == "velocity" and len(s.data)]
        if velocity:
            s = velocity[0]
            k = _nearest(s.data.t, t_s)
            R, p = extrinsic_parts(s.data.T_BS)
            v = R @ s.data.velocity[k] - np.cross(s.data.gyro[k], p)
        else:
            positions = [s for s in fixes if s.kind in ("position", "gnss") and len(s.data) >= 2]
            if positions:
                z, t = positions[0].data.position, positions[0].data.t
                v = C.T @ ((z[1] - z[0]) / (t[1] - t[0]))
    state = ImuState(r=r, v=v, C=so3.project(C), b_f=np.zeros(3), b_w=np.zeros(3))
    return t_s, state, np.diag(sigma**2)


def imu_from(imu: ImuSamples, t_s: float) -> ImuSamples:
    """The IMU stream from ``t_s`` on: a sample at ``t_s`` holding the reading before it (the
    zero-order hold every estimator applies, so nothing changes after ``t_s``), then the later
    samples. Nanosecond stamps are kept where they exist."""
    k = int(np.searchsorted(imu.t, t_s, side="right")) - 1
    if k < 0 or imu.t[k] == t_s:
        return imu.slice(max(k, 0), len(imu))
    later = imu.slice(k + 1, len(imu))
    t_ns = None if imu.t_ns is None else np.concatenate([[imu.t_ns[k] + round((t_s - imu.t[k]) * 1e9)], later.t_ns])
    return ImuSamples(np.concatenate([[t_s], later.t]), np.concatenate([imu.acc[k:k + 1], later.acc]),
                      np.concatenate([imu.gyro[k:k + 1], later.gyro]), t_ns)


def self_initialised(dataset, bias_sigma=(0.1, 0.01)):
    """``dataset`` started at :func:`start_time` with the state :func:`initial_state` finds,
    its own initial state and covariance (and any ground truth) left unused."""
    from dataclasses import replace

    from datasets.kinds import sensors_of

    t_s, state, cov = initial_state(dataset.imu, sensors_of(dataset), dataset.gravity, bias_sigma)
    return replace(dataset, imu=imu_from(dataset.imu, t_s), initial=state, initial_cov=cov)
