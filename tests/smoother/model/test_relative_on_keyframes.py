"""Relative measurements faster than the keyframe grid composed between keyframes
(smoother/model/timeline.py, the odometry kind's ``compose``): the composition and its covariance,
where the chains are cut, and the smoothers on a 50 Hz odometry against keyframes at every end."""
from __future__ import annotations

import functools
import warnings
from dataclasses import replace

import estimator_cases as cases
import numpy as np
import pytest

from datasets.kinds import KINDS
from datasets.simulate import simulate
from datasets.types import RelativePoseMeasurements
from factors import so3
from factors.selfcheck import random_rotation
from smoother.batch.solve import solve_batch
from smoother.commands.run import keyframe_line
from smoother.model.blocks import Layout
from smoother.model.problem import build_problem
from smoother.model.timeline import (
    EVERY_MEASUREMENT,
    keyframe_times,
    relative_anchors,
    relative_on_keyframes,
    relative_spans,
)
from smoother.online.replay import replay

ODOMETRY = KINDS["odometry"]


def _chain(rng, n: int) -> RelativePoseMeasurements:
    """``n`` consecutive random steps (up to half a metre, any rotation) with random covariances."""
    t = np.cumsum(rng.uniform(0.01, 0.03, n + 1))
    A = rng.normal(size=(n, 6, 6)) * 0.01
    cov = A @ np.swapaxes(A, 1, 2) + 1e-4 * np.eye(6)
    return RelativePoseMeasurements(t[:-1], t[1:], rng.normal(size=(n, 3)) * 0.3,
                                    np.stack([random_rotation(rng) for _ in range(n)]), cov)


def _compose_values(dr, dC):
    out_r, out_C = dr[0], dC[0]
    for r, C in zip(dr[1:], dC[1:]):
        out_r, out_C = out_r + out_C @ r, out_C @ C
    return out_r, out_C


def test_a_span_composes_into_the_relative_pose_of_its_ends_with_its_noise_propagated():
    """A span's composed measurement is the product of its steps (the pose of its end in its start's
    frame), and its covariance is ``sum_k J_k S_k J_k^T`` with ``J_k`` the composed error's Jacobian
    with respect to step ``k``'s noise (``dr + n_r``, ``exp(n_Phi) dC``) by central differences."""
    rng = np.random.default_rng(3)
    data = _chain(rng, 7)
    composed = ODOMETRY.compose(data, np.array([[0, 3], [3, 7]]))
    assert np.array_equal(composed.t_from, data.t_from[[0, 3]]) and np.array_equal(composed.t_to, data.t_to[[2, 6]])
    for s, (lo, hi) in enumerate([(0, 3), (3, 7)]):
        r, C = _compose_values(data.dr[lo:hi], data.dC[lo:hi])
        np.testing.assert_allclose(composed.dr[s], r, atol=1e-12)
        np.testing.assert_allclose(composed.dC[s], C, atol=1e-12)
        expected = np.zeros((6, 6))
        for k in range(lo, hi):
            J = np.zeros((6, 6))
            for a in range(6):
                def error(eps, k=k, a=a):
                    n = np.zeros(6)
                    n[a] = eps
                    dr, dC = data.dr[lo:hi].copy(), data.dC[lo:hi].copy()
                    dr[k - lo] += n[:3]
                    dC[k - lo] = so3.exp(n[3:]) @ dC[k - lo]
                    r2, C2 = _compose_values(dr, dC)
                    return np.concatenate([r2 - r, so3.log(C2 @ C.T)])
                J[:, a] = (error(1e-6) - error(-1e-6)) / 2e-6
            expected += J @ data.cov[k] @ J.T
        np.testing.assert_allclose(composed.cov[s], expected, rtol=1e-6, atol=1e-12)


def test_anchors_cut_chains_on_the_grid_and_at_their_breaks_and_are_their_own_anchors_once_composed():
    """On a 10 Hz grid a 50 Hz chain keeps an end about every 0.1 s, every chain's start and end
    (a dropped message breaks a chain), and the composed measurements' ends are the same anchors:
    composing again changes nothing."""
    t = np.round(np.arange(0.0, 2.0001, 0.02), 10)
    keep = np.ones(len(t) - 1, dtype=bool)
    keep[37] = False  # a message lost: the chain breaks at t[37] .. t[38]
    t_from, t_to = t[:-1][keep], t[1:][keep]
    anchors = relative_anchors(t_from, t_to, 10.0)
    assert {0.0, t[37], t[38], 2.0} <= set(anchors.tolist())
    assert np.all(np.diff(anchors) <= 0.1 + 1e-9) and len(anchors) <= 2 * 10 + 4
    spans = relative_spans(t_from, t_to, anchors)
    assert np.array_equal(t_from[spans[:, 0]], anchors[:-1][np.isin(anchors[:-1], t_from)])
    assert set(t_to[spans[:, 1] - 1]) <= set(anchors)
    rng = np.random.default_rng(0)
    n = len(t_from)
    data = RelativePoseMeasurements(t_from, t_to, rng.normal(size=(n, 3)) * 0.01,
                                    np.stack([so3.exp(v) for v in rng.normal(size=(n, 3)) * 0.01]), np.eye(6) * 1e-4)
    composed = ODOMETRY.compose(data, spans)
    np.testing.assert_array_equal(relative_anchors(composed.t_from, composed.t_to, 10.0), anchors)
    assert len(relative_spans(composed.t_from, composed.t_to, anchors)) == len(composed.t_to)


@functools.lru_cache(maxsize=None)
def _odometry_rig():
    """20 s gentle, 200 Hz IMU, 50 Hz odometry, 1 Hz positions."""
    return simulate("gentle", duration=20.0, seed=1, imu_rate=200.0, pose_rate=None, odometry_rate=50.0,
                    position_rate=1.0)


def test_fast_odometry_adds_no_keyframes_and_the_batch_keeps_its_estimate():
    """The 50 Hz odometry composed onto the 10 Hz grid: about 10 keyframes a second instead of 50,
    every odometry factor between consecutive keyframes, and the batch smoother's states within
    0.1 sigma of those with a keyframe at every end (the composition is exact; only its first-order
    covariance and the IMU's share differ)."""
    data = _odometry_rig()
    grid, every = build_problem(data), build_problem(data, EVERY_MEASUREMENT)
    assert len(grid.times) <= 10 * 20 + 2 and len(every.times) >= 50 * 20
    odometry = next(b for b in grid.blocks if b.name == "odometry")
    assert np.all(np.diff(odometry.keyframes, axis=1) == 1) and len(odometry) == len(grid.times) - 1
    on_grid, full = solve_batch(grid), solve_batch(every)
    at = np.searchsorted(every.times, grid.times)
    np.testing.assert_array_equal(every.times[at], grid.times)
    sigma = cases.sigma_difference(on_grid.trajectory.states, full.trajectory.states[at], full.trajectory.cov[at])
    assert sigma.max() < 0.1, sigma.max()


def test_the_fixed_lag_smoother_reads_the_same_composed_odometry_on_the_same_keyframes():
    """The replayed online smoother gets the composed measurements, so it keeps the batch smoother's
    keyframes and skips none of them."""
    data = _odometry_rig()
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        result = replay(data, lag_s=2.0, covariances=False)
    np.testing.assert_array_equal(result.smoothed.t, keyframe_times(data))
    assert not any(result.skipped.values())
    odometry = [next(s.data for s in d.sensors if s.kind == "odometry")
                for d in (data, relative_on_keyframes(data, keyframe_times(data)))]
    assert len(odometry[1].t_to) < len(odometry[0].t_to) / 4


def test_odometry_starting_between_grid_ticks_keeps_its_factors_on_consecutive_keyframes():
    """Where an odometry's chains run, their anchors stand in for the grid (a grid tick between two
    anchors would leave the composed measurement spanning three keyframes): the factors stay on
    consecutive keyframes, a chain of them (the batch's orders from the structure)."""
    data = _odometry_rig()
    sensors = tuple(replace(s, data=s.data.subset(slice(3, None))) if s.kind == "odometry" else s for s in data.sensors)
    late = replace(data, sensors=sensors)  # the odometry begins at 0.06 s, between the 10 Hz ticks
    problem = build_problem(late)
    odometry = next(b for b in problem.blocks if b.name == "odometry")
    assert np.all(np.diff(odometry.keyframes, axis=1) == 1)
    assert len(problem.times) <= 10 * 20 + 4
    assert Layout.of(problem.initial_states, problem.calibration, problem.blocks).chain
    n = len(next(s.data for s in late.sensors if s.kind == "odometry").t_to)
    assert (problem.keyframes["relative"], problem.keyframes["composed"]) == (n, len(odometry))
    assert keyframe_line(problem.keyframes, False).endswith(
        f"; {n} relative measurements composed into {len(odometry)} between keyframes")


@pytest.mark.parametrize("rate", [EVERY_MEASUREMENT, 50.0])
def test_where_every_end_is_a_keyframe_the_dataset_is_left_as_it_is(rate):
    data = _odometry_rig()
    assert relative_on_keyframes(data, keyframe_times(data, rate)) is data


def test_an_odometry_slower_than_the_grid_keeps_the_grid_between_its_ends():
    """2 Hz odometry on the 10 Hz grid: nothing to compose, and the grid's keyframes stay between
    its ends (each measurement then spans several keyframes, as before any composition)."""
    data = simulate("gentle", duration=6.0, seed=5, imu_rate=200.0, pose_rate=None, position_rate=20.0,
                    odometry_rate=2.0)
    times = keyframe_times(data)
    assert relative_on_keyframes(data, times) is data
    assert np.all(np.diff(times) <= 0.1 + 1e-9) and len(times) >= 10 * 6
