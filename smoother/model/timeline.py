"""The IMU stream cut at knot times (keyframes, measurements) into Euler-forward steps, and
where the estimators keep states.

IMU sample ``k`` is held over ``[t_k, t_{k+1})`` (zero-order hold, the primer's Euler-forward
step). A knot strictly inside such an interval splits it into two steps with the same sample, so
an estimator can stop exactly at the knot. The last IMU sample only marks the end of the stream.

States. The EKF updates at every measurement time (:func:`measurement_knots`) and keeps its state
there, or, in a run beside the smoothers, at their keyframes alone. The smoothers keep
keyframes (:func:`keyframe_times`): on a grid of a rate the motion needs, not at every measurement
time (``docs/design.md``, keyframes); a measurement between two keyframes is attached to the one
before it (:func:`attachment`): its state is predicted through the IMU's Euler steps from the
keyframe to the measurement's time.
"""
from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

from datasets.kinds import KINDS, sensors_of
from datasets.types import Dataset, ImuSamples, Trajectory
from factors.errors import InputError
from factors.imu import DEFAULT_GRAVITY, ImuNoise, ImuState, propagate_steps, transition_steps


@dataclass(frozen=True)
class Steps:
    """Euler steps: ``acc, gyro (S, 3)``, ``dt (S,)``, start times ``t (S,)``, and for each knot
    the number of steps taken before reaching it, ``knot_step (K,)``."""

    acc: np.ndarray
    gyro: np.ndarray
    dt: np.ndarray
    t: np.ndarray
    knot_step: np.ndarray

    def segments(self):
        """The steps between consecutive knots, padded: ``acc, gyro (J, L, 3)``, ``dt (J, L)``
        with ``J = K - 1`` and padding steps of ``dt = 0`` (the identity step)."""
        starts, stops = self.knot_step[:-1], self.knot_step[1:]
        lengths = stops - starts
        L = max(int(lengths.max(initial=0)), 1)
        valid = np.arange(L)[None, :] < lengths[:, None]
        steps = np.arange(starts[0], stops[-1]) if len(starts) else np.zeros(0, dtype=int)  # in order, as valid's
        dt, acc, gyro = np.zeros(valid.shape), np.zeros(valid.shape + (3,)), np.zeros(valid.shape + (3,))
        dt[valid], acc[valid], gyro[valid] = self.dt[steps], self.acc[steps], self.gyro[steps]  # no padded temporaries
        return acc, gyro, dt


def imu_steps(imu: ImuSamples, knots: np.ndarray) -> Steps:
    """Cut the IMU stream at ``knots`` (sorted, within ``[imu.t[0], imu.t[-1]]``)."""
    knots = np.asarray(knots, dtype=float)
    if not np.all(np.isfinite(knots)):  # a NaN passes every comparison below and yields NaN steps
        raise InputError(f"knot times must be finite, got {knots[~np.isfinite(knots)][:3]}")
    if knots.size and (knots[0] < imu.t[0] or knots[-1] > imu.t[-1]):
        raise InputError(
            f"knot times [{knots[0]}, {knots[-1]}] outside the IMU span [{imu.t[0]}, {imu.t[-1]}]"
        )
    if np.any(np.diff(knots) <= 0):
        raise InputError("knot times must increase strictly")
    return steps_between(imu.t, imu.acc, imu.gyro, knots)


def steps_between(t: np.ndarray, acc: np.ndarray, gyro: np.ndarray, knots) -> Steps:
    """:func:`imu_steps` of the samples ``t (N,)``, ``acc, gyro (N, 3)`` (checked by the caller:
    increasing times; ``knots`` increasing, finite, within ``[t[0], t[-1]]``)."""
    bounds = np.union1d(t, knots)
    starts = bounds[:-1]
    sample = np.searchsorted(t, starts, side="right") - 1
    return Steps(
        acc=acc[sample],
        gyro=gyro[sample],
        dt=np.diff(bounds),
        t=starts,
        knot_step=np.searchsorted(bounds, knots),
    )


def interval_steps(t: np.ndarray, acc: np.ndarray, gyro: np.ndarray, t_from: float, t_to: float) -> tuple:
    """The steps of :func:`steps_between` ``(t, acc, gyro, [t_from, t_to])`` from its first knot to its
    second, bit for bit, as ``(acc, gyro, dt)`` (``acc``, ``gyro`` views of the samples'), without
    its sort: one interval of an online smoother, at every keyframe. ``t[0] <= t_from < t_to``,
    the samples checked by the caller."""
    first = int(np.searchsorted(t, t_from, side="right")) - 1  # the sample held at t_from
    stop = int(np.searchsorted(t, t_to, side="left"))  # the samples before t_to
    bounds = np.empty(stop - first + 1)
    bounds[0], bounds[1:-1], bounds[-1] = t_from, t[first + 1:stop], t_to
    return acc[first:stop], gyro[first:stop], np.diff(bounds)


#: The default keyframe grid [Hz] where the measurements come faster (:func:`keyframe_rate`).
KEYFRAME_RATE = 10.0
#: The ``keyframe_rate`` that asks for a keyframe at every measurement time (no grid, nothing
#: attached), as the EKF keeps its states.
EVERY_MEASUREMENT = "measurements"


def measurement_knots(dataset: Dataset) -> np.ndarray:
    """Every measurement time of every sensor (both ends of a relative one), the times of
    held-out measurements (only their times: an evaluation wants estimates there; those a
    correlation time's fit used too, :attr:`datasets.types.Sensor.tuned`) and the start and end of
    the IMU data, within the IMU span: where the EKF keeps a state, and the keyframes of
    ``keyframe_rate=EVERY_MEASUREMENT``."""
    parts = [dataset.measurement_times(), [dataset.t0, dataset.t1]]
    parts += [part.t for s in dataset.sensors for part in (s.heldout, s.tuned) if part is not None]
    times = np.unique(np.concatenate([np.asarray(p, dtype=float) for p in parts]))
    return times[(times >= dataset.t0) & (times <= dataset.t1)]


def keyframe_rate(dataset: Dataset, rate=None) -> float | None:
    """The rate [Hz] of ``dataset``'s keyframe grid, or None for a keyframe at every measurement
    time: ``rate`` given as a number; None for :data:`EVERY_MEASUREMENT`; when ``rate`` is None,
    chosen from the data -- :data:`KEYFRAME_RATE` where the measurement times come faster than
    that on average (their number less one over their span), else None (the measurement times
    themselves are then no denser than the grid: each keeps its keyframe)."""
    if isinstance(rate, str):
        if rate != EVERY_MEASUREMENT:
            raise InputError(f"keyframe_rate: expected a rate [Hz], {EVERY_MEASUREMENT!r} or None, got {rate!r}")
        return None
    if rate is not None:
        if not (np.isfinite(rate) and rate > 0):
            raise InputError(f"keyframe_rate: expected a positive finite rate [Hz], got {rate!r}")
        return float(rate)
    measured = dataset.measurement_times()
    span = measured[-1] - measured[0] if len(measured) > 1 else 0.0
    return KEYFRAME_RATE if span > 0 and (len(measured) - 1) / span > KEYFRAME_RATE * (1 + 1e-9) else None


def keyframe_times(dataset: Dataset, rate=None) -> np.ndarray:
    """The smoothers' keyframes: with the grid of :func:`keyframe_rate` (``rate``), the grid
    ``t0 + k / rate``, the ends of the relative measurements composed onto the grid
    (:func:`relative_anchors`, in place of the grid inside a span composed of several, so that it
    joins consecutive keyframes) and the start and end of the IMU data; without one,
    :func:`measurement_knots`.
    Every other measurement is attached to the keyframe at or before its time (:func:`attachment`),
    and a held-out one is predicted from it the same way (:func:`states_at`): holding measurements
    out of a fast sensor (``every``) adds no keyframes.

    Grid times are correctly rounded (``t0 + k / rate``, like the measurement ticks; arange's
    accumulated ``k * step`` differs by an ulp, e.g. 0.30000000000000004 beside a measurement at
    0.3, which would then be attached 5e-17 s from its keyframe), and none lies within half an IMU
    step of another keyframe time: a near-duplicate keyframe makes an IMU interval of ~1e-16 s
    whose factor has a ~0 covariance, and the system becomes indeterminant."""
    grid_rate = keyframe_rate(dataset, rate)
    if grid_rate is None:
        return bounded_intervals(measurement_knots(dataset), dataset.imu.t)
    parts = [[dataset.t0, dataset.t1]]
    relative = [s.data for s in sensors_of(dataset) if KINDS[s.kind].relative]
    anchors = [relative_anchors(d.t_from, d.t_to, grid_rate) for d in relative]
    others = np.unique(np.concatenate([np.asarray(p, dtype=float) for p in parts + anchors]))
    grid = dataset.t0 + np.arange(len(np.arange(dataset.t0, dataset.t1, 1.0 / grid_rate))) / grid_rate
    for d, at in zip(relative, anchors):  # inside a span composed of several, its anchors are the grid
        spans = relative_spans(d.t_from, d.t_to, at)
        spans = spans[spans[:, 1] - spans[:, 0] > 1]
        if len(spans):
            start, end = d.t_from[spans[:, 0]], d.t_to[spans[:, 1] - 1]
            j = np.maximum(np.searchsorted(start, grid, side="right") - 1, 0)
            grid = grid[(grid <= start[j]) | (grid >= end[j])]
    i = np.searchsorted(others, grid)
    gap = np.minimum(np.abs(grid - others[np.maximum(i - 1, 0)]), np.abs(others[np.minimum(i, len(others) - 1)] - grid))
    grid = grid[gap >= 0.5 * float(np.median(np.diff(dataset.imu.t)))]
    times = np.union1d(others, grid)
    return bounded_intervals(times[(times >= dataset.t0) & (times <= dataset.t1)], dataset.imu.t)


def relative_chains(t_from: np.ndarray, t_to: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``(lo, hi)``: the chains ``[lo, hi)`` of a relative sensor's measurements, each beginning
    where the one before it ended."""
    breaks = np.flatnonzero(np.asarray(t_from)[1:] != np.asarray(t_to)[:-1]) + 1
    return np.concatenate([[0], breaks]), np.concatenate([breaks, [len(t_to)]])


def relative_anchors(t_from: np.ndarray, t_to: np.ndarray, rate: float) -> np.ndarray:
    """The ends of a relative sensor's measurements ``(t_from, t_to)`` that are keyframes on a grid
    of ``rate`` [Hz]: every chain's start and end (a chain: measurements each beginning where the
    one before it ended) and, within a chain, the last end at or before each multiple of
    ``1 / rate`` from its start. The measurements between two of them are composed into one
    (:func:`relative_on_keyframes`), so a relative sensor faster than the grid adds no keyframes
    of its own; the ends of measurements composed so are their own anchors again."""
    t_from, t_to = np.asarray(t_from, dtype=float), np.asarray(t_to, dtype=float)
    n = len(t_to)
    if not n:
        return np.zeros(0)
    first, _ = relative_chains(t_from, t_to)
    chain = np.cumsum(np.isin(np.arange(n), first)) - 1
    tick = np.ceil((t_to - t_from[first][chain]) * rate * (1 - 1e-9))  # the grid tick each end has reached
    closes = np.concatenate([(tick[1:] != tick[:-1]) | (chain[1:] != chain[:-1]), [True]])
    return np.union1d(t_from[first], t_to[closes])


def relative_spans(t_from: np.ndarray, t_to: np.ndarray, times: np.ndarray) -> np.ndarray:
    """``(S, 2)``: the spans ``[lo, hi)`` of consecutive relative measurements between keyframes
    ``times``: a span ends at a measurement whose end is a keyframe or that the next does not
    continue (it begins elsewhere), and at the last."""
    closes = np.isin(np.asarray(t_to, dtype=float), times)
    closes[relative_chains(t_from, t_to)[1] - 1] = True
    hi = np.flatnonzero(closes) + 1
    return np.stack([np.concatenate([[0], hi[:-1]]), hi], axis=1)


def relative_on_keyframes(dataset: Dataset, times: np.ndarray) -> Dataset:
    """``dataset`` with each relative sensor's consecutive measurements between keyframes
    ``times`` composed into one (:func:`relative_spans`, the kind's ``compose``): what the
    smoothers' factors and their verdicts read. The dataset itself where every end is a keyframe."""
    sensors, changed = [], False
    for sensor in dataset.sensors:
        kind = KINDS[sensor.kind]
        if kind.relative and sensor.data is not None and len(sensor.data.t_to):
            spans = relative_spans(sensor.data.t_from, sensor.data.t_to, times)
            if len(spans) < len(sensor.data.t_to):
                sensor, changed = replace(sensor, data=kind.compose(sensor.data, spans)), True
        sensors.append(sensor)
    return replace(dataset, sensors=tuple(sensors)) if changed else dataset


#: The longest keyframe interval, in IMU steps, as a multiple of the mean interval's, where the
#: intervals' padded steps would exceed :data:`PADDED_STEPS` (:func:`bounded_intervals`).
LONGEST_INTERVAL = 2
#: The padded steps (keyframe intervals times the longest one's IMU steps) left as they are, or
#: five times the IMU's steps if more: some 120 MB of the steps' readings and durations.
PADDED_STEPS = 1 << 21


def bounded_intervals(times: np.ndarray, imu_t: np.ndarray) -> np.ndarray:
    """``times`` (keyframes, sorted), with keyframes added, evenly, inside every interval of more
    than :data:`LONGEST_INTERVAL` times the mean number of IMU steps when the intervals' steps
    padded to the longest one exceed ``max(PADDED_STEPS, 5 * IMU steps)``. The estimators hold
    the intervals' steps so padded (:meth:`Steps.segments`), and one long interval -- a GNSS
    outage of minutes, IMU data long after the last fix -- made memory of the number of keyframes
    times its length: a 13-minute outage of a 2 Hz GNSS-only rig asked for 861 MiB at a time, and
    its batch failed in 4 GB. Cut so, the padded steps are at most about five times the IMU's;
    a short gap in a short run is left alone, and every keyframe given stays one."""
    times = np.asarray(times, dtype=float)
    if len(times) < 2:
        return times
    steps = np.diff(np.searchsorted(imu_t, times))  # IMU samples starting in each interval
    n = int(steps.sum())
    if len(steps) * int(steps.max()) <= max(PADDED_STEPS, 5 * n):
        return times
    longest = max(1, int(np.ceil(LONGEST_INTERVAL * n / len(steps))))
    long = np.flatnonzero(steps > longest)
    added = [np.linspace(times[j], times[j + 1], int(np.ceil(steps[j] / longest)) + 1)[1:-1] for j in long]
    return np.union1d(times, np.concatenate(added))


@dataclass(frozen=True)
class Attachment:
    """Where measurements at times ``t (M,)`` sit among keyframes (:func:`attachment`): the
    keyframe at or before each, ``keyframe (M,)``; whether it lies strictly after it,
    ``attached (M,)`` (False: it is at its keyframe's own time); and for an attached one the
    Euler steps from the keyframe to its time: the first ``steps (M,)`` steps of the keyframe's
    interval (:class:`Steps`), the last of them cut to ``last_dt (M,)`` (both 0 where not
    attached); ``distance (M,)``: how far each lies after its keyframe [s]."""

    keyframe: np.ndarray
    attached: np.ndarray
    steps: np.ndarray
    last_dt: np.ndarray
    distance: np.ndarray


def attachment(steps: Steps, times: np.ndarray, t: np.ndarray) -> Attachment:
    """The :class:`Attachment` of measurements at ``t`` among the keyframes ``times`` whose IMU
    stream was cut into ``steps`` (:func:`imu_steps` at ``times``). A time before the first
    keyframe or after the last is an InputError."""
    t = np.asarray(t, dtype=float)
    keyframe, distance = keyframe_before(times, t)
    attached = distance > 0
    step = np.searchsorted(steps.t, t, side="left") - 1  # the step that holds t (its start before t)
    count = np.where(attached, step - steps.knot_step[keyframe] + 1, 0)
    last_dt = np.where(attached, t - steps.t[np.maximum(step, 0)], 0.0)
    return Attachment(keyframe, attached, count, last_dt, distance)


def keyframe_before(times: np.ndarray, t: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``(keyframe, distance)``: the index of the keyframe at or before each time ``t`` among the
    keyframes ``times``, and how far ``t`` lies after it [s] (0 at its own time). A time before the
    first keyframe or after the last is an InputError."""
    t = np.asarray(t, dtype=float)
    if t.size and (t.min() < times[0] or t.max() > times[-1]):
        raise InputError(f"measurement times [{t.min()}, {t.max()}] outside the keyframes' span "
                         f"[{times[0]}, {times[-1]}]")
    keyframe = np.searchsorted(times, t, side="right") - 1
    return keyframe, t - times[keyframe]


def keyframe_record(dataset: Dataset, rate=None, times: np.ndarray | None = None) -> dict:
    """What a run reports of its smoothers' keyframes (``metrics.json``'s ``_run.keyframes``):
    their ``count``; ``rate_hz``, the grid's rate (:func:`keyframe_rate` of ``rate``) or
    :data:`EVERY_MEASUREMENT`; of the ``measurements`` of one state (a relative measurement's ends
    are keyframes), how many are ``attached`` to the keyframe before them, and the furthest of them
    from its keyframe, ``max_attached_distance_s``; of the ``relative`` measurements, how many
    there are ``composed`` into how many between keyframes (:func:`relative_on_keyframes`).
    ``times``: :func:`keyframe_times` of ``dataset`` and ``rate``, made here when not given."""
    grid = keyframe_rate(dataset, rate)
    times = keyframe_times(dataset, rate) if times is None else times
    stamps = [s.data.t for s in sensors_of(dataset) if not KINDS[s.kind].relative]
    _, distance = keyframe_before(times, np.concatenate(stamps) if stamps else np.zeros(0))
    relative = [s.data for s in sensors_of(dataset) if KINDS[s.kind].relative]
    return {"count": int(len(times)), "rate_hz": EVERY_MEASUREMENT if grid is None else grid,
            "measurements": int(len(distance)), "attached": int(np.count_nonzero(distance > 0)),
            "max_attached_distance_s": float(distance.max(initial=0.0)),
            "relative": int(sum(len(d.t_to) for d in relative)),
            "composed": int(sum(len(relative_spans(d.t_from, d.t_to, times)) for d in relative))}


def interval_attachment(t: np.ndarray, t_from: float, t_to: float, stamps) -> tuple[np.ndarray, np.ndarray]:
    """``(steps, last_dt)`` of measurements at ``stamps`` in ``(t_from, t_to)`` among the steps of
    :func:`interval_steps` ``(t, ..., t_from, t_to)``: each after the first ``steps`` of them, the
    last cut to ``last_dt`` -- what :func:`attachment` gives for one interval, without the whole
    stream's steps (an online smoother's keyframe)."""
    first = int(np.searchsorted(t, t_from, side="right")) - 1
    stop = int(np.searchsorted(t, t_to, side="left"))
    starts = np.concatenate([[t_from], t[first + 1:stop]])
    stamps = np.asarray(stamps, dtype=float)
    steps = np.searchsorted(starts, stamps, side="left")
    return steps, stamps - starts[steps - 1]


#: Queries :func:`states_at` propagates at once, at most (their padded steps are a few MB), and
#: the most padded steps (queries times the longest one's steps) it takes at once: a query far
#: from the state it is predicted from (keyframes inside an EKF's long gap without measurements:
#: a 13-minute outage gives some 100 queries of 150 000 steps each) would need 370 MiB per array.
STATES_CHUNK = 8192
STATES_PADDED = 1 << 20


def _chunks(count: np.ndarray) -> list[slice]:
    """Consecutive slices of the queries whose steps ``count`` padded to the longest in each are at
    most :data:`STATES_PADDED` (a query longer than that alone) and at most :data:`STATES_CHUNK`
    queries."""
    out, lo, longest = [], 0, 0
    for i, c in enumerate(np.maximum(np.asarray(count, dtype=np.int64), 1)):
        longest = max(longest, int(c))
        if i > lo and ((i + 1 - lo) * longest > STATES_PADDED or i - lo >= STATES_CHUNK):
            out.append(slice(lo, i))
            lo, longest = i, int(c)
    if len(count):
        out.append(slice(lo, len(count)))
    return out


def carry(states: ImuState, imu: ImuSamples, t_from, t_to, noise: ImuNoise, gravity=DEFAULT_GRAVITY, cov=None,
          transition: bool = False) -> tuple:
    """``(states, cov, Phi)``: ``states (M,)`` at times ``t_from (M,)`` carried to ``t_to (M,)``
    (each at or after its own, all within the IMU span) through the IMU's Euler steps -- each
    sample held over its interval, the first step from ``t_from`` and the last cut at ``t_to``,
    as an attached measurement is predicted (:func:`attachment`), so that each row is independent
    of the others -- with the EKF's prediction of the covariance ``cov (M, 15, 15)``,
    ``P <- F P F^T + G Q_d G^T`` (:func:`factors.imu.propagate_steps`), from zero where ``cov`` is
    None (then the process noise ``S`` of the steps); with ``transition`` the steps' error-state
    transition ``Phi (M, 15, 15)`` (:func:`factors.imu.transition_steps`), else None. In chunks of
    padded steps (:data:`STATES_CHUNK`, :data:`STATES_PADDED`)."""
    t_from, t_to = np.asarray(t_from, dtype=float), np.asarray(t_to, dtype=float)
    t = imu.t
    first = np.searchsorted(t, t_from, side="right")  # the first sample after t_from ...
    count = np.maximum(np.searchsorted(t, t_to, side="left") - first + 1, 0)  # ... and the steps to t_to
    last = len(t) - 1
    parts, covs, transitions = [], [], []
    for sl in _chunks(count):
        j = np.arange(max(1, int(count[sl].max(initial=1))))[None, :]
        sample = np.minimum(first[sl, None] - 1 + j, last)  # the sample held over step j
        valid = j < count[sl, None]
        begin = np.where(j == 0, t_from[sl, None], t[sample])
        end = np.where(j == count[sl, None] - 1, t_to[sl, None], t[np.minimum(sample + 1, last)])
        dt = np.where(valid, end - begin, 0.0)
        acc = np.where(valid[..., None], imu.acc[sample], 0.0)
        gyro = np.where(valid[..., None], imu.gyro[sample], 0.0)
        if transition:
            transitions.append(transition_steps(states[sl], acc, gyro, dt, gravity)[1])
        P0 = np.zeros((len(dt), 15, 15)) if cov is None else cov[sl]
        state, P = propagate_steps(states[sl], P0, acc, gyro, dt, noise, gravity)
        parts.append(state)
        covs.append(P)
    if not parts:
        empty = np.zeros((0, 15, 15))
        return states[:0], empty, empty if transition else None
    out = ImuState(*(np.concatenate([getattr(p, f) for p in parts]) for f in ("r", "v", "C", "b_f", "b_w")))
    return out, np.concatenate(covs), np.concatenate(transitions) if transition else None


def states_at(trajectory: Trajectory, imu: ImuSamples, t, noise: ImuNoise, gravity=DEFAULT_GRAVITY) -> Trajectory:
    """The states at times ``t`` (increasing, within the IMU span, none before the trajectory's
    first state), each predicted from ``trajectory``'s state at or before it through the IMU's
    Euler steps -- the primer's model, as a measurement between keyframes is evaluated -- with the
    EKF's prediction of its covariance, ``P <- F P F^T + G Q_d G^T`` (:func:`carry`), where the
    trajectory has covariances. A time at a state of the trajectory takes that state. What an
    output or a metric reads where it needs a state at a time that is not a keyframe."""
    t = np.asarray(t, dtype=float)
    source = np.searchsorted(trajectory.t, t, side="right") - 1
    if t.size and source.min() < 0:
        raise InputError(f"states_at: {t[source < 0][0]} s lies before the trajectory's first state "
                         f"({trajectory.t[0]} s)")
    has_cov = trajectory.cov is not None
    states, cov, _ = carry(trajectory.states[source], imu, trajectory.t[source], t, noise, gravity,
                           trajectory.cov[source] if has_cov else None)
    return Trajectory(t, states, cov if has_cov else None)
