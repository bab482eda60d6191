"""Calculus on SO(3) in the primer's convention, on rotation matrices.

Conventions (DESIGN.md section 1, Bloesch et al., "A Primer on the Differential Calculus of
3D Orientations"):

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
"""
from __future__ import annotations

import numpy as np

from factors import quaternion

#: Below this angle (rad) the coefficients that cancel are evaluated by their Taylor series.
SERIES_ANGLE = 1e-2


def skew(v: np.ndarray) -> np.ndarray:
    """Skew-symmetric matrix ``v^x`` with ``v^x r = v x r`` (primer section II)."""
    v = np.asarray(v, dtype=float)
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
    m = np.asarray(m, dtype=float)
    return 0.5 * np.stack(
        [m[..., 2, 1] - m[..., 1, 2], m[..., 0, 2] - m[..., 2, 0], m[..., 1, 0] - m[..., 0, 1]],
        axis=-1,
    )


def _angle(phi: np.ndarray) -> np.ndarray:
    return np.linalg.norm(phi, axis=-1)


def _sinc(t: np.ndarray) -> np.ndarray:
    """sin(t)/t, exact at 0 (numpy's sinc is normalised by pi)."""
    return np.sinc(t / np.pi)


def _series_or(t: np.ndarray, closed, coefficients) -> np.ndarray:
    """Evaluate ``closed(t)`` where ``t >= SERIES_ANGLE`` and the even power series
    ``c0 + c1 t^2 + c2 t^4 + ...`` below it."""
    t = np.asarray(t, dtype=float)
    small = t < SERIES_ANGLE
    t_safe = np.where(small, 1.0, t)
    t2 = t * t
    series = np.zeros_like(t)
    for c in reversed(coefficients):
        series = series * t2 + c
    return np.where(small, series, closed(t_safe))


def _one_minus_cos_over_t2(t: np.ndarray) -> np.ndarray:
    """(1 - cos t) / t^2 = sinc(t/2)^2 / 2, no cancellation at any angle."""
    return 0.5 * _sinc(0.5 * t) ** 2


def _t_minus_sin_over_t3(t: np.ndarray) -> np.ndarray:
    """(t - sin t) / t^3."""
    return _series_or(
        t, lambda s: (s - np.sin(s)) / s**3, (1 / 6, -1 / 120, 1 / 5040, -1 / 362880)
    )


def _gamma_inv_coefficient(t: np.ndarray) -> np.ndarray:
    """(1 - (t/2) cot(t/2)) / t^2, the phi^x^2 coefficient of gamma_inv; finite up to t = pi."""
    return _series_or(
        t,
        lambda s: (1.0 - 0.5 * s * np.cos(0.5 * s) / np.sin(0.5 * s)) / s**2,
        (1 / 12, 1 / 720, 1 / 30240, 1 / 1209600),
    )


def exp(phi: np.ndarray) -> np.ndarray:
    """Rotation matrix ``C(exp(phi))`` by Rodrigues' formula (primer eq. 21)."""
    phi = np.asarray(phi, dtype=float)
    t = _angle(phi)[..., None, None]
    k = skew(phi)
    return np.eye(3) + _sinc(t) * k + _one_minus_cos_over_t2(t) * (k @ k)


def log(C: np.ndarray) -> np.ndarray:
    """Rotation vector ``phi`` with ``exp(phi) = C`` and ``|phi| <= pi``.

    Goes through the unit quaternion of ``C`` (Shepperd's method) and ``2 atan2(|q_v|, q_0)``,
    so it keeps full precision near 0 and near pi, where the textbook
    ``arccos((tr C - 1) / 2)`` loses half the digits and ``1 / sin`` blows up.
    """
    return quaternion.log(quaternion.from_matrix(C))


def compose(C1: np.ndarray, C2: np.ndarray) -> np.ndarray:
    """``C(Phi1 o Phi2) = C1 C2`` (primer eq. 5)."""
    return np.asarray(C1, dtype=float) @ np.asarray(C2, dtype=float)


def inverse(C: np.ndarray) -> np.ndarray:
    """``C(Phi^-1) = C^T``."""
    return np.swapaxes(np.asarray(C, dtype=float), -1, -2)


def boxplus(C: np.ndarray, phi: np.ndarray) -> np.ndarray:
    """``Phi [+] phi = exp(phi) o Phi`` (primer eq. 14): ``phi`` is expressed in the frame
    ``Phi`` maps INTO (the world frame for ``Phi_IB``)."""
    return exp(phi) @ np.asarray(C, dtype=float)


def boxminus(C1: np.ndarray, C2: np.ndarray) -> np.ndarray:
    """``Phi1 [-] Phi2 = log(Phi1 o Phi2^-1)`` (primer eq. 15)."""
    return log(np.asarray(C1, dtype=float) @ inverse(C2))


def gamma(phi: np.ndarray) -> np.ndarray:
    """``Gamma(phi) = I + (1 - cos t)/t^2 phi^x + (t - sin t)/t^3 phi^x^2`` (primer eq. 33).

    The derivative of ``exp`` in the [+] sense (eq. 31): ``exp(phi + d) ~= exp(Gamma(phi) d) exp(phi)``.
    Equal to GTSAM's ``Rot3.ExpmapDerivative(-phi)`` (GTSAM's is the right Jacobian).
    """
    phi = np.asarray(phi, dtype=float)
    t = _angle(phi)[..., None, None]
    k = skew(phi)
    return np.eye(3) + _one_minus_cos_over_t2(t) * k + _t_minus_sin_over_t3(t) * (k @ k)


def gamma_inv(phi: np.ndarray) -> np.ndarray:
    """``Gamma(phi)^-1 = I - phi^x / 2 + (1 - (t/2) cot(t/2)) / t^2 phi^x^2``.

    The derivative of ``log`` in the [+] sense (eq. 32): ``d log(Phi) / d Phi = Gamma^-1(log Phi)``.
    Valid for ``|phi| < 2 pi``; at ``|phi| = pi`` (where ``log`` lives at most) it is finite.
    """
    phi = np.asarray(phi, dtype=float)
    t = _angle(phi)[..., None, None]
    k = skew(phi)
    return np.eye(3) - 0.5 * k + _gamma_inv_coefficient(t) * (k @ k)


def project(M: np.ndarray) -> np.ndarray:
    """Nearest rotation matrix to ``M`` (in the Frobenius norm), via the SVD."""
    u, _, vt = np.linalg.svd(np.asarray(M, dtype=float))
    d = np.sign(np.linalg.det(u @ vt))
    u = u.copy()
    u[..., :, 2] *= d[..., None]
    return u @ vt
