"""Block-banded matrices as the sliding window assembles them (blocks of 15, block bandwidth ``S``:
each keyframe's factor reaches ``S`` keyframes back), dense and in the window's band storage
``Hb (n, S + 1, 15, 15)`` (``Hb[k, s]`` = block ``(k, k - s)``), shared by the tests of the
banded algebra, the window and its calibration border."""
from __future__ import annotations

import numpy as np

from smoother.fixed_lag.sliding.banded import DIM


def random_banded(rng, n: int, S: int) -> np.ndarray:
    """A random symmetric positive definite matrix of ``n`` blocks, block bandwidth ``S``, as the
    window assembles one (a sum of ``J^T J`` of factors reaching ``S`` keyframes back)."""
    H = np.eye(n * DIM)
    for k in range(n):
        lo = max(0, k - S) * DIM
        J = rng.normal(size=(DIM, (k + 1) * DIM - lo))
        H[lo:(k + 1) * DIM, lo:(k + 1) * DIM] += J.T @ J
    return H


def band(H: np.ndarray, S: int) -> np.ndarray:
    """``H``'s lower block band as ``Hb (n, S + 1, 15, 15)``."""
    n = len(H) // DIM
    Hb = np.zeros((n, S + 1, DIM, DIM))
    for k in range(n):
        for s in range(min(k, S) + 1):
            Hb[k, s] = H[k * DIM:(k + 1) * DIM, (k - s) * DIM:(k - s + 1) * DIM]
    return Hb


def dense(Hb: np.ndarray) -> np.ndarray:
    """The symmetric matrix of the block band ``Hb`` (row blocks from 0)."""
    n, S1 = Hb.shape[:2]
    H = np.zeros((n * DIM, n * DIM))
    for k in range(n):
        for s in range(min(k, S1 - 1) + 1):
            H[k * DIM:(k + 1) * DIM, (k - s) * DIM:(k - s + 1) * DIM] = Hb[k, s]
            H[(k - s) * DIM:(k - s + 1) * DIM, k * DIM:(k + 1) * DIM] = Hb[k, s].T
    return H
