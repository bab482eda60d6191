"""Measurement errors correlated in time: a sensor whose errors drift (a GNSS receiver's multipath
and atmosphere, a fused solution's) as a first-order Gauss-Markov process -- its factors in the
batch smoother, and the process's conditional at a time between its measurements.

Model. A sensor with a correlation time ``tau`` (:attr:`datasets.types.Sensor.correlation_time`)
has errors ``n_m`` whose whitened values ``u_m = W_m n_m`` (``W_m`` the whitening of measurement
``m``'s own covariance ``R_m``, the stationary one) form an AR(1) sequence over its measurements in
time order:

    u_m = phi_m u_(m-1) + w_m,   phi_m = exp(-(t_m - t_(m-1)) / tau),   w_m ~ N(0, (1 - phi_m^2) I)

-- the Ornstein-Uhlenbeck process sampled at the measurement times, each ``u_m`` of unit covariance
(for one ``R``, ``n`` is the process of stationary covariance ``R``). Its density is that of ``u_0``
times the transitions', so the measurements' factors are the first one alone and the whitened
innovations of the others,

    f_0 = W_0 e_0,    f_m = (W_m e_m - phi_m W_(m-1) e_(m-1)) / sqrt(1 - phi_m^2)

with ``e_m = h(x) - z_m`` the measurement's residual: factors on two keyframes (those of the two
measurements), of unit covariance. ``tau -> 0`` gives the white factors back, ``tau -> inf`` a
sensor whose error is one constant (an offset). Each ``f_m`` reads the measurements' own residual
functions, their calibration variable included (a lever arm, a time offset: the same for both), so
their Jacobians are the differences of theirs. A robust kernel acts on ``f_m``.

Scaling ``R`` by a factor scales every ``f`` by its inverse square root, so a noise fit's factor on
the sensor's sigma (:mod:`smoother.batch.variance_components`) is the stationary sigma's; per axis
group where ``R`` is diagonal (its axes' whitened rows are the axes' own; with a full ``R`` the fit
refuses to split the groups).

Two measurements on one keyframe (a sensor faster than the keyframes) make a factor on that
keyframe alone; its first measurement's too. The :class:`~smoother.model.blocks.Block` holds two
keyframe slots per factor, so such a factor names a neighbouring keyframe in its first slot, with
a zero Jacobian there (a structural entry the IMU factor between them makes anyway).

The EKF carries the same process as augmented states (:mod:`smoother.ekf.filter`). The fixed-lag
smoother's own window makes the same factors as measurements reach it (:class:`Innovation`, from a
problem's keyframe factors or an online smoother's :mod:`smoother.online.drift`): the one before
a measurement must still be in the window, else the measurement is weighed alone, and counted
(:func:`weighed_alone_warning`). GTSAM's windows hold each measurement's own factor: white, and
the online smoother says so.
"""
from __future__ import annotations

from dataclasses import dataclass, replace
from typing import NamedTuple

import numpy as np

from datasets.types import Dataset
from factors.errors import InputError
from smoother.model.blocks import Block

#: The least share ``1 - phi^2`` of new error between two consecutive measurements: below it their
#: innovation's weight (its inverse square root) leaves double precision's reach beside the other factors.
MIN_INNOVATION_VARIANCE = 1e-12


@dataclass
class CorrelatedBlock(Block):
    """A :class:`~smoother.model.blocks.Block` of :func:`correlated_block`'s factors, with what made
    them: ``measurements``, a block of the measurements' own whitened residuals ``u_m = W_m e_m`` (one
    keyframe slot each, unit whitening: apply this block's ``whiten`` to it, as it is to the
    factors, to read them at a fitted noise); their ``times`` [s]; the ``correlation_time`` [s]."""

    measurements: Block | None = None
    times: np.ndarray | None = None
    correlation_time: float = 0.0


def transitions(times: np.ndarray, tau: float) -> np.ndarray:
    """``phi_m = exp(-(t_m - t_(m-1)) / tau)`` of each measurement after the first (``(M - 1,)``)."""
    return np.exp(-np.diff(times) / tau)


def innovation_weights(name: str, times: np.ndarray, tau: float) -> tuple[np.ndarray, np.ndarray]:
    """``(phi, s)`` of the factors of sensor ``name``'s measurements at ``times`` (strictly
    increasing, seconds) with errors of correlation time ``tau`` [s] (module docstring): each
    ``f_m = s_m (u_m - phi_m u_(m-1))``, ``s_m = 1 / sqrt(1 - phi_m^2)``; ``phi_0 = 0``, ``s_0 = 1``.
    An InputError, naming the sensor, for times that do not increase, a ``tau`` that is no positive
    number, or one so long that two consecutive errors would be one
    (:data:`MIN_INNOVATION_VARIANCE`)."""
    times = np.asarray(times, dtype=float)
    step = np.diff(times)
    if np.any(~(step > 0)):
        m = int(np.flatnonzero(~(step > 0))[0]) + 1
        raise InputError(f"sensor {name!r}: errors correlated in time need strictly increasing measurement "
                         f"times; measurement {m} at t = {times[m]:.9g} s follows one at {times[m - 1]:.9g} s")
    if not (np.isfinite(tau) and tau > 0):
        raise InputError(f"sensor {name!r}: correlation_time must be a positive number of seconds, got {tau!r}")
    phi, s = pair_weights(step, tau)
    if np.any(~np.isfinite(s)):
        m = int(np.flatnonzero(~np.isfinite(s))[0]) + 1
        raise InputError(f"sensor {name!r}: correlation_time {tau:g} s is too long for measurements "
                         f"{step[m - 1]:.3g} s apart (measurement {m}): their errors would be one, whose "
                         "differences the factors would weigh beyond double precision; give a shorter "
                         "correlation time")
    return np.concatenate([[0.0], phi]), np.concatenate([[1.0], s])


def pair_weights(step, tau: float) -> tuple:
    """``(phi, s)`` of measurements ``step > 0`` seconds after the one before them
    (:func:`innovation_weights`); ``s`` is inf where ``1 - phi^2`` is below
    :data:`MIN_INNOVATION_VARIANCE` (the two errors one)."""
    step = np.asarray(step, dtype=float)
    fresh = -np.expm1(-2.0 * step / tau)  # 1 - phi^2, without cancellation
    s = np.where(fresh < MIN_INNOVATION_VARIANCE, np.inf, 1.0 / np.sqrt(np.maximum(fresh, MIN_INNOVATION_VARIANCE)))
    return np.exp(-step / tau), s


class Innovation(NamedTuple):
    """What makes a drifting sensor's measurement the factor ``s u_m - c u_before`` (module
    docstring, ``c = s phi``) in a window that makes its own factors (the fixed-lag smoother's):
    the measurement before it, row ``row`` of ``spec`` (:class:`smoother.model.problem.MeasurementSpec`),
    the ``keyframe`` it reads and where it is attached to it (:class:`smoother.model.problem.AttachedAt`,
    or None at its time)."""

    spec: object
    row: int
    keyframe: int
    attached: object
    c: float
    s: float


def given_neighbours(t: np.ndarray, times: np.ndarray, tau: float) -> tuple:
    """The unit-variance process of the module docstring at times ``t``, given its values at the
    measurements' ``times`` (sorted): ``(before, after, w_before, w_after, variance)`` -- the
    nearest measurement at or before each time and after it (indices; -1 where there is none,
    its weight 0), and the conditional mean's weights on their values and the conditional
    variance. The process is Markov, so those two hold all the others say. With
    ``a = exp(-(t - t_0) / tau)``, ``b = exp(-(t_1 - t) / tau)`` and ``c = a b`` (the correlation
    of the two), the Gaussian conditional of ``u_t`` on ``(u_0, u_1)``:

        w_0 = a (1 - b^2) / (1 - c^2),   w_1 = b (1 - a^2) / (1 - c^2),
        variance = 1 - (a^2 + b^2 - 2 a b c) / (1 - c^2) = (1 - a^2) (1 - b^2) / (1 - c^2)

    (one side alone: ``w = a``, variance ``1 - a^2``; each ``1 - x^2`` as ``-expm1(-2 lag / tau)``,
    exact where the lags are far below ``tau``; no measurements at all: weights 0, variance 1). At a
    measurement's own time (:func:`one_error`) the process is given nothing either: there the
    model's error has no part of its own, so a second measurement would have to equal the first,
    and it is taken alone, as the factors weigh a second measurement at one stamp."""
    t = np.asarray(t, dtype=float)
    if not len(times):  # nothing to be given: the process itself
        none = np.full(t.shape, -1)
        return none, none.copy(), np.zeros(t.shape), np.zeros(t.shape), np.ones(t.shape)
    before = np.searchsorted(times, t, side="right") - 1
    after = before + 1
    has_before, has_after = before >= 0, after < len(times)
    # the lags (inf where there is no neighbour on that side), and 1 - a^2, 1 - b^2, 1 - c^2 without cancellation
    lag_a = np.where(has_before, t - times[np.maximum(before, 0)], np.inf)
    lag_b = np.where(has_after, times[np.minimum(after, len(times) - 1)] - t, np.inf)
    a, b = np.exp(-lag_a / tau), np.exp(-lag_b / tau)
    not_a, not_b, not_c = (-np.expm1(-2.0 * lag / tau) for lag in (lag_a, lag_b, lag_a + lag_b))
    alone = one_error(t, times, tau)
    not_c = np.where(alone, 1.0, not_c)
    w0, w1 = np.where(alone, 0.0, a * not_b / not_c), np.where(alone, 0.0, b * not_a / not_c)
    variance = np.where(alone, 1.0, not_a * not_b / not_c)
    return (np.where(has_before & ~alone, before, -1), np.where(has_after & ~alone, after, -1), w0, w1,
            variance)


def one_error(t: np.ndarray, times: np.ndarray, tau: float) -> np.ndarray:
    """Per time of ``t``, whether one of the measurements' ``times`` lies so close that the process
    of the module docstring is one there: less than :data:`MIN_INNOVATION_VARIANCE` of new error
    between them (a stamp of theirs, or within ``5e-13 tau`` of one: picoseconds where ``tau`` is seconds). A
    measurement there would have to equal theirs; the factors weigh such a second one alone, and a
    held-out prediction judges it alone (:func:`given_neighbours`)."""
    t = np.asarray(t, dtype=float)
    if not len(times):
        return np.zeros(t.shape, dtype=bool)
    i = np.clip(np.searchsorted(times, t), 1, max(len(times) - 1, 1))
    nearest = np.minimum(np.abs(t - times[i - 1]), np.abs(times[np.minimum(i, len(times) - 1)] - t))
    return ~np.isfinite(pair_weights(nearest, tau)[1])  # the factors' own test: an innovation beyond reach


def correlated_block(block: Block, times: np.ndarray, tau: float) -> CorrelatedBlock:
    """``block`` -- one sensor's measurement factors on one keyframe each, at ``times`` (strictly
    increasing, seconds) -- as factors of errors correlated with time constant ``tau`` [s] (module
    docstring): the same name, robust kernel and calibration variable; two keyframe slots per
    factor and unit whitening (the residual whitens)."""
    times = np.asarray(times, dtype=float)
    if block.keyframes.shape[1] != 1:
        raise InputError(f"sensor {block.name!r}: errors correlated in time need measurements of one state each")
    if len(times) != len(block):
        raise InputError(f"sensor {block.name!r}: {len(times)} times for {len(block)} measurements")
    M = len(block)
    own = block.keyframes[:, 0]
    phi, scale = innovation_weights(block.name, times, tau)
    # the keyframes each factor reads: the previous measurement's and its own; one keyframe alone
    # (the first factor, two measurements on one keyframe) names a neighbour with a zero Jacobian
    alone = np.ones(M, dtype=bool)
    alone[1:] = own[1:] == own[:-1]
    previous = np.concatenate([own[:1], own[:-1]])
    neighbour = np.where(own > 0, own - 1, own + 1)
    keyframes = np.stack([np.where(alone, neighbour, previous), own], axis=1)
    W = block.whiten

    def residual(slots, jacobians, rows, *calibration):
        index = np.arange(M)[rows]
        s = scale[index]
        current = _whitened(block, W, [slots[1]], jacobians, index, calibration)
        if jacobians:
            e = s[:, None] * current[0]
            # slot 0, slot 1, then the calibration variable's coordinates
            J = [np.zeros_like(current[1][0]), *(s[:, None, None] * j for j in current[1])]
        else:
            e = s[:, None] * current
        for slot in (0, 1):  # the previous measurement read from the first slot, or the second (one keyframe)
            here = np.flatnonzero((index > 0) & (alone[index] == (slot == 1)))
            if not len(here):
                continue
            k = (phi[index[here]] * s[here])[:, None]
            previous = _whitened(block, W, [slots[slot][here]], jacobians, index[here] - 1, calibration)
            if not jacobians:
                e[here] -= k * previous
                continue
            e[here] -= k * previous[0]
            J[slot][here] -= k[..., None] * previous[1][0]
            for c, j in enumerate(previous[1][1:], start=2):
                J[c][here] -= k[..., None] * j
        return (e, J) if jacobians else e

    unit = np.broadcast_to(np.eye(W.shape[-1]), W.shape).copy()

    def measured(slots, jacobians, rows, *calibration):
        return _whitened(block, W, slots, jacobians, np.arange(M)[rows], calibration)

    measurements = Block(block.name, block.keyframes, measured, unit, None, None, block.calibration)
    return CorrelatedBlock(block.name, keyframes, residual, unit.copy(), block.robust, block.before_linearize,
                           block.calibration, measurements, times, float(tau))


def _whitened(block: Block, W: np.ndarray, slots: list, jacobians: bool, rows: np.ndarray, calibration: tuple):
    """``W e`` (and ``W J`` for each Jacobian) of ``block``'s measurements ``rows`` at ``slots``."""
    out = block.residual(slots, jacobians, rows, *calibration)
    if not jacobians:
        return np.einsum("mab,mb->ma", W[rows], out)
    e, Js = out
    return np.einsum("mab,mb->ma", W[rows], e), [W[rows] @ J for J in Js]


def with_correlated_errors(problem, dataset: Dataset):
    """``problem`` (:class:`smoother.model.problem.Problem`) with the blocks of ``dataset``'s
    sensors that have a correlation time as :func:`correlated_block` s (the problem itself where
    none has): the batch smoother's model. (A problem's keyframe factors carry each measurement's
    own factor and, for a window that makes its own, its :class:`Innovation`.)"""
    taus = dataset.correlation_times
    if not taus:
        return problem
    times = {s.name: s.data.t for s in dataset.sensors if s.name in taus and s.data is not None}
    blocks = [correlated_block(b, times[b.name], taus[b.name]) if b.name in taus else b for b in problem.blocks]
    return replace(problem, blocks=blocks)


def weighed_alone_warning(estimator: str, count: int, lag_s: float) -> str | None:
    """The warning that ``estimator`` (a fixed-lag smoother of lag ``lag_s`` [s]) weighed ``count``
    measurements of drifting sensors as independent of the one before them; None for none."""
    if not count:
        return None
    return (f"{estimator}: {count} measurement(s) of sensors with a correlation_time were weighed as independent "
            f"of the one before, where it had left the window (a lag, {lag_s:g} s, shorter than their spacing), "
            "lay too many keyframes before it or shared its stamp, or where the window is GTSAM's; the covariances "
            "are too small there")
