"""``smoother run --rig --start/--end``: a part of a recording, and the check a fitted rig is made
for -- its calibration and noise fitted on one part, ``calibrated.toml`` run on the rest."""
from __future__ import annotations

import json

import pytest
from small_recording import write_recording

from smoother.cli import main


@pytest.fixture(scope="module")
def recording(tmp_path_factory):
    """40 s whose fixes' messages state 0.2 m for their 0.5 m of noise (a driver's covariance too
    small), every other fix held out, ``estimate = ["noise"]`` on them."""
    folder = tmp_path_factory.mktemp("part")
    rig, _ = write_recording(folder, duration=40.0, fix_sigma=0.2)
    rig.write_text(rig.read_text().replace('topic = "/fix"', 'topic = "/fix"\nestimate = ["noise"]'))
    return rig


def _run(rig, out, *options) -> dict:
    assert main(["run", "--rig", str(rig), "--out", str(out), "--no-progress", *options]) == 0
    return json.loads((out / "metrics.json").read_text())


def _heldout(metrics: dict) -> dict:
    return {name: (metrics[name]["sensors"]["gnss"]["heldout_per_dof"], metrics[name]["sensors"]["gnss"]["heldout_ok"])
            for name in ("batch", "fixed-lag", "ekf")}


def test_noise_fitted_on_the_first_half_holds_on_the_second(recording, tmp_path, capsys):
    """The first 20 s fit the fixes' sigma (x2.5 on the messages'); ``calibrated.toml`` run on the
    last 20 s without fitting: no estimator doubtful and every held-out verdict in its band, where
    the rig as written leaves every estimator's held-out fixes far above it."""
    first = _run(recording, tmp_path / "first", "--end", "20")
    part = first["_run"]["part"]
    assert part["start_s"] is None and part["end_s"] == 20.0 and part["t1"] <= 20.0
    assert "(0.000-20.000 s after the recording's first IMU sample)" in capsys.readouterr().err
    assert all(first["batch"]["noise"][f"gnss.{axes}"]["applied"] for axes in ("horizontal", "vertical"))

    second = _run(tmp_path / "first" / "calibrated.toml", tmp_path / "second", "--start", "20")
    assert second["_run"]["part"]["t0"] >= 20.0 and "noise" not in second["batch"]
    assert not [name for name in ("batch", "fixed-lag", "ekf") if "doubtful" in second[name]], second
    assert all(ok for _, ok in _heldout(second).values()), _heldout(second)

    as_written = _heldout(_run_without_noise(recording, tmp_path / "written"))
    assert all(per_dof > 3.0 and not ok for per_dof, ok in as_written.values()), as_written


def _run_without_noise(rig, out) -> dict:
    """The second half through the rig as written, its noise not fitted."""
    text = rig.read_text().replace('\nestimate = ["noise"]', "")
    plain = rig.with_name("plain.toml")
    plain.write_text(text)
    return _run(plain, out, "--start", "20")


@pytest.mark.parametrize("options, message", [
    (["--start", "100"], "smoother: error: --start/--end: the part from 100 s on holds 0 IMU samples, at least 2 "
                         "needed: the recording's IMU runs from 0 to 40.000 s after its first sample"),
    (["--start", "10", "--end", "5"], "smoother: error: --start 10 --end 5: expected the end after the start"),
    (["--start", "-1"], "smoother: error: --start: expected a value within [0, 1e+08]"),
])
def test_a_part_that_is_no_part_is_refused_naming_the_options(recording, tmp_path, capsys, options, message):
    assert main(["run", "--rig", str(recording), "--out", str(tmp_path / "out"), "--no-progress", *options]) == 2
    err = capsys.readouterr().err
    assert err.startswith(message) and err.count("\n") == 1, err
    assert not (tmp_path / "out").exists()


def test_the_simulator_takes_its_length_from_duration_and_a_dataset_is_whole(tmp_path, capsys):
    assert main(["run", "--end", "5", "--out", str(tmp_path / "out"), "--no-progress"]) == 2
    assert capsys.readouterr().err.startswith("smoother: error: --start/--end take a part of a recording given by "
                                              "--rig; the simulator's length is --duration")
    assert main(["run", "--dataset", "kitti", "--start", "5", "--out", str(tmp_path / "out"), "--no-progress"]) == 2
    assert capsys.readouterr().err.startswith("smoother: error: --start/--end take a part of a recording given by "
                                              "--rig, not of --dataset")
