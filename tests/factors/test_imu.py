"""factors.imu: the primer's IMU model (section VI) -- one Euler-forward step with its Jacobians F
(state) and G (noise), checked block by block against numerical Jacobians on the 15-dim state
manifold, at random states with large angular rates (several rad/s), biases, and attitudes from
tiny to within 1e-3 rad of pi.

Also documents that the primer's typeset attitude/gyro-bias block ``-dt C^T Gamma`` is wrong for
the LEFT boxplus (the numerical Jacobian is ``-dt C Gamma``), and checks dt = 0, integrate,
noise, physics sanity (rest, constant rate, free fall) and vectorisation.

Tolerance: central differences with step 1e-6 on a state whose entries reach ``SCALE`` (|r| up to
100 m) have round-off EPS SCALE / 1e-6; ``tol(...)`` = 1e-8 per unit of that scale is ~50x it. A
wrong block is O(dt) = O(1e-3) or larger, i.e. >= 1e3 times the tolerance.
"""
from __future__ import annotations

import math

import numpy as np
import pytest
import strategies as S
from hypothesis import given, settings
from hypothesis import strategies as st
from strategies import EPS

from factors import imu, so3
from factors.jacobians import numerical_jacobian

BLOCKS = {"r": imu.R, "v": imu.V, "phi": imu.PHI, "b_f": imu.BF, "b_w": imu.BW}
NOISE_BLOCKS = {"n_v": imu.NV, "n_f": imu.NF, "n_w": imu.NW, "n_bf": imu.NBF, "n_bw": imu.NBW}
G_WORLD = imu.DEFAULT_GRAVITY


def max_abs(a, b) -> float:
    return float(np.max(np.abs(np.asarray(a) - np.asarray(b))))


def tol(state, acc=np.zeros(3)) -> float:
    scale = max(1.0, np.abs(state.r).max(), np.abs(state.v).max(), np.abs(acc).max(), 9.81)
    return 1e-8 * scale


def numerical_F(state, acc, gyro, dt):
    (F,) = numerical_jacobian(lambda x: imu.propagate(x, acc, gyro, dt, jacobians=False)[0], state,
                              arg_kinds=[imu.StateManifold], value_kind=imu.StateManifold)
    return F


def numerical_G(state, acc, gyro, dt):
    (G,) = numerical_jacobian(lambda n: imu.propagate_with_noise(state, acc, gyro, dt, n), np.zeros(imu.NOISE_DIM),
                              arg_kinds=["vector"], value_kind=imu.StateManifold)
    return G


def assert_blocks_match(analytic, numerical, rows, cols, bound, label):
    for rname, rs in rows.items():
        for cname, cs in cols.items():
            err = max_abs(analytic[rs, cs], numerical[rs, cs])
            assert err <= bound, f"{label}[{rname}, {cname}]: {err:.3e} > {bound:.1e}"


rates = S.vectors(5.0)  # up to 5 rad/s per axis, 8.7 rad/s in norm
forces = S.vectors(20.0)
steps = st.floats(1e-3, 0.05)


# --------------------------------------------------------------------------- F and G, block by block


@given(S.imu_states(), forces, rates, steps)
def test_F_and_G_block_by_block(state, acc, gyro, dt):
    _, F, G = imu.propagate(state, acc, gyro, dt)
    assert F.shape == (15, 15) and G.shape == (15, 15)
    assert_blocks_match(F, numerical_F(state, acc, gyro, dt), BLOCKS, BLOCKS, tol(state, acc), "F")
    assert_blocks_match(G, numerical_G(state, acc, gyro, dt), BLOCKS, NOISE_BLOCKS, tol(state, acc), "G")


@settings(max_examples=30)
@given(S.imu_states(), forces, rates, st.floats(0.05, 0.6))
def test_F_and_G_with_large_rotation_steps(state, acc, gyro, dt):
    # dt |w| up to ~5 rad: Gamma(dt w) far from I, where an approximate Gamma would show
    _, F, G = imu.propagate(state, acc, gyro, dt)
    bound = tol(state, acc) * 10  # steps of 0.6 s make r' and v' 10x larger
    assert_blocks_match(F, numerical_F(state, acc, gyro, dt), BLOCKS, BLOCKS, bound, "F")
    assert_blocks_match(G, numerical_G(state, acc, gyro, dt), BLOCKS, NOISE_BLOCKS, bound, "G")


# --------------------------------------------------------------------------- the primer's typeset block


def primer_typeset_F_and_G(state, acc, gyro, dt):
    """F and G exactly as printed in the primer (section VI.C), with -dt C^T Gamma(dt w)."""
    C, v = state.C, state.v
    w = gyro - state.b_w
    I = np.eye(3)  # noqa: E741 -- the identity, as the matrices are typeset
    F, G = np.zeros((15, 15)), np.zeros((15, 15))
    Gam = so3.gamma(dt * w)
    F[0:3, 0:3], F[0:3, 3:6], F[0:3, 6:9] = I, dt * C, -dt * so3.skew(C @ v)
    F[3:6, 3:6], F[3:6, 6:9] = I - dt * so3.skew(w), dt * C.T @ so3.skew(G_WORLD)
    F[3:6, 9:12], F[3:6, 12:15] = -dt * I, -dt * so3.skew(v)
    F[6:9, 6:9], F[6:9, 12:15] = I, -dt * C.T @ Gam
    F[9:12, 9:12], F[12:15, 12:15] = I, I
    G[0:3, 0:3], G[3:6, 3:6], G[3:6, 6:9] = dt * C, -dt * I, -dt * so3.skew(v)
    G[6:9, 6:9], G[9:12, 9:12], G[12:15, 12:15] = -dt * C.T @ Gam, dt * I, dt * I
    return F, G


@settings(max_examples=40)
@given(S.imu_states(attitudes=S.asymmetric_rotations()), forces, rates, steps)
def test_primer_typeset_C_transpose_gamma_is_wrong_for_the_left_boxplus(state, acc, gyro, dt):
    # At a rotation with C != C^T, the numerical Jacobian of the attitude w.r.t. the gyro bias (and
    # the gyro noise) is -dt C Gamma(dt w), as factors.imu implements, NOT the printed
    # -dt C^T Gamma(dt w): C exp(dt (w - e)) = exp(-dt C Gamma e) C exp(dt w) (eqs. 31, 24).
    F_num, G_num = numerical_F(state, acc, gyro, dt), numerical_G(state, acc, gyro, dt)
    F_typeset, G_typeset = primer_typeset_F_and_G(state, acc, gyro, dt)
    C_gamma = -dt * state.C @ so3.gamma(dt * (gyro - state.b_w))
    assert max_abs(F_num[imu.PHI, imu.BW], C_gamma) <= tol(state, acc)
    assert max_abs(G_num[imu.PHI, imu.NW], C_gamma) <= tol(state, acc)
    # the typeset block is off by dt |C - C^T| Gamma ~ dt (>= 0.5 dt / |Gamma^-1|), not round-off
    assert max_abs(F_typeset[imu.PHI, imu.BW], F_num[imu.PHI, imu.BW]) > 0.3 * dt
    assert max_abs(G_typeset[imu.PHI, imu.NW], G_num[imu.PHI, imu.NW]) > 0.3 * dt
    # ... and it is the only block where the typeset matrices and the module disagree
    _, F, G = imu.propagate(state, acc, gyro, dt)
    F_typeset[imu.PHI, imu.BW] = F[imu.PHI, imu.BW]
    G_typeset[imu.PHI, imu.NW] = G[imu.PHI, imu.NW]
    assert max_abs(F, F_typeset) <= 4 * EPS * max(1.0, np.abs(F).max())
    assert max_abs(G, G_typeset) <= 4 * EPS * max(1.0, np.abs(G).max())


# --------------------------------------------------------------------------- dt = 0, noise, integrate


@given(S.imu_states(), forces, rates)
def test_dt_zero_is_the_identity_step(state, acc, gyro):
    nxt, F, G = imu.propagate(state, acc, gyro, 0.0)
    for name in ("r", "v", "C", "b_f", "b_w"):
        assert np.array_equal(getattr(nxt, name), getattr(state, name)), name
    assert np.array_equal(F, np.eye(15))
    assert np.array_equal(G, np.zeros((15, 15)))
    assert np.array_equal(imu.ImuNoise().discrete_covariance(0.0), np.zeros((15, 15)))


@given(S.imu_states(), forces, rates, steps)
def test_the_euler_step_moves_the_state_by_dt_times_its_rate(state, acc, gyro, dt):
    """``state_derivative`` is the one formula of the state's rate ``(C v, C^T g + f - w x v, C w,
    0, 0)`` (the time-offset Jacobians and the misfit patterns use it): the Euler step is linear
    in ``dt`` in the error-state chart, so ``propagate(x, ..., dt) [-] x = dt xdot`` to round-off,
    the attitude's ``log(exp(dt C w))`` included (``|dt w| < pi`` here)."""
    step = imu.boxminus(imu.propagate(state, acc, gyro, dt, jacobians=False)[0], state)
    xdot = imu.state_derivative(state, acc, gyro)
    assert max_abs(step, dt * xdot) < tol(state, acc) * dt


@given(S.imu_states(), forces, rates, steps)
def test_propagate_with_zero_noise_is_propagate(state, acc, gyro, dt):
    a, _, _ = imu.propagate(state, acc, gyro, dt)
    b = imu.propagate_with_noise(state, acc, gyro, dt, np.zeros(15))
    c, F, G = imu.propagate(state, acc, gyro, dt, jacobians=False)
    assert F is None and G is None
    for name in ("r", "v", "C", "b_f", "b_w"):
        assert np.array_equal(getattr(a, name), getattr(b, name)), name
        assert np.array_equal(getattr(a, name), getattr(c, name)), name


def _assert_integrate_matches_loop(state, acc, gyro, dt):
    n = len(dt)
    states = imu.integrate(state, acc, gyro, dt)
    assert len(states) == n + 1 and states.C.shape == (n + 1, 3, 3)
    for name in ("r", "v", "C", "b_f", "b_w"):
        assert np.array_equal(getattr(states[0], name), getattr(state, name)), name
    # integrate evaluates the same recursion by prefix products (recursive doubling), so it may
    # differ from the loop by round-off: a few EPS per doubling level, relative to the quantity.
    bound = 16 * EPS * (1 + math.log2(n + 1))
    x = state
    for k in range(n):
        x, _, _ = imu.propagate(x, acc[k], gyro[k], dt[k], jacobians=False)
        for name in ("r", "v", "C"):
            ref = getattr(x, name)
            err = max_abs(getattr(states[k + 1], name), ref)
            assert err <= bound * max(1.0, np.abs(ref).max()), (k, name, err)
        # the biases are held constant, exactly
        assert np.array_equal(states.b_f[k + 1], state.b_f) and np.array_equal(states.b_w[k + 1], state.b_w)


@given(S.imu_states(), st.integers(0, 2**32 - 1), st.integers(1, 40))
def test_integrate_equals_repeated_propagate(state, seed, n):
    rng = np.random.default_rng(seed)
    acc, gyro = rng.normal(size=(n, 3)) * 5, rng.normal(size=(n, 3)) * 3
    _assert_integrate_matches_loop(state, acc, gyro, rng.uniform(1e-3, 0.02, size=n))


def test_integrate_equals_repeated_propagate_over_a_long_run():
    rng = np.random.default_rng(7)
    n = 2000  # 20 s at 100 Hz
    state = imu.ImuState(rng.normal(size=3) * 100, rng.normal(size=3) * 10, so3.exp(rng.normal(size=3)),
                         rng.normal(size=3) * 0.5, rng.normal(size=3) * 0.2)
    _assert_integrate_matches_loop(state, rng.normal(size=(n, 3)) * 5, rng.normal(size=(n, 3)) * 3,
                                   np.full(n, 0.01))


def test_integrate_of_no_samples_is_the_initial_state():
    state = imu.ImuState.identity()
    states = imu.integrate(state, np.zeros((0, 3)), np.zeros((0, 3)), np.zeros(0))
    assert len(states) == 1 and np.array_equal(states.C[0], np.eye(3))


# --------------------------------------------------------------------------- physics sanity


@given(S.rotations(), S.vectors(100.0), S.vectors(0.5), S.vectors(0.2))
def test_an_imu_at_rest_stays_at_rest(C, r, b_f, b_w):
    # at rest the accelerometer reads -C^T g + b_f (specific force) and the gyro b_w
    state = imu.ImuState(r, np.zeros(3), C, b_f, b_w)
    n = 200
    acc = np.tile(-C.T @ G_WORLD + b_f, (n, 1))
    gyro = np.tile(b_w, (n, 1))
    end = imu.integrate(state, acc, gyro, np.full(n, 0.01))[-1]
    assert max_abs(end.r, r) <= 1e-12 * max(1.0, np.abs(r).max())
    assert max_abs(end.v, 0.0) <= 1e-12  # each step adds round-off of C^T g - C^T g, ~1e-15
    assert np.array_equal(end.C, C)  # w = gyro - b_w = 0 exactly, exp(0) = I exactly


@given(S.rotations(), S.vectors(3.0), st.floats(1e-3, 0.02), st.integers(1, 200))
def test_constant_rate_composes_to_one_rotation(C, w, dt, n):
    state = imu.ImuState(np.zeros(3), np.zeros(3), C, np.zeros(3), np.zeros(3))
    end = imu.integrate(state, np.zeros((n, 3)), np.tile(w, (n, 1)), np.full(n, dt))[-1]
    # C exp(dt w)^n = C exp(n dt w) (eq. 12); round-off grows like n EPS
    assert max_abs(end.C, C @ so3.exp(n * dt * w)) <= 4 * n * EPS + 16 * EPS


@given(S.rotations(), S.vectors(10.0), st.floats(1e-3, 0.02), st.integers(1, 200))
def test_free_fall_is_the_euler_forward_recursion(C, v0, dt, n):
    # zero specific force, no rotation: the world velocity gains dt g per step and the position
    # uses the velocity BEFORE the step (eq. 54): r_n = r_0 + n dt v_0 + dt^2 g n (n - 1) / 2.
    state = imu.ImuState(np.zeros(3), v0, C, np.zeros(3), np.zeros(3))
    end = imu.integrate(state, np.zeros((n, 3)), np.zeros((n, 3)), np.full(n, dt))[-1]
    world_v = end.world_velocity()
    assert max_abs(world_v, C @ v0 + n * dt * G_WORLD) <= 1e-13 * n * 20
    expected_r = n * dt * (C @ v0) + dt * dt * G_WORLD * n * (n - 1) / 2
    assert max_abs(end.r, expected_r) <= 1e-13 * n * n * 20


# --------------------------------------------------------------------------- state, noise, batches


@given(S.imu_states(), st.lists(st.floats(-1, 1), min_size=15, max_size=15).map(np.array))
def test_state_boxplus_boxminus(state, dx):
    dx = dx * np.array([10] * 6 + [3.0 / math.sqrt(3)] * 3 + [1] * 6)  # attitude part below pi
    back = imu.boxminus(imu.boxplus(state, dx), state)
    assert max_abs(back[imu.PHI], dx[imu.PHI]) <= 32 * EPS
    other = np.r_[0:6, 9:15]
    assert max_abs(back[other], dx[other]) <= 4 * EPS * max(1.0, np.abs(state.r).max(), np.abs(dx).max())
    assert np.array_equal(imu.StateManifold.minus(state, state)[imu.PHI], np.zeros(3))


def test_state_container():
    x = imu.ImuState.identity((4,))
    assert x.shape == (4,) and len(x) == 4 and np.array_equal(x.C, np.broadcast_to(np.eye(3), (4, 3, 3)))
    y = imu.ImuState.stack([x[0], x[1].replace(v=np.array([1.0, 2, 3]))])
    assert y.shape == (2,) and np.array_equal(y.v[1], [1.0, 2, 3])
    C = so3.exp(np.array([0.0, 0.0, math.pi / 2]))
    z = imu.ImuState(np.zeros(3), np.array([1.0, 0, 0]), C, np.zeros(3), np.zeros(3))
    assert max_abs(z.world_velocity(), [0.0, 1.0, 0.0]) <= EPS  # body x points along world y


def test_noise_densities_and_discrete_covariance():
    noise = imu.ImuNoise(acc=2e-3, gyro=2e-4, acc_bias=3e-4, gyro_bias=2e-5, velocity=1e-2)
    expected = np.repeat([1e-2, 2e-3, 2e-4, 3e-4, 2e-5], 3) ** 2  # (n_v, n_f, n_w, n_bf, n_bw)
    assert np.array_equal(noise.densities(), expected)
    Q = noise.discrete_covariance(np.array([0.01, 0.0, 0.5]))
    assert Q.shape == (3, 15, 15)
    assert np.allclose(Q[0], np.diag(expected / 0.01), rtol=4 * EPS, atol=0)
    assert np.array_equal(Q[1], np.zeros((15, 15)))
    assert np.allclose(Q[2], np.diag(expected / 0.5), rtol=4 * EPS, atol=0)


@pytest.mark.parametrize("field, value", [("acc", -1.0), ("gyro", math.nan), ("gyro_bias", math.inf)])
def test_noise_rejects_invalid_densities(field, value):
    with pytest.raises(ValueError, match=f"ImuNoise.{field}"):
        imu.ImuNoise(**{field: value})


@pytest.mark.parametrize("seed", range(3))
def test_vectorised_propagate_equals_loops(seed):
    rng = np.random.default_rng(seed)
    n = 6
    C = so3.exp(S.sample_rotation_vectors(rng, n))
    states = imu.ImuState(rng.normal(size=(n, 3)) * 10, rng.normal(size=(n, 3)), C,
                          rng.normal(size=(n, 3)) * 0.3, rng.normal(size=(n, 3)) * 0.1)
    acc, gyro, dt = rng.normal(size=(n, 3)) * 5, rng.normal(size=(n, 3)) * 4, rng.uniform(1e-3, 0.05, n)
    nxt, F, G = imu.propagate(states, acc, gyro, dt)
    assert F.shape == (n, 15, 15) and G.shape == (n, 15, 15)
    for k in range(n):
        one, Fk, Gk = imu.propagate(states[k], acc[k], gyro[k], dt[k])
        for name in ("r", "v", "C", "b_f", "b_w"):
            assert max_abs(getattr(nxt[k], name), getattr(one, name)) <= 4 * EPS * 30, name
        assert max_abs(F[k], Fk) <= 4 * EPS * 30 and max_abs(G[k], Gk) <= 4 * EPS * 30


@pytest.mark.parametrize("seed", range(3))
def test_propagate_steps_equals_dense_covariance_recursion(seed):
    """The compiled prediction (F applied as an operator, never formed) over J rows of K samples
    (padding dt = 0 skipped) equals the dense ``S <- F S F^T + G Q_d G^T`` with this module's F
    and G, step by step."""
    rng = np.random.default_rng(seed)
    J, K = 4, 9
    noise = imu.ImuNoise(acc=2e-2, gyro=3e-3, acc_bias=4e-4, gyro_bias=5e-5, velocity=1e-3)
    C = so3.exp(S.sample_rotation_vectors(rng, J))
    states = imu.ImuState(rng.normal(size=(J, 3)) * 10, rng.normal(size=(J, 3)) * 3, C,
                          rng.normal(size=(J, 3)) * 0.3, rng.normal(size=(J, 3)) * 0.1)
    A = rng.normal(size=(J, 15, 15))
    cov = A @ np.swapaxes(A, 1, 2) * 1e-2
    acc, gyro = rng.normal(size=(J, K, 3)) * 5, rng.normal(size=(J, K, 3)) * 4
    dt = rng.uniform(1e-3, 0.05, (J, K))
    dt[1, 5:] = 0.0  # a shorter row, padded
    dt[2, 0] = 0.0
    out, P = imu.propagate_steps(states, cov, acc, gyro, dt, noise)
    for j in range(J):
        x, Pj = states[j], cov[j]
        for k in range(K):
            if dt[j, k] == 0:
                continue
            x, F, G = imu.propagate(x, acc[j, k], gyro[j, k], dt[j, k])
            Pj = F @ Pj @ F.T + G @ (noise.discrete_covariance(dt[j, k])) @ G.T
        np.testing.assert_allclose(P[j], Pj, rtol=1e-12, atol=1e-13 * np.abs(Pj).max())
        for name in ("r", "v", "C", "b_f", "b_w"):
            assert max_abs(getattr(out[j], name), getattr(x, name)) <= 1e-12 * max(1.0, np.abs(getattr(x, name)).max())
    one, P1 = imu.propagate_steps(states[0], cov[0], acc[0], gyro[0], dt[0], noise)
    assert one.shape == () and P1.shape == (15, 15) and max_abs(P1, P[0]) == 0.0
