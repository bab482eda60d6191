"""Source specs: each scheme reaches its reader with the path relative to the base folder, and a
spec that cannot give the stream asked for is one error naming the spec."""
from __future__ import annotations

import numpy as np
import pytest
from bagfiles import Messages, write_bag

from datasets.sources import parse_spec, read_fixes, read_imu, read_poses, read_twists
from datasets.tum import write_tum
from factors import so3


def test_schemes_read_relative_to_the_base_folder(tmp_path):
    m = Messages("ros1")
    write_bag(tmp_path / "run.bag", "ros1", {"/imu": ("sensor_msgs/msg/Imu", [
        m.imu(10**18 + k * 10**7, (0, 0, 9.81), (0, 0, k)) for k in range(101)])})
    imu = read_imu("bag:run.bag", "/imu", tmp_path)
    assert np.array_equal(imu.gyro[:, 2], np.arange(101)) and imu.t_ns[0] == 10**18
    t = np.array([1.0, 2.0])
    write_tum(tmp_path / "sub" / "traj.txt", t, np.ones((2, 3)), so3.exp(np.zeros((2, 3))))
    assert np.array_equal(read_poses("tum:sub/traj.txt", base_dir=tmp_path).t, t)
    (tmp_path / "v.csv").write_text("t,vx,vy,vz\n1,2,3,4\n")
    assert read_twists(f"csv:{tmp_path / 'v.csv'}", None, "/elsewhere").linear.tolist() == [[2, 3, 4]]
    (tmp_path / "fix.csv").write_text("t,latitude,longitude,altitude\n1,47,8,400\n")
    assert read_fixes("csv:fix.csv", base_dir=tmp_path).altitude.tolist() == [400]


@pytest.mark.parametrize("call, message", [
    (lambda: read_imu("tum:traj.txt"), "a tum: source has no IMU samples; IMU samples come from bag: or csv:"),
    (lambda: read_fixes("tum:traj.txt"), "a tum: source has no GNSS fixes"),
    (lambda: read_poses("ros:run.bag", "/pose"), "'ros:run.bag': expected bag:PATH, csv:PATH or tum:PATH"),
    (lambda: read_poses("run.bag", "/pose"), "'run.bag': expected bag:PATH"),
    (lambda: read_poses("bag:", "/pose"), "no path after 'bag:'"),
    (lambda: read_imu("bag:run.bag"), "'bag:run.bag': a bag needs a topic"),
    (lambda: read_imu("csv:imu.csv", "/imu"), "a topic ('/imu') is only for bag sources"),
])
def test_bad_specs_are_one_error_naming_the_spec(call, message):
    with pytest.raises(ValueError) as info:
        call()
    assert message in str(info.value), str(info.value)


def test_parse_spec_reads_nothing(tmp_path):
    assert parse_spec("bag:missing/run.bag", tmp_path, "poses") == ("bag", tmp_path / "missing/run.bag")
    assert parse_spec("csv:/abs/imu.csv", tmp_path) == ("csv", parse_spec("csv:/abs/imu.csv")[1])
