"""The one adapter between the primer's orientation chart and GTSAM's.

The primer perturbs an orientation on the LEFT, ``Phi [+] phi = exp(phi) o Phi`` (``phi`` in the
frame ``Phi`` maps into). GTSAM's ``Rot3.retract(d) = R Exp(d)`` perturbs on the RIGHT (``d`` in
the body frame). By the adjoint identity (primer eq. 24), ``exp(phi) o Phi = Phi o exp(C(Phi)^T phi)``,
so a GTSAM increment ``d`` is the primer increment ``phi = C(Phi) d`` (:func:`primer_from_gtsam`).
Hence a Jacobian ``J`` taken with respect to the primer increment becomes ``J @ C(Phi)`` with
respect to GTSAM's (:func:`to_gtsam_chart`), and a covariance of GTSAM's increment becomes
``C Sigma C^T`` in the primer's (:mod:`factors.uncertainty`, which builds on this module:
``covariance_right_to_left``, ``state_covariance_to_primer``). Jacobians and covariances of
vectors (positions, velocities, biases) are unchanged.
"""
from __future__ import annotations

import numpy as np


def _matrix(rotation) -> np.ndarray:
    return np.asarray(rotation.matrix() if hasattr(rotation, "matrix") else rotation, dtype=float)


def primer_from_gtsam(rotation) -> np.ndarray:
    """The linear map ``d -> phi = C d`` from GTSAM's right increment of ``rotation`` to the
    primer's left increment (exact, not a first-order relation)."""
    return _matrix(rotation)


def to_gtsam_chart(jacobian: np.ndarray, rotation) -> np.ndarray:
    """Turn ``d f / d phi`` (primer, left increment of ``rotation``) into ``d f / d d`` (GTSAM,
    right increment): ``jacobian @ C``. ``rotation`` is the 3x3 matrix ``C(Phi)`` (or a
    ``gtsam.Rot3``); both arguments may carry matching leading dimensions."""
    return np.asarray(jacobian, dtype=float) @ primer_from_gtsam(rotation)

