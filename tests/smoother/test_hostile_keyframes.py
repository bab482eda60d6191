"""Hostile timing of the measurements: a long stretch without any (a GNSS outage of minutes, IMU
data long after the last fix) made one keyframe interval hold most of the IMU's steps, and the
estimators hold the intervals' steps padded to the longest (:meth:`smoother.model.timeline.Steps.
segments`): memory of the number of keyframes times that interval. A 15-minute GNSS-only rig (2 Hz)
with a 13-minute outage asked for 861 MiB at a time and its batch smoother failed in 4 GB.
:func:`smoother.model.timeline.bounded_intervals` adds keyframes inside such an interval, so that
the padded steps stay within a few times the IMU's."""
from __future__ import annotations

import numpy as np
import pytest

from datasets.simulate import simulate
from datasets.types import Trajectory
from smoother import build_problem, solve_batch
from smoother.model.timeline import (
    EVERY_MEASUREMENT,
    LONGEST_INTERVAL,
    PADDED_STEPS,
    imu_steps,
    keyframe_times,
    measurement_knots,
)


@pytest.fixture(scope="module")
def uniform():
    """Ten minutes of a 100 Hz IMU and 2 Hz fixes."""
    return simulate("gentle", duration=600.0, seed=3, imu_rate=100.0, pose_rate=None, position_rate=2.0,
                    position_sigma=0.5)


@pytest.fixture(scope="module")
def outage(uniform):
    """:func:`uniform` without the fixes between 20 s and 580 s: 81 intervals, one of 56 000 steps."""
    fixes = uniform.sensor("position").data
    keep = (fixes.t <= 20.0) | (fixes.t >= 580.0)
    return uniform.with_sensor("position", data=fixes.subset(np.flatnonzero(keep)))


@pytest.mark.parametrize("rate", [None, EVERY_MEASUREMENT, 0.01])
def test_a_long_interval_gets_keyframes_and_the_padded_steps_stay_within_five_times_the_imus(outage, rate):
    times = keyframe_times(outage, rate)
    steps = imu_steps(outage.imu, times)
    acc, _, dt = steps.segments()
    n = len(outage.imu.t)
    assert dt.size <= max(PADDED_STEPS, 5 * n + 2 * len(times)), (dt.shape, n)  # before: 81 x 56 000 steps
    if rate != 0.01:  # the measurement times stay keyframes: the added ones lie inside the outage only
        knots = measurement_knots(outage)
        assert set(knots) <= set(times)
        added = np.setdiff1d(times, knots)
        assert added.size and np.all((added > 20.0) & (added < 580.0)), added
        assert np.diff(steps.knot_step).max() <= np.ceil(LONGEST_INTERVAL * n / (len(knots) - 1))


def test_a_short_gap_in_a_short_run_is_left_alone():
    """Ten keyframes of 10 Hz poses around a 2-s gap pad to little: no keyframe is added."""
    data = simulate("gentle", duration=10.0, seed=0, imu_rate=100.0, pose_rate=10.0)
    poses = data.sensor("pose").data
    gapped = data.with_sensor("pose", data=poses.subset(np.flatnonzero((poses.t < 4.0) | (poses.t > 6.0))))
    assert np.array_equal(keyframe_times(gapped, EVERY_MEASUREMENT), measurement_knots(gapped))


def test_measurements_at_their_usual_pace_get_no_keyframe_and_the_added_ones_hold_the_truth(uniform, outage):
    """Keyframes are added only where an interval is long; inside it they are states the IMU's
    factors chain, and the batch's estimate at the fixes holds the truth within its sigmas."""
    assert np.array_equal(keyframe_times(uniform, EVERY_MEASUREMENT), measurement_knots(uniform))
    result = solve_batch(build_problem(outage, keyframe_rate=EVERY_MEASUREMENT)).trajectory
    at = np.isin(result.t, measurement_knots(outage))
    assert at.sum() == len(measurement_knots(outage)) and len(result.t) > at.sum()
    sigma = np.sqrt(np.einsum("nii->ni", result.cov[at][:, 0:3, 0:3]))
    truth = outage.truth
    r_true = np.array([truth.states.r[np.argmin(np.abs(truth.t - t))] for t in result.t[at]])
    assert np.all(np.abs(result.states.r[at] - r_true) < 5 * sigma + 1e-9)


def test_states_predicted_far_from_their_source_are_propagated_in_bounded_chunks(outage, monkeypatch):
    """The batch smoother starts from the EKF's states, which have none inside the outage: each
    keyframe added there was predicted from the state before the outage, all in one chunk padded
    to the longest (104 queries of 154 606 steps: 368 MiB an array, and the batch failed in 4 GB).
    Chunked by their padded steps, the states are the same to the last bit."""
    from smoother.model import timeline

    truth = outage.truth
    knots = measurement_knots(outage)
    source = Trajectory(knots, truth.states[np.searchsorted(truth.t, knots)], None)
    queries = np.setdiff1d(keyframe_times(outage, EVERY_MEASUREMENT), knots)
    shapes = []
    propagate = timeline.propagate_steps

    def recording(states, P0, acc, gyro, dt, *args):
        shapes.append(dt.shape)
        return propagate(states, P0, acc, gyro, dt, *args)

    monkeypatch.setattr(timeline, "propagate_steps", recording)
    chunked = timeline.states_at(source, outage.imu, queries, outage.noise, outage.gravity)
    longest = max(k for _, k in shapes)
    assert all(n * k <= max(timeline.STATES_PADDED, k) for n, k in shapes) and len(shapes) > 1, shapes
    monkeypatch.setattr(timeline, "STATES_PADDED", 10**12)  # one chunk, as before
    whole = timeline.states_at(source, outage.imu, queries, outage.noise, outage.gravity)
    assert shapes[-1] == (len(queries), longest)
    for name in ("r", "v", "C", "b_f", "b_w"):
        np.testing.assert_array_equal(getattr(chunked.states, name), getattr(whole.states, name))


def test_two_sensors_stamped_an_ulp_apart_give_a_solvable_problem():
    """Fixes of two sensors stamped "at once" but an ulp apart (1.5 and 1.4999999999999998 s: one
    clock's sum, another's product) are two keyframes an ulp apart. The initial trajectory's velocity
    was their positions' difference over that ulp, 1e15 m/s, and the IMU factor between them had a
    covariance no longer positive definite: the batch stopped inside numpy's Cholesky. Now the
    velocity's finite differences take them as one instant, and the run ends near the truth."""
    from dataclasses import replace

    from datasets.types import PositionMeasurements, Sensor

    data = simulate("gentle", duration=6.0, seed=1, pose_rate=None, position_rate=2.0, position_sigma=0.3)
    fixes = data.sensor("position").data
    fixes = fixes.subset(fixes.t > 0)  # (one an ulp before the IMU's first sample would be dropped)
    stamps = np.nextafter(fixes.t, -np.inf)  # each an ulp before the other sensor's
    rng = np.random.default_rng(0)
    other = PositionMeasurements(stamps, fixes.position + rng.normal(scale=0.3, size=fixes.position.shape), fixes.cov)
    data = replace(data, sensors=(*data.sensors, Sensor("second", "position", other)))
    times = keyframe_times(data, EVERY_MEASUREMENT)
    assert np.diff(times).min() < 1e-15  # the case: keyframes an ulp apart
    result = solve_batch(build_problem(data, EVERY_MEASUREMENT))
    truth = data.truth.states.r[np.searchsorted(data.truth.t, result.trajectory.t).clip(0, len(data.truth.t) - 1)]
    assert np.sqrt(np.mean(np.sum((result.trajectory.states.r - truth) ** 2, axis=1))) < 1.0
