"""Axis-angle: a unit axis ``n`` and an angle ``theta``, the rotation about ``n`` by ``theta``.

Convention. ``to_matrix(n, theta)`` is the active rotation about ``n`` by ``theta`` (right-hand
rule), ``C = I + sin(theta) n^x + (1 - cos(theta)) n^x n^x`` (Rodrigues), i.e. exactly
``so3.exp(theta n)``: the matrix ``C(Phi)`` of the project, mapping coordinates of the rotated
(body) frame into the fixed (world) frame, ``I_r = C B_r``. The rotation vector is
``phi = theta n``; the Hamilton quaternion (scalar first) is ``(cos(theta/2), sin(theta/2) n)``.

:func:`from_matrix` returns ``theta`` in ``[0, pi]`` and a unit axis. It is an implementation of
the matrix logarithm written independently of :func:`factors.so3.log` (which goes through the
quaternion), so that each can check the other; they agree to round-off. Its special cases:

* ``theta = 0`` (``C = I``): every axis is a solution. The axis returned is :data:`DEFAULT_AXIS`
  (``e_x``), so that ``to_matrix(*from_matrix(I)) == I`` and the rotation vector is ``0``.
* ``theta = pi`` (``tr C = -1``): ``C`` is symmetric, ``C = 2 n n^T - I``, the skew part that
  carries the axis elsewhere vanishes, and ``n`` and ``-n`` are both solutions. The axis is read
  from a column of ``I + C = 2 n n^T``: ``n = (I + C) e_i / sqrt(2 (1 + C_ii))``, with ``i`` the
  largest diagonal entry so that the division is by at least ``2/sqrt(3)``. Its sign is
  whatever that column gives (both are right).
* Near pi the same construction is used on the symmetric part, which for every angle is
  ``(C + C^T)/2 - cos(theta) I = (1 - cos(theta)) n n^T``; it equals ``I + C`` at pi. This is
  well conditioned for ``theta > pi/2`` (where it is used), while the skew part
  ``(C - C^T)/2 = sin(theta) n^x`` (used below pi/2) loses the axis as ``sin(theta) -> 0``.
  Off pi, the sign of the column is fixed by the skew part, so the result is continuous.

The angle is ``atan2(|skew part|, (tr C - 1)/2)``, accurate at 0 and pi, where the textbook
``arccos((tr C - 1)/2)`` loses half of the digits.

The module also holds the argument checks the other representation modules share
(:func:`check_rotation_matrix`, :func:`check_vector`).
"""
from __future__ import annotations

import numpy as np

from factors import quaternion, so3
from factors.errors import InputError

#: Axis returned for the identity rotation (angle 0), where the axis is undefined.
DEFAULT_AXIS = np.array([1.0, 0.0, 0.0])

#: Accepted deviation of ``C^T C`` from ``I`` (max abs entry) and of a unit axis's norm from 1.
ORTHONORMAL_TOLERANCE = 1e-6


def check_vector(v, name: str, size: int = 3) -> np.ndarray:
    """Return ``v`` as a float array of shape ``(..., size)``; raise ``ValueError`` naming
    ``name`` if the shape is wrong or a value is not finite."""
    try:
        v = np.asarray(v, dtype=float)
    except (TypeError, ValueError) as err:
        raise InputError(f"{name}: expected a float array of shape (..., {size}): {err}") from None
    if v.ndim < 1 or v.shape[-1] != size:
        raise InputError(f"{name}: expected shape (..., {size}), got {v.shape}")
    if not np.all(np.isfinite(v)):
        bad = tuple(int(i) for i in np.argwhere(~np.isfinite(v))[0])
        raise InputError(f"{name}: expected finite values, found {v[bad]} at index {bad}")
    return v


def check_matrix(M, name: str, size: int = 3) -> np.ndarray:
    """Return ``M`` as a float array of shape ``(..., size, size)`` with finite values, or raise
    ``ValueError`` naming ``name``."""
    try:
        M = np.asarray(M, dtype=float)
    except (TypeError, ValueError) as err:
        raise InputError(f"{name}: expected a float array of shape (..., {size}, {size}): {err}") from None
    if M.ndim < 2 or M.shape[-2:] != (size, size):
        raise InputError(f"{name}: expected shape (..., {size}, {size}), got {M.shape}")
    if not np.all(np.isfinite(M)):
        bad = tuple(int(i) for i in np.argwhere(~np.isfinite(M))[0])
        raise InputError(f"{name}: expected finite values, found {M[bad]} at index {bad}")
    return M


def check_rotation_matrix(C, name: str = "C", tolerance: float = ORTHONORMAL_TOLERANCE) -> np.ndarray:
    """Return ``C`` as a float array of shape ``(..., 3, 3)`` after checking that each matrix is a
    rotation: finite, ``|C^T C - I| <= tolerance`` entrywise and ``det C > 0``. Accepts a
    ``gtsam.Rot3`` too. Raises ``ValueError`` naming ``name`` and the first offending index."""
    if hasattr(C, "matrix") and callable(C.matrix):
        C = C.matrix()
    C = check_matrix(C, name)
    err = np.abs(np.swapaxes(C, -1, -2) @ C - np.eye(3)).max(axis=(-2, -1))
    det = np.linalg.det(C)
    bad = (err > tolerance) | (det <= 0.0)
    if np.any(bad):
        first = tuple(int(i) for i in np.argwhere(np.atleast_1d(bad))[0])
        index = first if C.ndim > 2 else ()
        raise InputError(
            f"{name}: expected a rotation matrix (C^T C = I within {tolerance:g}, det C = +1); "
            f"the matrix at index {index} has max|C^T C - I| = {np.atleast_1d(err)[first]:.3g} "
            f"and det = {np.atleast_1d(det)[first]:.6g}"
        )
    return C


def _norm(v: np.ndarray) -> np.ndarray:
    """Euclidean norm over the last axis without underflow for tiny vectors (|v| ~ 1e-200)."""
    scale = np.abs(v).max(axis=-1)
    safe = np.where(scale > 0.0, scale, 1.0)
    return scale * np.linalg.norm(v / safe[..., None], axis=-1)


def _check_axis_angle(axis, angle):
    """The checked unit ``axis`` and ``angle``, broadcast to their common leading shape."""
    axis = check_vector(axis, "axis")
    norm = np.linalg.norm(axis, axis=-1)
    if np.any(np.abs(norm - 1.0) > ORTHONORMAL_TOLERANCE):
        bad = tuple(int(i) for i in np.argwhere(np.atleast_1d(np.abs(norm - 1.0) > ORTHONORMAL_TOLERANCE))[0])
        raise InputError(
            f"axis: expected unit vectors (norm 1 within {ORTHONORMAL_TOLERANCE:g}), "
            f"found norm {np.atleast_1d(norm)[bad]:.9g} at index {bad if axis.ndim > 1 else ()}"
        )
    try:
        angle = np.asarray(angle, dtype=float)
    except (TypeError, ValueError) as err:
        raise InputError(f"angle: expected a float array of shape (...): {err}") from None
    if not np.all(np.isfinite(angle)):
        raise InputError("angle: expected finite values (radians)")
    try:
        lead = np.broadcast_shapes(axis.shape[:-1], angle.shape)
    except ValueError:
        raise InputError(
            f"angle: expected a shape broadcastable with axis.shape[:-1] = {axis.shape[:-1]}, got {angle.shape}"
        ) from None
    return np.broadcast_to(axis / norm[..., None], lead + (3,)), np.broadcast_to(angle, lead)


def to_matrix(axis, angle) -> np.ndarray:
    """Rotation matrix of the rotation about the unit ``axis`` (shape ``(..., 3)``) by ``angle``
    (radians, shape ``(...)``, any real value): ``I + sin(a) n^x + (1 - cos(a)) n^x n^x``.

    Equal to ``so3.exp(angle * axis)``; an axis off unit norm by more than
    :data:`ORTHONORMAL_TOLERANCE` raises ``ValueError`` (within it, the axis is normalised)."""
    axis, angle = _check_axis_angle(axis, angle)
    k = so3.skew(axis)
    a = angle[..., None, None]
    return np.eye(3) + np.sin(a) * k + (1.0 - np.cos(a)) * (k @ k)


def from_matrix(C):
    """``(axis, angle)`` of the rotation matrix ``C`` (shape ``(..., 3, 3)``): unit axes of shape
    ``(..., 3)`` and angles in ``[0, pi]`` of shape ``(...)``, with ``to_matrix(axis, angle) == C``.

    Angle 0 returns :data:`DEFAULT_AXIS`; angles above pi/2, pi included, read the axis from a
    column of the symmetric part (the ``(I + C) e_i`` construction); see the module docstring."""
    C = check_rotation_matrix(C)
    w = so3.vee(C)  # (C - C^T)^v / 2 = sin(angle) n
    s = _norm(w)
    c = 0.5 * (np.trace(C, axis1=-2, axis2=-1) - 1.0)
    angle = np.arctan2(s, c)

    # Small and moderate angles: the direction of the skew part.
    nonzero = s > 0.0
    axis_skew = np.where(nonzero[..., None], w / np.where(nonzero, s, 1.0)[..., None], DEFAULT_AXIS)

    # Large angles (cos < 0), pi included: a column of (C + C^T)/2 - cos I = (1 - cos) n n^T.
    S = 0.5 * (C + np.swapaxes(C, -1, -2)) - c[..., None, None] * np.eye(3)
    diag = np.diagonal(S, axis1=-2, axis2=-1)
    i = np.argmax(diag, axis=-1)
    column = np.take_along_axis(S, i[..., None, None], axis=-1)[..., 0]
    axis_sym = column / np.maximum(np.linalg.norm(column, axis=-1), 1e-300)[..., None]
    # Away from exactly pi the skew part fixes the sign; at pi both signs are solutions.
    flip = np.sum(axis_sym * w, axis=-1) < 0.0
    axis_sym = np.where(flip[..., None], -axis_sym, axis_sym)

    axis = np.where((c < 0.0)[..., None], axis_sym, axis_skew)
    return axis, angle


def to_rotation_vector(axis, angle) -> np.ndarray:
    """Rotation vector ``angle * axis`` (shape ``(..., 3)``), the argument of ``so3.exp``."""
    axis, angle = _check_axis_angle(axis, angle)
    return angle[..., None] * axis


def from_rotation_vector(phi):
    """``(axis, angle)`` of the rotation vector ``phi``: ``angle = |phi|`` (not wrapped to pi),
    ``axis = phi / |phi|``, and :data:`DEFAULT_AXIS` for ``phi = 0``."""
    phi = check_vector(phi, "phi")
    angle = _norm(phi)
    nonzero = angle > 0.0
    axis = np.where(nonzero[..., None], phi / np.where(nonzero, angle, 1.0)[..., None], DEFAULT_AXIS)
    return axis, angle


def log(C) -> np.ndarray:
    """Rotation vector ``angle * axis`` of ``C`` with norm in ``[0, pi]``, through
    :func:`from_matrix`. Agrees with ``so3.log`` except at exactly pi, where either sign of the
    axis is a solution and the two functions may pick different ones."""
    axis, angle = from_matrix(C)
    return angle[..., None] * axis


def to_quaternion(axis, angle) -> np.ndarray:
    """Hamilton unit quaternion, scalar first, ``(cos(angle/2), sin(angle/2) axis)``. Not
    canonicalised: for ``|angle| > pi`` its scalar part is negative (the same rotation as ``-q``)."""
    axis, angle = _check_axis_angle(axis, angle)
    half = 0.5 * angle
    return np.concatenate([np.cos(half)[..., None], np.sin(half)[..., None] * axis], axis=-1)


def from_quaternion(q):
    """``(axis, angle)`` of a unit quaternion (scalar first), angle in ``[0, pi]``:
    ``angle = 2 atan2(|q_v|, q_0)`` after choosing the sign with ``q_0 >= 0`` (accurate at 0 and
    pi, unlike ``2 arccos(q_0)``), ``axis = q_v / |q_v|``; :data:`DEFAULT_AXIS` at angle 0."""
    q = quaternion.canonical(quaternion.check_unit(q, "q"))
    qv = q[..., 1:]
    s = _norm(qv)
    angle = 2.0 * np.arctan2(s, q[..., 0])
    nonzero = s > 0.0
    axis = np.where(nonzero[..., None], qv / np.where(nonzero, s, 1.0)[..., None], DEFAULT_AXIS)
    return axis, angle
