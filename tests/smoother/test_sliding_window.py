"""The compiled sliding-window fixed-lag smoother (:mod:`smoother.sliding_window`): its linear
algebra against dense NumPy, its robust weights against GTSAM's, and its estimates against the
batch smoother where they must agree (a window longer than the run marginalises nothing)."""
from __future__ import annotations

import gtsam
import numpy as np
import pytest

import estimator_cases as cases
from smoother import sliding_window as sw
from smoother.batch import solve_batch
from smoother.graph import build_problem
from smoother.online import replay

DIM = sw.DIM


def _banded(rng, n: int, S: int) -> tuple[np.ndarray, np.ndarray]:
    """A random positive definite block-banded matrix (blocks of 15, bandwidth ``S``: each
    keyframe's factor reaches ``S`` keyframes back) as ``(Hb, dense)``."""
    H = np.eye(n * DIM)
    for k in range(n):
        lo = max(0, k - S) * DIM
        J = rng.normal(size=(DIM, (k + 1) * DIM - lo))
        H[lo:(k + 1) * DIM, lo:(k + 1) * DIM] += J.T @ J
    Hb = np.zeros((n, S + 1, DIM, DIM))
    for k in range(n):
        for s in range(min(k, S) + 1):
            Hb[k, s] = H[k * DIM:(k + 1) * DIM, (k - s) * DIM:(k - s + 1) * DIM]
    return Hb, H


@pytest.mark.parametrize("n, S", [(1, 1), (6, 1), (7, 2), (5, 4)])
def test_banded_cholesky_solve_and_covariances_equal_dense_numpy(n, S):
    rng = np.random.default_rng(n * 10 + S)
    Hb, H = _banded(rng, n, S)
    L = np.zeros_like(Hb)
    assert sw._factorise(Hb, L) == -1
    g = rng.normal(size=n * DIM)
    x = g[:, None].copy()
    sw._forward(L, x, 0)
    sw._backward(L, x, 0)
    np.testing.assert_allclose(x[:, 0], np.linalg.solve(H, g), rtol=1e-9, atol=1e-12)
    inverse = np.linalg.inv(H)
    for j in range(n):
        b = np.zeros((n * DIM, DIM))
        b[j * DIM:(j + 1) * DIM] = np.eye(DIM)
        sw._forward(L, b, j)
        sw._backward(L, b, j)
        np.testing.assert_allclose(b[j * DIM:(j + 1) * DIM], inverse[j * DIM:(j + 1) * DIM, j * DIM:(j + 1) * DIM],
                                   rtol=1e-8, atol=1e-12)


def test_an_indefinite_block_is_named():
    rng = np.random.default_rng(0)
    Hb, _ = _banded(rng, 4, 1)
    Hb[2, 0] -= 1e6 * np.eye(DIM)
    assert sw._factorise(Hb, np.zeros_like(Hb)) == 2


@pytest.mark.parametrize("nl", [1, 2])
def test_schur_complement_equals_dense_numpy(nl):
    rng = np.random.default_rng(nl)
    Hb, H = _banded(rng, 4, 1)
    g = rng.normal(size=len(H))
    Hs, gs, ok = sw._schur(Hb, g, nl)
    m = nl * DIM
    assert ok
    X = np.linalg.solve(H[:m, :m], np.concatenate([H[:m, m:], g[:m, None]], axis=1))
    np.testing.assert_allclose(Hs, H[m:, m:] - H[m:, :m] @ X[:, :-1], rtol=1e-9, atol=1e-9)
    np.testing.assert_allclose(gs, g[m:] - H[m:, :m] @ X[:, -1], rtol=1e-9, atol=1e-9)


def test_square_root_of_a_marginal_and_of_a_semidefinite_one():
    rng = np.random.default_rng(1)
    A = rng.normal(size=(20, DIM))
    g = rng.normal(size=DIM)
    for H in (A.T @ A, A[:, :10].T @ A[:, :10]):
        if H.shape != (DIM, DIM):
            H = np.pad(H, ((0, 5), (0, 5)))  # five directions carry no information
        gg = g if np.linalg.matrix_rank(H) == DIM else np.concatenate([g[:10], np.zeros(5)])
        R, e0 = sw._square_root(H, gg)
        np.testing.assert_allclose(R.T @ R, H, rtol=1e-9, atol=1e-9)
        np.testing.assert_allclose(R.T @ e0, gg, rtol=1e-9, atol=1e-9)


@pytest.mark.parametrize("name", sorted(sw.ROBUST_CODES))
def test_robust_weights_are_gtsams(name):
    estimators = {"huber": gtsam.noiseModel.mEstimator.Huber, "cauchy": gtsam.noiseModel.mEstimator.Cauchy,
                  "tukey": gtsam.noiseModel.mEstimator.Tukey}
    k = 2.5
    kernel = estimators[name].Create(k)
    for norm in (0.0, 0.3, 2.4, 2.5, 2.6, 7.0, 100.0):
        assert sw._robust_scale(sw.ROBUST_CODES[name], k, norm) ** 2 == pytest.approx(kernel.weight(norm), abs=1e-12)


def test_a_window_longer_than_the_run_reaches_the_batch_optimum(gentle):
    """Nothing is marginalised, one Gauss-Newton step per keyframe: at the end the window is the
    batch smoother's estimate (within 0.05 sigma) with its covariances (within 0.02 in correlation
    units at the newest keyframe, the only one solved at its final linearisation)."""
    data = cases.dataset(gentle)
    result = replay(data, 100.0, "sliding", covariances=True, progress=False)
    batch = solve_batch(build_problem(data))
    assert result.smoothed.t.tolist() == batch.trajectory.t.tolist()
    diff = cases.sigma_difference(result.smoothed.states, batch.trajectory.states, batch.trajectory.cov)
    assert diff.max() < 0.05, diff.max()
    a, b = result.smoothed.cov[-1], batch.trajectory.cov[-1]
    scale = np.sqrt(np.diag(b))
    assert (np.abs(a - b) / np.outer(scale, scale)).max() < 0.02


def test_an_imu_gap_longer_than_the_lag_keeps_its_imu_factor(gentle):
    """The newest keyframe stays until the next is added: keyframes 1 s apart with a 0.3-s lag
    are tied by their IMU factors, no weak prior; with nothing measured the estimates are the dead
    reckoning from the initial state, as GTSAM's incremental smoother's (equal within 1e-6 m)."""
    from smoother.online import OnlineSmoother

    data = cases.dataset(gentle)
    recovered, positions = {}, {}
    for kind in ("sliding", "incremental"):
        online = OnlineSmoother(data.initial, data.initial_cov, data.noise, gravity=data.gravity, lag_s=0.3,
                                kind=kind)
        online.keyframe_at(data.imu.t[0] + np.array([1.0, 2.0]))
        online.add_imu(data.imu.t, data.imu.acc, data.imu.gyro)
        online.finish()
        recovered[kind] = online.recovered
        positions[kind] = np.stack([e.state.r for e in online.smoothed()])
    assert recovered["sliding"] == []
    assert len(positions["sliding"]) == 4  # the start, 1 s, 2 s and the end of the data
    np.testing.assert_allclose(positions["sliding"], positions["incremental"], atol=1e-6)
