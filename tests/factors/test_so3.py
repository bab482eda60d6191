"""factors.so3: the primer's calculus on rotation matrices.

Covers the skew identities (1)-(3), exp/log/boxplus/boxminus and their identities (12), (13),
(16)-(18), (21)-(24), the cheat sheet's active/passive boxminus relations (its eqs. 10, 12, 21, 22),
Gamma and its inverse (eqs. 33, 74, 76, 80), agreement with GTSAM, accuracy against 60-digit
references at every angle (both sides of ``so3.SERIES_ANGLE``), and vectorisation.

Tolerances are stated in units of ``EPS`` = 2.2e-16 (float64 round-off). A Rodrigues evaluation
rounds a handful of times on terms of size up to 2 (near pi), so "exact to round-off" is taken as
``ROUNDOFF`` = 8 EPS (1.8e-15) absolute on entries of size <= 1; a result that also goes through a
product of two such matrices gets ``PRODUCT`` = 16 EPS, through three ``TRIPLE`` = 32 EPS (7e-15).
Every one of these is 6 orders of magnitude below what a wrong formula or a half-precision
algorithm (arccos-based log near pi: ~1e-8) would produce.
"""
from __future__ import annotations

import math
import re

import gtsam
import numpy as np
import pytest
import scipy.linalg
import strategies as S
from hypothesis import assume, given
from hypothesis import strategies as st
from strategies import EPS

from factors import so3

ROUNDOFF = 8 * EPS
PRODUCT = 16 * EPS
TRIPLE = 32 * EPS


def max_abs(a, b) -> float:
    return float(np.max(np.abs(np.asarray(a) - np.asarray(b))))


# --------------------------------------------------------------------------- skew, identities (1)-(3)


@given(S.rotations(), S.vectors(), S.vectors())
def test_skew_vee_and_identities_1_to_3(C, v, r):
    K = so3.skew(v)
    size = np.abs(v).max()
    assert max_abs(K @ r, np.cross(v, r)) <= 12 * EPS * size * np.abs(r).max(), "v^x r = v x r"
    assert np.array_equal(so3.vee(K), v), "vee inverts skew exactly (it halves v_i - -v_i)"
    assert np.array_equal(K.T, -K), "(1)"
    # (2): entries are sums of two products of size |v|^2
    assert max_abs(K @ K, np.outer(v, v) - (v @ v) * np.eye(3)) <= 4 * EPS * (v @ v), "(2)"
    # (3): a triple product, entries bounded by |v|
    assert max_abs(so3.skew(C @ v), C @ K @ C.T) <= 16 * EPS * size, "(3)"


# --------------------------------------------------------------------------- exp (eqs. 12, 13, 21-24)


@given(S.rotation_vectors())
def test_exp_is_a_rotation_about_its_own_axis(phi):
    C = so3.exp(phi)
    assert max_abs(C @ C.T, np.eye(3)) <= PRODUCT
    assert abs(np.linalg.det(C) - 1.0) <= PRODUCT
    # eq. (23): the rotation vector has the same coordinates in both frames, C phi = phi ...
    assert max_abs(C @ phi, phi) <= ROUNDOFF * np.abs(phi).max() + 1e-300
    # ... and exp(-phi) is the inverse (the same arithmetic with mirrored signs).
    assert max_abs(so3.exp(-phi), C.T) <= ROUNDOFF


@given(S.rotation_vectors())
def test_exp_matches_rodrigues_in_60_digits_and_the_matrix_exponential(phi):
    C = so3.exp(phi)
    # Eq. (21) evaluated in 60-digit arithmetic and rounded once.
    assert max_abs(C, S.reference_matrix("exp", phi)) <= ROUNDOFF
    # Appendix II-A, eq. (87): C(phi) = e^{phi^x}; scipy's Pade expm is itself good to a few EPS.
    assert max_abs(C, scipy.linalg.expm(so3.skew(phi))) <= 2 * ROUNDOFF


@given(S.unit_vectors(), st.floats(-2.0, 2.0), st.floats(-2.0, 2.0))
def test_identity_12_one_parameter_subgroup(axis, t, s):
    assert max_abs(so3.exp((t + s) * axis), so3.exp(t * axis) @ so3.exp(s * axis)) <= 2 * ROUNDOFF


@given(S.vectors(3.0), S.vectors())
def test_identity_13_derivative_at_zero_is_the_cross_product(phi, v):
    # d/dt exp(t phi) v at 0 = phi x v. Central difference with h: truncation h^2 |phi|^3 |v| / 6,
    # round-off EPS |v| / h; h = 1e-5 makes both <= 1e-9 relative to |phi| |v| (|phi| <= 5.2).
    h = 1e-5
    num = (so3.exp(h * phi) @ v - so3.exp(-h * phi) @ v) / (2 * h)
    scale = max(np.linalg.norm(phi), 1.0) ** 3 * max(np.linalg.norm(v), 1.0)
    assert max_abs(num, np.cross(phi, v)) <= 1e-9 * scale


@given(S.rotation_vectors("tiny"))
def test_identity_22_small_angle_approximation(phi):
    # C(phi) = I + phi^x + phi^x^2 / 2 + O(t^3): the remainder of I + phi^x is at most t^2 / 2.
    t = np.linalg.norm(phi)
    assert max_abs(so3.exp(phi), np.eye(3) + so3.skew(phi)) <= 0.5 * t * t + EPS


@given(S.rotations(), S.rotation_vectors())
def test_identity_24_adjoint(C, phi):
    # exp(Phi(phi)) = Phi o exp(phi) o Phi^-1.
    # C phi rounds by ~2 EPS pi per component, then a triple product: TRIPLE.
    assert max_abs(so3.exp(C @ phi), C @ so3.exp(phi) @ C.T) <= TRIPLE


# --------------------------------------------------------------------------- log


@given(S.rotation_vectors(min_pi_distance=1e-12))
def test_log_inverts_exp_at_every_angle(phi):
    # Relative accuracy: 8 EPS |phi| holds from 1e-12 rad (where an arccos-based log would return
    # 0) up to 1e-12 rad short of pi (where it would lose half the digits).
    C = so3.exp(phi)
    bound = ROUNDOFF * np.abs(phi).max() + 1e-300
    assert max_abs(so3.log(C), phi) <= bound
    assert max_abs(so3.log(C.T), -phi) <= bound


@given(S.unit_vectors(), st.floats(1e-12, 1e-6))
def test_log_accurate_within_a_micro_radian_of_pi(axis, distance):
    phi = (math.pi - distance) * axis
    assert max_abs(so3.log(so3.exp(phi)), phi) <= 4 * ROUNDOFF


@given(S.unit_vectors())
def test_log_at_exactly_pi_has_norm_pi_and_the_right_axis(axis):
    C = so3.exp(math.pi * axis)
    phi = so3.log(C)
    assert abs(np.linalg.norm(phi) - math.pi) <= 4 * EPS
    # either of the two vectors of norm pi is a valid answer
    assert min(max_abs(phi, math.pi * axis), max_abs(phi, -math.pi * axis)) <= 2 * ROUNDOFF
    assert max_abs(so3.exp(phi), C) <= ROUNDOFF


@pytest.mark.parametrize("i", [0, 1, 2])
def test_log_of_exact_half_turns_about_the_axes(i):
    C = -np.eye(3)
    C[i, i] = 1.0  # rotation by pi about e_i, exactly representable
    phi = so3.log(C)
    assert np.abs(phi[i]) == math.pi and np.count_nonzero(phi) == 1


def test_log_of_identity_is_exactly_zero():
    assert np.array_equal(so3.log(np.eye(3)), np.zeros(3))


# --------------------------------------------------------------------------- against GTSAM


@given(S.rotation_vectors(min_pi_distance=1e-12))
def test_exp_log_gamma_agree_with_gtsam(phi):
    C = so3.exp(phi)
    assert max_abs(C, gtsam.Rot3.Expmap(phi).matrix()) <= ROUNDOFF, "Expmap"
    assert max_abs(so3.log(C), gtsam.Rot3.Logmap(gtsam.Rot3(C))) <= ROUNDOFF * np.abs(phi).max() + 1e-300, "Logmap"
    # GTSAM's ExpmapDerivative is the RIGHT Jacobian Gamma(-phi) = Gamma(phi)^T (docs/design.md, section 4).
    assert max_abs(so3.gamma(phi), gtsam.Rot3.ExpmapDerivative(-phi)) <= ROUNDOFF, "ExpmapDerivative"
    # GTSAM's LogmapDerivative switches to an approximation close to pi (we measured 2.6e-8 off
    # the exact inverse of its own ExpmapDerivative at pi - 1e-3), so compare below 3 rad only;
    # near pi gamma_inv is checked against the exact inverse of gamma (below).
    if np.linalg.norm(phi) <= 3.0:
        assert max_abs(so3.gamma_inv(phi), gtsam.Rot3.LogmapDerivative(-phi)) <= ROUNDOFF, "LogmapDerivative"


@given(S.unit_vectors())
def test_exp_and_gamma_agree_with_gtsam_at_exactly_pi(axis):
    phi = math.pi * axis
    assert max_abs(so3.exp(phi), gtsam.Rot3.Expmap(phi).matrix()) <= ROUNDOFF
    assert max_abs(so3.gamma(phi), gtsam.Rot3.ExpmapDerivative(-phi)) <= ROUNDOFF


@given(S.asymmetric_rotations().map(so3.log))
def test_gamma_is_not_gtsams_expmap_derivative_of_phi(phi):
    # The sign matters: Gamma(phi) and its transpose differ by 2 (1 - cos t)/t^2 |phi| >= 0.23.
    assert max_abs(so3.gamma(phi), gtsam.Rot3.ExpmapDerivative(phi)) > 0.2


# --------------------------------------------------------------------------- Gamma and its inverse


@given(S.rotation_vectors())
def test_gamma_and_gamma_inv_match_references(phi):
    G = so3.gamma(phi)
    # 60-digit evaluations of eq. (33) and of its inverse's closed form, rounded once
    assert max_abs(G, S.reference_matrix("gamma", phi)) <= 4 * EPS
    assert max_abs(so3.gamma_inv(phi), S.reference_matrix("gamma_inv", phi)) <= 4 * EPS
    # Gamma(phi) = sum_n (phi^x)^n / (n+1)!, the top-right block of expm([[phi^x, I], [0, 0]])
    block = np.zeros((6, 6))
    block[:3, :3] = so3.skew(phi)
    block[:3, 3:] = np.eye(3)
    assert max_abs(G, scipy.linalg.expm(block)[:3, 3:]) <= 2 * ROUNDOFF


@given(S.rotation_vectors())
def test_gamma_properties_at_every_angle_including_pi(phi):
    G, Gi = so3.gamma(phi), so3.gamma_inv(phi)
    assert max_abs(Gi @ G, np.eye(3)) <= ROUNDOFF
    assert max_abs(G @ Gi, np.eye(3)) <= ROUNDOFF
    assert max_abs(so3.gamma(-phi), G.T) == 0.0  # the same arithmetic, mirrored
    # Appendix I, eqs. (76) and (74): Gamma(phi) phi = phi, Gamma(phi) phi^x = C(phi) - I.
    t = np.abs(phi).max()
    assert max_abs(G @ phi, phi) <= ROUNDOFF * t + 1e-300
    # C - I rounds its diagonal (1 - t^2/2) - 1 by up to EPS absolute, whatever t.
    assert max_abs(G @ so3.skew(phi), so3.exp(phi) - np.eye(3)) <= ROUNDOFF * t + EPS


@given(S.rotation_vectors("ordinary").filter(lambda p: np.linalg.norm(p) > 0.1))
def test_gamma_equals_the_closed_form_of_eq_80(phi):
    # ((I - C) phi^x + phi phi^T) / |phi|^2; no cancellation above 0.1 rad (loses < 2 digits).
    C = so3.exp(phi)
    closed = ((np.eye(3) - C) @ so3.skew(phi) + np.outer(phi, phi)) / (phi @ phi)
    assert max_abs(so3.gamma(phi), closed) <= 100 * ROUNDOFF


# ------------------------------------------------- coefficient accuracy on both sides of the switch

# Each matrix is I + a(t) phi^x + b(t) phi^x^2. For phi = t (cos u, sin u, 0) the entry [0, 2] is
# exactly a * phi_1 and [0, 1] exactly b * phi_0 phi_1 (the other term is an exact zero), so the
# coefficients can be read off the public functions to one rounding and compared, RELATIVELY, with
# 60-digit values. This catches what an absolute test cannot: (1 - cos t)/t^2 evaluated naively is
# 0 at t = 1e-9 and would still pass an absolute tolerance of 1e-15 on the matrix.
SWITCH_ANGLES = [so3.SERIES_ANGLE * (1 + f) for f in (-1e-3, -1e-9, 0.0, 1e-9, 1e-3, 0.05)]
GRID = sorted(set(list(np.logspace(-12, 0, 49)) + SWITCH_ANGLES))
FUNCTIONS = {"exp": so3.exp, "gamma": so3.gamma, "gamma_inv": so3.gamma_inv}


def _measured_coefficients(kind, t, u=0.7):
    phi = np.array([t * math.cos(u), t * math.sin(u), 0.0])
    M = FUNCTIONS[kind](phi)
    return M[0, 2] / phi[1], M[0, 1] / (phi[0] * phi[1])


def _allowed_relative_error(kind, which, t):
    """8 EPS, except where the module knowingly evaluates a closed form that cancels: just above
    SERIES_ANGLE, (t - sin t)/t^3 loses 6 EPS/t^2 (sin t rounds by EPS t on a difference of t^3/6)
    and (1 - (t/2)cot(t/2))/t^2 about 20 EPS/t^2 (three roundings of size EPS on a difference of
    t^2/12). Their weight in the matrix is t^2, so the matrix itself stays exact to round-off
    (test_gamma_and_gamma_inv_match_references). Whatever SERIES_ANGLE is, no coefficient may be
    worse than ``CANCELLATION_CAP`` = 5e-11 relative (measured: 1.9e-11 just above 1e-2), so moving
    the switch down to where the closed forms lose more digits fails this test."""
    base = 8 * EPS
    if which == "b" and t >= so3.SERIES_ANGLE:
        if kind == "gamma":
            return min(base + 6 * EPS / t**2, CANCELLATION_CAP)
        if kind == "gamma_inv":
            return min(base + 20 * EPS / t**2, CANCELLATION_CAP)
    return base


CANCELLATION_CAP = 5e-11


@pytest.mark.parametrize("kind", sorted(FUNCTIONS))
@pytest.mark.parametrize("t", GRID)
def test_coefficients_are_relatively_accurate_from_1e12_to_1_rad(kind, t):
    a_ref, b_ref = S.coefficients(kind, t)
    a, b = _measured_coefficients(kind, t)
    for which, got, ref in (("a", a, float(a_ref)), ("b", b, float(b_ref))):
        rel = abs(got - ref) / abs(ref)
        assert rel <= _allowed_relative_error(kind, which, t), (kind, which, t, rel)


@pytest.mark.parametrize("kind", sorted(FUNCTIONS))
def test_series_and_closed_form_meet_at_the_switch(kind):
    # The two sides of SERIES_ANGLE, 1e-12 apart in relative angle: the coefficients may change by
    # their derivative (~t^2 relative) plus the closed form's cancellation error, nothing more.
    lo, hi = so3.SERIES_ANGLE * (1 - 1e-12), so3.SERIES_ANGLE * (1 + 1e-12)
    for below, above in zip(_measured_coefficients(kind, lo), _measured_coefficients(kind, hi)):
        assert abs(below - above) <= min(8 * EPS + 20 * EPS / so3.SERIES_ANGLE**2, CANCELLATION_CAP) * abs(below)


# --------------------------------------------------------------------------- boxplus / boxminus


@given(S.rotations(), S.rotations(), S.rotation_vectors(min_pi_distance=1e-9))
def test_identities_16_to_18_and_the_left_perturbation(C, C2, phi):
    assert np.array_equal(so3.boxplus(C, np.zeros(3)), C), "(16)"
    # (17): log(exp(phi) C C^T), C C^T is I to ~2 EPS: an absolute error of a few EPS at any |phi|
    assert max_abs(so3.boxminus(so3.boxplus(C, phi), C), phi) <= 2 * ROUNDOFF, "(17)"
    # (18) holds even when C2 C^T is a half turn: both candidate logs give the same exp.
    assert max_abs(so3.boxplus(C, so3.boxminus(C2, C)), C2) <= 2 * ROUNDOFF, "(18)"
    # boxplus perturbs on the left (eq. 14) ...
    assert max_abs(so3.boxplus(C, phi), so3.exp(phi) @ C) == 0.0
    # ... which is the right perturbation by C^T phi (eq. 24), GTSAM's retract: two products of
    # rotations and two exps computed differently, a few EPS each (3.6e-15 = 2.03 ROUNDOFF seen).
    assert max_abs(so3.boxplus(C, phi), C @ so3.exp(C.T @ phi)) <= 4 * ROUNDOFF


# ------------------------------------------------ active and passive boxminus (cheat sheet 10, 12, 21, 22)

# Passive rotations C_IA = A and C_IB = B map A- and B-coordinates to I. The active ones are their
# inverses, Phi_AI = A^T and Phi_BI = B^T. The cheat sheet's relations, with matrices:
#   (10) Phi_AI [-] Phi_BI = log(A^T B) = B_phi_AB, the rotation vector of C_AB = A^T B;
#   (12) Phi_IA [-] Phi_IB = log(A B^T) = I_phi_BA = B log(B^T A), the vector of C_BA seen in I;
#   (21) Phi_AI [-] Phi_BI = -Phi_BI(Phi_IA [-] Phi_IB):  log(A^T B) = -B^T log(A B^T);
#   (22) Phi_AI [-] Phi_BI = -(Phi_BI [-] Phi_AI):         log(A^T B) = -log(B^T A).


@given(S.rotations(), S.rotation_vectors(min_pi_distance=1e-9))
def test_cheat_sheet_active_and_passive_boxminus(B, phi):
    A = so3.exp(phi) @ B  # C_IA, at a relative rotation of angle |phi| from C_IB = B
    active, passive = so3.boxminus(A.T, B.T), so3.boxminus(A, B)
    # the vectors compared are |phi| long: their round-off grows with it (4e-15 at |phi| = 2 and 3)
    tolerance = 2 * ROUNDOFF * max(1.0, float(np.linalg.norm(phi)))
    assert max_abs(active, -B.T @ passive) <= tolerance, "(21)"
    assert max_abs(active, -so3.boxminus(B.T, A.T)) <= tolerance, "(22)"
    assert max_abs(passive, -so3.boxminus(B, A)) <= tolerance, "(22) for passive rotations"
    assert max_abs(active, so3.log(A.T @ B)) <= tolerance, "(10)"
    assert max_abs(passive, B @ so3.log(B.T @ A)) <= tolerance, "(12)"
    # and by construction A = B [+] phi, so the passive difference is the phi we put in
    assert max_abs(passive, phi) <= tolerance


@given(S.asymmetric_rotations(), S.asymmetric_rotations())
def test_cheat_sheet_21_is_not_trivially_true(A, B):
    # Without the -Phi_BI( . ) on the right-hand side the relation fails: the active and passive
    # differences are different vectors in general, so the test above can fail.
    angle = np.linalg.norm(so3.boxminus(A, B))
    assume(0.5 < angle < math.pi - 1e-6)
    active, passive = so3.boxminus(A.T, B.T), so3.boxminus(A, B)
    assert max_abs(active, passive) > 1e-3 or max_abs(active, -passive) > 1e-3


# --------------------------------------------------------------------------- compose, inverse, project


@given(S.rotations(), S.rotations(), S.vectors())
def test_compose_and_inverse(C1, C2, r):
    # eq. (5): (Phi1 o Phi2)(r) = Phi1(Phi2(r)); eq. (7): Phi^-1 o Phi = identity
    assert max_abs(so3.compose(C1, C2) @ r, C1 @ (C2 @ r)) <= PRODUCT * np.abs(r).max()
    assert max_abs(so3.compose(so3.inverse(C1), C1), np.eye(3)) <= PRODUCT


def _spd(seed):
    rng = np.random.default_rng(seed)
    X = rng.normal(size=(3, 3))
    return X @ X.T + 0.5 * np.eye(3)


@given(S.rotations(), st.integers(0, 2**32 - 1))
def test_project_recovers_the_rotation_of_a_polar_decomposition(C, seed):
    assert max_abs(so3.project(C), C) <= ROUNDOFF
    # M = C S with S symmetric positive definite: the nearest rotation is C (polar decomposition).
    # The SVD's backward error, p(3) eps |M| (LAPACK's p(n) a modest polynomial), moves the polar
    # factor by up to that over sigma_min: p(3) eps cond(S), measured up to 12 eps cond(S).
    S_ = _spd(seed)
    assert max_abs(so3.project(C @ S_), C) <= 30 * EPS * np.linalg.cond(S_)


@pytest.mark.parametrize("seed", range(20))
def test_project_returns_the_nearest_proper_rotation_even_from_a_reflection(seed):
    M = np.random.default_rng(seed).normal(size=(3, 3))
    R = so3.project(M)
    assert max_abs(R @ R.T, np.eye(3)) <= PRODUCT
    assert abs(np.linalg.det(R) - 1.0) <= PRODUCT
    # a local minimum of |R - M|: every small rotation away from R is farther from M
    for phi in np.vstack([np.eye(3), -np.eye(3)]) * 1e-3:
        assert np.linalg.norm(R - M) <= np.linalg.norm(so3.exp(phi) @ R - M) + 1e-12


# --------------------------------------------------------------------------- vectorisation

SHAPE = (4, 3)


def _loop(f, *batched):
    out = [[f(*(b[i][j] for b in batched)) for j in range(SHAPE[1])] for i in range(SHAPE[0])]
    return np.array(out)


@pytest.mark.parametrize("seed", range(5))
def test_vectorised_functions_equal_loops_of_single_calls(seed):
    rng = np.random.default_rng(seed)
    phis, others = S.sample_rotation_vectors(rng, SHAPE), S.sample_rotation_vectors(rng, SHAPE)
    Cs, Ds = so3.exp(phis), so3.exp(others)
    assert Cs.shape == SHAPE + (3, 3)
    cases = [
        (so3.skew, (phis,)),
        (so3.vee, (so3.skew(phis),)),
        (so3.exp, (phis,)),
        (so3.log, (Cs,)),
        (so3.gamma, (phis,)),
        (so3.gamma_inv, (phis,)),
        (so3.compose, (Cs, Ds)),
        (so3.inverse, (Cs,)),
        (so3.boxplus, (Cs, others)),
        (so3.boxminus, (Cs, Ds)),
        (so3.project, (Cs,)),
    ]
    for f, args in cases:
        batched = f(*args)
        looped = _loop(f, *args)
        assert batched.shape == looped.shape, f.__name__
        # Elementwise code is bitwise identical; batched matmul and SVD may take other BLAS paths,
        # so allow round-off relative to the entry (4 EPS) with a floor far below any tiny angle.
        assert (np.allclose(batched, looped, rtol=4 * EPS, atol=1e-300)
                or max_abs(batched, looped) <= 2 * EPS), f.__name__


@pytest.mark.parametrize(
    "call, message",
    [
        (lambda: so3.skew([1.0, 2, 3, 4]), "v: expected shape (..., 3), got (4,)"),
        (lambda: so3.vee(np.eye(4)), "m: expected shape (..., 3, 3), got (4, 4)"),
        (lambda: so3.exp([1.0, 2]), "phi: expected shape (..., 3), got (2,)"),
        (lambda: so3.log(np.eye(4)), "C: expected shape (..., 3, 3), got (4, 4)"),
        (lambda: so3.compose(np.eye(4), np.eye(4)), "C1: expected shape (..., 3, 3), got (4, 4)"),
        (lambda: so3.compose(np.eye(3), np.ones(3)), "C2: expected shape (..., 3, 3), got (3,)"),
        (lambda: so3.inverse(np.eye(2)), "C: expected shape (..., 3, 3), got (2, 2)"),
        (lambda: so3.boxplus([1.0, 2, 3], np.zeros(3)), "C: expected shape (..., 3, 3), got (3,)"),
        (lambda: so3.boxplus(np.eye(3), np.zeros(4)), "phi: expected shape (..., 3), got (4,)"),
        (lambda: so3.boxminus(np.eye(3), np.eye(4)), "C2: expected shape (..., 3, 3), got (4, 4)"),
        (lambda: so3.gamma(np.zeros((2, 4))), "phi: expected shape (..., 3), got (2, 4)"),
        (lambda: so3.gamma_inv([0.1]), "phi: expected shape (..., 3), got (1,)"),
        (lambda: so3.project(np.eye(4)), "M: expected shape (..., 3, 3), got (4, 4)"),
    ],
)
def test_wrong_trailing_shapes_raise_value_error_naming_the_argument(call, message):
    # A 4-vector to skew, a 4x4 matrix to vee, ...: each refused naming the argument and shape.
    with pytest.raises(ValueError, match=re.escape(message)):
        call()


def test_vectorised_functions_accept_a_single_leading_dimension_of_zero_length():
    assert so3.exp(np.zeros((0, 3))).shape == (0, 3, 3)
    assert so3.gamma(np.zeros((0, 3))).shape == (0, 3, 3)
    assert so3.skew(np.zeros((0, 3))).shape == (0, 3, 3)
