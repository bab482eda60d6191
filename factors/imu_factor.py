"""The IMU factor: the preintegrated primer model between two keyframes inside GTSAM.

Variables of each keyframe (:mod:`factors.keys`): ``Rot3`` attitude, ``Point3`` position, body
velocity (3-vector) and ``imuBias.ConstantBias``. The 15-dim residual, its Jacobians and its
covariance are those of :func:`factors.preintegration.residual`; rotation Jacobians go through the
chart adapter in :func:`factors.custom.custom_factor`. The bias random walk is inside the factor
(its last six rows), so no separate bias-between factor is needed.

When the gyro bias of keyframe ``i`` moves more than ``reintegration_threshold`` (rad/s) from the
point the interval was integrated at, the interval is integrated again around the new value
(the first-order bias model is only good near its linearisation point). The noise model stays
the one computed at construction.
"""
from __future__ import annotations

import numpy as np

from factors import imu, preintegration
from factors.custom import BIAS, ROT, VEC, custom_factor
from factors.errors import InputError
from factors.keys import KeyframeKeys
from factors.priors import covariance_model

#: The variable types of one keyframe's end of the factor, in its key order (Rot3, Point3, V, bias).
KEYFRAME_VARIABLES = [ROT, VEC, VEC, BIAS]


def _reorder(J: np.ndarray) -> list[np.ndarray]:
    """Error-state columns (r, v, phi, b_f, b_w) -> the factor's variables (Rot3, Point3, V, bias)."""
    return [J[:, imu.PHI], J[:, imu.R], J[:, imu.V], J[:, imu.BF.start:imu.BW.stop]]  # (b_f, b_w) adjacent


class _Interval:
    """What the GTSAM callback of an IMU factor needs: the preintegrated interval (integrated again
    when the gyro bias moves, counted in ``reintegrations``), gravity and the threshold.

    It is kept apart from :class:`ImuFactor` so that the callback GTSAM holds does not refer back
    to the factor's Python objects: ``ImuFactor -> CustomFactor -> (C++) callback -> ImuFactor``
    would be a cycle through GTSAM's C++ object, which Python's collector cannot see, and every
    IMU factor ever made would stay in memory (a fixed-lag run makes one per keyframe)."""

    def __init__(self, pre: preintegration.Preintegrated, gravity: np.ndarray, threshold: float):
        self.pre = pre
        self.gravity = gravity
        self.threshold = threshold
        self.reintegrations = 0

    def _maybe_reintegrate(self, b_w: np.ndarray) -> None:
        bar = self.pre.b_w_bar
        if max(abs(b_w[0] - bar[0]), abs(b_w[1] - bar[1]), abs(b_w[2] - bar[2])) > self.threshold:
            self.pre = self.pre.relinearized(b_w)
            self.reintegrations += 1

    def residual(self, Ci, ri, vi, bi, Cj, rj, vj, bj, jacobians: bool):
        self._maybe_reintegrate(bi[3:])
        out = preintegration.residual_one(self.pre, Ci, ri, vi, bi, Cj, rj, vj, bj, self.gravity, jacobians)
        if not jacobians:
            return out
        e, (Ji, Jj) = out
        return e, _reorder(Ji) + _reorder(Jj)


class ImuFactor:
    """Builds the ``gtsam.CustomFactor`` of one preintegrated interval.

    ``pre`` is one interval of :class:`factors.preintegration.Preintegrated` (no leading
    dimension) with its covariance. ``factor`` is the GTSAM factor to add to a graph; ``pre`` the
    interval as the factor last used it and ``reintegrations`` how often it was integrated again.
    """

    def __init__(self, pre: preintegration.Preintegrated, keys_i: KeyframeKeys, keys_j: KeyframeKeys,
                 gravity=imu.DEFAULT_GRAVITY, noise_model=None,
                 reintegration_threshold: float = preintegration.REINTEGRATION_THRESHOLD):
        if pre.cov is None and noise_model is None:
            raise InputError("ImuFactor: the preintegrated interval has no covariance; integrate it with "
                             "a reference state and noise, or pass a noise model")
        self._interval = _Interval(pre, np.asarray(gravity, dtype=float), float(reintegration_threshold))
        model = noise_model if noise_model is not None else covariance_model(pre.cov)
        keys = keys_i.all() + keys_j.all()
        self.factor = custom_factor(model, keys, KEYFRAME_VARIABLES + KEYFRAME_VARIABLES, self._interval.residual)

    @property
    def pre(self) -> preintegration.Preintegrated:
        return self._interval.pre

    @property
    def reintegrations(self) -> int:
        return self._interval.reintegrations

    def predict(self, state_i: imu.ImuState) -> imu.ImuState:
        """The state this factor predicts at keyframe ``j`` from ``state_i``."""
        return preintegration.predict(self._interval.pre, state_i, self._interval.gravity)
