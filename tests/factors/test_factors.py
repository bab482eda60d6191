"""The GTSAM factors: sensor-model factors (factors.sensor_models), the state prior, the IMU factor
(factors.imu_factor) and the CustomFactor builder with its chart adapter (factors.custom).

What is proved here:

* :func:`factors.jacobians.check_factor` passes EVERY factor -- IMU, pose, position, orientation,
  relative pose, velocity, state prior -- at 1000 random linearisation points in total
  (300 for the IMU factor, 100-150 for each other one), with tiny, ordinary and near-pi
  rotations, large biases, preintegration intervals of 2 to 400 samples, gyro-bias offsets below
  and beyond the re-integration threshold, and Gaussian, Huber and Cauchy noise models; and the
  same check FAILS a factor with one deliberately wrong block and a factor whose chart adapter is
  handed ``C^T`` instead of ``C``;
* the IMU factor integrates again exactly when the gyro bias of keyframe i moves beyond the
  threshold (and only then), after which its error is the exact residual at the new bias;
* a three-keyframe graph (state prior, two IMU factors, pose measurements) optimised with
  Levenberg-Marquardt recovers the state it was simulated from.

Tolerance of the Jacobian check. ``check_factor`` compares WHITENED Jacobians. Its numerical side
differences a whitened error whose raw parts carry round-off ``EPS * |x|`` (positions up to
~200 m), amplified by the whitening ``1/sigma``; for the IMU factor sigma goes down to 1e-6 m, so
the whitened entries reach ~1e7 and their central differences carry absolute errors up to ~1e-2
(measured 6e-3; up to 1.5e-7 of the largest entry), which check_factor's default
``atol = 1e-6`` cannot absorb. The check is therefore run with ``atol = max(1e-6, 1e-7 * max|A|)`` (``A`` the
factor's whitened Jacobian) and the default ``rtol = 1e-5``. Measured over the 1000 points: the
worst entry uses 3% of this tolerance for the IMU factor and at most 2% for the others; the
deliberately wrong blocks below (1e-3 added to a raw Jacobian block) exceed it 20 to 200 times in
the IMU factor and far more in the measurement factor.
"""
from __future__ import annotations

import gc
import math
import weakref

import gtsam
import numpy as np
import pytest
from gtsam_values import insert_state, read_state
from strategies import random_rotation

from factors import custom, imu, preintegration, priors, so3
from factors import sensor_models as sm
from factors.custom import BIAS, ROT, VEC, custom_factor
from factors.imu_factor import ImuFactor
from factors.jacobians import check_factor
from factors.keys import keyframe_keys
from factors.selfcheck import random_extrinsic

GRAVITY = imu.DEFAULT_GRAVITY
REGIMES = ("tiny", "ordinary", "near_pi")
#: Relative part of the check's absolute tolerance (see the module docstring).
ATOL_REL = 1e-7

#: Numbers of random linearisation points per factor type, 1000 in all. The IMU factor's check
#: (~60 evaluations of its 15x30 residual each) dominates this file's runtime: ~15-20 s.
N_POINTS = {"imu": 300, "position": 100, "velocity": 100, "orientation": 100, "pose": 150,
            "relative_pose": 150, "state_prior": 100}
assert sum(N_POINTS.values()) == 1000

# --------------------------------------------------------------------------- helpers




def random_rotation_vector(rng: np.random.Generator, max_angle: float) -> np.ndarray:
    """A measurement-error rotation vector: 0, tiny (1e-12 .. 1e-6) or up to ``max_angle``."""
    axis = rng.normal(size=3)
    axis /= np.linalg.norm(axis)
    kind = rng.integers(3)
    angle = 0.0 if kind == 0 else (10.0 ** rng.uniform(-12, -6) if kind == 1 else rng.uniform(0, max_angle))
    return angle * axis


def random_covariance(rng: np.random.Generator, n: int, lo: float = 1e-2, hi: float = 1.0) -> np.ndarray:
    """A full (correlated) covariance with standard deviations log-uniform in ``[lo, hi]``."""
    sigma = 10.0 ** rng.uniform(math.log10(lo), math.log10(hi), n)
    A = rng.normal(size=(n, n))
    corr = A @ A.T + n * np.eye(n)
    d = np.sqrt(np.diag(corr))
    corr = corr / np.outer(d, d)
    return corr * np.outer(sigma, sigma)


def noise_model(kind: str, cov: np.ndarray):
    base = gtsam.noiseModel.Gaussian.Covariance(cov)
    if kind == "gaussian":
        return base
    if kind == "huber":
        return gtsam.noiseModel.Robust.Create(gtsam.noiseModel.mEstimator.Huber.Create(1.345), base)
    if kind == "cauchy":
        return gtsam.noiseModel.Robust.Create(gtsam.noiseModel.mEstimator.Cauchy.Create(2.385), base)
    raise ValueError(kind)


MODELS = ("gaussian", "huber", "cauchy")


def random_state(rng, regime="ordinary", b_f=1.0, b_w=0.5) -> imu.ImuState:
    return imu.ImuState(rng.uniform(-100, 100, 3), rng.uniform(-10, 10, 3), random_rotation(rng, regime),
                        rng.uniform(-b_f, b_f, 3), rng.uniform(-b_w, b_w, 3))


def transform(C_i: np.ndarray) -> np.ndarray:
    """``T = diag(C_i^T, I, C_i^T, I, I)`` (world error state -> residual coordinates)."""
    T = np.eye(15)
    T[imu.R, imu.R] = C_i.T
    T[imu.PHI, imu.PHI] = C_i.T
    return T


def checked(name: str, factor, values: gtsam.Values):
    """Run ``check_factor`` with the tolerance of the module docstring."""
    A = factor.linearize(values).jacobian()[0]
    return check_factor(factor, values, atol=max(1e-6, ATOL_REL * np.abs(A).max()))


def assert_passes(name: str, factor, values: gtsam.Values, context) -> None:
    result = checked(name, factor, values)
    assert result.ok, f"{context}\n{result}"
    assert np.all(np.isfinite(factor.unwhitenedError(values)))


# --------------------------------------------------------------------------- measurement factors


def _measurement_case(rng: np.random.Generator, name: str, p: int):
    """One random measurement factor of type ``name`` and values for it (point number ``p`` picks
    the rotation regime and the noise model round-robin)."""
    regime = REGIMES[p % 3]
    model_kind = MODELS[(p // 3) % 3]
    # mostly consistent measurements, sometimes gross ones (robust kernels in their outer region)
    scale = 1.0 if p % 4 else 30.0
    values = gtsam.Values()
    k = keyframe_keys(p)
    if name == "position":
        r, C = rng.uniform(-200, 200, 3), random_rotation(rng, regime)
        cov = random_covariance(rng, 3)
        values.insert(k.pos, gtsam.Point3(*r))
        values.insert(k.rot, gtsam.Rot3(C))
        z = r + scale * rng.multivariate_normal(np.zeros(3), cov)
        return sm.sensor_factor(sm.POSITION, k, sm.pack_position(z[None])[0], noise_model(model_kind, cov)), values
    if name == "velocity":
        v, b = rng.uniform(-20, 20, 3), np.concatenate([rng.uniform(-2, 2, 3), rng.uniform(-1, 1, 3)])
        cov = random_covariance(rng, 3)
        values.insert(k.vel, v)
        values.insert(k.bias, gtsam.imuBias.ConstantBias(b[:3], b[3:]))
        z, w = v + scale * rng.multivariate_normal(np.zeros(3), cov), rng.normal(0, 2, 3)
        row = sm.pack_velocity(z[None], w[None], random_extrinsic(rng))[0]
        return sm.sensor_factor(sm.VELOCITY, k, row, noise_model(model_kind, cov)), values
    if name == "orientation":
        C = random_rotation(rng, regime)
        measured = so3.exp(random_rotation_vector(rng, 2.5)) @ C
        values.insert(k.rot, gtsam.Rot3(C))
        row = sm.pack_orientation(measured[None])[0]
        return sm.sensor_factor(sm.ORIENTATION, k, row, noise_model(model_kind, random_covariance(rng, 3))), values
    if name == "pose":
        C, r = random_rotation(rng, regime), rng.uniform(-200, 200, 3)
        values.insert(k.rot, gtsam.Rot3(C))
        values.insert(k.pos, gtsam.Point3(*r))
        mC = so3.exp(random_rotation_vector(rng, 2.5)) @ C
        mr = r + scale * rng.normal(0, 0.1, 3)
        row = sm.pack_pose(mr[None], mC[None])[0]
        return sm.sensor_factor(sm.POSE, k, row, noise_model(model_kind, random_covariance(rng, 6))), values
    if name == "relative_pose":
        kj = keyframe_keys(p + 100000)
        Ci = random_rotation(rng, regime)
        # C_j near pi / tiny as well on every other point
        Cj = random_rotation(rng, regime) if p % 2 else so3.exp(rng.normal(0, 1, 3)) @ Ci
        ri, rj = rng.uniform(-200, 200, 3), rng.uniform(-200, 200, 3)
        for key, value in ((k.rot, gtsam.Rot3(Ci)), (k.pos, gtsam.Point3(*ri)), (kj.rot, gtsam.Rot3(Cj)),
                           (kj.pos, gtsam.Point3(*rj))):
            values.insert(key, value)
        m_dC = so3.exp(random_rotation_vector(rng, 2.5)) @ Ci.T @ Cj
        m_dr = Ci.T @ (rj - ri) + scale * rng.normal(0, 0.1, 3)
        factor = sm.odometry_factor(k, kj, m_dr, m_dC, None, noise_model(model_kind, random_covariance(rng, 6)))
        return factor, values
    if name == "state_prior":
        prior = random_state(rng, regime, 2.0, 1.0)
        cov = random_covariance(rng, 15, 1e-3, 1.0)
        dx = scale * rng.multivariate_normal(np.zeros(15), cov)
        dx[imu.PHI] = random_rotation_vector(rng, 2.5)
        x = imu.boxplus(prior, dx)
        insert_state(values, k, x)
        model = noise_model(model_kind, cov)
        return priors.state_prior_factor(k, prior, cov, noise_model=model), values
    raise ValueError(name)


MEASUREMENT_FACTORS = ("pose", "position", "orientation", "relative_pose", "velocity", "state_prior")


@pytest.mark.parametrize("name", MEASUREMENT_FACTORS)
def test_check_factor_passes_measurement_factor(name):
    """100 random linearisation points per factor type (``N_POINTS``): rotations tiny /
    ordinary / near pi, measurement errors of 0, 1e-12..1e-6 and up to 2.5 rad, positions up to
    200 m, biases up to 2 m/s^2 and 1 rad/s, full correlated covariances (sigmas 1e-2..1, biases 1e-3..1e-1), and
    Gaussian / Huber / Cauchy models round-robin, a quarter with gross (30x) errors."""
    rng = np.random.default_rng(list(MEASUREMENT_FACTORS).index(name) + 100)
    for p in range(N_POINTS[name]):
        factor, values = _measurement_case(rng, name, p)
        assert_passes(name, factor, values, (name, p))


def test_state_prior_default_model_is_the_given_covariance():
    """``state_prior_factor`` without a model whitens with ``cov``: error = e^T cov^-1 e / 2."""
    rng = np.random.default_rng(1)
    prior = random_state(rng)
    cov = random_covariance(rng, 15)
    x = imu.boxplus(prior, rng.normal(0, 0.1, 15))
    k = keyframe_keys(0)
    values = gtsam.Values()
    insert_state(values, k, x)
    factor = priors.state_prior_factor(k, prior, cov)
    e = imu.boxminus(x, prior)
    assert np.abs(factor.unwhitenedError(values) - e).max() < 1e-13
    assert factor.error(values) == pytest.approx(0.5 * e @ np.linalg.solve(cov, e), rel=1e-10)


# --------------------------------------------------------------------------- IMU factor


def _imu_cases(rng: np.random.Generator, n: int, long_every: int = 25):
    """``n`` IMU factors with values: intervals of 2..59 samples and every 25th one of 400
    samples, rates of several rad/s, dt 1..10 ms; attitude regime applied to C_i, to C_j, or to
    both (a slowly turning interval); gyro-bias offsets from b_w_bar of 0, 5e-3 (first-order
    correction) and 0.05 rad/s (beyond the threshold: the factor integrates again); noise of a
    tactical IMU without velocity noise and of a consumer IMU with it; whitened errors of 1, 3
    and 30 sigma; Gaussian, Huber, Cauchy models."""
    long = [p for p in range(n) if long_every and p % long_every == 0]
    short = [p for p in range(n) if p not in long]
    lengths = np.zeros(n, dtype=int)
    lengths[long] = 400
    lengths[short] = rng.integers(2, 60, len(short))
    anchors = [("i", "j", "both")[(p // 3) % 3] for p in range(n)]
    samples, b_w_bar = [], rng.uniform(-1.0, 1.0, (n, 3))
    for p in range(n):
        K = lengths[p]
        if anchors[p] == "both":
            gyro = b_w_bar[p] + rng.normal(0, 1e-3, (K, 3))
        else:
            gyro = rng.uniform(-3, 3, 3) + rng.normal(0, 1, (K, 3))
        acc = np.array([0, 0, 9.81]) + rng.normal(0, 5, (K, 3))
        samples.append((acc, gyro, rng.uniform(1e-3, 1e-2, K)))
    noises = [imu.ImuNoise(), imu.ImuNoise(acc=0.05, gyro=5e-3, acc_bias=1e-3, gyro_bias=1e-4, velocity=1e-2)]
    offsets = (0.0, 5e-3, 0.05)
    threshold = preintegration.REINTEGRATION_THRESHOLD
    out = [None] * n
    for group in (long, short):
        if not group:
            continue
        J, K = len(group), int(lengths[group].max())
        acc, gyro, dt = np.zeros((J, K, 3)), np.zeros((J, K, 3)), np.zeros((J, K))
        for g, p in enumerate(group):
            m = lengths[p]
            acc[g, :m], gyro[g, :m], dt[g, :m] = samples[p]
        b_w_i = np.stack([b_w_bar[p] + offsets[(p // 9) % 3] * rng.choice([-1.0, 1.0], 3) for p in group])
        pre = preintegration.integrate(acc, gyro, dt, b_w_bar[group])
        at_b_w_i = preintegration.integrate(acc, gyro, dt, b_w_i)  # what the factor will use beyond the threshold
        states, effective = [], []
        for g, p in enumerate(group):
            regime = REGIMES[p % 3]
            beyond = np.abs(b_w_i[g] - b_w_bar[p]).max() > threshold
            effective.append(at_b_w_i[g] if beyond else pre[g])
            x_i = random_state(rng, regime if anchors[p] != "j" else "ordinary").replace(b_w=b_w_i[g])
            if anchors[p] == "j":  # put the PREDICTED C_j into the regime
                dC = effective[-1].corrected(b_w_i[g])[0]
                x_i = x_i.replace(C=random_rotation(rng, regime) @ dC.T)
            states.append(x_i)
        x_is = imu.ImuState.stack(states)
        covs = [preintegration.noise_covariance((acc, gyro, dt), x_is, noise, GRAVITY) for noise in noises]
        for g, p in enumerate(group):
            one = pre[g]
            one.cov = covs[p % 2][g]
            x_i = states[g]
            x_pred = preintegration.predict(effective[g], x_i, GRAVITY)
            n_sigma = (1.0, 3.0, 30.0)[(p // 27) % 3]
            e = np.linalg.cholesky(one.cov) @ rng.normal(0, n_sigma, 15)
            if anchors[p] == "j":
                e[imu.PHI] = 0.0  # keep C_j exactly at the predicted attitude, in its regime
            x_j = imu.boxplus(x_pred, transform(x_i.C).T @ e)  # residual = e exactly
            out[p] = (one, x_i, x_j, MODELS[p % 3], anchors[p], REGIMES[p % 3])
    return out


def _imu_factor_and_values(pre, x_i, x_j, model_kind="gaussian", **kwargs):
    ki, kj = keyframe_keys(0), keyframe_keys(1)
    f = ImuFactor(pre, ki, kj, GRAVITY, noise_model=noise_model(model_kind, pre.cov), **kwargs)
    values = gtsam.Values()
    insert_state(values, ki, x_i)
    insert_state(values, kj, x_j)
    return f, values


def test_check_factor_passes_imu_factor():
    """300 random IMU factors (see ``_imu_cases``) pass the Jacobian check; the regimes of C_i
    and C_j are verified, and the factor integrated again exactly where the offset demanded it."""
    rng = np.random.default_rng(2024)
    reintegrated = 0
    for p, (pre, x_i, x_j, model_kind, anchor, regime) in enumerate(_imu_cases(rng, N_POINTS["imu"])):
        C = x_j.C if anchor == "j" else x_i.C
        angle = np.linalg.norm(so3.log(C))
        if regime == "tiny":
            assert angle <= 1e-6
        if regime == "near_pi":
            assert angle >= math.pi - 1e-3 - 1e-12
        f, values = _imu_factor_and_values(pre, x_i, x_j, model_kind)
        assert_passes("imu", f.factor, values, (p, anchor, regime, model_kind, len(pre.samples[2])))
        expect = np.abs(x_i.b_w - pre.b_w_bar).max() > preintegration.REINTEGRATION_THRESHOLD
        assert f.reintegrations == int(expect)
        reintegrated += f.reintegrations
    assert 0 < reintegrated < N_POINTS["imu"]


def test_imu_factor_error_is_the_residual_whitened_by_its_covariance():
    rng = np.random.default_rng(5)
    pre, x_i, x_j, *_ = _imu_cases(rng, 1, long_every=0)[0]
    f, values = _imu_factor_and_values(pre, x_i, x_j)
    e = preintegration.residual(pre, x_i, x_j, GRAVITY)
    assert np.abs(f.factor.unwhitenedError(values) - e).max() <= 1e-12 * max(1.0, np.abs(e).max())
    assert f.factor.error(values) == pytest.approx(0.5 * e @ np.linalg.solve(pre.cov, e), rel=1e-8)
    # ImuFactor without a noise model uses pre.cov
    f2 = ImuFactor(pre, keyframe_keys(0), keyframe_keys(1), GRAVITY)
    assert f2.factor.error(values) == pytest.approx(f.factor.error(values), rel=1e-10)
    assert imu.boxminus(f.predict(x_i), preintegration.predict(pre, x_i, GRAVITY)).max() == 0.0


def test_imu_factor_on_a_one_sample_interval_has_a_finite_error():
    """With ``ImuNoise.velocity = 0`` (the default) the position of a ONE-sample interval is
    deterministic (``r_j = r_i + dt C_i v_i``): the propagated covariance's position block is
    exactly zero, and ``preintegration.COVARIANCE_FLOOR`` keeps the factor's Gaussian model
    regular, so its error is finite (graphs get such intervals when two knots fall within one IMU
    period)."""
    rng = np.random.default_rng(12)
    acc, gyro, dt = np.array([[0.1, 0.2, 9.8]]), np.array([[0.3, -0.2, 0.1]]), np.array([5e-3])
    x_i = random_state(rng)
    pre = preintegration.integrate(acc[None], gyro[None], dt[None], x_i.b_w[None])
    pre.cov = preintegration.noise_covariance(pre.samples, imu.ImuState.stack([x_i]), imu.ImuNoise(), GRAVITY)
    np.linalg.cholesky(pre.cov[0])  # positive definite
    x_j = imu.boxplus(preintegration.predict(pre[0], x_i, GRAVITY), rng.normal(0, 1e-4, 15))
    f = ImuFactor(pre[0], keyframe_keys(0), keyframe_keys(1), GRAVITY)
    values = gtsam.Values()
    insert_state(values, keyframe_keys(0), x_i)
    insert_state(values, keyframe_keys(1), x_j)
    assert np.isfinite(f.factor.error(values))


# --------------------------------------------------------------------------- the check can fail


def _wrap(residual, index: int, block: slice | None, delta: float):
    """A residual whose Jacobian number ``index`` is wrong by ``delta`` in rows ``block``."""
    def wrong(*args, jacobians):
        if not jacobians:
            return residual(*args, jacobians=False)
        e, Js = residual(*args, jacobians=True)
        Js = [np.array(J, dtype=float) for J in Js]
        rows = block if block is not None else slice(None)
        Js[index][rows] += delta
        return e, Js
    return wrong


def _batch_one(args: list, which: int, n: int = 5) -> list:
    """``args`` with argument ``which`` replaced by ``n`` perturbed copies of it (the others single)."""
    rng = np.random.default_rng(which)
    one = np.asarray(args[which], dtype=float)
    batch = (so3.exp(0.3 * rng.normal(size=(n, 3))) @ one if one.shape == (3, 3)
             else one + rng.normal(size=(n,) + one.shape))
    return args[:which] + [batch] + args[which + 1:]


def _assert_rows_are_single_calls(residual, args: list, batched: list, n: int = 5) -> None:
    e, Js = residual(*batched, jacobians=True)
    assert e.shape[0] == n and all(J.shape[0] == n for J in Js)
    np.testing.assert_array_equal(residual(*batched), e)
    for k in range(n):
        row = [a[k] if np.shape(a) != np.shape(s) else a for a, s in zip(batched, args)]
        e_k, Js_k = residual(*row, jacobians=True)
        np.testing.assert_allclose(e[k], e_k, rtol=1e-14, atol=1e-14)
        for J, J_k in zip(Js, Js_k):
            np.testing.assert_allclose(J[k], J_k, rtol=1e-14, atol=1e-14)


@pytest.mark.parametrize("which", range(6))
def test_relative_pose_residual_broadcasts_when_only_some_arguments_are_batched(which):
    """One batched argument among single ones: each row equals the call with that row alone."""
    rng = np.random.default_rng(11)
    C_i, C_j, dC = (random_rotation(rng, "ordinary") for _ in range(3))
    args = [C_i, rng.normal(size=3), C_j, rng.normal(size=3), rng.normal(size=3), dC]
    batched = _batch_one(args, which)
    assert sm.odometry_residual(*batched).shape == (5, 6)
    _assert_rows_are_single_calls(sm.odometry_residual, args, batched)


@pytest.mark.parametrize("which", range(4))
def test_state_residual_broadcasts_when_only_some_arguments_are_batched(which):
    """C, v, b and the prior single, r of shape (5, 3) -> e of shape (5, 15); each row the call
    with that row alone; a batched prior with single variables as well."""
    rng = np.random.default_rng(12)
    r, v, b_f, b_w = rng.normal(size=(4, 3))
    prior = imu.ImuState(r, v, random_rotation(rng, "ordinary"), b_f, b_w)
    args = [random_rotation(rng, "ordinary"), rng.normal(size=3), rng.normal(size=3), rng.normal(size=6)]
    batched = _batch_one(args, which)

    def residual(C, r, v, b, jacobians=False):
        return priors.state_residual(C, r, v, b, prior, jacobians)

    assert residual(*batched).shape == (5, 15)
    _assert_rows_are_single_calls(residual, args, batched)
    # a batched prior with single variables
    batched_prior = imu.ImuState(*(np.broadcast_to(a, (5,) + a.shape) for a in
                                   (prior.r, prior.v, prior.C, prior.b_f, prior.b_w)))
    assert priors.state_residual(*args, batched_prior).shape == (5, 15)


def test_check_factor_fails_a_wrong_block_in_a_measurement_factor():
    """A pose factor whose rotation Jacobian is off by 1e-3 in every entry fails the check on the
    rotation key only; the same factor with the correct Jacobian passes."""
    rng = np.random.default_rng(3)
    C, r = random_rotation(rng, "ordinary"), rng.uniform(-10, 10, 3)
    mC, mr = so3.exp(rng.normal(0, 0.3, 3)) @ C, r + rng.normal(0, 0.1, 3)
    k = keyframe_keys(0)
    values = gtsam.Values()
    values.insert(k.rot, gtsam.Rot3(C))
    values.insert(k.pos, gtsam.Point3(*r))
    model = noise_model("gaussian", random_covariance(rng, 6))
    row = sm.pack_pose(mr[None], mC[None])[0]

    def residual(r_, C_, jacobians):
        e, H = sm.evaluate_one(sm.POSE, imu.ImuState(r_, np.zeros(3), C_, np.zeros(3), np.zeros(3)), row)
        return (e, [H[:, imu.R], H[:, imu.PHI]]) if jacobians else e

    good = custom_factor(model, [k.pos, k.rot], [VEC, ROT], residual)
    bad = custom_factor(model, [k.pos, k.rot], [VEC, ROT], _wrap(residual, 1, None, 1e-3))
    assert checked("control", good, values).ok
    result = checked("control", bad, values)
    assert not result.ok
    assert [c.ok for c in result.comparisons] == [True, False]
    # with a robust model as well
    robust = noise_model("cauchy", random_covariance(rng, 6))
    robust_control = custom_factor(robust, [k.pos, k.rot], [VEC, ROT], _wrap(residual, 1, None, 1e-3))
    assert not checked("control", robust_control, values).ok


@pytest.mark.parametrize("block, rows", [("attitude wrt gyro bias of i", imu.PHI), ("velocity wrt bias of i", imu.V)])
def test_check_factor_fails_a_wrong_block_in_the_imu_factor(block, rows):
    """The IMU factor's residual with a 1e-3 error in one block of the Jacobian of keyframe i's
    bias (variable number 3) fails the check on that key only."""
    rng = np.random.default_rng(4)
    pre, x_i, x_j, *_ = _imu_cases(rng, 2, long_every=0)[1]  # ordinary attitudes (p = 1)
    f, values = _imu_factor_and_values(pre, x_i, x_j)
    assert checked("control", f.factor, values).ok
    model = noise_model("gaussian", pre.cov)
    keys = keyframe_keys(0).all() + keyframe_keys(1).all()
    bad = custom_factor(model, keys, [ROT, VEC, VEC, BIAS] * 2, _wrap(f._interval.residual, 3, rows, 1e-3))
    result = checked("control", bad, values)
    assert not result.ok
    assert [c.ok for c in result.comparisons] == [True, True, True, False, True, True, True, True]


def test_check_factor_fails_when_the_chart_adapter_gets_C_transposed(monkeypatch):
    """Handing the adapter ``C^T`` instead of ``C`` (the classic convention slip) makes the
    orientation, relative-pose and IMU factors fail on their rotation keys, while the rotation-free
    position factor is unaffected."""
    rng = np.random.default_rng(6)
    C = so3.exp(np.array([0.4, -1.1, 0.7]))  # far from symmetric: C != C^T
    k = keyframe_keys(0)
    values = gtsam.Values()
    values.insert(k.rot, gtsam.Rot3(C))
    turned = so3.exp(np.array([0.1, 0.2, -0.1])) @ C
    orientation = sm.sensor_factor(sm.ORIENTATION, k, sm.pack_orientation(turned[None])[0],
                                   noise_model("gaussian", random_covariance(rng, 3)))
    pre, x_i, x_j, *_ = _imu_cases(rng, 2, long_every=0)[1]  # ordinary attitudes (p = 1)
    f, imu_values = _imu_factor_and_values(pre, x_i, x_j)
    assert np.abs(x_i.C - x_i.C.T).max() > 0.1 and np.abs(x_j.C - x_j.C.T).max() > 0.1
    assert checked("control", orientation, values).ok and checked("control", f.factor, imu_values).ok

    real = custom.to_gtsam_chart
    monkeypatch.setattr(custom, "to_gtsam_chart", lambda J, rotation: real(J, np.asarray(rotation).T))
    result = checked("control", orientation, values)
    assert not result.ok
    result = checked("control", f.factor, imu_values)
    assert not result.ok
    # exactly the two Rot3 keys fail
    assert [c.ok for c in result.comparisons] == [False, True, True, True, False, True, True, True]
    position = sm.sensor_factor(sm.POSITION, k, sm.pack_position(np.zeros((1, 3)))[0],
                                noise_model("gaussian", np.eye(3)))
    values.insert(k.pos, gtsam.Point3(1.0, 2.0, 3.0))
    assert checked("control", position, values).ok


# --------------------------------------------------------------------------- re-integration


def _reintegration_setup(offset):
    rng = np.random.default_rng(8)
    K = 150
    acc = np.array([0, 0, 9.81]) + rng.normal(0, 4, (K, 3))
    gyro = np.array([1.5, -2.0, 2.5]) + rng.normal(0, 1, (K, 3))
    dt = np.full(K, 5e-3)
    b_w_bar = np.array([0.1, -0.2, 0.05])
    pre = preintegration.integrate(acc[None], gyro[None], dt[None], b_w_bar[None])
    x_i = random_state(rng).replace(b_w=b_w_bar)
    pre.cov = preintegration.noise_covariance(pre.samples, imu.ImuState.stack([x_i]), imu.ImuNoise(), GRAVITY)
    pre = pre[0]
    x_i = x_i.replace(b_w=b_w_bar + offset)
    x_j = imu.boxplus(imu.integrate(x_i, acc, gyro, dt, GRAVITY)[-1], rng.normal(0, 1e-3, 15))
    f, values = _imu_factor_and_values(pre, x_i, x_j)
    exact = preintegration.integrate(acc[None], gyro[None], dt[None], x_i.b_w[None])[0]
    return f, values, pre, exact, x_i, x_j


def test_imu_factor_integrates_again_beyond_the_threshold():
    """Gyro bias of i moved by 0.03 rad/s on one axis (> 0.02): the first evaluation integrates
    again (counter 1), later evaluations at the same bias do not, and the factor's error is the
    EXACT residual at the new bias (to 1e-12), whitened by the covariance kept from construction."""
    offset = np.array([0.0, 0.03, -0.01])
    f, values, pre, exact, x_i, x_j = _reintegration_setup(offset)
    assert f.reintegrations == 0
    e = f.factor.unwhitenedError(values)
    assert f.reintegrations == 1
    e_exact = preintegration.residual(exact, x_i, x_j, GRAVITY)
    assert np.abs(e - e_exact).max() <= 1e-12 * max(1.0, np.abs(e_exact).max())
    assert np.array_equal(f.pre.b_w_bar, x_i.b_w)
    assert f.factor.error(values) == pytest.approx(0.5 * e_exact @ np.linalg.solve(pre.cov, e_exact), rel=1e-8)
    f.factor.linearize(values)
    f.factor.error(values)
    assert f.reintegrations == 1
    # the first-order model it replaced was measurably worse at this offset
    e_first = preintegration.residual(pre, x_i, x_j, GRAVITY)
    assert np.abs(e_first - e_exact).max() > 1e3 * np.abs(e - e_exact).max() + 1e-9


def test_imu_factor_is_freed_when_nothing_refers_to_it_and_its_factor_outlives_it():
    """GTSAM's C++ factor holds the Python callback; if that callback referred back to the
    ImuFactor (which holds the factor), the cycle would run through C++, where Python's collector
    cannot see it, and no IMU factor would ever be freed (every one a fixed-lag run made stayed in
    memory). Dropped, the ImuFactor is gone at once; its GTSAM factor, still in a graph, keeps
    working and re-integrating on its own."""
    f, values, pre, exact, x_i, x_j = _reintegration_setup(np.array([0.0, 0.03, -0.01]))
    graph = gtsam.NonlinearFactorGraph()
    graph.add(f.factor)
    alive = weakref.ref(f)
    expected = f.factor.error(values)
    f.factor.error(_reintegration_setup(np.zeros(3))[1])  # back at the original bias: integrated again
    del f
    gc.collect()
    assert alive() is None
    assert graph.error(values) == expected  # re-integrated once more, by the callback alone


def test_imu_factor_keeps_its_integration_below_the_threshold():
    """Offset 0.015 rad/s (< 0.02): no re-integration; the error is the first-order residual of the
    original integration, which differs from the exact one only at second order."""
    offset = np.array([0.015, -0.015, 0.01])
    f, values, pre, exact, x_i, x_j = _reintegration_setup(offset)
    e = f.factor.unwhitenedError(values)
    f.factor.linearize(values)
    assert f.reintegrations == 0
    assert np.array_equal(f.pre.b_w_bar, pre.b_w_bar)
    e_first = preintegration.residual(pre, x_i, x_j, GRAVITY)
    assert np.abs(e - e_first).max() <= 1e-12 * max(1.0, np.abs(e_first).max())
    e_exact = preintegration.residual(exact, x_i, x_j, GRAVITY)
    assert np.abs(e_first - e_exact).max() > 1e-9  # the two differ: the branch matters


# --------------------------------------------------------------------------- end to end


def test_three_keyframe_graph_recovers_the_simulated_state():
    """Simulate: a known start state with biases, 3 s of known IMU samples (turning at ~1 rad/s),
    states at keyframes 1 and 2 by sample-by-sample integration (the model's own truth). Graph: a
    weak state prior on keyframe 0 AT the truth, IMU factors 0-1 and 1-2 integrated around a gyro
    bias of 0 (the truth is 0.03 rad/s away, beyond the threshold), exact pose measurements at 1
    and 2. From initial values off by ~0.3 rad, metres, 0.5 m/s and the wrong biases, LM recovers
    the simulated states. The exact-residual minimum is the truth; with a re-integration threshold
    of 1e-9 the factors integrate again whenever the bias estimate moves, so the recovery is exact
    up to the optimiser's convergence (tolerances 1e-6 on every component, the convergence test
    being relative 1e-12 on the error)."""
    rng = np.random.default_rng(10)
    K, h = 150, 0.01
    t = np.arange(2 * K) * h
    gyro = np.stack([0.8 * np.sin(t), 0.5 * np.cos(1.3 * t), 1.0 + 0.2 * t], axis=1)
    acc = np.stack([np.sin(2 * t), 0.5 * np.cos(t), 9.81 + 0.3 * np.sin(3 * t)], axis=1)
    dt = np.full(2 * K, h)
    x0 = imu.ImuState(np.array([1.0, 2.0, 3.0]), np.array([2.0, -1.0, 0.5]), so3.exp(np.array([0.1, -0.2, 0.8])),
                      np.array([0.1, -0.2, 0.05]), np.array([0.03, -0.02, 0.01]))
    truth = imu.integrate(x0, acc, gyro, dt, GRAVITY)[[0, K, 2 * K]]
    keys = [keyframe_keys(k) for k in range(3)]

    acc_j, gyro_j, dt_j = acc.reshape(2, K, 3), gyro.reshape(2, K, 3), dt.reshape(2, K)
    pre = preintegration.integrate(acc_j, gyro_j, dt_j, np.zeros((2, 3)))
    pre.cov = preintegration.noise_covariance(pre.samples, truth[:2], imu.ImuNoise(velocity=1e-3), GRAVITY)
    graph = gtsam.NonlinearFactorGraph()
    prior_cov = np.diag(np.concatenate([np.full(3, 10.0), np.full(3, 1.0), np.full(3, 0.5), np.full(3, 0.1),
                                        np.full(3, 0.1)]) ** 2)
    graph.add(priors.state_prior_factor(keys[0], truth[0], prior_cov))
    imu_factors = [ImuFactor(pre[k], keys[k], keys[k + 1], GRAVITY, reintegration_threshold=1e-9) for k in range(2)]
    for f in imu_factors:
        graph.add(f.factor)
    pose_model = gtsam.noiseModel.Diagonal.Sigmas(np.array([1e-3] * 3 + [1e-3] * 3))
    for k in (1, 2):
        graph.add(sm.sensor_factor(sm.POSE, keys[k], sm.pack_pose(truth[k].r[None], truth[k].C[None])[0], pose_model))

    initial = gtsam.Values()
    for k in range(3):
        dx = np.concatenate([rng.normal(0, 2, 3), rng.normal(0, 0.5, 3), rng.normal(0, 0.3, 3), np.zeros(6)])
        guess = imu.boxplus(truth[k], dx).replace(b_f=np.zeros(3), b_w=np.zeros(3))
        insert_state(initial, keys[k], guess)
    params = gtsam.LevenbergMarquardtParams()
    params.setRelativeErrorTol(1e-12)
    params.setAbsoluteErrorTol(1e-15)
    params.setMaxIterations(100)
    result = gtsam.LevenbergMarquardtOptimizer(graph, initial, params).optimize()
    assert graph.error(initial) > 1e3
    assert graph.error(result) < 1e-10
    for k in range(3):
        err = imu.boxminus(read_state(result, keys[k]), truth[k])
        assert np.abs(err).max() < 1e-6, (k, err)
    assert all(f.reintegrations > 0 for f in imu_factors)
