"""A run's estimates as an MCAP file of ROS 2 messages (``smoother run --mcap``: ``estimates.mcap``),
for Foxglove, ``ros2 bag`` and ``rosbags``; written with rosbags' ROS 2 writer (MCAP storage, zstd
chunks; the message definitions are those of ROS 2 Humble, whose types Jazzy keeps -- same type
hashes -- adding constants such as ``NavSatStatus.SERVICE_UNKNOWN = 0``, the fixes' ``service``).

Topics (an estimator's name with ``-`` as ``_``, which ROS names do not allow):

* ``/<estimator>/odometry``, ``nav_msgs/msg/Odometry``, one message per state of each estimator
  that finished;
* ``/tf``, ``tf2_msgs/msg/TFMessage``: the world frame to ``base_link`` at every state of one
  estimate, the first of :data:`TF_ESTIMATORS` that finished (the batch smoother's when it ran);
* ``/<estimator>/fix``, ``sensor_msgs/msg/NavSatFix``, when the run has a datum (a rig with GNSS):
  the estimated position in latitude, longitude and altitude.

Conventions:

* **Stamps**: header stamps (and each message's log time) in the data's own clock,
  ``Dataset.time_origin_ns + round(t * 1e9)`` nanoseconds, as ``.tum`` and ``.npz`` keep them
  (:func:`smoother.outputs.files.save_trajectory`); from 0 when the data have no clock of their own.
* **Frames**: ``header.frame_id`` is the world frame, :func:`datasets.initialise.world_frame` (REP-105's ``map`` when a
  sensor fixes the position in the world, ``odom`` otherwise); ``child_frame_id`` is ``base_link``,
  which here is the IMU frame ``B`` itself: the estimate is of the IMU, and a rig names no other
  body frame (its ``forward`` is a direction in the IMU frame, its sensors' ``T_BS`` place them in
  it). ``NavSatFix.header.frame_id`` is ``base_link`` too: the fix is of the IMU's origin.
* **Pose**: ``position`` is ``I_r_IB`` and ``orientation`` the quaternion of ``C = C(Phi_IB)``, the
  rotation taking ``base_link`` coordinates to world coordinates: the attitude of the child in the
  parent frame, as ROS has it. ``pose.covariance`` (6x6, row major) is the estimate's covariance of
  ``(dr, dphi)``, taken as it is from the 15x15 error-state covariance (order ``dr, dv, dphi, db_f,
  db_w``). ``geometry_msgs/PoseWithCovariance`` orders it ``x, y, z`` then the rotations about the
  X, Y and Z axes in a fixed-axis representation, and ``nav_msgs/Odometry`` gives the pose in
  ``header.frame_id``: a position error in world axes and a small rotation about the world's
  (the parent's, fixed) axes applied to the attitude, ``C <- exp(dphi) C``. That is the project's
  own error state (the primer's left boxplus, world-frame ``dphi``; docs/design.md), so no
  rotation of the covariance is needed. (A body-frame perturbation ``C exp(dtheta)`` would need
  ``dtheta = C^T dphi``; ROS's fixed-axis wording rules it out.)
* **Twist**: in ``child_frame_id``, as ``nav_msgs/Odometry`` says. ``linear`` is the state's
  velocity, already in the body frame (``B_v_B``, :mod:`factors.imu`); ``angular`` the body rate,
  the gyro reading held at the state's time less the estimated gyro bias, ``w~ - b_w``.
  ``twist.covariance`` is that of ``(dv, -db_w)`` plus, on the angular block, the variance of one
  gyro reading's white noise (``density^2 / dt`` per axis).
* **Fix**: latitude, longitude, altitude of ``I_r_IB`` about the datum (WGS-84,
  :func:`datasets.gnss.enu_to_geodetic`); ``position_covariance`` the position's, in the datum's
  ENU frame (the ENU frame at the fix differs by the earth's curvature, negligible over a local
  frame: :mod:`datasets.gnss`), type ``COVARIANCE_TYPE_KNOWN``; ``status`` ``STATUS_FIX``.
* **Without covariances** (``--no-covariance``) every covariance is all zero, which ROS tools (and
  this project's bag reader) take as unknown, and a fix's covariance type is
  ``COVARIANCE_TYPE_UNKNOWN``.

:func:`write_mcap` writes the file whole or not at all: rosbags writes a bag folder, hidden beside
the target, whose storage file is then moved onto it; on any error the folder is deleted. Inside a
run directory the target is in its staging folder (:meth:`smoother.commands.run_directory.
RunDirectory.outputs`), so the MCAP joins the run's other files together or not at all.
"""
from __future__ import annotations

import heapq
import os
import secrets
import shutil
from pathlib import Path

import numpy as np

from datasets.initialise import world_frame
from datasets.kinds import sensors_of
from datasets.types import Dataset
from factors import imu, quaternion
from factors.errors import InputError
from smoother.estimators import ESTIMATORS

#: The child frame of every pose and transform: the IMU frame (see the module docstring).
BASE_LINK = "base_link"
#: Whose estimate ``/tf`` carries: the first of these that finished.
TF_ESTIMATORS = ESTIMATORS

_ODOMETRY = "nav_msgs/msg/Odometry"
_TF = "tf2_msgs/msg/TFMessage"
_FIX = "sensor_msgs/msg/NavSatFix"
#: The error-state components of a pose covariance, in ROS's order (x y z, rotations about x y z).
_POSE = np.r_[imu.R, imu.PHI]


def topic(estimator: str, leaf: str) -> str:
    """``/<estimator>/<leaf>`` with the estimator's name made a ROS name (``fixed-lag`` ->
    ``fixed_lag``)."""
    return f"/{estimator.replace('-', '_')}/{leaf}"


def stamps_ns(t: np.ndarray, time_origin_ns: int | None) -> np.ndarray:
    """The data clock's stamps [ns] of the run's times ``t`` [s]; a ValueError for one before 0,
    which neither ROS time nor an MCAP log time can hold."""
    ns = (0 if time_origin_ns is None else int(time_origin_ns)) + np.round(np.asarray(t) * 1e9).astype(np.int64)
    if len(ns) and ns[0] < 0:
        raise InputError(f"MCAP output: a stamp before 0 ({int(ns[0])} ns in the data's clock); ROS stamps and "
                         "MCAP log times count from 0")
    return ns


class Messages:
    """Builders of the ROS 2 messages of :func:`write_mcap` from arrays, one message at a time."""

    def __init__(self, store, frame: str):
        self.T = store.types
        self.frame = frame

    def header(self, ns: int, frame: str):
        stamp = self.T["builtin_interfaces/msg/Time"](sec=int(ns // 1_000_000_000), nanosec=int(ns % 1_000_000_000))
        return self.T["std_msgs/msg/Header"](stamp=stamp, frame_id=frame)

    def vector(self, v, kind: str = "Vector3"):
        return self.T[f"geometry_msgs/msg/{kind}"](x=float(v[0]), y=float(v[1]), z=float(v[2]))

    def quaternion(self, q_wxyz):
        return self.T["geometry_msgs/msg/Quaternion"](x=float(q_wxyz[1]), y=float(q_wxyz[2]), z=float(q_wxyz[3]),
                                                      w=float(q_wxyz[0]))

    def odometry(self, ns, r, q, pose_cov, v, w, twist_cov):
        T = self.T
        pose = T["geometry_msgs/msg/PoseWithCovariance"](
            pose=T["geometry_msgs/msg/Pose"](position=self.vector(r, "Point"), orientation=self.quaternion(q)),
            covariance=pose_cov.ravel())
        twist = T["geometry_msgs/msg/TwistWithCovariance"](
            twist=T["geometry_msgs/msg/Twist"](linear=self.vector(v), angular=self.vector(w)),
            covariance=twist_cov.ravel())
        return T[_ODOMETRY](header=self.header(ns, self.frame), child_frame_id=BASE_LINK, pose=pose, twist=twist)

    def tf(self, ns, r, q):
        T = self.T
        transform = T["geometry_msgs/msg/TransformStamped"](
            header=self.header(ns, self.frame), child_frame_id=BASE_LINK,
            transform=T["geometry_msgs/msg/Transform"](translation=self.vector(r), rotation=self.quaternion(q)))
        return T[_TF](transforms=[transform])

    def fix(self, ns, lat, lon, alt, cov, known: bool):
        T = self.T
        Status, Fix = T["sensor_msgs/msg/NavSatStatus"], T[_FIX]
        return Fix(header=self.header(ns, BASE_LINK), status=Status(status=Status.STATUS_FIX, service=0),
                   latitude=float(lat), longitude=float(lon), altitude=float(alt), position_covariance=cov.ravel(),
                   position_covariance_type=Fix.COVARIANCE_TYPE_KNOWN if known else Fix.COVARIANCE_TYPE_UNKNOWN)


def _covariances(trajectory, n: int) -> np.ndarray:
    """The (n, 15, 15) error-state covariances of ``trajectory``, zero where it has none."""
    return np.zeros((n, 15, 15)) if trajectory.cov is None else np.asarray(trajectory.cov)


def twist_of(dataset: Dataset, trajectory) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``(v (N, 3), w (N, 3), cov (N, 6, 6))``: each state's body velocity and body rate (the gyro
    reading held at its time less its gyro bias) and their covariance (of ``(dv, -db_w)``, with
    the gyro reading's white-noise variance ``density^2 / dt`` added to the rate's block; zero
    where the trajectory has no covariances)."""
    s, n = trajectory.states, len(trajectory)
    w = dataset.imu.gyro[dataset.imu.held(trajectory.t)] - s.b_w
    P = _covariances(trajectory, n)
    sign = np.r_[np.ones(3), -np.ones(3)]
    cov = P[:, np.r_[imu.V, imu.BW]][:, :, np.r_[imu.V, imu.BW]] * np.outer(sign, sign)
    if trajectory.cov is not None:
        gyro_variance = dataset.noise.gyro**2 / float(np.median(np.diff(dataset.imu.t)))
        cov[:, 3:, 3:] += gyro_variance * np.eye(3)
    return s.v, w, cov


def _odometry_messages(build, dataset, trajectory, ns):
    s = trajectory.states
    q = quaternion.from_matrix(s.C)
    P = _covariances(trajectory, len(trajectory))
    pose_cov = P[:, _POSE][:, :, _POSE]
    v, w, twist_cov = twist_of(dataset, trajectory)
    for k in range(len(ns)):
        yield int(ns[k]), build.odometry(ns[k], s.r[k], q[k], pose_cov[k], v[k], w[k], twist_cov[k])


def _tf_messages(build, trajectory, ns):
    q = quaternion.from_matrix(trajectory.C)
    for k in range(len(ns)):
        yield int(ns[k]), build.tf(ns[k], trajectory.position[k], q[k])


def _fix_messages(build, trajectory, ns, datum):
    from datasets.gnss import enu_to_geodetic

    lat, lon, alt = enu_to_geodetic(trajectory.position, datum)
    known = trajectory.cov is not None
    cov = _covariances(trajectory, len(trajectory))[:, imu.R, imu.R]
    for k in range(len(ns)):
        yield int(ns[k]), build.fix(ns[k], lat[k], lon[k], alt[k], cov[k], known)


def streams(dataset: Dataset, estimates: dict, store) -> list[tuple[str, str, object]]:
    """``(topic, message type, messages)`` of every topic of the file, each ``messages`` an
    iterator of ``(stamp [ns], message)`` in time order (see the module docstring)."""
    build = Messages(store, world_frame(sensors_of(dataset)).frame_id)
    finished = {name: est.trajectory for name, est in estimates.items() if est.failed is None}
    datum = getattr(dataset, "datum", None)
    out = []
    for name, trajectory in finished.items():
        ns = stamps_ns(trajectory.t, dataset.time_origin_ns)
        out.append((topic(name, "odometry"), _ODOMETRY, _odometry_messages(build, dataset, trajectory, ns)))
        if datum is not None:
            out.append((topic(name, "fix"), _FIX, _fix_messages(build, trajectory, ns, datum)))
    tf = next((name for name in TF_ESTIMATORS if name in finished), None)
    if tf is not None:
        out.append(("/tf", _TF, _tf_messages(build, finished[tf], stamps_ns(finished[tf].t, dataset.time_origin_ns))))
    return out


def _tagged(index: int, messages):
    """``(stamp, index, message)`` of each ``(stamp, message)``: the topic's index for the merge."""
    for ns, message in messages:
        yield ns, index, message


def write_mcap(path, dataset: Dataset, estimates: dict) -> Path:
    """Write the finished ``estimates`` (name -> :class:`smoother.pipeline.Estimate`) of a run on
    ``dataset`` as an MCAP file at ``path``, messages in time order across topics; the file is
    complete or absent (see the module docstring). Returns ``path``."""
    from rosbags.rosbag2 import StoragePlugin, Writer
    from rosbags.rosbag2.enums import CompressionFormat, CompressionMode
    from rosbags.typesys import Stores, get_typestore

    path = Path(path)
    store = get_typestore(Stores.ROS2_HUMBLE)
    folder = path.with_name(f".{path.name}.{secrets.token_hex(4)}.tmp")  # rosbags writes a bag folder
    try:
        writer = Writer(folder, version=Writer.VERSION_LATEST, storage_plugin=StoragePlugin.MCAP)
        writer.set_compression(CompressionMode.STORAGE, CompressionFormat.ZSTD)
        with writer:
            topics = streams(dataset, estimates, store)
            connections = [writer.add_connection(name, msgtype, typestore=store) for name, msgtype, _ in topics]
            tagged = [_tagged(i, messages) for i, (_, _, messages) in enumerate(topics)]
            for ns, i, message in heapq.merge(*tagged, key=lambda item: (item[0], item[1])):
                writer.write(connections[i], ns, store.serialize_cdr(message, topics[i][1]))
        os.replace(folder / f"{folder.name}.mcap", path)
    finally:
        shutil.rmtree(folder, ignore_errors=True)
    return path
