"""What every measurement kind declares (:class:`Kind`), and the helpers the kinds share.

A kind module (``pose.py``, ``velocity.py``, ...) holds everything of one kind but the residual's
mathematics (its :class:`factors.sensor_models.SensorModel`): how its measurements are laid out
as the model's kernel rows, how the simulator draws them from a ground truth, what they say about
the initial trajectory, and how a rig's sensor of that kind is read from its source. The registry
(:mod:`datasets.kinds`) lists the kinds.
"""
from __future__ import annotations

from dataclasses import dataclass, replace
from typing import Callable, NamedTuple

import numpy as np

from factors import sensor_models as sm
from factors import so3
from factors.errors import InputError


@dataclass(frozen=True)
class Kind:
    """One measurement kind: everything the rest of the project knows of it.

    ``name``: what a rig file's ``kind``, the simulator's ``<name>_rate`` and the command line call
    it; ``data_type``: its measurements' dataclass, whose fields are ``times`` (``("t",)``, or
    ``("t_from", "t_to")`` for a relative kind), then ``fields`` (the measured values), then
    ``cov`` and ``T_BS``, in that order (``OnlineSmoother.add`` takes the values in it);
    ``dim``: the residual's dimension; ``model``: the one-state model (None for a relative kind,
    which connects two keyframes through :func:`factors.sensor_models.odometry_kernel`);
    ``pack(data) -> (N, width)``: the model's kernel rows; ``simulate(truth, k, imu, T_BS, sigma
    (dim,), rng)``: measurements at truth samples ``k`` (``imu`` an :class:`ImuAt` there);
    ``anchor(data) -> (t, r or None, C or None)``: the IMU positions and attitudes the
    measurements imply (they reset the dead reckoning of the smoothers' initial trajectory), or
    None; ``read(sensor, clock) -> (data, datum)``: a rig's sensor
    (:class:`datasets.rig.SensorConfig`) read from its source (:class:`Clock`);
    ``random_row(rng) -> (state, row)``: a random state (for a relative kind the pair ``(x_i,
    x_j)``) and a measurement row near its prediction, with a random extrinsic (the Jacobian
    self-check and the every-kind tests evaluate the model there); ``default_sigma``: the
    simulator's noise when none is given (as :func:`kind_sigmas` reads it); ``corrupt(data,
    index, scale, rng)``: the data with the measurements ``index`` made outliers, moved by
    ``scale = (metres, radians)`` in random directions (None: the simulator cannot corrupt this
    kind); ``scaled_field``: the field of readings that a sensor's scale multiplies (what it reads
    per unit of the truth; the model's :attr:`~factors.sensor_models.SensorModel.scaled` rows),
    None if none; ``sigma_units``: the unit of each residual axis (``"m"``, ``"rad"``, ``"m/s"``),
    in which a sensor's ``sigma`` for it is given and checked (:data:`datasets.ranges.SIGMA_RANGES`);
    ``noise_groups``: the residual's axes in the groups whose noise is estimated apart
    (``((name, axes), ...)``, the axes a partition of ``range(dim)``, one unit each: a GNSS's
    horizontal and vertical, a velocity's forward, lateral and vertical); default one group of every
    axis; ``compose(data, spans) -> data``: for a relative kind, the measurements of each span
    ``spans[s] = (lo, hi)`` of consecutive ones (each beginning where the one before ended) as one
    from the first's start to the last's end, with its covariance (what a keyframe grid slower than
    the measurements keeps of them). The registry (:func:`datasets.kinds.registered`) checks these
    declarations."""

    name: str
    data_type: type
    dim: int
    model: sm.SensorModel | None
    pack: Callable | None
    simulate: Callable
    anchor: Callable | None
    read: Callable
    fields: tuple[str, ...]
    random_row: Callable
    default_sigma: tuple
    times: tuple[str, ...] = ("t",)
    corrupt: Callable | None = None
    scaled_field: str | None = None
    sigma_units: tuple[str, ...] = ()
    noise_groups: tuple = ()
    compose: Callable | None = None

    @property
    def axis_groups(self) -> tuple:
        """``((name, axes, unit), ...)``: :attr:`noise_groups` with their axes' unit, or one group
        ``("all", every axis, unit)`` when none is declared (the unit "" where the axes' differ)."""
        groups = self.noise_groups or (("all", tuple(range(self.dim))),)
        units = self.sigma_units or ("",) * self.dim
        return tuple((name, tuple(axes), units[axes[0]] if len({units[a] for a in axes}) == 1 else "")
                     for name, axes in groups)

    def unscaled(self, data, scale: float):
        """``data`` with its :attr:`scaled_field` divided by ``scale`` and its covariance by
        ``scale^2`` (the readings of a sensor that reads ``scale`` per unit of the truth, as the
        truth); only the scaled rows' block of the covariance changes."""
        if scale == 1.0:
            return data
        if self.scaled_field is None:
            raise InputError(f"a {self.name} sensor has no scale")
        k = np.shape(getattr(data, self.scaled_field))[-1]
        f = np.ones(self.dim)
        f[:k] = 1.0 / scale
        return replace(data, **{self.scaled_field: getattr(data, self.scaled_field) / scale},
                       cov=data.cov * f[:, None] * f[None, :])

    @property
    def relative(self) -> bool:
        return self.model is None

    @property
    def absolute(self) -> bool:
        """Whether the kind fixes a position or an attitude in the world (it has an anchor): what
        ends a stretch of dead reckoning. Velocities and relative poses do not."""
        return self.anchor is not None

    @property
    def width(self) -> int:
        """The width of its kernel rows."""
        return sm.ODOMETRY_WIDTH if self.relative else self.model.width


class ImuAt(NamedTuple):
    """What the IMU says at a sensor's measurement times: ``gyro`` the readings held there (N, 3),
    ``rate`` the true body rates (N, 3; in simulation), ``gyro_variance`` the variance of one
    reading's white noise per axis (``density^2 / dt``) [rad^2/s^2]."""

    gyro: np.ndarray
    rate: np.ndarray
    gyro_variance: float


@dataclass
class Clock:
    """What a kind's reader needs besides its sensor's configuration: ``stamps(t, t_ns, offset)``
    turns a source's stamps into the dataset's times (:mod:`datasets.recording`), ``gyro_at(t)``
    gives the IMU's gyro reading held at each time, ``gyro_variance`` the variance of one reading's
    white noise (``density^2 / dt``), ``datum`` the local ENU frame's origin (None until a GNSS
    reader sets it from its first fix)."""

    stamps: Callable
    gyro_at: Callable
    gyro_variance: float
    datum: object = None


def sigma_counts(dim: int) -> str:
    """How many numbers the ``sigma`` of a ``dim``-dimensional kind takes, as text."""
    return f"1 or {dim} numbers" + (" (or translation and rotation)" if dim == 6 else "")


def kind_sigmas(where: str, sigma, dim: int) -> np.ndarray:
    """A sensor's noise sigmas for a ``dim``-dimensional residual: one number (every axis), one per
    axis, or for 6-dim kinds ``(translation, rotation)``; a ValueError naming ``where`` else."""
    s = np.atleast_1d(np.asarray(sigma, dtype=float))
    if s.size == 1:
        s = np.repeat(s, dim)
    elif dim == 6 and s.size == 2:
        s = np.repeat(s, 3)
    if s.shape != (dim,) or not np.all(np.isfinite(s)) or np.any(s <= 0):
        raise InputError(f"{where}: sigma: expected {sigma_counts(dim)} > 0, got {np.asarray(sigma).tolist()!r}")
    return s


def noise(sensor, dim: int, cov, n: int) -> np.ndarray:
    """A rig sensor's covariances ``(n, dim, dim)``: its ``sigma`` if given, else the messages'
    ``cov`` when every message has one (the leading ``dim`` block), with its ``sigma_factor`` (if
    any) on their standard deviations, ``D C D`` with ``D`` the axes' factors; a ValueError asking
    for ``sigma`` else."""
    if sensor.sigma is not None:
        return np.broadcast_to(np.diag(kind_sigmas("sigma", sensor.sigma, dim) ** 2), (n, dim, dim)).copy()
    if cov is None or not np.all(np.isfinite(cov)):
        raise InputError(f"its messages carry no covariance{'' if cov is None else ' in every message'}; "
                         "give the sensor's sigma in the rig file")
    cov = np.asarray(cov)[:, :dim, :dim]
    if sensor.sigma_factor is None:
        return cov
    return with_sigma_factor(cov, kind_sigmas("sigma_factor", sensor.sigma_factor, dim))


def with_sigma_factor(cov: np.ndarray, factor: np.ndarray) -> np.ndarray:
    """Covariances ``cov (..., d, d)`` with their standard deviations scaled per axis by ``factor
    (d,)``: ``D C D``, ``D = diag(factor)`` (a rig's or an online sensor's ``sigma_factor``)."""
    return cov * (factor[:, None] * factor[None, :])


def noisy(x: np.ndarray, sigma: np.ndarray, rng) -> np.ndarray:
    """``x`` plus independent Gaussian noise of ``sigma`` per column."""
    return x + sigma * rng.standard_normal(x.shape)


def poses(sensor, clock: Clock):
    """``(stream, t)``: a sensor's poses (:func:`datasets.sources.read_poses`) and their times."""
    from datasets.sources import read_poses

    stream = read_poses(sensor.source, sensor.topic)
    return stream, clock.stamps(stream.t, stream.t_ns, sensor.time_offset)


def unit_vectors(rng, n: int) -> np.ndarray:
    """``n`` directions uniform on the sphere (N, 3)."""
    u = rng.standard_normal((n, 3))
    return u / np.linalg.norm(u, axis=1, keepdims=True)


def displaced(m, index, scale, rng):
    """``m`` (a data type with a ``position`` and/or an attitude ``C`` field) with the
    measurements ``index`` made outliers: positions moved by ``scale[0]`` metres, then attitudes
    turned by ``scale[1]`` rad (``C <- exp(angle axis) C``), in uniformly random directions."""
    changes = {}
    if hasattr(m, "position"):
        changes["position"] = m.position.copy()
        changes["position"][index] += scale[0] * unit_vectors(rng, len(index))
    if hasattr(m, "C"):
        changes["C"] = m.C.copy()
        changes["C"][index] = so3.boxplus(m.C[index], scale[1] * unit_vectors(rng, len(index)))
    return replace(m, **changes)


def near_prediction(state, rng):
    """``(T_BS, z, Z)``: a random extrinsic, and a sensor position ``z`` and attitude ``Z`` near
    what ``state`` predicts for it (0.1 m, 0.1 rad of noise: the attitude residual stays small
    even where the attitude is near pi)."""
    from factors.selfcheck import random_extrinsic

    T = random_extrinsic(rng)
    z = state.r + state.C @ T[:3, 3] + rng.normal(size=3) * 0.1
    Z = so3.boxplus(state.C @ T[:3, :3], rng.normal(size=3) * 0.1)
    return T, z, Z
