"""Reading sensor streams from ROS bags with the ``rosbags`` library (no ROS installation).

Formats (chosen by the path): a ROS 1 ``.bag`` file; a ROS 2 bag folder (with its
``metadata.yaml``), or one of its storage files on its own, ``.db3`` (sqlite3) or ``.mcap``.
Message definitions come from the bag; a ROS 2 storage file without them is decoded with the
standard ROS 2 Humble definitions.

Messages and what they give (:mod:`datasets.streams` for the stream types and conventions):

* ``sensor_msgs/msg/Imu`` -> :class:`datasets.types.ImuSamples`: ``linear_acceleration`` as
  ``acc``, ``angular_velocity`` as ``gyro`` (the covariances are ignored); and, read as
  attitudes, :class:`AttitudeStream`: ``orientation`` (REP-145: the attitude of the message's
  frame in an east-north-up world) with ``orientation_covariance`` (row major, a small rotation
  about the world's fixed x, y, z axes: ``C_meas = exp(n) C``, the primer's left perturbation).
  A first covariance element of -1 is REP-145's "this IMU gives no orientation": such a topic is
  refused as attitudes.
* ``nav_msgs/msg/Odometry`` -> :class:`PoseStream` (``pose.pose`` with ``pose.covariance``) or
  :class:`TwistStream` (``twist.twist`` with ``twist.covariance``, in the child frame).
* ``geometry_msgs/msg/TwistWithCovarianceStamped`` and ``TwistStamped`` -> :class:`TwistStream`
  (the twist in the header's frame, the sensor's: a GNSS receiver's velocity, a DVL; the latter
  without covariance).
* ``geometry_msgs/msg/PoseWithCovarianceStamped``, ``PoseStamped`` and ``TransformStamped`` ->
  :class:`PoseStream` (the last two without covariance); every pose message also gives
  attitudes (:class:`AttitudeStream`, the rotation block of its covariance).
* ``sensor_msgs/msg/NavSatFix`` -> :class:`FixStream`. ``position_covariance`` is ENU, row major;
  ``position_covariance_type`` is read per message: 0 (unknown) makes that fix's covariance
  unknown (a NaN row), 2 (diagonal known) keeps the diagonal only, 1 (approximated) and 3 (known)
  keep the whole matrix. A stream mixing known and unknown rows keeps both, row by row.

* ``sensor_msgs/msg/FluidPressure`` -> :class:`PressureStream` (``fluid_pressure`` [Pa] with
  ``variance``, 0 meaning unknown).
* ``sensor_msgs/msg/MagneticField`` -> :class:`MagneticFieldStream` (``magnetic_field`` [T] in
  the header's frame with ``magnetic_field_covariance``, row major; all zero: unknown).

Times are HEADER stamps, not the times the recorder received the messages. Messages are taken
in the order the bag stores them (the recorder's receive times), never re-sorted, and their
stamps must increase strictly in that order: the rule of the CSV readers
(:func:`datasets.errors.check_increasing`), so that a clock stepping back or a repeated stamp is
an error naming the bag, the topic, the message and both stamps. A covariance that is all zero
or not positive definite counts as unknown for its message
(:func:`datasets.streams.known_covariances`); ``cov`` is None when no message of the stream has
one. Quaternions must have norm 1 within :data:`QUATERNION_TOLERANCE` and are normalised.

Before ``rosbags`` opens anything, the files it will read are checked
(:func:`datasets.errors.check_source`): a bag file, or a ROS 2 folder's ``metadata.yaml``
(read within the YAML limits) and the storage files it lists, must be regular files within the
size limit of bags; a named pipe or a device would block or never end.

Errors are :class:`datasets.errors.DataError` naming the bag and the topic: a missing or unreadable
bag, one that is not a regular file or beyond the size limit, a damaged one (anything rosbags
raises while reading or deserialising a message, or fewer messages than the bag's index lists), a
topic that is not in the bag (the message lists the topics present with their types), a topic of
another message type than the stream asked for (both named), an empty topic, stamps out of order,
an IMU topic shorter than :func:`datasets.errors.require_imu_recording` asks, a bad quaternion or
non-finite values.
"""
from __future__ import annotations

import contextlib
import os
from pathlib import Path, PurePath

import numpy as np
from rosbags.highlevel import AnyReader
from rosbags.typesys import Stores, get_typestore

from datasets.errors import (
    DataError,
    check_increasing,
    check_name,
    check_source,
    read_source,
    require_imu_recording,
)
from datasets.streams import (
    STATUS_NO_FIX,
    AttitudeStream,
    FixStream,
    MagneticFieldStream,
    PoseStream,
    PressureStream,
    TwistStream,
    known_covariances,
    seconds,
)
from datasets.types import ImuSamples
from datasets.yamlfile import read_yaml
from factors import quaternion

IMU = "sensor_msgs/msg/Imu"
ODOMETRY = "nav_msgs/msg/Odometry"
POSE = "geometry_msgs/msg/PoseStamped"
POSE_WITH_COVARIANCE = "geometry_msgs/msg/PoseWithCovarianceStamped"
TRANSFORM = "geometry_msgs/msg/TransformStamped"
NAV_SAT_FIX = "sensor_msgs/msg/NavSatFix"
FLUID_PRESSURE = "sensor_msgs/msg/FluidPressure"
MAGNETIC_FIELD = "sensor_msgs/msg/MagneticField"
TWIST = "geometry_msgs/msg/TwistStamped"
TWIST_WITH_COVARIANCE = "geometry_msgs/msg/TwistWithCovarianceStamped"

#: Accepted deviation of a message's quaternion norm from 1 before it is normalised.
QUATERNION_TOLERANCE = 1e-3

_NO_COVARIANCE_6 = (0.0,) * 36


def _vector(v) -> tuple:
    return v.x, v.y, v.z


def _pose_row(pose, cov) -> tuple:
    """``x y z qw qx qy qz`` and the 36 covariance entries of a ``geometry_msgs/Pose``."""
    q = pose.orientation
    return (*_vector(pose.position), q.w, q.x, q.y, q.z, *cov)


def _transform_row(m) -> tuple:
    q = m.transform.rotation
    return (*_vector(m.transform.translation), q.w, q.x, q.y, q.z, *_NO_COVARIANCE_6)


def _twist_row(twist, cov) -> tuple:
    """``vx vy vz wx wy wz`` and the 36 covariance entries of a ``geometry_msgs/Twist``."""
    return (*_vector(twist.linear), *_vector(twist.angular), *cov)


def _fix_row(m) -> tuple:
    kind = m.position_covariance_type
    cov = np.asarray(m.position_covariance, dtype=float)
    if kind == 0:
        cov = np.full(9, np.nan)
    elif kind == 2:
        cov = np.diag(cov.reshape(3, 3).diagonal()).ravel()
    return (m.latitude, m.longitude, m.altitude, m.status.status, *cov)


def _imu_attitude_row(m) -> tuple:
    q = m.orientation
    return (q.w, q.x, q.y, q.z, *m.orientation_covariance)


#: The pose messages and how one becomes a row (position, quaternion wxyz, 36 covariance entries).
_POSE_ROWS = {
    ODOMETRY: lambda m: _pose_row(m.pose.pose, m.pose.covariance),
    POSE_WITH_COVARIANCE: lambda m: _pose_row(m.pose.pose, m.pose.covariance),
    POSE: lambda m: _pose_row(m.pose, _NO_COVARIANCE_6),
    TRANSFORM: _transform_row,
}


def _attitude_of_pose(row):
    """A pose row made an attitude row: quaternion and the rotation block of the covariance."""
    def attitude(m) -> tuple:
        values = row(m)
        cov = np.asarray(values[7:], dtype=float).reshape(6, 6)[3:, 3:]
        return (*values[3:7], *cov.ravel())
    return attitude


#: Per stream: the message types that give it and how one message becomes a row of numbers.
_ROWS = {
    "IMU samples": {IMU: lambda m: (*_vector(m.linear_acceleration), *_vector(m.angular_velocity))},
    "poses": _POSE_ROWS,
    "attitudes": {IMU: _imu_attitude_row, **{k: _attitude_of_pose(row) for k, row in _POSE_ROWS.items()}},
    "twists": {
        ODOMETRY: lambda m: _twist_row(m.twist.twist, m.twist.covariance),
        TWIST_WITH_COVARIANCE: lambda m: _twist_row(m.twist.twist, m.twist.covariance),
        TWIST: lambda m: _twist_row(m.twist, _NO_COVARIANCE_6),
    },
    "GNSS fixes": {NAV_SAT_FIX: _fix_row},
    "pressures": {FLUID_PRESSURE: lambda m: (m.fluid_pressure, m.variance)},
    "magnetic fields": {MAGNETIC_FIELD: lambda m: (*_vector(m.magnetic_field), *m.magnetic_field_covariance)},
}


#: What a bag's path may be, for the errors.
_A_BAG = "a ROS bag (.bag, a ROS 2 bag folder, .db3, .mcap)"
#: Longest text of a rosbags exception quoted in an error.
_MAX_CAUSE = 100


def _cause(error: Exception) -> str:
    """``Type: message`` of an exception from inside rosbags, shortened."""
    text = f"{type(error).__name__}: {error}".strip().rstrip(":")
    return text if len(text) <= _MAX_CAUSE else text[: _MAX_CAUSE - 3] + "..."


def _check_files(path: Path, topic: str) -> None:
    """The files ``rosbags`` will read for the bag ``path`` are regular files within the size
    limit of bags (a ROS 2 folder: its ``metadata.yaml`` read within the YAML limits, and the
    storage files it lists); a :class:`DataError` naming the file and ``topic`` otherwise."""
    try:
        if not path.is_dir():
            check_source(path, "bag")
            if path.suffix == ".bag":  # what rosbags reads as ROS 1
                _check_ros1_start(path)
            return
        metadata = path / "metadata.yaml"
        if not os.path.lexists(metadata):
            return  # not a ROS 2 bag folder: rosbags says so
        data = read_yaml(metadata).data
        info = data.get("rosbag2_bagfile_information") if isinstance(data, dict) else None
        names = info.get("relative_file_paths") if isinstance(info, dict) else None
        for name in names if isinstance(names, list) else ():
            check_source(path / PurePath(str(name)).name, "bag")  # where rosbags looks for it
    except DataError as error:
        raise DataError(error.path, error.line, f"topic {topic}" if error.field is None else error.field,
                        error.found, error.expected, error.whole) from None


#: How a ROS 1 bag (format 2.0) starts: its version line.
ROS1_MAGIC = b"#ROSBAG V2.0\n"
#: The longest header of a ROS 1 bag's first record, the bag header: the record is padded to 4096
#: bytes, its header a few dozen of them.
ROS1_BAG_HEADER_MAX = 4096


def _check_ros1_start(path: Path) -> None:
    """A ``.bag`` file starts as a ROS 1 bag does: its version line and a bag header record of at
    most :data:`ROS1_BAG_HEADER_MAX` bytes; a :class:`DataError` otherwise. ``rosbags`` reads the
    version as a line and the header as long as its length field says, so that a file of no line
    end (a sparse file, a disk image) would be read whole into memory, and a length field of
    garbage allocate gigabytes, before it could say the file is no bag."""
    head = read_source(path, "bag", head=len(ROS1_MAGIC) + 4)
    if not head.startswith(ROS1_MAGIC):
        raise DataError(path, None, None, f"an unreadable bag (it starts with {head[:len(ROS1_MAGIC)]!r}, a ROS 1 "
                        f"bag with {ROS1_MAGIC!r}; a .bag file is read as ROS 1)", _A_BAG, whole=True)
    length = int.from_bytes(head[len(ROS1_MAGIC):], "little") if len(head) == len(ROS1_MAGIC) + 4 else None
    if length is None or length > ROS1_BAG_HEADER_MAX:
        found = "no bag header" if length is None else f"a bag header of {length} bytes"
        raise DataError(path, None, None, f"an unreadable bag ({found}; a ROS 1 bag's is at most "
                        f"{ROS1_BAG_HEADER_MAX} bytes)", _A_BAG, whole=True)


def _out_of_memory(path: Path, topic: str, where: str, error: MemoryError) -> DataError:
    """The error for a bag whose reading asked for more memory than the process may use:
    a damaged record claiming gigabytes, or a topic too large for the machine."""
    details = str(error).strip().splitlines()[0] if str(error).strip() else "no details"
    return DataError(path, None, f"topic {topic}", f"{where}: out of memory ({details})",
                     "a bag whose records and topic fit in memory (a damaged record can claim gigabytes)", whole=True)


@contextlib.contextmanager
def _opened(path: Path, topic: str):
    """An open ``AnyReader`` of ``path``, or a :class:`DataError` naming the bag and ``topic``."""
    check_name(path)
    if not path.exists():
        raise DataError(path, None, f"topic {topic}", "no such file or folder", _A_BAG)
    _check_files(path, topic)
    try:
        reader = AnyReader([path], default_typestore=get_typestore(Stores.ROS2_HUMBLE))
        reader.open()
    except MemoryError as error:
        raise _out_of_memory(path, topic, "opening it", error) from None
    except Exception as error:  # noqa: BLE001 -- rosbags raises its own errors, OSError, KeyError, ... for damaged files
        raise DataError(path, None, f"topic {topic}", f"an unreadable bag ({_cause(error)})", _A_BAG,
                        whole=True) from None
    try:
        yield reader
    finally:
        with contextlib.suppress(Exception):  # closing what was only read; an error here changes nothing
            reader.close()


def _messages(path: Path, reader, topic: str, msgtype: str, row) -> tuple[list[int], list[float]]:
    """Header stamps [ns] and the values of every message of ``topic`` (of type ``msgtype``,
    each made a row by ``row``), in the order the bag stores them. Whatever fails inside rosbags
    while reading or deserialising (a damaged bag raises anything from its own errors to
    ``AssertionError`` or ``struct.error``), and a bag that yields fewer or more messages than its
    index lists, is one :class:`DataError` naming the bag, the topic and the message."""
    info = reader.topics[topic]
    stamps: list[int] = []
    values: list[float] = []
    expected = f"a readable bag with the {info.msgcount} {msgtype} message(s) its index lists on the topic"
    try:
        for connection, _, raw in reader.messages(connections=info.connections):
            message = reader.deserialize(raw, connection.msgtype)
            stamps.append(message.header.stamp.sec * 1_000_000_000 + message.header.stamp.nanosec)
            values.extend(row(message))
    except MemoryError as error:
        raise _out_of_memory(path, topic, f"reading message {len(stamps) + 1} of {info.msgcount}", error) from None
    except Exception as error:  # noqa: BLE001 -- a damaged message raises whatever its decoder meets
        raise DataError(path, None, f"topic {topic}", f"a damaged bag: message {len(stamps) + 1} cannot be read "
                        f"({_cause(error)})", expected, whole=True) from None
    if len(stamps) != info.msgcount:
        raise DataError(path, None, f"topic {topic}", f"a damaged bag: {len(stamps)} message(s) could be read",
                        expected, whole=True)
    return stamps, values


def _read(path, topic: str, stream: str) -> tuple[np.ndarray, np.ndarray]:
    """The messages of ``topic`` as ``(header stamps [ns] int64, rows (N, m) float)`` in the
    order the bag stores them, the stamps strictly increasing, for the ``stream`` named (a key
    of :data:`_ROWS`)."""
    path = Path(path)
    wanted = _ROWS[stream]
    with _opened(path, topic) as reader:
        topics = reader.topics
        if topic not in topics:
            present = ", ".join(f"{name} ({info.msgtype})" for name, info in sorted(topics.items())) or "none"
            raise DataError(path, None, "topic", topic, f"a topic of the bag; it has: {present}")
        msgtype = topics[topic].msgtype
        if msgtype not in wanted:
            raise DataError(path, None, f"topic {topic}", f"messages of type {msgtype}",
                            f"{stream}: {' or '.join(wanted)}")
        stamps, values = _messages(path, reader, topic, msgtype, wanted[msgtype])
    if not stamps:
        raise DataError(path, None, f"topic {topic}", "no messages", f"at least one message ({stream})")
    t_ns = np.array(stamps, dtype=np.int64)
    check_increasing(path, t_ns, np.arange(1, len(t_ns) + 1), f"topic {topic}, header stamp [ns]", counted="message")
    return t_ns, np.array(values, dtype=float).reshape(len(stamps), -1)


def _finite(path, topic: str, t_ns: np.ndarray, values: np.ndarray, what: str) -> np.ndarray:
    bad = ~np.all(np.isfinite(values), axis=1)
    if bad.any():
        i = int(np.flatnonzero(bad)[0])
        raise DataError(path, None, f"topic {topic}", f"a non-finite {what} at stamp {int(t_ns[i])} ns",
                        f"finite values ({int(bad.sum())} message(s) have some)")
    return values


def _rotations(path, topic: str, t_ns: np.ndarray, q_wxyz: np.ndarray) -> np.ndarray:
    norm = np.linalg.norm(q_wxyz, axis=1)
    bad = np.flatnonzero(np.abs(norm - 1.0) > QUATERNION_TOLERANCE)
    if bad.size:
        i = int(bad[0])
        raise DataError(path, None, f"topic {topic}", f"a quaternion of norm {norm[i]:.9g} at stamp {int(t_ns[i])} ns",
                        f"unit quaternions (norm 1 within {QUATERNION_TOLERANCE:g})")
    return quaternion.to_matrix(q_wxyz / norm[:, None])


def read_bag_imu(path, topic: str) -> ImuSamples:
    """``sensor_msgs/msg/Imu`` messages of ``topic`` as IMU samples (``t_ns`` exact), a recording
    as long as :func:`datasets.errors.require_imu_recording` asks."""
    t_ns, rows = _read(path, topic, "IMU samples")
    require_imu_recording(path, t_ns, f"topic {topic}")
    _finite(path, topic, t_ns, rows, "acceleration or angular rate")
    return ImuSamples(seconds(t_ns), rows[:, 0:3], rows[:, 3:6], t_ns=t_ns)


def read_bag_poses(path, topic: str) -> PoseStream:
    """Poses of ``topic`` (Odometry, PoseWithCovarianceStamped, PoseStamped, TransformStamped)."""
    t_ns, rows = _read(path, topic, "poses")
    _finite(path, topic, t_ns, rows[:, :7], "position or orientation")
    C = _rotations(path, topic, t_ns, rows[:, 3:7])
    cov = known_covariances(rows[:, 7:].reshape(-1, 6, 6))
    return PoseStream(seconds(t_ns), rows[:, 0:3], C, cov, t_ns)


def read_bag_attitudes(path, topic: str) -> AttitudeStream:
    """Attitudes of ``topic``: the ``orientation`` of ``sensor_msgs/msg/Imu`` messages, or the
    attitude of pose messages (module docstring). An Imu message whose orientation covariance
    starts with -1 (REP-145: no orientation) makes the topic a :class:`DataError`."""
    t_ns, rows = _read(path, topic, "attitudes")
    none = np.flatnonzero(rows[:, 4] == -1.0)
    if none.size:
        raise DataError(path, None, f"topic {topic}",
                        f"{none.size} of {len(t_ns)} messages without an orientation (orientation_covariance[0] = -1, "
                        f"REP-145), the first at stamp {int(t_ns[none[0]])} ns",
                        "an IMU that estimates its orientation (an AHRS), or another topic for this orientation sensor",
                        whole=True)
    _finite(path, topic, t_ns, rows[:, :4], "orientation")
    C = _rotations(path, topic, t_ns, rows[:, 0:4])
    return AttitudeStream(seconds(t_ns), C, known_covariances(rows[:, 4:].reshape(-1, 3, 3)), t_ns)


def read_bag_twists(path, topic: str) -> TwistStream:
    """Twists of ``topic``: ``nav_msgs/msg/Odometry`` (child frame), ``TwistWithCovarianceStamped``
    or ``TwistStamped``."""
    t_ns, rows = _read(path, topic, "twists")
    _finite(path, topic, t_ns, rows[:, :6], "velocity")
    cov = known_covariances(rows[:, 6:].reshape(-1, 6, 6))
    return TwistStream(seconds(t_ns), rows[:, 0:3], rows[:, 3:6], cov, t_ns)


def read_bag_fixes(path, topic: str) -> FixStream:
    """``sensor_msgs/msg/NavSatFix`` messages of ``topic``; NaN positions are allowed where the
    status says there is no fix (see :class:`FixStream`)."""
    t_ns, rows = _read(path, topic, "GNSS fixes")
    status = rows[:, 3].astype(np.int64)
    fixed = status > STATUS_NO_FIX
    _finite(path, topic, t_ns[fixed], rows[fixed, :3], "latitude, longitude or altitude of a fix")
    cov = known_covariances(rows[:, 4:].reshape(-1, 3, 3))
    try:
        return FixStream(seconds(t_ns), rows[:, 0], rows[:, 1], rows[:, 2], status, cov, t_ns)
    except ValueError as error:
        raise DataError(path, None, f"topic {topic}", str(error), "valid GNSS fixes") from None


def read_bag_pressures(path, topic: str) -> PressureStream:
    """``sensor_msgs/msg/FluidPressure`` messages of ``topic`` (a barometer)."""
    t_ns, rows = _read(path, topic, "pressures")
    _finite(path, topic, t_ns, rows[:, :1], "pressure")
    bad = np.flatnonzero(rows[:, 0] <= 0)
    if bad.size:
        raise DataError(path, None, f"topic {topic}", f"a pressure of {rows[bad[0], 0]!r} Pa at stamp "
                        f"{int(t_ns[bad[0]])} ns", "pressures > 0 in pascals", whole=True)
    return PressureStream(seconds(t_ns), rows[:, 0], rows[:, 1], t_ns)


def read_bag_magnetic_fields(path, topic: str) -> MagneticFieldStream:
    """``sensor_msgs/msg/MagneticField`` messages of ``topic`` (a magnetometer)."""
    t_ns, rows = _read(path, topic, "magnetic fields")
    _finite(path, topic, t_ns, rows[:, :3], "magnetic field")
    zero = np.flatnonzero(np.linalg.norm(rows[:, :3], axis=1) == 0)
    if zero.size:
        raise DataError(path, None, f"topic {topic}", f"a zero field at stamp {int(t_ns[zero[0]])} ns",
                        "measured fields (not all zero)", whole=True)
    return MagneticFieldStream(seconds(t_ns), rows[:, :3], known_covariances(rows[:, 3:].reshape(-1, 3, 3)), t_ns)
