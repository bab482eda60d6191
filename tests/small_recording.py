"""A recording written by a test as a real user's would be: a ROS 2 bag (MCAP) of the simulator's
IMU, GNSS fixes in latitude/longitude (``sensor_msgs/NavSatFix``, the antenna on a lever arm) and
wheel odometry (``nav_msgs/Odometry``: the wheel frame's twist, the wheel frame rotated and away from
the IMU), header stamps in seconds since the epoch, and its rig file with a datum."""
from __future__ import annotations

from pathlib import Path

import numpy as np
from bagfiles import Messages, write_bag
from rigfiles import imu_table, toml_matrix

from datasets.gnss import Datum, enu_to_geodetic
from datasets.simulate import simulate
from datasets.simulated_sensors import SensorSpec
from factors import so3

T0_NS = 1_700_000_000_000_000_000
DATUM = Datum(47.3769, 8.5417, 408.0)
ANTENNA = np.eye(4)
ANTENNA[:3, 3] = [0.3, 0.0, 0.95]
WHEEL = np.eye(4)
WHEEL[:3, :3], WHEEL[:3, 3] = so3.exp([np.pi, 0, np.pi / 2]), [-0.8, 0.3, -0.4]  # upside down, turned


def write_recording(folder: Path, name: str = "rig", duration: float = 10.0, seed: int = 1, imu_rate: float = 100.0,
                    gnss_rate: float = 2.0, every: int = 2, fix_sigma: float = 0.5):
    """``(rig file, simulated dataset)``: the bag ``<name>.mcap`` and the rig file ``<name>.toml``
    in ``folder``, of ``duration`` seconds of the ``gentle`` profile: IMU at ``imu_rate``, fixes
    at ``gnss_rate`` (every ``every``-th used; their noise 0.5 m, their messages' covariance
    stating ``fix_sigma``), wheel twists at 10 Hz."""
    folder.mkdir(parents=True, exist_ok=True)
    data = simulate("gentle", duration=duration, seed=seed, imu_rate=imu_rate, pose_rate=None, sensors=[
        SensorSpec("gnss", "gnss", gnss_rate, 0.5, ANTENNA), SensorSpec("wheel", "velocity", 10, 0.05, WHEEL)])
    gnss, wheel = data.sensors
    ns = lambda t: T0_NS + np.round(np.asarray(t) * 1e9).astype(np.int64)  # noqa: E731
    m = Messages("mcap")
    lat, lon, alt = enu_to_geodetic(gnss.data.position, DATUM)
    topics = {
        "/imu/data": ("sensor_msgs/msg/Imu", [m.imu(*row) for row in zip(ns(data.imu.t), data.imu.acc, data.imu.gyro)]),
        "/wheel/odom": ("nav_msgs/msg/Odometry", [
            m.odometry(t, np.zeros(3), np.array([1.0, 0, 0, 0]), np.zeros((6, 6)), v, np.zeros(3),
                       np.diag([0.0025] * 6))
            for t, v in zip(ns(wheel.data.t), wheel.data.velocity)]),
        "/fix": ("sensor_msgs/msg/NavSatFix", [m.fix(t, a, b, c, 0, np.diag([fix_sigma**2] * 3), 3)
                                               for t, a, b, c in zip(ns(gnss.data.t), lat, lon, alt)]),
    }
    bag = write_bag(folder / f"{name}.mcap", "mcap", topics)
    rig = folder / f"{name}.toml"
    rig.write_text(imu_table(f"bag:{bag.name}", data.noise, "/imu/data") + f"""
[datum]
latitude = {DATUM.latitude}
longitude = {DATUM.longitude}
altitude = {DATUM.altitude}

[[sensor]]
name = "gnss"
kind = "gnss"
source = "bag:{bag.name}"
topic = "/fix"
T_BS = {toml_matrix(ANTENNA)}
every = {every}

[[sensor]]
name = "wheel"
kind = "velocity"
source = "bag:{bag.name}"
topic = "/wheel/odom"
T_BS = {toml_matrix(WHEEL)}
""")
    return rig, data
