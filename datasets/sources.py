"""One entry point for reading a sensor stream named by a source spec.

A spec is ``SCHEME:PATH`` with the path relative to ``base_dir`` (a rig file's folder) unless
absolute; ``~`` expands to the home folder:

* ``bag:PATH``: a ROS bag (:mod:`datasets.bags`): a ROS 1 ``.bag``, a ROS 2 bag folder, a
  ``.db3`` or a ``.mcap`` file; needs a ``topic``.
* ``csv:PATH``: a CSV file (:mod:`datasets.csv_sources`): EuRoC/ASL IMU or ground-truth layout,
  or the generic layout of the stream asked for.
* ``tum:PATH``: a TUM trajectory (:mod:`datasets.tum`), for poses only.

What each scheme gives: IMU samples from ``bag`` and ``csv``; poses, positions and attitudes from
all three (a CSV file of positions or attitudes alone has only the columns they need);
velocities (twists), GNSS fixes, pressures and magnetic fields from ``bag`` and ``csv``. Asking a
scheme for a stream it cannot give, an
unknown scheme, a bag without a topic or a file with one is one ``ValueError`` naming the spec;
errors in the data are :class:`datasets.errors.DataError` naming the file (and topic or line).
"""
from __future__ import annotations

from pathlib import Path

from datasets.bags import (
    read_bag_attitudes,
    read_bag_fixes,
    read_bag_imu,
    read_bag_magnetic_fields,
    read_bag_poses,
    read_bag_pressures,
    read_bag_twists,
)
from datasets.csv_sources import (
    read_csv_attitudes,
    read_csv_fixes,
    read_csv_imu,
    read_csv_magnetic_fields,
    read_csv_poses,
    read_csv_positions,
    read_csv_pressures,
    read_csv_twists,
)
from datasets.streams import (
    AttitudeStream,
    FixStream,
    MagneticFieldStream,
    PoseStream,
    PositionStream,
    PressureStream,
    TwistStream,
)
from datasets.tum import read_tum
from datasets.types import ImuSamples
from factors.errors import InputError


def _tum_poses(path) -> PoseStream:
    trajectory = read_tum(path)
    return PoseStream(trajectory.t, trajectory.position, trajectory.C)


#: For each stream, the schemes that give it and their readers (each takes a path, bags a topic too).
READERS = {
    "IMU samples": {"bag": read_bag_imu, "csv": read_csv_imu},
    "poses": {"bag": read_bag_poses, "csv": read_csv_poses, "tum": _tum_poses},
    "positions": {"bag": lambda path, topic: PositionStream.of_poses(read_bag_poses(path, topic)),
                  "csv": read_csv_positions, "tum": lambda path: PositionStream.of_poses(_tum_poses(path))},
    "attitudes": {"bag": read_bag_attitudes, "csv": read_csv_attitudes,
                  "tum": lambda path: AttitudeStream.of_poses(_tum_poses(path))},
    "velocities": {"bag": read_bag_twists, "csv": read_csv_twists},
    "GNSS fixes": {"bag": read_bag_fixes, "csv": read_csv_fixes},
    "pressures": {"bag": read_bag_pressures, "csv": read_csv_pressures},
    "magnetic fields": {"bag": read_bag_magnetic_fields, "csv": read_csv_magnetic_fields},
}
SCHEMES = ("bag", "csv", "tum")


def user_path(text: str, base_dir=".") -> Path:
    """The path a user wrote (a rig file's value, a source spec's), ``~`` or ``~user`` expanded and
    relative to ``base_dir`` unless absolute; an InputError naming it when it cannot be a path: a
    NUL character (no file system takes one; the system call would fail without naming it) or a
    ``~user`` of no known user (``Path.expanduser`` raises a ``RuntimeError`` there)."""
    if "\0" in text:
        raise InputError(f"path {text!r}: a NUL character (\\x00) cannot be part of a file name")
    try:
        path = Path(text).expanduser()
    except RuntimeError:  # no home folder for "~" or "~user"
        head = text.split("/", 1)[0]
        raise InputError(f"path {text!r}: {head} names no home folder (no such user, or no HOME); write the "
                         "folder out") from None
    return Path(base_dir) / path


def parse_spec(spec: str, base_dir=".", stream: str | None = None) -> tuple[str, Path]:
    """``(scheme, path)`` of ``spec``, the path resolved against ``base_dir``; with ``stream`` (a
    key of :data:`READERS`) the scheme must be able to give it. Reads nothing."""
    if not isinstance(spec, str):
        raise InputError(f"source {spec!r}: expected a string SCHEME:PATH")
    scheme, sep, rest = spec.partition(":")
    if not sep or scheme not in SCHEMES:
        raise InputError(f"source {spec!r}: expected bag:PATH, csv:PATH or tum:PATH")
    if not rest.strip():
        raise InputError(f"source {spec!r}: no path after '{scheme}:'")
    if stream is not None and scheme not in READERS[stream]:
        raise InputError(f"source {spec!r}: a {scheme}: source has no {stream}; "
                         f"{stream} come from {' or '.join(s + ':' for s in READERS[stream])}")
    try:
        return scheme, user_path(rest, base_dir)
    except InputError as error:
        raise InputError(f"source {spec!r}: {error}") from None


def _read(stream: str, spec: str, topic: str | None, base_dir):
    scheme, path = parse_spec(spec, base_dir, stream)
    reader = READERS[stream][scheme]
    if scheme == "bag":
        if not topic:
            raise InputError(f"source {spec!r}: a bag needs a topic")
        return reader(path, topic)
    if topic is not None:
        raise InputError(f"source {spec!r}: a topic ({topic!r}) is only for bag sources")
    return reader(path)


def read_imu(spec: str, topic: str | None = None, base_dir=".") -> ImuSamples:
    """IMU samples (``sensor_msgs/Imu`` of a bag, or an EuRoC/ASL CSV file)."""
    return _read("IMU samples", spec, topic, base_dir)


def read_poses(spec: str, topic: str | None = None, base_dir=".") -> PoseStream:
    """Poses (bag: Odometry, PoseWithCovarianceStamped, PoseStamped, TransformStamped; CSV; TUM)."""
    return _read("poses", spec, topic, base_dir)


def read_positions(spec: str, topic: str | None = None, base_dir=".") -> PositionStream:
    """Positions (the positions of a bag's or a TUM file's poses; a CSV file of positions or
    poses)."""
    return _read("positions", spec, topic, base_dir)


def read_attitudes(spec: str, topic: str | None = None, base_dir=".") -> AttitudeStream:
    """Attitudes (bag: ``sensor_msgs/Imu``'s orientation, or any pose message's; a CSV file of
    attitudes or poses; the attitudes of a TUM file)."""
    return _read("attitudes", spec, topic, base_dir)


def read_twists(spec: str, topic: str | None = None, base_dir=".") -> TwistStream:
    """Velocities in the sensor frame (bag: Odometry's twist, TwistStamped,
    TwistWithCovarianceStamped; CSV)."""
    return _read("velocities", spec, topic, base_dir)


def read_fixes(spec: str, topic: str | None = None, base_dir=".") -> FixStream:
    """GNSS fixes (bag: NavSatFix; CSV)."""
    return _read("GNSS fixes", spec, topic, base_dir)


def read_pressures(spec: str, topic: str | None = None, base_dir=".") -> PressureStream:
    """Static pressures of a barometer (bag: FluidPressure; CSV)."""
    return _read("pressures", spec, topic, base_dir)


def read_magnetic_fields(spec: str, topic: str | None = None, base_dir=".") -> MagneticFieldStream:
    """Magnetic fields in the sensor frame (bag: MagneticField; CSV)."""
    return _read("magnetic fields", spec, topic, base_dir)
