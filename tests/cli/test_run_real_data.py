"""`smoother run` end to end on the real-data loaders: an EuRoC/ASL folder (written by the test)
and the KITTI example shipped with gtsam."""
import json

import pytest
from eurocfiles import GT, IMU_STEP, write_sequence

from datasets.euroc import load_euroc
from smoother.cli import main


def _run(capsys, *argv) -> tuple[int, str, str]:
    code = main(["run", *argv, "--no-progress"])
    captured = capsys.readouterr()
    return code, captured.out, captured.err


def test_euroc_folder_with_pose_and_gps_from_truth(tmp_path, capsys):
    write_sequence(tmp_path / "seq")
    out = tmp_path / "out"
    code = main(["run", "--dataset", f"euroc:{tmp_path / 'seq'}", "--pose-from-truth", "20", "0.05", "0.01",
                 "--gps-from-truth", "10", "0.3", "--out", str(out), "--no-progress"])
    assert code == 0, capsys.readouterr().err
    metrics = json.loads((out / "metrics.json").read_text())
    for name in ("batch", "fixed-lag", "ekf"):
        assert (out / f"{name}.tum").exists()
        assert metrics[name]["compared_states"] > 10
        assert metrics[name]["ate_rmse_m"] is not None and metrics[name]["ate_rmse_m"] >= 0
        assert metrics[name]["gps_fit_residual_m"] is not None
    assert metrics["_run"]["aiding_sensors"] == ["pose", "gps"] and metrics["_run"]["dead_reckoning"] is False


def test_dead_reckoning_is_said_and_an_ate_over_one_state_is_not_a_number(tmp_path, capsys):
    """EuRoC without an aiding sensor, the EKF: its states are the first and the last IMU sample
    only, and only the first lies on a truth sample (the last ground-truth row moved 1 ms off the
    IMU's grid). Comparing exactly coinciding stamps scored that one state: ATE 0.0000 from
    compared_states 1, the last state far off. The table marks the figures unscored, stderr says
    why, metrics.json has them null with ate_note, and the run says it is dead reckoning."""
    seq = tmp_path / "seq"
    write_sequence(seq, gt_offset=10 * IMU_STEP)
    gt = seq / GT
    lines = gt.read_text().splitlines()
    stamp, rest = lines[-1].split(",", 1)
    lines[-1] = f"{int(stamp) + 1_000_000},{rest}"
    gt.write_text("\n".join(lines) + "\n")
    out = tmp_path / "out"
    code, table, err = _run(capsys, "--dataset", f"euroc:{seq}", "--estimator", "ekf", "--out", str(out))
    assert code == 0, err
    rows = table.splitlines()
    assert rows[1].split() == ["ekf", "unscored", "unscored", "unscored", rows[1].split()[-1]]
    assert "dead reckoning: no aiding sensor, the IMU alone; the errors grow without bound" in table
    document = json.loads((out / "metrics.json").read_text())
    ekf = document["ekf"]
    assert ekf["ate_rmse_m"] is None and ekf["rot_rmse_deg"] is None and ekf["nees_mean"] is None
    assert ekf["compared_states"] == 1
    assert ekf["ate_note"].startswith("not scored against the truth: 1 of the estimate's 2 states lie in the truth's "
                                      "span")
    assert f"warning: ekf: {ekf['ate_note']}" in err.splitlines()
    assert document["_run"]["dead_reckoning"] is True and document["_run"]["aiding_sensors"] == []


def test_a_ground_truth_of_two_rows_scores_nothing_and_keeps_the_imu(tmp_path, capsys):
    """A ground truth cut to two rows: the IMU after it is kept and estimated (the loader says the
    truth covers 0.005 s of 2 s), and no ATE is printed from the two states it covers."""
    seq = tmp_path / "seq"
    write_sequence(seq, gt_offset=10 * IMU_STEP)
    gt = seq / GT
    gt.write_text("\n".join(gt.read_text().splitlines()[:3]) + "\n")
    out = tmp_path / "out"
    with pytest.warns(UserWarning, match="the ground truth covers 0.005 s of the 2 s"):
        code, table, err = _run(capsys, "--dataset", f"euroc:{seq}", "--estimator", "ekf", "--out", str(out))
    assert code == 0, err
    assert "dataset euroc: 391 IMU samples over 2.0 s" in err  # not the 2 of the truth's 5 ms
    ekf = json.loads((out / "metrics.json").read_text())["ekf"]
    assert ekf["ate_rmse_m"] is None and "the truth covers 0.005 s of it" in ekf["ate_note"]
    assert table.splitlines()[1].split()[1] == "unscored"


def test_a_run_npz_is_in_the_data_clock_and_evaluates_against_the_recording_reference(tmp_path, capsys):
    """EuRoC's clock starts at 1.4e9 s: the run's .npz carries that origin, so `smoother evaluate`
    pairs it with a TUM reference in the data's clock (the .npz is the output with covariances) and
    gives the NEES, the run's own within the association's 1.3 ms at the first state."""
    from datasets.tum import write_tum
    from smoother.outputs.files import load_stamped_trajectory

    seq = tmp_path / "seq"
    write_sequence(seq)
    out = tmp_path / "out"
    # states at the fixes' 20 Hz (not the default 10 Hz keyframes, which halve the pairs)
    code, _, err = _run(capsys, "--dataset", f"euroc:{seq}", "--estimator", "ekf", "--gps-from-truth", "20", "0.1",
                        "--keyframe-rate", "20", "--out", str(out))
    assert code == 0, err
    data = load_euroc(seq)
    trajectory, origin = load_stamped_trajectory(out / "ekf.npz")
    assert origin == data.time_origin_ns and trajectory.t[0] == 0.0
    reference = tmp_path / "reference.tum"
    write_tum(reference, data.truth.t, data.truth.position, data.truth.C, time_origin_ns=data.time_origin_ns)
    assert main(["evaluate", "--reference", str(reference), "--estimate", str(out / "ekf.npz"), "--align", "none",
                 "--json"]) == 0
    result = json.loads(capsys.readouterr().out)
    run = json.loads((out / "metrics.json").read_text())["ekf"]
    assert result["pairs"] >= run["compared_states"] - 1 > 30
    assert result["nees_mean"] == pytest.approx(run["nees_mean"], rel=0.05)
    assert result["ate"]["translation_m"]["rmse"] == pytest.approx(run["ate_rmse_m"], rel=0.05)


def test_gyro_data_in_deg_per_s_stop_the_run_naming_the_cause(tmp_path, capsys):
    """The EuRoC folder's gyro columns written in deg/s (99th percentile ~200 "rad/s"): the run
    stops with one line naming the rate, deg/s and the option; --max-gyro-rate lets it run."""
    import numpy as np

    write_sequence(tmp_path / "seq")
    imu_csv = tmp_path / "seq" / "mav0" / "imu0" / "data.csv"
    lines = imu_csv.read_text().splitlines()
    rows = [line.split(",") for line in lines[1:]]
    for row in rows:
        row[1:4] = [repr(float(x) * 180.0 / np.pi) for x in row[1:4]]
    imu_csv.write_text("\n".join([lines[0]] + [",".join(row) for row in rows]) + "\n")
    base = ["run", "--dataset", f"euroc:{tmp_path / 'seq'}", "--pose-from-truth", "20", "0.05", "0.01",
            "--estimator", "ekf", "--no-progress"]
    assert main(base + ["--out", str(tmp_path / "refused")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert err[-1].startswith("smoother: error: Dataset.imu.gyro: 99th percentile angular rate "), err
    assert "probably in deg/s" in err[-1] and "--max-gyro-rate" in err[-1]
    assert not (tmp_path / "refused" / "metrics.json").exists()
    assert main(base + ["--out", str(tmp_path / "accepted"), "--max-gyro-rate", "1000"]) == 0
    assert (tmp_path / "accepted" / "metrics.json").exists()


def test_euroc_without_a_folder_is_a_one_line_error(tmp_path, capsys):
    assert main(["run", "--dataset", f"euroc:{tmp_path / 'missing'}", "--out", str(tmp_path / "o")]) == 2
    err = capsys.readouterr().err
    assert "missing" in err and "Traceback" not in err


def test_kitti_batch_beats_2_m_on_held_out_fixes(tmp_path, capsys):
    """The fixes GTSAM's example uses (10, 20, ...), 422 held out: the batch smoother's RMS
    distance to the held-out fixes measured 1.416 m (GTSAM's native pipeline with the same bias
    model: 1.412 m)."""
    out = tmp_path / "kitti"
    assert main(["run", "--dataset", "kitti", "--gps-every", "10", "--estimator", "batch", "--out", str(out),
                 "--no-progress", "--no-covariance"]) == 0
    metrics = json.loads((out / "metrics.json").read_text())["batch"]
    assert metrics["gps_heldout_rmse_m"] == pytest.approx(1.416, abs=0.01)
    assert (out / "gps.npz").exists()


def test_kitti_with_its_noise_estimated_beats_both_native_pipelines_and_fits(tmp_path, capsys):
    """From the metadata's noise with --estimate-noise (the noise fitted to the 46 used fixes and
    the IMU's own factors: no held-out data), the batch smoother's held-out RMS measured 0.70 m:
    below GTSAM's native pipeline with either bias count (1.41 m per interval, 0.78 m cumulative;
    benchmarks/kitti_native.py), and every estimator's verdict on its own data in band."""
    out = tmp_path / "kitti-fitted"
    assert main(["run", "--dataset", "kitti", "--gps-every", "10", "--estimator", "all", "--estimate-noise",
                 "--out", str(out), "--no-progress"]) == 0
    document = json.loads((out / "metrics.json").read_text())
    assert document["batch"]["gps_heldout_rmse_m"] < 0.75
    for name in ("batch", "fixed-lag", "ekf"):
        # every verdict formed (the fixed-lag smoother's on the fixes, at the default 2-s lag, has less than a
        # degree of freedom: not judged)
        assert all(v["ok"] for v in document[name]["sensors"].values() if v.get("ok") is not None), name
    assert document["batch"]["noise"]["imu.gyro"]["applied"]


def test_kitti_fixed_lag_with_a_lag_shorter_than_the_gps_gaps_beats_the_ekf(tmp_path, capsys):
    """GPS every 10 s, 1-s keyframes, a 2-s lag: each fix's correction must reach the states'
    linearisation before they leave the window. With ISAM2 relinearising every 10th update (its
    default) those updates fell on the fixes themselves, before their correction, and the
    fixed-lag smoother's held-out RMS was 25.7 m, worse than the EKF's 14.2 m; relinearising at
    every update gives 7.7 m. The run says that the lag is shorter than the gaps (the keyframes
    between fixes keep their dead-reckoned estimates)."""
    out = tmp_path / "kitti-lag2"
    far_apart = r"measurements \(fixes, poses, attitudes\) up to 9 s apart, longer than the lag \(2 s\)"
    with pytest.warns(UserWarning, match=far_apart):
        assert main(["run", "--dataset", "kitti", "--gps-every", "10", "--estimator", "fixed-lag", "--lag", "2",
                     "--out", str(out), "--no-progress", "--no-covariance"]) == 0
    assert json.loads((out / "metrics.json").read_text())["fixed-lag"]["gps_heldout_rmse_m"] < 10.0


def test_outputs_keep_the_sequence_stamps(tmp_path):
    """A run's TUM files carry EuRoC's own nanosecond stamps (evo associates them with the
    sequence's ground truth), not times from 0."""
    from datasets.tum import format_ns

    root = tmp_path / "seq"
    write_sequence(root)
    data = load_euroc(root)
    assert data.time_origin_ns == int(data.imu.t_ns[0])
    assert main(["run", "--dataset", f"euroc:{root}", "--estimator", "ekf", "--gps-from-truth", "10", "0.5",
                 "--out", str(tmp_path / "out"), "--no-progress"]) == 0
    first = (tmp_path / "out" / "ekf.tum").read_text().splitlines()[1].split()[0]
    assert first == format_ns(int(data.imu.t_ns[0]))
