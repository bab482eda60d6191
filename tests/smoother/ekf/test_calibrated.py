"""The EKF with calibrations as augmented states (smoother/ekf/calibrated.py) against the same
filter stepped in NumPy, dense and independently of the compiled loop.

Tolerance: 1e-9 relative to each quantity's largest magnitude (round-off of a few hundred IMU
steps and updates, each one 15 + 9 dimensional product or solve, condition numbers below 1e6;
the two differ in the order of their floating-point operations only).
"""
from __future__ import annotations

import dataclasses

import numpy as np

from datasets.kinds import KINDS, calibrated_rows, sensors_of
from datasets.simulate import simulate
from datasets.simulated_sensors import SensorSpec
from factors import imu, so3
from factors import sensor_models as sm
from factors.calibration import Calibration, CalibrationPrior
from smoother import stats
from smoother.ekf.calibrated import run_calibrated_ekf
from smoother.model.problem import calibration_set
from smoother.model.timeline import imu_steps, measurement_knots


def _rig():
    """3 s of ``gentle`` at 100 Hz: wheel speeds (50 Hz, mounted behind and pitched, reading 1 %
    low) calibrating every part, GNSS (10 Hz, an antenna above, fixes stamped 0.05 s late, one
    50 m outlier) calibrating its time offset and lever arm, and an orientation sensor (20 Hz)
    without calibration, so updates of all three sorts share knots."""
    wheels, antenna = np.eye(4), np.eye(4)
    wheels[:3, :3], wheels[:3, 3] = so3.exp(np.radians([0.0, 2.0, 0.0])), [-1.2, 0.0, -0.3]
    antenna[:3, 3] = [0.0, 0.0, 1.2]
    data = simulate("gentle", duration=3.0, seed=3, imu_rate=100.0, pose_rate=0, sensors=(
        SensorSpec("wheels", "velocity", 50.0, 0.05, wheels), SensorSpec("gnss", "gnss", 10.0, 0.2, antenna),
        SensorSpec("attitude", "orientation", 20.0, 0.01)))
    speeds, fixes = data.sensor("wheels").data, data.sensor("gnss").data
    data = data.with_sensor("wheels", data=dataclasses.replace(speeds, velocity=0.99 * speeds.velocity),
                            calibrate=CalibrationPrior(("time_offset", "rotation", "lever_arm", "scale"),
                                                       time_offset=0.02))
    late = fixes.t + 0.05 <= data.imu.t[-1]
    moved = fixes.subset(late)
    outlier = np.where(np.arange(len(moved.t)) == 12, 50.0, 0.0)[:, None]
    late_fixes = dataclasses.replace(moved, t=moved.t + 0.05, position=moved.position + outlier)
    return data.with_sensor("gnss", data=late_fixes, calibrate=CalibrationPrior(("time_offset", "lever_arm")))


def _dense_filter(data, calibrations, gate_probability):
    """The augmented EKF in NumPy: each IMU step's ``F``, ``G`` (:func:`factors.imu.propagate`)
    on the whole ``P``, ``A P A^T + G Q_d G^T`` with ``A = diag(F, I)``; updates sensor by sensor
    at each knot through the batch's calibrated residual (or the model's own), the Kalman
    equations written out; the corrections' boxplus written out (``exp(dphi) C``, ``exp(rho)
    R_BS``). Returns the states, the IMU blocks of ``P``, the NIS and acceptance of every update,
    the calibrations and their covariance blocks at the end."""
    knots = measurement_knots(data)
    steps = imu_steps(data.imu, knots)
    bounds = np.concatenate([[0], steps.knot_step])
    columns = [prior.columns for prior in calibrations.priors]
    at = 15 + np.concatenate([[0], np.cumsum([len(c) for c in columns])])
    n = at[-1]
    P = np.zeros((n, n))
    P[:15, :15] = data.initial_cov
    for j, prior in enumerate(calibrations.priors):
        P[at[j]:at[j + 1], at[j]:at[j + 1]] = np.diag(prior.sigmas**2)
    x, values = data.initial, list(calibrations.values)
    states, covs, nis, accepted = [], [], [], []
    for k, t in enumerate(knots):
        for i in range(bounds[k], bounds[k + 1]):
            x, F, G = imu.propagate(x, steps.acc[i], steps.gyro[i], steps.dt[i], data.gravity)
            A = np.eye(n)
            A[:15, :15] = F
            P = A @ P @ A.T
            P[:15, :15] += G @ data.noise.discrete_covariance(steps.dt[i]) @ G.T
        for s in sensors_of(data):
            kind = KINDS[s.kind]
            rows = kind.pack(s.data)
            for i in np.flatnonzero(s.data.t == t):
                H = np.zeros((kind.dim, n))
                if s.name in calibrations.names:
                    j = calibrations.names.index(s.name)
                    held = data.imu.held(t)
                    readings = ((data.imu.acc[held][None], data.imu.gyro[held][None])
                                if "time_offset" in calibrations.priors[j].parts else None)
                    e, H_x, H_c = calibrated_rows(kind, imu.ImuState(*(a[None] for a in (x.r, x.v, x.C, x.b_f, x.b_w))),
                                                  rows[i:i + 1], values[j], readings, data.gravity)
                    e, H[:, :15] = e[0], H_x[0]
                    H[:, at[j]:at[j + 1]] = H_c[0][:, columns[j]]
                else:
                    e, H[:, :15] = sm.evaluate_one(kind.model, x, rows[i])
                R = s.data.cov[i]
                S = H @ P @ H.T + R
                nis.append(e @ np.linalg.solve(S, e))
                accepted.append(nis[-1] <= stats.chi2_quantile(gate_probability, len(e)))
                if not accepted[-1]:
                    continue
                K = P @ H.T @ np.linalg.inv(S)
                dx, IKH = -K @ e, np.eye(n) - K @ H
                P = IKH @ P @ IKH.T + K @ R @ K.T
                x = imu.ImuState(x.r + dx[0:3], x.v + dx[3:6], so3.exp(dx[6:9]) @ x.C, x.b_f + dx[9:12],
                                 x.b_w + dx[12:15])
                for j, c in enumerate(values):
                    d = np.zeros(8)
                    d[columns[j]] = dx[at[j]:at[j + 1]]
                    values[j] = Calibration(c.time_offset + d[0], so3.exp(d[1:4]) @ c.R, c.p + d[4:7], c.scale + d[7])
        states.append(x)
        covs.append(P[:15, :15])
    return (imu.ImuState.stack(states), np.stack(covs), np.array(nis), np.array(accepted), values,
            [P[at[j]:at[j + 1], at[j]:at[j + 1]] for j in range(len(values))])


def _close(actual, expected, what):
    scale = np.abs(expected).max()
    np.testing.assert_allclose(actual, expected, rtol=0, atol=1e-9 * scale, err_msg=what)


def test_the_compiled_calibrating_filter_equals_the_dense_filter_stepped_in_numpy():
    """Its states, covariances, innovations and calibrations at every knot equal the dense
    reference's, with every part of a calibration estimated, a time offset on two sensors, a
    sensor without calibration, knots shared by all three and an outlier gated out. The
    calibrations move (the filter does not leave them at the priors' means)."""
    data = _rig()
    calibrations = calibration_set(data)
    result = run_calibrated_ekf(data, calibrations, gate_probability=0.999, progress=False)
    states, covs, nis, accepted, values, blocks = _dense_filter(data, calibrations, 0.999)
    for name in ("r", "v", "C", "b_f", "b_w"):
        _close(getattr(result.trajectory.states, name), getattr(states, name), name)
    _close(result.trajectory.cov, covs, "covariances")
    _close(result.innovations.nis, nis, "NIS")
    assert np.array_equal(result.innovations.accepted, accepted) and result.rejected == (~accepted).sum()
    outlier = (result.innovations.sensor == "gnss") & (result.innovations.t == data.sensor("gnss").data.t[12])
    assert outlier.sum() == 1 and not accepted[outlier].any()
    assert result.calibration.names == calibrations.names
    for j, (value, mean) in enumerate(zip(values, calibrations.means)):
        estimated = result.calibration.values[j]
        for part in ("time_offset", "R", "p", "scale"):
            _close(getattr(estimated, part), getattr(value, part), f"calibration {j}: {part}")
        _close(result.calibration_cov[j], blocks[j], f"calibration {j}: covariance")
        moved = np.abs(estimated.boxminus(mean))[calibrations.priors[j].columns]
        assert np.all(moved > 1e-6), (j, moved)
