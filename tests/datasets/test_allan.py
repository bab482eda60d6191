"""Allan deviation: exact on white noise, and the four densities of synthetic white noise plus
random walk recovered within 15%."""
from __future__ import annotations

import numpy as np
import pytest

from datasets.allan import allan, allan_deviation
from datasets.types import ImuSamples

DT = 0.01
WHITE = np.array([2e-3, 1e-3, 5e-3, 2e-4, 1e-4, 4e-4])  # acc x y z [m/s^2/sqrt(Hz)], gyro [rad/s/sqrt(Hz)]
WALK = 10 * WHITE  # [m/s^3/sqrt(Hz)], [rad/s^2/sqrt(Hz)]


def test_white_noise_follows_the_minus_half_line():
    rng = np.random.default_rng(1)
    tau, adev = allan_deviation(0.01 / np.sqrt(DT) * rng.normal(size=200_000), DT)
    assert tau[0] == DT and np.all(np.diff(tau) > 0) and tau[-1] <= 200_000 * DT / 4
    few = tau < 10  # thousands of clusters: the estimate is within a few per cent
    assert np.abs(adev[few] * np.sqrt(tau[few]) / 0.01 - 1).max() < 0.05


def test_densities_of_white_noise_and_random_walk():
    rng = np.random.default_rng(7)
    n = 60_000  # 10 minutes at 100 Hz
    x = WHITE / np.sqrt(DT) * rng.normal(size=(n, 6)) + np.cumsum(WALK * np.sqrt(DT) * rng.normal(size=(n, 6)), axis=0)
    x[:, 2] += 9.81  # a constant (gravity) does not change an Allan deviation
    imu = ImuSamples(1.7e9 + DT * np.arange(n), x[:, :3], x[:, 3:])
    result = allan(imu)
    white = np.r_[result.acc_white, result.gyro_white]
    walk = np.r_[result.acc_walk, result.gyro_walk]
    assert result.dt == pytest.approx(DT)
    assert np.abs(white / WHITE - 1).max() < 0.15, white / WHITE
    assert np.abs(walk / WALK - 1).max() < 0.15, walk / WALK
    noise = result.noise()
    assert (noise.acc, noise.gyro_bias) == (result.acc_white.max(), result.gyro_walk.max())


def test_too_short():
    with pytest.raises(ValueError, match="at least two IMU samples"):
        allan(ImuSamples([0.0], np.zeros((1, 3)), np.zeros((1, 3))))
    with pytest.raises(ValueError, match="too few cluster times"):
        allan(ImuSamples(np.arange(8.0), np.zeros((8, 3)), np.zeros((8, 3))))


def test_a_random_walk_the_recording_cannot_show_is_not_estimated():
    """Two seconds of a good IMU (random walks far below the white noise): the white noise is
    measured, the random walks are NaN, and the note asks for a longer recording. With 10
    independent clusters at most at 0.2 s the curve cannot rise with the +1/2 slope yet."""
    rng = np.random.default_rng(3)
    n, white, walk = 200, WHITE, WHITE / 100
    x = white / np.sqrt(DT) * rng.normal(size=(n, 6)) + np.cumsum(walk * np.sqrt(DT) * rng.normal(size=(n, 6)), axis=0)
    result = allan(ImuSamples(DT * np.arange(n), x[:, :3], x[:, 3:]))
    assert np.abs(np.r_[result.acc_white, result.gyro_white] / WHITE - 1).max() < 0.3
    assert np.all(np.isnan(result.acc_walk)) and np.all(np.isnan(result.gyro_walk))
    assert result.record_s == pytest.approx(2.0) and result.walk_record_s >= 3 * result.record_s and result.walk_beyond
    note = result.walk_note()
    assert ("random walk not estimated (accelerometer x" in note
            and f"record at least {result.walk_record_s:.4g} s" in note)
    with pytest.raises(ValueError, match="random walk not estimated"):
        result.noise()
