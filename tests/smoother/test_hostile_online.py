"""Hostile arguments of the online smoother: ``max_delay_s`` infinite was accepted and then no
keyframe was ever made while ``estimate()`` asked for IMU samples; every value outside
``smoother.online.delay.MAX_DELAY_RANGE`` is refused naming the argument and the range. And what
the README and the docstring say of late measurements is what the code does: a measurement is
dropped when its time is at or before the newest keyframe made, not for being later than
``max_delay_s`` as such."""
from __future__ import annotations

import math

import numpy as np
import pytest

from datasets.simulate import simulate
from factors.errors import InputError
from smoother.online.delay import MAX_DELAY_RANGE
from smoother.online.smoother import OnlineSmoother, SensorSetup


@pytest.fixture(scope="module")
def data():
    return simulate("gentle", duration=3.0, seed=0, imu_rate=100.0, pose_rate=10.0)


def _smoother(data, **options) -> OnlineSmoother:
    pose = SensorSetup("pose", sigma=[0.05, 0.05, 0.05, 0.01, 0.01, 0.01])
    return OnlineSmoother(data.initial, data.initial_cov, data.noise, {"pose": pose}, gravity=data.gravity, **options)


@pytest.mark.parametrize("delay", [math.inf, -math.inf, math.nan, -1e-9, MAX_DELAY_RANGE.high * 1.000001, 1e300,
                                   "0.1", None])
def test_a_delay_outside_its_range_is_refused_naming_it_and_the_range(data, delay):
    with pytest.raises(InputError, match=r"^max_delay_s: expected "):
        _smoother(data, max_delay_s=delay)
    if isinstance(delay, float):
        with pytest.raises(InputError, match=r"within \[0, 60\] s"):
            _smoother(data, max_delay_s=delay)


@pytest.mark.parametrize("delay", [MAX_DELAY_RANGE.low, MAX_DELAY_RANGE.high, 0.2])
def test_a_delay_at_or_within_its_bounds_is_taken(data, delay):
    assert _smoother(data, max_delay_s=delay).max_delay_s == delay


def test_a_late_measurement_is_dropped_when_a_keyframe_at_or_after_its_time_was_made_and_used_otherwise(data):
    """``max_delay_s`` 0.1: a pose arriving 1 s late is used while no keyframe has been made since
    its time (none was due); once one has, a pose at or before it is dropped and counted."""
    pose = data.sensor("pose").data
    online = _smoother(data, max_delay_s=0.1)
    i = np.searchsorted(data.imu.t, 2.0)
    online.add_imu(data.imu.t[:i], data.imu.acc[:i], data.imu.gyro[:i])  # the IMU stream at 2 s, no pose yet
    k = int(np.searchsorted(pose.t, 1.0))
    online.add("pose", pose.t[k], pose.position[k], pose.C[k])  # a second late: no keyframe since its time
    online.add_imu(data.imu.t[i:i + 1], data.imu.acc[i:i + 1], data.imu.gyro[i:i + 1])
    assert online.dropped == {}
    with pytest.warns(UserWarning, match="arrived after its keyframe time had been processed"):
        online.add("pose", pose.t[k - 2], pose.position[k - 2], pose.C[k - 2])  # before the keyframe just made
    assert online.dropped == {"pose": 1}
    online.finish()
    times = [e.t for e in online.smoothed()]
    assert pose.t[k] in times and pose.t[k - 2] not in times  # the late one made its keyframe


@pytest.mark.parametrize("delay", [0.2, MAX_DELAY_RANGE.high])
def test_a_realtime_replay_with_a_delay_runs_and_estimates_once_the_first_keyframe_is_made(data, delay):
    """``smoother run --realtime --max-delay 0.2`` failed every time: the replay asked for the
    estimate after every IMU sample, and before the first keyframe (made once the stream is
    ``max_delay_s`` past it) there is none ("estimate: no keyframe yet")."""
    from smoother.online.replay import replay

    online = _smoother(data, max_delay_s=delay)
    assert not online.started
    with pytest.raises(InputError, match="no keyframe yet"):
        online.estimate()
    result = replay(data, lag_s=1.0, max_delay_s=delay, realtime=True, speed=1000.0, covariances=False,
                    progress=False)
    offline = replay(data, lag_s=1.0, max_delay_s=delay, covariances=False, progress=False)
    np.testing.assert_array_equal(result.smoothed.t, offline.smoothed.t)
    assert len(result.latency_s) > 0
