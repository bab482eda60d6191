"""The ``roll_pitch`` kind: the roll and pitch of an attitude sensor whose heading is not to be
trusted (an AHRS without a magnetometer, whose heading is the integral of its gyro): a rig's
``orientation`` sensor with ``roll_pitch_only = true``. The measurement is the sensor's whole
attitude ``Z``; the model (:func:`factors.sensor_models.roll_pitch_kernel`) compares the vertical
only, so the measured heading never enters the residual, and the measurements fix neither the
initial heading nor a dead-reckoning stretch's (no anchor).

Noise: ``Z = exp(n) C R_BS`` with ``n`` about the world axes of the sensor's own attitude output
(for an AHRS whose heading drifts, its own drifting world); the residual's covariance is the
upper-left 2x2 block (about x, y) of ``n``'s: from the messages' 3x3 attitude covariance, or
``sigma`` (1 or 2 numbers, roll and pitch about the world's x and y axes) [rad].
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from datasets.kinds.base import Kind, near_prediction, noise
from datasets.kinds.orientation import attitudes
from datasets.types import Rows, check_covariances, check_extrinsic, check_rotations, check_times
from factors import sensor_models as sm
from factors import so3
from factors.selfcheck import random_state


@dataclass(frozen=True, eq=False)
class RollPitchMeasurements(Rows):
    """Attitudes ``C`` (N, 3, 3) of the sensor frame of which only roll and pitch are used, with
    ``cov`` (N, 2, 2) [rad^2] the covariance of the world-frame attitude noise about x and y."""

    t: np.ndarray
    C: np.ndarray
    cov: np.ndarray
    T_BS: np.ndarray | None = None

    def __post_init__(self):
        t = check_times("RollPitchMeasurements.t", self.t)
        object.__setattr__(self, "t", t)
        object.__setattr__(self, "C", check_rotations("RollPitchMeasurements.C", self.C, len(t)))
        object.__setattr__(self, "cov", check_covariances("RollPitchMeasurements.cov", self.cov, len(t), 2))
        object.__setattr__(self, "T_BS", check_extrinsic("RollPitchMeasurements.T_BS", self.T_BS))


def _yaw(angle) -> np.ndarray:
    """Rotations about the world vertical by ``angle`` (N,)."""
    return so3.exp(np.asarray(angle)[:, None] * np.array([0.0, 0.0, 1.0]))


def _simulate(truth, k, imu, T_BS, sigma, rng):
    """Attitudes whose heading is off by anything (uniform: the model must not see it), with
    noise ``sigma`` about the x and y axes of that world (the sensor's own)."""
    R, _ = sm.extrinsic_parts(T_BS)
    n = np.zeros((len(k), 3))
    n[:, :2] = sigma * rng.standard_normal((len(k), 2))
    Z = so3.boxplus(_yaw(rng.uniform(-np.pi, np.pi, len(k))) @ truth.C[k] @ R, n)
    return RollPitchMeasurements(truth.t[k], Z, np.diag(sigma**2), T_BS)


def _random_row(rng):
    """A random state and a row near its prediction (tilted by ~0.1 rad, heading anything: the
    model must not see it), with a random extrinsic."""
    x = random_state(rng)
    T, _, Z = near_prediction(x, rng)
    return x, sm.pack_orientation((_yaw([rng.uniform(-np.pi, np.pi)]) @ Z[None]), T)[0]


def _read(sensor, clock):
    stream, t = attitudes(sensor, clock)
    cov = None if stream.cov is None else stream.cov[:, :2, :2]
    return RollPitchMeasurements(t, stream.C, noise(sensor, 2, cov, len(t)), sensor.T_BS), clock.datum


KIND = Kind("roll_pitch", RollPitchMeasurements, 2, sm.ROLL_PITCH, lambda m: sm.pack_orientation(m.C, m.T_BS),
            _simulate, None, _read, fields=("C",), random_row=_random_row, default_sigma=(0.01,),
            sigma_units=("rad", "rad"),
            noise_groups=(("tilt", (0, 1)),))
