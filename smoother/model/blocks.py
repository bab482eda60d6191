"""The problem's factors as vectorised blocks on the primer's chart, and their linearisation into
a GTSAM ``GaussianFactorGraph``.

Why: GTSAM's nonlinear optimisers call a ``CustomFactor`` back once per factor and, inside C++,
hand each call a copy of the whole ``Values`` -- a batch solve of a long run becomes quadratic
and spends its time in Python call overhead. Here every factor type is evaluated for all its
instances at once with NumPy (the SAME residual functions the ``CustomFactor`` wrappers call),
and GTSAM does what it does best: the sparse linear algebra (:mod:`smoother.batch.optimiser`
for the steps, :mod:`smoother.model.covariances` for the covariances).

Variables: one 15-dim linear variable per keyframe (key = keyframe index), the primer's error
state ``(dr, dv, dphi, db_f, db_w)``; a step is applied with :func:`factors.imu.boxplus` (LEFT
attitude increment), so covariances come out directly in the primer's convention. A problem may
add calibration variables (:class:`factors.calibration.CalibrationSet`): sensor ``j``'s is the
linear variable ``n + j`` (``n`` keyframes) over its estimated coordinates, stepped with
:meth:`~factors.calibration.CalibrationSet.boxplus`; they take part in every step and covariance
like the keyframes (:class:`Layout`).

A :class:`Block` holds the factors of one kind: their keyframe indices, a vectorised residual
returning errors and Jacobians in error-state columns, the whitening matrices of their
covariances and an optional robust kernel (GTSAM's ``mEstimator``, applied by iteratively
reweighting as GTSAM does: rows scaled by ``sqrt(w(|e_w|))``, cost ``rho(|e_w|)``).
"""
from __future__ import annotations

from collections.abc import Iterator
from dataclasses import dataclass
from typing import Callable

import gtsam
import numpy as np

from factors import imu
from factors.errors import InputError

DIM = imu.STATE_DIM


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
class Evaluated:
    """What :func:`evaluate_block` returns."""

    e: np.ndarray  # whitened and reweighted residuals (M, d)
    A: list  # whitened and reweighted Jacobians, one (M, d, 15) per slot
    loss: float
    #: the robust kernel's row scale ``sqrt(w(|e_w|))`` (M, 1) applied to ``e`` and ``A``; None without one
    scale: np.ndarray | None = None


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
                   keyframe_offset: int = 0, calibration=None, reweight: bool = True) -> Evaluated:
    """Whitened (and robustly reweighted) residuals and Jacobians of the factors ``rows`` of
    ``block``; ``states[k - keyframe_offset]`` is the state of keyframe ``k``; ``calibration``
    the calibration variables' values (:func:`block_residual`). ``reweight`` False: whitened
    only, a robust kernel left out (its rows and loss as without one)."""
    keyframes = block.keyframes[rows] - keyframe_offset
    whiten = block.whiten[rows]
    slots = [states[keyframes[:, s]] for s in range(keyframes.shape[1])]
    if jacobians:
        e, Js = block_residual(block, slots, True, rows, calibration)
    else:
        e, Js = block_residual(block, slots, False, rows, calibration), None
    e_w = np.einsum("mab,mb->ma", whiten, e)
    if block.robust is None or not reweight:
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
    return Evaluated(e_w, A, loss, scale)


def evaluated_chunks(block: Block, states: imu.ImuState, jacobians: bool, calibration=None,
                     reweight: bool = True) -> Iterator[tuple[slice, Evaluated]]:
    """:func:`evaluate_block` over every factor of ``block``, :data:`CHUNK` factors at a time:
    ``(rows, evaluated)`` per chunk, ``states`` one per keyframe. A long run's Jacobians are
    never all held at once, and a chunk's stay in cache between their evaluation and their use."""
    for start in range(0, len(block), CHUNK):
        rows = slice(start, min(start + CHUNK, len(block)))
        yield rows, evaluate_block(block, states, jacobians, rows, calibration=calibration, reweight=reweight)


#: Factors of a block evaluated at once by :func:`evaluated_chunks` (a few MB of Jacobians:
#: cache-resident, so the cost per factor does not grow with the length of the run).
CHUNK = 1024


def total_cost(blocks: list[Block], states: imu.ImuState, calibration=None) -> float:
    """``sum rho(|e_w|)`` over every factor (``|e_w|^2 / 2`` without a robust kernel)."""
    return sum(evaluate_block(b, states, False, calibration=calibration).loss for b in blocks)


_UNIT_MODELS = {}


def unit_model(d: int):
    """GTSAM's unit noise model of dimension ``d`` (the rows are whitened already), made once."""
    if d not in _UNIT_MODELS:
        _UNIT_MODELS[d] = gtsam.noiseModel.Unit.Create(d)
    return _UNIT_MODELS[d]


def linearize(blocks: list[Block], states: imu.ImuState, calibration=None) -> tuple[gtsam.GaussianFactorGraph, float]:
    """The Gauss-Newton system ``|A delta - b|^2`` at ``states`` and the calibration variables'
    values ``calibration`` (``b = -e``; a calibrated block's factors also on key ``n + j``), and
    the cost there. Consecutive factors of a block on the same keys -- the measurements of one
    sensor at one keyframe -- are one GTSAM factor, their rows stacked (the same system): GTSAM's
    ordering and elimination take time growing faster than the number of factors on one variable,
    and a calibration variable is on every measurement of its sensor (on 15 minutes of 83 Hz wheel
    speeds, 75 000 factors on one key, the ordering took 1.5 s and the solves 3 s; 0.3 s and 1.2 s
    with the rows of a keyframe as one factor)."""
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
        for rows, ev in evaluated_chunks(block, states, True, calibration):
            cost += ev.loss
            keys = [*block.keyframes[rows].T.tolist(), *([[extra[0]] * len(ev.e)] if extra else [])]
            A, b = ev.A, -ev.e
            for lo, hi in _runs(np.array(keys).T):
                at = [key[lo] for key in keys]
                parts = [x for pair in zip(at, (a[lo:hi].reshape(-1, a.shape[2]) for a in A)) for x in pair]
                model = unit_model(b.shape[1] * (hi - lo))
                graph.add(gtsam.JacobianFactor(*parts, b[lo:hi].reshape(-1), model))
    return graph, cost


def _runs(keys: np.ndarray) -> list[tuple[int, int]]:
    """``(lo, hi)`` of each run of consecutive rows of ``keys`` (factors x their keys) that are equal."""
    if not len(keys):
        return []
    bounds = [0, *(np.flatnonzero(np.any(keys[1:] != keys[:-1], axis=1)) + 1).tolist(), len(keys)]
    return list(zip(bounds[:-1], bounds[1:]))


@dataclass(frozen=True)
class Layout:
    """The linear variables of a problem: ``n`` keyframes (keys ``0 .. n - 1``, 15 each), then the
    calibration variables (keys ``n + j``, ``extra[j]`` each). A step is one flat vector in key
    order. ``chain``: every factor is on one keyframe or on two consecutive ones (and calibration
    variables), which lets :meth:`ordering` choose the elimination order from the structure
    instead of searching for one."""

    n: int
    extra: tuple[int, ...] = ()
    chain: bool = False
    #: Not a chain, but every factor on keyframes in time order with at most :data:`BAND` of them over
    #: any keyframe interval (a drifting sensor's factors between its consecutive measurements,
    #: :mod:`smoother.model.correlated`): eliminated in time order too (:meth:`ordering`).
    banded: bool = False

    def dim(self, key: int) -> int:
        return DIM if key < self.n else self.extra[key - self.n]

    def calibration_columns(self) -> dict:
        """``{n + j: slice}``: where each calibration variable's coordinates sit when all of
        them are stacked in key order."""
        bounds = np.cumsum([0, *self.extra])
        return {self.n + j: slice(int(bounds[j]), int(bounds[j + 1])) for j in range(len(self.extra))}

    def ordering(self, graph: gtsam.GaussianFactorGraph, nested: bool = False) -> gtsam.Ordering | None:
        """The elimination order of ``graph`` (whose keys are this layout's) for the steps'
        sparse Cholesky (``nested``) or the covariances' QR; None for GTSAM's default (COLAMD).

        Calibration variables go last: every keyframe's conditional then has them among its
        parents, the dense border of an arrowhead system. But every factor on one makes GTSAM's
        elimination tree walk from its keyframe up to the root (its construction does not
        compress paths), and COLAMD orders a dense column in time growing with the run too: both
        quadratic in the run's length (on an hour's car, 36 000 keyframes, 2.4 s for the ordering
        and about 1 s for each elimination tree). On a ``chain`` the order comes from the
        structure instead:

        * ``nested``, with calibration variables: nested dissection of the chain, the keyframes
          whose index ``k + 1`` has no factor 2 first, then those with one, and so on -- each
          level splits what is left in halves, so the tree is ``log2 n`` deep, and a
          conditional's parents are at most its two neighbours at its level;
        * for the covariances: the keyframes in time order, a sweep, where the selected
          inversion runs over one keyframe parent per conditional (QR costs more on the nested
          order's wider conditionals: 87 us a keyframe against 65 at 24 000 keyframes), swept in
          pieces that leave the calibration variables to the end
          (:func:`smoother.model.covariances.marginal_covariances`).

        A ``banded`` problem's covariances are swept in time order the same way: a conditional's
        keyframe parents are the next keyframe and the far ends of the (at most :data:`BAND`)
        factors over it. Its steps, and everything else, COLAMD, with the calibration variables
        constrained last (time order there makes the elimination tree as deep as the run)."""
        calibrations = list(range(self.n, self.n + len(self.extra)))
        if self.banded and not nested:  # a conditional's keyframe parents: the next, the far ends of factors over it
            return gtsam.Ordering(gtsam.KeyVector([*range(self.n), *calibrations]))
        if self.chain and (self.extra or not nested):
            keyframes = nested_dissection(self.n) if nested else np.arange(self.n)
            return gtsam.Ordering(gtsam.KeyVector([*keyframes.tolist(), *calibrations]))
        if not self.extra:
            return None
        return gtsam.Ordering.ColamdConstrainedLastGaussianFactorGraph(graph, gtsam.KeyVector(calibrations))

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
    def of(states: imu.ImuState, calibration=None, blocks: list[Block] | None = None) -> "Layout":
        """The layout of ``states`` and ``calibration``; a ``chain`` if ``blocks`` (the factors)
        are given and every one of them is on consecutive keyframes."""
        chain = blocks is not None and all(
            b.keyframes.shape[1] < 2 or not len(b.keyframes) or np.abs(np.diff(b.keyframes, axis=1)).max() <= 1
            for b in blocks)
        banded = blocks is not None and not chain and _spanned_at_most(blocks, len(states), BAND)
        return Layout(len(states), () if calibration is None else tuple(calibration.dims), chain, banded)


#: The most factors over one keyframe interval for which :class:`Layout` eliminates a problem that is
#: no chain in time order (``banded``): each keyframe's conditional then has at most this many
#: keyframe parents beyond the next.
BAND = 8


def _spanned_at_most(blocks: list[Block], n: int, most: int) -> bool:
    """Whether at most ``most`` factors of ``blocks`` (on ``n`` keyframes) reach over any keyframe
    interval beyond the next keyframe (a factor from ``a`` to ``b > a + 1`` reaches over ``a + 1 ..
    b - 1``)."""
    over = np.zeros(n + 1, dtype=np.int64)
    for b in blocks:
        if b.keyframes.shape[1] < 2 or not len(b.keyframes):
            continue
        lo, hi = b.keyframes.min(axis=1), b.keyframes.max(axis=1)
        far = hi > lo + 1
        np.add.at(over, lo[far] + 1, 1)
        np.add.at(over, hi[far], -1)
    return bool(np.cumsum(over).max() <= most)


def nested_dissection(n: int) -> np.ndarray:
    """The keyframes ``0 .. n - 1`` of a chain in nested-dissection order: by the number of
    factors 2 in ``k + 1`` (the middle of every stretch the levels before left is eliminated
    after both its halves), in time order within a level."""
    index = np.arange(n)
    level, odd = np.zeros(n, dtype=np.int64), index + 1
    while np.any(odd % 2 == 0):
        even = odd % 2 == 0
        level[even] += 1
        odd = np.where(even, odd // 2, odd)
    return np.lexsort((index, level))


