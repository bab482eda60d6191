"""Self-calibration through a rig file: ``estimate = [...]`` in the rig, the printed table,
``metrics.json``'s records, ``calibrated.toml`` and the next run from it."""
from __future__ import annotations

import json
import sys

import numpy as np
import pytest
from rigfiles import toml_matrix
from small_recording import WHEEL, write_recording

from datasets.rig import RigError, load_rig
from factors import so3
from smoother.cli import main

if sys.version_info >= (3, 11):
    import tomllib
else:
    import tomli as tomllib

#: The wheel frame as a user would write it: 3 deg of pitch and 1 deg of yaw off the truth.
WRITTEN = WHEEL.copy()
WRITTEN[:3, :3] = so3.exp(np.radians([0.0, 3.0, 1.0])) @ WHEEL[:3, :3]


@pytest.fixture(scope="module")
def recording(tmp_path_factory):
    folder = tmp_path_factory.mktemp("calibration")
    rig, data = write_recording(folder, duration=20.0)
    return folder, rig.read_text()


def _rig(folder, text: str, wheel_extra: str, name: str) -> str:
    """The recording's rig with the wheel's T_BS as written and ``wheel_extra`` keys."""
    text = text.replace(f"T_BS = {toml_matrix(WHEEL)}", f"T_BS = {toml_matrix(WRITTEN)}\n{wheel_extra}")
    path = folder / f"{name}.toml"
    path.write_text(text)
    return str(path)


def _run(rig, out, estimator: str = "batch") -> dict:
    assert main(["run", "--rig", rig, "--estimator", estimator, "--out", str(out), "--no-progress"]) == 0
    return json.loads((out / "metrics.json").read_text())


def test_a_rig_run_calibrates_prints_records_and_writes_a_rig_the_next_run_reproduces(recording, tmp_path, capsys):
    folder, text = recording
    rig = _rig(folder, text, 'scale = 1.02\nestimate = ["rotation", "scale"]\nrotation_sigma = 0.1', "calibrate")
    metrics = _run(rig, tmp_path / "first")
    printed = capsys.readouterr().out
    record = metrics["batch"]["calibration"]["wheel"]
    assert set(record) == {"T_BS", "rotation_sigma_rad", "scale", "scale_sigma"}
    assert "calibration wheel: rotation turned by (" in printed and " +- " in printed
    assert metrics["batch"]["sensors"]["wheel"]["ok"] and "per dof (band" not in printed  # its sigma is right
    # the truth: the written mounting turned back by (0, -3, -1) deg, and readings 1/1.02 of the truth
    change = np.degrees(metrics["batch"]["calibration_against_prior"]["wheel"]["rotation_change_rad"])
    sigma = np.degrees(record["rotation_sigma_rad"])
    assert np.all(np.abs(change[1:] - [-3.0, -1.0]) < 3 * sigma[1:]), (change, sigma)
    assert abs(record["scale"] - 1 / 1.02) < 3 * record["scale_sigma"]

    calibrated = tmp_path / "first" / "calibrated.toml"
    again = load_rig(calibrated)  # a rig file, paths absolute, the values written in
    wheel = next(s for s in again.sensors if s.name == "wheel")
    assert wheel.calibrate is None and np.allclose(wheel.T_BS, record["T_BS"], atol=1e-12)
    assert wheel.scale == pytest.approx(1.02 * record["scale"])
    assert "# calibrated by the batch smoother" in calibrated.read_text() and "# caution" not in calibrated.read_text()

    second = _run(str(calibrated), tmp_path / "second")
    assert "calibration" not in second["batch"]
    first_npz, second_npz = (np.load(tmp_path / d / "batch.npz") for d in ("first", "second"))
    sigma_r = np.sqrt(np.diagonal(first_npz["cov"], axis1=1, axis2=2))[:, :3]
    assert np.abs(second_npz["r"] - first_npz["r"]).max(axis=0).max() < 0.1 * sigma_r.min()


@pytest.mark.parametrize("estimator", ["batch", "fixed-lag"])
def test_a_time_offset_is_reported_as_the_whole_offset_and_written_so(recording, tmp_path, estimator):
    folder, text = recording
    text = text.replace('topic = "/fix"\n', 'topic = "/fix"\ntime_offset = 0.05\nestimate = ["time_offset"]\n')
    metrics = _run(_rig(folder, text, "", "offset"), tmp_path / "run", estimator)
    record = metrics[estimator]["calibration"]["gnss"]
    assert set(record) == {"time_offset_s", "time_offset_sigma_s"}
    assert abs(record["time_offset_s"]) < 3 * record["time_offset_sigma_s"]  # the truth: 0, not the 0.05 written
    if estimator != "batch":  # calibrated.toml is the batch's
        return
    gnss = next(s for s in load_rig(tmp_path / "run" / "calibrated.toml").sensors if s.name == "gnss")
    assert gnss.time_offset == pytest.approx(record["time_offset_s"])


def test_a_calibration_fitted_to_a_sensor_whose_sigma_is_too_small_says_how_overconfident_it_is(recording, tmp_path,
                                                                                                capsys):
    """The wheel's sigma written a quarter of its noise's: its residuals are ~16 per dof, and the
    calibration line says its sigmas are that many times too small (the square root of it)."""
    folder, text = recording
    rig = _rig(folder, text, 'sigma = 0.0125\nestimate = ["rotation", "scale"]', "overconfident")
    metrics = _run(rig, tmp_path / "run", "all")
    lines = [line for line in capsys.readouterr().out.splitlines() if "calibration wheel:" in line]
    line = next(x for x in lines if "its residuals are" in x)  # the batch's (the EKF's says innovations)
    verdict = metrics["batch"]["sensors"]["wheel"]
    assert not verdict["ok"] and verdict["per_dof"] > 8.0, verdict
    assert f"its residuals are {verdict['per_dof']:.3g} per dof" in line, line
    assert f"by its residuals they would be {np.sqrt(verdict['per_dof']):.2g}x these" in line, line
    caution = line[line.index("its residuals are"):]  # the line's note, also beside the values for the next run
    assert f"# caution: {caution}" in (tmp_path / "run" / "calibrated.toml").read_text().splitlines(), caution
    # the fixed-lag smoother judges no calibrated sensor: its line says the batch's verdict, and whose,
    # and it is doubtful by it (the same model on the same data)
    assert "wheel" not in metrics["fixed-lag"]["sensors"]
    assert sum(f"its residuals by the batch are {verdict['per_dof']:.3g} per dof" in x for x in lines) == 1, lines
    assert (f"its calibrated wheel, which it does not judge itself, is {verdict['per_dof']:.3g} per dof by the batch"
            in metrics["fixed-lag"]["doubtful"]), metrics["fixed-lag"].get("doubtful")


def test_the_run_gives_each_calibrated_position_sensor_its_own_residual_correlation(recording, tmp_path, capsys,
                                                                                   monkeypatch):
    """The printed calibration line of the GNSS carries its own fixes' lag-one correlation (here
    made 0.9, as a 10-Hz receiver's drifting error gives)."""
    from smoother.evaluation import scoring as report

    folder, text = recording
    text = text.replace('topic = "/fix"\n', 'topic = "/fix"\nestimate = ["time_offset"]\n')
    correlation, asked = report.residual_correlation, []

    def drifting(dataset, estimate, calibration=None, sensor=None, following=None):
        asked.append(sensor)
        return 0.9 if sensor == "gnss" else correlation(dataset, estimate, calibration, sensor, following)

    monkeypatch.setattr(report, "residual_correlation", drifting)
    _run(_rig(folder, text, "", "drifting"), tmp_path / "run")
    line = next(line for line in capsys.readouterr().out.splitlines() if "calibration gnss:" in line)
    assert asked == ["gnss"] and "lag-one correlation is 0.90" in line, (asked, line)


@pytest.mark.parametrize("extra, key, message", [
    ('estimate = ["mounting"]', "estimate", "expected a list of any of time_offset, rotation, lever_arm, scale"),
    ('rotation_sigma = 0.1', "rotation_sigma", "has no effect without estimate"),
    ('estimate = ["scale"]\nscale_sigma = -1.0', "scale_sigma", "expected a number > 0"),
    ('estimate = []', "estimate", "non-empty"),
    ('sigma_factor = 0.001', "sigma_factor", r"expected a value within \[0.01, 100\]"),
    ('sigma_factor = [1.0, 2.0]', "sigma_factor", "a velocity sensor's sigma_factor is"),
    ('sigma = 0.05\nsigma_factor = 2.0', "sigma_factor", "with sigma given, write the sigmas themselves"),
])
def test_bad_calibration_keys_name_the_file_and_the_key(recording, extra, key, message):
    folder, text = recording
    with pytest.raises(RigError, match=rf'bad\.toml: sensor\[2\] "wheel"\.{key}: .*{message}'):
        load_rig(_rig(folder, text, extra, "bad"))


def test_a_part_the_kind_cannot_estimate_is_refused_in_the_rig(recording):
    folder, text = recording
    text = text.replace('topic = "/fix"\n', 'topic = "/fix"\nestimate = ["rotation"]\nscale = 1.1\n')
    refused = r'sensor\[1\] "gnss"\.(estimate: a gnss sensor cannot estimate its rotation|scale)'
    with pytest.raises(RigError, match=refused):
        load_rig(_rig(folder, text, "", "kind"))


def test_a_rig_that_asks_for_its_noise_gets_it_written_and_the_next_run_starts_from_it(recording, tmp_path, capsys):
    """``estimate = ["noise"]`` on ``[imu]`` and on the GNSS, whose sigma the rig states 2.5 times
    too small: the batch smoother fits it; ``calibrated.toml`` carries the fitted sigma, a comment on
    every group the fit examined (fitted, checked or not determined) and no ``"noise"`` left in any
    ``estimate``; the run from it fits nothing and finds the fixes in band."""
    folder, text = recording
    text = text.replace("[imu]\n", '[imu]\nestimate = ["noise"]\n')
    text = text.replace('topic = "/fix"', 'topic = "/fix"\nsigma = 0.2\nestimate = ["noise"]')
    path = folder / "noise.toml"
    path.write_text(text)
    metrics = _run(str(path), tmp_path / "first")
    assert "noise fitted by the batch smoother" in capsys.readouterr().out
    noise = metrics["batch"]["noise"]
    fitted = [noise[f"gnss.{part}"] for part in ("horizontal", "vertical")]
    assert all(g["applied"] and g["estimable"] and g["factor"] > 1.6 for g in fitted), fitted

    calibrated = tmp_path / "first" / "calibrated.toml"
    written = calibrated.read_text()
    document = tomllib.loads(written)
    assert "estimate" not in document["imu"] and all("estimate" not in s for s in document["sensor"])
    gnss = next(s for s in load_rig(calibrated).sensors if s.name == "gnss")
    expected = 0.2 * np.array([fitted[0]["factor"]] * 2 + [fitted[1]["factor"]])
    np.testing.assert_allclose(gnss.sigma, expected, rtol=1e-12)
    for key in ("accel_noise_density", "gyro_noise_density", "accel_random_walk", "gyro_random_walk"):
        assert sum(line.startswith(f"# {key} ") and " by the batch smoother" in line
                   for line in written.splitlines()) == 1, (key, written)
    assert sum(line.startswith("# horizontal noise fitted by the batch smoother") for line in written.splitlines()) == 1

    second = _run(str(calibrated), tmp_path / "second")
    assert "noise fitted by the batch smoother" not in capsys.readouterr().out
    assert "noise" not in second["batch"] and second["batch"]["sensors"]["gnss"]["ok"]


def test_a_sensor_whose_messages_carry_its_noise_gets_a_sigma_factor_the_next_run_applies(tmp_path, capsys):
    """Fixes whose messages state 0.2 m for their 0.5 m of noise (a driver's covariance too small)
    and ``estimate = ["noise"]`` on them: ``calibrated.toml`` carries ``sigma_factor`` per axis, the
    fitted factors on the messages' sigmas, and the run from it applies them without fitting again
    and finds the fixes in band."""
    folder = tmp_path / "messages"
    rig, _ = write_recording(folder, duration=20.0, fix_sigma=0.2)
    rig.write_text(rig.read_text().replace('topic = "/fix"', 'topic = "/fix"\nestimate = ["noise"]'))
    metrics = _run(str(rig), tmp_path / "first")
    noise = metrics["batch"]["noise"]
    fitted = [noise[f"gnss.{part}"] for part in ("horizontal", "vertical")]
    assert all(g["applied"] and g["estimable"] and g["factor"] > 1.6 for g in fitted), fitted

    calibrated = tmp_path / "first" / "calibrated.toml"
    gnss = next(s for s in load_rig(calibrated).sensors if s.name == "gnss")
    expected = np.array([fitted[0]["factor"]] * 2 + [fitted[1]["factor"]])
    assert gnss.sigma is None
    np.testing.assert_allclose(gnss.sigma_factor, expected, rtol=1e-12)
    assert "(as sigma_factor, on its messages' sigmas)" in calibrated.read_text()
    capsys.readouterr()
    second = _run(str(calibrated), tmp_path / "second")
    assert "noise fitted by the batch smoother" not in capsys.readouterr().out
    assert "noise" not in second["batch"] and second["batch"]["sensors"]["gnss"]["ok"]


def test_a_correlation_time_to_fit_is_fitted_printed_recorded_and_written_for_the_next_run(recording, tmp_path,
                                                                                           capsys):
    """``correlation_time = "fit"`` on the GNSS (white errors, one fix in two held out): the run prints
    the fit, ``metrics.json`` records every time tried and how the held-out fixes were split, the
    held-out verdict counts the judging half only, and ``calibrated.toml`` carries the result for
    the next run, which fits nothing."""
    folder, text = recording
    path = folder / "fit.toml"
    path.write_text(text.replace('topic = "/fix"', 'topic = "/fix"\ncorrelation_time = "fit"'))
    metrics = _run(str(path), tmp_path / "first")
    printed = capsys.readouterr().out
    fit = metrics["_run"]["correlation_fit"]["gnss"]
    assert "correlation time of gnss: " in printed and f"the other {fit['judged_on']} judge the run" in printed
    assert fit["tuned_on"] + fit["judged_on"] == 20 and min(fit["tuned_on"], fit["judged_on"]) >= 8
    assert len(fit["candidates"]) >= 5 and fit["candidates"][0]["correlation_time_s"] is None
    scores = [c["score"] for c in fit["candidates"] if c["score"] is not None]
    chosen = next(c["score"] for c in fit["candidates"] if c["correlation_time_s"] == fit["correlation_time_s"])
    assert chosen == min(scores)
    assert metrics["batch"]["sensors"]["gnss"]["heldout_measurements"] == fit["judged_on"]

    written = (tmp_path / "first" / "calibrated.toml").read_text()
    assert '"fit"' not in written.replace('correlation_time = "fit" fits it again', "")
    assert "fitted to the held-out measurements" in written
    gnss = next(s for s in load_rig(tmp_path / "first" / "calibrated.toml").sensors if s.name == "gnss")
    assert gnss.correlation_time == fit["correlation_time_s"] and not gnss.fit_correlation_time
    second = _run(str(tmp_path / "first" / "calibrated.toml"), tmp_path / "second")
    assert "correlation time of gnss" not in capsys.readouterr().out and "correlation_fit" not in second["_run"]
