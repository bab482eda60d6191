"""smoother.model.timeline: the IMU stream cut at knot times into Euler-forward steps.

What is proved here: a knot strictly inside an IMU interval splits it into two steps that hold
the same sample (zero-order hold); a knot on a sample time adds no step; the steps tile the IMU
span (sum of dt = span, every dt > 0, start times = the merged time grid); ``knot_step`` points at
the step that starts at each knot; ``interval_steps`` (one interval, the online smoother's) gives
the same steps between two knots bit for bit; ``segments()`` returns the steps between consecutive
knots padded with ``dt = 0`` (and zero samples), so that preintegrating the segments reproduces the
sample-by-sample integration of the steps at every knot; knots outside the IMU span or not
strictly increasing raise ``ValueError``.

Tolerances: times are compared exactly where they are copied (start times, dt of a copied step)
and to ``4 n EPS |t|`` where a sum of ``n`` differences telescopes; states to 1e-9 (the
preintegration's prediction identity, see tests/factors/test_preintegration.py).
"""
from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from datasets.types import ImuSamples
from factors import imu, preintegration, so3
from smoother.model.timeline import imu_steps, interval_steps, steps_between

EPS = float(np.finfo(float).eps)


def samples(t) -> ImuSamples:
    """IMU samples at times ``t`` whose values identify them: ``acc[k] = (k, 10k, 100k)``,
    ``gyro[k] = -acc[k] / 1000``."""
    t = np.asarray(t, dtype=float)
    k = np.arange(len(t), dtype=float)
    acc = np.stack([k, 10 * k, 100 * k], axis=1)
    return ImuSamples(t, acc, -acc / 1000)


def test_knot_inside_an_interval_splits_it_with_the_same_sample():
    steps = imu_steps(samples([0.0, 1.0, 2.0, 3.0]), [0.0, 0.25, 2.0, 3.0])
    assert np.array_equal(steps.t, [0.0, 0.25, 1.0, 2.0])
    assert np.array_equal(steps.dt, [0.25, 0.75, 1.0, 1.0])
    assert np.array_equal(steps.acc[:, 0], [0.0, 0.0, 1.0, 2.0])  # sample 0 held on both sides of 0.25
    assert np.array_equal(steps.gyro[:, 2], [0.0, 0.0, -0.1, -0.2])
    assert np.array_equal(steps.knot_step, [0, 1, 3, 4])


def test_knots_on_sample_times_add_no_step():
    t = np.array([0.0, 0.01, 0.02, 0.035, 0.05, 0.06])
    imu_data = samples(t)
    steps = imu_steps(imu_data, t[[0, 2, 3, 5]])
    assert len(steps.dt) == len(t) - 1
    assert np.array_equal(steps.dt, np.diff(t))
    assert np.array_equal(steps.acc, imu_data.acc[:-1])  # the last sample only ends the stream
    assert np.array_equal(steps.gyro, imu_data.gyro[:-1])
    assert np.array_equal(steps.knot_step, [0, 2, 3, 5])
    # no knots at all: the plain stream
    plain = imu_steps(imu_data, [])
    assert np.array_equal(plain.dt, np.diff(t)) and plain.knot_step.shape == (0,)


def test_segments_are_padded_with_zero_steps():
    steps = imu_steps(samples([0.0, 1.0, 2.0, 3.0, 4.0]), [0.0, 0.5, 3.5, 4.0])
    acc, gyro, dt = steps.segments()
    # segments: [0, 0.5) one step; [0.5, 3.5) four steps (0.5, 1, 1, 0.5); [3.5, 4] one step
    assert dt.shape == (3, 4) and acc.shape == (3, 4, 3) and gyro.shape == (3, 4, 3)
    assert np.array_equal(dt, [[0.5, 0, 0, 0], [0.5, 1.0, 1.0, 0.5], [0.5, 0, 0, 0]])
    assert np.array_equal(acc[:, :, 0], [[0, 0, 0, 0], [0, 1, 2, 3], [3, 0, 0, 0]])
    assert np.array_equal(gyro[:, :, 1], [[0, 0, 0, 0], [0, -0.01, -0.02, -0.03], [-0.03, 0, 0, 0]])
    # padding is zero in every channel
    assert not acc[0, 1:].any() and not gyro[2, 1:].any()


def test_segments_of_a_single_knot_are_empty():
    acc, gyro, dt = imu_steps(samples([0.0, 1.0, 2.0]), [1.0]).segments()
    assert dt.shape[0] == 0 and acc.shape[0] == 0 and gyro.shape[0] == 0


@pytest.mark.parametrize(
    "knots",
    [[-0.001, 1.0], [0.0, 3.0 + 1e-9], [-5.0], [10.0]],
    ids=["before start", "after end", "single before", "single after"],
)
def test_knots_outside_the_imu_span_raise(knots):
    with pytest.raises(ValueError, match="outside the IMU span"):
        imu_steps(samples([0.0, 1.0, 2.0, 3.0]), knots)


def test_nan_knots_raise():
    """A NaN knot is refused as not finite (it would pass a span and an ordering check: every
    comparison with NaN is False)."""
    for knots in ([0.0, np.nan, 3.0], [np.nan]):
        with pytest.raises(ValueError, match="finite"):
            imu_steps(samples([0.0, 1.0, 2.0, 3.0]), knots)


@pytest.mark.parametrize("knots", [[0.0, 1.5, 1.5, 3.0], [0.0, 2.0, 1.0]], ids=["duplicate", "decreasing"])
def test_knots_must_increase_strictly(knots):
    with pytest.raises(ValueError, match="increase strictly"):
        imu_steps(samples([0.0, 1.0, 2.0, 3.0]), knots)


def test_knots_at_both_ends_of_the_span_are_accepted():
    steps = imu_steps(samples([0.0, 1.0, 2.0]), [0.0, 2.0])
    assert np.array_equal(steps.knot_step, [0, 2])
    acc, gyro, dt = steps.segments()
    assert np.array_equal(dt, [[1.0, 1.0]])


@st.composite
def streams_and_knots(draw):
    """IMU times (2..40 strictly increasing samples, gaps from 1e-4 to 0.1 s, starting anywhere
    in [-1000, 1000] s) and sorted unique knots: some on sample times, some strictly inside."""
    n = draw(st.integers(2, 40))
    t0 = draw(st.floats(-1000, 1000, allow_nan=False))
    gaps = draw(st.lists(st.floats(1e-4, 0.1), min_size=n - 1, max_size=n - 1))
    t = t0 + np.concatenate([[0.0], np.cumsum(gaps)])
    t = np.unique(t)  # cumsum at large t0 may round two times together: keep them distinct
    if len(t) < 2:
        t = np.array([t0, t0 + 0.1])
    on = draw(st.lists(st.integers(0, len(t) - 1), max_size=len(t)))
    inside = draw(st.lists(st.floats(0.0, 1.0, exclude_min=True, exclude_max=True), max_size=10))
    knots = np.concatenate([t[on], t[0] + np.array(inside, dtype=float) * (t[-1] - t[0])])
    knots = np.unique(np.clip(knots, t[0], t[-1]))
    return t, knots


@settings(max_examples=100, deadline=None)
@given(streams_and_knots())
def test_steps_tile_the_span_with_zero_order_hold(case):
    t, knots = case
    imu_data = samples(t)
    steps = imu_steps(imu_data, knots)
    new_times = np.setdiff1d(knots, t)  # knots strictly between samples
    grid = np.union1d(t, knots)
    assert len(steps.dt) == len(t) - 1 + len(new_times)
    assert np.array_equal(steps.t, grid[:-1])
    assert np.array_equal(steps.dt, np.diff(grid))
    assert np.all(steps.dt > 0)
    span = t[-1] - t[0]
    assert abs(steps.dt.sum() - span) <= 4 * len(steps.dt) * EPS * max(abs(t[0]), abs(t[-1]), span)
    # zero-order hold: the step starting at s holds the last sample at or before s
    k = np.rint(steps.acc[:, 0]).astype(int)
    assert np.array_equal(steps.acc, imu_data.acc[k]) and np.array_equal(steps.gyro, imu_data.gyro[k])
    assert np.all(t[k] <= steps.t) and np.all(steps.t < t[k + 1])
    # knot_step: the step that starts at each knot (or the end of the steps at the last sample)
    assert np.all(np.append(steps.t, t[-1])[steps.knot_step] == knots)

    acc, gyro, dt = steps.segments()
    lengths = np.diff(steps.knot_step)
    assert dt.shape == (max(len(knots) - 1, 0), max(int(lengths.max(initial=0)), 1))
    for j, (start, n) in enumerate(zip(steps.knot_step[:-1], lengths)):
        assert np.array_equal(dt[j, :n], steps.dt[start:start + n])
        assert np.array_equal(acc[j, :n], steps.acc[start:start + n])
        assert np.array_equal(gyro[j, :n], steps.gyro[start:start + n])
        assert not dt[j, n:].any() and not acc[j, n:].any() and not gyro[j, n:].any()
        assert abs(dt[j].sum() - (knots[j + 1] - knots[j])) <= 4 * (n + 1) * EPS * max(abs(t[0]), abs(t[-1]), span)


@settings(max_examples=100, deadline=None)
@given(streams_and_knots())
def test_interval_steps_are_those_of_steps_between_bit_for_bit(case):
    t, knots = case
    imu_data = samples(t)
    for t_from, t_to in zip(knots[:-1], knots[1:]):
        steps = steps_between(imu_data.t, imu_data.acc, imu_data.gyro, [t_from, t_to])
        a, b = steps.knot_step
        acc, gyro, dt = interval_steps(imu_data.t, imu_data.acc, imu_data.gyro, t_from, t_to)
        assert np.array_equal(acc, steps.acc[a:b]) and np.array_equal(gyro, steps.gyro[a:b])
        assert np.array_equal(dt, steps.dt[a:b])


def test_preintegrated_segments_reproduce_the_steps_at_every_knot():
    """The use the smoother makes of the timeline: preintegrate the padded segments in one call and
    chain the predictions from knot to knot; they equal ``imu.integrate`` over all the steps, read
    at ``knot_step``, to 1e-9. Knots are placed off the 200 Hz sample grid (and two on it)."""
    rng = np.random.default_rng(0)
    n = 400
    t = np.cumsum(rng.uniform(4e-3, 6e-3, n))
    acc = np.array([0.0, 0.0, 9.81]) + rng.normal(0, 3, (n, 3))
    gyro = np.array([0.5, -1.0, 2.0]) + rng.normal(0, 0.5, (n, 3))
    knots = np.sort(np.concatenate([[t[0], t[123], t[-1]], rng.uniform(t[0], t[-1], 5)]))
    steps = imu_steps(ImuSamples(t, acc, gyro), knots)
    x0 = imu.ImuState(np.array([1.0, 2.0, 3.0]), np.array([1.0, 0.0, -0.5]), so3.exp(np.array([0.2, 0.1, -1.0])),
                      np.array([0.05, -0.02, 0.1]), np.array([0.01, 0.02, -0.03]))
    truth = imu.integrate(x0, steps.acc, steps.gyro, steps.dt)[steps.knot_step]

    seg_acc, seg_gyro, seg_dt = steps.segments()
    pre = preintegration.integrate(seg_acc, seg_gyro, seg_dt, np.broadcast_to(x0.b_w, (len(seg_dt), 3)))
    x = x0
    for j in range(len(seg_dt)):
        x = preintegration.predict(pre[j], x)
        err = imu.boxminus(x, truth[j + 1])
        assert np.abs(err).max() < 1e-9, (j, err)
    assert np.allclose(pre.duration, np.diff(knots), rtol=0, atol=1e-12)
