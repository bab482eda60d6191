"""Building the factor graph of a dataset: keyframes, IMU factors, measurement factors, priors
and initial values.

Keyframes sit at :func:`smoother.model.timeline.keyframe_times`: on the grid of ``keyframe_rate``
(by default chosen from the data, :func:`smoother.model.timeline.keyframe_rate`), at held-out
times, both ends of relative measurements and the start and end of the IMU data -- or at every
measurement time. Keyframe 0 carries a joint prior from ``dataset.initial`` and
``dataset.initial_cov``. Consecutive keyframes are joined by an IMU factor
(:class:`factors.imu_factor.ImuFactor`); every interval is preintegrated in one batched call. A
measurement between two keyframes is attached to the one before it
(:func:`datasets.kinds.attached_into`: its state the exact product of the Euler steps from the
keyframe to its time), its covariance grown by the process noise over that partial interval
(:func:`attached_covariance`).

Initial values come from dead reckoning and the measurements: keyframe ``k`` starts as the IMU
prediction from keyframe ``k-1``; a measured position or attitude then replaces the predicted one
and, where positions are measured, the velocity is taken from their finite differences. The same
initial trajectory is the reference along which each IMU factor's noise covariance is computed
(one call: :func:`factors.preintegration.integrate_with_covariance`).

The GTSAM factors are made keyframe by keyframe (``Problem.keyframe_factors``, what the fixed-lag
smoothers take), and the whole GTSAM graph (``Problem.graph`` and friends) from them on first use:
the batch solver runs on the vectorised blocks and never needs them.
"""
from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field, replace
from typing import NamedTuple

import gtsam
import numpy as np

from datasets.kinds import KINDS, attached_noise, attached_rows, calibrated_rows, measure_rows, model_index, sensors_of
from datasets.types import Dataset, Trajectory
from factors import calibration, imu, preintegration, priors
from factors.custom import BIAS, ROT, VEC, custom_factor
from factors.errors import InputError
from factors.imu_factor import ImuFactor
from factors.keys import KeyframeKeys, keyframe_keys
from factors.sensor_models import odometry_factor, odometry_residual, pack_odometry, sensor_factor
from smoother.model.blocks import Block, whitening
from smoother.model.correlated import Innovation, innovation_weights
from smoother.model.robust import noise_model, robust_estimator
from smoother.model.timeline import (
    Attachment,
    Steps,
    attachment,
    imu_steps,
    keyframe_record,
    keyframe_times,
    relative_on_keyframes,
    states_at,
)


@dataclass
class KeyframeFactors:
    """The GTSAM factors that become available at one keyframe ``k`` (all their keyframes are
    ``<= k``), in the order they are added: the prior (keyframe 0), the IMU factor from keyframe
    ``k - 1`` (``imu``, None at keyframe 0), then the measurement factors that become available at
    ``k``, block by block: those whose latest keyframe is ``k``, and those attached to keyframe
    ``k - 1`` (taken after it, before ``k``). ``rows[i]`` is ``(block index, row)`` of
    ``factors[i]`` in the problem's blocks, ``oldest[i]`` its earliest keyframe. What the prior and
    the measurement factors are made of, for a window that makes its own (the sliding window's
    ``add_keyframe``): ``prior`` ``(state, cov)`` (keyframe 0; None elsewhere) and
    ``measurements``, one ``(spec, m, keyframes, kernel, attached, innovation)`` per measurement
    factor in their order (:class:`MeasurementSpec`, the row, the keyframes it reads, the robust
    kernel spec or None, :class:`AttachedAt` or None, and for a measurement after the first of a
    sensor whose errors drift, :class:`smoother.model.correlated.Innovation`, else None: ``factors``
    holds its own white factor all the same)."""

    imu: ImuFactor | None
    factors: list
    rows: list[tuple[int, int]]
    oldest: list[int]
    prior: tuple | None = None
    measurements: list = field(default_factory=list)


class AttachedAt(NamedTuple):
    """Where a measurement attached to a keyframe lies in the keyframe's IMU interval: after the
    first ``steps`` Euler steps, the last cut to ``last_dt`` [s]; ``held``: the IMU reading
    ``(acc, gyro)`` held at its stamp (what a calibrated time offset steps with)."""

    steps: int
    last_dt: float
    held: tuple


@dataclass
class GtsamGraph:
    """A problem's factors as GTSAM factors: the ``graph`` with its ``initial`` values, the IMU
    factors, the factors grouped by the keyframe at which they become available (``factors_at``)
    and ``rows_of``: ``id(gtsam factor) -> (block index, row)``, where each factor sits in the
    problem's blocks."""

    graph: gtsam.NonlinearFactorGraph
    initial: gtsam.Values
    imu_factors: list[ImuFactor]
    factors_at: list[list]
    rows_of: dict


@dataclass
class Problem:
    """A dataset's factor graph, twice over: as vectorised :class:`smoother.model.blocks.Block` s (the
    batch solver's) and as GTSAM factors over the same residual functions.

    ``keyframe_factors(k)`` makes the GTSAM factors that become available at keyframe ``k``
    (:class:`KeyframeFactors`), new ones at every call: the fixed-lag smoothers take them keyframe
    by keyframe and let them go when GTSAM has marginalised them, so a run holds the window's
    factors only. The whole GTSAM graph (:class:`GtsamGraph`: for GTSAM's optimisers and the
    cross-checks) is built from them on first use (``gtsam_parts`` is None until then): the batch
    solver never needs it, and building it took about half of the problem's construction."""

    times: np.ndarray
    keys: list[KeyframeKeys]
    initial_states: imu.ImuState
    blocks: list[Block]
    keyframe_factors: Callable[[int], KeyframeFactors] = field(repr=False)
    gravity: np.ndarray = field(default_factory=lambda: imu.DEFAULT_GRAVITY.copy())
    gtsam_parts: GtsamGraph | None = field(default=None, repr=False)
    #: The names of the blocks of absolute measurements (:attr:`datasets.kinds.base.Kind.absolute`).
    absolute: frozenset = frozenset()
    #: The calibration variables (:class:`factors.calibration.CalibrationSet`) of the sensors that
    #: ask for them (:attr:`datasets.types.Sensor.calibrate`), at their initial values, or None.
    #: Only the vectorised blocks read them; ``keyframe_factors`` keep the values given.
    calibration: calibration.CalibrationSet | None = None
    #: The keyframes chosen (:func:`smoother.model.timeline.keyframe_record`).
    keyframes: dict = field(default_factory=dict)

    @property
    def gtsam(self) -> GtsamGraph:
        if self.gtsam_parts is None:
            self.gtsam_parts = _whole_graph(self)
        return self.gtsam_parts

    @property
    def graph(self) -> gtsam.NonlinearFactorGraph:
        return self.gtsam.graph

    @property
    def initial(self) -> gtsam.Values:
        return self.gtsam.initial

    @property
    def imu_factors(self) -> list[ImuFactor]:
        return self.gtsam.imu_factors

    @property
    def factors_at(self) -> list[list]:
        return self.gtsam.factors_at

    @property
    def rows_of(self) -> dict:
        return self.gtsam.rows_of


def _match(times: np.ndarray, t: np.ndarray) -> np.ndarray:
    """Keyframe index of each time in ``t`` (which must all be keyframe times), -1 if outside."""
    i = np.searchsorted(times, t)
    ok = (i < len(times)) & (times[np.minimum(i, len(times) - 1)] == t)
    return np.where(ok, i, -1)


def insert_state(values: gtsam.Values, keys: KeyframeKeys, state: imu.ImuState) -> None:
    """Insert one state's variables (Rot3, Point3, velocity, bias) under ``keys``."""
    values.insert(keys.rot, gtsam.Rot3(state.C))
    values.insert(keys.pos, gtsam.Point3(*state.r))
    values.insert(keys.vel, np.array(state.v, dtype=float))
    values.insert(keys.bias, gtsam.imuBias.ConstantBias(state.b_f, state.b_w))


def read_state(values: gtsam.Values, keys: KeyframeKeys) -> imu.ImuState:
    """The state of one keyframe from GTSAM values."""
    b = values.atConstantBias(keys.bias).vector()
    return imu.ImuState(
        r=values.atPoint3(keys.pos), v=values.atVector(keys.vel), C=values.atRot3(keys.rot).matrix(),
        b_f=b[:3], b_w=b[3:],
    )


def _anchors(dataset: Dataset, times: np.ndarray) -> preintegration.Anchors:
    """What the measurements say about keyframes ``1 ..``, to reset the dead reckoning of the
    initial trajectory: measured positions and attitudes at the keyframes they fall on or are
    attached to (the nearest after a keyframe, its position moved back along the world velocity
    by how far it lies after it), and the world velocity interpolated from the finite differences
    of the positions over their own times (when there are two or more); NaN where unknown.
    Keyframe 0 is the dataset's initial state, never reset."""
    n = len(times)
    anchors = preintegration.Anchors.none(n)
    at = np.full(n, np.nan)  # the time of each keyframe's anchoring position
    # where several sensors anchor one keyframe, the later wins: one that gives both position and attitude
    implied = [KINDS[s.kind].anchor(s.data) for s in sensors_of(dataset) if KINDS[s.kind].anchor is not None]
    for t, r, C in sorted(implied, key=lambda a: a[1] is not None and a[2] is not None):
        k = np.searchsorted(times, t, side="right") - 1
        inside = (k >= 0) & (t <= times[-1])
        # per keyframe, its nearest measurement at or after it
        order = np.argsort(t - times[np.maximum(k, 0)], kind="stable")
        order = order[inside[order]]
        kk, first = np.unique(k[order], return_index=True)
        rows = order[first]
        if r is not None:
            anchors.r[kk] = r[rows]
            at[kk] = t[rows]
        if C is not None:
            anchors.C[kk] = C[rows]
    has_r = np.isfinite(anchors.r[:, 0])
    apart = np.flatnonzero(has_r)[_apart(at[has_r], SAME_INSTANT)]
    if len(apart) >= 2:
        tr, rr = at[apart], anchors.r[apart]
        gradient = np.gradient(rr, tr, axis=0)
        anchors.world_v[:] = np.stack([np.interp(times, tr, gradient[:, a]) for a in range(3)], axis=-1)
        anchors.r[has_r] -= (at[has_r] - times[has_r])[:, None] * anchors.world_v[has_r]
    anchors.r[0], anchors.C[0], anchors.world_v[0] = np.nan, np.nan, np.nan
    return anchors


#: Anchoring positions closer in time than this [s] are one instant to the velocity's finite differences:
#: two sensors' fixes stamped "at once" may differ by an ulp (1.5 and 1.4999999999999998), and their
#: difference over that ulp made a velocity of 1e15 m/s, and an IMU factor's covariance no longer positive
#: definite along it.
SAME_INSTANT = 1e-6


def _apart(t: np.ndarray, gap: float) -> np.ndarray:
    """Indices into the sorted times ``t`` of those at least ``gap`` after the one before them (the
    first always)."""
    return np.flatnonzero(np.concatenate([[True], np.diff(t) >= gap])) if len(t) else np.zeros(0, dtype=np.int64)


def _started_from(estimate: Trajectory, times: np.ndarray, dataset: Dataset) -> tuple[preintegration.Anchors, tuple]:
    """Anchors and per-interval biases that start the graph at ``estimate`` (an EKF's run over the
    same data): every keyframe is anchored at the estimate's position, attitude and velocity
    there -- its state where a keyframe is one of the estimate's times, else the prediction from
    its state before through the IMU (:func:`smoother.model.timeline.states_at`) -- and each
    interval is integrated around the biases at its start. A filter carries what every
    measurement so far implies -- a gyro bias, a heading -- which dead reckoning from the prior
    does not: the optimiser starts near the optimum."""
    held = np.clip(np.searchsorted(estimate.t, times + MATCH_TOLERANCE, side="right") - 1, 0, len(estimate.t) - 1)
    at = np.abs(estimate.t[held] - times) <= MATCH_TOLERANCE
    states = estimate.states[held]
    between = ~at & (times >= estimate.t[0])
    if between.any():
        predicted = states_at(replace(estimate, cov=None), dataset.imu, times[between], dataset.noise,
                              dataset.gravity).states
        for name in ("r", "v", "C", "b_f", "b_w"):
            getattr(states, name)[between] = getattr(predicted, name)
        at = at | between
    anchors = preintegration.Anchors.none(len(times))
    anchors.r[at], anchors.C[at], anchors.world_v[at] = states.r[at], states.C[at], states.world_velocity()[at]
    return anchors, (states.b_f[:-1], states.b_w[:-1])


#: Largest difference [s] between a keyframe's time and an estimate's for :func:`_started_from`
#: to take the estimate's state there.
MATCH_TOLERANCE = 1e-9


_SLOTS = {"rot": imu.PHI, "pos": imu.R, "vel": imu.V, "bias": slice(9, 15)}


def _place(jacobians: list[np.ndarray], variables: list[str]) -> np.ndarray:
    """Per-variable Jacobians (primer convention) -> one (..., d, 15) error-state Jacobian."""
    d = jacobians[0].shape[-2]
    out = np.zeros(jacobians[0].shape[:-2] + (d, imu.STATE_DIM))
    for J, name in zip(jacobians, variables):
        out[..., _SLOTS[name]] = J
    return out


def _imu_block(pre: preintegration.Preintegrated, gravity: np.ndarray, threshold: float) -> Block:
    def residual(slots, jacobians, rows):
        intervals = pre if isinstance(rows, slice) and rows == slice(None) else pre[rows]
        out = preintegration.residual(intervals, slots[0], slots[1], gravity, jacobians)
        return (out[0], list(out[1])) if jacobians else out

    def reintegrate(states):
        drift = np.max(np.abs(states.b_w[:-1] - pre.b_w_bar), axis=1)
        moved = np.flatnonzero(drift > threshold)
        if moved.size:
            pre.assign(moved, pre[moved].relinearized(states.b_w[moved]))

    n = len(pre)
    keyframes = np.stack([np.arange(n), np.arange(1, n + 1)], axis=1)
    return Block("imu", keyframes, residual, whitening(pre.cov), None, reintegrate)


def build_problem(dataset: Dataset, keyframe_rate=None, robust: dict | None = None,
                  reintegration_threshold: float = preintegration.REINTEGRATION_THRESHOLD,
                  start: Trajectory | None = None) -> Problem:
    """The factor graph of ``dataset`` (see the module docstring).

    ``keyframe_rate``: the keyframe grid [Hz], :data:`smoother.model.timeline.EVERY_MEASUREMENT`
    or None (chosen from the data; :func:`smoother.model.timeline.keyframe_rate`). ``robust`` maps
    a sensor's name (``Dataset.sensors``) to a kernel spec ``(name, threshold)`` from
    :func:`datasets.robust.robust_spec`. ``start``: an estimate of the run (an EKF's) to start
    from instead of dead reckoning (:func:`_started_from`).
    """
    times = keyframe_times(dataset, keyframe_rate)
    if len(times) < 2:
        raise InputError("the dataset spans less than one keyframe interval")
    keys = [keyframe_keys(k) for k in range(len(times))]
    steps = imu_steps(dataset.imu, times)
    acc, gyro, dt = steps.segments()
    # initial trajectory: dead reckoning from the initial state, reset by the measurements (or by
    # the estimate given); the IMU factors' covariances are evaluated along it (one call does both)
    anchors, biases = (_anchors(dataset, times), None) if start is None else _started_from(start, times, dataset)
    pre, initial_states = preintegration.integrate_with_covariance((acc, gyro, dt), dataset.initial, dataset.noise,
                                                                   dataset.gravity, anchors, biases)
    del acc, gyro, dt  # the intervals keep their own copies (pre.samples)

    blocks: list[Block] = [_imu_block(pre, dataset.gravity, reintegration_threshold)]
    prior = dataset.initial

    def prior_residual(slots, jacobians, rows):
        s = slots[0]
        out = priors.state_residual(s.C, s.r, s.v, np.concatenate([s.b_f, s.b_w], axis=-1), prior, jacobians)
        return (out[0], [_place(out[1], ["rot", "pos", "vel", "bias"])]) if jacobians else out

    blocks.append(Block("prior", np.zeros((1, 1), dtype=int), prior_residual, whitening(dataset.initial_cov[None])))
    measurements = []  # (block index, spec, keyframes, cov, kernel) of each measurement block
    calibrations = calibration_set(dataset)
    for block, spec, kernel in measurement_blocks(dataset, times, robust, calibrations, initial_states, steps,
                                                  pre.samples):
        blocks.append(block)
        measurements.append((len(blocks) - 1, spec, block.keyframes, spec.cov, kernel))
    if calibrations is not None:
        blocks.extend(calibration_prior_blocks(calibrations))

    # the rows of each measurement block by the keyframe at which they become available (their
    # latest, or the one after the keyframe they are attached to): rows order[bounds[k]:bounds[k + 1]],
    # ascending within a keyframe
    available = []
    for _, spec, kf, _, _ in measurements:
        latest = kf.max(axis=1) + (0 if spec.attached is None else spec.attached.attached)
        order = np.argsort(latest, kind="stable")
        available.append((order, np.searchsorted(latest[order], np.arange(len(times) + 1))))
    held = {}  # the IMU readings held at an attached sensor's stamps, made when first asked for
    # a drifting sensor's innovation weights (smoother.model.correlated), for a window's own factors
    taus = {spec.name: dataset.sensor(spec.name).correlation_time for _, spec, _, _, _ in measurements}
    drifting = {spec.name: innovation_weights(spec.name, spec.times[0], taus[spec.name])
                for _, spec, _, _, _ in measurements if taus[spec.name] is not None}

    def attached_at(spec, m: int):
        att = spec.attached
        if att is None or not att.attached[m]:
            return None
        if spec.name not in held:
            i = dataset.imu.held(spec.times[0])
            held[spec.name] = (dataset.imu.acc[i], dataset.imu.gyro[i])
        acc_h, gyro_h = held[spec.name]
        return AttachedAt(int(att.steps[m]), float(att.last_dt[m]), (acc_h[m], gyro_h[m]))

    def innovation(spec, m: int, kf) -> Innovation | None:
        """A drifting sensor's measurement ``m > 0`` as its innovation on the one before it."""
        if spec.name not in drifting or m == 0:
            return None
        phi, s = drifting[spec.name]
        return Innovation(spec, m - 1, int(kf[m - 1, 0]), attached_at(spec, m - 1), float(s[m] * phi[m]),
                          float(s[m]))

    def keyframe_factors(k: int) -> KeyframeFactors:
        """The GTSAM factors available at keyframe ``k`` (see :class:`Problem`)."""
        if k == 0:
            out = KeyframeFactors(None, [priors.state_prior_factor(keys[0], prior, dataset.initial_cov)], [(1, 0)], [0],
                                  (prior, dataset.initial_cov))
        else:
            imu_factor = ImuFactor(pre[k - 1], keys[k - 1], keys[k], dataset.gravity,
                                   reintegration_threshold=reintegration_threshold)
            out = KeyframeFactors(imu_factor, [imu_factor.factor], [(0, k - 1)], [k - 1])
        for (block, spec, kf, cov, kernel), (order, bounds) in zip(measurements, available):
            for m in order[bounds[k]:bounds[k + 1]]:
                where = attached_at(spec, int(m))
                model = noise_model(cov[m], kernel)
                if where is None:
                    factor = spec.factor([keys[j] for j in kf[m]], int(m), model)
                else:
                    j = int(kf[m, 0])
                    factor = attached_factor(KINDS[spec.kind], keys[j], tuple(a[j] for a in pre.samples), where,
                                             spec.rows[m], model, dataset.gravity)
                out.factors.append(factor)
                out.rows.append((block, int(m)))
                out.oldest.append(int(kf[m].min()))
                out.measurements.append((spec, int(m), [int(j) for j in kf[m]], kernel, where,
                                         innovation(spec, int(m), kf)))
        return out

    absolute = frozenset(s.name for s in sensors_of(dataset) if KINDS[s.kind].absolute)
    return Problem(times, keys, initial_states, blocks, keyframe_factors, dataset.gravity, absolute=absolute,
                   calibration=calibrations, keyframes=keyframe_record(dataset, keyframe_rate, times))


def attached_factor(kind, keys: KeyframeKeys, samples: tuple, where: AttachedAt, row: np.ndarray, noise,
                    gravity) -> gtsam.CustomFactor:
    """A GTSAM factor of one measurement ``row`` of ``kind`` attached to the keyframe ``keys``
    (:func:`datasets.kinds.attached_rows`), ``where`` in the keyframe's interval of samples
    ``samples = (acc, gyro (K, 3), dt (K,))``: its keys are every variable of the keyframe (the
    prediction to its time reads them all)."""
    padded = tuple(np.ascontiguousarray(a, dtype=float)[None] for a in samples)
    at = ([0], [where.steps], [where.last_dt])
    row = np.ascontiguousarray(row, dtype=float)[None]

    def residual(C, r, v, b, jacobians):
        state = imu.ImuState(r[None], v[None], C[None], b[None, :3], b[None, 3:])
        e, H, _ = attached_rows(kind, state, padded, *at, row, gravity=gravity, jacobians=jacobians)
        if not jacobians:
            return e[0]
        return e[0], [H[0][:, imu.PHI], H[0][:, imu.R], H[0][:, imu.V], H[0][:, 9:15]]

    return custom_factor(noise, keys.all(), [ROT, VEC, VEC, BIAS], residual)


def calibration_set(dataset: Dataset) -> calibration.CalibrationSet | None:
    """The calibration variables of the sensors of ``dataset`` that ask for them
    (:attr:`datasets.types.Sensor.calibrate`), starting at the values given (their data's
    ``T_BS``, no further time offset, scale 1), or None. A part the sensor's kind cannot estimate
    (:func:`factors.calibration.applicable`) is refused, naming the sensor."""
    asking = [s for s in sensors_of(dataset) if s.calibrate is not None]
    if not asking:
        return None
    priors = [calibration.checked_prior(s.calibrate, s.kind, KINDS[s.kind].model,
                                        f"sensor {s.name!r} (kind {s.kind}): calibrate") for s in asking]
    return calibration.CalibrationSet.given([s.name for s in asking], [s.data.T_BS for s in asking], priors)


def calibration_prior_blocks(calibrations: calibration.CalibrationSet) -> list[Block]:
    """One block per calibration variable: its prior (:func:`factors.calibration.prior_residual`)."""
    out = []
    for j, (name, prior, mean) in enumerate(zip(calibrations.names, calibrations.priors, calibrations.means)):
        def residual(slots, jacobians, rows, c, prior=prior, mean=mean):
            e, J = calibration.prior_residual(c, mean, prior.columns)
            return (e[None], [J[None]]) if jacobians else e[None]

        whiten = np.diag(1.0 / prior.sigmas)[None]
        out.append(Block(f"calibration prior {name}", np.zeros((1, 0), dtype=int), residual, whiten, calibration=j))
    return out


def measurement_blocks(dataset: Dataset, times: np.ndarray, robust: dict | None = None,
                       calibrations: calibration.CalibrationSet | None = None,
                       reference: imu.ImuState | None = None, steps: Steps | None = None,
                       samples: tuple | None = None) -> list[tuple]:
    """``(Block, MeasurementSpec, kernel spec or None)`` of each sensor of ``dataset`` on the
    keyframes ``times``: the measurement factors of :func:`build_problem`, without the IMU's. A
    measurement at a keyframe's time reads it; one after it (a one-state kind) is attached to it
    (:attr:`MeasurementSpec.attached`, :func:`attached_residual`), its covariance grown by the
    process noise between them (:func:`attached_covariance`, along the ``reference`` keyframe
    states; needed only when a measurement is attached). A relative sensor's consecutive
    measurements between keyframes are composed into one
    (:func:`smoother.model.timeline.relative_on_keyframes`), whose ends must be keyframes. A
    sensor among ``calibrations``' names reads its calibration variable
    (:func:`calibrated_residual`); the others, and every sensor without ``calibrations``, use the
    values given. ``steps`` and ``samples``: the IMU stream cut at ``times``
    (:func:`smoother.model.timeline.imu_steps`) and its padded intervals (:meth:`Steps.segments`),
    made here when not given."""
    robust = robust or {}
    out = []
    names = () if calibrations is None else calibrations.names
    dataset = relative_on_keyframes(dataset, times)
    if steps is None:
        steps = imu_steps(dataset.imu, times)
    for sensor, spec in zip(sensors_of(dataset), _measurement_specs(dataset)):
        kind = KINDS[sensor.kind]
        if kind.relative:
            kf = np.stack([_match(times, t) for t in spec.times], axis=1)
            placed = np.all(kf >= 0, axis=1)
            if not placed.all():  # both ends are keyframes (timeline.keyframe_times): a defect if not
                raise InputError(f"sensor {spec.name!r}: {int((~placed).sum())} of {len(placed)} relative "
                                 "measurements fall on no keyframe")
        else:
            att = attachment(steps, times, spec.times[0])
            kf = att.keyframe[:, None]
            if att.attached.any():
                if samples is None:
                    samples = steps.segments()
                if reference is None:
                    raise InputError(f"sensor {spec.name!r}: measurements attached to keyframes need the reference "
                                     "keyframe states their process noise is evaluated along")
                spec = replace(spec, cov=attached_covariance(kind, spec, att, samples, reference, dataset.noise,
                                                             dataset.gravity), attached=att)
        kernel = robust.get(spec.name)
        estimator = robust_estimator(kernel, spec.cov.shape[-1])
        prior = calibrations.priors[names.index(spec.name)] if spec.name in names else None
        if spec.attached is not None:
            residual = attached_residual(sensor, spec, dataset, samples, prior)
        elif prior is not None:
            residual = calibrated_residual(sensor, spec, dataset, prior)
        else:
            residual = spec.residual
        j = names.index(spec.name) if prior is not None else None
        out.append((Block(spec.name, kf, residual, whitening(spec.cov), estimator, calibration=j), spec, kernel))
    return out


def attached_covariance(kind, spec: "MeasurementSpec", att: Attachment, samples: tuple, reference: imu.ImuState,
                        noise: imu.ImuNoise, gravity) -> np.ndarray:
    """The covariances of ``spec``'s measurements with those attached to a keyframe (``att``)
    grown by the process noise between the keyframe and their time: ``R + H S_w H^T``
    (:func:`datasets.kinds.attached_noise`), ``S_w`` the covariance of the state predicted from
    keyframe ``k`` to the measurement's time, the EKF's own growth ``F S F^T + G Q_d G^T`` from
    zero along the prediction from ``reference[k]``, and ``H`` the model's Jacobian at the
    predicted state: the covariance of the measurement's error given the keyframe's state,
    ``H (x_m [-] f(x_k)) + n``, to first order. What it leaves out (``docs/design.md``,
    keyframes): the correlation of that process noise with the IMU factor from keyframe ``k``
    (the same samples) and with the other measurements attached to ``k``."""
    cov = np.array(spec.cov, dtype=float, copy=True)
    which = np.flatnonzero(att.attached)
    k = att.keyframe[which]
    cov[which] += attached_noise(kind, reference[k], samples, k, att.steps[which], att.last_dt[which],
                                 spec.rows[which], noise, gravity)
    return cov


def attached_residual(sensor, spec: "MeasurementSpec", dataset: Dataset, samples: tuple,
                      prior: calibration.CalibrationPrior | None):
    """The block residual of ``sensor``'s measurements, some attached to the keyframe before them
    (``spec.attached``; :func:`datasets.kinds.attached_rows` through the padded IMU intervals
    ``samples``), the others at their keyframe's time (the model's own residual): Jacobians of the
    slot's state, then, through its calibration variable where ``prior`` is given (the IMU reading
    held at each stamp where the time offset is estimated), of the estimated calibration
    coordinates (:func:`calibrated_residual`'s)."""
    kind, att = KINDS[sensor.kind], spec.attached
    at_keyframe = calibrated_residual(sensor, spec, dataset, prior) if prior is not None else spec.residual
    readings = None
    if prior is not None and "time_offset" in prior.parts:
        i = dataset.imu.held(spec.times[0])
        readings = (dataset.imu.acc[i], dataset.imu.gyro[i])

    def residual(slots, jacobians, which, c=None):
        index = np.arange(len(att.keyframe))[which]
        on = ~att.attached[index]
        e = np.empty((len(index), kind.dim))
        parts = [np.empty((len(index), kind.dim, imu.STATE_DIM))]
        if prior is not None:
            parts.append(np.empty((len(index), kind.dim, len(prior.columns))))
        if on.any():
            args = ([slots[0][on]], jacobians, index[on]) + (() if prior is None else (c,))
            out = at_keyframe(*args)
            if jacobians:
                e[on] = out[0]
                for part, J in zip(parts, out[1]):
                    part[on] = J
            else:
                e[on] = out
        off = ~on
        if off.any():
            m = index[off]
            e_a, H_a, Hc_a = attached_rows(kind, slots[0][off], samples, att.keyframe[m], att.steps[m], att.last_dt[m],
                                           spec.rows[m], c, None if readings is None else tuple(a[m] for a in readings),
                                           dataset.gravity, jacobians)
            e[off] = e_a
            if jacobians:
                parts[0][off] = H_a
                if prior is not None:
                    parts[1][off] = Hc_a[:, :, prior.columns]
        return (e, parts) if jacobians else e

    return residual


def calibrated_residual(sensor, spec: "MeasurementSpec", dataset: Dataset, prior: calibration.CalibrationPrior):
    """The block residual of ``sensor``'s measurements through its calibration variable
    (:func:`datasets.kinds.calibrated_rows`): Jacobians of the slots' states, then of the
    estimated calibration coordinates. With a time offset among them, the IMU reading held at each
    measurement's stamp(s) enters (:meth:`datasets.types.ImuSamples.held`)."""
    kind = KINDS[sensor.kind]
    cols = prior.columns
    readings = None
    if "time_offset" in prior.parts:
        held = [dataset.imu.held(t) for t in spec.times]
        readings = [(dataset.imu.acc[k], dataset.imu.gyro[k]) for k in held]

    def residual(slots, jacobians, which, c):
        at = None if readings is None else [(acc[which], gyro[which]) for acc, gyro in readings]
        states = tuple(slots) if kind.relative else slots[0]
        e, H, H_c = calibrated_rows(kind, states, spec.rows[which], c,
                                    None if at is None else (tuple(at) if kind.relative else at[0]), dataset.gravity,
                                    jacobians)
        if not jacobians:
            return e
        parts = [H[:, :, :imu.STATE_DIM], H[:, :, imu.STATE_DIM:]] if kind.relative else [H]
        return e, [*parts, H_c[:, :, cols]]

    return residual


def _whole_graph(problem: Problem) -> GtsamGraph:
    """All of ``problem``'s GTSAM factors in one graph, with initial values from
    ``problem.initial_states`` at the time of the call (so a copy of the problem with other
    initial states gets its own)."""
    groups = [problem.keyframe_factors(k) for k in range(len(problem.times))]
    graph = gtsam.NonlinearFactorGraph()
    for group in groups:
        for f in group.factors:
            graph.add(f)
    values = gtsam.Values()
    for k, kk in enumerate(problem.keys):
        insert_state(values, kk, problem.initial_states[k])
    rows_of = {id(f): where for group in groups for f, where in zip(group.factors, group.rows)}
    return GtsamGraph(graph, values, [group.imu for group in groups[1:]], [group.factors for group in groups], rows_of)

#: :attr:`MeasurementSpec.model` of a relative pose (odometry: :func:`factors.sensor_models.odometry_kernel`)
RELATIVE_MODEL = -1


@dataclass
class MeasurementSpec:
    """One sensor's measurements as the graph needs them: ``times`` of the keyframes each
    measurement connects (one array per keyframe it reads), the block ``residual(slots,
    jacobians, rows)`` (:class:`smoother.model.blocks.Block`), covariances, and ``factor(keys, m,
    noise_model)`` making the GTSAM factor of measurement ``m``."""

    name: str
    times: list[np.ndarray]
    residual: Callable
    cov: np.ndarray
    factor: Callable
    #: the model's index in :data:`datasets.kinds.MODELS` (:data:`RELATIVE_MODEL` for odometry)
    #: and the measurements' packed rows, as the compiled kernels take them
    model: int = -1
    rows: np.ndarray | None = None
    #: the sensor's kind (a name of :data:`datasets.kinds.KINDS`)
    kind: str = ""
    #: where the measurements sit among a problem's keyframes when some are attached to the
    #: keyframe before them (:func:`measurement_blocks`; ``cov`` then includes the process noise
    #: between them), else None
    attached: Attachment | None = None


def measurement_spec(sensor) -> MeasurementSpec:
    """The measurements of one :class:`datasets.types.Sensor` through its kind's model."""
    return (_relative_spec if KINDS[sensor.kind].relative else _absolute_spec)(sensor)


def _measurement_specs(dataset: Dataset) -> list[MeasurementSpec]:
    """Each sensor of ``dataset`` (:func:`datasets.kinds.sensors_of`) through its kind's model."""
    return [measurement_spec(s) for s in sensors_of(dataset)]


def _absolute_spec(sensor) -> MeasurementSpec:
    kind, m = KINDS[sensor.kind], sensor.data
    rows = kind.pack(m)

    def residual(slots, jacobians, which):
        e, H = measure_rows(kind, slots[0], rows[which])
        return (e, [H]) if jacobians else e

    return MeasurementSpec(sensor.name, [m.t], residual, m.cov,
                           lambda kk, i, model: sensor_factor(kind.model, kk[0], rows[i], model),
                           model_index(kind), rows, sensor.kind)


def _relative_spec(sensor) -> MeasurementSpec:
    m = sensor.data

    def residual(slots, jacobians, which):
        a, b = slots
        out = odometry_residual(a.C, a.r, b.C, b.r, m.dr[which], m.dC[which], m.T_BS, jacobians)
        if not jacobians:
            return out
        e, (J_Ci, J_ri, J_Cj, J_rj) = out
        return e, [_place([J_Ci, J_ri], ["rot", "pos"]), _place([J_Cj, J_rj], ["rot", "pos"])]

    return MeasurementSpec(sensor.name, [m.t_from, m.t_to], residual, m.cov,
                           lambda kk, i, model: odometry_factor(kk[0], kk[1], m.dr[i], m.dC[i], m.T_BS, model),
                           RELATIVE_MODEL, pack_odometry(m.dr, m.dC, m.T_BS), sensor.kind)
