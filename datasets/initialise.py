"""The initial state of a recording without ground truth, from the IMU and the sensors alone.

The estimate starts at ``t_s``, the first measurement at or after the first IMU sample that fixes a
position (a pose, position or GNSS sensor's; without any, the first IMU sample, with the world
origin there: an odometry-frame run, :func:`world_frame`). Only measurements at or after ``t_s``
are used:

* **attitude**: from the pose or orientation measurement nearest to ``t_s`` (``C_IB = Z R_BS^T``,
  carried to ``t_s`` through the gyro); otherwise roll and pitch from the mean specific force over
  :data:`LEVEL_WINDOW_S` (at rest ``f = -C^T g``; while accelerating good to about ``a / g``, so
  the level sigma is wider when the IMU is not at rest) and the heading from the course over
  ground: the first two fixes a baseline apart (at least :data:`COURSE_DISTANCE_M` and five
  times the fixes' noise), against the body's direction of travel over that stretch (the velocity
  sensor's measurements then, signed: reversing counts; without one the vehicle's forward
  direction in the IMU frame, ``forward``, by default the IMU's x axis: the vehicle is assumed to
  drive forwards), carried back to ``t_s`` through the gyro. Its sigma is that of the baseline's
  direction plus the gyro-bias drift over the carry. Without any position sensor (and so no
  course) the heading is 0 at ``t_s`` by definition of the odometry frame, with the sigma
  :data:`ODOMETRY_FRAME_SIGMA`. A magnetometer gives the heading before the course does: the first
  reading's direction against the world field's, sigma :data:`MAGNETIC_HEADING_SIGMA`;
* **position**: the fix at ``t_s`` minus its lever arm, ``r = z - C p_BS``; without a position
  sensor the world origin, with the sigma :data:`ODOMETRY_FRAME_SIGMA` (the start defines the
  frame; the estimators' covariances grow from there);
* **velocity**: from the velocity sensor's measurement nearest ``t_s`` (within
  :data:`VELOCITY_WINDOW_S`) when there is one; else a straight line through the fixes of the
  first :data:`VELOCITY_WINDOW_S` seconds (fewer than two there: through the first two, their
  mean velocity, with :data:`UNKNOWN_VELOCITY_SIGMA` when they show motion -- how the velocity
  changed between them the fixes cannot tell), with the sigma of that fit, each axis judged by its
  own noise (a receiver's vertical sigma is twice its horizontal one: a car cruising at 10 m/s
  moves 20 m in 2 s, less than three times a 5-m vertical sigma but forty horizontal ones); when
  no axis's slope is three of its sigmas from zero and the IMU is at rest (mean angular rate
  below :data:`REST_RATE`, specific force within :data:`REST_FORCE` of ``|g|`` -- which a
  constant-velocity cruise satisfies too), zero, with the sigma the fixes leave
  (:data:`REST_VELOCITY_SIGMA` at least); without fixes, zero at rest, else unknown;
* **biases**: zero, with the prior sigmas given.

The measurements that fix the start are applied again at ``t_s`` by the estimators; so that they
do not count twice, the parts taken from them enter the prior with :data:`PRIOR_INFLATION` times
their sigma. When the data cannot fix the attitude, one :class:`InitialisationError` says what is
missing.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from datasets.kinds.magnetometer import MagneticFieldMeasurements, heading
from datasets.types import (
    ImuSamples,
    OrientationMeasurements,
    PoseMeasurements,
    PositionMeasurements,
    Sensor,
    VelocityMeasurements,
)
from factors import preintegration, so3
from factors.errors import InputError
from factors.imu import STATE_DIM, ImuState
from factors.sensor_models import extrinsic_parts

#: The vehicle's forward direction in the IMU frame unless a rig says otherwise: the IMU's x axis.
FORWARD = (1.0, 0.0, 0.0)
#: Seconds of IMU data averaged for roll and pitch (and the rest test).
LEVEL_WINDOW_S = 0.5
#: The course over ground needs fixes at least this far apart [m] (and five times their noise).
COURSE_DISTANCE_M = 5.0
#: Seconds over which the velocity is taken from the velocity sensor or the fixes.
VELOCITY_WINDOW_S = 2.0
#: At rest: mean angular rate below this [rad/s], specific force within this of |g| [m/s^2].
REST_RATE = 0.05
REST_FORCE = 0.3
#: 1-sigma of parts found from the IMU: level at rest / while moving [rad], a resting velocity
#: [m/s], a velocity nothing measures [m/s].
LEVEL_SIGMA = np.deg2rad(2.0)
MOVING_LEVEL_SIGMA = np.deg2rad(10.0)
REST_VELOCITY_SIGMA = 0.05
UNKNOWN_VELOCITY_SIGMA = 10.0
#: The prior's sigma of parts taken from a measurement the estimators apply again, in its sigmas.
PRIOR_INFLATION = 10.0
#: 1-sigma of what an odometry-frame run's start defines rather than measures: the position [m]
#: (the world origin) and, without an absolute attitude, the heading [rad] (0).
ODOMETRY_FRAME_SIGMA = 1e-3

#: What fixes a position (any kind measuring these data types), what an attitude and what a heading.
_POSITION_TYPES = (PoseMeasurements, PositionMeasurements)
_ATTITUDE_TYPES = (PoseMeasurements, OrientationMeasurements)
_HEADING_TYPES = _ATTITUDE_TYPES + (MagneticFieldMeasurements,)
#: 1-sigma [rad] of a heading from a magnetometer's first reading (its direction's noise, the
#: level's error carried into the heading and the local disturbances of the field together).
MAGNETIC_HEADING_SIGMA = np.deg2rad(10.0)


class InitialisationError(InputError):
    """The data cannot fix the initial state; the message says what is missing."""


@dataclass(frozen=True)
class WorldFrame:
    """The world frame of a run's estimates. ``odometry``: no sensor measures an absolute position
    (no pose, position or GNSS sensor), so the world origin is the start (REP-105's ``odom``
    frame; with one, ``map``); ``relative_heading``: no sensor measures an absolute heading either
    (no pose, orientation or magnetometer sensor; a ``roll_pitch`` sensor gives none), so the yaw
    is 0 at the start and relative to it."""

    odometry: bool
    relative_heading: bool

    @property
    def frame_id(self) -> str:
        """REP-105's name of the frame: ``odom`` or ``map``."""
        return "odom" if self.odometry else "map"

    def describe(self) -> dict:
        """What ``metrics.json`` records (``_run.world_frame``)."""
        return {"frame_id": self.frame_id, "position": "relative to the start" if self.odometry else "absolute",
                "yaw": "relative to the start" if self.relative_heading else "absolute"}

    def note(self) -> str | None:
        """The line a run's table closes with in the odometry frame, None otherwise."""
        if not self.odometry:
            return None
        what = "position and yaw are" if self.relative_heading else "position is"
        return (f"odometry frame: no absolute position sensor; {what} relative to the start "
                "(metrics.json: _run.world_frame)")


def world_frame(sensors: list[Sensor]) -> WorldFrame:
    """The :class:`WorldFrame` of a run on ``sensors`` (:func:`datasets.kinds.sensors_of` of a
    dataset)."""
    def measures(types) -> bool:
        return any(isinstance(s.data, types) and len(s.data) for s in sensors)

    odometry = not measures(_POSITION_TYPES)
    return WorldFrame(odometry, odometry and not measures(_HEADING_TYPES))


def is_odometry_frame(sensors: list[Sensor]) -> bool:
    """Whether a run on ``sensors`` is in the odometry frame (no absolute position sensor: the
    world origin is the start; :class:`WorldFrame`)."""
    return world_frame(sensors).odometry


def start_time(imu: ImuSamples, sensors: list[Sensor]) -> float:
    """``t_s``: the first position measurement at or after the first IMU sample (module
    docstring), or the IMU's first sample."""
    t0 = float(imu.t[0])
    firsts = [float(s.data.t[s.data.t >= t0][0]) for s in sensors
              if isinstance(s.data, _POSITION_TYPES) and len(s.data) and np.any(s.data.t >= t0)]
    return min(firsts) if firsts else t0


def _from_start(sensors: list[Sensor], t_s: float, types) -> list:
    """``(sensor, data)`` of the ``sensors`` whose data are of ``types``, from ``t_s`` on (sensors
    left with none dropped)."""
    out = []
    for s in sensors:
        if isinstance(s.data, types) and len(s.data) and np.any(s.data.t >= t_s):
            out.append((s, s.data.subset(s.data.t >= t_s)))
    return out


def _attitude_change(imu: ImuSamples, t_a: float, t_b: float, b_w: np.ndarray) -> np.ndarray:
    """``dC`` with ``C(t_b) = C(t_a) dC``: the gyro readings between the two times (each held to
    the next sample, as the estimators step) integrated by the preintegration's recursion."""
    lo, hi = min(t_a, t_b), max(t_a, t_b)
    bounds = np.union1d(imu.t[(imu.t > lo) & (imu.t < hi)], [lo, hi])
    held = imu.held(bounds[:-1])
    dt = np.diff(bounds)
    if dt.size == 0:
        return np.eye(3)
    dC = preintegration.integrate(imu.acc[held][None], imu.gyro[held][None], dt[None], b_w[None]).dC[0]
    return dC if t_b >= t_a else dC.T


def _nearest(t: np.ndarray, time: float) -> int:
    return int(np.argmin(np.abs(t - time)))


def _window(imu: ImuSamples, t_s: float):
    """The IMU readings of the :data:`LEVEL_WINDOW_S` after ``t_s`` (at least the two samples
    nearest to it)."""
    inside = (imu.t >= t_s) & (imu.t <= t_s + LEVEL_WINDOW_S)
    if inside.sum() < 2:
        inside = np.zeros(len(imu), bool)
        inside[np.argsort(np.abs(imu.t - t_s))[:2]] = True
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


def _travel_direction(velocity: list, t_a: float, t_b: float, forward: np.ndarray):
    """The body-frame direction of travel between ``t_a`` and ``t_b``: the signed mean of a velocity
    sensor's measurements there (faster than 0.5 m/s), rotated into the body; else ``forward``
    (a vehicle driving forwards). Whether it is horizontal is judged in the world frame, by
    :func:`_heading_from_course` (the IMU may be mounted in any orientation). Returns the direction
    and where it came from (for the message when it is not horizontal)."""
    for s, m in velocity:
        R, _ = extrinsic_parts(m.T_BS)
        inside = (m.t >= t_a) & (m.t <= t_b) & (np.linalg.norm(m.velocity, axis=1) > 0.5)
        if inside.any():
            d = R @ m.velocity[inside].mean(axis=0)
            if np.linalg.norm(d) > 0.25:
                return d / np.linalg.norm(d), (f"velocity sensor {s.name!r}'s measured direction: check the rotation "
                                               "of its T_BS, the sensor frame in the IMU frame")
    return forward / np.linalg.norm(forward), (
        f"vehicle's forward direction in the IMU frame, {np.round(forward, 3).tolist()} (the rig's [imu] forward), "
        "taken as the direction of travel without a velocity sensor: set it, or add a velocity sensor "
        "(wheel odometry), or a pose or orientation sensor")


def _horizontal_sigma(m, k: int) -> float:
    """The larger horizontal sigma of fix ``k`` [m]."""
    return float(np.sqrt(max(m.cov[k, 0, 0], m.cov[k, 1, 1])))


def _course(fixes: list):
    """``(t_a, t_b, world direction, sigma [rad])`` of the earliest, shortest stretch of fixes
    ``a .. b`` whose horizontal baseline is at least COURSE_DISTANCE_M and five times the two
    fixes' combined noise (so that it is motion, not noise), or None."""
    for s, m in fixes:
        if not isinstance(m, PositionMeasurements) or len(m) < 2:
            continue
        z = m.position
        for b in range(1, len(m)):
            for a in range(b - 1, -1, -1):  # the latest start that is far enough back: a short chord
                noise = float(np.hypot(_horizontal_sigma(m, a), _horizontal_sigma(m, b)))
                baseline = float(np.linalg.norm(z[b, :2] - z[a, :2]))
                if baseline >= max(COURSE_DISTANCE_M, 5.0 * noise):
                    d = z[b] - z[a]
                    return float(m.t[a]), float(m.t[b]), d / np.linalg.norm(d), float(np.arctan2(noise, baseline))
    return None


def _heading_from_course(level: np.ndarray, imu: ImuSamples, t_s: float, fixes: list, velocity: list, gyro_bias_sigma,
                         forward: np.ndarray):
    """``(C, heading sigma)``: the level attitude turned about the vertical so that the body's
    direction of travel, midway through the course's fix pair, points along the course (carried
    back to ``t_s``), or None without a course."""
    course = _course(fixes)
    if course is None:
        return None
    t_a, t_b, d_world, sigma = course
    t_mid = 0.5 * (t_a + t_b)
    C_mid = level @ _attitude_change(imu, t_s, t_mid, np.zeros(3))  # heading 0 at t_s
    d_body, source = _travel_direction(velocity, t_a, t_b, forward)
    d_body_world = C_mid @ d_body
    if np.linalg.norm(d_body_world[:2]) < 0.5:  # the vehicle would travel up or down
        raise InitialisationError("cannot fix the initial heading from the course over ground: the direction of "
                                  f"travel in the IMU frame is not horizontal; it is the {source}")
    yaw = np.arctan2(d_world[1], d_world[0]) - np.arctan2(d_body_world[1], d_body_world[0])
    return so3.exp(np.array([0.0, 0.0, yaw])) @ level, sigma + gyro_bias_sigma * abs(t_mid - t_s)


def _heading_from_field(level: np.ndarray, imu: ImuSamples, t_s: float, fields: list, gyro_bias_sigma):
    """``(C, heading sigma)``: the level attitude turned about the vertical so that the first
    magnetometer reading's direction, carried back to ``t_s`` through the gyro, points along the
    world field's horizontal direction; or None without a magnetometer."""
    if not fields:
        return None
    _, m = min(fields, key=lambda sm: float(sm[1].t[0]))
    t_m = float(m.t[0])
    C_m = level @ _attitude_change(imu, t_s, t_m, np.zeros(3))  # heading 0 at t_s
    yaw = heading(m, C_m)
    return so3.exp(np.array([0.0, 0.0, yaw])) @ level, MAGNETIC_HEADING_SIGMA + gyro_bias_sigma * abs(t_m - t_s)


def _imu_at_rest(imu: ImuSamples, t_s: float, gravity: np.ndarray) -> bool:
    """The window's mean angular rate below REST_RATE and its mean specific force within
    REST_FORCE of ``|g|`` (means: a noisy unit's single samples exceed both while at rest)."""
    acc, gyro = _window(imu, t_s)
    return bool(np.linalg.norm(gyro.mean(axis=0)) < REST_RATE
                and abs(np.linalg.norm(acc.mean(axis=0)) - np.linalg.norm(gravity)) < REST_FORCE)


def initial_velocity(imu, t_s, gravity, C, velocity: list, fixes: list):
    """``(body velocity, sigma)`` at ``t_s`` (module docstring)."""
    for s, m in velocity:
        k = _nearest(m.t, t_s)
        if abs(m.t[k] - t_s) <= VELOCITY_WINDOW_S:
            R, p = extrinsic_parts(m.T_BS)
            lever = np.cross(m.gyro[k], p)
            return R @ m.velocity[k] - lever, float(np.sqrt(np.max(np.diag(m.cov[k])))) + 0.1
    window = [(s, _first_fixes(m, t_s)) for s, m in fixes if isinstance(m, PositionMeasurements)]
    window = [(s, m) for s, m in window if len(m) >= 2]
    if window:
        s, m = max(window, key=lambda sm: len(sm[1]))
        dt = float(m.t[-1] - m.t[0])
        slope = np.polyfit(m.t - m.t[0], m.position, 1)[0]  # the world velocity of a line through the fixes
        noise = np.sqrt(np.max(m.cov[:, [0, 1, 2], [0, 1, 2]], axis=0))  # each axis's
        fit_sigma = np.sqrt(12.0 / len(m)) * noise / dt  # a fit's slope sigma, per axis
        moving = bool(np.any(np.abs(slope) > 3.0 * fit_sigma))
        if not moving and _imu_at_rest(imu, t_s, gravity):  # or cruising too slowly for the fixes to tell
            return np.zeros(3), max(REST_VELOCITY_SIGMA, float(np.max(np.abs(slope) + fit_sigma)))
        if dt > VELOCITY_WINDOW_S:  # the mean velocity of a longer stretch: how it changed there is unknown
            return C.T @ slope, max(UNKNOWN_VELOCITY_SIGMA, float(fit_sigma.max()) + 0.5)
        return C.T @ slope, float(fit_sigma.max()) + 0.5  # and what it may change meanwhile
    if _imu_at_rest(imu, t_s, gravity):
        return np.zeros(3), REST_VELOCITY_SIGMA
    return np.zeros(3), UNKNOWN_VELOCITY_SIGMA


def _first_fixes(m: PositionMeasurements, t_s: float) -> PositionMeasurements:
    """The fixes of ``m`` from ``t_s`` to ``t_s + VELOCITY_WINDOW_S``, or its first two from
    ``t_s`` on when that window holds fewer (fixes further apart, or a sensor's ``every``)."""
    after = m.subset(m.t >= t_s)
    early = after.subset(after.t <= t_s + VELOCITY_WINDOW_S)
    return early if len(early) >= 2 else after.subset(np.arange(len(after)) < 2)


def initial_state(imu: ImuSamples, sensors: list[Sensor], gravity, bias_sigma=(0.1, 0.01), forward=FORWARD):
    """``(t_s, state, cov)``: the start time, the state there and its 15x15 covariance
    (error-state order) found as the module docstring says. ``bias_sigma = (accelerometer
    [m/s^2], gyro [rad/s])`` is the biases' prior; ``forward`` the vehicle's forward direction in
    the IMU frame (any length)."""
    gravity = np.asarray(gravity, dtype=float)
    t_s = start_time(imu, sensors)
    sigma = np.zeros(STATE_DIM)
    sigma[9:12], sigma[12:15] = bias_sigma
    fixes = _from_start(sensors, t_s, _POSITION_TYPES)
    velocity = _from_start(sensors, t_s, (VelocityMeasurements,))

    # attitude
    attitude = _from_start(sensors, t_s, _ATTITUDE_TYPES)
    if attitude:
        s, m = min(attitude, key=lambda sm: float(sm[1].t[0]))
        R, _ = extrinsic_parts(m.T_BS)
        C = m.C[0] @ R.T @ _attitude_change(imu, float(m.t[0]), t_s, np.zeros(3))
        block = slice(3, 6) if isinstance(m, PoseMeasurements) else slice(0, 3)
        sigma[6:9] = PRIOR_INFLATION * np.sqrt(np.diag(m.cov[0])[block]) + bias_sigma[1] * float(m.t[0] - t_s)
    else:
        level = _level(imu, t_s, gravity)
        found = _heading_from_field(level, imu, t_s, _from_start(sensors, t_s, (MagneticFieldMeasurements,)),
                                    bias_sigma[1])
        if found is None:
            found = _heading_from_course(level, imu, t_s, fixes, velocity, bias_sigma[1],
                                         np.asarray(forward, dtype=float))
        if found is None and is_odometry_frame(sensors):
            found = level, ODOMETRY_FRAME_SIGMA  # the start's heading defines the frame
        if found is None:
            raise InitialisationError(
                "cannot fix the initial heading: no pose or orientation sensor, and no position/GNSS fixes "
                f"{COURSE_DISTANCE_M:g} m (and five times their noise) apart to take the course over ground from "
                "(add a pose or orientation sensor, or record the vehicle moving)")
        C, heading_sigma = found
        level_sigma = LEVEL_SIGMA if _imu_at_rest(imu, t_s, gravity) else MOVING_LEVEL_SIGMA
        sigma[6:9] = [level_sigma, level_sigma, heading_sigma]

    # position
    r = np.zeros(3)
    sigma[0:3] = ODOMETRY_FRAME_SIGMA  # without fixes the world origin is the start
    if fixes:
        s, m = min(fixes, key=lambda sm: float(sm[1].t[0]))
        _, p = extrinsic_parts(m.T_BS)
        r = m.position[0] - C @ p
        sigma[0:3] = PRIOR_INFLATION * np.sqrt(np.diag(m.cov[0])[:3]) + np.linalg.norm(p) * sigma[6:9].max()

    v, sigma[3:6] = initial_velocity(imu, t_s, gravity, C, velocity, fixes)
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


def self_initialised(dataset, bias_sigma=(0.1, 0.01), forward=FORWARD):
    """``dataset`` started at :func:`start_time` with the state :func:`initial_state` finds
    (``bias_sigma``, ``forward`` as there), its own initial state and covariance (and any ground
    truth) left unused."""
    from dataclasses import replace

    from datasets.kinds import sensors_of

    t_s, state, cov = initial_state(dataset.imu, sensors_of(dataset), dataset.gravity, bias_sigma, forward)
    return replace(dataset, imu=imu_from(dataset.imu, t_s), initial=state, initial_cov=cov)
