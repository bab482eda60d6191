"""Sensor models with extrinsics (factors.sensor_models): every Jacobian against its numerical
twin at random states and extrinsics, attitudes of every size (below 1e-6 rad, near pi), through
the kernels (EKF, batch solver) and through GTSAM (check_factor on the factors)."""
import gtsam
import numpy as np
import pytest

from factors import imu, measurements, selfcheck, so3
from factors import sensor_models as sm
from factors.jacobians import check_factor
from factors.keys import keyframe_keys
from smoother.graph import insert_state

MODELS = [sm.POSITION, sm.ORIENTATION, sm.POSE, sm.VELOCITY]


def _state(rng, regime):
    return imu.ImuState(r=rng.normal(size=3) * 10, v=rng.normal(size=3) * 5,
                        C=selfcheck.random_rotation(rng, regime), b_f=rng.normal(size=3) * 0.5,
                        b_w=rng.normal(size=3) * 0.2)


@pytest.mark.parametrize("model", MODELS, ids=lambda m: m.name)
@pytest.mark.parametrize("regime", ["tiny", "near_pi", "any"])
def test_kernel_jacobian_equals_central_differences(model, regime):
    draw = selfcheck.CHECKS[f"{model.name} sensor with extrinsic T_BS, H"]
    rng = np.random.default_rng(hash((model.name, regime)) % 2**32)
    for _ in range(30):
        x = _state(rng, regime)
        row = selfcheck.random_sensor_row(model, x, rng)
        _, H = sm.evaluate_one(model, x, row)
        num = selfcheck._num(lambda s: sm.evaluate_one(model, s, row)[0], x, arg_kinds=[imu.StateManifold],
                             value_kind="vector")[0]
        np.testing.assert_allclose(H, num, atol=1e-6, rtol=1e-6)
    assert draw is not None


@pytest.mark.parametrize("model", MODELS, ids=lambda m: m.name)
def test_gtsam_factor_passes_check_factor_at_1000_points(model):
    """The GTSAM factor (chart adapter included) at 1000 random points: a third with attitudes
    below 1e-6 rad, a third within 1e-3 of pi."""
    rng = np.random.default_rng(7)
    keys = keyframe_keys(0)
    for i in range(1000):
        x = _state(rng, ("tiny", "near_pi", "any")[i % 3])
        row = selfcheck.random_sensor_row(model, x, rng)
        values = gtsam.Values()
        insert_state(values, keys, x)
        factor = sm.sensor_factor(model, keys, row, gtsam.noiseModel.Isotropic.Sigma(model.dim, 0.1))
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
    rng = np.random.default_rng(3)
    x = _state(rng, "any")
    z, Z = rng.normal(size=3), so3.boxplus(x.C, rng.normal(size=3) * 0.2)
    e, _ = sm.evaluate_one(sm.POSE, x, sm.pack_pose(z[None], Z[None])[0])
    np.testing.assert_allclose(e, measurements.pose_residual(x.r, x.C, z, Z), atol=1e-14)
    e, _ = sm.evaluate_one(sm.VELOCITY, x, sm.pack_velocity(z[None], rng.normal(size=(1, 3)))[0])
    np.testing.assert_allclose(e, x.v - z, atol=1e-14)
    xj = _state(rng, "any")
    np.testing.assert_allclose(sm.odometry_residual(x.C, x.r, xj.C, xj.r, z, Z),
                               measurements.relative_pose_residual(x.C, x.r, xj.C, xj.r, z, Z), atol=1e-13)


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
    from smoother.ekf import Ekf

    x = imu.ImuState.identity()
    with pytest.raises(InputError, match="position measurement row: expected 6 numbers"):
        sm.evaluate_one(sm.POSITION, x, np.zeros(5))
    with pytest.raises(InputError, match="expected 24 numbers"):
        sm.sensor_factor(sm.POSE, keyframe_keys(0), np.zeros(6), gtsam.noiseModel.Unit.Create(6))
    with pytest.raises(InputError, match="leading dimension"):
        sm.pack_position([1.0, 2.0, 3.0])
    ekf = Ekf(x, np.eye(15), imu.ImuNoise())
    with pytest.raises(InputError, match="a relative kind needs a cloned past state"):
        ekf.update_sensor("odometry", np.zeros(6), np.eye(6))
