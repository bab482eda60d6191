"""Small ROS bags written by the tests with rosbags' writers: ROS 1 (``.bag``), ROS 2 sqlite3
and ROS 2 MCAP, from messages built here (header stamps given in integer nanoseconds)."""
from __future__ import annotations

from pathlib import Path

import numpy as np
from rosbags.rosbag1 import Writer as Writer1
from rosbags.rosbag2 import StoragePlugin
from rosbags.rosbag2 import Writer as Writer2
from rosbags.typesys import Stores, get_typestore

FORMATS = ("ros1", "sqlite3", "mcap")


def bag_path(folder: Path, fmt: str) -> Path:
    """Where a bag of format ``fmt`` goes in ``folder``: a ``.bag`` file or a ROS 2 bag folder."""
    return folder / ("run.bag" if fmt == "ros1" else f"run_{fmt}")


def storage_file(bag: Path, fmt: str) -> Path:
    """The ``.db3`` or ``.mcap`` file inside a ROS 2 bag folder."""
    return next(bag.glob("*.db3" if fmt == "sqlite3" else "*.mcap"))


class Messages:
    """Message builders for one bag format (ROS 1 and ROS 2 differ in ``Header``)."""

    def __init__(self, fmt: str):
        self.fmt = fmt
        self.store = get_typestore(Stores.ROS1_NOETIC if fmt == "ros1" else Stores.ROS2_HUMBLE)
        self.T = self.store.types

    def header(self, t_ns: int, frame: str = "map"):
        stamp = self.T["builtin_interfaces/msg/Time"](sec=int(t_ns) // 10**9, nanosec=int(t_ns) % 10**9)
        extra = {"seq": 0} if self.fmt == "ros1" else {}
        return self.T["std_msgs/msg/Header"](stamp=stamp, frame_id=frame, **extra)

    def vector(self, v):
        return self.T["geometry_msgs/msg/Vector3"](x=float(v[0]), y=float(v[1]), z=float(v[2]))

    def point(self, v):
        return self.T["geometry_msgs/msg/Point"](x=float(v[0]), y=float(v[1]), z=float(v[2]))

    def quaternion(self, q_wxyz):
        w, x, y, z = (float(c) for c in q_wxyz)
        return self.T["geometry_msgs/msg/Quaternion"](x=x, y=y, z=z, w=w)

    def pose(self, p, q):
        return self.T["geometry_msgs/msg/Pose"](position=self.point(p), orientation=self.quaternion(q))

    def imu(self, t_ns, acc, gyro, q_wxyz=None, orientation_cov=None):
        """An Imu message; without ``q_wxyz`` REP-145's "no orientation" (covariance -1)."""
        cov = np.full(9, -1.0) if q_wxyz is None else np.ravel(orientation_cov).astype(float)
        return self.T["sensor_msgs/msg/Imu"](
            header=self.header(t_ns, "imu"), orientation=self.quaternion((1, 0, 0, 0) if q_wxyz is None else q_wxyz),
            orientation_covariance=cov, angular_velocity=self.vector(gyro),
            angular_velocity_covariance=np.zeros(9), linear_acceleration=self.vector(acc),
            linear_acceleration_covariance=np.zeros(9))

    def odometry(self, t_ns, p, q, cov, v, w, twist_cov):
        pose = self.T["geometry_msgs/msg/PoseWithCovariance"](pose=self.pose(p, q), covariance=np.ravel(cov))
        twist = self.T["geometry_msgs/msg/TwistWithCovariance"](
            twist=self.T["geometry_msgs/msg/Twist"](linear=self.vector(v), angular=self.vector(w)),
            covariance=np.ravel(twist_cov))
        return self.T["nav_msgs/msg/Odometry"](header=self.header(t_ns), child_frame_id="base", pose=pose, twist=twist)

    def twist(self, v, w):
        return self.T["geometry_msgs/msg/Twist"](linear=self.vector(v), angular=self.vector(w))

    def twist_stamped(self, t_ns, v, w):
        return self.T["geometry_msgs/msg/TwistStamped"](header=self.header(t_ns, "sensor"), twist=self.twist(v, w))

    def twist_with_covariance(self, t_ns, v, w, cov):
        twist = self.T["geometry_msgs/msg/TwistWithCovariance"](twist=self.twist(v, w), covariance=np.ravel(cov))
        return self.T["geometry_msgs/msg/TwistWithCovarianceStamped"](header=self.header(t_ns, "sensor"), twist=twist)

    def fluid_pressure(self, t_ns, pressure, variance):
        return self.T["sensor_msgs/msg/FluidPressure"](header=self.header(t_ns, "baro"), fluid_pressure=float(pressure),
                                                       variance=float(variance))

    def magnetic_field(self, t_ns, field, cov):
        return self.T["sensor_msgs/msg/MagneticField"](header=self.header(t_ns, "mag"),
                                                       magnetic_field=self.vector(field),
                                                       magnetic_field_covariance=np.ravel(cov).astype(float))

    def pose_stamped(self, t_ns, p, q):
        return self.T["geometry_msgs/msg/PoseStamped"](header=self.header(t_ns), pose=self.pose(p, q))

    def pose_with_covariance(self, t_ns, p, q, cov):
        pose = self.T["geometry_msgs/msg/PoseWithCovariance"](pose=self.pose(p, q), covariance=np.ravel(cov))
        return self.T["geometry_msgs/msg/PoseWithCovarianceStamped"](header=self.header(t_ns), pose=pose)

    def transform(self, t_ns, p, q):
        transform = self.T["geometry_msgs/msg/Transform"](translation=self.vector(p), rotation=self.quaternion(q))
        return self.T["geometry_msgs/msg/TransformStamped"](header=self.header(t_ns), child_frame_id="base",
                                                             transform=transform)

    def fix(self, t_ns, lat, lon, alt, status, cov, cov_type):
        status_msg = self.T["sensor_msgs/msg/NavSatStatus"](status=int(status), service=1)
        return self.T["sensor_msgs/msg/NavSatFix"](
            header=self.header(t_ns, "gps"), status=status_msg, latitude=float(lat), longitude=float(lon),
            altitude=float(alt), position_covariance=np.ravel(cov).astype(float),
            position_covariance_type=int(cov_type))


def write_bag(path: Path, fmt: str, topics: dict, bz2: bool = False) -> Path:
    """Write ``topics`` (name -> ``(message type, [messages])``, messages in the order given,
    each recorded 1 ms after its header stamp; or ``(message type, [messages], [receive times
    in ns])``) into a new bag of format ``fmt`` at ``path`` (ROS 1 with ``bz2``: its chunks
    compressed)."""
    store = Messages(fmt).store
    if fmt == "ros1":
        writer = Writer1(path)
        if bz2:
            writer.set_compression(Writer1.CompressionFormat.BZ2)
        serialize = store.serialize_ros1
    else:
        plugin = StoragePlugin.SQLITE3 if fmt == "sqlite3" else StoragePlugin.MCAP
        writer = Writer2(path, version=9, storage_plugin=plugin)
        serialize = store.serialize_cdr
    with writer:
        for topic, (msgtype, messages, *received) in topics.items():
            connection = writer.add_connection(topic, msgtype, typestore=store)
            for k, message in enumerate(messages):
                stamp = message.header.stamp
                at = int(received[0][k]) if received else stamp.sec * 10**9 + stamp.nanosec + 1_000_000
                writer.write(connection, at, serialize(message, msgtype))
    return path
