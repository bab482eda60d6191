"""KITTI loader: GTSAM's shipped example data, small files written here, and malformed copies."""
from __future__ import annotations

import tempfile
from pathlib import Path

import gtsam
import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from datasets import kitti
from datasets.errors import DataError
from datasets.kitti import load_kitti, read_gps, read_imu, read_metadata
from factors import so3


@pytest.fixture(scope="module")
def real():
    return load_kitti()


@pytest.fixture(scope="module")
def real_files():
    return {name: Path(gtsam.findExampleDataFile(name))
            for name in (kitti.IMU_FILE, kitti.GPS_FILE, kitti.METADATA_FILE)}


# ------------------------------------------------------------------------------------------
# the real data


def test_real_data_noise_gravity_and_start(real, real_files):
    meta = read_metadata(real_files[kitti.METADATA_FILE])
    assert real.name == "kitti"
    assert np.array_equal(real.gravity, [0.0, 0.0, -9.8])
    assert real.noise.acc == meta.accelerometer_sigma == 0.01
    assert real.noise.gyro == meta.gyroscope_sigma == 0.000175
    assert real.noise.velocity == meta.integration_sigma == 0.0
    # bias sigmas are per-sample random-walk steps: density = sigma / sqrt(dt)
    assert meta.accelerometer_bias_sigma == 0.000167 and meta.gyroscope_bias_sigma == 2.91e-6
    assert real.noise.acc_bias == pytest.approx(0.000167 / np.sqrt(meta.average_delta_t), rel=1e-12)
    assert real.noise.gyro_bias == pytest.approx(2.91e-6 / np.sqrt(meta.average_delta_t), rel=1e-12)
    assert 9.0 < real.noise.acc_bias / 0.000167 < 11.0
    t_gps, p_gps, _ = read_gps(real_files[kitti.GPS_FILE])
    # Fix 1 is the start (as in GTSAM's example): the IMU begins exactly at its time.
    assert real.imu.t[0] == t_gps[1]
    assert np.array_equal(real.initial.r, p_gps[1])
    # All later fixes are measurements with gps_every=1; GTSAM's example's GPS variance.
    assert np.array_equal(real.sensor("gps").data.t, t_gps[2:])
    assert np.array_equal(real.sensor("gps").data.position, p_gps[2:])
    assert real.sensor("gps").heldout is None
    assert np.allclose(real.sensor("gps").data.cov, 0.07 * np.eye(3))
    # The lone first IMU sample and the 1.9 s gap are left out; the rest is a 100 Hz stream that
    # misses a sample here and there.
    assert np.diff(real.imu.t).max() < 0.021
    imu, _ = read_imu(real_files[kitti.IMU_FILE])
    k = int(np.flatnonzero(imu.t == t_gps[1])[0])  # fix times are sample times in this file
    assert k > 1 and len(real.imu) == len(imu) - k
    assert np.array_equal(real.imu.acc, imu.acc[k:]) and np.array_equal(real.imu.gyro, imu.gyro[k:])


def test_gps_every_partitions_the_fixes(real_files):
    d = load_kitti(gps_every=10)
    t_gps, _, _ = read_gps(real_files[kitti.GPS_FILE])
    later = t_gps[2:]  # the fixes after fix 1, the first
    # GTSAM's example's rule: fix i of the file is used when i % 10 == 0 (fixes 10, 20, ...)
    assert np.array_equal(d.sensor("gps").data.t, t_gps[10::10][: len(d.sensor("gps").data.t)])
    assert len(d.sensor("gps").data.t) == np.sum(np.arange(2, 2 + len(later)) % 10 == 0)
    assert np.array_equal(np.sort(np.concatenate([d.sensor("gps").data.t, d.sensor("gps").heldout.t])), later)
    assert not set(d.sensor("gps").data.t) & set(d.sensor("gps").heldout.t)
    for bad in (0, -1, 1.5, True):
        with pytest.raises(ValueError, match="gps_every"):
            load_kitti(gps_every=bad)


def test_gps_frame_turns_with_the_imu(real):
    """The GPS course turns as the integrated yaw rate says: the GPS frame is right-handed z-up
    like the IMU's (a left-handed or z-down frame would turn the other way)."""
    t = real.imu.t
    yaw = np.concatenate([[0.0], np.cumsum(real.imu.gyro[:-1, 2] * np.diff(t))])
    gps_t = np.concatenate([[t[0]], real.sensor("gps").data.t])
    gps_p = np.vstack([real.initial.r, real.sensor("gps").data.position])
    vel = np.diff(gps_p[:, :2], axis=0) / np.diff(gps_t)[:, None]
    mid = 0.5 * (gps_t[1:] + gps_t[:-1])
    course = np.unwrap(np.arctan2(vel[:, 1], vel[:, 0]))
    fast = np.linalg.norm(vel, axis=1) > 3.0
    turned_gps = course[fast] - course[fast][0]
    turned_imu = np.interp(mid[fast], t, yaw) - np.interp(mid[fast][0], t, yaw)
    # Over 470 s the car turns by more than 400 degrees; the two agree within 15 degrees.
    assert np.ptp(turned_gps) > np.radians(400)
    assert np.abs(turned_gps - turned_imu).max() < np.radians(15)


def test_initial_state_agrees_with_a_gtsam_solution(real):
    """The documented initial state is within its stated sigmas of what GTSAM's own ImuFactor and
    GPSFactor make of the first 20 s (prior on the attitude loose: 1 rad)."""
    from gtsam.symbol_shorthand import B, V, X

    d = real
    n = 20
    t_fix = np.concatenate([[d.t0], d.sensor("gps").data.t[:n]])
    p_fix = np.vstack([d.initial.r, d.sensor("gps").data.position[:n]])
    params = gtsam.PreintegrationParams.MakeSharedU(9.8)
    params.setAccelerometerCovariance(np.eye(3) * d.noise.acc**2)
    params.setGyroscopeCovariance(np.eye(3) * d.noise.gyro**2)
    params.setIntegrationCovariance(np.eye(3) * 1e-8)
    graph, values = gtsam.NonlinearFactorGraph(), gtsam.Values()
    C0, v0 = d.initial.C, d.initial.C @ d.initial.v
    graph.add(gtsam.PriorFactorPose3(X(0), gtsam.Pose3(gtsam.Rot3(C0), d.initial.r),
                                     gtsam.noiseModel.Diagonal.Sigmas([1, 1, 1, 1, 1, 1.0])))
    graph.add(gtsam.PriorFactorVector(V(0), v0, gtsam.noiseModel.Isotropic.Sigma(3, 100.0)))
    graph.add(gtsam.PriorFactorConstantBias(B(0), gtsam.imuBias.ConstantBias(),
                                            gtsam.noiseModel.Diagonal.Sigmas([0.1] * 3 + [5e-5] * 3)))
    t = d.imu.t
    for i in range(len(t_fix)):
        values.insert(X(i), gtsam.Pose3(gtsam.Rot3(C0), p_fix[i]))
        values.insert(V(i), v0)
        values.insert(B(i), gtsam.imuBias.ConstantBias())
        if i == 0:
            continue
        pim = gtsam.PreintegratedImuMeasurements(params, gtsam.imuBias.ConstantBias())
        for k in np.flatnonzero((t >= t_fix[i - 1]) & (t < t_fix[i])):
            pim.integrateMeasurement(d.imu.acc[k], d.imu.gyro[k], min(t[k + 1], t_fix[i]) - t[k])
        graph.add(gtsam.ImuFactor(X(i - 1), V(i - 1), X(i), V(i), B(i - 1), pim))
        graph.add(gtsam.BetweenFactorConstantBias(B(i - 1), B(i), gtsam.imuBias.ConstantBias(),
                                                  gtsam.noiseModel.Diagonal.Sigmas([1e-3] * 3 + [1e-5] * 3)))
        graph.add(gtsam.GPSFactor(X(i), p_fix[i], gtsam.noiseModel.Isotropic.Sigma(3, 0.3)))
    result = gtsam.LevenbergMarquardtOptimizer(graph, values).optimize()
    pose = result.atPose3(X(0))
    C_opt = pose.rotation().matrix()
    sigma = np.sqrt(np.diag(d.initial_cov))
    attitude_error = so3.boxminus(C_opt, d.initial.C)  # world frame, the error-state convention
    velocity_error = C_opt.T @ result.atVector(V(0)) - d.initial.v
    assert np.all(np.abs(attitude_error) < 2 * sigma[6:9]), attitude_error
    assert np.all(np.abs(velocity_error) < 2 * sigma[3:6]), velocity_error
    assert np.all(np.abs(pose.translation() - d.initial.r) < 2 * sigma[0:3])


# ------------------------------------------------------------------------------------------
# small files written here


IMU_HEADER = "Time dt accelX accelY accelZ omegaX omegaY omegaZ"
META_HEADER = " ".join(kitti.METADATA_FIELDS)


def _write_small(tmp: Path, gps_times=None, meta_values=None, t0=1000.0, n=501, dt=0.01):
    t = [float(x) for x in t0 + dt * np.arange(n)]
    imu_lines = [IMU_HEADER]
    for k, tk in enumerate(t):
        step = tk if k == 0 else tk - t[k - 1]
        imu_lines.append(f"{tk!r} {step!r} 0.1 0.2 9.8 0.001 0.002 {0.01 * k!r}")
    if gps_times is None:
        gps_times = t0 + np.arange(0.0, 5.0, 1.0)
    gps_lines = ["Time,X,Y,Z"] + [f"{float(tg)!r},{float(5.0 * (tg - t0))!r},1.0,0.5" for tg in gps_times]
    meta = meta_values or [0, 0, 0, 0, 0, 0, 0.01, 0.000175, 0, 0.000167, 2.91e-6, dt]
    paths = {"imu_path": tmp / "imu.txt", "gps_path": tmp / "gps.txt", "metadata_path": tmp / "meta.txt"}
    paths["imu_path"].write_text("\n".join(imu_lines) + "\n")
    paths["gps_path"].write_text("\n".join(gps_lines) + "\n")
    paths["metadata_path"].write_text(META_HEADER + "\n" + " ".join(str(v) for v in meta) + "\n")
    return paths


def test_used_fixes_are_counted_from_the_start_of_the_file_like_the_example(tmp_path):
    """GTSAM's example uses fix i when i % gps_skip == 0 with i the fix's number in the file, not
    its number after the first fix: with the first fix at 1 and gps_every=2, fixes 2 and 4 are
    used and 3 is held out (counting after the first would use 3)."""
    paths = _write_small(tmp_path)
    d = load_kitti(**paths, first_gps=1, gps_every=2)
    assert np.allclose(d.sensor("gps").data.t, [1002.0, 1004.0]) and np.allclose(d.sensor("gps").heldout.t, [1003.0])


def test_small_files_with_explicit_paths(tmp_path):
    paths = _write_small(tmp_path)
    d = load_kitti(**paths, first_gps=0, gps_every=2)
    assert d.imu.t[0] == 1000.0 and len(d.imu) == 501
    # fixes 1..4 after the first: 2 and 4 used, 1 and 3 held out
    assert (np.allclose(d.sensor("gps").data.t, [1002.0, 1004.0])
            and np.allclose(d.sensor("gps").heldout.t, [1001.0, 1003.0]))
    # initial state: first fix, course along +x (yaw 0), body velocity (5, 0, 0)
    assert np.array_equal(d.initial.r, [0.0, 1.0, 0.5])
    assert np.allclose(d.initial.C, np.eye(3)) and np.allclose(d.initial.v, [5.0, 0.0, 0.0])
    assert np.allclose(np.sqrt(np.diag(d.initial_cov)),
                       [1, 1, 1, 1, 1, 1, 0.05, 0.05, 0.1, 0.1, 0.1, 0.1, 5e-5, 5e-5, 5e-5])
    with pytest.raises(DataError, match=r"gps\.txt, line 6: found '5 GPS fixes'; expected at least first_gps \+ 2 = 6"):
        load_kitti(**paths, first_gps=4)


def test_gps_fix_between_imu_samples(tmp_path):
    """A fix between two samples keeps its exact time; the IMU starts exactly at the first fix
    with the sample before it held (zero-order hold)."""
    gps = np.array([1000.0 + 0.1234, 1001.0 + 0.0567, 1002.0 + 0.0089, 1003.5])
    paths = _write_small(tmp_path, gps_times=gps)
    d = load_kitti(**paths, first_gps=0)
    imu_all, _ = read_imu(paths["imu_path"])
    assert d.imu.t[0] == gps[0]
    assert np.array_equal(d.sensor("gps").data.t, gps[1:])  # not moved to IMU stamps
    k = int(np.searchsorted(imu_all.t, gps[0])) - 1  # the sample before the fix
    assert imu_all.t[k] < gps[0] < imu_all.t[k + 1]
    assert np.array_equal(d.imu.gyro[0], imu_all.gyro[k])
    assert np.array_equal(d.imu.t[1:], imu_all.t[k + 1:])
    assert np.array_equal(d.imu.gyro[1:], imu_all.gyro[k + 1:])
    # The integrated signal from the fix on is unchanged by the cut.
    full = np.sum(imu_all.gyro[k:-1, 2] * np.diff(np.concatenate([[gps[0]], imu_all.t[k + 1:]])))
    assert np.isclose(np.sum(d.imu.gyro[:-1, 2] * np.diff(d.imu.t)), full, rtol=0, atol=1e-12)


def test_fixes_after_the_imu_are_dropped_and_before_it_refused(tmp_path):
    paths = _write_small(tmp_path, gps_times=1000.0 + np.array([0.0, 1.0, 2.0, 7.0, 9.0]))
    d = load_kitti(**paths, first_gps=0)
    assert np.allclose(d.sensor("gps").data.t, [1001.0, 1002.0])
    paths = _write_small(tmp_path, gps_times=np.array([999.0, 1001.0, 1002.0]))
    with pytest.raises(DataError, match=r"gps\.txt, line 2, field 'Time'.*within the IMU samples"):
        load_kitti(**paths, first_gps=0)


def _corrupt(path: Path, line: int, old: str, new: str) -> None:
    lines = path.read_text().splitlines()
    assert old in lines[line - 1], (old, lines[line - 1])
    lines[line - 1] = lines[line - 1].replace(old, new, 1)
    path.write_text("\n".join(lines) + "\n")


@pytest.mark.parametrize(
    "which, line, old, new, field, expected",
    [
        ("imu_path", 7, " 9.8 ", " nan ", "accelZ", "finite"),
        ("imu_path", 7, " 0.001 ", " ", "omegaZ", "8 fields"),
        ("imu_path", 7, " 0.1 ", " 0.1 0.1 ", None, "8 fields"),
        ("imu_path", 9, "1000.07", "1000.06", "Time", "strictly increasing"),
        ("imu_path", 9, "1000.07", "1000.05", "Time", "strictly increasing"),
        ("imu_path", 9, " 0.01", " 0.02", "dt", "time since the previous sample"),
        ("imu_path", 1, "accelX", "accX", "header", "column names"),
        ("gps_path", 3, ",5.0,", ",abc,", "X", "a number"),
        ("gps_path", 4, ",0.5", "", "Z", "4 fields"),
        ("gps_path", 4, "1002.0,", "1001.0,", "Time", "strictly increasing"),
        ("metadata_path", 2, "0.01 ", "-0.01 ", "AccelerometerSigma", ">= 0"),
        ("metadata_path", 2, "0 0 0 0 0 0 ", "0 0 0.1 0 0 0 ", "BodyPtz", "identity"),
        ("metadata_path", 2, " 0.01\n", " 0.03\n", "AverageDeltaT", "mean IMU step"),
    ],
)
def test_malformed_small_files(tmp_path, which, line, old, new, field, expected):
    paths = _write_small(tmp_path)
    if which == "metadata_path" and old.endswith("\n"):
        text = paths[which].read_text().replace(old, new)
        paths[which].write_text(text)
    else:
        _corrupt(paths[which], line, old, new)
    with pytest.raises(DataError) as info:
        load_kitti(**paths, first_gps=0)
    message = str(info.value)
    assert str(paths[which]) in message and f"line {line}" in message, message
    assert expected in message
    if field is not None:
        assert info.value.field == field, message


@pytest.mark.parametrize("which", ["imu_path", "gps_path", "metadata_path"])
def test_empty_and_header_only_files(tmp_path, which):
    paths = _write_small(tmp_path)
    for text in ("", paths[which].read_text().splitlines()[0] + "\n"):
        paths[which].write_text(text)
        with pytest.raises(DataError) as info:
            load_kitti(**paths, first_gps=0)
        assert str(paths[which]) in str(info.value) and "line 1" in str(info.value)


def test_malformed_copies_of_the_real_files(tmp_path, real_files):
    """Truncated copies of the shipped files, then one bad line each."""
    imu = real_files[kitti.IMU_FILE].read_text().splitlines()[:3001]
    gps = real_files[kitti.GPS_FILE].read_text().splitlines()[:30]
    paths = {"imu_path": tmp_path / "imu.txt", "gps_path": tmp_path / "gps.txt",
             "metadata_path": tmp_path / "meta.txt"}
    paths["metadata_path"].write_text(real_files[kitti.METADATA_FILE].read_text())
    paths["gps_path"].write_text("\n".join(gps) + "\n")
    paths["imu_path"].write_text("\n".join(imu) + "\n")
    d = load_kitti(**paths)
    assert d.t1 == float(imu[-1].split()[0]) and d.sensor("gps").data.t[-1] == float(gps[-1].split(",")[0])
    # a NaN gyro reading on line 1234
    bad = list(imu)
    fields = bad[1233].split(" ")
    fields[6] = "NaN"
    bad[1233] = " ".join(fields)
    paths["imu_path"].write_text("\n".join(bad) + "\n")
    with pytest.raises(DataError, match=r"imu\.txt, line 1234, field 'omegaY': found 'NaN'; expected a finite number"):
        load_kitti(**paths)
    # a duplicated GPS line
    paths["imu_path"].write_text("\n".join(imu) + "\n")
    paths["gps_path"].write_text("\n".join(gps[:10] + [gps[9]] + gps[10:]) + "\n")
    with pytest.raises(DataError, match=r"gps\.txt, line 11, field 'Time'.*duplicate of line 10"):
        load_kitti(**paths)
    # a gap inside the used span
    paths["gps_path"].write_text("\n".join(gps) + "\n")
    paths["imu_path"].write_text("\n".join(imu[:1000] + imu[1100:]) + "\n")
    with pytest.raises(DataError, match=r"imu\.txt, line 1001, field '(Time|dt)'"):
        load_kitti(**paths)


_TOKENS = st.sampled_from(
    ["0", "1000.5", "-1", "0.01", "9.8", "1e400", "nan", "inf", "x", "", ",", " ", "#", "\t", "1_0", "1.2.3",
     "Time", "\u00e9", "0 0 0 0 0 0 0 0", "1000.0,1,2,3", "9" * 30]
)
_LINE = st.lists(_TOKENS, min_size=0, max_size=10).map(" ".join)


@settings(max_examples=80, deadline=None, derandomize=True, suppress_health_check=[HealthCheck.too_slow])
@given(which=st.sampled_from(["imu_path", "gps_path", "metadata_path"]), line=_LINE,
       where=st.integers(0, 12), replace=st.booleans())
def test_fuzz_only_data_errors_naming_the_file(which, line, where, replace):
    with tempfile.TemporaryDirectory() as tmp:
        paths = _write_small(Path(tmp), n=201)
        lines = paths[which].read_text().splitlines()
        where = min(where, len(lines))
        lines[where: where + int(replace)] = [line]
        paths[which].write_text("\n".join(lines) + "\n")
        try:
            d = load_kitti(**paths, first_gps=0)
        except DataError as error:
            assert str(paths[which]) in str(error), str(error)
        else:
            assert np.all(np.diff(d.imu.t) > 0)
