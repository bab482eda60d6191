"""The 24 Euler-angle conventions: definitions, round trips, singular cases, SciPy as an
independent reference (test-only), the project's roll-pitch-yaw against GTSAM, and the Jacobian
of the angles against central differences."""
import math

import gtsam
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.spatial.transform import Rotation
from strategies import EPS

from factors import euler, quaternion, so3

TAU = 2 * np.pi


# The lecture's principal rotations, written out here so the tests do not rely on euler.elementary.
def Rx(t):
    c, s = np.cos(t), np.sin(t)
    return np.array([[1, 0, 0], [0, c, -s], [0, s, c]])


def Ry(t):
    c, s = np.cos(t), np.sin(t)
    return np.array([[c, 0, s], [0, 1, 0], [-s, 0, c]])


def Rz(t):
    c, s = np.cos(t), np.sin(t)
    return np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]])


R_OF = {"x": Rx, "y": Ry, "z": Rz}


def wrap(a):
    """Angle difference wrapped to (-pi, pi]."""
    return -np.remainder(-np.asarray(a) + np.pi, TAU) + np.pi


def random_angles(rng, n):
    return rng.uniform(-np.pi, np.pi, size=(n, 3))


def in_canonical_range(angles, convention):
    """Angles that from_matrix returns unchanged: middle angle inside its range, away from the
    singular ends, first/third strictly inside (-pi, pi)."""
    b = angles[:, 1]
    if euler.is_proper_euler(convention):
        ok = (b > 1e-3) & (b < np.pi - 1e-3)
    else:
        ok = np.abs(b) < np.pi / 2 - 1e-3
    return ok & (np.abs(angles[:, 0]) < np.pi - 1e-9) & (np.abs(angles[:, 2]) < np.pi - 1e-9)


def canonical_angles(rng, n, convention):
    a = random_angles(rng, n)
    if euler.is_proper_euler(convention):
        a[:, 1] = rng.uniform(0.01, np.pi - 0.01, n)
    else:
        a[:, 1] = rng.uniform(-np.pi / 2 + 0.01, np.pi / 2 - 0.01, n)
    return a


def test_there_are_24_conventions_named_as_in_the_lecture():
    assert len(euler.CONVENTIONS) == 24 == len(set(euler.CONVENTIONS))
    for name in ("sxyz", "rzyx", "rzxz", "szyz", "ryxy", "sxzy"):
        assert name in euler.CONVENTIONS
    proper = [c for c in euler.CONVENTIONS if euler.is_proper_euler(c)]
    assert len(proper) == 12 and all(c[1] == c[3] for c in proper)
    tait = [c for c in euler.CONVENTIONS if not euler.is_proper_euler(c)]
    assert len(tait) == 12 and all(len(set(c[1:])) == 3 for c in tait)
    assert sum(c[0] == "r" for c in euler.CONVENTIONS) == 12


@pytest.mark.parametrize("convention", euler.CONVENTIONS)
def test_to_matrix_is_the_product_of_principal_rotations(convention):
    rng = np.random.default_rng(1)
    angles = random_angles(rng, 5)
    i, j, k = convention[1:]
    got = euler.to_matrix(angles, convention)
    for a, C in zip(angles, got):
        if convention[0] == "r":  # moving axes: first rotation leftmost
            want = R_OF[i](a[0]) @ R_OF[j](a[1]) @ R_OF[k](a[2])
        else:  # fixed axes: first rotation rightmost
            want = R_OF[k](a[2]) @ R_OF[j](a[1]) @ R_OF[i](a[0])
        np.testing.assert_allclose(C, want, atol=1e-15)


def test_elementary_rotations_are_the_lectures():
    for t in (-2.0, 0.3, np.pi):
        np.testing.assert_allclose(euler.elementary("x", t), Rx(t), atol=1e-15)
        np.testing.assert_allclose(euler.elementary(1, t), Ry(t), atol=1e-15)
        np.testing.assert_allclose(euler.elementary("z", t), Rz(t), atol=1e-15)
    # Active, right-handed: R_z(90 deg) takes e_x to e_y.
    np.testing.assert_allclose(euler.elementary("z", np.pi / 2) @ [1, 0, 0], [0, 1, 0], atol=1e-15)


def test_intrinsic_axes_move_with_the_body():
    # rzyx: yaw 90 deg about z, then pitch 90 deg about the moved y axis (now the world's -x).
    C = euler.to_matrix([np.pi / 2, np.pi / 2, 0.0], "rzyx")
    step1 = Rz(np.pi / 2)
    moved_y = step1 @ [0, 1, 0]
    np.testing.assert_allclose(moved_y, [-1, 0, 0], atol=1e-15)
    np.testing.assert_allclose(C, so3.exp(np.pi / 2 * moved_y) @ step1, atol=1e-15)


@pytest.mark.parametrize("sequence", euler.SEQUENCES)
def test_extrinsic_equals_intrinsic_with_reversed_order(sequence):
    """The lecture's sxyz = rzyx, for every sequence: same angle on the same axis."""
    rng = np.random.default_rng(2)
    angles = random_angles(rng, 200)
    static = euler.to_matrix(angles, "s" + sequence)
    rotating = euler.to_matrix(angles[:, ::-1], "r" + sequence[::-1])
    np.testing.assert_allclose(static, rotating, atol=1e-14)
    assert euler.reverse("s" + sequence) == "r" + sequence[::-1]
    assert euler.reverse(euler.reverse("s" + sequence)) == "s" + sequence
    # ... and differs from the intrinsic rotation in the same order (the identity is not trivial).
    assert np.abs(static - euler.to_matrix(angles, "r" + sequence)).max() > 0.1


@pytest.mark.parametrize("convention", euler.CONVENTIONS)
def test_round_trip_over_random_angles(convention):
    rng = np.random.default_rng(3)
    angles = random_angles(rng, 2000)
    C = euler.to_matrix(angles, convention)
    back = euler.from_matrix(C, convention)
    np.testing.assert_allclose(euler.to_matrix(back, convention), C, atol=2e-15)
    # Ranges: first/third in [-pi, pi], middle in [-pi/2, pi/2] or [0, pi].
    assert np.all(np.abs(back) <= np.pi)
    if euler.is_proper_euler(convention):
        assert np.all((back[:, 1] >= 0) & (back[:, 1] <= np.pi))
    else:
        assert np.all(np.abs(back[:, 1]) <= np.pi / 2)
    # Angles already in range come back unchanged.
    canon = canonical_angles(rng, 2000, convention)
    np.testing.assert_allclose(wrap(euler.from_matrix(euler.to_matrix(canon, convention), convention) - canon),
                               0.0, atol=1e-12)


def singular_middles(convention):
    return (0.0, np.pi) if euler.is_proper_euler(convention) else (np.pi / 2, -np.pi / 2)


@pytest.mark.parametrize("convention", euler.CONVENTIONS)
def test_round_trip_at_gimbal_lock_and_degenerate_middle_angle(convention):
    rng = np.random.default_rng(4)
    for middle in singular_middles(convention):
        angles = random_angles(rng, 500)
        angles[:, 1] = middle
        C = euler.to_matrix(angles, convention)
        back = euler.from_matrix(C, convention)
        np.testing.assert_allclose(euler.to_matrix(back, convention), C, atol=2e-15)
        np.testing.assert_allclose(back[:, 1], middle, atol=1e-7)
        # Documented choice: the body-most angle (intrinsic third = extrinsic first) is 0.
        body_most = 2 if convention[0] == "r" else 0
        np.testing.assert_array_equal(back[:, body_most], 0.0)


@pytest.mark.parametrize("convention", euler.CONVENTIONS)
def test_round_trip_just_off_the_singularity(convention):
    """Where the angles are ill-conditioned the matrix must still be reproduced to round-off."""
    rng = np.random.default_rng(5)
    for middle in singular_middles(convention):
        for offset in (1e-15, 1e-13, 1e-11, 1e-9, 1e-7, 1e-5):
            angles = random_angles(rng, 300)
            towards_inside = -np.sign(middle) if middle != 0 else 1.0
            angles[:, 1] = middle + towards_inside * offset
            # Passing through a product with R and R^T leaves round-off of ~1e-16 in every entry,
            # as any composed matrix has: reading each angle from its own pair of entries would
            # then be off by up to 1e-2 in C at offset 1e-13 (checked when writing this test).
            R = so3.exp(rng.normal(size=(300, 3)))
            C = (euler.to_matrix(angles, convention) @ R) @ R.transpose(0, 2, 1)
            back = euler.from_matrix(C, convention)
            # Below SINGULAR_TOLERANCE the singular solution is used and moves C by ~offset.
            atol = 5e-15 if offset > euler.SINGULAR_TOLERANCE else 5e-15 + 2 * euler.SINGULAR_TOLERANCE
            np.testing.assert_allclose(euler.to_matrix(back, convention), C, atol=atol)


@pytest.mark.parametrize("convention", euler.CONVENTIONS)
def test_agrees_with_scipy(convention):
    rng = np.random.default_rng(6)
    seq = euler.scipy_sequence(convention)
    angles = random_angles(rng, 1000)
    np.testing.assert_allclose(euler.to_matrix(angles, convention),
                               Rotation.from_euler(seq, angles).as_matrix(), atol=1e-14)
    # Same ranges as SciPy, so away from singularities the angles agree too.
    C = so3.exp(rng.normal(size=(1000, 3)))
    ours = euler.from_matrix(C, convention)
    theirs = Rotation.from_matrix(C).as_euler(seq)
    keep = in_canonical_range(theirs, convention)
    assert keep.mean() > 0.9
    np.testing.assert_allclose(wrap(ours[keep] - theirs[keep]), 0.0, atol=1e-10)


def test_scipy_name_mapping():
    assert euler.scipy_sequence("sxyz") == "xyz"
    assert euler.scipy_sequence("rzyx") == "ZYX"
    assert euler.scipy_sequence("rzxz") == "ZXZ"
    assert euler.scipy_sequence("syzy") == "yzy"
    names = [euler.scipy_sequence(c) for c in euler.CONVENTIONS]
    assert len(set(names)) == 24
    for c, n in zip(euler.CONVENTIONS, names):
        assert n.lower() == c[1:] and (n.isupper() if c[0] == "r" else n.islower())
    # What the mapping relies on: SciPy's lower case is extrinsic, upper case intrinsic.
    a, b, c = 0.3, -1.1, 2.0
    np.testing.assert_allclose(Rotation.from_euler("xyz", [a, b, c]).as_matrix(), Rz(c) @ Ry(b) @ Rx(a), atol=1e-15)
    np.testing.assert_allclose(Rotation.from_euler("XYZ", [a, b, c]).as_matrix(), Rx(a) @ Ry(b) @ Rz(c), atol=1e-15)
    # and the mapping is not the naive one (lower-casing everything would be wrong for 'r').
    assert np.abs(Rotation.from_euler("zyx", [a, b, c]).as_matrix() - euler.to_matrix([a, b, c], "rzyx")).max() > 0.1


def test_roll_pitch_yaw_is_sxyz_and_rzyx_with_the_angles_reversed():
    rng = np.random.default_rng(7)
    rpy = random_angles(rng, 1000)
    rpy[:, 1] /= 2
    assert euler.ROLL_PITCH_YAW == "sxyz"
    np.testing.assert_allclose(euler.rpy_to_matrix(rpy), euler.to_matrix(rpy[:, ::-1], "rzyx"), atol=1e-15)
    C = so3.exp(rng.normal(size=(1000, 3)))
    np.testing.assert_allclose(euler.matrix_to_rpy(C)[:, ::-1], euler.from_matrix(C, "rzyx"), atol=1e-12)


ROUNDOFF = 8 * EPS
angle = st.floats(-math.pi, math.pi, allow_nan=False)


def max_wrapped(a, b) -> float:
    """Largest difference of two angle arrays, modulo 2 pi."""
    return float(np.max(np.abs(np.angle(np.exp(1j * (np.asarray(a) - np.asarray(b)))))))


@given(angle, st.floats(-1.5, 1.5), angle)
def test_rpy_against_gtsam_and_round_trip_away_from_gimbal_lock(roll, pitch, yaw):
    rpy = np.array([roll, pitch, yaw])
    C = euler.rpy_to_matrix(rpy)
    assert np.abs(C - gtsam.Rot3.Ypr(yaw, pitch, roll).matrix()).max() <= ROUNDOFF
    back = euler.matrix_to_rpy(C)
    # angles are defined modulo 2 pi; cos(1.5) = 0.07 keeps the conditioning within 15x
    assert max_wrapped(back, rpy) <= 15 * ROUNDOFF
    assert max_wrapped(back, gtsam.Rot3(C).rpy()) <= 15 * ROUNDOFF


@pytest.mark.parametrize("pitch", [math.pi / 2, -math.pi / 2])
@given(roll=angle, yaw=angle)
@settings(max_examples=50)
def test_rpy_at_gimbal_lock_reproduces_the_matrix(pitch, roll, yaw):
    C = euler.rpy_to_matrix([roll, pitch, yaw])
    rpy = euler.matrix_to_rpy(C)
    assert rpy[0] == 0.0  # roll is set to 0 ...
    assert abs(rpy[1] - pitch) <= 1e-7  # pitch is exact to sqrt(EPS) (atan2 of 1 against ~1e-17)
    # ... and yaw carries yaw - roll (pitch +pi/2) or yaw + roll (pitch -pi/2), modulo 2 pi
    expected = yaw - roll if pitch > 0 else yaw + roll
    assert max_wrapped(rpy[2], expected) <= 4 * ROUNDOFF
    assert np.abs(euler.rpy_to_matrix(rpy) - C).max() <= 4 * ROUNDOFF


@pytest.mark.parametrize("convention", euler.CONVENTIONS)
@pytest.mark.parametrize("chart", ["left", "right"])
def test_perturbation_jacobian_against_central_differences(convention, chart):
    rng = np.random.default_rng(8)
    angles = canonical_angles(rng, 20, convention)
    E = euler.perturbation_jacobian(angles, convention, chart)
    C = euler.to_matrix(angles, convention)
    h = 1e-6
    for m in range(3):
        d = np.zeros(3)
        d[m] = h
        Cp, Cm = euler.to_matrix(angles + d, convention), euler.to_matrix(angles - d, convention)
        if chart == "left":
            num = (so3.log(Cp @ C.transpose(0, 2, 1)) - so3.log(Cm @ C.transpose(0, 2, 1))) / (2 * h)
        else:
            num = (so3.log(C.transpose(0, 2, 1) @ Cp) - so3.log(C.transpose(0, 2, 1) @ Cm)) / (2 * h)
        np.testing.assert_allclose(E[:, :, m], num, atol=1e-8)
    expected_det = np.abs(np.sin(angles[:, 1]) if euler.is_proper_euler(convention) else np.cos(angles[:, 1]))
    np.testing.assert_allclose(np.abs(np.linalg.det(E)), expected_det, atol=1e-12)


def test_vectorised_over_leading_dimensions():
    rng = np.random.default_rng(9)
    angles = random_angles(rng, 24).reshape(2, 3, 4, 3)
    for convention in ("rzxz", "syxz"):
        C = euler.to_matrix(angles, convention)
        assert C.shape == (2, 3, 4, 3, 3)
        back = euler.from_matrix(C, convention)
        assert back.shape == angles.shape
        np.testing.assert_allclose(back[1, 2, 3], euler.from_matrix(C[1, 2, 3], convention))
        np.testing.assert_allclose(C[0, 1, 2], euler.to_matrix(angles[0, 1, 2], convention))


def test_quaternion_and_convention_conversions():
    rng = np.random.default_rng(10)
    angles = random_angles(rng, 500)
    q = euler.to_quaternion(angles, "rzxz")
    np.testing.assert_allclose(quaternion.to_matrix(q), euler.to_matrix(angles, "rzxz"), atol=1e-14)
    np.testing.assert_allclose(euler.to_matrix(euler.from_quaternion(q, "syzx"), "syzx"),
                               euler.to_matrix(angles, "rzxz"), atol=1e-14)
    converted = euler.convert(angles, "rzxz", "sxyx")
    np.testing.assert_allclose(euler.to_matrix(converted, "sxyx"), euler.to_matrix(angles, "rzxz"), atol=1e-14)


@pytest.mark.parametrize(
    "call, match",
    [
        (lambda: euler.to_matrix([0, 0, 0], "xyz"), "convention"),
        (lambda: euler.to_matrix([0, 0, 0], "sXYZ"), "convention"),
        (lambda: euler.to_matrix([0, 0, 0], "sxxy"), "convention"),
        (lambda: euler.to_matrix([0, 0, 0], None), "convention"),
        (lambda: euler.to_matrix([0, 0], "sxyz"), "angles"),
        (lambda: euler.to_matrix([0, np.nan, 0], "sxyz"), "angles"),
        (lambda: euler.from_matrix(np.eye(4), "sxyz"), "C"),
        (lambda: euler.from_matrix(2 * np.eye(3), "sxyz"), "C"),
        (lambda: euler.from_matrix(-np.eye(3), "sxyz"), "C"),
        (lambda: euler.from_matrix(np.full((3, 3), np.nan), "sxyz"), "C"),
        (lambda: euler.perturbation_jacobian([0, 0, 0], "sxyz", "middle"), "chart"),
        (lambda: euler.elementary("w", 0.0), "axis"),
    ],
)
def test_bad_input_raises_value_error_naming_the_argument(call, match):
    with pytest.raises(ValueError, match=match):
        call()
