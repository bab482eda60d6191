"""The cross-checks of docs/design.md section 9 as tests on small cases (``smoother crosscheck``:
``tests/cli/test_crosscheck_cli.py``).

Tolerances (the project's targets, smoother.evaluation.crosscheck.TARGETS):

* prediction identity < 1e-9: the IMU factor and the EKF run the same Euler model, so they
  differ by round-off only (measured ~1e-15);
* final state: batch vs EKF at the LAST keyframe below 0.1 EKF sigma in every component, and
  covariance traces within 10% -- filtering and smoothing coincide there up to linearisation
  (the EKF linearises once, the smoother iterates); measured 0.01-0.04 sigma, ratio 1.000-1.001;
* fixed-lag tracking: the newest fixed-lag state within 0.2 EKF sigma of the EKF at every
  keyframe (both are filters up to linearisation and the smoothers' relinearisation thresholds),
  for every kind of fixed-lag smoother in ``tests/smoother/fixed_lag/test_window_contract.py`` and
  for the kinds ``smoother crosscheck`` checks here; measured 0.02-0.1;
* smoothed at least as accurate as filtered: batch ATE <= EKF ATE (measured about half).
"""
from __future__ import annotations

import estimator_cases as cases
import numpy as np
import pytest

from datasets.simulate import simulate
from smoother import stats
from smoother.batch.solve import solve_batch
from smoother.ekf.filter import Ekf
from smoother.evaluation import metrics
from smoother.evaluation.crosscheck import TARGETS, prediction_error
from smoother.model.problem import build_problem
from smoother.model.timeline import imu_steps

# ------------------------------------------------------------------------------------------
# prediction identity


def _ekf_prediction(data, start, k0, k1, times, drop_sample=False):
    """The EKF's propagation of ``start`` over the dataset's IMU samples between keyframe times
    ``times[k0]`` and ``times[k1]`` (cut by smoother.model.timeline, as run_ekf does)."""
    steps = imu_steps(data.imu, times)
    ekf = Ekf(start, np.zeros((15, 15)), data.noise, data.gravity)
    for s in range(steps.knot_step[k0], steps.knot_step[k1]):
        if drop_sample and s == steps.knot_step[k0]:
            continue
        ekf.predict(steps.acc[s], steps.gyro[s], steps.dt[s])
    return ekf.state


def test_imu_factor_prediction_equals_ekf_propagation(case):
    """For EVERY keyframe interval: the factor's prediction from a state with non-zero biases
    (accelerometer bias arbitrary: it enters linearly, exactly; gyro bias at the factor's
    linearisation point) equals the EKF's sample-by-sample propagation to < 1e-9 in r, v and
    C. The same comparison with the first sample of an interval left out differs by > 1e-6, so
    the check can tell a wrong interval from a right one."""
    data = cases.dataset(case)
    problem = cases.problem(case)
    rng = np.random.default_rng(0)
    worst = 0.0
    for k, factor in enumerate(problem.imu_factors):
        start = problem.initial_states[k].replace(b_f=0.05 * rng.normal(size=3), b_w=factor.pre.b_w_bar)
        predicted = factor.predict(start)
        ekf = _ekf_prediction(data, start, k, k + 1, problem.times)
        for name in ("r", "v", "C"):
            worst = max(worst, float(np.abs(getattr(predicted, name) - getattr(ekf, name)).max()))
        if k == 3:
            wrong = _ekf_prediction(data, start, k, k + 1, problem.times, drop_sample=True)
            assert np.abs(predicted.v - wrong.v).max() > 1e-6
    assert worst < TARGETS["prediction_max_abs_error"], worst
    assert prediction_error(problem, data) < TARGETS["prediction_max_abs_error"]


# ------------------------------------------------------------------------------------------
# filtering and smoothing at the last state (the fixed-lag smoothers' tracking of the EKF, on every
# kind: tests/smoother/fixed_lag/test_window_contract.py)


def test_batch_equals_ekf_at_the_last_state(case):
    """Same measurements: the batch smoother's LAST state is the EKF's within 0.1 EKF sigma,
    with covariance traces within 10%; beyond the trace, the whole covariance agrees: the
    difference of the two covariances normalised by the EKF standard deviations (a correlation
    scale) is below 0.05 everywhere (measured < 0.01)."""
    ekf = cases.ekf(case).trajectory
    _, batch = cases.batch(case)
    np.testing.assert_array_equal(batch.trajectory.t, ekf.t)
    sigma = cases.sigma_difference(batch.trajectory.states[-1], ekf.states[-1], ekf.cov[-1])
    assert sigma.max() < TARGETS["final_state_max_sigma"], sigma
    ratio = np.trace(batch.trajectory.cov[-1]) / np.trace(ekf.cov[-1])
    assert abs(ratio - 1.0) <= TARGETS["final_cov_trace_ratio_tolerance"], ratio
    s = np.sqrt(np.diag(ekf.cov[-1]))
    assert np.abs((batch.trajectory.cov[-1] - ekf.cov[-1]) / np.outer(s, s)).max() < 0.05
    # not trivially true: inside the run the smoother is much more certain than the filter
    middle = len(ekf.t) // 2
    assert np.trace(batch.trajectory.cov[middle][:3, :3]) < 0.8 * np.trace(ekf.cov[middle][:3, :3])


def test_smoothed_trajectory_is_at_least_as_accurate_as_the_filtered(case):
    """Position RMSE over the keyframes against the truth: batch <= EKF (measured about half)."""
    data = cases.dataset(case)
    ate_ekf = cases.position_rmse(data, cases.ekf(case).trajectory)
    ate_batch = cases.position_rmse(data, cases.batch(case)[1].trajectory)
    assert ate_batch <= ate_ekf, (ate_batch, ate_ekf)


@pytest.mark.parametrize("profile", ["gentle", "tumbling"])
def test_batch_nees_is_consistent_over_monte_carlo_runs(profile):
    """The smoother's covariances are consistent too: pose NEES / 6 over 30 runs of 5 s,
    averaged over runs and keyframes, in the 95% interval nees_bounds(6, 30) / 6 (conservative
    for the time average, as explained in ekf/test_filter.py; smoothed errors are even more strongly
    correlated over time than filtered ones, so one run alone says little: 0.5-0.8 here)."""
    runs = 30
    lo, hi = (b / 6.0 for b in stats.nees_bounds(6, runs))
    values = []
    for seed in range(runs):
        data = simulate(profile=profile, duration=5.0, seed=1000 + seed, imu_rate=cases.IMU_RATE,
                        pose_rate=cases.POSE_RATE)
        traj = solve_batch(build_problem(data)).trajectory
        values.append(metrics.nees(cases.truth_at(data, traj.t), traj.states, traj.cov, "pose") / 6.0)
    mean = float(np.mean(values))
    assert lo <= mean <= hi, f"{profile}: batch NEES/6 {mean:.3f} outside [{lo:.3f}, {hi:.3f}]"


# ------------------------------------------------------------------------------------------
# measurements attached to keyframes


def test_the_crosscheck_holds_with_measurements_attached_to_the_keyframes():
    """The wheels rig (100 Hz speeds and 4 Hz fixes beside the 10 Hz poses): the keyframes are
    the 10 Hz grid, nine speeds in ten and every other fix attached to the keyframe before them,
    and every check holds (2 seeds x 10 s; at 5 s one seed's accelerometer z bias is 0.17 EKF
    sigma from the batch's at the last state, with a keyframe at every measurement time too: the
    EKF's linearisation while the biases are still settling)."""
    from smoother.evaluation.crosscheck import CrosscheckOptions, crosscheck

    result = crosscheck(CrosscheckOptions(seeds=2, duration=10.0, sensors="wheels"))
    assert result["keyframes"]["rate_hz"] == 10.0 and result["keyframes"]["attached"] == 900 + 20
    assert result["ok"], result["checks"]


def test_the_crosscheck_sees_an_attached_measurement_predicted_one_imu_step_short(monkeypatch):
    """The same rig with every attached measurement evaluated one IMU step (5 ms) before its time:
    the batch's last state and the fixed-lag smoothers' newest leave the EKF's by more than the
    targets allow, so the check can tell a wrong attachment from a right one."""
    from dataclasses import replace

    from smoother.evaluation.crosscheck import TARGETS, CrosscheckOptions, crosscheck
    from smoother.model import problem as problem_module
    from smoother.model.timeline import attachment

    def one_step_short(steps, times, t):
        a = attachment(steps, times, t)
        return replace(a, steps=np.where(a.steps > 1, a.steps - 1, a.steps))

    monkeypatch.setattr(problem_module, "attachment", one_step_short)
    result = crosscheck(CrosscheckOptions(seeds=2, duration=10.0, sensors="wheels"))
    assert result["final_state_max_sigma"] > TARGETS["final_state_max_sigma"]
    assert not result["ok"]


# ------------------------------------------------------------------------------------------
# the options


def test_crosscheck_rejects_an_unknown_fixed_lag_kind():
    from smoother.evaluation.crosscheck import CrosscheckOptions, crosscheck

    with pytest.raises(ValueError, match="fixed_lag_kinds: expected one or more of sliding, incremental, batch"):
        crosscheck(CrosscheckOptions(seeds=2, duration=1.0, fixed_lag_kinds=("window",)))
    with pytest.raises(ValueError, match="sensors: expected one of pose, wheels"):
        crosscheck(CrosscheckOptions(seeds=2, duration=1.0, sensors="sonar"))
