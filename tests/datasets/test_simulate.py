"""Tests of the simulator (datasets/simulate.py) and its motion profiles (datasets/trajectories.py).

Statistical tests compare a sample second moment ``m = mean(x^2)`` of zero-mean Gaussian noise of
variance ``s^2`` with ``s^2``: ``m / s^2`` has mean 1 and standard error ``sqrt(2 / n)``. We accept
within ``Z = 5`` standard errors (a correct simulator fails with probability < 1e-6 per check, and
the seeds are fixed anyway), and every such test also asserts that the same sample REJECTS a
density 10 % too large (variance x 1.21), so a test that could pass by accident would fail here.
"""
from __future__ import annotations

import numpy as np
import pytest

from datasets import simulate as sim
from datasets.simulate import PROFILES, SimulatedDataset, euler_truth, simulate
from datasets.simulated_sensors import sensor_stream
from datasets.trajectories import body_rate_from_rpy
from datasets.types import Dataset
from factors import euler, imu, so3
from factors.imu import ImuNoise

Z = 5.0
WRONG_DENSITY = 1.1  # a density 10 % off must be rejected


def assert_variance(x: np.ndarray, variance, what: str):
    """Per column of ``x`` (n, d): zero mean and second moment ``variance`` within Z standard
    errors; and a variance WRONG_DENSITY^2 times larger is rejected by the same sample."""
    x = np.asarray(x, dtype=float)
    n = len(x)
    variance = np.broadcast_to(np.asarray(variance, dtype=float), x.shape[1:])
    ratio = np.mean(x**2, axis=0) / variance
    se = np.sqrt(2.0 / n)
    assert np.all(np.abs(ratio - 1.0) < Z * se), f"{what}: variance ratio {ratio} (tolerance {Z * se:.4f}, n={n})"
    assert np.all(np.abs(ratio / WRONG_DENSITY**2 - 1.0) > Z * se), f"{what}: test cannot tell a 10 % wrong density"
    mean_z = np.mean(x, axis=0) / np.sqrt(variance / n)
    assert np.all(np.abs(mean_z) < Z), f"{what}: mean off by {mean_z} standard errors"


def assert_white(x: np.ndarray, what: str):
    """Columns uncorrelated with each other and with their own previous sample (|rho| < Z / sqrt n)."""
    n = len(x)
    rho = np.corrcoef(x, rowvar=False)
    assert np.all(np.abs(rho[np.triu_indices(x.shape[1], 1)]) < Z / np.sqrt(n)), f"{what}: cross-correlation {rho}"
    lag1 = np.sum(x[1:] * x[:-1], axis=0) / np.sqrt(np.sum(x[1:] ** 2, axis=0) * np.sum(x[:-1] ** 2, axis=0))
    assert np.all(np.abs(lag1) < Z / np.sqrt(n)), f"{what}: lag-1 autocorrelation {lag1}"


def assert_same_dataset(a: Dataset, b: Dataset):
    np.testing.assert_array_equal(a.imu.t, b.imu.t)
    np.testing.assert_array_equal(a.imu.acc, b.imu.acc)
    np.testing.assert_array_equal(a.imu.gyro, b.imu.gyro)
    for name in ("r", "v", "C", "b_f", "b_w"):
        np.testing.assert_array_equal(getattr(a.truth.states, name), getattr(b.truth.states, name))
        np.testing.assert_array_equal(getattr(a.initial, name), getattr(b.initial, name))
    np.testing.assert_array_equal(a.sensor("pose").data.position, b.sensor("pose").data.position)
    np.testing.assert_array_equal(a.sensor("pose").data.C, b.sensor("pose").data.C)


# ------------------------------------------------------------------------------------------
# reproducibility and independent streams


def test_same_seed_same_dataset_and_different_seeds_differ():
    kw = dict(profile="gentle", duration=5.0, position_rate=5.0, odometry_rate=10.0)
    a, b, c = simulate(seed=3, **kw), simulate(seed=3, **kw), simulate(seed=4, **kw)
    assert isinstance(a, Dataset) and isinstance(a, SimulatedDataset)
    assert a.name == "synthetic:gentle"
    assert_same_dataset(a, b)
    np.testing.assert_array_equal(a.sensor("position").data.position, b.sensor("position").data.position)
    np.testing.assert_array_equal(a.sensor("odometry").data.dr, b.sensor("odometry").data.dr)
    for x, y in [
        (a.imu.acc, c.imu.acc), (a.imu.gyro, c.imu.gyro), (a.truth.states.b_f, c.truth.states.b_f),
        (a.sensor("pose").data.position, c.sensor("pose").data.position),
        (a.sensor("position").data.position, c.sensor("position").data.position),
        (a.sensor("odometry").data.dr, c.sensor("odometry").data.dr), (a.initial.r, c.initial.r),
    ]:
        assert np.all(x != y)  # every random element differs, not just some
    np.testing.assert_array_equal(a.clean_imu.acc, c.clean_imu.acc)  # the motion does not depend on the seed


def test_switching_measurements_on_or_off_changes_nothing_else():
    base = simulate("tumbling", duration=3.0, seed=11)
    more = simulate("tumbling", duration=3.0, seed=11, position_rate=20.0, orientation_rate=4.0,
                    odometry_rate=5.0, outlier_fraction=0.0)
    assert_same_dataset(base, more)
    slower_pose = simulate("tumbling", duration=3.0, seed=11, pose_rate=5.0)
    np.testing.assert_array_equal(base.imu.acc, slower_pose.imu.acc)
    np.testing.assert_array_equal(base.truth.states.b_w, slower_pose.truth.states.b_w)
    no_pose = simulate("tumbling", duration=3.0, seed=11, pose_rate=None)
    assert no_pose.sensor_names == ()
    np.testing.assert_array_equal(base.imu.gyro, no_pose.imu.gyro)


# ------------------------------------------------------------------------------------------
# analytic kinematics against finite differences


def _gimbal_lock_times(profile, t):
    """Times where the profile's pitch crosses +-pi/2 (bisection between grid points ``t``)."""

    def gap(times):
        return np.abs(PROFILES[profile].evaluate(times).rpy[:, 1]) - np.pi / 2

    g = gap(t)
    cross = np.flatnonzero(np.sign(g[:-1]) != np.sign(g[1:]))
    lo, hi = t[cross], t[cross + 1]
    for _ in range(50):
        mid = 0.5 * (lo + hi)
        left = np.sign(gap(mid)) == np.sign(gap(lo))
        lo, hi = np.where(left, mid, lo), np.where(left, hi, mid)
    return lo


def _times(profile):
    # tumbling: include the times where the pitch is exactly at +-pi/2 (no inverse anywhere)
    t = np.linspace(0.0, 30.0, 301)
    if profile == "tumbling":
        lock = _gimbal_lock_times(profile, t)
        assert len(lock) >= 10
        pitch = PROFILES[profile].evaluate(lock).rpy[:, 1]
        np.testing.assert_allclose(np.abs(pitch), np.pi / 2, atol=1e-12)
        t = np.concatenate([t, lock])
    return t


@pytest.mark.parametrize("profile", sorted(PROFILES))
def test_body_rate_is_the_derivative_of_the_attitude(profile):
    """C^T dC/dt = omega^x with central differences, h = 1e-5. The truncation error is
    h^2 |d3C/dt3| / 6 <= h^2 (|w|^3 + 3 |w| |dw| + |ddw|) / 6 ~ 1e-8 for tumbling's |w| <= 6,
    |dw| ~ 20, |ddw| ~ 100; round-off ~ eps / h ~ 1e-11. An error in the formula is O(1)."""
    p = PROFILES[profile]
    t, h = _times(profile), 1e-5
    k = p.evaluate(t)
    dC = (p.evaluate(t + h).C - p.evaluate(t - h).C) / (2 * h)
    omega_x = so3.inverse(k.C) @ dC
    np.testing.assert_allclose(omega_x, so3.skew(k.omega), rtol=0, atol=1e-7)


def test_body_rate_formula_against_euler_angle_matrices():
    """Independent of any profile: random angles and rates, derivative of rpy_to_matrix."""
    rng = np.random.default_rng(0)
    rpy = rng.uniform(-np.pi, np.pi, (200, 3))
    rpy[:10, 1] = np.pi / 2  # gimbal lock is no problem for the forward formula
    rate = rng.normal(0, 3, (200, 3))
    h = 1e-6
    dC = (euler.rpy_to_matrix(rpy + h * rate) - euler.rpy_to_matrix(rpy - h * rate)) / (2 * h)
    np.testing.assert_allclose(
        so3.inverse(euler.rpy_to_matrix(rpy)) @ dC, so3.skew(body_rate_from_rpy(rpy, rate)), atol=1e-8
    )


@pytest.mark.parametrize("profile", sorted(PROFILES))
def test_velocity_acceleration_and_specific_force_are_the_derivatives_of_the_position(profile):
    """v = dr/dt and a = dv/dt (central differences, h = 1e-5: truncation h^2 |r'''| / 6 < 1e-9,
    round-off eps |r| / h < 1e-10), and the simulator's clean specific force is
    C^T (d2r/dt2 - g) with a second difference (h = 1e-3: truncation h^2 |r''''| / 12 < 4e-7 for
    tumbling's 0.5 m at 1.7 rad/s, round-off 4 eps |r| / h^2 < 1e-8): tolerance 2e-6."""
    p = PROFILES[profile]
    t = np.arange(301) / 10.0  # the simulator's sample times at 10 Hz
    k = p.evaluate(t)
    h = 1e-5
    np.testing.assert_allclose(k.v, (p.evaluate(t + h).r - p.evaluate(t - h).r) / (2 * h), rtol=0, atol=1e-8)
    np.testing.assert_allclose(k.a, (p.evaluate(t + h).v - p.evaluate(t - h).v) / (2 * h), rtol=0, atol=1e-8)
    np.testing.assert_allclose(k.body_velocity(), np.einsum("kji,kj->ki", k.C, k.v), atol=1e-12)

    d = simulate(profile, duration=30.0, imu_rate=10.0, pose_rate=None, clean_imu="analytic", gravity=[0.3, -0.2, -9.8])
    np.testing.assert_array_equal(d.imu.t, t)
    H = 1e-3
    second = (p.evaluate(t + H).r - 2 * k.r + p.evaluate(t - H).r) / H**2
    f_fd = np.einsum("kji,kj->ki", k.C, second - d.gravity)
    np.testing.assert_allclose(d.clean_imu.acc, f_fd, rtol=0, atol=2e-6)
    np.testing.assert_allclose(d.clean_imu.gyro, k.omega, rtol=0, atol=0)


def test_gentle_heads_along_its_path():
    k = PROFILES["gentle"].evaluate(np.linspace(0, 60, 6001))
    heading = np.arctan2(k.v[:, 1], k.v[:, 0])
    yaw = euler.matrix_to_rpy(k.C)[:, 2]
    np.testing.assert_allclose(np.angle(np.exp(1j * (yaw - heading))), 0.0, atol=1e-12)
    speed = np.linalg.norm(k.v, axis=1)
    assert 0.6 < speed.min() and speed.max() < 1.6 and abs(speed.mean() - 1.0) < 0.1
    assert np.abs(k.rpy[:, :2]).max() < 0.15  # mild roll and pitch
    extent = k.r.max(axis=0) - k.r.min(axis=0)
    assert 4 < extent[0] <= 10.001 and 2 < extent[1] <= 5.001  # a few metres
    # a figure-eight: the path crosses itself at the origin twice per loop
    assert np.sum(np.abs(np.diff(np.sign(k.r[:, 1]))) > 0) >= 4


# ------------------------------------------------------------------------------------------
# profiles


def test_tumbling_rotates_several_radians_per_second_about_every_axis():
    d = simulate("tumbling", duration=60.0, pose_rate=None, noise=ImuNoise(0, 0, 0, 0), initial_bias_sigma=(0, 0))
    peak = np.abs(d.clean_imu.gyro).max(axis=0)
    assert np.all(peak > 4.0) and np.all(peak < 8.0), peak
    rms = np.sqrt(np.mean(d.clean_imu.gyro**2, axis=0))
    assert np.all(rms > 1.5), rms  # not a single spike: several rad/s most of the time
    pitch = PROFILES["tumbling"].evaluate(d.imu.t).rpy[:, 1]
    assert np.abs(pitch).max() > np.pi / 2  # goes through gimbal lock
    assert np.linalg.norm(PROFILES["tumbling"].evaluate(d.imu.t).v, axis=1).max() > 1.0  # and translates


@pytest.mark.parametrize("profile", ["static", "static_level"])
@pytest.mark.parametrize("truth", ["discrete", "continuous"])
def test_static_measures_only_gravity(profile, truth):
    g = np.array([0.1, 0.0, -9.8])
    d = simulate(profile, duration=10.0, truth=truth, gravity=g)
    C = d.truth.C
    np.testing.assert_allclose(d.clean_imu.acc, -np.einsum("kji,j->ki", C, g), atol=1e-13)
    np.testing.assert_array_equal(d.clean_imu.gyro, 0.0)
    np.testing.assert_allclose(d.truth.states.r - d.truth.states.r[0], 0.0, atol=1e-12)
    np.testing.assert_allclose(d.truth.states.v, 0.0, atol=1e-12)
    np.testing.assert_array_equal(C - C[0], 0.0)
    rpy = euler.matrix_to_rpy(C[0])
    if profile == "static":
        assert np.all(np.abs(rpy[:2]) > 0.05)  # tilted
    else:
        np.testing.assert_allclose(rpy[:2], 0.0, atol=1e-15)
        np.testing.assert_allclose(d.clean_imu.acc[0], [-0.1 * np.cos(0.7), 0.1 * np.sin(0.7), 9.8], atol=1e-13)


# ------------------------------------------------------------------------------------------
# the truth


def test_discrete_truth_is_the_models_own_integration_of_the_clean_imu():
    d = simulate("tumbling", duration=8.0, seed=5, clean_imu="analytic")
    s = d.truth.states
    start = s[0].replace(b_f=np.zeros(3), b_w=np.zeros(3))
    loop = imu.integrate(start, d.clean_imu.acc[:-1], d.clean_imu.gyro[:-1], np.diff(d.imu.t), d.gravity)
    # round-off only: the doubling scan associates the products differently from the loop
    np.testing.assert_allclose(s.r, loop.r, rtol=0, atol=1e-10)
    np.testing.assert_allclose(s.v, loop.v, rtol=0, atol=1e-10)
    np.testing.assert_allclose(s.C, loop.C, rtol=0, atol=1e-12)
    # the truth starts on the analytic motion and carries the bias sequence
    k0 = PROFILES["tumbling"].evaluate(d.imu.t[:1])
    np.testing.assert_allclose(s.r[0], k0.r[0], atol=0)
    np.testing.assert_allclose(s.C[0], k0.C[0], atol=0)
    np.testing.assert_allclose(s.v[0], k0.body_velocity()[0], atol=0)
    assert np.all(np.diff(s.b_f, axis=0) != 0) and np.all(np.diff(s.b_w, axis=0) != 0)


def test_euler_truth_with_velocity_noise_matches_the_model_step():
    rng = np.random.default_rng(1)
    n = 300
    t = np.cumsum(rng.uniform(0.001, 0.01, n))
    acc, gyro, n_v = rng.normal(0, 3, (n, 3)), rng.normal(0, 4, (n, 3)), rng.normal(0, 0.5, (n - 1, 3))
    start = imu.ImuState(rng.normal(size=3), rng.normal(size=3), so3.exp(rng.normal(size=3)), np.zeros(3), np.zeros(3))
    fast = euler_truth(start, acc, gyro, t, velocity_noise=n_v)
    state, states = start, [start]
    for k in range(n - 1):
        noise = np.zeros(15)
        noise[imu.NV] = n_v[k]
        state = imu.propagate_with_noise(state, acc[k], gyro[k], t[k + 1] - t[k], noise)
        states.append(state)
    loop = imu.ImuState.stack(states)
    for name in ("r", "v", "C"):
        np.testing.assert_allclose(getattr(fast, name), getattr(loop, name), rtol=0, atol=1e-11)


def test_noise_free_imu_integrated_from_the_true_start_reproduces_the_truth():
    quiet = ImuNoise(acc=0, gyro=0, acc_bias=0, gyro_bias=0, velocity=0)
    d = simulate("tumbling", duration=10.0, noise=quiet, initial_bias_sigma=(0, 0))
    np.testing.assert_array_equal(d.imu.acc, d.clean_imu.acc)
    again = imu.integrate(d.truth.states[0], d.imu.acc[:-1], d.imu.gyro[:-1], np.diff(d.imu.t), d.gravity)
    for name in ("r", "v", "C", "b_f", "b_w"):
        np.testing.assert_allclose(getattr(again, name), getattr(d.truth.states, name), rtol=0, atol=1e-10)
    # constant non-zero biases: the model removes them exactly
    biased = simulate("tumbling", duration=10.0, noise=quiet, initial_bias_sigma=(0.2, 0.05))
    assert np.abs(biased.truth.states.b_w[0]).min() > 0
    again = imu.integrate(biased.truth.states[0], biased.imu.acc[:-1], biased.imu.gyro[:-1], np.diff(biased.imu.t))
    np.testing.assert_allclose(again.r, biased.truth.states.r, rtol=0, atol=1e-10)
    np.testing.assert_allclose(again.C, biased.truth.states.C, rtol=0, atol=1e-12)
    # and the same check fails on noisy data: the test can tell
    noisy = simulate("tumbling", duration=10.0, initial_bias_sigma=(0, 0))
    again = imu.integrate(noisy.truth.states[0], noisy.imu.acc[:-1], noisy.imu.gyro[:-1], np.diff(noisy.imu.t))
    assert np.abs(again.r - noisy.truth.states.r).max() > 1e-3


def _truth_gap(profile, imu_rate, duration=1.0):
    kw = dict(duration=duration, imu_rate=imu_rate, pose_rate=None, clean_imu="analytic")
    a, b = (simulate(profile, truth="discrete", **kw).truth.states,
            simulate(profile, truth="continuous", **kw).truth.states)
    return np.array([
        np.abs(a.r - b.r).max(), np.abs(a.v - b.v).max(), np.linalg.norm(so3.boxminus(a.C, b.C), axis=1).max()
    ])


@pytest.mark.parametrize("profile", ["gentle", "tumbling"])
def test_continuous_truth_is_close_to_discrete_and_the_gap_is_first_order_in_dt(profile):
    """Euler-forward is first order: halving dt halves the gap (ratio 2 within 10 %)."""
    gaps = np.array([_truth_gap(profile, rate) for rate in (100.0, 200.0, 400.0)])
    ratios = gaps[:-1] / gaps[1:]
    assert np.all(np.abs(ratios - 2.0) < 0.2), ratios
    # small over 1 s at 200 Hz (tumbling: 4 cm, 0.1 m/s, 0.015 rad; gentle 50x less)
    assert np.all(gaps[1] < [0.05, 0.15, 0.02]), gaps[1]


def test_matched_clean_imu_keeps_the_discrete_truth_on_the_profile():
    d = simulate("tumbling", duration=60.0, clean_imu="matched", pose_rate=None)
    k = PROFILES["tumbling"].evaluate(d.imu.t)
    np.testing.assert_allclose(d.truth.states.r, k.r, rtol=0, atol=1e-9)
    np.testing.assert_allclose(d.truth.states.C, k.C, rtol=0, atol=1e-12)
    # its velocity is the forward difference: within O(dt) of the analytic one, as the signals are
    dt = 1 / 200
    assert np.abs(d.truth.states.v - k.body_velocity()).max() < 2.0 * dt
    assert 0 < np.abs(d.clean_imu.gyro - k.omega).max() < 30 * dt
    # and it is still exactly the model's integration of its clean signals
    loop = imu.integrate(d.truth.states[0].replace(b_f=np.zeros(3), b_w=np.zeros(3)), d.clean_imu.acc[:400],
                         d.clean_imu.gyro[:400], np.diff(d.imu.t)[:400])
    np.testing.assert_allclose(loop.r, d.truth.states.r[:401], atol=1e-12)
    # whereas the analytic signals drift (a 0.02 rad attitude error lets gravity leak in)
    analytic = simulate("tumbling", duration=60.0, pose_rate=None, clean_imu="analytic")
    assert np.abs(analytic.truth.states.r - k.r).max() > 10.0


# ------------------------------------------------------------------------------------------
# noise statistics


NOISE = ImuNoise(acc=2e-3, gyro=2e-4, acc_bias=3e-4, gyro_bias=2e-5, velocity=1e-2)
RATE = 100.0


@pytest.fixture(scope="module")
def long_run():
    """1e5 IMU samples and 1e5 measurements of every kind (about 1.5 s), tumbling (so that frames
    matter) with the matched clean IMU (so that the truth stays on the profile for 1000 s)."""
    return simulate(
        "tumbling", duration=1000.0, imu_rate=RATE, seed=7, noise=NOISE, clean_imu="matched",
        pose_rate=RATE, pose_sigma=(0.05, 0.01), position_rate=RATE, position_sigma=0.5,
        orientation_rate=RATE, orientation_sigma=0.02, odometry_rate=RATE, odometry_sigma=(0.02, 0.005),
    )


def test_imu_white_noise_has_the_discrete_variance_R_over_dt(long_run):
    d, dt = long_run, 1 / RATE
    assert len(d.imu) == 100_001
    n_f = d.imu.acc - d.clean_imu.acc - d.truth.states.b_f
    n_w = d.imu.gyro - d.clean_imu.gyro - d.truth.states.b_w
    assert_variance(n_f, NOISE.acc**2 / dt, "accelerometer white noise")
    assert_variance(n_w, NOISE.gyro**2 / dt, "gyro white noise")
    assert_white(n_f, "accelerometer white noise")
    assert_white(n_w, "gyro white noise")
    assert d.noise == NOISE


def test_bias_random_walk_increments_have_variance_R_dt(long_run):
    d, dt = long_run, 1 / RATE
    db_f, db_w = np.diff(d.truth.states.b_f, axis=0), np.diff(d.truth.states.b_w, axis=0)
    # b_{k+1} = b_k + dt n_b, n_b ~ N(0, R_b / dt)
    assert_variance(db_f / dt, NOISE.acc_bias**2 / dt, "accelerometer bias walk")
    assert_variance(db_w / dt, NOISE.gyro_bias**2 / dt, "gyro bias walk")
    assert_white(db_f, "accelerometer bias walk")


def test_velocity_noise_enters_the_discrete_truth(long_run):
    d, dt = long_run, 1 / RATE
    s = d.truth.states
    n_v = np.diff(s.r, axis=0) / dt - np.einsum("kij,kj->ki", s.C[:-1], s.v[:-1])
    n_v = np.einsum("kji,kj->ki", s.C[:-1], n_v)  # back into the body frame
    assert_variance(n_v, NOISE.velocity**2 / dt, "velocity noise")


def test_measurement_noise_has_the_declared_covariances(long_run):
    d = long_run
    s = d.truth.states
    k = np.searchsorted(d.imu.t, d.sensor("pose").data.t)
    # pose: the declared covariance, and the one asked for
    np.testing.assert_array_equal(d.sensor("pose").data.cov[0], np.diag([0.05**2] * 3 + [0.01**2] * 3))
    declared = np.diagonal(d.sensor("pose").data.cov, axis1=1, axis2=2)
    assert_variance(d.sensor("pose").data.position - s.r[k], declared[:, :3].mean(0), "pose position noise")
    n_phi = so3.boxminus(d.sensor("pose").data.C, s.C[k])  # C_meas = exp(n) C
    assert_variance(n_phi, declared[:, 3:].mean(0), "pose attitude noise (world frame)")
    assert_white(np.hstack([d.sensor("pose").data.position - s.r[k], n_phi]), "pose noise")
    # GPS
    k = np.searchsorted(d.imu.t, d.sensor("position").data.t)
    np.testing.assert_array_equal(d.sensor("position").data.cov[0], 0.25 * np.eye(3))
    assert_variance(d.sensor("position").data.position - s.r[k], 0.5**2, "GPS noise")
    # orientation
    k = np.searchsorted(d.imu.t, d.sensor("orientation").data.t)
    np.testing.assert_array_equal(d.sensor("orientation").data.cov[0], 0.02**2 * np.eye(3))
    assert_variance(so3.boxminus(d.sensor("orientation").data.C, s.C[k]), 0.02**2, "orientation noise")


def test_relative_pose_noise_is_in_frame_i(long_run):
    d = long_run
    s = d.truth.states
    rp = d.sensor("odometry").data
    i, j = np.searchsorted(d.imu.t, rp.t_from), np.searchsorted(d.imu.t, rp.t_to)
    np.testing.assert_array_equal(i[1:], j[:-1])  # consecutive
    Ci_T = so3.inverse(s.C[i])
    n_r = rp.dr - np.einsum("kij,kj->ki", Ci_T, s.r[j] - s.r[i])
    n_phi = so3.boxminus(rp.dC, Ci_T @ s.C[j])
    np.testing.assert_array_equal(rp.cov[0], np.diag([0.02**2] * 3 + [0.005**2] * 3))
    assert_variance(n_r, 0.02**2, "relative translation noise")
    assert_variance(n_phi, 0.005**2, "relative rotation noise")


def test_attitude_noise_is_applied_on_the_left():
    """With isotropic noise ``exp(n) C`` and ``C exp(n)`` have the same distribution, so no
    statistic can tell them apart: check the construction itself against the documented streams
    (each sensor's stream derived from the ``sensors`` role's by its name)."""
    d = simulate("tumbling", duration=2.0, seed=9, pose_rate=50.0, odometry_rate=25.0)
    root = np.random.SeedSequence(9).spawn(len(sim.STREAMS))[sim.STREAMS.index("sensors")]
    s = d.truth.states
    rng = np.random.default_rng(sensor_stream(root, "pose"))
    k = np.arange(0, len(d.imu), 4)
    n_p, n_phi = rng.standard_normal((len(k), 3)) * 0.05, rng.standard_normal((len(k), 3)) * 0.01
    np.testing.assert_allclose(d.sensor("pose").data.position, s.r[k] + n_p, rtol=0, atol=1e-14)
    np.testing.assert_allclose(d.sensor("pose").data.C, so3.exp(n_phi) @ s.C[k], rtol=0, atol=1e-14)
    rng = np.random.default_rng(sensor_stream(root, "odometry"))
    i, j = np.arange(0, len(d.imu) - 8, 8), np.arange(8, len(d.imu), 8)
    n_r, n_phi = rng.standard_normal((len(i), 3)) * 0.02, rng.standard_normal((len(i), 3)) * 0.005
    Ci_T = so3.inverse(s.C[i])
    np.testing.assert_allclose(d.sensor("odometry").data.dr, np.einsum("kij,kj->ki", Ci_T, s.r[j] - s.r[i]) + n_r,
                               atol=1e-14)
    np.testing.assert_allclose(d.sensor("odometry").data.dC, so3.exp(n_phi) @ Ci_T @ s.C[j], rtol=0, atol=1e-14)


def test_initial_estimate_error_is_a_draw_from_initial_cov():
    """Over 1500 seeds the normalised initial errors ``(initial [-] truth_0) / sigma`` have unit
    variance in every block (n = 4500 per block: standard error 0.021, tolerance 0.105, so a
    sigma 10 % off, variance x 1.21, is rejected) and the NEES has mean 15."""
    sigmas = dict(initial_sigma=(0.3, 0.2, 0.05), initial_bias_sigma=(0.1, 0.01))
    errors, covs = [], []
    for seed in range(1500):
        d = simulate("gentle", duration=0.01, seed=seed, pose_rate=None, **sigmas)
        np.testing.assert_array_equal(d.initial.b_f, 0.0)
        np.testing.assert_array_equal(d.initial.b_w, 0.0)
        errors.append(imu.boxminus(d.initial, d.truth.states[0]))
        covs.append(d.initial_cov)
    errors = np.array(errors)
    cov = covs[0]
    assert all(np.array_equal(c, cov) for c in covs)
    np.testing.assert_allclose(np.diag(cov), np.repeat([0.3, 0.2, 0.05, 0.1, 0.01], 3) ** 2)
    assert np.count_nonzero(cov - np.diag(np.diag(cov))) == 0
    for block, name in zip(range(5), ("position", "velocity", "attitude", "acc bias", "gyro bias")):
        part = slice(3 * block, 3 * block + 3)
        assert_variance(errors[:, part].reshape(-1, 1), cov[part, part][0, 0], f"initial {name} error")
    nees = np.einsum("ki,ij,kj->k", errors, np.linalg.inv(cov), errors)
    assert abs(nees.mean() - 15.0) < Z * np.sqrt(30.0 / len(nees))


@pytest.mark.parametrize("truth", ["discrete", "continuous"])
@pytest.mark.parametrize("clean_imu", ["analytic", "matched"])
def test_zero_initial_sigma_means_known_exactly(truth, clean_imu):
    d = simulate("tumbling", duration=1.0, initial_sigma=(0, 0, 0), initial_bias_sigma=(0, 0), truth=truth,
                 clean_imu=clean_imu)
    np.testing.assert_array_equal(imu.boxminus(d.initial, d.truth.states[0]), 0.0)
    np.testing.assert_allclose(np.diag(d.initial_cov), sim.MIN_SIGMA**2)


# ------------------------------------------------------------------------------------------
# measurement times, outliers, options


def test_measurement_times_are_imu_sample_times():
    d = simulate("gentle", duration=60.0, t0=12.5, imu_rate=200.0, pose_rate=10.0, position_rate=1.0,
                 orientation_rate=40.0, odometry_rate=5.0)
    t = d.imu.t
    assert len(t) == 12001 and t[0] == 12.5 and t[-1] == pytest.approx(72.5, abs=1e-12)
    np.testing.assert_allclose(np.diff(t), 1 / 200, rtol=0, atol=1e-12)
    for times, stride, count in [
        (d.sensor("pose").data.t, 20, 601), (d.sensor("position").data.t, 200, 61),
        (d.sensor("orientation").data.t, 5, 2401), (d.sensor("odometry").data.t_from, 40, 300),
    ]:
        assert len(times) == count
        k = np.searchsorted(t, times)
        np.testing.assert_array_equal(t[k], times)  # the same floats, not just close
        np.testing.assert_array_equal(k, stride * np.arange(count))  # first at t0, exact rate
    np.testing.assert_array_equal(d.sensor("odometry").data.t_to[:-1], d.sensor("odometry").data.t_from[1:])
    np.testing.assert_array_equal(d.truth.t, t)
    assert np.isin(d.measurement_times(), t).all()


def test_outliers_corrupt_the_chosen_pose_measurements_only():
    clean = simulate("gentle", duration=20.0, seed=2)
    dirty = simulate("gentle", duration=20.0, seed=2, outlier_fraction=0.1, outlier_scale=(4.0, 0.8))
    assert clean.outliers == {}
    out = dirty.outliers["pose"]
    assert len(out) == round(0.1 * len(dirty.sensor("pose").data)) == 20 and len(np.unique(out)) == 20
    other = simulate("gentle", duration=20.0, seed=3, outlier_fraction=0.1).outliers["pose"]
    # drawn, not the first ones
    assert not np.array_equal(out, other) and out.max() > len(dirty.sensor("pose").data) // 2
    keep = np.setdiff1d(np.arange(len(dirty.sensor("pose").data)), out)
    np.testing.assert_array_equal(dirty.sensor("pose").data.position[keep], clean.sensor("pose").data.position[keep])
    np.testing.assert_array_equal(dirty.sensor("pose").data.C[keep], clean.sensor("pose").data.C[keep])
    np.testing.assert_allclose(np.linalg.norm(dirty.sensor("pose").data.position[out]
                                              - clean.sensor("pose").data.position[out], axis=1), 4.0)
    angle = np.linalg.norm(so3.boxminus(dirty.sensor("pose").data.C[out], clean.sensor("pose").data.C[out]), axis=1)
    np.testing.assert_allclose(angle, 0.8, atol=1e-12)
    # nominal covariance: that is the point
    np.testing.assert_array_equal(dirty.sensor("pose").data.cov, clean.sensor("pose").data.cov)
    assert_same_dataset(clean, simulate("gentle", duration=20.0, seed=2, outlier_fraction=0.0))
    np.testing.assert_array_equal(clean.imu.acc, dirty.imu.acc)


@pytest.mark.parametrize(
    "options, name",
    [
        (dict(pose_rate=30.0), "pose_rate"),
        (dict(position_rate=7.0), "position_rate"),
        (dict(orientation_rate=400.0), "orientation_rate"),
        (dict(odometry_rate=-5.0), "odometry_rate"),
        (dict(odometry_sigma=(0.1, 0.2, 0.3), odometry_rate=1.0), "odometry_sigma"),
        (dict(wheel_rate=1.0), "unknown option 'wheel_rate'"),
        (dict(duration=-1.0), "duration"),
        (dict(duration=0.0), "duration"),
        (dict(duration=0.001), "duration"),  # shorter than one IMU step
        (dict(duration=float("nan")), "duration"),
        (dict(profile="loop-the-loop"), "profile"),
        (dict(imu_rate=0.0), "imu_rate"),
        (dict(truth="exact"), "truth"),
        (dict(clean_imu="smooth"), "clean_imu"),
        (dict(outlier_fraction=1.5), "outlier_fraction"),
        (dict(outlier_scale=(1.0,)), "outlier_scale"),
        (dict(pose_sigma=(0.0, 0.01)), "pose_sigma"),
        (dict(position_rate=1.0, position_sigma=-0.5), "position_sigma"),
        (dict(initial_sigma=(0.1, -0.1, 0.1)), "initial_sigma"),
        (dict(initial_bias_sigma=0.1), "initial_bias_sigma"),
        (dict(gravity=[0, 0]), "gravity"),
    ],
)
def test_bad_options_raise_value_error_naming_the_option(options, name):
    with pytest.raises(ValueError, match=name):
        simulate(**options)


def test_rates_of_none_or_zero_mean_no_measurement():
    d = simulate("static", duration=1.0, pose_rate=0, position_rate=None, orientation_rate=0.0, odometry_rate=None)
    assert d.sensors == () and d.outliers == {}
