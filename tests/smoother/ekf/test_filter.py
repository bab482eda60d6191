"""The primer's EKF (smoother/ekf/filter.py): prediction, update, gate and statistical consistency.

Tolerances: identities between two evaluations of the same floating-point operations are held to
1e-12 (round-off of a few hundred steps on quantities of order 1-10); hand-computed Kalman
algebra to 1e-9 relative (one 15x15 solve, condition numbers below 1e6); statistical checks use
chi-square intervals stated where they are built.
"""
from __future__ import annotations

import dataclasses

import estimator_cases as cases
import numpy as np
import pytest

from datasets.simulate import simulate
from factors import imu, so3
from factors import sensor_models as sm
from smoother import stats
from smoother.ekf.filter import Ekf, run_ekf
from smoother.evaluation import metrics
from smoother.model.timeline import imu_steps, measurement_knots


def _update_pose(ekf, r, C, R) -> bool:
    return ekf.update_sensor("pose", sm.pack_pose(np.reshape(r, (1, 3)), np.reshape(C, (1, 3, 3)))[0], R)


def _update_position(ekf, z, R) -> bool:
    return ekf.update_sensor("position", sm.pack_position(np.reshape(z, (1, 3)))[0], R)


def _update_orientation(ekf, C, R) -> bool:
    return ekf.update_sensor("orientation", sm.pack_orientation(np.reshape(C, (1, 3, 3)))[0], R)


def _pose_residual(x, r, C):
    """``(e, H)`` of a pose measurement at the IMU (the pose model's kernel)."""
    return sm.evaluate_one(sm.POSE, x, sm.pack_pose(np.reshape(r, (1, 3)), np.reshape(C, (1, 3, 3)))[0])


def _initial_ekf(noise=imu.ImuNoise(velocity=1e-3), seed=0):
    """An EKF at a generic state (all blocks non-zero) with a diagonal covariance."""
    rng = np.random.default_rng(seed)
    state = imu.ImuState(
        r=rng.normal(size=3), v=rng.normal(size=3), C=so3.exp(rng.normal(size=3)),
        b_f=0.1 * rng.normal(size=3), b_w=0.01 * rng.normal(size=3),
    )
    cov = np.diag(np.repeat([0.1, 0.1, 0.02, 0.1, 0.01], 3) ** 2)
    return Ekf(state, cov, noise)


def _predict_some(ekf: Ekf, steps: int = 50, seed: int = 1) -> None:
    """Correlate the covariance blocks by a few predictions with generic IMU samples."""
    rng = np.random.default_rng(seed)
    for _ in range(steps):
        ekf.predict(rng.normal(size=3) + [0, 0, 9.81], 0.5 * rng.normal(size=3), 0.01)


# ------------------------------------------------------------------------------------------
# prediction


def test_without_measurements_the_ekf_is_dead_reckoning():
    """run_ekf on a dataset without measurements reports the start and the end only, and its end
    state is factors.imu.integrate of the same samples (same function, same order: round-off)."""
    data = simulate(profile="tumbling", duration=2.0, seed=5, imu_rate=cases.IMU_RATE, pose_rate=None)
    result = run_ekf(data, progress=False)
    traj = result.trajectory
    np.testing.assert_array_equal(traj.t, [data.t0, data.t1])
    dead = imu.integrate(data.initial, data.imu.acc[:-1], data.imu.gyro[:-1], np.diff(data.imu.t), data.gravity)
    for name in ("r", "v", "C", "b_f", "b_w"):
        np.testing.assert_allclose(getattr(traj.states, name)[-1], getattr(dead, name)[-1], rtol=0, atol=1e-12,
                                   err_msg=name)
        np.testing.assert_array_equal(getattr(traj.states, name)[0], getattr(data.initial, name))
    # the run moved far from the start (a tumbling body for 2 s), so the identity is not vacuous
    assert np.linalg.norm(dead.r[-1] - dead.r[0]) > 0.1
    assert result.rejected == 0


def test_prediction_step_by_step_equals_dead_reckoning():
    """Ekf.predict over samples of varying dt follows integrate() at every step."""
    rng = np.random.default_rng(3)
    n = 40
    acc = rng.normal(size=(n, 3)) + [0, 0, 9.81]
    gyro = rng.normal(size=(n, 3))
    dt = rng.uniform(0.001, 0.02, size=n)
    ekf = _initial_ekf()
    start = ekf.state
    dead = imu.integrate(start, acc, gyro, dt)
    for k in range(n):
        ekf.predict(acc[k], gyro[k], dt[k])
        for name in ("r", "v", "C"):
            np.testing.assert_allclose(getattr(ekf.state, name), getattr(dead, name)[k + 1], rtol=0, atol=1e-12)


def _numerical_jacobian(f, x, plus, minus, dim, h=1e-6):
    """Central differences of ``f`` at ``x`` with the manifold's [+] / [-] (primer eqs. 19, 20)."""
    y0 = f(x)
    J = np.zeros((len(minus(y0, y0)), dim))
    for j in range(dim):
        d = np.zeros(dim)
        d[j] = h
        J[:, j] = (minus(f(plus(x, d)), y0) - minus(f(plus(x, -d)), y0)) / (2 * h)
    return J


def test_covariance_prediction_equals_F_P_Ft_plus_G_Qd_Gt_by_hand():
    """P after a few steps (uneven dt) equals F P F^T + G Q_d G^T computed here, with
    Q_d = diag(R_i / dt) written out from the noise densities (not ImuNoise.discrete_covariance),
    and F, G themselves agree with central differences of the noisy step
    (imu.propagate_with_noise), so the hand computation does not just repeat the code."""
    noise = imu.ImuNoise(acc=2e-3, gyro=2e-4, acc_bias=3e-4, gyro_bias=2e-5, velocity=1e-3)
    ekf = _initial_ekf(noise)
    P = ekf.P.copy()
    rng = np.random.default_rng(7)
    for dt in (0.01, 0.004, 0.013, 0.01):
        acc, gyro = rng.normal(size=3) + [0, 0, 9.81], rng.normal(size=3)
        x = ekf.state
        _, F, G = imu.propagate(x, acc, gyro, dt, ekf.gravity)
        densities = np.repeat([noise.velocity, noise.acc, noise.gyro, noise.acc_bias, noise.gyro_bias], 3) ** 2
        Qd = np.diag(densities / dt)
        P = F @ P @ F.T + G @ Qd @ G.T
        ekf.predict(acc, gyro, dt)
        np.testing.assert_allclose(ekf.P, P, rtol=1e-12, atol=1e-15 * np.abs(P).max())

        # F and G against numerical derivatives (h = 1e-6: truncation ~1e-12, round-off ~1e-10
        # relative to entries of order 1-10; 1e-7 leaves margin and still catches any wrong
        # block, whose entries are of order dt * |v|, dt * |g| ~ 1e-3 .. 1e-1).
        def step(state):
            return imu.propagate(state, acc, gyro, dt, ekf.gravity, jacobians=False)[0]

        F_num = _numerical_jacobian(step, x, imu.boxplus, imu.boxminus, imu.STATE_DIM)
        G_num = _numerical_jacobian(
            lambda n: imu.propagate_with_noise(x, acc, gyro, dt, n, ekf.gravity), np.zeros(imu.NOISE_DIM),
            lambda n, d: n + d, lambda a, b: imu.boxminus(a, b) if isinstance(a, imu.ImuState) else a - b,
            imu.NOISE_DIM,
        )
        np.testing.assert_allclose(F, F_num, rtol=0, atol=1e-7)
        np.testing.assert_allclose(G, G_num, rtol=0, atol=1e-7)
    assert np.abs(P - ekf.P).max() <= 1e-12 * np.abs(P).max()


# ------------------------------------------------------------------------------------------
# update


def test_update_matches_the_kalman_equations_by_hand():
    """A pose update with moderate noise: dx = -K e with K = P H^T S^-1, the state corrected with
    the boxplus, P = (I - K H) P (the Joseph form equals it for the optimal gain), computed here
    with the residual and Jacobian of the pose model's kernel."""
    ekf = _initial_ekf()
    _predict_some(ekf)
    x, P = ekf.state, ekf.P.copy()
    measured_r = x.r + [0.05, -0.02, 0.03]
    measured_C = so3.exp([0.01, -0.02, 0.015]) @ x.C
    R = np.diag(np.repeat([0.05, 0.01], 3) ** 2)
    e, H = _pose_residual(x, measured_r, measured_C)
    K = P @ H.T @ np.linalg.inv(H @ P @ H.T + R)
    expected_state = imu.boxplus(x, -K @ e)
    expected_P = (np.eye(15) - K @ H) @ P

    assert _update_pose(ekf, measured_r, measured_C, R)
    for name in ("r", "v", "C", "b_f", "b_w"):
        np.testing.assert_allclose(getattr(ekf.state, name), getattr(expected_state, name), rtol=0, atol=1e-12)
    np.testing.assert_allclose(ekf.P, expected_P, rtol=0, atol=1e-9 * np.abs(P).max())
    # the correction is not trivial: every block of the state moved (correlations from prediction)
    moved = np.abs(imu.boxminus(ekf.state, x)).reshape(5, 3).max(axis=1)
    assert np.all(moved > 1e-6), moved


def test_precise_position_measurement_pulls_the_state_onto_it():
    """With sigma = 1e-6 m the posterior position is the measurement up to R P^-1 |e| ~ 1e-10 m
    (prior sigma ~0.1 m), and its covariance is R up to the same relative amount."""
    ekf = _initial_ekf()
    _predict_some(ekf)
    target = ekf.state.r + [0.3, -0.2, 0.1]
    R = (1e-6) ** 2 * np.eye(3)
    assert _update_position(ekf, target, R)
    np.testing.assert_allclose(ekf.state.r, target, rtol=0, atol=1e-9)
    np.testing.assert_allclose(ekf.P[imu.R, imu.R], R, rtol=0, atol=1e-3 * R[0, 0])


def test_precise_pose_measurement_pulls_position_and_attitude_onto_it():
    """The attitude innovation is the boxminus C [-] C_meas and its exact Jacobian Gamma^-1(e):
    with a tiny noise one update lands on the measured attitude (the Gauss-Newton step of
    log(exp(-e) exp(e) C_meas) is exact), here from 0.1 rad away."""
    ekf = _initial_ekf()
    _predict_some(ekf)
    measured_r = ekf.state.r + [0.2, 0.1, -0.3]
    measured_C = so3.exp([0.06, -0.05, 0.06]) @ ekf.state.C
    R = np.diag([1e-12] * 3 + [1e-14] * 3)
    assert _update_pose(ekf, measured_r, measured_C, R)
    np.testing.assert_allclose(ekf.state.r, measured_r, rtol=0, atol=1e-9)
    assert np.linalg.norm(so3.boxminus(ekf.state.C, measured_C)) < 1e-9


def test_orientation_update_pulls_the_attitude_onto_a_precise_measurement():
    ekf = _initial_ekf()
    _predict_some(ekf)
    measured_C = so3.exp([-0.04, 0.03, 0.02]) @ ekf.state.C
    assert _update_orientation(ekf, measured_C, 1e-14 * np.eye(3))
    assert np.linalg.norm(so3.boxminus(ekf.state.C, measured_C)) < 1e-9


def test_joseph_form_keeps_the_covariance_symmetric_positive_definite():
    """Forty very precise updates (1e-7 m, 1e-8 rad) interleaved with predictions: P stays
    exactly symmetric and positive definite, and each measured position variance is between R/2
    and R (the posterior (P^-1 + R^-1)^-1 of a prior P >= R). The same numbers through the short
    form P - K H P give, at the first update (prior 1e4 m^2 against 1e-14 m^2), position variances
    180 times too large or exactly 0 and a negative eigenvalue: the case really stresses the
    update formula (it is not one any formula would pass)."""
    ekf = _initial_ekf()
    ekf.P[imu.R, imu.R] = 1e4 * np.eye(3)  # a poor prior (100 m) against 1e-7 m: cancellation
    rng = np.random.default_rng(11)
    R = np.diag([1e-14] * 3 + [1e-16] * 3)
    worst_short_error = 0.0
    for k in range(40):
        _predict_some(ekf, steps=3, seed=k)
        measured_r = ekf.state.r + 1e-7 * rng.normal(size=3)
        measured_C = so3.exp(1e-8 * rng.normal(size=3)) @ ekf.state.C
        e, H = _pose_residual(ekf.state, measured_r, measured_C)
        P = ekf.P
        K = P @ H.T @ np.linalg.inv(H @ P @ H.T + R)
        short = P - K @ H @ P
        short_error = np.abs(np.diag(short)[imu.R] / R[0, 0] - 1.0).max()
        worst_short_error = max(worst_short_error, short_error)
        assert _update_pose(ekf, measured_r, measured_C, R)
        np.testing.assert_array_equal(ekf.P, ekf.P.T)
        eigenvalues = np.linalg.eigvalsh(ekf.P)
        assert eigenvalues.min() > 0, f"update {k}: smallest eigenvalue {eigenvalues.min():.3g}"
        variances = np.diag(ekf.P)[imu.R]
        assert np.all((variances >= 0.5 * R[0, 0]) & (variances <= R[0, 0] * (1 + 1e-9))), variances
    assert worst_short_error > 0.5


def test_gate_rejects_a_gross_outlier_and_counts_it():
    """A 5 m / 0.5 rad pose error against sigmas 0.05 m / 0.01 rad is far beyond the 99.9%
    chi-square(6) gate: the update returns False, changes nothing and is counted; a measurement
    at the predicted pose passes."""
    ekf = _initial_ekf()
    ekf.gate_probability = 0.999
    _predict_some(ekf)
    x, P = ekf.state, ekf.P.copy()
    R = np.diag(np.repeat([0.05, 0.01], 3) ** 2)
    assert not _update_pose(ekf, x.r + [3.0, 4.0, 0.0], so3.exp([0.5, 0, 0]) @ x.C, R)
    assert ekf.rejected == 1
    assert ekf.state is x
    np.testing.assert_array_equal(ekf.P, P)
    assert _update_pose(ekf, x.r, x.C, R)
    assert ekf.rejected == 1


def test_run_ekf_gate_rejects_exactly_the_simulated_outliers():
    """10% of the pose measurements moved by 5 m and 1 rad (sigmas 0.05 m, 0.01 rad): with a
    99.9% gate exactly those are rejected (an inlier is rejected with probability 1e-3, about 4%
    for the 37 inliers of this fixed seed; it does not happen here), and the gated filter is far
    more accurate than the ungated one."""
    data = simulate(profile="gentle", duration=4.0, seed=2, imu_rate=cases.IMU_RATE, pose_rate=cases.POSE_RATE,
                    outlier_fraction=0.1)
    assert len(data.outliers["pose"]) == 4
    gated = run_ekf(data, gate_probability=0.999, progress=False)
    plain = run_ekf(data, progress=False)
    assert gated.rejected == len(data.outliers["pose"])
    assert plain.rejected == 0
    ate_gated = cases.position_rmse(data, gated.trajectory)
    ate_plain = cases.position_rmse(data, plain.trajectory)
    assert ate_gated < 0.1 < ate_plain, (ate_gated, ate_plain)


def test_run_ekf_reports_every_knot(gentle):
    """States at the start, at every measurement time and at the end, covariances with them."""
    data = cases.dataset(gentle)
    traj = cases.ekf(gentle).trajectory
    np.testing.assert_array_equal(traj.t, np.union1d(data.sensor("pose").data.t, [data.t0, data.t1]))
    assert traj.cov.shape == (len(traj.t), 15, 15)
    assert np.all(np.linalg.eigvalsh(traj.cov).min(axis=1) > 0)


@pytest.mark.parametrize("calibrating", [False, True], ids=["plain", "calibrating"])
def test_states_kept_at_chosen_times_are_the_filter_s_states_there(calibrating):
    """``kept_at`` (the smoothers' keyframes): the filter still updates at every measurement; it
    keeps its state at those times alone, and where they are measurement times (or IMU samples),
    that state is the full run's, to rounding."""
    from datasets.simulated_sensors import SensorSpec
    from factors.calibration import CalibrationPrior
    from smoother.ekf.calibrated import run_calibrated_ekf
    from smoother.model.problem import calibration_set
    from smoother.model.timeline import keyframe_times

    data = simulate("gentle", duration=8.0, seed=2, imu_rate=100.0, pose_rate=0,
                    sensors=(SensorSpec("wheels", "velocity", 50.0, 0.05), SensorSpec("gnss", "gnss", 5.0, 0.2)))
    if calibrating:
        data = data.with_sensor("wheels", calibrate=CalibrationPrior(("rotation", "scale")))
        run = lambda kept_at=None: run_calibrated_ekf(data, calibration_set(data), progress=False,  # noqa: E731
                                                      kept_at=kept_at)
    else:
        run = lambda kept_at=None: run_ekf(data, progress=False, kept_at=kept_at)  # noqa: E731
    every, kept_at = run(), keyframe_times(data)
    kept = run(kept_at)
    assert len(kept_at) < len(every.trajectory.t) / 4  # a 10 Hz grid beside 55 Hz of measurements
    np.testing.assert_array_equal(kept.trajectory.t, kept_at)
    both, i, j = np.intersect1d(every.trajectory.t, kept_at, return_indices=True)
    assert len(both) > 0.9 * len(kept_at)
    for name in ("r", "v", "b_f"):
        np.testing.assert_allclose(getattr(kept.trajectory.states, name)[j], getattr(every.trajectory.states, name)[i],
                                   rtol=0, atol=1e-9)
    np.testing.assert_allclose(kept.trajectory.cov[j], every.trajectory.cov[i], rtol=1e-9, atol=1e-15)
    np.testing.assert_array_equal(kept.innovations.nis, every.innovations.nis)


@pytest.mark.parametrize("calibrating", [False, True], ids=["plain", "calibrating"])
def test_held_out_measurements_are_predicted_from_the_filter_s_own_state_and_not_used(calibrating):
    """A rig's held-out measurements (``every = K``) are predicted in the filter's loop
    (``FilterResult.heldout``) and not used: the states, covariances and innovations are those of
    the same run without them; each prediction is the residual of the filter's state at the
    held-out time (after the updates taken then) and ``H P H^T`` with its covariance there, and
    its normalised error is ``e^T (H P H^T + R)^-1 e``."""
    from datasets.kinds import KINDS, measure_rows
    from datasets.simulated_sensors import SensorSpec
    from factors.calibration import CalibrationPrior
    from smoother.ekf.calibrated import run_calibrated_ekf
    from smoother.model.problem import calibration_set
    from smoother.model.timeline import keyframe_times

    data = simulate("gentle", duration=8.0, seed=3, imu_rate=100.0, pose_rate=0,
                    sensors=(SensorSpec("wheels", "velocity", 50.0, 0.05), SensorSpec("gnss", "gnss", 5.0, 0.2)))
    for name, every in (("wheels", 5), ("gnss", 2)):
        s = data.sensor(name)
        used = np.arange(len(s.data.t)) % every == 0
        data = data.with_sensor(name, data=s.data.subset(used), heldout=s.data.subset(~used))
    if calibrating:
        data = data.with_sensor("wheels", calibrate=CalibrationPrior(("rotation", "scale")))
    without = data.with_sensor("wheels", heldout=None).with_sensor("gnss", heldout=None)
    held_t = np.concatenate([data.sensor(name).heldout.t for name in ("wheels", "gnss")])
    kept_at = np.union1d(keyframe_times(data), held_t)

    def run(d):
        if calibrating:
            return run_calibrated_ekf(d, calibration_set(d), progress=False, kept_at=kept_at)
        return run_ekf(d, progress=False, kept_at=kept_at)

    with_held, plain = run(data), run(without)
    assert plain.heldout == {} and set(with_held.heldout) == {"wheels", "gnss"}
    np.testing.assert_array_equal(with_held.trajectory.position, plain.trajectory.position)
    np.testing.assert_array_equal(with_held.trajectory.cov, plain.trajectory.cov)
    np.testing.assert_array_equal(with_held.innovations.nis, plain.innovations.nis)
    traj = with_held.trajectory
    for name in ("wheels", "gnss"):
        held, predicted = data.sensor(name).heldout, with_held.heldout[name]
        np.testing.assert_array_equal(predicted.index, np.arange(len(held.t)))
        assert np.isfinite(predicted.e).all()
        S = predicted.state_part + held.cov
        nis = np.einsum("ma,ma->m", predicted.e, np.linalg.solve(S, predicted.e[..., None])[..., 0])
        assert np.isfinite(nis).all() and 0.5 < nis.mean() / held.cov.shape[-1] < 2.0
        if calibrating:  # the residual is the calibrated one, P the augmented one: the plain filter's below
            continue
        k = np.searchsorted(traj.t, held.t)
        at = imu.ImuState(*(getattr(traj.states, f)[k] for f in ("r", "v", "C", "b_f", "b_w")))
        e, H = measure_rows(KINDS[data.sensor(name).kind], at, KINDS[data.sensor(name).kind].pack(held))
        np.testing.assert_allclose(predicted.e, e, rtol=0, atol=1e-12)
        np.testing.assert_allclose(predicted.state_part, H @ traj.cov[k] @ np.swapaxes(H, -1, -2), rtol=1e-9,
                                   atol=1e-15)


def test_a_relative_measurement_is_refused_by_the_filter_that_keeps_no_past_state():
    """An odometry row needs a cloned past state, which this filter does not keep: refused with
    the reason, not read as a one-state measurement."""
    from factors.errors import InputError

    ekf = Ekf(imu.ImuState.identity(), np.eye(15), imu.ImuNoise())
    with pytest.raises(InputError, match="a relative kind needs a cloned past state"):
        ekf.update_sensor("odometry", np.zeros(6), np.eye(6))


def test_run_ekf_warns_that_relative_poses_are_not_used():
    data = simulate(profile="gentle", duration=0.5, seed=0, imu_rate=cases.IMU_RATE, pose_rate=cases.POSE_RATE,
                    odometry_rate=5.0)
    with pytest.warns(UserWarning, match="relative-pose"):
        run_ekf(data, progress=False)


# ------------------------------------------------------------------------------------------
# consistency over Monte Carlo runs

MC_RUNS = 30
MC_DURATION = 5.0


@pytest.mark.parametrize("profile", ["gentle", "tumbling"])
def test_nees_is_consistent_over_monte_carlo_runs(profile):
    """Average pose NEES / 6 of the EKF over 30 simulated runs (5 s, 100 Hz IMU, 10 Hz poses,
    discrete-model truth) lies in the 95% chi-square interval.

    How the interval is built: at one time the NEES of a consistent filter is chi2(6); summed
    over M independent runs it is chi2(6M), so the per-time average over runs, divided by 6, lies
    in [q_0.025, q_0.975](chi2(6M)) / (6M) with probability 95%
    (``stats.nees_bounds(6, M) / 6``). We test the average of those per-time averages over the
    51 knots; the knots of one run are positively correlated, so averaging them shrinks the
    spread below that of one per-time average: the interval is conservative (a consistent
    filter passes with more than 95% probability; a filter whose covariance is off by 25% in
    either direction does not: the interval is about +-20% wide for M = 30).

    The biases are estimated from a wrong initial guess: the simulator's initial estimate has
    zero biases while the truth's are drawn from N(0, initial_cov), so the bias error is part of
    the initial error. The full 15-dimensional NEES (velocity and biases included) is tested in
    the same way.
    """
    lo, hi = (b / 6.0 for b in stats.nees_bounds(6, MC_RUNS))
    lo15, hi15 = (b / 15.0 for b in stats.nees_bounds(15, MC_RUNS))
    assert hi / lo < 1.6  # the interval is narrow enough to detect a 25% covariance error
    pose, full = [], []
    for seed in range(MC_RUNS):
        data = simulate(profile=profile, duration=MC_DURATION, seed=1000 + seed, imu_rate=cases.IMU_RATE,
                        pose_rate=cases.POSE_RATE)
        np.testing.assert_array_equal(data.initial.b_f, 0.0)
        np.testing.assert_array_equal(data.initial.b_w, 0.0)
        assert np.all(data.truth.states.b_w[0] != 0.0)
        traj = run_ekf(data, progress=False).trajectory
        T = cases.truth_at(data, traj.t)
        pose.append(metrics.nees(T, traj.states, traj.cov, "pose") / 6.0)
        full.append(metrics.nees(T, traj.states, traj.cov, "full") / 15.0)
    pose_mean = float(np.mean(pose))
    full_mean = float(np.mean(full))
    assert lo <= pose_mean <= hi, f"{profile}: pose NEES/6 {pose_mean:.3f} outside [{lo:.3f}, {hi:.3f}]"
    assert lo15 <= full_mean <= hi15, f"{profile}: full NEES/15 {full_mean:.3f} outside [{lo15:.3f}, {hi15:.3f}]"


def test_gate_threshold_follows_the_innovation_dimension():
    """A 3-dim position update is gated at chi2_3(p), not at the 6-dim pose threshold: a
    normalised innovation of 19 (between chi2_3(0.999) = 16.3 and chi2_6(0.999) = 22.5) is
    rejected as a position update, which a 6-dim threshold would have let through."""
    assert stats.chi2_quantile(0.999, 3) < 19.0 < stats.chi2_quantile(0.999, 6)
    ekf = _initial_ekf()
    ekf.gate_probability = 0.999
    _predict_some(ekf)
    x = ekf.state
    S_pos = ekf.P[imu.R, imu.R] + 0.01 * np.eye(3)
    # a position innovation with e^T S^-1 e = 19 along the first eigenvector of S
    w, V = np.linalg.eigh(S_pos)
    offset = V[:, 0] * np.sqrt(19.0 * w[0])
    assert not _update_position(ekf, x.r + offset, 0.01 * np.eye(3))
    assert ekf.rejected == 1


def test_log_likelihood_accumulates_the_innovation_densities():
    """Each accepted update adds log N(e; 0, S) (scipy as the reference); a gated one adds nothing."""
    from scipy.stats import multivariate_normal

    ekf = _initial_ekf()
    _predict_some(ekf)
    R = np.diag(np.repeat([0.05, 0.01], 3) ** 2)
    x = ekf.state
    measured_r, measured_C = x.r + [0.02, -0.01, 0.03], so3.exp([0.004, 0.0, -0.002]) @ x.C
    e, H = _pose_residual(x, measured_r, measured_C)
    expected = multivariate_normal(np.zeros(6), H @ ekf.P @ H.T + R).logpdf(e)
    assert _update_pose(ekf, measured_r, measured_C, R)
    assert ekf.log_likelihood == pytest.approx(expected, rel=1e-12)
    ekf.gate_probability = 0.999
    before = ekf.log_likelihood
    assert not _update_pose(ekf, ekf.state.r + [5.0, 0, 0], ekf.state.C, R)
    assert ekf.log_likelihood == before


def test_a_diverging_filter_stops_with_an_error_naming_the_time():
    """A filter whose state has run away (here: forced through its initial state or covariance)
    stops with an error naming the knot's time, instead of writing a trajectory of NaNs or 1e9 m."""
    from smoother.ekf.filter import FilterDiverged

    data = simulate("gentle", duration=1.0, seed=0)
    first = measurement_knots(data)[0]
    run_ekf(data, progress=False)  # a sane filter passes
    fast = dataclasses.replace(data, initial=data.initial.replace(v=np.array([1e5, 0.0, 0.0])))
    with pytest.raises(FilterDiverged, match=rf"diverged at t = {first:.6f} s"):
        run_ekf(fast, progress=False)
    cov = data.initial_cov.copy()
    cov[3, 3] = 1e14  # a velocity spread of 1e7 m/s
    with pytest.raises(FilterDiverged, match=rf"diverged at t = {first:.6f} s"):
        run_ekf(dataclasses.replace(data, initial_cov=cov), progress=False)


def test_run_ekf_equals_the_filter_driven_step_by_step():
    """The compiled filter loop of run_ekf equals the Ekf class driven knot by knot from Python
    (predict_steps, then the pose, position and orientation updates at their times), with
    all three measurement types, a gate and a rejected outlier."""
    data = simulate("tumbling", duration=6.0, seed=2, pose_rate=2.0, position_rate=5.0, orientation_rate=4.0)
    pose = data.sensor("pose").data
    bad = dataclasses.replace(pose, position=pose.position + np.where(np.arange(len(pose.t)) == 4, 50.0, 0.0)[:, None])
    data = data.with_sensor("pose", data=bad)
    result = run_ekf(data, gate_probability=0.999, progress=False)

    knots = measurement_knots(data)
    samples = imu_steps(data.imu, knots)
    ekf = Ekf(data.initial, data.initial_cov, data.noise, data.gravity, gate_probability=0.999)
    start = 0
    for k, (t, stop) in enumerate(zip(knots, samples.knot_step)):
        ekf.predict_steps(samples.acc[start:stop], samples.gyro[start:stop], samples.dt[start:stop])
        start = stop
        poses, positions, attitudes = (data.sensor(name).data for name in ("pose", "position", "orientation"))
        for m, update in ((poses, lambda i: _update_pose(ekf, poses.position[i], poses.C[i], poses.cov[i])),
                          (positions, lambda i: _update_position(ekf, positions.position[i], positions.cov[i])),
                          (attitudes, lambda i: _update_orientation(ekf, attitudes.C[i], attitudes.cov[i]))):
            hit = np.flatnonzero(m.t == t)
            if len(hit):
                update(hit[0])
        for name in ("r", "v", "C", "b_f", "b_w"):
            np.testing.assert_allclose(getattr(result.trajectory.states, name)[k], getattr(ekf.state, name),
                                       rtol=0, atol=1e-9)
        np.testing.assert_allclose(result.trajectory.cov[k], ekf.P, rtol=1e-9, atol=1e-15)
    assert result.rejected == ekf.rejected == 1
    assert result.log_likelihood == pytest.approx(ekf.log_likelihood, rel=1e-12)


def test_the_compiled_filter_needs_no_scipy(tmp_path):
    """The kernels load no SciPy (Numba's ``@`` on matrices would need its BLAS). A fresh
    interpreter with SciPy made unimportable and an empty Numba cache (so every kernel compiles
    anew) predicts and updates."""
    import os
    import subprocess
    import sys

    script = (
        "import sys\n"
        "sys.modules['scipy'] = None\n"
        "import numpy as np\n"
        "from factors import imu, so3\n"
        "from factors.sensor_models import pack_pose\n"
        "from smoother.ekf.filter import Ekf\n"
        "ekf = Ekf(imu.ImuState.identity(), np.eye(15) * 0.01, imu.ImuNoise())\n"
        "ekf.predict_steps(np.tile([0, 0, 9.81], (5, 1)), np.full((5, 3), 0.1), np.full(5, 0.01))\n"
        "row = pack_pose([ekf.state.r + 0.01], [so3.exp([0.01, 0, 0]) @ ekf.state.C])[0]\n"
        "assert ekf.update_sensor('pose', row, np.eye(6) * 1e-4)\n"
    )
    env = {**os.environ, "NUMBA_CACHE_DIR": str(tmp_path)}
    done = subprocess.run([sys.executable, "-c", script], env=env, capture_output=True, text=True)
    assert done.returncode == 0, done.stderr[-2000:]


def test_the_calibrating_filter_with_pinned_calibrations_is_the_plain_filter():
    """Calibrations whose priors' sigmas are negligible (1e-10) stay at the values given: the
    calibrating filter, its augmented covariance predicted and updated through the calibrated
    residuals, gives the plain filter's estimates, covariances, innovations, rejections and
    likelihood, here with three sensors measuring at common times, a gate and a rejected
    outlier."""
    from factors.calibration import CalibrationPrior, CalibrationSet
    from smoother.ekf.calibrated import run_calibrated_ekf

    data = simulate("tumbling", duration=6.0, seed=2, pose_rate=2.0, position_rate=4.0, orientation_rate=4.0)
    pose = data.sensor("pose").data
    bad = dataclasses.replace(pose, position=pose.position + np.where(np.arange(len(pose.t)) == 4, 50.0, 0.0)[:, None])
    data = data.with_sensor("pose", data=bad)
    pinned = dict(time_offset=1e-10, rotation=1e-10, lever_arm=1e-10)
    calibrations = CalibrationSet.given(("pose", "position"), (None, None), (
        CalibrationPrior(("time_offset", "rotation", "lever_arm"), **pinned),
        CalibrationPrior(("time_offset", "lever_arm"), **pinned)))
    plain = run_ekf(data, gate_probability=0.999, progress=False)
    augmented = run_calibrated_ekf(data, calibrations, gate_probability=0.999, progress=False)
    for name in ("r", "v", "C", "b_f", "b_w"):
        np.testing.assert_allclose(getattr(augmented.trajectory.states, name), getattr(plain.trajectory.states, name),
                                   rtol=0, atol=1e-9)
    np.testing.assert_allclose(augmented.trajectory.cov, plain.trajectory.cov, rtol=1e-9, atol=1e-15)
    a, b = augmented.innovations, plain.innovations
    assert list(a.sensor) == list(b.sensor) and np.array_equal(a.t, b.t) and np.array_equal(a.accepted, b.accepted)
    np.testing.assert_allclose(a.nis, b.nis, rtol=1e-9)
    assert augmented.rejected == plain.rejected == 1
    assert augmented.log_likelihood == pytest.approx(plain.log_likelihood, rel=1e-9)
    for value, mean in zip(augmented.calibration.values, calibrations.means):
        assert np.abs(value.boxminus(mean)).max() < 1e-8


def test_the_shared_update_on_an_augmented_state_matches_the_kalman_equations():
    """smoother.ekf.update.kalman_update on a covariance wider than the IMU's error state (a
    calibration's coordinates after it): dx = -K e and Joseph's P = (I - K H) P (I - K H)^T + K R
    K^T from the dense formulas, the log density of the innovation added; a gated update leaves
    P and dx alone and is counted."""
    from smoother.ekf.update import gate_thresholds, kalman_update

    rng = np.random.default_rng(4)
    n, m = imu.STATE_DIM + 6, 3
    A = rng.normal(size=(n, n))
    P = A @ A.T / n + 0.1 * np.eye(n)
    H, R, e = rng.normal(size=(m, n)), np.diag([0.2, 0.3, 0.4]), rng.normal(size=m)
    S = H @ P @ H.T + R
    K = P @ H.T @ np.linalg.inv(S)
    IKH = np.eye(n) - K @ H
    counts, dx, updated = np.zeros(2), np.empty(n), P.copy()
    d2 = kalman_update(updated, e, H, R, gate_thresholds(None), counts, dx)
    assert d2 == pytest.approx(e @ np.linalg.solve(S, e), rel=1e-12)
    np.testing.assert_allclose(dx, -K @ e, rtol=0, atol=1e-12 * np.abs(K @ e).max())
    np.testing.assert_allclose(updated, IKH @ P @ IKH.T + K @ R @ K.T, rtol=0, atol=1e-12 * np.abs(P).max())
    assert np.array_equal(updated, updated.T)
    log_density = -0.5 * (d2 + np.linalg.slogdet(S)[1] + m * np.log(2 * np.pi))
    assert counts[0] == 0 and counts[1] == pytest.approx(log_density, rel=1e-12)

    before, dx[:] = updated.copy(), np.nan
    gated = kalman_update(updated, 100.0 * e / np.sqrt(d2), H, R, gate_thresholds(0.999), counts, dx)
    assert gated > stats.chi2_quantile(0.999, m) and counts[0] == 1
    assert np.array_equal(updated, before) and np.all(np.isnan(dx))
