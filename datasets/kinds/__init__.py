"""The measurement kinds: each declared once, everything else iterates over :data:`KINDS`.

A :class:`~datasets.kinds.base.Kind` names its data type (a dataclass of :mod:`datasets.types`),
its measurement model (:class:`factors.sensor_models.SensorModel`: residual, Jacobians, GTSAM
factor, EKF update all run the model's one compiled kernel), how its measurements become the
kernel's rows, how the simulator draws them, what they say about the initial trajectory and how a
rig's sensor of that kind is read. Each kind lives in a module of this package (``pose``,
``position`` with ``gnss``, ``orientation``, ``roll_pitch``, ``velocity``, ``odometry``,
``altitude``, ``magnetometer``). A relative kind
(``odometry``) connects two keyframes and has no one-state model: the smoothers use it through
:func:`factors.sensor_models.odometry_residual`, the EKF does not.

Adding a kind: a module with its :class:`~datasets.kinds.base.Kind` (and its model, if new, with
a kernel of the common signature), its tests, and one line in :data:`KINDS`.

The compiled :func:`measure_into` dispatches to a model's kernel by its index in :data:`MODELS`;
the EKF's loop and the batch solver's blocks call it, so neither knows any kind by name.
"""
from __future__ import annotations

import warnings
from contextlib import contextmanager

import numpy as np
from numba import literal_unroll, njit
from numba.core.errors import NumbaExperimentalFeatureWarning

from datasets.kinds import altitude, magnetometer, odometry, orientation, pose, position, roll_pitch, velocity
from datasets.kinds.base import Clock, Kind, kind_sigmas
from datasets.types import Dataset, Sensor
from factors import sensor_models as sm
from factors.errors import InputError

__all__ = ["KINDS", "KIND_NAMES", "MODELS", "Clock", "Kind", "kind_sigmas", "measure_into", "measure_rows",
           "model_index", "quiet_dispatch", "sensors_of"]


#: The registry: every kind, by name. Adding a kind is a module of its own and a line here.
KINDS: dict[str, Kind] = {k.name: k for k in (
    pose.KIND, position.POSITION, position.GNSS, orientation.KIND, roll_pitch.KIND, velocity.KIND, odometry.KIND,
    altitude.KIND, magnetometer.KIND,
)}

#: The kinds of aiding sensor, by the name a rig file's ``kind`` and the command line use.
KIND_NAMES = tuple(KINDS)

#: The distinct one-state models, in the order :func:`measure_into` indexes them.
MODELS: tuple[sm.SensorModel, ...] = tuple(dict.fromkeys(k.model for k in KINDS.values() if k.model is not None))
_KERNELS = tuple(m.kernel for m in MODELS)


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
            raise InputError(f"sensor {s.name!r}: unknown kind {s.kind!r}; expected one of {', '.join(KINDS)}")
        expected = KINDS[s.kind].data_type
        for part in (s.data, s.heldout):
            if part is not None and not isinstance(part, expected):
                raise InputError(f"sensor {s.name!r} of kind {s.kind!r}: expected {expected.__name__}, "
                                 f"got {type(part).__name__}")
        if names.count(s.name) > 1:
            raise InputError(f"sensor name {s.name!r} is used twice")
    return out
