"""The primer's EKF (section VI.E) on the model of :mod:`factors.imu`.

Prediction per IMU step with ``F``, ``G`` and ``Q_d = diag(R_i / dt)`` (between two updates all
steps at once, :meth:`Ekf.predict_steps`, the same recursion unrolled); updates linearise the
same measurement models the smoother's factors use (:mod:`factors.sensor_models`, through the
kinds' registry :mod:`datasets.kinds`), so the
innovation of an attitude is the boxminus ``C [-] C_meas`` and the correction is applied with
the state boxplus (``exp(dphi) C`` for the attitude). Covariance update in Joseph form, kept
symmetric. An optional chi-square gate rejects measurements whose normalised innovation is
improbable. A sensor's held-out measurements (a rig's ``every = K``) are predicted in the same
loop and not used (:class:`smoother.model.predicted.HeldoutPrediction`): the filter's own
prediction of data it did not use. The update, its gate, the order of the updates and the
divergence test are :mod:`smoother.ekf.update`'s; the compiled loop over the knots
(:func:`run_filter`) is shared with
the calibrating filter (:mod:`smoother.ekf.calibrated`), which carries the sensors' calibrations
as augmented states through it.

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

from datasets.kinds import KINDS, LAYOUTS, calibrated_into, measure_into, model_index, quiet_dispatch, sensors_of
from datasets.types import Dataset, ImuSamples, Trajectory
from factors import calibration, imu
from factors.calibration import CALIBRATION_DIM, CalibrationSet
from factors.errors import InputError, SolverError
from factors.sensor_models import MAX_RESIDUAL_DIM, evaluate_one
from smoother.ekf.update import diverged, gate_thresholds, kalman_update, predict_only, update_order
from smoother.model.correlated import one_error
from smoother.model.predicted import Conditioned, HeldoutPrediction
from smoother.model.timeline import imu_steps, measurement_knots
from smoother.progress import progress_bar


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
        (:func:`smoother.ekf.update.kalman_update`, the same code as :func:`run_ekf`'s)."""
        e = np.ascontiguousarray(e, dtype=float)
        H = np.ascontiguousarray(H, dtype=float)
        R = np.ascontiguousarray(R, dtype=float)
        m = len(e)
        if H.shape != (m, imu.STATE_DIM) or R.shape != (m, m):
            raise InputError(f"update: expected H ({m}, 15) and R ({m}, {m}), got {H.shape} and {R.shape}")
        x = self.state
        r, v, C, b_f, b_w = (np.array(a, dtype=float) for a in (x.r, x.v, x.C, x.b_f, x.b_w))
        stats, dx = np.zeros(2), np.empty(len(self.P))
        kalman_update(self.P, e, H, R, gate_thresholds(self.gate_probability), stats, dx)
        if stats[0]:
            self.rejected += 1
            return False
        imu.boxplus_into(r, v, C, b_f, b_w, dx)
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
    """Estimates and covariances at the knots kept (every knot -- start, each measurement time, end --
    or the times asked for: :func:`run_filter`'s ``kept_at``), and the
    innovations of every update (:class:`Innovations`)."""

    trajectory: Trajectory
    runtime_s: float
    rejected: int
    log_likelihood: float
    innovations: Innovations | None = None
    #: Per sensor name, its held-out measurements as the filter predicted them.
    heldout: dict[str, HeldoutPrediction] | None = None
    #: With calibrations as augmented states (:mod:`smoother.ekf.calibrated`): their values at the
    #: end of the data (:class:`factors.calibration.CalibrationSet`) and covariance blocks.
    calibration: object = None
    calibration_cov: list | None = None


def filter_inputs(dataset: Dataset, kept_at=None) -> tuple[list, np.ndarray, np.ndarray, object]:
    """``(sensors, knots, kept, steps)`` of a filter run: the one-state sensors (relative poses
    need a cloned past state: left out, with a warning), the knots
    (:func:`smoother.model.timeline.measurement_knots`, and the times ``kept_at`` within the IMU's
    span), which of them keep their state (``kept``: those of ``kept_at``; every one where None)
    and the IMU steps between them."""
    every = sensors_of(dataset)
    sensors = [s for s in every if not KINDS[s.kind].relative]
    if len(sensors) < len(every):
        warnings.warn("the EKF does not use relative-pose measurements; the smoothers do", stacklevel=3)
    knots = measurement_knots(dataset)
    if kept_at is None:
        return sensors, knots, np.ones(len(knots), dtype=np.bool_), imu_steps(dataset.imu, knots)
    kept_at = np.asarray(kept_at, dtype=float)
    knots = np.union1d(knots, kept_at[(kept_at >= dataset.t0) & (kept_at <= dataset.t1)])
    return sensors, knots, np.isin(knots, kept_at), imu_steps(dataset.imu, knots)


def run_ekf(dataset: Dataset, gate_probability: float | None = None, progress: bool | None = None,
            kept_at=None) -> FilterResult:
    """Run the EKF over a dataset: predict through every IMU step, update at each measurement
    time with every measurement taken then (sensor by sensor in the order of
    :func:`datasets.kinds.sensors_of`), record the state after the updates, there or at the
    times ``kept_at`` (:func:`run_filter` without calibrations)."""
    return run_filter(dataset, np.array(dataset.initial_cov, dtype=float), None, gate_probability, progress, kept_at)


def run_filter(dataset: Dataset, P: np.ndarray, calibrations: CalibrationSet | None,
               gate_probability: float | None = None, progress: bool | None = None, kept_at=None) -> FilterResult:
    """:func:`run_ekf`, or with ``calibrations`` as augmented states (:mod:`smoother.ekf.calibrated`),
    from the dataset's initial state, the calibrations' values and the joint covariance ``P``
    (square, the IMU's 15 error-state components, then the calibrations' estimated coordinates
    in their order: :func:`factors.calibration.placement`). The loop over knots is compiled
    (:func:`_filter_knots`); it runs in chunks so the progress bar moves and Ctrl-C stops it
    between chunks. The states and 15x15 covariances are kept at every knot, or, with
    ``kept_at``, at those times alone (the smoothers' keyframes: a filter updated at 93 Hz need
    not keep 93 covariances a second), which are then knots too (:func:`filter_inputs`; a time
    between two IMU samples splits that step); they are written into arrays allocated once. With
    calibrations the result carries their values at the end of the data and their covariance
    blocks."""
    start = time.perf_counter()
    sensors, knots, kept, steps = filter_inputs(dataset, kept_at)
    n, out_index = len(knots), np.where(kept, np.cumsum(kept) - 1, -1).astype(np.int64)
    m = int(kept.sum())
    x0 = dataset.initial
    r, v, C, b_f, b_w = (np.array(a, dtype=float) for a in (x0.r, x0.v, x0.C, x0.b_f, x0.b_w))
    P = np.array(P, dtype=float)
    out = (np.empty((m, 3)), np.empty((m, 3)), np.empty((m, 3, 3)), np.empty((m, 3)), np.empty((m, 3)),
           np.empty((m, imu.STATE_DIM, imu.STATE_DIM)))
    c = calibrations if calibrations is not None else CalibrationSet((), (), (), ())
    values = np.array([calibration.packed(value) for value in c.values]).reshape(len(c), calibration.PACKED_SIZE)
    timed = np.array(["time_offset" in prior.parts for prior in c.priors], dtype=np.bool_)
    owner, coordinate = calibration.placement(c.priors)
    if P.shape != (imu.STATE_DIM + len(owner),) * 2:
        raise InputError(f"run_filter: expected P of shape {(imu.STATE_DIM + len(owner),) * 2} (the IMU's error "
                         f"state and the calibrations' estimated coordinates), got {P.shape}")
    gm_first, gm_dim, gm_tau = _drifting_columns(sensors, imu.STATE_DIM + len(owner))
    if len(gm_first):  # each drifting sensor's error, unit-variance and zero-mean where the data start
        G = int(gm_dim.sum())
        P = np.block([[P, np.zeros((len(P), G))], [np.zeros((G, len(P))), np.eye(G)]])
    gm_mean = np.zeros(len(P))
    names = [s.name for s in sensors if s.correlation_time is not None]
    updates = _Updates.of(sensors, knots, [c.names.index(s.name) if s.name in c.names else -1 for s in sensors],
                          dataset.imu if len(c) else None, dict(zip(names, gm_first.tolist())))
    bounds = np.concatenate([[0], steps.knot_step]).astype(np.int64)
    stats = np.zeros(2)
    samples = (np.ascontiguousarray(steps.acc, dtype=float), np.ascontiguousarray(steps.gyro, dtype=float),
               np.ascontiguousarray(steps.dt, dtype=float))
    with progress_bar(len(steps.dt), "EKF (calibrating)" if len(c) else "EKF", progress) as bar, quiet_dispatch():
        for first in range(0, n, _KNOTS_PER_CALL):
            last = min(n, first + _KNOTS_PER_CALL)
            stopped = _filter_knots(r, v, C, b_f, b_w, P, *samples, bounds, first, last, updates.start,
                                    updates.model, updates.dim, updates.rows, updates.R, updates.slot,
                                    updates.held_acc, updates.held_gyro, values, timed, owner, coordinate,
                                    updates.drifting, updates.root, gm_first, gm_dim, gm_tau, gm_mean,
                                    updates.nis, updates.accepted, updates.predicted, updates.predicted_e,
                                    updates.predicted_state, updates.predicted_given, updates.predicted_drift,
                                    updates.predicted_total,
                                    dataset.noise.densities(),
                                    np.asarray(dataset.gravity, dtype=float), gate_thresholds(gate_probability),
                                    out_index, *out, stats)
            if stopped >= 0:  # the state where it diverged
                raise divergence_error(knots[stopped], v, P[:imu.STATE_DIM, :imu.STATE_DIM])
            bar.update(int(bounds[last]) - bar.n)
    moved, blocks = None, None
    if calibrations is not None:
        at = imu.STATE_DIM + np.concatenate([[0], np.cumsum(c.dims)]).astype(int)
        moved = CalibrationSet(c.names, tuple(calibration.unpacked(value) for value in values), c.priors, c.means)
        blocks = [P[at[j]:at[j + 1], at[j]:at[j + 1]].copy() for j in range(len(c))]
    return FilterResult(Trajectory(knots[kept], imu.ImuState(*out[:5]), out[5]), time.perf_counter() - start,
                        int(stats[0]), float(stats[1]), updates.innovations([s.name for s in sensors], knots),
                        updates.heldout(), moved, blocks)


def _drifting_columns(sensors: list, first: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``(first column, dimension, correlation time)`` of each of ``sensors`` with a correlation
    time (:attr:`datasets.types.Sensor.correlation_time`), its error's augmented state placed in
    order from column ``first`` of ``P``."""
    drifting = [s for s in sensors if s.correlation_time is not None]
    dims = np.array([KINDS[s.kind].dim for s in drifting], dtype=np.int64)
    starts = (first + np.concatenate([[0], np.cumsum(dims)[:-1]])).astype(np.int64) if len(dims) else dims
    return starts, dims, np.array([s.correlation_time for s in drifting], dtype=float)


@dataclass
class _Updates:
    """The measurement updates of a run in the order the filter applies them
    (:func:`smoother.ekf.update.update_order`), as flat arrays for the compiled loop: those at
    knot ``k`` are ``start[k]:start[k + 1]``; each has its model's index, dimension, kernel row
    (zero-padded to the widest), noise (padded to 6x6) and the index of its sensor's calibration
    among the augmented states (``slot``, -1: none), with the IMU reading held at its time
    (``held_acc``, ``held_gyro``; empty without calibrations); ``nis`` and ``accepted`` are
    filled by the loop. The sensors' held-out measurements within the knots' span come after
    their used ones at a knot (``source`` counts the sensors, then those with held-out
    measurements again): predicted, not used, each into its row ``predicted`` (-1: an update) of
    ``predicted_e`` and ``predicted_state`` (:func:`smoother.ekf.update.predict_only`)."""

    start: np.ndarray
    model: np.ndarray
    dim: np.ndarray
    rows: np.ndarray
    R: np.ndarray
    slot: np.ndarray
    held_acc: np.ndarray
    held_gyro: np.ndarray
    source: np.ndarray
    knot: np.ndarray
    nis: np.ndarray
    accepted: np.ndarray
    predicted: np.ndarray
    predicted_e: np.ndarray
    predicted_state: np.ndarray
    #: Per update, the first column of its sensor's drifting error among the augmented states (-1:
    #: none; its noise then is that state's, ``n = root u``, and ``R`` is zero) and ``root``, the
    #: Cholesky factor of its stated covariance; per prediction of a drifting sensor, the residual
    #: with the error's estimate in it (``predicted_given``), its whole covariance ``H P H^T``
    #: (``predicted_total``) and the drifting error's own share of it, ``root P_(u|x) root^T`` with
    #: ``P_(u|x)`` the error's covariance given every other state (``predicted_drift``, positive
    #: semi-definite, and so is the rest); ``predicted_state`` holds the residual without it, ``H_x P
    #: H_x^T`` over the other states.
    drifting: np.ndarray
    root: np.ndarray
    predicted_given: np.ndarray
    predicted_drift: np.ndarray
    predicted_total: np.ndarray
    #: Per held-out source (in ``source``'s order after the sensors): its sensor's name, the
    #: indices of the held-out measurements predicted among the sensor's, their dimension and which
    #: of them a drifting sensor's used one makes one error with (judged alone: the model's ``one_error``).
    heldout_of: list

    @classmethod
    def of(cls, sensors: list, knots: np.ndarray, slots: list[int], samples: ImuSamples | None,
           drifting: dict | None = None) -> "_Updates":
        """The updates of ``sensors`` (``slots``: each one's calibration index, -1: none) at
        ``knots``, and the predictions of their held-out measurements there, with the readings of
        the IMU ``samples`` held at their times (None: no calibrations); ``drifting``: the first
        column of each drifting sensor's error state, by name."""
        drifting = drifting or {}
        parts = [(model_index(KINDS[s.kind]), KINDS[s.kind].pack(s.data), s.data.cov, s.data.t, slot)
                 for s, slot in zip(sensors, slots)]
        columns = [drifting.get(s.name, -1) for s in sensors]
        heldout_of = []
        for s, slot in zip(sensors, slots):
            held = s.heldout
            if held is None or len(held.t) == 0:
                continue
            index = np.flatnonzero((held.t >= knots[0]) & (held.t <= knots[-1])) if len(knots) else np.zeros(0, int)
            alone = (one_error(held.t[index], s.data.t, s.correlation_time)
                     if s.name in drifting and s.data is not None else np.zeros(len(index), dtype=bool))
            heldout_of.append((s.name, index, held.cov.shape[-1], alone))
            parts.append((model_index(KINDS[s.kind]), KINDS[s.kind].pack(held)[index], held.cov[index],
                          held.t[index], slot))
            columns.append(drifting.get(s.name, -1))
        names = [s.name for s in sensors] + [f"{name} (held out)" for name, *_ in heldout_of]
        if not parts:
            parts.append((0, np.zeros((0, 1)), np.zeros((0, 1, 1)), np.zeros(0), -1))
        u = sum(len(p[1]) for p in parts)
        width = max(p[1].shape[1] for p in parts)
        rows, R = np.zeros((u, width)), np.zeros((u, MAX_RESIDUAL_DIM, MAX_RESIDUAL_DIM))
        model, dim = np.empty(u, np.int64), np.empty(u, np.int64)
        at, first = 0, []
        for index, block, cov, _, _ in parts:
            first.append(at)
            rows[at:at + len(block), :block.shape[1]] = block
            d = cov.shape[-1]
            R[at:at + len(block), :d, :d] = cov
            model[at:at + len(block)], dim[at:at + len(block)] = index, d
            at += len(block)
        o = update_order([p[3] for p in parts], knots, names)
        order = np.asarray(first, dtype=np.int64)[o.sensor] + o.measurement if u else np.zeros(0, dtype=np.int64)
        slot = np.asarray([p[4] for p in parts], dtype=np.int64)[o.sensor] if u else np.zeros(0, dtype=np.int64)
        held = samples.held(knots[o.knot]) if samples is not None else np.zeros(0, dtype=np.int64)
        held_acc, held_gyro = ((np.ascontiguousarray(samples.acc[held], dtype=float),
                                np.ascontiguousarray(samples.gyro[held], dtype=float))
                               if samples is not None else (np.zeros((0, 3)), np.zeros((0, 3))))
        used = sum(len(p[1]) for p in parts[:len(sensors)])
        predicted = np.where(order >= used, order - used, -1).astype(np.int64)
        column = np.asarray(columns or [-1], dtype=np.int64)[o.sensor] if u else np.zeros(0, dtype=np.int64)
        R, root = R[order], np.zeros((u, MAX_RESIDUAL_DIM, MAX_RESIDUAL_DIM))
        for i in np.flatnonzero(column >= 0):  # its noise is the drifting state's: n = root u
            d = dim[order][i]
            root[i, :d, :d] = np.linalg.cholesky(R[i, :d, :d])
            R[i] = 0.0
        return cls(o.start, model[order], dim[order], rows[order], R, slot, held_acc, held_gyro, o.sensor,
                   o.knot, np.full(u, np.nan), np.zeros(u, dtype=np.bool_), predicted,
                   np.full((u - used, MAX_RESIDUAL_DIM), np.nan),
                   np.full((u - used, MAX_RESIDUAL_DIM, MAX_RESIDUAL_DIM), np.nan), column, root,
                   np.full((u - used, MAX_RESIDUAL_DIM), np.nan),
                   np.full((u - used, MAX_RESIDUAL_DIM, MAX_RESIDUAL_DIM), np.nan),
                   np.full((u - used, MAX_RESIDUAL_DIM, MAX_RESIDUAL_DIM), np.nan), heldout_of)

    def innovations(self, names: list[str], knots: np.ndarray) -> Innovations:
        """The updates' innovations (the held-out measurements' predictions left out)."""
        used = self.predicted < 0
        return Innovations(np.asarray(names, dtype=object)[self.source[used]] if len(names)
                           else np.zeros(0, dtype=object), knots[self.knot[used]], self.dim[used], self.nis[used],
                           self.accepted[used])

    def heldout(self) -> dict[str, HeldoutPrediction]:
        """Per sensor with held-out measurements, their predictions (:class:`HeldoutPrediction`)."""
        out, at = {}, 0
        update_of = np.empty(len(self.predicted_e), dtype=np.int64)  # each prediction's update
        made = np.flatnonzero(self.predicted >= 0)
        update_of[self.predicted[made]] = made
        for name, index, d, alone in self.heldout_of:
            rows = slice(at, at + len(index))
            at += len(index)
            e, S = self.predicted_e[rows, :d].copy(), self.predicted_state[rows, :d, :d].copy()
            update = update_of[rows]
            if not len(index) or self.drifting[update[0]] < 0:
                out[name] = HeldoutPrediction(index, e, S)
                continue
            # a drifting sensor: judged given its error's estimate, whitened by its stated noise; the
            # error's own share of the covariance in the noise's place, the rest the state's
            W = np.linalg.inv(self.root[update, :d, :d])
            drift, total = self.predicted_drift[rows, :d, :d], self.predicted_total[rows, :d, :d]
            given = np.einsum("mab,mb->ma", W, self.predicted_given[rows, :d])
            WT = np.swapaxes(W, 1, 2)
            state, noise = W @ (total - drift) @ WT, W @ drift @ WT
            # at a used measurement's stamp: judged alone (smoother.model.correlated.one_error), its own noise
            given[alone], state[alone] = np.einsum("mab,mb->ma", W[alone], e[alone]), W[alone] @ S[alone] @ WT[alone]
            noise[alone] = np.eye(d)
            out[name] = HeldoutPrediction(index, e, S, Conditioned(given, state, noise))
        return out


#: Knots per call of the compiled loop (between two calls the progress bar moves and Ctrl-C is seen).
_KNOTS_PER_CALL = 256


@njit(cache=True)
def _filter_knots(r, v, C, b_f, b_w, P, acc, gyro, dt, bounds, first, last, start, model, dim, rows, R, slot,
                  held_acc, held_gyro, values, timed, owner, coordinate, drifting, root, gm_first, gm_dim, gm_tau,
                  gm_mean, nis, accepted, predicted, predicted_e, predicted_state, predicted_given, predicted_drift,
                  predicted_total, q, g, gates, out_index, out_r, out_v, out_C, out_b_f, out_b_w, out_P, stats) -> int:
    """Knots ``first .. last - 1`` of :func:`run_filter`: predict through the knot's IMU steps
    (``bounds[k] .. bounds[k + 1]``; with calibrations, :func:`_predict_augmented`), apply the
    updates taken there (``start[k] .. start[k + 1]`` of :class:`_Updates`, each through its
    model's kernel, or through its calibration's for a sensor with one,
    :func:`datasets.kinds.calibrated_into`, and :func:`smoother.ekf.update.kalman_update` on
    the whole ``P``), the correction applied with the state's boxplus and the calibrations'
    (:func:`factors.calibration.set_boxplus_into`) -- a held-out measurement's residual and
    ``H P H^T`` into its row ``predicted[u]`` of ``predicted_e``, ``predicted_state`` instead, no
    update (:func:`smoother.ekf.update.predict_only`) -- store the state where the knot's ``out_index``
    is one (-1: not kept). A drifting sensor's error (columns ``gm_first[i]`` on, ``gm_dim[i]`` of
    them, its mean in ``gm_mean``) decays between knots as :func:`_drift` steps it and enters its
    measurements' residuals as ``root u`` (``drifting[u]``: its first column; its ``R`` zero), each
    held-out one's residual with it into ``predicted_given``, its covariance into ``predicted_total``
    and the error's own share of it into ``predicted_drift`` (:func:`_given_the_rest`); the residual
    without it stays in ``predicted_e``, its ``H_x P H_x^T`` in ``predicted_state``. ``values`` are the packed
    calibrations (moved in place), ``timed`` which estimate their time offset, ``owner`` and
    ``coordinate`` their estimated coordinates' places (:func:`factors.calibration.placement`),
    those of ``P`` after the IMU's 15. Returns the first knot where the filter diverged
    (:func:`smoother.ekf.update.diverged`), else -1."""
    D, n = imu.STATE_DIM, P.shape[0]
    dx = np.empty(n)
    P_xx, P_xc = np.empty((D, D)), np.empty((D, n - D))
    x = (np.empty(3), np.empty(3), np.empty((3, 3)))
    H_c, work = np.empty((MAX_RESIDUAL_DIM, CALIBRATION_DIM)), calibration.work_array()
    for knot in range(first, last):
        a, b = bounds[knot], bounds[knot + 1]
        if n == D:
            imu.predict_into(r, v, C, b_f, b_w, P, acc[a:b], gyro[a:b], dt[a:b], q, g)
        elif b > a:
            _predict_augmented(r, v, C, b_f, b_w, P, acc[a:b], gyro[a:b], dt[a:b], q, g, P_xx, P_xc, x)
            _drift(P, gm_mean, gm_first, gm_dim, gm_tau, np.sum(dt[a:b]))
        for u in range(start[knot], start[knot + 1]):
            if diverged(r, v, C, b_f, b_w, P):
                continue
            m, j = dim[u], slot[u]
            e, H_x, H = np.empty(m), np.empty((m, D)), np.zeros((m, n))
            if j < 0:
                measure_into(model[u], r, v, C, b_f, b_w, rows[u], e, H_x)
            else:
                calibrated_into(model[u], LAYOUTS[model[u]], r, v, C, b_f, b_w, rows[u], values[j], timed[j],
                                held_acc[u], held_gyro[u], g, e, H_x, H_c[:m], work, True)
            H[:, :D] = H_x
            for k in range(owner.shape[0]):
                if owner[k] == j:
                    H[:, D + k] = H_c[:m, coordinate[k]]
            p, f = predicted[u], drifting[u]
            if p >= 0:
                predicted_e[p, :m] = e
            if f >= 0:  # e + root u: the drifting error's estimate in the residual, root its Jacobian
                for i in range(m):
                    for k in range(m):
                        e[i] += root[u, i, k] * gm_mean[f + k]
                        H[i, f + k] = root[u, i, k]
            if p >= 0:
                nis[u] = predict_only(P, e, H, np.ascontiguousarray(R[u, :m, :m]), predicted_state[p, :m, :m])
                if f >= 0:
                    predicted_given[p, :m] = e
                    predicted_total[p, :m, :m] = predicted_state[p, :m, :m]
                    Lr = np.ascontiguousarray(root[u, :m, :m])
                    predicted_drift[p, :m, :m] = Lr @ _given_the_rest(P, f, m) @ Lr.T
                    H_x = H.copy()
                    H_x[:, f:f + m] = 0.0
                    predicted_state[p, :m, :m] = H_x @ P @ H_x.T
                continue
            rejected = stats[0]
            nis[u] = kalman_update(P, e, H, np.ascontiguousarray(R[u, :m, :m]), gates, stats, dx)
            accepted[u] = stats[0] == rejected
            if accepted[u]:
                imu.boxplus_into(r, v, C, b_f, b_w, dx)
                calibration.set_boxplus_into(values, owner, coordinate, dx[D:])
                gm_mean[D + owner.shape[0]:] += dx[D + owner.shape[0]:]  # the drifting errors: the last columns
        o = out_index[knot]
        if o >= 0:
            out_r[o], out_v[o], out_C[o], out_b_f[o], out_b_w[o] = r, v, C, b_f, b_w
            out_P[o] = P[:D, :D]
        if diverged(r, v, C, b_f, b_w, P):
            return knot
    return -1


#: Relative cut-off of :func:`_given_the_rest`'s pseudo-inverse, on the rest's correlations.
GIVEN_RCOND = 1e-12


@njit(cache=True)
def _given_the_rest(P, f, m) -> np.ndarray:
    """``P_uu - P_ur P_rr^+ P_ru``: the covariance of the states ``f .. f + m - 1`` of ``P`` given
    all the others (``r``), the Schur complement. With the pseudo-inverse ``+``: a drifting
    sensor's measurement has no noise of its own (``R`` zero), so just after one, ``P_rr`` is
    singular where the rest hold its error (another drifting sensor's, at one instant), and the
    conditional is a degenerate Gaussian's, which the pseudo-inverse gives (``P_ru`` lies in
    ``P_rr``'s range). It is taken of the rest's correlations (``P_rr`` scaled to a unit
    diagonal), so that :data:`GIVEN_RCOND` is relative to each state's own variance, not to the
    largest (metres squared beside a bias's)."""
    rest = np.concatenate((np.arange(f), np.arange(f + m, P.shape[0])))
    P_rr = np.ascontiguousarray(P[rest][:, rest])
    P_ru = np.ascontiguousarray(P[rest][:, f:f + m])
    d = np.diag(P_rr)
    scale = np.where(d > 0.0, 1.0 / np.sqrt(np.maximum(d, 1e-300)), 0.0)
    G = scale[:, None] * P_ru
    Q = scale[:, None] * P_rr * scale[None, :]
    return P[f:f + m, f:f + m] - G.T @ np.linalg.pinv(Q, GIVEN_RCOND) @ G


@njit(cache=True)
def _drift(P, mean, first, dims, taus, dt) -> None:
    """The drifting sensors' errors over ``dt`` [s], each a first-order Gauss-Markov process of unit
    variance (:mod:`smoother.model.correlated`): ``u <- phi u + w``, ``phi = exp(-dt / tau)``,
    ``w ~ N(0, (1 - phi^2) I)`` -- their rows and columns of ``P`` times ``phi``, their own diagonal
    plus ``1 - phi^2``."""
    for i in range(first.shape[0]):
        phi = math.exp(-dt / taus[i])
        fresh = -math.expm1(-2.0 * dt / taus[i])  # 1 - phi^2 without cancellation (an IMU step against hours)
        for k in range(first[i], first[i] + dims[i]):
            mean[k] *= phi
            for j in range(P.shape[0]):
                P[k, j] *= phi
                P[j, k] *= phi
            P[k, k] += fresh


@njit(cache=True)
def _predict_augmented(r, v, C, b_f, b_w, P, acc, gyro, dt, q, g, P_xx, P_xc, x) -> None:
    """The prediction of the augmented ``P`` (:mod:`smoother.ekf.calibrated`): ``P_xx`` by
    :func:`factors.imu.predict_into` (the state stepped with it), ``P_xc <- Phi P_xc`` by
    :func:`factors.imu.transition_into` on a copy ``x`` of ``(r, v, C)``, ``P_cc`` unchanged;
    ``P_xx``, ``P_xc`` work arrays of their blocks' shapes."""
    D = imu.STATE_DIM
    P_xx[:, :], P_xc[:, :] = P[:D, :D], P[:D, D:]
    x[0][:], x[1][:], x[2][:, :] = r, v, C
    imu.transition_into(x[0], x[1], x[2], b_f, b_w, acc, gyro, dt, g, P_xc)
    imu.predict_into(r, v, C, b_f, b_w, P_xx, acc, gyro, dt, q, g)
    P[:D, :D], P[:D, D:], P[D:, :D] = P_xx, P_xc, P_xc.T


class FilterDiverged(SolverError, ValueError):
    """The EKF's state or covariance left any plausible range (non-finite or absurdly large)."""


def divergence_error(t: float, v: np.ndarray, P: np.ndarray) -> FilterDiverged:
    return FilterDiverged(
        f"the EKF diverged at t = {t:.6f} s (|v| = {np.linalg.norm(v):.3g} m/s, sqrt(trace P) = "
        f"{np.sqrt(abs(np.trace(P))):.3g}): the linearisation failed, typically after a long stretch "
        "without measurements or with a bias random walk far looser than the data; a smoother "
        "(batch or fixed-lag) relinearises and is the tool for such data")
