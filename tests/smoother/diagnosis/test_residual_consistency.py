"""A smoother's own verdict on each sensor and on the IMU (smoother/diagnosis/residual_consistency.py):
residuals normalised by their leverages."""
from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from datasets.simulate import simulate
from datasets.simulated_sensors import SensorSpec
from datasets.types import ImuSamples, max_gyro_rate
from factors.imu import ImuNoise
from smoother.batch.solve import solve_batch
from smoother.diagnosis.residual_consistency import block_consistency
from smoother.diagnosis.verdicts import consistency_lines, consistency_warnings
from smoother.model.problem import build_problem
from smoother.pipeline import judged, run_estimators, verdicts_by_estimator


def _solved(data):
    problem = build_problem(data)
    result = solve_batch(problem)
    return problem, result


def test_the_leverages_of_all_factors_add_up_to_the_number_of_estimated_variables():
    """``sum_i tr(A_i Sigma A_i^T) = tr(Sigma H) = n`` at the solution: the degrees of freedom of
    the blocks (residual dimensions minus leverages) add up to ``m - n`` exactly."""
    data = simulate("gentle", duration=3, seed=5, pose_rate=None, sensors=[
        SensorSpec("gnss", "gnss", 2.0, 0.3), SensorSpec("wheels", "velocity", 10, 0.05)])
    problem, result = _solved(data)
    t = result.trajectory
    verdicts = [block_consistency(b, t.states, t.cov, result.joint) for b in problem.blocks]
    m = sum(b.whiten.shape[0] * b.whiten.shape[1] for b in problem.blocks)
    n = 15 * len(problem.times)
    assert sum(v["dof"] for v in verdicts) == pytest.approx(m - n, rel=1e-6)


def test_a_sensor_that_determines_its_state_is_judged_by_what_is_left_of_its_residuals():
    """GNSS fixes of 1 cm a second beside a poor accelerometer (0.2 m/s^2/sqrt(Hz)): each fix
    nearly fixes the position it measures (leverage close to 3), so its raw residuals are far
    below their nominal size; normalised by the degrees of freedom left, they are consistent, in
    every seed."""
    for seed in range(3):
        data = simulate("gentle", duration=20, seed=seed, pose_rate=None, noise=ImuNoise(acc=0.2),
                        sensors=[SensorSpec("gnss", "gnss", 1.0, 0.01)])
        problem, result = _solved(data)
        block = next(b for b in problem.blocks if b.name == "gnss")
        t = result.trajectory
        c = block_consistency(block, t.states, t.cov, result.joint)
        raw = c["per_dof"] * c["dof"] / (3 * c["measurements"])
        assert raw < 0.6 and c["dof"] < 0.6 * 3 * c["measurements"], (raw, c)
        assert c["band"][0] / 1.05 < c["per_dof"] < 1.05 * c["band"][1], c


@pytest.fixture(scope="module")
def gyro_in_degrees():
    """A wheeled rig whose gyro was recorded in deg/s (every other sensor right)."""
    data = simulate("gentle", duration=20, seed=2, pose_rate=None, sensors=[
        SensorSpec("gnss", "gnss", 1.0, 1.0), SensorSpec("wheels", "velocity", 10, 0.05)])
    with max_gyro_rate(1e4):
        wrong = dataclasses.replace(data, imu=ImuSamples(data.imu.t, data.imu.acc, np.degrees(data.imu.gyro)))
        estimates = run_estimators(wrong, ["batch", "fixed-lag", "ekf"], keep_going=True)
        consistency = verdicts_by_estimator(wrong, estimates)
    judged(estimates, consistency)
    return estimates, consistency


def test_an_imu_fault_is_named_as_one(gyro_in_degrees):
    """The IMU's own residuals are judged through the batch smoother: far out of band, the first
    warning names the IMU and its units, and every other sensor's warning says the IMU is the
    likelier cause (measured: IMU residuals ~6e5 per dof, wheels ~6e3, GNSS ~1.4e3)."""
    _, consistency = gyro_in_degrees
    assert consistency["batch"]["imu"]["per_dof"] > 1e3
    warnings = consistency_warnings(consistency)
    assert warnings[0].startswith("imu:") and "deg/s" in warnings[0]
    others = warnings[1:]
    assert {w.split(":")[0] for w in others} == {"gnss", "wheels"}
    assert all("the IMU is the likelier cause" in w for w in others)
    assert consistency_lines(consistency)[-1].startswith("imu (")


def test_an_estimate_that_does_not_fit_its_data_is_doubtful_whatever_the_optimiser_says(gyro_in_degrees):
    estimates, _ = gyro_in_degrees
    for name, est in estimates.items():
        assert est.failed is None
        assert "the model does not fit the data" in est.details["doubtful"], name
    assert estimates["batch"].details["converged"] in (True, False)  # reported beside it, not instead


def test_a_right_rig_is_neither_warned_of_nor_doubtful():
    data = simulate("gentle", duration=20, seed=2, pose_rate=None, sensors=[
        SensorSpec("gnss", "gnss", 1.0, 1.0), SensorSpec("wheels", "velocity", 10, 0.05)])
    estimates = run_estimators(data, ["batch", "fixed-lag", "ekf"])
    consistency = verdicts_by_estimator(data, estimates)
    judged(estimates, consistency)
    assert consistency_warnings(consistency) == []
    assert not any("doubtful" in est.details for est in estimates.values())
    assert set(consistency["batch"]) == {"gnss", "wheels", "imu"}
    assert set(consistency["fixed-lag"]) == {"gnss", "wheels"}  # its IMU factors' joint covariances are not kept


def test_an_imu_slightly_out_of_band_is_not_blamed_for_a_sensor_far_worse():
    """The IMU's residuals at 2.02 per dof, a GNSS's at 5.68 (a real bag with a GNSS sigma too
    small): the IMU is mentioned, not named the likelier cause."""
    def c(value, lo=0.9, hi=1.1):
        return {"per_dof": value, "band": [lo, hi], "ok": lo <= value <= hi, "measurements": 100, "dof": 100.0,
                "statistic": "residual"}

    lines = consistency_warnings({"batch": {"gnss": c(5.68), "imu": c(2.02)}})
    gnss = next(line for line in lines if line.startswith("gnss"))
    assert "likelier cause" not in gnss and "out of band too (2.02 per dof): check both" in gnss
    lines = consistency_warnings({"batch": {"gnss": c(5.68), "imu": c(600.0)}})
    assert "the IMU is the likelier cause" in next(line for line in lines if line.startswith("gnss"))


def test_a_sensor_s_warning_names_every_estimator_out_of_its_band():
    """The car's GNSS with a delay and a lever arm left out: batch 2.01 and EKF 2.21 per dof raise
    the warning, the fixed-lag smoother's 1.99 (out of band, not twice off) is in it too; one in
    its band is not."""
    def c(value, lo=0.93, hi=1.1):
        return {"per_dof": value, "band": [lo, hi], "ok": lo <= value <= hi, "measurements": 579, "dof": 1737.0,
                "statistic": "residual"}

    [line] = consistency_warnings({"batch": {"gnss": c(2.01)}, "fixed-lag": {"gnss": c(1.99)},
                                   "ekf": {"gnss": c(2.21)}, "other": {"gnss": c(1.0)}})
    assert "batch 2.01" in line and "fixed-lag 1.99" in line and "ekf 2.21" in line and "other" not in line
    assert consistency_warnings({"fixed-lag": {"gnss": c(1.99)}}) == []  # alone it warns of nothing


def test_evaluating_in_chunks_changes_nothing(monkeypatch):
    import smoother.model.blocks as blocks

    data = simulate("gentle", duration=3, seed=5, pose_rate=None, sensors=[SensorSpec("wheels", "velocity", 20, 0.05)])
    problem, result = _solved(data)
    t = result.trajectory
    whole = [block_consistency(b, t.states, t.cov, result.joint) for b in problem.blocks]
    monkeypatch.setattr(blocks, "CHUNK", 7)
    chunked = [block_consistency(b, t.states, t.cov, result.joint) for b in problem.blocks]
    for a, b in zip(whole, chunked):
        assert a["measurements"] == b["measurements"]
        assert a["per_dof"] == pytest.approx(b["per_dof"], rel=1e-12) and a["dof"] == pytest.approx(b["dof"], rel=1e-12)
