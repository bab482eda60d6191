"""The ``pose`` kind: a sensor frame's position and attitude in the world (a camera's visual
odometry in a fixed map, motion capture), ``(r + C p_BS, C R_BS)``."""
from __future__ import annotations

import numpy as np

from datasets.kinds.base import Kind, displaced, near_prediction, noise, noisy, poses
from datasets.types import PoseMeasurements
from factors import sensor_models as sm
from factors import so3
from factors.selfcheck import random_state


def _simulate(truth, k, imu, T_BS, sigma, rng):
    R, p = sm.extrinsic_parts(T_BS)
    z = noisy(truth.position[k] + truth.C[k] @ p, sigma[:3], rng)
    Z = so3.boxplus(truth.C[k] @ R, sigma[3:] * rng.standard_normal((len(k), 3)))
    return PoseMeasurements(truth.t[k], z, Z, np.diag(sigma**2), T_BS)


def _anchor(m):
    R, p = sm.extrinsic_parts(m.T_BS)
    C = m.C @ R.T
    return m.t, m.position - C @ p, C


def _read(sensor, clock):
    stream, t = poses(sensor, clock)
    return (PoseMeasurements(t, stream.position, stream.C, noise(sensor, 6, stream.cov, len(t)), sensor.T_BS),
            clock.datum)


def _random_row(rng):
    x = random_state(rng)
    T, z, Z = near_prediction(x, rng)
    return x, sm.pack_pose(z[None], Z[None], T)[0]



KIND = Kind("pose", PoseMeasurements, 6, sm.POSE, lambda m: sm.pack_pose(m.position, m.C, m.T_BS), _simulate,
            _anchor, _read, fields=("position", "C"), random_row=_random_row, default_sigma=(0.05, 0.01),
            corrupt=displaced, sigma_units=("m",) * 3 + ("rad",) * 3,
            noise_groups=(("position", (0, 1, 2)), ("attitude", (3, 4, 5))))
