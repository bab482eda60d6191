"""Keyframes on a grid with the measurements between them attached to the keyframe before (docs/design.md,
keyframes) against keyframes at every measurement time, on a rig whose speed sensor is faster than the
grid: the same trajectory and calibrations to a fraction of their sigma, and a consistent one."""
from __future__ import annotations

import functools
import warnings

import numpy as np
import pytest

from datasets.simulate import simulate
from datasets.simulated_sensors import SensorSpec, scaled_speeds, stamped_late
from factors import imu, so3
from factors.calibration import CalibrationPrior
from smoother.batch.solve import solve_batch
from smoother.ekf.calibrated import run_calibrated_ekf
from smoother.evaluation import metrics
from smoother.model.problem import build_problem, calibration_set
from smoother.model.timeline import EVERY_MEASUREMENT
from smoother.online.replay import replay
from smoother.stats import nees_bounds

SEEDS = range(20)
DURATION_S = 8.0


@functools.lru_cache(maxsize=None)
def rig(seed: int):
    """A 200 Hz IMU, a speed sensor (velocity, 100 Hz) pitched 3 deg and reading 1 % low, a GNSS
    antenna (1 Hz) 0.5 m above the IMU whose fixes are stamped 0.05 s late (between 10 Hz
    keyframes), the wheels' rotation and scale and the fixes' time offset to estimate."""
    pitched, antenna = np.eye(4), np.eye(4)
    pitched[:3, :3] = so3.exp(np.radians([0.0, 3.0, 0.0]))
    antenna[:3, 3] = [0.0, 0.0, 0.5]
    data = simulate("gentle", duration=DURATION_S, seed=seed, imu_rate=200.0, pose_rate=0,
                    sensors=(SensorSpec("wheels", "velocity", 100.0, 0.05, pitched),
                             SensorSpec("gnss", "gnss", 1.0, 0.1, antenna)))
    data = stamped_late(scaled_speeds(data, "wheels", 0.99), "gnss", 0.05)
    data = data.with_sensor("wheels", calibrate=CalibrationPrior(("rotation", "scale")))
    return data.with_sensor("gnss", calibrate=CalibrationPrior(("time_offset",)))


@functools.lru_cache(maxsize=None)
def batch(seed: int, rate):
    data = rig(seed)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        start = run_calibrated_ekf(data, calibration_set(data), progress=False).trajectory
        problem = build_problem(data, rate, start=start)
        return problem, solve_batch(problem)


def _worst_sigma(coarse, fine) -> float:
    """The largest difference of the coarse trajectory from the fine one at the coarse one's
    times, in the fine one's sigmas, over every error-state component."""
    at = np.searchsorted(fine.t, coarse.t)
    np.testing.assert_array_equal(fine.t[at], coarse.t)
    d = imu.boxminus(coarse.states, fine.states[at])
    return float(np.max(np.abs(d) / np.sqrt(np.diagonal(fine.cov[at], axis1=1, axis2=2))))


def test_the_rig_attaches_the_speed_sensor_and_the_fixes_to_10_hz_keyframes():
    problem, _ = batch(0, 10.0)
    record = problem.keyframes
    assert record["rate_hz"] == 10.0 and record["count"] == 81
    # of 801 speeds and 8 fixes, every speed off the grid (9 of 10) and every fix is attached
    assert record["measurements"] == 801 + 8 and record["attached"] == 720 + 8
    assert record["max_attached_distance_s"] == pytest.approx(0.09, abs=1e-12)
    full, _ = batch(0, EVERY_MEASUREMENT)
    assert full.keyframes["attached"] == 0 and full.keyframes["count"] == 801  # the fixes at speed times


@pytest.mark.parametrize("seed", SEEDS)
def test_10_hz_keyframes_give_the_batch_trajectory_and_calibrations_of_keyframes_at_every_measurement(seed):
    """Every state of the 10 Hz run within 0.2 sigma of the run with a keyframe at every
    measurement time (sigma: the latter's marginal), in every error-state component, and every
    calibration coordinate within 0.2 of its sigma."""
    _, coarse = batch(seed, 10.0)
    _, fine = batch(seed, EVERY_MEASUREMENT)
    assert _worst_sigma(coarse.trajectory, fine.trajectory) < 0.2
    for a, b, cov in zip(coarse.calibration.values, fine.calibration.values, fine.calibration_cov):
        columns = fine.calibration.priors[fine.calibration.names.index("wheels")].columns if len(cov) == 4 else [0]
        offset = a.boxminus(b)[columns]
        assert np.all(np.abs(offset) < 0.2 * np.sqrt(np.diag(cov))), (offset, np.sqrt(np.diag(cov)))


def test_10_hz_keyframes_are_consistent_over_20_seeds():
    """The pose NEES of the last keyframe of the 10 Hz runs, summed over the 20 seeds, within its
    95 % chi-square interval."""
    total = 0.0
    for seed in SEEDS:
        _, result = batch(seed, 10.0)
        t = result.trajectory
        truth = rig(seed).truth.interpolate(t.t[-1:])[0]
        total += float(metrics.nees(truth, t.states[-1:], t.cov[-1:], "pose")[0])
    low, high = nees_bounds(6, len(SEEDS))
    assert low <= total / len(SEEDS) <= high, (total / len(SEEDS), low, high)


@pytest.mark.parametrize("seed", SEEDS[:5])
def test_10_hz_keyframes_give_the_fixed_lag_trajectory_of_keyframes_at_every_measurement(seed):
    """The sliding window fed the rig live (its mountings and offsets as given): every smoothed
    keyframe of the 10 Hz run within 0.2 sigma of the same keyframe with a keyframe at every
    measurement time. A measurement between keyframes reaches the window with the keyframe after
    it, so a keyframe leaving the 10 Hz window at the update of ``t`` has seen the data up to the
    keyframe before ``t``; the lags (2.05 s, 2.005 s, neither on a keyframe's grid) give both runs
    the same data for every keyframe. (With its calibrations estimated the window's own
    linearisation points of the calibrations, moved at different updates in the two runs, part
    them by up to about 0.4 sigma.)"""
    data = rig(seed).with_sensor("wheels", calibrate=None).with_sensor("gnss", calibrate=None)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        coarse = replay(data, 2.05, keyframe_rate=10.0, progress=False).smoothed
        fine = replay(data, 2.005, keyframe_rate=EVERY_MEASUREMENT, progress=False).smoothed
    assert _worst_sigma(coarse, fine) < 0.2
