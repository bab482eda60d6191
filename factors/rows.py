"""Arrays laid out for the compiled per-element kernels (:mod:`factors.compiled`).

A kernel ``loop(flat_in, flat_out)`` loops over the first axis of C-contiguous, writable float64
rows and indexes the trailing dimensions without bounds checks. The helpers here check the
trailing shapes, broadcast and flatten the leading ones, and give a kernel the vectorised
interface of a NumPy function (:func:`apply_rows`: ``(..., *in_dims) -> (..., *out_dims)``).
"""
from __future__ import annotations

import math

import numpy as np

from factors.errors import InputError


def as_trailing(a, dims: tuple, name: str) -> np.ndarray:
    """``a`` as a float array whose trailing dimensions are ``dims``: checked here, because the
    compiled kernels index them without bounds checks."""
    a = np.asarray(a, dtype=float)
    if a.ndim < len(dims) or a.shape[a.ndim - len(dims):] != tuple(dims):
        raise InputError(f"{name}: expected shape (..., {', '.join(map(str, dims))}), got {a.shape}")
    return a


def apply_rows(loop, a, in_dims: tuple, out_dims: tuple, name: str) -> np.ndarray:
    """``loop(flat, out)`` over ``a`` of shape ``(..., *in_dims)``, returning ``(..., *out_dims)``.
    ``flat`` is C-contiguous and writable (a copy of ``a`` where it is not), the one layout the
    kernels are compiled for."""
    a = as_trailing(a, in_dims, name)
    lead = a.shape[: a.ndim - len(in_dims)]
    flat = np.require(a.reshape((-1,) + tuple(in_dims)), np.float64, ["C", "W"])
    out = np.empty((flat.shape[0],) + tuple(out_dims))
    loop(flat, out)
    return out.reshape(lead + tuple(out_dims))


def rows(lead: tuple, arrays, tails) -> list:
    """Each array broadcast to ``lead + tail`` (its own trailing shape ``tail``) and flattened to
    contiguous, writable rows ``(prod(lead),) + tail`` -- the one layout the compiled row loops are
    compiled for (a read-only array, such as a broadcast, would compile and cache a second copy of
    the kernel). Arrays already in that shape and layout are reshaped views (this sits on the
    per-factor callback path, so the common case does no copying and few checks)."""
    lead = tuple(lead)
    n = math.prod(lead)
    out = []
    for a, t in zip(arrays, tails):
        shape = lead + tuple(t)
        if type(a) is not np.ndarray or a.dtype != np.float64:
            a = np.asarray(a, dtype=float)
        if a.shape != shape:
            a = np.broadcast_to(a, shape)
        if not (a.flags.c_contiguous and a.flags.writeable):
            a = np.array(a, order="C")
        out.append(a.reshape((n,) + tuple(t)))
    return out


def common_shape(*shapes) -> tuple:
    """The broadcast of ``shapes`` (fast when they are all equal)."""
    first = shapes[0]
    return first if all(s == first for s in shapes) else np.broadcast_shapes(*shapes)
