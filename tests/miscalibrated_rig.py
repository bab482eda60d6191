"""A rig written as a user would, whose sensors are mounted otherwise: the calibration tests' shared
case (the batch smoother's, tests/smoother/test_calibration_estimates.py, and the sliding
window's, tests/smoother/fixed_lag/sliding/test_window_calibration.py)."""
from __future__ import annotations

from dataclasses import replace

import numpy as np

from datasets.simulate import simulate
from datasets.simulated_sensors import SensorSpec, scaled_speeds, stamped_late
from factors import so3

#: A 3 deg pitched and 1 deg yawed speed sensor.
PITCHED = np.eye(4)
PITCHED[:3, :3] = so3.exp(np.radians([0.0, 3.0, 1.0]))


def miscalibrated_rig(seed: int, duration: float = 30.0, profile="gentle", **kw):
    """A wheel speed sensor (velocity, 10 Hz) pitched 3 deg and yawed 1 deg, reading 1 % low, and a
    GNSS antenna (5 Hz) 0.5 m above the IMU whose fixes are stamped 0.1 s late; returned with the
    values a user would write: identity mountings, no offsets."""
    antenna = np.eye(4)
    antenna[:3, 3] = [0.0, 0.0, 0.5]
    data = simulate(profile, duration=duration, seed=seed, pose_rate=0, **kw,
                    sensors=(SensorSpec("wheels", "velocity", 10.0, 0.05, PITCHED), SensorSpec("gnss", "gnss", 5.0, 0.1,
                                                                                             antenna)))
    data = stamped_late(scaled_speeds(data, "wheels", 0.99), "gnss", 0.1)
    for name in ("wheels", "gnss"):
        data = data.with_sensor(name, data=replace(data.sensor(name).data, T_BS=np.eye(4)))
    return data
