"""A batch nonlinear least-squares solver on the primer's chart, with GTSAM as the sparse engine.

Why: GTSAM's nonlinear optimisers call a ``CustomFactor`` back once per factor and, inside C++,
hand each call a copy of the whole ``Values`` -- a batch solve of a long run becomes quadratic
and spends its time in Python call overhead. Here every factor type is evaluated for all its
instances at once with NumPy (the SAME residual functions the ``CustomFactor`` wrappers call),
and GTSAM does what it does best: the sparse linear algebra (``GaussianFactorGraph``
elimination: Cholesky for the steps, QR where Cholesky refuses them and for the covariances).

Variables: one 15-dim linear variable per keyframe (key = keyframe index), the primer's error
state ``(dr, dv, dphi, db_f, db_w)``; a step is applied with :func:`factors.imu.boxplus` (LEFT
attitude increment), so covariances come out directly in the primer's convention. A problem may
add calibration variables (:class:`factors.calibration.CalibrationSet`): sensor ``j``'s is the
linear variable ``n + j`` (``n`` keyframes) over its estimated coordinates, stepped with
:meth:`~factors.calibration.CalibrationSet.boxplus`; they take part in every step and covariance
like the keyframes.

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
from factors.errors import InputError

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
    ``before_linearize(states)``: an optional hook (the IMU block re-integrates there);
    ``calibration``: the index of the calibration variable every factor of the block also reads
    (:class:`factors.calibration.CalibrationSet`), or None. The residual of such a block takes that
    variable's current :class:`~factors.calibration.Calibration` as a fourth argument and returns
    one more Jacobian, ``(rows, d, k)`` over its ``k`` estimated coordinates, after the slots'
    (a block may read the calibration alone: ``keyframes`` of shape ``(1, 0)``, its prior)."""

    name: str
    keyframes: np.ndarray
    residual: Callable
    whiten: np.ndarray
    robust: object | None = None
    before_linearize: Callable | None = None
    calibration: int | None = None

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


def block_residual(block: Block, slots: list, jacobians: bool, rows, calibration=None):
    """``block.residual`` of the factors ``rows`` at the states ``slots``, handed the current value
    of its calibration variable from ``calibration`` (a :class:`factors.calibration.CalibrationSet`)
    when it reads one."""
    if block.calibration is None:
        return block.residual(slots, jacobians, rows)
    if calibration is None:
        raise InputError(f"block {block.name}: it reads calibration variable {block.calibration}, and none was given")
    return block.residual(slots, jacobians, rows, calibration.values[block.calibration])


def evaluate_block(block: Block, states: imu.ImuState, jacobians: bool, rows=slice(None),
                   keyframe_offset: int = 0, calibration=None) -> _Evaluated:
    """Whitened (and robustly reweighted) residuals and Jacobians of the factors ``rows`` of
    ``block``; ``states[k - keyframe_offset]`` is the state of keyframe ``k``; ``calibration``
    the calibration variables' values (:func:`block_residual`)."""
    keyframes = block.keyframes[rows] - keyframe_offset
    whiten = block.whiten[rows]
    slots = [states[keyframes[:, s]] for s in range(keyframes.shape[1])]
    if jacobians:
        e, Js = block_residual(block, slots, True, rows, calibration)
    else:
        e, Js = block_residual(block, slots, False, rows, calibration), None
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


def total_cost(blocks: list[Block], states: imu.ImuState, calibration=None) -> float:
    """``sum rho(|e_w|)`` over every factor (``|e_w|^2 / 2`` without a robust kernel)."""
    return sum(evaluate_block(b, states, False, calibration=calibration).loss for b in blocks)


_UNIT = {}


def _unit(d: int):
    if d not in _UNIT:
        _UNIT[d] = gtsam.noiseModel.Unit.Create(d)
    return _UNIT[d]


def linearize(blocks: list[Block], states: imu.ImuState, calibration=None) -> tuple[gtsam.GaussianFactorGraph, float]:
    """The Gauss-Newton system ``|A delta - b|^2`` at ``states`` and the calibration variables'
    values ``calibration`` (``b = -e``; a calibrated block's factors also on key ``n + j``), and
    the cost there."""
    for b in blocks:
        if b.before_linearize is not None:
            b.before_linearize(states)
    graph = gtsam.GaussianFactorGraph()
    cost = 0.0
    n = len(states)
    for block in blocks:
        if block.keyframes.shape[1] > 2:
            raise InputError(f"block {block.name}: factors on more than two keyframes are not supported")
        extra = () if block.calibration is None else (n + block.calibration,)
        # in chunks, so the Jacobians of a long run stay in cache between evaluation and use
        for start in range(0, len(block), LINEARIZE_CHUNK):
            rows = slice(start, min(start + LINEARIZE_CHUNK, len(block)))
            ev = evaluate_block(block, states, True, rows, calibration=calibration)
            cost += ev.loss
            model = _unit(ev.e.shape[1])
            keys = [*block.keyframes[rows].T.tolist(), *([[extra[0]] * len(ev.e)] if extra else [])]
            A, b = ev.A, -ev.e
            if len(keys) == 1:
                for m, k in enumerate(keys[0]):
                    graph.add(gtsam.JacobianFactor(k, A[0][m], b[m], model))
            elif len(keys) == 2:
                for m, (k0, k1) in enumerate(zip(*keys)):
                    graph.add(gtsam.JacobianFactor(k0, A[0][m], k1, A[1][m], b[m], model))
            else:
                for m, (k0, k1, k2) in enumerate(zip(*keys)):
                    graph.add(gtsam.JacobianFactor(k0, A[0][m], k1, A[1][m], k2, A[2][m], b[m], model))
    return graph, cost


#: Factors of a block linearised at once (a few MB of Jacobians: cache-resident, so the cost per
#: factor does not grow with the length of the run).
LINEARIZE_CHUNK = 1024


def _keyframe_of(error: RuntimeError) -> int | None:
    match = re.search(INDETERMINANT_KEY, str(error))
    return int(match.group(1)) if match else None


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
            raise _named_free(again, graph, ordering) from None
    return layout.flat(solution)


def _named_free(error: RuntimeError, graph: gtsam.GaussianFactorGraph, ordering: gtsam.Ordering) -> Exception:
    """GTSAM's indeterminant-system ``error`` under QR as :class:`IndeterminantSystem` naming the
    keyframe and its free components; any other error as it is."""
    if not is_indeterminant(error):
        return error
    key = _keyframe_of(error)
    return IndeterminantSystem(str(error), key, _free_after(graph, ordering, key))


@dataclass(frozen=True)
class Layout:
    """The linear variables of a problem: ``n`` keyframes (keys ``0 .. n - 1``, 15 each), then the
    calibration variables (keys ``n + j``, ``extra[j]`` each). A step is one flat vector in key
    order."""

    n: int
    extra: tuple[int, ...] = ()

    def dim(self, key: int) -> int:
        return DIM if key < self.n else self.extra[key - self.n]

    def calibration_columns(self) -> dict:
        """``{n + j: slice}``: where each calibration variable's coordinates sit when all of
        them are stacked in key order."""
        bounds = np.cumsum([0, *self.extra])
        return {self.n + j: slice(int(bounds[j]), int(bounds[j + 1])) for j in range(len(self.extra))}

    def ordering(self, graph: gtsam.GaussianFactorGraph) -> gtsam.Ordering | None:
        """COLAMD with the calibration variables last, or None (GTSAM's default) without any."""
        if not self.extra:
            return None
        last = gtsam.KeyVector(list(range(self.n, self.n + len(self.extra))))
        return gtsam.Ordering.ColamdConstrainedLastGaussianFactorGraph(graph, last)

    @property
    def keys(self) -> range:
        return range(self.n + len(self.extra))

    def flat(self, vv: gtsam.VectorValues) -> np.ndarray:
        return np.concatenate([vv.at(k) for k in self.keys])

    def vector_values(self, delta: np.ndarray) -> gtsam.VectorValues:
        vv, at = gtsam.VectorValues(), 0
        for k in self.keys:
            vv.insert(k, delta[at:at + self.dim(k)])
            at += self.dim(k)
        return vv

    def apply(self, states: imu.ImuState, calibration, delta: np.ndarray):
        """``(states [+] delta_x, calibration [+] delta_c)``."""
        moved = imu.boxplus(states, delta[:self.n * DIM].reshape(self.n, DIM))
        if calibration is None:
            return moved, None
        bounds = np.cumsum([self.n * DIM, *self.extra])
        return moved, calibration.boxplus(np.split(delta[bounds[0]:], bounds[1:-1] - bounds[0]))

    @staticmethod
    def of(states: imu.ImuState, calibration=None) -> "Layout":
        return Layout(len(states), () if calibration is None else tuple(calibration.dims))


def _damped(graph: gtsam.GaussianFactorGraph, layout: Layout, lam: float) -> gtsam.GaussianFactorGraph:
    damped = gtsam.GaussianFactorGraph()
    damped.push_back(graph)
    for k in layout.keys:
        d = layout.dim(k)
        damped.add(gtsam.JacobianFactor(k, np.sqrt(lam) * np.eye(d), np.zeros(d), _unit(d)))
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
    itself, keeping that step, or after ``max_iterations``."""
    if method not in METHODS:
        raise InputError(f"method {method!r}: expected one of {', '.join(METHODS)}")
    layout = Layout.of(initial, calibration)
    states = initial
    graph, cost = linearize(blocks, states, calibration)
    # the factors' keys are the same at every linearisation, and damping adds unary factors only:
    # one elimination ordering serves every step
    ordering = layout.ordering(graph)
    history = [cost]
    lam, radius = 1e-5, 1.0
    converged = False
    iterations = 0
    for iterations in range(1, max_iterations + 1):
        accepted = False
        for _ in range(30):  # inner loop: damping / trust-region adjustments
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
            trial, trial_calibration = layout.apply(states, calibration, delta)
            trial_cost = total_cost(blocks, trial, trial_calibration)
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
                promised = cost - graph.error(layout.vector_values(delta))
                if promised <= max(absolute_tolerance, relative_tolerance * cost):
                    break
                lam *= 10.0
                if lam > 1e10:
                    break
            else:
                predicted = cost - graph.error(layout.vector_values(delta))
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
        states, calibration = trial, trial_calibration
        if abs(decrease) < absolute_tolerance or abs(decrease) < relative_tolerance * max(trial_cost, 1e-300):
            cost = trial_cost  # converged: the step kept, no further linearisation
            history.append(cost)
            converged = True
            break
        graph, cost = linearize(blocks, states, calibration)
        history.append(cost)
    return SolverResult(states, cost, iterations, converged, history, calibration)


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


def covariances(blocks: list[Block], states: imu.ImuState, which=None, pairs: bool = False, calibration=None):
    """Marginal 15x15 covariances (primer convention) of the keyframes ``which`` (default all),
    from the linearisation at ``states`` and ``calibration`` (:func:`marginal_covariances`; with
    ``pairs`` also the joint blocks it computes on the way, those of the calibration variables,
    keys ``n + j``, among them)."""
    graph, _ = linearize(blocks, states, calibration)
    return marginal_covariances(graph, len(states), which, pairs, Layout.of(states, calibration))


#: The error state's quantities, three components each, in their order.
QUANTITIES = ("position (world) ", "velocity (body) ", "attitude (world) about ", "accelerometer bias ",
              "gyro bias ")


def marginal_covariances(graph: gtsam.GaussianFactorGraph, n: int, which=None, pairs: bool = False,
                         layout: Layout | None = None):
    """Marginal covariances of the variables ``which`` (default all keyframes) of the whitened
    linear system ``graph`` on the 15-dim keys ``0 .. n - 1`` (and the keys of ``layout``'s
    calibration variables, if given), from its square-root information.

    GTSAM eliminates ``graph`` with QR (COLAMD ordering, the calibration variables last) into
    conditionals ``R_i x_i + S_i x_P(i) = d_i``, which work on the rows themselves: the condition
    number that matters is that of the rows, not of their squares (``A^T A``), so a long
    dead-reckoned stretch -- whose information matrix Cholesky declares indeterminant -- still
    factors. The covariance blocks follow from the selected-inversion recursion over the
    conditionals in reverse elimination order, ``Sigma_iP = K_i Sigma_PP`` and
    ``Sigma_ii = R_i^-1 R_i^-T + Sigma_iP K_i^T`` with ``K_i = -R_i^-1 S_i``: a conditional's
    parents were eliminated after it and are pairwise parents of one another, so every block the
    recursion needs is computed before it is used. (GTSAM's own ``marginalCovariance`` goes
    through Cholesky-based shortcuts and loses those digits again.)

    With calibration variables ``c`` (the dense border: every keyframe's conditional may have them
    among its parents) the keyframes' recursion runs on their keyframe parents alone, which gives
    the covariances given ``c``, ``Sigma^c``; the conditionals' calibration columns give the gain
    of the keyframes' mean on ``c``, ``G_i = K_i,x G_P + K_i,c``; and the law of total covariance
    adds what ``c``'s own uncertainty contributes: ``Sigma_ab = Sigma^c_ab + G_a Sigma_cc G_b^T``,
    ``Sigma_ic = G_i Sigma_cc``. The same blocks as the recursion over every parent, at the cost of
    the plain chain's recursion and a few products.

    A variable the rows do not determine -- GTSAM finds too few rows for it, or a pivot of its
    ``R_i`` is below ``RANK_TOLERANCE`` times the largest -- raises :class:`IndeterminantSystem`
    naming its key and the error-state components left free there (:func:`free_components`).

    ``pairs``: also return the dict ``{(a, b): Sigma_ab}`` of every block the recursion computed
    (``Sigma_ba = Sigma_ab^T``). Every two variables that share a factor are a conditional and its
    parent, so it holds the joint covariance of every factor's variables."""
    layout = layout or Layout(n)
    ordering = layout.ordering(graph) or gtsam.Ordering.ColamdGaussianFactorGraph(graph)
    try:
        net = graph.eliminateSequential(ordering, gtsam.EliminateQR)
    except RuntimeError as error:
        raise _named_free(error, graph, ordering) from None
    conditionals = [net.at(i) for i in range(net.size())]
    keys = [[int(k) for k in c.keys()] for c in conditionals]
    R_inv, own = _inverted(conditionals, keys, n)
    columns = layout.calibration_columns()  # key n + j: its columns in the stacked calibrations
    nc = sum(layout.extra)
    sigma: dict[tuple[int, int], np.ndarray] = {}  # Sigma^c between keyframes; Sigma between calibrations
    gain: dict[int, np.ndarray] = {}  # G_i (15, nc) of each keyframe
    for i in reversed(range(len(conditionals))):
        frontal, parents = keys[i][0], keys[i][1:]
        if not parents:
            sigma[(frontal, frontal)] = own[i]
            if frontal < n and nc:  # its mean does not depend on the calibrations
                gain[frontal] = np.zeros((own[i].shape[0], nc))
            continue
        K = -R_inv[i] @ conditionals[i].S()
        bounds = [0]
        for p in parents:
            bounds.append(bounds[-1] + layout.dim(p))
        # a keyframe's recursion runs over its keyframe parents, a calibration's over all of its
        kept = [j for j, p in enumerate(parents) if p < n or frontal >= n]
        if len(kept) == 1:
            K_kept = K[:, bounds[kept[0]]:bounds[kept[0] + 1]]
            cross = K_kept @ sigma[(parents[kept[0]], parents[kept[0]])]
            sigma[(frontal, parents[kept[0]])] = cross
        elif kept:
            # Sigma_PP over the kept parents (all computed: see the docstring)
            rows = [np.hstack([sigma[(parents[a], parents[b])] if (parents[a], parents[b]) in sigma
                               else sigma[(parents[b], parents[a])].T for b in kept]) for a in kept]
            K_kept = K if len(kept) == len(parents) else np.hstack([K[:, bounds[j]:bounds[j + 1]] for j in kept])
            cross = K_kept @ np.vstack(rows)
            at = 0
            for j in kept:
                width = bounds[j + 1] - bounds[j]
                sigma[(frontal, parents[j])] = cross[:, at:at + width]
                at += width
        if kept:
            both = own[i] + cross @ K_kept.T
            sigma[(frontal, frontal)] = 0.5 * (both + both.T)
        else:
            sigma[(frontal, frontal)] = own[i]
        if frontal < n and nc:
            G = np.zeros((K.shape[0], nc))
            for j, parent in enumerate(parents):
                block = K[:, bounds[j]:bounds[j + 1]]
                if parent < n:
                    G += block @ gain[parent]
                else:
                    G[:, columns[parent]] += block
            gain[frontal] = G
    if nc:
        _add_calibration_share(sigma, gain, layout, columns)
    which = range(n) if which is None else which
    marginals = np.stack([sigma[(int(k), int(k))] for k in which])
    return (marginals, sigma) if pairs else marginals


def _inverted(conditionals: list, keys: list, n: int) -> tuple[list, list]:
    """``R_i^-1`` and ``R_i^-1 R_i^-T`` of every conditional, inverted together where their
    dimensions agree; :class:`IndeterminantSystem` where a pivot of ``R_i`` is at most
    ``RANK_TOLERANCE`` times the largest of them all (:func:`marginal_covariances`)."""
    R = [c.R() for c in conditionals]  # upper triangular, the frontal variable's dimension
    groups: dict[int, list[int]] = {}
    for i, r in enumerate(R):
        groups.setdefault(r.shape[0], []).append(i)
    stacks = {d: np.stack([R[i] for i in which]) for d, which in groups.items()}
    pivots = {d: np.abs(np.diagonal(stack, axis1=1, axis2=2)) for d, stack in stacks.items()}
    tolerance = RANK_TOLERANCE * max(p.max() for p in pivots.values())
    weak = [which[j] for d, which in groups.items() for j in np.flatnonzero(pivots[d].min(axis=1) <= tolerance)]
    if weak:
        i = max(weak)  # the one eliminated last: the first the recursion meets
        frontal = keys[i][0]
        raise IndeterminantSystem(f"indeterminant linear system near variable {frontal}", frontal,
                                  free_components(R[i], tolerance) if frontal < n else None)
    R_inv, own = [None] * len(R), [None] * len(R)
    for d, which in groups.items():
        inv = np.linalg.inv(stacks[d])
        product = inv @ inv.transpose(0, 2, 1)
        for j, i in enumerate(which):
            R_inv[i], own[i] = inv[j], product[j]
    return R_inv, own


def _add_calibration_share(sigma: dict, gain: dict, layout: Layout, columns: dict) -> None:
    """Turn the keyframes' blocks of ``sigma`` from covariances given the calibrations into
    marginal ones (:func:`marginal_covariances`: ``+ G_a Sigma_cc G_b^T``), and add the blocks
    between each keyframe and each calibration variable (``G_i Sigma_cc``), in place."""
    n = layout.n
    calibrations = list(columns)
    S_cc = np.vstack([np.hstack([sigma[(a, b)] if (a, b) in sigma else sigma[(b, a)].T for b in calibrations])
                      for a in calibrations])
    frames = list(gain)
    at = {k: i for i, k in enumerate(frames)}
    G = np.stack([gain[k] for k in frames])
    GS = G @ S_cc
    between = [pair for pair in sigma if pair[0] < n]  # both keyframes: no other keyframe block yet
    a = np.array([at[p[0]] for p in between])
    b = np.array([at[p[1]] for p in between])
    blocks = np.stack([sigma[p] for p in between]) + GS[a] @ G[b].transpose(0, 2, 1)
    same = a == b
    blocks[same] = 0.5 * (blocks[same] + blocks[same].transpose(0, 2, 1))
    sigma.update(zip(between, blocks))
    for k, G_S in zip(frames, GS):
        for key in calibrations:
            sigma[(k, key)] = G_S[:, columns[key]]


#: Pivots of the square-root information below this fraction of the largest count as zero: the
#: variable is not determined (a condition number of the rows beyond 1e10 leaves no digit of a
#: covariance anyway).
RANK_TOLERANCE = 1e-10


def _free_after(graph: gtsam.GaussianFactorGraph, ordering: gtsam.Ordering, key: int | None) -> str | None:
    """:func:`free_components` of the rows left on ``key`` once the variables before it in
    ``ordering`` are eliminated (None when that cannot be told)."""
    if key is None:
        return None
    position = [int(ordering.at(i)) for i in range(ordering.size())].index(key)
    before = gtsam.Ordering()
    for i in range(position):
        before.push_back(ordering.at(i))
    try:
        _, rest = graph.eliminatePartialSequential(before, gtsam.EliminateQR)
    except RuntimeError:
        return None
    rows = [rest.at(i).jacobian()[0][:, _columns(rest.at(i), key)] for i in range(rest.size())
            if rest.at(i) is not None and key in rest.at(i).keys()]
    A = np.vstack(rows) if rows else np.zeros((0, DIM))
    return free_components(A, 1e-9 * np.abs(A).max() if A.size else 0.0)


def free_components(rows: np.ndarray, tolerance: float) -> str | None:
    """The error-state components that the rows ``(m, 15)`` of one variable leave free, e.g.
    ``"position (world) x, y, attitude (world) about z"`` (a yaw about the origin): those that
    take part in the null space of the rows (singular values at most ``tolerance``; the weakest
    direction if none is), with a weight of at least 1e-8 of the largest -- a rotation about the
    origin moves a position km away 1e3 times more than the attitude, in their units."""
    s, V = np.zeros(DIM), np.eye(DIM)
    if rows.shape[0]:
        _, top, Vt = np.linalg.svd(rows, full_matrices=True)
        s[:len(top)], V = top, Vt.T
    null = V[:, s <= tolerance]
    if null.shape[1] == 0:  # nearly singular only: its weakest direction
        null = V[:, -1:]
    weight = np.sum(null * null, axis=1)
    free = (weight >= 1e-8 * weight.max()).reshape(len(QUANTITIES), 3)
    if free.all():
        return "whole state (position, velocity, attitude, biases)"
    return ", ".join(quantity + ", ".join(np.array(list("xyz"))[axes])
                     for quantity, axes in zip(QUANTITIES, free) if axes.any()) or None


def _columns(factor, key: int) -> slice:
    """The columns of ``key`` in ``factor.jacobian()`` (its keys' 15 columns each, in order)."""
    j = [int(k) for k in factor.keys()].index(key)
    return slice(j * DIM, (j + 1) * DIM)
