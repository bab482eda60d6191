"""Marginal and joint covariances of a whitened linear system's variables, in the primer's
convention, from its square-root information (QR elimination and a selected-inversion recursion):
the batch smoother's keyframes and calibrations, GTSAM's fixed-lag windows, the factors' leverages.
Also a keyframe's covariance from GTSAM's own marginals on its nonlinear graph
(:func:`keyframe_covariance`), for the estimators that run GTSAM's optimisers and smoothers."""
from __future__ import annotations

from dataclasses import dataclass

import gtsam
import numpy as np

from factors import imu
from factors.keys import KeyframeKeys
from factors.uncertainty import state_covariance_to_primer
from smoother.errors import IndeterminantSystem
from smoother.model.blocks import DIM, Block, Layout, linearize
from smoother.model.rank import RANK_TOLERANCE, free_components, indeterminant_error


def keyframe_covariance(marginals, keys: KeyframeKeys, rotation) -> np.ndarray:
    """The primer-convention 15x15 covariance ``(dr, dv, dphi, db_f, db_w)`` of the keyframe with
    ``keys`` from GTSAM's joint marginal of its four variables: ``marginals`` is anything with
    GTSAM's ``jointMarginalCovariance`` (``gtsam.Marginals`` of a nonlinear graph, ``gtsam.ISAM2``),
    ``rotation`` the keyframe's attitude at the linearisation point (a ``gtsam.Rot3`` or its 3x3
    matrix), where GTSAM's right chart of the attitude is taken
    (:func:`factors.uncertainty.state_covariance_to_primer`)."""
    joint = marginals.jointMarginalCovariance(gtsam.KeyVector(keys.all())).fullMatrix()
    return state_covariance_to_primer(joint, rotation)


def covariances_at(blocks: list[Block], states: imu.ImuState, which=None, pairs: bool = False, calibration=None):
    """Marginal 15x15 covariances (primer convention) of the keyframes ``which`` (default all),
    from the linearisation at ``states`` and ``calibration`` (:func:`marginal_covariances`; with
    ``pairs`` also the joint blocks it computes on the way, those of the calibration variables,
    keys ``n + j``, among them)."""
    graph, _ = linearize(blocks, states, calibration)
    return marginal_covariances(graph, len(states), which, pairs, Layout.of(states, calibration, blocks))


def marginal_covariances(graph: gtsam.GaussianFactorGraph, n: int, which=None, pairs: bool = False,
                         layout: Layout | None = None, square_root: bool = False):
    """Marginal covariances of the variables ``which`` (default all keyframes) of the whitened
    linear system ``graph`` on the 15-dim keys ``0 .. n - 1`` (and the keys of ``layout``'s
    calibration variables, if given), from its square-root information.

    GTSAM eliminates ``graph`` with QR (:meth:`Layout.ordering`, the calibration variables last) into
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

    ``pairs``: also return the dict ``{(a, b): Sigma_ab}`` of every block the recursion computed,
    each pair once (:func:`joint_block` reads either order). Every two variables that share a
    factor are a conditional and its parent, so it holds the joint covariance of every factor's
    variables.

    ``square_root`` (with ``pairs``): also return the conditionals as a :class:`SquareRoot`, with
    which :func:`covariance_tangent` differentiates those blocks, and the system's solution."""
    layout = layout or Layout(n)
    keys, R, S, d = _eliminated(graph, layout)
    R_inv, own = _inverted(R, keys, n)
    del R
    columns = layout.calibration_columns()  # key n + j: its columns in the stacked calibrations
    nc = sum(layout.extra)
    sigma: dict[tuple[int, int], np.ndarray] = {}  # Sigma^c between keyframes; Sigma between calibrations
    gains: list = [None] * len(keys)  # K_i of each conditional with parents
    gain: dict[int, np.ndarray] = {}  # G_i (15, nc) of each keyframe
    for i in reversed(range(len(keys))):
        frontal, parents = keys[i][0], keys[i][1:]
        if not parents:
            sigma[(frontal, frontal)] = own[i].copy()  # own's arrays are views of one stack
            if frontal < n and nc:  # its mean does not depend on the calibrations
                gain[frontal] = np.zeros((own[i].shape[0], nc))
            continue
        K = -R_inv[i] @ S[i]
        if square_root:
            gains[i] = K
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
            rows = [np.hstack([joint_block(sigma, parents[a], parents[b]) for b in kept]) for a in kept]
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
            sigma[(frontal, frontal)] = own[i].copy()
        if frontal < n and nc:
            G = np.zeros((K.shape[0], nc))
            for j, parent in enumerate(parents):
                block = K[:, bounds[j]:bounds[j + 1]]
                if parent < n:
                    G += block @ gain[parent]
                else:
                    G[:, columns[parent]] += block
            gain[frontal] = G
    root = SquareRoot(keys, own, gains, layout, _back_substituted(keys, R_inv, S, d, layout)) if square_root else None
    del R_inv, own, S, d  # before the calibrations' share: the largest of the arrays made at once
    if nc:
        _add_calibration_share(sigma, gain, layout, columns)
    which = range(n) if which is None else which
    marginals = np.stack([sigma[(int(k), int(k))] for k in which])
    if square_root:
        return marginals, sigma, root
    return (marginals, sigma) if pairs else marginals


def joint_block(joint: dict, a: int, b: int) -> np.ndarray:
    """``Sigma_ab`` from ``joint`` (:func:`marginal_covariances`' ``pairs``), which holds each pair
    of variables in one order only: ``Sigma_ba = Sigma_ab^T``."""
    a, b = int(a), int(b)
    return joint[(a, b)] if (a, b) in joint else joint[(b, a)].T


def joint_blocks(joint: dict, a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """``Sigma_ab`` of each pair ``(a[m], b[m])`` stacked (:func:`joint_block`), each distinct pair
    read once: a sensor's measurements at one keyframe, or all of them with its calibration
    variable, share theirs."""
    width = int(max(a.max(), b.max())) + 1
    pairs, at = np.unique(a.astype(np.int64) * width + b, return_inverse=True)
    return np.stack([joint_block(joint, x, y) for x, y in zip((pairs // width).tolist(), (pairs % width).tolist())])[at]


@dataclass(frozen=True)
class SquareRoot:
    """The conditionals of an elimination (:func:`marginal_covariances`), in elimination order:
    each one's ``keys`` (its frontal variable, then its parents), ``inverse`` ``R_i^-1 R_i^-T`` and
    ``gain`` ``K_i = -R_i^-1 S_i`` (None without parents), on the variables of ``layout``; and
    ``solution``, the system's least-squares solution by their back-substitution (flat, in the
    layout's order)."""

    keys: list
    inverse: list
    gain: list
    layout: Layout
    solution: np.ndarray


class CovarianceBetween:
    """``Sigma_ab`` of any two variables of an elimination (:class:`SquareRoot`), not only of a
    conditional and its parent as :func:`marginal_covariances` computes them (``sigma``, its
    ``pairs``): for ``a`` eliminated before ``b``, ``Sigma_ab = K_a Sigma_(P(a) b)`` over all of
    ``a``'s parents -- the recursion's own identity, taken across the pattern -- each ``Sigma_pb``
    read from ``sigma`` or found the same way, until every pair is one ``sigma`` holds. Memoised:
    the pairs met on the way (the keyframes between two measurements whose errors are correlated,
    say) serve the next call. Two variables eliminated far apart cost a chain of products as long
    as the elimination path between them."""

    def __init__(self, root: SquareRoot, sigma: dict):
        self._root, self._sigma = root, sigma
        self._position = {int(keys[0]): i for i, keys in enumerate(root.keys)}
        self._found: dict = {}

    def __call__(self, a: int, b: int) -> np.ndarray:
        a, b = int(a), int(b)
        if self._position[a] > self._position[b]:
            return self(b, a).T
        pending = [(a, b)]
        while pending:
            x, y = pending[-1]
            if self._known(x, y) is not None:
                pending.pop()
                continue
            i = self._position[x]
            parents = [int(p) for p in self._root.keys[i][1:]]
            if not parents:  # a root eliminated before y: y is in another component, independent of it
                self._found[(x, y)] = np.zeros((self._root.layout.dim(x), self._root.layout.dim(y)))
                pending.pop()
                continue
            missing = [(p, y) if self._position[p] <= self._position[y] else (y, p)
                       for p in parents if self._known(p, y) is None]
            if missing:
                pending.extend(missing)
                continue
            blocks = [self._known(p, y) for p in parents]
            self._found[(x, y)] = self._root.gain[i] @ np.vstack(blocks)
            pending.pop()
        return self._known(a, b)

    def _known(self, a: int, b: int) -> np.ndarray | None:
        """``Sigma_ab`` where ``sigma`` holds it or it was found, else None."""
        for x, y, flip in ((a, b, False), (b, a, True)):
            value = self._sigma.get((x, y))
            if value is None:
                value = self._found.get((x, y))
            if value is not None:
                return value.T if flip else value
        return None


def covariance_tangent(root: SquareRoot, sigma: dict, information: dict) -> dict:
    """The change of the covariance blocks ``sigma`` (:func:`marginal_covariances`' ``pairs``) for
    changes of the information matrix on its pattern: ``information`` maps pairs of variables
    ``(a, b)`` to ``dLambda_ab`` stacked over directions ``(D, da, db)`` (each pair in one order;
    a missing one unchanged); returns ``dSigma = -Sigma dLambda Sigma`` on every pair of a
    conditional and its parent (and of such a keyframe and every calibration variable),
    ``{(a, b): (D, da, db)}`` with ``a <= b``, without forming ``Sigma`` whole.

    The elimination in information form: eliminating variable ``i`` leaves ``D_i = R_i^T R_i`` and
    ``Lambda'_iP = R_i^T S_i = -D_i K_i`` of the matrix reduced so far, and takes ``K_i^T D_i K_i``
    off its parents' block. Its tangent, in elimination order (every block it adds to is on the
    pattern: a conditional's parents are parents of one another): ``dK_i = -D_i^-1 (dLambda'_iP +
    dD_i K_i)`` and ``dLambda'_PP += dLambda'_Pi K_i + K_i^T dLambda'_iP + K_i^T dD_i K_i``. Then
    the selected inversion's (``Sigma_iP = K_i Sigma_PP``, ``Sigma_ii = D_i^-1 + K_i Sigma_PP K_i^T``)
    in reverse order: ``dSigma_iP = dK_i Sigma_PP + K_i dSigma_PP`` and ``dSigma_ii =
    -D_i^-1 dD_i D_i^-1 + K_i dSigma_PP K_i^T + dK_i Sigma_PP K_i^T + K_i Sigma_PP dK_i^T``. The
    calibration variables, eliminated last, are one variable ``c`` here (a keyframe's gain on those
    it does not read is zero), and theirs is the inverse's: ``dSigma_cc = -Sigma_cc dLambda'_cc
    Sigma_cc``. Two sweeps of the keyframes' conditionals for all directions at once, where
    differencing takes an elimination and an inversion per direction."""
    layout = root.layout
    n, nc = layout.n, sum(layout.extra)
    columns = layout.calibration_columns()
    directions = len(next(iter(information.values())))
    c = n  # the calibration variables as one

    def dim(key):
        return DIM if key < n else nc

    acc: dict = {}

    def add(a, b, rows, cols, value):
        if (a, b) not in acc:
            acc[(a, b)] = np.zeros((directions, dim(a), dim(b)))
        acc[(a, b)][:, rows, cols] += value

    everything = slice(None)
    for (a, b), block in information.items():
        if a > b:
            a, b, block = b, a, np.swapaxes(block, -1, -2)
        if b < n:
            if (a, b) in acc:
                acc[(a, b)] += block
            else:
                acc[(a, b)] = np.array(block, dtype=float)  # a copy: the sweep adds to it
        elif a < n:
            add(a, c, everything, columns[b], block)
        else:
            add(c, c, columns[a], columns[b], block)
            if a != b:
                add(c, c, columns[b], columns[a], np.swapaxes(block, -1, -2))

    def read(store, a, b, take=False):  # take: the entry is read for the last time, and let go
        pair = (a, b) if a <= b else (b, a)
        value = store.pop(pair, None) if take else store.get(pair)
        if value is None:
            return np.zeros((directions, dim(a), dim(b)))
        return value if a <= b else np.swapaxes(value, -1, -2)

    S_cc = np.vstack([np.hstack([joint_block(sigma, a, b) for b in columns]) for a in columns]) if nc else None
    S_kc: dict = {}  # Sigma between a keyframe and c

    def covariance(a, b):
        if a < n and b < n:
            return joint_block(sigma, a, b)
        if a >= n and b >= n:
            return S_cc
        k = min(a, b)
        if k not in S_kc:
            S_kc[k] = np.hstack([joint_block(sigma, k, key) for key in columns])
        return S_kc[k] if a < n else S_kc[k].T

    frames = [i for i, k in enumerate(root.keys) if k[0] < n]  # the calibrations' come after them
    conditionals = {}  # i -> (parents, bounds, K over the parents, dD, dK)
    for i in frames:
        frontal, *parents = root.keys[i]
        dD = read(acc, frontal, frontal, take=True)  # eliminated: its blocks are not read again
        if not parents:
            conditionals[i] = ([], None, None, dD, None)
            continue
        P = [p for p in parents if p < n]
        bounds = [DIM * j for j in range(len(P) + 1)]
        if nc:
            P.append(c)
            bounds.append(bounds[-1] + nc)
        if parents[len(P) - 1:] == list(columns) or not nc:  # every calibration variable, in order
            K = root.gain[i]
        else:
            K = np.zeros((DIM, bounds[-1]))
            K[:, :bounds[-2]] = root.gain[i][:, :bounds[-2]]
            at = start = bounds[-2]
            for p in parents[len(P) - 1:]:
                K[:, start + columns[p].start:start + columns[p].stop] = root.gain[i][:, at:at + layout.dim(p)]
                at += layout.dim(p)
        dL = np.concatenate([read(acc, frontal, p, take=True) for p in P], axis=-1)
        dD_K = dD @ K
        dK = -root.inverse[i] @ (dL + dD_K)
        KT_dL = K.T @ dL
        update = KT_dL + np.swapaxes(KT_dL, -1, -2) + K.T @ dD_K
        for x, a in enumerate(P):
            for y, b in enumerate(P[x:], x):
                block = update[:, bounds[x]:bounds[x + 1], bounds[y]:bounds[y + 1]]
                if (a, b) in acc:
                    acc[(a, b)] += block
                else:
                    acc[(a, b)] = block
        conditionals[i] = (P, bounds, K, dD, dK)
    out: dict = {}
    if nc:
        out[(c, c)] = -S_cc @ read(acc, c, c) @ S_cc
    for i in reversed(frames):
        frontal = root.keys[i][0]
        P, bounds, K, dD, dK = conditionals.pop(i)
        D_inv = root.inverse[i]
        own = -D_inv @ dD @ D_inv
        if P:
            S_PP = np.empty((bounds[-1], bounds[-1]))
            dS_PP = np.empty((directions, bounds[-1], bounds[-1]))
            for x, a in enumerate(P):
                for y, b in enumerate(P):
                    S_PP[bounds[x]:bounds[x + 1], bounds[y]:bounds[y + 1]] = covariance(a, b)
                    dS_PP[:, bounds[x]:bounds[x + 1], bounds[y]:bounds[y + 1]] = read(out, a, b)
            dK_S = dK @ S_PP
            K_dS = K @ dS_PP
            cross = dK_S + K_dS
            dK_S_KT = dK_S @ K.T
            own = own + K_dS @ K.T + dK_S_KT + np.swapaxes(dK_S_KT, -1, -2)
            for x, p in enumerate(P):
                block = cross[:, :, bounds[x]:bounds[x + 1]]
                if frontal <= p:
                    out[(frontal, p)] = block
                else:
                    out[(p, frontal)] = np.swapaxes(block, -1, -2)
        out[(frontal, frontal)] = 0.5 * (own + np.swapaxes(own, -1, -2))
    # c back into the calibration variables
    for (a, b) in [pair for pair in out if pair[1] == c]:
        block = out.pop((a, b))
        if a < n:
            out.update({(a, key): block[:, :, cols] for key, cols in columns.items()})
        else:
            out.update({(x, y): block[:, columns[x], columns[y]] for x in columns for y in columns if x <= y})
    return out


#: Keyframes of a chain eliminated per GTSAM call in the covariances' sweep (:func:`_eliminated`).
SWEEP_PIECE = 4000


def _eliminated(graph: gtsam.GaussianFactorGraph, layout: Layout) -> tuple[list, list, list, list]:
    """The conditionals ``R_i x_i + S_i x_P(i) = d_i`` of ``graph``'s QR elimination in
    :meth:`Layout.ordering`'s order (COLAMD without one), as ``(keys, R, S, d)``: each
    conditional's keys (frontal, then parents) and its three arrays.

    On a chain the sweep runs in pieces of :data:`SWEEP_PIECE` keyframes, each GTSAM's partial
    elimination of the graph the piece before left, and the calibration variables alone at the
    end. GTSAM keeps every conditional's stacked rows whole (on the car, about four times its
    ``R`` and ``S``): one piece of them is alive at a time instead of the whole run's. And no
    factor on a calibration variable sends GTSAM's elimination tree walking from its keyframe
    to the root (:meth:`Layout.ordering`): they are not eliminated with the keyframes."""
    ordering = layout.ordering(graph) or gtsam.Ordering.ColamdGaussianFactorGraph(graph)
    pieces = [ordering]
    if layout.chain or layout.banded:
        pieces = [gtsam.Ordering(gtsam.KeyVector(list(range(at, min(at + SWEEP_PIECE, layout.n)))))
                  for at in range(0, layout.n, SWEEP_PIECE)]
        if layout.extra:
            pieces.append(gtsam.Ordering(gtsam.KeyVector(list(range(layout.n, layout.n + len(layout.extra))))))
    keys, R, S, d = [], [], [], []
    remaining = graph
    try:
        for j, piece in enumerate(pieces):
            if j == len(pieces) - 1:
                net = remaining.eliminateSequential(piece, gtsam.EliminateQR)
            else:
                net, remaining = remaining.eliminatePartialSequential(piece, gtsam.EliminateQR)
            for i in range(net.size()):  # copies: GTSAM's arrays are views into the net
                conditional = net.at(i)
                keys.append([int(k) for k in conditional.keys()])
                R.append(np.array(conditional.R()))
                S.append(np.array(conditional.S()))
                d.append(np.array(conditional.d()))
    except RuntimeError as error:
        raise indeterminant_error(error, graph, ordering) from None
    return keys, R, S, d


def _back_substituted(keys: list, R_inv: list, S: list, d: list, layout: Layout) -> np.ndarray:
    """The least-squares solution of the conditionals (:func:`_eliminated`; ``R_inv`` their
    ``R_i^-1``), ``x_i = R_i^-1 (d_i - S_i x_P(i))`` in reverse elimination order, flat in the
    layout's key order."""
    x: dict[int, np.ndarray] = {}
    for i in reversed(range(len(keys))):
        frontal, parents = keys[i][0], keys[i][1:]
        rhs = d[i] - S[i] @ np.concatenate([x[p] for p in parents]) if parents else d[i]
        x[frontal] = R_inv[i] @ rhs
    return np.concatenate([x[k] for k in layout.keys])


def _inverted(R: list, keys: list, n: int) -> tuple[list, list]:
    """``R_i^-1`` and ``R_i^-1 R_i^-T`` of every conditional's ``R_i`` (upper triangular, its
    frontal variable's dimension), inverted together where their dimensions agree;
    :class:`IndeterminantSystem` where a pivot of ``R_i`` is at most ``RANK_TOLERANCE`` times the
    largest of them all (:func:`marginal_covariances`)."""
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


#: Keyframe blocks given the calibration share added per stack (:func:`_add_calibration_share`).
SHARE_PIECE = 4096


def _add_calibration_share(sigma: dict, gain: dict, layout: Layout, columns: dict) -> None:
    """Turn the keyframes' blocks of ``sigma`` from covariances given the calibrations into
    marginal ones (:func:`marginal_covariances`: ``+ G_a Sigma_cc G_b^T``), and add the blocks
    between each keyframe and each calibration variable (``G_i Sigma_cc``), in place."""
    n = layout.n
    calibrations = list(columns)
    S_cc = np.vstack([np.hstack([joint_block(sigma, a, b) for b in calibrations]) for a in calibrations])
    frames = list(gain)
    at = {k: i for i, k in enumerate(frames)}
    G = np.stack([gain[k] for k in frames])
    GS = G @ S_cc
    between = [pair for pair in sigma if pair[0] < n]  # both keyframes: no other keyframe block yet
    for lo in range(0, len(between), SHARE_PIECE):  # in pieces: each makes a stack of its blocks
        pairs = between[lo:lo + SHARE_PIECE]
        a = np.array([at[p[0]] for p in pairs])
        b = np.array([at[p[1]] for p in pairs])
        blocks = np.stack([sigma[p] for p in pairs]) + GS[a] @ G[b].transpose(0, 2, 1)
        same = a == b
        blocks[same] = 0.5 * (blocks[same] + blocks[same].transpose(0, 2, 1))
        sigma.update(zip(pairs, blocks))
    for k, G_S in zip(frames, GS):
        for key in calibrations:
            sigma[(k, key)] = G_S[:, columns[key]]


def hat_blocks(A: list, keyframes: np.ndarray, calibration_key: int | None, cov: np.ndarray, joint: dict) -> np.ndarray:
    """Each factor's hat block ``A P A^T`` (``(M, d, d)``): ``A`` its whitened Jacobians (one
    ``(M, d, k)`` per keyframe slot of ``keyframes (M, slots)``, then its calibration variable's,
    key ``calibration_key``, if any), ``P`` the joint covariance of the variables it reads (the
    keyframes' marginals ``cov``, the other blocks from ``joint``: :func:`joint_block`). Its trace
    is the factor's leverage; ``I - A P A^T`` the covariance of its whitened residual at an
    estimate that used it."""
    keys = [keyframes[:, s] for s in range(keyframes.shape[1])]
    if calibration_key is not None:
        keys.append(np.full(len(keyframes), calibration_key))
    H = 0.0
    for a, (Aa, ka) in enumerate(zip(A, keys)):
        for b, (Ab, kb) in enumerate(zip(A, keys)):
            if b < a:
                continue
            if a == b and calibration_key is None or (a == b and a < keyframes.shape[1]):
                P = cov[ka]
            else:
                P = joint_blocks(joint, ka, kb)
            term = Aa @ P @ np.swapaxes(Ab, -1, -2)
            H = H + (term if a == b else term + np.swapaxes(term, -1, -2))
    return H
