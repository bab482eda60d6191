"""The primer's EKF (section VI.E) on the model of :mod:`factors.imu`.

Prediction per IMU step with ``F``, ``G`` and ``Q_d = diag(R_i / dt)`` (between two updates all
steps at once, :meth:`Ekf.predict_steps`, the same recursion unrolled); updates linearise the
same measurement models the smoother's factors use (:mod:`factors.sensor_models`, through the
kinds' registry :mod:`datasets.kinds`), so the
innovation of an attitude is the boxminus ``C [-] C_meas`` and the correction is applied with
the state boxplus (``exp(dphi) C`` for the attitude). Covariance update in Joseph form, kept
symmetric. An optional chi-square gate rejects measurements whose normalised innovation is
improbable.

Relative-pose measurements need a cloned past state and are not used by this filter (the
smoother uses them); :func:`run_ekf` warns when a dataset has them.
"""
from __future__ import annotations

import math
import time
import warnings
from dataclasses import dataclass

import numpy as np
from numba import njit

from datasets.kinds import KINDS, measure_into, model_index, quiet_dispatch, sensors_of
from datasets.types import Dataset, Trajectory
from factors import imu
from factors.errors import InputError, SolverError
from factors.sensor_models import MAX_RESIDUAL_DIM, evaluate_one
from factors.small_linalg import cholesky_into, matmul_into
from smoother.stats import chi2_quantile
from smoother.progress import progress_bar
from smoother.model.timeline import estimate_times, imu_steps


class Ekf:
    """Error-state EKF over ``x = (r, v, Phi, b_f, b_w)`` with covariance ``P`` (15x15, the
    primer's left-perturbation error state)."""

    def __init__(self, state: imu.ImuState, cov: np.ndarray, noise: imu.ImuNoise, gravity=imu.DEFAULT_GRAVITY,
                 gate_probability: float | None = None):
        self.state = state
        self.P = np.array(cov, dtype=float)
        self.noise = noise
        self.gravity = np.asarray(gravity, dtype=float)
        self.gate_probability = gate_probability
        self.rejected = 0
        #: Sum of the log densities of the accepted innovations, ``log N(e; 0, S)``: the
        #: prediction-error decomposition of the measurements' likelihood under the model.
        self.log_likelihood = 0.0

    def predict(self, acc, gyro, dt) -> None:
        """One Euler-forward step: ``x <- f(x)``, ``P <- F P F^T + G Q_d G^T``."""
        self.predict_steps(np.reshape(acc, (1, 3)), np.reshape(gyro, (1, 3)), np.reshape(dt, (1,)))

    def predict_steps(self, acc, gyro, dt) -> None:
        """:meth:`predict` applied to every step of ``acc, gyro (K, 3)``, ``dt (K,)``: one call of
        the compiled :func:`factors.imu.propagate_steps`, no Python per step."""
        if np.size(dt) == 0:
            return
        self.state, self.P = imu.propagate_steps(self.state, self.P, acc, gyro, dt, self.noise, self.gravity)

    def update(self, e: np.ndarray, H: np.ndarray, R: np.ndarray) -> bool:
        """Correct with a residual ``e(x)`` (measurement model minus measurement, e.g.
        ``C [-] C_meas``), its Jacobian ``H`` (m x 15, error-state columns) and noise ``R``.
        Returns False when the chi-square gate rejects it: the normalised innovation
        ``e^T S^-1 e`` beyond the ``gate_probability`` quantile of chi-square with ``len(e)``
        degrees of freedom (so 3-dim and 6-dim updates are gated alike). Compiled
        (:func:`_kalman_update`, the same code as :func:`run_ekf`'s)."""
        e = np.ascontiguousarray(e, dtype=float)
        H = np.ascontiguousarray(H, dtype=float)
        R = np.ascontiguousarray(R, dtype=float)
        m = len(e)
        if H.shape != (m, imu.STATE_DIM) or R.shape != (m, m):
            raise InputError(f"update: expected H ({m}, 15) and R ({m}, {m}), got {H.shape} and {R.shape}")
        x = self.state
        r, v, C, b_f, b_w = (np.array(a, dtype=float) for a in (x.r, x.v, x.C, x.b_f, x.b_w))
        stats = np.zeros(2)
        _kalman_update(r, v, C, b_f, b_w, self.P, e, H, R, gate_thresholds(self.gate_probability), stats)
        if stats[0]:
            self.rejected += 1
            return False
        self.log_likelihood += stats[1]
        self.state = imu.ImuState(r, v, C, b_f, b_w)
        return True

    def update_sensor(self, kind: str, row: np.ndarray, R: np.ndarray) -> bool:
        """Correct with one measurement of ``kind`` (a name of :data:`datasets.kinds.KINDS`; its
        ``row`` laid out as the kind's ``pack`` does, extrinsic included): the residual and its
        Jacobian from the model's kernel, the one the smoothers' factors run."""
        if kind not in KINDS or KINDS[kind].relative:
            one_state = [name for name, k in KINDS.items() if not k.relative]
            raise InputError(f"update_sensor: kind {kind!r}: expected one of {', '.join(one_state)} (a relative kind "
                             "needs a cloned past state, which this filter does not keep)")
        e, H = evaluate_one(KINDS[kind].model, self.state, row)
        return self.update(e, H, R)


@dataclass
class Innovations:
    """Every measurement update of a run: the sensor's name, its time, the residual's dimension,
    the normalised innovation squared ``e^T S^-1 e`` and whether the gate accepted it (NaN and
    False where the filter had diverged before it)."""

    sensor: np.ndarray
    t: np.ndarray
    dim: np.ndarray
    nis: np.ndarray
    accepted: np.ndarray


@dataclass
class FilterResult:
    """Estimates and covariances at every knot (start, each measurement time, end), and the
    innovations of every update (:class:`Innovations`)."""

    trajectory: Trajectory
    runtime_s: float
    rejected: int
    log_likelihood: float
    innovations: Innovations | None = None
    #: With calibrations as augmented states (:mod:`smoother.ekf.calibrated`): their values at the
    #: end of the data (:class:`factors.calibration.CalibrationSet`) and covariance blocks.
    calibration: object = None
    calibration_cov: list | None = None


def filter_inputs(dataset: Dataset) -> tuple[list, np.ndarray, object]:
    """``(sensors, knots, steps)`` of a filter run: the one-state sensors (relative poses need a
    cloned past state: left out, with a warning), the knots (:func:`smoother.model.timeline.estimate_times`)
    and the IMU steps between them."""
    every = sensors_of(dataset)
    sensors = [s for s in every if not KINDS[s.kind].relative]
    if len(sensors) < len(every):
        warnings.warn("the EKF does not use relative-pose measurements; the smoothers do", stacklevel=3)
    knots = estimate_times(dataset)
    return sensors, knots, imu_steps(dataset.imu, knots)


def run_ekf(dataset: Dataset, gate_probability: float | None = None, progress: bool | None = None) -> FilterResult:
    """Run the EKF over a dataset: predict through every IMU step, update at each measurement
    time with every measurement taken then (sensor by sensor in the order of
    :func:`datasets.kinds.sensors_of`), record the state after the updates. The loop over knots
    is compiled (:func:`_filter_knots`); it runs in chunks so the progress bar moves and Ctrl-C
    stops it between chunks."""
    start = time.perf_counter()
    sensors, knots, steps = filter_inputs(dataset)
    n = len(knots)
    x0 = dataset.initial
    r, v, C, b_f, b_w = (np.array(a, dtype=float) for a in (x0.r, x0.v, x0.C, x0.b_f, x0.b_w))
    P = np.array(dataset.initial_cov, dtype=float)
    out = (np.empty((n, 3)), np.empty((n, 3)), np.empty((n, 3, 3)), np.empty((n, 3)), np.empty((n, 3)),
           np.empty((n, imu.STATE_DIM, imu.STATE_DIM)))
    updates = _Updates.of(sensors, knots)
    bounds = np.concatenate([[0], steps.knot_step]).astype(np.int64)
    stats = np.zeros(2)
    samples = (np.ascontiguousarray(steps.acc, dtype=float), np.ascontiguousarray(steps.gyro, dtype=float),
               np.ascontiguousarray(steps.dt, dtype=float))
    with progress_bar(len(steps.dt), "EKF", progress) as bar, quiet_dispatch():
        for first in range(0, n, _KNOTS_PER_CALL):
            last = min(n, first + _KNOTS_PER_CALL)
            diverged = _filter_knots(r, v, C, b_f, b_w, P, *samples, bounds, first, last, updates.start,
                                     updates.model, updates.dim, updates.rows, updates.R, updates.nis,
                                     updates.accepted, dataset.noise.densities(),
                                     np.asarray(dataset.gravity, dtype=float), gate_thresholds(gate_probability), *out, stats)
            if diverged >= 0:
                raise divergence_error(knots[diverged], out[1][diverged], out[5][diverged])
            bar.update(int(bounds[last]) - bar.n)
    states = imu.ImuState(*out[:5])
    return FilterResult(Trajectory(knots, states, out[5]), time.perf_counter() - start, int(stats[0]), float(stats[1]),
                        updates.innovations([s.name for s in sensors], knots))


@dataclass
class _Updates:
    """The measurement updates of a run in the order the filter applies them, as flat arrays for
    the compiled loop: those at knot ``k`` are ``start[k]:start[k + 1]``; each has its model's
    index, dimension, kernel row (zero-padded to the widest) and noise (padded to 6x6); ``nis``
    and ``accepted`` are filled by the loop."""

    start: np.ndarray
    model: np.ndarray
    dim: np.ndarray
    rows: np.ndarray
    R: np.ndarray
    sensor: np.ndarray
    knot: np.ndarray
    nis: np.ndarray
    accepted: np.ndarray

    @classmethod
    def of(cls, sensors: list, knots: np.ndarray) -> "_Updates":
        parts = []  # (knot, sensor index, model, rows, cov) per sensor
        for index, sensor in enumerate(sensors):
            kind, m = KINDS[sensor.kind], sensor.data
            knot = np.searchsorted(knots, m.t)
            if np.any(knots[np.minimum(knot, len(knots) - 1)] != m.t):
                raise InputError(f"sensor {sensor.name!r}: measurement times that are not knots")
            parts.append((knot, np.full(len(m), index), model_index(kind), kind.pack(m), m.cov))
        if not parts:
            parts.append((np.zeros(0, int), np.zeros(0, int), 0, np.zeros((0, 1)), np.zeros((0, 1, 1))))
        u = sum(len(p[0]) for p in parts)
        width = max(p[3].shape[1] for p in parts)
        rows, R = np.zeros((u, width)), np.zeros((u, MAX_RESIDUAL_DIM, MAX_RESIDUAL_DIM))
        model, dim = np.empty(u, np.int64), np.empty(u, np.int64)
        at = 0
        for _, _, index, block, cov in parts:
            rows[at:at + len(block), :block.shape[1]] = block
            d = cov.shape[-1]
            R[at:at + len(block), :d, :d] = cov
            model[at:at + len(block)], dim[at:at + len(block)] = index, d
            at += len(block)
        knot = np.concatenate([p[0] for p in parts])
        sensor = np.concatenate([p[1] for p in parts])
        order = np.lexsort((sensor, knot))  # by knot, then sensor by sensor
        start = np.searchsorted(knot[order], np.arange(len(knots) + 1)).astype(np.int64)
        return cls(start, model[order], dim[order], rows[order], R[order], sensor[order], knot[order],
                   np.full(u, np.nan), np.zeros(u, dtype=np.bool_))

    def innovations(self, names: list[str], knots: np.ndarray) -> Innovations:
        return Innovations(np.asarray(names, dtype=object)[self.sensor] if len(names) else np.zeros(0, dtype=object),
                           knots[self.knot], self.dim.copy(), self.nis, self.accepted)


#: Knots per call of the compiled loop (between two calls the progress bar moves and Ctrl-C is seen).
_KNOTS_PER_CALL = 256


def gate_thresholds(probability: float | None) -> np.ndarray:
    """Chi-square gate per measurement dimension (index m), infinite without a gate."""
    gates = np.full(7, np.inf)
    if probability is not None:
        for m in range(1, 7):
            gates[m] = chi2_quantile(probability, m)
    return gates


@njit(cache=True)
def _solve_lower(L, b, out) -> None:
    """``out = L^-1 b`` (forward substitution)."""
    for i in range(L.shape[0]):
        acc = b[i]
        for k in range(i):
            acc -= L[i, k] * out[k]
        out[i] = acc / L[i, i]


@njit(cache=True)
def _kalman_update(r, v, C, b_f, b_w, P, e, H, R, gates, stats) -> float:
    """The update of :meth:`Ekf.update` in place on the state arrays and ``P``.

    ``S = H P H^T + R = L L^T``; normalised innovation ``d2 = |L^-1 e|^2``; if ``d2`` passes the
    gate, ``K = P H^T S^-1`` (rows of ``K`` solved through ``L``), ``x <- x [+] (-K e)`` and
    Joseph's ``P <- (I - K H) P (I - K H)^T + K R K^T``; ``stats[0]`` counts rejections,
    ``stats[1]`` accumulates ``log N(e; 0, S)``. A non-positive-definite ``S`` raises. Returns
    ``d2``, the normalised innovation squared."""
    m, n = e.shape[0], P.shape[0]
    PHt, S = np.empty((n, m)), np.empty((m, m))
    matmul_into(P, np.ascontiguousarray(H.T), PHt)  # C-contiguous: matmul_into's one compiled layout
    matmul_into(H, PHt, S)
    S += R
    L = np.empty((m, m))
    if not cholesky_into(0.5 * (S + S.T), L):
        raise SolverError("EKF update: the innovation covariance H P H^T + R is not positive definite")
    y = np.empty(m)
    _solve_lower(L, e, y)
    d2 = 0.0
    logdet = 0.0
    for i in range(m):
        d2 += y[i] * y[i]
        logdet += 2.0 * math.log(L[i, i])
    if d2 > gates[m]:
        stats[0] += 1
        return d2
    stats[1] -= 0.5 * (d2 + logdet + m * math.log(2.0 * math.pi))
    # K^T = S^-1 (P H^T)^T = L^-T L^-1 PHt^T, row by row of K
    K = np.empty((n, m))
    z, col = np.empty(m), np.empty(m)
    for row in range(n):
        _solve_lower(L, PHt[row], z)
        for i in range(m - 1, -1, -1):  # back substitution with L^T
            acc = z[i]
            for k in range(i + 1, m):
                acc -= L[k, i] * col[k]
            col[i] = acc / L[i, i]
        K[row] = col
    dx = np.zeros(n)
    for row in range(n):
        for i in range(m):
            dx[row] -= K[row, i] * e[i]
    imu.boxplus_into(r, v, C, b_f, b_w, dx)
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
def _filter_knots(r, v, C, b_f, b_w, P, acc, gyro, dt, bounds, first, last, start, model, dim, rows, R, nis,
                  accepted, q, g, gates, out_r, out_v, out_C, out_b_f, out_b_w, out_P, stats) -> int:
    """Knots ``first .. last - 1`` of :func:`run_ekf`: predict through the knot's IMU steps
    (``bounds[k] .. bounds[k + 1]``), apply the updates taken there (``start[k] .. start[k + 1]``
    of :class:`_Updates`, each through its model's kernel), store the state. Returns the first
    knot where the filter diverged (see :func:`_diverged`), else -1."""
    n = P.shape[0]
    for knot in range(first, last):
        a, b = bounds[knot], bounds[knot + 1]
        imu.predict_into(r, v, C, b_f, b_w, P, acc[a:b], gyro[a:b], dt[a:b], q, g)
        for u in range(start[knot], start[knot + 1]):
            if _diverged(r, v, C, b_f, b_w, P):
                continue
            m = dim[u]
            e, H = np.empty(m), np.empty((m, n))
            measure_into(model[u], r, v, C, b_f, b_w, rows[u], e, H)
            rejected = stats[0]
            nis[u] = _kalman_update(r, v, C, b_f, b_w, P, e, H, np.ascontiguousarray(R[u, :m, :m]), gates, stats)
            accepted[u] = stats[0] == rejected
        out_r[knot], out_v[knot], out_C[knot], out_b_f[knot], out_b_w[knot] = r, v, C, b_f, b_w
        out_P[knot] = P
        if _diverged(r, v, C, b_f, b_w, P):
            return knot
    return -1


#: Beyond these the filter is declared diverged: |velocity| [m/s], sqrt(trace P) (mixed units).
DIVERGED_SPEED = 1e4
DIVERGED_SPREAD = 1e6


class FilterDiverged(SolverError, ValueError):
    """The EKF's state or covariance left any plausible range (non-finite or absurdly large)."""


@njit(cache=True)
def _diverged(r, v, C, b_f, b_w, P) -> bool:
    """Non-finite state or covariance, ``|v| > DIVERGED_SPEED`` or ``sqrt(trace P) > DIVERGED_SPREAD``."""
    total = P.sum() + r.sum() + v.sum() + C.sum() + b_f.sum() + b_w.sum()  # finite only if every term is
    speed = math.sqrt(v[0] * v[0] + v[1] * v[1] + v[2] * v[2])
    return not math.isfinite(total) or speed > DIVERGED_SPEED or np.trace(P) > DIVERGED_SPREAD**2


def divergence_error(t: float, v: np.ndarray, P: np.ndarray) -> FilterDiverged:
    return FilterDiverged(
        f"the EKF diverged at t = {t:.6f} s (|v| = {np.linalg.norm(v):.3g} m/s, sqrt(trace P) = "
        f"{np.sqrt(abs(np.trace(P))):.3g}): the linearisation failed, typically after a long stretch "
        "without measurements or with a bias random walk far looser than the data; a smoother "
        "(batch or fixed-lag) relinearises and is the tool for such data")
