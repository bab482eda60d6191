"""GTSAM keys of one keyframe: one chart-simple variable per quantity (docs/design.md, section 4).

``R(k)`` a ``Rot3`` for ``Phi_IB``, ``P(k)`` a ``Point3`` for ``I_r``, ``V(k)`` a 3-vector for the
BODY-frame velocity, ``B(k)`` an ``imuBias.ConstantBias`` (accelerometer first, then gyro).
"""
from __future__ import annotations

from dataclasses import dataclass

import gtsam


@dataclass(frozen=True)
class KeyframeKeys:
    rot: int
    pos: int
    vel: int
    bias: int

    def all(self) -> list[int]:
        return [self.rot, self.pos, self.vel, self.bias]


def keyframe_keys(k: int) -> KeyframeKeys:
    """The keys of keyframe ``k``: ``R k``, ``P k``, ``V k``, ``B k``."""
    return KeyframeKeys(gtsam.symbol("R", k), gtsam.symbol("P", k), gtsam.symbol("V", k), gtsam.symbol("B", k))
