"""Batch smoothing: the whole graph optimised at once, with marginal covariances.

Levenberg-Marquardt by default; Gauss-Newton and Dogleg selectable. Covariances are GTSAM's
marginals of each keyframe's four variables, converted to the primer's 15-dim error state with
:func:`factors.chart.state_covariance_to_primer`. An indeterminant system is reported with the
variable GTSAM names and a hint instead of a bare exception.
"""
from __future__ import annotations

import re
import time
from dataclasses import dataclass

import gtsam
import numpy as np

from datasets.types import Trajectory
from factors import imu
from factors.chart import state_covariance_to_primer
from factors.keys import KeyframeKeys
from smoother.errors import UserError
from smoother.graph import Problem, read_state

OPTIMIZERS = ("lm", "gn", "dogleg")


class IndeterminantSystem(UserError):
    """The linear system is rank-deficient: some variable is not constrained by the factors."""


@dataclass
class SmootherResult:
    """Estimates (and covariances, if computed) at every keyframe, the optimiser's final error
    and iteration count, and the wall time."""

    trajectory: Trajectory
    error: float
    iterations: int
    runtime_s: float


def is_indeterminant(error: BaseException) -> bool:
    """Whether ``error`` is GTSAM's indeterminant-system exception (spelled "Indeterminate" by
    GTSAM 4.3.0, "Indeterminant" by older versions)."""
    text = str(error)
    return "ndeterminate" in text or "ndeterminant" in text


def explain_indeterminant(error: RuntimeError, problem: Problem | None = None) -> IndeterminantSystem:
    """Turn GTSAM's indeterminant-system exception into a readable error naming the keyframe."""
    text = str(error)
    # GTSAM 4.3.0 says "Indeterminate linear system ... near variable\n<key> (Symbol: ...)"
    # (older versions "Indeterminant", with a space before the key).
    match = re.search(r"near variable\s+(\d+)", text)
    where = ""
    if match:
        key = int(match.group(1))
        where = f" near variable {gtsam.DefaultKeyFormatter(key)}"
        if problem is not None:
            for k, kk in enumerate(problem.keys):
                if key in kk.all():
                    where += f" (keyframe {k}, t = {problem.times[k]:.6f} s)"
                    break
    return IndeterminantSystem(
        f"indeterminant system{where}: the factors do not constrain every variable there. "
        "Typical causes: a stretch with no measurements and no IMU link, yaw unobservable with "
        "position-only measurements and a prior too weak, or a diverging bias. Add a prior, a "
        "measurement, or check the data around that time."
    )


def _parameters(optimizer: str, max_iterations: int):
    if optimizer == "lm":
        p = gtsam.LevenbergMarquardtParams()
    elif optimizer == "gn":
        p = gtsam.GaussNewtonParams()
    elif optimizer == "dogleg":
        p = gtsam.DoglegParams()
    else:
        raise UserError(f"optimizer {optimizer!r}: expected one of {', '.join(OPTIMIZERS)}")
    p.setMaxIterations(max_iterations)
    p.setRelativeErrorTol(1e-9)
    p.setAbsoluteErrorTol(1e-9)
    return p


def _optimizer(optimizer: str, graph, values, params):
    cls = {"lm": gtsam.LevenbergMarquardtOptimizer, "gn": gtsam.GaussNewtonOptimizer,
           "dogleg": gtsam.DoglegOptimizer}[optimizer]
    return cls(graph, values, params)


def keyframe_covariances(graph, values, keys: list[KeyframeKeys]) -> np.ndarray:
    """Primer-convention 15x15 covariances of the keyframes with ``keys``."""
    marginals = gtsam.Marginals(graph, values)
    out = []
    for kk in keys:
        joint = marginals.jointMarginalCovariance(gtsam.KeyVector(kk.all())).fullMatrix()
        out.append(state_covariance_to_primer(joint, values.atRot3(kk.rot)))
    return np.stack(out)


def solve_batch(problem: Problem, optimizer: str = "lm", max_iterations: int = 100,
                covariances: bool = True) -> SmootherResult:
    """Optimise the whole graph from its initial values."""
    start = time.perf_counter()
    params = _parameters(optimizer, max_iterations)
    opt = _optimizer(optimizer, problem.graph, problem.initial, params)
    try:
        values = opt.optimize()
        cov = keyframe_covariances(problem.graph, values, problem.keys) if covariances else None
    except RuntimeError as error:
        if is_indeterminant(error):
            raise explain_indeterminant(error, problem) from None
        raise
    states = imu.ImuState.stack([read_state(values, kk) for kk in problem.keys])
    trajectory = Trajectory(problem.times, states, cov)
    return SmootherResult(trajectory, float(problem.graph.error(values)), int(opt.iterations()),
                          time.perf_counter() - start)
