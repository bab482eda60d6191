"""The measurement kinds: each declared once, everything else iterates over :data:`KINDS`.

A :class:`Kind` names its data type (a dataclass of :mod:`datasets.types`), its measurement model
(:class:`factors.sensor_models.SensorModel`: residual, Jacobians, GTSAM factor, EKF update all run
the model's one compiled kernel) with the function that lays its measurements out as the kernel's
rows, and the function that draws its measurements from a ground truth (the simulator's stream).
A relative kind (``odometry``) connects two keyframes and has no one-state model: the smoothers
use it through :func:`factors.sensor_models.odometry_residual`, the EKF does not.

Adding a kind: write its data type and model (with their tests), then one line in :data:`KINDS`.

The compiled :func:`measure_into` dispatches to a model's kernel by its index in :data:`MODELS`;
the EKF's loop and the batch solver's blocks call it, so neither knows any kind by name.
"""
from __future__ import annotations

import warnings
from contextlib import contextmanager
from dataclasses import dataclass
from typing import Callable

import numpy as np
from numba import literal_unroll, njit
from numba.core.errors import NumbaExperimentalFeatureWarning

from datasets.types import (Dataset, OrientationMeasurements, PoseMeasurements, PositionMeasurements,
                            RelativePoseMeasurements, Sensor, Trajectory, VelocityMeasurements)
from factors import so3
from factors import sensor_models as sm


def _noisy_vectors(x: np.ndarray, sigma: np.ndarray, rng) -> np.ndarray:
    return x + sigma * rng.standard_normal(x.shape)


def _simulate_position(truth: Trajectory, k, gyro, T_BS, sigma, rng):
    R, p = sm.extrinsic_parts(T_BS)
    z = truth.position[k] + truth.C[k] @ p
    return PositionMeasurements(truth.t[k], _noisy_vectors(z, sigma[:3], rng), np.diag(sigma[:3] ** 2), T_BS)


def _simulate_orientation(truth: Trajectory, k, gyro, T_BS, sigma, rng):
    R, _ = sm.extrinsic_parts(T_BS)
    Z = so3.boxplus(truth.C[k] @ R, sigma[:3] * rng.standard_normal((len(k), 3)))
    return OrientationMeasurements(truth.t[k], Z, np.diag(sigma[:3] ** 2), T_BS)


def _simulate_pose(truth: Trajectory, k, gyro, T_BS, sigma, rng):
    R, p = sm.extrinsic_parts(T_BS)
    z = _noisy_vectors(truth.position[k] + truth.C[k] @ p, sigma[:3], rng)
    Z = so3.boxplus(truth.C[k] @ R, sigma[3:] * rng.standard_normal((len(k), 3)))
    return PoseMeasurements(truth.t[k], z, Z, np.diag(sigma**2), T_BS)


def _simulate_velocity(truth: Trajectory, k, gyro, T_BS, sigma, rng):
    R, p = sm.extrinsic_parts(T_BS)
    omega = gyro - truth.states.b_w[k]
    u = truth.states.v[k] + np.cross(omega, p)
    return VelocityMeasurements(truth.t[k], _noisy_vectors(u @ R, sigma[:3], rng), gyro, np.diag(sigma[:3] ** 2), T_BS)


def _simulate_odometry(truth: Trajectory, k, gyro, T_BS, sigma, rng):
    """Consecutive sensor poses as relative poses (``k[:-1]`` to ``k[1:]``), noise in ``S_i``."""
    R, p = sm.extrinsic_parts(T_BS)
    C_S = truth.C[k] @ R
    r_S = truth.position[k] + truth.C[k] @ p
    dr = np.einsum("nba,nb->na", C_S[:-1], r_S[1:] - r_S[:-1])
    dC = np.swapaxes(C_S[:-1], 1, 2) @ C_S[1:]
    n = len(k) - 1
    return RelativePoseMeasurements(truth.t[k[:-1]], truth.t[k[1:]], _noisy_vectors(dr, sigma[:3], rng),
                                    so3.boxplus(dC, sigma[3:] * rng.standard_normal((n, 3))), np.diag(sigma**2),
                                    T_BS)


def _anchor_position(m):
    return m.t, m.position, None  # the antenna's lever arm is left in: initial values only


def _anchor_orientation(m):
    R, _ = sm.extrinsic_parts(m.T_BS)
    return m.t, None, m.C @ R.T


def _anchor_pose(m):
    R, p = sm.extrinsic_parts(m.T_BS)
    C = m.C @ R.T
    return m.t, m.position - C @ p, C


@dataclass(frozen=True)
class Kind:
    """One measurement kind (module docstring). ``dim``: the residual's dimension (also the
    number of sigmas a rig's ``sigma`` may give per axis); ``pack(data) -> (N, width)`` rows for
    the model's kernel; ``simulate(truth, k, gyro, T_BS, sigma, rng)`` the measurements at truth
    samples ``k`` (``gyro`` the IMU's readings there) with noise ``sigma (dim,)``; ``anchor(data)
    -> (t, r or None, C or None)``: the IMU positions and attitudes the measurements imply, which
    reset the dead reckoning of the smoothers' initial trajectory (None: they imply neither)."""

    name: str
    data_type: type
    dim: int
    model: sm.SensorModel | None
    pack: Callable | None
    simulate: Callable
    anchor: Callable | None = None

    @property
    def relative(self) -> bool:
        return self.model is None


KINDS: dict[str, Kind] = {k.name: k for k in (
    Kind("pose", PoseMeasurements, 6, sm.POSE, lambda m: sm.pack_pose(m.position, m.C, m.T_BS), _simulate_pose,
         _anchor_pose),
    Kind("position", PositionMeasurements, 3, sm.POSITION, lambda m: sm.pack_position(m.position, m.T_BS),
         _simulate_position, _anchor_position),
    Kind("gnss", PositionMeasurements, 3, sm.POSITION, lambda m: sm.pack_position(m.position, m.T_BS),
         _simulate_position, _anchor_position),
    Kind("orientation", OrientationMeasurements, 3, sm.ORIENTATION, lambda m: sm.pack_orientation(m.C, m.T_BS),
         _simulate_orientation, _anchor_orientation),
    Kind("velocity", VelocityMeasurements, 3, sm.VELOCITY, lambda m: sm.pack_velocity(m.velocity, m.gyro, m.T_BS),
         _simulate_velocity),
    Kind("odometry", RelativePoseMeasurements, 6, None, None, _simulate_odometry),
)}

#: The kinds of aiding sensor, by the name a rig file's ``kind`` and the command line use.
KIND_NAMES = tuple(KINDS)

#: The distinct one-state models, in the order :func:`measure_into` indexes them.
MODELS: tuple[sm.SensorModel, ...] = tuple(dict.fromkeys(k.model for k in KINDS.values() if k.model is not None))
_KERNELS = tuple(m.kernel for m in MODELS)


def kind_sigmas(where: str, sigma, dim: int) -> np.ndarray:
    """A sensor's noise sigmas for a ``dim``-dimensional residual: one number (every axis), one per
    axis, or for 6-dim kinds ``(translation, rotation)``; a ValueError naming ``where`` else."""
    s = np.atleast_1d(np.asarray(sigma, dtype=float))
    if s.size == 1:
        s = np.repeat(s, dim)
    elif dim == 6 and s.size == 2:
        s = np.repeat(s, 3)
    if s.shape != (dim,) or not np.all(np.isfinite(s)) or np.any(s <= 0):
        expected = f"1 or {dim} numbers > 0" + (" (or translation and rotation)" if dim == 6 else "")
        raise ValueError(f"{where}: sigma: expected {expected}, got {np.asarray(sigma).tolist()!r}")
    return s


def model_index(kind: Kind) -> int:
    """The index of ``kind``'s model in :data:`MODELS` (the first argument of :func:`measure_into`)."""
    return MODELS.index(kind.model)


@njit(cache=True)
def measure_into(model, r, v, C, b_f, b_w, row, e, H) -> None:
    """Run the kernel of ``MODELS[model]`` (signature of :mod:`factors.sensor_models`)."""
    i = 0
    for kernel in literal_unroll(_KERNELS):
        if i == model:
            kernel(r, v, C, b_f, b_w, row, e, H)
        i += 1


@njit(cache=True)
def _measure_rows(model, r, v, C, b_f, b_w, rows, e, H) -> None:
    for n in range(rows.shape[0]):
        measure_into(model, r[n], v[n], C[n], b_f[n], b_w[n], rows[n], e[n], H[n])


@contextmanager
def quiet_dispatch():
    """Silences Numba's note, shown when :func:`measure_into` compiles, that dispatching over a
    tuple of kernels is an experimental feature."""
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", NumbaExperimentalFeatureWarning)
        yield


def measure_rows(kind: Kind, states, rows: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``(e (N, d), H (N, d, 15))`` of ``kind``'s measurement ``rows`` at ``states`` (an
    :class:`factors.imu.ImuState` with leading dimension N)."""
    n = len(rows)
    e, H = np.empty((n, kind.dim)), np.empty((n, kind.dim, 15))
    parts = [np.ascontiguousarray(a, dtype=float) for a in (states.r, states.v, states.C, states.b_f, states.b_w)]
    with quiet_dispatch():
        _measure_rows(model_index(kind), *parts, np.ascontiguousarray(rows, dtype=float), e, H)
    return e, H


def sensors_of(dataset: Dataset) -> list[Sensor]:
    """Every sensor of ``dataset``: the IMU-centred fields as sensors named after their field
    (``pose``, ``position``, ``orientation``, ``relative_pose`` of kind ``odometry``), then the
    named ``sensors``. Each sensor's kind is checked against :data:`KINDS` and its data type."""
    legacy = [Sensor(name, kind, getattr(dataset, name)) for name, kind in (
        ("pose", "pose"), ("position", "position"), ("orientation", "orientation"), ("relative_pose", "odometry"))
        if getattr(dataset, name) is not None]
    out = legacy + list(dataset.sensors)
    names = [s.name for s in out]
    for s in out:
        if s.kind not in KINDS:
            raise ValueError(f"sensor {s.name!r}: unknown kind {s.kind!r}; expected one of {', '.join(KINDS)}")
        expected = KINDS[s.kind].data_type
        for part in (s.data, s.heldout):
            if part is not None and not isinstance(part, expected):
                raise ValueError(f"sensor {s.name!r} of kind {s.kind!r}: expected {expected.__name__}, "
                                 f"got {type(part).__name__}")
        if names.count(s.name) > 1:
            raise ValueError(f"sensor name {s.name!r} is used twice")
    return out
