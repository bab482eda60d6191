"""smoother.model.blocks: a block's whitened residuals and Jacobians, robustly reweighted, with the
kernel's row scale the same numbers came from."""
from __future__ import annotations

import numpy as np

from factors import imu
from smoother.model.blocks import Block, evaluate_block, whitening
from smoother.model.robust import robust_estimator


def _block(robust=None) -> Block:
    """Three 3-dim factors on keyframe 0 whose residual is a fixed vector each (Jacobian: the
    position's identity), covariance diag(0.25, 1, 4)."""
    e = np.array([[0.1, 0.2, 0.3], [3.0, -1.0, 0.5], [-8.0, 2.0, 6.0]])

    def residual(slots, jacobians, rows):
        J = np.zeros((len(e[rows]), 3, imu.STATE_DIM))
        J[:, :, :3] = np.eye(3)
        return (e[rows], [J]) if jacobians else e[rows]

    cov = np.repeat(np.diag([0.25, 1.0, 4.0])[None], 3, axis=0)
    return Block("fixes", np.zeros((3, 1), dtype=int), residual, whitening(cov), robust)


def test_a_kernel_s_row_scale_is_the_square_root_of_its_weight_at_the_whitened_residual():
    states = imu.ImuState.identity(1)
    plain = evaluate_block(_block(), states, True)
    assert plain.scale is None
    cauchy = robust_estimator(("cauchy", 1.0), 3)
    ev = evaluate_block(_block(cauchy), states, True)
    size = np.linalg.norm(plain.e, axis=1)
    expected = np.sqrt([cauchy.weight(float(x)) for x in size])
    np.testing.assert_allclose(ev.scale[:, 0], expected, rtol=1e-15)
    assert expected[2] < 0.3 < expected[0] < 1.0  # the far factor weighs less
    np.testing.assert_allclose(ev.e, plain.e * expected[:, None], rtol=1e-15)
    np.testing.assert_allclose(ev.A[0], plain.A[0] * expected[:, None, None], rtol=1e-15)
