"""A nearly straight drive and an estimate of it in another frame: the degenerate alignment case
shared by the metrics' tests (tests/smoother/evaluation/test_metrics.py) and the ``evaluate``
command's (tests/cli/test_evaluate_cli.py)."""
from __future__ import annotations

import numpy as np

from datasets.simulate import simulate
from datasets.trajectories import Sinusoids, sinusoid_profile
from factors import so3

#: A straight road at 10 m/s with a 5 cm weave (the simulator's profile; no turn, level).
STRAIGHT = sinusoid_profile("straight", "a straight road at 10 m/s, a 5 cm weave",
                            position=(Sinusoids(slope=10.0), Sinusoids(terms=((0.05, 0.4, 0.0),)),
                                      Sinusoids(offset=1.0)),
                            attitude=(Sinusoids(), Sinusoids(), Sinusoids()))


def transformed(R, t, r, C, s=1.0):
    """Positions ``r (N, 3)`` and attitudes ``C (N, 3, 3)`` moved into another frame: rotated by
    ``R``, scaled by ``s`` and offset by ``t``."""
    return s * r @ R.T + t, R @ C


def straight_drive(roll_error_deg: float = 7.0, seed: int = 4):
    """30 s of :data:`STRAIGHT` at 10 Hz and an estimate of it: positions drifting as a random walk
    (5 cm a step, about 0.6 m at the end), every attitude rolled ``roll_error_deg`` about the road
    (the true rotation error), the whole in another frame (yaw 0.6 rad, an offset). Returns the
    reference ``(t, r, C)`` and the estimate ``(r, C)``."""
    truth = simulate(profile=STRAIGHT, duration=30.0, seed=0, pose_rate=None).truth.subset(slice(0, None, 20))
    drift = np.cumsum(np.random.default_rng(seed).normal(scale=0.05, size=(len(truth), 3)), axis=0)
    R, offset = so3.exp([0.0, 0.0, 0.6]), np.array([3.0, -2.0, 0.5])
    rolled = so3.exp([np.radians(roll_error_deg), 0.0, 0.0]) @ truth.C
    return (truth.t, truth.position, truth.C), transformed(R, offset, truth.position + drift, rolled)
