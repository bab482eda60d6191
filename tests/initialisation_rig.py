"""The mounted sensors the self-initialisation tests start from: a camera pose, a GNSS antenna and
a wheel speed sensor, each turned and offset from the IMU (shared by the tests of how the start
is found and of the estimators started from it)."""
from __future__ import annotations

import numpy as np

from datasets.simulated_sensors import SensorSpec
from factors import so3


def mounting(rotation_vector, lever) -> np.ndarray:
    """``T_BS`` (4, 4) of a sensor turned by ``rotation_vector`` [rad] at ``lever`` [m]."""
    T = np.eye(4)
    T[:3, :3], T[:3, 3] = so3.exp(np.asarray(rotation_vector, dtype=float)), lever
    return T


CAMERA = SensorSpec("camera", "pose", 10, (0.05, 0.01), mounting([0.3, -1.2, 0.5], [0.15, 0.05, -0.3]))
GNSS = SensorSpec("gnss", "gnss", 1, 0.3, mounting([0, 0, 0], [0.2, -0.4, 0.9]))
WHEEL = SensorSpec("wheel", "velocity", 10, 0.05, mounting([0, 0, 0.4], [-0.6, 0.3, -0.35]))
