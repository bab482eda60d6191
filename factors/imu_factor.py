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
from factors.keys import KeyframeKeys
from factors.measurements import covariance_model

KINDS = [ROT, VEC, VEC, BIAS]


def _reorder(J: np.ndarray) -> list[np.ndarray]:
    """Error-state columns (r, v, phi, b_f, b_w) -> the factor's variables (Rot3, Point3, V, bias)."""
    return [J[:, imu.PHI], J[:, imu.R], J[:, imu.V], J[:, imu.BF.start:imu.BW.stop]]  # (b_f, b_w) adjacent


class ImuFactor:
    """Builds and owns the ``gtsam.CustomFactor`` of one preintegrated interval.

    ``pre`` is one interval of :class:`factors.preintegration.Preintegrated` (no leading
    dimension) with its covariance. ``factor`` is the GTSAM factor to add to a graph.
    """

    def __init__(self, pre: preintegration.Preintegrated, keys_i: KeyframeKeys, keys_j: KeyframeKeys,
                 gravity=imu.DEFAULT_GRAVITY, noise_model=None,
                 reintegration_threshold: float = preintegration.REINTEGRATION_THRESHOLD):
        if pre.cov is None and noise_model is None:
            raise ValueError("ImuFactor: the preintegrated interval has no covariance; integrate it with "
                             "a reference state and noise, or pass a noise model")
        self.pre = pre
        self.gravity = np.asarray(gravity, dtype=float)
        self.threshold = float(reintegration_threshold)
        self.reintegrations = 0
        model = noise_model if noise_model is not None else covariance_model(pre.cov)
        keys = keys_i.all() + keys_j.all()
        self.factor = custom_factor(model, keys, KINDS + KINDS, self._residual)

    def _maybe_reintegrate(self, b_w: np.ndarray) -> None:
        bar = self.pre.b_w_bar
        if max(abs(b_w[0] - bar[0]), abs(b_w[1] - bar[1]), abs(b_w[2] - bar[2])) > self.threshold:
            self.pre = self.pre.relinearized(b_w)
            self.reintegrations += 1

    def _residual(self, Ci, ri, vi, bi, Cj, rj, vj, bj, jacobians: bool):
        self._maybe_reintegrate(bi[3:])
        out = preintegration.residual_one(self.pre, Ci, ri, vi, bi, Cj, rj, vj, bj, self.gravity, jacobians)
        if not jacobians:
            return out
        e, (Ji, Jj) = out
        return e, _reorder(Ji) + _reorder(Jj)

    def predict(self, state_i: imu.ImuState) -> imu.ImuState:
        """The state this factor predicts at keyframe ``j`` from ``state_i``."""
        return preintegration.predict(self.pre, state_i, self.gravity)
