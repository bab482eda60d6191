"""``smoother run`` in-process (smoother.cli.main): outputs, table, one-line errors, atomic
metrics.json."""
from __future__ import annotations

import json
import math
import warnings

import numpy as np
import pytest

from datasets.tum import read_tum
from smoother.cli import main
from smoother.commands.run import format_table, interpolation_note
from smoother.evaluation import scoring as report
from smoother.outputs import files

ESTIMATORS = ("batch", "fixed-lag", "ekf")


def test_run_all_estimators_writes_trajectories_truth_metrics_and_a_table(tmp_path, capsys):
    out = tmp_path / "run"
    code = main(["run", "--dataset", "synthetic:gentle", "--duration", "4", "--estimator", "all", "--out", str(out),
                 "--no-progress"])
    captured = capsys.readouterr()
    assert code == 0, captured.err
    names = {p.name for p in out.iterdir()}
    assert names >= {f"{e}.{ext}" for e in ESTIMATORS for ext in ("tum", "npz")} | {"truth.npz", "metrics.json"}
    assert not [n for n in names if n.endswith(".tmp")]

    document = json.loads((out / "metrics.json").read_text())
    assert set(ESTIMATORS) <= set(document)
    truth = files.load_trajectory(out / "truth.npz")
    for name in ESTIMATORS:
        m = document[name]
        for key in ("ate_rmse_m", "rot_rmse_deg", "nees_mean", "runtime_s"):
            assert isinstance(m[key], float) and math.isfinite(m[key]), (name, key, m.get(key))
        # sane values on a 4 s gentle run with 10 Hz poses (0.05 m, 0.01 rad): errors of a few cm
        assert m["ate_rmse_m"] < 0.2 and m["rot_rmse_deg"] < 2.0 and 0.1 < m["nees_mean"] < 10.0
        traj = files.load_trajectory(out / f"{name}.npz")
        tum = read_tum(out / f"{name}.tum")
        np.testing.assert_array_equal(tum.t, traj.t)
        np.testing.assert_allclose(tum.position, traj.position, rtol=0, atol=1e-12)
        assert traj.cov is not None and traj.cov.shape == (len(traj.t), 15, 15)
        assert traj.t[0] == truth.t[0] and traj.t[-1] == truth.t[-1]
        # the metrics are those of the files (re-scored here from what was written)
        assert report.against_truth(truth, traj)["ate_rmse_m"] == pytest.approx(m["ate_rmse_m"], rel=1e-12)
    assert document["_run"]["dataset"] == "synthetic:gentle"

    lines = captured.out.strip().splitlines()
    assert lines[0].split()[0] == "estimator" and "ATE" in lines[0] and "NEES/dim" in lines[0]
    assert [line.split()[0] for line in lines[1:]] == list(ESTIMATORS)
    ekf_row = lines[1 + ESTIMATORS.index("ekf")].split()
    assert float(ekf_row[1]) == pytest.approx(document["ekf"]["ate_rmse_m"], abs=5e-5)


def test_the_run_says_and_records_its_keyframes(tmp_path, capsys):
    """``_run.keyframes`` and one line on stderr: 40 Hz fixes beside the 10 Hz poses come faster
    than 10 Hz, so the default grid is 10 Hz and the fixes between its keyframes (three of four)
    are attached, at most 0.075 s after theirs; ``--keyframe-rate 5`` sets the grid (the poses
    between attached too); the poses alone keep a keyframe each; an EKF alone keeps no keyframes."""
    def run(*argv):
        out = tmp_path / str(len(list(tmp_path.iterdir())))
        code = main(["run", "--duration", "2", "--no-progress", "--no-covariance", "--out", str(out), *argv])
        err = capsys.readouterr().err
        assert code == 0, err
        lines = [line for line in err.splitlines() if line.startswith("keyframes: ")]
        return json.loads((out / "metrics.json").read_text())["_run"].get("keyframes"), lines

    record, lines = run("--estimator", "batch", "--gps-from-truth", "40", "0.1")
    assert record == {"count": 21, "rate_hz": 10.0, "measurements": 81 + 21, "attached": 60,
                      "max_attached_distance_s": pytest.approx(0.075, abs=1e-12), "relative": 0, "composed": 0}
    assert lines == ["keyframes: 21 on a 10 Hz grid (the default: a 10 Hz grid where measurements come faster; "
                     "--keyframe-rate HZ sets it); 60 of 102 measurements attached to the keyframe before them, at "
                     "most 0.075 s after it"]
    record, lines = run("--estimator", "fixed-lag", "--gps-from-truth", "40", "0.1", "--keyframe-rate", "5")
    # a fix and a pose at each of the 11 keyframes
    assert (record["count"], record["rate_hz"], record["attached"]) == (11, 5.0, 102 - 2 * 11)
    assert lines[0].startswith("keyframes: 11 on a 5 Hz grid; 80 of 102 measurements attached")
    record, lines = run("--estimator", "batch")
    assert record == {"count": 21, "rate_hz": "measurements", "measurements": 21, "attached": 0,
                      "max_attached_distance_s": 0.0, "relative": 0, "composed": 0}
    assert lines == ["keyframes: 21, one at every measurement time (the default: a 10 Hz grid where measurements "
                     "come faster; --keyframe-rate HZ sets it)"]
    assert run("--estimator", "ekf") == (None, [])


def test_format_table_marks_missing_values():
    table = format_table({"ekf": {"ate_rmse_m": 0.01234, "nees_mean": float("nan"), "runtime_s": 1.0},
                          "batch": {"ate_rmse_m": 0.5, "nees_mean": None, "runtime_s": 2.0}})
    header, ekf, batch = table.splitlines()
    assert header.split() == ["estimator", "ATE", "[m]", "NEES/dim", "time", "[s]"]
    assert ekf.split() == ["ekf", "0.0123", "-", "1.0000"]
    assert batch.split() == ["batch", "0.5000", "-", "2.0000"]


def test_format_table_marks_unscored_figures_and_dead_reckoning():
    """A figure against the truth over too few states is no number: 'unscored' (not the '-' of a
    figure that does not exist), a closing line says where the reason is; an IMU-only run says so."""
    note = "not scored against the truth: 1 of the estimate's 2 states lie in the truth's span"
    table = format_table({"ekf": {"ate_rmse_m": float("nan"), "rot_rmse_deg": float("nan"), "nees_mean": float("nan"),
                                  "ate_note": note, "runtime_s": 1.0},
                          "batch": {"ate_rmse_m": 0.5, "rot_rmse_deg": 1.0, "nees_mean": None, "runtime_s": 2.0}},
                         dead_reckoning=True)
    lines = table.splitlines()
    assert lines[1].split() == ["ekf", "unscored", "unscored", "unscored", "1.0000"]
    assert lines[2].split() == ["batch", "0.5000", "1.0000", "-", "2.0000"]
    assert lines[3].startswith("unscored: ekf compared with the truth at too few states")
    assert lines[4].startswith("dead reckoning: no aiding sensor, the IMU alone")
    assert "dead reckoning" not in format_table({"batch": {"ate_rmse_m": 0.5}})


def test_the_table_ranks_by_held_out_fixes_and_labels_the_fit_residual():
    """KITTI with every fix used (issue figures): the fixed-lag smoother fits the used fixes more
    closely (0.32 m against 0.65 m) at a far higher cost; held out, the batch is the more accurate.
    The table ranks by the held-out RMSE only and says what the residual is."""
    table = format_table({"batch": {"gps_heldout_rmse_m": 1.41, "gps_fit_residual_m": 0.65, "runtime_s": 1.0},
                          "fixed-lag": {"gps_heldout_rmse_m": 1.75, "gps_fit_residual_m": 0.32, "runtime_s": 2.0},
                          "ekf": {"gps_heldout_rmse_m": 14.2, "gps_fit_residual_m": 0.9, "runtime_s": 0.5}})
    lines = table.splitlines()
    assert lines[0].split() == ["estimator", "held-out", "[m]", "fit", "resid", "[m]", "time", "[s]"]
    assert lines[4] == "ranked by held-out RMSE: batch < fixed-lag < ekf"
    assert lines[5] == "fit resid: RMS distance to the fixes the estimators used -- a residual, not an accuracy"
    every_fix_used = format_table({"batch": {"gps_heldout_rmse_m": float("nan"), "gps_fit_residual_m": 0.65},
                                   "fixed-lag": {"gps_heldout_rmse_m": float("nan"), "gps_fit_residual_m": 0.32}})
    assert "no held-out fixes: no ranking (hold fixes out with --gps-every K > 1)" in every_fix_used.splitlines()


def test_when_interpolation_wins_the_note_says_whether_the_fixes_drift():
    """Only when interpolating the used fixes beats every smoother: with fix errors that drift
    (the residuals at consecutive used fixes correlated) the note points to the drift and an
    independent reference; with white ones, to the rig."""
    from types import SimpleNamespace

    from drifting_fixes import fixes_with_noise

    for phi, words in ((0.98, "drifts slowly over the fix spacing"), (0.0, "the fixes look independent")):
        data, truth = fixes_with_noise(phi)
        baseline = report.interpolation_baseline(data)
        estimates = {"batch": SimpleNamespace(trajectory=truth, calibration=None, following=None)}
        losing = {"batch": {"gps_heldout_rmse_m": baseline["gps_heldout_rmse_m"] + 0.1}}
        assert words in interpolation_note(baseline, losing, estimates, data)
        winning = {"batch": {"gps_heldout_rmse_m": baseline["gps_heldout_rmse_m"] - 0.1}}
        assert interpolation_note(baseline, winning, estimates, data) is None


def _one_line_error(capsys) -> str:
    """The error is the last line of stderr, one line (progress notes such as 'running ekf ...'
    may come before it), without a traceback."""
    captured = capsys.readouterr()
    err = captured.err.strip().splitlines()
    assert err and err[-1].startswith("smoother: error: "), captured.err
    assert sum(line.startswith("smoother:") for line in err) == 1
    assert "Traceback" not in captured.err and captured.out == ""
    return err[-1]


@pytest.mark.parametrize("argv, mentions", [
    (["--dataset", "synthetic:wobbly"], "wobbly"),
    (["--dataset", "nonsense"], "nonsense"),
    (["--duration", "-1"], "--duration"),
    (["--duration", "0"], "--duration"),
    (["--gps-every", "0"], "--gps-every"),
    (["--robust", "huber:abc"], "--robust"),
    (["--robust", "l1"], "--robust"),
    (["--robust", "speed=huber"], "speed"),
    (["--robust", "pose=tukey:-2"], "--robust"),
    (["--lag", "0"], "--lag"),
    (["--ekf-gate", "1.5"], "--ekf-gate"),
    (["--keyframe-rate", "-1"], "--keyframe-rate: expected a value within [0.001, 10000] Hz"),
    (["--keyframe-rate", "0"], "--keyframe-rate: expected a value within [0.001, 10000] Hz"),
    (["--keyframe-rate", "inf"], "--keyframe-rate: expected a value within [0.001, 10000] Hz"),
    (["--keyframe-rate", "nan"], "--keyframe-rate: expected a value within [0.001, 10000] Hz"),
    (["--duration", "inf"], "--duration"),
    (["--dataset", "kitti", "--duration", "nan"], "--duration"),
    (["--lag", "inf"], "--lag"),
    (["--outliers", "1.5"], "--outliers"),
    (["--outliers", "nan"], "--outliers"),
    (["--pose-from-truth", "10", "0", "0.01"], "--pose-from-truth"),
    (["--gps-from-truth", "inf", "1"], "--gps-from-truth"),
    # a value only the data can refuse: named by its option, not by the library's parameter
    (["--duration", "2", "--pose-from-truth", "1000", "0.1", "0.01"], "--pose-from-truth: rate_hz: 1000 Hz is above"),
    (["--seed", "-1"], "--seed: expected a value within [0, 4.29497e+09]"),
    (["--max-iterations", "0"], "--max-iterations: expected a value within [1, 10000]"),
    (["--max-gyro-rate", "0"], "--max-gyro-rate: expected a value within [1, 10000] rad/s"),
    (["--duration", "1e10"], "--duration: expected a value within [1, 1e+08] s"),
    (["--duration", "0.001"], "--duration: expected a value within [1, 1e+08] s"),
    (["--duration", "1e20"], "--duration: expected a value within [1, 1e+08] s"),
])
def test_bad_options_exit_2_with_one_line(tmp_path, capsys, argv, mentions):
    out = tmp_path / "run"
    code = main(["run", "--duration", "1", "--estimator", "ekf", "--out", str(out), "--no-progress"] + argv)
    assert code == 2
    assert mentions in _one_line_error(capsys)
    assert not out.exists()  # nothing written


@pytest.mark.parametrize("where", ["an existing file", "a path under a file"])
def test_a_bad_out_is_one_line_before_any_estimator_runs(tmp_path, capsys, monkeypatch, where):
    """--out that cannot be a directory: exit 2, one line naming --out and the path, checked
    before the estimators run (their results would otherwise be lost)."""
    import smoother.pipeline

    monkeypatch.setattr(smoother.pipeline, "estimate_each", lambda *a, **k: pytest.fail("estimators ran"))
    blocker = tmp_path / "metrics.json"
    blocker.write_text("{}")
    out = blocker if where == "an existing file" else blocker / "run"
    assert main(["run", "--duration", "1", "--estimator", "ekf", "--out", str(out), "--no-progress"]) == 2
    assert f"--out {out}: " in _one_line_error(capsys)
    assert blocker.read_text() == "{}"


def test_a_failure_while_writing_the_outputs_is_one_line_naming_the_file(tmp_path, capsys, monkeypatch):
    """An OSError after the estimators ran (here a full disk while writing metrics.json):
    exit 2 and one line naming the file, no traceback."""
    import errno

    def full_disk(obj, handle, **kwargs):
        raise OSError(errno.ENOSPC, "No space left on device")

    monkeypatch.setattr(files.json, "dump", full_disk)
    out = tmp_path / "run"
    assert main(["run", "--duration", "1", "--estimator", "ekf", "--out", str(out), "--no-progress"]) == 2
    line = _one_line_error(capsys)
    assert str(out / "metrics.json") in line and "No space left on device" in line
    assert not (out / "metrics.json").exists()


def test_running_out_of_memory_is_one_line_naming_the_size(tmp_path, capsys, monkeypatch):
    """A MemoryError (here from the simulator, as NumPy raises it for a duration that is
    allowed but too long for this machine): exit 2, one line with NumPy's size and a hint."""
    import datasets.simulate

    def too_big(*args, **kwargs):
        raise MemoryError("Unable to allocate 14.6 TiB for an array with shape (2000000000001, 3) "
                          "and data type float64")

    monkeypatch.setattr(datasets.simulate, "simulate", too_big)
    out = tmp_path / "run"
    assert main(["run", "--duration", "1e7", "--estimator", "ekf", "--out", str(out), "--no-progress"]) == 2
    line = _one_line_error(capsys)
    assert "out of memory (Unable to allocate 14.6 TiB" in line and line.endswith("try a shorter --duration")
    assert not out.exists()


@pytest.fixture()
def good_run(tmp_path, capsys):
    """A finished cheap run (EKF, 1 s) whose metrics.json later runs must not spoil."""
    out = tmp_path / "run"
    assert main(["run", "--duration", "1", "--estimator", "ekf", "--out", str(out), "--no-progress"]) == 0
    capsys.readouterr()
    return out, (out / "metrics.json").read_bytes()


def test_a_run_with_bad_options_leaves_the_previous_metrics(good_run, capsys):
    out, before = good_run
    assert main(["run", "--duration", "-1", "--estimator", "ekf", "--out", str(out)]) == 2
    _one_line_error(capsys)
    assert (out / "metrics.json").read_bytes() == before


def test_a_failing_estimator_is_reported_and_the_others_run(tmp_path, capsys, monkeypatch):
    """The EKF fails: exit 2 naming it; the batch (started from dead reckoning, since the EKF it
    starts from failed) and the fixed-lag smoother still run and are written; metrics.json and the
    table say why the EKF failed."""
    import smoother.pipeline

    def failing(*args, **kwargs):
        raise ValueError("simulated estimator failure")

    monkeypatch.setattr(smoother.pipeline, "run_ekf", failing)
    out = tmp_path / "run"
    assert main(["run", "--duration", "2", "--out", str(out), "--no-progress", "--no-covariance"]) == 2
    captured = capsys.readouterr()
    assert "ekf failed: ValueError: simulated estimator failure" in captured.err
    assert "failed: ValueError: simulated estimator failure" in captured.out  # the table's row
    metrics = json.loads((out / "metrics.json").read_text())
    assert metrics["_run"]["estimators"] == ["batch", "fixed-lag", "ekf"] and "stopped" not in metrics["_run"]
    assert metrics["ekf"]["failed"] == "ValueError: simulated estimator failure"
    assert metrics["batch"]["start"].startswith("dead reckoning (the EKF failed")
    assert (out / "batch.tum").exists() and (out / "fixed-lag.npz").exists() and not (out / "ekf.tum").exists()


def test_the_batch_starts_from_the_ekf(tmp_path, capsys):
    out = tmp_path / "run"
    assert main(["run", "--duration", "2", "--estimator", "batch", "--out", str(out), "--no-progress"]) == 0
    metrics = json.loads((out / "metrics.json").read_text())
    assert metrics["batch"]["start"] == "ekf" and metrics["batch"]["start_ekf_s"] > 0


def test_ctrl_c_after_the_batch_keeps_it_with_one_line(tmp_path, capsys, monkeypatch):
    """Ctrl-C while the fixed-lag smoother runs: exit 130, the EKF and batch estimates written
    with stopped: interrupted, and one line on stderr saying so."""
    import smoother.online.replay

    def interrupted(*args, **kwargs):
        raise KeyboardInterrupt

    # the pipeline imports it when the fixed-lag runs
    monkeypatch.setattr(smoother.online.replay, "replay", interrupted)
    out = tmp_path / "run"
    assert main(["run", "--duration", "2", "--out", str(out), "--no-progress", "--no-covariance"]) == 130
    said = [line for line in capsys.readouterr().err.splitlines()
            if not line.startswith(("dataset ", "keyframes: ", "running "))]
    assert said == [f"smoother: interrupted: wrote the finished estimators (batch, ekf) to {out}; metrics.json says "
                    "stopped: interrupted"], said
    assert json.loads((out / "metrics.json").read_text())["_run"]["stopped"] == "interrupted"
    assert (out / "batch.tum").exists() and (out / "ekf.tum").exists() and not (out / "fixed-lag.tum").exists()


def test_a_run_interrupted_while_writing_metrics_leaves_the_previous_file(good_run, capsys, monkeypatch):
    """Ctrl-C in the middle of writing metrics.json (after part of it was written): exit 130,
    the previous complete metrics.json is still there, no temporary file is left."""
    def interrupted_dump(obj, handle, **kwargs):
        handle.write('{"ekf": ')
        raise KeyboardInterrupt

    out, before = good_run
    monkeypatch.setattr(files.json, "dump", interrupted_dump)
    assert main(["run", "--duration", "1", "--estimator", "ekf", "--out", str(out), "--seed", "3"]) == 130
    assert "interrupted" in capsys.readouterr().err
    assert (out / "metrics.json").read_bytes() == before
    json.loads(before)
    assert not [p for p in out.iterdir() if p.name.endswith(".tmp")]


def test_failures_inside_the_library_are_one_line_without_traceback(monkeypatch, capsys, tmp_path):
    """A GTSAM/NumPy failure surfacing as RuntimeError, or a data ValueError, is one line on
    stderr with exit code 3 (internal) or 2 (data); SMOOTHER_DEBUG=1 re-raises it."""
    import smoother.pipeline

    def boom(*args, **kwargs):
        raise RuntimeError("\nIndeterminate linear system detected while working near variable\n42")

    monkeypatch.setattr(smoother.pipeline, "estimate_each", boom)
    from smoother.cli import main as cli_main

    assert cli_main(["run", "--duration", "1", "--out", str(tmp_path)]) == 3
    err = capsys.readouterr().err
    assert "internal failure (RuntimeError): Indeterminate linear system" in err
    assert "Traceback" not in err and len(err.strip().splitlines()) <= 3
    monkeypatch.setenv("SMOOTHER_DEBUG", "1")
    with pytest.raises(RuntimeError):
        cli_main(["run", "--duration", "1", "--out", str(tmp_path)])


def test_warnings_are_one_readable_line(monkeypatch, capsys, tmp_path):
    """During a command, a data warning (e.g. measurements dropped outside the IMU span) is
    formatted as one line 'smoother: warning: ...' without Python's source-code echo; the
    previous format is restored afterwards."""
    import warnings as pywarnings

    import smoother.commands.dataset_specs
    from smoother.cli import main as cli_main

    real, seen = smoother.commands.dataset_specs.load, []

    def load_and_format(spec, options):
        seen.append(pywarnings.formatwarning("Dataset.position: 2 of 5 dropped", UserWarning, "types.py", 1))
        return real(spec, options)

    monkeypatch.setattr(smoother.commands.dataset_specs, "load", load_and_format)
    before = pywarnings.formatwarning
    assert cli_main(["run", "--duration", "1", "--estimator", "ekf", "--out", str(tmp_path), "--no-progress"]) == 0
    assert seen == ["smoother: warning: Dataset.position: 2 of 5 dropped\n"]
    assert pywarnings.formatwarning is before


def test_estimate_noise_fits_prints_and_records_the_noise(tmp_path, capsys):
    """--estimate-noise (--tune-noise its other name): the batch smoother fits every group, the
    table is printed after the estimates, metrics.json has each group's record under the batch and
    says the other estimators ran with it, and every estimator has its held-out verdicts."""
    out = tmp_path / "fitted"
    code = main(["run", "--dataset", "synthetic:gentle", "--duration", "6", "--estimator", "all", "--out", str(out),
                 "--tune-noise", "--no-progress"])
    captured = capsys.readouterr()
    assert code == 0, captured.err
    assert "noise fitted by the batch smoother" in captured.out
    metrics = json.loads((out / "metrics.json").read_text())
    noise = metrics["batch"]["noise"]
    assert {"imu.acc", "imu.gyro", "imu.acc_bias", "imu.gyro_bias", "pose.position", "pose.attitude"} <= set(noise)
    for record in (v for k, v in noise.items() if not k.startswith("_")):
        assert {"factor", "factor_sd", "redundancy", "value", "merged_with", "estimable", "applied"} <= set(record)
    assert metrics["ekf"]["noise_from"] == metrics["fixed-lag"]["noise_from"] == "batch"


def test_estimate_noise_without_the_batch_asked_for_still_prints_and_records_the_fit(tmp_path, capsys):
    """--estimate-noise with only the EKF asked for: the batch smoother runs for the fit alone (not
    in the table), and the fit the EKF ran with is printed and recorded as the run's (``_run.noise``)."""
    out = tmp_path / "ekf"
    code = main(["run", "--dataset", "synthetic:gentle", "--duration", "6", "--estimator", "ekf", "--out", str(out),
                 "--estimate-noise", "--no-progress"])
    captured = capsys.readouterr()
    assert code == 0, captured.err
    assert "noise fitted by the batch smoother" in captured.out and "pose.position" in captured.out
    metrics = json.loads((out / "metrics.json").read_text())
    assert set(metrics) == {"ekf", "_run"} and metrics["ekf"]["noise_from"] == "batch"
    assert {"imu.acc", "pose.position", "pose.attitude"} <= set(metrics["_run"]["noise"])


def test_kitti_refuses_a_path(capsys):
    """``--dataset kitti:PATH`` is refused in one line (KITTI is the shipped data; it takes no path)."""
    from smoother.cli import main

    assert main(["run", "--dataset", "kitti:/some/where", "--out", "unused"]) == 2
    err = capsys.readouterr().err
    assert "kitti takes no path" in err and "Traceback" not in err


def test_a_batch_stopped_by_max_iterations_says_so_in_a_warning_and_metrics(tmp_path, capsys):
    """--max-iterations 1 on a problem LM needs more for: a warning naming the iterations and the
    last relative decrease, and ``converged`` false in metrics.json (true with the default)."""
    documents = {}
    for cap in ("1", "100"):
        out = tmp_path / cap
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always")
            code = main(["run", "--duration", "4", "--estimator", "batch", "--out", str(out), "--no-progress",
                         "--no-covariance", "--max-iterations", cap])
        captured = capsys.readouterr()
        assert code == 0, captured.err
        documents[cap] = json.loads((out / "metrics.json").read_text())["batch"]
        warned = [str(w.message) for w in caught if "without converging" in str(w.message)]
        if cap == "1":
            assert len(warned) == 1 and "stopped after 1 iterations" in warned[0], warned
            assert "--max-iterations" in warned[0] and "lowered the cost by" in warned[0]
        else:
            assert not warned, warned
    assert documents["1"]["converged"] is False and documents["1"]["iterations"] == 1
    assert documents["100"]["converged"] is True and documents["100"]["iterations"] < 100


@pytest.mark.parametrize("args, message", [
    (["--estimator", "ekf", "--max-delay", "3"], "--max-delay applies to the fixed-lag smoother"),
    (["--speed", "7"], "--speed sets the pace of --realtime"),
])
def test_options_that_would_be_ignored_are_refused(tmp_path, capsys, args, message):
    assert main(["run", "--duration", "2", "--out", str(tmp_path / "o"), *args]) == 2
    assert message in capsys.readouterr().err


def test_an_imu_fault_is_named_as_one_and_the_sensors_nis_as_its_symptom(monkeypatch, capsys, tmp_path):
    """A vibrating vehicle (1 g at 5 Hz on z for 3 s) on an accelerometer of +-2 g range: the
    clipped samples are a ``warning: imu:`` line and ``_run.imu`` in metrics.json, and the pose
    sensor's NIS, far out of band, is named as the IMU's symptom; a clean run has no finding."""
    import dataclasses

    import smoother.commands.dataset_specs
    from datasets.types import ImuSamples

    real = smoother.commands.dataset_specs.load

    def clipped(spec, options):
        dataset = real(spec, options)
        t, acc = dataset.imu.t, dataset.imu.acc.copy()
        during = (t >= 2.0) & (t < 5.0)
        acc[during, 2] += 2 * 9.80665 * np.sin(2 * np.pi * 5 * t[during])
        acc = np.clip(acc, -2 * 9.80665, 2 * 9.80665)
        return dataclasses.replace(dataset, imu=ImuSamples(t, acc, dataset.imu.gyro))

    out = tmp_path / "clean"
    assert main(["run", "--duration", "8", "--estimator", "ekf", "--out", str(out), "--no-progress"]) == 0
    assert "imu:" not in capsys.readouterr().err
    assert json.loads((out / "metrics.json").read_text())["_run"]["imu"] == {"ok": True, "findings": []}
    monkeypatch.setattr(smoother.commands.dataset_specs, "load", clipped)
    out = tmp_path / "clipped"
    assert main(["run", "--duration", "8", "--estimator", "ekf", "--out", str(out), "--no-progress"]) == 0
    err = capsys.readouterr().err
    imu_lines = [line for line in err.splitlines() if line.startswith("warning: imu:")]
    assert len(imu_lines) == 1 and "accelerometer: " in imu_lines[0] and "saturated" in imu_lines[0], err
    record = json.loads((out / "metrics.json").read_text())["_run"]["imu"]
    assert record["ok"] is False and [f["what"] for f in record["findings"]] == ["saturation"]
    assert 2.0 <= record["findings"][0]["t_start"] and record["findings"][0]["t_end"] < 5.0
    pose = [line for line in err.splitlines() if line.startswith("warning: pose: per dof")]
    assert pose and "the IMU is the likelier cause (accelerometer saturation" in pose[0], err
