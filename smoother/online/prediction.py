"""The state of an online smoother (:class:`smoother.online.smoother.OnlineSmoother`) at IMU rate: the
EKF's per-sample prediction (:func:`factors.imu.predict_into`, the filter's own step) from the
newest keyframe's estimate through the samples since, no re-solve; with covariances its 15x15
covariance too, from the keyframe's marginal. Each call steps on from where the last stopped.
"""
from __future__ import annotations

import numpy as np

from factors import imu
from factors.compiled import recursion
from factors.errors import InputError
from smoother.online.handover import OnlineEstimate


@recursion
def _predict_to(t, acc, gyro, held, n, t_from, r, v, C, b_f, b_w, P, q, g) -> None:
    """The state ``(r, v, C, b_f, b_w)`` and covariance ``P`` at ``t_from`` (where sample ``held``
    is held) stepped in place to ``t[n - 1]`` through the samples ``held .. n - 2``
    (:func:`factors.imu.predict_into`, the EKF's step), in one compiled call per estimate."""
    dt = np.empty(n - 1 - held)
    for k in range(dt.size):
        dt[k] = t[held + k + 1] - (t_from if k == 0 else t[held + k])
    imu.predict_into(r, v, C, b_f, b_w, P, acc[held:n - 1], gyro[held:n - 1], dt, q, g)


class ImuRatePrediction:
    """The prediction from the newest keyframe (module docstring) with the IMU ``noise`` and
    ``gravity``; ``covariances``: whether :meth:`at` gives the covariance."""

    def __init__(self, noise: imu.ImuNoise, gravity: np.ndarray, covariances: bool):
        self.gravity, self.covariances = gravity, covariances
        self._q = noise.densities()
        self._x = None  # (r, v, C, b_f, b_w) flat, 21 numbers
        self._parts = None  # views of it, which the kernel steps in place
        self._cov = None
        self._t = None  # the time reached
        self._held = 0  # the sample held there, as an index into the whole stream

    def restart(self, t: float, state: imu.ImuState, cov: np.ndarray | None, held: int) -> None:
        """Predict from the keyframe at ``t``: its ``state`` and covariance ``cov`` (None: zeros,
        not reported) with the stream's sample ``held`` (an index into the whole stream) held."""
        self._cov = np.array(cov) if cov is not None else np.zeros((imu.STATE_DIM, imu.STATE_DIM))
        self._x = np.concatenate([state.r, state.v, np.ravel(state.C), state.b_f, state.b_w]).astype(float)
        x = imu.ImuState.of_flat(self._x)
        self._parts = (x.r, x.v, x.C, x.b_f, x.b_w)
        self._t, self._held = t, held

    @property
    def started(self) -> bool:
        """Whether a keyframe's estimate has been given to predict from (:meth:`restart`)."""
        return self._x is not None

    def at(self, buffer) -> OnlineEstimate:
        """The state at the newest sample of ``buffer`` (a :class:`smoother.online.imu_buffer.ImuBuffer`);
        an InputError before the first keyframe."""
        if self._x is None:
            raise InputError("estimate: no keyframe yet (feed IMU samples first)")
        n, held = buffer.n, self._held - buffer.released
        if n - 1 > held:
            _predict_to(buffer.t, buffer.acc, buffer.gyro, held, n, self._t, *self._parts, self._cov, self._q,
                        self.gravity)
            self._t, self._held = float(buffer.t[n - 1]), buffer.released + n - 1
        return OnlineEstimate(self._t, imu.ImuState.of_flat(self._x.copy()),
                              self._cov.copy() if self.covariances else None)
