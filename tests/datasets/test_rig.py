"""Rig files: a full rig read into its dataclasses without reading data, paths relative to the
rig's folder, Kalibr files, and every kind of mistake as one line naming file and key."""
from __future__ import annotations

import numpy as np
import pytest

from datasets.gnss import Datum
from datasets.rig import RigError, load_rig
from factors import so3
from factors.imu import ImuNoise

IMU = """[imu]
source = "bag:run.bag"
topic = "/imu/data"
accel_noise_density = 2.0e-3
gyro_noise_density = 1.7e-4
accel_random_walk = 3.0e-3
gyro_random_walk = 1.9e-5
"""
GNSS = """[[sensor]]
name = "gnss"
kind = "gnss"
source = "bag:run.bag"
topic = "/fix"
T_BS = [[1,0,0,0],[0,1,0,0],[0,0,1,0.5],[0,0,0,1]]
"""
FULL = IMU + """gravity = 9.80665
forward = [-2, 0, 0]

[datum]
latitude = 47.0
longitude = 8.0
altitude = 400

""" + GNSS + """time_offset = -0.02
sigma = [0.5, 0.5, 1.0]
every = 2
robust = "cauchy:3"
correlation_time = 20

[[sensor]]
name = "mocap"
kind = "pose"
source = "tum:data/mocap.txt"
sigma = 0.01
"""


def _rig(tmp_path, text, name="rig.toml"):
    path = tmp_path / name
    path.write_text(text)
    return path


def test_a_full_rig(tmp_path):
    rig = load_rig(_rig(tmp_path, FULL))
    assert rig.imu.source == f"bag:{tmp_path / 'run.bag'}" and rig.imu.topic == "/imu/data"
    assert rig.imu.noise == ImuNoise(acc=2.0e-3, gyro=1.7e-4, acc_bias=3.0e-3, gyro_bias=1.9e-5)
    assert rig.imu.gravity == 9.80665 and rig.datum == Datum(47.0, 8.0, 400.0)
    assert rig.imu.forward == (-1.0, 0.0, 0.0)  # a direction: any length
    gnss, mocap = rig.sensors
    assert (gnss.name, gnss.kind, gnss.topic, gnss.time_offset, gnss.every, gnss.robust) == (
        "gnss", "gnss", "/fix", -0.02, 2, ("cauchy", 3.0))
    assert gnss.T_BS[2, 3] == 0.5 and np.array_equal(gnss.sigma, [0.5, 0.5, 1.0])
    assert gnss.correlation_time == 20.0 and mocap.correlation_time is None
    assert not gnss.fit_correlation_time and not mocap.fit_correlation_time
    assert mocap.source == f"tum:{tmp_path / 'data/mocap.txt'}" and mocap.topic is None
    assert np.array_equal(mocap.T_BS, np.eye(4)) and np.array_equal(mocap.sigma, [0.01]) and mocap.robust is None
    assert (mocap.time_offset, mocap.every) == (0.0, 1)


def test_defaults_and_no_sensors(tmp_path):
    rig = load_rig(_rig(tmp_path, IMU.replace('"bag:run.bag"\ntopic = "/imu/data"', '"csv:imu0/data.csv"')))
    assert rig.imu.topic is None and rig.imu.gravity == pytest.approx(9.81) and rig.datum is None
    assert rig.imu.forward == (1.0, 0.0, 0.0)
    assert rig.sensors == ()


def test_kalibr_densities_with_overrides_and_camchain(tmp_path):
    (tmp_path / "calib").mkdir()
    (tmp_path / "calib" / "imu.yaml").write_text(
        "imu0:\n  accelerometer_noise_density: 0.01\n  accelerometer_random_walk: 0.02\n"
        "  gyroscope_noise_density: 0.001\n  gyroscope_random_walk: 0.002\n")
    T_cam_imu = np.eye(4)
    T_cam_imu[:3, :3], T_cam_imu[:3, 3] = so3.exp(np.array([0.1, -0.2, 0.3])), [0.1, 0.2, 0.3]
    (tmp_path / "calib" / "camchain.yaml").write_text(
        "cam0:\n  T_cam_imu: " + str(T_cam_imu.tolist()) + "\n")
    text = ('[imu]\nsource = "csv:imu.csv"\nkalibr = "calib/imu.yaml"\ngyro_random_walk = 5e-5\n'
            '[[sensor]]\nname = "cam"\nkind = "pose"\nsource = "csv:cam.csv"\ncamchain = "calib/camchain.yaml"\n'
            'camera = "cam0"\n')
    rig = load_rig(_rig(tmp_path, text))
    assert rig.imu.noise == ImuNoise(acc=0.01, gyro=0.001, acc_bias=0.02, gyro_bias=5e-5)
    assert np.abs(rig.sensors[0].T_BS @ T_cam_imu - np.eye(4)).max() < 1e-14


def test_a_correlation_time_to_fit(tmp_path):
    gnss = load_rig(_rig(tmp_path, FULL.replace("correlation_time = 20", 'correlation_time = "fit"'))).sensors[0]
    assert gnss.fit_correlation_time and gnss.correlation_time is None


def _replace(old, new):
    return lambda text: text.replace(old, new, 1)


NOT_RIGID = "[[1,0,0,0],[0,1,0,0],[0,0,1.001,0],[0,0,0,1]]"


def test_a_rotation_rounded_by_hand_is_taken_to_the_nearest_one(tmp_path):
    """A T_BS rotation written to 6 decimals (1e-5 from orthonormal) is accepted and made exactly
    orthonormal; the translation is kept."""
    R = so3.exp(np.array([0.3, -0.2, 1.1]))
    rows = ",".join("[" + ",".join(f"{x:.6f}" for x in list(R[i]) + [0.5 * i]) + "]" for i in range(3))
    rig = load_rig(_rig(tmp_path, FULL.replace("T_BS = [[1,0,0,0],[0,1,0,0],[0,0,1,0.5],[0,0,0,1]]",
                                               f"T_BS = [{rows},[0,0,0,1]]")))
    T = rig.sensors[0].T_BS
    assert np.abs(T[:3, :3] @ T[:3, :3].T - np.eye(3)).max() < 1e-14
    assert np.abs(T[:3, :3] - R).max() < 1e-6 and T[:3, 3].tolist() == [0.0, 0.5, 1.0]


@pytest.mark.parametrize("edit, message", [
    (_replace("accel_noise_density", "acel_noise_density"),
     "rig.toml: imu.acel_noise_density: unknown key (did you mean 'accel_noise_density'?); expected one of source,"),
    (_replace("every = 2", "evry = 2"), "rig.toml: sensor[1] \"gnss\".evry: unknown key (did you mean 'every'?)"),
    (_replace("[datum]", "[datums]"), "rig.toml: datums: unknown key (did you mean 'datum'?)"),
    (_replace("gyro_noise_density = 1.7e-4", "gyro_noise_density = \"1.7e-4\""),
     "rig.toml: imu.gyro_noise_density: expected a number, got a string '1.7e-4'"),
    (_replace("gyro_random_walk = 1.9e-5\n", ""),
     "rig.toml: imu.gyro_random_walk: missing; expected a density >= 0"),
    (_replace('name = "mocap"\n', ""), "rig.toml: sensor[2].name: missing"),
    (_replace('topic = "/fix"\n', ""),
     "rig.toml: sensor[1] \"gnss\".topic: missing; a bag source ('bag:run.bag') needs"),
    (_replace('sigma = 0.01', 'sigma = 0.01\ntopic = "/x"'),
     "rig.toml: sensor[2] \"mocap\".topic: only bag sources have"),
    (_replace("T_BS = [[1,0,0,0],[0,1,0,0],[0,0,1,0.5],[0,0,0,1]]", "T_BS = " + NOT_RIGID),
     "rig.toml: sensor[1] \"gnss\".T_BS: expected a rigid transform (rotation orthonormal with det +1 to 0.0001, "
     "last row 0 0 0 1); got a rotation part with"),
    (_replace("[0,0,0,1]]", "[0,0,1,1]]"), "rig.toml: sensor[1] \"gnss\".T_BS: expected a rigid transform"),
    (_replace("T_BS = [[1,0,0,0],", "T_BS = ["), "rig.toml: sensor[1] \"gnss\".T_BS: expected a 4x4 array of numbers"),
    (_replace('name = "mocap"', 'name = "gnss"'),
     "rig.toml: sensor[2] \"gnss\".name: a second sensor named 'gnss'; sensor[1] has that name"),
    (_replace('kind = "pose"', 'kind = "poses"'),
     "rig.toml: sensor[2] \"mocap\".kind: unknown kind 'poses' (did you mean 'pose'?); expected one of pose,"),
    (_replace("sigma = 0.01", "sigma = -0.01"),
     "rig.toml: sensor[2] \"mocap\".sigma: expected standard deviations > 0"),
    (_replace("sigma = [0.5, 0.5, 1.0]", "sigma = []"), "rig.toml: sensor[1] \"gnss\".sigma: expected a standard"),
    (_replace("correlation_time = 20", "correlation_time = 0"),
     "rig.toml: sensor[1] \"gnss\".correlation_time: expected a number > 0, got 0"),
    (_replace("correlation_time = 20", "correlation_time = 1e6"),
     "rig.toml: sensor[1] \"gnss\".correlation_time: expected a value within [0.01, 86400] s"),
    (_replace('kind = "pose"', 'kind = "odometry"\ncorrelation_time = 3'),
     "rig.toml: sensor[2] \"mocap\".correlation_time: odometry measurements are relative"),
    (_replace("correlation_time = 20", 'correlation_time = "fitted"'),
     "rig.toml: sensor[1] \"gnss\".correlation_time: expected a number of seconds or \"fit\", got 'fitted'"),
    (lambda text: text.replace("correlation_time = 20", 'correlation_time = "fit"').replace("every = 2", "every = 1"),
     "rig.toml: sensor[1] \"gnss\".correlation_time: \"fit\" needs held-out measurements to fit it to (every = K > 1)"),
    (_replace('kind = "pose"', 'kind = "odometry"\ncorrelation_time = "fit"\nevery = 3'),
     "rig.toml: sensor[2] \"mocap\".correlation_time: odometry measurements are relative"),
    (_replace("every = 2", "every = 0"), "rig.toml: sensor[1] \"gnss\".every: expected an integer >= 1, got 0"),
    (_replace("every = 2", "every = 1.5"),
     "rig.toml: sensor[1] \"gnss\".every: expected an integer >= 1, got a number"),
    (_replace('robust = "cauchy:3"', 'robust = "hubber"'),
     "rig.toml: sensor[1] \"gnss\".robust: robust kernel 'hubber': expected one of none, huber, cauchy, tukey"),
    (_replace("latitude = 47.0", "latitude = 147.0"),
     "rig.toml: datum.latitude: expected a value within [-90, 90] deg"),
    (_replace("altitude = 400\n", ""), "rig.toml: datum.altitude: missing; expected a number"),
    (_replace('source = "tum:data/mocap.txt"', 'source = "ftp:data/mocap.txt"'),
     "rig.toml: sensor[2] \"mocap\".source: source 'ftp:data/mocap.txt': expected bag:PATH, csv:PATH or tum:PATH"),
    (_replace('source = "bag:run.bag"', 'source = "tum:run.txt"'),
     "rig.toml: imu.source: source 'tum:run.txt': a tum: source has no IMU samples"),
    (_replace("time_offset = -0.02", "time_offset = nan"),
     "rig.toml: sensor[1] \"gnss\".time_offset: expected a finite"),
    (_replace("T_BS = [[1,0,0,0],[0,1,0,0],[0,0,1,0.5],[0,0,0,1]]", 'camchain = "c.yaml"'),
     "rig.toml: sensor[1] \"gnss\".camera: missing; camchain and camera come together"),
    (_replace("T_BS = [[1,0,0,0],[0,1,0,0],[0,0,1,0.5],[0,0,0,1]]",
              "T_BS = [[1,0,0,0],[0,1,0,0],[0,0,1,0.5],[0,0,0,1]]\ncamchain = 'c.yaml'\ncamera = 'cam0'"),
     "rig.toml: sensor[1] \"gnss\".camchain: give either T_BS or camchain, not both"),
    (_replace("[imu]", "[[imu]]"), "rig.toml: imu: expected a table, got an array"),
    (_replace("forward = [-2, 0, 0]", "forward = [0, 0, 0]"),
     "rig.toml: imu.forward: expected the vehicle's forward direction in the IMU frame: 3 finite numbers, not all "
     "zero (e.g. [-1, 0, 0] for an IMU whose x axis points backwards), got [0, 0, 0]"),
    (_replace("forward = [-2, 0, 0]", "forward = [1, 0]"), "rig.toml: imu.forward: expected the vehicle's forward"),
    (_replace("forward = [-2, 0, 0]", 'forward = "-x"'),
     "rig.toml: imu.forward: expected the vehicle's forward direction in the IMU frame: 3 numbers, got a string"),
    (lambda text: IMU + '[sensor]\nname = "gnss"\n',
     "rig.toml: sensor: expected an array of tables ([[sensor]]), got a table"),
    (_replace("gravity = 9.80665", "gravity = 9.80665 m/s^2"), "rig.toml: TOML syntax error: Expected newline or end "
     "of document after a statement (at line 8, column 19)"),
    (lambda text: text.split("[datum]")[1].replace("latitude", "[datum]\nlatitude", 1),
     "rig.toml: imu: missing; expected an [imu] table"),
])
def test_each_mistake_is_one_line_naming_file_and_key(tmp_path, monkeypatch, edit, message):
    monkeypatch.chdir(tmp_path)
    text = edit(FULL)
    assert text != FULL
    _rig(tmp_path, text)
    with pytest.raises(RigError) as info:
        load_rig("rig.toml")
    assert str(info.value).startswith(message) and "\n" not in str(info.value), str(info.value)


def test_a_camchain_error_names_the_rig_key_and_the_camchain(tmp_path):
    (tmp_path / "c.yaml").write_text("cam0:\n  T_cam_imu: [[1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 0]]\n")
    text = FULL.replace("T_BS = [[1,0,0,0],[0,1,0,0],[0,0,1,0.5],[0,0,0,1]]", "camchain = 'c.yaml'\ncamera = 'cam0'")
    with pytest.raises(RigError, match=r"sensor\[1\] \"gnss\"\.camchain: .*c\.yaml, line 2, field 'cam0.T_cam_imu'"):
        load_rig(_rig(tmp_path, text))
    with pytest.raises(RigError, match=r"rig2.toml: no such file"):
        load_rig(tmp_path / "rig2.toml")
