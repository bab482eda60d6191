"""The 24 Euler-angle conventions, named as in the ECE276A rotations lecture (reference 004).

Names. A convention is a 4-letter string: ``'r'`` (rotating axes = intrinsic) or ``'s'`` (static
axes = extrinsic), then the three axes in the order the rotations are applied, e.g. ``'rzyx'``,
``'sxyz'``, ``'rzxz'``. Six sequences use three different axes (Tait-Bryan: xyz, xzy, yxz, yzx,
zxy, zyx) and six repeat the first axis last (proper Euler: xyx, xzx, yxy, yzy, zxz, zyz); each
comes intrinsic and extrinsic: 2 x 12 = 24 names, listed in :data:`CONVENTIONS`.

Angles. ``angles[..., m]`` is the angle about the m-th axis of the name (radians, right-hand
rule, the active elementary rotations ``R_x, R_y, R_z`` of the lecture). For axes ``(i, j, k)``:

* intrinsic ``'r' + ijk``: rotate about ``i`` by ``a``, then about the *moved* ``j`` by ``b``, then
  about the twice-moved ``k`` by ``c``:  ``C = R_i(a) R_j(b) R_k(c)``;
* extrinsic ``'s' + ijk``: rotate about the *fixed* ``i`` by ``a``, then the fixed ``j`` by ``b``,
  then the fixed ``k`` by ``c``:  ``C = R_k(c) R_j(b) R_i(a)``.

Hence an extrinsic sequence equals the intrinsic one with the axis order reversed and each angle
kept with its axis: ``to_matrix((a, b, c), 's' + ijk) == to_matrix((c, b, a), 'r' + kji)``
(the lecture's ``sxyz = rzyx``).

Frames. ``C`` is the project's ``C(Phi_IB)``: it maps body coordinates to world coordinates,
``I_r = C B_r``; "fixed" axes are the world's, "moved" axes the body's. Roll, pitch, yaw
``(r, p, y)`` in the project's convention (:func:`rpy_to_matrix`,
``C = R_z(y) R_y(p) R_x(r)``) is ``'sxyz'`` with angles ``(r, p, y)``, or ``'rzyx'`` with
``(y, p, r)`` (:data:`ROLL_PITCH_YAW`).

SciPy. ``scipy.spatial.transform.Rotation.from_euler`` takes lower-case axes as extrinsic and
upper-case as intrinsic, with the angles in the same order as here; :func:`scipy_sequence` maps a
name onto SciPy's (``'sxyz' -> 'xyz'``, ``'rzyx' -> 'ZYX'``). SciPy is not needed by this module.

Ranges and singular cases of :func:`from_matrix`. For an intrinsic name the first and third angles
are in ``[-pi, pi]``; the middle angle is in ``[-pi/2, pi/2]`` (Tait-Bryan) or ``[0, pi]``
(proper Euler). When the middle angle is at an end of its range where the first and last axes
line up -- ``b = +-pi/2`` for Tait-Bryan (gimbal lock), ``b = 0`` or ``pi`` for proper Euler (the
degenerate case) -- only a sum or difference of the first and third angles is determined. Then the
angle applied LAST in the body-fixed order -- the third angle of an intrinsic name, the first angle
of an extrinsic name (for roll-pitch-yaw: the roll) -- is set to 0 and the other one carries the
whole rotation, so ``to_matrix(from_matrix(C))`` still reproduces ``C``. This is the choice of
:func:`matrix_to_rpy`. "Singular" means ``|cos b|`` (or ``|sin b|``), as read from ``C``,
below :data:`SINGULAR_TOLERANCE` (1e-14: exact lock computed in floating point gives about 1e-16;
snapping to the singular solution moves ``C`` by at most about this much). Off the singularity the
first angle is computed from what is left of ``C`` once the other two rotations are removed, not
from its own pair of entries, so the result reproduces ``C`` to round-off even just off the
singularity, where the angles themselves are ill-conditioned.
"""
from __future__ import annotations

import numpy as np

from factors import quaternion
from factors.axis_angle import check_rotation_matrix, check_vector
from factors.errors import InputError

_AXES = "xyz"

#: The 12 axis sequences: Tait-Bryan first, then proper Euler.
TAIT_BRYAN = ("xyz", "xzy", "yxz", "yzx", "zxy", "zyx")
PROPER_EULER = ("xyx", "xzx", "yxy", "yzy", "zxz", "zyz")
SEQUENCES = TAIT_BRYAN + PROPER_EULER

#: All 24 convention names: ``'r'`` (intrinsic) and ``'s'`` (extrinsic) for each sequence.
CONVENTIONS = tuple("r" + s for s in SEQUENCES) + tuple("s" + s for s in SEQUENCES)

#: Below this ``|cos b|`` (Tait-Bryan) or ``|sin b|`` (proper Euler) :func:`from_matrix` treats the
#: middle angle as singular and sets the body-most angle to 0.
SINGULAR_TOLERANCE = 1e-14

#: The project's roll-pitch-yaw: angles ``(roll, pitch, yaw)``, ``C = R_z(yaw) R_y(pitch) R_x(roll)``.
ROLL_PITCH_YAW = "sxyz"


def parse(convention: str):
    """``(intrinsic, (i, j, k))`` of a convention name, axes as indices 0, 1, 2 (x, y, z).
    Raises ``ValueError`` for anything but the 24 names of :data:`CONVENTIONS`."""
    if not isinstance(convention, str) or convention not in CONVENTIONS:
        hint = ""
        if isinstance(convention, str) and convention.lower() in CONVENTIONS:
            hint = " (names are lower case; SciPy's case-coded names map through scipy_sequence)"
        elif isinstance(convention, str) and len(convention) == 3:
            hint = " (prefix 'r' for intrinsic/rotating or 's' for extrinsic/static axes)"
        raise InputError(
            f"convention: expected one of the 24 names {', '.join(CONVENTIONS)}; got {convention!r}{hint}"
        )
    return convention[0] == "r", tuple(_AXES.index(a) for a in convention[1:])


def is_proper_euler(convention: str) -> bool:
    """True for the proper Euler sequences (first axis repeated last), False for Tait-Bryan."""
    _, (i, _, k) = parse(convention)
    return i == k


def reverse(convention: str) -> str:
    """The equivalent name with the other kind of axes: ``'sxyz' <-> 'rzyx'``. Angles go with their
    axes, so they are reversed too: ``to_matrix(a, c) == to_matrix(a[..., ::-1], reverse(c))``."""
    parse(convention)
    return ("s" if convention[0] == "r" else "r") + convention[:0:-1]


def scipy_sequence(convention: str) -> str:
    """The ``seq`` argument of SciPy's ``Rotation.from_euler`` / ``as_euler`` for a convention:
    extrinsic names map to lower case (``'sxyz' -> 'xyz'``), intrinsic to upper case
    (``'rzyx' -> 'ZYX'``); the angle order is the same in both libraries."""
    intrinsic, _ = parse(convention)
    return convention[1:].upper() if intrinsic else convention[1:]


def elementary(axis: int, angle) -> np.ndarray:
    """The lecture's ``R_x``, ``R_y``, ``R_z``: the active rotation by ``angle`` (shape ``(...)``)
    about coordinate axis ``axis`` (0, 1, 2 or 'x', 'y', 'z'); shape ``(..., 3, 3)``."""
    if isinstance(axis, str):
        if axis not in _AXES:
            raise InputError(f"axis: expected 'x', 'y', 'z', 0, 1 or 2, got {axis!r}")
        axis = _AXES.index(axis)
    if axis not in (0, 1, 2):
        raise InputError(f"axis: expected 'x', 'y', 'z', 0, 1 or 2, got {axis!r}")
    angle = np.asarray(angle, dtype=float)
    c, s = np.cos(angle), np.sin(angle)
    p, q = (axis + 1) % 3, (axis + 2) % 3
    out = np.zeros(angle.shape + (3, 3))
    out[..., axis, axis] = 1.0
    out[..., p, p] = c
    out[..., q, q] = c
    out[..., q, p] = s
    out[..., p, q] = -s
    return out


def _check_angles(angles) -> np.ndarray:
    return check_vector(angles, "angles")


def to_matrix(angles, convention: str) -> np.ndarray:
    """Rotation matrix ``C`` (body to world, shape ``(..., 3, 3)``) of Euler angles
    ``angles`` (shape ``(..., 3)``, radians, one per axis of the name) in ``convention``:
    ``R_i(a) R_j(b) R_k(c)`` for ``'r' + ijk`` (intrinsic), ``R_k(c) R_j(b) R_i(a)`` for
    ``'s' + ijk`` (extrinsic)."""
    intrinsic, (i, j, k) = parse(convention)
    angles = _check_angles(angles)
    Ra, Rb, Rc = (elementary(ax, angles[..., m]) for m, ax in enumerate((i, j, k)))
    return Ra @ Rb @ Rc if intrinsic else Rc @ Rb @ Ra


def _canonical_frame(i: int, j: int) -> np.ndarray:
    """Rotation ``Q`` with rows ``e_i, e_j, e_i x e_j``: ``Q R_i(t) Q^T = R_x(t)``,
    ``Q R_j(t) Q^T = R_y(t)``, ``Q R_{i x j}(t) Q^T = R_z(t)`` (``Q`` is proper, so angles keep
    their signs)."""
    e = np.eye(3)
    return np.stack([e[i], e[j], np.cross(e[i], e[j])])


def _intrinsic_from_matrix(C: np.ndarray, i: int, j: int, k: int) -> np.ndarray:
    """Angles ``(a, b, c)`` with ``C = R_i(a) R_j(b) R_k(c)``."""
    Q = _canonical_frame(i, j)
    M = Q @ C @ Q.T
    if i == k:
        # M = R_x(a) R_y(b) R_x(c): M00 = cos b, (M01, M02) = sin b (sin c, cos c).
        sin_b = np.hypot(M[..., 0, 1], M[..., 0, 2])
        b = np.arctan2(sin_b, M[..., 0, 0])
        singular = sin_b < SINGULAR_TOLERANCE
        c = np.where(singular, 0.0, np.arctan2(M[..., 0, 1], M[..., 0, 2]))
        third = elementary(0, c)
    else:
        # The third axis is +-(e_i x e_j): M = R_x(a) R_y(b) R_z(sign c).
        sign = float(np.dot(np.cross(np.eye(3)[i], np.eye(3)[j]), np.eye(3)[k]))
        # M02 = sin b, (M00, M01) = cos b (cos c', -sin c') with c' = sign c.
        cos_b = np.hypot(M[..., 0, 0], M[..., 0, 1])
        b = np.arctan2(M[..., 0, 2], cos_b)
        singular = cos_b < SINGULAR_TOLERANCE
        c_canonical = np.where(singular, 0.0, np.arctan2(-M[..., 0, 1], M[..., 0, 0]))
        c = sign * c_canonical
        third = elementary(2, c_canonical)
    # What is left once R_y(b) and the third rotation are taken off is R_x(a); reading a from it
    # (instead of from its own pair of entries) keeps C reproduced when b is near-singular.
    rest = M @ np.swapaxes(third, -1, -2) @ np.swapaxes(elementary(1, b), -1, -2)
    a = np.arctan2(rest[..., 2, 1], rest[..., 1, 1])
    return np.stack([a, b, c], axis=-1)


def from_matrix(C, convention: str) -> np.ndarray:
    """Euler angles (shape ``(..., 3)``) of the rotation matrix ``C`` (body to world, shape
    ``(..., 3, 3)``) in ``convention``, with ``to_matrix(from_matrix(C, n), n) == C``.

    Ranges (intrinsic order ``a, b, c``): ``a, c`` in ``[-pi, pi]``; ``b`` in ``[-pi/2, pi/2]``
    (Tait-Bryan) or ``[0, pi]`` (proper Euler). For an extrinsic name the angles are those of the
    reversed intrinsic name, reversed. At gimbal lock / the degenerate middle angle the body-most
    angle (intrinsic third, extrinsic first) is 0; see the module docstring."""
    intrinsic, (i, j, k) = parse(convention)
    C = check_rotation_matrix(C)
    if intrinsic:
        return _intrinsic_from_matrix(C, i, j, k)
    return _intrinsic_from_matrix(C, k, j, i)[..., ::-1]


def perturbation_jacobian(angles, convention: str, chart: str = "left") -> np.ndarray:
    """``E = d eps / d angles`` (shape ``(..., 3, 3)``): the rotation-vector perturbation that a
    small change of the Euler angles makes, ``to_matrix(angles + d) ~= exp(E d) to_matrix(angles)``
    for ``chart='left'`` (the primer's [+], world frame) or
    ``~= to_matrix(angles) exp(E d)`` for ``'right'`` (GTSAM's chart, body frame; ``E_right =
    C^T E_left``).

    Columns, intrinsic ``C = R_i(a) R_j(b) R_k(c)``: ``e_i, R_i(a) e_j, R_i(a) R_j(b) e_k``
    (each axis as it is when its rotation is applied, in world coordinates). ``|det E|`` is
    ``|cos b|`` (Tait-Bryan) or ``|sin b|`` (proper Euler): singular at gimbal lock / the
    degenerate middle angle, where the angles cannot follow every perturbation."""
    intrinsic, (i, j, k) = parse(convention)
    angles = _check_angles(angles)
    if chart not in ("left", "right"):
        raise InputError(f"chart: expected 'left' or 'right' (see uncertainty.convert_covariance for 'middle'), "
                         f"got {chart!r}")
    e = np.eye(3)
    a, b, c = angles[..., 0], angles[..., 1], angles[..., 2]
    if intrinsic:
        Ra = elementary(i, a)
        cols = [np.broadcast_to(e[i], angles.shape), Ra @ e[j], Ra @ elementary(j, b) @ e[k]]
    else:
        Rc = elementary(k, c)
        cols = [Rc @ elementary(j, b) @ e[i], Rc @ e[j], np.broadcast_to(e[k], angles.shape)]
    E = np.stack(cols, axis=-1)
    if chart == "right":
        E = np.swapaxes(to_matrix(angles, convention), -1, -2) @ E
    return E


def to_quaternion(angles, convention: str) -> np.ndarray:
    """Hamilton unit quaternion (scalar first, ``q0 >= 0``) of Euler angles, via the matrix."""
    return quaternion.from_matrix(to_matrix(angles, convention))


def from_quaternion(q, convention: str) -> np.ndarray:
    """Euler angles of a Hamilton unit quaternion (scalar first), via the matrix; see
    :func:`from_matrix` for ranges and singular cases."""
    return from_matrix(quaternion.to_matrix(quaternion.check_unit(q, "q")), convention)


def convert(angles, source: str, target: str) -> np.ndarray:
    """Re-express Euler angles given in convention ``source`` in convention ``target``."""
    return from_matrix(to_matrix(angles, source), target)


def rpy_to_matrix(rpy) -> np.ndarray:
    """``C = R_z(yaw) R_y(pitch) R_x(roll)`` for ``rpy = (roll, pitch, yaw)`` of shape ``(..., 3)``
    (:data:`ROLL_PITCH_YAW`)."""
    return to_matrix(rpy, ROLL_PITCH_YAW)


def matrix_to_rpy(C) -> np.ndarray:
    """``(roll, pitch, yaw)`` with ``C = R_z(yaw) R_y(pitch) R_x(roll)``, pitch in ``[-pi/2, pi/2]``.
    At gimbal lock (``|cos(pitch)| <`` :data:`SINGULAR_TOLERANCE`) only ``yaw - roll`` (pitch
    ``+pi/2``) or ``yaw + roll`` (pitch ``-pi/2``) is defined: roll is 0 and yaw carries the whole
    rotation about the vertical, so :func:`rpy_to_matrix` of the result reproduces ``C``."""
    return from_matrix(C, ROLL_PITCH_YAW)
