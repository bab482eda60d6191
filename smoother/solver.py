"""A batch nonlinear least-squares solver on the primer's chart, with GTSAM as the sparse engine.

Why: GTSAM's nonlinear optimisers call a ``CustomFactor`` back once per factor and, inside C++,
hand each call a copy of the whole ``Values`` -- a batch solve of a long run becomes quadratic
and spends its time in Python call overhead. Here every factor type is evaluated for all its
instances at once with NumPy (the SAME residual functions the ``CustomFactor`` wrappers call),
and GTSAM does what it does best: the sparse linear algebra (``GaussianFactorGraph``
elimination, ``Marginals``).

Variables: one 15-dim linear variable per keyframe (key = keyframe index), the primer's error
state ``(dr, dv, dphi, db_f, db_w)``; a step is applied with :func:`factors.imu.boxplus` (LEFT
attitude increment), so covariances come out directly in the primer's convention.

A :class:`Block` holds the factors of one kind: their keyframe indices, a vectorised residual
returning errors and Jacobians in error-state columns, the whitening matrices of their
covariances and an optional robust kernel (GTSAM's ``mEstimator``, applied by iteratively
reweighting as GTSAM does: rows scaled by ``sqrt(w(|e_w|))``, cost ``rho(|e_w|)``).

Methods: Levenberg-Marquardt (``lm``, damping ``lambda I`` on every variable, GTSAM's default
schedule), Gauss-Newton (``gn``) and Powell's dogleg (``dogleg``) with a trust region.
"""
from __future__ import annotations

import re
from dataclasses import dataclass, field
from typing import Callable

import gtsam
import numpy as np

from factors import imu
from smoother.errors import INDETERMINANT_KEY, IndeterminantSystem, is_indeterminant

DIM = imu.STATE_DIM
METHODS = ("lm", "gn", "dogleg")


@dataclass
class Block:
    """Factors of one kind, evaluated together.

    ``keyframes (M, n)``: the keyframes each factor connects; ``residual(states, jacobians,
    rows)`` evaluates the factors ``rows`` (an index array, or ``slice(None)`` for all) from one
    :class:`factors.imu.ImuState` per slot (leading dimension = number of rows) and returns
    ``e`` and, with ``jacobians``, a list of ``n`` arrays ``(rows, d, 15)``; ``whiten (M, d, d)``
    with ``|whiten e|^2 = e^T cov^-1 e``; ``robust``: a GTSAM mEstimator or None;
    ``before_linearize(states)``: an optional hook (the IMU block re-integrates there)."""

    name: str
    keyframes: np.ndarray
    residual: Callable
    whiten: np.ndarray
    robust: object | None = None
    before_linearize: Callable | None = None

    def __len__(self) -> int:
        return len(self.keyframes)


def whitening(cov: np.ndarray) -> np.ndarray:
    """``W = L^-1`` with ``cov = L L^T`` (so ``|W e|^2 = e^T cov^-1 e``), vectorised."""
    L = np.linalg.cholesky(np.asarray(cov, dtype=float))
    return np.linalg.inv(L)


@dataclass
class _Evaluated:
    e: np.ndarray  # whitened and reweighted residuals (M, d)
    A: list  # whitened and reweighted Jacobians, one (M, d, 15) per slot
    loss: float


def evaluate_block(block: Block, states: imu.ImuState, jacobians: bool, rows=slice(None),
              keyframe_offset: int = 0) -> _Evaluated:
    """Whitened (and robustly reweighted) residuals and Jacobians of the factors ``rows`` of
    ``block``; ``states[k - keyframe_offset]`` is the state of keyframe ``k``."""
    keyframes = block.keyframes[rows] - keyframe_offset
    whiten = block.whiten[rows]
    slots = [states[keyframes[:, s]] for s in range(keyframes.shape[1])]
    if jacobians:
        e, Js = block.residual(slots, True, rows)
    else:
        e, Js = block.residual(slots, False, rows), None
    e_w = np.einsum("mab,mb->ma", whiten, e)
    if block.robust is None:
        loss = 0.5 * float(np.sum(e_w * e_w))
        scale = None
    else:
        d = np.linalg.norm(e_w, axis=1)
        loss = float(sum(block.robust.loss(float(x)) for x in d))
        scale = np.sqrt([block.robust.weight(float(x)) for x in d])[:, None]
    A = None
    if Js is not None:
        A = [whiten @ J for J in Js]
        if scale is not None:
            A = [a * scale[..., None] for a in A]
    if scale is not None:
        e_w = e_w * scale
    return _Evaluated(e_w, A, loss)


def total_cost(blocks: list[Block], states: imu.ImuState) -> float:
    """``sum rho(|e_w|)`` over every factor (``|e_w|^2 / 2`` without a robust kernel)."""
    return sum(evaluate_block(b, states, False).loss for b in blocks)


_UNIT = {}


def _unit(d: int):
    if d not in _UNIT:
        _UNIT[d] = gtsam.noiseModel.Unit.Create(d)
    return _UNIT[d]


def linearize(blocks: list[Block], states: imu.ImuState) -> tuple[gtsam.GaussianFactorGraph, float]:
    """The Gauss-Newton system ``|A delta - b|^2`` at ``states`` (``b = -e``) and the cost there."""
    for b in blocks:
        if b.before_linearize is not None:
            b.before_linearize(states)
    graph = gtsam.GaussianFactorGraph()
    cost = 0.0
    for block in blocks:
        if block.keyframes.shape[1] > 2:
            raise ValueError(f"block {block.name}: factors on more than two keyframes are not supported")
        # in chunks, so the Jacobians of a long run stay in cache between evaluation and use
        for start in range(0, len(block), LINEARIZE_CHUNK):
            rows = slice(start, min(start + LINEARIZE_CHUNK, len(block)))
            ev = evaluate_block(block, states, True, rows)
            cost += ev.loss
            model = _unit(ev.e.shape[1])
            keys = block.keyframes[rows]
            if keys.shape[1] == 1:
                for m in range(len(keys)):
                    graph.add(gtsam.JacobianFactor(int(keys[m, 0]), ev.A[0][m], -ev.e[m], model))
            else:
                for m in range(len(keys)):
                    graph.add(gtsam.JacobianFactor(int(keys[m, 0]), ev.A[0][m], int(keys[m, 1]), ev.A[1][m],
                                                   -ev.e[m], model))
    return graph, cost


#: Factors of a block linearised at once (a few MB of Jacobians: cache-resident, so the cost per
#: factor does not grow with the length of the run).
LINEARIZE_CHUNK = 1024


def _keyframe_of(error: RuntimeError) -> int | None:
    match = re.search(INDETERMINANT_KEY, str(error))
    return int(match.group(1)) if match else None


def _solve(graph: gtsam.GaussianFactorGraph, n: int) -> np.ndarray:
    try:
        solution = graph.optimize()
    except RuntimeError as error:
        if is_indeterminant(error):
            k = _keyframe_of(error)
            raise IndeterminantSystem(str(error), k) from None
        raise
    return _to_array(solution, n)


def _to_array(vv: gtsam.VectorValues, n: int) -> np.ndarray:
    return np.stack([vv.at(k) for k in range(n)])


def _to_vector_values(delta: np.ndarray) -> gtsam.VectorValues:
    vv = gtsam.VectorValues()
    for k, d in enumerate(delta):
        vv.insert(k, d)
    return vv


def _damped(graph: gtsam.GaussianFactorGraph, n: int, lam: float) -> gtsam.GaussianFactorGraph:
    damped = gtsam.GaussianFactorGraph()
    damped.push_back(graph)
    A = np.sqrt(lam) * np.eye(DIM)
    zero, model = np.zeros(DIM), _unit(DIM)
    for k in range(n):
        damped.add(gtsam.JacobianFactor(k, A, zero, model))
    return damped


@dataclass
class SolverResult:
    states: imu.ImuState
    cost: float
    iterations: int
    converged: bool
    history: list = field(default_factory=list)


def optimize(blocks: list[Block], initial: imu.ImuState, method: str = "lm", max_iterations: int = 100,
             relative_tolerance: float = 1e-9, absolute_tolerance: float = 1e-9) -> SolverResult:
    """Minimise the blocks' cost from ``initial`` (see the module docstring for the methods).
    Stops when the cost decreases by less than ``absolute_tolerance`` or by less than
    ``relative_tolerance`` of itself, or after ``max_iterations``."""
    if method not in METHODS:
        raise ValueError(f"method {method!r}: expected one of {', '.join(METHODS)}")
    n = len(initial)
    states = initial
    graph, cost = linearize(blocks, states)
    history = [cost]
    lam, radius = 1e-5, 1.0
    converged = False
    iterations = 0
    for iterations in range(1, max_iterations + 1):
        accepted = False
        for _ in range(30):  # inner loop: damping / trust-region adjustments
            if method == "gn":
                delta = _solve(graph, n)
            elif method == "lm":
                try:
                    delta = _solve(_damped(graph, n, lam), n)
                except IndeterminantSystem:
                    # as GTSAM's LM does: a damped system too poorly conditioned to factor
                    # counts as a rejected step; more damping, and try again
                    lam *= 10.0
                    if lam > 1e10:
                        break
                    continue
            else:
                delta = _dogleg_step(graph, n, radius)
            trial = imu.boxplus(states, delta)
            trial_cost = total_cost(blocks, trial)
            if method == "gn":
                accepted = True  # Gauss-Newton takes every step
                break
            if method == "lm":
                if trial_cost < cost:
                    lam = max(lam / 10.0, 1e-12)
                    accepted = True
                    break
                # At the minimum the linear model promises a decrease at round-off level and no
                # damping can realise it: stop there instead of raising lambda to its bound.
                promised = cost - graph.error(_to_vector_values(delta))
                if promised <= max(absolute_tolerance, relative_tolerance * cost):
                    break
                lam *= 10.0
                if lam > 1e10:
                    break
            else:
                predicted = cost - graph.error(_to_vector_values(delta))
                rho = (cost - trial_cost) / predicted if predicted > 0 else -1.0
                step = np.linalg.norm(delta)
                if rho > 0.75:
                    radius = max(radius, 3.0 * step)
                elif rho < 0.25:
                    radius = 0.5 * step
                if rho > 0:
                    accepted = True
                    break
                if radius < 1e-12:
                    break
        if not accepted:
            converged = True  # no step decreases the cost: a (local) minimum at this precision
            break
        decrease = cost - trial_cost
        states = trial
        graph, cost = linearize(blocks, states)
        history.append(cost)
        if abs(decrease) < absolute_tolerance or abs(decrease) < relative_tolerance * max(cost, 1e-300):
            converged = True
            break
    return SolverResult(states, cost, iterations, converged, history)


def _dogleg_step(graph: gtsam.GaussianFactorGraph, n: int, radius: float) -> np.ndarray:
    gn = _solve(graph, n)
    if np.linalg.norm(gn) <= radius:
        return gn
    sd = _to_array(graph.optimizeGradientSearch(), n)
    sd_norm = np.linalg.norm(sd)
    if sd_norm >= radius:
        return sd * (radius / sd_norm)
    d = gn - sd
    a, b, c = np.sum(d * d), 2.0 * np.sum(sd * d), sd_norm**2 - radius**2
    tau = (-b + np.sqrt(b * b - 4 * a * c)) / (2 * a)
    return sd + tau * d


def covariances(blocks: list[Block], states: imu.ImuState, which=None) -> np.ndarray:
    """Marginal 15x15 covariances (primer convention) of the keyframes ``which`` (default all),
    from the linearisation at ``states``."""
    graph, _ = linearize(blocks, states)
    n = len(states)
    try:
        marginals = gtsam.Marginals(graph, _to_vector_values(np.zeros((n, DIM))))
        which = range(n) if which is None else which
        return np.stack([marginals.marginalCovariance(int(k)) for k in which])
    except RuntimeError as error:
        if is_indeterminant(error):
            raise IndeterminantSystem(str(error), _keyframe_of(error)) from None
        raise
