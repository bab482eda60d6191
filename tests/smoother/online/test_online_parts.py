"""The parts of the online smoother (``smoother/online/``), each on its own contract: the IMU
buffer (imu_buffer.py), the keyframe schedule (schedule.py), the pending-measurement heap
(pending.py), the hand-over (handover.py) and the IMU-rate prediction (prediction.py). The whole
smoother is tested in test_smoother.py."""
from __future__ import annotations

import random
import warnings

import numpy as np
import pytest

from factors import imu
from factors.errors import InputError
from smoother.ekf.filter import Ekf
from smoother.online.handover import HandOver, OnlineEstimate
from smoother.online.imu_buffer import TYPICAL_INTERVALS, ImuBuffer
from smoother.online.pending import PendingMeasurements
from smoother.online.prediction import ImuRatePrediction
from smoother.online.schedule import KeyframeSchedule


def _resting(n: int, rate: float = 200.0):
    """``n`` samples of a slowly turning IMU at ``rate`` Hz: times, specific force, rates."""
    t = np.arange(n) / rate
    return t, np.tile([0.1, 0.0, 9.81], (n, 1)), np.tile([0.0, 0.02, 0.3], (n, 1))


# ------------------------------------------------------------------------------------------
# the IMU buffer


def test_the_buffer_lets_go_only_samples_before_the_one_held_at_keep_from_and_counts_them():
    """Fed 5000 samples one by one and in chunks while ``keep_from`` follows a keyframe every
    0.1 s, the buffer keeps every sample from the one held at ``keep_from`` on, in order; what it
    let go is counted in ``released``, so that stream index ``i`` is buffer index
    ``i - released``."""
    t, acc, gyro = _resting(5000)
    buffer = ImuBuffer()
    i = 0
    while i < len(t):
        if i % 700 < 600:
            buffer.add_one(float(t[i]), acc[i], gyro[i])
            i += 1
        else:
            buffer.add(t[i:i + 50], acc[i:i + 50], gyro[i:i + 50])
            i += 50
        if i % 20 == 0:
            buffer.keep_from = float(t[i - 1])
    assert buffer.released > 0 and buffer.released + buffer.n == len(t)
    np.testing.assert_array_equal(buffer.t[:buffer.n], t[buffer.released:])
    np.testing.assert_array_equal(buffer.gyro[:buffer.n], gyro[buffer.released:])
    held = int(np.searchsorted(t, buffer.keep_from, side="right")) - 1
    assert buffer.released <= held
    assert buffer.t[held - buffer.released] == t[held] and buffer.held_at(buffer.keep_from) == held - buffer.released


def test_a_batch_then_single_samples_beyond_the_first_arrays_are_all_taken():
    """400 samples in one call, then 1600 one by one (past the 1024 the arrays first hold): the
    smoother takes every one and its estimate reaches the last."""
    from smoother.online.smoother import OnlineSmoother

    t, acc, gyro = _resting(2000)
    online = OnlineSmoother(imu.ImuState.identity(), np.eye(15) * 0.01, imu.ImuNoise(), lag_s=0.5)
    online.add_imu(t[:400], acc[:400], gyro[:400])
    for i in range(400, len(t)):
        online.add_imu(float(t[i]), acc[i], gyro[i])
    assert online._n == len(t) and online.estimate().t == t[-1]


def test_the_buffer_refuses_without_taking_and_knows_the_typical_period_after_twenty_intervals():
    """A refused sample (a step back, NaN, a shape other than the contract's) leaves the buffer
    as it was; the gap rule applies once :data:`TYPICAL_INTERVALS` intervals are known, with the
    offline rule's warning, counted."""
    t, acc, gyro = _resting(TYPICAL_INTERVALS + 5)
    buffer = ImuBuffer()
    buffer.add(t[:TYPICAL_INTERVALS + 2], acc[:TYPICAL_INTERVALS + 2], gyro[:TYPICAL_INTERVALS + 2])
    n = buffer.n
    for bad in ((t[3], acc[3], gyro[3]), (t[-1], np.array([np.nan, 0, 0]), gyro[-1])):
        with pytest.raises(InputError, match="add_imu: "):
            buffer.add_one(float(bad[0]), *bad[1:])
    with pytest.raises(InputError, match=r"add_imu: acc: expected shape \(3, 3\)"):
        buffer.add(t[-3:], acc[-3:].T[:2], gyro[-3:])
    assert buffer.n == n and buffer.t_last == t[n - 1]
    with pytest.warns(UserWarning, match=r"1 gap\(s\) longer than 5 x the typical period \(0.005 s\)"):
        buffer.add_one(float(t[n - 1] + 1.0), acc[0], gyro[0])
    assert buffer.imu_gaps == 1 and buffer.longest_imu_gap_s == pytest.approx(1.0)


# ------------------------------------------------------------------------------------------
# the keyframe schedule


def _drain(schedule: KeyframeSchedule, horizon: float, end: float) -> list[float]:
    out = []
    while (t := schedule.next_due(horizon, end)) is not None:
        out.append(t)
    return out


def test_the_schedule_gives_each_time_once_in_order_as_the_stream_passes_it():
    """Times asked for in any order (some twice) come out increasing, each once, only up to the
    horizon and the IMU's end; one before the first sample is let go."""
    schedule = KeyframeSchedule(None)
    schedule.start(1.0)
    for x in (1.7, 1.2, 0.5, 1.7, 1.45, 1.2, 3.0):
        schedule.ask(x)
    assert schedule.next_time() == 0.5  # asked for, let go when taken (before t0)
    assert _drain(schedule, 1.5, 10.0) == [1.0, 1.2, 1.45]
    assert _drain(schedule, 10.0, 2.0) == [1.7]
    assert schedule.next_time() == 3.0
    assert _drain(schedule, 10.0, 10.0) == [3.0]


def test_the_grid_leaves_out_times_within_half_an_imu_interval_of_another_keyframe():
    """A 10 Hz grid from t0 = 0 with a measurement at 0.301 and the newest keyframe at 0.102:
    the grid times 0.1 (0.002 before the newest) and 0.3 (0.001 from the measurement) are left
    out for a half-interval of 0.0025 s, the others asked for."""
    schedule = KeyframeSchedule(10.0)
    schedule.start(0.0)
    assert _drain(schedule, 0.0, 0.0) == [0.0]
    schedule.ask(0.301)
    schedule.grid_up_to(0.55, 0.0025, newest=0.102)
    assert _drain(schedule, 0.55, 1.0) == pytest.approx([0.2, 0.301, 0.4, 0.5])


def test_the_grid_leaves_out_the_times_a_scan_of_every_time_asked_for_would():
    """Times asked for all at once over a whole run, as a replay does (``keyframe_at``), the grid
    made as the stream passes: the keyframes are those of a schedule that scans every time asked
    for at each grid time (the schedule searches its heap instead), some grid times left out."""
    class Scanning(KeyframeSchedule):
        def _near(self, g, step):
            return any(abs(x - g) < step for x in self._knots)

    rng = np.random.default_rng(3)
    asked = rng.permutation(np.unique(np.round(rng.uniform(0.0, 20.0, 400), 3))).tolist()
    runs = []
    for schedule in (KeyframeSchedule(10.0), Scanning(10.0)):
        schedule.start(0.0)
        for x in asked:
            schedule.ask(x)
        made = []
        for horizon in np.arange(0.0, 20.5, 0.05):
            schedule.grid_up_to(horizon, 0.004, made[-1] if made else None)
            made += _drain(schedule, horizon, horizon)
        runs.append(made)
    assert runs[0] == runs[1]
    assert set(asked) < set(runs[0]) and len(set(runs[0]) - set(asked)) < 205  # of the grid's 205, some left out


# ------------------------------------------------------------------------------------------
# the pending measurements (late data)


def test_pending_measurements_come_out_sorted_whatever_the_order_of_arrival():
    """Measurements of three sensors offered in shuffled order come out at their keyframe sorted
    by time, then sensor, then order of arrival; those due at a later keyframe stay."""
    pending = PendingMeasurements(max_delay_s=0.3, lag_s=1.0)
    items = [(s, t, row) for t in (0.1, 0.2) for s in ("b", "a", "c") for row in range(2)]
    random.Random(4).shuffle(items)
    for s, t, row in items:
        assert pending.offer(s, (t,), None, row, 0.0, None, {})
    first, between = pending.due(0.1, True, {})
    assert between == []
    assert [(p.sensor, p.latest) for p in first] == sorted((s, t) for s, t, _ in items if t == 0.1)
    assert [p.row for p in first if p.sensor == "a"] == [row for s, t, row in items if s == "a" and t == 0.1]
    assert len(pending) == 6 and pending.dropped == {} and pending.skipped == {}
    assert [p.sensor for p in pending.due(0.2, False, {0.1: 0})[0]] == ["a", "a", "b", "b", "c", "c"]


def test_pending_measurements_between_keyframes_come_with_the_next_one():
    """A measurement of one time between the newest keyframe made and the next comes out with
    the next, apart from those at its time (attached to the keyframe before it); one before the
    first keyframe comes out with it, dropped."""
    pending = PendingMeasurements(max_delay_s=0.0, lag_s=1.0)
    assert pending.offer("v", (-0.05,), None, 0, 0.0, None, {})
    with pytest.warns(UserWarning, match="lies before the IMU's first sample"):
        assert pending.due(0.0, True, {}) == ([], [])
    for sensor, t in (("v", 0.13), ("p", 0.2), ("v", 0.27)):
        assert pending.offer(sensor, (t,), None, 0, 0.0, 0.1, {0.1: 0})
    at, between = pending.due(0.2, False, {0.1: 0})
    assert [(p.sensor, p.latest) for p in at] == [("p", 0.2)]
    assert [p.latest for p in between] == [0.13]
    assert pending.dropped == {"v": 1} and len(pending) == 1


def test_pending_measurements_older_than_the_window_are_refused_counted_and_warned_of_once():
    """With the newest keyframe at 1.0 and the window's keyframes at 0.8 and 1.0: a measurement at
    1.0 or before is dropped, an odometry from 0.9 (no keyframe) skipped, one from 0.8 taken; a
    sensor's first refusal is warned of, the next only counted; at the keyframe a measurement
    whose earlier keyframe has left by then is skipped, and at the end those left are dropped."""
    pending = PendingMeasurements(max_delay_s=0.3, lag_s=0.5)
    window = {0.8: 4, 1.0: 5}
    with pytest.warns(UserWarning, match=r"'gps' arrived after its keyframe time had been processed \(more than "
                                         r"max_delay_s = 0.3 s behind the IMU\)"):
        assert not pending.offer("gps", (1.0,), None, 0, 0.0, 1.0, window)
    with pytest.warns(UserWarning, match=r"'odo' refers to a time that has left the window \(older than the lag, "
                                         r"0.5 s, or no keyframe\)"):
        assert not pending.offer("odo", (0.9, 1.1), None, 0, 0.0, 1.0, window)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        assert not pending.offer("gps", (0.95,), None, 1, 0.0, 1.0, window)
    assert pending.offer("odo", (0.8, 1.1), None, 1, 0.0, 1.0, window)
    assert pending.offer("gps", (1.3,), None, 2, 0.0, 1.0, window)
    assert pending.dropped == {"gps": 2} and pending.skipped == {"odo": 1}
    assert pending.due(1.1, False, {1.0: 5}) == ([], [])  # 0.8 has left the window meanwhile
    assert pending.skipped == {"odo": 2} and len(pending) == 1
    pending.drop_all("lies after the last IMU sample and was dropped")  # gps was warned of already
    assert pending.dropped == {"gps": 3} and len(pending) == 0


# ------------------------------------------------------------------------------------------
# the hand-over


class _Window:
    """A keyframe window's reading side: keyframe j at time j / 10 with position (j, 0, 0)."""

    def __init__(self):
        self.read, self.newest = [], 100

    def covariances(self, keyframes):
        return [np.eye(15) * j for j in keyframes]

    def joint_with_next(self, keyframes):
        return None

    def taken(self, keyframes):
        self.read += list(keyframes)

    def time(self, j):
        return j / 10

    def state(self, j):
        return imu.ImuState.identity().replace(r=np.array([float(j), 0.0, 0.0]))


def test_the_hand_over_queues_or_calls_back_oldest_first_and_records_what_it_read():
    """Read estimates carry the window's time, state and (with covariances) marginal, and the
    window learns they were read; given without a callback they queue for ``smoothed()`` (each
    once, oldest first), with one they go to it."""
    window = _Window()
    hand = HandOver(window, covariances=True)
    read = hand.read([2, 3])
    assert [j for j, _ in read] == [2, 3] and window.read == [2, 3]
    assert read[1][1].t == 0.3 and read[1][1].state.r[0] == 3.0 and read[1][1].cov[0, 0] == 3.0
    hand.give([e for _, e in read])
    hand.give([e for _, e in hand.read([4])])
    assert [e.t for e in hand.smoothed()] == [0.2, 0.3, 0.4] and list(hand.smoothed()) == []
    got = []
    hand = HandOver(window, covariances=False, on_smoothed=got.append)
    hand.give([e for _, e in hand.read([5])])
    assert [e.t for e in got] == [0.5] and got[0].cov is None and list(hand.smoothed()) == []
    assert hand.read([]) == []


# ------------------------------------------------------------------------------------------
# the IMU-rate prediction


def test_the_prediction_is_the_ekf_step_from_the_keyframe_and_survives_the_buffer_letting_go():
    """From a keyframe at t = 2.0 s, the state at the newest sample equals the EKF's prediction
    through the same samples, called once at the end or after every sample, while the buffer lets
    go of the samples before the keyframe; before any keyframe it is an InputError."""
    t, acc, gyro = _resting(2000)
    noise = imu.ImuNoise(1e-2, 1e-3, 1e-3, 1e-4)
    gravity = np.array(imu.DEFAULT_GRAVITY, dtype=float)
    start = imu.ImuState.identity().replace(v=np.array([1.0, 0.0, 0.0]))
    P0 = np.eye(15) * 1e-3
    k = 400  # the keyframe's sample
    results = []
    for every_sample in (False, True):
        buffer = ImuBuffer()
        prediction = ImuRatePrediction(noise, gravity, covariances=True)
        with pytest.raises(InputError, match="estimate: no keyframe yet"):
            prediction.at(buffer)
        buffer.add(t[:k + 1], acc[:k + 1], gyro[:k + 1])
        buffer.keep_from = float(t[k])
        prediction.restart(float(t[k]), start, P0, buffer.released + buffer.held_at(float(t[k])))
        for i in range(k + 1, len(t)):
            buffer.add_one(float(t[i]), acc[i], gyro[i])
            if every_sample:
                prediction.at(buffer)
        assert buffer.released > 0
        results.append(prediction.at(buffer))
    ekf = Ekf(start, P0, noise, gravity)
    for i in range(k, len(t) - 1):
        ekf.predict(acc[i], gyro[i], t[i + 1] - t[i])
    for e in results:
        assert e.t == t[-1]
        for name in ("r", "v", "C", "b_f", "b_w"):
            np.testing.assert_allclose(getattr(e.state, name), getattr(ekf.state, name), rtol=0, atol=1e-9)
        np.testing.assert_allclose(e.cov, ekf.P, rtol=1e-9, atol=1e-15)
    assert isinstance(results[0], OnlineEstimate)
