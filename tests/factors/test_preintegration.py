"""factors.preintegration: exact preintegration of the primer's Euler-forward IMU model.

What is proved here:

* the prediction equals sample-by-sample Euler-forward propagation (:func:`factors.imu.integrate`)
  to round-off, for random states, rates of several rad/s, large biases, up to 400 samples, and a
  batch of padded intervals equals the same intervals integrated one by one (``dt = 0`` padding is
  the identity);
* the gyro bias enters to first order: the prediction error after a bias change ``d`` shrinks like
  ``|d|^2`` (log-log slope 2), ``relinearized`` is exact again, and the bias Jacobians ``JC, dW,
  dRm`` are the numerical derivatives of the exact integration;
* ``noise_covariance`` is the EKF's covariance growth ``P <- F P F^T + G Q_d G^T`` rotated into
  body frame ``i``, it is symmetric positive semidefinite, and it is the covariance of the
  residual under Monte Carlo noise drawn per :class:`factors.imu.ImuNoise`;
* the residual is exactly ``T (x_j [-] prediction)`` and its analytic Jacobians match central
  differences on the IMU-state manifold at tiny, ordinary and near-pi attitudes.

Tolerances. ``EPS`` = 2.2e-16. The prediction identity is required to 1e-9 (absolute, on every
component of ``predicted [-] integrated``; positions are up to ~200 m, velocities ~50 m/s): the
measured error is ~1e-13, and any modelling slip (a missing sample, a transposed rotation, a
wrong sign) is at least ``dt * rate`` ~ 1e-3. Central differences (step ``h = 1e-6``) carry a
round-off error of about ``EPS |f| / h`` ~ 2e-10 |f|; they are compared with a bound of
``1e-7 * max(1, |f|)`` (500 times that round-off estimate, 1e-7 relative), while a wrong block is
wrong at order one.
"""
from __future__ import annotations

import math
import zlib

import numpy as np
import pytest
import strategies as S
from hypothesis import given, settings
from hypothesis import strategies as st
from strategies import EPS, random_rotation

from factors import imu, preintegration, so3
from factors.jacobians import numerical_jacobian
from factors.threads import thread_limit

GRAVITY = imu.DEFAULT_GRAVITY
#: Required agreement of prediction and sample-by-sample integration (see module docstring).
PREDICTION_TOL = 1e-9
#: Relative bound for central differences with step 1e-6 (see module docstring).
NUMERIC_REL = 1e-7


# --------------------------------------------------------------------------- helpers




def random_state(rng: np.random.Generator, regime: str = "ordinary", b_f: float = 1.0,
                 b_w: float = 0.5) -> imu.ImuState:
    """Position within 100 m, body velocity within 10 m/s, LARGE biases (1 m/s^2, 0.5 rad/s)."""
    return imu.ImuState(
        r=rng.uniform(-100, 100, 3),
        v=rng.uniform(-10, 10, 3),
        C=random_rotation(rng, regime),
        b_f=rng.uniform(-b_f, b_f, 3),
        b_w=rng.uniform(-b_w, b_w, 3),
    )


def random_samples(rng: np.random.Generator, K: int, rate: float = 3.0):
    """``K`` IMU samples: a constant turn of up to ``rate`` rad/s per axis plus a jitter of 1 rad/s
    (so rates of several rad/s), specific force around 1 g with 5 m/s^2 jitter, dt in [1, 10] ms."""
    gyro = rng.uniform(-rate, rate, 3) + rng.normal(0.0, 1.0, (K, 3))
    acc = np.array([0.0, 0.0, 9.81]) + rng.normal(0.0, 5.0, (K, 3))
    dt = rng.uniform(1e-3, 1e-2, K)
    return acc, gyro, dt


def integrate_one(acc, gyro, dt, b_w_bar) -> preintegration.Preintegrated:
    """One interval (no leading dimension)."""
    return preintegration.integrate(acc[None], gyro[None], dt[None], np.asarray(b_w_bar)[None])[0]


def euler_loop(state: imu.ImuState, acc, gyro, dt) -> imu.ImuState:
    """The reference: :func:`factors.imu.propagate` (the model's one Euler-forward step) applied
    sample by sample, written out here; ``state`` may be a batch (leading dimension)."""
    for a, g, h in zip(acc, gyro, dt):
        state, _, _ = imu.propagate(state, a, g, h, GRAVITY, jacobians=False)
    return state


def euler(state: imu.ImuState, acc, gyro, dt) -> imu.ImuState:
    """The state after the last sample by dead reckoning, :func:`factors.imu.integrate` (the
    library's sample-by-sample propagation)."""
    return imu.integrate(state, acc, gyro, dt, GRAVITY)[-1]


def batch(states: list[imu.ImuState]) -> imu.ImuState:
    return imu.ImuState.stack(states)


def transform(C_i: np.ndarray) -> np.ndarray:
    """``T = diag(C_i^T, I, C_i^T, I, I)``: world error state -> the residual's body-i coordinates."""
    T = np.eye(15)
    T[imu.R, imu.R] = C_i.T
    T[imu.PHI, imu.PHI] = C_i.T
    return T


def big_bias_states(regime: str = "any"):
    """Hypothesis states with LARGE biases: accelerometer within 2 m/s^2, gyro within 1 rad/s."""
    return st.builds(
        imu.ImuState, r=S.vectors(100.0), v=S.vectors(10.0), C=S.rotations(regime),
        b_f=S.vectors(2.0), b_w=S.vectors(1.0),
    )


seeds = st.integers(0, 2**32 - 1)


# --------------------------------------------------------------------------- prediction identity


@settings(max_examples=25, deadline=None)
@given(big_bias_states(), st.integers(1, 400), st.floats(0.0, 5.0), seeds)
def test_prediction_equals_sample_by_sample_euler_integration(x_i, K, rate, seed):
    rng = np.random.default_rng(seed)
    acc, gyro, dt = random_samples(rng, K, rate)
    pre = integrate_one(acc, gyro, dt, x_i.b_w)
    predicted = preintegration.predict(pre, x_i, GRAVITY)
    for integrated in (euler_loop(x_i, acc, gyro, dt), euler(x_i, acc, gyro, dt)):
        err = imu.boxminus(predicted, integrated)
        assert np.abs(err).max() < PREDICTION_TOL, err
    # the biases are carried unchanged, bit for bit
    assert np.array_equal(predicted.b_f, x_i.b_f) and np.array_equal(predicted.b_w, x_i.b_w)
    assert pre.duration == pytest.approx(dt.sum(), rel=4 * K * EPS)


def test_prediction_from_one_state_through_several_intervals_broadcasts_every_field():
    """One state, J intervals: J predictions, each that of its interval alone, and every field of
    the result (the carried biases too) has the leading dimension J."""
    rng = np.random.default_rng(5)
    J, K = 4, 30
    acc, gyro, dt = (np.stack(a) for a in zip(*[random_samples(rng, K, 2.0) for _ in range(J)]))
    x_i = random_state(rng, "ordinary")
    pre = preintegration.integrate(acc, gyro, dt, np.broadcast_to(x_i.b_w + 0.01, (J, 3)))  # first-order branch
    predicted = preintegration.predict(pre, x_i, GRAVITY)
    for name in ("r", "v", "b_f", "b_w"):
        assert getattr(predicted, name).shape == (J, 3), name
    assert predicted.C.shape == (J, 3, 3)
    for j in range(J):
        alone = preintegration.predict(pre[j], x_i, GRAVITY)
        assert np.abs(imu.boxminus(predicted[j], alone)).max() <= 64 * EPS * max(1.0, np.abs(alone.r).max())
        assert np.array_equal(predicted.b_f[j], x_i.b_f) and np.array_equal(predicted.b_w[j], x_i.b_w)


def test_prediction_identity_long_fast_interval_with_large_biases():
    """The hardest fixed case: 400 samples of 10 ms (4 s), turn rates up to ~6 rad/s, gyro bias
    1 rad/s, accelerometer bias 2 m/s^2, positions ~100 m and speeds growing to tens of m/s."""
    rng = np.random.default_rng(7)
    K = 400
    gyro = np.array([5.0, -3.0, 4.0]) + rng.normal(0.0, 1.0, (K, 3))
    acc = np.array([0.0, 0.0, 9.81]) + rng.normal(0.0, 8.0, (K, 3))
    dt = np.full(K, 1e-2)
    x_i = imu.ImuState(np.array([80.0, -60.0, 30.0]), np.array([9.0, -7.0, 3.0]), random_rotation(rng, "ordinary"),
                       np.array([2.0, -2.0, 1.5]), np.array([1.0, -0.8, 0.9]))
    pre = integrate_one(acc, gyro, dt, x_i.b_w)
    err = imu.boxminus(preintegration.predict(pre, x_i, GRAVITY), euler(x_i, acc, gyro, dt))
    assert np.abs(err).max() < PREDICTION_TOL


def test_batch_of_padded_intervals_equals_single_interval_calls():
    """J intervals of different lengths (0, 1, 2, 13, 100, 399, 400 samples) padded with dt = 0 to
    400 in ONE call give, interval by interval, the preintegrated arrays of single unpadded calls
    and the sample-by-sample prediction."""
    rng = np.random.default_rng(11)
    lengths = [0, 1, 2, 13, 100, 399, 400]
    J, K = len(lengths), max(lengths)
    acc, gyro, dt = np.zeros((J, K, 3)), np.zeros((J, K, 3)), np.zeros((J, K))
    # the padding carries garbage samples: only dt = 0 may make them harmless
    acc[:] = rng.normal(0, 50, (J, K, 3))
    gyro[:] = rng.normal(0, 50, (J, K, 3))
    pieces, states = [], []
    for j, n in enumerate(lengths):
        a, g, h = random_samples(rng, n, rate=4.0)
        acc[j, :n], gyro[j, :n], dt[j, :n] = a, g, h
        pieces.append((a, g, h))
        states.append(random_state(rng, ["tiny", "ordinary", "near_pi"][j % 3]))
    x_i = batch(states)
    pre = preintegration.integrate(acc, gyro, dt, x_i.b_w)
    predicted = preintegration.predict(pre, x_i, GRAVITY)
    for j, (a, g, h) in enumerate(pieces):
        single = preintegration.integrate(a[None], g[None], h[None], x_i.b_w[j][None])
        for name in ("dC", "W", "Rm", "JC", "dW", "dRm"):
            ref = getattr(single, name)[0]
            got = getattr(pre, name)[j]
            # same operations in a different batch: round-off only (64 EPS of the array's scale)
            assert np.abs(got - ref).max() <= 64 * EPS * max(1.0, np.abs(ref).max()), (lengths[j], name)
        assert pre.duration[j] == pytest.approx(h.sum(), rel=4 * K * EPS, abs=0.0)  # summation order
        err = imu.boxminus(predicted[j], euler(states[j], a, g, h))
        assert np.abs(err).max() < PREDICTION_TOL, lengths[j]
    # the empty interval predicts the state itself (Rm = 0, W = [I|0|0|0], dC = I exactly)
    assert np.array_equal(pre.dC[0], np.eye(3)) and np.array_equal(pre.Rm[0], np.zeros((3, 10)))
    assert np.array_equal(predicted[0].r, x_i.r[0]) and np.array_equal(predicted[0].v, x_i.v[0])


def test_zero_dt_padding_is_exactly_the_identity():
    """Padding steps anywhere in the interval (not only at the end) leave every preintegrated array
    bit for bit unchanged, whatever sample values they carry: ``A = I``, ``exp(0) = I``, ``0 * x = 0``."""
    rng = np.random.default_rng(3)
    acc, gyro, dt = random_samples(rng, 50)
    b_w = rng.uniform(-0.5, 0.5, 3)
    plain = integrate_one(acc, gyro, dt, b_w)
    insert = [0, 0, 17, 17, 17, 50, 50]
    padded = integrate_one(
        np.insert(acc, insert, rng.normal(0, 100, (len(insert), 3)), axis=0),
        np.insert(gyro, insert, rng.normal(0, 100, (len(insert), 3)), axis=0),
        np.insert(dt, insert, 0.0),
        b_w,
    )
    for name in ("dC", "W", "Rm", "JC", "dW", "dRm"):
        assert np.array_equal(getattr(plain, name), getattr(padded, name)), name


# --------------------------------------------------------------------------- gyro bias: first order


def _exact_after_bias_change(x_i, acc, gyro, dt, direction, sizes) -> imu.ImuState:
    """Sample-by-sample integration from ``x_i`` with gyro bias ``b_w + size * direction`` for every
    size at once (one vectorised run)."""
    n = len(sizes)
    x = imu.ImuState(*(np.repeat(np.asarray(a)[None], n, axis=0) for a in (x_i.r, x_i.v, x_i.C, x_i.b_f, x_i.b_w)))
    x = x.replace(b_w=x.b_w + sizes[:, None] * direction)
    return x, euler_loop(x, acc, gyro, dt)


def _sweep_errors(pre, x, exact) -> np.ndarray:
    return np.abs(imu.boxminus(preintegration.predict(pre, x, GRAVITY), exact)).max(axis=-1)


def _slope(sizes, errors) -> float:
    return float(np.polyfit(np.log(sizes), np.log(errors), 1)[0])


@settings(max_examples=5, deadline=None)
@given(seeds)
def test_gyro_bias_enters_to_first_order_and_relinearized_is_exact(seed):
    """Bias changes d = 1e-2 ... 1e-5 rad/s (7 log-spaced sizes) on a 200-sample interval: the
    error of the first-order prediction has log-log slope 2 (required within [1.9, 2.1]; measured
    2.0000 +- 0.0004), and at 1e-5 it is still ~1e3 times the round-off floor (required > 1e-11),
    so the fit sees the model, not noise. The same sweep WITHOUT the bias correction (Jacobians
    zeroed) has slope 1 and fails the bound: the check can fail. Integrating again at the new
    bias is exact (1e-9), even for the largest change."""
    rng = np.random.default_rng(seed)
    acc, gyro, dt = random_samples(rng, 200, rate=3.0)
    x_i = random_state(rng)
    pre = integrate_one(acc, gyro, dt, x_i.b_w)
    direction = rng.normal(size=3)
    direction /= np.linalg.norm(direction)
    sizes = np.logspace(-2, -5, 7)
    x, exact = _exact_after_bias_change(x_i, acc, gyro, dt, direction, sizes)
    errors = _sweep_errors(pre, x, exact)
    assert errors[-1] > 1e-11  # far above round-off (~1e-13) at the smallest change
    assert 1.9 <= _slope(sizes, errors) <= 2.1, (errors, _slope(sizes, errors))

    # negative control: the same interval with the bias Jacobians zeroed is only zeroth order
    frozen = preintegration.Preintegrated(pre.dC, pre.W, pre.Rm, 0 * pre.JC, 0 * pre.dW, 0 * pre.dRm,
                                          pre.b_w_bar, pre.samples)
    assert abs(_slope(sizes, _sweep_errors(frozen, x, exact)) - 1.0) < 0.1

    # relinearised at the new bias: exact again
    fresh = pre.relinearized(x.b_w[0])
    assert np.array_equal(fresh.b_w_bar, x.b_w[0])
    err = imu.boxminus(preintegration.predict(fresh, x[0], GRAVITY), exact[0])
    assert np.abs(err).max() < PREDICTION_TOL


def test_relinearized_batch_and_covariance_kept():
    rng = np.random.default_rng(5)
    acc, gyro, dt = (np.stack(a) for a in zip(*[random_samples(rng, 30) for _ in range(3)]))
    states = batch([random_state(rng) for _ in range(3)])
    pre = preintegration.integrate(acc, gyro, dt, states.b_w)
    pre.cov = preintegration.noise_covariance(pre.samples, states, imu.ImuNoise(), GRAVITY)
    new_b_w = states.b_w + rng.uniform(-0.1, 0.1, (3, 3))
    fresh = pre.relinearized(new_b_w)
    assert fresh.cov is pre.cov
    for j in range(3):
        x = states[j].replace(b_w=new_b_w[j])
        err = imu.boxminus(preintegration.predict(fresh[j], x, GRAVITY), euler(x, acc[j], gyro[j], dt[j]))
        assert np.abs(err).max() < PREDICTION_TOL
    # the samples kept for re-integration are the integrator's own copies, not the caller's arrays
    kept = [a.copy() for a in pre.samples]
    for a in (acc, gyro, dt):
        a *= 2.0
    assert all(np.array_equal(a, b) for a, b in zip(pre.samples, kept))


@settings(max_examples=8, deadline=None)
@given(st.integers(1, 400), seeds)
def test_bias_jacobians_are_derivatives_of_the_exact_integration(K, seed):
    """``JC``, ``dW``, ``dRm`` equal central differences (step h = 1e-6) of ``integrate`` with
    respect to ``b_w``: ``dC`` in the [+]/[-] sense of eqs. (19)-(20), column ``l`` being
    ``(dC(b + h e_l) [-] dC(b) - dC(b - h e_l) [-] dC(b)) / 2h``; ``W`` and ``Rm`` as plain arrays.
    The seven integrations (b and b +- h e_l) run as one batch of seven intervals."""
    rng = np.random.default_rng(seed)
    acc, gyro, dt = random_samples(rng, K, rate=4.0)
    b_w = rng.uniform(-1.0, 1.0, 3)
    h = 1e-6
    biases = np.concatenate([b_w[None], b_w + h * np.eye(3), b_w - h * np.eye(3)])
    all7 = preintegration.integrate(*(np.repeat(a[None], 7, axis=0) for a in (acc, gyro, dt)), biases)
    pre, plus, minus = all7[0], all7[1:4], all7[4:7]
    # (columns l = 0, 1, 2 of each numerical Jacobian)
    num_JC = ((so3.boxminus(plus.dC, pre.dC) - so3.boxminus(minus.dC, pre.dC)) / (2 * h)).T
    num_dW = np.moveaxis((plus.W - minus.W) / (2 * h), 0, -1)
    num_dRm = np.moveaxis((plus.Rm - minus.Rm) / (2 * h), 0, -1)
    for name, analytic, numeric, scale in (
        ("JC", pre.JC, num_JC, 1.0),
        ("dW", pre.dW, num_dW, np.abs(pre.W).max()),
        ("dRm", pre.dRm, num_dRm, np.abs(pre.Rm).max()),
    ):
        assert np.abs(analytic - numeric).max() <= NUMERIC_REL * max(1.0, scale), name


def test_bias_jacobian_check_uses_numerical_jacobian_too():
    """The same derivative through the library's :func:`numerical_jacobian` (one interval, so the
    slow sequential calls stay cheap): ``dC`` as a rotation value, ``W`` as a vector value."""
    rng = np.random.default_rng(12)
    acc, gyro, dt = random_samples(rng, 40, rate=4.0)
    b_w = rng.uniform(-1.0, 1.0, 3)
    pre = integrate_one(acc, gyro, dt, b_w)
    (num_JC,) = numerical_jacobian(lambda b: integrate_one(acc, gyro, dt, b).dC, b_w,
                                   arg_kinds=["vector"], value_kind="rotation")
    (num_dW,) = numerical_jacobian(lambda b: integrate_one(acc, gyro, dt, b).W, b_w,
                                   arg_kinds=["vector"], value_kind="vector")
    assert np.abs(pre.JC - num_JC).max() <= NUMERIC_REL
    assert np.abs(pre.dW.reshape(30, 3) - num_dW).max() <= NUMERIC_REL * max(1.0, np.abs(pre.W).max())


# --------------------------------------------------------------------------- noise covariance


def ekf_covariance(x_i: imu.ImuState, acc, gyro, dt, noise: imu.ImuNoise) -> np.ndarray:
    """The EKF's covariance growth written out independently: one state, one sample at a time,
    ``P <- F P F^T + G Qd G^T`` from ``P = 0``, ``Qd = diag(R_i / dt)``, then ``T P T^T``."""
    P = np.zeros((15, 15))
    x = x_i
    for a, g, h in zip(acc, gyro, dt):
        x, F, G = imu.propagate(x, a, g, h, GRAVITY)
        Qd = np.diag(noise.densities() / h) if h > 0 else np.zeros((15, 15))
        P = F @ P @ F.T + G @ Qd @ G.T
    T = transform(x_i.C)
    return T @ P @ T.T


def test_noise_covariance_is_the_ekf_covariance_growth_and_psd():
    rng = np.random.default_rng(21)
    lengths = [1, 2, 40, 250]
    J, K = len(lengths), max(lengths)
    acc, gyro, dt = np.zeros((J, K, 3)), np.zeros((J, K, 3)), np.zeros((J, K))
    pieces = []
    for j, n in enumerate(lengths):
        a, g, h = random_samples(rng, n)
        acc[j, :n], gyro[j, :n], dt[j, :n] = a, g, h
        pieces.append((a, g, h))
    states = batch([random_state(rng, regime) for regime in ("ordinary", "tiny", "near_pi", "ordinary")])
    noise = imu.ImuNoise(acc=0.02, gyro=2e-3, acc_bias=1e-3, gyro_bias=1e-4, velocity=1e-3)
    cov = preintegration.noise_covariance((acc, gyro, dt), states, noise, GRAVITY)
    assert cov.shape == (J, 15, 15)
    for j, (a, g, h) in enumerate(pieces):
        # noise_covariance may add a documented floor (COVARIANCE_FLOOR^2 I) for one-sample intervals
        floor = getattr(preintegration, "COVARIANCE_FLOOR", 0.0) ** 2
        ref = ekf_covariance(states[j], a, g, h, noise) + floor * np.eye(15)
        scale = np.abs(ref).max()
        # same products in another order: round-off relative to the largest entry
        assert np.abs(cov[j] - ref).max() <= 1e-12 * scale, lengths[j]
        assert np.array_equal(cov[j], cov[j].T)
        eig = np.linalg.eigvalsh(cov[j])
        assert eig.min() >= -1e-13 * eig.max(), eig
    # with every density positive and two or more samples the covariance is positive definite
    for j in (1, 2, 3):
        np.linalg.cholesky(cov[j])


def padded_intervals(rng, lengths):
    """Random samples of intervals of the given lengths, padded with ``dt = 0`` to ``(J, K)``."""
    J, K = len(lengths), max(lengths)
    acc, gyro, dt = np.zeros((J, K, 3)), np.zeros((J, K, 3)), np.zeros((J, K))
    for j, n in enumerate(lengths):
        acc[j, :n], gyro[j, :n], dt[j, :n] = random_samples(rng, n)
    return acc, gyro, dt


def reference_chain(start, pre, anchors):
    """The reference trajectory of :func:`integrate_with_covariance` written out with
    :func:`preintegration.predict`: each keyframe predicted from the one before, then the known
    anchors (position, attitude, then body velocity ``C^T v_world``) put in."""
    def anchored(x, k):
        if np.isfinite(anchors.r[k, 0]):
            x = x.replace(r=anchors.r[k])
        if np.isfinite(anchors.C[k, 0, 0]):
            x = x.replace(C=anchors.C[k])
        if np.isfinite(anchors.world_v[k, 0]):
            x = x.replace(v=x.C.T @ anchors.world_v[k])
        return x

    states = [anchored(start, 0)]
    for j in range(len(pre)):
        states.append(anchored(preintegration.predict(pre[j], states[-1], GRAVITY), j + 1))
    return batch(states)


@pytest.mark.parametrize("anchored", ["none", "some", "all"])
def test_integrate_with_covariance_is_integrate_plus_noise_covariance_along_the_chain(anchored):
    """The one call = the separate computations: exactly the preintegrated quantities and bias
    Jacobians of :func:`integrate`, reference states equal to the prediction chain reset by the
    anchors, and the covariance :func:`noise_covariance` gives at those states."""
    rng = np.random.default_rng(31)
    lengths = [7, 1, 40, 23, 60]
    acc, gyro, dt = padded_intervals(rng, lengths)
    J = len(lengths)
    start = random_state(rng)
    anchors = preintegration.Anchors.none(J + 1)
    if anchored != "none":
        truth = batch([random_state(rng, regime) for regime in ("ordinary", "tiny", "near_pi") * 2])
        every = slice(None) if anchored == "all" else slice(None, None, 2)
        anchors.r[every], anchors.C[every] = truth.r[every], truth.C[every]
        anchors.world_v[1::3] = truth.world_velocity()[1::3]  # velocity at other keyframes than r, C
    noise = imu.ImuNoise(acc=0.02, gyro=2e-3, acc_bias=1e-3, gyro_bias=1e-4, velocity=1e-3)
    pre, states = preintegration.integrate_with_covariance((acc, gyro, dt), start, noise, GRAVITY, anchors)
    alone = preintegration.integrate(acc, gyro, dt, start.b_w)
    for name in ("dC", "W", "Rm", "JC", "dW", "dRm", "b_w_bar", "duration"):
        assert np.array_equal(getattr(pre, name), getattr(alone, name)), name
    chain = reference_chain(start, alone, anchors)
    assert states.shape == (J + 1,)
    assert np.abs(imu.boxminus(states, chain)).max() < 1e-12
    assert np.array_equal(states.b_f, np.broadcast_to(start.b_f, (J + 1, 3)))
    assert np.array_equal(states.b_w, np.broadcast_to(start.b_w, (J + 1, 3)))
    cov = preintegration.noise_covariance((acc, gyro, dt), chain[:-1], noise, GRAVITY)
    scale = np.abs(cov).max(axis=(1, 2), keepdims=True)
    assert np.all(np.abs(pre.cov - cov) <= 1e-12 * scale)
    if anchored == "all":  # every keyframe is its anchor (velocity only where given)
        assert np.allclose(states.r, anchors.r) and np.allclose(states.C, anchors.C)


def test_integrate_interval_is_integrate_with_covariance_of_one_interval_and_predict():
    """The unchecked one-interval path gives what the checked call gives for ``J = 1`` (every
    preintegrated quantity, the covariance, bit for bit or to round-off where the kernels are
    compiled into another caller; the samples it keeps exactly, as copies) and the prediction
    :func:`predict` gives from the start through it."""
    rng = np.random.default_rng(7)
    acc, gyro, dt = padded_intervals(rng, [23])
    start = random_state(rng)
    noise = imu.ImuNoise(acc=0.02, gyro=2e-3, acc_bias=1e-3, gyro_bias=1e-4, velocity=1e-3)
    whole, _ = preintegration.integrate_with_covariance((acc, gyro, dt), start, noise, GRAVITY)
    given = acc[0].copy()
    one, predicted = preintegration.integrate_interval(given, gyro[0], dt[0], start, noise, GRAVITY)
    for name in ("dC", "W", "Rm", "JC", "dW", "dRm", "b_w_bar", "cov"):
        mine, theirs = getattr(one, name), getattr(whole[0], name)
        np.testing.assert_allclose(mine, theirs, rtol=1e-13, atol=1e-13 * np.abs(theirs).max(), err_msg=name)
    for mine, theirs in zip(one.samples, whole[0].samples):
        assert np.array_equal(mine, theirs)
    given[:] = 0.0  # the interval keeps its own samples
    assert np.array_equal(one.samples[0], acc[0])
    expected = preintegration.predict(whole[0], start, GRAVITY)
    assert imu.boxminus(predicted, expected).max() < 1e-12
    assert np.array_equal(predicted.b_f, start.b_f) and np.array_equal(predicted.b_w, start.b_w)


def test_results_do_not_depend_on_the_number_of_threads(monkeypatch):
    """Intervals are split among threads in contiguous ranges; each interval's arithmetic is the
    same whichever thread runs it, so the results are identical bit for bit."""
    rng = np.random.default_rng(8)
    lengths = [int(n) for n in rng.integers(1, 30, size=11)]
    acc, gyro, dt = padded_intervals(rng, lengths)
    start, noise = random_state(rng), imu.ImuNoise(acc=0.02, gyro=2e-3, acc_bias=1e-3, gyro_bias=1e-4)
    anchors = preintegration.Anchors.none(len(lengths) + 1)
    anchors.r[::3] = rng.normal(size=(4, 3))
    monkeypatch.setattr(preintegration, "_MIN_INTERVALS_PER_THREAD", 2)
    runs = []
    for threads in (1, 2, 5):
        with thread_limit(threads):
            runs.append(preintegration.integrate_with_covariance((acc, gyro, dt), start, noise, GRAVITY, anchors))
    (one, states_one), others = runs[0], runs[1:]
    for pre, states in others:
        for name in ("dC", "W", "Rm", "JC", "dW", "dRm", "cov"):
            assert np.array_equal(getattr(pre, name), getattr(one, name)), name
        for name in ("r", "v", "C"):
            assert np.array_equal(getattr(states, name), getattr(states_one, name)), name


def test_integrate_with_covariance_refuses_bad_input():
    rng = np.random.default_rng(2)
    acc, gyro, dt = padded_intervals(rng, [5, 3])
    start, noise = random_state(rng), imu.ImuNoise()
    with pytest.raises(ValueError, match="start: expected one state"):
        preintegration.integrate_with_covariance((acc, gyro, dt), batch([start, start]), noise)
    with pytest.raises(ValueError, match=r"acc, gyro \(J, K, 3\) and dt \(J, K\)"):
        preintegration.integrate_with_covariance((acc, gyro, dt[:, :-1]), start, noise)
    with pytest.raises(ValueError, match="acc: expected shape"):
        preintegration.integrate_with_covariance((acc[..., :2], gyro, dt), start, noise)
    anchors = preintegration.Anchors.none(3)
    anchors.r[1, 2] = 4.0  # one coordinate known, two not: not an anchor, not unknown
    with pytest.raises(ValueError, match=r"anchors.r\[1\]: expected all finite"):
        preintegration.integrate_with_covariance((acc, gyro, dt), start, noise, anchors=anchors)
    with pytest.raises(ValueError, match=r"anchors.r: expected shape \(3, 3\)"):  # J + 1 = 3 keyframes
        preintegration.integrate_with_covariance((acc, gyro, dt), start, noise, anchors=preintegration.Anchors.none(4))
    # nothing is broadcast where it would silently change the meaning
    with pytest.raises(ValueError, match="gravity"):
        preintegration.integrate_with_covariance((acc, gyro, dt), start, noise, gravity=-9.81)
    with pytest.raises(ValueError, match="b_w_bar"):
        preintegration.integrate(acc, gyro, dt, np.full((2, 1), 0.1))
    with pytest.raises(ValueError, match=r"b_w_bar: expected shape \(2, 3\) \(or one that broadcasts to it\), "
                                         r"got \(5, 3\)"):
        preintegration.integrate(acc, gyro, dt, np.zeros((5, 3)))
    with pytest.raises(ValueError, match="start.v"):
        preintegration.integrate_with_covariance((acc, gyro, dt), start.replace(v=np.full(3, np.nan)), noise)
    with pytest.raises(ValueError, match=r"start.b_w: expected finite"):
        preintegration.integrate_with_covariance((acc, gyro, dt), start.replace(b_w=np.full(3, np.nan)), noise)
    with pytest.raises(ValueError, match=r"b_w_bar: expected finite"):
        preintegration.integrate(acc, gyro, dt, np.full((2, 3), np.inf))
    # the samples are checked first: with bad samples AND a bad gravity, the samples are named
    with pytest.raises(ValueError, match=r"acc, gyro \(J, K, 3\) and dt \(J, K\)"):
        preintegration.integrate_with_covariance((acc, gyro, np.float64(0.01)), start, noise, gravity=-9.81)
    # a NaN reference is an error for noise_covariance (NaN would read as an unknown anchor)
    states = batch([start, start.replace(v=np.full(3, np.nan))])
    with pytest.raises(ValueError, match=r"reference.v\[1\]: expected finite"):
        preintegration.noise_covariance((acc, gyro, dt), states, noise)


def test_noise_covariance_does_not_depend_on_the_yaw_of_keyframe_i():
    """In body-i coordinates the covariance is invariant under a rotation of the world about
    gravity (the reason for T); the world-frame covariance P would not be."""
    rng = np.random.default_rng(4)
    a, g, h = random_samples(rng, 60)
    x = random_state(rng)
    yawed = x.replace(C=so3.exp(np.array([0.0, 0.0, 1.2])) @ x.C)
    noise = imu.ImuNoise(velocity=1e-3)
    pair = batch([x, yawed])
    cov = preintegration.noise_covariance((np.stack([a, a]), np.stack([g, g]), np.stack([h, h])), pair, noise, GRAVITY)
    assert np.abs(cov[0] - cov[1]).max() <= 1e-12 * np.abs(cov[0]).max()


def _whitened_sample_covariance(e: np.ndarray, cov: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    L = np.linalg.cholesky(cov)
    w = np.linalg.solve(L, e.T).T
    return w.mean(axis=0), w.T @ w / len(w)


def _z_scores(mean: np.ndarray, S: np.ndarray, n: int) -> tuple[float, float]:
    """Largest standardised deviation of a whitened sample covariance from I (entry sd ``1/sqrt(n)``
    off the diagonal, ``sqrt(2/n)`` on it) and of the whitened mean from 0 (sd ``1/sqrt(n)``)."""
    sd = np.full(S.shape, 1.0 / math.sqrt(n))
    np.fill_diagonal(sd, math.sqrt(2.0 / n))
    return float(np.abs((S - np.eye(len(S))) / sd).max()), float(np.abs(mean).max() * math.sqrt(n))


def test_noise_covariance_is_the_residual_covariance_monte_carlo():
    """2000 noisy realisations of a 20-sample interval (0.1 s, 2 rad/s turns, all five noise
    densities nonzero): the true state at j is propagated from x_i with discrete noise
    ``n ~ N(0, R_i / dt)`` per step (``propagate_with_noise``, the biases random-walking), and the
    residual is taken against the noise-free preintegration. Whitened by ``noise_covariance``, the
    residuals' sample covariance must be I and their mean 0.

    Statistical tolerance: each of the 120 + 15 distinct entries of the whitened sample covariance
    has standard deviation 1/sqrt(N) (off-diagonal) or sqrt(2/N) (diagonal); all must lie within
    5 of their standard deviations (for N = 2000: 0.11 and 0.16). Under the hypothesis the chance
    of any of the 135 exceeding 5 sd is ~1e-4 (and the seed is fixed). Measured here: 2.5 sd
    (covariance) and 2.0 sd (mean); with other seeds the worst stays near 3.3 sd, the same in units
    of sd for N = 2e3, 2e4 and 1e5 -- sampling noise, not bias. The same statistic rejects a
    covariance 30% too large (8.5 sd) and one left in world coordinates without T (139 sd)."""
    rng = np.random.default_rng(2)
    K, N = 20, 2000
    acc = np.array([0.0, 0.0, 9.81]) + rng.normal(0.0, 3.0, (K, 3))
    gyro = rng.normal(0.0, 2.0, (K, 3))
    dt = np.full(K, 5e-3)
    x_i = random_state(rng, b_w=0.2, b_f=0.5)
    noise = imu.ImuNoise(acc=0.05, gyro=0.01, acc_bias=0.01, gyro_bias=2e-3, velocity=0.02)
    pre = integrate_one(acc, gyro, dt, x_i.b_w)
    cov = preintegration.noise_covariance((acc[None], gyro[None], dt[None]), batch([x_i]), noise, GRAVITY)[0]

    x = imu.ImuState(*(np.repeat(np.asarray(a)[None], N, axis=0) for a in (x_i.r, x_i.v, x_i.C, x_i.b_f, x_i.b_w)))
    sigma = np.sqrt(noise.densities())
    for k in range(K):
        n = rng.normal(size=(N, 15)) * sigma / math.sqrt(dt[k])
        x = imu.propagate_with_noise(x, acc[k], gyro[k], dt[k], n, GRAVITY)
    e = preintegration.residual(pre, x_i, x, GRAVITY)

    cov_z, mean_z = _z_scores(*_whitened_sample_covariance(e, cov), N)
    assert cov_z < 5.0 and mean_z < 5.0, (cov_z, mean_z)
    # negative controls: the same statistic rejects wrong covariances
    assert _z_scores(*_whitened_sample_covariance(e, 1.3 * cov), N)[0] > 5.0
    T = transform(x_i.C)
    assert _z_scores(*_whitened_sample_covariance(e, T.T @ cov @ T), N)[0] > 5.0


# --------------------------------------------------------------------------- residual


def test_residual_is_the_error_state_in_body_i_coordinates():
    """At ``x_j = predict(x_i) [+] dx`` the residual is EXACTLY ``T dx`` (not only to first
    order): ``C_i^T (r + dr - r_i) - Rm z = C_i^T dr`` and ``log(C_i^T exp(dphi) C_i dC dC^T) =
    C_i^T dphi``. So the residual's coordinates are those of ``noise_covariance``. Checked for
    increments up to 3 rad in attitude; round-off bound 1e-12 on positions of ~100 m."""
    rng = np.random.default_rng(8)
    for regime in ("tiny", "ordinary", "near_pi"):
        a, g, h = random_samples(rng, 120)
        x_i = random_state(rng, regime)
        pre = integrate_one(a, g, h, x_i.b_w)
        x_pred = preintegration.predict(pre, x_i, GRAVITY)
        assert np.abs(preintegration.residual(pre, x_i, x_pred, GRAVITY)).max() < PREDICTION_TOL
        for _ in range(5):
            dx = rng.normal(0, 1, 15)
            axis = rng.normal(size=3)
            dx[imu.PHI] = rng.uniform(0.0, 3.0) * axis / np.linalg.norm(axis)
            e = preintegration.residual(pre, x_i, imu.boxplus(x_pred, dx), GRAVITY)
            assert np.abs(e - transform(x_i.C) @ dx).max() < 1e-11, regime


def _residual_cases(rng, anchor: str, regime: str, lengths, offsets):
    """Intervals (one batched integration) and state pairs whose residual attitude error is at most
    ~1.5 rad while the attitude of ``anchor`` (``"i"``, ``"j"`` or ``"both"``) is drawn from
    ``regime``. ``offsets`` are the sizes of the gyro-bias offsets of ``x_i`` from ``b_w_bar``
    (the first-order correction active), up to 1 rad/s absolute biases."""
    J, K = len(lengths), max(lengths)
    acc, gyro, dt = np.zeros((J, K, 3)), np.zeros((J, K, 3)), np.zeros((J, K))
    b_w_bar = rng.uniform(-1.0, 1.0, (J, 3))
    for j, n in enumerate(lengths):
        acc[j, :n], gyro[j, :n], dt[j, :n] = random_samples(rng, n, 3.0)
        if anchor == "both":  # a slow interval (true rate ~1e-3 rad/s) keeps C_j near C_i
            gyro[j, :n] = b_w_bar[j] + rng.normal(0.0, 1e-3, (n, 3))
    pres = preintegration.integrate(acc, gyro, dt, b_w_bar)
    cases = []
    for j, offset in enumerate(offsets):
        pre = pres[j]
        x_i = random_state(rng, regime if anchor in ("i", "both") else "ordinary")
        x_i = x_i.replace(b_w=b_w_bar[j] + offset * rng.uniform(-1, 1, 3))
        x_pred = preintegration.predict(pre, x_i, GRAVITY)
        dx = rng.normal(0.0, 1.0, 15)
        dx[imu.PHI] = rng.normal(0.0, 1e-2 if anchor == "both" else 0.5, 3)
        x_j = imu.boxplus(x_pred, dx)
        if anchor == "j":
            # rotate the pair rigidly so that C_j lands in the regime: the attitude error is
            # unchanged, the gravity direction seen by x_i changes (another valid case)
            C_target = random_rotation(rng, regime)
            Rw = C_target @ x_j.C.T
            x_i = x_i.replace(C=Rw @ x_i.C)
            x_j = x_j.replace(C=C_target)
        cases.append((pre, x_i, x_j))
    return cases


@pytest.mark.parametrize("anchor", ["i", "j", "both"])
@pytest.mark.parametrize("regime", ["tiny", "ordinary", "near_pi"])
def test_residual_jacobians_match_numerical(anchor, regime):
    """Analytic ``(Ji, Jj)`` of the residual against central differences on the IMU-state manifold
    (``numerical_jacobian`` with ``StateManifold`` arguments, ``value_kind="vector"``): 6 random
    cases per parametrisation (54 in all), intervals of 1 to 400 samples at rates of several
    rad/s, gyro-bias offsets of 0, 1e-3 and 0.05 rad/s from ``b_w_bar`` (which is up to 1 rad/s).
    Bound: 1e-7 * max(1, |e|, |J|) per block (see the module docstring). A transposed ``C_i`` in
    the attitude block fails the same bound."""
    rng = np.random.default_rng(zlib.crc32(f"{anchor}-{regime}".encode()))
    cases = _residual_cases(rng, anchor, regime, [1, 5, 60, 400, 20, 150], [0.0, 1e-3, 0.05] * 2)
    for case, (pre, x_i, x_j) in enumerate(cases):
        if regime == "tiny" and anchor != "j":
            assert np.linalg.norm(so3.log(x_i.C)) <= 1e-6
        if regime == "near_pi" and anchor != "i":
            assert np.linalg.norm(so3.log(x_j.C)) >= math.pi - 1e-3 - (0.1 if anchor == "both" else 0.0)
        e, (Ji, Jj) = preintegration.residual(pre, x_i, x_j, GRAVITY, jacobians=True)
        Ni, Nj = numerical_jacobian(
            lambda a, b: preintegration.residual(pre, a, b, GRAVITY), x_i, x_j,
            arg_kinds=[imu.StateManifold] * 2, value_kind="vector",
        )
        assert np.abs(e[imu.PHI]).max() < 2.0  # away from the cut of log at pi
        for A, N, name in ((Ji, Ni, "Ji"), (Jj, Nj, "Jj")):
            scale = max(1.0, np.abs(e).max(), np.abs(N).max())
            err = np.abs(A - N).max()
            assert err <= NUMERIC_REL * scale, (name, case, err, scale)
        # a transposed C_i in the attitude block is caught by the same bound
        if np.abs(x_i.C - x_i.C.T).max() > 1e-2:
            bad = Ji.copy()
            bad[imu.PHI, imu.PHI] = -so3.gamma_inv(e[imu.PHI]) @ x_i.C
            assert np.abs(bad - Ni).max() > NUMERIC_REL * max(1.0, np.abs(e).max(), np.abs(Ni).max())


def test_residual_is_vectorised_over_intervals():
    rng = np.random.default_rng(9)
    cases = _residual_cases(rng, "i", "ordinary", [30, 3, 17, 30], [0.01] * 4)
    acc = np.stack([c[0].samples[0] for c in cases])
    gyro = np.stack([c[0].samples[1] for c in cases])
    dt = np.stack([c[0].samples[2] for c in cases])
    pre = preintegration.integrate(acc, gyro, dt, np.stack([c[0].b_w_bar for c in cases]))
    xi, xj = batch([c[1] for c in cases]), batch([c[2] for c in cases])
    e, (Ji, Jj) = preintegration.residual(pre, xi, xj, GRAVITY, jacobians=True)
    for j, (p, a, b) in enumerate(cases):
        e1, (Ji1, Jj1) = preintegration.residual(p, a, b, GRAVITY, jacobians=True)
        assert np.abs(e[j] - e1).max() <= 1e-12 * max(1.0, np.abs(e1).max())
        assert np.abs(Ji[j] - Ji1).max() <= 1e-12 * max(1.0, np.abs(Ji1).max())
        assert np.abs(Jj[j] - Jj1).max() <= 1e-12 * max(1.0, np.abs(Jj1).max())


def test_assign_replaces_intervals_with_relinearized_ones():
    """``assign`` (used to re-integrate the drifted intervals of a batch in place) makes those
    intervals exact at their new gyro bias, leaves the others and the covariance untouched."""
    rng = np.random.default_rng(13)
    acc, gyro, dt = (np.stack(a) for a in zip(*[random_samples(rng, 25) for _ in range(4)]))
    states = batch([random_state(rng) for _ in range(4)])
    pre = preintegration.integrate(acc, gyro, dt, states.b_w)
    pre.cov = preintegration.noise_covariance(pre.samples, states, imu.ImuNoise(), GRAVITY)
    cov, untouched = pre.cov.copy(), pre[[0, 2]]
    moved = np.array([1, 3])
    new_b_w = states.b_w[moved] + 0.1
    pre.assign(moved, pre[moved].relinearized(new_b_w))
    assert np.array_equal(pre.cov, cov) and np.array_equal(pre.b_w_bar[moved], new_b_w)
    for name in ("dC", "W", "Rm", "JC", "dW", "dRm", "b_w_bar"):
        assert np.array_equal(getattr(pre, name)[[0, 2]], getattr(untouched, name))
    for j, b in zip(moved, new_b_w):
        x = states[j].replace(b_w=b)
        err = imu.boxminus(preintegration.predict(pre[j], x, GRAVITY), euler(x, acc[j], gyro[j], dt[j]))
        assert np.abs(err).max() < PREDICTION_TOL
