"""The project's own fixed-lag smoother: a sliding window of keyframes solved by Gauss-Newton on
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

* one Gauss-Newton step per update, every factor of the window relinearised (ISAM2, the GTSAM
  smoother it replaces, also takes one step per update): ``H = sum J^T J``, ``g = sum J^T e``
  over whitened, robustly reweighted residuals (GTSAM's Huber, Cauchy and Tukey weights), ``H
  delta = -g``, ``x <- x [+] delta``;
* keyframes in time order and factors that couple keyframes at most ``S`` apart (IMU factors 1,
  a relative pose its span, the marginal prior what it ties) make ``H`` block-banded; its
  Cholesky factor keeps the band, so a step costs ``O(n S^2 15^3)`` for ``n`` keyframes;
* a keyframe older than the newest keyframe's time minus the lag is marginalised before the next
  keyframe is added: the factors touching it, linearised at the current estimate, are replaced by
  their Schur complement onto the keyframes they also touch, kept as the linear prior
  ``e(x) = R (x [-] x_lin) + e0`` with ``R^T R = H_mm - H_ml H_ll^-1 H_lm`` and ``R^T e0 = g_m -
  H_ml H_ll^-1 g_l`` at ``x_lin``, the estimate then (GTSAM keeps its marginals the same way, as
  linear factors at their linearisation point); ``[-]`` is the state's boxminus, whose attitude
  Jacobian is ``Gamma^-1(log(C C_lin^T))`` (eqs. 24, 32). The prior at keyframe 0 is such a prior
  too (``R`` the whitening of the initial covariance, ``e0 = 0``);
* the newest keyframe never leaves before the next one is added, so an IMU gap longer than the
  lag keeps its IMU factor (GTSAM's smoothers drop it and need a weak prior);
* the marginal covariance of a window keyframe is its block of ``H^-1`` (two banded triangular
  solves with 15 right-hand sides; the newest keyframe's is the last block of ``L^-T L^-1``).

The interface is :class:`smoother.fixed_lag.KeyframeWindow`'s (``leaving``, ``taken``,
``add_keyframe``, ``state``, ``covariances``), so :class:`smoother.online.OnlineSmoother` drives
either.
"""
from __future__ import annotations

import time
from contextlib import nullcontext
from dataclasses import dataclass

import numpy as np
from numba import njit

from datasets.kinds import measure_into, quiet_dispatch
from factors import imu, preintegration, so3
from factors.errors import InputError
from factors.preintegration import _residual_into, _residual_work
from factors.sensor_models import ODOMETRY_WIDTH, odometry_kernel
from smoother.fixed_lag import WEAK_PRIOR_SIGMAS, FixedLagFailed
from smoother.graph import RELATIVE_MODEL, robust_threshold
from smoother.small_linalg import cholesky_into
from smoother.solver import whitening

DIM = imu.STATE_DIM
#: Robust kernels by their code in the compiled loop (0: none).
ROBUST_CODES = {"huber": 1, "cauchy": 2, "tukey": 3}
_MAX_DIM = 6  # the widest measurement residual (pose, odometry)
#: Reassociation and contraction only (no assumptions about NaN or infinities): lets LLVM turn the
#: dot products of the linear algebra into SIMD code.
_FAST = {"reassoc", "contract"}


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
    for a one-keyframe factor)."""
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
def _linearise(first, cut, cap, r, v, C, bf, bw, has_imu, dC, Wp, Rm, JC, dW, dRm, bwbar, Wimu, gravity,
               m, mk, model, rows, dims, Wm, rcode, rk, Hb, g) -> None:
    """Add to ``Hb``, ``g`` the factors whose earliest keyframe is before ``cut`` (all: ``cut`` past
    the newest): the IMU intervals (stored at the slot of their later keyframe) and the
    measurements ``0 .. m - 1``. Keyframe ``k`` is at slot ``k % cap``, block ``k - first``."""
    work = _residual_work()
    e, A, B = np.empty(DIM), np.empty((DIM, DIM)), np.empty((DIM, DIM))
    J, JT, Jt0, ew = np.empty((DIM, 2 * DIM)), np.empty((2 * DIM, DIM)), np.empty((2 * DIM, DIM)), np.empty(DIM)
    n = Hb.shape[0]
    for blk in range(1, n):
        k = first + blk
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
        _add_normal(Hb, g, blk - 1, 0, blk, DIM, JT, ew, DIM)
    H = np.empty((_MAX_DIM, 2 * DIM))
    for f in range(m):
        k0, k1 = mk[f, 0], mk[f, 1]
        if k0 >= cut:
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
            _add_normal(Hb, g, k0 - first, 0, k1 - first, DIM, JT, ew, d)
        else:
            _add_normal(Hb, g, k0 - first, 0, -1, 0, JT, ew, d)


@njit(cache=True)
def _prior_into(blocks, xr, xv, xC, xbf, xbw, R, e0, cap, r, v, C, bf, bw, first, Hb, g) -> None:
    """Add the linear prior ``e = R (x [-] x_lin) + e0`` on keyframes ``blocks`` (global numbers,
    ascending) to ``Hb``, ``g``."""
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
        ba = blocks[a] - first
        for p in range(DIM):
            s = 0.0
            for row in range(N):
                s += J[row, a * DIM + p] * e[row]
            g[ba * DIM + p] += s
        for b in range(a + 1):
            bb = blocks[b] - first
            for p in range(DIM):
                for q in range(DIM):
                    s = 0.0
                    for row in range(N):
                        s += J[row, a * DIM + p] * J[row, b * DIM + q]
                    Hb[ba, ba - bb, p, q] += s


@njit(cache=True)
def _factorise(Hb, L) -> int:
    """Block-banded Cholesky ``H = L L^T`` (``L[k, s]``: block ``(k, k - s)``); returns -1, or the
    block whose pivot failed."""
    n, S1 = Hb.shape[0], Hb.shape[1]
    S = S1 - 1
    M = np.empty((DIM, DIM))
    for k in range(n):
        for s in range(min(k, S), 0, -1):
            j = k - s
            M[:, :] = Hb[k, s]
            for i in range(max(k - S, 0), j):  # blocks left of j in both rows k and j
                if j - i <= S:
                    A, B = L[k, k - i], L[j, j - i]
                    for p in range(DIM):
                        for q in range(DIM):
                            acc = 0.0
                            for c in range(DIM):
                                acc += A[p, c] * B[q, c]
                            M[p, q] -= acc
            Ljj = L[j, 0]
            X = L[k, s]
            for p in range(DIM):  # X Ljj^T = M, row by row (forward substitution)
                for q in range(DIM):
                    acc = M[p, q]
                    for c in range(q):
                        acc -= X[p, c] * Ljj[q, c]
                    X[p, q] = acc / Ljj[q, q]
        M[:, :] = Hb[k, 0]
        for s in range(1, min(k, S) + 1):
            A = L[k, s]
            for p in range(DIM):
                for q in range(p + 1):
                    acc = 0.0
                    for c in range(DIM):
                        acc += A[p, c] * A[q, c]
                    M[p, q] -= acc
        for p in range(DIM):  # symmetric: the lower triangle is what the block Cholesky reads
            for q in range(p + 1, DIM):
                M[p, q] = M[q, p]
        if not cholesky_into(M, L[k, 0]):
            return k
    return -1


@njit(cache=True)
def _forward(L, b, first_block) -> None:
    """``b <- L^-1 b`` in place (``b (n*15, m)``; blocks before ``first_block`` are zero)."""
    n, S = L.shape[0], L.shape[1] - 1
    m = b.shape[1]
    for k in range(first_block, n):
        for s in range(1, min(k - first_block, S) + 1):
            A = L[k, s]
            for p in range(DIM):
                for c in range(m):
                    acc = 0.0
                    for q in range(DIM):
                        acc += A[p, q] * b[(k - s) * DIM + q, c]
                    b[k * DIM + p, c] -= acc
        Lkk = L[k, 0]
        for c in range(m):
            for p in range(DIM):
                acc = b[k * DIM + p, c]
                for q in range(p):
                    acc -= Lkk[p, q] * b[k * DIM + q, c]
                b[k * DIM + p, c] = acc / Lkk[p, p]


@njit(cache=True)
def _backward(L, b, last_block) -> None:
    """``b <- L^-T b`` in place, blocks ``n - 1`` down to ``last_block``."""
    n, S = L.shape[0], L.shape[1] - 1
    m = b.shape[1]
    for k in range(n - 1, last_block - 1, -1):
        for s in range(1, min(n - 1 - k, S) + 1):
            A = L[k + s, s]  # block (k + s, k)
            for p in range(DIM):
                for c in range(m):
                    acc = 0.0
                    for q in range(DIM):
                        acc += A[q, p] * b[(k + s) * DIM + q, c]
                    b[k * DIM + p, c] -= acc
        Lkk = L[k, 0]
        for c in range(m):
            for p in range(DIM - 1, -1, -1):
                acc = b[k * DIM + p, c]
                for q in range(p + 1, DIM):
                    acc -= Lkk[q, p] * b[k * DIM + q, c]
                b[k * DIM + p, c] = acc / Lkk[p, p]


@njit(cache=True)
def _step(first, n, cap, delta, r, v, C, bf, bw) -> None:
    """``x <- x [+] delta`` for the window's keyframes (left attitude increment)."""
    E = np.empty((3, 3))
    T = np.empty((3, 3))
    for blk in range(n):
        s = (first + blk) % cap
        o = blk * DIM
        for c in range(3):
            r[s, c] += delta[o + c]
            v[s, c] += delta[o + 3 + c]
            bf[s, c] += delta[o + 9 + c]
            bw[s, c] += delta[o + 12 + c]
        so3.exp_into(delta[o + 6], delta[o + 7], delta[o + 8], E)
        for a in range(3):
            for b in range(3):
                T[a, b] = E[a, 0] * C[s, 0, b] + E[a, 1] * C[s, 1, b] + E[a, 2] * C[s, 2, b]
        C[s] = T


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
    ``gravity`` (world, m/s^2) and ``reintegration_threshold`` (rad/s) as the IMU factor's. Keyframe ``k`` (0, 1, ...) has a time stamp and
    the window is ``first .. newest``; :meth:`leaving` names the keyframes the next update
    marginalises, which the caller reads (and records with :meth:`taken`) before it."""

    kind = "sliding"

    def __init__(self, lag_s: float, gravity=imu.DEFAULT_GRAVITY,
                 reintegration_threshold: float = preintegration.REINTEGRATION_THRESHOLD):
        if not lag_s > 0:
            raise InputError(f"lag must be positive, got {lag_s}")
        self.lag_s = float(lag_s)
        self.gravity = np.asarray(gravity, dtype=float)
        self.threshold = float(reintegration_threshold)
        self.first, self.newest = 0, -1
        self.recovered: list[int] = []
        self.skipped = 0
        self.update_s: list[float] = []
        self._taken_after: dict[int, int] = {}
        self._priors: list[_LinearPrior] = []
        self._L = None  # the last factorisation (its blocks: keyframes first .. newest)
        self._allocate_keyframes(64)
        self._allocate_measurements(64)
        self._m = 0

    # -- storage ----------------------------------------------------------------------------------

    def _allocate_keyframes(self, cap: int) -> None:
        shapes = {"_t": (), "_r": (3,), "_v": (3,), "_C": (3, 3), "_bf": (3,), "_bw": (3,), "_dC": (3, 3),
                  "_Wp": (3, 10), "_Rm": (3, 10), "_JC": (3, 3), "_dW": (3, 10, 3), "_dRm": (3, 10, 3),
                  "_bwbar": (3,), "_Wimu": (DIM, DIM)}
        old = {name: getattr(self, name, None) for name in shapes}
        old_imu, old_pre, old_cap = getattr(self, "_has_imu", None), getattr(self, "_pre", None), getattr(self, "_cap", 0)
        self._cap = cap
        for name, tail in shapes.items():
            setattr(self, name, np.zeros((cap,) + tail))
        self._has_imu = np.zeros(cap, dtype=np.bool_)
        self._pre = [None] * cap
        for k in range(self.first, self.newest + 1):  # the window, moved to its new slots
            a, b = k % old_cap, k % cap
            for name in shapes:
                getattr(self, name)[b] = old[name][a]
            self._has_imu[b], self._pre[b] = old_imu[a], old_pre[a]

    def _allocate_measurements(self, cap: int) -> None:
        m = getattr(self, "_m", 0)
        shapes = {"_mk": ((2,), np.int64), "_model": ((), np.int64), "_rows": ((ODOMETRY_WIDTH,), float),
                  "_dims": ((), np.int64), "_Wm": ((_MAX_DIM, _MAX_DIM), float), "_rcode": ((), np.int64),
                  "_rk": ((), float)}
        for name, (tail, dtype) in shapes.items():
            fresh = np.zeros((cap,) + tail, dtype=dtype)
            if m:
                fresh[:m] = getattr(self, name)[:m]
            setattr(self, name, fresh)

    def _state_arrays(self):
        return self._r, self._v, self._C, self._bf, self._bw

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
        return imu.ImuState(self._r[s].copy(), self._v[s].copy(), self._C[s].copy(), self._bf[s].copy(),
                            self._bw[s].copy())

    @property
    def newest_state(self) -> imu.ImuState:
        return self.state(self.newest)

    def add_keyframe(self, t: float, guess: imu.ImuState, pre=None, measurements=(), prior=None) -> imu.ImuState:
        """Add keyframe ``newest + 1`` at ``t`` with the initial value ``guess``, the preintegrated
        interval ``pre`` from the newest keyframe (one :class:`factors.preintegration.Preintegrated`
        interval with its covariance; None: no IMU factor), ``measurements`` (``(spec, m,
        keyframes, robust)``: measurement ``m`` of a :class:`smoother.graph.MeasurementSpec`, the
        keyframes it reads, a robust spec or None) and ``prior`` ``(state, cov)`` on the new keyframe; one Gauss-Newton step; returns the new keyframe's estimate.
        Measurements reading a keyframe that has left are skipped and counted in ``skipped``."""
        tick = time.perf_counter()
        k = self.newest + 1
        self._marginalise(self.leaving(t))
        if k - self.first + 1 > self._cap:
            self._allocate_keyframes(2 * self._cap)
        s = k % self._cap
        self._t[s] = t
        for name, value in zip(("_r", "_v", "_C", "_bf", "_bw"), (guess.r, guess.v, guess.C, guess.b_f, guess.b_w)):
            getattr(self, name)[s] = value
        self._has_imu[s] = False
        self._pre[s] = None
        linked = k == 0
        if pre is not None and k > 0:
            self._store_interval(s, pre)
            linked = True
        for spec, m, keyframes, robust in measurements:
            if min(keyframes) < self.first:
                self.skipped += 1
                continue
            self._add_measurement(spec.model, spec.rows[m], spec.cov[m], robust, keyframes)
            linked = linked or (len(keyframes) > 1 and min(keyframes) < k)
        self.newest = k
        if prior is not None:
            self._add_prior(k, prior[0], prior[1])
        if not linked:  # nothing ties the new keyframe to the window: a weak prior around its guess
            self._add_prior(k, guess, np.diag(WEAK_PRIOR_SIGMAS ** 2))
            self.recovered.append(k)
        self._gauss_newton_step(t)
        self.update_s.append(time.perf_counter() - tick)
        return self.newest_state

    def covariances(self, wanted) -> np.ndarray:
        """The 15x15 marginal covariances (primer convention) of window keyframes ``wanted`` at the
        last linearisation: blocks of ``H^-1``."""
        out = []
        for k in wanted:
            blk = k - self.first
            n = self._L.shape[0]
            b = np.zeros((n * DIM, DIM))
            b[blk * DIM:(blk + 1) * DIM] = np.eye(DIM)
            _forward(self._L, b, blk)
            _backward(self._L, b, blk)
            cov = b[blk * DIM:(blk + 1) * DIM]
            out.append(0.5 * (cov + cov.T))
        return np.stack(out)

    # -- inside -----------------------------------------------------------------------------------

    def _store_interval(self, s: int, pre, whiten: bool = True) -> None:
        """Keep interval ``pre`` at slot ``s``; ``whiten``: its covariance is new (an interval
        integrated again keeps its covariance, and so its whitening)."""
        self._has_imu[s] = True
        self._pre[s] = pre
        for name, value in (("_dC", pre.dC), ("_Wp", pre.W), ("_Rm", pre.Rm), ("_JC", pre.JC), ("_dW", pre.dW),
                            ("_dRm", pre.dRm), ("_bwbar", pre.b_w_bar)):
            getattr(self, name)[s] = value
        if whiten and not _whitening_into(pre.cov, self._Wimu[s]):
            raise InputError("the IMU interval's covariance is not positive definite")

    def _add_measurement(self, model: int, row, cov, robust, keyframes) -> None:
        if self._m == len(self._mk):
            self._allocate_measurements(2 * len(self._mk))
        f = self._m
        d = cov.shape[-1]
        self._mk[f] = (min(keyframes), max(keyframes))
        self._model[f] = model
        self._rows[f, :len(row)] = row
        self._dims[f] = d
        self._Wm[f] = 0.0
        if not _whitening_into(np.ascontiguousarray(cov, dtype=float), self._Wm[f]):
            raise InputError(f"a measurement's covariance is not positive definite: {cov.tolist()}")
        self._rcode[f] = 0 if robust is None else ROBUST_CODES[robust[0]]
        self._rk[f] = 0.0 if robust is None else robust_threshold(robust, d)
        self._m = f + 1

    def _add_prior(self, k: int, state: imu.ImuState, cov) -> None:
        self._priors.append(_LinearPrior(np.array([k]), state.r[None].copy(), state.v[None].copy(),
                                         state.C[None].copy(), state.b_f[None].copy(), state.b_w[None].copy(),
                                         whitening(cov), np.zeros(DIM)))

    def _reintegrate(self) -> None:
        """Integrate again the intervals whose earlier keyframe's gyro bias moved beyond the threshold."""
        ks = np.arange(self.first + 1, self.newest + 1)
        if not ks.size:
            return
        later, earlier = ks % self._cap, (ks - 1) % self._cap
        drift = np.max(np.abs(self._bw[earlier] - self._bwbar[later]), axis=1)
        for j, i in zip(later[(drift > self.threshold) & self._has_imu[later]],
                        earlier[(drift > self.threshold) & self._has_imu[later]]):
            self._store_interval(j, self._pre[j].relinearized(self._bw[i]), whiten=False)

    def _bandwidth(self) -> int:
        S = 1
        if self._m:
            S = max(S, int(np.max(self._mk[:self._m, 1] - self._mk[:self._m, 0])))
        for p in self._priors:
            S = max(S, int(p.keyframes[-1] - p.keyframes[0]))
        return S

    def _normal_equations(self, cut: int, n: int, S: int):
        Hb = np.zeros((n, S + 1, DIM, DIM))
        g = np.zeros(n * DIM)
        with _compiling():
            _linearise(self.first, cut, self._cap, *self._state_arrays(), self._has_imu, self._dC, self._Wp, self._Rm,
                       self._JC, self._dW, self._dRm, self._bwbar, self._Wimu, self.gravity, self._m, self._mk,
                       self._model, self._rows, self._dims, self._Wm, self._rcode, self._rk, Hb, g)
        for p in self._priors:
            if p.keyframes[0] < cut:
                _prior_into(p.keyframes, p.r, p.v, p.C, p.b_f, p.b_w, p.R, p.e0, self._cap, *self._state_arrays(),
                            self.first, Hb, g)
        return Hb, g

    def _gauss_newton_step(self, t: float) -> None:
        n = self.newest - self.first + 1
        self._reintegrate()
        Hb, g = self._normal_equations(self.newest + 1, n, self._bandwidth())
        L = np.zeros_like(Hb)
        failed = _factorise(Hb, L)
        if failed >= 0:
            k = self.first + failed
            raise FixedLagFailed(f"the fixed-lag smoother failed at keyframe {self.newest} (t = {t:.6f} s): the "
                                 f"information of keyframe {k} (t = {self.time(k):.6f} s) is not positive definite. "
                                 "Check the data around that time (an IMU gap, a measurement far off).")
        delta = -g[:, None]
        _forward(L, delta, 0)
        _backward(L, delta, 0)
        _step(self.first, n, self._cap, delta[:, 0], *self._state_arrays())
        self._L = L

    def _marginalise(self, leaving: list[int]) -> None:
        """Replace the factors touching ``leaving`` (the oldest window keyframes) by their Schur
        complement onto the keyframes they also touch, a :class:`_LinearPrior` at the current estimate."""
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
        Hb, g = self._normal_equations(cut, n, S)
        Hs, gs, ok = _schur(Hb, g, nl)
        if not ok:
            raise FixedLagFailed(f"the fixed-lag smoother cannot marginalise keyframes {self.first}..{cut - 1} "
                                 f"(t = {self.time(self.first):.6f}..{self.time(cut - 1):.6f} s): their information "
                                 "is not positive definite. Check the data around that time.")
        # keep the keyframes the marginal ties (non-zero information)
        touched = np.flatnonzero(np.any(Hs.reshape(n - nl, DIM * Hs.shape[1]) != 0.0, axis=1))
        self._priors = [p for p in self._priors if p.keyframes[0] >= cut]
        keep = self._mk[:self._m, 0] >= cut
        for name in ("_mk", "_model", "_rows", "_dims", "_Wm", "_rcode", "_rk"):
            a = getattr(self, name)
            a[:int(keep.sum())] = a[:self._m][keep]
        self._m = int(keep.sum())
        for k in range(self.first + 1, cut + 1):  # the IMU factors into and out of the leaving keyframes
            self._has_imu[k % self._cap] = False
            self._pre[k % self._cap] = None
        self.first = cut
        if touched.size:
            if touched.size < n - nl:
                idx = (touched[:, None] * DIM + np.arange(DIM)).ravel()
                Hs, gs = Hs[np.ix_(idx, idx)], gs[idx]
            R, e0 = _square_root(Hs, gs)
            keyframes = np.array([cut + b for b in touched])
            slots = keyframes % self._cap
            self._priors.append(_LinearPrior(keyframes, self._r[slots].copy(), self._v[slots].copy(),
                                             self._C[slots].copy(), self._bf[slots].copy(), self._bw[slots].copy(),
                                             R, e0))


def _square_root(H: np.ndarray, g: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``(R, e0)`` with ``R^T R = H`` and ``R^T e0 = g``: Cholesky, or for a semi-definite ``H``
    (directions the marginalised factors did not inform) its eigen-decomposition without them."""
    Lc = np.empty_like(H)
    if cholesky_into(H, Lc):
        e0 = g[:, None].copy()
        _solve_lower(Lc, e0)
        return Lc.T.copy(), e0[:, 0]
    else:
        lam, V = np.linalg.eigh(0.5 * (H + H.T))
        keep = lam > 1e-12 * max(lam.max(), 1e-300)
        R = np.sqrt(lam[keep])[:, None] * V[:, keep].T
        R = np.vstack([R, np.zeros((len(H) - R.shape[0], len(H)))])
        e0 = np.zeros(len(H))
        e0[:int(keep.sum())] = (V[:, keep].T @ g) / np.sqrt(lam[keep])
        return R, e0
