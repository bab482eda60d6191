"""Uncertain rotations and rotated vectors against Monte Carlo (fixed seeds), and the chart
conversions against exactly converted samples.

Tolerances. Every Monte Carlo comparison is in units of the estimate's own standard error (SE),
measured by batch means (50 batches), so it includes all the sampling noise there is. "Agrees"
means every entry within 5 SE; the same test then shows its resolution by rejecting a competitor
(the lower-order expression, the unconverted covariance, the slides' printed Jacobian) by at least
15 SE. The rotated-vector Monte Carlo uses antithetic pairs (eps, -eps), an unbiased estimator
whose pair averages cancel the odd terms of exp and so most of the noise.

Measured at the seeds used below (|x| = 2.3; "z" = max over entries of |error| / SE; "quad" =
max |error| against Gauss-Hermite quadrature, which is exact to ~1e-15 here):
  Sigma std (rad)      mean: order 0 / 2 / 4             covariance: order 2 / 4
  (0.02, 0.015, 0.01)  z   367 / 1.0 / 1.0               z   1.8 / 1.8
                       quad 4.4e-4 / 4.6e-8 / 3.0e-12    quad 4.9e-7 / 1.2e-10
  (0.2, 0.13, 0.08)    z   261 / 3.3 / 1.3               z   32 / 1.2
                       quad 3.6e-2 / 3.5e-4 / 2.2e-6     quad 3.5e-3 / 8.1e-5
  (0.6, 0.4, 0.3)      z   299 / 27 / 2.2                z   88 / 38
                       quad 3.3e-1 / 3.1e-2 / 1.7e-3     quad 2.5e-1 / 5.6e-2
At the largest Sigma the 4th-order mean still has a truncation error (1.7e-3, ~1.5 SE), which this
Monte Carlo cannot resolve; the 4th-order covariance is visibly biased there and is only tested
to be closer than the 2nd order.
"""
import numpy as np
import pytest

from factors import euler, so3, uncertainty

ROT = so3.exp(np.array([0.4, -0.3, 0.8]))
C_BAR = so3.exp(np.array([0.3, 1.2, -0.7]))
X = np.array([1.0, -2.0, 0.5])

SMALL = (0.02, 0.015, 0.01)
MEDIUM = (0.2, 0.13, 0.08)
LARGE = (0.6, 0.4, 0.3)

N_PAIRS = 100_000
BATCHES = 50
AGREE = 5.0
REJECT = 15.0


def sigma(stds, rot=ROT):
    """A full (non-diagonal) covariance with the given principal standard deviations."""
    return rot @ np.diag(np.square(stds)) @ rot.T


def gaussian(rng, Sigma, n):
    return rng.standard_normal((n, 3)) @ np.linalg.cholesky(Sigma).T


def batch_se(per_batch):
    per_batch = np.asarray(per_batch)
    return per_batch.std(axis=0, ddof=1) / np.sqrt(len(per_batch))


def mc_rotated_vector(C_bar, Sigma, x, chart="left", seed=1, n_pairs=N_PAIRS):
    """Monte Carlo mean and covariance of y = C x, C = exp(eps) C_bar (left) or C_bar exp(eps)
    (right), with antithetic pairs; returns (mean, cov, se_mean, se_cov)."""
    rng = np.random.default_rng(seed)
    eps = gaussian(rng, Sigma, n_pairs)
    ys = []
    for e in (eps, -eps):
        C = so3.exp(e) @ C_bar if chart == "left" else C_bar @ so3.exp(e)
        ys.append(C @ x)
    first = 0.5 * (ys[0] + ys[1])
    second = 0.5 * (ys[0][:, :, None] * ys[0][:, None, :] + ys[1][:, :, None] * ys[1][:, None, :])

    def estimate(f, s):
        m = f.mean(axis=0)
        return m, s.mean(axis=0) - np.outer(m, m)

    mean, cov = estimate(first, second)
    parts = [estimate(f, s) for f, s in zip(np.array_split(first, BATCHES), np.array_split(second, BATCHES))]
    return mean, cov, batch_se([p[0] for p in parts]), batch_se([p[1] for p in parts])


def sample_cov(samples):
    """Sample covariance and its batch-means standard error."""
    cov = np.cov(samples.T)
    return cov, batch_se([np.cov(b.T) for b in np.array_split(samples, BATCHES)])


def z(estimate, prediction, se):
    return np.max(np.abs(np.asarray(prediction) - estimate) / se)


def quadrature_rotated_vector(C_bar, Sigma, x, nodes=20):
    """Mean and covariance of y = exp(eps) C_bar x by tensor Gauss-Hermite quadrature: a
    deterministic reference, accurate to ~1e-15 here (the integrand is entire)."""
    t, w = np.polynomial.hermite_e.hermegauss(nodes)
    w = w / np.sqrt(2 * np.pi)
    grid = np.stack(np.meshgrid(t, t, t, indexing="ij"), axis=-1).reshape(-1, 3)
    weight = np.einsum("i,j,k->ijk", w, w, w).reshape(-1)
    y = so3.exp(grid @ np.linalg.cholesky(Sigma).T) @ (C_bar @ x)
    mean = weight @ y
    d = y - mean
    return mean, np.einsum("n,ni,nj->ij", weight, d, d)


# ----------------------------------------------------------------------------------------------
# Conventions of the slides vs the project
# ----------------------------------------------------------------------------------------------


def test_slides_left_perturbation_is_the_primers_boxplus():
    rng = np.random.default_rng(0)
    eps = rng.normal(size=(100, 3))
    C = uncertainty.perturb(C_BAR, eps, "left")
    np.testing.assert_allclose(C, so3.boxplus(C_BAR, eps), atol=1e-15)
    np.testing.assert_allclose(uncertainty.perturbation_of(C, C_BAR, "left"), so3.boxminus(C, C_BAR), atol=0)
    # The slides' second moment E[eps^ eps^] = Sigma - tr(Sigma) I holds for so3.skew (the hat map).
    S = sigma(MEDIUM)
    e = gaussian(rng, S, 200_000)
    K = so3.skew(e)
    second = (K @ K).mean(axis=0)
    np.testing.assert_allclose(second, S - np.trace(S) * np.eye(3), atol=5e-4)


@pytest.mark.parametrize("chart", uncertainty.CHARTS)
def test_perturb_and_perturbation_of_are_inverse(chart):
    rng = np.random.default_rng(1)
    eps = gaussian(rng, sigma(LARGE), 1000)
    C = uncertainty.perturb(C_BAR, eps, chart)
    np.testing.assert_allclose(uncertainty.perturbation_of(C, C_BAR, chart), eps, atol=1e-12)


# ----------------------------------------------------------------------------------------------
# Rotated vector: mean
# ----------------------------------------------------------------------------------------------


def test_mean_small_sigma_against_monte_carlo():
    S = sigma(SMALL)
    mean, _, se, _ = mc_rotated_vector(C_BAR, S, X, seed=11)
    for order in (2, 4):
        assert z(mean, uncertainty.rotated_vector_mean(C_BAR, S, X, order), se) < AGREE
    # The Monte Carlo resolves the bias of the nominal C_bar x even at 0.02 rad.
    assert z(mean, uncertainty.rotated_vector_mean(C_BAR, S, X, 0), se) > 10 * REJECT
    np.testing.assert_array_equal(uncertainty.rotated_vector_mean(C_BAR, S, X, 0), C_BAR @ X)


def test_mean_large_sigma_against_monte_carlo_beats_nominal():
    S = sigma(LARGE)
    mean, _, se, _ = mc_rotated_vector(C_BAR, S, X, seed=12)
    m0, m2, m4 = (uncertainty.rotated_vector_mean(C_BAR, S, X, o) for o in (0, 2, 4))
    assert z(mean, m4, se) < AGREE
    assert z(mean, m2, se) > REJECT
    assert z(mean, m0, se) > 10 * REJECT
    err0, err2, err4 = (np.linalg.norm(m - mean) for m in (m0, m2, m4))
    assert err0 > 5 * err2 and err2 > 5 * err4


def test_mean_closed_form_for_isotropic_sigma():
    """For Sigma = s^2 I, E[exp(eps^)] = (1/3 + 2/3 (1 - s^2) exp(-s^2/2)) I exactly; its Taylor
    series is 1 - s^2 + 5/12 s^4 - ..., which the 2nd/4th-order expressions must reproduce."""
    for s in (0.01, 0.1, 0.3):
        S = s * s * np.eye(3)
        z0 = C_BAR @ X
        np.testing.assert_allclose(uncertainty.rotated_vector_mean(C_BAR, S, X, 2), (1 - s * s) * z0, rtol=1e-14)
        np.testing.assert_allclose(uncertainty.rotated_vector_mean(C_BAR, S, X, 4),
                                   (1 - s * s + 5 / 12 * s**4) * z0, rtol=1e-14)
        exact = (1 / 3 + 2 / 3 * (1 - s * s) * np.exp(-s * s / 2)) * z0
        np.testing.assert_allclose(quadrature_rotated_vector(C_BAR, S, X)[0], exact, atol=1e-14)


# ----------------------------------------------------------------------------------------------
# Rotated vector: covariance
# ----------------------------------------------------------------------------------------------


def test_covariance_small_sigma_against_monte_carlo():
    S = sigma(SMALL)
    _, cov, _, se = mc_rotated_vector(C_BAR, S, X, seed=13)
    for order in (2, 4):
        assert z(cov, uncertainty.rotated_vector_covariance(C_BAR, S, X, order), se) < AGREE
    assert z(cov, np.zeros((3, 3)), se) > 10 * REJECT  # the covariance itself is well resolved


def test_covariance_medium_sigma_fourth_order_needed():
    S = sigma(MEDIUM)
    _, cov, _, se = mc_rotated_vector(C_BAR, S, X, seed=14)
    assert z(cov, uncertainty.rotated_vector_covariance(C_BAR, S, X, 4), se) < AGREE
    assert z(cov, uncertainty.rotated_vector_covariance(C_BAR, S, X, 2), se) > REJECT


def test_covariance_large_sigma_fourth_order_is_closer():
    """At 0.6 rad both truncations are biased (the next term is O(Sigma^3)); the Monte Carlo
    resolves both errors and the 4th order is the smaller by a factor > 2."""
    S = sigma(LARGE)
    _, cov, _, se = mc_rotated_vector(C_BAR, S, X, seed=15)
    c2, c4 = (uncertainty.rotated_vector_covariance(C_BAR, S, X, o) for o in (2, 4))
    assert z(cov, c2, se) > 3 * REJECT
    assert np.linalg.norm(c4 - cov) < 0.5 * np.linalg.norm(c2 - cov)


def test_truncation_errors_scale_as_predicted_against_quadrature():
    """Deterministic check of the 4th-order terms: halving the standard deviations divides the
    2nd-order error by 2^4 and the 4th-order error by 2^6 (a wrong 4th-order term would leave an
    s^4 error, shrinking only 16-fold)."""
    shape = sigma((1.0, 0.7, 0.4))
    errors = {}
    for s in (0.1, 0.05):
        S = s * s * shape
        mean, cov = quadrature_rotated_vector(C_BAR, S, X)
        for o in (2, 4):
            errors[("mean", o, s)] = np.linalg.norm(uncertainty.rotated_vector_mean(C_BAR, S, X, o) - mean)
            errors[("cov", o, s)] = np.linalg.norm(uncertainty.rotated_vector_covariance(C_BAR, S, X, o) - cov)
    for what in ("mean", "cov"):
        r2 = errors[(what, 2, 0.1)] / errors[(what, 2, 0.05)]
        r4 = errors[(what, 4, 0.1)] / errors[(what, 4, 0.05)]
        assert 13 < r2 < 19, (what, r2)
        assert 52 < r4 < 76, (what, r4)
        assert errors[(what, 4, 0.05)] < 0.01 * errors[(what, 2, 0.05)]


def test_right_chart_sigma_against_monte_carlo():
    """GTSAM's chart, C = C_bar exp(eps): chart='right' converts exactly."""
    S = sigma(MEDIUM)
    mean, cov, se_m, se_c = mc_rotated_vector(C_BAR, S, X, chart="right", seed=16)
    assert z(mean, uncertainty.rotated_vector_mean(C_BAR, S, X, 4, chart="right"), se_m) < AGREE
    assert z(cov, uncertainty.rotated_vector_covariance(C_BAR, S, X, 4, chart="right"), se_c) < AGREE
    # Using the right-chart Sigma as if it were the left one is rejected.
    assert z(cov, uncertainty.rotated_vector_covariance(C_BAR, S, X, 4, chart="left"), se_c) > REJECT


def test_rotated_vector_functions_are_vectorised():
    rng = np.random.default_rng(17)
    C = so3.exp(rng.normal(size=(4, 1, 3)))
    S = np.stack([sigma(MEDIUM), sigma(SMALL), sigma(LARGE)])  # (3, 3, 3)
    x = rng.normal(size=(4, 3, 3))
    for order in (2, 4):
        m = uncertainty.rotated_vector_mean(C, S, x, order)
        c = uncertainty.rotated_vector_covariance(C, S, x, order)
        assert m.shape == (4, 3, 3) and c.shape == (4, 3, 3, 3)
        for i in range(4):
            for j in range(3):
                np.testing.assert_allclose(m[i, j], uncertainty.rotated_vector_mean(C[i, 0], S[j], x[i, j], order))
                np.testing.assert_allclose(c[i, j],
                                           uncertainty.rotated_vector_covariance(C[i, 0], S[j], x[i, j], order))


# ----------------------------------------------------------------------------------------------
# Chart conversions
# ----------------------------------------------------------------------------------------------


@pytest.mark.parametrize("stds", [SMALL, LARGE])
def test_left_right_conversion_is_exact_per_sample(stds):
    rng = np.random.default_rng(20)
    S = sigma(stds)
    eps_l = gaussian(rng, S, 200_000)
    C = so3.exp(eps_l) @ C_BAR
    eps_r = so3.log(C_BAR.T @ C)  # the right perturbation, exactly
    np.testing.assert_allclose(eps_r, eps_l @ C_BAR, atol=1e-12)  # = C_bar^T eps_l
    cov, se = sample_cov(eps_r)
    assert z(cov, uncertainty.covariance_left_to_right(S, C_BAR), se) < AGREE
    assert z(cov, S, se) > REJECT
    # and back
    cov_l, se_l = sample_cov(eps_l)
    assert z(cov_l, uncertainty.covariance_right_to_left(uncertainty.covariance_left_to_right(S, C_BAR), C_BAR),
             se_l) < AGREE
    np.testing.assert_allclose(
        uncertainty.covariance_right_to_left(uncertainty.covariance_left_to_right(S, C_BAR), C_BAR), S, atol=1e-15
    )


def test_right_to_left_from_right_samples():
    rng = np.random.default_rng(21)
    S = sigma(LARGE)
    eps_r = gaussian(rng, S, 200_000)
    eps_l = so3.log((C_BAR @ so3.exp(eps_r)) @ C_BAR.T)
    cov, se = sample_cov(eps_l)
    assert z(cov, uncertainty.covariance_right_to_left(S, C_BAR), se) < AGREE
    assert z(cov, S, se) > REJECT


# |log C_MID| = 2.12 rad: far from the identity, so the middle chart differs clearly from the others.
C_MID = so3.exp(np.array([1.5, -1.2, 0.9]))


@pytest.mark.parametrize("source, target", [("left", "middle"), ("middle", "left"), ("right", "middle"),
                                            ("middle", "right")])
def test_middle_chart_conversions_against_monte_carlo(source, target):
    """First order: checked at 0.05 rad (the O(Sigma^2) error is below the Monte Carlo's reach)."""
    rng = np.random.default_rng(22)
    S = sigma((0.05, 0.03, 0.02))
    eps = gaussian(rng, S, 200_000)
    C = uncertainty.perturb(C_MID, eps, source)
    converted = uncertainty.perturbation_of(C, C_MID, target)
    cov, se = sample_cov(converted)
    assert z(cov, uncertainty.convert_covariance(S, C_MID, source, target), se) < AGREE
    assert z(cov, S, se) > 10 * REJECT


def test_slides_struck_out_jacobian_would_be_wrong():
    """The slides' table prints phi ~= mu + J_l(mu) eps_l; the samples need J_l(mu)^-1."""
    rng = np.random.default_rng(23)
    S = sigma((0.05, 0.03, 0.02))
    eps_l = gaussian(rng, S, 200_000)
    eps_m = uncertainty.perturbation_of(so3.exp(eps_l) @ C_MID, C_MID, "middle")
    cov, se = sample_cov(eps_m)
    J_printed = so3.gamma(so3.log(C_MID))
    assert z(cov, J_printed @ S @ J_printed.T, se) > 10 * REJECT
    J_inverse = so3.gamma_inv(so3.log(C_MID))
    assert z(cov, J_inverse @ S @ J_inverse.T, se) < AGREE


def test_chart_jacobians_compose():
    J = {(a, b): uncertainty.chart_jacobian(C_MID, a, b) for a in uncertainty.CHARTS for b in uncertainty.CHARTS}
    for a in uncertainty.CHARTS:
        np.testing.assert_array_equal(J[(a, a)], np.eye(3))
        for b in uncertainty.CHARTS:
            np.testing.assert_allclose(J[(b, a)] @ J[(a, b)], np.eye(3), atol=1e-13)
            for c in uncertainty.CHARTS:
                np.testing.assert_allclose(J[(b, c)] @ J[(a, b)], J[(a, c)], atol=1e-13)
    np.testing.assert_allclose(J[("left", "right")], C_MID.T, atol=0)


@pytest.mark.parametrize("source", uncertainty.CHARTS)
@pytest.mark.parametrize("target", uncertainty.CHARTS)
def test_chart_jacobian_is_a_new_array_not_a_view_of_C(source, target):
    # left -> right returned np.swapaxes(C): writing into the Jacobian changed the caller's C.
    C = so3.exp(np.array([[0.3, -0.2, 0.9], [1.0, 2.0, -0.5]]))
    before = C.copy()
    J = uncertainty.chart_jacobian(C, source, target)
    assert not np.shares_memory(J, C)
    J[...] = 0.0
    assert np.array_equal(C, before)


def test_state_covariance_block_conversion_with_cross_terms():
    """A joint covariance (position 3, attitude 3 at index 3, velocity 3): converting the samples'
    attitude part exactly must give the converted covariance, cross-covariances included."""
    rng = np.random.default_rng(24)
    A = rng.normal(size=(9, 9))
    P = 0.05 * (A @ A.T / 9 + 0.2 * np.eye(9))
    samples = rng.standard_normal((200_000, 9)) @ np.linalg.cholesky(P).T
    converted = samples.copy()
    converted[:, 3:6] = so3.log(C_BAR.T @ (so3.exp(samples[:, 3:6]) @ C_BAR))
    cov = np.cov(converted.T)
    se = batch_se([np.cov(b.T) for b in np.array_split(converted, BATCHES)])
    P_right = uncertainty.covariance_left_to_right(P, C_BAR, index=3)
    assert z(cov, P_right, se) < AGREE
    assert z(cov, P, se) > REJECT
    np.testing.assert_array_equal(P_right[np.ix_([0, 1, 2, 6, 7, 8], [0, 1, 2, 6, 7, 8])],
                                  P[np.ix_([0, 1, 2, 6, 7, 8], [0, 1, 2, 6, 7, 8])])
    # 15-dim IMU state, attitude at index 6, a batch of states with their own rotations.
    B = rng.normal(size=(5, 15, 15))
    P15 = B @ B.transpose(0, 2, 1)
    Cs = so3.exp(rng.normal(size=(5, 3)))
    out = uncertainty.covariance_right_to_left(P15, Cs, index=6)
    for k in range(5):
        T = np.eye(15)
        T[6:9, 6:9] = Cs[k]
        np.testing.assert_allclose(out[k], T @ P15[k] @ T.T, atol=1e-12)


def test_gtsam_marginals_are_right_chart_and_convert_to_left():
    """GTSAM's Rot3 chart is the right one, and covariance_right_to_left turns its marginals into
    the primer's: a rotation X1 = X0 R_rel (known R_rel) has the same LEFT covariance as X0, while
    GTSAM's (right-chart) marginal of X1 is rotated."""
    gtsam = pytest.importorskip("gtsam")
    rng = np.random.default_rng(25)
    R0 = gtsam.Rot3(so3.exp(rng.normal(size=3)))
    for _ in range(20):
        d = rng.normal(size=3)
        np.testing.assert_allclose(so3.log(R0.retract(d).matrix() @ R0.matrix().T), R0.matrix() @ d, atol=1e-12)
    S0 = sigma(MEDIUM)
    R_rel = gtsam.Rot3(so3.exp(np.array([0.7, -1.9, 0.4])))
    graph = gtsam.NonlinearFactorGraph()
    graph.add(gtsam.PriorFactorRot3(0, R0, gtsam.noiseModel.Gaussian.Covariance(S0)))
    graph.add(gtsam.BetweenFactorRot3(0, 1, R_rel, gtsam.noiseModel.Isotropic.Sigma(3, 1e-3)))
    values = gtsam.Values()
    values.insert(0, R0)
    values.insert(1, R0.compose(R_rel))
    marginals = gtsam.Marginals(graph, values)
    M0, M1 = marginals.marginalCovariance(0), marginals.marginalCovariance(1)
    np.testing.assert_allclose(M0, S0, atol=1e-10)
    R1 = R0.compose(R_rel)
    left0 = uncertainty.covariance_right_to_left(M0, R0)
    left1 = uncertainty.covariance_right_to_left(M1, R1)
    # X1 = X0 R_rel exp(n), n ~ N(0, 1e-6 I) in X1's body frame: left covariance S_left(X0) + 1e-6 I.
    np.testing.assert_allclose(left1, left0 + 1e-6 * np.eye(3), atol=1e-12)
    assert np.abs(M1 - M0).max() > 1e-3  # the right-chart marginals differ: the conversion matters


# ----------------------------------------------------------------------------------------------
# Euler angles
# ----------------------------------------------------------------------------------------------


@pytest.mark.parametrize("convention", ["sxyz", "rzxz", "syzx"])
@pytest.mark.parametrize("chart", ["left", "right"])
def test_covariance_to_euler_against_monte_carlo(convention, chart):
    rng = np.random.default_rng(26)
    S = sigma((0.01, 0.008, 0.005))
    eps = gaussian(rng, S, 100_000)
    a0 = euler.from_matrix(C_MID, convention)
    angles = euler.from_matrix(uncertainty.perturb(C_MID, eps, chart), convention)
    d = np.remainder(angles - a0 + np.pi, 2 * np.pi) - np.pi
    cov, se = sample_cov(d)
    P = uncertainty.covariance_to_euler(S, C_MID, convention, chart)
    assert z(cov, P, se) < AGREE
    assert z(cov, S, se) > REJECT
    np.testing.assert_allclose(uncertainty.covariance_from_euler(P, a0, convention, chart), S, atol=1e-15)


def test_covariance_to_euler_is_nan_at_gimbal_lock_and_middle_chart_works():
    C = euler.to_matrix([0.3, np.pi / 2, -0.4], "sxyz")
    assert np.all(np.isnan(uncertainty.covariance_to_euler(sigma(SMALL), C, "sxyz")))
    # from_euler is finite there (rank-deficient).
    P = uncertainty.covariance_from_euler(np.diag([1e-4, 2e-4, 3e-4]), [0.0, np.pi / 2, -0.4], "sxyz")
    assert np.all(np.isfinite(P)) and np.linalg.matrix_rank(P, tol=1e-12) == 2
    # middle chart = left chart converted.
    S = sigma(SMALL)
    np.testing.assert_allclose(
        uncertainty.covariance_to_euler(S, C_MID, "rzyx", "middle"),
        uncertainty.covariance_to_euler(uncertainty.covariance_middle_to_left(S, C_MID), C_MID, "rzyx", "left"),
        atol=1e-15,
    )


# ----------------------------------------------------------------------------------------------
# Bad input
# ----------------------------------------------------------------------------------------------


@pytest.mark.parametrize(
    "call, match",
    [
        (lambda: uncertainty.rotated_vector_mean(C_BAR, sigma(SMALL), X, 3), "order"),
        (lambda: uncertainty.rotated_vector_mean(C_BAR, sigma(SMALL), X, True), "order"),
        (lambda: uncertainty.rotated_vector_covariance(C_BAR, sigma(SMALL), X, 0), "order"),
        (lambda: uncertainty.rotated_vector_mean(C_BAR, sigma(SMALL), X, 2, chart="middle"), "chart"),
        (lambda: uncertainty.rotated_vector_mean(C_BAR, np.eye(2), X), "Sigma"),
        (lambda: uncertainty.rotated_vector_mean(C_BAR, [[1, 2, 0], [0, 1, 0], [0, 0, 1]], X), "Sigma"),
        (lambda: uncertainty.rotated_vector_mean(C_BAR, -np.eye(3), X), "Sigma"),
        (lambda: uncertainty.rotated_vector_mean(C_BAR, np.full((3, 3), np.nan), X), "Sigma"),
        (lambda: uncertainty.rotated_vector_mean(C_BAR, sigma(SMALL), [1.0, np.nan, 0.0]), "x"),
        (lambda: uncertainty.rotated_vector_mean(2 * C_BAR, sigma(SMALL), X), "C_bar"),
        (lambda: uncertainty.covariance_left_to_right(np.eye(9), C_BAR, index=7), "index"),
        (lambda: uncertainty.covariance_left_to_right(np.eye(3), np.eye(4)), "C"),
        (lambda: uncertainty.convert_covariance(np.eye(3), C_BAR, "left", "global"), "target"),
        (lambda: uncertainty.perturb(C_BAR, [0.0, 0.0], "left"), "eps"),
        (lambda: uncertainty.covariance_to_euler(np.eye(3), C_BAR, "xyz"), "convention"),
    ],
)
def test_bad_input_raises_value_error_naming_the_argument(call, match):
    with pytest.raises(ValueError, match=match):
        call()
