"""Sensors drawn from a ground truth: the measurement ticks, the kinds' noise, the streams."""
from __future__ import annotations

import numpy as np
import pytest

from datasets.simulated_sensors import SensorSpec, measurement_indices, sensor_stream, sensors_from_truth, truth_sensors
from datasets.types import ImuSamples, Trajectory
from factors import so3
from factors.imu import ImuState


def _truth(n=2001, rate=200.0, t0=0.0, seed=0):
    rng = np.random.default_rng(seed)
    t = t0 + np.arange(n) / rate
    r = np.cumsum(rng.normal(scale=0.01, size=(n, 3)), axis=0)
    C = so3.exp(np.cumsum(rng.normal(scale=0.01, size=(n, 3)), axis=0))
    z = np.full((n, 3), np.nan)
    return Trajectory(t, ImuState(r, z, C, np.zeros((n, 3)), np.zeros((n, 3))))


def _imu(truth):
    return ImuSamples(truth.t, np.zeros((len(truth.t), 3)), np.zeros((len(truth.t), 3)))


def _drawn(truth, *specs, seed=0):
    return {s.name: s.data for s in sensors_from_truth(truth, _imu(truth), specs, seed)}


def test_indices_every_tenth_sample_and_exact_times():
    truth = _truth()
    k = measurement_indices(truth.t, 20.0)
    assert np.array_equal(k, np.arange(0, 2001, 10))
    m = _drawn(truth, SensorSpec("gps", "position", 20.0, 0.1))["gps"]
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
    m = _drawn(truth, SensorSpec("pose", "pose", 100.0, (pos_sigma, rot_sigma)), seed=seed)["pose"]
    k = measurement_indices(truth.t, 100.0)
    # Reproduce the draws: positions first, then attitude noise, from the sensor's own stream.
    rng = np.random.default_rng(sensor_stream(np.random.SeedSequence(seed), "pose"))
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
    drawn = _drawn(truth, SensorSpec("pose", "pose", 200.0, (0.3, 0.01)), SensorSpec("gps", "position", 200.0, 0.5),
                   seed=3)
    m, g = drawn["pose"], drawn["gps"]
    k = measurement_indices(truth.t, 200.0)
    e_p = m.position - truth.position[k]
    e_r = so3.boxminus(m.C, truth.C[k])
    # 40001 samples per axis: the sample std is within 2% of sigma with overwhelming probability.
    assert np.allclose(e_p.std(axis=0), 0.3, rtol=0.02)
    assert np.allclose(e_r.std(axis=0), 0.01, rtol=0.02)
    assert np.allclose((g.position - truth.position[k]).std(axis=0), 0.5, rtol=0.02)
    assert np.allclose(g.cov, 0.25 * np.eye(3))


def test_seeded_reproducible_and_independent_of_the_other_sensors():
    truth = _truth()
    spec = SensorSpec("pose", "pose", 10.0, (0.1, 0.01))
    a = _drawn(truth, spec, seed=5)["pose"]
    b = _drawn(truth, SensorSpec("gps", "position", 5.0, 1.0), spec, seed=5)["pose"]
    c = _drawn(truth, spec, seed=6)["pose"]
    assert np.array_equal(a.position, b.position) and np.array_equal(a.C, b.C)
    assert not np.allclose(a.position, c.position)


def test_bad_sigmas_name_the_sensor():
    for sigma in (0.0, -1.0, np.inf, (0.1, 0.2, 0.3)):
        with pytest.raises(ValueError, match="sensor 'pose'.*sigma"):
            _drawn(_truth(), SensorSpec("pose", "pose", 10.0, sigma))


def test_pose_and_gps_of_one_dataset_have_independent_noise():
    """Each sensor its own stream: at a common rate the GPS fixes do not sit on the pose sensor's
    positions, and each is reproducible on its own."""
    truth = _truth(n=20001)
    pose, gps = (s.data for s in truth_sensors(truth, _imu(truth), (20.0, 0.1, 0.01), (20.0, 0.1), seed=3))
    assert np.array_equal(pose.t, gps.t)
    k = np.searchsorted(truth.t, pose.t)
    n_pose, n_gps = pose.position - truth.position[k], gps.position - truth.position[k]
    assert abs(np.corrcoef(n_pose.ravel(), n_gps.ravel())[0, 1]) < 0.1  # 6000 pairs: |r| ~ 0.013
    (again,) = truth_sensors(truth, _imu(truth), (20.0, 0.1, 0.01), None, seed=3)
    assert np.array_equal(again.data.position, pose.position) and np.array_equal(again.data.C, pose.C)


@pytest.mark.parametrize("pose, gps, name", [((1e4, 0.1, 0.01), None, "pose_from_truth: .*rate_hz"),
                                             (None, (10.0, -1.0), "gps_from_truth: .*sigma")])
def test_truth_sensors_name_the_option_at_fault(pose, gps, name):
    truth = _truth()
    with pytest.raises(ValueError, match=name):
        truth_sensors(truth, _imu(truth), pose, gps)
