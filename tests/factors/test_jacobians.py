"""factors.jacobians: numerical differentiation on manifolds, ``compare``, and ``check_factor`` on
any GTSAM factor -- a user's ``gtsam.CustomFactor`` (Rot3, Point3 and Vector keys, analytic
Jacobians in GTSAM's chart), native factors, robust noise models -- including proof that the
checker FAILS a factor with one wrong Jacobian block.

``check_factor`` compares whitened Jacobians with default ``atol`` = 1e-6 sigma per unit and
``rtol`` = 1e-5; a correct factor shows ~1e-9 (central differences, step 1e-6), a wrong block O(1).
The tests assert the verdict and the measured errors, e.g. ``max_abs_error < 1e-7`` for correct
factors, so a checker that compared nothing would fail them.
"""
from __future__ import annotations

import json
import math

import gtsam
import numpy as np
import pytest
import strategies as S
from hypothesis import given, settings
from hypothesis import strategies as st

from factors import chart, so3
from factors import derivatives as d
from factors import jacobians as J
from factors.jacobians import numerical_jacobian

R0, P0, V0 = gtsam.symbol("R", 0), gtsam.symbol("p", 0), gtsam.symbol("v", 0)
R1 = gtsam.symbol("R", 1)
CORRECT = 1e-7  # largest error we accept from a correct factor (measured ~1e-9)


def max_abs(a, b) -> float:
    return float(np.max(np.abs(np.asarray(a) - np.asarray(b))))


# ============================================================================ numerical_jacobian


@given(st.integers(0, 2**32 - 1))
def test_linear_map_is_recovered(seed):
    rng = np.random.default_rng(seed)
    A, x = rng.normal(size=(4, 3)), rng.normal(size=3) * 10
    (Jx,) = numerical_jacobian(lambda v: A @ v, x)
    # round-off only: EPS |A x| / step ~ 1e-9 at most here
    assert Jx.shape == (4, 3)
    assert max_abs(Jx, A) <= 1e-8


@given(st.lists(st.floats(-2, 2), min_size=3, max_size=3).map(np.array))
def test_central_differences_exactly(x):
    # For x^3 the central difference is 3 x^2 + h^2 exactly (a forward one would add 3 x h):
    # this pins down both the formula and the use of ``step``.
    h = 1e-3
    (Jx,) = numerical_jacobian(lambda v: v**3, x, step=h)
    assert max_abs(Jx, np.diag(3 * x**2 + h * h)) <= 1e-10


@given(S.rotations(), S.vectors())
def test_rotation_arguments_as_matrix_or_rot3_and_left_perturbation(C, r):
    (Jm,) = numerical_jacobian(lambda X: X @ r, C)
    (Jg,) = numerical_jacobian(lambda X: X.rotate(r), gtsam.Rot3(C))  # kind detected from Rot3
    assert max_abs(Jm, Jg) <= 1e-8 * max(1.0, np.abs(r).max())
    # the perturbation is the primer's LEFT one: eq. (27), not GTSAM's -C r^x
    assert max_abs(Jm, -so3.skew(C @ r)) <= 1e-8 * max(1.0, np.abs(r).max())


@given(S.rotations())
def test_rotation_values_are_compared_with_boxminus(C):
    # f = identity: the derivative of a rotation w.r.t. itself is I in the [+]/[-] sense
    (J1,) = numerical_jacobian(lambda X: X, C)
    assert J1.shape == (3, 3) and max_abs(J1, np.eye(3)) <= 1e-8
    # a Rot3 value is a rotation value too
    (J2,) = numerical_jacobian(lambda X: gtsam.Rot3(X), C, arg_kinds=["rotation"])
    assert max_abs(J2, np.eye(3)) <= 1e-8


def test_kind_overrides_and_detection():
    C = so3.exp(np.array([0.3, -0.2, 0.9]))
    # a rotation matrix treated as a vector: 9 columns (entries), value flattened: 9 rows
    (Jv,) = numerical_jacobian(lambda X: 2.0 * X, C, arg_kinds=["vector"], value_kind="vector")
    assert Jv.shape == (9, 9) and max_abs(Jv, 2 * np.eye(9)) <= 1e-8
    # an orthonormal matrix with det -1 is not a rotation: detected as a vector argument
    reflection = np.diag([1.0, 1.0, -1.0])
    (Jr,) = numerical_jacobian(lambda X: X.sum(), reflection)
    assert Jr.shape == (1, 9) and max_abs(Jr, np.ones((1, 9))) <= 1e-8
    # the rotation value of so3.exp is detected, the vector value of so3.log too
    (Je,) = numerical_jacobian(so3.exp, np.array([0.1, 0.2, 0.3]))
    assert max_abs(Je, so3.gamma(np.array([0.1, 0.2, 0.3]))) <= 1e-8


class Scaled(J.Manifold):
    """R^2 with x [+] d = x + 2 d: its increments are half-size."""

    dim = 2

    def plus(self, x, delta):
        return np.asarray(x) + 2.0 * np.asarray(delta)

    def minus(self, a, b):
        return (np.asarray(a) - np.asarray(b)) / 2.0


def test_manifold_kinds_for_arguments_and_values():
    x = np.array([1.0, -3.0])
    (Ja,) = numerical_jacobian(lambda v: v, x, arg_kinds=[Scaled()], value_kind="vector")
    assert max_abs(Ja, 2 * np.eye(2)) <= 1e-8
    (Jb,) = numerical_jacobian(lambda v: v, x, arg_kinds=["vector"], value_kind=Scaled())
    assert max_abs(Jb, 0.5 * np.eye(2)) <= 1e-8
    (Jc,) = numerical_jacobian(lambda v: v, x, arg_kinds=[Scaled()], value_kind=Scaled())
    assert max_abs(Jc, np.eye(2)) <= 1e-8


@pytest.mark.parametrize("where", ["arg", "value"])
@pytest.mark.parametrize("kind", ["quaternion", "Rotation", object()])
def test_unknown_kinds_raise_value_error(where, kind):
    x = np.ones(3)
    kw = {"arg_kinds": [kind]} if where == "arg" else {"value_kind": kind}
    with pytest.raises(ValueError, match="kind"):
        numerical_jacobian(lambda v: 2 * v, x, **kw)


def test_arg_kinds_length_must_match():
    with pytest.raises(ValueError, match="2 entries for 1 arguments"):
        numerical_jacobian(lambda v: v, np.ones(3), arg_kinds=["vector", "vector"])


# ============================================================================ compare, table


def test_compare_verdict_is_entrywise_atol_plus_rtol():
    num = np.array([[1.0, -4.0], [0.0, 2.0]])
    atol, rtol = 1e-6, 1e-3
    limit = atol + rtol * np.abs(num)
    assert J.compare("x", num + 0.999 * limit, num, atol, rtol).ok
    bad = num.copy()
    bad[1, 0] += 1.01 * atol  # one entry just over its bound
    c = J.compare("x", bad, num, atol, rtol)
    assert not c.ok
    assert c.max_abs_error == pytest.approx(1.01 * atol, rel=1e-9)
    # relative error is normalised by max(|numerical|, 1) = 4
    c = J.compare("x", num + np.array([[0, 0.4], [0, 0]]), num, atol, rtol)
    assert c.max_rel_error == pytest.approx(0.1, rel=1e-12)


def test_compare_small_jacobians_are_normalised_by_one():
    c = J.compare("tiny", np.array([[2e-3]]), np.array([[1e-3]]), 1e-6, 1e-6)
    assert c.max_rel_error == pytest.approx(1e-3, rel=1e-9) and not c.ok


def test_compare_rejects_shape_mismatch_and_fails_non_finite():
    with pytest.raises(ValueError, match="name: analytic Jacobian has shape"):
        J.compare("name", np.zeros((3, 3)), np.zeros((3, 2)), 1e-6, 1e-6)
    for bad in (np.nan, np.inf):
        c = J.compare("nan", np.array([[bad]]), np.array([[0.0]]), 1.0, 1.0)
        assert not c.ok and c.max_abs_error == math.inf


def test_comparison_as_dict_and_table():
    rows = [J.Comparison("first check", 1e-10, 2e-10, True), J.Comparison("second", np.float64(3.0), 0.5, False)]
    dicts = [r.as_dict() for r in rows]
    assert json.loads(json.dumps(dicts)) == [
        {"name": "first check", "max_abs_error": 1e-10, "max_rel_error": 2e-10, "ok": True},
        {"name": "second", "max_abs_error": 3.0, "max_rel_error": 0.5, "ok": False},
    ]
    text = J.table(rows, title="T")
    lines = text.splitlines()
    assert lines[0] == "T" and len(lines) == 4
    assert lines[2].startswith("first check") and lines[2].endswith("ok")
    assert lines[3].startswith("second") and lines[3].endswith("FAIL") and "3.000e+00" in lines[3]


# ============================================================================ check_factor

# A user's factor on (Rot3 R, Point3 p, Vector v): e = R^T (p - m) + v, i.e. Phi^-1(p - m) + v.
# Jacobians written in the primer's convention and passed through the chart adapter for R:
#   d e / d Phi = (eq. 27 at Phi^-1)(eq. 28) = (C^T y)^x C^T,  d e / d p = C^T,  d e / d v = I.


def _values(C, p, v, C1=None):
    values = gtsam.Values()
    values.insert(R0, gtsam.Rot3(C))
    values.insert(P0, np.asarray(p, dtype=float))
    values.insert(V0, np.asarray(v, dtype=float))
    if C1 is not None:
        values.insert(R1, gtsam.Rot3(C1))
    return values


def point_factor(noise, m, wrong=None):
    """The factor above; ``wrong`` in {None, "R-sign", "R-no-chart", "p-transposed", "v-tiny"} breaks
    exactly one block."""
    m = np.asarray(m, dtype=float)

    def error(this, values, H):
        C = values.atRot3(this.keys()[0]).matrix()
        p, v = values.atPoint3(this.keys()[1]), values.atVector(this.keys()[2])
        y = p - m
        e = C.T @ y + v
        if H is not None:  # GTSAM segfaults if H is requested and not filled
            primer = d.rotate_wrt_rotation(C.T, y) @ d.inverse_wrt_rotation(C)
            H_R = chart.to_gtsam_chart(primer, C)
            H_p, H_v = C.T.copy(), np.eye(3)
            if wrong == "R-sign":
                H_R = -H_R
            elif wrong == "R-no-chart":
                H_R = primer  # forgot the adapter: right for C = I only
            elif wrong == "p-transposed":
                H_p = C.copy()
            elif wrong == "v-tiny":
                H_v = H_v + 1e-4 * np.array([[0, 1, 0], [0, 0, 0], [0, 0, 0]])
            H[0], H[1], H[2] = H_R, H_p, H_v
        return e

    return gtsam.CustomFactor(noise, [R0, P0, V0], error)


def log_factor(noise, Z):
    """A log-based factor on two rotations: e = (R0 o Z) [-] R1 = log(C0 Z C1^T)."""
    Z = np.asarray(Z, dtype=float)

    def error(this, values, H):
        C0, C1 = values.atRot3(this.keys()[0]).matrix(), values.atRot3(this.keys()[1]).matrix()
        e = so3.boxminus(C0 @ Z, C1)
        if H is not None:
            H[0] = chart.to_gtsam_chart(d.boxminus_wrt_left(C0 @ Z, C1) @ d.compose_wrt_left(C0), C0)
            H[1] = chart.to_gtsam_chart(d.boxminus_wrt_right(C0 @ Z, C1), C1)
        return e

    return gtsam.CustomFactor(noise, [R0, R1], error)


SIGMAS = gtsam.noiseModel.Diagonal.Sigmas(np.array([0.1, 0.2, 0.5]))


@settings(max_examples=30)
@given(S.rotations(), S.vectors(), S.vectors(), S.vectors())
def test_check_factor_passes_a_correct_custom_factor(C, p, v, m):
    result = J.check_factor(point_factor(SIGMAS, m), _values(C, p, v))
    assert result.ok and bool(result), str(result)
    assert result.keys == [R0, P0, V0]
    assert [c.name for c in result.comparisons] == ["R0", "p0", "v0"]
    assert max(result.max_abs_error.values()) < CORRECT * max(1.0, np.abs(p - m).max())
    # the analytic side is the factor's own whitened Jacobian
    A, _ = point_factor(SIGMAS, m).linearize(_values(C, p, v)).jacobian()
    assert np.array_equal(np.hstack([result.analytic[k] for k in (R0, P0, V0)]), A)
    assert result.numerical[P0].shape == (3, 3)


@settings(max_examples=30)
@given(S.rotations(), S.rotations(), S.rotation_vectors(min_pi_distance=1e-4))
def test_check_factor_passes_a_log_based_custom_factor_up_to_near_pi(C0, Z, phi):
    C1 = so3.boxplus(C0 @ Z, -phi)  # residual (C0 Z) [-] C1 = phi, up to pi - 1e-4 in angle
    result = J.check_factor(log_factor(SIGMAS, Z), _values(C0, np.zeros(3), np.zeros(3), C1=C1))
    assert result.ok, str(result)
    assert max(result.max_abs_error.values()) < CORRECT * 10  # 1/sigma = 10 whitening


@pytest.mark.parametrize(
    "wrong, bad_key",
    [("R-sign", "R0"), ("R-no-chart", "R0"), ("p-transposed", "p0"), ("v-tiny", "v0")],
)
def test_check_factor_fails_a_factor_with_one_wrong_block(wrong, bad_key):
    C = so3.exp(np.array([0.4, -1.1, 0.8]))  # C != C^T, so transposes and charts matter
    values = _values(C, np.array([1.0, -2.0, 3.0]), np.array([0.5, 0.1, -0.2]))
    result = J.check_factor(point_factor(SIGMAS, np.array([-1.0, 0.5, 2.0]), wrong=wrong), values)
    assert not result.ok and not bool(result)
    verdicts = {c.name: c.ok for c in result.comparisons}
    assert verdicts == {k: k != bad_key for k in ("R0", "p0", "v0")}
    # the error found is the planted one: 1e-4 / sigma_0 = 1e-3 for "v-tiny", O(1) otherwise
    worst = result.max_abs_error[bad_key]
    if wrong == "v-tiny":
        assert worst == pytest.approx(1e-3, rel=1e-3)
    else:
        assert worst > 0.1
    line = [text for text in str(result).splitlines() if text.startswith(bad_key)][0]
    assert line.endswith("FAIL") and "CustomFactor: FAIL" in str(result)


# ---------------------------------------------------------------------------- native factors


def _pose(rng):
    phi = S.sample_rotation_vectors(rng, ())
    return gtsam.Pose3(gtsam.Rot3.Expmap(phi), rng.normal(size=3) * 5)


@pytest.mark.parametrize("seed", range(4))
def test_check_factor_passes_native_factors(seed):
    rng = np.random.default_rng(seed)
    X1, X2, L = gtsam.symbol("x", 1), gtsam.symbol("x", 2), gtsam.symbol("l", 1)
    values = gtsam.Values()
    values.insert(X1, _pose(rng))
    values.insert(X2, _pose(rng))
    values.insert(R0, gtsam.Rot3.Expmap(rng.normal(size=3)))
    values.insert(R1, gtsam.Rot3.Expmap(rng.normal(size=3)))
    values.insert(L, rng.normal(size=3) * 5)
    values.insert(V0, rng.normal(size=3))
    n3 = gtsam.noiseModel.Diagonal.Sigmas(np.array([0.1, 0.2, 0.3]))
    n6 = gtsam.noiseModel.Diagonal.Sigmas(np.array([0.05, 0.05, 0.05, 0.3, 0.3, 0.3]))
    # measurements near the truth, so the relative rotations stay away from pi
    rel = values.atPose3(X1).between(values.atPose3(X2)).retract(rng.normal(size=6) * 0.1)
    factors = [
        gtsam.PriorFactorRot3(R0, gtsam.Rot3.Expmap(rng.normal(size=3) * 0.1).compose(values.atRot3(R0)), n3),
        gtsam.BetweenFactorRot3(R0, R1, values.atRot3(R0).between(values.atRot3(R1)), n3),
        gtsam.PriorFactorPose3(X1, values.atPose3(X1).retract(rng.normal(size=6) * 0.1), n6),
        gtsam.BetweenFactorPose3(X1, X2, rel, n6),
        gtsam.PriorFactorPoint3(L, rng.normal(size=3), n3),
        gtsam.PriorFactorVector(V0, rng.normal(size=3), n3),
    ]
    for factor in factors:
        result = J.check_factor(factor, values)
        assert result.ok, str(result)
        assert result.factor_name == type(factor).__name__
        assert max(result.max_abs_error.values()) < CORRECT * 20, str(result)  # 1/sigma <= 20


# ---------------------------------------------------------------------------- robust noise models


def _robust(k=0.3, scheme=None):
    huber = (gtsam.noiseModel.mEstimator.Huber.Create(k) if scheme is None
             else gtsam.noiseModel.mEstimator.Huber.Create(k, scheme))
    return gtsam.noiseModel.Robust.Create(huber, SIGMAS)


def _far_values():
    # a whitened error of norm ~30, far beyond the Huber threshold: weight ~0.01
    C = so3.exp(np.array([0.4, -1.1, 0.8]))
    return _values(C, np.array([1.0, -2.0, 3.0]), np.array([0.5, 0.1, -0.2])), np.array([-1.0, 0.5, 2.0])


def test_robust_native_factor_is_checked_through_its_gaussian_base():
    values, _ = _far_values()
    target = gtsam.Rot3.Expmap(np.array([1.0, 0.5, -0.3]))
    robust = gtsam.PriorFactorRot3(R0, target, _robust())
    gaussian = gtsam.PriorFactorRot3(R0, target, SIGMAS)
    A_robust, b_robust = robust.linearize(values).jacobian()
    A_gauss, b_gauss = gaussian.linearize(values).jacobian()
    assert np.linalg.norm(b_robust) < 0.5 * np.linalg.norm(b_gauss)  # the weight is really active
    result = J.check_factor(robust, values)
    assert result.ok, str(result)
    assert max_abs(result.analytic[R0], A_gauss) <= 1e-12 * np.abs(A_gauss).max()
    assert max(result.max_abs_error.values()) < CORRECT * 10


def test_robust_custom_factor_passes_and_a_wrong_one_still_fails():
    values, m = _far_values()
    gaussian = J.check_factor(point_factor(SIGMAS, m), values)
    robust = J.check_factor(point_factor(_robust(), m), values)
    assert robust.ok, str(robust)
    for key in (R0, P0, V0):
        assert (max_abs(robust.analytic[key], gaussian.analytic[key])
                <= 1e-12 * max(1.0, np.abs(gaussian.analytic[key]).max()))
    assert not J.check_factor(point_factor(_robust(), m, wrong="R-sign"), values).ok


def test_robust_custom_factor_with_scalar_reweighting():
    # Scalar reweighting weights each row by its own |e_i|: rows below and above the threshold.
    values, m = _far_values()
    scheme = gtsam.noiseModel.mEstimator.Base.ReweightScheme.Scalar
    factor = point_factor(_robust(k=3.0, scheme=scheme), m)
    e = SIGMAS.whiten(factor.unwhitenedError(values))
    assert np.min(np.abs(e)) < 3.0 < np.max(np.abs(e))  # mixed weights: the interesting case
    result = J.check_factor(factor, values)
    assert result.ok, str(result)


# ---------------------------------------------------------------------------- errors


def test_check_factor_names_missing_keys():
    values = gtsam.Values()
    values.insert(R0, gtsam.Rot3())
    with pytest.raises(KeyError, match=r"p0.*v0"):
        J.check_factor(point_factor(SIGMAS, np.zeros(3)), values)


def test_check_factor_result_summary():
    values, m = _far_values()
    result = J.check_factor(point_factor(SIGMAS, m), values)
    text = str(result).splitlines()
    assert text[0] == "CustomFactor: ok"
    assert [line.split()[0] for line in text[2:]] == ["R0", "p0", "v0"]
    assert set(result.max_rel_error) == {"R0", "p0", "v0"}
    assert all(0 <= x < CORRECT for x in result.max_rel_error.values())


def test_check_factor_tolerances_are_honoured():
    # the planted 1e-3 (whitened) error of "v-tiny" passes with atol = 2e-3 and fails with 5e-4
    values, m = _far_values()
    factor = point_factor(SIGMAS, m, wrong="v-tiny")
    assert J.check_factor(factor, values, atol=2e-3).ok
    assert not J.check_factor(factor, values, atol=5e-4).ok


def test_check_factor_refuses_a_hessian_linearisation():
    # A HessianFactor carries A^T A, not A: there is no Jacobian to check, and converting it
    # would silently compare a Cholesky factor. LinearContainerFactor returns the Hessian as is.
    X = gtsam.symbol("x", 1)
    values = gtsam.Values()
    values.insert(X, np.zeros(3))
    hessian = gtsam.LinearContainerFactor(gtsam.HessianFactor(X, 4 * np.eye(3), np.ones(3), 1.0), values)
    with pytest.raises(TypeError, match="LinearContainerFactor gave HessianFactor"):
        J.check_factor(hessian, values)
    # the same container around a JacobianFactor is checked normally, and exactly (it is linear)
    jacobian = gtsam.LinearContainerFactor(
        gtsam.JacobianFactor(X, 2 * np.eye(3), np.ones(3), gtsam.noiseModel.Unit.Create(3)), values)
    result = J.check_factor(jacobian, values)
    assert result.ok and max_abs(result.analytic[X], 2 * np.eye(3)) == 0.0
    assert result.max_abs_error["x1"] < 1e-9
