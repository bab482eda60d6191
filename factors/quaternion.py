"""Hamilton unit quaternions, scalar first, as in section V of the primer.

A quaternion is an array ``q = (q0, qx, qy, qz)`` of shape ``(..., 4)`` with ``q0`` the real part;
every function is vectorised over leading dimensions. ``q`` and ``-q`` are the same orientation;
functions that return a quaternion return the one with ``q0 >= 0`` unless said otherwise:
``compose``, ``inverse``, ``normalize`` and the reorderings ``from_xyzw``, ``to_xyzw`` keep the
sign their inputs imply, and ``exp`` returns ``q0 = cos(|phi|/2)``, negative for ``|phi| > pi``.
``exp`` is the exponential onto the unit quaternions, which cover each rotation twice: forced to
``q0 >= 0`` it would jump at ``|phi| = pi`` and break ``exp(a phi) o exp(b phi) = exp((a + b) phi)``.

The orientation ``Phi = q`` maps coordinates with eq. (35),
``Phi(r) = (2 q0^2 - 1) r + 2 q0 qv x r + 2 qv (qv . r)``, i.e. ``C(q)`` of eq. (36) is the usual
active rotation matrix of ``q``, the same matrix GTSAM's ``Rot3.Quaternion(w, x, y, z)`` builds.

Small angles: ``exp`` uses ``(cos(t/2), sin(t/2)/t phi)`` and below ``SMALL_ANGLE`` its Taylor
form, whose leading term is eq. (39), ``(1, phi/2)``. ``log`` uses ``2 atan2(|qv|, q0) qv/|qv|``
(eq. 40) and below ``SMALL_ANGLE`` its Taylor form, whose leading term is ``2 qv``. (The primer's
eq. 41 prints ``log ~= qv``: that drops the factor 2 and contradicts eqs. 39 and 40; the
consistency test ``exp(log(q)) == q`` decides for ``2 qv``.)
"""
from __future__ import annotations

import math

import numpy as np
from numba import njit

from factors.compiled import exact_leaf
from factors.errors import InputError
from factors.rows import apply_rows, as_trailing

#: Below this rotation angle (rad) exp and log use their Taylor forms (primer: "below 1e-4 rad").
SMALL_ANGLE = 1e-4

#: Tolerance on ``| |q| - 1 |`` accepted by :func:`check_unit`.
UNIT_TOLERANCE = 1e-6



def _split(q: np.ndarray, name: str = "q"):
    q = as_trailing(q, (4,), name)
    return q[..., 0], q[..., 1:]


def identity(shape=()) -> np.ndarray:
    """The identity orientation ``(1, 0, 0, 0)`` of the given leading shape."""
    shape = (shape,) if isinstance(shape, int) else tuple(shape)
    q = np.zeros(shape + (4,))
    q[..., 0] = 1.0
    return q


def check_unit(q: np.ndarray, name: str = "quaternion", tolerance: float = UNIT_TOLERANCE) -> np.ndarray:
    """Return ``q`` as a float array after checking shape ``(..., 4)``, finiteness and unit norm.

    Raises ``ValueError`` naming ``name``, the first offending index and the norm found.
    """
    q = np.asarray(q, dtype=float)
    if q.shape[-1:] != (4,):
        raise InputError(f"{name}: expected shape (..., 4) (q0, qx, qy, qz), got {q.shape}")
    if not np.all(np.isfinite(q)):
        bad = _first_index(~np.isfinite(q).all(axis=-1))
        raise InputError(f"{name}: non-finite value at index {bad}")
    norm = np.linalg.norm(q, axis=-1)
    off = np.abs(norm - 1.0) > tolerance
    if np.any(off):
        bad = _first_index(off)
        raise InputError(
            f"{name}: not a unit quaternion at index {bad}: norm {norm[bad]:.9g}, "
            f"expected 1 within {tolerance:g}"
        )
    return q


def _first_index(mask: np.ndarray) -> tuple:
    """Index (a tuple of Python ints, ``()`` for a single quaternion) of the first True in ``mask``."""
    return tuple(int(i) for i in np.argwhere(mask)[0]) if np.ndim(mask) else ()


def normalize(q: np.ndarray) -> np.ndarray:
    """``q / |q|``."""
    q = as_trailing(q, (4,), "q")
    return q / np.linalg.norm(q, axis=-1, keepdims=True)


def canonical(q: np.ndarray) -> np.ndarray:
    """The representative of ``q`` with ``q0 >= 0`` (the same orientation)."""
    q = as_trailing(q, (4,), "q")
    return np.where(q[..., :1] < 0.0, -q, q)


def rotate(q: np.ndarray, r: np.ndarray) -> np.ndarray:
    """The coordinate map ``Phi(r)`` of eq. (35)."""
    q0, qv = _split(q)
    r = as_trailing(r, (3,), "r")
    dot = np.sum(qv * r, axis=-1, keepdims=True)
    return (2 * q0[..., None] ** 2 - 1) * r + 2 * q0[..., None] * np.cross(qv, r) + 2 * qv * dot


def to_matrix(q: np.ndarray) -> np.ndarray:
    """``C(Phi)`` of eq. (36): ``(2 q0^2 - 1) I + 2 q0 qv^x + 2 qv qv^T``."""
    q0, qv = _split(q)
    x, y, z = qv[..., 0], qv[..., 1], qv[..., 2]
    out = np.empty(q0.shape + (3, 3))
    a = 2 * q0**2 - 1
    out[..., 0, 0] = a + 2 * x * x
    out[..., 1, 1] = a + 2 * y * y
    out[..., 2, 2] = a + 2 * z * z
    out[..., 0, 1] = 2 * (x * y - q0 * z)
    out[..., 1, 0] = 2 * (x * y + q0 * z)
    out[..., 0, 2] = 2 * (x * z + q0 * y)
    out[..., 2, 0] = 2 * (x * z - q0 * y)
    out[..., 1, 2] = 2 * (y * z - q0 * x)
    out[..., 2, 1] = 2 * (y * z + q0 * x)
    return out


@exact_leaf
def matrix_to_quaternion(C) -> tuple:
    """Compiled core of :func:`from_matrix` for one 3x3 matrix: ``(q0, qx, qy, qz)``, ``q0 >= 0``."""
    c00, c11, c22 = C[0, 0], C[1, 1], C[2, 2]
    # 4 * (component)^2 for each candidate pivot: q0, qx, qy, qz; the first largest is used.
    pivots = (1.0 + c00 + c11 + c22, 1.0 + c00 - c11 - c22, 1.0 - c00 + c11 - c22, 1.0 - c00 - c11 + c22)
    which = 0
    for i in range(1, 4):
        if pivots[i] > pivots[which]:
            which = i
    s = 2.0 * math.sqrt(max(pivots[which], 1e-300))
    quarter = 0.25 * s * s  # = s^2 / 4, divided by s below: the pivot component itself
    d21, d02, d10 = C[2, 1] - C[1, 2], C[0, 2] - C[2, 0], C[1, 0] - C[0, 1]
    s01, s02, s12 = C[0, 1] + C[1, 0], C[0, 2] + C[2, 0], C[1, 2] + C[2, 1]
    if which == 0:
        q = (quarter, d21, d02, d10)
    elif which == 1:
        q = (d21, quarter, s01, s02)
    elif which == 2:
        q = (d02, s01, quarter, s12)
    else:
        q = (d10, s02, s12, quarter)
    q0, qx, qy, qz = q[0] / s, q[1] / s, q[2] / s, q[3] / s
    n = math.sqrt(q0 * q0 + qx * qx + qy * qy + qz * qz)
    if q0 < 0.0:
        n = -n
    return q0 / n, qx / n, qy / n, qz / n


@njit(cache=True)
def _from_matrix_rows(C, out):
    for i in range(C.shape[0]):
        out[i, 0], out[i, 1], out[i, 2], out[i, 3] = matrix_to_quaternion(C[i])


def from_matrix(C: np.ndarray) -> np.ndarray:
    """Unit quaternion (``q0 >= 0``) of a rotation matrix, by Shepperd's method.

    Of the four algebraically equivalent formulas, each matrix uses the one that divides by the
    largest of ``|q0|, |qx|, |qy|, |qz|`` (at least 1/2), so the result is accurate to round-off
    for every rotation, including angles of pi. Compiled (:func:`matrix_to_quaternion`),
    vectorised over leading dimensions.
    """
    return apply_rows(_from_matrix_rows, C, (3, 3), (4,), "C")


def compose(q1: np.ndarray, q2: np.ndarray) -> np.ndarray:
    """``Phi1 o Phi2`` by eq. (37): ``(q0 p0 - qv.pv, q0 pv + p0 qv + qv x pv)``."""
    q0, qv = _split(q1, "q1")
    p0, pv = _split(q2, "q2")
    real = q0 * p0 - np.sum(qv * pv, axis=-1)
    imag = q0[..., None] * pv + p0[..., None] * qv + np.cross(qv, pv)
    return np.concatenate([real[..., None], imag], axis=-1)


def inverse(q: np.ndarray) -> np.ndarray:
    """``Phi^-1``: the conjugate ``(q0, -qv)`` of a unit quaternion."""
    q = as_trailing(q, (4,), "q")
    return np.concatenate([q[..., :1], -q[..., 1:]], axis=-1)


def exp(phi: np.ndarray) -> np.ndarray:
    """Unit quaternion of the rotation vector ``phi`` (eq. 38; eq. 39 below ``SMALL_ANGLE``), with
    ``q0 = cos(|phi|/2)``: negative for ``|phi| > pi``, not canonicalised (see the module docstring)."""
    phi = as_trailing(phi, (3,), "phi")
    t = np.linalg.norm(phi, axis=-1)
    small = t < SMALL_ANGLE
    t_safe = np.where(small, 1.0, t)
    # sin(t/2)/t; its series 1/2 - t^2/48 starts with eq. (39)'s 1/2.
    half_sinc = np.where(small, 0.5 - t * t / 48.0, np.sin(0.5 * t_safe) / t_safe)
    real = np.where(small, 1.0 - t * t / 8.0, np.cos(0.5 * t))
    q = np.concatenate([real[..., None], half_sinc[..., None] * phi], axis=-1)
    return q / np.linalg.norm(q, axis=-1, keepdims=True)


@njit(cache=True)
def quaternion_log(q0, qx, qy, qz) -> tuple:
    """Compiled core of :func:`log` for one unit quaternion: the rotation vector ``(x, y, z)``;
    NaN if a component is not finite (or ``|qv|^2`` overflows, which no unit quaternion does)."""
    if q0 < 0.0:
        q0, qx, qy, qz = -q0, -qx, -qy, -qz
    s = math.sqrt(qx * qx + qy * qy + qz * qz)
    if not (q0 < math.inf and s < math.inf):
        return math.nan, math.nan, math.nan
    if s < 0.5 * SMALL_ANGLE:
        # 2 atan2(s, q0) / s as its series (2/q0)(1 - x^2/3 + x^4/5), x = s/q0 (q0 ~ 1 here)
        q0_safe = q0 if q0 > 0.0 else 1.0
        x2 = (s / q0_safe) ** 2
        scale = 2.0 / q0_safe * (1.0 - x2 / 3.0 + x2 * x2 / 5.0)
    else:
        scale = 2.0 * math.atan2(s, q0) / s
    return scale * qx, scale * qy, scale * qz


@njit(cache=True)
def _log_rows(q, out):
    for i in range(q.shape[0]):
        out[i, 0], out[i, 1], out[i, 2] = quaternion_log(q[i, 0], q[i, 1], q[i, 2], q[i, 3])


def log(q: np.ndarray) -> np.ndarray:
    """Rotation vector of a unit quaternion, ``|phi| <= pi`` (eq. 40; its Taylor form, led by
    ``2 qv``, below ``SMALL_ANGLE``). ``q`` and ``-q`` give the same vector except at exactly pi.
    A quaternion with a NaN or infinite component gives NaN, as ``so3.log`` of such a matrix does
    (:func:`check_unit` rejects it with an error instead). Compiled (:func:`quaternion_log`),
    vectorised over leading dimensions."""
    return apply_rows(_log_rows, q, (4,), (3,), "q")


def from_rot3(R) -> np.ndarray:
    """Quaternion of a ``gtsam.Rot3`` (``q0 >= 0``)."""
    return from_matrix(np.asarray(R.matrix()))


def to_rot3(q: np.ndarray):
    """``gtsam.Rot3`` of one unit quaternion."""
    import gtsam

    q = normalize(q)
    if q.ndim != 1:
        raise InputError(f"q: expected shape (4,) (one quaternion), got {q.shape}")
    return gtsam.Rot3.Quaternion(float(q[0]), float(q[1]), float(q[2]), float(q[3]))


def from_xyzw(q: np.ndarray) -> np.ndarray:
    """Reorder a scalar-last ``(qx, qy, qz, qw)`` array (TUM, ROS) to this module's scalar-first."""
    q = as_trailing(q, (4,), "q")
    return np.concatenate([q[..., 3:], q[..., :3]], axis=-1)


def to_xyzw(q: np.ndarray) -> np.ndarray:
    """Reorder to scalar-last ``(qx, qy, qz, qw)``."""
    q = as_trailing(q, (4,), "q")
    return np.concatenate([q[..., 1:], q[..., :1]], axis=-1)
