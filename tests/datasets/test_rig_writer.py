"""Rig files written back (``calibrated.toml``): the user's comments, key order and blank lines
survive, the calibrated values are in place, the calibration keys become a comment after the
sensor's values, paths are absolute, a Kalibr file and a camchain give way to their values; and
the file reads as a rig again."""
from __future__ import annotations

import sys

import numpy as np

from datasets.rig import load_rig
from datasets.rig_writer import calibrated_rig_text
from factors import so3

if sys.version_info >= (3, 11):
    import tomllib
else:
    import tomli as tomllib

RIG = """\
# The lab's test cart, recorded 2024-05-02.
[imu]
source = "csv:imu.csv"   # the IMU at 200 Hz
kalibr = "calib/imu.yaml"   # densities from the Kalibr run
gyro_random_walk = 5e-5

# the wheel speed sensor on the left axle
[[sensor]]
name = "wheel"       # odometry from the CAN bus
kind = "velocity"
source = "csv:wheel.csv"
# measured by hand with a ruler
T_BS = [[1.0, 0.0, 0.0, 0.1], [0.0, 1.0, 0.0, 0.0], [0.0, 0.0, 1.0, 0.0], [0.0, 0.0, 0.0, 1.0]]
scale = 1.02   # the tyre's nominal radius
estimate = ["rotation", "scale"]
rotation_sigma = 0.1   # about 6 degrees

# the camera, pose from a visual odometry
[[sensor]]
name = "cam"
kind = "pose"
source = "csv:cam.csv"
camchain = "calib/camchain.yaml"   # Kalibr
camera = "cam0"
"""


def _rig(tmp_path):
    (tmp_path / "calib").mkdir()
    (tmp_path / "calib" / "imu.yaml").write_text(
        "imu0:\n  accelerometer_noise_density: 0.01\n  accelerometer_random_walk: 0.02\n"
        "  gyroscope_noise_density: 0.001\n  gyroscope_random_walk: 0.002\n")
    T_cam_imu = np.eye(4)
    T_cam_imu[:3, :3], T_cam_imu[:3, 3] = so3.exp(np.array([0.1, -0.2, 0.3])), [0.1, 0.2, 0.3]
    (tmp_path / "calib" / "camchain.yaml").write_text("cam0:\n  T_cam_imu: " + str(T_cam_imu.tolist()) + "\n")
    path = tmp_path / "rig.toml"
    path.write_text(RIG)
    return load_rig(path)


def test_a_calibrated_rig_keeps_the_users_comments_and_layout(tmp_path):
    rig = _rig(tmp_path)
    T_BS = np.eye(4)
    T_BS[:3, :3] = so3.exp(np.array([0.0, 0.05, 0.01]))
    records = {"wheel": {"T_BS": T_BS.tolist(), "scale": 0.99}}
    text = calibrated_rig_text(rig, records, {"wheel": "its residuals are 2 per dof"})
    lines = text.splitlines()

    for comment in ("# The lab's test cart, recorded 2024-05-02.", "# the wheel speed sensor on the left axle",
                    "# measured by hand with a ruler", "# the camera, pose from a visual odometry"):
        assert comment in lines, comment
    assert f'source = "csv:{tmp_path / "imu.csv"}"   # the IMU at 200 Hz' in lines  # absolute, comment kept
    assert 'name = "wheel"       # odometry from the CAN bus' in lines
    assert "gyro_random_walk = 5e-5" in lines  # the rig's own density as written, the Kalibr file's beside it
    assert "accel_noise_density = 0.01" in lines
    assert f"scale = {1.02 * 0.99!r}   # the tyre's nominal radius" in lines  # in place, comment kept
    # the wheel's values in their order, then the calibration's comments, then the camera's comment
    wheel = lines.index('name = "wheel"       # odometry from the CAN bus')
    assert [line.split(" =")[0] for line in lines[wheel:wheel + 6] if "=" in line] == [
        "name", "kind", "source", "T_BS", "scale"]
    calibrated = lines.index('# calibrated by the batch smoother; estimated with estimate = ["rotation", "scale"], '
                             "rotation_sigma = 0.1")
    assert lines[calibrated + 1] == "# caution: its residuals are 2 per dof"
    assert calibrated < lines.index("# the camera, pose from a visual odometry")
    assert "kalibr" not in text and "camchain" not in text and "camera =" not in text

    written = tmp_path / "calibrated.toml"
    written.write_text(text)
    again = load_rig(written)
    assert again.imu.noise == rig.imu.noise and again.imu.source == rig.imu.source
    wheel, cam = again.sensors
    assert wheel.calibrate is None and np.allclose(wheel.T_BS, T_BS, atol=1e-15)
    assert wheel.scale == 1.02 * 0.99
    assert np.allclose(cam.T_BS, rig.sensors[1].T_BS, atol=1e-15)


def test_a_rig_without_calibration_comes_back_as_written_but_for_the_paths(tmp_path):
    path = tmp_path / "rig.toml"
    text = '# a comment\n[imu]\nsource = "csv:imu.csv"  # here\naccel_noise_density = 2.0e-3\n' \
           'gyro_noise_density = 1.7e-4\naccel_random_walk = 3.0e-3\ngyro_random_walk = 1.9e-5\n'
    path.write_text(text)
    out = calibrated_rig_text(load_rig(path), {})
    body = out.splitlines()[3:]  # after the header and its blank line
    assert body == text.replace('"csv:imu.csv"', f'"csv:{tmp_path / "imu.csv"}"').splitlines()
    assert tomllib.loads(out)["imu"]["accel_noise_density"] == 2.0e-3


def test_a_correlation_time_the_run_modelled_is_written_in_and_one_the_rig_gave_stays(tmp_path):
    """A correlation time given on the command line (the noise was fitted with it) is written into the
    sensor's table, with a comment saying where it came from; one the rig gave itself is left as written."""
    rig = _rig(tmp_path)
    text = calibrated_rig_text(rig, {}, None, None, {"wheel": 5.0, "cam": None})
    again = tomllib.loads(text)
    wheel, cam = again["sensor"]
    assert wheel["correlation_time"] == 5.0 and "correlation_time" not in cam
    assert "# correlation_time: as the run modelled it (--correlation-time)" in text
    path = tmp_path / "calibrated.toml"
    path.write_text(text)
    assert load_rig(path).sensors[0].correlation_time == 5.0
    same = calibrated_rig_text(load_rig(path), {}, None, None, {"wheel": 5.0})
    assert same.count("correlation_time = 5.0") == 1 and same.count("as the run modelled it") == 1


def test_a_fitted_correlation_time_is_written_in_as_fitted_and_a_white_fit_takes_the_key_out(tmp_path):
    """A correlation time fitted to the held-out measurements replaces the rig's ``"fit"``, with a
    comment saying so, and reads back as a number; fitted white, the key goes: the errors are white."""
    _rig(tmp_path)  # its files
    path = tmp_path / "rig.toml"
    path.write_text(RIG.replace('kind = "velocity"', 'kind = "velocity"\ncorrelation_time = "fit"\nevery = 4', 1))
    rig = load_rig(path)
    assert rig.sensors[0].fit_correlation_time
    text = calibrated_rig_text(rig, {}, None, None, {"wheel": 7.5}, ("wheel",))
    assert tomllib.loads(text)["sensor"][0]["correlation_time"] == 7.5
    assert '# correlation_time: this, fitted to the held-out measurements (correlation_time = "fit" fits it again)' \
        in text
    (tmp_path / "calibrated.toml").write_text(text)
    again = load_rig(tmp_path / "calibrated.toml").sensors[0]
    assert again.correlation_time == 7.5 and not again.fit_correlation_time
    white = calibrated_rig_text(rig, {}, None, None, {}, ("wheel",))
    assert "correlation_time" not in tomllib.loads(white)["sensor"][0]
    assert "# correlation_time: white, fitted to the held-out measurements" in white
