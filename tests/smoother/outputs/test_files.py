"""A run's files (:mod:`smoother.outputs.files`): trajectories in ``.npz`` with the data's clock,
TUM files, ``metrics.json`` written atomically with NaN as null."""
from __future__ import annotations

import json
import math

import estimator_cases as cases
import numpy as np
import pytest

from datasets.tum import read_tum
from factors.errors import InputError
from smoother.outputs import files
from smoother.pipeline import Estimate


@pytest.mark.parametrize("with_cov", [True, False])
def test_trajectory_npz_round_trip(tmp_path, with_cov):
    truth = cases.scored_truth()
    est = cases.offset_estimate(truth, with_cov)
    files.save_trajectory(tmp_path / "x.npz", est)
    back = files.load_trajectory(tmp_path / "x.npz")
    np.testing.assert_array_equal(back.t, est.t)
    for name in ("r", "v", "C", "b_f", "b_w"):
        np.testing.assert_array_equal(getattr(back.states, name), getattr(est.states, name))
    if with_cov:
        np.testing.assert_array_equal(back.cov, est.cov)
    else:
        assert back.cov is None
    assert files.load_stamped_trajectory(tmp_path / "x.npz")[1] is None


def test_a_trajectory_npz_carries_the_data_clock(tmp_path):
    """The clock's origin beside times from the start: EuRoC's 1403636579758555392 ns, exactly."""
    est = cases.offset_estimate(cases.scored_truth())
    files.save_trajectory(tmp_path / "x.npz", est, time_origin_ns=1403636579758555392)
    back, origin = files.load_stamped_trajectory(tmp_path / "x.npz")
    assert origin == 1403636579758555392 and np.array_equal(back.t, est.t)
    arrays = dict(np.load(tmp_path / "x.npz"))
    np.savez(tmp_path / "bad.npz", **{**arrays, "time_origin_ns": np.array([1.5, 2.0])})
    with pytest.raises(InputError, match=r"bad\.npz: time_origin_ns is float64 of shape \(2,\); expected"):
        files.load_stamped_trajectory(tmp_path / "bad.npz")


def _estimates(truth):
    return {
        "ekf": Estimate("ekf", cases.offset_estimate(truth), 0.25, {"rejected_measurements": 0}),
        "batch": Estimate("batch", cases.offset_estimate(truth, with_cov=False), 0.5, {"iterations": 3}),
    }


def test_write_outputs_writes_every_file_and_valid_json(tmp_path):
    data = cases.scored_data()
    truth = cases.scored_truth()
    metrics = files.write_outputs(tmp_path / "run", data, _estimates(truth), {"seed": 7})
    names = {p.name for p in (tmp_path / "run").iterdir()}
    assert names == {"ekf.tum", "ekf.npz", "batch.tum", "batch.npz", "truth.npz", "metrics.json"}
    document = json.loads((tmp_path / "run" / "metrics.json").read_text())
    assert document["_run"] == {"seed": 7, "estimators": ["ekf", "batch"], "aiding_sensors": [],
                                "dead_reckoning": True, "world_frame": {
                                    "frame_id": "odom", "position": "relative to the start",
                                    "yaw": "relative to the start"}}
    assert document["ekf"]["ate_rmse_m"] == pytest.approx(0.5)
    assert document["ekf"]["runtime_s"] == 0.25 and document["ekf"]["rejected_measurements"] == 0
    assert document["batch"]["nees_mean"] is None  # NaN (no covariances) is written as null
    assert math.isnan(metrics["batch"]["nees_mean"])
    tum = read_tum(tmp_path / "run" / "ekf.tum")
    np.testing.assert_array_equal(tum.t, truth.t)
    np.testing.assert_allclose(tum.position, truth.position + [0.3, 0.4, 0.0], rtol=0, atol=1e-12)
    saved_truth = files.load_trajectory(tmp_path / "run" / "truth.npz")
    np.testing.assert_array_equal(saved_truth.t, data.truth.t)


def test_a_failing_write_keeps_the_previous_metrics_json(tmp_path, monkeypatch):
    """metrics.json is written atomically: an error in the middle of writing it (here json.dump
    fails after writing part of the document) leaves the previous complete file, and no
    temporary file behind."""
    data, truth = cases.scored_data(), cases.scored_truth()
    out = tmp_path / "run"
    files.write_outputs(out, data, _estimates(truth), {"first": True})
    before = (out / "metrics.json").read_bytes()

    def broken_dump(obj, handle, **kwargs):
        handle.write('{"ekf": {"ate_rmse_m": 0.')
        raise OSError("disk full")

    monkeypatch.setattr(files.json, "dump", broken_dump)
    with pytest.raises(OSError, match="disk full"):
        files.write_outputs(out, data, _estimates(truth), {"first": False})
    assert (out / "metrics.json").read_bytes() == before
    assert json.loads(before)["_run"]["first"] is True
    assert not [p for p in out.iterdir() if p.name.endswith(".tmp")]


def test_jsonable_turns_numpy_and_non_finite_values_into_json():
    out = files.jsonable({"a": np.float64(np.inf), "b": [np.int64(3), np.array([1.5, np.nan])], "c": (1, "x")})
    assert json.loads(json.dumps(out)) == {"a": None, "b": [3, [1.5, None]], "c": [1, "x"]}
