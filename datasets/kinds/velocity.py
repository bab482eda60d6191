"""The ``velocity`` kind: a sensor frame's linear velocity in its own frame, ``R_BS^T (v + (w -
b_w) x p_BS)`` (wheel odometry's twist, a Doppler sensor); each measurement keeps the gyro reading
held at its time for the lever arm's rate."""
from __future__ import annotations

import numpy as np

from datasets.kinds.base import Kind, noise, noisy
from datasets.types import VelocityMeasurements
from factors import sensor_models as sm


def _simulate(truth, k, gyro, T_BS, sigma, rng):
    R, p = sm.extrinsic_parts(T_BS)
    u = truth.states.v[k] + np.cross(gyro - truth.states.b_w[k], p)
    return VelocityMeasurements(truth.t[k], noisy(u @ R, sigma, rng), gyro, np.diag(sigma**2), T_BS)


def _read(sensor, clock):
    from datasets.sources import read_twists

    twists = read_twists(sensor.source, sensor.topic)
    t = clock.stamps(twists.t, twists.t_ns, sensor.time_offset)
    return (VelocityMeasurements(t, twists.linear, clock.gyro_at(t), noise(sensor, 3, twists.cov, len(t)), sensor.T_BS),
            clock.datum)


KIND = Kind("velocity", VelocityMeasurements, 3, sm.VELOCITY, lambda m: sm.pack_velocity(m.velocity, m.gyro, m.T_BS),
            _simulate, None, _read)
