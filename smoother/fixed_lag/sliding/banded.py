"""Block-banded linear algebra of the sliding window (:mod:`smoother.fixed_lag.sliding.window`), compiled.

The matrices are symmetric positive definite, in blocks of ``DIM = 15`` (one keyframe's error
state), block-banded with bandwidth ``S``: block ``(k, j)`` is zero when ``k - j > S``. Nothing
outside the band is stored (a linear prior on several keyframes widens the band to its span; the
calibration variables' dense border, ``nc`` columns beside it, is stored apart).

Two layouts:

* a matrix to factorise or marginalise, ``Hb (n, S + 1, 15, 15)``: ``Hb[k, s]`` is block
  ``(k, k - s)`` of rows ``0 .. n - 1`` (only the lower band; ``s <= k``);
* the Cholesky factor ``H = L L^T`` and right-hand sides in a ring of ``cap`` slots, so that the
  window moves without copying: keyframe ``k`` at slot ``k % cap``, ``L[k % cap, s]`` block
  ``(k, k - s)`` of ``L``, ``b[k % cap]`` the ``(15, m)`` rows of keyframe ``k``. The window is
  keyframes ``first .. newest``.

Row ``k`` of ``L`` depends on the rows of ``H`` up to ``k`` only: :func:`factorise` computes rows
``start ..`` and keeps the ones before, and :func:`forward_solve` continues a forward solution from a
row on. Eliminating the leading blocks first, the rows of ``L`` after them are the factor of their
Schur complement (:func:`schur`, :func:`marginal_prior`; both with the calibrations' dense border
of :mod:`smoother.fixed_lag.sliding.calibration`, which :func:`border_solve` solves for). ``docs/design.md`` (fixed-lag
smoothing) gives the derivation.
"""
from __future__ import annotations

import numpy as np
from numba import njit

from factors.imu import STATE_DIM as DIM
from factors.small_linalg import cholesky_into, solve_lower


@njit(cache=True)
def factorise(Hr, L, first, start, newest, cap, S) -> int:
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
def forward_solve(L, b, first, start, zero_before, newest, cap, S) -> None:
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
def backward_solve(L, b, stop, newest, cap, S) -> None:
    """``b <- L^-T b`` in place, rows ``newest`` down to ``stop`` (``b`` as :func:`forward_solve`'s)."""
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


def no_border(n: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The border ``(B, D, g_c)`` of a system of ``n`` keyframe blocks without calibrations."""
    return np.zeros((n, DIM, 0)), np.zeros((0, 0)), np.zeros(0)


@njit(cache=True)
def schur(Hb, g, B, D, gc, nl):
    """The Schur complement of the first ``nl`` blocks of the block-banded ``(Hb, g)`` bordered by
    ``nc`` calibration coordinates (``B (n, 15, nc)`` their coupling with each block, ``D (nc,
    nc)``, ``g_c (nc)`` their own; ``nc = 0``: no border): ``(H_mm - H_ml H_ll^-1 H_lm, g_m -
    H_ml H_ll^-1 g_l)`` over the remaining blocks, then the calibrations, and True, or False if
    ``H_ll`` is not positive definite."""
    n, S1, nc = Hb.shape[0], Hb.shape[1], D.shape[0]
    N = n * DIM
    H = np.zeros((N + nc, N + nc))
    for k in range(n):
        for s in range(min(k, S1 - 1) + 1):
            j = k - s
            for p in range(DIM):
                for q in range(DIM):
                    H[k * DIM + p, j * DIM + q] = Hb[k, s, p, q]
                    H[j * DIM + q, k * DIM + p] = Hb[k, s, p, q]
        for p in range(DIM):
            for c in range(nc):
                H[k * DIM + p, N + c] = B[k, p, c]
                H[N + c, k * DIM + p] = B[k, p, c]
    H[N:, N:] = D
    full = np.empty(N + nc)
    full[:N] = g
    full[N:] = gc
    m0, M = nl * DIM, N + nc
    Lll = np.empty((m0, m0))
    Hs, gs = np.empty((M - m0, M - m0)), np.empty(M - m0)
    if not cholesky_into(H[:m0, :m0].copy(), Lll):
        return Hs, gs, False
    Y = np.empty((m0, M - m0 + 1))
    Y[:, :M - m0] = H[:m0, m0:]
    Y[:, M - m0] = full[:m0]
    solve_lower(Lll, Y)
    for a in range(M - m0):
        for b in range(a + 1):  # symmetric: the lower triangle, mirrored
            s = H[m0 + a, m0 + b]
            for c in range(m0):
                s -= Y[c, a] * Y[c, b]
            Hs[a, b] = s
            Hs[b, a] = s
        s = full[m0 + a]
        for c in range(m0):
            s -= Y[c, a] * Y[c, M - m0]
        gs[a] = s
    return Hs, gs, True


@njit(cache=True)
def marginal_prior(Hb, g, B, D, gc, nl):
    """The linear prior that replaces the first ``nl`` blocks of the block-banded ``(Hb, g)`` with
    the border ``(B, D, g_c)`` (:func:`schur`): their Schur complement on the blocks it informs
    (rows not all zero), ``touched`` (their numbers after the first ``nl``), and on every
    calibration coordinate, as ``R`` (upper triangular, ``R^T R = H_s``) and ``e0`` (``R^T e0 =
    g_s``). Returns ``(status, touched, A, b, D_s, g_cs)``: status 0 with ``(R, e0)``; 1 when
    ``H_ll`` is not positive definite; 2 when ``H_s`` is only semi-definite, with ``(H_s, g_s)``
    on the touched blocks and the calibrations for :func:`semidefinite_square_root`. ``(D_s,
    g_cs)``: the calibrations' block of ``(H_s, g_s)`` -- the prior's own share of ``(D, g_c)``
    where it is made (``R_c^T R_c``, ``R_c^T e0`` with ``R_c`` its calibration columns)."""
    nc = D.shape[0]
    Hs, gs, ok = schur(Hb, g, B, D, gc, nl)
    if not ok:
        return 1, np.empty(0, dtype=np.int64), Hs, gs, np.empty((nc, nc)), np.empty(nc)
    n = (Hs.shape[0] - nc) // DIM
    keep = np.zeros(n, dtype=np.bool_)
    for b in range(n):
        for p in range(b * DIM, (b + 1) * DIM):
            for q in range(Hs.shape[1]):
                if Hs[p, q] != 0.0:
                    keep[b] = True
    touched = np.flatnonzero(keep)
    at = np.empty(touched.size * DIM + nc, dtype=np.int64)
    for a in range(touched.size):
        for p in range(DIM):
            at[a * DIM + p] = touched[a] * DIM + p
    for c in range(nc):
        at[touched.size * DIM + c] = n * DIM + c
    m = at.size
    Ht, gt = np.empty((m, m)), np.empty(m)
    for a in range(m):
        gt[a] = gs[at[a]]
        for b in range(m):
            Ht[a, b] = Hs[at[a], at[b]]
    own_D, own_g = Ht[m - nc:, m - nc:].copy(), gt[m - nc:].copy()
    Lc = np.empty((m, m))
    if not cholesky_into(Ht, Lc):
        return 2, touched, Ht, gt, own_D, own_g
    e0 = gt.reshape(m, 1).copy()
    solve_lower(Lc, e0)
    return 0, touched, Lc.T.copy(), e0[:, 0].copy(), own_D, own_g


@njit(cache=True)
def border_solve(L, Z, ZZ, B, D, gc, y, dx, first, start, newest, cap, S, L_D, delta_c, threshold, fraction,
                  widest, limits) -> int:
    """The border's part of a solve of the bordered window (:mod:`smoother.fixed_lag.sliding.calibration`):
    the rows ``start ..`` of ``Z = L^-1 B`` (``B[k - start]`` keyframe ``k``'s coupling with the
    ``nc`` calibration coordinates; ``Z`` by slot like ``L``) and of their products ``ZZ[k % cap]
    = Z_k^T [Z_k, y_k]`` (``(nc, nc + 1)``, the lower triangle of ``Z_k^T Z_k`` and the column
    ``Z_k^T y_k``, which like ``Z_k`` and ``y_k`` stay while row ``k`` of ``L`` does), ``L_D
    L_D^T = D - Z^T Z`` from their sums, ``delta_c = -(L_D L_D^T)^-1 (g_c + Z^T y)`` with ``y``
    the forward solution, and ``dx -= Z delta_c`` over the window (which the backward solve turns
    into the keyframes' step). ``limits`` gets each coordinate's limit: the larger of its
    ``threshold`` and ``fraction`` of its marginal sigma (the square root of the diagonal of
    ``(L_D L_D^T)^-1``: the squared norms of ``L_D^-1``'s columns), at most ``widest`` times the
    threshold. Returns 1 when some ``|delta_c|`` exceeds its limit, else 0; -1, ``L_D``,
    ``delta_c``, ``limits`` and ``dx`` untouched, when ``D - Z^T Z`` is not positive definite."""
    nc = D.shape[0]
    for k in range(start, newest + 1):
        Z[k % cap] = B[k - start]
    forward_solve(L, Z, first, start, first, newest, cap, S)
    for k in range(start, newest + 1):
        s = k % cap
        for a in range(nc):
            for b in range(a + 1):
                acc = 0.0
                for p in range(DIM):
                    acc += Z[s, p, a] * Z[s, p, b]
                ZZ[s, a, b] = acc
            acc = 0.0
            for p in range(DIM):
                acc += Z[s, p, a] * y[s, p, 0]
            ZZ[s, a, nc] = acc
    Sc, rhs = D.copy(), np.empty(nc)
    for a in range(nc):
        rhs[a] = -gc[a]
    for k in range(first, newest + 1):
        s = k % cap
        for a in range(nc):
            rhs[a] -= ZZ[s, a, nc]
            for b in range(a + 1):
                Sc[a, b] -= ZZ[s, a, b]
    factor = np.empty((nc, nc))  # cholesky_into reads the lower triangle
    if not cholesky_into(Sc, factor):
        return -1
    x = rhs.reshape(nc, 1).copy()
    solve_lower(factor, x)
    for a in range(nc - 1, -1, -1):  # L_D^T delta = x
        acc = x[a, 0]
        for b in range(a + 1, nc):
            acc -= factor[b, a] * x[b, 0]
        x[a, 0] = acc / factor[a, a]
    L_D[:, :] = factor
    inv = np.zeros((nc, nc))  # L_D^-1: coordinate a's marginal variance is the squared norm of its column
    for a in range(nc):
        inv[a, a] = 1.0 / factor[a, a]
        for i in range(a + 1, nc):
            acc = 0.0
            for b in range(a, i):
                acc -= factor[i, b] * inv[b, a]
            inv[i, a] = acc / factor[i, i]
    exceeds = 0
    for a in range(nc):
        delta_c[a] = x[a, 0]
        var = 0.0
        for i in range(a, nc):
            var += inv[i, a] * inv[i, a]
        limits[a] = max(threshold[a], min(fraction * np.sqrt(var), widest * threshold[a]))
        if abs(x[a, 0]) > limits[a]:
            exceeds = 1
    for k in range(first, newest + 1):
        s = k % cap
        for p in range(DIM):
            acc = 0.0
            for a in range(nc):
                acc += Z[s, p, a] * x[a, 0]
            dx[s, p, 0] -= acc
    return exceeds


def semidefinite_square_root(H: np.ndarray, g: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
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
