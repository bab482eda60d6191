"""CSV sources: the EuRoC/ASL layouts and the generic layout of each stream, read to the arrays
written, and malformed files as one error naming file, line and column."""
from __future__ import annotations

import numpy as np
import pytest

from datasets.csv_sources import read_csv_fixes, read_csv_imu, read_csv_poses, read_csv_twists
from datasets.errors import DataError
from datasets.streams import seconds
from factors import quaternion, so3

NS0 = 1_403_636_579_758_555_392


def _rng_poses(n=20, seed=0):
    rng = np.random.default_rng(seed)
    t = 1.7e9 + np.cumsum(rng.uniform(0.01, 0.1, n))
    return t, rng.normal(scale=10, size=(n, 3)), so3.exp(rng.normal(size=(n, 3)))


def test_euroc_imu_layout_keeps_nanoseconds(tmp_path):
    rng = np.random.default_rng(1)
    t_ns = NS0 + 5_000_000 * np.arange(201)  # a second at 200 Hz, the shortest recording read
    gyro, acc = rng.normal(size=(201, 3)), rng.normal(size=(201, 3))
    rows = [f"{s},{','.join(repr(float(x)) for x in (*g, *a))}" for s, g, a in zip(t_ns, gyro, acc)]
    path = tmp_path / "data.csv"
    path.write_text("#timestamp [ns],w_RS_S_x [rad s^-1],w_RS_S_y [rad s^-1],w_RS_S_z [rad s^-1],"
                    "a_RS_S_x [m s^-2],a_RS_S_y [m s^-2],a_RS_S_z [m s^-2]\n" + "\n".join(rows) + "\n")
    imu = read_csv_imu(path)
    assert np.array_equal(imu.t_ns, t_ns) and np.array_equal(imu.t, seconds(t_ns))
    assert np.array_equal(imu.acc, acc) and np.array_equal(imu.gyro, gyro)


def test_euroc_ground_truth_layout(tmp_path):
    _, p, C = _rng_poses()
    t_ns = NS0 + 5_000_000 * np.arange(len(p))
    q = quaternion.from_matrix(C)
    rest = ",0,0,0,0,0,0,0,0,0"
    path = tmp_path / "data.csv"
    path.write_text("#timestamp, p_RS_R_x [m], p_RS_R_y [m], p_RS_R_z [m], q_RS_w [], q_RS_x [], q_RS_y [], q_RS_z [], "
                    "v_RS_R_x [m s^-1], v_RS_R_y [m s^-1], v_RS_R_z [m s^-1], b_w_RS_S_x [rad s^-1], "
                    "b_w_RS_S_y [rad s^-1], b_w_RS_S_z [rad s^-1], b_a_RS_S_x [m s^-2], b_a_RS_S_y [m s^-2], "
                    "b_a_RS_S_z [m s^-2]\n"
                    + "".join(f"{s},{','.join(repr(float(x)) for x in (*pp, *qq))}{rest}\n"
                              for s, pp, qq in zip(t_ns, p, q)))
    poses = read_csv_poses(path)
    assert np.array_equal(poses.t_ns, t_ns) and np.array_equal(poses.position, p) and poses.cov is None
    assert np.abs(poses.C - C).max() < 1e-14


def test_generic_poses_any_column_order_with_sigmas(tmp_path):
    t, p, C = _rng_poses()
    q = quaternion.from_matrix(C)
    sig = np.array([0.1, 0.2, 0.3, 0.01, 0.02, 0.03])
    path = tmp_path / "poses.csv"
    columns = "qw,qx,qy,qz,t,x,y,z,sigma_x,sigma_y,sigma_z,sigma_rx,sigma_ry,sigma_rz"
    path.write_text(f"# {columns}\n\n" + "".join(
        ",".join(repr(float(x)) for x in (*qq, tt, *pp, *sig)) + "\n" for tt, pp, qq in zip(t, p, q)))
    poses = read_csv_poses(path)
    assert np.array_equal(poses.t, t) and np.array_equal(poses.position, p) and poses.t_ns is None
    assert np.abs(poses.C - C).max() < 1e-14 and np.allclose(poses.cov, np.diag(sig**2))
    path.write_text("t,x,y,z,qw,qx,qy,qz\n" + "".join(
        ",".join(repr(float(x)) for x in (tt, *pp, *qq)) + "\n" for tt, pp, qq in zip(t, p, q)))
    assert read_csv_poses(path).cov is None


def test_generic_velocities_and_fixes(tmp_path):
    rng = np.random.default_rng(3)
    t = 10 + 0.1 * np.arange(8)
    v, w = rng.normal(size=(8, 3)), rng.normal(size=(8, 3))
    path = tmp_path / "v.csv"
    path.write_text("t,vx,vy,vz\n" + "".join(",".join(repr(float(x)) for x in (tt, *vv)) + "\n"
                                             for tt, vv in zip(t, v)))
    twists = read_csv_twists(path)
    assert np.array_equal(twists.linear, v) and twists.angular is None and twists.cov is None
    path.write_text("t,vx,vy,vz,wx,wy,wz,sigma_vx,sigma_vy,sigma_vz,sigma_wx,sigma_wy,sigma_wz\n" + "".join(
        ",".join(repr(float(x)) for x in (tt, *vv, *ww, 1, 2, 3, 4, 5, 6)) + "\n" for tt, vv, ww in zip(t, v, w)))
    twists = read_csv_twists(path)
    assert np.array_equal(twists.angular, w) and np.allclose(twists.cov[3], np.diag(np.arange(1, 7.0) ** 2))
    path.write_text("t,latitude,longitude,altitude,status,sigma_e,sigma_n,sigma_u\n"
                    "1.0,47.1,8.2,400.5,0,1,1,2\n2.0,0,0,0,-1,1,1,2\n3.0,47.2,8.3,401,2,1,1,2\n")
    fixes = read_csv_fixes(path)
    assert np.array_equal(fixes.status, [0, -1, 2]) and np.array_equal(fixes.latitude, [47.1, 0, 47.2])
    assert np.allclose(fixes.cov[0], np.diag([1, 1, 4.0]))
    path.write_text("t,latitude,longitude,altitude\n1.0,47.1,8.2,400.5\n")
    assert read_csv_fixes(path).status.tolist() == [0] and read_csv_fixes(path).cov is None


@pytest.mark.parametrize("reader, text, line, field, expected", [
    (read_csv_poses, "t,x,y,z,qw,qx,qy\n", 1, "qz", "a column named qz"),
    (read_csv_poses, "t,x,y,z,qw,qx,qy,qz,speed\n", 1, "speed", "columns among t, x"),
    (read_csv_poses, "t,x,y,z,qw,qx,qy,qz,sigma_x\n", 1, "sigma_y", "all of sigma_x"),
    (read_csv_poses, "t,x,y,z,qw,qx,qy,qz\n1,0,0,0,1,0,0,0\n2,0,0,0,0.5,0,0,0\n", 3, "qw qx qy qz", "unit quaternion"),
    (read_csv_poses, "t,x,y,z,qw,qx,qy,qz\n1,0,0,0,1,0,0,0\n1,0,0,0,1,0,0,0\n", 3, "t", "strictly increasing"),
    (read_csv_poses, "t,x,y,z,qw,qx,qy,qz\n1,0,0,zero,1,0,0,0\n", 2, "z", "a number"),
    (read_csv_twists, "t,vx,vy,vz,sigma_vx,sigma_vy,sigma_vz\n1,0,0,0,1,0,1\n", 2, "sigma_vy", "> 0"),
    (read_csv_twists, "t,vx,vy,vz,wx,wy,wz,sigma_vx,sigma_vy,sigma_vz\n1,0,0,0,0,0,0,1,1,1\n", 1, "sigma_vx",
     "sigma_v* and sigma_w*"),
    (read_csv_twists, "t,vx,vy,vz\n", 1, None, "at least 1 velocity lines"),
    (read_csv_fixes, "t,latitude,longitude,altitude,status\n1,47,8,400,0.5\n", 2, "status", "an integer"),
    (read_csv_fixes, "t,latitude,longitude,altitude\n1,47,8,400\n2,-91,8,400\n", 3, "latitude", "within +-90"),
    (read_csv_imu, "", 1, None, "a header"),
])
def test_malformed_files_name_file_line_and_column(tmp_path, reader, text, line, field, expected):
    path = tmp_path / "data.csv"
    path.write_text(text)
    with pytest.raises(DataError) as info:
        reader(path)
    assert (info.value.line, info.value.field) == (line, field), str(info.value)
    assert str(path) in str(info.value) and expected in str(info.value), str(info.value)
