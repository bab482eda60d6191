"""A recorded dataset fed through an :class:`~smoother.online.smoother.OnlineSmoother` in order of
arrival (:func:`replay`; ``smoother run --estimator fixed-lag``), optionally at its own pace
(``realtime``), with what came out of it: every keyframe's smoothed estimate, the updates' times,
the measurements' latencies, what was dropped or skipped.

Run as a program (``python -m smoother.online.replay``) it replays 3 s of the simulator's default
run through the sliding window and writes nothing but Numba's kernel cache: the warm-up child of
:func:`smoother.online.warm_up.start` (every kernel of an update, a marginalisation and the
covariances)."""
from __future__ import annotations

import time
from dataclasses import dataclass

import numpy as np

from datasets.kinds import sensors_of
from datasets.types import Dataset, Trajectory
from factors import imu
from factors.errors import InputError
from smoother.model.between import Following
from smoother.model.problem import measurement_spec
from smoother.model.timeline import keyframe_rate as grid_rate
from smoother.model.timeline import keyframe_times, relative_on_keyframes
from smoother.online.handover import OnlineEstimate
from smoother.online.smoother import OnlineSmoother
from smoother.progress import progress_bar


@dataclass
class ReplayResult:
    """A dataset replayed through an :class:`OnlineSmoother`: ``smoothed``, each keyframe's
    estimate (and covariance) as it left the window; ``update_s`` the wall time of each update;
    ``latency_s`` each used measurement's, from its arrival to the end of its update (meaningful
    with ``realtime``); ``dropped`` late measurements and ``skipped`` relative ones reaching back
    beyond the window, per sensor; ``recovered`` keyframes that
    needed a weak prior; ``longest_gap_s`` between measurements; ``runtime_s`` the whole replay;
    ``calibration`` ``(values, covariances)`` of the calibration variables at the end
    (:attr:`OnlineSmoother.calibration`), or None."""

    smoothed: Trajectory
    update_s: np.ndarray
    latency_s: np.ndarray
    dropped: dict
    skipped: dict
    recovered: list
    longest_gap_s: float
    runtime_s: float
    calibration: tuple | None = None
    #: Each keyframe's next as the window had them together (:class:`smoother.model.between.Following`),
    #: where the window computes joint covariances, or None.
    following: object = None
    #: How many drifting measurements it weighed alone (:attr:`OnlineSmoother.weighed_alone`).
    weighed_alone: int = 0


def replaying(dataset: Dataset, robust: dict | None = None, keyframe_rate=None, **options) -> OnlineSmoother:
    """The :class:`OnlineSmoother` that :func:`replay` feeds ``dataset`` to
    (:meth:`OnlineSmoother.for_dataset` with ``options``), its keyframes the batch smoother's
    (:func:`smoother.model.timeline.keyframe_times`: its grid, asked for at those times)."""
    online = OnlineSmoother.for_dataset(dataset, robust, keyframe_rate=grid_rate(dataset, keyframe_rate), **options)
    online.keyframe_at(keyframe_times(dataset, keyframe_rate))
    return online


def arrivals(dataset: Dataset, starts: np.ndarray | None = None, early=()):
    """``dataset``'s measurements in their order of arrival, each at its (latest) time stamp, before
    the IMU samples of that time, in groups: one ``(t, upto, arrived)`` per arrival time ``t``,
    ``upto`` the number of IMU samples before it (which arrive first) and ``arrived`` the ``(sensor
    name, measurements)`` that arrive then, each sensor's rows in one block in their order of
    arrival. With ``starts`` (increasing sample counts from 0), those of the sensors named in
    ``early`` arrive earlier, at the last of ``starts`` at or before their own ``upto``, and a group
    is all that arrives at one ``upto`` (``t`` its earliest arrival time)."""
    sensors = sensors_of(dataset)
    arrival = [np.max(np.stack(measurement_spec(s).times, axis=1), axis=1) for s in sensors]
    none = [np.zeros(0)]  # dead reckoning: no sensor, no measurement
    which = np.concatenate(none + [np.full(len(a), i) for i, a in enumerate(arrival)]).astype(int)
    rows = np.concatenate(none + [np.arange(len(a)) for a in arrival]).astype(int)
    at = np.concatenate(none + arrival)
    upto = np.searchsorted(dataset.imu.t, at, side="left")
    if starts is not None:
        moved = np.isin(which, [i for i, s in enumerate(sensors) if s.name in early])
        upto[moved] = starts[np.searchsorted(starts, upto[moved], side="right") - 1]
    key = at if starts is None else upto
    order = np.lexsort((rows, at, which, key))  # a group's sensors in turn, each's rows in order of arrival
    if not len(order):
        return
    k, w = key[order], which[order]
    heads = np.flatnonzero(np.r_[True, (k[1:] != k[:-1]) | (w[1:] != w[:-1])])  # where each sensor's rows start
    runs = np.split(order, heads[1:])
    for group in np.split(np.arange(len(runs)), np.flatnonzero(k[heads[1:]] != k[heads[:-1]]) + 1):
        members = [runs[r] for r in group]
        yield (float(min(at[m[0]] for m in members)), int(upto[members[0][0]]),
               [(sensors[which[m[0]]].name, sensors[which[m[0]]].data.subset(rows[m])) for m in members])


def replay(dataset: Dataset, lag_s: float = 2.0, kind: str = "sliding", keyframe_rate=None,
           robust: dict | None = None, covariances: bool = True, max_delay_s: float = 0.0, realtime: bool = False,
           speed: float = 1.0, progress: bool | None = None, joint_with_next: bool = False,
           before_leaving=None) -> ReplayResult:
    """Feed ``dataset`` through an :class:`OnlineSmoother` (:meth:`OnlineSmoother.for_dataset`)
    in the order of arrival: each measurement arrives at its (latest) time stamp, before the IMU
    sample of the same time; its keyframes are those of the batch smoother's graph
    (:func:`smoother.model.timeline.keyframe_times` of ``keyframe_rate``: the grid or the measurement
    times, the ends). ``realtime``: at the data's own pace (``speed`` times it), sample by
    sample, so that the latencies are those a robot would see; otherwise as fast as it goes, in
    blocks with the same estimates: the IMU between the measurements that ask for keyframes
    (:meth:`OnlineSmoother.asks_keyframes`), the others (attached to the keyframe before them) arriving
    together at the time of that keyframe (:func:`arrivals`), which is earlier than their own
    and changes nothing but their latencies: a measurement waits for the keyframe after its time
    however early it arrives. ``joint_with_next`` (with ``covariances``): the result's ``following``
    too (:class:`smoother.model.between.Following`; :class:`OnlineSmoother`'s option); ``before_leaving``
    the :class:`OnlineSmoother`'s option."""
    if not speed > 0:
        raise InputError(f"speed must be positive, got {speed}")
    # a relative sensor's measurements between keyframes arrive composed, as the batch smoother reads them
    dataset = relative_on_keyframes(dataset, keyframe_times(dataset, keyframe_rate))
    smoothed: list[OnlineEstimate] = []
    began = time.perf_counter()  # the whole replay: loading the kernels (the first smoother of a process) too
    online = replaying(dataset, robust, lag_s=lag_s, kind=kind, keyframe_rate=keyframe_rate, max_delay_s=max_delay_s,
                       covariances=covariances, on_smoothed=smoothed.append, joint_with_next=joint_with_next,
                       before_leaving=before_leaving)
    imu_t = dataset.imu.t
    if realtime:
        groups = arrivals(dataset)
    else:
        attached = [s.name for s in sensors_of(dataset) if not online.asks_keyframes(s.name)]
        knots = np.searchsorted(imu_t, keyframe_times(dataset, keyframe_rate), side="left")
        groups = arrivals(dataset, np.union1d([0], knots), attached)
    start = time.perf_counter()

    def wait(t: float) -> None:
        if realtime:
            delay = start + (t - imu_t[0]) / speed - time.perf_counter()
            if delay > 0:
                time.sleep(delay)

    def feed(i: int, j: int) -> None:
        if realtime:
            for m in range(i, j):
                wait(imu_t[m])
                online.add_imu(imu_t[m], dataset.imu.acc[m], dataset.imu.gyro[m])
                if online.started:  # with --max-delay, no keyframe (and no estimate) for that long
                    online.estimate()
        elif j > i:
            online.add_imu(imu_t[i:j], dataset.imu.acc[i:j], dataset.imu.gyro[i:j])

    fed = 0
    with progress_bar(len(imu_t), f"fixed-lag ({kind}, online)", progress) as bar:
        for t, upto, arrived in groups:
            feed(fed, upto)
            bar.update(upto - fed)
            fed = upto
            wait(t)
            for name, data in arrived:
                online.add_measurements(name, data)
        feed(fed, len(imu_t))
        bar.update(len(imu_t) - fed)
        online.finish()
    smoothed.sort(key=lambda e: e.t)
    trajectory = Trajectory(np.array([e.t for e in smoothed]), imu.ImuState.stack([e.state for e in smoothed]),
                            np.stack([e.cov for e in smoothed]) if covariances else None)
    return ReplayResult(trajectory, np.array(online.update_s), np.array(online.latency_s), dict(online.dropped),
                        dict(online.skipped), online.recovered, online.longest_gap_s, time.perf_counter() - began,
                        online.calibration,
                        Following.of_handed_over(smoothed) if covariances and joint_with_next else None,
                        online.weighed_alone)


if __name__ == "__main__":
    import warnings

    from datasets.simulate import simulate

    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        replay(simulate("gentle", duration=3.0, seed=0), 1.0, "sliding", covariances=True, progress=False)
