"""Recordings that used to run and mislead, or fail and point the wrong way: ``load_recording``
given a path, sensors whose CSV files were asked for columns they do not use, and IMU recordings
too short for anything fitted to them (at least MIN_RECORDING_SAMPLES samples over
MIN_RECORDING_SECONDS from every loader, with an error naming the file)."""
from __future__ import annotations

import re
from pathlib import Path

import numpy as np
import pytest
from bagfiles import Messages, write_bag
from rigfiles import imu_table

from datasets import kitti
from datasets.csv_sources import read_csv_fixes, read_csv_magnetic_fields, read_csv_pressures, read_csv_twists
from datasets.errors import DataError
from datasets.euroc import load_euroc
from datasets.kinds import sensors_of
from datasets.recording import load_recording
from datasets.rig import load_rig
from datasets.simulate import simulate
from datasets.simulated_sensors import SensorSpec
from datasets.sources import read_attitudes, read_imu, read_positions
from datasets.types import MIN_RECORDING_SAMPLES, MIN_RECORDING_SECONDS
from factors import quaternion
from factors.errors import InputError

T0 = 1_600_000_000.0
IMU_HEADER = ("#timestamp [ns],w_RS_S_x [rad s^-1],w_RS_S_y [rad s^-1],w_RS_S_z [rad s^-1],"
              "a_RS_S_x [m s^-2],a_RS_S_y [m s^-2],a_RS_S_z [m s^-2]")


@pytest.fixture(scope="module")
def data():
    return simulate("gentle", duration=6, seed=3, pose_rate=None,
                    sensors=[SensorSpec("antenna", "position", 5, 0.05), SensorSpec("ahrs", "orientation", 10, 0.01)])


def _imu_csv(path: Path, t, gyro, acc) -> Path:
    ns = np.round((T0 + np.asarray(t)) * 1e9).astype(np.int64)
    rows = [f"{n}," + ",".join(repr(float(x)) for x in (*g, *a)) for n, g, a in zip(ns, gyro, acc)]
    path.write_text(IMU_HEADER + "\n" + "\n".join(rows) + "\n")
    return path


def _rig(folder: Path, data, sensors: str) -> Path:
    _imu_csv(folder / "imu.csv", data.imu.t, data.imu.gyro, data.imu.acc)
    rig = folder / "rig.toml"
    rig.write_text(imu_table("csv:imu.csv", data.noise) + sensors)
    return rig


def _positions_csv(path: Path, m, columns: str = "t,x,y,z,sigma_x,sigma_y,sigma_z") -> None:
    rows = [",".join(repr(float(x)) for x in (T0 + t, *p)) + ",0.05,0.05,0.05" for t, p in zip(m.t, m.position)]
    path.write_text(columns + "\n" + "\n".join(rows) + "\n")


def _attitudes_csv(path: Path, m) -> None:
    q = quaternion.from_matrix(m.C)
    rows = [",".join(repr(float(x)) for x in (T0 + t, *qq)) + ",0.01,0.01,0.01" for t, qq in zip(m.t, q)]
    path.write_text("t,qw,qx,qy,qz,sigma_rx,sigma_ry,sigma_rz\n" + "\n".join(rows) + "\n")


@pytest.mark.parametrize("given", ["rig.toml", Path("rig.toml"), {"imu": {}}, None])
def test_load_recording_of_anything_but_a_rig_says_to_read_the_rig_first(given):
    with pytest.raises(InputError) as info:
        load_recording(given)
    message = str(info.value)
    assert message.startswith(f"load_recording: expected a Rig, got a {type(given).__name__}")
    assert "datasets.load_rig(path)" in message and "\n" not in message
    if isinstance(given, (str, Path)):
        assert "'rig.toml'" in message


def test_a_position_and_an_attitude_file_need_only_their_own_columns(tmp_path, data):
    """A position sensor's CSV of ``t,x,y,z`` (no quaternion) and an orientation sensor's of
    ``t,qw,qx,qy,qz`` (no position) run as recordings, measured as simulated."""
    antenna, ahrs = data.sensors
    _positions_csv(tmp_path / "antenna.csv", antenna.data)
    _attitudes_csv(tmp_path / "ahrs.csv", ahrs.data)
    rig = _rig(tmp_path, data, '\n[[sensor]]\nname = "antenna"\nkind = "position"\nsource = "csv:antenna.csv"\n'
                               '\n[[sensor]]\nname = "ahrs"\nkind = "orientation"\nsource = "csv:ahrs.csv"\n')
    recording = load_recording(load_rig(rig))
    got = {s.name: s for s in sensors_of(recording)}
    k = np.searchsorted(antenna.data.t, got["antenna"].data.t[0] - 1e-9)
    np.testing.assert_allclose(got["antenna"].data.position, antenna.data.position[k:], atol=1e-9)
    np.testing.assert_allclose(got["antenna"].data.cov[0], np.diag([0.05**2] * 3))
    k = np.searchsorted(ahrs.data.t, got["ahrs"].data.t[0] - 1e-9)
    np.testing.assert_allclose(got["ahrs"].data.C, ahrs.data.C[k:], atol=1e-12)
    np.testing.assert_allclose(got["ahrs"].data.cov[0], np.diag([0.01**2] * 3))


def test_a_pose_file_still_serves_positions_and_attitudes(tmp_path, data):
    m = data.sensors[0].data
    q = np.tile([1.0, 0, 0, 0], (len(m.t), 1))
    rows = [",".join(repr(float(x)) for x in (T0 + t, *p, *qq)) + ",0.1,0.1,0.1,0.2,0.2,0.2"
            for t, p, qq in zip(m.t, m.position, q)]
    path = tmp_path / "poses.csv"
    path.write_text("t,x,y,z,qw,qx,qy,qz,sigma_x,sigma_y,sigma_z,sigma_rx,sigma_ry,sigma_rz\n" + "\n".join(rows) + "\n")
    positions, attitudes = read_positions(f"csv:{path}"), read_attitudes(f"csv:{path}")
    np.testing.assert_array_equal(positions.position, m.position)
    np.testing.assert_allclose(positions.cov[0], np.diag([0.01] * 3))
    np.testing.assert_allclose(attitudes.C, np.tile(np.eye(3), (len(m.t), 1, 1)))
    np.testing.assert_allclose(attitudes.cov[0], np.diag([0.04] * 3))


@pytest.mark.parametrize("kind, columns, missing", [
    ("pose", "t,x,y,z", "qw"), ("odometry", "t,x,y,z", "qw"), ("pose", "t,qw,qx,qy,qz", "x"),
    ("position", "t,x,y,z,qw,qx", "qy"),  # an optional group comes whole or not at all
])
def test_a_kind_that_uses_the_columns_still_needs_them(tmp_path, data, kind, columns, missing):
    m = data.sensors[0].data
    n = len(columns.split(","))
    (tmp_path / "s.csv").write_text(columns + "\n" + "\n".join(repr(float(T0 + t)) + ",0" * (n - 1) for t in m.t)
                                    + "\n")
    sigma = "sigma = [0.1, 0.1]\n" if kind in ("pose", "odometry") else "sigma = 0.1\n"
    rig = _rig(tmp_path, data, f'\n[[sensor]]\nname = "s"\nkind = "{kind}"\nsource = "csv:s.csv"\n{sigma}')
    with pytest.raises(InputError, match=re.escape(f"{tmp_path / 's.csv'}, line 1, field '{missing}': ")):
        load_recording(load_rig(rig))


@pytest.mark.parametrize("read, text", [
    (read_csv_twists, "t,vx,vy,vz\n1,0,0,0\n"),
    (read_csv_fixes, "t,latitude,longitude,altitude\n1,47,8,400\n"),
    (read_csv_pressures, "t,pressure\n1,95000\n"),
    (read_csv_magnetic_fields, "t,mx,my,mz\n1,2e-5,0,-4e-5\n"),
], ids=["velocities", "fixes", "pressures", "magnetic fields"])
def test_every_other_kinds_file_needs_only_its_own_columns(tmp_path, read, text):
    path = tmp_path / "s.csv"
    path.write_text(text)
    assert len(read(path)) == 1


def _short(n: int, seconds: float):
    t = np.linspace(0.0, seconds, n)
    return t, np.zeros((n, 3)), np.tile([0.0, 0.0, 9.81], (n, 1))


@pytest.mark.parametrize("n, seconds", [(2, 0.01), (1, 0.0), (MIN_RECORDING_SAMPLES - 1, 10.0),
                                        (1000, MIN_RECORDING_SECONDS * 0.99)])
def test_an_imu_recording_too_short_is_refused_by_every_loader_naming_the_file(tmp_path, n, seconds):
    t, gyro, acc = _short(n, seconds)
    expected = (f"found {n} IMU sample{'s' if n != 1 else ''} over {seconds:.4g} s; expected an IMU recording of at "
                f"least {MIN_RECORDING_SAMPLES} samples over at least {MIN_RECORDING_SECONDS:g} s (")
    csv = _imu_csv(tmp_path / "imu.csv", t, gyro, acc)
    if n >= 2:  # the CSV layout itself needs two lines
        with pytest.raises(DataError, match=re.escape(f"{csv}: {expected}")):
            read_imu(f"csv:{csv}")
    m = Messages("ros1")
    bag = write_bag(tmp_path / "run.bag", "ros1", {"/imu": ("sensor_msgs/msg/Imu", [
        m.imu(int(round((T0 + s) * 1e9)), a, g) for s, a, g in zip(t, acc, gyro)])})
    with pytest.raises(DataError, match=re.escape(f"{bag}, field 'topic /imu': {expected}")):
        read_imu("bag:run.bag", "/imu", tmp_path)
    rig = tmp_path / "rig.toml"
    rig.write_text(imu_table("bag:run.bag", simulate("gentle", duration=1, seed=0).noise, topic="/imu"))
    with pytest.raises(DataError, match=re.escape(f"{bag}, field 'topic /imu': {expected}")):
        load_recording(load_rig(rig))


def test_a_recording_of_the_minimum_reads(tmp_path):
    t, gyro, acc = _short(MIN_RECORDING_SAMPLES, MIN_RECORDING_SECONDS)
    assert len(read_imu(f"csv:{_imu_csv(tmp_path / 'imu.csv', t, gyro, acc)}")) == MIN_RECORDING_SAMPLES


def test_a_short_kitti_or_euroc_imu_file_is_refused_naming_it(tmp_path):
    lines = ["Time dt accelX accelY accelZ omegaX omegaY omegaZ"]
    lines += [f"{k * 0.01:.2f} 0.01 0 0 9.8 0 0 0" for k in range(20)]
    (tmp_path / "imu.txt").write_text("\n".join(lines) + "\n")
    with pytest.raises(DataError, match=re.escape(f"{tmp_path / 'imu.txt'}: found 20 IMU samples over 0.19 s")):
        kitti.read_imu(tmp_path / "imu.txt")
    (tmp_path / "mav0" / "imu0").mkdir(parents=True)
    t, gyro, acc = _short(10, 0.05)
    _imu_csv(tmp_path / "mav0" / "imu0" / "data.csv", t, gyro, acc)
    (tmp_path / "mav0" / "imu0" / "sensor.yaml").write_text(
        "T_BS:\n  cols: 4\n  rows: 4\n  data: [1, 0, 0, 0, 0, 1, 0, 0, 0, 0, 1, 0, 0, 0, 0, 1]\n")
    (tmp_path / "mav0" / "state_groundtruth_estimate0").mkdir()
    (tmp_path / "mav0" / "state_groundtruth_estimate0" / "sensor.yaml").write_text(
        (tmp_path / "mav0" / "imu0" / "sensor.yaml").read_text())
    (tmp_path / "mav0" / "state_groundtruth_estimate0" / "data.csv").write_text("#timestamp\n")
    with pytest.raises(DataError, match=re.escape(f"{tmp_path / 'mav0' / 'imu0' / 'data.csv'}: found 10 IMU samples")):
        load_euroc(tmp_path)


@pytest.mark.parametrize("read, header, row, column, value, expected", [
    (read_positions, "t,x,y,z,sigma_x,sigma_y,sigma_z", "1,0,0,0,{v},0.1,0.1", "sigma_x", "1e-12", "[0.0001, 10000] m"),
    (read_positions, "t,x,y,z,sigma_x,sigma_y,sigma_z", "1,0,0,0,0.1,{v},0.1", "sigma_y", "1e300", "[0.0001, 10000] m"),
    (read_csv_fixes, "t,latitude,longitude,altitude,sigma_e,sigma_n,sigma_u", "1,47,8,400,0.5,0.5,{v}", "sigma_u",
     "1e12", "[0.0001, 10000] m"),
    (read_attitudes, "t,qw,qx,qy,qz,sigma_rx,sigma_ry,sigma_rz", "1,1,0,0,0,{v},0.01,0.01", "sigma_rx", "4.0",
     "[1e-06, 3.14159] rad"),
    (read_csv_twists, "t,vx,vy,vz,sigma_vx,sigma_vy,sigma_vz", "1,0,0,0,0.05,0.05,{v}", "sigma_vz", "1e-9",
     "[0.0001, 100] m/s"),
    (read_csv_pressures, "t,pressure,sigma_pressure", "1,95000,{v}", "sigma_pressure", "1e-300", "[1e-150, 1e+150]"),
    (read_csv_magnetic_fields, "t,mx,my,mz,sigma_mx,sigma_my,sigma_mz", "1,2e-5,0,-4e-5,{v},1e-7,1e-7", "sigma_mx",
     "1e200", "[1e-150, 1e+150]"),
], ids=["position 1e-12", "position 1e300", "fix 1e12", "attitude 4 rad", "velocity 1e-9", "pressure 1e-300",
        "field 1e200"])
def test_a_sigma_column_beyond_its_units_range_is_refused_naming_file_line_and_column(tmp_path, read, header, row,
                                                                                       column, value, expected):
    """The rig's sigma had its range per unit, a CSV's sigma columns were only > 0: a fix's 1e-12 m
    made every estimator fail on numbers double precision cannot hold, 1e300 overflowed when
    squared ("overflow encountered in square", then a covariance "not finite" naming no file),
    1e12 m left the run unable to find its heading."""
    path = tmp_path / "s.csv"
    path.write_text(f"{header}\n{row.format(v=value)}\n")
    spec = read in (read_positions, read_attitudes)
    with pytest.raises(DataError) as info:
        read(f"csv:{path}") if spec else read(path)
    message = str(info.value)
    assert message.startswith(f"{path}, line 2, field '{column}': found ") and f"within {expected}" in message, message
