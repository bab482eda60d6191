"""Small simulated cases shared by the estimator tests, computed once per session.

Every case is short (a few seconds at ``IMU_RATE`` = 100 Hz with 10 Hz pose measurements), so an
EKF run costs a few hundred predictions and a batch solve a few dozen keyframes. Results are
cached with ``functools.lru_cache`` on their (hashable) arguments; the fixtures in
``conftest.py`` hand them out. Every estimator run gets its OWN :class:`smoother.model.problem.Problem`
(the IMU factors re-integrate themselves when a gyro bias moves, so a problem is stateful and
sharing one between a batch solve and a fixed-lag run would couple the two).
"""
from __future__ import annotations

import functools
import warnings
from dataclasses import dataclass

import numpy as np

from datasets.simulate import simulate
from datasets.types import Dataset, Trajectory
from factors import imu, so3
from smoother.ekf.filter import FilterResult, run_ekf
from smoother.evaluation.crosscheck import sigma_difference  # noqa: F401  (used by the tests as cases.sigma_difference)

# The smoothers are imported where used, so that the EKF tests do not depend on them.

IMU_RATE = 100.0
POSE_RATE = 10.0


@dataclass(frozen=True)
class CaseSpec:
    profile: str
    duration: float
    seed: int


#: The two small cases most tests use: a gentle and a tumbling run.
GENTLE = CaseSpec("gentle", 4.0, 0)
TUMBLING = CaseSpec("tumbling", 3.0, 1)


@functools.lru_cache(maxsize=None)
def dataset(spec: CaseSpec) -> Dataset:
    return simulate(profile=spec.profile, duration=spec.duration, seed=spec.seed, imu_rate=IMU_RATE,
                    pose_rate=POSE_RATE)


def problem(spec: CaseSpec):
    """A fresh :class:`smoother.model.problem.Problem` (not cached: see the module docstring)."""
    from smoother.model.problem import build_problem

    return build_problem(dataset(spec))


@functools.lru_cache(maxsize=None)
def ekf(spec: CaseSpec) -> FilterResult:
    return run_ekf(dataset(spec), progress=False)


@functools.lru_cache(maxsize=None)
def batch(spec: CaseSpec):
    """``(problem, smoother.batch.solve.SmootherResult)`` of the default batch solve."""
    from smoother.batch.solve import solve_batch

    p = problem(spec)
    return p, solve_batch(p)


@functools.lru_cache(maxsize=None)
def fixed_lag(spec: CaseSpec, kind: str, lag_s: float):
    """``(problem, smoother.fixed_lag.offline.FixedLagResult)``."""
    from smoother.fixed_lag.offline import run_fixed_lag

    p = problem(spec)
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # no factor may be skipped in these cases
        return p, run_fixed_lag(p, lag_s, kind, progress=False)


def truth_at(data: Dataset, t: np.ndarray) -> imu.ImuState:
    """The true states at times ``t`` (which must be truth sample times exactly)."""
    i = np.searchsorted(data.truth.t, t)
    assert np.array_equal(data.truth.t[i], t), "estimate times are not truth sample times"
    return data.truth.states[i]


def position_rmse(data: Dataset, trajectory: Trajectory) -> float:
    """Translation ATE (RMSE of the position error, no alignment: same world frame)."""
    T = truth_at(data, trajectory.t)
    return float(np.sqrt(np.mean(np.sum((trajectory.states.r - T.r) ** 2, axis=1))))


# ------------------------------------------------------------------------------------------
# scoring: a truth and an estimate off it by a known error

#: The attitude error of :func:`offset_estimate`.
OFFSET_ANGLE = np.radians(2.0)


def scored_data():
    """One second of the tumbling case, no poses: a truth to score estimates against."""
    return simulate(profile="tumbling", duration=1.0, seed=0, imu_rate=IMU_RATE, pose_rate=None)


def scored_truth(n: int = 12) -> Trajectory:
    """Every fifth truth sample of :func:`scored_data`, ``n`` of them (enough states to score:
    ``smoother.evaluation.scoring.MIN_COMPARED_STATES``)."""
    return scored_data().truth.subset(np.arange(0, 5 * n, 5))


def offset_estimate(truth: Trajectory, with_cov: bool = True) -> Trajectory:
    """Every position 0.5 m off (0.3, 0.4, 0), every attitude rotated by 2 degrees about the world
    z axis (C_est = exp(a z) C_true); covariance 0.01 m^2 and 1e-4 rad^2 on the pose blocks."""
    s = truth.states
    states = s.replace(r=s.r + [0.3, 0.4, 0.0], C=so3.exp([0.0, 0.0, OFFSET_ANGLE]) @ s.C)
    cov = None
    if with_cov:
        cov = np.tile(np.eye(15), (len(truth), 1, 1))
        cov[:, 0:3, 0:3] = 0.01 * np.eye(3)
        cov[:, 6:9, 6:9] = 1e-4 * np.eye(3)
    return Trajectory(truth.t, states, cov)
