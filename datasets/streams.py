"""Raw sensor streams as read from a recording, before they become measurements.

A stream is what one topic of a bag (or one CSV/TUM file) holds, in the sensor's own frames and
units, with no extrinsics, time offsets or datum applied: the readers (:mod:`datasets.bags`,
:mod:`datasets.csv_sources`) produce them and the rig glue turns them into measurements. IMU
readings are :class:`datasets.types.ImuSamples` (specific force and angular rate in the IMU frame).

Conventions shared by every stream:

* ``t`` (N,): header stamps (not receive times) in seconds since the Unix epoch, float64, strictly
  increasing. A float64 of that size resolves about 0.2 us; ``t_ns`` (N,) int64 holds the exact
  nanoseconds where the source has them (bags, EuRoC CSV), else None.
* ``cov``: covariances in the message's own order (below). A source may give a covariance for some
  rows and not for others (a driver publishing zeros until its filter converges): a row whose
  covariance is unknown is all NaN, and ``cov`` is None when no row has one. :func:`known_covariances`
  applies the rule readers use: a matrix that is all zero or not positive definite is unknown.
* Arrays only, no objects per sample. Every constructor validates shapes and values and raises
  ``ValueError`` naming the field.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from datasets.types import Rows, check_array, check_covariances, check_rotations, check_times
from factors.errors import InputError

#: ``sensor_msgs/NavSatStatus.STATUS_NO_FIX``: a fix with a status below this carries no position.
STATUS_NO_FIX = -1


def seconds(t_ns) -> np.ndarray:
    """Integer nanoseconds since the epoch as float seconds, ``sec + nsec * 1e-9`` (the whole
    seconds are exact in float64, so the result is within one rounding of the true value)."""
    t_ns = np.asarray(t_ns, dtype=np.int64)
    sec, nsec = np.divmod(t_ns, 1_000_000_000)
    return sec.astype(float) + nsec * 1e-9


def known_covariances(cov) -> np.ndarray | None:
    """Covariances ``(N, d, d)`` with the unknown ones replaced by NaN: a matrix that is all
    zero (ROS's "not given"), contains NaN, or is not symmetric positive definite is unknown.
    None if none is known."""
    cov = np.array(cov, dtype=float)
    usable = np.all(np.isfinite(cov), axis=(1, 2)) & np.any(cov != 0, axis=(1, 2))
    usable &= np.all(np.abs(cov - np.swapaxes(cov, 1, 2)) <= 1e-9 * np.abs(cov).max(axis=(1, 2), keepdims=True)
                     + 1e-300, axis=(1, 2))
    if usable.any():
        ok = np.flatnonzero(usable)
        eig_min = np.linalg.eigvalsh(cov[ok]).min(axis=1)
        usable[ok[eig_min <= 0]] = False
    if not usable.any():
        return None
    cov[~usable] = np.nan
    return cov


def _stamps(name: str, t_ns, n: int) -> np.ndarray | None:
    if t_ns is None:
        return None
    t_ns = np.asarray(t_ns)
    if t_ns.shape != (n,) or not np.issubdtype(t_ns.dtype, np.integer):
        raise InputError(f"{name}: expected {n} integer nanosecond stamps, got shape {t_ns.shape} of {t_ns.dtype}")
    return t_ns.astype(np.int64)


def _optional_covariances(name: str, cov, n: int, dim: int) -> np.ndarray | None:
    """None, or ``(n, dim, dim)`` covariances whose rows are valid or all NaN (unknown); None
    when every row is unknown."""
    if cov is None:
        return None
    cov = np.array(cov, dtype=float)
    if cov.shape != (n, dim, dim):
        raise InputError(f"{name}: expected shape ({n}, {dim}, {dim}), got {cov.shape}")
    unknown = np.all(np.isnan(cov), axis=(1, 2))
    if unknown.all():
        return None
    check_covariances(name, cov[~unknown], int((~unknown).sum()), dim)
    return cov


@dataclass(frozen=True, eq=False)
class PoseStream(Rows):
    """Poses of a message's child frame in its parent frame (``nav_msgs/Odometry``,
    ``geometry_msgs/PoseStamped``, ``PoseWithCovarianceStamped``, ``TransformStamped``, TUM or
    CSV files): ``position`` (N, 3) [m] of the child's origin in the parent frame and ``C``
    (N, 3, 3) the child-to-parent rotation (what the project calls ``C(Phi)`` for a body).

    ``cov`` (N, 6, 6) is over ``(position, rotation)``, ROS's ``x y z rotX rotY rotZ``. The
    rotation noise is read as a small angle in the PARENT (world) frame: ``C_meas = exp(n) C``,
    the primer's left perturbation used throughout the project (ROS does not pin down the frame of
    ``rotX rotY rotZ``; for the small, near-isotropic angles of real covariances the choice hardly
    matters, and a rig's ``sigma`` can override it)."""

    t: np.ndarray
    position: np.ndarray
    C: np.ndarray
    cov: np.ndarray | None = None
    t_ns: np.ndarray | None = None

    def __post_init__(self):
        t = check_times("PoseStream.t", self.t)
        n = len(t)
        object.__setattr__(self, "t", t)
        object.__setattr__(self, "position", check_array("PoseStream.position", self.position, (3,), n))
        object.__setattr__(self, "C", check_rotations("PoseStream.C", self.C, n))
        object.__setattr__(self, "cov", _optional_covariances("PoseStream.cov", self.cov, n, 6))
        object.__setattr__(self, "t_ns", _stamps("PoseStream.t_ns", self.t_ns, n))


@dataclass(frozen=True, eq=False)
class PositionStream(Rows):
    """Positions of a frame's origin in the world, without its attitude (a position CSV file, or
    the positions of any pose source): ``position`` (N, 3) [m], ``cov`` (N, 3, 3) [m^2]."""

    t: np.ndarray
    position: np.ndarray
    cov: np.ndarray | None = None
    t_ns: np.ndarray | None = None

    def __post_init__(self):
        t = check_times("PositionStream.t", self.t)
        n = len(t)
        object.__setattr__(self, "t", t)
        object.__setattr__(self, "position", check_array("PositionStream.position", self.position, (3,), n))
        object.__setattr__(self, "cov", _optional_covariances("PositionStream.cov", self.cov, n, 3))
        object.__setattr__(self, "t_ns", _stamps("PositionStream.t_ns", self.t_ns, n))

    @classmethod
    def of_poses(cls, poses: PoseStream) -> "PositionStream":
        """The positions of ``poses`` with the position block of their covariances."""
        return cls(poses.t, poses.position, None if poses.cov is None else poses.cov[:, :3, :3], poses.t_ns)


@dataclass(frozen=True, eq=False)
class AttitudeStream(Rows):
    """Attitudes of a frame in the world: ``C`` (N, 3, 3) the frame-to-world rotation, as the
    attitude part of a :class:`PoseStream` or the ``orientation`` of ``sensor_msgs/Imu`` (REP-145:
    the attitude of the message's frame in an east-north-up world). ``cov`` (N, 3, 3) [rad^2] is
    over a small rotation about the world's fixed ``x, y, z`` axes, ``C_meas = exp(n) C`` (the
    primer's left perturbation; ``orientation_covariance``'s "row major about x, y, z axes")."""

    t: np.ndarray
    C: np.ndarray
    cov: np.ndarray | None = None
    t_ns: np.ndarray | None = None

    def __post_init__(self):
        t = check_times("AttitudeStream.t", self.t)
        n = len(t)
        object.__setattr__(self, "t", t)
        object.__setattr__(self, "C", check_rotations("AttitudeStream.C", self.C, n))
        object.__setattr__(self, "cov", _optional_covariances("AttitudeStream.cov", self.cov, n, 3))
        object.__setattr__(self, "t_ns", _stamps("AttitudeStream.t_ns", self.t_ns, n))

    @classmethod
    def of_poses(cls, poses: PoseStream) -> "AttitudeStream":
        """The attitudes of ``poses`` with the rotation block of their covariances."""
        return cls(poses.t, poses.C, None if poses.cov is None else poses.cov[:, 3:, 3:], poses.t_ns)


@dataclass(frozen=True, eq=False)
class TwistStream(Rows):
    """Velocities of a frame expressed in that frame (``nav_msgs/Odometry``'s twist is in the
    child frame): ``linear`` (N, 3) [m/s] and ``angular`` (N, 3) [rad/s], or None where the
    source has no angular rate (a CSV file with velocities only).

    ``cov`` is over ``(linear, angular)`` (N, 6, 6) -- ROS's ``vx vy vz wx wy wz`` -- or over
    ``linear`` alone (N, 3, 3) when ``angular`` is None; ``cov[:, :3, :3]`` is the linear
    velocity's covariance in both cases."""

    t: np.ndarray
    linear: np.ndarray
    angular: np.ndarray | None = None
    cov: np.ndarray | None = None
    t_ns: np.ndarray | None = None

    def __post_init__(self):
        t = check_times("TwistStream.t", self.t)
        n = len(t)
        object.__setattr__(self, "t", t)
        object.__setattr__(self, "linear", check_array("TwistStream.linear", self.linear, (3,), n))
        if self.angular is not None:
            object.__setattr__(self, "angular", check_array("TwistStream.angular", self.angular, (3,), n))
        dim = 3 if self.angular is None else 6
        object.__setattr__(self, "cov", _optional_covariances("TwistStream.cov", self.cov, n, dim))
        object.__setattr__(self, "t_ns", _stamps("TwistStream.t_ns", self.t_ns, n))


@dataclass(frozen=True, eq=False)
class PressureStream(Rows):
    """Static pressures (``sensor_msgs/FluidPressure``, a barometer): ``pressure`` (N,) [Pa],
    finite and > 0, with ``variance`` (N,) [Pa^2] (NaN where unknown; None when no row has one:
    ROS's 0 is "unknown")."""

    t: np.ndarray
    pressure: np.ndarray
    variance: np.ndarray | None = None
    t_ns: np.ndarray | None = None

    def __post_init__(self):
        t = check_times("PressureStream.t", self.t)
        n = len(t)
        object.__setattr__(self, "t", t)
        pressure = check_array("PressureStream.pressure", self.pressure, (), n)
        if np.any(pressure <= 0):
            i = int(np.flatnonzero(pressure <= 0)[0])
            raise InputError(f"PressureStream.pressure: row {i}: {float(pressure[i])!r} Pa; expected a pressure > 0")
        object.__setattr__(self, "pressure", pressure)
        if self.variance is not None:
            variance = np.array(self.variance, dtype=float)
            if variance.shape != (n,):
                raise InputError(f"PressureStream.variance: expected shape ({n},), got {variance.shape}")
            variance[~(variance > 0)] = np.nan  # 0 (ROS's "unknown"), negative or NaN
            object.__setattr__(self, "variance", None if np.isnan(variance).all() else variance)
        object.__setattr__(self, "t_ns", _stamps("PressureStream.t_ns", self.t_ns, n))


@dataclass(frozen=True, eq=False)
class MagneticFieldStream(Rows):
    """Magnetic fields measured in the sensor's frame (``sensor_msgs/MagneticField``, a
    magnetometer): ``field`` (N, 3) [T], finite and not zero; ``cov`` (N, 3, 3) [T^2] in the
    sensor frame (NaN rows unknown; None when no row has one)."""

    t: np.ndarray
    field: np.ndarray
    cov: np.ndarray | None = None
    t_ns: np.ndarray | None = None

    def __post_init__(self):
        t = check_times("MagneticFieldStream.t", self.t)
        n = len(t)
        object.__setattr__(self, "t", t)
        field = check_array("MagneticFieldStream.field", self.field, (3,), n)
        zero = np.flatnonzero(np.linalg.norm(field, axis=1) == 0)
        if zero.size:
            raise InputError(f"MagneticFieldStream.field: row {int(zero[0])}: a zero field; expected a measured field")
        object.__setattr__(self, "field", field)
        object.__setattr__(self, "cov", _optional_covariances("MagneticFieldStream.cov", self.cov, n, 3))
        object.__setattr__(self, "t_ns", _stamps("MagneticFieldStream.t_ns", self.t_ns, n))


@dataclass(frozen=True, eq=False)
class FixStream(Rows):
    """GNSS fixes (``sensor_msgs/NavSatFix``): ``latitude``, ``longitude`` [deg] and
    ``altitude`` [m] above the WGS-84 ellipsoid, each (N,); ``status`` (N,) int, ``NavSatStatus``'s
    values (-1 no fix, 0 fix, 1 SBAS, 2 GBAS). Fixes with ``status < 0`` may hold anything,
    NaN included (drivers publish NaN without a fix): :func:`datasets.gnss.fixes_to_enu` drops
    them; the others must be finite, with ``|latitude| <= 90`` and ``|longitude| <= 180``.

    ``cov`` (N, 3, 3) [m^2] is in the local East-North-Up frame at the fix, as ROS defines
    ``position_covariance``."""

    t: np.ndarray
    latitude: np.ndarray
    longitude: np.ndarray
    altitude: np.ndarray
    status: np.ndarray
    cov: np.ndarray | None = None
    t_ns: np.ndarray | None = None

    def __post_init__(self):
        t = check_times("FixStream.t", self.t)
        n = len(t)
        object.__setattr__(self, "t", t)
        status = np.asarray(self.status)
        if status.shape != (n,) or not np.issubdtype(status.dtype, np.integer):
            raise InputError(f"FixStream.status: expected {n} integers, got shape {status.shape} of {status.dtype}")
        status = status.astype(np.int64)
        object.__setattr__(self, "status", status)
        valid = status > STATUS_NO_FIX
        for name, limit in (("latitude", 90.0), ("longitude", 180.0), ("altitude", None)):
            value = np.asarray(getattr(self, name), dtype=float)
            if value.shape != (n,):
                raise InputError(f"FixStream.{name}: expected shape ({n},), got {value.shape}")
            bad = valid & ~np.isfinite(value)
            if bad.any():
                i = int(np.flatnonzero(bad)[0])
                raise InputError(f"FixStream.{name}: non-finite value at row {i}, a fix of status {status[i]}")
            if limit is not None and np.any(np.abs(value[valid]) > limit):
                i = int(np.flatnonzero(valid & (np.abs(np.nan_to_num(value)) > limit))[0])
                raise InputError(f"FixStream.{name}: row {i}: {float(value[i])!r} is beyond +-{limit:g} degrees")
            object.__setattr__(self, name, value)
        object.__setattr__(self, "cov", _optional_covariances("FixStream.cov", self.cov, n, 3))
        object.__setattr__(self, "t_ns", _stamps("FixStream.t_ns", self.t_ns, n))
