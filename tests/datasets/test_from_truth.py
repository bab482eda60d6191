"""Pose and position measurements drawn from a ground truth."""
from __future__ import annotations

import numpy as np
import pytest

from datasets.from_truth import (measurement_indices, measurements_from_truth, pose_measurements_from_truth,
                                 position_measurements_from_truth)
from datasets.types import Trajectory
from factors import so3
from factors.imu import ImuState


def _truth(n=2001, rate=200.0, t0=0.0, seed=0):
    rng = np.random.default_rng(seed)
    t = t0 + np.arange(n) / rate
    r = np.cumsum(rng.normal(scale=0.01, size=(n, 3)), axis=0)
    C = so3.exp(np.cumsum(rng.normal(scale=0.01, size=(n, 3)), axis=0))
    z = np.full((n, 3), np.nan)
    return Trajectory(t, ImuState(r, z, C, z, z))


def test_indices_every_tenth_sample_and_exact_times():
    truth = _truth()
    k = measurement_indices(truth.t, 20.0)
    assert np.array_equal(k, np.arange(0, 2001, 10))
    m = position_measurements_from_truth(truth, 20.0, 0.1, seed=1)
    assert np.array_equal(m.t, truth.t[k])  # exact truth stamps, never interpolated


def test_indices_with_an_offset_start_and_irregular_truth():
    t = 100.0 + np.array([0.0, 0.004, 0.011, 0.019, 0.021, 0.03, 0.041, 0.05, 0.062])
    # 50 Hz ticks at 100.0, 100.02, 100.04, 100.06 -> first samples at or after them.
    assert np.array_equal(measurement_indices(t, 50.0), [0, 4, 6, 8])


def test_rate_above_the_truth_rate_is_refused():
    with pytest.raises(ValueError, match="above the rate of the ground truth"):
        measurement_indices(_truth().t, 500.0)
    for bad in (0.0, -1.0, np.nan, "x"):
        with pytest.raises(ValueError, match="rate_hz"):
            measurement_indices(_truth().t, bad)


def test_pose_noise_is_the_primers_left_perturbation_with_the_stated_covariance():
    truth = _truth()
    pos_sigma, rot_sigma, seed = 0.05, 0.02, 7
    m = pose_measurements_from_truth(truth, 100.0, pos_sigma, rot_sigma, seed=seed)
    k = measurement_indices(truth.t, 100.0)
    # Reproduce the draws: positions first, then attitude noise, from default_rng(seed).
    rng = np.random.default_rng(seed)
    n_p = pos_sigma * rng.standard_normal((len(k), 3))
    n_phi = rot_sigma * rng.standard_normal((len(k), 3))
    assert np.allclose(m.position - truth.position[k], n_p, atol=1e-15)
    # C_meas = exp(n) C: the world-frame error log(C_meas C^T) is n itself.
    assert np.allclose(so3.boxminus(m.C, truth.C[k]), n_phi, atol=1e-12)
    # ... and not the body-frame (right) perturbation C exp(n).
    assert not np.allclose(so3.log(np.swapaxes(truth.C[k], 1, 2) @ m.C), n_phi, atol=1e-4)
    assert np.allclose(m.cov, np.diag([pos_sigma**2] * 3 + [rot_sigma**2] * 3))


def test_noise_statistics_match_the_sigmas():
    truth = _truth(n=40001)
    m = pose_measurements_from_truth(truth, 200.0, 0.3, 0.01, seed=3)
    k = measurement_indices(truth.t, 200.0)
    e_p = m.position - truth.position[k]
    e_r = so3.boxminus(m.C, truth.C[k])
    # 40001 samples per axis: the sample std is within 2% of sigma with overwhelming probability.
    assert np.allclose(e_p.std(axis=0), 0.3, rtol=0.02)
    assert np.allclose(e_r.std(axis=0), 0.01, rtol=0.02)
    g = position_measurements_from_truth(truth, 200.0, 0.5, seed=4)
    assert np.allclose((g.position - truth.position[k]).std(axis=0), 0.5, rtol=0.02)
    assert np.allclose(g.cov, 0.25 * np.eye(3))


def test_seeded_and_reproducible():
    truth = _truth()
    a = pose_measurements_from_truth(truth, 10.0, 0.1, 0.01, seed=5)
    b = pose_measurements_from_truth(truth, 10.0, 0.1, 0.01, seed=5)
    c = pose_measurements_from_truth(truth, 10.0, 0.1, 0.01, seed=6)
    assert np.array_equal(a.position, b.position) and np.array_equal(a.C, b.C)
    assert not np.allclose(a.position, c.position)
    gen = np.random.default_rng(5)
    d = pose_measurements_from_truth(truth, 10.0, 0.1, 0.01, seed=gen)
    assert np.array_equal(a.position, d.position)


@pytest.mark.parametrize("kwargs", [dict(pos_sigma=0.0), dict(pos_sigma=-1.0), dict(rot_sigma=np.inf)])
def test_bad_sigmas(kwargs):
    args = dict(rate_hz=10.0, pos_sigma=0.1, rot_sigma=0.01)
    args.update(kwargs)
    name = next(iter(kwargs))
    with pytest.raises(ValueError, match=name):
        pose_measurements_from_truth(_truth(), **args)


def test_pose_and_gps_of_one_dataset_have_independent_noise():
    """One seed for both kinds drew the same position noise twice: at a common rate the GPS fixes
    sat exactly on the pose sensor's positions. Spawned streams: uncorrelated, and reproducible."""
    truth = _truth(n=20001)
    pose, gps = measurements_from_truth(truth, (20.0, 0.1, 0.01), (20.0, 0.1), seed=3)
    assert np.array_equal(pose.t, gps.t)
    k = np.searchsorted(truth.t, pose.t)
    n_pose, n_gps = pose.position - truth.position[k], gps.position - truth.position[k]
    assert abs(np.corrcoef(n_pose.ravel(), n_gps.ravel())[0, 1]) < 0.1  # 6000 pairs: |r| ~ 0.013
    again, _ = measurements_from_truth(truth, (20.0, 0.1, 0.01), None, seed=3)
    assert np.array_equal(again.position, pose.position) and np.array_equal(again.C, pose.C)


@pytest.mark.parametrize("pose, gps, name", [((1e4, 0.1, 0.01), None, "pose_from_truth: rate_hz"),
                                             (None, (10.0, -1.0), "gps_from_truth: pos_sigma")])
def test_measurements_from_truth_names_the_kind_at_fault(pose, gps, name):
    with pytest.raises(ValueError, match=name):
        measurements_from_truth(_truth(), pose, gps)
