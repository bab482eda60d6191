"""The ``orientation`` kind: a sensor frame's attitude in the world, ``C R_BS`` (an AHRS: the
``orientation`` of ``sensor_msgs/Imu``; the attitude part of poses)."""
from __future__ import annotations

import numpy as np

from datasets.kinds.base import Kind, displaced, near_prediction, noise
from datasets.types import OrientationMeasurements
from factors import sensor_models as sm
from factors import so3
from factors.selfcheck import random_state


def _simulate(truth, k, imu, T_BS, sigma, rng):
    R, _ = sm.extrinsic_parts(T_BS)
    Z = so3.boxplus(truth.C[k] @ R, sigma * rng.standard_normal((len(k), 3)))
    return OrientationMeasurements(truth.t[k], Z, np.diag(sigma**2), T_BS)


def _anchor(m):
    R, _ = sm.extrinsic_parts(m.T_BS)
    return m.t, None, m.C @ R.T


def attitudes(sensor, clock):
    """``(stream, t)``: a sensor's attitudes (:func:`datasets.sources.read_attitudes`: an Imu
    topic's orientation or any poses') and their times."""
    from datasets.sources import read_attitudes

    stream = read_attitudes(sensor.source, sensor.topic)
    return stream, clock.stamps(stream.t, stream.t_ns, sensor.time_offset)


def _read(sensor, clock):
    stream, t = attitudes(sensor, clock)
    return OrientationMeasurements(t, stream.C, noise(sensor, 3, stream.cov, len(t)), sensor.T_BS), clock.datum


def _random_row(rng):
    x = random_state(rng)
    T, _, Z = near_prediction(x, rng)
    return x, sm.pack_orientation(Z[None], T)[0]



KIND = Kind("orientation", OrientationMeasurements, 3, sm.ORIENTATION, lambda m: sm.pack_orientation(m.C, m.T_BS),
            _simulate, _anchor, _read, fields=("C",), random_row=_random_row, default_sigma=(0.01,),
            corrupt=displaced, sigma_units=("rad",) * 3,
            noise_groups=(("attitude", (0, 1, 2)),))
