"""factors.derivatives: the primer's analytic Jacobians (eqs. 25-34, boxplus, boxminus), each
against its numerical twin ``factors.jacobians.numerical_jacobian`` (central differences built
from [+] and [-], primer eqs. 19-20), at rotations with angles from 0 to pi.

Tolerance of a numerical Jacobian with the default step h = 1e-6: round-off EPS |f| / h
(~2e-10 |f|, a few times over for the several roundings in f) plus truncation h^2 |f'''| / 6
(~1e-13 here). ``NUM_TOL`` = 1e-8 per unit of the function's scale is 50x the round-off and still
1e7 times smaller than any wrong block (a transposed C, a missing sign, Gamma for Gamma^T), which
is O(1). Rotations whose derivative involves log are kept 1e-5 rad away from pi so the +-1e-6 step
cannot cross the cut where log jumps.
"""
from __future__ import annotations

import math

import numpy as np
import pytest
import strategies as S
from hypothesis import given
from hypothesis import strategies as st
from strategies import EPS

from factors import derivatives as d
from factors import so3
from factors.jacobians import numerical_jacobian

NUM_TOL = 1e-8
LOG_MARGIN = 1e-5  # distance to pi kept by rotations whose derivative goes through log


def max_abs(a, b) -> float:
    return float(np.max(np.abs(np.asarray(a) - np.asarray(b))))


def scale(*vectors) -> float:
    return max([1.0] + [float(np.abs(v).max()) for v in vectors])


# --------------------------------------------------------------------------- eq. (25)


@given(S.rotations(), S.vectors(5.0), st.floats(-1.0, 1.0))
def test_eq_25_time_derivative_of_an_orientation(C_AB0, w, t0):
    # B turns with body rate B_w_AB = w: C_AB(t) = C_AB0 exp(t w), so Phi_BA(t) = C_AB(t)^T and
    # d Phi_BA / dt (eq. 19) = -B_w_AB. The minus sign is the primer's angular-velocity convention.
    def phi_ba(t):
        return (C_AB0 @ so3.exp(t[0] * w)).T

    (J,) = numerical_jacobian(phi_ba, np.array([t0]), arg_kinds=["vector"], value_kind="rotation")
    assert max_abs(J[:, 0], -w) <= NUM_TOL * scale(w) ** 2


# --------------------------------------------------------------------------- eqs. (26)-(30)


@given(S.rotations(), S.vectors())
def test_eqs_26_27_coordinate_map(C, r):
    JC, Jr = numerical_jacobian(lambda X, x: X @ x, C, r, arg_kinds=["rotation", "vector"])
    assert max_abs(d.rotate_wrt_vector(C), Jr) <= NUM_TOL * scale(r)
    assert max_abs(d.rotate_wrt_rotation(C, r), JC) <= NUM_TOL * scale(r)


@given(S.rotations())
def test_eq_28_inverse(C):
    (J,) = numerical_jacobian(so3.inverse, C, arg_kinds=["rotation"], value_kind="rotation")
    assert max_abs(d.inverse_wrt_rotation(C), J) <= NUM_TOL


@given(S.rotations(), S.rotations())
def test_eqs_29_30_composition(C1, C2):
    J1, J2 = numerical_jacobian(so3.compose, C1, C2, arg_kinds=["rotation"] * 2, value_kind="rotation")
    assert max_abs(d.compose_wrt_left(C1), J1) <= NUM_TOL
    assert max_abs(d.compose_wrt_right(C1), J2) <= NUM_TOL


# --------------------------------------------------------------------------- eqs. (31)-(34)


@given(S.rotation_vectors())
def test_eq_31_exp_wrt_vector_is_gamma_at_every_angle(phi):
    # exp is smooth through pi, so angles up to and including pi are fine here.
    (J,) = numerical_jacobian(so3.exp, phi, arg_kinds=["vector"], value_kind="rotation")
    assert max_abs(d.exp_wrt_vector(phi), J) <= NUM_TOL
    # Gamma(phi) (left) and Gamma(phi)^T (right, GTSAM's ExpmapDerivative) differ by
    # 2 (1 - cos t)/t^2 phi^x; where that is large the [+] derivative must pick the left one.
    t = np.linalg.norm(phi)
    if t > 0.3:
        assert max_abs(so3.gamma(phi).T, J) > 0.05 * t


@given(S.rotation_vectors(min_pi_distance=LOG_MARGIN))
def test_eq_32_log_wrt_rotation_is_gamma_inverse(phi):
    C = so3.exp(phi)
    (J,) = numerical_jacobian(so3.log, C, arg_kinds=["rotation"], value_kind="vector")
    assert max_abs(d.log_wrt_rotation(C), J) <= NUM_TOL
    # with eq. (31), the chain rule on log(exp(phi)) = phi gives Gamma^-1(phi) Gamma(phi) = I
    assert max_abs(d.log_wrt_rotation(C) @ d.exp_wrt_vector(phi), np.eye(3)) <= 16 * EPS


@given(S.rotation_vectors("tiny"))
def test_eq_34_gamma_small_angle_approximation(phi):
    # Gamma = I + phi^x / 2 + phi^x^2 / 6 + O(t^3): the remainder is at most t^2 / 6 entrywise.
    t = np.linalg.norm(phi)
    assert max_abs(so3.gamma(phi), np.eye(3) + 0.5 * so3.skew(phi)) <= t * t / 6 + EPS
    # and the first-order term is really phi^x / 2 (relative to t, round-off only)
    off = ~np.eye(3, dtype=bool)
    assert max_abs(so3.gamma(phi)[off], (0.5 * so3.skew(phi))[off]) <= t * t / 6 + 4 * EPS * t


# --------------------------------------------------------------------------- boxplus and boxminus


@given(S.rotations(), S.rotation_vectors())
def test_boxplus_derivatives(C, phi):
    JC, Jphi = numerical_jacobian(so3.boxplus, C, phi, arg_kinds=["rotation", "vector"], value_kind="rotation")
    assert max_abs(d.boxplus_wrt_rotation(C, phi), JC) <= NUM_TOL
    assert max_abs(d.boxplus_wrt_vector(C, phi), Jphi) <= NUM_TOL


@given(S.rotations(), S.rotation_vectors(min_pi_distance=LOG_MARGIN))
def test_boxminus_derivatives(C2, phi):
    C1 = so3.boxplus(C2, phi)  # C1 [-] C2 = phi, of any angle up to pi - 1e-5
    J1, J2 = numerical_jacobian(so3.boxminus, C1, C2, arg_kinds=["rotation"] * 2, value_kind="vector")
    left, right = d.boxminus_wrt_left(C1, C2), d.boxminus_wrt_right(C1, C2)
    assert max_abs(left, J1) <= NUM_TOL
    assert max_abs(right, J2) <= NUM_TOL
    # from (28), (30), (32): d/dPhi2 = -Gamma^-1(phi) C(Phi1 o Phi2^-1) = -(d/dPhi1) C(exp(phi))
    assert max_abs(right, -left @ so3.exp(phi)) <= 32 * EPS
    # at Phi1 = Phi2 they are +I and -I
    assert max_abs(d.boxminus_wrt_left(C2, C2), np.eye(3)) <= 16 * EPS
    assert max_abs(d.boxminus_wrt_right(C2, C2), -np.eye(3)) <= 16 * EPS


# --------------------------------------------------------------------------- chain rule on a composite


@given(S.rotations(min_pi_distance=LOG_MARGIN), S.rotations(), S.vectors())
def test_chain_rule_on_composite_maps(A, B, r):
    # f(Phi) = (Phi o B) [-] B: the boxminus rule after eq. (29), Gamma^-1(f) I.
    (Jf,) = numerical_jacobian(lambda X: so3.boxminus(X @ B, B), A, arg_kinds=["rotation"])
    assert max_abs(d.boxminus_wrt_left(A @ B, B) @ d.compose_wrt_left(A), Jf) <= NUM_TOL
    # g(Phi) = Phi^-1(r): eq. (27) at Phi^-1, times eq. (28).
    (Jg,) = numerical_jacobian(lambda X: X.T @ r, B, arg_kinds=["rotation"])
    analytic = d.rotate_wrt_rotation(B.T, r) @ d.inverse_wrt_rotation(B)
    assert max_abs(analytic, Jg) <= NUM_TOL * scale(r)


# --------------------------------------------------------------------------- vectorisation


@pytest.mark.parametrize("seed", range(5))
def test_vectorised_derivatives_equal_loops(seed):
    rng = np.random.default_rng(seed)
    P = S.sample_rotation_vectors(rng, (2, 3))
    P *= np.minimum(1.0, (math.pi - LOG_MARGIN) / np.maximum(np.linalg.norm(P, axis=-1, keepdims=True), 1e-300))
    C2 = so3.exp(S.sample_rotation_vectors(rng, (2, 3)))
    C1 = so3.boxplus(C2, P)
    R = rng.normal(size=(2, 3, 3)) * 10
    cases = [
        (d.rotate_wrt_vector, (C1,)), (d.rotate_wrt_rotation, (C1, R)), (d.inverse_wrt_rotation, (C1,)),
        (d.compose_wrt_left, (C1,)), (d.compose_wrt_right, (C1,)), (d.exp_wrt_vector, (P,)),
        (d.log_wrt_rotation, (C1,)), (d.boxplus_wrt_rotation, (C2, P)), (d.boxplus_wrt_vector, (C2, P)),
        (d.boxminus_wrt_left, (C1, C2)), (d.boxminus_wrt_right, (C1, C2)),
    ]
    for f, args in cases:
        batched = f(*args)
        looped = np.array([[f(*(a[i, j] for a in args)) for j in range(3)] for i in range(2)])
        assert batched.shape == (2, 3, 3, 3), f.__name__
        assert max_abs(batched, looped) <= 4 * EPS * max(1.0, np.abs(looped).max()), f.__name__


def test_compose_wrt_left_returns_a_writable_identity_per_batch_entry():
    J = d.compose_wrt_left(np.zeros((4, 3, 3)))
    assert J.shape == (4, 3, 3) and np.array_equal(J, np.broadcast_to(np.eye(3), (4, 3, 3)))
    J[0, 0, 0] = 5.0  # a copy, not a read-only broadcast view
    assert J[1, 0, 0] == 1.0


@pytest.mark.parametrize("distance", [1e-3, 1e-4, LOG_MARGIN])
def test_log_derivative_close_to_pi(distance):
    # The worst place for eq. (32): Gamma^-1 grows like 1/(pi - t) in no entry, but log is
    # discontinuous just beyond; the derivative must still match within NUM_TOL at pi - 1e-5.
    axis = np.array([0.48, -0.6, 0.64])
    C = so3.exp((math.pi - distance) * axis)
    (J,) = numerical_jacobian(so3.log, C, arg_kinds=["rotation"])
    assert max_abs(d.log_wrt_rotation(C), J) <= NUM_TOL
