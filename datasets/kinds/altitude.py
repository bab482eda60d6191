"""The ``altitude`` kind: the height of a sensor's origin in the world, ``e_z^T (r + C p_BS)``,
from a barometer's static pressure (``sensor_msgs/FluidPressure``).

Pressure becomes height through the International Standard Atmosphere's troposphere
(:func:`pressure_height`), RELATIVE TO THE SENSOR'S FIRST READING: the weather moves the absolute
pressure-height relation by tens of metres, a difference over minutes by far less. The first
reading's height is taken as known, the world frame's ``z = 0`` (the start of an odometry-frame
run, or the datum, by default the first GNSS fix): the reference is a fixed number, not a state,
and a barometer's bias against it is not estimated (the estimators have no state for it). The first
reading's own noise is thus an offset common to every height, which shows as residuals somewhat
above their band where the start's height is fixed (an odometry-frame run). Noise: the messages' ``variance`` [Pa^2]
carried through the slope of the height curve, or ``sigma`` [m].
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from datasets.kinds.base import Kind, near_prediction, noise, noisy
from datasets.types import Rows, check_array, check_covariances, check_extrinsic, check_times
from factors import sensor_models as sm
from factors.selfcheck import random_state

#: The International Standard Atmosphere at sea level and in its troposphere: pressure [Pa],
#: temperature [K], lapse rate [K/m]; the exponent ``R L / (g M)`` of its pressure-height relation
#: (R = 8.3144598 J/(mol K), g = 9.80665 m/s^2, M = 0.0289644 kg/mol).
ISA_PRESSURE = 101_325.0
ISA_TEMPERATURE = 288.15
ISA_LAPSE_RATE = 0.0065
ISA_EXPONENT = 8.3144598 * ISA_LAPSE_RATE / (9.80665 * 0.0289644)


def pressure_height(pressure) -> np.ndarray:
    """The standard atmosphere's height [m] at ``pressure`` [Pa]:
    ``T0 / L (1 - (p / p0)^(R L / (g M)))``."""
    return ISA_TEMPERATURE / ISA_LAPSE_RATE * (1.0 - (np.asarray(pressure, dtype=float) / ISA_PRESSURE) ** ISA_EXPONENT)


def height_pressure(height) -> np.ndarray:
    """The inverse of :func:`pressure_height`: the pressure [Pa] at ``height`` [m]."""
    height = np.asarray(height, dtype=float)
    return ISA_PRESSURE * (1.0 - height * ISA_LAPSE_RATE / ISA_TEMPERATURE) ** (1 / ISA_EXPONENT)


def height_per_pascal(pressure) -> np.ndarray:
    """``dh/dp`` [m/Pa] of :func:`pressure_height` (negative: height falls as pressure rises)."""
    p = np.asarray(pressure, dtype=float)
    return -ISA_TEMPERATURE / ISA_LAPSE_RATE * ISA_EXPONENT * (p / ISA_PRESSURE) ** ISA_EXPONENT / p


@dataclass(frozen=True, eq=False)
class AltitudeMeasurements(Rows):
    """Heights ``height`` (N,) [m] of the sensor's origin in the world frame, ``cov`` (N, 1, 1)
    [m^2]; ``T_BS`` its extrinsic (None: at the IMU)."""

    t: np.ndarray
    height: np.ndarray
    cov: np.ndarray
    T_BS: np.ndarray | None = None

    def __post_init__(self):
        t = check_times("AltitudeMeasurements.t", self.t)
        object.__setattr__(self, "t", t)
        object.__setattr__(self, "height", check_array("AltitudeMeasurements.height", self.height, (), len(t), t))
        object.__setattr__(self, "cov", check_covariances("AltitudeMeasurements.cov", self.cov, len(t), 1))
        object.__setattr__(self, "T_BS", check_extrinsic("AltitudeMeasurements.T_BS", self.T_BS))


def heights_from_pressures(pressure, variance=None) -> tuple[np.ndarray, np.ndarray | None]:
    """``(height relative to the first reading [m], its variance [m^2] or None)`` of pressures
    [Pa] with their variances [Pa^2]."""
    h = pressure_height(pressure)
    var = None if variance is None else np.asarray(variance) * height_per_pascal(pressure) ** 2
    return h - h[0], var


def _simulate(truth, k, imu, T_BS, sigma, rng):
    _, p = sm.extrinsic_parts(T_BS)
    z = truth.position[k, 2] + (truth.C[k] @ p)[:, 2]
    return AltitudeMeasurements(truth.t[k], noisy(z, sigma[0], rng), np.diag(sigma**2), T_BS)


def _read(sensor, clock):
    from datasets.sources import read_pressures

    stream = read_pressures(sensor.source, sensor.topic)
    t = clock.stamps(stream.t, stream.t_ns, sensor.time_offset)
    height, var = heights_from_pressures(stream.pressure, stream.variance)
    cov = None if var is None else var[:, None, None]
    return AltitudeMeasurements(t, height, noise(sensor, 1, cov, len(t)), sensor.T_BS), clock.datum


def _random_row(rng):
    """A random state and a height near its sensor's predicted one, with a random extrinsic."""
    x = random_state(rng)
    T, z, _ = near_prediction(x, rng)
    return x, sm.pack_altitude(z[None, 2], T)[0]


KIND = Kind("altitude", AltitudeMeasurements, 1, sm.ALTITUDE, lambda m: sm.pack_altitude(m.height, m.T_BS),
            _simulate, None, _read, fields=("height",), random_row=_random_row, default_sigma=(0.3,),
            sigma_units=("m",),
            noise_groups=(("height", (0,)),))
