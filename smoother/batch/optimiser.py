"""Levenberg-Marquardt (``lm``, damping ``lambda I`` on every variable, GTSAM's default schedule),
Gauss-Newton (``gn``) and Powell's dogleg (``dogleg``, a trust region) over the vectorised blocks
of :mod:`smoother.model.blocks`, with GTSAM's sparse elimination for each step."""
from __future__ import annotations

from dataclasses import dataclass, field

import gtsam
import numpy as np

from factors import imu
from factors.errors import InputError
from smoother.batch.methods import OPTIMIZERS
from smoother.errors import IndeterminantSystem, is_indeterminant
from smoother.model.blocks import Block, Layout, linearize, total_cost, unit_model
from smoother.model.rank import indeterminant_error


def _solve(graph: gtsam.GaussianFactorGraph, layout: "Layout", ordering: gtsam.Ordering | None) -> np.ndarray:
    """The least-squares solution of ``graph``: sparse Cholesky (GTSAM's default, the fastest), and
    QR where Cholesky calls the system indeterminant -- a dead-reckoned stretch squares into an
    information matrix it cannot factor, while the rows themselves determine the step. Without
    that fallback Levenberg-Marquardt could only add damping there and crawled: 1867 iterations to
    converge on 60 s of tumbling with a fix every 10 s and 10 Hz keyframes, 7 with it.

    Calibration variables are eliminated last (:meth:`Layout.ordering`): every keyframe's
    conditional then has them among its parents, the dense border of an arrowhead system, and no
    keyframe is eliminated after them (COLAMD alone placed them among the last keyframes, whose
    Cholesky pivots then failed on systems QR solves with a condition number of 4e5). ``ordering``:
    :meth:`Layout.ordering` of a graph with the same factors' keys (None: GTSAM's default)."""
    try:
        solution = graph.optimize() if ordering is None else graph.optimize(ordering)
    except RuntimeError as error:
        if not is_indeterminant(error):
            raise
        ordering = ordering or gtsam.Ordering.ColamdGaussianFactorGraph(graph)
        try:
            solution = graph.optimize(ordering, gtsam.EliminateQR)
        except RuntimeError as again:
            raise indeterminant_error(again, graph, ordering) from None
    return layout.flat(solution)


def _damped(graph: gtsam.GaussianFactorGraph, layout: Layout, lam: float) -> gtsam.GaussianFactorGraph:
    damped = gtsam.GaussianFactorGraph()
    damped.push_back(graph)
    for k in layout.keys:
        d = layout.dim(k)
        damped.add(gtsam.JacobianFactor(k, np.sqrt(lam) * np.eye(d), np.zeros(d), unit_model(d)))
    return damped


@dataclass
class SolverResult:
    states: imu.ImuState
    cost: float
    iterations: int
    converged: bool
    history: list = field(default_factory=list)
    #: The calibration variables at the optimum (:class:`factors.calibration.CalibrationSet`), if any.
    calibration: object = None
    #: The whitened linear system at the optimum (:func:`smoother.model.blocks.linearize`), what
    #: its covariances come from.
    graph: gtsam.GaussianFactorGraph | None = None


#: The optimisation stops when a step lowers the cost by less than this: in the quadratic model a
#: step's decrease is half its squared length in the whitened metric, so the step moved the
#: estimate by less than ``sqrt(2e-3) = 0.045`` of its sigma in any direction, and the steps after
#: it, shrinking, less again: where the convergence is linear (a calibrated problem, whose
#: Gauss-Newton model leaves out the curvature of weakly determined calibrations), the next step
#: moved the positions of a 60-s rig by 0.0016 of their sigma, and KITTI's by 0.0005. GTSAM's
#: default (1e-5 relative) stops a cost of 1e4 at 0.1 in it, half a sigma in the worst direction.
ABSOLUTE_TOLERANCE = 1e-3


def optimize(blocks: list[Block], initial: imu.ImuState, method: str = "lm", max_iterations: int = 100,
             relative_tolerance: float = 1e-9, absolute_tolerance: float = ABSOLUTE_TOLERANCE,
             calibration=None) -> SolverResult:
    """Minimise the blocks' cost from ``initial`` and the calibration variables' values
    ``calibration`` (a :class:`factors.calibration.CalibrationSet` or None; see the module
    docstring for the methods). Stops when a step decreases the cost by less than
    ``absolute_tolerance`` (:data:`ABSOLUTE_TOLERANCE`) or by less than ``relative_tolerance`` of
    itself, keeping that step, or after ``max_iterations``.

    While the first trial of every iteration is accepted -- a smoother started from a filter's
    estimate accepts nearly every one -- each trial is linearised at once, its cost a by-product,
    instead of costed and then linearised once accepted: one pass over the factors per iteration
    instead of two. After a rejection (which then costs a linearisation of the current point
    again), trials are costed first until an iteration's first is accepted. One linear system is
    held at a time. The result carries the system at the optimum, for its covariances."""
    if method not in OPTIMIZERS:
        raise InputError(f"method {method!r}: expected one of {', '.join(OPTIMIZERS)}")
    layout = Layout.of(initial, calibration, blocks)
    states = initial
    graph, cost = linearize(blocks, states, calibration)
    # the factors' keys are the same at every linearisation, and damping adds unary factors only:
    # one elimination ordering serves every step
    ordering = layout.ordering(graph, nested=True)
    history = [cost]
    lam, radius = 1e-5, 1.0
    converged = False
    iterations = 0
    eager = True  # trials linearised at once (their cost a by-product) while the first of each is accepted
    for iterations in range(1, max_iterations + 1):
        accepted = False
        for attempt in range(30):  # inner loop: damping / trust-region adjustments
            if method == "gn":
                delta = _solve(graph, layout, ordering)
            elif method == "lm":
                try:
                    delta = _solve(_damped(graph, layout, lam), layout, ordering)
                except IndeterminantSystem:
                    # as GTSAM's LM does: a damped system too poorly conditioned to factor
                    # counts as a rejected step; more damping, and try again
                    lam *= 10.0
                    if lam > 1e10:
                        break
                    continue
            else:
                delta = _dogleg_step(graph, layout, radius, ordering)
            # the decrease the linear model predicts, before its system is let go
            predicted = cost - graph.error(layout.vector_values(delta)) if method == "dogleg" else None
            trial, trial_calibration = layout.apply(states, calibration, delta)
            if eager:
                graph = None  # one linear system held at a time (a long run's is hundreds of MB)
                trial_graph, trial_cost = linearize(blocks, trial, trial_calibration)
            else:
                trial_graph, trial_cost = None, total_cost(blocks, trial, trial_calibration)
            if method == "gn":
                accepted = True  # Gauss-Newton takes every step
                break
            if method == "lm":
                if trial_cost < cost:
                    lam = max(lam / 10.0, 1e-12)
                    accepted = True
                    break
                graph, eager = _after_rejection(graph, blocks, states, calibration)
                # At the minimum the linear model promises a decrease at round-off level and no
                # damping can realise it: stop there instead of raising lambda to its bound.
                promised = cost - graph.error(layout.vector_values(delta))
                if promised <= max(absolute_tolerance, relative_tolerance * cost):
                    break
                lam *= 10.0
                if lam > 1e10:
                    break
            else:
                rho = (cost - trial_cost) / predicted if predicted > 0 else -1.0
                step = np.linalg.norm(delta)
                if rho > 0.75:
                    radius = max(radius, 3.0 * step)
                elif rho < 0.25:
                    radius = 0.5 * step
                if rho > 0:
                    accepted = True
                    break
                graph, eager = _after_rejection(graph, blocks, states, calibration)
                if radius < 1e-12:
                    break
        if not accepted:
            converged = True  # no step decreases the cost: a (local) minimum at this precision
            break
        eager = attempt == 0
        decrease = cost - trial_cost
        if trial_graph is None:
            graph = None
            trial_graph, trial_cost = linearize(blocks, trial, trial_calibration)
        states, calibration, graph, cost = trial, trial_calibration, trial_graph, trial_cost
        history.append(cost)
        if abs(decrease) < absolute_tolerance or abs(decrease) < relative_tolerance * max(trial_cost, 1e-300):
            converged = True  # the step kept
            break
    return SolverResult(states, cost, iterations, converged, history, calibration, graph)


def _after_rejection(graph, blocks: list[Block], states: imu.ImuState, calibration) -> tuple:
    """``(graph, eager)`` after a rejected trial: the linear system at the current ``states``
    (``graph``, or linearised again where an eager trial let it go), and trials costed before
    they are linearised until an iteration's first is accepted again."""
    if graph is None:
        graph, _ = linearize(blocks, states, calibration)
    return graph, False


def _dogleg_step(graph: gtsam.GaussianFactorGraph, layout: Layout, radius: float,
                 ordering: gtsam.Ordering | None) -> np.ndarray:
    gn = _solve(graph, layout, ordering)
    if np.linalg.norm(gn) <= radius:
        return gn
    sd = layout.flat(graph.optimizeGradientSearch())
    sd_norm = np.linalg.norm(sd)
    if sd_norm >= radius:
        return sd * (radius / sd_norm)
    d = gn - sd
    a, b, c = np.sum(d * d), 2.0 * np.sum(sd * d), sd_norm**2 - radius**2
    tau = (-b + np.sqrt(b * b - 4 * a * c)) / (2 * a)
    return sd + tau * d
