"""Sensor models with extrinsics (factors.sensor_models), over every kind of the registry: each
Jacobian against its numerical twin at random states and extrinsics, attitudes of every size
(below 1e-6 rad, near pi), through the kernels (EKF, batch solver) and through GTSAM
(check_factor on the factors)."""
import gtsam
import numpy as np
import pytest
import strategies as S
from gtsam_values import insert_state
from hypothesis import given, settings
from hypothesis import strategies as st

from datasets.kinds import KINDS
from factors import imu, selfcheck, so3
from factors import sensor_models as sm
from factors.jacobians import check_factor, numerical_jacobian
from factors.keys import keyframe_keys

ONE_STATE = [k for k in KINDS.values() if not k.relative]


def _state(rng, regime):
    return imu.ImuState(r=rng.normal(size=3) * 10, v=rng.normal(size=3) * 5,
                        C=selfcheck.random_rotation(rng, regime), b_f=rng.normal(size=3) * 0.5,
                        b_w=rng.normal(size=3) * 0.2)


@pytest.mark.parametrize("kind", KINDS.values(), ids=lambda k: k.name)
def test_kernel_jacobian_equals_central_differences_at_300_points(kind):
    """The kind's registered self-check (its own random rows, :attr:`Kind.random_row`: attitudes
    tiny, near pi and of any size among them, against central differences on the state's
    boxplus) at 300 points, to 1e-6."""
    (result,) = selfcheck.run_checks(samples=300, seed=sum(map(ord, kind.name)),
                                     names=[f"{kind.name} measurement: H of its residual, extrinsic T_BS"])
    assert result.ok and result.max_abs_error < 1e-6, result


@pytest.mark.parametrize("kind", ONE_STATE, ids=lambda k: k.name)
def test_gtsam_factor_passes_check_factor_at_1000_points(kind):
    """The GTSAM factor (chart adapter included) at the kind's random rows at 1000 points (their
    attitudes a quarter below 1e-6 rad, a quarter within 1e-3 of pi)."""
    rng = np.random.default_rng(7)
    keys = keyframe_keys(0)
    for i in range(1000):
        x, row = kind.random_row(rng)
        values = gtsam.Values()
        insert_state(values, keys, x)
        factor = sm.sensor_factor(kind.model, keys, row, gtsam.noiseModel.Isotropic.Sigma(kind.dim, 0.1))
        result = check_factor(factor, values, atol=1e-5)
        assert result.ok, (i, str(result))


def test_odometry_factor_passes_check_factor_at_1000_points():
    rng = np.random.default_rng(8)
    ki, kj = keyframe_keys(0), keyframe_keys(1)
    for i in range(1000):
        regime = ("tiny", "near_pi", "any")[i % 3]
        xi = _state(rng, regime)
        T = selfcheck.random_extrinsic(rng)
        Cj = xi.C @ T[:3, :3] @ selfcheck.random_rotation(rng, regime, pi_margin=1e-4) @ T[:3, :3].T
        xj = _state(rng, regime).replace(C=Cj)
        dr, dC = rng.normal(size=3), selfcheck.random_rotation(rng, "any")
        e = sm.odometry_residual(xi.C, xi.r, xj.C, xj.r, dr, dC, T)
        dC = so3.exp(-e[3:]) @ dC if np.linalg.norm(e[3:]) > 3.0 else dC  # keep away from log's jump at pi
        values = gtsam.Values()
        insert_state(values, ki, xi)
        insert_state(values, kj, xj)
        factor = sm.odometry_factor(ki, kj, dr, dC, T, gtsam.noiseModel.Isotropic.Sigma(6, 0.1))
        result = check_factor(factor, values, atol=1e-5)
        assert result.ok, (i, str(result))


def test_identity_extrinsic_reduces_to_the_imu_centred_models():
    """At ``T_BS = I``: pose ``(r - z, log(C Z^T))``, velocity ``v - z``, odometry
    ``(C_i^T (r_j - r_i) - dr, log(C_i^T C_j dC^T))`` (primer eqs. 61-63)."""
    rng = np.random.default_rng(3)
    x = _state(rng, "any")
    z, Z = rng.normal(size=3), so3.boxplus(x.C, rng.normal(size=3) * 0.2)
    e, _ = sm.evaluate_one(sm.POSE, x, sm.pack_pose(z[None], Z[None])[0])
    np.testing.assert_allclose(e, np.concatenate([x.r - z, so3.log(x.C @ Z.T)]), atol=1e-14)
    e, _ = sm.evaluate_one(sm.VELOCITY, x, sm.pack_velocity(z[None], rng.normal(size=(1, 3)))[0])
    np.testing.assert_allclose(e, x.v - z, atol=1e-14)
    xj = _state(rng, "any")
    dC = so3.boxplus(x.C.T @ xj.C, rng.normal(size=3) * 0.2)
    expected = np.concatenate([x.C.T @ (xj.r - x.r) - z, so3.log(x.C.T @ xj.C @ dC.T)])
    np.testing.assert_allclose(sm.odometry_residual(x.C, x.r, xj.C, xj.r, z, dC), expected, atol=1e-13)


def test_models_predict_the_sensor_frame():
    """Zero residual when the measurement is the sensor frame's own pose and velocity, computed
    independently from the rigid-body formulas."""
    rng = np.random.default_rng(4)
    x, T = _state(rng, "any"), selfcheck.random_extrinsic(rng)
    p = T[:3, 3]
    w = rng.normal(size=3)
    T_IB = np.eye(4)
    T_IB[:3, :3], T_IB[:3, 3] = x.C, x.r
    T_IS = T_IB @ T
    omega = w - x.b_w
    world_velocity_of_S = x.C @ x.v + x.C @ np.cross(omega, p)
    e, _ = sm.evaluate_one(sm.POSE, x, sm.pack_pose(T_IS[None, :3, 3], T_IS[None, :3, :3], T)[0])
    np.testing.assert_allclose(e, 0, atol=1e-12)
    e, _ = sm.evaluate_one(sm.VELOCITY, x, sm.pack_velocity((T_IS[:3, :3].T @ world_velocity_of_S)[None],
                                                             w[None], T)[0])
    np.testing.assert_allclose(e, 0, atol=1e-12)


def test_rows_of_the_wrong_width_and_single_measurements_are_refused():
    """A row of another layout would be read past its end by the compiled kernel; a single
    measurement given to pack_* would be read as three rows."""
    from factors.errors import InputError

    x = imu.ImuState.identity()
    with pytest.raises(InputError, match="position measurement row: expected 6 numbers"):
        sm.evaluate_one(sm.POSITION, x, np.zeros(5))
    with pytest.raises(InputError, match="expected 24 numbers"):
        sm.sensor_factor(sm.POSE, keyframe_keys(0), np.zeros(6), gtsam.noiseModel.Unit.Create(6))
    with pytest.raises(InputError, match="leading dimension"):
        sm.pack_position([1.0, 2.0, 3.0])


def _yawed(angle, C):
    return so3.exp(np.array([0.0, 0.0, angle])) @ C


@settings(max_examples=1000)
@given(S.imu_states(), S.rotations(), S.rotation_vectors("any"), st.floats(-np.pi, np.pi))
def test_roll_pitch_jacobian_equals_central_differences_at_1000_points(x, R, tilt, heading):
    """At attitudes of every regime (below 1e-6 rad, ordinary, within 1e-3 of pi), extrinsic
    rotations of every regime, measured tilts up to pi and any measured heading."""
    T = np.eye(4)
    T[:3, :3] = R
    Z = _yawed(heading, so3.exp(0.3 / np.pi * tilt) @ x.C @ R)  # tilted by up to 0.3 rad
    row = sm.pack_orientation(Z[None], T)[0]
    _, H = sm.evaluate_one(sm.ROLL_PITCH, x, row)
    num = numerical_jacobian(lambda s: sm.evaluate_one(sm.ROLL_PITCH, s, row)[0], x, arg_kinds=[imu.StateManifold],
                         value_kind="vector")[0]
    np.testing.assert_allclose(H, num, atol=1e-6, rtol=1e-6)


@settings(max_examples=300)
@given(S.imu_states(), S.rotations(), st.floats(-np.pi, np.pi), st.floats(-np.pi, np.pi))
def test_roll_pitch_ignores_both_headings(x, R, state_heading, measured_heading):
    """Turning the state about the world vertical changes neither the residual nor its Jacobian;
    turning the measurement turns the residual within the horizontal plane, its size kept."""
    T = np.eye(4)
    T[:3, :3] = R
    Z = so3.boxplus(x.C @ R, np.array([0.05, -0.03, 0.4]))
    row = sm.pack_orientation(Z[None], T)[0]
    e, H = sm.evaluate_one(sm.ROLL_PITCH, x, row)
    e_turned, H_turned = sm.evaluate_one(sm.ROLL_PITCH, x.replace(C=_yawed(state_heading, x.C)), row)
    np.testing.assert_allclose(e_turned, e, atol=1e-12)
    np.testing.assert_allclose(H[:, 8], 0.0, atol=0.0)
    np.testing.assert_allclose(H_turned[:, 8], 0.0, atol=0.0)
    e_meas, _ = sm.evaluate_one(sm.ROLL_PITCH, x, sm.pack_orientation(_yawed(measured_heading, Z)[None], T)[0])
    np.testing.assert_allclose(np.linalg.norm(e_meas), np.linalg.norm(e), atol=1e-12)


@given(S.rotations(), S.rotations(), S.rotation_vectors("tiny"))
def test_roll_pitch_is_the_tilt_part_of_the_attitude_error_for_small_errors(C, R, eps):
    """``e = (eps_x, eps_y)`` of ``eps = log(C R Z^T)`` to first order, also upside down and at
    any heading (tiny errors: the second-order part is below 1e-12)."""
    T = np.eye(4)
    T[:3, :3] = R
    Z = so3.exp(-eps) @ C @ R  # so that C R Z^T = exp(eps)
    x = imu.ImuState.identity().replace(C=C)
    e, _ = sm.evaluate_one(sm.ROLL_PITCH, x, sm.pack_orientation(Z[None], T)[0])
    full, _ = sm.evaluate_one(sm.ORIENTATION, x, sm.pack_orientation(Z[None], T)[0])
    np.testing.assert_allclose(e, full[:2], atol=1e-12)


def test_roll_pitch_noise_has_the_covariance_of_the_attitudes_horizontal_block():
    """With ``Z = exp(n) Rz(psi) C R`` -- noise about the axes of the sensor's own world, whose
    heading is off by any ``psi`` -- the residuals' covariance is ``cov(n)[:2, :2]`` (Monte Carlo,
    40 000 draws of a correlated 3x3 attitude covariance)."""
    rng = np.random.default_rng(11)
    x = _state(rng, "any")
    T = selfcheck.random_extrinsic(rng)
    A = rng.normal(size=(3, 3)) * 0.01
    cov = A @ A.T
    n = rng.multivariate_normal(np.zeros(3), cov, size=40_000)
    psi = rng.uniform(-np.pi, np.pi, len(n))
    Z = so3.exp(n) @ so3.exp(psi[:, None] * np.array([0.0, 0.0, 1.0])) @ (x.C @ T[:3, :3])
    rows = sm.pack_orientation(Z, T)
    e = np.array([sm.evaluate_one(sm.ROLL_PITCH, x, row)[0] for row in rows])
    np.testing.assert_allclose(np.cov(e.T), cov[:2, :2], rtol=0.05, atol=2e-7)
