"""factors.rows: how the compiled kernels see arrays (flattened leading dimensions, checked
trailing shapes), and that the public vectorised functions built on it broadcast like NumPy."""
from __future__ import annotations

import numpy as np
import pytest

from factors import imu, preintegration, so3
from factors.rows import as_trailing, common_shape, rows


def test_rows_broadcasts_flattens_and_keeps_views_when_it_can():
    a = np.arange(2 * 4 * 3, dtype=float).reshape(2, 4, 3)
    b = np.array([1.0, 2.0, 3.0])
    ra, rb = rows((2, 4), (a, b), ((3,), (3,)))
    assert ra.shape == (8, 3) and rb.shape == (8, 3)
    assert np.shares_memory(ra, a)  # already in shape: a view, no copy
    np.testing.assert_array_equal(rb, np.broadcast_to(b, (8, 3)))
    (rc,) = rows((), (np.asfortranarray(np.eye(3)),), ((3, 3),))
    assert rc.shape == (1, 3, 3) and rc.flags.c_contiguous
    (ri,) = rows((2,), ([[1, 2, 3], [4, 5, 6]],), ((3,),))
    assert ri.dtype == np.float64


def test_common_shape():
    assert common_shape((4,), (4,), (4,)) == (4,)
    assert common_shape((4,), (), (1,)) == (4,)
    with pytest.raises(ValueError):
        common_shape((4,), (3,))


@pytest.mark.parametrize("bad", [np.zeros(4), np.zeros((2, 2)), np.zeros(())])
def test_wrong_trailing_shapes_are_refused_before_any_kernel_runs(bad):
    with pytest.raises(ValueError, match=r"phi: expected shape \(\.\.\., 3\)"):
        so3.exp(bad)
    with pytest.raises(ValueError, match="C: expected shape"):
        so3.log(bad)
    with pytest.raises(ValueError, match="x: expected"):
        as_trailing(bad, (3,), "x")
    with pytest.raises(ValueError, match="C2: expected shape"):
        so3.boxminus(np.eye(3), bad)


def test_kernels_keep_leading_dimensions_and_accept_empty_batches():
    phi = np.random.default_rng(0).normal(size=(2, 3, 3))
    assert so3.exp(phi).shape == (2, 3, 3, 3)
    assert so3.log(so3.exp(phi)).shape == (2, 3, 3)
    assert so3.gamma(np.zeros((0, 3))).shape == (0, 3, 3)


def test_residual_broadcasts_one_interval_against_many_states():
    rng = np.random.default_rng(1)
    K = 7
    acc, gyro, dt = rng.normal(size=(1, K, 3)), rng.normal(size=(1, K, 3)), np.full((1, K), 0.01)
    pre = preintegration.integrate(acc, gyro, dt, np.zeros((1, 3)))[0]
    states = imu.ImuState(rng.normal(size=(5, 3)), rng.normal(size=(5, 3)), so3.exp(rng.normal(size=(5, 3))),
                          np.zeros((5, 3)), rng.normal(size=(5, 3)) * 1e-3)
    e, (Ji, Jj) = preintegration.residual(pre, states, states[::-1], jacobians=True)
    assert e.shape == (5, 15) and Ji.shape == (5, 15, 15)
    for k in range(5):
        ek, (Jik, Jjk) = preintegration.residual(pre, states[k], states[4 - k], jacobians=True)
        np.testing.assert_array_equal(e[k], ek)
        np.testing.assert_array_equal(Ji[k], Jik)
        np.testing.assert_array_equal(Jj[k], Jjk)


def test_residual_one_equals_the_vectorised_residual_and_checks_its_inputs():
    """The factor callback's direct path (:func:`preintegration.residual_one`, variables as GTSAM
    hands them over) runs the same kernel as the vectorised residual: identical numbers."""
    rng = np.random.default_rng(2)
    K = 9
    acc, gyro, dt = rng.normal(size=(1, K, 3)), rng.normal(size=(1, K, 3)), np.full((1, K), 0.01)
    pre = preintegration.integrate(acc, gyro, dt, np.full((1, 3), 0.01))[0]
    states = imu.ImuState(rng.normal(size=(2, 3)), rng.normal(size=(2, 3)), so3.exp(rng.normal(size=(2, 3))),
                          rng.normal(size=(2, 3)) * 0.1, rng.normal(size=(2, 3)) * 1e-2)
    g = imu.DEFAULT_GRAVITY

    def variables(x):
        return [x.C, x.r, x.v, np.concatenate([x.b_f, x.b_w])]

    e, (Ji, Jj) = preintegration.residual(pre, states[0], states[1], g, jacobians=True)
    e1, (Ji1, Jj1) = preintegration.residual_one(pre, *variables(states[0]), *variables(states[1]), g, True)
    np.testing.assert_array_equal(e1, e)
    np.testing.assert_array_equal(Ji1, Ji)
    np.testing.assert_array_equal(Jj1, Jj)
    np.testing.assert_array_equal(preintegration.residual_one(pre, *variables(states[0]), *variables(states[1]), g), e)
    bad = variables(states[1])
    bad[3] = bad[3][:3]  # a 3-vector where the bias 6-vector belongs
    with pytest.raises(ValueError, match="expected float arrays"):
        preintegration.residual_one(pre, *variables(states[0]), *bad, g)
    with pytest.raises(ValueError, match="one interval"):
        preintegration.residual_one(preintegration.integrate(acc, gyro, dt, np.zeros((1, 3))),
                                    *variables(states[0]), *variables(states[1]), g)
