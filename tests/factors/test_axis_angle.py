"""Axis-angle and the logarithm's special cases (angle 0, angle pi), checked against
factors.so3 (exp, and log, which is computed differently: through the quaternion)."""
import math

import numpy as np
import pytest

from factors import axis_angle, quaternion, so3


def unit(v):
    v = np.asarray(v, dtype=float)
    return v / np.linalg.norm(v, axis=-1, keepdims=True)


def random_axes(rng, n):
    return unit(rng.normal(size=(n, 3)))


def test_to_matrix_is_so3_exp_for_any_angle():
    rng = np.random.default_rng(1)
    n = random_axes(rng, 3000)
    angle = rng.uniform(-3 * np.pi, 3 * np.pi, 3000)
    np.testing.assert_allclose(axis_angle.to_matrix(n, angle), so3.exp(angle[:, None] * n), atol=2e-15)
    # Right-hand rule: a quarter turn about z takes x to y.
    np.testing.assert_allclose(axis_angle.to_matrix([0, 0, 1], np.pi / 2) @ [1, 0, 0], [0, 1, 0], atol=1e-15)


def test_log_agrees_with_so3_log_over_the_ball():
    rng = np.random.default_rng(2)
    n = random_axes(rng, 20000)
    angle = rng.uniform(0, np.pi, 20000)
    C = so3.exp(angle[:, None] * n)
    axis, got_angle = axis_angle.from_matrix(C)
    np.testing.assert_allclose(got_angle, angle, atol=2e-15)
    np.testing.assert_allclose(axis[angle > 1e-3], n[angle > 1e-3], atol=1e-12)
    np.testing.assert_allclose(axis_angle.log(C), so3.log(C), atol=2e-15)
    np.testing.assert_allclose(np.linalg.norm(axis, axis=-1), 1.0, atol=1e-15)
    np.testing.assert_allclose(axis_angle.to_matrix(axis, got_angle), C, atol=2e-15)


@pytest.mark.parametrize("angle", [1e-300, 1e-200, 1e-15, 1e-12, 1e-9, 1e-6, 1e-4, 1e-2])
def test_small_angles_keep_full_relative_precision(angle):
    """arccos((tr C - 1)/2) would give 0 below ~1e-8 and only half the digits above; the
    atan2 form keeps the angle and the axis."""
    rng = np.random.default_rng(3)
    n = random_axes(rng, 100)
    C = so3.exp(angle * n)
    axis, got = axis_angle.from_matrix(C)
    np.testing.assert_allclose(got, angle, rtol=1e-14)
    np.testing.assert_allclose(axis, n, atol=1e-14)
    np.testing.assert_allclose(axis_angle.log(C), so3.log(C), rtol=1e-14, atol=0)


def test_angle_zero_returns_the_documented_axis():
    axis, angle = axis_angle.from_matrix(np.eye(3))
    assert angle == 0.0
    np.testing.assert_array_equal(axis, axis_angle.DEFAULT_AXIS)
    np.testing.assert_array_equal(axis_angle.log(np.eye(3)), np.zeros(3))
    np.testing.assert_array_equal(axis_angle.to_matrix(axis, angle), np.eye(3))
    axis, angle = axis_angle.from_rotation_vector(np.zeros((2, 3)))
    np.testing.assert_array_equal(axis, [axis_angle.DEFAULT_AXIS] * 2)
    np.testing.assert_array_equal(angle, [0.0, 0.0])
    axis, angle = axis_angle.from_quaternion(quaternion.identity())
    assert angle == 0.0 and np.array_equal(axis, axis_angle.DEFAULT_AXIS)


def lecture_pi_axis(R, i):
    """The lecture's construction at angle pi: (I + R) e_i / sqrt(2 (1 + R_ii))."""
    return (np.eye(3) + R)[:, i] / np.sqrt(2 * (1 + R[i, i]))


def pi_axes():
    rng = np.random.default_rng(4)
    fixed = [[1, 0, 0], [0, 1, 0], [0, 0, 1], [1, 1, 0], [0, -1, 1], [1, 1, 1], [-1, 2, -3]]
    return np.concatenate([unit(np.array(fixed, dtype=float)), random_axes(rng, 500)])


def test_angle_pi_uses_the_column_construction_and_agrees_with_so3():
    n = pi_axes()
    C = so3.exp(np.pi * n)
    # At pi the skew part vanishes: C is symmetric to round-off, so the skew-part formula has nothing.
    assert np.abs(C - C.transpose(0, 2, 1)).max() < 1e-14
    axis, angle = axis_angle.from_matrix(C)
    np.testing.assert_allclose(angle, np.pi, atol=1e-15)
    # The axis is +-n ...
    sign = np.sign(np.sum(axis * n, axis=-1))
    np.testing.assert_allclose(axis, sign[:, None] * n, atol=1e-15)
    # ... it is the lecture's (I + R) e_i column for every i where that is defined ...
    for R, a, m in zip(C, axis, n):
        for i in range(3):
            if abs(m[i]) > 1e-3:
                col = lecture_pi_axis(R, i)
                np.testing.assert_allclose(a, np.sign(a @ col) * col, atol=1e-12)
    # ... it reproduces C, and so does so3.log's choice (both signs are logarithms at pi).
    np.testing.assert_allclose(axis_angle.to_matrix(axis, angle), C, atol=2e-15)
    ours, theirs = axis_angle.log(C), so3.log(C)
    same = np.minimum(np.abs(ours - theirs).max(-1), np.abs(ours + theirs).max(-1))
    np.testing.assert_allclose(same, 0.0, atol=5e-15)
    np.testing.assert_allclose(so3.exp(ours), so3.exp(theirs), atol=2e-15)


@pytest.mark.parametrize("gap", [1e-14, 1e-12, 1e-9, 1e-6, 1e-3, 0.5, np.pi / 2 - 1e-9, np.pi / 2 + 1e-9])
def test_near_pi_the_axis_keeps_its_sign_and_precision(gap):
    """Just below pi the axis is unique again: the column construction takes its sign from the
    skew part, so log is continuous up to pi and accurate to round-off (the skew-part formula
    alone would lose the axis as sin(angle) -> 0). Also the switch between the two branches at
    pi/2 is seamless."""
    n = pi_axes()
    angle = np.pi - gap
    C = so3.exp(angle * n)
    axis, got = axis_angle.from_matrix(C)
    np.testing.assert_allclose(axis, n, atol=2e-15 if gap > 1e-13 else 0.2)
    np.testing.assert_allclose(got, angle, atol=3e-15)
    np.testing.assert_allclose(axis_angle.log(C), so3.log(C), atol=4e-15)


def test_skew_part_alone_would_fail_near_pi():
    """Shows that the near-pi branch matters: the skew part's direction is off by ~eps/sin."""
    n = unit(np.array([1.0, -2.0, 0.7]))
    C = (so3.exp((np.pi - 1e-10) * n) @ so3.exp([0.3, 0.2, 0.1])) @ so3.exp([0.3, 0.2, 0.1]).T
    w = so3.vee(C)
    assert np.abs(unit(w) - n).max() > 1e-8
    axis, _ = axis_angle.from_matrix(C)
    assert np.abs(axis - n).max() < 1e-14


def test_rotation_vector_and_quaternion_forms():
    rng = np.random.default_rng(5)
    n = random_axes(rng, 1000)
    angle = rng.uniform(0, np.pi, 1000)
    phi = axis_angle.to_rotation_vector(n, angle)
    np.testing.assert_allclose(phi, angle[:, None] * n, atol=0)
    a2, t2 = axis_angle.from_rotation_vector(phi)
    np.testing.assert_allclose(a2, n, atol=1e-15)
    np.testing.assert_allclose(t2, angle, atol=1e-15)
    q = axis_angle.to_quaternion(n, angle)
    np.testing.assert_allclose(q, quaternion.exp(phi), atol=1e-15)
    np.testing.assert_allclose(quaternion.to_matrix(q), axis_angle.to_matrix(n, angle), atol=2e-15)
    a3, t3 = axis_angle.from_quaternion(q)
    np.testing.assert_allclose(t3, angle, atol=2e-15)
    np.testing.assert_allclose(a3[angle > 1e-6], n[angle > 1e-6], atol=1e-12)
    # q and -q: same axis-angle.
    a4, t4 = axis_angle.from_quaternion(-q)
    np.testing.assert_allclose(t4, t3, atol=0)
    np.testing.assert_allclose(a4, a3, atol=0)
    # Rotation vectors longer than pi are not wrapped by from_rotation_vector.
    _, t5 = axis_angle.from_rotation_vector([0.0, 0.0, 5.0])
    assert t5 == 5.0


def test_vectorised_and_scalar_inputs():
    rng = np.random.default_rng(6)
    n = random_axes(rng, 12).reshape(3, 4, 3)
    angle = rng.uniform(0, 3, (3, 4))
    C = axis_angle.to_matrix(n, angle)
    assert C.shape == (3, 4, 3, 3)
    axis, got = axis_angle.from_matrix(C)
    assert axis.shape == (3, 4, 3) and got.shape == (3, 4)
    np.testing.assert_allclose(C[2, 1], axis_angle.to_matrix(n[2, 1], angle[2, 1]))
    # one angle for many axes
    assert axis_angle.to_matrix(n, 0.5).shape == (3, 4, 3, 3)


@pytest.mark.parametrize("axis_shape, angle_shape, lead", [
    ((3,), (), ()), ((3, 3), (), (3,)), ((3,), (4,), (4,)), ((3, 3), (2, 1), (2, 3)), ((2, 1, 3), (4,), (2, 4)),
])
def test_axes_and_angles_broadcast_alike_in_every_form(axis_shape, angle_shape, lead):
    # to_quaternion broadcasts axes and angles as to_matrix and to_rotation_vector do, e.g.
    # (np.eye(3), 1.0): three axes, one angle.
    rng = np.random.default_rng(7)
    n = random_axes(rng, math.prod(axis_shape[:-1])).reshape(axis_shape)
    angle = rng.uniform(-4, 4, angle_shape)
    C, phi, q = (f(n, angle) for f in (axis_angle.to_matrix, axis_angle.to_rotation_vector, axis_angle.to_quaternion))
    assert (C.shape, phi.shape, q.shape) == (lead + (3, 3), lead + (3,), lead + (4,))
    n_b, angle_b = np.broadcast_to(n, lead + (3,)), np.broadcast_to(angle, lead)
    for i in np.ndindex(lead):
        assert np.array_equal(q[i], axis_angle.to_quaternion(n_b[i], angle_b[i]))
        assert np.array_equal(C[i], axis_angle.to_matrix(n_b[i], angle_b[i]))
        assert np.array_equal(phi[i], axis_angle.to_rotation_vector(n_b[i], angle_b[i]))


@pytest.mark.parametrize(
    "call, match",
    [
        (lambda: axis_angle.to_matrix([1.0, 1.0, 0.0], 0.1), "axis"),
        (lambda: axis_angle.to_matrix([1.0, 0.0], 0.1), "axis"),
        (lambda: axis_angle.to_matrix([np.nan, 0.0, 1.0], 0.1), "axis"),
        (lambda: axis_angle.to_matrix([1.0, 0.0, 0.0], np.nan), "angle"),
        (lambda: axis_angle.to_matrix(np.eye(3), np.zeros(2)), "angle"),
        (lambda: axis_angle.from_matrix(np.ones((3, 3))), "C"),
        (lambda: axis_angle.from_matrix(np.diag([1.0, 1.0, -1.0])), "C"),
        (lambda: axis_angle.from_matrix(np.zeros((2, 2))), "C"),
        (lambda: axis_angle.from_matrix([[np.inf, 0, 0], [0, 1, 0], [0, 0, 1]]), "C"),
        (lambda: axis_angle.from_rotation_vector([0.0, 1.0]), "phi"),
        (lambda: axis_angle.from_quaternion([1.0, 1.0, 0.0, 0.0]), "q"),
    ],
)
def test_bad_input_raises_value_error_naming_the_argument(call, match):
    with pytest.raises(ValueError, match=match):
        call()


def test_check_rotation_matrix_names_the_offending_matrix():
    C = np.stack([np.eye(3), np.eye(3), 1.01 * np.eye(3)])
    with pytest.raises(ValueError, match=r"R_stack.*index \(2,\)"):
        axis_angle.check_rotation_matrix(C, "R_stack")
