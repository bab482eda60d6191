"""Compiled linear algebra on small dense matrices, shared by the EKF's update, the sliding
window (:mod:`smoother.fixed_lag.sliding.window`) and the data types' checks (:mod:`datasets.types`): calls
into LAPACK cost more than the arithmetic at these sizes (3 to a few hundred rows)."""
from __future__ import annotations

import math

from numba import njit


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
