"""Per-sensor consistency through a smoother: each factor block's own normalised residuals.

The EKF judges a sensor by its innovations (:mod:`smoother.diagnosis.verdicts`); a smoother by its
residuals at its own estimate. A measurement's residual ``e = h(x^) - z`` at an estimate
conditioned on data that include ``z`` has, to first order, the covariance ``R - J P J^T``
(``R`` the measurement's covariance, ``J`` the residual's Jacobian with respect to the variables
the factor reads, ``P`` their joint posterior covariance): smaller than the innovation's, by the
factor's *leverage* ``h = tr(R^-1 J P J^T)``, between 0 (the other data determine the state) and
``d`` (this measurement alone does). With ``W`` the whitening of ``R`` and ``A = W J``::

    E |W e|^2 = d - h,        h = tr(A P A^T)

so over a sensor's rows ``sum |W e|^2 / sum (d_i - h_i)`` is 1 for a sensor whose model fits, and
the sum is approximately chi-square with ``sum (d_i - h_i)`` degrees of freedom, which gives its
band (:data:`smoother.diagnosis.verdicts.BAND_PROBABILITY`). The leverages of all factors add up to the
number of estimated variables: the residuals of a least-squares fit have ``m - n`` degrees of
freedom.

A factor on one keyframe needs that keyframe's marginal covariance; one on two keyframes (the IMU
factors, odometry) the joint covariance of both (the batch smoother's
:attr:`smoother.batch.solve.SmootherResult.joint`). The IMU block's figure is the IMU's own verdict:
its residuals out of band point at the IMU (units, saturation, noise densities), not at the
sensors beside it.
"""
from __future__ import annotations

import numpy as np

from smoother.diagnosis.verdicts import verdict
from smoother.model.blocks import Block, evaluated_chunks
from smoother.model.covariances import hat_blocks

#: Blocks with no verdict of their own (the prior on the first keyframe is not a sensor).
NOT_JUDGED = ("prior",)


def block_consistency(block: Block, states, cov: np.ndarray, joint: dict | None = None,
                      calibration=None) -> dict | None:
    """The verdict (:func:`smoother.diagnosis.verdicts.verdict`) of one block's residuals at ``states``
    (one per keyframe), with the keyframes' marginal covariances ``cov (n, 15, 15)`` and, for
    factors on two keyframes, ``joint`` (``{(a, b): Sigma_ab}``, :func:`smoother.model.covariances.joint_block`);
    None where those are missing.
    The residuals are whitened, not robustly reweighted: a robust kernel's outliers count, as
    they are in the data. A block that reads a calibration variable (``calibration``'s values;
    key ``n + j`` of ``joint``) counts that variable's share of the leverage too."""
    kf = block.keyframes
    if (kf.shape[1] == 2 or block.calibration is not None) and joint is None:
        return None
    total, dof = 0.0, 0.0
    for rows, ev in evaluated_chunks(block, states, True, calibration, reweight=False):
        chunk, e_w, A = kf[rows], ev.e, ev.A
        if not np.isfinite(e_w).all():
            return None
        key = None if block.calibration is None else len(states) + block.calibration
        lev = np.trace(hat_blocks(A, chunk, key, cov, joint), axis1=1, axis2=2)
        d = e_w.shape[1]
        total += float(np.sum(e_w * e_w))
        dof += float(np.sum(np.clip(d - lev, 0.0, d)))
    if not dof > 0.0:
        return None
    return verdict(total, dof, len(kf), "residual")


def smoother_consistency(blocks: list[Block], states, cov: np.ndarray | None, joint: dict | None = None,
                         calibration=None) -> dict:
    """:func:`block_consistency` of every block but :data:`NOT_JUDGED` and the calibrations'
    priors (blocks on no keyframe), by block name (a sensor's name; ``"imu"`` for the IMU
    factors); blocks without the covariances they need are left out."""
    if cov is None:
        return {}
    out = {}
    for block in blocks:
        if block.name in NOT_JUDGED or len(block) == 0 or block.keyframes.shape[1] == 0:
            continue
        c = block_consistency(block, states, cov, joint, calibration)
        if c is not None:
            out[block.name] = c
    return out
