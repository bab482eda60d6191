"""Calculus on SO(3) in the primer's convention, on rotation matrices.

Conventions (docs/design.md, sections 1 and 3; Bloesch et al., "A Primer on the Differential
Calculus of 3D Orientations"):

* An orientation ``Phi`` is represented by its matrix ``C(Phi)``: ``Phi(r) = C(Phi) r``.
* ``exp(phi)`` is Rodrigues' formula (primer eq. 21); ``log`` is its inverse on the closed ball
  of radius pi (at an angle of exactly pi it returns one of the two vectors of norm pi).
* ``boxplus(C, phi) = exp(phi) C`` -- a LEFT perturbation (eq. 14).
* ``boxminus(C1, C2) = log(C1 C2^T)`` (eq. 15), so ``boxplus(C2, boxminus(C1, C2)) == C1``.
* ``gamma(phi) = d exp(phi) / d phi`` in the [+]/[-] sense (eq. 31, 33): the SO(3) *left*
  Jacobian, ``exp(phi + d) ~= exp(gamma(phi) d) exp(phi)``. ``gamma_inv`` is its inverse, the
  derivative of ``log`` (eq. 32).

Every function is vectorised over leading dimensions: ``phi`` has shape ``(..., 3)`` and ``C``
shape ``(..., 3, 3)``.

Numerics: the coefficient functions of Rodrigues' formula and of ``gamma`` are evaluated in forms
free of cancellation (``(1 - cos t) / t^2 = sinc(t/2)^2 / 2``) or, for the two that cancel
(``(t - sin t) / t^3`` and the ``gamma_inv`` coefficient), by their Taylor series below
``SERIES_ANGLE``. ``log`` goes through the quaternion of the matrix (Shepperd's method) and
``2 atan2(|q_v|, q_0)``, which is accurate to round-off at every angle, 0 and pi included.

exp, log, gamma and gamma_inv are compiled scalar kernels (``*_into``, ``log_of``; see
:mod:`factors.compiled`) that the IMU recursions call directly; the public functions run them
over any leading dimensions.
"""
from __future__ import annotations

import math

import numpy as np
from numba import njit

from factors import quaternion
from factors.compiled import exact_leaf
from factors.rows import apply_rows, as_trailing, common_shape, rows

#: Below this angle (rad) the coefficients that cancel are evaluated by their Taylor series.
SERIES_ANGLE = 1e-2


def skew(v: np.ndarray) -> np.ndarray:
    """Skew-symmetric matrix ``v^x`` with ``v^x r = v x r`` (primer section II)."""
    v = as_trailing(v, (3,), "v")
    out = np.zeros(v.shape[:-1] + (3, 3))
    out[..., 0, 1] = -v[..., 2]
    out[..., 0, 2] = v[..., 1]
    out[..., 1, 0] = v[..., 2]
    out[..., 1, 2] = -v[..., 0]
    out[..., 2, 0] = -v[..., 1]
    out[..., 2, 1] = v[..., 0]
    return out


def vee(m: np.ndarray) -> np.ndarray:
    """Inverse of :func:`skew` on the skew-symmetric part of ``m``."""
    m = as_trailing(m, (3, 3), "m")
    return 0.5 * np.stack(
        [m[..., 2, 1] - m[..., 1, 2], m[..., 0, 2] - m[..., 2, 0], m[..., 1, 0] - m[..., 0, 1]],
        axis=-1,
    )


#: Decorator of the scalar helpers (:func:`coefficients`, :func:`quadratic_entries`,
#: :func:`exp_and_gamma_entries`): inlined by Numba into the kernels that use them, because a call
#: that returns tuples goes through memory (inlined, the IMU recursions run 5-10% faster). Inlined
#: code follows its caller's floating-point rules: strict IEEE in this module's kernels, fused
#: multiply-adds inside the IMU recursions (:data:`factors.compiled.recursion`, tested at 1e-12).
_inlined = njit(cache=True, inline="always")


@_inlined
def coefficients(t: float) -> tuple:
    """``(sin t / t, (1 - cos t) / t^2, (t - sin t) / t^3)`` at ``t >= 0``: the coefficients of
    exp (first two) and Gamma (last two). Below ``SERIES_ANGLE`` all three by their Taylor series
    (no trigonometric call; truncation below 1e-27 relative there); above, from ``sin t`` and
    ``sin(t/2)`` with ``(1 - cos t) / t^2 = sinc(t/2)^2 / 2``, free of cancellation."""
    if t < SERIES_ANGLE:
        t2 = t * t
        return (1.0 + t2 * (-1 / 6 + t2 * (1 / 120 + t2 * (-1 / 5040 + t2 * (1 / 362880)))),
                0.5 + t2 * (-1 / 24 + t2 * (1 / 720 + t2 * (-1 / 40320 + t2 * (1 / 3628800)))),
                1 / 6 + t2 * (-1 / 120 + t2 * (1 / 5040 + t2 * (-1 / 362880))))
    s = math.sin(t)
    half = math.sin(0.5 * t) / (0.5 * t)
    return s / t, 0.5 * half * half, (t - s) / t**3


@njit(cache=True)
def _gamma_inv_coefficient(t: float) -> float:
    """(1 - (t/2) cot(t/2)) / t^2, the phi^x^2 coefficient of gamma_inv; finite up to t = pi;
    its Taylor series below ``SERIES_ANGLE``."""
    if t < SERIES_ANGLE:
        t2 = t * t
        return 1 / 12 + t2 * (1 / 720 + t2 * (1 / 30240 + t2 * (1 / 1209600)))
    return (1.0 - 0.5 * t * math.cos(0.5 * t) / math.sin(0.5 * t)) / (t * t)


@_inlined
def quadratic_entries(x: float, y: float, z: float, a: float, b: float) -> tuple:
    """The nine entries (row-major) of ``I + a phi^x + b phi^x^2`` for ``phi = (x, y, z)`` (the
    form of exp, Gamma and Gamma^-1), with ``phi^x^2 = phi phi^T - |phi|^2 I`` written entry by
    entry; as a tuple, so compiled callers keep them in registers."""
    xy, xz, yz = b * x * y, b * x * z, b * y * z
    return (1.0 - b * (y * y + z * z), -a * z + xy, a * y + xz,
            a * z + xy, 1.0 - b * (x * x + z * z), -a * x + yz,
            -a * y + xz, a * x + yz, 1.0 - b * (x * x + y * y))


@exact_leaf
def quadratic_into(x: float, y: float, z: float, a: float, b: float, out) -> None:
    """:func:`quadratic_entries` into the 3x3 array ``out``."""
    e = quadratic_entries(x, y, z, a, b)
    out[0, 0], out[0, 1], out[0, 2] = e[0], e[1], e[2]
    out[1, 0], out[1, 1], out[1, 2] = e[3], e[4], e[5]
    out[2, 0], out[2, 1], out[2, 2] = e[6], e[7], e[8]


@exact_leaf
def exp_into(x: float, y: float, z: float, out) -> None:
    """Compiled core of :func:`exp`: Rodrigues' matrix of ``(x, y, z)`` into ``out`` (3x3)."""
    a, b, _ = coefficients(math.sqrt(x * x + y * y + z * z))
    quadratic_into(x, y, z, a, b, out)


@exact_leaf
def gamma_into(x: float, y: float, z: float, out) -> None:
    """Compiled core of :func:`gamma`."""
    _, b, c = coefficients(math.sqrt(x * x + y * y + z * z))
    quadratic_into(x, y, z, b, c, out)


@_inlined
def exp_and_gamma_entries(x: float, y: float, z: float) -> tuple:
    """The entries (row-major 9-tuples) of ``exp`` and ``Gamma`` of the same vector, sharing their
    coefficients (the IMU recursions need both at every sample)."""
    a, b, c = coefficients(math.sqrt(x * x + y * y + z * z))
    return quadratic_entries(x, y, z, a, b), quadratic_entries(x, y, z, b, c)


@exact_leaf
def gamma_inv_into(x: float, y: float, z: float, out) -> None:
    """Compiled core of :func:`gamma_inv`."""
    t = math.sqrt(x * x + y * y + z * z)
    quadratic_into(x, y, z, -0.5, _gamma_inv_coefficient(t), out)


@exact_leaf
def log_of(C) -> tuple:
    """Compiled core of :func:`log` for one 3x3 rotation matrix: ``(x, y, z)``."""
    q0, qx, qy, qz = quaternion.matrix_to_quaternion(C)
    return quaternion.quaternion_log(q0, qx, qy, qz)


_EXP, _GAMMA, _GAMMA_INV = 0, 1, 2


@njit(cache=True)
def _quadratic_rows(phi, out, which):
    """exp, gamma or gamma_inv (``which``) of every row of ``phi``."""
    for i in range(phi.shape[0]):
        x, y, z = phi[i, 0], phi[i, 1], phi[i, 2]
        if which == _EXP:
            exp_into(x, y, z, out[i])
        elif which == _GAMMA:
            gamma_into(x, y, z, out[i])
        else:
            gamma_inv_into(x, y, z, out[i])


def _matrices(phi, which: int) -> np.ndarray:
    return apply_rows(lambda flat, out: _quadratic_rows(flat, out, which), phi, (3,), (3, 3), "phi")


@njit(cache=True)
def boxminus_of(C1, C2) -> tuple:
    """Compiled core of :func:`boxminus` for one pair of 3x3 matrices: ``log(C1 C2^T)``."""
    X = np.empty((3, 3))
    for a in range(3):
        for b in range(3):
            X[a, b] = C1[a, 0] * C2[b, 0] + C1[a, 1] * C2[b, 1] + C1[a, 2] * C2[b, 2]
    return log_of(X)


@njit(cache=True)
def _boxminus_rows(C1, C2, out):
    for i in range(C1.shape[0]):
        out[i, 0], out[i, 1], out[i, 2] = boxminus_of(C1[i], C2[i])


@njit(cache=True)
def _log_rows(C, out):
    for i in range(C.shape[0]):
        out[i, 0], out[i, 1], out[i, 2] = log_of(C[i])


def exp(phi: np.ndarray) -> np.ndarray:
    """Rotation matrix ``C(exp(phi))`` by Rodrigues' formula (primer eq. 21)."""
    return _matrices(phi, _EXP)


def log(C: np.ndarray) -> np.ndarray:
    """Rotation vector ``phi`` with ``exp(phi) = C`` and ``|phi| <= pi``.

    Goes through the unit quaternion of ``C`` (Shepperd's method) and ``2 atan2(|q_v|, q_0)``,
    so it keeps full precision near 0 and near pi, where the textbook
    ``arccos((tr C - 1) / 2)`` loses half the digits and ``1 / sin`` blows up.
    """
    return apply_rows(_log_rows, C, (3, 3), (3,), "C")


def compose(C1: np.ndarray, C2: np.ndarray) -> np.ndarray:
    """``C(Phi1 o Phi2) = C1 C2`` (primer eq. 5)."""
    return as_trailing(C1, (3, 3), "C1") @ as_trailing(C2, (3, 3), "C2")


def inverse(C: np.ndarray) -> np.ndarray:
    """``C(Phi^-1) = C^T``."""
    return np.swapaxes(as_trailing(C, (3, 3), "C"), -1, -2)


def boxplus(C: np.ndarray, phi: np.ndarray) -> np.ndarray:
    """``Phi [+] phi = exp(phi) o Phi`` (primer eq. 14): ``phi`` is expressed in the frame
    ``Phi`` maps INTO (the world frame for ``Phi_IB``)."""
    return exp(phi) @ as_trailing(C, (3, 3), "C")


def boxminus(C1: np.ndarray, C2: np.ndarray) -> np.ndarray:
    """``Phi1 [-] Phi2 = log(Phi1 o Phi2^-1)`` (primer eq. 15), over broadcast leading dimensions."""
    C1, C2 = as_trailing(C1, (3, 3), "C1"), as_trailing(C2, (3, 3), "C2")
    lead = common_shape(C1.shape[:-2], C2.shape[:-2])
    out = np.empty((math.prod(lead), 3))
    _boxminus_rows(*rows(lead, (C1, C2), ((3, 3), (3, 3))), out)
    return out.reshape(lead + (3,))


def gamma(phi: np.ndarray) -> np.ndarray:
    """``Gamma(phi) = I + (1 - cos t)/t^2 phi^x + (t - sin t)/t^3 phi^x^2`` (primer eq. 33).

    The derivative of ``exp`` in the [+] sense (eq. 31): ``exp(phi + d) ~= exp(Gamma(phi) d) exp(phi)``.
    Equal to GTSAM's ``Rot3.ExpmapDerivative(-phi)`` (GTSAM's is the right Jacobian).
    """
    return _matrices(phi, _GAMMA)


def gamma_inv(phi: np.ndarray) -> np.ndarray:
    """``Gamma(phi)^-1 = I - phi^x / 2 + (1 - (t/2) cot(t/2)) / t^2 phi^x^2``.

    The derivative of ``log`` in the [+] sense (eq. 32): ``d log(Phi) / d Phi = Gamma^-1(log Phi)``.
    Valid for ``|phi| < 2 pi``; at ``|phi| = pi`` (where ``log`` lives at most) it is finite.
    """
    return _matrices(phi, _GAMMA_INV)


def project(M: np.ndarray) -> np.ndarray:
    """Nearest rotation matrix to ``M`` (in the Frobenius norm), via the SVD."""
    u, _, vt = np.linalg.svd(as_trailing(M, (3, 3), "M"))
    d = np.sign(np.linalg.det(u @ vt))
    u = u.copy()
    u[..., :, 2] *= d[..., None]
    return u @ vt
