"""``smoother run --mcap``: ``estimates.mcap`` read back with rosbags, every field against the
run's ``.npz`` (stamps in the bag's clock, frames, pose and twist with their covariances in ROS's
order, ``/tf``, the fixes in latitude/longitude); the world frame REP-105 names; a write that fails
leaves no file behind."""
from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from rosbags.highlevel import AnyReader
from small_recording import DATUM, WHEEL, write_recording

from datasets.atomic import STAGING_PREFIX
from datasets.gnss import enu_to_geodetic
from datasets.initialise import world_frame
from datasets.kinds import sensors_of
from datasets.simulate import simulate
from datasets.simulated_sensors import SensorSpec
from factors import imu, quaternion
from smoother.cli import main
from smoother.commands import dataset_specs
from smoother.commands.run_directory import LOCK, RunDirectory
from smoother.outputs import files
from smoother.outputs import mcap as mcap_export

ESTIMATORS = ("batch", "fixed-lag", "ekf")


def _read(path: Path) -> dict:
    """``{topic: (message type, [(log time, message)])}`` of an MCAP file, and the log times of
    all messages in the file's order under the key ``None``."""
    out: dict = {None: []}
    with AnyReader([path]) as reader:
        for connection, at, raw in reader.messages():
            message = reader.deserialize(raw, connection.msgtype)
            out.setdefault(connection.topic, (connection.msgtype, []))[1].append((at, message))
            out[None].append(at)
    return out


def _stamp(message) -> int:
    return message.header.stamp.sec * 1_000_000_000 + message.header.stamp.nanosec


@pytest.fixture(scope="module")
def run(tmp_path_factory):
    folder = tmp_path_factory.mktemp("mcap")
    rig, _ = write_recording(folder)
    out = folder / "out"
    assert main(["run", "--rig", str(rig), "--estimator", "all", "--out", str(out), "--no-progress", "--mcap"]) == 0
    return rig, out, _read(out / "estimates.mcap")


def test_odometry_of_each_estimator_is_its_npz(run):
    """Per estimator one Odometry per state: the header stamp (and log time) is the npz's time in
    the bag's clock; frame ``map`` (GNSS fixes the position), child ``base_link``; position,
    attitude, pose covariance = the npz's (dr, dphi) block; twist = body velocity and gyro less
    its bias, with the (dv, -db_w) covariance and the gyro's white noise on the rate."""
    rig, out, messages = run
    dataset, _ = dataset_specs.load_rig_dataset(rig)
    gyro_variance = dataset.noise.gyro**2 / np.median(np.diff(dataset.imu.t))
    for name in ESTIMATORS:
        trajectory, origin = files.load_stamped_trajectory(out / f"{name}.npz")
        msgtype, got = messages[f"/{name.replace('-', '_')}/odometry"]
        assert msgtype == "nav_msgs/msg/Odometry" and len(got) == len(trajectory)
        s, P = trajectory.states, trajectory.cov
        ns = origin + np.round(trajectory.t * 1e9).astype(np.int64)
        held = np.searchsorted(dataset.imu.t, trajectory.t, side="right") - 1
        for k, (at, m) in enumerate(got):
            assert at == _stamp(m) == ns[k]
            assert (m.header.frame_id, m.child_frame_id) == ("map", "base_link")
            p, q = m.pose.pose.position, m.pose.pose.orientation
            np.testing.assert_array_equal([p.x, p.y, p.z], s.r[k])
            np.testing.assert_allclose(quaternion.to_matrix(np.array([q.w, q.x, q.y, q.z])), s.C[k], atol=1e-12)
            pose = np.r_[imu.R, imu.PHI]
            np.testing.assert_array_equal(m.pose.covariance.reshape(6, 6), P[k][np.ix_(pose, pose)])
            v, w = m.twist.twist.linear, m.twist.twist.angular
            np.testing.assert_array_equal([v.x, v.y, v.z], s.v[k])
            np.testing.assert_allclose([w.x, w.y, w.z], dataset.imu.gyro[held[k]] - s.b_w[k], rtol=0, atol=1e-15)
            twist = m.twist.covariance.reshape(6, 6)
            np.testing.assert_array_equal(twist[:3, :3], P[k][imu.V, imu.V])
            np.testing.assert_array_equal(twist[:3, 3:], -P[k][imu.V, imu.BW])
            np.testing.assert_allclose(twist[3:, 3:], P[k][imu.BW, imu.BW] + gyro_variance * np.eye(3), rtol=1e-12)


def test_tf_carries_the_batch_estimate(run):
    _, out, messages = run
    trajectory, origin = files.load_stamped_trajectory(out / "batch.npz")
    msgtype, got = messages["/tf"]
    assert msgtype == "tf2_msgs/msg/TFMessage" and len(got) == len(trajectory)
    for k, (at, m) in enumerate(got):
        (tf,) = m.transforms
        assert at == _stamp(tf) == origin + round(trajectory.t[k] * 1e9)
        assert (tf.header.frame_id, tf.child_frame_id) == ("map", "base_link")
        r, q = tf.transform.translation, tf.transform.rotation
        np.testing.assert_array_equal([r.x, r.y, r.z], trajectory.position[k])
        np.testing.assert_allclose(quaternion.to_matrix(np.array([q.w, q.x, q.y, q.z])), trajectory.C[k], atol=1e-12)


def test_fixes_give_latitude_longitude_with_the_position_covariance(run):
    _, out, messages = run
    for name in ESTIMATORS:
        trajectory, origin = files.load_stamped_trajectory(out / f"{name}.npz")
        msgtype, got = messages[f"/{name.replace('-', '_')}/fix"]
        assert msgtype == "sensor_msgs/msg/NavSatFix" and len(got) == len(trajectory)
        lat, lon, alt = enu_to_geodetic(trajectory.position, DATUM)
        for k, (at, m) in enumerate(got):
            assert at == _stamp(m) and m.header.frame_id == "base_link" and m.status.status == 0
            assert (m.latitude, m.longitude, m.altitude) == (lat[k], lon[k], alt[k])
            assert m.position_covariance_type == 3
            np.testing.assert_array_equal(m.position_covariance.reshape(3, 3), trajectory.cov[k][imu.R, imu.R])


def test_messages_are_in_time_order_and_nothing_else_is_in_the_file(run):
    _, _, messages = run
    assert messages[None] == sorted(messages[None])
    expected = {f"/{name.replace('-', '_')}/{leaf}" for name in ESTIMATORS for leaf in ("odometry", "fix")} | {"/tf"}
    assert set(messages) - {None} == expected


def test_without_covariances_they_are_zero_and_fixes_say_unknown(run, tmp_path):
    """``--no-covariance``, the batch smoother alone: covariances all zero (unknown to ROS tools),
    fixes of covariance type unknown."""
    rig, _, _ = run
    out = tmp_path / "out"
    assert main(["run", "--rig", str(rig), "--estimator", "batch", "--out", str(out), "--no-progress", "--mcap",
                 "--no-covariance"]) == 0
    messages = _read(out / "estimates.mcap")
    assert set(messages) - {None} == {"/batch/odometry", "/batch/fix", "/tf"}
    for _, m in messages["/batch/odometry"][1]:
        assert not m.pose.covariance.any() and not m.twist.covariance.any()
    for _, m in messages["/batch/fix"][1]:
        assert m.position_covariance_type == 0 and not m.position_covariance.any()


def test_the_world_frame_is_map_with_a_position_sensor_and_odom_without():
    """REP-105: a pose, position or GNSS sensor fixes the position in the world (``map``);
    attitudes, velocities and relative poses alone leave it relative to the start (``odom``)."""
    def frame(**kwargs):
        return world_frame(sensors_of(simulate("gentle", duration=2.0, imu_rate=100.0, **kwargs))).frame_id

    assert frame() == "map"  # poses
    assert frame(pose_rate=None, sensors=[SensorSpec("gnss", "gnss", 1, 0.5)]) == "map"
    assert frame(pose_rate=None, position_rate=2.0) == "map"
    assert frame(pose_rate=None, sensors=[SensorSpec("wheel", "velocity", 10, 0.05, WHEEL)],
                 orientation_rate=10.0, odometry_rate=5.0) == "odom"
    assert frame(pose_rate=None) == "odom"  # dead reckoning


def test_a_failure_while_writing_leaves_the_previous_run_whole(tmp_path, monkeypatch, capsys):
    """The MCAP goes through the run directory's staging: when writing it fails part-way, neither
    a partial ``estimates.mcap`` nor any other file of the new run reaches the directory, and no
    hidden folder stays behind."""
    out = tmp_path / "run"
    args = ["run", "--duration", "2", "--estimator", "ekf", "--out", str(out), "--no-progress"]
    assert main(args) == 0
    before = {p.name: p.read_bytes() for p in out.iterdir() if p.name != LOCK}
    written = []

    def failing(self, *a):
        if len(written) == 20:
            raise OSError(28, "No space left on device")
        written.append(1)
        return original(self, *a)

    original = mcap_export.Messages.odometry
    monkeypatch.setattr(mcap_export.Messages, "odometry", failing)
    assert main(args + ["--mcap"]) == 2
    assert "No space left on device" in capsys.readouterr().err
    assert {p.name: p.read_bytes() for p in out.iterdir() if p.name != LOCK} == before
    assert not list(out.glob(f"{STAGING_PREFIX}*"))


def test_a_killed_runs_half_written_mcap_folder_is_cleared(tmp_path):
    """A run killed (SIGKILL) while rosbags wrote the MCAP leaves its hidden bag folder in the
    staging folder: the next run into the directory deletes both."""
    folder = tmp_path / f"{STAGING_PREFIX}123-abcd" / ".estimates.mcap.0a1b2c3d.tmp"
    folder.mkdir(parents=True)
    (folder / ".estimates.mcap.0a1b2c3d.tmp.mcap").write_bytes(b"\x89MCAP0\r\n")
    with RunDirectory(tmp_path):
        pass
    assert not list(tmp_path.glob(f"{STAGING_PREFIX}*"))

