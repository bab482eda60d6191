"""One way to turn a residual written in the primer's convention into a ``gtsam.CustomFactor``.

A residual function takes the variables as NumPy arrays -- a rotation as its 3x3 matrix ``C``, a
point or velocity as a 3-vector, a bias as the 6-vector ``(b_f, b_w)`` -- and returns the error
and, on request, one Jacobian per variable with respect to the primer's increments (LEFT
boxplus for rotations). :func:`custom_factor` reads the variables from GTSAM's ``Values``, calls
the residual and passes every rotation Jacobian through the one chart adapter
(:func:`factors.chart.to_gtsam_chart`) so GTSAM receives Jacobians in its own chart.
"""
from __future__ import annotations

from typing import Callable, Sequence

import gtsam
import numpy as np

from factors.chart import to_gtsam_chart
from factors.errors import InputError

ROT, VEC, BIAS = "rot", "vec", "bias"


def read(values: gtsam.Values, key: int, kind: str) -> np.ndarray:
    """A variable of ``values`` as the array the residuals take (C-contiguous: GTSAM's matrices are
    column-major, and the compiled kernels are compiled for row-major arrays only)."""
    if kind == ROT:
        return np.ascontiguousarray(values.atRot3(key).matrix())
    if kind == VEC:
        return values.atVector(key)
    if kind == BIAS:
        return values.atConstantBias(key).vector()
    raise InputError(f"unknown variable kind {kind!r}")


def custom_factor(noise_model, keys: Sequence[int], kinds: Sequence[str], residual: Callable) -> gtsam.CustomFactor:
    """A ``CustomFactor`` on ``keys`` whose error is ``residual(*arrays, jacobians=bool)``.

    ``residual`` returns ``e`` when ``jacobians`` is False and ``(e, [J_1, ..., J_n])`` (primer
    convention) when it is True. Any GTSAM noise model works, robust ones included.
    """
    keys, kinds = list(keys), list(kinds)
    if len(keys) != len(kinds):
        raise InputError(f"{len(keys)} keys but {len(kinds)} kinds")

    def error(this, values, H):
        args = [read(values, k, kind) for k, kind in zip(keys, kinds)]
        if H is None:
            return np.asarray(residual(*args, jacobians=False), dtype=float)
        e, jacs = residual(*args, jacobians=True)
        for i, (kind, arg, J) in enumerate(zip(kinds, args, jacs)):
            H[i] = to_gtsam_chart(J, arg) if kind == ROT else np.asarray(J, dtype=float)
        return np.asarray(e, dtype=float)

    return gtsam.CustomFactor(noise_model, keys, error)
