"""The ``velocity`` kind: a sensor frame's linear velocity in its own frame, ``R_BS^T (v + (w -
b_w) x p_BS)`` (wheel odometry's twist, a Doppler sensor); each measurement keeps the gyro reading
held at its time for the lever arm's rate. That reading's white noise ``n_w`` reaches the residual
through the lever arm as ``R_BS^T p_BS^x n_w``: its covariance is added to the measurement's
(:func:`with_gyro_noise`)."""
from __future__ import annotations

import numpy as np

from datasets.kinds.base import Kind, noise, noisy
from datasets.types import VelocityMeasurements
from factors import sensor_models as sm
from factors.selfcheck import random_extrinsic, random_state


def with_gyro_noise(m: VelocityMeasurements, gyro_variance: float) -> VelocityMeasurements:
    """``m`` with the gyro reading's white noise (variance per axis, ``density^2 / dt``) carried
    through the lever arm added to its covariance: ``R^T p^x (s I) p^x^T R``."""
    R, p = sm.extrinsic_parts(m.T_BS)
    P = R.T @ np.array([[0.0, -p[2], p[1]], [p[2], 0.0, -p[0]], [-p[1], p[0], 0.0]])
    return VelocityMeasurements(m.t, m.velocity, m.gyro, m.cov + gyro_variance * (P @ P.T), m.T_BS)


def _simulate(truth, k, imu, T_BS, sigma, rng):
    """The sensor frame's true velocity (the true body rate through the lever arm) plus noise; the
    measurement keeps the IMU's reading, whose noise :func:`with_gyro_noise` accounts for."""
    R, p = sm.extrinsic_parts(T_BS)
    u = truth.states.v[k] + np.cross(imu.rate, p)
    m = VelocityMeasurements(truth.t[k], noisy(u @ R, sigma, rng), imu.gyro, np.diag(sigma**2), T_BS)
    return with_gyro_noise(m, imu.gyro_variance)


def _read(sensor, clock):
    from datasets.sources import read_twists

    twists = read_twists(sensor.source, sensor.topic)
    t = clock.stamps(twists.t, twists.t_ns, sensor.time_offset)
    m = VelocityMeasurements(t, twists.linear, clock.gyro_at(t), noise(sensor, 3, twists.cov, len(t)), sensor.T_BS)
    return with_gyro_noise(m, clock.gyro_variance), clock.datum


def _random_row(rng):
    return random_state(rng), sm.pack_velocity(rng.normal(size=(1, 3)), rng.normal(size=(1, 3)) * 3,
                                               random_extrinsic(rng))[0]


KIND = Kind("velocity", VelocityMeasurements, 3, sm.VELOCITY, lambda m: sm.pack_velocity(m.velocity, m.gyro, m.T_BS),
            _simulate, None, _read, fields=("velocity", "gyro"), random_row=_random_row, default_sigma=(0.05,),
            scaled_field="velocity", sigma_units=("m/s",) * 3,
            noise_groups=(("forward", (0,)), ("lateral", (1,)), ("vertical", (2,))))
