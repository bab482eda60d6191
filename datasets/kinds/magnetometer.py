"""The ``magnetometer`` kind: the direction of the Earth's magnetic field in a sensor's frame
(``sensor_msgs/MagneticField``), against the world field's direction ``m`` given by the rig as
its declination and inclination (:func:`field_direction`); the model is
:func:`factors.sensor_models.magnetometer_kernel`. Only the direction is used: the field's
strength varies with the place and with the vehicle's own iron, its direction much less (a
magnetometer must be calibrated for hard and soft iron; this kind takes its readings as given).

Noise: the messages' 3x3 covariance of the field [T^2] in the sensor frame, carried to the
direction's two components across the measured one (``B^T cov B / |f|^2``), or ``sigma``
[rad], 1 or 2 numbers: the direction's angular noise.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from datasets.kinds.base import Kind, noise
from datasets.types import Rows, check_array, check_covariances, check_extrinsic, check_times
from factors import sensor_models as sm
from factors import so3
from factors.errors import InputError
from factors.selfcheck import random_extrinsic, random_state


def field_direction(declination_deg: float, inclination_deg: float) -> np.ndarray:
    """The unit direction of the magnetic field in the east-north-up world frame: its horizontal
    part points to magnetic north, ``declination`` degrees east of true north, and it dips
    ``inclination`` degrees below the horizontal (positive in the northern hemisphere)."""
    d, i = np.deg2rad(declination_deg), np.deg2rad(inclination_deg)
    return np.array([np.cos(i) * np.sin(d), np.cos(i) * np.cos(d), -np.sin(i)])


@dataclass(frozen=True, eq=False)
class MagneticFieldMeasurements(Rows):
    """Measured field directions ``direction`` (N, 3) in the sensor frame (made unit), against the
    world field's direction ``world`` (N, 3) (made unit); ``cov`` (N, 2, 2) [rad^2] over the two
    components across ``direction`` (:func:`factors.sensor_models.normal_basis`)."""

    t: np.ndarray
    direction: np.ndarray
    world: np.ndarray
    cov: np.ndarray
    T_BS: np.ndarray | None = None

    def __post_init__(self):
        t = check_times("MagneticFieldMeasurements.t", self.t)
        n = len(t)
        object.__setattr__(self, "t", t)
        for name in ("direction", "world"):
            v = check_array(f"MagneticFieldMeasurements.{name}", np.broadcast_to(getattr(self, name), (n, 3)),
                            (3,), n, t)
            norm = np.linalg.norm(v, axis=1, keepdims=True)
            if np.any(norm == 0):
                raise InputError(f"MagneticFieldMeasurements.{name}: a zero vector; expected directions")
            object.__setattr__(self, name, v / norm)
        object.__setattr__(self, "cov", check_covariances("MagneticFieldMeasurements.cov", self.cov, n, 2))
        object.__setattr__(self, "T_BS", check_extrinsic("MagneticFieldMeasurements.T_BS", self.T_BS))


def direction_covariance(field: np.ndarray, cov: np.ndarray) -> np.ndarray:
    """``(N, 2, 2)``: the covariance of the residual's two components of measured fields
    ``field`` (N, 3) whose covariance is ``cov`` (N, 3, 3), ``B^T cov B / |f|^2``."""
    B = sm.normal_basis(field / np.linalg.norm(field, axis=1, keepdims=True))
    return np.einsum("nia,nab,njb->nij", B, cov, B) / np.sum(field**2, axis=1)[:, None, None]


def _simulate(truth, k, imu, T_BS, sigma, rng, world=None):
    """Directions of ``world`` (default: declination 2, inclination 60 degrees) with angular noise
    ``sigma`` across them."""
    m = field_direction(2.0, 60.0) if world is None else np.asarray(world, dtype=float)
    R, _ = sm.extrinsic_parts(T_BS)
    u = np.einsum("ab,nca,c->nb", R, truth.C[k], m)  # R^T C^T m
    B = sm.normal_basis(u)
    z = u + np.einsum("nib,ni->nb", B, sigma * rng.standard_normal((len(k), 2)))
    return MagneticFieldMeasurements(truth.t[k], z, m, np.diag(sigma**2), T_BS)


def _read(sensor, clock):
    from datasets.sources import read_magnetic_fields

    stream = read_magnetic_fields(sensor.source, sensor.topic)
    t = clock.stamps(stream.t, stream.t_ns, sensor.time_offset)
    cov = None if stream.cov is None else direction_covariance(stream.field, stream.cov)
    world = field_direction(sensor.declination, sensor.inclination)
    return (MagneticFieldMeasurements(t, stream.field, world, noise(sensor, 2, cov, len(t)), sensor.T_BS),
            clock.datum)


def heading(m: MagneticFieldMeasurements, level: np.ndarray, k: int = 0) -> float:
    """The rotation about the world vertical [rad] that turns ``level`` (an attitude with the right
    roll and pitch) so that measurement ``k``'s direction points along the world field's in the
    horizontal plane."""
    R, _ = sm.extrinsic_parts(m.T_BS)
    measured = level @ R @ m.direction[k]
    return float(np.arctan2(m.world[k, 1], m.world[k, 0]) - np.arctan2(measured[1], measured[0]))


def _random_row(rng):
    """A random state, world field and extrinsic, and a measured direction ~0.1 rad off the
    predicted one."""
    x, T, world = random_state(rng), random_extrinsic(rng), rng.normal(size=3)
    measured = so3.exp(rng.normal(size=3) * 0.1) @ T[:3, :3].T @ x.C.T @ world
    return x, sm.pack_magnetometer(measured[None], world, T)[0]


KIND = Kind("magnetometer", MagneticFieldMeasurements, 2, sm.MAGNETOMETER,
            lambda m: sm.pack_magnetometer(m.direction, m.world, m.T_BS), _simulate, None, _read,
            fields=("direction", "world"), random_row=_random_row, default_sigma=(0.02,),
            sigma_units=("rad", "rad"),
            noise_groups=(("direction", (0, 1)),))
