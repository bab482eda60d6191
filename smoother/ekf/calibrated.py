"""The EKF with sensors' calibrations as augmented states: the same model as the batch smoother's.

The state is the IMU's error state (15) followed by the estimated coordinates of each calibrating
sensor's calibration (:class:`factors.calibration.CalibrationSet`, their order), with one joint
covariance ``P``. The calibrations are constants of the recording: between updates

    P_xx <- Phi P_xx Phi^T + Q,   P_xc <- Phi P_xc,   P_cc unchanged,

``Phi`` the error-state transition of the IMU steps (:func:`factors.imu.transition_into`) and
``P_xx``'s own step that of :func:`factors.imu.predict_into` (the plain filter's, noise
included). An update linearises the calibrated residual (:func:`datasets.kinds.calibrated_rows`,
the batch's): ``H = [H_x, 0 .., H_c, 0 ..]`` with ``H_c`` in its sensor's columns; a sensor that
does not calibrate has zeros there. The correction ``dx = -K e`` is applied with the state's
boxplus and the calibrations' (:meth:`~factors.calibration.CalibrationSet.boxplus`: rotations on
the left). The updates' order, the Kalman update with its gate (Joseph form, on the whole
augmented ``P``) and the divergence test are the plain filter's (:mod:`smoother.ekf.update`).

The loop runs in Python per knot (measurement time); the IMU steps between knots are compiled.
Relative poses (odometry) are left out, as in the plain filter.
"""
from __future__ import annotations

import time

import numpy as np

from datasets.kinds import KINDS, calibrated_rows
from datasets.types import Dataset, Trajectory
from factors import calibration, imu
from factors.sensor_models import evaluate_one
from smoother.ekf.filter import FilterResult, Innovations, divergence_error, filter_inputs
from smoother.ekf.update import diverged, gate_thresholds, kalman_update, update_order
from smoother.progress import progress_bar

D = imu.STATE_DIM


def run_calibrated_ekf(dataset: Dataset, calibrations: calibration.CalibrationSet,
                       gate_probability: float | None = None, progress: bool | None = None) -> FilterResult:
    """The EKF over ``dataset`` with ``calibrations`` (its sensors' variables, at their priors'
    means and covariances) as augmented states (module docstring). The result carries the
    calibrations at the end of the data and their covariance blocks (``calibration``,
    ``calibration_cov``)."""
    start = time.perf_counter()
    sensors, knots, steps = filter_inputs(dataset)
    bounds = np.concatenate([[0], steps.knot_step]).astype(np.int64)
    acc, gyro, dt = (np.ascontiguousarray(a, dtype=float) for a in (steps.acc, steps.gyro, steps.dt))
    dims = calibrations.dims
    offsets = np.concatenate([[D], D + np.cumsum(dims)]).astype(int)
    n = int(offsets[-1])
    P = np.zeros((n, n))
    P[:D, :D] = dataset.initial_cov
    for j, prior in enumerate(calibrations.priors):
        P[offsets[j]:offsets[j + 1], offsets[j]:offsets[j + 1]] = np.diag(prior.sigmas ** 2)
    x0 = dataset.initial
    r, v, C, b_f, b_w = (np.array(a, dtype=float) for a in (x0.r, x0.v, x0.C, x0.b_f, x0.b_w))
    g, q = np.asarray(dataset.gravity, dtype=float), dataset.noise.densities()
    c = calibrations
    slot = {name: j for j, name in enumerate(c.names)}
    prepared = []  # per sensor: kind, rows, cov, calibration index or None, IMU readings at its stamps or None
    for s in sensors:
        kind, m = KINDS[s.kind], s.data
        j = slot.get(s.name)
        readings = None
        if j is not None and "time_offset" in c.priors[j].parts:
            held = dataset.imu.held(m.t)
            readings = (dataset.imu.acc[held], dataset.imu.gyro[held])
        prepared.append((kind, kind.pack(m), m.cov, j, readings))
    order = update_order([s.data.t for s in sensors], knots, [s.name for s in sensors])
    gates = gate_thresholds(gate_probability)
    out_states, out_P = [], []
    names, times, update_dims, nis, accepted = [], [], [], [], []
    stats, step = np.zeros(2), np.empty(n)  # rejections and log-likelihood; the correction
    Phi = np.empty((D, D))
    with progress_bar(len(dt), "EKF (calibrating)", progress) as bar:
        for knot in range(len(knots)):
            a, b = bounds[knot], bounds[knot + 1]
            if b > a:
                Phi[:, :] = np.eye(D)
                imu.transition_into(r.copy(), v.copy(), C.copy(), b_f, b_w, acc[a:b], gyro[a:b], dt[a:b], g, Phi)
                P_xx = np.ascontiguousarray(P[:D, :D])
                imu.predict_into(r, v, C, b_f, b_w, P_xx, acc[a:b], gyro[a:b], dt[a:b], q, g)
                P[:D, :D] = P_xx
                P[:D, D:] = Phi @ P[:D, D:]
                P[D:, :D] = P[:D, D:].T
            for u in range(order.start[knot], order.start[knot + 1]):
                index, i = order.sensor[u], order.measurement[u]
                kind, rows, cov, j, readings = prepared[index]
                names.append(sensors[index].name)
                times.append(knots[knot])
                update_dims.append(kind.dim)
                if diverged(r, v, C, b_f, b_w, P):
                    nis.append(np.nan)
                    accepted.append(False)
                    continue
                state = imu.ImuState(r, v, C, b_f, b_w)
                H = np.zeros((kind.dim, n))
                if j is None:
                    e, H[:, :D] = evaluate_one(kind.model, state, rows[i])
                else:
                    at = None if readings is None else (readings[0][i:i + 1], readings[1][i:i + 1])
                    e, H_x, H_c = calibrated_rows(kind, state[None], rows[i:i + 1], c.values[j], at, dataset.gravity)
                    e, H[:, :D] = e[0], H_x[0]
                    H[:, offsets[j]:offsets[j + 1]] = H_c[0][:, c.priors[j].columns]
                rejected = stats[0]
                nis.append(kalman_update(P, np.ascontiguousarray(e, dtype=float), H,
                                         np.ascontiguousarray(cov[i], dtype=float), gates, stats, step))
                accepted.append(bool(stats[0] == rejected))
                if not accepted[-1]:
                    continue
                moved = imu.boxplus(state, step[:D])
                r, v, C = moved.r.copy(), moved.v.copy(), moved.C.copy()
                b_f, b_w = moved.b_f.copy(), moved.b_w.copy()
                c = c.boxplus(np.split(step[D:], offsets[1:-1] - D))
            out_states.append(imu.ImuState(r.copy(), v.copy(), C.copy(), b_f.copy(), b_w.copy()))
            out_P.append(P[:D, :D].copy())
            if diverged(r, v, C, b_f, b_w, P):
                raise divergence_error(knots[knot], v, P[:D, :D])
            bar.update(int(b) - bar.n)
    innovations = Innovations(np.asarray(names, dtype=object), np.asarray(times), np.asarray(update_dims),
                              np.asarray(nis), np.asarray(accepted, dtype=bool))
    return FilterResult(Trajectory(knots, imu.ImuState.stack(out_states), np.stack(out_P)),
                        time.perf_counter() - start, int(stats[0]), float(stats[1]), innovations, c,
                        [P[offsets[j]:offsets[j + 1], offsets[j]:offsets[j + 1]].copy() for j in range(len(c))])

