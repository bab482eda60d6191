"""ROS bags (ROS 1, ROS 2 sqlite3, MCAP) written from simulated data read back to the same
arrays, by header stamp; and the errors naming the bag and the topic."""
from __future__ import annotations

import numpy as np
import pytest
from bagfiles import FORMATS, Messages, bag_path, storage_file, write_bag

from datasets.bags import (
    read_bag_attitudes,
    read_bag_fixes,
    read_bag_imu,
    read_bag_magnetic_fields,
    read_bag_poses,
    read_bag_pressures,
    read_bag_twists,
)
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
        "ahrs_cov": np.array([_cov(rng, 3) * 1e-4 for _ in poses]),
        "pressure": 95_000 + rng.normal(size=len(poses)) * 10, "pressure_var": np.r_[0.0, np.full(len(poses) - 1, 4.0)],
        "field": rng.normal(size=(len(poses), 3)) * 3e-5, "field_cov": np.array([_cov(rng, 3) * 1e-14 for _ in poses]),
    }


def _write(folder, fmt, data):
    m = Messages(fmt)
    q = quaternion.from_matrix(data["C"])
    n_pose = len(data["pose_ns"])
    imu = [m.imu(*row) for row in zip(data["imu_ns"], data["acc"], data["gyro"])]
    imu[3], imu[4] = imu[4], imu[3]  # written out of order, received in stamp order: read in receive order
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
        "/twist": ("geometry_msgs/msg/TwistStamped", [m.twist_stamped(*row) for row in zip(
            data["pose_ns"], data["v"], data["w"])]),
        "/twist_cov": ("geometry_msgs/msg/TwistWithCovarianceStamped", [m.twist_with_covariance(*row) for row in zip(
            data["pose_ns"], data["v"], data["w"], data["twist_cov"])]),
        "/pressure": ("sensor_msgs/msg/FluidPressure", [m.fluid_pressure(*row) for row in zip(
            data["pose_ns"], data["pressure"], data["pressure_var"])]),
        "/mag": ("sensor_msgs/msg/MagneticField", [m.magnetic_field(*row) for row in zip(
            data["pose_ns"], data["field"], data["field_cov"])]),
        "/ahrs": ("sensor_msgs/msg/Imu", [m.imu(t, a, w, qq, c) for t, a, w, qq, c in zip(
            data["pose_ns"], data["acc"], data["gyro"], q, data["ahrs_cov"])]),
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


@pytest.mark.parametrize("topic, has_cov", [("/odom", True), ("/twist_cov", True), ("/twist", False),
                                            ("/odom_nocov", False)])
def test_twists_of_every_message_type(bag, data, topic, has_cov):
    """Odometry's twist, TwistWithCovarianceStamped and TwistStamped (no covariance)."""
    twists = read_bag_twists(bag[1], topic)
    assert np.array_equal(twists.t_ns, data["pose_ns"])
    assert np.array_equal(twists.linear, data["v"]) and np.array_equal(twists.angular, data["w"])
    if has_cov:
        assert np.array_equal(twists.cov, data["twist_cov"])
    else:
        assert twists.cov is None


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


def test_attitudes_of_an_imu_topic_and_of_poses(bag, data):
    """An Imu topic's orientation with its orientation_covariance (row major, 3x3); a pose
    topic's attitude with the rotation block of its covariance."""
    ahrs = read_bag_attitudes(bag[1], "/ahrs")
    assert np.array_equal(ahrs.t_ns, data["pose_ns"]) and np.abs(ahrs.C - data["C"]).max() < 1e-14
    assert np.array_equal(ahrs.cov, data["ahrs_cov"])
    poses = read_bag_attitudes(bag[1], "/odom")
    assert np.abs(poses.C - data["C"]).max() < 1e-14 and np.array_equal(poses.cov, data["cov"][:, 3:, 3:])
    assert read_bag_attitudes(bag[1], "/pose").cov is None


def test_pressures_and_magnetic_fields(bag, data):
    """FluidPressure with its variance (0: unknown, NaN) and MagneticField with its covariance."""
    pressures = read_bag_pressures(bag[1], "/pressure")
    assert np.array_equal(pressures.t_ns, data["pose_ns"]) and np.array_equal(pressures.pressure, data["pressure"])
    assert np.isnan(pressures.variance[0]) and np.array_equal(pressures.variance[1:], data["pressure_var"][1:])
    fields = read_bag_magnetic_fields(bag[1], "/mag")
    assert np.array_equal(fields.field, data["field"]) and np.array_equal(fields.cov, data["field_cov"])
    with pytest.raises(DataError, match=r"topic /mag.*sensor_msgs/msg/MagneticField.*pressures: sensor_msgs/msg/Fluid"):
        read_bag_pressures(bag[1], "/mag")


def test_an_imu_without_orientation_is_refused_as_attitudes_in_one_line(bag):
    """REP-145: orientation_covariance[0] = -1 says the IMU gives no orientation."""
    fmt, path = bag
    with pytest.raises(DataError) as info:
        read_bag_attitudes(path, "/imu")
    message = str(info.value)
    assert "\n" not in message and str(path) in message and "topic /imu" in message, message
    assert "without an orientation (orientation_covariance[0] = -1, REP-145)" in message, message


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
    with pytest.raises(DataError, match=r"run\.bag, field 'topic /imu': found an unreadable bag"):
        read_bag_imu(path, "/imu")


def _imu_bag(folder, fmt, stamps_ns, received_ns=None, seed=0, bz2=False):
    """A bag of ``sensor_msgs/Imu`` messages on ``/imu`` with the header stamps given (random,
    non-zero readings; ROS 1 chunks compressed with ``bz2``); returns ``(bag, acc, gyro)``."""
    rng = np.random.default_rng(seed)
    acc, gyro = rng.normal(size=(len(stamps_ns), 3)) + 1.0, rng.normal(size=(len(stamps_ns), 3)) + 1.0
    m = Messages(fmt)
    messages = [m.imu(t, a, g) for t, a, g in zip(stamps_ns, acc, gyro)]
    topic = ("sensor_msgs/msg/Imu", messages) + (() if received_ns is None else (received_ns,))
    folder.mkdir(parents=True, exist_ok=True)
    return write_bag(bag_path(folder, fmt), fmt, {"/imu": topic}, bz2=bz2), acc, gyro


@pytest.mark.parametrize("fmt, bz2", [(fmt, False) for fmt in FORMATS] + [("ros1", True)])
def test_a_damaged_bag_reads_whole_or_is_one_error(tmp_path, fmt, bz2):
    """64 bytes zeroed at offsets through the whole file: every read is either the package's
    error naming the bag and the topic, or all the messages with their stamps. (A message's
    payload has no checksum in these formats: bytes zeroed inside the readings change the
    message they hit, and only it.)"""
    stamps = T0_NS + STEP_NS * np.arange(200)
    bag, acc, gyro = _imu_bag(tmp_path, fmt, stamps, bz2=bz2)
    storage = bag if fmt == "ros1" else storage_file(bag, fmt)
    original = storage.read_bytes()
    errors = reads = 0
    for offset in range(0, len(original), len(original) // 48):
        damaged = bytearray(original)
        damaged[offset:offset + 64] = bytes(64)
        storage.write_bytes(bytes(damaged))
        try:
            imu = read_bag_imu(bag, "/imu")
        except DataError as error:
            assert str(bag) in str(error) and "topic /imu" in str(error), (offset, str(error))
            errors += 1
            continue
        reads += 1
        assert np.array_equal(imu.t_ns, stamps), offset
        changed = np.any((imu.acc != acc) | (imu.gyro != gyro), axis=1)
        assert changed.sum() <= 2, offset  # 64 bytes reach into two messages of ~300 bytes at most
    assert errors and reads  # both outcomes occur: the offsets hit the bag's structure and its payloads


@pytest.mark.parametrize("fmt", FORMATS)
def test_a_clock_stepping_back_is_refused_as_in_a_csv_file(tmp_path, fmt):
    """Header stamps stepping back 5 s at message 101 (received in order): the bag reader stops
    as the CSV reader stops on the same stamps, naming the bag, the topic, the message and both
    stamps; nothing is re-sorted."""
    from datasets.csv_sources import read_csv_imu

    stamps = T0_NS + STEP_NS * np.arange(200)
    stamps[100:] -= 5_000_000_000
    bag, acc, gyro = _imu_bag(tmp_path, fmt, stamps, received_ns=T0_NS + STEP_NS * np.arange(200) + 1_000_000)
    with pytest.raises(DataError) as info:
        read_bag_imu(bag, "/imu")
    assert str(info.value) == (
        f"{bag}, field 'topic /imu, header stamp [ns]': found message 101 stamped {stamps[100]}, earlier than "
        f"message 100 ({stamps[99]}); expected strictly increasing time stamps, message after message")

    csv = tmp_path / "imu.csv"
    csv.write_text("#timestamp [ns],w_RS_S_x,w_RS_S_y,w_RS_S_z,a_RS_S_x,a_RS_S_y,a_RS_S_z\n" + "".join(
        f"{t},{g[0]},{g[1]},{g[2]},{a[0]},{a[1]},{a[2]}\n" for t, a, g in zip(stamps, acc, gyro)))
    with pytest.raises(DataError, match=rf"line 102, field 'timestamp \[ns\]': found {stamps[100]}, earlier than line "
                                        rf"101 \({stamps[99]}\); expected strictly increasing"):
        read_csv_imu(csv)


@pytest.mark.parametrize("reader, topic", [(read_bag_poses, "/pose"), (read_bag_fixes, "/fix"),
                                           (read_bag_twists, "/odom")])
def test_every_stream_keeps_the_time_order_rule(tmp_path, reader, topic):
    """Poses, fixes and twists: a stamp repeated (message 3 as message 2), received in order,
    is refused as the IMU's would be."""
    m = Messages("ros1")
    stamps = T0_NS + STEP_NS * np.array([0, 1, 1, 2])
    p, q, cov = np.zeros(3), (1.0, 0.0, 0.0, 0.0), np.eye(6)
    messages = {
        "/pose": ("geometry_msgs/msg/PoseStamped", [m.pose_stamped(t, p, q) for t in stamps]),
        "/fix": ("sensor_msgs/msg/NavSatFix", [m.fix(t, 47.0, 8.0, 400.0, 0, np.eye(3), 3) for t in stamps]),
        "/odom": ("nav_msgs/msg/Odometry", [m.odometry(t, p, q, cov, p, p, cov) for t in stamps]),
    }
    msgtype, topic_messages = messages[topic]
    bag = write_bag(tmp_path / "run.bag", "ros1",
                    {topic: (msgtype, topic_messages, T0_NS + STEP_NS * np.arange(4) + 1_000_000)})
    with pytest.raises(DataError, match=rf"field 'topic {topic}, header stamp \[ns\]': found message 3 stamped "
                                        rf"{stamps[2]}, a duplicate of message 2 \({stamps[1]}\)"):
        reader(bag, topic)


def test_an_imu_topic_of_one_message_is_refused(tmp_path):
    """One IMU message is no IMU stream: refused by the reader with how many there are, how many
    are needed and why."""
    bag, _, _ = _imu_bag(tmp_path, "ros1", [T0_NS])
    with pytest.raises(DataError) as info:
        read_bag_imu(bag, "/imu")
    assert str(info.value).startswith(f"{bag}, field 'topic /imu': found 1 IMU sample over 0 s; expected an IMU "
                                      "recording of at least 50 samples over at least 1 s (")
