"""Runs without an absolute position sensor, in the odometry frame (REP-105 ``odom``): the world
origin is the start and, without an absolute heading, so is the yaw; and the attitude of
``sensor_msgs/Imu`` messages (an AHRS) as an orientation sensor, whole or roll and pitch only.

The recording is an IMU + wheel odometry run written by the test as a ROS 1 bag, its Imu
messages carrying an AHRS attitude; no ground truth reaches the estimators."""
from __future__ import annotations

import json

import numpy as np
import pytest
from bagfiles import Messages, write_bag
from rigfiles import imu_table, sensor_table, toml_matrix

from datasets.initialise import is_odometry_frame, self_initialised, world_frame
from datasets.kinds import sensors_of
from datasets.simulate import simulate
from datasets.simulated_sensors import SensorSpec
from factors import quaternion, so3
from smoother.cli import main

T0_NS = 1_600_000_000_000_000_000
WHEEL = np.eye(4)
WHEEL[:3, :3], WHEEL[:3, 3] = so3.exp([0.0, 0.0, np.pi / 2]), [-0.4, 0.2, -0.3]
AHRS_SIGMA = 0.01  # rad, about every world axis
#: The AHRS's heading error: an offset and a drift (an AHRS without a magnetometer).
HEADING_OFFSET, HEADING_DRIFT = 0.7, 0.01  # rad, rad/s
#: A chi-square bound of 3 degrees of freedom (99.99 %).
CHI2_3 = 21.1


def _yaw(C) -> np.ndarray:
    return np.arctan2(C[..., 1, 0], C[..., 0, 0])


@pytest.fixture(scope="module")
def recording(tmp_path_factory):
    """The simulated run and its bag: ``/imu/data`` with the true attitude plus noise and
    ``/imu/drifting`` with a heading off by a drifting angle, and ``/wheel/odom``."""
    folder = tmp_path_factory.mktemp("odom")
    data = simulate("gentle", duration=40, seed=3, pose_rate=None, sensors=[
        SensorSpec("wheel", "velocity", 10, 0.05, WHEEL)])
    (wheel,) = data.sensors
    rng = np.random.default_rng(1)
    ahrs = so3.boxplus(data.truth.C[: len(data.imu)], AHRS_SIGMA * rng.standard_normal((len(data.imu), 3)))
    t = data.imu.t
    drifting = so3.exp((HEADING_OFFSET + HEADING_DRIFT * t)[:, None] * np.array([0.0, 0.0, 1.0])) @ ahrs
    ns = lambda t: T0_NS + np.round(np.asarray(t) * 1e9).astype(np.int64)  # noqa: E731
    m = Messages("ros1")
    cov = np.eye(3) * AHRS_SIGMA**2

    def imu_messages(C):
        return [m.imu(k, a, w, q, cov) for k, a, w, q in zip(ns(t), data.imu.acc, data.imu.gyro,
                                                                quaternion.from_matrix(C))]

    topics = {
        "/imu/data": ("sensor_msgs/msg/Imu", imu_messages(ahrs)),
        "/imu/drifting": ("sensor_msgs/msg/Imu", imu_messages(drifting)),
        "/imu/raw": ("sensor_msgs/msg/Imu", [m.imu(*row) for row in zip(ns(t), data.imu.acc, data.imu.gyro)]),
        "/wheel/odom": ("nav_msgs/msg/Odometry", [
            m.odometry(k, np.zeros(3), np.array([1.0, 0, 0, 0]), np.zeros((6, 6)), v, np.zeros(3),
                       np.diag([0.0025] * 6))
            for k, v in zip(ns(wheel.data.t), wheel.data.velocity)]),
    }
    bag = write_bag(folder / "run.bag", "ros1", topics)
    return data, folder, bag


def _rig(folder, bag, data, attitude: str | None = None, name: str = "rig") -> str:
    source = f"bag:{bag.name}"
    text = imu_table(source, data.noise, "/imu/data") + sensor_table(
        "wheel", "velocity", source, f'topic = "/wheel/odom"\nT_BS = {toml_matrix(WHEEL)}')
    if attitude is not None:
        text += sensor_table("ahrs", "orientation", source, f"{attitude}\nevery = 3")
    path = folder / f"{name}.toml"
    path.write_text(text)
    return str(path)


def _run(rig, out, estimators="all") -> dict:
    assert main(["run", "--rig", rig, "--estimator", estimators, "--lag", "3", "--out", str(out), "--no-progress"]) == 0
    return json.loads((out / "metrics.json").read_text())


def _truth_in_odometry_frame(data, estimate):
    """The truth's final position and attitude in the odometry frame the estimate started: its
    start moved to the origin and turned about the vertical as the estimate's start is."""
    t, C = estimate["t"], estimate["C"]
    states, _, _ = data.truth.interpolate(t[[0, -1]] + data.imu.t[0])  # the bag's clock starts at the IMU's
    turn = so3.exp(np.array([0.0, 0.0, _yaw(C[0] @ states.C[0].T)]))
    return turn @ (states.r[1] - states.r[0]), turn @ states.C[1]


def _within_covariance(estimate, r_true) -> float:
    e = estimate["r"][-1] - r_true
    return float(e @ np.linalg.solve(estimate["cov"][-1][:3, :3], e))


def test_imu_and_wheels_alone_run_in_the_odometry_frame(recording, tmp_path, capsys):
    """The rig path: position and yaw relative to the start, the final position within what every
    estimator's covariance says, which has grown from the start's."""
    data, folder, bag = recording
    metrics = _run(_rig(folder, bag, data), tmp_path / "out")
    assert metrics["_run"]["world_frame"] == {"frame_id": "odom", "position": "relative to the start",
                                              "yaw": "relative to the start"}
    assert "odometry frame: no absolute position sensor; position and yaw are relative to the start" in \
        capsys.readouterr().out
    for name in ("batch", "fixed-lag", "ekf"):
        estimate = np.load(tmp_path / "out" / f"{name}.npz")
        assert np.allclose(estimate["r"][0], 0.0, atol=0.01) and abs(so3.log(estimate["C"][0])[2]) < 0.01, name
        r_true, _ = _truth_in_odometry_frame(data, estimate)
        assert _within_covariance(estimate, r_true) < CHI2_3, name
        sigma0, sigma1 = (np.sqrt(np.diag(estimate["cov"][k])) for k in (0, -1))
        assert sigma0[:3].max() < 0.01 and sigma0[8] < 0.01, name  # the start defines the frame
        assert sigma1[:3].max() > 10 * sigma0[:3].max() and sigma1[8] > 2 * sigma0[8], name  # and the errors grow


def test_the_python_api_and_the_online_smoother_start_in_the_odometry_frame(recording):
    """A dataset of IMU + wheels self-initialises at the world origin with heading 0 (level by
    the shortest turn, about a horizontal axis), and the online smoother runs from there."""
    from smoother.online.replay import replay

    data, _, _ = recording
    started = self_initialised(data)
    assert is_odometry_frame(sensors_of(started)) and world_frame(sensors_of(started)).relative_heading
    assert np.array_equal(started.initial.r, np.zeros(3)) and abs(so3.log(started.initial.C)[2]) < 1e-12
    online = replay(started, lag_s=3.0, progress=False)
    final = online.smoothed
    r_true, _ = _truth_in_odometry_frame(data, {"t": final.t, "r": final.states.r, "C": final.states.C})
    e = final.states.r[-1] - r_true
    assert e @ np.linalg.solve(final.cov[-1][:3, :3], e) < CHI2_3


def test_an_attitude_read_from_the_imu_s_own_messages_is_known_to_follow_the_imu(recording):
    """An orientation on the IMU's topic is a filter's output on the same gyro: the dataset says so
    (``Sensor.imu_stream``, naming the stream), and a run's verdicts then name it beside an
    overstated sigma; one on a topic of its own is independent."""
    from datasets.recording import load_recording
    from datasets.rig import load_rig
    from smoother.pipeline import imu_followers

    data, folder, bag = recording
    same = load_recording(load_rig(_rig(folder, bag, data, 'topic = "/imu/data"', "same")))
    own = load_recording(load_rig(_rig(folder, bag, data, 'topic = "/imu/drifting"', "own")))
    [ahrs] = [s for s in same.sensors if s.name == "ahrs"]
    assert ahrs.imu_stream == f"bag:{bag}, topic /imu/data", ahrs.imu_stream
    assert all(s.imu_stream is None for s in own.sensors)
    assert imu_followers(same, {}) == {"ahrs": f"it reads the IMU's own messages, bag:{bag}, topic /imu/data"}
    assert imu_followers(own, {}) == {}


def test_the_imu_attitude_fixes_the_heading_and_roll_pitch_only_leaves_it_out(recording, tmp_path):
    """``kind = "orientation"`` on the Imu topic: yaw absolute (the AHRS's), position relative.
    The same with a drifting heading: used whole it pulls the estimate's heading along; with
    ``roll_pitch_only`` the heading is the odometry frame's again and the drift does not enter."""
    data, folder, bag = recording
    whole = _run(_rig(folder, bag, data, 'topic = "/imu/data"', "whole"), tmp_path / "whole", "ekf")
    assert whole["_run"]["world_frame"] == {"frame_id": "odom", "position": "relative to the start", "yaw": "absolute"}
    estimate = np.load(tmp_path / "whole" / "ekf.npz")
    states, _, _ = data.truth.interpolate(estimate["t"][[-1]] + data.imu.t[0])
    assert abs(_yaw(estimate["C"][-1] @ states.C[0].T)) < 0.02  # the true heading, through the AHRS
    assert whole["ekf"]["sensors"]["ahrs"]["ok"]

    drift = HEADING_OFFSET + HEADING_DRIFT * estimate["t"][-1]
    _run(_rig(folder, bag, data, 'topic = "/imu/drifting"', "pulled"), tmp_path / "pulled", "ekf")
    estimate = np.load(tmp_path / "pulled" / "ekf.npz")
    assert abs(_yaw(estimate["C"][-1] @ states.C[0].T) - drift) < 0.05

    metrics = _run(_rig(folder, bag, data, 'topic = "/imu/drifting"\nroll_pitch_only = true', "tilt"),
                   tmp_path / "tilt")
    assert metrics["_run"]["world_frame"]["yaw"] == "relative to the start"
    for name in ("batch", "fixed-lag", "ekf"):
        estimate = np.load(tmp_path / "tilt" / f"{name}.npz")
        r_true, C_true = _truth_in_odometry_frame(data, estimate)
        assert abs(_yaw(estimate["C"][-1] @ C_true.T)) < 0.05, name  # no trace of the drift
        tilt = so3.log(estimate["C"][-1] @ C_true.T)[:2]
        assert np.abs(tilt).max() < 0.01, name
        assert _within_covariance(estimate, r_true) < CHI2_3, name
        assert metrics[name]["sensors"]["ahrs"]["ok"], name


def test_roll_pitch_only_is_refused_on_other_kinds_and_an_imu_without_orientation_in_one_line(recording, tmp_path,
                                                                                              capsys):
    data, folder, bag = recording
    rig = _rig(folder, bag, data, 'topic = "/imu/raw"', "raw")
    assert main(["run", "--rig", rig, "--estimator", "ekf", "--out", str(tmp_path / "raw"), "--no-progress"]) == 2
    err = capsys.readouterr().err.strip().splitlines()[-1]
    assert "run.bag" in err and "topic /imu/raw" in err and "orientation_covariance[0] = -1, REP-145" in err, err
    text = open(_rig(folder, bag, data)).read()
    text = text.replace('kind = "velocity"', 'kind = "velocity"\nroll_pitch_only = true')
    (folder / "bad.toml").write_text(text)
    assert main(["run", "--rig", str(folder / "bad.toml"), "--estimator", "ekf", "--out", str(tmp_path / "bad"),
                 "--no-progress"]) == 2
    err = capsys.readouterr().err.strip().splitlines()[-1]
    assert 'sensor[1] "wheel".roll_pitch_only: expected only on an orientation sensor' in err, err
