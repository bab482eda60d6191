"""Held-out measurements of a sensor whose errors drift, as the fixed-lag smoother predicts them
given the used measurements' errors (the batch smoother's: :mod:`smoother.diagnosis.heldout_correlated`).

The prediction given the used errors, ``d = W_t e_t - w_0 u_0 - w_1 u_1``, cancels the state's error
between the held-out time and the used measurements' keyframes, so it needs their estimates and
joint covariance from one solve: a fixed-lag smoother's output takes each keyframe from another
update (the last that held it), and the differences between updates would not cancel. So each
held-out measurement is predicted inside the window (:class:`WindowedPredictions`, an online
smoother's ``before_leaving``), from the last update that holds the keyframe of the used
measurement before it: the window then holds that keyframe, the keyframes the held-out time is
bridged between and, where it has arrived, the used measurement after it -- their estimates and
their joint covariance (:meth:`smoother.fixed_lag.sliding.window.SlidingWindow.joint_span`), given
the used measurements in the window (:func:`smoother.diagnosis.heldout_correlated.given_used`). One
before the first used measurement, or whose bridge reaches past the window at that update (the next
used measurement more than the lag later), is predicted at the last update that holds its own
bridging keyframe, given the used ones in the window then.

The plain prediction (the residual and ``H P H^T``) stays the fixed-lag smoother's own output's;
the held-out verdict of such a sensor judges the prediction given the used errors
(``given_used_errors``), as the batch smoother's and the EKF's.
"""
from __future__ import annotations

from dataclasses import replace

import numpy as np

from datasets.types import Dataset, Trajectory
from factors.errors import InternalError
from factors.imu import STATE_DIM, ImuState
from smoother.diagnosis.heldout_correlated import given_used
from smoother.model.between import Following
from smoother.model.correlated import CorrelatedBlock
from smoother.model.predicted import Conditioned, HeldoutPrediction

DIM = STATE_DIM


def check_keyframes(window, times: np.ndarray, reader: str) -> None:
    """An InternalError, naming the ``reader``, unless the window's first and newest keyframes lie
    at the problem's keyframe ``times``: what reads the window reads the problem's factors there."""
    for k in (window.first, window.newest):
        if abs(window.time(k) - times[k]) > 1e-9:
            raise InternalError(f"{reader}: window keyframe {k} at t = {window.time(k):.9f} s is the problem's at "
                                f"{times[k]:.9f} s")


class WindowedPredictions:
    """The held-out measurements of ``dataset``'s drifting ``sensors`` (names) whose block in
    ``problem`` (the batch's factors on the fixed-lag smoother's keyframes) is a
    :class:`~smoother.model.correlated.CorrelatedBlock`, predicted as the window's keyframes leave it
    (module docstring): call it with the window and the keyframes about to leave
    (:class:`smoother.online.smoother.OnlineSmoother`'s ``before_leaving``), then read
    :meth:`attached_to`."""

    def __init__(self, dataset: Dataset, problem, sensors):
        self._dataset, self._times = dataset, problem.times
        n = len(problem.times)
        self._sensors = []
        for block in problem.blocks:
            if not isinstance(block, CorrelatedBlock) or block.name not in sensors:
                continue
            sensor = dataset.sensor(block.name)
            if sensor.heldout is None or not len(sensor.heldout.t):
                continue
            t = sensor.heldout.t
            index = np.flatnonzero((t >= self._times[0]) & (t <= min(self._times[-1], dataset.imu.t[-1])))
            bridge = np.clip(np.searchsorted(self._times, t[index], side="right") - 1, 0, n - 2)
            before = np.searchsorted(block.times, t[index], side="right") - 1
            used_keyframe = block.measurements.keyframes[:, 0]
            at = np.where(before >= 0, used_keyframe[np.maximum(before, 0)], bridge)
            self._sensors.append({"sensor": sensor, "block": block, "index": index, "bridge": bridge, "at": at,
                                  "done": np.zeros(len(index), dtype=bool), "parts": []})

    def __bool__(self) -> bool:
        return bool(self._sensors)

    def __call__(self, window, leaving) -> None:
        """Predict the held-out measurements due at this update (``leaving``: the keyframes the next
        update marginalises, or the whole window at the end)."""
        leaving = np.asarray(list(leaving), dtype=int)
        if not len(leaving):
            return
        check_keyframes(window, self._times, "held-out predictions")
        for s in self._sensors:
            due = ~s["done"] & np.isin(s["at"], leaving)
            # its time is after the newest keyframe's (its bridge reaches past the window): later
            after = s["sensor"].heldout.t[s["index"]] > self._times[s["bridge"]]
            late = due & ((s["bridge"] > window.newest) | ((s["bridge"] == window.newest) & after))
            s["at"][late] = s["bridge"][late]
            due &= ~late
            for at in np.unique(s["at"][due]):
                self._predict(window, s, np.flatnonzero(due & (s["at"] == at)))

    def _predict(self, window, s: dict, rows: np.ndarray) -> None:
        """Sensor ``s``'s held-out measurements ``rows`` (of its ``index``) from the window now."""
        block = s["block"]
        used_keyframe = block.measurements.keyframes[:, 0]
        newest_t = window.time(window.newest)
        # the used measurements whose factors the window holds: their keyframes in it, none beyond the newest
        available = (used_keyframe >= window.first) & (used_keyframe <= window.newest) & (block.times <= newest_t)
        t = s["sensor"].heldout.t[s["index"][rows]]
        mine = np.flatnonzero(available)
        if len(mine):
            i = np.searchsorted(block.times[mine], t, side="right")
            near = np.concatenate([mine[np.clip(i - 1, 0, len(mine) - 1)], mine[np.clip(i, 0, len(mine) - 1)]])
            ends = used_keyframe[near]
        else:
            ends = np.zeros(0, dtype=int)
        bridge = s["bridge"][rows]
        # (one at the newest keyframe's time is that keyframe's state: bridged up to it from the one before)
        hi = int(min(max(bridge.max() + 1, ends.max(initial=0)), window.newest))
        lo = int(min(bridge.min(), ends.min(initial=bridge.min()), hi - 1))
        count = hi - lo + 1
        joint = window.joint_span(lo, count)
        blocks = joint.reshape(count, DIM, count, DIM).transpose(0, 2, 1, 3)
        states = ImuState.stack([window.state(k) for k in range(lo, hi + 1)])
        cov = blocks[np.arange(count), np.arange(count)]
        local = Trajectory(np.array([window.time(k) for k in range(lo, hi + 1)]), states, cov)
        following = Following(states[1:], cov[1:], blocks[np.arange(count - 1), np.arange(1, count)])

        def between(a: int, b: int) -> np.ndarray:
            return blocks[int(a) - lo, int(b) - lo]

        predicted = given_used(self._dataset, block, s["sensor"], local, None, following, between,
                               s["index"][rows], offset=lo, available=available)
        s["parts"].append((rows, predicted.conditioned))
        s["done"][rows] = True

    def attached_to(self, plain: dict[str, HeldoutPrediction]) -> dict[str, HeldoutPrediction]:
        """The fixed-lag smoother's own predictions ``plain`` (by sensor, from its output:
        :func:`smoother.diagnosis.heldout.heldout_predictions`) with the predictions given the used
        errors made in the window (:class:`~smoother.model.predicted.Conditioned`) for the sensors
        whose held-out measurements were all predicted there; the others as they are."""
        out = dict(plain)
        for s in self._sensors:
            name = s["sensor"].name
            own = plain.get(name)
            if own is None or not s["parts"]:
                continue
            rows = np.concatenate([r for r, _ in s["parts"]])
            where = {int(m): i for i, m in enumerate(s["index"][rows])}
            if not all(int(m) in where for m in own.index):
                continue
            order = np.array([where[int(m)] for m in own.index], dtype=int)
            parts = [c for _, c in s["parts"]]
            e, state_part, noise = (np.concatenate([getattr(c, f) for c in parts])[order]
                                    for f in ("e", "state_part", "noise"))
            out[name] = replace(own, conditioned=Conditioned(e, state_part, noise))
        return out
