"""Simulated calibration errors (datasets/simulated_sensors.py): a speed sensor reading a scale of
the truth, a sensor stamped late."""
from __future__ import annotations

import numpy as np
import pytest

from datasets.simulate import simulate
from datasets.simulated_sensors import SensorSpec, scaled_speeds, stamped_late
from factors.errors import InputError


@pytest.fixture(scope="module")
def data():
    return simulate("gentle", duration=3.0, seed=1, imu_rate=100.0, pose_rate=0,
                    sensors=(SensorSpec("wheels", "velocity", 20.0, 0.05), SensorSpec("gnss", "gnss", 5.0, 0.2)))


def test_scaled_speeds_read_the_scale_of_the_velocity_with_their_covariance(data):
    scaled = scaled_speeds(data, "wheels", 0.99).sensor("wheels").data
    given = data.sensor("wheels").data
    np.testing.assert_array_equal(scaled.velocity, 0.99 * given.velocity)
    np.testing.assert_array_equal(scaled.cov, 0.99**2 * given.cov)
    np.testing.assert_array_equal(scaled.t, given.t)


def test_a_scale_on_a_sensor_that_reads_no_speed_is_refused_naming_it(data):
    with pytest.raises(InputError, match="'gnss' is a gnss sensor; expected a velocity one"):
        scaled_speeds(data, "gnss", 0.99)


def test_stamped_late_shifts_the_stamps_and_drops_those_past_the_imu(data):
    late = stamped_late(data, "gnss", 0.1).sensor("gnss").data
    given = data.sensor("gnss").data
    kept = given.t + 0.1 <= data.imu.t[-1]
    assert not kept.all()  # the last fix, at the IMU's end, would be stamped after it
    np.testing.assert_array_equal(late.t, given.t[kept] + 0.1)
    np.testing.assert_array_equal(late.position, given.position[kept])
