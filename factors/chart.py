"""The one adapter between the primer's orientation chart and GTSAM's.

The primer perturbs an orientation on the LEFT, ``Phi [+] phi = exp(phi) o Phi`` (``phi`` in the
frame ``Phi`` maps into). GTSAM's ``Rot3.retract(d) = R Exp(d)`` perturbs on the RIGHT (``d`` in
the body frame). By the adjoint identity (primer eq. 24), ``exp(phi) o Phi = Phi o exp(C(Phi)^T phi)``,
so a GTSAM increment ``d`` is the primer increment ``phi = C(Phi) d``. A Jacobian ``J`` taken with
respect to the primer increment therefore becomes, by the chain rule, ``J @ C(Phi)`` with respect
to GTSAM's. Jacobians with respect to vectors (positions, velocities, biases) are unchanged.
"""
from __future__ import annotations

import numpy as np


def to_gtsam_chart(jacobian: np.ndarray, rotation: np.ndarray) -> np.ndarray:
    """Turn ``d f / d phi`` (primer, left increment of ``rotation``) into ``d f / d d`` (GTSAM,
    right increment): ``jacobian @ C``. ``rotation`` is the 3x3 matrix ``C(Phi)`` (or a
    ``gtsam.Rot3``); both arguments may carry matching leading dimensions."""
    C = rotation.matrix() if hasattr(rotation, "matrix") else rotation
    return np.asarray(jacobian, dtype=float) @ np.asarray(C, dtype=float)


def state_covariance_to_primer(cov_rpvb: np.ndarray, rotation: np.ndarray) -> np.ndarray:
    """A keyframe's joint covariance from GTSAM -- variables ``(Rot3, Point3, velocity, bias)`` in
    that order, the ``Rot3`` block in GTSAM's right chart -- as the primer's 15x15 error-state
    covariance ``(dr, dv, dphi, db_f, db_w)`` with the LEFT attitude increment ``dphi = C d``."""
    C = rotation.matrix() if hasattr(rotation, "matrix") else np.asarray(rotation, dtype=float)
    T = np.zeros((15, 15))
    T[6:9, 0:3] = C  # dphi <- C d_rot
    T[0:3, 3:6] = np.eye(3)  # dr <- d_pos
    T[3:6, 6:9] = np.eye(3)  # dv <- d_vel
    T[9:15, 9:15] = np.eye(6)  # (db_f, db_w) <- d_bias
    out = T @ np.asarray(cov_rpvb, dtype=float) @ T.T
    return 0.5 * (out + out.T)
