"""The primer's EKF (section VI.E) on the model of :mod:`factors.imu`.

Prediction per IMU step with ``F``, ``G`` and ``Q_d = diag(R_i / dt)`` (between two updates all
steps at once, :meth:`Ekf.predict_steps`, the same recursion unrolled); updates linearise the
same measurement residuals the smoother's factors use (:mod:`factors.measurements`), so the
innovation of an attitude is the boxminus ``C [-] C_meas`` and the correction is applied with
the state boxplus (``exp(dphi) C`` for the attitude). Covariance update in Joseph form, kept
symmetric. An optional chi-square gate rejects measurements whose normalised innovation is
improbable.

Relative-pose measurements need a cloned past state and are not used by this filter (the
smoother uses them); :func:`run_ekf` warns when a dataset has them.
"""
from __future__ import annotations

import math
import time
import warnings
from dataclasses import dataclass

import numpy as np

from datasets.types import Dataset, Trajectory
from factors import imu, measurements as meas
from smoother.metrics import chi2_quantile
from smoother.progress import progress_bar
from smoother.timeline import estimate_times, imu_steps


class Ekf:
    """Error-state EKF over ``x = (r, v, Phi, b_f, b_w)`` with covariance ``P`` (15x15, the
    primer's left-perturbation error state)."""

    def __init__(self, state: imu.ImuState, cov: np.ndarray, noise: imu.ImuNoise, gravity=imu.DEFAULT_GRAVITY,
                 gate_probability: float | None = None):
        self.state = state
        self.P = np.array(cov, dtype=float)
        self.noise = noise
        self.gravity = np.asarray(gravity, dtype=float)
        self.gate_probability = gate_probability
        self.rejected = 0
        #: Sum of the log densities of the accepted innovations, ``log N(e; 0, S)``: the
        #: prediction-error decomposition of the measurements' likelihood under the model.
        self.log_likelihood = 0.0

    def predict(self, acc, gyro, dt) -> None:
        """One Euler-forward step: ``x <- f(x)``, ``P <- F P F^T + G Q_d G^T``."""
        self.predict_steps(np.reshape(acc, (1, 3)), np.reshape(gyro, (1, 3)), np.reshape(dt, (1,)))

    def predict_steps(self, acc, gyro, dt) -> None:
        """:meth:`predict` applied to every step of ``acc, gyro (K, 3)``, ``dt (K,)``: one call of
        the compiled :func:`factors.imu.propagate_steps`, no Python per step."""
        if np.size(dt) == 0:
            return
        self.state, self.P = imu.propagate_steps(self.state, self.P, acc, gyro, dt, self.noise, self.gravity)

    def update(self, e: np.ndarray, H: np.ndarray, R: np.ndarray) -> bool:
        """Correct with a residual ``e(x)`` (measurement model minus measurement, e.g.
        ``C [-] C_meas``), its Jacobian ``H`` (m x 15, error-state columns) and noise ``R``.
        Returns False when the chi-square gate rejects it: the normalised innovation
        ``e^T S^-1 e`` beyond the ``gate_probability`` quantile of chi-square with ``len(e)``
        degrees of freedom (so 3-dim and 6-dim updates are gated alike)."""
        S = H @ self.P @ H.T + R
        PHt = self.P @ H.T
        d2 = float(e @ np.linalg.solve(S, e))
        if self.gate_probability is not None and d2 > chi2_quantile(self.gate_probability, len(e)):
            self.rejected += 1
            return False
        self.log_likelihood -= 0.5 * (d2 + np.linalg.slogdet(2.0 * np.pi * S)[1])
        K = np.linalg.solve(S, PHt.T).T
        dx = -K @ e
        self.state = imu.boxplus(self.state, dx)
        IKH = np.eye(imu.STATE_DIM) - K @ H
        P = IKH @ self.P @ IKH.T + K @ R @ K.T
        self.P = 0.5 * (P + P.T)
        return True

    def update_position(self, measured, R) -> bool:
        e, (J,) = meas.position_residual(self.state.r, measured, jacobians=True)
        H = np.zeros((3, imu.STATE_DIM))
        H[:, imu.R] = J
        return self.update(e, H, R)

    def update_orientation(self, measured_C, R) -> bool:
        e, (J,) = meas.orientation_residual(self.state.C, measured_C, jacobians=True)
        H = np.zeros((3, imu.STATE_DIM))
        H[:, imu.PHI] = J
        return self.update(e, H, R)

    def update_pose(self, measured_r, measured_C, R) -> bool:
        """Primer section VI.D: ``H = [[I 0 0 0 0], [0 0 I 0 0]]`` at zero innovation; here the
        exact Jacobian of the residual (``Gamma^-1(e)`` on the attitude block)."""
        e, (J_r, J_C) = meas.pose_residual(self.state.r, self.state.C, measured_r, measured_C, jacobians=True)
        H = np.zeros((6, imu.STATE_DIM))
        H[:, imu.R] = J_r
        H[:, imu.PHI] = J_C
        return self.update(e, H, R)


@dataclass
class FilterResult:
    """Estimates and covariances at every knot (start, each measurement time, end)."""

    trajectory: Trajectory
    runtime_s: float
    rejected: int
    log_likelihood: float


def run_ekf(dataset: Dataset, gate_probability: float | None = None, progress: bool | None = None) -> FilterResult:
    """Run the EKF over a dataset: predict through every IMU step, update at each measurement
    time with every measurement taken then, record the state after the updates."""
    start = time.perf_counter()
    if dataset.relative_pose is not None and len(dataset.relative_pose):
        warnings.warn("the EKF does not use relative-pose measurements; the smoothers do", stacklevel=2)
    knots = estimate_times(dataset)
    steps = imu_steps(dataset.imu, knots)
    ekf = Ekf(dataset.initial, dataset.initial_cov, dataset.noise, dataset.gravity, gate_probability)
    lookups = _measurement_lookup(dataset)
    states, covs = [], []
    step = 0
    with progress_bar(len(steps.dt), "EKF", progress) as bar:
        for knot, stop in zip(knots, steps.knot_step):
            ekf.predict_steps(steps.acc[step:stop], steps.gyro[step:stop], steps.dt[step:stop])
            step = int(stop)
            bar.update(step - bar.n)
            for kind, (times, apply) in lookups.items():
                i = np.searchsorted(times, knot)
                if i < len(times) and times[i] == knot:
                    apply(ekf, i)
            _check_divergence(ekf, knot)
            states.append(ekf.state)
            covs.append(ekf.P.copy())
    trajectory = Trajectory(knots, imu.ImuState.stack(states), np.stack(covs))
    return FilterResult(trajectory, time.perf_counter() - start, ekf.rejected, ekf.log_likelihood)


#: Beyond these the filter is declared diverged: |velocity| [m/s], sqrt(trace P) (mixed units).
DIVERGED_SPEED = 1e4
DIVERGED_SPREAD = 1e6


class FilterDiverged(ValueError):
    """The EKF's state or covariance left any plausible range (non-finite or absurdly large)."""


def _check_divergence(ekf: Ekf, t: float) -> None:
    x, P = ekf.state, ekf.P
    speed = float(np.sqrt(x.v @ x.v))
    # one sum is finite only if every term is: a single check instead of one per array
    finite = np.isfinite(speed + P.sum() + x.r.sum() + x.C.sum() + x.b_f.sum() + x.b_w.sum())
    spread = float(np.sqrt(max(np.trace(P), 0.0))) if finite else math.inf
    if not finite or speed > DIVERGED_SPEED or spread > DIVERGED_SPREAD:
        raise FilterDiverged(
            f"the EKF diverged at t = {t:.6f} s (|v| = {speed:.3g} m/s, sqrt(trace P) = "
            f"{np.sqrt(abs(np.trace(P))):.3g}): the linearisation failed, typically after a long stretch "
            "without measurements or with a bias random walk far looser than the data; a smoother "
            "(batch or fixed-lag) relinearises and is the tool for such data")


def _measurement_lookup(dataset: Dataset) -> dict:
    """For each measurement type: its times and a function applying row ``i`` to the filter."""
    out = {}
    if dataset.pose is not None:
        m = dataset.pose
        out["pose"] = (m.t, lambda f, i: f.update_pose(m.position[i], m.C[i], m.cov[i]))
    if dataset.position is not None:
        m2 = dataset.position
        out["position"] = (m2.t, lambda f, i: f.update_position(m2.position[i], m2.cov[i]))
    if dataset.orientation is not None:
        m3 = dataset.orientation
        out["orientation"] = (m3.t, lambda f, i: f.update_orientation(m3.C[i], m3.cov[i]))
    return out
