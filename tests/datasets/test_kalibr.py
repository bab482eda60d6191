"""Kalibr imu.yaml and camchain readers, and the YAML reading they share (OpenCV header,
duplicate keys, errors with file, line and key)."""
from __future__ import annotations

import numpy as np
import pytest

from datasets.errors import DataError
from datasets.kalibr import read_camchain_T_BS, read_kalibr_imu, rigid_problem
from datasets.yamlfile import read_yaml
from factors import so3

DENSITIES = ("accelerometer_noise_density: 2.0e-3\naccelerometer_random_walk: 3.0e-3\n"
             "gyroscope_noise_density: 1.7e-4\ngyroscope_random_walk: 1.9e-5\n")
EXPECTED = {"acc": 2.0e-3, "acc_bias": 3.0e-3, "gyro": 1.7e-4, "gyro_bias": 1.9e-5}


def test_imu_yaml_flat_or_in_one_imu_entry(tmp_path):
    path = tmp_path / "imu.yaml"
    path.write_text("rostopic: /imu0\nupdate_rate: 200.0\n" + DENSITIES)
    assert read_kalibr_imu(path) == EXPECTED
    path.write_text("imu0:\n  rostopic: /imu0\n" + "".join("  " + line + "\n" for line in DENSITIES.splitlines()))
    assert read_kalibr_imu(path) == EXPECTED
    path.write_text("imu0:\n  gyroscope_noise_density: -1.0\n")
    with pytest.raises(DataError,
                       match=r"line 2, field 'imu0.gyroscope_noise_density': found -1.0; expected a number >= 0"):
        read_kalibr_imu(path)
    path.write_text("rostopic: /imu0\n")
    with pytest.raises(DataError, match="no noise densities"):
        read_kalibr_imu(path)


def test_camchain_T_cam_imu_is_inverted(tmp_path):
    rng = np.random.default_rng(2)
    T_cam_imu = np.eye(4)
    T_cam_imu[:3, :3], T_cam_imu[:3, 3] = so3.exp(rng.normal(size=3)), rng.normal(size=3)
    rows = "\n".join("  - [" + ", ".join(repr(float(x)) for x in row) + "]" for row in T_cam_imu)
    path = tmp_path / "camchain.yaml"
    path.write_text("cam0:\n  camera_model: pinhole\n  T_cam_imu:\n" + rows + "\n"
                    "cam1:\n  T_cam_imu: [[1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1]]\n")
    T_BS = read_camchain_T_BS(path, "cam0")
    assert np.abs(T_BS @ T_cam_imu - np.eye(4)).max() < 1e-14
    with pytest.raises(DataError,
                       match=r"found \"no camera 'cam2'\"; expected one of the cameras in the file: cam0, cam1"):
        read_camchain_T_BS(path, "cam2")
    path.write_text("cam0:\n  T_cam_imu: [[1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 2, 0], [0, 0, 0, 1]]\n")
    with pytest.raises(DataError, match=r"line 2, field 'cam0.T_cam_imu': found 'a rotation part"):
        read_camchain_T_BS(path, "cam0")


def test_rigid_problem():
    T = np.eye(4)
    assert rigid_problem(T) is None
    T[:3, :3] = so3.exp(np.array([0.1, 0.2, 0.3])) * (1 + 2e-6)
    assert "rotation part" in rigid_problem(T)
    assert "last row" in rigid_problem(np.diag([1.0, 1, 1, 2]))
    assert "shape (3, 3)" in rigid_problem(np.eye(3))


def test_yaml_opencv_header_duplicates_and_syntax(tmp_path):
    path = tmp_path / "x.yaml"
    path.write_text("%YAML:1.0\nK: !!opencv-matrix\n  rows: 1\n  cols: 1\n  dt: d\n  data: [2.5]\n")
    doc = read_yaml(path)
    assert doc.data["K"]["data"] == [2.5] and doc.lines[("K", "data", 0)] == 6
    path.write_text("a: 1\nb:\n  c: 2\n  c: 3\n")
    with pytest.raises(DataError, match=r"line 4, field 'b.c': found \"a second 'c:' \(the first at line 3\)\""):
        read_yaml(path)
    path.write_text("a: [1, 2\nb: 3\n")
    with pytest.raises(DataError, match=r"x\.yaml, line 2: .*expected valid YAML"):
        read_yaml(path)
