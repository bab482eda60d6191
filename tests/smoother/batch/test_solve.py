"""Batch smoothing (smoother/batch/solve.py): optimisers and engines agree, covariances, indeterminant
systems, robust kernels."""
from __future__ import annotations

import functools
from dataclasses import replace

import estimator_cases as cases
import gtsam
import numpy as np
import pytest

from datasets.robust import ROBUST_KERNEL_NAMES, robust_spec
from datasets.simulate import simulate
from factors import imu
from factors.errors import SolverError
from smoother.batch import solve as batch
from smoother.batch.solve import solve_batch
from smoother.errors import IndeterminantSystem
from smoother.model.blocks import Layout, linearize
from smoother.model.covariances import marginal_covariances
from smoother.model.problem import build_problem
from smoother.model.robust import ROBUST_KERNELS, noise_model

ENGINES = getattr(batch, "ENGINES", (None,))


def _solve(problem, optimizer="lm", engine=None, **kwargs):
    if engine is None:
        return solve_batch(problem, optimizer, **kwargs)
    return solve_batch(problem, optimizer, engine=engine, **kwargs)


@functools.lru_cache(maxsize=None)
def small():
    """2 s gentle, 10 Hz poses: 21 keyframes."""
    return simulate(profile="gentle", duration=2.0, seed=0, imu_rate=cases.IMU_RATE, pose_rate=cases.POSE_RATE)


@functools.lru_cache(maxsize=None)
def reference():
    """LM on the default engine: the optimum and covariances the others are compared with."""
    return solve_batch(build_problem(small()), "lm")


@pytest.mark.parametrize("engine", ENGINES)
@pytest.mark.parametrize("optimizer", ["lm", "gn", "dogleg"])
def test_optimizers_and_engines_reach_the_same_optimum(optimizer, engine):
    """Every optimiser (and engine) from the same initial values reaches the reference optimum:
    states within 1e-3 of the batch standard deviations (the stopping rule, a relative cost
    decrease below 1e-9 of a cost ~66, leaves |dx|^2 ~ 1e-7 in whitened units, i.e. ~3e-4
    sigma) and the same cost to 1e-7 relative; covariances to 1e-5 relative (they are evaluated
    at those states)."""
    ref = reference()
    result = _solve(build_problem(small()), optimizer, engine)
    sigma = cases.sigma_difference(result.trajectory.states, ref.trajectory.states, ref.trajectory.cov)
    assert sigma.max() < 1e-3, sigma.max()
    assert result.error == pytest.approx(ref.error, rel=1e-7)
    scale = np.abs(ref.trajectory.cov).max(axis=(1, 2), keepdims=True)
    assert np.abs(result.trajectory.cov - ref.trajectory.cov).max() / scale.min() < 1e-5
    assert 1 <= result.iterations < 100
    # the optimisation did something: the optimum is far from the initial values
    start = build_problem(small()).initial_states
    assert cases.sigma_difference(start, ref.trajectory.states, ref.trajectory.cov).max() > 1.0


def test_linearizing_in_chunks_changes_nothing(monkeypatch):
    """The vectorised engine linearises each block in chunks of factors (cache-sized for long
    runs); chunks of 4 factors (blocks of 20 and 21 split unevenly) give the reference optimum
    exactly: the same factors, the same arithmetic."""
    from smoother.model import blocks as solver

    monkeypatch.setattr(solver, "CHUNK", 4)
    result = solve_batch(build_problem(small()), "lm")
    ref = reference()
    assert result.iterations == ref.iterations
    for name in ("r", "v", "C", "b_f", "b_w"):
        np.testing.assert_allclose(getattr(result.trajectory.states, name), getattr(ref.trajectory.states, name),
                                   rtol=0, atol=1e-12)


def _counting(monkeypatch):
    """Counts of the optimiser's linearisations and cost-only passes over the factors."""
    from smoother.batch import optimiser

    counts = {"linearize": 0, "total_cost": 0}
    for name in counts:
        def counted(*args, _name=name, _f=getattr(optimiser, name), **kwargs):
            counts[_name] += 1
            return _f(*args, **kwargs)
        monkeypatch.setattr(optimiser, name, counted)
    return counts


def test_accepted_trials_are_linearised_once_and_the_optimum_comes_with_its_system(monkeypatch):
    """From the simulator's start every trial is accepted: one linearisation per iteration and
    the first, no cost-only pass; the result's linear system is the linearisation at its states
    (what the covariances come from)."""
    from smoother.batch.optimiser import optimize

    counts = _counting(monkeypatch)
    problem = build_problem(small())
    result = optimize(problem.blocks, problem.initial_states)
    assert counts == {"linearize": result.iterations + 1, "total_cost": 0}
    again, cost = linearize(problem.blocks, result.states)
    A, b = result.graph.jacobian()
    A_again, b_again = again.jacobian()
    np.testing.assert_array_equal(A, A_again)
    np.testing.assert_array_equal(b, b_again)
    assert result.cost == cost


@pytest.mark.parametrize("optimizer", ["lm", "dogleg"])
def test_rejected_trials_far_from_the_optimum_still_reach_it(optimizer, monkeypatch):
    """Started a sigma-sized step off in every state, trials are rejected (so costed first for a
    while): the optimiser still reaches the reference optimum, returned with the linear system at
    its states."""
    from smoother.batch.optimiser import optimize

    counts = _counting(monkeypatch)
    problem = build_problem(small())
    rng = np.random.default_rng(1)
    scale = np.r_[np.ones(9), 0.01 * np.ones(6)]
    start = imu.boxplus(problem.initial_states, rng.normal(size=(len(problem.initial_states), 15)) * scale)
    result = optimize(problem.blocks, start, optimizer)
    assert result.converged and counts["total_cost"] > 0, counts
    ref = reference()
    sigma = cases.sigma_difference(result.states, ref.trajectory.states, ref.trajectory.cov)
    assert sigma.max() < 1e-3, sigma.max()
    A, b = result.graph.jacobian()
    A_again, b_again = linearize(problem.blocks, result.states)[0].jacobian()
    np.testing.assert_array_equal(A, A_again)
    np.testing.assert_array_equal(b, b_again)


def test_covariances_are_symmetric_positive_definite_and_below_the_prior():
    """Every keyframe's 15x15 covariance is symmetric (to round-off) and positive definite, and
    keyframe 0's is below the prior's in the Loewner order (measurements only add information:
    initial_cov - P_0 is positive semi-definite)."""
    cov = reference().trajectory.cov
    assert cov.shape == (21, 15, 15)
    asym = np.abs(cov - np.swapaxes(cov, 1, 2)).max(axis=(1, 2)) / np.abs(cov).max(axis=(1, 2))
    assert asym.max() < 1e-9
    assert np.linalg.eigvalsh(cov).min() > 0
    gap = np.linalg.eigvalsh(small().initial_cov - cov[0])
    assert gap.min() > -1e-12, gap.min()


def test_covariances_can_be_skipped():
    result = solve_batch(build_problem(small()), covariances=False)
    assert result.trajectory.cov is None


def _without_prior(problem):
    """The same problem with the prior on keyframe 0 removed (GTSAM graph and vectorised
    blocks)."""
    prior = problem.factors_at[0][0]
    graph = gtsam.NonlinearFactorGraph()
    for group in problem.factors_at:
        for f in group:
            if f is not prior:
                graph.add(f)
    factors_at = [[f for f in group if f is not prior] for group in problem.factors_at]
    blocks = [b for b in problem.blocks if b.name != "prior"]
    assert len(blocks) == len(problem.blocks) - 1
    return replace(problem, blocks=blocks, gtsam_parts=replace(problem.gtsam, graph=graph, factors_at=factors_at))


@pytest.mark.parametrize("engine", ENGINES)
@pytest.mark.parametrize("optimizer", ["lm", "gn"])
def test_an_indeterminant_system_names_the_keyframe(optimizer, engine):
    """No prior and no measurement: nothing fixes the start, the system is rank-deficient. The
    error is IndeterminantSystem (a SolverError the command line prints in one line), not GTSAM's
    bare RuntimeError, and it names a keyframe and its time."""
    data = simulate(profile="gentle", duration=1.0, seed=3, imu_rate=cases.IMU_RATE, pose_rate=None)
    problem = _without_prior(build_problem(data))
    assert len(problem.times) == 2
    with pytest.raises(IndeterminantSystem) as info:
        _solve(problem, optimizer, engine)
    assert isinstance(info.value, SolverError)
    message = str(info.value)
    assert "keyframe 0 (t = 0.000000 s)" in message or "keyframe 1 (t = 1.000000 s)" in message, message
    assert "\n" not in message
    if engine in (None, "vectorized"):  # the vectorised engine also names what is free there
        assert ("it is free along whole state" in message
                or "it is free along position (world) x, y, z, velocity (body) x, y, z" in message), message


def test_without_the_prior_but_with_measurements_the_system_is_determined():
    """The contrast: with 10 Hz poses the prior is not needed (IMU factors fix velocity and
    biases), so the indeterminant case above really is about the missing constraints."""
    result = solve_batch(_without_prior(build_problem(small())))
    assert np.all(np.isfinite(result.trajectory.cov))


@functools.lru_cache(maxsize=None)
def dead_reckoned():
    """IMU only for 6.6 s after the prior, keyframes at 20 Hz: a unique optimum whose rows are
    badly conditioned (their condition number beyond 1e7: position is only dead-reckoned)."""
    problem = build_problem(simulate(profile="gentle", duration=6.6, seed=0, pose_rate=None), keyframe_rate=20)
    return problem, solve_batch(problem)


def test_covariances_of_a_badly_conditioned_chain_equal_a_dense_reference():
    """Cholesky of the information matrix (GTSAM's ``Marginals``) calls this chain indeterminant;
    the batch's covariances equal those of the dense SVD of the same whitened rows to 1e-9 of the
    largest entry (and to 1e-9 of each pair's standard deviations)."""
    problem, result = dead_reckoned()
    graph, _ = linearize(problem.blocks, result.trajectory.states)
    n = len(result.trajectory)
    with pytest.raises(RuntimeError, match="ndetermina"):
        gtsam.Marginals(graph, Layout(n).vector_values(np.zeros(n * 15)))
    A = graph.jacobian(gtsam.Ordering(list(range(n))))[0]
    _, s, Vt = np.linalg.svd(A, full_matrices=False)
    assert s[0] / s[-1] > 1e7
    dense = (Vt.T / s**2) @ Vt
    reference = np.stack([dense[15 * k:15 * k + 15, 15 * k:15 * k + 15] for k in range(n)])
    cov = result.trajectory.cov
    assert np.abs(cov - reference).max() < 1e-9 * np.abs(reference).max()
    sd = np.sqrt(np.einsum("kii->ki", reference))
    assert (np.abs(cov - reference) / (sd[:, :, None] * sd[:, None, :])).max() < 1e-9


def test_an_unconstrained_yaw_is_named_in_the_error():
    """The prior without its yaw (attitude about the world z axis) and no measurement: the whole
    trajectory may turn about z through the origin. The error names that direction: attitude
    about z and the positions it moves (x, y), nothing else."""
    problem, _ = dead_reckoned()
    blocks = []
    for block in problem.blocks:
        if block.name == "prior":
            whiten = block.whiten.copy()
            assert np.count_nonzero(whiten[0] - np.diag(np.diag(whiten[0]))) == 0  # diagonal prior
            whiten[0, 8, 8] = 0.0  # error-state component 8: attitude about z (world)
            block = replace(block, whiten=whiten)
        blocks.append(block)
    with pytest.raises(IndeterminantSystem) as info:
        solve_batch(replace(problem, blocks=blocks))
    message = str(info.value)
    assert "free along position (world) x, y, attitude (world) about z;" in message, message
    assert "\n" not in message


@functools.lru_cache(maxsize=None)
def sparse_fixes():
    """60 s tumbling, a position fix every 10 s, keyframes at 10 Hz: long dead-reckoned stretches
    whose lightly damped systems Cholesky calls indeterminant."""
    data = simulate(profile="tumbling", duration=60.0, seed=0, pose_rate=None, position_rate=0.1)
    return build_problem(data, keyframe_rate=10.0)


def test_lm_converges_on_long_dead_reckoned_stretches_within_the_default_cap():
    """Levenberg-Marquardt solves its steps with QR where Cholesky refuses them: it converges in
    a few iterations, well within the cap."""
    result = solve_batch(sparse_fixes(), covariances=False)
    assert result.converged and result.iterations < 20, result.iterations


def test_a_batch_stopped_at_its_cap_warns_and_says_it_did_not_converge():
    with pytest.warns(UserWarning, match=r"batch \(lm\): stopped after 2 iterations without converging \(the last "
                                         r"iteration still lowered the cost by [0-9.e+-]+ of itself\)"):
        result = solve_batch(sparse_fixes(), max_iterations=2, covariances=False)
    assert not result.converged and result.iterations == 2


# ------------------------------------------------------------------------------------------
# robust kernels


@pytest.mark.parametrize("spec, expected", [
    (None, None), ("none", None),
    ("huber", ("huber", None)), ("cauchy", ("cauchy", None)), ("tukey", ("tukey", None)),
    ("huber:2", ("huber", 2.0)), ("cauchy:0.5", ("cauchy", 0.5)), ("tukey:4.0", ("tukey", 4.0)),
    ("huber:", ("huber", None)),
])
def test_robust_spec_parses_kernels(spec, expected):
    assert robust_spec(spec) == expected


@pytest.mark.parametrize("junk", ["", "Huber", "l2", "huber:abc", "huber:-1", "cauchy:0", "tukey:nan", "huber:1:2",
                                  ":1.0"])
def test_robust_spec_rejects_junk_with_value_error(junk):
    with pytest.raises(ValueError):
        robust_spec(junk)


def test_every_kernel_name_has_a_kernel():
    assert sorted(ROBUST_KERNELS) == sorted(ROBUST_KERNEL_NAMES)


@pytest.mark.parametrize("name", sorted(ROBUST_KERNELS))
def test_noise_model_wraps_the_kernel(name):
    model = noise_model(np.diag([0.01, 0.01, 0.01, 1e-4, 1e-4, 1e-4]), (name, 2.0))
    assert isinstance(model, gtsam.noiseModel.Robust)
    assert isinstance(noise_model(np.eye(3), None), gtsam.noiseModel.Gaussian)


@pytest.mark.parametrize("name", sorted(ROBUST_KERNELS))
def test_robust_kernels_are_accepted_on_clean_data(name):
    """On clean data every kernel solves, changes the optimum (the kernel is applied: a threshold
    of 3 (Tukey: 4.5) on the NORM of the 6-dim whitened pose error down-weights many inliers) and keeps the
    position error near the plain solution's: over four seeds at most 1.5 times on average and 2
    times on each (Tukey, which gives weight 0 beyond its threshold, ends 1.8 times off on one
    of eight seeds, Huber and Cauchy within 1.12)."""
    ref = reference()
    threshold = 4.5 if name == "tukey" else 3  # tukey gives weight 0 beyond it: keep most inliers
    result = solve_batch(build_problem(small(), robust={"pose": robust_spec(f"{name}:{threshold}")}))
    diff = cases.sigma_difference(result.trajectory.states, ref.trajectory.states, ref.trajectory.cov)
    assert diff.max() > 1e-6
    assert np.all(np.isfinite(result.trajectory.cov))
    ratios = []
    for seed in range(4):
        data = simulate(profile="gentle", duration=2.0, seed=seed, imu_rate=cases.IMU_RATE, pose_rate=cases.POSE_RATE)
        plain = solve_batch(build_problem(data), covariances=False)
        robust_problem = build_problem(data, robust={"pose": robust_spec(f"{name}:{threshold}")})
        robust = solve_batch(robust_problem, covariances=False)
        ratios.append(cases.position_rmse(data, robust.trajectory) / cases.position_rmse(data, plain.trajectory))
    assert np.mean(ratios) <= 1.5 and max(ratios) < 2.0, ratios


def test_default_thresholds_scale_with_the_factor_dimension():
    from smoother.model.robust import default_threshold

    assert default_threshold("huber", 1) == pytest.approx(1.959964, abs=1e-5)
    assert default_threshold("huber", 6) == pytest.approx(3.548, abs=1e-3)
    assert default_threshold("tukey", 6) > default_threshold("cauchy", 6)


def test_default_huber_threshold_leaves_clean_data_nearly_unchanged():
    """The default threshold is dimension-aware (sqrt(chi2_6(0.95)) = 3.55 for a pose factor): the
    textbook scalar constant 1.345 moved this optimum by 0.77 sigma, the default by < 0.25."""
    ref = reference()
    result = solve_batch(build_problem(small(), robust={"pose": robust_spec("huber")}))
    diff = cases.sigma_difference(result.trajectory.states, ref.trajectory.states, ref.trajectory.cov)
    assert diff[:, imu.R].max() < 0.25


def test_a_dimension_scaled_huber_threshold_leaves_clean_data_unchanged():
    """The contrast to the xfail above: with the threshold sqrt(chi2_6(0.95)) = 3.55 no inlier
    pose factor of this run is downweighted noticeably (< 0.05 sigma)."""
    ref = reference()
    result = solve_batch(build_problem(small(), robust={"pose": robust_spec("huber:3.55")}))
    diff = cases.sigma_difference(result.trajectory.states, ref.trajectory.states, ref.trajectory.cov)
    assert diff[:, imu.R].max() < 0.05


@pytest.mark.parametrize("engine", ENGINES)
@pytest.mark.parametrize("name", ["huber", "cauchy"])
def test_robust_kernels_resist_outliers(name, engine):
    """10% of the poses moved by 5 m / 1 rad: the plain solution is dragged ~0.4 m off, a Huber
    or Cauchy kernel keeps the error at the ~2 cm of clean data. (Tukey, a redescending kernel,
    is not tested here: from initial values that sit ON the outlier measurements it stops in a
    local minimum ~1 m off, in both engines.)"""
    data = simulate(profile="gentle", duration=3.0, seed=0, imu_rate=cases.IMU_RATE, pose_rate=cases.POSE_RATE,
                    outlier_fraction=0.1)
    plain = _solve(build_problem(data), "lm", engine, covariances=False)
    robust = _solve(build_problem(data, robust={"pose": robust_spec(name)}), "lm", engine, covariances=False)
    ate_plain = cases.position_rmse(data, plain.trajectory)
    ate_robust = cases.position_rmse(data, robust.trajectory)
    assert ate_robust < 0.05 < 0.2 < ate_plain, (ate_robust, ate_plain)


def test_started_from_the_ekf_the_batch_reaches_the_same_optimum_in_a_few_iterations():
    """An AHRS attitude and a wheel speed at 50 Hz, a gyro bias of ~0.07 rad/s, 61 s: from dead
    reckoning LM needs 25 iterations, from the EKF's estimate (every keyframe anchored at it, every
    interval integrated around its biases) 3; both end at the same trajectory (1.2 mm apart, the
    IMU factors' covariances being evaluated along the two starts; the error is 0.11 m)."""
    from datasets.simulated_sensors import SensorSpec
    from smoother.ekf.filter import run_ekf

    data = simulate("gentle", duration=61, seed=3, imu_rate=100, pose_rate=None, initial_bias_sigma=(0.05, 0.07),
                    sensors=[SensorSpec("ahrs", "orientation", 50, 0.01), SensorSpec("wheels", "velocity", 50, 0.05)])
    ekf = run_ekf(data).trajectory
    cold = solve_batch(build_problem(data), covariances=False)
    warm = solve_batch(build_problem(data, start=ekf), covariances=False)
    assert cold.converged and warm.converged
    assert warm.iterations <= 5 < cold.iterations, (warm.iterations, cold.iterations)
    assert np.abs(warm.trajectory.position - cold.trajectory.position).max() < 5e-3


def test_a_start_keeps_grid_keyframes_between_its_states_predicted():
    """A start whose times are a subset of the keyframes (a grid added): the keyframes it has are
    anchored at it, the others predicted from the keyframe before; the optimum is the same."""
    from smoother.ekf.filter import run_ekf

    data = simulate("gentle", duration=4, seed=1)
    ekf = run_ekf(data).trajectory
    gridded = build_problem(data, keyframe_rate=25.0, start=ekf)
    at = np.isin(gridded.times, ekf.t)
    assert 0 < at.sum() < len(at)
    k = np.searchsorted(ekf.t, gridded.times[at])
    assert np.allclose(gridded.initial_states.r[at], ekf.states.r[k], atol=1e-12)
    warm = solve_batch(gridded, covariances=False)
    cold = solve_batch(build_problem(data, keyframe_rate=25.0), covariances=False)
    assert np.abs(warm.trajectory.position - cold.trajectory.position).max() < 1e-3


def test_covariances_with_calibrations_equal_a_dense_reference():
    """With calibration variables (the dense border), every block the batch returns -- keyframe
    with keyframe, keyframe with calibration, calibration with calibration -- equals that of the
    dense SVD of the same whitened rows, to 1e-9 of each pair's standard deviations."""
    from datasets.simulated_sensors import SensorSpec
    from factors.calibration import CalibrationPrior

    data = simulate(profile="gentle", duration=4.0, seed=3, pose_rate=0, sensors=(
        SensorSpec("wheels", "velocity", 10.0, 0.05), SensorSpec("gnss", "gnss", 5.0, 0.2)))
    data = data.with_sensor("wheels", calibrate=CalibrationPrior(("rotation", "scale", "time_offset")))
    data = data.with_sensor("gnss", calibrate=CalibrationPrior(("time_offset", "lever_arm")))
    problem = build_problem(data)
    result = solve_batch(problem)
    states, calibration = result.trajectory.states, result.calibration
    graph, _ = linearize(problem.blocks, states, calibration)
    layout = Layout.of(states, calibration)
    A = graph.jacobian(gtsam.Ordering(list(layout.keys)))[0]
    _, s, Vt = np.linalg.svd(A, full_matrices=False)
    dense = (Vt.T / s**2) @ Vt
    at = np.cumsum([0, *(layout.dim(k) for k in layout.keys)])
    block = lambda a, b: dense[at[a]:at[a + 1], at[b]:at[b + 1]]  # noqa: E731
    n = layout.n
    assert len(result.joint) >= 2 * n + 2 * (n + 1)  # chain, calibrations, and each keyframe with each
    for (a, b), sigma_ab in result.joint.items():
        sd = np.sqrt(np.diag(block(a, a)))[:, None] * np.sqrt(np.diag(block(b, b)))[None, :]
        assert (np.abs(sigma_ab - block(a, b)) / sd).max() < 1e-9, (a, b)
    for j, cov in enumerate(result.calibration_cov):
        np.testing.assert_allclose(cov, block(n + j, n + j), rtol=1e-9, atol=0)


def test_covariances_with_calibrations_where_a_keyframe_does_not_reach_them():
    """A keyframe whose rows share nothing with the others or the calibrations (its conditional
    has no parents) keeps its own covariance, and the others still get the calibrations' share:
    every marginal equals the dense inverse of the information."""
    rng = np.random.default_rng(0)
    n, nc = 4, 2
    graph = gtsam.GaussianFactorGraph()
    unit = gtsam.noiseModel.Unit
    for k in range(n):
        graph.add(gtsam.JacobianFactor(k, rng.normal(size=(15, 15)) + 5 * np.eye(15), rng.normal(size=15),
                                       unit.Create(15)))
    graph.add(gtsam.JacobianFactor(0, rng.normal(size=(15, 15)), 1, rng.normal(size=(15, 15)), rng.normal(size=15),
                                   unit.Create(15)))
    graph.add(gtsam.JacobianFactor(2, rng.normal(size=(3, 15)), n, rng.normal(size=(3, nc)), rng.normal(size=3),
                                   unit.Create(3)))
    graph.add(gtsam.JacobianFactor(n, np.eye(nc), np.zeros(nc), unit.Create(nc)))
    marginals, joint = marginal_covariances(graph, n, None, True, Layout(n, (nc,)))
    A = graph.jacobian(gtsam.Ordering(list(range(n + 1))))[0]
    dense = np.linalg.inv(A.T @ A)
    for k in range(n):
        np.testing.assert_allclose(marginals[k], dense[15 * k:15 * k + 15, 15 * k:15 * k + 15], rtol=0, atol=1e-12)
    np.testing.assert_allclose(joint[(2, n)], dense[30:45, 60:], rtol=0, atol=1e-12)


def test_a_keyframe_covariance_from_gtsams_marginals_or_isam2_is_the_prior_it_came_from():
    """``keyframe_covariance``, the one conversion of GTSAM's joint marginal of a keyframe's four
    variables into the primer's 15x15 covariance (the gtsam engine's and GTSAM's fixed-lag
    smoothers'): a keyframe whose only factor is a state prior of covariance ``P`` has ``P``
    back at the prior's mean, from ``gtsam.Marginals`` and from ISAM2 alike (1e-10 relative:
    one factorisation of a well-conditioned 15x15 system)."""
    from factors import priors, so3
    from factors.keys import keyframe_keys
    from smoother.model.covariances import keyframe_covariance
    from smoother.model.problem import insert_state

    rng = np.random.default_rng(8)
    prior = imu.ImuState(rng.normal(0, 10, 3), rng.normal(0, 2, 3), so3.exp(rng.normal(0, 1, 3)),
                         rng.normal(0, 0.1, 3), rng.normal(0, 0.01, 3))
    Q = np.linalg.qr(rng.normal(size=(15, 15)))[0]
    sigma = np.diag(np.repeat([2.0, 0.5, 0.2, 0.1, 0.01], 3))
    P = sigma @ Q @ np.diag(rng.uniform(0.5, 2.0, 15)) @ Q.T @ sigma  # correlated, moderately conditioned
    k = keyframe_keys(3)
    graph = gtsam.NonlinearFactorGraph()
    graph.add(priors.state_prior_factor(k, prior, P))
    values = gtsam.Values()
    insert_state(values, k, prior)
    isam = gtsam.ISAM2()
    isam.update(graph, values)
    for marginals in (gtsam.Marginals(graph, values), isam):
        back = keyframe_covariance(marginals, k, values.atRot3(k.rot))
        assert np.abs(back - P).max() <= 1e-10 * np.abs(P).max()
