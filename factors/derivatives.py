"""Analytic derivatives of the primer's elementary maps (eqs. 26-32), in the [+]/[-] sense.

Each function returns the Jacobian of one map at the given point; arguments are vectorised over
leading dimensions like :mod:`factors.so3`. The derivation of each is the primer's (Appendix I)
and every one has a numerical twin in :mod:`factors.selfcheck`.
"""
from __future__ import annotations

import numpy as np

from factors import so3


def rotate_wrt_vector(C: np.ndarray) -> np.ndarray:
    """d Phi(r) / d r = C(Phi)  (eq. 26)."""
    return np.asarray(C, dtype=float)


def rotate_wrt_rotation(C: np.ndarray, r: np.ndarray) -> np.ndarray:
    """d Phi(r) / d Phi = -(Phi(r))^x  (eq. 27): exp(d) C r ~= C r + d x (C r)."""
    return -so3.skew(np.einsum("...ij,...j->...i", C, r))


def inverse_wrt_rotation(C: np.ndarray) -> np.ndarray:
    """d Phi^-1 / d Phi = -C(Phi)^T  (eq. 28)."""
    return -so3.inverse(C)


def compose_wrt_left(C1: np.ndarray) -> np.ndarray:
    """d (Phi1 o Phi2) / d Phi1 = I  (eq. 29)."""
    return np.broadcast_to(np.eye(3), np.shape(C1)).copy()


def compose_wrt_right(C1: np.ndarray) -> np.ndarray:
    """d (Phi1 o Phi2) / d Phi2 = C(Phi1)  (eq. 30)."""
    return np.asarray(C1, dtype=float)


def exp_wrt_vector(phi: np.ndarray) -> np.ndarray:
    """d exp(phi) / d phi = Gamma(phi)  (eq. 31)."""
    return so3.gamma(phi)


def log_wrt_rotation(C: np.ndarray) -> np.ndarray:
    """d log(Phi) / d Phi = Gamma^-1(log Phi)  (eq. 32)."""
    return so3.gamma_inv(so3.log(C))


def boxplus_wrt_rotation(C: np.ndarray, phi: np.ndarray) -> np.ndarray:
    """d (Phi [+] phi) / d Phi = C(exp(phi)): Phi is the RIGHT operand of exp(phi) o Phi, so
    eq. (30) applies (not eq. 29)."""
    return compose_wrt_right(so3.exp(phi))


def boxplus_wrt_vector(C: np.ndarray, phi: np.ndarray) -> np.ndarray:
    """d (Phi [+] phi) / d phi = Gamma(phi): eqs. (29), (31)."""
    return so3.gamma(phi)


def boxminus_wrt_left(C1: np.ndarray, C2: np.ndarray) -> np.ndarray:
    """d (Phi1 [-] Phi2) / d Phi1 = Gamma^-1(Phi1 [-] Phi2): eqs. (29), (32)."""
    return so3.gamma_inv(so3.boxminus(C1, C2))


def boxminus_wrt_right(C1: np.ndarray, C2: np.ndarray) -> np.ndarray:
    """d (Phi1 [-] Phi2) / d Phi2 = -Gamma^-1(Phi1 [-] Phi2) C(Phi1 o Phi2^-1):
    eqs. (28), (30), (32) on log(Phi1 o Phi2^-1)."""
    D = np.asarray(C1, dtype=float) @ so3.inverse(C2)
    return -so3.gamma_inv(so3.log(D)) @ D
