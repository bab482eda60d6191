"""Every kind of the registry on a sensor mounted away from the IMU, for the tests that go through
every kind with no list of kinds of their own (``tests/datasets/test_every_kind.py``,
``tests/smoother/test_kinds_in_the_estimators.py``).

Import as ``import mounted_kinds`` (``tests/conftest.py`` puts this directory on ``sys.path``)."""
from __future__ import annotations

import numpy as np
import pytest

from datasets.kinds import KINDS
from datasets.simulate import simulate
from datasets.simulated_sensors import SensorSpec
from factors.selfcheck import random_extrinsic

#: Parametrises a test over every registered kind (``kind``), named by the kind.
EVERY_KIND = pytest.mark.parametrize("kind", KINDS.values(), ids=lambda k: k.name)


def mounting(seed: int) -> np.ndarray:
    """A random mounting with a lever arm of some 0.3 m."""
    T = random_extrinsic(np.random.default_rng(seed))
    T[:3, 3] *= 0.3
    return T


def mounted(kind, seed: int = 0, duration: float = 3.0):
    """A gentle run with a 10 Hz sensor of ``kind`` on a random mounting, and a 2 Hz pose sensor
    at the IMU so that every kind's run is observable."""
    spec = SensorSpec("sensor", kind.name, 10.0, kind.default_sigma, mounting(seed))
    return simulate("gentle", duration=duration, seed=seed, pose_rate=2.0, sensors=(spec,))
