"""A keyframe's state put into and read from ``gtsam.Values`` under its keys
(:func:`factors.keys.keyframe_keys`), for the tests of ``factors`` (which do not import ``smoother``,
where the estimators do the same).

Import as ``import gtsam_values`` (``tests/conftest.py`` puts this directory on ``sys.path``)."""
from __future__ import annotations

import gtsam
import numpy as np

from factors import imu


def insert_state(values: gtsam.Values, keys, x: imu.ImuState) -> None:
    """Insert ``x``'s variables (Rot3, Point3, velocity, bias) under ``keys``."""
    values.insert(keys.rot, gtsam.Rot3(x.C))
    values.insert(keys.pos, gtsam.Point3(*x.r))
    values.insert(keys.vel, np.array(x.v, dtype=float))
    values.insert(keys.bias, gtsam.imuBias.ConstantBias(x.b_f, x.b_w))


def read_state(values: gtsam.Values, keys) -> imu.ImuState:
    """The state under ``keys``."""
    b = values.atConstantBias(keys.bias).vector()
    return imu.ImuState(values.atPoint3(keys.pos), values.atVector(keys.vel), values.atRot3(keys.rot).matrix(),
                        b[:3], b[3:])
