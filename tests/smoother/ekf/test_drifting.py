"""The EKF with a sensor whose errors drift (``correlation_time``): each such sensor's error a
first-order Gauss-Markov state beside the IMU's, the batch smoother's model -- the batch's last
state is the filter's (filtering and smoothing coincide there), a vanishing correlation time is the
white filter, and its innovations and held-out predictions fit where the model is the truth."""
from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest
from drifting_fixes import drifting_run as drifting

from datasets.types import PositionMeasurements, Sensor
from smoother import pipeline
from smoother.batch.solve import solve_batch
from smoother.ekf.filter import run_ekf
from smoother.evaluation.crosscheck import sigma_difference
from smoother.model.correlated import with_correlated_errors
from smoother.model.problem import build_problem


def _attitude_fixed(data):
    """``data`` with its pose sensor's positions a hundred times less certain: its attitudes keep the
    problem near linear (position fixes alone leave the yaw to the linearisation, where filter and
    smoother part by 2 sigma on the white model too), the drifting fixes set the positions."""
    pose = data.sensor("pose")
    cov = pose.data.cov.copy()
    cov[:, :3, :] *= 100.0
    cov[:, :, :3] *= 100.0
    return data.with_sensor("pose", data=replace(pose.data, cov=cov))


@pytest.mark.parametrize("seed, tau", [(0, 10.0), (1, 3.0)])
def test_the_batch_s_last_state_is_the_filter_s_on_the_drifting_model(seed, tau):
    """The same model on both sides: the batch's last keyframe within 0.15 of the EKF's sigma in
    every component (measured 0.08-0.12; the white model's pair: 0.12-0.23) and position covariance
    traces within 1 %; the white EKF against the drifting batch is not the same model (0.9-2.2
    sigma, traces 1.8 times apart)."""
    data = _attitude_fixed(drifting(seed, tau, duration=30.0, pose_rate=1.0))
    problem = with_correlated_errors(build_problem(data), data)
    batch = solve_batch(problem).trajectory
    ekf = run_ekf(data, progress=False, kept_at=problem.times).trajectory
    np.testing.assert_array_equal(ekf.t, batch.t)

    def apart(a, b):
        gap = sigma_difference(a.states[-1], b.states[-1], b.cov[-1])
        return gap.max(), np.trace(a.cov[-1][:3, :3]) / np.trace(b.cov[-1][:3, :3])

    gap, ratio = apart(batch, ekf)
    assert gap < 0.15 and abs(ratio - 1.0) < 0.01, (gap, ratio)
    white = run_ekf(data.with_sensor("gnss", correlation_time=None), progress=False, kept_at=problem.times).trajectory
    gap, ratio = apart(batch, white)
    assert gap > 0.5 and ratio > 1.5, (gap, ratio)


def test_a_vanishing_correlation_time_is_the_white_filter():
    data = drifting(2, 0.01, duration=10.0)  # the shortest a dataset takes: 20 of them between fixes
    drifting_filter = run_ekf(data, progress=False)
    white = run_ekf(data.with_sensor("gnss", correlation_time=None), progress=False)
    np.testing.assert_allclose(drifting_filter.trajectory.states.r, white.trajectory.states.r, rtol=0, atol=1e-9)
    np.testing.assert_allclose(drifting_filter.trajectory.cov, white.trajectory.cov, rtol=1e-9, atol=1e-15)
    np.testing.assert_allclose(drifting_filter.innovations.nis, white.innovations.nis, rtol=1e-8)
    held, plain = drifting_filter.heldout["gnss"], white.heldout["gnss"]
    np.testing.assert_allclose(held.e, plain.e, rtol=0, atol=1e-9)
    np.testing.assert_allclose(held.state_part, plain.state_part, rtol=1e-8, atol=1e-15)
    np.testing.assert_allclose(held.conditioned.noise, np.broadcast_to(np.eye(3), held.conditioned.noise.shape),
                               atol=1e-8)  # the error given the state: all of it, independent
    np.testing.assert_allclose(held.conditioned.e, held.e / 0.5, rtol=1e-8)  # whitened by the stated 0.5 m


def test_the_filter_s_innovations_and_held_out_predictions_of_drifting_fixes_are_in_band():
    """Six simulated runs whose fixes drift as the model says: the EKF's held-out verdicts' mean per
    dof in one run's band and its innovations' near 1 per dof; taking the errors as white, far below."""
    held, nis, white = [], [], []
    for seed in range(6):
        data = drifting(seed, 10.0)
        estimates = pipeline.run_estimators(data, ["ekf"], pipeline.RunOptions(progress=False))
        verdict = pipeline.heldout_by_estimator(data, estimates)["ekf"]["gnss"]
        assert verdict["given_used_errors"]
        held.append(verdict["per_dof"])
        band = verdict["band"]
        innovations = estimates["ekf"].innovations
        conditioned = estimates["ekf"].heldout["gnss"].conditioned
        for part in (conditioned.state_part, conditioned.noise):  # a split into two covariances
            assert np.linalg.eigvalsh(part).min() > -1e-9
        assert 0.0 <= verdict["state_share"] <= 1.0
        nis.append(np.mean(innovations.nis[innovations.sensor == "gnss"]) / 3)
        plain = pipeline.run_estimators(data.with_sensor("gnss", correlation_time=None), ["ekf"],
                                        pipeline.RunOptions(progress=False))
        white.append(pipeline.heldout_by_estimator(data, plain)["ekf"]["gnss"]["per_dof"])
    assert band[0] < np.mean(held) < band[1], held
    assert 0.85 < np.mean(nis) < 1.15, nis
    assert max(white) < 0.5, white


def _with_second_sensor(data, shift: float):
    """``data`` with a second drifting position sensor (3 s) used at every fix of ``gnss`` (its
    held-out ones too), stamped ``shift`` seconds later."""
    gnss = data.sensor("gnss")
    t = np.concatenate([gnss.data.t, gnss.heldout.t])
    order = np.argsort(t)
    fixes = PositionMeasurements(t[order] + shift, np.concatenate([gnss.data.position, gnss.heldout.position])[order],
                                 np.concatenate([gnss.data.cov, gnss.heldout.cov])[order])
    return replace(data, sensors=(*data.sensors, Sensor("second", "position", fixes, correlation_time=3.0)))


def test_a_held_out_fix_where_another_drifting_sensor_was_just_used_is_predicted_as_a_moment_after_it():
    """Another drifting sensor's update at the same instant (its noise all its error's, ``R`` zero)
    leaves the rest of the state singular beside ``gnss``'s error, and its held-out prediction
    conditions on it (a degenerate Gaussian: the pseudo-inverse, where a solve stops in numpy's
    "singular matrix"): its verdict is the one of the same data with the other sensor's stamps a
    tenth of a millisecond earlier, where nothing is singular, within 1e-3."""
    data = drifting(0, 5.0, duration=10.0)
    per_dof = []
    for shift in (0.0, -1e-4):
        shifted = _with_second_sensor(data, shift)
        estimates = pipeline.run_estimators(shifted, ["ekf"], pipeline.RunOptions(progress=False))
        per_dof.append(pipeline.heldout_by_estimator(shifted, estimates)["ekf"]["gnss"]["per_dof"])
    assert np.isfinite(per_dof[0])
    assert per_dof[0] == pytest.approx(per_dof[1], rel=1e-3), per_dof
