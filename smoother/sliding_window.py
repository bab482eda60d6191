"""The project's own fixed-lag smoother: a sliding window of keyframes solved incrementally on
the compiled residuals, the keyframes that leave it marginalised into a linear prior.

Why: GTSAM's fixed-lag smoothers call every project factor back through Python at each
relinearisation (a ``CustomFactor`` per factor, each handed a copy of the ``Values``); that
overhead, not the mathematics, set the cost of an online update. Here a whole update is a few
compiled calls over flat arrays: the IMU residual (:func:`factors.preintegration._residual_into`),
the sensor kernels (:func:`datasets.kinds.measure_into`,
:func:`factors.sensor_models.odometry_kernel`), the same code the batch solver, the GTSAM factors
and the EKF run. ``docs/design.md`` (fixed-lag smoothing) gives the derivation in full.

The mathematics, in the primer's convention (error state ``(dr, dv, dphi, db_f, db_w)`` of each
window keyframe, LEFT attitude increment ``C <- exp(dphi) C``):

* ISAM2's scheme on a chain: keyframe ``k`` has a linearisation point ``theta_k`` and an offset
  ``delta_k``, its estimate is ``theta_k [+] delta_k``; the factors, linearised at the
  ``theta``s, give ``H = sum J^T J``, ``g = sum J^T e`` over whitened, robustly reweighted
  residuals (GTSAM's Huber, Cauchy and Tukey weights), and each update solves ``H delta = -g``.
  A keyframe is linearised again (``theta <- theta [+] delta``, ``delta <- 0``) when its offset
  exceeds :data:`RELINEARISATION_THRESHOLD` in any component; a step that would turn an attitude
  further than :data:`MAX_ATTITUDE_STEP` is shortened along its direction;
* keyframes in time order and factors that couple keyframes at most ``S`` apart (IMU factors 1,
  a relative pose its span, the marginal prior what it ties) make ``H`` block-banded; its
  Cholesky factor ``L`` (oldest keyframe first) keeps the band. Row ``k`` of ``L`` depends on the
  rows of ``H`` up to ``k`` only, so an update factorises again from the oldest changed row on
  (the new keyframe's factors reach ``S`` back; a relinearised keyframe's as far) and keeps the
  forward solution ``y = L^-1 (-g)`` of the rows before it; one backward solve gives every
  ``delta``;
* a keyframe older than the newest keyframe's time minus the lag is marginalised before the next
  keyframe is added: the factors touching it, linearised at the ``theta``s, are replaced by
  their Schur complement onto the keyframes they also touch, kept as the linear prior
  ``e(x) = R (x [-] x_lin) + e0`` with ``R^T R = H_mm - H_ml H_ll^-1 H_lm`` and ``R^T e0 = g_m -
  H_ml H_ll^-1 g_l`` at ``x_lin = theta`` (GTSAM keeps its marginals the same way, as linear
  factors at their linearisation point); ``[-]`` is the state's boxminus, whose attitude
  Jacobian is ``Gamma^-1(log(C C_lin^T))`` (eqs. 24, 32). The prior at keyframe 0 is such a prior
  too (``R`` the whitening of the initial covariance, ``e0 = 0``). Eliminating the oldest
  keyframes first, the rows of ``L`` after them are already the factor of that Schur complement
  (and ``y``'s rows its forward solution): no new factorisation;
* the newest keyframe never leaves before the next one is added, so an IMU gap longer than the
  lag keeps its IMU factor (GTSAM's smoothers drop it and need a weak prior);
* the marginal covariance of a window keyframe is its block of ``H^-1`` (two banded triangular
  solves with 15 right-hand sides).

The interface is :class:`smoother.fixed_lag.KeyframeWindow`'s (``leaving``, ``taken``,
``add_keyframe``, ``state``, ``covariances``), so :class:`smoother.online.OnlineSmoother` drives
either.
"""
from __future__ import annotations

import math
import time
from collections import deque
from contextlib import nullcontext
from dataclasses import dataclass

import numpy as np
from numba import njit

from datasets.kinds import measure_into, quiet_dispatch
from factors import imu, preintegration, so3
from factors.errors import InputError
from factors.preintegration import _residual_into, _residual_work
from factors.sensor_models import ODOMETRY_WIDTH, odometry_kernel
from smoother.fixed_lag import HISTORY, WEAK_PRIOR_SIGMAS, FixedLagFailed
from smoother.graph import RELATIVE_MODEL, robust_threshold
from factors.small_linalg import cholesky_into
from smoother.solver import whitening

DIM = imu.STATE_DIM
#: Robust kernels by their code in the compiled loop (0: none).
ROBUST_CODES = {"huber": 1, "cauchy": 2, "tukey": 3}
_MAX_DIM = 6  # the widest measurement residual (pose, odometry)
#: Reassociation and contraction only (no assumptions about NaN or infinities): lets LLVM turn the
#: dot products of the linear algebra into SIMD code.
_FAST = {"reassoc", "contract"}
#: How far a keyframe's estimate may move from its linearisation point before its factors are
#: linearised again, per error-state component ``(dr [m], dv [m/s], dphi [rad], db_f [m/s^2],
#: db_w [rad/s])`` (ISAM2's relinearisation threshold, per component). The residuals are linear in
#: position and accelerometer bias, bilinear in velocity and attitude and nearly linear in the gyro
#: bias, so what is left out is second order in these offsets: on the benchmark's run the
#: estimates stay within 0.02 sigma of relinearising every keyframe at every update
#: (``docs/performance.md``), with 0.5 keyframes relinearised per update instead of all 20.
RELINEARISATION_THRESHOLD = np.array([0.05] * 3 + [0.05] * 3 + [5e-3] * 3 + [0.05] * 3 + [2e-3] * 3)
#: No update turns an attitude further than this [rad]: a longer Gauss-Newton step -- a large
#: correction, such as a fix after a long dead-reckoned gap, taken from linearisation points that
#: far off -- is shortened to it along its direction (every offset scaled alike), and the next
#: updates go on from there. Without it a start whose heading nothing observed for minutes, then
#: fixes 10 s apart with a 2-s lag, swung the heading round and ran 190 m off (a real recording;
#: with it 7.6 m, GTSAM's ISAM2 7.2 m).
MAX_ATTITUDE_STEP = 0.2


@dataclass
class _LinearPrior:
    """``e(x) = R (x [-] x_lin) + e0`` on the window keyframes ``keyframes`` (ascending; their
    linearisation points ``r, v, C, b_f, b_w`` row by row)."""

    keyframes: np.ndarray
    r: np.ndarray
    v: np.ndarray
    C: np.ndarray
    b_f: np.ndarray
    b_w: np.ndarray
    R: np.ndarray
    e0: np.ndarray


# -- compiled parts -------------------------------------------------------------------------------


@njit(cache=True)
def _robust_scale(code, k, norm) -> float:
    """``sqrt(w(|e_w|))`` of GTSAM's mEstimator ``code`` (:data:`ROBUST_CODES`) at threshold ``k``."""
    if code == 1:  # Huber
        return 1.0 if norm <= k else np.sqrt(k / norm)
    if code == 2:  # Cauchy
        return np.sqrt(k * k / (k * k + norm * norm))
    if code == 3:  # Tukey
        if norm > k:
            return 0.0
        u = 1.0 - (norm / k) ** 2
        return u
    return 1.0


@njit(cache=True, fastmath=_FAST)
def _whiten(W, e, J, d, ncol, ew, JT, Jt0) -> None:
    """``ew = W e`` and ``JT = (W J)^T`` for the first ``d`` rows (``W`` lower triangular; ``JT``
    holds the whitened Jacobian transposed, so that the normal equations read contiguous rows;
    ``Jt0`` work space)."""
    for a in range(d):
        s = 0.0
        for b in range(a + 1):
            s += W[a, b] * e[b]
        ew[a] = s
    for c in range(ncol):
        for b in range(d):
            Jt0[c, b] = J[b, c]
    for c in range(ncol):
        for a in range(d):
            s = 0.0
            for b in range(a + 1):
                s += W[a, b] * Jt0[c, b]
            JT[c, a] = s


@njit(cache=True, fastmath=_FAST)
def _add_diagonal(Hb, g, a, ca, JT, ew, d) -> None:
    """Add ``J_a^T J_a`` and ``J_a^T e`` of a factor to keyframe ``a``'s diagonal block (``JT``: its
    whitened Jacobian transposed, ``d`` columns; keyframe ``a`` in rows ``ca:ca+15``)."""
    for p in range(DIM):
        s = 0.0
        for i in range(d):
            s += JT[ca + p, i] * ew[i]
        g[a * DIM + p] += s
        for q in range(p + 1):
            s = 0.0
            for i in range(d):
                s += JT[ca + p, i] * JT[ca + q, i]
            Hb[a, 0, p, q] += s
            if q != p:
                Hb[a, 0, q, p] += s


@njit(cache=True, fastmath=_FAST)
def _add_normal(Hb, g, a, ca, b, cb, JT, ew, d) -> None:
    """Add a factor's ``J^T J`` and ``J^T e`` (``JT``: its whitened Jacobian transposed, ``d``
    columns; keyframe ``a`` in rows ``ca:ca+15``, keyframe ``b > a`` in ``cb:cb+15``; ``b = -1``
    for a one-keyframe factor). Block rows are counted from the first row assembled: a keyframe
    before it (``a < 0``) gets nothing on its own row, only its coupling in row ``b``."""
    if a >= 0:
        _add_diagonal(Hb, g, a, ca, JT, ew, d)
    if b < 0:
        return
    _add_diagonal(Hb, g, b, cb, JT, ew, d)
    for p in range(DIM):
        for q in range(DIM):
            s = 0.0
            for i in range(d):
                s += JT[cb + p, i] * JT[ca + q, i]
            Hb[b, b - a, p, q] += s


@njit(cache=True)
def _linearise(first, lo, cut, cap, r, v, C, bf, bw, has_imu, dC, Wp, Rm, JC, dW, dRm, bwbar, Wimu, gravity,
               m, mk, model, rows, dims, Wm, rcode, rk, Hb, g) -> None:
    """Add to ``Hb``, ``g`` (block row 0 = keyframe ``lo``) the rows ``lo ..`` of the normal
    equations of the factors that reach keyframe ``lo`` or later and begin before ``cut``: the
    IMU intervals (stored at the slot of their later keyframe) and the measurements ``0 .. m - 1``,
    linearised at the state arrays given. Keyframe ``k`` is at slot ``k % cap``."""
    work = _residual_work()
    e, A, B = np.empty(DIM), np.empty((DIM, DIM)), np.empty((DIM, DIM))
    J, JT, Jt0, ew = np.empty((DIM, 2 * DIM)), np.empty((2 * DIM, DIM)), np.empty((2 * DIM, DIM)), np.empty(DIM)
    n = Hb.shape[0]
    for k in range(max(lo, first + 1), lo + n):
        if k - 1 >= cut:
            break
        j = k % cap
        if not has_imu[j]:
            continue
        i = (k - 1) % cap
        _residual_into(dC[j], Wp[j], Rm[j], JC[j], dW[j], dRm[j], bwbar[j], r[i], v[i], C[i], bf[i], bw[i],
                       r[j], v[j], C[j], bf[j], bw[j], gravity, True, e, A, B, work)
        J[:, :DIM] = A
        J[:, DIM:] = B
        _whiten(Wimu[j], e, J, DIM, 2 * DIM, ew, JT, Jt0)
        _add_normal(Hb, g, k - 1 - lo, 0, k - lo, DIM, JT, ew, DIM)
    H = np.empty((_MAX_DIM, 2 * DIM))
    for f in range(m):
        k0, k1 = mk[f, 0], mk[f, 1]
        if k0 >= cut or k1 < lo:
            continue
        d = dims[f]
        i = k0 % cap
        if model[f] == RELATIVE_MODEL:
            j = k1 % cap
            odometry_kernel(r[i], C[i], r[j], C[j], rows[f], e[:d], H[:d])
            _whiten(Wm[f], e, H, d, 2 * DIM, ew, JT, Jt0)
        else:
            measure_into(model[f], r[i], v[i], C[i], bf[i], bw[i], rows[f], e[:d], H[:d, :DIM])
            _whiten(Wm[f], e, H, d, DIM, ew, JT, Jt0)
        if rcode[f] != 0:
            norm = 0.0
            for a in range(d):
                norm += ew[a] * ew[a]
            scale = _robust_scale(rcode[f], rk[f], np.sqrt(norm))
            ew[:d] *= scale
            JT[:, :d] *= scale
        if model[f] == RELATIVE_MODEL:
            _add_normal(Hb, g, k0 - lo, 0, k1 - lo, DIM, JT, ew, d)
        else:
            _add_normal(Hb, g, k0 - lo, 0, -1, 0, JT, ew, d)


@njit(cache=True)
def _prior_into(blocks, xr, xv, xC, xbf, xbw, R, e0, cap, r, v, C, bf, bw, lo, Hb, g) -> None:
    """Add the linear prior ``e = R (x [-] x_lin) + e0`` on keyframes ``blocks`` (global numbers,
    ascending), linearised at the state arrays given, to the rows ``lo ..`` of ``Hb``, ``g`` (block
    row 0 = keyframe ``lo``)."""
    P = blocks.shape[0]
    N = DIM * P
    dx = np.zeros(N)
    D = np.zeros((P, 3, 3))  # Gamma^-1 of each attitude difference
    for a in range(P):
        s = blocks[a] % cap
        for c in range(3):
            dx[a * DIM + c] = r[s, c] - xr[a, c]
            dx[a * DIM + 3 + c] = v[s, c] - xv[a, c]
            dx[a * DIM + 9 + c] = bf[s, c] - xbf[a, c]
            dx[a * DIM + 12 + c] = bw[s, c] - xbw[a, c]
        p0, p1, p2 = so3.boxminus_of(C[s], xC[a])
        dx[a * DIM + 6], dx[a * DIM + 7], dx[a * DIM + 8] = p0, p1, p2
        so3.gamma_inv_into(p0, p1, p2, D[a])
    e = e0.copy()
    J = R.copy()  # R times the block diagonal (I, I, Gamma^-1, I, I)
    for row in range(N):
        for col in range(N):
            e[row] += R[row, col] * dx[col]
        for a in range(P):
            for c in range(3):
                s = 0.0
                for q in range(3):
                    s += R[row, a * DIM + 6 + q] * D[a, q, c]
                J[row, a * DIM + 6 + c] = s
    for a in range(P):
        ba = blocks[a] - lo
        if ba < 0:
            continue
        for p in range(DIM):
            s = 0.0
            for row in range(N):
                s += J[row, a * DIM + p] * e[row]
            g[ba * DIM + p] += s
        for b in range(a + 1):
            bb = blocks[b] - lo
            for p in range(DIM):
                for q in range(DIM):
                    s = 0.0
                    for row in range(N):
                        s += J[row, a * DIM + p] * J[row, b * DIM + q]
                    Hb[ba, ba - bb, p, q] += s


@njit(cache=True)
def _factorise(Hr, L, first, start, newest, cap, S) -> int:
    """Rows ``start .. newest`` of the block-banded Cholesky factor ``H = L L^T`` of the window
    ``first .. newest`` (bandwidth ``S``): ``Hr[k - start, s]`` is block ``(k, k - s)`` of ``H``,
    ``L[k % cap, s]`` block ``(k, k - s)`` of ``L`` (the rows before ``start`` are kept: they
    depend on the rows of ``H`` before ``start`` only). Returns -1, or the keyframe whose pivot
    failed."""
    M = np.empty((DIM, DIM))
    for k in range(start, newest + 1):
        top = min(k - first, S)
        row = k % cap
        for s in range(top, 0, -1):
            j = k - s
            jrow = j % cap
            M[:, :] = Hr[k - start, s]
            for i in range(max(k - top, j - min(j - first, S)), j):  # blocks left of j in rows k and j
                A, B = L[row, k - i], L[jrow, j - i]
                for p in range(DIM):
                    for q in range(DIM):
                        acc = 0.0
                        for c in range(DIM):
                            acc += A[p, c] * B[q, c]
                        M[p, q] -= acc
            Ljj = L[jrow, 0]
            X = L[row, s]
            for p in range(DIM):  # X Ljj^T = M, row by row (forward substitution)
                for q in range(DIM):
                    acc = M[p, q]
                    for c in range(q):
                        acc -= X[p, c] * Ljj[q, c]
                    X[p, q] = acc / Ljj[q, q]
        M[:, :] = Hr[k - start, 0]
        for s in range(1, top + 1):
            A = L[row, s]
            for p in range(DIM):
                for q in range(p + 1):
                    acc = 0.0
                    for c in range(DIM):
                        acc += A[p, c] * A[q, c]
                    M[p, q] -= acc
        for p in range(DIM):  # symmetric: the lower triangle is what the block Cholesky reads
            for q in range(p + 1, DIM):
                M[p, q] = M[q, p]
        if not cholesky_into(M, L[row, 0]):
            return k
    return -1


@njit(cache=True)
def _forward(L, b, first, start, zero_before, newest, cap, S) -> None:
    """``b <- L^-1 b`` for the rows ``start .. newest`` of the window ``first .. newest``, in
    place (``b[k % cap]`` the ``(15, m)`` block of keyframe ``k``; the rows before ``start`` are
    solved already, those before ``zero_before`` are zero)."""
    m = b.shape[2]
    for k in range(start, newest + 1):
        row = k % cap
        for s in range(1, min(k - max(first, zero_before), S) + 1):
            A, x = L[row, s], b[(k - s) % cap]
            for p in range(DIM):
                for c in range(m):
                    acc = 0.0
                    for q in range(DIM):
                        acc += A[p, q] * x[q, c]
                    b[row, p, c] -= acc
        Lkk = L[row, 0]
        for c in range(m):
            for p in range(DIM):
                acc = b[row, p, c]
                for q in range(p):
                    acc -= Lkk[p, q] * b[row, q, c]
                b[row, p, c] = acc / Lkk[p, p]


@njit(cache=True)
def _backward(L, b, stop, newest, cap, S) -> None:
    """``b <- L^-T b`` in place, rows ``newest`` down to ``stop`` (``b`` as :func:`_forward`'s)."""
    m = b.shape[2]
    for k in range(newest, stop - 1, -1):
        row = k % cap
        for s in range(1, min(newest - k, S) + 1):
            A, x = L[(k + s) % cap, s], b[(k + s) % cap]  # block (k + s, k)
            for p in range(DIM):
                for c in range(m):
                    acc = 0.0
                    for q in range(DIM):
                        acc += A[q, p] * x[q, c]
                    b[row, p, c] -= acc
        Lkk = L[row, 0]
        for c in range(m):
            for p in range(DIM - 1, -1, -1):
                acc = b[row, p, c]
                for q in range(p + 1, DIM):
                    acc -= Lkk[q, p] * b[row, q, c]
                b[row, p, c] = acc / Lkk[p, p]


@njit(cache=True)
def _boxplus(first, newest, cap, delta, r, v, C, bf, bw, xr, xv, xC, xbf, xbw) -> None:
    """``x = theta [+] delta`` for the window's keyframes (:func:`factors.imu.boxplus_into`: the
    left attitude increment)."""
    for k in range(first, newest + 1):
        s = k % cap
        xr[s], xv[s], xC[s], xbf[s], xbw[s] = r[s], v[s], C[s], bf[s], bw[s]
        imu.boxplus_into(xr[s], xv[s], xC[s], xbf[s], xbw[s], delta[s, :, 0])


@njit(cache=True)
def _solve_rows(Hr, g, L, y, delta, first, start, newest, cap, S, threshold, max_turn, moved, r, v, C, bf, bw, xr, xv,
                xC, xbf, xbw):
    """One update's linear algebra: the rows ``start ..`` of ``L`` from ``Hr`` (:func:`_factorise`),
    the forward solution ``y = L^-1 (-g)`` from row ``start`` on (``g``'s rows from ``start``;
    the rows before kept), ``delta = L^-T y`` -- the whole step from the offsets before shortened
    so that no attitude turns by more than ``max_turn`` [rad] -- the estimates ``theta [+] delta``
    (:func:`_boxplus`), then the keyframes whose offset exceeds ``threshold`` linearised again
    (:func:`_relinearise`). Returns ``(failed, oldest, shortened)``: -1 or the keyframe whose pivot
    failed (nothing else done), -1 or the oldest keyframe linearised again, and whether the step
    was shortened."""
    failed = _factorise(Hr, L, first, start, newest, cap, S)
    if failed >= 0:
        return failed, -1, False
    n = newest - first + 1
    before = np.empty((n, DIM))
    for k in range(first, newest + 1):
        s = k % cap
        for p in range(DIM):
            before[k - first, p] = delta[s, p, 0]
    for k in range(start, newest + 1):
        s = k % cap
        for p in range(DIM):
            y[s, p, 0] = -g[(k - start) * DIM + p]
    _forward(L, y, first, start, first, newest, cap, S)
    for k in range(first, newest + 1):
        s = k % cap
        for p in range(DIM):
            delta[s, p, 0] = y[s, p, 0]
    _backward(L, delta, first, newest, cap, S)
    turn = 0.0
    for k in range(first, newest + 1):
        s = k % cap
        d0, d1, d2 = (delta[s, 6, 0] - before[k - first, 6], delta[s, 7, 0] - before[k - first, 7],
                      delta[s, 8, 0] - before[k - first, 8])
        turn = max(turn, math.sqrt(d0 * d0 + d1 * d1 + d2 * d2))
    shortened = turn > max_turn
    if shortened:  # along the Gauss-Newton step, no further than max_turn in attitude
        a = max_turn / turn
        for k in range(first, newest + 1):
            s = k % cap
            for p in range(DIM):
                delta[s, p, 0] = before[k - first, p] + a * (delta[s, p, 0] - before[k - first, p])
    _boxplus(first, newest, cap, delta, r, v, C, bf, bw, xr, xv, xC, xbf, xbw)
    return -1, _relinearise(first, newest, cap, delta, threshold, r, v, C, bf, bw, xr, xv, xC, xbf, xbw, moved), shortened


@njit(cache=True)
def _drop_measurements(cut, m, mk, model, rows, dims, Wm, rcode, rk):
    """Remove the measurements whose earliest keyframe is before ``cut``, keeping the order of the
    rest; returns their number and the longest span (later minus earlier keyframe) among them."""
    n, span = 0, 0
    for f in range(m):
        if mk[f, 0] >= cut:
            if n != f:
                mk[n], model[n], rows[n], dims[n] = mk[f], model[f], rows[f], dims[f]
                Wm[n], rcode[n], rk[n] = Wm[f], rcode[f], rk[f]
            span = max(span, mk[n, 1] - mk[n, 0])
            n += 1
    return n, span


@njit(cache=True)
def _relinearise(first, newest, cap, delta, threshold, r, v, C, bf, bw, xr, xv, xC, xbf, xbw, moved) -> int:
    """Move the linearisation point ``theta`` of each window keyframe whose offset ``delta`` exceeds
    ``threshold`` in any component to its estimate (``theta <- theta [+] delta = x``,
    ``delta <- 0``), flagging it in ``moved``; returns the oldest moved keyframe, or -1."""
    oldest = -1
    for k in range(first, newest + 1):
        s = k % cap
        moved[s] = False
        for i in range(DIM):
            if abs(delta[s, i, 0]) > threshold[i]:
                moved[s] = True
                break
        if moved[s]:
            if oldest < 0:
                oldest = k
            r[s, :], v[s, :], bf[s, :], bw[s, :] = xr[s], xv[s], xbf[s], xbw[s]
            C[s, :, :] = xC[s]
            delta[s] = 0.0
    return oldest


@njit(cache=True)
def _solve_lower(L, B) -> None:
    """``B <- L^-1 B`` in place (``L`` lower triangular)."""
    n, m = B.shape
    for c in range(m):
        for i in range(n):
            s = B[i, c]
            for j in range(i):
                s -= L[i, j] * B[j, c]
            B[i, c] = s / L[i, i]


@njit(cache=True)
def _schur(Hb, g, nl):
    """The Schur complement of the first ``nl`` blocks of the block-banded ``(Hb, g)``:
    ``(H_mm - H_ml H_ll^-1 H_lm, g_m - H_ml H_ll^-1 g_l)`` and True, or False if ``H_ll`` is not
    positive definite."""
    n, S1 = Hb.shape[0], Hb.shape[1]
    N = n * DIM
    H = np.zeros((N, N))
    for k in range(n):
        for s in range(min(k, S1 - 1) + 1):
            j = k - s
            for p in range(DIM):
                for q in range(DIM):
                    H[k * DIM + p, j * DIM + q] = Hb[k, s, p, q]
                    H[j * DIM + q, k * DIM + p] = Hb[k, s, p, q]
    m0 = nl * DIM
    Lll = np.empty((m0, m0))
    Hs, gs = np.empty((N - m0, N - m0)), np.empty(N - m0)
    if not cholesky_into(H[:m0, :m0].copy(), Lll):
        return Hs, gs, False
    Y = np.empty((m0, N - m0 + 1))
    Y[:, :N - m0] = H[:m0, m0:]
    Y[:, N - m0] = g[:m0]
    _solve_lower(Lll, Y)
    for a in range(N - m0):
        for b in range(N - m0):
            s = H[m0 + a, m0 + b]
            for c in range(m0):
                s -= Y[c, a] * Y[c, b]
            Hs[a, b] = s
        s = g[m0 + a]
        for c in range(m0):
            s -= Y[c, a] * Y[c, N - m0]
        gs[a] = s
    return Hs, gs, True


@njit(cache=True)
def _marginal_prior(Hb, g, nl):
    """The linear prior that replaces the first ``nl`` blocks of the block-banded ``(Hb, g)``:
    their Schur complement (:func:`_schur`) on the blocks it informs (rows not all zero),
    ``touched`` (their numbers after the first ``nl``), as ``R`` (upper triangular, ``R^T R =
    H_s``) and ``e0`` (``R^T e0 = g_s``). Returns ``(status, touched, A, b)``: status 0 with
    ``(R, e0)``; 1 when ``H_ll`` is not positive definite; 2 when ``H_s`` is only semi-definite,
    with ``(H_s, g_s)`` on the touched blocks for :func:`_semidefinite_square_root`."""
    Hs, gs, ok = _schur(Hb, g, nl)
    if not ok:
        return 1, np.empty(0, dtype=np.int64), Hs, gs
    n = Hs.shape[0] // DIM
    keep = np.zeros(n, dtype=np.bool_)
    for b in range(n):
        for p in range(b * DIM, (b + 1) * DIM):
            for q in range(Hs.shape[1]):
                if Hs[p, q] != 0.0:
                    keep[b] = True
    touched = np.flatnonzero(keep)
    m = touched.size * DIM
    Ht, gt = np.empty((m, m)), np.empty(m)
    for a in range(touched.size):
        for p in range(DIM):
            gt[a * DIM + p] = gs[touched[a] * DIM + p]
            for b in range(touched.size):
                for q in range(DIM):
                    Ht[a * DIM + p, b * DIM + q] = Hs[touched[a] * DIM + p, touched[b] * DIM + q]
    Lc = np.empty((m, m))
    if not cholesky_into(Ht, Lc):
        return 2, touched, Ht, gt
    e0 = gt.reshape(m, 1).copy()
    _solve_lower(Lc, e0)
    return 0, touched, Lc.T.copy(), e0[:, 0].copy()


@njit(cache=True)
def _whitening_into(cov, W) -> bool:
    """``W = L^-1`` with ``cov = L L^T`` (:func:`smoother.solver.whitening`, compiled for one
    matrix); False if ``cov`` is not positive definite."""
    d = cov.shape[0]
    L = np.empty((d, d))
    if not cholesky_into(cov, L):
        return False
    W[:d, :d] = 0.0
    for c in range(d):
        W[c, c] = 1.0
    _solve_lower(L, W[:d, :d])
    return True


# -- the window -----------------------------------------------------------------------------------


_compiled = False


def _compiling():
    """:func:`datasets.kinds.quiet_dispatch` around the first call (which compiles or loads
    :func:`_linearise`), nothing after: the warning filters cost more than an update's mathematics."""
    global _compiled
    if _compiled:
        return nullcontext()
    _compiled = True
    return quiet_dispatch()


class SlidingWindow:
    """The compiled fixed-lag smoother (module docstring), fed one keyframe at a time.

    ``lag_s``: keyframes older than the newest one's time minus the lag leave at the next update;
    ``gravity`` (world, m/s^2) and ``reintegration_threshold`` (rad/s) as the IMU factor's;
    ``relinearisation_threshold`` (15 numbers in the error state's units, or one for all): a
    keyframe is linearised again when its offset from its linearisation point exceeds it in any
    component (0: every keyframe at every update). Keyframe ``k`` (0, 1, ...) has a time stamp and
    the window is ``first .. newest``; :meth:`leaving` names the keyframes the next update
    marginalises, which the caller reads (and records with :meth:`taken`) before it."""

    kind = "sliding"

    def __init__(self, lag_s: float, gravity=imu.DEFAULT_GRAVITY,
                 reintegration_threshold: float = preintegration.REINTEGRATION_THRESHOLD,
                 relinearisation_threshold=None):
        if not lag_s > 0:
            raise InputError(f"lag must be positive, got {lag_s}")
        threshold = RELINEARISATION_THRESHOLD if relinearisation_threshold is None else relinearisation_threshold
        threshold = np.broadcast_to(np.asarray(threshold, dtype=float), (DIM,)).copy()
        if not np.all(threshold >= 0):
            raise InputError(f"relinearisation_threshold: expected numbers >= 0, got {threshold.tolist()}")
        self.lag_s = float(lag_s)
        self.gravity = np.asarray(gravity, dtype=float)
        self.reintegration_threshold = float(reintegration_threshold)
        self.relinearisation_threshold = threshold
        self.first, self.newest = 0, -1
        self.recovered: list[int] = []
        self.skipped = 0
        self.update_s: deque[float] = deque(maxlen=HISTORY)
        #: keyframes linearised again at each update that linearised any again
        self.relinearised: deque[int] = deque(maxlen=HISTORY)
        #: updates whose step was shortened (MAX_ATTITUDE_STEP)
        self.shortened = 0
        self._taken_after: dict[int, int] = {}
        self._priors: list[_LinearPrior] = []
        self._S = 1  # the band L is factorised with (at least the factors' reach; narrowed at whole factorisations)
        self._spans = [0, 0]  # the longest span of the measurements, of the priors
        self._stale = 0  # the rows of L (and of the forward solution) from this keyframe on are stale
        self._allocate_keyframes(64)
        self._allocate_measurements(64)
        self._m = 0

    # -- storage ----------------------------------------------------------------------------------

    def _allocate_keyframes(self, cap: int) -> None:
        """Ring arrays for ``cap`` keyframes (slot ``k % cap``), the window's moved over."""
        shapes = {"_t": (), "_r": (3,), "_v": (3,), "_C": (3, 3), "_bf": (3,), "_bw": (3,),
                  "_xr": (3,), "_xv": (3,), "_xC": (3, 3), "_xbf": (3,), "_xbw": (3,), "_dx": (DIM, 1), "_y": (DIM, 1),
                  "_L": (self._L.shape[1] if hasattr(self, "_L") else self._S + 1, DIM, DIM), "_dC": (3, 3),
                  "_Wp": (3, 10), "_Rm": (3, 10), "_JC": (3, 3), "_dW": (3, 10, 3), "_dRm": (3, 10, 3),
                  "_bwbar": (3,), "_Wimu": (DIM, DIM)}
        old = {name: getattr(self, name, None) for name in shapes}
        old_imu, old_pre, old_cap = getattr(self, "_has_imu", None), getattr(self, "_pre", None), getattr(self, "_cap", 0)
        self._cap = cap
        for name, tail in shapes.items():
            setattr(self, name, np.zeros((cap,) + tail))
        self._has_imu = np.zeros(cap, dtype=np.bool_)
        self._moved = np.zeros(cap, dtype=np.bool_)
        self._pre = [None] * cap
        for k in range(self.first, self.newest + 1):  # the window, moved to its new slots
            a, b = k % old_cap, k % cap
            for name in shapes:
                getattr(self, name)[b] = old[name][a]
            self._has_imu[b], self._pre[b] = old_imu[a], old_pre[a]

    def _allocate_measurements(self, cap: int) -> None:
        """Measurement tables for ``cap`` rows, the current ones kept."""
        m = getattr(self, "_m", 0)
        shapes = {"_mk": ((2,), np.int64), "_model": ((), np.int64), "_rows": ((ODOMETRY_WIDTH,), float),
                  "_dims": ((), np.int64), "_Wm": ((_MAX_DIM, _MAX_DIM), float), "_rcode": ((), np.int64),
                  "_rk": ((), float)}
        for name, (tail, dtype) in shapes.items():
            fresh = np.zeros((cap,) + tail, dtype=dtype)
            if m:
                fresh[:m] = getattr(self, name)[:m]
            setattr(self, name, fresh)

    def _linearisation_points(self):
        """The ``theta`` arrays ``(r, v, C, b_f, b_w)`` by slot."""
        return self._r, self._v, self._C, self._bf, self._bw

    def _estimates(self):
        """The estimate arrays ``theta [+] delta`` by slot."""
        return self._xr, self._xv, self._xC, self._xbf, self._xbw

    # -- the KeyframeWindow interface -----------------------------------------------------------

    def time(self, k: int) -> float:
        """The time stamp of window keyframe ``k``."""
        return float(self._t[k % self._cap])

    def leaving(self, t_next: float) -> list[int]:
        """The window keyframes an update at ``t_next`` marginalises: older than ``t_next`` minus the
        lag (as GTSAM's smoothers count it), never the newest."""
        boundary = t_next - self.lag_s
        out = []
        for j in range(self.first, self.newest):
            if self.time(j) >= boundary:
                break
            out.append(j)
        return out

    def taken(self, keyframes) -> None:
        """Record that the estimates of ``keyframes`` were read after the last update."""
        self._taken_after.update((j, self.newest) for j in keyframes)

    def state(self, k: int) -> imu.ImuState:
        """Window keyframe ``k``'s estimate after the last update."""
        s = k % self._cap
        return imu.ImuState(self._xr[s].copy(), self._xv[s].copy(), self._xC[s].copy(), self._xbf[s].copy(),
                            self._xbw[s].copy())

    @property
    def newest_state(self) -> imu.ImuState:
        return self.state(self.newest)

    def add_keyframe(self, t: float, guess: imu.ImuState, pre=None, measurements=(), prior=None) -> imu.ImuState:
        """Add keyframe ``newest + 1`` at ``t`` with the initial value ``guess``, the preintegrated
        interval ``pre`` from the newest keyframe (one :class:`factors.preintegration.Preintegrated`
        interval with its covariance; None: no IMU factor), ``measurements`` (``(spec, m,
        keyframes, robust)``: measurement ``m`` of a :class:`smoother.graph.MeasurementSpec`, the
        keyframes it reads, a robust spec or None) and ``prior`` ``(state, cov)`` on the new
        keyframe; one update (module docstring); returns the new keyframe's estimate.
        Measurements reading a keyframe that leaves are skipped and counted in ``skipped``. What
        can be refused (a covariance that is not positive definite, an unknown robust kernel) is
        refused before the window changes."""
        tick = time.perf_counter()
        k = self.newest + 1
        leaving = self.leaving(t)
        first = leaving[-1] + 1 if leaving else self.first
        interval = None
        if pre is not None and k > 0:
            interval = np.zeros((DIM, DIM))
            if not _whitening_into(pre.cov, interval):
                raise InputError("the IMU interval's covariance is not positive definite")
        factors = [self._measurement_row(spec, m, keyframes, robust) for spec, m, keyframes, robust in measurements
                   if min(keyframes) >= first]
        priors = [] if prior is None else [(prior[0], whitening(prior[1]))]
        self.skipped += len(measurements) - len(factors)
        self._marginalise(leaving)
        if k - self.first + 1 > self._cap:
            self._allocate_keyframes(2 * self._cap)
        s = k % self._cap
        self._t[s] = t
        for arrays in (self._linearisation_points(), self._estimates()):
            for a, value in zip(arrays, (guess.r, guess.v, guess.C, guess.b_f, guess.b_w)):
                a[s] = value
        self._dx[s] = 0.0
        self._has_imu[s] = False
        self._pre[s] = None
        linked = k == 0 or interval is not None
        if interval is not None:
            self._store_interval(s, pre, interval)
        for row in factors:
            self._add_measurement(*row)
            keyframes = row[-1]
            linked = linked or (len(keyframes) > 1 and min(keyframes) < k == max(keyframes))
        self.newest = k
        if not linked:  # nothing ties the new keyframe to the window: a weak prior around its guess
            priors.append((guess, whitening(np.diag(WEAK_PRIOR_SIGMAS ** 2))))
            self.recovered.append(k)
        for state, R in priors:
            self._add_prior(k, state, R)
        self._solve(t)
        self.update_s.append(time.perf_counter() - tick)
        return self.newest_state

    def covariances(self, wanted) -> np.ndarray:
        """The 15x15 marginal covariances (primer convention) of window keyframes ``wanted``: blocks
        of ``H^-1`` with ``H`` at the linearisation points of the last update's solve (before the
        keyframes it moved far enough were linearised again)."""
        out = []
        b = np.zeros((self._cap, DIM, DIM))
        for k in wanted:
            for j in range(k, self.newest + 1):
                b[j % self._cap] = 0.0
            b[k % self._cap] = np.eye(DIM)
            _forward(self._L, b, self.first, k, k, self.newest, self._cap, self._S)
            _backward(self._L, b, k, self.newest, self._cap, self._S)
            cov = b[k % self._cap]
            out.append(0.5 * (cov + cov.T))
        return np.stack(out)

    # -- inside -----------------------------------------------------------------------------------

    def _store_interval(self, s: int, pre, whitening_matrix=None) -> None:
        """Keep interval ``pre`` at slot ``s``, with the whitening of its covariance (None: keep the
        slot's: an interval integrated again keeps its covariance)."""
        self._has_imu[s] = True
        self._pre[s] = pre
        for name, value in (("_dC", pre.dC), ("_Wp", pre.W), ("_Rm", pre.Rm), ("_JC", pre.JC), ("_dW", pre.dW),
                            ("_dRm", pre.dRm), ("_bwbar", pre.b_w_bar)):
            getattr(self, name)[s] = value
        if whitening_matrix is not None:
            self._Wimu[s] = whitening_matrix

    @staticmethod
    def _measurement_row(spec, m: int, keyframes, robust) -> tuple:
        """Measurement ``m`` of ``spec`` as the arguments of :meth:`_add_measurement`, checked:
        its covariance's whitening (an InputError if it is not positive definite) and robust code."""
        cov = np.ascontiguousarray(spec.cov[m], dtype=float)
        d = cov.shape[-1]
        W = np.zeros((_MAX_DIM, _MAX_DIM))
        if not _whitening_into(cov, W):
            raise InputError(f"a measurement's covariance is not positive definite: {cov.tolist()}")
        if robust is not None and robust[0] not in ROBUST_CODES:
            raise InputError(f"robust kernel {robust[0]!r}: expected one of {', '.join(ROBUST_CODES)}")
        code, k = (0, 0.0) if robust is None else (ROBUST_CODES[robust[0]], robust_threshold(robust, d))
        return spec.model, spec.rows[m], W, d, code, k, keyframes

    def _add_measurement(self, model: int, row, W, d: int, code: int, k: float, keyframes) -> None:
        """Append a checked measurement (:meth:`_measurement_row`); the rows of ``L`` from its
        oldest keyframe on are stale."""
        if self._m == len(self._mk):
            self._allocate_measurements(2 * len(self._mk))
        f = self._m
        self._mk[f] = (min(keyframes), max(keyframes))
        self._spans[0] = max(self._spans[0], max(keyframes) - min(keyframes))
        self._model[f] = model
        self._rows[f, :len(row)] = row
        self._dims[f] = d
        self._Wm[f] = W
        self._rcode[f] = code
        self._rk[f] = k
        self._m = f + 1
        self._stale = min(self._stale, min(keyframes))

    def _add_prior(self, k: int, state: imu.ImuState, R: np.ndarray) -> None:
        """A prior ``R (x_k [-] state)`` on keyframe ``k`` (``R`` the whitening of its covariance)."""
        self._priors.append(_LinearPrior(np.array([k]), state.r[None].copy(), state.v[None].copy(),
                                         state.C[None].copy(), state.b_f[None].copy(), state.b_w[None].copy(),
                                         R, np.zeros(DIM)))
        self._stale = min(self._stale, k)

    def _relinearised(self, oldest: int) -> None:
        """After :func:`_solve_rows` linearised keyframes ``oldest ..`` (those flagged) again:
        integrate again the intervals out of those whose gyro bias moved beyond the reintegration
        threshold, and mark the rows of ``L`` their factors change as stale."""
        moved = [k for k in range(oldest, self.newest + 1) if self._moved[k % self._cap]]
        self.relinearised.append(len(moved))
        for i in moved:
            j = (i + 1) % self._cap
            drift = np.max(np.abs(self._bw[i % self._cap] - self._bwbar[j]))
            if i < self.newest and self._has_imu[j] and drift > self.reintegration_threshold:
                self._store_interval(j, self._pre[j].relinearized(self._bw[i % self._cap]))
        # the factors of a moved keyframe reach at most the bandwidth back
        self._stale = min(self._stale, oldest - self._bandwidth())

    def _bandwidth(self) -> int:
        """How many keyframes back the longest factor reaches (IMU factors: 1)."""
        return max(1, *self._spans)

    def _normal_equations(self, lo: int, cut: int, n: int, S: int):
        """Rows ``lo .. lo + n - 1`` of the normal equations at the linearisation points, of the
        factors that begin before keyframe ``cut``: block-banded ``Hb (n, S + 1, 15, 15)`` and ``g``."""
        Hb = np.zeros((n, S + 1, DIM, DIM))
        g = np.zeros(n * DIM)
        with _compiling():
            _linearise(self.first, lo, cut, self._cap, *self._linearisation_points(), self._has_imu, self._dC,
                       self._Wp, self._Rm, self._JC, self._dW, self._dRm, self._bwbar, self._Wimu, self.gravity,
                       self._m, self._mk, self._model, self._rows, self._dims, self._Wm, self._rcode, self._rk, Hb, g)
        for p in self._priors:
            if p.keyframes[0] < cut and p.keyframes[-1] >= lo:
                _prior_into(p.keyframes, p.r, p.v, p.C, p.b_f, p.b_w, p.R, p.e0, self._cap,
                            *self._linearisation_points(), lo, Hb, g)
        return Hb, g

    def _solve(self, t: float) -> None:
        """Factorise the rows of ``H`` that changed (those of the new keyframe's factors and of the
        keyframes linearised again, and everything after them), solve ``H delta = -g`` at the
        linearisation points, set the estimates to ``theta [+] delta``. A keyframe whose
        information is not positive definite (nothing in the window determines some part of it)
        gets a weak prior about its estimate (:data:`WEAK_PRIOR_SIGMAS`, recorded in
        ``recovered``) and the window is factorised again; if it still fails, the update does."""
        for attempt in range(2):
            failed = self._solve_once()
            if failed < 0:
                return
            self._stale = self.first  # the next factorisation covers the whole window again
            if attempt == 0:
                self._add_prior(failed, self.state(failed), whitening(np.diag(WEAK_PRIOR_SIGMAS ** 2)))
                self.recovered.append(failed)
        raise FixedLagFailed(f"the fixed-lag smoother failed at keyframe {self.newest} (t = {t:.6f} s): the "
                             f"information of keyframe {failed} (t = {self.time(failed):.6f} s) is not positive "
                             "definite even with a weak prior on it: the window's information spans more orders of "
                             "magnitude than double precision holds (keyframes a few microseconds apart, or a sensor "
                             "many orders more precise than the rest)")

    def _solve_once(self) -> int:
        """One factorisation and solve of :meth:`_solve`; returns -1, or the keyframe whose pivot
        failed (the estimates then unchanged)."""
        reach = self._bandwidth()
        if reach > self._S:  # a wider band: L anew, the whole window factorised
            self._L = np.zeros((self._cap, reach + 1, DIM, DIM))
            self._S, self._stale = reach, self.first
        start = max(min(self._stale, self.newest - reach), self.first)
        if start == self.first:  # factorised whole: the band the factors need now (it narrows as they leave)
            self._S = reach
        S = self._S
        Hr, g = self._normal_equations(start, self.newest + 1, self.newest - start + 1, S)
        failed, oldest, shortened = _solve_rows(Hr, g, self._L, self._y, self._dx, self.first, start, self.newest,
                                                self._cap, S, self.relinearisation_threshold, MAX_ATTITUDE_STEP,
                                                self._moved, *self._linearisation_points(), *self._estimates())
        if failed >= 0:
            return failed
        self._stale = self.newest + 1
        self.shortened += shortened
        if oldest >= 0:
            self._relinearised(oldest)
        return -1

    def _marginalise(self, leaving: list[int]) -> None:
        """Replace the factors touching ``leaving`` (the oldest window keyframes) by their Schur
        complement onto the keyframes they also touch, a :class:`_LinearPrior` at their
        linearisation points. The rows of ``L`` after ``leaving`` stay: eliminating the oldest
        keyframes first, they are the factor of that Schur complement already."""
        if not leaving:
            return
        for j in leaving:
            if self._taken_after.pop(j, None) != self.newest:
                raise RuntimeError(f"fixed-lag: keyframe {j} (t = {self.time(j):.6f} s) left the window before its "
                                   "estimate was taken")
        cut = leaving[-1] + 1
        S = self._bandwidth()
        nl = cut - self.first
        n = min(self.newest - self.first + 1, nl + S)
        Hb, g = self._normal_equations(self.first, cut, n, S)
        status, touched, A, b = _marginal_prior(Hb, g, nl)
        if status == 1:
            raise FixedLagFailed(f"the fixed-lag smoother cannot marginalise keyframes {self.first}..{cut - 1} "
                                 f"(t = {self.time(self.first):.6f}..{self.time(cut - 1):.6f} s): their information "
                                 "is not positive definite. Check the data around that time.")
        self._priors = [p for p in self._priors if p.keyframes[0] >= cut]
        self._m, self._spans[0] = _drop_measurements(cut, self._m, self._mk, self._model, self._rows, self._dims,
                                                     self._Wm, self._rcode, self._rk)
        for k in range(self.first + 1, cut + 1):  # the IMU factors into and out of the leaving keyframes
            self._has_imu[k % self._cap] = False
            self._pre[k % self._cap] = None
        self.first = cut
        if touched.size:  # keep the keyframes the marginal ties (non-zero information)
            R, e0 = (A, b) if status == 0 else _semidefinite_square_root(A, b)
            keyframes = cut + touched
            slots = keyframes % self._cap
            self._priors.append(_LinearPrior(keyframes, *(a[slots] for a in self._linearisation_points()), R, e0))
        self._spans[1] = max((int(p.keyframes[-1] - p.keyframes[0]) for p in self._priors), default=0)


def _semidefinite_square_root(H: np.ndarray, g: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``(R, e0)`` with ``R^T R = H`` and ``R^T e0 = g`` for a positive semi-definite ``H``, the
    directions the marginalised factors did not inform left out: those of the eigenvalues below
    1e-12 of ``H`` scaled to a unit diagonal (each state component in its own units: a short IMU
    interval's position information reaches 1e14 beside a bias's 1e2, which a cut-off relative to
    the largest eigenvalue would drop); ``g`` has no part along them."""
    d = np.sqrt(np.maximum(np.diag(H), 0.0))
    d[d == 0.0] = 1.0
    lam, V = np.linalg.eigh(0.5 * (H + H.T) / np.outer(d, d))
    keep = lam > 1e-12 * max(lam.max(), 1e-300)
    R = np.sqrt(lam[keep])[:, None] * V[:, keep].T * d[None, :]
    R = np.vstack([R, np.zeros((len(H) - R.shape[0], len(H)))])
    e0 = np.zeros(len(H))
    e0[:int(keep.sum())] = (V[:, keep].T @ (g / d)) / np.sqrt(lam[keep])
    return R, e0
