"""``smoother run --rig``: a recording the project has never seen, from its rig file alone.

The recording is written by the test as a ROS 2 bag (MCAP, ``small_recording.write_recording``):
IMU, wheel odometry and GNSS fixes in latitude/longitude from an antenna on a lever arm, with
header stamps in seconds since the epoch. No ground truth reaches the estimators. A rig file that
states a mounting off by a pitch is warned of, with the rotation that undoes it."""
from __future__ import annotations

import json

import numpy as np
import pytest
from rigfiles import toml_matrix
from small_recording import DATUM, WHEEL, write_recording

from datasets.tum import read_tum
from factors import so3
from smoother.cli import main


@pytest.fixture(scope="module")
def recording(tmp_path_factory):
    folder = tmp_path_factory.mktemp("recording")
    rig, data = write_recording(folder, "rig", duration=60, seed=5, imu_rate=200.0, gnss_rate=1.0, every=4)
    out = folder / "out"
    assert main(["run", "--rig", str(rig), "--estimator", "all", "--lag", "5", "--out", str(out), "--no-progress"]) == 0
    return data, out


def test_outputs_keep_the_bag_stamps_and_give_latitude_longitude(recording):
    data, out = recording
    for name in ("batch", "fixed-lag", "ekf"):
        tum = read_tum(out / f"{name}.tum")
        assert 1.7e9 <= tum.t[0] < tum.t[-1] < 1.7e9 + 61  # the bag's clock, not seconds from 0
        geo = json.loads((out / f"{name}.geojson").read_text())
        lon, lat, _ = np.array(geo["features"][0]["geometry"]["coordinates"]).T
        assert abs(lat.mean() - DATUM.latitude) < 1e-3 and abs(lon.mean() - DATUM.longitude) < 1e-3
        assert geo["features"][0]["properties"]["t_start"] == pytest.approx(tum.t[0], abs=1e-6)  # the data's clock


def test_sensors_are_consistent_and_held_out_fixes_beat_interpolating_the_used_ones(recording):
    """Every 4th fix used: the smoothers' held-out GNSS error is below that of interpolating the
    used fixes (the antenna's lever arm included), which the run reports as its yardstick (the
    held-out fixes between the first and the last used one), and each sensor's NIS is in its band."""
    data, out = recording
    metrics = json.loads((out / "metrics.json").read_text())
    gnss = data.sensors[0].data
    used = np.arange(len(gnss)) % 4 == 0
    between = ~used & (gnss.t <= gnss.t[used][-1])
    interpolated = np.stack([np.interp(gnss.t[between], gnss.t[used], gnss.position[used, a]) for a in range(3)], -1)
    baseline = float(np.sqrt(np.mean(np.sum((interpolated - gnss.position[between]) ** 2, axis=1))))
    reported = metrics["_run"]["interpolated_fixes"]
    assert reported["heldout_fixes"] == between.sum()
    assert reported["gps_heldout_rmse_m"] == pytest.approx(baseline, rel=1e-9)  # stamps through the bag
    for name in ("batch", "fixed-lag"):
        assert metrics[name]["gps_heldout_rmse_m"] < baseline, (name, metrics[name]["gps_heldout_rmse_m"], baseline)
    for name, block in metrics["batch"]["sensors"].items():
        assert block["ok"], (name, block)


def test_plots_of_a_recording_show_its_fixes(recording):
    """``smoother plot`` on a rig's run: the GNSS fixes (used and held out) are in gps.npz."""
    data, out = recording
    gps = np.load(out / "gps.npz")
    assert len(gps["t"]) == len(data.sensors[0].data) and gps["heldout"].sum() == len(data.sensors[0].data) * 3 // 4
    assert main(["plot", str(out)]) == 0
    assert (out / "trajectory.png").stat().st_size > 0


def test_held_out_error_splits_into_horizontal_and_vertical(recording):
    """GNSS heights wander more than their horizontal positions: the two parts are reported too
    (their squares add up to the 3-d figure)."""
    _, out = recording
    m = json.loads((out / "metrics.json").read_text())["batch"]
    total = m["gps_heldout_horizontal_rmse_m"] ** 2 + m["gps_heldout_vertical_rmse_m"] ** 2
    assert total == pytest.approx(m["gps_heldout_rmse_m"] ** 2, rel=1e-12)
    assert m["sensors"]["gnss"]["statistic"] == "residual"


def test_realtime_replay_reports_latency_and_gives_the_same_estimates(recording, capsys):
    """``--realtime`` (here 20 times the recorded pace) replays the bag sample by sample through
    the online smoother and reports the latency from a measurement's arrival to the updated
    estimate (median, p99, max; in metrics.json too); the estimates are those of the replay as
    fast as it goes, whatever the pace."""
    data, out = recording
    rig = out.parent / "rig.toml"
    realtime = out.parent / "realtime"
    args = ["run", "--rig", str(rig), "--estimator", "fixed-lag", "--lag", "5", "--no-progress", "--no-covariance"]
    assert main(args + ["--out", str(realtime), "--realtime", "--speed", "20"]) == 0
    printed = capsys.readouterr().out
    assert "fixed-lag latency, measurement arrival to updated estimate" in printed
    assert all(word in printed for word in ("median", "p99", "max"))
    latency = json.loads((realtime / "metrics.json").read_text())["fixed-lag"]["latency_ms"]
    used = int(np.ceil(len(data.sensors[0].data) / 4)) + len(data.sensors[1].data)
    assert latency["measurements"] >= used - 2 and 0 < latency["median"] <= latency["p99"] <= latency["max"]
    a, b = read_tum(out / "fixed-lag.tum"), read_tum(realtime / "fixed-lag.tum")
    np.testing.assert_array_equal(a.t, b.t)
    np.testing.assert_array_equal(a.position, b.position)


@pytest.mark.parametrize("option, value", [("--gps-every", "10"), ("--duration", "5"), ("--outliers", "0.1")])
def test_options_of_the_built_in_datasets_are_refused_with_a_rig(recording, capsys, option, value):
    """Each is refused with exit 2, not ignored (``--gps-every`` is the rig's ``every``)."""
    _, out = recording
    assert main(["run", "--rig", str(out.parent / "rig.toml"), option, value, "--out", str(out.parent / "x")]) == 2
    assert f"{option} shapes a built-in dataset" in capsys.readouterr().err


def test_smoother_run_on_a_rig_names_a_mounting_off_by_a_pitch(tmp_path, capsys):
    """A recording's rig file with the wheel's ``T_BS`` pitched by 5 deg about the IMU's y axis
    (``R_BS`` given as ``exp(phi) R_BS`` of the true one): the states follow the wheel, which stays
    in its band (1.08 per dof) while the fixes go out of theirs (1.6); ``smoother run`` warns of the
    wheel and names the rotation that undoes it, ``-phi`` (measured -4.88 deg +- 0.37 deg)."""
    rig, _ = write_recording(tmp_path, "rig", duration=30, seed=2, imu_rate=100.0, gnss_rate=2.0, every=1)
    wrong = WHEEL.copy()
    wrong[:3, :3] = so3.exp([0.0, np.radians(5.0), 0.0]) @ WHEEL[:3, :3]
    rig.write_text(rig.read_text().replace(f"T_BS = {toml_matrix(WHEEL)}", f"T_BS = {toml_matrix(wrong)}"))
    out = tmp_path / "out"
    assert main(["run", "--rig", str(rig), "--estimator", "batch", "--out", str(out), "--no-progress"]) == 0
    [line] = [line for line in capsys.readouterr().err.splitlines() if line.startswith("warning: wheel:")]
    assert "its residuals point at rotation about y -" in line and 'add estimate = ["rotation"]' in line, line
    pitch = float(line.split("rotation about y ")[1].split(" deg")[0])
    assert abs(pitch + 5.0) < 1.0, line
