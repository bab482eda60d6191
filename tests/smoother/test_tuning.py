"""Noise identification by the EKF's likelihood (smoother/tuning.py)."""
from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from datasets.simulate import simulate
from factors.imu import ImuNoise
from smoother.ekf.filter import run_ekf
from smoother.diagnosis.noise_tuning import TUNED, tune_noise

NOISE = ImuNoise(acc=0.05, gyro=0.005, acc_bias=1e-3, gyro_bias=1e-4)


def _simulated(seed=3):
    """30 s of tumbling with accurate position and attitude fixes at 2 Hz: between fixes the IMU
    noise dominates the innovations, so the likelihood sees it (with 10 Hz poses it hardly does)."""
    return simulate("tumbling", duration=30.0, seed=seed, noise=NOISE, pose_rate=None, position_rate=2.0,
                    position_sigma=0.02, orientation_rate=2.0, orientation_sigma=0.002)


@pytest.mark.parametrize("seed", [2, 3])
def test_tuning_recovers_the_white_noise_a_dataset_was_simulated_with(seed):
    """Simulated with known densities, handed over with the accelerometer and gyro noise 30x too
    small: the maximum-likelihood factors bring both back to within a factor 2 (|log10| < 0.3) of
    the truth, and the likelihood rises. (The bias walks are hardly observable in 30 s and are not
    checked.)"""
    data = _simulated(seed)
    truth = data.noise
    wrong = dataclasses.replace(truth, acc=truth.acc / 30.0, gyro=truth.gyro / 30.0)
    result = tune_noise(dataclasses.replace(data, noise=wrong), progress=False)
    assert abs(np.log10(result.noise.acc / truth.acc)) < 0.3, result.summary()
    assert abs(np.log10(result.noise.gyro / truth.gyro)) < 0.3, result.summary()
    assert result.log_likelihood > result.initial_log_likelihood + 100.0
    assert result.log_likelihood == pytest.approx(
        run_ekf(dataclasses.replace(data, noise=result.noise), progress=False).log_likelihood)
    summary = result.summary()
    assert set(summary["scale"]) == set(TUNED)
    assert summary["scale"]["acc"] == pytest.approx(result.noise.acc / wrong.acc)


def test_zero_densities_stay_zero_and_factors_stay_within_bounds():
    data = _simulated()
    noise = dataclasses.replace(data.noise, acc_bias=0.0)
    result = tune_noise(dataclasses.replace(data, noise=noise), max_log10=0.5, progress=False)
    assert result.noise.acc_bias == 0.0 and "acc_bias" not in result.log10_scale
    assert all(abs(x) <= 0.5 for x in result.log10_scale.values())


def test_a_dataset_without_measurements_is_refused():
    data = dataclasses.replace(_simulated(), sensors=())
    with pytest.raises(ValueError, match="needs measurements the EKF uses"):
        tune_noise(data, progress=False)


@pytest.mark.parametrize("options", [{"step": 0.1, "min_step": 0.25}, {"min_step": 0.0}, {"max_log10": 0.0}])
def test_invalid_search_settings_are_refused(options):
    with pytest.raises(ValueError, match="expected 0 < min_step <= step and max_log10 > 0"):
        tune_noise(_simulated(), progress=False, **options)


def test_a_rig_with_named_sensors_can_be_tuned_and_one_with_odometry_only_cannot():
    """The likelihood comes from every sensor the EKF uses, a rig's named ones included (a rig
    with GNSS was refused as having no measurements)."""
    from datasets.simulated_sensors import SensorSpec

    rig = simulate("gentle", duration=5, seed=1, pose_rate=None, sensors=[SensorSpec("gnss", "gnss", 2, 0.3)])
    assert tune_noise(rig, min_step=1.0, max_log10=1.0, progress=False).evaluations > 1
    odometry = simulate("gentle", duration=5, seed=1, pose_rate=None, sensors=[SensorSpec("vo", "odometry", 5, (0.02, 0.01))])
    with pytest.raises(ValueError, match="noise tuning needs measurements the EKF uses"):
        tune_noise(odometry, progress=False)
