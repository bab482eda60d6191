"""A prior on a whole keyframe state in the primer's convention, and the Gaussian noise model.

:func:`state_residual` is ``x [-] x_prior`` over the error state ``(r, v, phi, b_f, b_w)`` (LEFT
boxplus for the attitude: ``log(C C_prior^T)``, whose Jacobian is ``Gamma^-1(e)``, eqs. 29, 32);
:func:`state_prior_factor` wraps it in a ``gtsam.CustomFactor`` through
:func:`factors.custom.custom_factor` (the chart adapter). The measurement models are in
:mod:`factors.sensor_models`.
"""
from __future__ import annotations

import gtsam
import numpy as np

from factors import so3
from factors.custom import BIAS, ROT, VEC, custom_factor


def covariance_model(cov: np.ndarray):
    """A Gaussian GTSAM noise model of covariance ``cov``."""
    return gtsam.noiseModel.Gaussian.Covariance(np.asarray(cov, dtype=float))


def _eye(shape: tuple, n: int = 3) -> np.ndarray:
    return np.broadcast_to(np.eye(n), shape + (n, n)).copy()


def state_residual(C, r, v, b, prior, jacobians: bool = False):
    """``e = x [-] x_prior`` over the whole state, in error-state order ``(r, v, phi, b_f, b_w)``;
    Jacobians for the variables ``(C, r, v, b)`` (the keyframe's Rot3, Point3, velocity, bias).
    Vectorised over broadcast leading dimensions (of the variables and of ``prior``'s arrays)."""
    b = np.asarray(b, dtype=float)
    e_phi = so3.boxminus(C, prior.C)
    parts = [np.asarray(r) - prior.r, np.asarray(v) - prior.v, e_phi,
             b[..., :3] - prior.b_f, b[..., 3:] - prior.b_w]
    if any(part.shape != e_phi.shape for part in parts):
        parts = np.broadcast_arrays(*parts)
    e = np.concatenate(parts, axis=-1)
    if not jacobians:
        return e
    shape = e.shape[:-1]
    J_C, J_r, J_v, J_b = (np.zeros(shape + (15, n)) for n in (3, 3, 3, 6))
    J_r[..., 0:3, :] = _eye(shape)
    J_v[..., 3:6, :] = _eye(shape)
    J_C[..., 6:9, :] = so3.gamma_inv(e_phi)
    J_b[..., 9:15, :] = _eye(shape, 6)
    return e, [J_C, J_r, J_v, J_b]


def state_prior_factor(keys, prior, cov, noise_model=None) -> gtsam.CustomFactor:
    """A joint prior on a keyframe ``keys`` (:class:`factors.keys.KeyframeKeys`) from an
    :class:`factors.imu.ImuState` and its 15x15 covariance (error-state order)."""
    model = noise_model if noise_model is not None else covariance_model(cov)
    return custom_factor(
        model, keys.all(), [ROT, VEC, VEC, BIAS],
        lambda C, r, v, b, jacobians: state_residual(C, r, v, b, prior, jacobians),
    )
