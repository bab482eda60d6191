"""Held-out measurements of a sensor whose errors are correlated in time (its ``correlation_time``:
:mod:`smoother.model.correlated`), as the batch smoother predicts them.

Where the errors drift, a held-out measurement's error is not independent of the used ones': the
estimate knows the used measurements' errors (their residuals), and the model says how much of
them the held-out one shares. In whitened units (``u = W n``, the model's unit-variance process)
the held-out measurement at ``t`` between used measurements ``0`` and ``1`` has

    u_t | u_0, u_1  ~  N(w_0 u_0 + w_1 u_1, v I)

(:func:`smoother.model.correlated.given_neighbours`), and each ``u`` is the measurement's residual
with the state's error taken out, ``u_m = W_m (e_m - H_m dx_m)`` to first order (``e = h(x^) - z``).
So the normalised prediction error of ``z_t`` given what the estimate used is that of

    d = W_t e_t - w_0 u^_0 - w_1 u^_1,    Cov d = C Sigma C^T + W_t H_t Q_t H_t^T W_t^T + v I

with ``u^_m`` the used measurements' whitened residuals at the estimate, ``C`` the row of
coefficients ``W_t H_t [A K]`` on the two keyframes the held-out time is bridged between and
``-w_m G_m`` on the used measurements' (``G_m`` their whitened Jacobians, through the keyframe a
measurement is attached to), ``Sigma`` the joint covariance of those up to four keyframes -- any
two, not only neighbours (:class:`smoother.model.covariances.CovarianceBetween`) -- and ``Q_t`` the
bridge's own covariance (:func:`smoother.model.between.bridge_parts`), taken as independent of the
used measurements' errors. For a model that fits, ``d^T (Cov d)^-1 d`` is chi-square with the
measurement's dimension, as a white sensor's held-out error is against ``H P H^T + R``
(:mod:`smoother.diagnosis.heldout`). A factor ``k`` on the sensor's sigma scales ``d`` and the
state's part by ``1 / k`` and leaves ``v`` as it is, so the sigma factor at which they would be
1 per dof is found as for a white sensor with ``v I`` in the place of ``R``.

A smoother's calibration's uncertainty is left out, as it is for a white sensor.
"""
from __future__ import annotations

from dataclasses import replace

import numpy as np

from datasets.kinds import KINDS, calibrated_rows, measure_rows
from datasets.types import Dataset, Trajectory
from smoother.model.between import Following, bridge_parts
from smoother.model.blocks import Layout, evaluate_block, linearize, whitening
from smoother.model.correlated import CorrelatedBlock, given_neighbours
from smoother.model.covariances import CovarianceBetween, marginal_covariances
from smoother.model.predicted import Conditioned, HeldoutPrediction
from smoother.model.timeline import STATES_CHUNK


def predicts_correlated(dataset: Dataset, problem) -> bool:
    """Whether ``problem`` (the batch's, on ``dataset``) has a sensor whose errors are correlated in
    time and which holds measurements out: :func:`batch_predictions` then needs the elimination
    (a solve that keeps it saves making it again)."""
    return any(isinstance(b, CorrelatedBlock) and dataset.sensor(b.name).heldout is not None for b in problem.blocks)


def batch_predictions(dataset: Dataset, problem, result, following: Following | None) -> dict | None:
    """:func:`correlated_predictions` of the batch estimate ``result`` (a
    :class:`smoother.batch.solve.SmootherResult`) of ``problem`` on ``dataset`` (as it ran, its
    noise fitted where it was), with its keyframes' ``following``; None where it has no sensor with
    errors correlated in time and held-out measurements, or no covariances. The elimination it
    needs is made again where ``result`` did not keep it."""
    if following is None or not predicts_correlated(dataset, problem):
        return None
    root, sigma = result.square_root, result.joint
    if root is None:
        states, calibration = result.trajectory.states, result.calibration
        graph, _ = linearize(problem.blocks, states, calibration)
        _, sigma, root = marginal_covariances(graph, len(states), None, True,
                                              Layout.of(states, calibration, problem.blocks), square_root=True)
    return correlated_predictions(dataset, problem.blocks, result.trajectory, result.calibration, following,
                                  CovarianceBetween(root, sigma))


def correlated_predictions(dataset: Dataset, blocks: list, trajectory: Trajectory, calibration, following: Following,
                           between) -> dict[str, HeldoutPrediction]:
    """Per sensor of ``dataset`` (as the estimate ran on it: its noise fitted, where it was) with
    held-out measurements whose block among ``blocks`` (the batch problem's, at its estimate
    ``trajectory`` and calibration variables ``calibration``) is a
    :class:`~smoother.model.correlated.CorrelatedBlock`: its held-out measurements inside the span
    as the batch predicts them (:class:`HeldoutPrediction`: each one's residual and ``H P H^T``, as
    for a white sensor, and :class:`Conditioned`: the prediction given the used measurements'
    errors, module docstring). ``between(a, b)``: the estimate's covariance ``Sigma_ab`` of keyframes
    ``a`` and ``b`` (:class:`smoother.model.covariances.CovarianceBetween` of a batch estimate's
    elimination)."""
    out = {}
    for block in blocks:
        if not isinstance(block, CorrelatedBlock):
            continue
        sensor = dataset.sensor(block.name)
        if sensor.heldout is None or not len(sensor.heldout.t):
            continue
        out[sensor.name] = _predicted(dataset, block, sensor, trajectory, calibration, following, between)
    return out


def _predicted(dataset: Dataset, block: CorrelatedBlock, sensor, trajectory: Trajectory, calibration,
               following: Following, between) -> HeldoutPrediction:
    """:func:`correlated_predictions` of one ``sensor`` (its ``block``): its held-out measurements
    inside the trajectory's span (:func:`given_used`)."""
    c = None if calibration is None else calibration.value_of(sensor.name)
    times = sensor.heldout.t + (0.0 if c is None else c.time_offset)
    index = np.flatnonzero((times >= trajectory.t[0]) & (times <= min(trajectory.t[-1], dataset.imu.t[-1])))
    return given_used(dataset, block, sensor, trajectory, calibration, following, between, index)


def given_used(dataset: Dataset, block: CorrelatedBlock, sensor, trajectory: Trajectory, calibration,
               following: Following, between, index: np.ndarray, offset: int = 0,
               available: np.ndarray | None = None) -> HeldoutPrediction:
    """The held-out measurements ``index`` of ``sensor`` (its ``block``; their times, on the IMU's
    clock, within ``trajectory``'s span) as an estimate predicts them (:class:`HeldoutPrediction`,
    with :class:`Conditioned`, module docstring), a chunk at a time; each one's covariance from the
    few keyframes it reads (a loop over the measurements: their pairs of keyframes differ, and
    ``between`` finds and keeps each pair once). ``trajectory`` holds keyframes ``offset ..``
    (``between`` and ``following`` number them as the problem does); ``available`` (a mask over the
    used measurements; None: all) the used measurements the prediction is given: the nearest of
    them on either side of each held-out one."""
    kind, held = KINDS[sensor.kind], sensor.heldout
    c = None if calibration is None else calibration.value_of(sensor.name)
    times = held.t + (0.0 if c is None else c.time_offset)
    if c is not None:
        c = replace(c, time_offset=0.0)  # taken at the time it gives, as a white sensor's
    used_at = np.flatnonzero(np.ones(len(block.times), dtype=bool) if available is None else available)
    # the used measurements' whitened residuals and Jacobians at the estimate, at the noise in use
    measured = replace(block.measurements, whiten=block.whiten)
    rows = kind.pack(held)[index]
    n = len(trajectory.t)
    pieces = []
    for lo in range(0, len(index), STATES_CHUNK):
        part = slice(lo, lo + STATES_CHUNK)
        t = times[index[part]]
        k = np.clip(np.searchsorted(trajectory.t, t, side="right") - 1, 0, n - 2)
        states, AK, own = bridge_parts(trajectory, following, dataset.imu, k, t, dataset.noise, dataset.gravity)
        k = k + offset
        if c is None:
            e, H = measure_rows(kind, states, rows[part])
        else:
            e, H, _ = calibrated_rows(kind, states, rows[part], c, None, dataset.gravity)
        W = whitening(held.cov[index[part]])
        before, after, w0, w1, v = given_neighbours(held.t[index[part]], block.times[used_at], block.correlation_time)
        before, after = (np.where(side >= 0, used_at[side], -1) if len(used_at) else side for side in (before, after))
        needed = np.unique(np.concatenate([before[before >= 0], after[after >= 0]]))
        used = evaluate_block(measured, trajectory.states, True, rows=needed, keyframe_offset=offset,
                              calibration=calibration, reweight=False)
        place = {int(m): i for i, m in enumerate(needed)}
        WH = W @ H
        d = np.einsum("mab,mb->ma", W, e)
        for side, w in ((before, w0), (after, w1)):
            for m in np.flatnonzero(side >= 0):
                d[m] -= w[m] * used.e[place[int(side[m])]]
        plain, given = [], []
        for m in range(len(t)):
            coefficients = {int(k[m]): WH[m] @ AK[m, :, :15]}
            _add(coefficients, int(k[m]) + 1, WH[m] @ AK[m, :, 15:])
            bridge_only = _quadratic(coefficients, between)
            for side, w in ((before, w0), (after, w1)):
                if side[m] >= 0:
                    _add(coefficients, int(block.measurements.keyframes[side[m], 0]),
                         -w[m] * used.A[0][place[int(side[m])]])
            own_part = WH[m] @ own[m] @ WH[m].T
            plain.append(bridge_only + own_part)
            given.append(_quadratic(coefficients, between) + own_part)
        L = np.linalg.inv(W)  # back to the measurement's units for the plain prediction
        pieces.append((e, L @ np.stack(plain) @ np.swapaxes(L, 1, 2), d, np.stack(given),
                       v[:, None, None] * np.eye(kind.dim)))
    if not pieces:
        empty = np.zeros((0, kind.dim))
        square = np.zeros((0, kind.dim, kind.dim))
        return HeldoutPrediction(index, empty, square, Conditioned(empty, square, square))
    e, plain, d, given, noise = (np.concatenate(p) for p in zip(*pieces))
    return HeldoutPrediction(index, e, plain, Conditioned(d, given, noise))


def _add(coefficients: dict, key: int, value: np.ndarray) -> None:
    """Add ``value`` to the coefficient row of keyframe ``key``."""
    coefficients[key] = coefficients[key] + value if key in coefficients else value


def _quadratic(coefficients: dict, between) -> np.ndarray:
    """``sum_ab C_a Sigma_ab C_b^T`` over the keyframes of ``coefficients``."""
    keys = list(coefficients)
    total = 0.0
    for i, a in enumerate(keys):
        for b in keys[i:]:
            term = coefficients[a] @ between(a, b) @ coefficients[b].T
            total = total + (term if a == b else term + term.T)
    return total
