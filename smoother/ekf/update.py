"""What both EKFs do at a measurement time besides predicting: the order of the updates, the
Kalman update with its chi-square gate, and the test that the filter has diverged. The plain
filter (:mod:`smoother.ekf.filter`) and the filter with calibrations as augmented states
(:mod:`smoother.ekf.calibrated`) run them inside one compiled loop over the knots, so that the
two filters agree wherever no calibration is estimated.

Order. At each knot (a measurement time) the updates are applied sensor by sensor, in the order
of the sensors given (:func:`datasets.kinds.sensors_of`), and a sensor's measurements at that
time in their own order (:func:`update_order`); the held-out measurements taken then are
predicted after all of them.

Update. With the residual ``e`` (measurement model minus measurement), its Jacobian ``H`` in the
error-state columns and the noise ``R``: ``S = H P H^T + R = L L^T``, the normalised innovation
squared ``d2 = |L^-1 e|^2``; when ``d2`` passes the gate of its dimension (:func:`gate_thresholds`),
``K = P H^T S^-1``, the correction ``dx = -K e`` (the caller applies it with the state's boxplus,
``exp(dphi) C`` for the attitude) and Joseph's form ``P <- (I - K H) P (I - K H)^T + K R K^T``,
kept exactly symmetric (:func:`kalman_update`). ``P`` may be wider than the IMU's 15 error-state
components (augmented states after them). A held-out measurement (a rig's ``every = K``) is
predicted and not used: its ``d2`` and the state's share ``H P H^T`` of ``S``, ``P`` untouched
(:func:`predict_only`).

Divergence. A filter whose state or covariance is not finite, whose speed exceeds
:data:`DIVERGED_SPEED` or whose ``sqrt(trace P)`` over the IMU's error state exceeds
:data:`DIVERGED_SPREAD` has diverged (:func:`diverged`): it skips the updates after that and stops
at the end of the knot.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numba import njit

from factors import imu
from factors.errors import InputError, SolverError
from factors.small_linalg import cholesky_into, matmul_into, solve_lower
from smoother.stats import chi2_quantile

#: Beyond these the filter is declared diverged: |velocity| [m/s], sqrt(trace P) (mixed units).
DIVERGED_SPEED = 1e4
DIVERGED_SPREAD = 1e6


def gate_thresholds(probability: float | None) -> np.ndarray:
    """Chi-square gate per measurement dimension (index m), infinite without a gate."""
    gates = np.full(7, np.inf)
    if probability is not None:
        for m in range(1, 7):
            gates[m] = chi2_quantile(probability, m)
    return gates


@dataclass
class UpdateOrder:
    """The measurement updates of a run in the order a filter applies them (module docstring):
    update ``u`` is measurement ``measurement[u]`` of sensor ``sensor[u]``, at knot ``knot[u]``;
    those at knot ``k`` are ``start[k]:start[k + 1]``."""

    start: np.ndarray
    knot: np.ndarray
    sensor: np.ndarray
    measurement: np.ndarray


def update_order(times: list[np.ndarray], knots: np.ndarray, names: list[str] | None = None) -> UpdateOrder:
    """The :class:`UpdateOrder` of sensors measuring at ``times`` (one array per sensor, in the
    order the sensors are given) among ``knots`` (sorted; every measurement time one of them, else
    an InputError naming the sensor from ``names``)."""
    knot_of, sensor_of, index_of = [], [], []
    for s, t in enumerate(times):
        knot = np.searchsorted(knots, t)
        if len(t) and np.any(knots[np.minimum(knot, len(knots) - 1)] != t):
            name = names[s] if names is not None else s
            raise InputError(f"sensor {name!r}: measurement times that are not knots")
        knot_of.append(knot)
        sensor_of.append(np.full(len(t), s))
        index_of.append(np.arange(len(t)))
    knot = np.concatenate(knot_of) if knot_of else np.zeros(0, dtype=np.int64)
    sensor = np.concatenate(sensor_of) if sensor_of else np.zeros(0, dtype=np.int64)
    index = np.concatenate(index_of) if index_of else np.zeros(0, dtype=np.int64)
    order = np.lexsort((sensor, knot))  # by knot, then sensor by sensor; stable: a sensor's own order
    start = np.searchsorted(knot[order], np.arange(len(knots) + 1)).astype(np.int64)
    return UpdateOrder(start, knot[order].astype(np.int64), sensor[order].astype(np.int64),
                       index[order].astype(np.int64))


@njit(cache=True)
def kalman_update(P, e, H, R, gates, stats, dx) -> float:
    """One Kalman update (module docstring) in place on ``P``: ``dx <- -K e`` when the gate
    accepts it (``P`` and ``dx`` untouched otherwise). ``stats[0]`` counts rejections,
    ``stats[1]`` accumulates ``log N(e; 0, S)``; a non-positive-definite ``S`` raises a
    SolverError. Returns ``d2``, the normalised innovation squared."""
    m, n = e.shape[0], P.shape[0]
    PHt, S, L = np.empty((n, m)), np.empty((m, m)), np.empty((m, m))
    _state_share(P, H, PHt, S)
    S += R
    if not cholesky_into(0.5 * (S + S.T), L):
        raise SolverError("EKF update: the innovation covariance H P H^T + R is not positive definite")
    d2 = _normalised_squared(L, e)
    logdet = 0.0
    for i in range(m):
        logdet += 2.0 * math.log(L[i, i])
    if d2 > gates[m]:
        stats[0] += 1
        return d2
    stats[1] -= 0.5 * (d2 + logdet + m * math.log(2.0 * math.pi))
    # K^T = S^-1 (P H^T)^T = L^-T L^-1 PHt^T, row by row of K
    K = np.empty((n, m))
    z, col = np.empty(m), np.empty(m)
    for row in range(n):
        z[:] = PHt[row]
        solve_lower(L, z.reshape((m, 1)))
        for i in range(m - 1, -1, -1):  # back substitution with L^T
            acc = z[i]
            for k in range(i + 1, m):
                acc -= L[k, i] * col[k]
            col[i] = acc / L[i, i]
        K[row] = col
    for row in range(n):
        dx[row] = 0.0
        for i in range(m):
            dx[row] -= K[row, i] * e[i]
    IKH, T, KR = np.empty((n, n)), np.empty((n, n)), np.empty((n, m))
    matmul_into(K, H, IKH)
    IKH[:, :] = np.eye(n) - IKH
    matmul_into(IKH, P, T)
    matmul_into(K, R, KR)
    for i in range(n):
        for j in range(i, n):
            acc = 0.0
            for k in range(n):
                acc += T[i, k] * IKH[j, k]
            for k in range(m):
                acc += KR[i, k] * K[j, k]
            P[i, j] = P[j, i] = acc
    return d2


@njit(cache=True)
def predict_only(P, e, H, R, state_part) -> float:
    """A measurement predicted and not used (a held-out one): the state's share of its innovation
    covariance, ``H P H^T``, into ``state_part`` (m x m) and ``d2 = e^T (H P H^T + R)^-1 e``
    returned (NaN where that covariance is not positive definite); ``P`` untouched."""
    m, n = e.shape[0], P.shape[0]
    PHt, S, L = np.empty((n, m)), np.empty((m, m)), np.empty((m, m))
    _state_share(P, H, PHt, S)
    state_part[:, :] = S
    S += R
    if not cholesky_into(0.5 * (S + S.T), L):
        return np.nan
    return _normalised_squared(L, e)


@njit(cache=True)
def _state_share(P, H, PHt, out) -> None:
    """``PHt <- P H^T`` and ``out <- H P H^T``."""
    matmul_into(P, np.ascontiguousarray(H.T), PHt)  # C-contiguous: matmul_into's one compiled layout
    matmul_into(H, PHt, out)


@njit(cache=True)
def _normalised_squared(L, e) -> float:
    """``|L^-1 e|^2``: ``e^T S^-1 e`` for ``S = L L^T``."""
    y = e.copy()
    solve_lower(L, y.reshape((len(e), 1)))
    return float(np.sum(y * y))


@njit(cache=True)
def diverged(r, v, C, b_f, b_w, P) -> bool:
    """Non-finite state or covariance (all of ``P``), ``|v| > DIVERGED_SPEED`` or ``sqrt(trace
    P) > DIVERGED_SPREAD`` over the IMU's 15 error-state components."""
    total = P.sum() + r.sum() + v.sum() + C.sum() + b_f.sum() + b_w.sum()  # finite only if every term is
    speed = math.sqrt(v[0] * v[0] + v[1] * v[1] + v[2] * v[2])
    trace = 0.0
    for i in range(imu.STATE_DIM):
        trace += P[i, i]
    return not math.isfinite(total) or speed > DIVERGED_SPEED or trace > DIVERGED_SPREAD**2
