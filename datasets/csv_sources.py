"""Sensor streams from CSV files: the EuRoC/ASL layouts and one generic layout per stream.

IMU samples: the EuRoC/ASL ``imu0/data.csv`` layout only (``#timestamp [ns],w_RS_S_x,w_RS_S_y,
w_RS_S_z,a_RS_S_x,a_RS_S_y,a_RS_S_z``; read by :func:`datasets.euroc.read_imu_csv`, which finds the
columns by name); times in integer nanoseconds since the epoch, kept exactly in ``t_ns``.

Poses, positions and attitudes: the EuRoC/ASL ``state_groundtruth_estimate0/data.csv`` layout
(``#timestamp,p_RS_R_x,...,q_RS_w,q_RS_x,q_RS_y,q_RS_z,...``; velocities and biases are ignored)
or the generic layouts below. A file whose header has a column ``t`` is generic; any other is
read as EuRoC/ASL.

Generic layouts: comma separated, the first non-blank line a header naming the columns (a
leading ``#`` is allowed), in any order; ``t`` in seconds (since the epoch, or any origin shared
by the rig's streams); blank lines and lines starting with ``#`` after the header are ignored.
Optional columns come as a whole group or not at all; ``sigma_*`` are standard deviations (> 0)
that make a diagonal covariance:

============  ==========================  ===============================================
stream        required columns            optional groups
============  ==========================  ===============================================
poses         ``t,x,y,z,qw,qx,qy,qz``     ``sigma_x,sigma_y,sigma_z`` with
                                          ``sigma_rx,sigma_ry,sigma_rz`` [m, rad]
positions     ``t,x,y,z``                 ``sigma_x,sigma_y,sigma_z`` [m]; a pose file's
                                          ``qw,qx,qy,qz`` and ``sigma_r*`` (not used)
attitudes     ``t,qw,qx,qy,qz``           ``sigma_rx,sigma_ry,sigma_rz`` [rad]; a pose
                                          file's ``x,y,z`` and ``sigma_x..z`` (not used)
velocities    ``t,vx,vy,vz``              ``wx,wy,wz`` [rad/s]; ``sigma_vx,sigma_vy,sigma_vz``
                                          (and ``sigma_wx,sigma_wy,sigma_wz`` with ``wx..``)
GNSS fixes    ``t,latitude,longitude,     ``status`` (integer, NavSatStatus: -1 no fix, 0 fix;
              altitude``                  default 0); ``sigma_e,sigma_n,sigma_u`` [m]
pressures     ``t,pressure`` [Pa]         ``sigma_pressure`` [Pa]
magnetic      ``t,mx,my,mz`` [T]          ``sigma_mx,sigma_my,sigma_mz`` [T]
fields
============  ==========================  ===============================================

Poses: ``(x, y, z)`` the position [m] of the sensor frame in its world frame, ``(qw, qx, qy, qz)``
the Hamilton quaternion of the sensor-to-world rotation, norm 1 within
:data:`QUATERNION_TOLERANCE` (then normalised). Positions and attitudes are read from the columns
they use only: a pose file gives both, a file of positions or of attitudes alone gives its own.
Velocities: of the sensor frame, in the sensor frame [m/s]. Fixes: degrees and metres above the
WGS-84 ellipsoid; every value must be a finite number, also in rows with ``status < 0`` (which
:func:`datasets.gnss.fixes_to_enu` drops). See :mod:`datasets.streams` for the stream types.

Every malformed file is one :class:`datasets.errors.DataError` naming the file, line and column.
"""
from __future__ import annotations

from pathlib import Path

import numpy as np

from datasets import euroc
from datasets.errors import DataError, check_increasing, check_unit_quaternions, read_lines, read_table
from datasets.ranges import SIGMA_RANGES
from datasets.streams import (
    AttitudeStream,
    FixStream,
    MagneticFieldStream,
    PoseStream,
    PositionStream,
    PressureStream,
    TwistStream,
    seconds,
)
from datasets.types import ImuSamples
from factors import quaternion

#: Accepted deviation of a quaternion's norm from 1 before it is normalised.
QUATERNION_TOLERANCE = 1e-3

POSITION_COLUMNS = ["t", "x", "y", "z"]
ATTITUDE_COLUMNS = ["t", "qw", "qx", "qy", "qz"]
POSE_COLUMNS = POSITION_COLUMNS + ATTITUDE_COLUMNS[1:]
POSITION_SIGMAS = ["sigma_x", "sigma_y", "sigma_z"]
ROTATION_SIGMAS = ["sigma_rx", "sigma_ry", "sigma_rz"]
POSE_SIGMAS = POSITION_SIGMAS + ROTATION_SIGMAS
VELOCITY_COLUMNS = ["t", "vx", "vy", "vz"]
ANGULAR_COLUMNS = ["wx", "wy", "wz"]
VELOCITY_SIGMAS = ["sigma_vx", "sigma_vy", "sigma_vz"]
ANGULAR_SIGMAS = ["sigma_wx", "sigma_wy", "sigma_wz"]
FIX_COLUMNS = ["t", "latitude", "longitude", "altitude"]
FIX_SIGMAS = ["sigma_e", "sigma_n", "sigma_u"]
PRESSURE_COLUMNS = ["t", "pressure"]
PRESSURE_SIGMAS = ["sigma_pressure"]
MAGNETIC_COLUMNS = ["t", "mx", "my", "mz"]
MAGNETIC_SIGMAS = ["sigma_mx", "sigma_my", "sigma_mz"]


def _header(path: Path, lines: list[str]) -> tuple[int, list[str]]:
    """(0-based index, column names) of the first non-blank line."""
    first = next((i for i, text in enumerate(lines) if text.strip()), None)
    if first is None:
        raise DataError(path, max(len(lines), 1), None, "an empty file", "a header line naming the columns")
    return first, [name.strip() for name in lines[first].strip().lstrip("#").split(",")]


def _generic(path: Path, required: list[str], groups: list[list[str]], what: str) -> dict:
    """The columns of a generic-layout file by name (absent optional groups left out),
    ``"lines"``: the 1-based line of each row, and ``"header_line"``."""
    lines = read_lines(path)
    index, names = _header(path, lines)
    line = index + 1
    allowed = required + [name for group in groups for name in group]
    for name in names:
        if name not in allowed:
            raise DataError(path, line, name, "an unknown column", f"columns among {', '.join(allowed)}")
        if names.count(name) > 1:
            raise DataError(path, line, name, "this column twice", "each column once")
    for name in required:
        if name not in names:
            raise DataError(path, line, name, "a header without this column", f"a column named {name}")
    for group in groups:
        present = [name for name in group if name in names]
        if present and len(present) < len(group):
            missing = next(name for name in group if name not in names)
            raise DataError(path, line, missing, f"a header with {', '.join(present)} but not {missing}",
                            f"all of {', '.join(group)} or none")
    values, rows = read_table(path, lines, names, 1, what, delimiter=",", skip=index + 1)
    columns = {name: values[:, j] for j, name in enumerate(names)}
    check_increasing(path, columns["t"], rows, "t")
    for name in names:
        if name.startswith("sigma_") and np.any(columns[name] <= 0):
            i = int(np.flatnonzero(columns[name] <= 0)[0])
            raise DataError(path, int(rows[i]), name, repr(float(columns[name][i])), "a standard deviation > 0")
        if name in SIGMA_UNITS:  # a sigma in the rig's units lies in the rig's range for them
            plausible = SIGMA_RANGES[SIGMA_UNITS[name]]
            beyond = ~((columns[name] >= plausible.low) & (columns[name] <= plausible.high))
        elif name.startswith("sigma_"):  # Pa, T, rad/s: a square that is a number (no overflow, no 0)
            plausible = None
            beyond = ~((columns[name] >= SQUARABLE[0]) & (columns[name] <= SQUARABLE[1]))
        else:
            continue
        if beyond.any():
            i = int(np.flatnonzero(beyond)[0])
            expected = (f"a standard deviation within {plausible.text()} ({plausible.why})" if plausible is not None
                        else f"a standard deviation within [{SQUARABLE[0]:g}, {SQUARABLE[1]:g}] (its square a number)")
            raise DataError(path, int(rows[i]), name, repr(float(columns[name][i])), expected)
    columns["lines"], columns["header_line"] = rows, line
    return columns


#: The unit of each ``sigma_*`` column whose unit a rig's ``sigma`` has, and so its range
#: (:data:`datasets.ranges.SIGMA_RANGES`): a position's 1e-12 m made every estimator fail on
#: numbers double precision cannot hold, 1e300 overflowed when squared.
SIGMA_UNITS = {**dict.fromkeys(POSITION_SIGMAS + FIX_SIGMAS, "m"), **dict.fromkeys(ROTATION_SIGMAS, "rad"),
               **dict.fromkeys(VELOCITY_SIGMAS, "m/s")}
#: Where the other ``sigma_*`` columns (Pa, T, rad/s) must lie: their squares are numbers.
SQUARABLE = (1e-150, 1e150)


def _diagonal(columns: dict, names: list[str]) -> np.ndarray | None:
    if names[0] not in columns:
        return None
    sigma = np.stack([columns[name] for name in names], axis=1)
    return np.einsum("ni,ij->nij", sigma**2, np.eye(len(names)))


def _is_generic(path: Path) -> bool:
    lines = read_lines(path)
    return "t" in _header(path, lines)[1]


def read_csv_imu(path) -> ImuSamples:
    """IMU samples of an EuRoC/ASL ``data.csv`` (see the module docstring)."""
    t_ns, acc, gyro = euroc.read_imu_csv(path)
    return ImuSamples(seconds(t_ns), acc, gyro, t_ns=t_ns)


def read_csv_poses(path) -> PoseStream:
    """Poses of a generic pose file or an EuRoC/ASL ground-truth file."""
    path = Path(path)
    if not _is_generic(path):
        gt = euroc.read_groundtruth_csv(path)
        return PoseStream(seconds(gt.t_ns), gt.p, quaternion.to_matrix(gt.q), None, gt.t_ns)
    c = _generic(path, POSE_COLUMNS, [POSE_SIGMAS], "pose lines (" + ",".join(POSE_COLUMNS) + ")")
    position = np.stack([c["x"], c["y"], c["z"]], axis=1)
    return PoseStream(c["t"], position, _rotations(path, c), _diagonal(c, POSE_SIGMAS))


def _rotations(path: Path, columns: dict) -> np.ndarray:
    """The rotations of the quaternion columns ``qw qx qy qz``, each of norm 1 within
    :data:`QUATERNION_TOLERANCE`."""
    q = np.stack([columns[name] for name in ATTITUDE_COLUMNS[1:]], axis=1)
    q = check_unit_quaternions(path, q, columns["lines"], "qw qx qy qz", QUATERNION_TOLERANCE)
    return quaternion.to_matrix(q)


def read_csv_positions(path) -> PositionStream:
    """Positions of a generic position (or pose) file, or of an EuRoC/ASL ground-truth file."""
    path = Path(path)
    if not _is_generic(path):
        return PositionStream.of_poses(read_csv_poses(path))
    c = _generic(path, POSITION_COLUMNS, [ATTITUDE_COLUMNS[1:], POSITION_SIGMAS, ROTATION_SIGMAS],
                 "position lines (" + ",".join(POSITION_COLUMNS) + ")")
    return PositionStream(c["t"], np.stack([c["x"], c["y"], c["z"]], axis=1), _diagonal(c, POSITION_SIGMAS))


def read_csv_attitudes(path) -> AttitudeStream:
    """Attitudes of a generic attitude (or pose) file, or of an EuRoC/ASL ground-truth file."""
    path = Path(path)
    if not _is_generic(path):
        return AttitudeStream.of_poses(read_csv_poses(path))
    c = _generic(path, ATTITUDE_COLUMNS, [POSITION_COLUMNS[1:], ROTATION_SIGMAS, POSITION_SIGMAS],
                 "attitude lines (" + ",".join(ATTITUDE_COLUMNS) + ")")
    return AttitudeStream(c["t"], _rotations(path, c), _diagonal(c, ROTATION_SIGMAS))


def read_csv_twists(path) -> TwistStream:
    """Velocities (and optionally angular rates) of a generic velocity file."""
    path = Path(path)
    c = _generic(path, VELOCITY_COLUMNS, [ANGULAR_COLUMNS, VELOCITY_SIGMAS, ANGULAR_SIGMAS],
                 "velocity lines (" + ",".join(VELOCITY_COLUMNS) + ")")
    angular = np.stack([c[name] for name in ANGULAR_COLUMNS], axis=1) if "wx" in c else None
    has_sigma_v, has_sigma_w = "sigma_vx" in c, "sigma_wx" in c
    if has_sigma_w != (angular is not None and has_sigma_v):
        raise DataError(path, c["header_line"], "sigma_wx" if has_sigma_w else "sigma_vx",
                        "standard deviations for only some of the velocity components",
                        "sigma_v* and sigma_w* together with wx,wy,wz; sigma_v* alone without them")
    sigmas = VELOCITY_SIGMAS + (ANGULAR_SIGMAS if angular is not None else [])
    linear = np.stack([c[name] for name in ("vx", "vy", "vz")], axis=1)
    return TwistStream(c["t"], linear, angular, _diagonal(c, sigmas))


def read_csv_fixes(path) -> FixStream:
    """GNSS fixes of a generic fix file."""
    path = Path(path)
    c = _generic(path, FIX_COLUMNS, [["status"], FIX_SIGMAS], "fix lines (" + ",".join(FIX_COLUMNS) + ")")
    if "status" in c:
        whole = c["status"] == np.round(c["status"])
        if not whole.all():
            i = int(np.flatnonzero(~whole)[0])
            raise DataError(path, int(c["lines"][i]), "status", repr(float(c["status"][i])), "an integer")
    for name, limit in (("latitude", 90.0), ("longitude", 180.0)):
        beyond = np.abs(c[name]) > limit
        if beyond.any():
            i = int(np.flatnonzero(beyond)[0])
            raise DataError(path, int(c["lines"][i]), name, repr(float(c[name][i])), f"degrees within +-{limit:g}")
    status = c.get("status", np.zeros(len(c["t"]))).astype(np.int64)
    return FixStream(c["t"], c["latitude"], c["longitude"], c["altitude"], status, _diagonal(c, FIX_SIGMAS))


def read_csv_pressures(path) -> PressureStream:
    """Pressures of a generic pressure file (a barometer)."""
    path = Path(path)
    c = _generic(path, PRESSURE_COLUMNS, [PRESSURE_SIGMAS], "pressure lines (" + ",".join(PRESSURE_COLUMNS) + ")")
    bad = np.flatnonzero(c["pressure"] <= 0)
    if bad.size:
        raise DataError(path, int(c["lines"][bad[0]]), "pressure", repr(float(c["pressure"][bad[0]])),
                        "a pressure > 0 in pascals")
    return PressureStream(c["t"], c["pressure"], c["sigma_pressure"] ** 2 if "sigma_pressure" in c else None)


def read_csv_magnetic_fields(path) -> MagneticFieldStream:
    """Magnetic fields of a generic magnetometer file."""
    path = Path(path)
    c = _generic(path, MAGNETIC_COLUMNS, [MAGNETIC_SIGMAS], "magnetic field lines (" + ",".join(MAGNETIC_COLUMNS) + ")")
    field = np.stack([c[name] for name in ("mx", "my", "mz")], axis=1)
    zero = np.flatnonzero(np.linalg.norm(field, axis=1) == 0)
    if zero.size:
        raise DataError(path, int(c["lines"][zero[0]]), "mx,my,mz", "a zero field", "a measured field (not all zero)")
    return MagneticFieldStream(c["t"], field, _diagonal(c, MAGNETIC_SIGMAS))
