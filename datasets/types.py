"""The project's data types: a few NumPy arrays in a dataclass each, never objects per sample.

Conventions (docs/design.md, section 1): times in seconds (float64; loaders with nanosecond stamps keep
them exactly in ``t_ns``), world frame ``I``, body = IMU frame ``B``, attitudes as body-to-world
rotation matrices ``C(Phi_IB)`` of shape ``(N, 3, 3)``. Orientation covariances are in the
primer's convention: ``C_meas = exp(n) C_true`` with ``n ~ N(0, cov)`` in WORLD coordinates.
Every constructor validates shapes and values and raises ``ValueError`` naming the field.
"""
from __future__ import annotations

import contextlib
import contextvars
import warnings
from dataclasses import dataclass, field, fields, replace

import numpy as np
from numba import njit

from datasets.ranges import correlation_time_problem, sensor_name_problem
from factors import so3
from factors.errors import InputError
from factors.imu import DEFAULT_GRAVITY, ImuNoise, ImuState
from factors.small_linalg import cholesky_into

#: An IMU interval longer than this many typical periods is reported as a gap.
IMU_GAP_FACTOR = 5.0
#: An IMU interval longer than this [s] is no gap but a jump of the clock (or stamps of another
#: clock): refused, since dead reckoning across it is meaningless.
MAX_IMU_GAP_S = 3600.0
#: Time difference [s] within which two stamps are the same instant (round-off of stamps written
#: and read again): :meth:`Trajectory.interpolate` takes such a sample as it is.
SAME_INSTANT_S = 1e-6
#: The 99th-percentile angular rate [rad/s] beyond which gyro data are refused as probably in
#: deg/s: 35 rad/s (2000 deg/s, a MEMS gyro's full scale) is beyond what a vehicle turns at. No
#: single sample may exceed it on any axis either (a gyro reads nothing beyond its full scale).
MAX_PLAUSIBLE_RATE = 35.0
#: The specific force [m/s^2] no accelerometer axis reads beyond: about 200 g, the full scale of
#: high-g MEMS accelerometers (a navigation IMU's is 2-40 g). A sample beyond it is corrupt.
MAX_PLAUSIBLE_SPECIFIC_FORCE = 2000.0
#: The largest plausible coordinate of a position or displacement measurement [m] (five times
#: the geostationary orbit's radius: room for Earth-centred coordinates).
MAX_PLAUSIBLE_DISTANCE = 2e8
#: The largest plausible component of a velocity measurement [m/s] (above orbital speed).
MAX_PLAUSIBLE_SPEED = 1e4
_max_rate = contextvars.ContextVar("max_gyro_rate", default=MAX_PLAUSIBLE_RATE)


@contextlib.contextmanager
def max_gyro_rate(limit: float):
    """Inside the block, datasets and online smoothers made there accept gyro data up to
    ``limit`` [rad/s] (a 99th-percentile rate, and each sample's axes) instead of
    :data:`MAX_PLAUSIBLE_RATE` (the rare real case: a spinning projectile, a rotor-mounted IMU).
    The loaders construct their datasets inside, so it reaches them too."""
    token = _max_rate.set(float(limit))
    try:
        yield
    finally:
        _max_rate.reset(token)


def gyro_rate_limit() -> float:
    """The angular rate [rad/s] in force (:func:`max_gyro_rate`, default :data:`MAX_PLAUSIBLE_RATE`)."""
    return _max_rate.get()


def check_array(name: str, value, shape_tail: tuple, n: int | None = None, t=None) -> np.ndarray:
    """``value`` as a finite float array of shape ``(n,) + shape_tail``; a clear error otherwise
    (naming the row, and its time where the rows' times ``t`` are given)."""
    try:
        a = np.asarray(value, dtype=float)
    except (TypeError, ValueError):
        raise InputError(f"{name}: expected an array of numbers, got {type(value).__name__}") from None
    expected = ("N",) + shape_tail if n is None else (n,) + shape_tail
    if a.ndim != 1 + len(shape_tail) or a.shape[1:] != shape_tail or (n is not None and a.shape[0] != n):
        raise InputError(f"{name}: expected shape {expected}, got {a.shape}")
    if not np.isfinite(a).all():  # the method: np.all's dispatch costs as much as the test, per row
        bad = np.argwhere(~np.isfinite(a.reshape(a.shape[0], -1)).all(axis=1))[0][0]
        raise InputError(f"{name}: non-finite value (NaN or inf) at {_row(bad, t)}")
    return a


def _row(i: int, t=None) -> str:
    """``row i``, with its time where the times ``t`` are known (and finite)."""
    if t is None or not np.isfinite(t[i]):
        return f"row {i}"
    return f"row {i} (t = {float(t[i]):.6f} s)"


def check_magnitude(name: str, a: np.ndarray, limit: float, unit: str, t=None, why: str = "") -> np.ndarray:
    """``a`` (rows of finite numbers) with no entry beyond ``+-limit``; an error naming the row
    (and its time, where ``t`` is given), the value and the limit otherwise (``why``: what a value
    beyond it probably means)."""
    if a.size and not np.abs(a).max() <= limit:
        bad = int(np.argmax(np.abs(a.reshape(a.shape[0], -1)).max(axis=1) > limit))
        value = a.reshape(a.shape[0], -1)[bad]
        value = value[np.argmax(np.abs(value))]
        raise InputError(f"{name}: {value:.4g} {unit} at {_row(bad, t)} is beyond the plausible +-{limit:g} {unit}"
                         + (f" ({why})" if why else ""))
    return a


def check_imu_range(prefix: str, t, acc: np.ndarray, gyro: np.ndarray, rate_limit: float | None = None) -> None:
    """No axis of ``acc`` beyond :data:`MAX_PLAUSIBLE_SPECIFIC_FORCE`, none of ``gyro`` beyond
    ``rate_limit`` (default :func:`gyro_rate_limit`): such a sample is corrupt (or in other units);
    an error naming the field (``prefix`` + ``acc`` / ``gyro``), the row and its time otherwise."""
    check_magnitude(f"{prefix}acc", acc, MAX_PLAUSIBLE_SPECIFIC_FORCE, "m/s^2", t,
                    "beyond any accelerometer's range: a corrupt sample, or data in mm/s^2")
    check_magnitude(f"{prefix}gyro", gyro, gyro_rate_limit() if rate_limit is None else rate_limit, "rad/s", t,
                    "beyond a MEMS gyro's full scale: a corrupt sample, or data in deg/s; for a real case, raise "
                    "the limit (smoother run --max-gyro-rate)")


def check_imu_rates(prefix: str, gyro: np.ndarray) -> None:
    """The 99th percentile of the angular rate's magnitude at most :func:`gyro_rate_limit`: no
    vehicle turns faster for long, so data beyond it are in deg/s; an error naming the field
    (``prefix`` + ``gyro``) otherwise. Checked on the IMU's own samples before anything carries
    them on (a velocity sensor's rows hold the IMU's gyro for the lever arm), so that the error
    names the IMU."""
    w = float(np.percentile(np.linalg.norm(gyro, axis=1), 99)) if len(gyro) else 0.0
    limit = gyro_rate_limit()
    if w > limit:
        raise InputError(f"{prefix}gyro: 99th percentile angular rate {w:.4g}, above {limit:g} rad/s that no vehicle "
                         f"reaches; the data are probably in deg/s (convert them to rad/s), or, for a real case, raise "
                         f"the limit (smoother run --max-gyro-rate)")


def imu_gaps(t: np.ndarray, typical: float | None = None, where: str = "Dataset.imu",
             rows: bool = True) -> tuple[np.ndarray, str | None]:
    """The rule for the intervals of IMU times ``t``: one longer than :data:`MAX_IMU_GAP_S` is
    an error (a clock jump); those longer than :data:`IMU_GAP_FACTOR` ``typical`` periods (default:
    the median interval) are gaps, bridged by holding the sample before each (zero-order hold,
    only as good as the motion is steady there). Returns the gaps' lengths and the warning about
    them (how many, the longest, its start and length; ``rows``: its row too), or None. ``where``
    names the stream."""
    dt = np.diff(t)
    if dt.size == 0:
        return dt, None
    jump = np.flatnonzero(dt > MAX_IMU_GAP_S)
    if jump.size:
        i = int(jump[0])
        raise InputError(f"{where}: t: a step of {dt[i]:.6g} s after t = {t[i]:.6f} s" + (f" (row {i})" if rows else "")
                         + f", beyond any plausible gap ({MAX_IMU_GAP_S:g} s): a jump of the clock, or stamps of "
                         "another clock")
    typical = float(np.median(dt)) if typical is None else typical
    long = np.flatnonzero(dt > IMU_GAP_FACTOR * typical)
    if not long.size:
        return dt[long], None
    i = int(long[np.argmax(dt[long])])
    return dt[long], (f"{where}: {long.size} gap(s) longer than {IMU_GAP_FACTOR:g} x the typical period "
                      f"({typical:.4g} s); the longest is {dt[i]:.4g} s after t = {t[i]:.6f} s"
                      + (f" (row {i})" if rows else "") + "; each is bridged by holding the sample before it")


def check_times(name: str, t, strictly_increasing: bool = True) -> np.ndarray:
    """``t`` as a finite float array of shape ``(N,)``, strictly increasing unless told otherwise."""
    t = check_array(name, t, ())
    if strictly_increasing and t.size > 1:
        step = np.diff(t)
        if np.any(step <= 0):
            i = int(np.argmax(step <= 0))
            what = "duplicate" if step[i] == 0 else "decreasing"
            raise InputError(
                f"{name}: timestamps must increase strictly; row {i + 1} ({t[i + 1]!r}) is {what} "
                f"after row {i} ({t[i]!r})"
            )
    return t


def check_covariances(name: str, cov, n: int, dim: int) -> np.ndarray:
    """``cov`` (one ``(dim, dim)`` matrix, broadcast, or ``(n, dim, dim)``) as symmetric positive
    definite covariances of shape ``(n, dim, dim)`` (:func:`_covariance_defect`)."""
    cov = np.asarray(cov, dtype=float)
    if cov.shape == (dim, dim):
        cov = np.repeat(cov[None], n, axis=0)
    cov = check_array(name, cov, (dim, dim), n)
    i, defect = _covariance_defect(np.ascontiguousarray(cov))
    if defect == 1:
        raise InputError(f"{name}: covariance at row {i} is not symmetric")
    if defect == 2:
        raise InputError(f"{name}: covariance at row {i} is not positive definite (smallest eigenvalue "
                         f"{np.linalg.eigvalsh(cov[i]).min():.3g})")
    return cov


@njit(cache=True)
def _covariance_defect(cov):
    """``(row, 1)`` for the first of the matrices ``cov (n, d, d)`` that is not symmetric (an
    entry off its transpose's by more than 1e-9 times the largest), else ``(row, 2)`` for the
    first that is not positive definite (its Cholesky factorisation, what whitening needs, fails),
    else ``(-1, 0)``."""
    n, d = cov.shape[0], cov.shape[1]
    for i in range(n):
        scale, asym = 1e-300, 0.0
        for a in range(d):
            for b in range(d):
                scale = max(scale, abs(cov[i, a, b]))
                asym = max(asym, abs(cov[i, a, b] - cov[i, b, a]))
        if asym > 1e-9 * scale:
            return i, 1
    L = np.empty((d, d))
    for i in range(n):
        if not cholesky_into(cov[i], L):
            return i, 2
    return -1, 0


def _distances(name: str, value, t: np.ndarray) -> np.ndarray:
    """Positions or displacements [m] at times ``t``: finite, shape ``(len(t), 3)``, no coordinate
    beyond :data:`MAX_PLAUSIBLE_DISTANCE`."""
    return check_magnitude(name, check_array(name, value, (3,), len(t), t), MAX_PLAUSIBLE_DISTANCE, "m", t)


def check_rotations(name: str, C, n: int) -> np.ndarray:
    """``C`` as ``n`` rotation matrices (orthonormal within 1e-6, det > 0) of shape ``(n, 3, 3)``
    (:func:`_rotation_defect`)."""
    C = check_array(name, C, (3, 3), n)
    i, err, det = _rotation_defect(np.ascontiguousarray(C))
    if i >= 0:
        raise InputError(f"{name}: row {i} is not a rotation matrix (|C C^T - I| = {err:.3g}, det {det:.6g})")
    return C


@njit(cache=True)
def _rotation_defect(C):
    """``(row, |C C^T - I|, det C)`` of the first of the matrices ``C (n, 3, 3)`` that is not a
    rotation (an entry of ``C C^T - I`` beyond 1e-6, or ``det C <= 0``), or ``(-1, 0, 0)``."""
    for i in range(C.shape[0]):
        err, det = _orthonormality(C[i])
        if err > 1e-6 or det <= 0.0:
            return i, err, det
    return -1, 0.0, 0.0


@njit(cache=True)
def _orthonormality(M):
    """``(max |M M^T - I|, det M)`` of a 3x3 matrix."""
    err = 0.0
    for a in range(3):
        for b in range(3):
            s = M[a, 0] * M[b, 0] + M[a, 1] * M[b, 1] + M[a, 2] * M[b, 2]
            err = max(err, abs(s - 1.0) if a == b else abs(s))
    det = (M[0, 0] * (M[1, 1] * M[2, 2] - M[1, 2] * M[2, 1]) - M[0, 1] * (M[1, 0] * M[2, 2] - M[1, 2] * M[2, 0])
           + M[0, 2] * (M[1, 0] * M[2, 1] - M[1, 1] * M[2, 0]))
    return err, det


#: Accepted deviation of a rigid transform's rotation from orthonormality (and of det from 1).
RIGID_TOLERANCE = 1e-6


def rigid_problem(T, tolerance: float = RIGID_TOLERANCE) -> str | None:
    """What keeps ``T`` from being a 4x4 rigid transform -- a finite 4x4 array with last row
    ``0 0 0 1`` and a rotation part ``R`` with ``|R R^T - I| <= tolerance`` and
    ``|det R - 1| <= tolerance`` -- or None if it is one."""
    T = np.asarray(T, dtype=float)
    if T.shape != (4, 4):
        return f"a matrix of shape {T.shape}"
    if not np.isfinite(T).all():
        return "a matrix with non-finite entries"
    if max(abs(T[3, 0]), abs(T[3, 1]), abs(T[3, 2]), abs(T[3, 3] - 1.0)) > 1e-9:
        return f"last row {T[3].tolist()}"
    err, det = _orthonormality(np.ascontiguousarray(T[:3, :3]))
    if err > tolerance or abs(det - 1) > tolerance:
        return f"a rotation part with |R R^T - I| = {err:.3g}, det {det:.9g}"
    return None


def check_extrinsic(name: str, T_BS) -> np.ndarray | None:
    """``T_BS`` as a 4x4 rigid transform (:func:`rigid_problem`), or None."""
    if T_BS is None:
        return None
    problem = rigid_problem(T_BS)
    if problem is not None:
        raise InputError(f"{name}: expected a 4x4 rigid transform, got {problem}")
    return np.asarray(T_BS, dtype=float)


def check_state(name: str, state) -> ImuState:
    """``state`` as one :class:`ImuState`: 3-vectors ``r``, ``v``, ``b_f``, ``b_w`` and a rotation
    matrix ``C``, all finite; an error naming the field otherwise."""
    if not isinstance(state, ImuState):
        raise InputError(f"{name}: expected an ImuState, got {type(state).__name__}")
    for field_name in ("r", "v", "b_f", "b_w"):
        check_array(f"{name}.{field_name}", getattr(state, field_name), (), 3)
    check_rotations(f"{name}.C", np.asarray(state.C, dtype=float)[None], 1)
    return state


def check_state_covariance(name: str, cov) -> np.ndarray:
    """``cov`` as one symmetric positive definite 15x15 error-state covariance."""
    cov = check_array(name, cov, (15,), 15)
    return check_covariances(name, cov[None], 1, 15)[0]


class Rows:
    """Shared by the row-wise data types: ``len()`` and ``subset(index)`` (every array field but
    the per-set extrinsic ``T_BS``, re-validated by the constructor)."""

    def __len__(self) -> int:
        return len(getattr(self, fields(self)[0].name))

    def subset(self, index):
        return type(self)(**{f.name: getattr(self, f.name) if f.name == "T_BS" or getattr(self, f.name) is None
                             else getattr(self, f.name)[index] for f in fields(self)})


#: The fewest IMU samples a recording can have, and why: the sampling interval (and with it the
#: noise of one step) is measured between two samples, and every estimator steps from one to the next.
MIN_IMU_SAMPLES = 2
MIN_IMU_SAMPLES_WHY = "the estimators step from one sample to the next and take the IMU's rate from their spacing"
#: The shortest IMU recording a loader accepts from a file (:func:`datasets.errors.require_imu_recording`),
#: and why. A :class:`Dataset` built in Python needs only :data:`MIN_IMU_SAMPLES`.
MIN_RECORDING_SAMPLES = 50
MIN_RECORDING_SECONDS = 1.0
MIN_RECORDING_WHY = ("the start's roll and pitch average the first half second of specific force, and the noise "
                     "figures, verdicts and checks of the IMU need many samples: on fewer they describe the noise "
                     "of a few samples")


@dataclass(frozen=True, eq=False)
class ImuSamples:
    """IMU samples: specific force ``acc`` [m/s^2] and angular rate ``gyro`` [rad/s] in the body
    frame at times ``t`` [s]. Sample ``k`` drives the Euler step over ``[t[k], t[k+1]]``.
    ``t_ns`` keeps integer nanosecond stamps where the source had them."""

    t: np.ndarray
    acc: np.ndarray
    gyro: np.ndarray
    t_ns: np.ndarray | None = None

    def __post_init__(self):
        t = check_times("ImuSamples.t", self.t)
        object.__setattr__(self, "t", t)
        object.__setattr__(self, "acc", check_array("ImuSamples.acc", self.acc, (3,), len(t), t))
        object.__setattr__(self, "gyro", check_array("ImuSamples.gyro", self.gyro, (3,), len(t), t))
        if self.t_ns is not None:
            t_ns = np.asarray(self.t_ns, dtype=np.int64)
            if t_ns.shape != t.shape:
                raise InputError(f"ImuSamples.t_ns: expected shape {t.shape}, got {t_ns.shape}")
            object.__setattr__(self, "t_ns", t_ns)

    def __len__(self) -> int:
        return len(self.t)

    def held(self, t) -> np.ndarray:
        """The index of the sample held at each time ``t`` (the last at or before it: the
        zero-order hold every estimator steps with; the first sample before the stream starts)."""
        return np.clip(np.searchsorted(self.t, t, side="right") - 1, 0, len(self.t) - 1)

    def slice(self, start: int, stop: int) -> "ImuSamples":
        return ImuSamples(
            self.t[start:stop], self.acc[start:stop], self.gyro[start:stop],
            None if self.t_ns is None else self.t_ns[start:stop],
        )


@dataclass(frozen=True, eq=False)
class PositionMeasurements(Rows):
    """World positions [m] (GPS-like) of the sensor's origin: ``r + C p_BS`` with ``p_BS`` from
    ``T_BS`` (None: at the IMU, ``r``); covariance ``cov`` (N, 3, 3) [m^2]."""

    t: np.ndarray
    position: np.ndarray
    cov: np.ndarray
    T_BS: np.ndarray | None = None

    def __post_init__(self):
        t = check_times("PositionMeasurements.t", self.t)
        object.__setattr__(self, "t", t)
        object.__setattr__(self, "position", _distances("PositionMeasurements.position", self.position, t))
        object.__setattr__(self, "cov", check_covariances("PositionMeasurements.cov", self.cov, len(t), 3))
        object.__setattr__(self, "T_BS", check_extrinsic("PositionMeasurements.T_BS", self.T_BS))



@dataclass(frozen=True, eq=False)
class OrientationMeasurements(Rows):
    """Attitudes of the sensor frame, ``C R_BS`` (``R_BS`` from ``T_BS``; None: the IMU's ``C``),
    with ``C_meas = exp(n) C R_BS`` (eqs. 62, 63), ``n ~ N(0, cov)`` [rad^2] in world coordinates."""

    t: np.ndarray
    C: np.ndarray
    cov: np.ndarray
    T_BS: np.ndarray | None = None

    def __post_init__(self):
        t = check_times("OrientationMeasurements.t", self.t)
        object.__setattr__(self, "t", t)
        object.__setattr__(self, "C", check_rotations("OrientationMeasurements.C", self.C, len(t)))
        object.__setattr__(self, "cov", check_covariances("OrientationMeasurements.cov", self.cov, len(t), 3))
        object.__setattr__(self, "T_BS", check_extrinsic("OrientationMeasurements.T_BS", self.T_BS))



@dataclass(frozen=True, eq=False)
class PoseMeasurements(Rows):
    """Pose-sensor readings (eqs. 61-63) of the sensor frame: position ``r + C p_BS`` [m] and
    attitude ``C R_BS`` (``T_BS`` None: the IMU's own pose); ``cov`` (N, 6, 6) over
    ``(n_p, n_Phi)`` (position first, world-frame orientation noise second)."""

    t: np.ndarray
    position: np.ndarray
    C: np.ndarray
    cov: np.ndarray
    T_BS: np.ndarray | None = None

    def __post_init__(self):
        t = check_times("PoseMeasurements.t", self.t)
        object.__setattr__(self, "t", t)
        object.__setattr__(self, "position", _distances("PoseMeasurements.position", self.position, t))
        object.__setattr__(self, "C", check_rotations("PoseMeasurements.C", self.C, len(t)))
        object.__setattr__(self, "cov", check_covariances("PoseMeasurements.cov", self.cov, len(t), 6))
        object.__setattr__(self, "T_BS", check_extrinsic("PoseMeasurements.T_BS", self.T_BS))


@dataclass(frozen=True, eq=False)
class VelocityMeasurements(Rows):
    """Linear velocity of the sensor frame in its own frame (wheel odometry's twist, a Doppler
    sensor): ``R_BS^T (v + (w - b_w) x p_BS)`` with ``v`` the body velocity and ``w`` (``gyro``,
    N x 3) the gyro sample at the measurement time (the lever arm's velocity); ``cov`` (N, 3, 3)
    [m^2/s^2]; ``T_BS`` None: the IMU's body velocity."""

    t: np.ndarray
    velocity: np.ndarray
    gyro: np.ndarray
    cov: np.ndarray
    T_BS: np.ndarray | None = None

    def __post_init__(self):
        t = check_times("VelocityMeasurements.t", self.t)
        object.__setattr__(self, "t", t)
        velocity = check_array("VelocityMeasurements.velocity", self.velocity, (3,), len(t), t)
        object.__setattr__(self, "velocity", check_magnitude("VelocityMeasurements.velocity", velocity,
                                                             MAX_PLAUSIBLE_SPEED, "m/s", t))
        gyro = check_array("VelocityMeasurements.gyro", self.gyro, (3,), len(t), t)
        object.__setattr__(self, "gyro", check_magnitude(
            "VelocityMeasurements.gyro", gyro, gyro_rate_limit(), "rad/s", t,
            "the IMU's gyro reading held at the measurement, for the lever arm: beyond a MEMS gyro's full scale, the "
            "IMU's gyro data are probably in deg/s"))
        object.__setattr__(self, "cov", check_covariances("VelocityMeasurements.cov", self.cov, len(t), 3))
        object.__setattr__(self, "T_BS", check_extrinsic("VelocityMeasurements.T_BS", self.T_BS))



@dataclass(frozen=True, eq=False)
class RelativePoseMeasurements(Rows):
    """Odometry between times ``t_from`` and ``t_to``: ``dr = C_i^T (r_j - r_i)`` [m] (in the body
    frame at ``t_from``) and ``dC = C_i^T C_j``; noise ``dC_meas = exp(n_Phi) dC``,
    ``dr_meas = dr + n_r`` with ``cov`` (N, 6, 6) over ``(n_r, n_Phi)``, both in frame ``i``.
    With ``T_BS`` the same of the sensor frame ``S`` (:func:`factors.sensor_models.odometry_residual`)."""

    t_from: np.ndarray
    t_to: np.ndarray
    dr: np.ndarray
    dC: np.ndarray
    cov: np.ndarray
    T_BS: np.ndarray | None = None

    def __post_init__(self):
        t_from = check_array("RelativePoseMeasurements.t_from", self.t_from, ())
        n = len(t_from)
        t_to = check_array("RelativePoseMeasurements.t_to", self.t_to, (), n)
        if np.any(t_to <= t_from):
            i = int(np.argmax(t_to <= t_from))
            raise InputError(f"RelativePoseMeasurements: row {i}: t_to ({t_to[i]}) must be after t_from ({t_from[i]})")
        object.__setattr__(self, "t_from", t_from)
        object.__setattr__(self, "t_to", t_to)
        object.__setattr__(self, "dr", _distances("RelativePoseMeasurements.dr", self.dr, t_to))
        object.__setattr__(self, "dC", check_rotations("RelativePoseMeasurements.dC", self.dC, n))
        object.__setattr__(self, "cov", check_covariances("RelativePoseMeasurements.cov", self.cov, n, 6))
        object.__setattr__(self, "T_BS", check_extrinsic("RelativePoseMeasurements.T_BS", self.T_BS))

    @property
    def t(self) -> np.ndarray:
        """The later time of each measurement (when it becomes available)."""
        return self.t_to


@dataclass(frozen=True, eq=False)
class Trajectory(Rows):
    """States over time: ``t`` (N,) and an :class:`ImuState` with leading dimension N. Biases are
    NaN where unknown (e.g. a TUM file or a ground truth without biases). ``cov`` optionally holds
    the (N, 15, 15) error-state covariances of an estimate (error-state order of
    ``factors.imu``)."""

    t: np.ndarray
    states: ImuState
    cov: np.ndarray | None = None

    def __post_init__(self):
        t = check_times("Trajectory.t", self.t)
        object.__setattr__(self, "t", t)
        n = len(t)
        s = self.states
        for name in ("r", "v", "b_f", "b_w"):
            a = getattr(s, name)
            if a.shape != (n, 3):
                raise InputError(f"Trajectory.states.{name}: expected shape ({n}, 3), got {a.shape}")
        check_rotations("Trajectory.states.C", s.C, n)
        if not (np.all(np.isfinite(s.r)) and np.all(np.isfinite(s.C))):
            raise InputError("Trajectory: positions and attitudes must be finite")
        if self.cov is not None:
            cov = np.asarray(self.cov, dtype=float)
            if cov.shape != (n, 15, 15):
                raise InputError(f"Trajectory.cov: expected shape ({n}, 15, 15), got {cov.shape}")
            object.__setattr__(self, "cov", check_covariances("Trajectory.cov", cov, n, 15))

    @property
    def position(self) -> np.ndarray:
        return self.states.r

    @property
    def C(self) -> np.ndarray:
        return self.states.C

    def interpolate(self, t, max_step: float | None = None) -> tuple[ImuState, np.ndarray | None, np.ndarray]:
        """The states (and covariances, element-wise linear) at times ``t``, and the mask of the
        ``t`` that lie in the trajectory's span (within :data:`SAME_INSTANT_S` of its ends) and, with
        ``max_step``, not inside a step between samples longer than it (a gap, never bridged); the
        returned states cover only those. A time within :data:`SAME_INSTANT_S` of a sample takes
        that sample as it is; otherwise positions, velocities and biases are interpolated
        linearly and the attitude along the geodesic ``exp(w log(C_b C_a^T)) C_a`` (primer
        [+]/[-], :mod:`factors.so3`), ``w`` the fraction of the step."""
        tt, s, cov = self.t, self.states, self.cov
        t = np.asarray(t, dtype=float)
        inside = (t >= tt[0] - SAME_INSTANT_S) & (t <= tt[-1] + SAME_INSTANT_S)
        if len(tt) == 1:
            k = np.zeros(int(inside.sum()), dtype=int)
            return s[k], None if cov is None else cov[k], inside
        a_all = np.clip(np.searchsorted(tt, t, side="right") - 1, 0, len(tt) - 2)
        b_all = a_all + 1
        near_all = np.where(np.abs(tt[a_all] - t) <= np.abs(tt[b_all] - t), a_all, b_all)
        exact_all = np.abs(tt[near_all] - t) <= SAME_INSTANT_S
        if max_step is not None:
            inside &= exact_all | (tt[b_all] - tt[a_all] <= max_step)
        tq, a, near, exact = t[inside], a_all[inside], near_all[inside], exact_all[inside]
        w = np.clip((tq - tt[a]) / (tt[a + 1] - tt[a]), 0.0, 1.0)
        b = np.where(exact, near, a + 1)
        a = np.where(exact, near, a)
        w = np.where(exact, 0.0, w)

        def lerp(x):
            shape = (-1,) + (1,) * (x.ndim - 1)
            return (1.0 - w.reshape(shape)) * x[a] + w.reshape(shape) * x[b]

        C = so3.boxplus(s.C[a], w[:, None] * so3.boxminus(s.C[b], s.C[a]))
        states = ImuState(r=lerp(s.r), v=lerp(s.v), C=C, b_f=lerp(s.b_f), b_w=lerp(s.b_w))
        return states, None if cov is None else lerp(cov), inside



@dataclass(frozen=True, eq=False)
class Sensor:
    """One aiding sensor's measurements: its ``name`` (unique in a dataset; metrics and plots use
    it), its ``kind`` (a name of :data:`datasets.kinds.KINDS`), the measurements used
    (``data``, that kind's data type) and those held out for evaluation (``heldout`` or None);
    ``calibrate``: what of its calibration the batch smoother estimates, about the ``T_BS`` and
    stamps of its data (a :class:`factors.calibration.CalibrationPrior`), or None;
    ``estimate_noise``: whether the batch smoother estimates its noise from the data (its
    covariances scaled per axis group, :mod:`smoother.batch.variance_components`);
    ``imu_stream``: where it reads the IMU's own messages (the IMU's bag topic: a ROS
    ``sensor_msgs/Imu``'s orientation), that stream as the rig names it, else None -- its
    measurements are then a filter's output on the same gyro and accelerometer, and their errors
    follow the IMU's; ``correlation_time``: None for errors independent from one measurement to the
    next, else the time constant [s] of errors that drift as a first-order Gauss-Markov process of
    the stated covariance (:mod:`smoother.model.correlated`; a kind of one state per measurement);
    ``fit_correlation_time``: whether that time constant is to be fitted to the held-out
    measurements before the run (``correlation_time`` then None; it needs held-out ones);
    ``tuned``: held-out measurements such a fit used (its tuning half, of ``data``'s type, or
    None), which neither the estimators use nor the run's held-out verdicts judge -- only their
    times are kept, as keyframes where held-out times are, so the run is the one the fit scored."""

    name: str
    kind: str
    data: object
    heldout: object = None
    calibrate: object = None
    estimate_noise: bool = False
    imu_stream: str | None = None
    correlation_time: float | None = None
    fit_correlation_time: bool = False
    tuned: object = None


@dataclass(frozen=True, eq=False)
class Dataset:
    """Everything an estimator needs: IMU samples, noise densities, gravity, an initial state with
    its 15x15 covariance, the aiding ``sensors`` (:class:`Sensor`: each named, of a kind of
    :data:`datasets.kinds.KINDS`, with its measurements used and held out) and, where known, the
    ground truth. The sensors are the one store of measurements: the built-in datasets, the
    simulator and a rig's recording all make named sensors.

    ``time_origin_ns``: where the data have a clock of their own (EuRoC's nanosecond stamps, a
    bag's header stamps since the epoch), its reading at ``t = 0``, in integer nanoseconds; times
    inside stay small (float64 keeps sub-microsecond steps) and outputs are written in the data's
    clock. None: the times are the data's own. ``estimate_imu_noise``: whether the batch smoother
    estimates the IMU's noise densities from the data (``noise`` then starts it)."""

    name: str
    imu: ImuSamples
    noise: ImuNoise
    initial: ImuState
    initial_cov: np.ndarray
    gravity: np.ndarray = field(default_factory=lambda: DEFAULT_GRAVITY.copy())
    sensors: tuple = ()
    truth: Trajectory | None = None
    time_origin_ns: int | None = None
    estimate_imu_noise: bool = False

    @property
    def noise_to_estimate(self) -> tuple[str, ...]:
        """What the data ask to have its noise estimated: ``"imu"`` and the sensors' names."""
        return ("imu",) * self.estimate_imu_noise + tuple(s.name for s in self.sensors if s.estimate_noise)

    def __post_init__(self):
        object.__setattr__(self, "initial_cov", check_state_covariance("Dataset.initial_cov", self.initial_cov))
        object.__setattr__(self, "gravity", check_array("Dataset.gravity", self.gravity, (), 3))
        if len(self.imu) < MIN_IMU_SAMPLES:
            raise InputError(f"Dataset.imu: at least {MIN_IMU_SAMPLES} IMU samples are needed ({MIN_IMU_SAMPLES_WHY})")
        check_state("Dataset.initial", self.initial)
        self._check_sensors()
        self._check_imu_gaps()
        self._check_imu_units()
        object.__setattr__(self, "sensors", tuple(self._sensor_inside_imu_span(s) for s in self.sensors))

    def _check_sensors(self) -> None:
        """``sensors`` is a sequence of :class:`Sensor` with usable names
        (:func:`datasets.ranges.sensor_name_problem`) used once."""
        if isinstance(self.sensors, Sensor) or not isinstance(self.sensors, (tuple, list)):
            raise InputError(f"Dataset.sensors: expected a tuple of Sensor, got {type(self.sensors).__name__}")
        names = []
        for i, s in enumerate(self.sensors):
            if not isinstance(s, Sensor):
                raise InputError(f"Dataset.sensors[{i}]: expected a Sensor, got {type(s).__name__}")
            problem = sensor_name_problem(s.name)
            if problem is not None:
                raise InputError(f"Dataset.sensors[{i}].name: {problem}")
            if s.name in names:
                raise InputError(f"sensor name {s.name!r} is used twice")
            problem = None if s.correlation_time is None else correlation_time_problem(s.correlation_time)
            if problem is not None:
                raise InputError(f"sensor {s.name!r}: correlation_time: {problem}")
            if s.fit_correlation_time and s.correlation_time is not None:
                raise InputError(f"sensor {s.name!r}: correlation_time: given ({s.correlation_time:g} s) and to be "
                                 "fitted; expected one of them")
            if s.fit_correlation_time and not (s.heldout is not None and len(s.heldout) and s.data is not None
                                               and len(s.data)):
                raise InputError(f"sensor {s.name!r}: correlation_time: fitting it needs measurements used and held "
                                 "out (every = K > 1): the used ones alone hardly tell it")
            names.append(s.name)
        object.__setattr__(self, "sensors", tuple(self.sensors))

    def sensor(self, name: str) -> Sensor:
        """The sensor called ``name``; an InputError listing the sensors there are else."""
        for s in self.sensors:
            if s.name == name:
                return s
        raise InputError(f"{self.name}: no sensor {name!r}; its sensors: {', '.join(self.sensor_names) or 'none'}")

    @property
    def sensor_names(self) -> tuple[str, ...]:
        return tuple(s.name for s in self.sensors)

    @property
    def correlation_times(self) -> dict[str, float]:
        """Per sensor whose errors drift, its ``correlation_time`` [s] (:attr:`Sensor.correlation_time`)."""
        return {s.name: s.correlation_time for s in self.sensors if s.correlation_time is not None}

    @property
    def correlation_to_fit(self) -> tuple[str, ...]:
        """The sensors whose correlation time is to be fitted (:attr:`Sensor.fit_correlation_time`)."""
        return tuple(s.name for s in self.sensors if s.fit_correlation_time)

    def with_sensor(self, name: str, **changes) -> "Dataset":
        """This dataset with the sensor ``name``'s fields changed (``data=``, ``heldout=``, ...;
        :func:`dataclasses.replace`); an InputError if there is no such sensor."""
        self.sensor(name)
        sensors = tuple(replace(s, **changes) if s.name == name else s for s in self.sensors)
        return replace(self, sensors=sensors)

    def _check_imu_units(self) -> None:
        """Warn when the specific force does not look like m/s^2 (a median far from |g|: data in g,
        or in mm/s^2); refuse angular rates no vehicle reaches (a 99th percentile beyond
        :data:`MAX_PLAUSIBLE_RATE`, or the limit of :func:`max_gyro_rate`): data in deg/s run on
        to a wrong estimate that looks like a result."""
        g = float(np.linalg.norm(self.gravity))
        f = float(np.median(np.linalg.norm(self.imu.acc, axis=1)))
        if g > 0 and not 0.3 * g <= f <= 3.0 * g:
            warnings.warn(f"Dataset.imu.acc: median specific-force magnitude {f:.4g}; expected about |g| = "
                          f"{g:.4g} in m/s^2 (is the data in g, or in mm/s^2?)", stacklevel=3)
        check_imu_rates("Dataset.imu.", self.imu.gyro)
        check_imu_range("Dataset.imu.", self.imu.t, self.imu.acc, self.imu.gyro)

    def _check_imu_gaps(self) -> None:
        """Warn about gaps in the IMU stream, refuse a clock jump (:func:`imu_gaps`)."""
        _, text = imu_gaps(self.imu.t)
        if text is not None:
            warnings.warn(text, stacklevel=3)

    def _sensor_inside_imu_span(self, sensor: Sensor) -> Sensor:
        """``sensor`` without the measurements outside the IMU span (warned about, as above); a
        sensor left with no measurement is an error naming it (nothing of it could be used). An empty
        set of measurements is none (``None``)."""
        t0, t1 = self.t0, self.t1
        parts = {}
        for part in ("data", "heldout"):
            m = getattr(sensor, part)
            if m is None or not len(m):  # none given: a sensor whose every measurement is held out, or none held out
                parts[part] = None
                continue
            first = getattr(m, "t_from", m.t)
            inside = (first >= t0) & (m.t <= t1)
            if not inside.any() and part == "data":
                raise InputError(f"sensor {sensor.name!r}: none of its {len(m)} measurements "
                                 f"([{first.min():.6f}, {m.t.max():.6f}] s) lies in the IMU span "
                                 f"[{t0:.6f}, {t1:.6f}] s (a time offset, or stamps in another clock?)")
            if not inside.all():
                warnings.warn(f"sensor {sensor.name!r}: {int((~inside).sum())} of {len(m)} {part} measurements "
                              f"lie outside the IMU span [{t0:.6f}, {t1:.6f}] s and are dropped", stacklevel=3)
            parts[part] = m if inside.all() else (m.subset(inside) if inside.any() else None)
        return replace(sensor, data=parts["data"], heldout=parts["heldout"])

    @property
    def t0(self) -> float:
        return float(self.imu.t[0])

    @property
    def t1(self) -> float:
        return float(self.imu.t[-1])

    def measurement_times(self) -> np.ndarray:
        """Sorted unique times of the sensors' measurements used (both ends of a relative one)."""
        data = [s.data for s in self.sensors if s.data is not None]
        parts = [m.t for m in data] + [m.t_from for m in data if hasattr(m, "t_from")]
        return np.unique(np.concatenate(parts)) if parts else np.zeros(0)
