"""Measurement residuals in the primer's convention, and the GTSAM factors built on them.

Each ``*_residual`` function returns the error and, with ``jacobians=True``, its Jacobians with
respect to the primer's increments of each variable (LEFT boxplus for attitudes). The EKF
(``smoother.ekf``) linearises the same functions, and each ``*_factor`` wraps one in a
``gtsam.CustomFactor`` through :func:`factors.custom.custom_factor` (the chart adapter). Any GTSAM
noise model is accepted, robust ones included; ``covariance_model`` makes the Gaussian one.

Noise conventions (primer eqs. 61-63): ``r_meas = r + n_p``; ``C_meas = exp(n_Phi) C`` with
``n_Phi`` in WORLD coordinates; so ``C [-] C_meas = log(C C_meas^T) = -n_Phi`` has covariance
``cov(n_Phi)``. Relative poses carry their noise in the body frame of the earlier keyframe.

Derivatives used (eqs. 27-32): ``d log(C C_m^T)/d phi = Gamma^-1(e)`` (eqs. 29, 32);
``d C_i^T x / d phi_i = (C_i^T x)^x C_i^T`` (eqs. 27, 28, 3); ``log(C_i^T C_j D^T)`` moves by
``-Gamma^-1(e) C_i^T`` for ``phi_i`` and ``Gamma^-1(e) C_i^T`` for ``phi_j`` (eq. 24).
"""
from __future__ import annotations

import math

import gtsam
import numpy as np
from numba import njit

from factors import so3
from factors.compiled import as_trailing, common_shape, rows
from factors.custom import BIAS, ROT, VEC, custom_factor
from factors.sensor_models import odometry_residual, orientation_error_into

def covariance_model(cov: np.ndarray):
    """A Gaussian GTSAM noise model of covariance ``cov``."""
    return gtsam.noiseModel.Gaussian.Covariance(np.asarray(cov, dtype=float))


def _eye(shape: tuple, n: int = 3) -> np.ndarray:
    return np.broadcast_to(np.eye(n), shape + (n, n)).copy()


def position_residual(r, measured, jacobians: bool = False):
    """``e = r - r_meas`` (eq. 61); ``de/dr = I``."""
    e = np.asarray(r, dtype=float) - measured
    return (e, [_eye(e.shape[:-1])]) if jacobians else e


@njit(cache=True)
def _orientation_rows(C, measured, e, J):
    for n in range(C.shape[0]):
        orientation_error_into(C[n], measured[n], e[n], J[n])


def _orientation_errors(C, measured):
    """``(e, Gamma^-1(e))`` of :func:`orientation_error_into` over broadcast leading dimensions."""
    C, measured = as_trailing(C, (3, 3), "C"), as_trailing(measured, (3, 3), "measured C")
    lead = common_shape(C.shape[:-2], measured.shape[:-2])
    n = math.prod(lead)
    e, J = np.empty((n, 3)), np.empty((n, 3, 3))
    _orientation_rows(*rows(lead, (C, measured), ((3, 3), (3, 3))), e, J)
    return e.reshape(lead + (3,)), J.reshape(lead + (3, 3))


def orientation_residual(C, measured, jacobians: bool = False):
    """``e = C [-] C_meas = log(C C_meas^T)`` (eqs. 62, 63); ``de/dphi = Gamma^-1(e)``."""
    e, J = _orientation_errors(C, measured)
    return (e, [J]) if jacobians else e


def pose_residual(r, C, measured_r, measured_C, jacobians: bool = False):
    """``e = (r - r_meas, C [-] C_meas)`` (eqs. 61-63); Jacobians for ``(r, C)``. Vectorised over
    broadcast leading dimensions; one pose (a factor's callback, the EKF's update) takes a
    shorter way to the same compiled core (:func:`orientation_error_into`)."""
    if (np.shape(r), np.shape(C), np.shape(measured_r), np.shape(measured_C)) == ((3,), (3, 3), (3,), (3, 3)):
        return _one_pose_residual(r, C, measured_r, measured_C, jacobians)
    e_r = np.asarray(r, dtype=float) - measured_r
    e_phi, J_phi = _orientation_errors(C, measured_C)
    e_r, e_phi = np.broadcast_arrays(e_r, e_phi)
    e = np.concatenate([e_r, e_phi], axis=-1)
    if not jacobians:
        return e
    shape = e.shape[:-1]
    J_r = np.zeros(shape + (6, 3))
    J_r[..., :3, :] = _eye(shape)
    J_C = np.zeros(shape + (6, 3))
    J_C[..., 3:, :] = J_phi
    return e, [J_r, J_C]


def _one_pose_residual(r, C, measured_r, measured_C, jacobians: bool):
    """:func:`pose_residual` of one pose without the broadcasting plumbing, which cost several
    times the mathematics in each factor callback (34 -> 8 us)."""
    e, J = np.empty(6), np.zeros((2, 6, 3))
    e[:3] = np.asarray(r, dtype=float) - measured_r
    orientation_error_into(np.asarray(C, dtype=float), np.asarray(measured_C, dtype=float), e[3:], J[1, 3:])
    J[0, 0, 0] = J[0, 1, 1] = J[0, 2, 2] = 1.0
    return (e, [J[0], J[1]]) if jacobians else e


def relative_pose_residual(C_i, r_i, C_j, r_j, measured_dr, measured_dC, jacobians: bool = False):
    """``e = (C_i^T (r_j - r_i) - dr_meas, log(C_i^T C_j dC_meas^T))`` in body frame ``i``;
    Jacobians for ``(C_i, r_i, C_j, r_j)``. Vectorised over broadcast leading dimensions. The
    IMU-centred case of :func:`factors.sensor_models.odometry_residual`."""
    return odometry_residual(C_i, r_i, C_j, r_j, measured_dr, measured_dC, None, jacobians)


def velocity_residual(v, measured, jacobians: bool = False):
    """``e = B_v - v_meas`` (body-frame velocity, e.g. a zero-velocity update); ``de/dv = I``."""
    e = np.asarray(v, dtype=float) - measured
    return (e, [_eye(e.shape[:-1])]) if jacobians else e


def bias_residual(b, measured, jacobians: bool = False):
    """``e = (b_f, b_w) - prior``; ``de/db = I_6``."""
    e = np.asarray(b, dtype=float) - measured
    return (e, [_eye(e.shape[:-1], 6)]) if jacobians else e


def position_factor(key: int, measured, noise_model) -> gtsam.CustomFactor:
    """Position (GPS) or position prior on a ``Point3`` key."""
    m = np.array(measured, dtype=float)
    return custom_factor(noise_model, [key], [VEC], lambda r, jacobians: position_residual(r, m, jacobians))


def orientation_factor(key: int, measured_C, noise_model) -> gtsam.CustomFactor:
    """Attitude measurement or prior on a ``Rot3`` key."""
    m = np.array(measured_C, dtype=float)
    return custom_factor(noise_model, [key], [ROT], lambda C, jacobians: orientation_residual(C, m, jacobians))


def pose_factor(pos_key: int, rot_key: int, measured_r, measured_C, noise_model) -> gtsam.CustomFactor:
    """Pose-sensor measurement (position first, then attitude, 6x6 noise)."""
    mr, mC = np.array(measured_r, dtype=float), np.array(measured_C, dtype=float)
    return custom_factor(
        noise_model, [pos_key, rot_key], [VEC, ROT],
        lambda r, C, jacobians: pose_residual(r, C, mr, mC, jacobians),
    )


def relative_pose_factor(rot_i: int, pos_i: int, rot_j: int, pos_j: int, measured_dr, measured_dC,
                         noise_model) -> gtsam.CustomFactor:
    """Odometry between two keyframes (noise in body frame ``i``, position first)."""
    mr, mC = np.array(measured_dr, dtype=float), np.array(measured_dC, dtype=float)
    return custom_factor(
        noise_model, [rot_i, pos_i, rot_j, pos_j], [ROT, VEC, ROT, VEC],
        lambda Ci, ri, Cj, rj, jacobians: relative_pose_residual(Ci, ri, Cj, rj, mr, mC, jacobians),
    )


def velocity_factor(key: int, measured_v, noise_model) -> gtsam.CustomFactor:
    """Body-frame velocity measurement or prior (zero-velocity update with ``measured_v = 0``)."""
    m = np.array(measured_v, dtype=float)
    return custom_factor(noise_model, [key], [VEC], lambda v, jacobians: velocity_residual(v, m, jacobians))


def bias_factor(key: int, measured_bias, noise_model) -> gtsam.CustomFactor:
    """Prior on an ``imuBias.ConstantBias`` key, ``measured_bias = (b_f, b_w)``."""
    m = np.array(measured_bias, dtype=float)
    return custom_factor(noise_model, [key], [BIAS], lambda b, jacobians: bias_residual(b, m, jacobians))


def state_residual(C, r, v, b, prior, jacobians: bool = False):
    """``e = x [-] x_prior`` over the whole state, in error-state order ``(r, v, phi, b_f, b_w)``;
    Jacobians for the variables ``(C, r, v, b)`` (the keyframe's Rot3, Point3, velocity, bias).
    Vectorised over broadcast leading dimensions (of the variables and of ``prior``'s arrays)."""
    b = np.asarray(b, dtype=float)
    e_phi = so3.boxminus(C, prior.C)
    parts = [np.asarray(r) - prior.r, np.asarray(v) - prior.v, e_phi,
             b[..., :3] - prior.b_f, b[..., 3:] - prior.b_w]
    if any(part.shape != e_phi.shape for part in parts):  # as in relative_pose_residual
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
