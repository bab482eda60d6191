"""The EKF with sensors' calibrations as augmented states: the same model as the batch smoother's.

The state is the IMU's error state (15) followed by the estimated coordinates of each calibrating
sensor's calibration (:class:`factors.calibration.CalibrationSet`, their order), with one joint
covariance ``P``. The calibrations are constants of the recording: between updates

    P_xx <- Phi P_xx Phi^T + Q,   P_xc <- Phi P_xc,   P_cc unchanged,

``Phi`` the error-state transition of the IMU steps (:func:`factors.imu.transition_into`) and
``P_xx``'s own step that of :func:`factors.imu.predict_into` (the plain filter's, noise
included). An update linearises the calibrated residual (:func:`datasets.kinds.calibrated_into`,
the batch's kernel): ``H = [H_x, 0 .., H_c, 0 ..]`` with ``H_c`` in its sensor's columns; a sensor
that does not calibrate has zeros there. The correction ``dx = -K e`` is applied with the state's
boxplus and the calibrations' (:func:`factors.calibration.set_boxplus_into`, the kernel of
:meth:`~factors.calibration.CalibrationSet.boxplus`: rotations on the left). The updates' order,
the Kalman update with its gate (Joseph form, on the whole augmented ``P``) and the divergence
test are the plain filter's (:mod:`smoother.ekf.update`).

The loop over knots is the plain filter's, compiled (:func:`smoother.ekf.filter.run_filter`): the
calibrations ride along as packed values (:func:`factors.calibration.packed`), the states and
15x15 covariances of the knots kept go into arrays allocated once. Relative poses (odometry) are
left out, as in the plain filter.
"""
from __future__ import annotations

import numpy as np

from datasets.types import Dataset
from factors import calibration, imu
from smoother.ekf.filter import FilterResult, run_filter

D = imu.STATE_DIM


def run_calibrated_ekf(dataset: Dataset, calibrations: calibration.CalibrationSet,
                       gate_probability: float | None = None, progress: bool | None = None,
                       kept_at=None) -> FilterResult:
    """The EKF over ``dataset`` with ``calibrations`` (its sensors' variables, at their priors'
    means and covariances) as augmented states (module docstring), its states kept at every knot
    or at the times ``kept_at`` (:func:`smoother.ekf.filter.run_filter`). The result carries the
    calibrations at the end of the data and their covariance blocks (``calibration``,
    ``calibration_cov``)."""
    sigmas = np.concatenate([np.zeros(0), *(prior.sigmas for prior in calibrations.priors)])
    P = np.zeros((D + len(sigmas),) * 2)
    P[:D, :D] = dataset.initial_cov
    P[D:, D:] = np.diag(sigmas**2)
    return run_filter(dataset, P, calibrations, gate_probability, progress, kept_at)
