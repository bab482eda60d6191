"""factors.quaternion: Hamilton, scalar-first unit quaternions (primer section V).

The centre piece is the primer's consistency table (section V.D), run over rotations in every
angle regime (down to 1e-12 rad, and within 1e-12 rad of pi and at pi):

    C(q) r == q(r)                     eqs. (35), (36)
    (q1 o q2)(r) == q1(q2(r))          eqs. (35), (37)
    C(exp(phi)) == Rodrigues C(phi)    eqs. (36), (38), (21) -- against so3.exp
    q == exp(log(q)) up to sign        eqs. (38)-(41)

plus the small-angle branches on both sides of ``quaternion.SMALL_ANGLE`` against 60-digit
references, GTSAM and scipy interoperability, ``check_unit``
and vectorisation. Tolerances are in units of EPS = 2.2e-16 (see tests/factors/test_so3.py).
"""
from __future__ import annotations

import math
import re
import warnings

import gtsam
import numpy as np
import pytest
import strategies as S
from hypothesis import given
from hypothesis import strategies as st
from scipy.spatial.transform import Rotation
from strategies import EPS

from factors import quaternion as Q
from factors import so3

ROUNDOFF = 8 * EPS
PRODUCT = 16 * EPS


def max_abs(a, b) -> float:
    return float(np.max(np.abs(np.asarray(a) - np.asarray(b))))


def same_orientation(q1, q2) -> float:
    """Distance between two quaternions up to the sign ambiguity q ~ -q."""
    return min(max_abs(q1, q2), max_abs(q1, -np.asarray(q2)))


def quaternions(regime="any", min_pi_distance=0.0):
    """Unit quaternions of both signs: exp of a rotation vector, sometimes negated."""
    return st.builds(lambda phi, flip: (-1.0 if flip else 1.0) * Q.exp(phi),
                     S.rotation_vectors(regime, min_pi_distance), st.booleans())


def raw_quaternions():
    """Unit quaternions from normalised 4-vectors: a distribution exp() never produces exactly
    (any sign of q0, components not tied to a rotation vector's rounding)."""
    comp = st.floats(-1, 1, allow_nan=False, allow_subnormal=False)
    return (st.tuples(comp, comp, comp, comp).map(np.array)
            .filter(lambda q: np.linalg.norm(q) > 0.1).map(lambda q: q / np.linalg.norm(q)))


# --------------------------------------------------------------------------- the table of section V.D


@given(st.one_of(quaternions(), raw_quaternions()), S.vectors())
def test_table_row_1_matrix_and_coordinate_map_agree(q, r):
    # C(q) r == q(r): both round O(10) times on terms of size |r|.
    assert max_abs(Q.to_matrix(q) @ r, Q.rotate(q, r)) <= PRODUCT * np.abs(r).max()


@given(st.one_of(quaternions(), raw_quaternions()), st.one_of(quaternions(), raw_quaternions()), S.vectors())
def test_table_row_2_composition_is_the_composition_of_maps(q1, q2, r):
    assert max_abs(Q.rotate(Q.compose(q1, q2), r), Q.rotate(q1, Q.rotate(q2, r))) <= 2 * PRODUCT * np.abs(r).max()


@given(S.rotation_vectors())
def test_table_row_3_exp_matches_rodrigues(phi):
    C = Q.to_matrix(Q.exp(phi))
    # absolute agreement at every angle ...
    assert max_abs(C, so3.exp(phi)) <= ROUNDOFF
    # ... and relative agreement of the off-diagonal entries, which carry phi itself at tiny
    # angles (an absolute 1e-15 would not see a wrong first-order term at 1e-9 rad).
    off = ~np.eye(3, dtype=bool)
    t = np.linalg.norm(phi)
    assert max_abs(C[off], so3.exp(phi)[off]) <= ROUNDOFF * min(t, 1.0) + 1e-300


@given(st.one_of(quaternions(), raw_quaternions()))
def test_table_row_4_exp_of_log_is_the_quaternion_up_to_sign(q):
    back = Q.exp(Q.log(q))
    assert same_orientation(back, q) <= ROUNDOFF
    # the sign convention: log then exp returns the representative with q0 >= 0 ...
    if abs(q[0]) > 1e-12:
        assert np.sign(back[0]) == 1.0
        assert max_abs(back, Q.canonical(q)) <= ROUNDOFF


@given(S.rotation_vectors("tiny"))
def test_table_row_4_at_tiny_angles_is_relatively_exact(phi):
    # At 1e-12 rad the vector part is ~5e-13; absolute 1e-15 would accept a 0.2% error.
    q = Q.exp(phi)
    back = Q.exp(Q.log(q))
    assert abs(back[0] - q[0]) <= EPS
    assert max_abs(back[1:], q[1:]) <= ROUNDOFF * np.abs(q[1:]).max() + 1e-300


@given(S.unit_vectors())
def test_table_row_4_at_exactly_pi(axis):
    q = np.concatenate([[0.0], axis])  # a half turn: q0 = 0 exactly
    assert same_orientation(Q.exp(Q.log(q)), q) <= ROUNDOFF
    assert abs(np.linalg.norm(Q.log(q)) - math.pi) <= 4 * EPS


# --------------------------------------------------------------------------- exp, log and their branches


@given(S.rotation_vectors(min_pi_distance=1e-12))
def test_exp_matches_eq_38_in_60_digits_and_log_inverts_it(phi):
    ref = S.reference_quaternion_exp(phi)
    q = Q.exp(phi)
    assert abs(q[0] - ref[0]) <= 2 * EPS
    # vector part relatively exact: |qv| = sin(t/2), from 1e-12 rad up to pi
    assert max_abs(q[1:], ref[1:]) <= 4 * EPS * np.abs(ref[1:]).max() + 1e-300
    assert max_abs(Q.log(q), phi) <= ROUNDOFF * np.abs(phi).max() + 1e-300


SMALL = Q.SMALL_ANGLE
SWITCH = [SMALL * (1 + f) for f in (-1e-2, -1e-9, 0.0, 1e-9, 1e-2)] + [1e-12, 1e-9, 1e-6, 1e-3]


@pytest.mark.parametrize("t", SWITCH)
@pytest.mark.parametrize("axis", [np.array([1.0, 0.0, 0.0]), np.array([0.48, -0.6, 0.64])])
def test_exp_both_sides_of_small_angle_against_reference(t, axis):
    phi = t * axis
    ref, q = S.reference_quaternion_exp(phi), Q.exp(phi)
    assert abs(q[0] - ref[0]) <= EPS
    assert max_abs(q[1:], ref[1:]) <= 2 * EPS * np.abs(ref[1:]).max()


@pytest.mark.parametrize("t", SWITCH)
@pytest.mark.parametrize("axis", [np.array([0.0, 0.0, 1.0]), np.array([0.48, -0.6, 0.64])])
def test_log_both_sides_of_its_switch_against_reference(t, axis):
    # log switches at |qv| = SMALL_ANGLE / 2, i.e. an angle of SMALL_ANGLE, like exp.
    q = S.reference_quaternion_exp(t * axis)
    ref = S.reference_quaternion_log(q)
    assert max_abs(Q.log(q), ref) <= 2 * EPS * np.abs(ref).max()


@given(st.one_of(quaternions(), raw_quaternions()))
def test_log_matches_high_precision_eq_40(q):
    q = Q.canonical(q)
    ref = S.reference_quaternion_log(q)
    # near pi (q0 ~ 0) the angle 2 atan2(|qv|, q0) is absolutely, not relatively, accurate
    assert max_abs(Q.log(q), ref) <= ROUNDOFF * max(np.abs(ref).max(), 1.0) * (1 if q[0] > 1e-3 else 2)


@given(S.rotation_vectors("tiny"))
def test_eq_41_small_angle_log_is_twice_the_vector_part_not_the_vector_part(phi):
    # The primer prints log(q) ~= qv (eq. 41). With exp(phi) ~= (1, phi/2) (eq. 39) the inverse
    # must be 2 qv; the module uses 2 qv and the consistency table (row 4) confirms it.
    q = Q.exp(phi)
    t = np.linalg.norm(phi)
    # log(q) = 2 qv (1 + t^2/24 + ...): relative deviation below t^2/20 + round-off
    assert max_abs(Q.log(q), 2 * q[1:]) <= (t * t / 20 + 4 * EPS) * t + 1e-300
    if t > 0:
        # the printed formula is off by a factor 2: |log q - qv| = |qv| = t/2
        assert np.linalg.norm(Q.log(q) - q[1:]) >= 0.49 * t


def test_log_of_half_turns_raises_no_floating_point_warnings():
    # q0 tiny but positive: the small-angle series must not be evaluated (s / q0 overflows).
    qs = np.array([[1e-200, 1.0, 0, 0], [0.0, 0, 1.0, 0], [1e-300, 0.6, 0.8, 0], [1e-17, 0, 0, 1.0]])
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        phis = Q.log(qs)
        so3.log(Q.to_matrix(qs))
    assert np.max(np.abs(np.linalg.norm(phis, axis=-1) - math.pi)) <= 4 * EPS
    assert max_abs(phis / math.pi, qs[:, 1:]) <= 4 * EPS


@pytest.mark.parametrize("bad", [np.nan, np.inf, -np.inf])
@pytest.mark.parametrize("component", range(4))
def test_log_of_a_non_finite_quaternion_is_nan_like_so3_log(bad, component):
    # A NaN or infinite component anywhere makes every component of the log NaN, near the
    # identity (the small-angle series) too, as so3.log does for a matrix.
    for base in (Q.identity(), -Q.exp([1e-6, 0, 0]), Q.exp([0.3, -2.5, 1.0])):
        q = base.copy()
        q[component] = bad
        assert np.isnan(Q.log(q)).all(), q
        C = Q.to_matrix(base)
        C[component % 3, component // 3] = bad
        assert np.isnan(so3.log(C)).all(), C


def test_hamilton_product_of_the_units():
    i, j, k = (np.array(v, dtype=float) for v in ([0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1]))
    # Hamilton: i j = k, j k = i, k i = j, i^2 = -1 (the JPL convention would give i j = -k)
    assert np.array_equal(Q.compose(i, j), k)
    assert np.array_equal(Q.compose(j, k), i)
    assert np.array_equal(Q.compose(k, i), j)
    assert np.array_equal(Q.compose(i, i), np.array([-1.0, 0, 0, 0]))


@given(quaternions(), quaternions(), quaternions())
def test_compose_inverse_identity(q1, q2, q3):
    assert max_abs(Q.compose(Q.compose(q1, q2), q3), Q.compose(q1, Q.compose(q2, q3))) <= PRODUCT
    assert max_abs(Q.to_matrix(Q.compose(q1, q2)), Q.to_matrix(q1) @ Q.to_matrix(q2)) <= 2 * PRODUCT
    assert max_abs(Q.compose(q1, Q.inverse(q1)), Q.identity()) <= ROUNDOFF
    assert max_abs(Q.to_matrix(Q.inverse(q1)), Q.to_matrix(q1).T) == 0.0
    assert np.array_equal(Q.compose(Q.identity(), q1), q1)
    # eq. (23): exp(phi) maps its rotation vector phi to itself
    phi = Q.log(q2)
    assert max_abs(Q.rotate(q2, phi), phi) <= PRODUCT * np.abs(phi).max() + 1e-300


#: The scalar part returned by each quaternion-valued function for arguments that give
#: ``q0 < 0`` unless the function returns the representative with ``q0 >= 0``.
SCALAR_PARTS = {
    "exp": lambda: Q.exp([4.0, 0, 0])[0],
    "compose": lambda: Q.compose(Q.exp([2.0, 0, 0]), Q.exp([2.0, 0, 0]))[0],
    "inverse": lambda: Q.inverse([-1.0, 0, 0, 0])[0],
    "normalize": lambda: Q.normalize([-2.0, 0, 0, 0])[0],
    "from_xyzw": lambda: Q.from_xyzw([0, 0, 0, -1.0])[0],
    "to_xyzw": lambda: Q.to_xyzw([-1.0, 0, 0, 0])[3],
    "canonical": lambda: Q.canonical(Q.exp([4.0, 0, 0]))[0],
    "identity": lambda: Q.identity()[0],
    "from_matrix": lambda: Q.from_matrix(Q.to_matrix(Q.exp([4.0, 0, 0])))[0],
    "from_rot3": lambda: Q.from_rot3(gtsam.Rot3.Quaternion(-0.6, 0.8, 0, 0))[0],
}


@pytest.mark.parametrize("name", SCALAR_PARTS)
def test_the_module_docstring_names_every_function_that_can_return_q0_below_zero(name):
    # The docstring promised q0 >= 0 "unless said otherwise" and named only compose and inverse,
    # but exp([4, 0, 0]) has q0 = cos(2) < 0 (the exponential onto the double cover, kept as such),
    # and normalize and the xyzw reorderings keep the sign they are given.
    exceptions = Q.__doc__.split("\n\n")[1]
    assert (SCALAR_PARTS[name]() < 0.0) == (f"``{name}``" in exceptions)


def test_exp_is_the_exponential_onto_the_double_cover():
    phi = np.array([1.0, 2.0, -0.5])
    t = np.linalg.norm(phi)
    assert Q.exp(phi)[0] == pytest.approx(math.cos(t / 2), abs=EPS)
    for a, b in ((1.5, 2.1), (3.0, 4.0), (-2.0, 5.0)):
        assert max_abs(Q.compose(Q.exp(a * phi), Q.exp(b * phi)), Q.exp((a + b) * phi)) <= PRODUCT


# --------------------------------------------------------------------------- from_matrix (Shepperd)


@given(st.one_of(quaternions(), raw_quaternions()))
def test_from_matrix_inverts_to_matrix(q):
    back = Q.from_matrix(Q.to_matrix(q))
    assert back[0] >= 0.0
    assert same_orientation(back, q) <= PRODUCT


@pytest.mark.parametrize("pivot", [0, 1, 2, 3])
def test_from_matrix_every_pivot_branch(pivot):
    # a quaternion whose largest component is `pivot`, including half turns (q0 = 0)
    rng = np.random.default_rng(pivot)
    for _ in range(50):
        q = rng.normal(size=4) * 0.3
        q[pivot] = 1.0
        if pivot:
            q[0] = 0.0 if rng.random() < 0.3 else q[0]
        q /= np.linalg.norm(q)
        assert same_orientation(Q.from_matrix(Q.to_matrix(q)), q) <= PRODUCT


@pytest.mark.parametrize("i", [1, 2, 3])
def test_from_matrix_of_exact_half_turns(i):
    C = -np.eye(3)
    C[i - 1, i - 1] = 1.0
    q = Q.from_matrix(C)
    expected = np.zeros(4)
    expected[i] = 1.0
    assert same_orientation(q, expected) == 0.0


# --------------------------------------------------------------------------- GTSAM, scipy, xyzw


@given(st.one_of(quaternions(), raw_quaternions()))
def test_gtsam_rot3_interoperability(q):
    R = gtsam.Rot3.Quaternion(*map(float, q))
    assert max_abs(Q.to_matrix(q), R.matrix()) <= ROUNDOFF  # eq. (36) is GTSAM's matrix
    assert max_abs(Q.to_rot3(q).matrix(), Q.to_matrix(q)) <= ROUNDOFF
    assert same_orientation(Q.from_rot3(R), q) <= PRODUCT
    g = R.toQuaternion()
    assert same_orientation(np.array([g.w(), g.x(), g.y(), g.z()]), q) <= PRODUCT
    phi = Q.log(q)
    g = gtsam.Rot3.Expmap(phi).toQuaternion()
    assert same_orientation(Q.exp(phi), np.array([g.w(), g.x(), g.y(), g.z()])) <= PRODUCT


@given(st.one_of(quaternions(), raw_quaternions()))
def test_xyzw_reorder_round_trip_and_scipy(q):
    xyzw = Q.to_xyzw(q)
    assert np.array_equal(xyzw, np.array([q[1], q[2], q[3], q[0]]))
    assert np.array_equal(Q.from_xyzw(xyzw), q)
    # scipy's from_quat is scalar-last, the TUM / ROS order
    assert max_abs(Rotation.from_quat(xyzw).as_matrix(), Q.to_matrix(q)) <= PRODUCT


# --------------------------------------------------------------------------- check_unit


def test_check_unit_accepts_unit_quaternions_and_returns_floats():
    q = Q.check_unit([1, 0, 0, 0])
    assert q.dtype == float and np.array_equal(q, [1.0, 0.0, 0.0, 0.0])
    batch = np.tile([0.5, 0.5, 0.5, 0.5], (2, 3, 1))
    assert Q.check_unit(batch).shape == (2, 3, 4)


def test_check_unit_names_the_first_non_unit_index():
    batch = np.array([[1, 0, 0, 0], [0, 1, 0, 0], [0.5, 0.5, 0.5, 0.6], [2, 0, 0, 0.0]])
    with pytest.raises(ValueError) as info:
        Q.check_unit(batch, name="q_IB")
    message = str(info.value)
    assert message.startswith("q_IB")
    assert "index (2,)" in message
    assert re.search(r"norm 1\.0535", message)


def test_check_unit_names_a_multi_dimensional_index():
    batch = np.tile([1.0, 0, 0, 0], (2, 3, 1))
    batch[1, 2] = [0, 0, 0, 2.0]
    with pytest.raises(ValueError, match=re.escape("index (1, 2)")):
        Q.check_unit(batch)


@pytest.mark.parametrize("bad", [np.nan, np.inf, -np.inf])
def test_check_unit_rejects_non_finite_values_with_the_index(bad):
    batch = np.tile([1.0, 0, 0, 0], (4, 1))
    batch[3, 2] = bad
    with pytest.raises(ValueError, match=r"q_wb: non-finite value at index \(3,\)"):
        Q.check_unit(batch, name="q_wb")


def test_check_unit_rejects_a_single_non_finite_quaternion():
    with pytest.raises(ValueError, match="quaternion: non-finite"):
        Q.check_unit([np.nan, 0, 0, 1])


@pytest.mark.parametrize("shape", [(3,), (5,), (4, 3), ()])
def test_check_unit_rejects_wrong_shapes(shape):
    with pytest.raises(ValueError, match=re.escape(f"got {shape}")):
        Q.check_unit(np.ones(shape), name="q")


def test_check_unit_tolerance():
    q = np.array([1.0 + 5e-7, 0, 0, 0])
    assert Q.check_unit(q) is not None  # within the default 1e-6
    with pytest.raises(ValueError, match="within 1e-07"):
        Q.check_unit(q, tolerance=1e-7)


def test_check_unit_reports_a_single_non_unit_quaternion():
    with pytest.raises(ValueError, match=r"not a unit quaternion.*norm 1\.00498756"):
        Q.check_unit([1.0, 0, 0, 0.1])


# --------------------------------------------------------------------------- vectorisation


@pytest.mark.parametrize("seed", range(5))
def test_vectorised_functions_equal_loops(seed):
    rng = np.random.default_rng(seed)
    qb = Q.exp(S.sample_rotation_vectors(rng, (2, 3))) * rng.choice([-1.0, 1.0], size=(2, 3, 1))
    pb = Q.exp(S.sample_rotation_vectors(rng, (2, 3)))
    rb = rng.normal(size=(2, 3, 3)) * 10
    phis = Q.log(qb)
    cases = [
        (Q.rotate, (qb, rb)), (Q.to_matrix, (qb,)), (Q.compose, (qb, pb)), (Q.inverse, (qb,)),
        (Q.exp, (phis,)), (Q.log, (qb,)), (Q.from_matrix, (Q.to_matrix(qb),)), (Q.canonical, (qb,)),
        (Q.normalize, (qb,)), (Q.to_xyzw, (qb,)), (Q.from_xyzw, (qb,)), (Q.check_unit, (qb,)),
    ]
    for f, args in cases:
        batched = f(*args)
        looped = np.array([[f(*(a[i, j] for a in args)) for j in range(3)] for i in range(2)])
        assert batched.shape == looped.shape, f.__name__
        assert (np.allclose(batched, looped, rtol=4 * EPS, atol=1e-300)
                or max_abs(batched, looped) <= 2 * EPS), f.__name__


@pytest.mark.parametrize(
    "call, message",
    [
        (lambda: Q.exp([0.1, 0.2, 0.3, 0.4]), "phi: expected shape (..., 3), got (4,)"),
        (lambda: Q.to_matrix([1.0, 0, 0, 0, 0]), "q: expected shape (..., 4), got (5,)"),
        (lambda: Q.rotate([1.0, 0, 0], [1.0, 2, 3]), "q: expected shape (..., 4), got (3,)"),
        (lambda: Q.rotate([1.0, 0, 0, 0], [1.0, 2, 3, 4]), "r: expected shape (..., 3), got (4,)"),
        (lambda: Q.compose([1.0, 0, 0, 0, 0], [1.0, 0, 0, 0]), "q1: expected shape (..., 4), got (5,)"),
        (lambda: Q.compose([1.0, 0, 0, 0], np.eye(3)), "q2: expected shape (..., 4), got (3, 3)"),
        (lambda: Q.inverse([1.0, 0, 0]), "q: expected shape (..., 4), got (3,)"),
        (lambda: Q.normalize([1.0, 0, 0, 0, 0]), "q: expected shape (..., 4), got (5,)"),
        (lambda: Q.canonical([-1.0, 0, 0]), "q: expected shape (..., 4), got (3,)"),
        (lambda: Q.from_xyzw([0, 0, 1.0]), "q: expected shape (..., 4), got (3,)"),
        (lambda: Q.to_xyzw(1.0), "q: expected shape (..., 4), got ()"),
        (lambda: Q.to_rot3([1.0, 0, 0]), "q: expected shape (..., 4), got (3,)"),
        (lambda: Q.to_rot3(Q.identity(2)), "q: expected shape (4,) (one quaternion), got (2, 4)"),
        (lambda: Q.log([1.0, 0, 0]), "q: expected shape (..., 4), got (3,)"),
        (lambda: Q.from_matrix(np.eye(4)), "C: expected shape (..., 3, 3), got (4, 4)"),
    ],
)
def test_wrong_trailing_shapes_raise_value_error_naming_the_argument(call, message):
    # A 4-vector to exp, a 5-vector to to_matrix, ...: each refused naming the argument and shape.
    with pytest.raises(ValueError, match=re.escape(message)):
        call()


def test_identity_shapes():
    assert np.array_equal(Q.identity(), [1.0, 0, 0, 0])
    assert Q.identity(5).shape == (5, 4) and Q.identity((2, 3)).shape == (2, 3, 4)
    assert np.array_equal(Q.identity((2, 3))[..., 0], np.ones((2, 3)))
