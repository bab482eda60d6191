"""ROS bags (ROS 1, ROS 2 sqlite3, MCAP) written from simulated data read back to the same
arrays, by header stamp; and the errors naming the bag and the topic."""
from __future__ import annotations

import numpy as np
import pytest
from bagfiles import FORMATS, Messages, bag_path, storage_file, write_bag

from datasets.bags import read_bag_fixes, read_bag_imu, read_bag_poses, read_bag_twists
from datasets.errors import DataError
from datasets.simulate import simulate
from datasets.streams import seconds
from factors import quaternion

T0_NS = 1_700_000_000_123_456_789  # seconds since the epoch need t_ns to stay exact
STEP_NS = 10_000_000


def _cov(rng, dim):
    a = rng.normal(size=(dim, dim))
    return a @ a.T + dim * np.eye(dim)


@pytest.fixture(scope="module")
def data():
    d = simulate(duration=1.0, imu_rate=100.0, pose_rate=10.0, seed=4)
    rng = np.random.default_rng(0)
    n_imu, truth = len(d.imu), d.truth
    poses = np.arange(0, len(truth), 10)
    return {
        "imu_ns": T0_NS + STEP_NS * np.arange(n_imu), "acc": d.imu.acc, "gyro": d.imu.gyro,
        "pose_ns": T0_NS + STEP_NS * poses, "p": truth.position[poses], "C": truth.C[poses],
        "v": truth.states.v[poses], "w": rng.normal(size=(len(poses), 3)),
        "cov": np.array([_cov(rng, 6) for _ in poses]), "twist_cov": np.array([_cov(rng, 6) for _ in poses]),
        "lat": 47.0 + rng.normal(scale=1e-4, size=len(poses)), "lon": 8.0 + rng.normal(scale=1e-4, size=len(poses)),
        "alt": 400 + rng.normal(size=len(poses)), "fix_cov": np.array([_cov(rng, 3) for _ in poses]),
    }


def _write(folder, fmt, data):
    m = Messages(fmt)
    q = quaternion.from_matrix(data["C"])
    n_pose = len(data["pose_ns"])
    imu = [m.imu(*row) for row in zip(data["imu_ns"], data["acc"], data["gyro"])]
    imu[3], imu[4] = imu[4], imu[3]  # recorded out of stamp order: read back sorted by header stamp
    cov_type = [3, 2, 0] * n_pose
    status = [0] * n_pose
    status[1] = -1  # no fix: NaN position, no covariance
    fixes = [m.fix(t, np.nan if s < 0 else la, np.nan if s < 0 else lo, np.nan if s < 0 else al, s, c, k)
             for t, la, lo, al, s, c, k in zip(data["pose_ns"], data["lat"], data["lon"], data["alt"], status,
                                               data["fix_cov"], cov_type)]
    zero = np.zeros((6, 6))
    topics = {
        "/imu": ("sensor_msgs/msg/Imu", imu),
        "/odom": ("nav_msgs/msg/Odometry", [m.odometry(*row) for row in zip(
            data["pose_ns"], data["p"], q, data["cov"], data["v"], data["w"], data["twist_cov"])]),
        "/odom_nocov": ("nav_msgs/msg/Odometry", [m.odometry(t, p, qq, zero, v, w, zero) for t, p, qq, v, w in zip(
            data["pose_ns"], data["p"], q, data["v"], data["w"])]),
        "/pose": ("geometry_msgs/msg/PoseStamped", [m.pose_stamped(*row) for row in zip(data["pose_ns"], data["p"],
                                                                                        q)]),
        "/pose_cov": ("geometry_msgs/msg/PoseWithCovarianceStamped", [
            m.pose_with_covariance(*row) for row in zip(data["pose_ns"], data["p"], q, data["cov"])]),
        "/tf_base": ("geometry_msgs/msg/TransformStamped", [m.transform(*row) for row in zip(data["pose_ns"],
                                                                                               data["p"], q)]),
        "/fix": ("sensor_msgs/msg/NavSatFix", fixes),
        "/empty": ("sensor_msgs/msg/Imu", []),
    }
    return write_bag(bag_path(folder, fmt), fmt, topics)


@pytest.fixture(scope="module", params=FORMATS)
def bag(request, tmp_path_factory, data):
    return request.param, _write(tmp_path_factory.mktemp(request.param), request.param, data)


def test_imu_reads_back_exactly_by_header_stamp(bag, data):
    fmt, path = bag
    for where in [path] + ([] if fmt == "ros1" else [storage_file(path, fmt)]):  # a ROS 2 folder or its file
        imu = read_bag_imu(where, "/imu")
        assert np.array_equal(imu.t_ns, data["imu_ns"]) and np.array_equal(imu.t, seconds(data["imu_ns"]))
        assert np.array_equal(imu.acc, data["acc"]) and np.array_equal(imu.gyro, data["gyro"])


@pytest.mark.parametrize("topic, has_cov", [("/odom", True), ("/pose_cov", True), ("/pose", False),
                                            ("/tf_base", False), ("/odom_nocov", False)])
def test_poses_of_every_message_type(bag, data, topic, has_cov):
    poses = read_bag_poses(bag[1], topic)
    assert np.array_equal(poses.t_ns, data["pose_ns"]) and np.array_equal(poses.position, data["p"])
    assert np.abs(poses.C - data["C"]).max() < 1e-14
    if has_cov:
        assert np.array_equal(poses.cov, data["cov"])
    else:  # all-zero covariances (or none in the message type) are unknown
        assert poses.cov is None


def test_twists_of_odometry(bag, data):
    twists = read_bag_twists(bag[1], "/odom")
    assert np.array_equal(twists.linear, data["v"]) and np.array_equal(twists.angular, data["w"])
    assert np.array_equal(twists.cov, data["twist_cov"]) and read_bag_twists(bag[1], "/odom_nocov").cov is None


def test_fixes_with_covariance_types_per_message(bag, data):
    fixes = read_bag_fixes(bag[1], "/fix")
    assert np.array_equal(fixes.t_ns, data["pose_ns"])
    assert fixes.status[1] == -1 and np.isnan(fixes.latitude[1]) and np.all(fixes.status[[0, 2, 3]] == 0)
    keep = fixes.status >= 0
    assert np.array_equal(fixes.latitude[keep], data["lat"][keep]) and np.array_equal(fixes.altitude[keep],
                                                                                      data["alt"][keep])
    assert np.array_equal(fixes.cov[0], data["fix_cov"][0])  # type 3, known
    assert np.array_equal(fixes.cov[1], np.diag(np.diag(data["fix_cov"][1])))  # type 2: the diagonal only
    assert np.all(np.isnan(fixes.cov[2]))  # type 0: unknown


def test_errors_name_the_bag_and_the_topic(bag, tmp_path):
    fmt, path = bag
    with pytest.raises(DataError, match="no such file"):
        read_bag_imu(tmp_path / "missing.bag", "/imu")
    with pytest.raises(DataError) as info:
        read_bag_imu(path, "/imu0")
    message = str(info.value)
    assert str(path) in message and "'/imu0'" in message and "/imu (sensor_msgs/msg/Imu)" in message, message
    assert "/fix (sensor_msgs/msg/NavSatFix)" in message, message
    with pytest.raises(DataError, match=r"topic /fix.*sensor_msgs/msg/NavSatFix.*IMU samples: sensor_msgs/msg/Imu"):
        read_bag_imu(path, "/fix")
    with pytest.raises(DataError, match=r"topic /imu.*sensor_msgs/msg/Imu.*poses: nav_msgs/msg/Odometry or"):
        read_bag_poses(path, "/imu")
    with pytest.raises(DataError, match="topic /empty.*no messages"):
        read_bag_imu(path, "/empty")


def test_a_file_that_is_no_bag(tmp_path):
    path = tmp_path / "run.bag"
    path.write_text("not a bag\n")
    with pytest.raises(DataError, match=r"run\.bag: found 'an unreadable bag"):
        read_bag_imu(path, "/imu")
