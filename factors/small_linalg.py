"""Compiled linear algebra on small dense matrices, shared by the EKF's update
(:mod:`smoother.ekf.update`), the preintegration, the sliding window's banded algebra
(:mod:`smoother.fixed_lag.sliding.banded`) and the data types' checks (:mod:`datasets.types`): calls
into LAPACK cost more than the arithmetic at these sizes (3 to a few hundred rows)."""
from __future__ import annotations

import math

from numba import njit

from factors.compiled import exact_leaf


@njit(cache=True)
def cholesky_into(S, L) -> bool:
    """Lower Cholesky factor of the symmetric positive definite ``S`` into ``L`` (every entry
    written; only the lower triangle of ``S`` is read); False if ``S`` is not positive definite."""
    m = S.shape[0]
    for i in range(m):
        for j in range(i + 1):
            acc = S[i, j]
            for k in range(j):
                acc -= L[i, k] * L[j, k]
            if i == j:
                if not acc > 0.0:
                    return False
                L[i, i] = math.sqrt(acc)
            else:
                L[i, j] = acc / L[j, j]
        for j in range(i + 1, m):
            L[i, j] = 0.0
    return True


@exact_leaf
def matmul_into(A, B, out) -> None:
    """``out = A B`` for small 2-d arrays of any layout (``out`` must not alias ``A`` or ``B``).
    Written out because Numba's ``@`` on matrices calls SciPy's BLAS: the kernels load no SciPy
    (slow to import; only the chi-square quantiles of :mod:`smoother.stats` use it)."""
    for a in range(A.shape[0]):
        for b in range(B.shape[1]):
            acc = 0.0
            for k in range(A.shape[1]):
                acc += A[a, k] * B[k, b]
            out[a, b] = acc
@njit(cache=True)
def solve_lower(L, B) -> None:
    """``B <- L^-1 B`` in place by forward substitution, column by column (``L`` lower
    triangular, ``B (n, m)``; a single right-hand side is passed as an ``(n, 1)`` view). Every
    caller passes C-contiguous float64 arrays: one compiled copy."""
    n, m = B.shape
    for c in range(m):
        for i in range(n):
            s = B[i, c]
            for j in range(i):
                s -= L[i, j] * B[j, c]
            B[i, c] = s / L[i, i]
