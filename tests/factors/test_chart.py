"""factors.chart.to_gtsam_chart: the one adapter from a primer Jacobian (left increment,
``Phi [+] phi = exp(phi) o Phi``) to GTSAM's chart (right increment, ``R.retract(d) = R Exp(d)``).

The proof is against GTSAM's own numerical derivative (``gtsam.utils.numerical_derivative``,
which perturbs with ``Rot3.retract``) on functions GTSAM evaluates itself: ``Rot3.rotate``,
``Rot3.unrotate``, ``Rot3.Logmap`` of a composition, and a scalar.

Tolerance: numericalDerivative11 uses central differences with delta = 1e-5, so its error is
about delta^2 |f'''| / 6 + EPS |f| / delta ~ 2e-11 per unit of |f|; ``TOL`` = 1e-9 per unit is
50x that and 1e8 times smaller than the O(1) error of a missing or transposed ``C``.
"""
from __future__ import annotations

import gtsam
import numpy as np
import strategies as S
from gtsam.utils.numerical_derivative import numericalDerivative11
from hypothesis import given, settings
from hypothesis import strategies as st
from strategies import EPS

from factors import chart, so3
from factors import derivatives as d

TOL = 1e-9
LOG_MARGIN = 1e-4  # keep log's argument this far from pi (delta = 1e-5 steps must not cross it)


def max_abs(a, b) -> float:
    return float(np.max(np.abs(np.asarray(a) - np.asarray(b))))


def scale(v) -> float:
    return max(1.0, float(np.abs(v).max()))


@given(S.rotations(), S.vectors())
def test_rotating_a_point(C, p):
    R = gtsam.Rot3(C)
    gtsam_numerical = numericalDerivative11(lambda X: X.rotate(p), R)
    primer = d.rotate_wrt_rotation(C, p)  # eq. (27): -(C p)^x
    assert max_abs(chart.to_gtsam_chart(primer, R), gtsam_numerical) <= TOL * scale(p)


@given(S.rotations(), S.vectors())
def test_unrotating_a_point(C, p):
    # Phi^-1(p): eq. (27) at Phi^-1 times eq. (28), then the adapter
    R = gtsam.Rot3(C)
    gtsam_numerical = numericalDerivative11(lambda X: X.unrotate(p), R)
    primer = d.rotate_wrt_rotation(C.T, p) @ d.inverse_wrt_rotation(C)
    assert max_abs(chart.to_gtsam_chart(primer, C), gtsam_numerical) <= TOL * scale(p)


@given(S.rotations(), S.rotations(min_pi_distance=LOG_MARGIN))
def test_logmap_of_a_composition(C, D):
    # f(R) = Logmap(R S) with S chosen so that R S = D stays LOG_MARGIN away from pi.
    R, S_ = gtsam.Rot3(C), gtsam.Rot3(C.T @ D)
    gtsam_numerical = numericalDerivative11(lambda X: gtsam.Rot3.Logmap(X.compose(S_)), R)
    primer = d.log_wrt_rotation(C @ S_.matrix()) @ d.compose_wrt_left(C)  # eqs. (32), (29)
    assert max_abs(chart.to_gtsam_chart(primer, R), gtsam_numerical) <= TOL


@given(S.rotations(), S.vectors(), S.vectors())
def test_a_scalar_function(C, p, q):
    R = gtsam.Rot3(C)
    gtsam_numerical = numericalDerivative11(lambda X: float(p @ X.rotate(q)), R)
    primer = p[None, :] @ d.rotate_wrt_rotation(C, q)
    assert max_abs(chart.to_gtsam_chart(primer, R), gtsam_numerical) <= TOL * scale(p) * scale(q)


@given(S.rotations(), S.rotations())
def test_a_rotation_valued_function_needs_the_output_side_too(C, D):
    # The adapter converts the INPUT increment. For a Rot3-valued f, GTSAM also measures the output
    # in its right chart, d_out = C(f)^T phi_out; with that, f(R) = R S has Jacobian S^T (GTSAM's
    # Adjoint of S^-1), built here from the primer's eq. (29).
    R, S_ = gtsam.Rot3(C), gtsam.Rot3(D)
    gtsam_numerical = numericalDerivative11(lambda X: X.compose(S_), R)
    out = C @ D
    ours = out.T @ chart.to_gtsam_chart(d.compose_wrt_left(C), R)
    assert max_abs(ours, gtsam_numerical) <= TOL
    assert max_abs(ours, D.T) <= 16 * EPS


@given(S.asymmetric_rotations(), S.vectors(1.0).filter(lambda p: np.linalg.norm(p) > 0.5))
def test_the_adapter_is_needed_and_goes_the_right_way(C, p):
    # Without it (or with C^T instead of C) the Jacobian is wrong by O(|p|): the charts differ.
    R = gtsam.Rot3(C)
    gtsam_numerical = numericalDerivative11(lambda X: X.rotate(p), R)
    primer = d.rotate_wrt_rotation(C, p)
    assert max_abs(chart.to_gtsam_chart(primer, R), gtsam_numerical) <= TOL
    assert max_abs(primer, gtsam_numerical) > 1e-3
    assert max_abs(primer @ C.T, gtsam_numerical) > 1e-3


@given(S.rotations(), S.rotation_vectors())
def test_gtsam_retract_is_the_boxplus_of_the_rotated_increment(C, d_gtsam):
    # The fact the adapter rests on: R Exp(d) = exp(C d) o R (eq. 24), i.e. phi = C d.
    R = gtsam.Rot3(C)
    assert max_abs(R.retract(d_gtsam).matrix(), so3.boxplus(C, C @ d_gtsam)) <= 32 * EPS


@settings(max_examples=25)
@given(st.lists(S.rotations(), min_size=4, max_size=4), st.lists(S.vectors(), min_size=4, max_size=4))
def test_adapter_accepts_rot3_matrices_and_batches(Cs, ps):
    Cs = np.array(Cs)
    J = d.rotate_wrt_rotation(Cs, np.array(ps))  # (4, 3, 3)
    batched = chart.to_gtsam_chart(J, Cs)
    for i in range(4):
        single = chart.to_gtsam_chart(J[i], gtsam.Rot3(Cs[i]))
        assert max_abs(batched[i], single) <= 4 * EPS * scale(ps[i])
        assert np.array_equal(chart.to_gtsam_chart(J[i], Cs[i]), J[i] @ Cs[i])
    # a 2x3 Jacobian (two outputs) keeps its shape
    assert chart.to_gtsam_chart(np.ones((2, 3)), Cs[0]).shape == (2, 3)
