"""The compiled sliding-window fixed-lag smoother (:mod:`smoother.fixed_lag.sliding.window`): its linear
algebra against dense NumPy, its robust weights against GTSAM's, the factor it keeps across updates
against one made from scratch, its relinearisation, its step limit and its recovery. What every
kind of window does (against the EKF, the batch smoother, an IMU gap) is in
``tests/smoother/fixed_lag/test_window_contract.py``."""
from __future__ import annotations

import estimator_cases as cases
import gtsam
import numpy as np
import pytest
from banded_cases import band, dense, random_banded

from datasets.simulate import simulate
from factors.imu import ImuNoise
from smoother.fixed_lag.sliding import banded, kernels, normal_equations
from smoother.fixed_lag.sliding import window as sw
from smoother.model.timeline import EVERY_MEASUREMENT
from smoother.online.replay import replay

DIM = sw.DIM


def _random(rng, n: int, S: int) -> tuple[np.ndarray, np.ndarray]:
    """A random positive definite block-banded matrix (:func:`banded_cases.random_banded`) as
    ``(Hb, dense)``."""
    H = random_banded(rng, n, S)
    return band(H, S), H


def _ring(Hb: np.ndarray, first: int, cap: int) -> np.ndarray:
    """The keyframe blocks ``Hb`` (keyframes ``first ..``) in ring slots ``k % cap``."""
    out = np.zeros((cap,) + Hb.shape[1:])
    for b in range(len(Hb)):
        out[(first + b) % cap] = Hb[b]
    return out


def _solve(L, g, first, n, cap, S):
    """``H^-1 g`` through the ring factor ``L`` (window ``first .. first + n - 1``)."""
    y = _ring(-g.reshape(n, DIM, 1), first, cap)
    banded.forward_solve(L, y, first, first, first, first + n - 1, cap, S)
    banded.backward_solve(L, y, first, first + n - 1, cap, S)
    return -np.concatenate([y[(first + b) % cap, :, 0] for b in range(n)])


@pytest.mark.parametrize("n, S", [(1, 1), (6, 1), (7, 2), (5, 4)])
def test_banded_cholesky_solve_and_covariances_equal_dense_numpy(n, S):
    """Window keyframes 5 .. 5 + n - 1 in a ring of 8 slots (it wraps round)."""
    rng = np.random.default_rng(n * 10 + S)
    Hb, H = _random(rng, n, S)
    first, cap = 5, 8
    L = np.zeros((cap, S + 1, DIM, DIM))
    assert banded.factorise(Hb, L, first, first, first + n - 1, cap, S) == -1
    g = rng.normal(size=n * DIM)
    np.testing.assert_allclose(_solve(L, g, first, n, cap, S), np.linalg.solve(H, g), rtol=1e-9, atol=1e-12)
    inverse = np.linalg.inv(H)
    for j in range(n):
        b = np.zeros((cap, DIM, DIM))
        b[(first + j) % cap] = np.eye(DIM)
        banded.forward_solve(L, b, first, first + j, first + j, first + n - 1, cap, S)
        banded.backward_solve(L, b, first + j, first + n - 1, cap, S)
        np.testing.assert_allclose(b[(first + j) % cap], inverse[j * DIM:(j + 1) * DIM, j * DIM:(j + 1) * DIM],
                                   rtol=1e-8, atol=1e-12)


@pytest.mark.parametrize("S", [1, 2])
def test_rows_factorised_again_from_a_keyframe_on_equal_a_whole_factorisation(S):
    """Changing the rows of ``H`` from keyframe ``b0`` on and factorising only those rows again
    gives the factor of the new matrix, and the forward solution kept for the rows before ``b0``
    stays valid."""
    rng = np.random.default_rng(S)
    n, first, cap, b0 = 7, 3, 8, 4
    Hb, H = _random(rng, n, S)
    L = np.zeros((cap, S + 1, DIM, DIM))
    assert banded.factorise(Hb, L, first, first, first + n - 1, cap, S) == -1
    g = rng.normal(size=n * DIM)
    y = _ring(-g.reshape(n, DIM, 1), first, cap)
    banded.forward_solve(L, y, first, first, first, first + n - 1, cap, S)
    J = rng.normal(size=(DIM, DIM * (S + 1)))  # a factor on keyframes b0 .. b0 + S (within the band)
    H2 = H.copy()
    H2[b0 * DIM:(b0 + S + 1) * DIM, b0 * DIM:(b0 + S + 1) * DIM] += J.T @ J
    Hb2 = Hb.copy()
    for k in range(b0, n):
        for s in range(min(k, S) + 1):
            Hb2[k, s] = H2[k * DIM:(k + 1) * DIM, (k - s) * DIM:(k - s + 1) * DIM]
    g2 = g.copy()
    g2[b0 * DIM:] += rng.normal(size=(n - b0) * DIM)
    assert banded.factorise(Hb2[b0:], L, first, first + b0, first + n - 1, cap, S) == -1
    for k in range(b0, n):
        y[(first + k) % cap, :, 0] = -g2[k * DIM:(k + 1) * DIM]
    banded.forward_solve(L, y, first, first + b0, first, first + n - 1, cap, S)
    banded.backward_solve(L, y, first, first + n - 1, cap, S)
    x = -np.concatenate([y[(first + b) % cap, :, 0] for b in range(n)])
    np.testing.assert_allclose(x, np.linalg.solve(H2, g2), rtol=1e-8, atol=1e-11)


def test_the_rows_after_marginalised_keyframes_factor_their_schur_complement():
    """Eliminating the oldest keyframes first, the factor's rows after them (and their forward
    solution) are those of the Schur complement: marginalising needs no new factorisation."""
    rng = np.random.default_rng(3)
    n, S, nl, cap = 6, 2, 2, 8
    Hb, H = _random(rng, n, S)
    g = rng.normal(size=n * DIM)
    L = np.zeros((cap, S + 1, DIM, DIM))
    assert banded.factorise(Hb, L, 0, 0, n - 1, cap, S) == -1
    m = nl * DIM
    Hs = H[m:, m:] - H[m:, :m] @ np.linalg.solve(H[:m, :m], H[:m, m:])
    gs = g[m:] - H[m:, :m] @ np.linalg.solve(H[:m, :m], g[:m])
    y = _ring(-g.reshape(n, DIM, 1), 0, cap)
    banded.forward_solve(L, y, 0, 0, 0, n - 1, cap, S)
    banded.backward_solve(L, y, nl, n - 1, cap, S)  # the window is now nl .. n - 1
    x = -np.concatenate([y[b % cap, :, 0] for b in range(nl, n)])
    np.testing.assert_allclose(x, np.linalg.solve(Hs, gs), rtol=1e-8, atol=1e-11)
    np.testing.assert_allclose(_solve(L, gs, nl, n - nl, cap, S), np.linalg.solve(Hs, gs), rtol=1e-8, atol=1e-11)


def test_an_indefinite_block_is_named():
    rng = np.random.default_rng(0)
    Hb, _ = _random(rng, 4, 1)
    Hb[2, 0] -= 1e6 * np.eye(DIM)
    assert banded.factorise(Hb, np.zeros((8, 2, DIM, DIM)), 0, 0, 3, 8, 1) == 2


@pytest.mark.parametrize("nl", [1, 2])
def test_schur_complement_equals_dense_numpy(nl):
    rng = np.random.default_rng(nl)
    Hb, H = _random(rng, 4, 1)
    g = rng.normal(size=len(H))
    Hs, gs, ok = banded.schur(Hb, g, *banded.no_border(4), nl)
    m = nl * DIM
    assert ok
    X = np.linalg.solve(H[:m, :m], np.concatenate([H[:m, m:], g[:m, None]], axis=1))
    np.testing.assert_allclose(Hs, H[m:, m:] - H[m:, :m] @ X[:, :-1], rtol=1e-9, atol=1e-9)
    np.testing.assert_allclose(gs, g[m:] - H[m:, :m] @ X[:, -1], rtol=1e-9, atol=1e-9)


@pytest.mark.parametrize("nl", [1, 2])
def test_the_marginal_prior_is_the_square_root_of_the_schur_complement(nl):
    rng = np.random.default_rng(nl)
    Hb, H = _random(rng, 4, 2)
    g = rng.normal(size=len(H))
    status, touched, R, e0, _, _ = banded.marginal_prior(Hb, g, *banded.no_border(4), nl)
    m = nl * DIM
    Hs = H[m:, m:] - H[m:, :m] @ np.linalg.solve(H[:m, :m], H[:m, m:])
    gs = g[m:] - H[m:, :m] @ np.linalg.solve(H[:m, :m], g[:m])
    informed = [b for b in range(4 - nl) if np.any(Hs[b * DIM:(b + 1) * DIM] != 0.0)]
    keep = (touched[:, None] * DIM + np.arange(DIM)).ravel()
    assert status == 0 and touched.tolist() == informed and np.allclose(np.triu(R), R)
    np.testing.assert_allclose(R.T @ R, Hs[np.ix_(keep, keep)], rtol=1e-9, atol=1e-9)
    np.testing.assert_allclose(R.T @ e0, gs[keep], rtol=1e-9, atol=1e-9)


@pytest.mark.parametrize("nl", [1, 2])
def test_the_bordered_marginal_prior_is_the_square_root_of_the_bordered_schur_complement(nl):
    """With three calibration coordinates coupled to every keyframe: the prior is on the informed
    keyframes and the calibrations, the Schur complement of the dense bordered system, and its
    own share of the calibrations' ``(D, g_c)`` is that complement's calibration block."""
    rng = np.random.default_rng(10 + nl)
    _, A = _random(rng, 4, 2)
    nc, N = 3, len(A)
    H = np.zeros((N + nc, N + nc))
    H[:N, :N] = A
    for k in range(4):  # a calibrated factor on each keyframe
        J = rng.normal(size=(5, DIM + nc))
        at = np.r_[k * DIM:(k + 1) * DIM, N:N + nc]
        H[np.ix_(at, at)] += J.T @ J
    Hb = np.zeros((4, 3, DIM, DIM))
    for k in range(4):
        for s_ in range(min(k, 2) + 1):
            Hb[k, s_] = H[k * DIM:(k + 1) * DIM, (k - s_) * DIM:(k - s_ + 1) * DIM]
    g = rng.normal(size=N + nc)
    B = H[:N, N:].reshape(4, DIM, nc).copy()
    status, touched, R, e0, own_D, own_g = banded.marginal_prior(Hb, g[:N], B, H[N:, N:].copy(), g[N:], nl)
    m = nl * DIM
    Hs = H[m:, m:] - H[m:, :m] @ np.linalg.solve(H[:m, :m], H[:m, m:])
    gs = g[m:] - H[m:, :m] @ np.linalg.solve(H[:m, :m], g[:m])
    keep = np.concatenate([(touched[:, None] * DIM + np.arange(DIM)).ravel(), (4 - nl) * DIM + np.arange(nc)])
    assert status == 0 and touched.tolist() == list(range(4 - nl)) and np.allclose(np.triu(R), R)
    np.testing.assert_allclose(R.T @ R, Hs[np.ix_(keep, keep)], rtol=1e-9, atol=1e-8)
    np.testing.assert_allclose(R.T @ e0, gs[keep], rtol=1e-9, atol=1e-8)
    np.testing.assert_allclose(own_D, R[:, -nc:].T @ R[:, -nc:], rtol=1e-9, atol=1e-8)
    np.testing.assert_allclose(own_g, R[:, -nc:].T @ e0, rtol=1e-9, atol=1e-8)


def test_a_semidefinite_marginal_keeps_only_the_informed_directions():
    """The leaving keyframe informs ten of the next keyframe's fifteen directions, which nothing
    else informs: the prior's square root spans those ten and reproduces the Schur complement;
    a leaving block that is not positive definite is status 1."""
    rng = np.random.default_rng(1)
    A = rng.normal(size=(40, 2 * DIM))
    A[:, DIM + 10:] = 0.0
    H = A.T @ A + np.diag(np.r_[np.ones(DIM), np.zeros(DIM)])  # the leaving block made definite
    Hb = np.zeros((2, 2, DIM, DIM))
    Hb[0, 0], Hb[1, 0], Hb[1, 1] = H[:DIM, :DIM], H[DIM:, DIM:], H[DIM:, :DIM]
    g = A.T @ rng.normal(size=40)
    status, touched, Hs, gs, _, _ = banded.marginal_prior(Hb, g, *banded.no_border(2), 1)
    assert status == 2 and touched.tolist() == [0]
    R, e0 = banded.semidefinite_square_root(Hs, gs)
    np.testing.assert_allclose(R.T @ R, Hs, rtol=1e-8, atol=1e-8)
    np.testing.assert_allclose(R.T @ e0, gs, rtol=1e-8, atol=1e-8)
    assert np.count_nonzero(np.abs(R).sum(axis=1) > 1e-9) == 10
    Hb[0, 0] = -np.eye(DIM)
    assert banded.marginal_prior(Hb, g, *banded.no_border(2), 1)[0] == 1


def test_the_semidefinite_square_root_keeps_weak_directions_beside_strong_ones():
    """Information of 1e14 on one component (a short IMU interval's position) and 1e2 on another
    (a bias) with exact null directions beside them: both informed directions are kept, only the
    null ones dropped."""
    rng = np.random.default_rng(4)
    Q = np.linalg.qr(rng.normal(size=(4, 4)))[0]
    H = np.zeros((DIM, DIM))
    H[:4, :4] = Q @ np.diag([1e14, 1e2, 0.0, 0.0]) @ Q.T
    H[10, 10] = 1e2
    g = H @ rng.normal(size=DIM)
    R, e0 = banded.semidefinite_square_root(H, g)
    assert np.count_nonzero(np.abs(R).sum(axis=1) > 0) == 3
    np.testing.assert_allclose(R.T @ R, H, rtol=1e-9, atol=1e-9 * np.abs(H).max())
    np.testing.assert_allclose(R.T @ e0, g, rtol=1e-7, atol=1e-7 * np.abs(g).max())


@pytest.mark.parametrize("name", sorted(normal_equations.ROBUST_CODES))
def test_robust_weights_are_gtsams(name):
    estimators = {"huber": gtsam.noiseModel.mEstimator.Huber, "cauchy": gtsam.noiseModel.mEstimator.Cauchy,
                  "tukey": gtsam.noiseModel.mEstimator.Tukey}
    k = 2.5
    kernel = estimators[name].Create(k)
    for norm in (0.0, 0.3, 2.4, 2.5, 2.6, 7.0, 100.0):
        assert (normal_equations.robust_scale(normal_equations.ROBUST_CODES[name], k, norm) ** 2
                == pytest.approx(kernel.weight(norm), abs=1e-12))


def test_the_factor_kept_across_updates_is_that_of_the_whole_window(gentle):
    """After each update -- rows factorised again only from the oldest change on, keyframes
    marginalised without a new factorisation -- the window's factor and offsets equal a
    factorisation of the whole window's normal equations at the linearisation points, made from
    scratch (factor to 1e-9 relative, offsets to 1e-6 of the largest). An update that ends by
    linearising keyframes again leaves the rows from theirs on stale (the next update factorises
    them again): the rows before must still agree."""
    data = cases.dataset(gentle)
    checked = {"whole": 0, "before the stale rows": 0}
    solve = sw.SlidingWindow._solve

    def solve_and_check(window, t):
        solve(window, t)
        n, S, cap = window.newest - window.first + 1, window._S, window._cap
        Hb, g, _ = window._normal_equations(window.first, window.newest + 1, n, S)
        L = np.zeros_like(window._L)
        assert banded.factorise(Hb, L, window.first, window.first, window.newest, cap, S) == -1
        valid = min(window._stale, window.newest + 1) - window.first  # the rows still up to date
        slots = np.arange(window.first, window.first + valid) % cap
        for s in range(min(S, valid - 1) + 1):
            rows = slots[s:]  # the blocks (k, k - s) inside the window
            np.testing.assert_allclose(window._L[rows, s], L[rows, s], rtol=1e-9, atol=1e-9 * np.abs(L[rows, s]).max())
        if valid == n:
            delta = np.linalg.solve(dense(Hb), -g)
            slots = np.arange(window.first, window.newest + 1) % cap
            # (a dense solve of H, conditioned as it is, against the banded one: 1e-6 of the largest
            # offset; a stale row or a wrong prior is wrong at the offsets' own size)
            np.testing.assert_allclose(window._dx[slots, :, 0].ravel(), delta, rtol=1e-6,
                                       atol=1e-6 * np.abs(delta).max())
            checked["whole"] += 1
        elif valid > 0:
            checked["before the stale rows"] += 1

    sw.SlidingWindow._solve = solve_and_check
    try:
        replay(data, 0.5, "sliding", covariances=False, progress=False)
    finally:
        sw.SlidingWindow._solve = solve
    assert checked["whole"] > 10 and checked["before the stale rows"] > 0, checked


def test_relinearising_less_often_stays_close_to_relinearising_everything(gentle, monkeypatch):
    """The default thresholds against relinearising every keyframe at every update (threshold 0):
    within 0.02 sigma (measured 0.006), relinearising fewer keyframes (measured 109 against 222 on
    these 4 s, which begin far from the truth; a fortieth on the benchmark's steady run); a
    negative threshold is refused."""
    data = cases.dataset(gentle)
    windows = []
    init = sw.SlidingWindow.__init__

    def recorded(window, *args, **kwargs):
        init(window, *args, **kwargs)
        windows.append(window)

    monkeypatch.setattr(sw.SlidingWindow, "__init__", recorded)
    default = replay(data, 0.5, "sliding", covariances=True, progress=False).smoothed
    monkeypatch.setattr(sw, "RELINEARISATION_THRESHOLD", np.zeros(DIM))
    every = replay(data, 0.5, "sliding", covariances=True, progress=False).smoothed
    diff = cases.sigma_difference(default.states, every.states, every.cov)
    assert diff.max() < 0.02, diff.max()
    relinearised = [sum(w.relinearised) for w in windows]
    assert relinearised[0] < 0.75 * relinearised[1], relinearised
    with pytest.raises(ValueError, match="relinearisation_threshold"):
        sw.SlidingWindow(0.5, relinearisation_threshold=-1.0)


def test_an_update_that_assembles_rows_anyway_linearises_their_keyframes_again_early(monkeypatch):
    """Keyframes (and, on a whole-window assembly, calibrations) half-way to their threshold are
    linearised again where an update assembles their rows anyway: over 15 s of wheels, GNSS and
    an AHRS, with and without the wheels' mounting and scale to estimate, fewer updates assemble
    more than three rows (measured 33 against 42 and 46 against 60) -- never deeper ones: every
    update that linearises early assembles from the row it would have assembled from."""
    from datasets.simulated_sensors import SensorSpec
    from factors.calibration import CalibrationPrior

    data = simulate("gentle", duration=15.0, seed=1, imu_rate=100.0, pose_rate=0, sensors=(
        SensorSpec("wheels", "velocity", 10.0, 0.05), SensorSpec("gnss", "gnss", 5.0, 0.2),
        SensorSpec("ahrs", "orientation", 10.0, 0.02)))
    calibrating = data.with_sensor("wheels", calibrate=CalibrationPrior(("rotation", "scale")))
    assembled = []
    normal_equations, early = sw.SlidingWindow._normal_equations, sw.SlidingWindow._relinearise_early

    def recorded(window, lo, cut, n, S, solving=True):
        if solving:
            assembled.append(n)
        return normal_equations(window, lo, cut, n, S, solving)

    def recorded_early(window, start, reach):
        early(window, start, reach)
        assert max(window._stale, window.first) >= start  # no row before start made stale

    monkeypatch.setattr(sw.SlidingWindow, "_normal_equations", recorded)
    monkeypatch.setattr(sw.SlidingWindow, "_relinearise_early", recorded_early)
    deep = {}
    for name, d in (("plain", data), ("calibrating", calibrating)):
        for fraction in (1.0, sw.EARLY_RELINEARISATION):  # 1: what exceeds the threshold has moved already
            monkeypatch.setattr(sw, "EARLY_RELINEARISATION", fraction)
            assembled.clear()
            replay(d, 2.0, "sliding", covariances=False, progress=False)
            deep[name, fraction] = sum(n > 3 for n in assembled[-150:])
    for name in ("plain", "calibrating"):
        assert deep[name, 0.5] < 0.85 * deep[name, 1.0], deep


def test_a_large_correction_is_taken_in_steps_no_longer_than_the_attitude_limit(gentle):
    """The start's heading 1 rad off (with a prior that allows it): the first poses call for a turn
    of about 1 rad, which the window takes in steps of at most ``MAX_ATTITUDE_STEP`` per update
    along the Gauss-Newton direction, and it still ends on the truth (within 3 sigma)."""
    from dataclasses import replace

    from factors import imu, so3

    data = cases.dataset(gentle)
    initial = replace(data.initial, C=so3.exp(np.array([0.0, 0.0, 1.0])) @ data.initial.C)
    cov = data.initial_cov.copy()
    cov[8, 8] = 2.0 ** 2
    windows, headings = [], []
    init, solve = sw.SlidingWindow.__init__, sw.SlidingWindow._solve

    def recorded(window, *args, **kwargs):
        init(window, *args, **kwargs)
        windows.append(window)

    def solve_and_record(window, t):
        before = [window._xC[k % window._cap].copy() for k in range(window.first, window.newest)]
        solve(window, t)
        after = [window._xC[k % window._cap] for k in range(window.first, window.newest)]
        headings.append(max((np.linalg.norm(so3.boxminus(b, a)) for a, b in zip(after, before)), default=0.0))

    sw.SlidingWindow.__init__, sw.SlidingWindow._solve = recorded, solve_and_record
    try:
        result = replay(replace(data, initial=initial, initial_cov=cov), 0.5, "sliding", covariances=True,
                        progress=False)
    finally:
        sw.SlidingWindow.__init__, sw.SlidingWindow._solve = init, solve
    assert windows[0].shortened > 0
    assert max(headings) <= sw.MAX_ATTITUDE_STEP + 1e-9, max(headings)
    last = result.smoothed
    error = imu.boxminus(last.states[-1], data.truth.states[np.searchsorted(data.truth.t, last.t[-1])])
    assert np.all(np.abs(error) < 3 * np.sqrt(np.diag(last.cov[-1]))), error


def test_a_measurement_on_older_keyframes_only_refactorises_from_them(gentle, monkeypatch):
    """A measurement that reads older window keyframes and not the new one (here every fifth
    pose, put on the keyframe three back) changes rows of ``H`` before the new keyframe's: the
    update factorises from there, and the offsets equal a dense solve of the whole window's
    normal equations (within 1e-6 sigma; factorising only from the new keyframe's rows: 12 sigma off)."""
    add, solve = sw.SlidingWindow.add_keyframe, sw.SlidingWindow._solve
    worst = []

    def earlier(window, t, guess, pre=None, measurements=(), prior=None):
        k = window.newest + 1
        if k >= 6 and k % 5 == 0:
            measurements = [(spec, m, [k - 3] if len(at) == 1 else at, robust, attached)
                            for spec, m, at, robust, attached in measurements]
        return add(window, t, guess, pre, measurements, prior)

    def checked(window, t):
        solve(window, t)
        if window._stale <= window.newest:  # relinearised at the end of the update: rows stale until the next
            return
        Hb, g, _ = window._normal_equations(window.first, window.newest + 1, window.newest - window.first + 1,
                                         window._S)
        H = dense(Hb)
        delta = np.linalg.solve(H, -g)
        slots = np.arange(window.first, window.newest + 1) % window._cap
        worst.append(np.max(np.abs(window._dx[slots, :, 0].ravel() - delta) / np.sqrt(np.diag(np.linalg.inv(H)))))

    monkeypatch.setattr(sw.SlidingWindow, "add_keyframe", earlier)
    monkeypatch.setattr(sw.SlidingWindow, "_solve", checked)
    monkeypatch.setattr(sw, "RELINEARISATION_THRESHOLD", np.full(DIM, np.inf))  # every update comparable
    replay(cases.dataset(gentle), 1.0, "sliding", covariances=False, progress=False)
    assert len(worst) > 30 and max(worst) < 1e-6, (len(worst), max(worst))


def test_a_refused_keyframe_leaves_the_window_as_it_was(gentle):
    """A measurement whose covariance is not positive definite, or whose robust kernel is unknown,
    is refused before anything changes: no keyframe marginalised, no measurement appended."""
    from datasets.types import Sensor
    from smoother.model.problem import measurement_spec
    from smoother.online.smoother import OnlineSmoother

    data = cases.dataset(gentle)
    online = OnlineSmoother.for_dataset(data, lag_s=0.3)
    online.add_imu(data.imu.t[:150], data.imu.acc[:150], data.imu.gyro[:150])
    window = online._window
    before = (window.first, window.newest, window._m, len(window._priors), window.skipped)
    # a copy of the first pose (a slice would be a view: the case's data are shared by the session)
    spec = measurement_spec(Sensor("pose", "pose", data.sensor("pose").data.subset([0])))
    state = window.newest_state
    t = window.time(window.newest) + 1.0  # the older keyframes would leave
    spec.cov[0] = -np.eye(6)
    with pytest.raises(ValueError, match="not positive definite"):
        window.add_keyframe(t, state, None, [(spec, 0, [window.newest + 1], None, None)])
    spec.cov[0] = np.eye(6)
    with pytest.raises(ValueError, match="robust kernel 'hubber'"):
        window.add_keyframe(t, state, None, [(spec, 0, [window.newest + 1], ("hubber", None), None)])
    assert (window.first, window.newest, window._m, len(window._priors), window.skipped) == before


@pytest.mark.parametrize("gap", [5e-3, 4e-6])
def test_keyframes_within_one_imu_sample_and_weak_fixes_keep_the_window_positive_definite(gap):
    """A slow robot: a 30 Hz IMU, two wheel-speed streams stamped ``gap`` apart (keyframes inside
    one IMU sample), GNSS of 5 m, a start known to 5 m. Without the position-kinematics noise
    (``ImuNoise.velocity = 0``: the Euler step's position is then exact, its information ~1e14
    beside the fixes' 0.04) the window's information loses definiteness to round-off within a
    second; with the default density it stays positive definite over the whole run, and ends
    within the accuracy the fixes allow."""
    from dataclasses import replace as copy

    from datasets.simulated_sensors import SensorSpec
    from datasets.types import Sensor, VelocityMeasurements
    from smoother.fixed_lag.contract import FixedLagFailed

    def run(velocity_density):
        noise = ImuNoise(acc=1.8e-2, gyro=3.7e-3, acc_bias=3e-3, gyro_bias=5e-4, velocity=velocity_density)
        data = simulate("static", duration=12, seed=1, imu_rate=30, noise=noise, pose_rate=None,
                        initial_sigma=(5.0, 0.1, 0.05), sensors=[SensorSpec("gnss", "gnss", 0.6, 5.0)])
        rng = np.random.default_rng(0)
        wheels = []
        for name, offset in (("w1", 0.003), ("w2", 0.003 + gap)):
            t = np.arange(0.0, 11.5, 0.1) + offset
            wheels.append(Sensor(name, "velocity", VelocityMeasurements(
                t, rng.normal(0, 0.05, (len(t), 3)), np.zeros((len(t), 3)),
                np.tile(np.eye(3) * 0.05**2, (len(t), 1, 1)))))
        data = copy(data, sensors=tuple(data.sensors) + tuple(wheels))
        return data, replay(data, lag_s=20.0, keyframe_rate=EVERY_MEASUREMENT)

    with pytest.raises(FixedLagFailed, match="not positive definite"):
        run(0.0)
    data, result = run(ImuNoise().velocity)
    error = np.linalg.norm(result.smoothed.position - data.truth.position[0], axis=1)
    assert result.recovered == [] and error.max() < 10.0


def test_a_keyframe_whose_information_fails_gets_a_weak_prior_and_the_update_goes_on(monkeypatch):
    """The factorisation refusing keyframe 7 once (as a numerically singular window would): the
    window adds a weak prior on it, records it in ``recovered``, factorises again and carries on;
    the run ends as accurate as without the refusal (the weak prior is 1e2 m, 1e1 m/s, pi rad)."""
    data = simulate("gentle", duration=4, seed=2)
    clean = replay(data, lag_s=1.0)
    factorise_forward, refused = kernels.factorise_forward, []

    def refusing_once(Hr, g, L, y, first, start, newest, *rest):
        if newest == 9 and not refused:
            refused.append(7)
            return 7
        return factorise_forward(Hr, g, L, y, first, start, newest, *rest)

    monkeypatch.setattr(sw, "factorise_forward", refusing_once)
    result = replay(data, lag_s=1.0)
    assert refused == [7] and result.recovered == [7]
    diff = np.abs(result.smoothed.position - clean.smoothed.position).max()
    assert diff < 1e-3, diff


def test_a_keyframe_refused_again_after_its_weak_prior_stops_the_update_naming_why(monkeypatch):
    from smoother.fixed_lag.contract import FixedLagFailed

    data = simulate("gentle", duration=2, seed=2)

    def refusing(Hr, g, L, y, first, start, newest, *rest):
        return newest if newest == 5 else factorise_forward(Hr, g, L, y, first, start, newest, *rest)

    factorise_forward = kernels.factorise_forward
    monkeypatch.setattr(sw, "factorise_forward", refusing)
    with pytest.raises(FixedLagFailed, match="even with a weak prior on it: the window's information spans"):
        replay(data, lag_s=1.0)
