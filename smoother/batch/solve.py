"""Batch smoothing: the whole graph optimised at once, with marginal covariances.

Two engines over the same residuals:

* ``vectorized`` (default): :mod:`smoother.model.blocks` -- every factor type linearised at once with
  NumPy, GTSAM's sparse elimination for the steps and its QR elimination for the covariances
  (:func:`smoother.model.covariances.marginal_covariances`), which come out directly in the primer's
  convention. Linear in the length of the run.
* ``gtsam``: GTSAM's own nonlinear optimisers on the ``CustomFactor`` graph (one Python callback
  per factor, each handed a copy of the whole ``Values``: quadratic in the run length; kept as the
  independent reference the tests compare against). Covariances from GTSAM's marginals are
  converted to the primer's chart by :func:`smoother.model.covariances.keyframe_covariance`.

Levenberg-Marquardt by default; Gauss-Newton and Dogleg selectable in both. The vectorised
engine's covariances come from the square-root information, so a problem with a unique optimum
has them however long it dead-reckons. An indeterminant system raises
:class:`smoother.errors.IndeterminantSystem` naming the keyframe, its time and (vectorised
covariances) the error-state components left free, with a hint, instead of a bare GTSAM
exception.
"""
from __future__ import annotations

import time
import warnings
from dataclasses import dataclass

import gtsam
import numpy as np

from datasets.types import Trajectory
from factors import imu
from factors.errors import InputError
from factors.keys import KeyframeKeys
from smoother.batch.methods import OPTIMIZERS
from smoother.batch.optimiser import optimize
from smoother.errors import IndeterminantSystem, NotConverged, indeterminant_key, is_indeterminant
from smoother.model.blocks import Layout
from smoother.model.covariances import keyframe_covariance, marginal_covariances
from smoother.model.problem import Problem, read_state

ENGINES = ("vectorized", "gtsam")

_HINT = ("the factors do not constrain every variable there. Typical causes: a stretch with no "
         "measurements and no IMU link, yaw unobservable with position-only measurements and a "
         "prior too weak, or a diverging bias. Add a prior or a measurement, or check the data "
         "around that time.")

__all__ = ["IndeterminantSystem", "SmootherResult", "solve_batch", "keyframe_covariances", "ENGINES"]


@dataclass
class SmootherResult:
    """Estimates (and covariances, if computed) at every keyframe, the optimiser's final cost
    (``sum rho(|e_w|)``, i.e. GTSAM's graph error) and iteration count, the wall time, and
    ``converged``: False when the optimiser stopped at ``max_iterations`` still decreasing the cost
    (the estimate may be off the optimum; :func:`solve_batch` warns)."""

    trajectory: Trajectory
    error: float
    iterations: int
    runtime_s: float
    converged: bool
    #: The joint covariance blocks ``{(a, b): Sigma_ab}`` of every two keyframes that share a factor
    #: (``vectorized`` engine with covariances; :func:`smoother.model.covariances.marginal_covariances`).
    joint: dict | None = None
    #: The calibration variables at the optimum (:class:`factors.calibration.CalibrationSet`) and
    #: each one's marginal covariance over its estimated coordinates (with covariances), or None.
    calibration: object = None
    calibration_cov: list | None = None
    #: The covariances' elimination (:class:`smoother.model.covariances.SquareRoot`), kept where
    #: :func:`solve_batch` was asked for it: what the noise fit's first evaluation reads.
    square_root: object = None
    #: The last iteration's decrease of the cost, relative to it (vectorised engine; None where none
    #: was taken, or with GTSAM's): what :func:`warn_not_converged` says of an unconverged solve.
    decrease: float | None = None


def _explained(keyframe: int | None, problem: Problem, free: str | None = None) -> IndeterminantSystem:
    where = ""
    if keyframe is not None and 0 <= keyframe < len(problem.times):
        where = f" near keyframe {keyframe} (t = {problem.times[keyframe]:.6f} s)"
    what = f"it is free along {free}; " if free else ""
    return IndeterminantSystem(f"indeterminant system{where}: {what}{_HINT}", keyframe, free)


def _keyframe_of_gtsam_key(error: Exception, problem: Problem) -> int | None:
    key = indeterminant_key(error)
    if key is not None:
        for k, kk in enumerate(problem.keys):
            if key in kk.all():
                return k
    return None


def keyframe_covariances(graph, values, keys: list[KeyframeKeys]) -> np.ndarray:
    """Primer-convention 15x15 covariances of the keyframes with ``keys``, from GTSAM's marginals
    of a nonlinear graph (the ``gtsam`` engine and the fixed-lag smoothers)."""
    marginals = gtsam.Marginals(graph, values)
    return np.stack([keyframe_covariance(marginals, kk, values.atRot3(kk.rot)) for kk in keys])


def _gtsam_engine(problem: Problem, optimizer: str, max_iterations: int, covariances: bool):
    """GTSAM's optimiser of ``optimizer`` on the graph: ``(states, covariances, cost, iterations,
    converged)``; converged unless it used all ``max_iterations``."""
    if optimizer == "lm":
        params, cls = gtsam.LevenbergMarquardtParams(), gtsam.LevenbergMarquardtOptimizer
    elif optimizer == "gn":
        params, cls = gtsam.GaussNewtonParams(), gtsam.GaussNewtonOptimizer
    else:
        params, cls = gtsam.DoglegParams(), gtsam.DoglegOptimizer
    params.setMaxIterations(max_iterations)
    params.setRelativeErrorTol(1e-9)
    params.setAbsoluteErrorTol(1e-9)
    opt = cls(problem.graph, problem.initial, params)
    values = opt.optimize()
    iterations = int(opt.iterations())
    cov = keyframe_covariances(problem.graph, values, problem.keys) if covariances else None
    states = imu.ImuState.stack([read_state(values, kk) for kk in problem.keys])
    return states, cov, float(problem.graph.error(values)), iterations, iterations < max_iterations


def solve_batch(problem: Problem, optimizer: str = "lm", max_iterations: int = 100,
                covariances: bool = True, engine: str = "vectorized", square_root: bool = False) -> SmootherResult:
    """Optimise the whole graph from its initial values (see the module docstring); at most
    ``max_iterations`` iterations, and a warning naming them and the last relative decrease of the
    cost when they end before convergence (``SmootherResult.converged`` False). ``square_root``
    (vectorised engine, with covariances): keep the covariances' elimination in the result (a
    noise fit follows, :func:`smoother.batch.variance_components.estimate_noise`)."""
    if optimizer not in OPTIMIZERS:
        raise InputError(f"optimizer {optimizer!r}: expected one of {', '.join(OPTIMIZERS)}")
    if engine not in ENGINES:
        raise InputError(f"engine {engine!r}: expected one of {', '.join(ENGINES)}")
    start = time.perf_counter()
    try:
        decrease = None
        calibration, calibration_cov, root = None, None, None
        if engine == "vectorized":
            result = optimize(problem.blocks, problem.initial_states, optimizer, max_iterations,
                                     calibration=problem.calibration)
            states, cost, iterations, converged = result.states, result.cost, result.iterations, result.converged
            calibration = result.calibration
            if len(result.history) > 1:
                decrease = (result.history[-2] - result.history[-1]) / max(result.history[-1], 1e-300)
            if not converged:  # before the covariances, which may fail away from the optimum
                warn_not_converged(optimizer, iterations, decrease)
            cov, joint = None, None
            if covariances:
                layout = Layout.of(states, calibration, problem.blocks)
                out = marginal_covariances(result.graph, len(states), pairs=True, layout=layout,
                                           square_root=square_root)
                cov, joint, root = out if square_root else (*out, None)
            if covariances and calibration is not None:
                n = len(states)
                calibration_cov = [joint[(n + j, n + j)] for j in range(len(calibration))]
        else:
            if problem.calibration is not None:
                raise InputError(f"the gtsam engine does not estimate calibrations (sensors "
                                 f"{', '.join(problem.calibration.names)}): use the vectorized engine")
            joint = None
            states, cov, cost, iterations, converged = _gtsam_engine(problem, optimizer, max_iterations, covariances)
            if not converged:
                warn_not_converged(optimizer, iterations, decrease)
    except IndeterminantSystem as error:
        raise _explained(error.keyframe, problem, error.free) from None
    except RuntimeError as error:
        if is_indeterminant(error):
            raise _explained(_keyframe_of_gtsam_key(error, problem), problem) from None
        raise
    trajectory = Trajectory(problem.times, states, cov)
    return SmootherResult(trajectory, cost, iterations, time.perf_counter() - start, converged, joint,
                          calibration, calibration_cov, root, decrease)


def warn_not_converged(optimizer: str, iterations: int, decrease: float | None, stacklevel: int = 3) -> None:
    """The :class:`smoother.errors.NotConverged` warning of a batch solve by ``optimizer`` that
    stopped after ``iterations`` still lowering its cost (by ``decrease`` of itself, if known)."""
    last = "" if decrease is None else f" (the last iteration still lowered the cost by {decrease:.3g} of itself)"
    warnings.warn(f"batch ({optimizer}): stopped after {iterations} iterations without converging{last}; the "
                  f"estimate may be off the optimum: raise max_iterations (smoother run --max-iterations)",
                  NotConverged, stacklevel=stacklevel)
