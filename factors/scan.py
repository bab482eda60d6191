"""Prefix products of stacks of matrices by recursive doubling (a parallel scan in NumPy)."""
from __future__ import annotations

import numpy as np


def prefix_products(M: np.ndarray, later_on_left: bool) -> np.ndarray:
    """Inclusive prefix products of ``M`` (K, n, n): ``P_k = M_k ... M_1 M_0`` when
    ``later_on_left``, else ``P_k = M_0 M_1 ... M_k``. ``ceil(log2 K)`` batched products instead
    of a Python loop over K; equal to the loop up to the association of round-off."""
    P = np.array(M, dtype=float, copy=True)
    shift = 1
    while shift < len(P):
        P[shift:] = P[shift:] @ P[:-shift] if later_on_left else P[:-shift] @ P[shift:]
        shift *= 2
    return P

