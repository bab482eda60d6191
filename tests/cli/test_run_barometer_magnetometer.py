"""A rig with IMU, wheels, a barometer (``sensor_msgs/FluidPressure``, kind ``altitude``) and a
magnetometer (``sensor_msgs/MagneticField``, kind ``magnetometer``) on a ROS 2 bag written by
the test: the magnetometer gives the odometry frame an absolute heading from the start, the
barometer holds the height."""
from __future__ import annotations

import json

import numpy as np
from bagfiles import Messages, write_bag
from rigfiles import imu_table, sensor_table

from datasets.kinds import altitude
from datasets.simulate import simulate
from datasets.simulated_sensors import SensorSpec
from smoother.cli import main

T0_NS = 1_650_000_000_000_000_000
FIELD_T = 4.8e-5  # the field's strength [T]
BARO_SIGMA, MAG_SIGMA = 0.3, 0.02  # m, rad
ELEVATION = 420.0  # m: the place's height, which the barometer's first reading takes as 0


def test_magnetometer_gives_the_heading_and_barometer_the_height(tmp_path):
    data = simulate("gentle", duration=40, seed=8, pose_rate=None, sensors=[
        SensorSpec("wheel", "velocity", 10, 0.05), SensorSpec("baro", "altitude", 10, BARO_SIGMA),
        SensorSpec("mag", "magnetometer", 10, MAG_SIGMA)])
    wheel, baro, mag = data.sensors
    ns = lambda t: T0_NS + np.round(np.asarray(t) * 1e9).astype(np.int64)  # noqa: E731
    m = Messages("sqlite3")
    pressure = altitude.height_pressure(ELEVATION + baro.data.height)
    variance = (BARO_SIGMA / altitude.height_per_pascal(pressure)) ** 2
    field_cov = np.eye(3) * (MAG_SIGMA * FIELD_T) ** 2
    topics = {
        "/imu": ("sensor_msgs/msg/Imu", [m.imu(*row) for row in zip(ns(data.imu.t), data.imu.acc, data.imu.gyro)]),
        "/odom": ("nav_msgs/msg/Odometry", [
            m.odometry(k, np.zeros(3), np.array([1.0, 0, 0, 0]), np.zeros((6, 6)), v, np.zeros(3),
                       np.diag([0.0025] * 6))
            for k, v in zip(ns(wheel.data.t), wheel.data.velocity)]),
        "/pressure": ("sensor_msgs/msg/FluidPressure", [m.fluid_pressure(*row) for row in zip(
            ns(baro.data.t), pressure, variance)]),
        "/mag": ("sensor_msgs/msg/MagneticField", [m.magnetic_field(k, FIELD_T * d, field_cov)
                                                   for k, d in zip(ns(mag.data.t), mag.data.direction)]),
    }
    bag = write_bag(tmp_path / "run", "sqlite3", topics)
    source = f"bag:{bag.name}"
    sensors = (sensor_table("wheel", "velocity", source, 'topic = "/odom"')
               + sensor_table("baro", "altitude", source, 'topic = "/pressure"')
               + sensor_table("mag", "magnetometer", source, 'topic = "/mag"\ndeclination = 2.0\ninclination = 60.0'))
    rig = tmp_path / "rig.toml"
    rig.write_text(imu_table(source, data.noise, "/imu") + sensors)
    out = tmp_path / "out"
    assert main(["run", "--rig", str(rig), "--estimator", "all", "--lag", "3", "--out", str(out), "--no-progress"]) == 0
    metrics = json.loads((out / "metrics.json").read_text())
    assert metrics["_run"]["world_frame"] == {"frame_id": "odom", "position": "relative to the start",
                                              "yaw": "absolute"}
    for name in ("ekf", "batch", "fixed-lag"):
        estimate = np.load(out / f"{name}.npz")
        truth, _, _ = data.truth.interpolate(estimate["t"][[0, -1]] + data.imu.t[0])
        heading = np.arctan2(estimate["C"][:, 1, 0], estimate["C"][:, 0, 0])
        true_heading = np.arctan2(truth.C[:, 1, 0], truth.C[:, 0, 0])
        error = abs((heading[[0, -1]] - true_heading + np.pi) % (2 * np.pi) - np.pi)
        # the filter's start has seen one reading (the heading's sigma there is some 0.1 rad); the
        # smoothers' start and every end have seen them all
        assert error[0] < 3 * np.sqrt(estimate["cov"][0][8, 8]) and error[-1] < 0.05, (name, error)
        if name != "ekf":
            assert error[0] < 0.05, (name, error)
        height = estimate["r"][-1, 2] - (truth.r[1, 2] - baro.data.height[0])  # z = 0: the first reading
        assert abs(height) < 3 * np.sqrt(estimate["cov"][-1][2, 2]) and abs(height) < 0.5, name
        assert metrics[name]["sensors"]["mag"]["ok"], (name, metrics[name]["sensors"]["mag"])
        # the first reading's own noise is an offset common to every height (the reference is that
        # reading as measured), which the start's fixed height cannot take up: above 1 by about
        # offset^2 / sigma^2, here 0.2-0.3
        assert 0.87 < metrics[name]["sensors"]["baro"]["per_dof"] < 1.6, (name, metrics[name]["sensors"]["baro"])
