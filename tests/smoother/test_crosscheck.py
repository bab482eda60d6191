"""The cross-checks of docs/design.md section 9 as tests on small cases, and ``smoother crosscheck``.

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

import json

import numpy as np
import pytest

from datasets.simulate import simulate
from smoother import stats
from smoother.evaluation import metrics
from smoother.batch.solve import solve_batch
from smoother.cli import main
from smoother.evaluation.crosscheck import TARGETS, prediction_error
from smoother.ekf.filter import Ekf
from smoother.model.problem import build_problem
from smoother.model.timeline import imu_steps

import estimator_cases as cases


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
    for the time average, as explained in test_ekf.py; smoothed errors are even more strongly
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
# the command


CROSSCHECK_KEYS = {
    "profile", "seeds", "duration_s", "prediction_max_abs_error", "final_state_max_sigma",
    "final_cov_trace_ratio", "final_cov_trace_ratio_range", "fixed_lag_kind", "fixed_lag_max_sigma",
    "fixed_lag_max_sigma_by_kind", "ate_rmse_m", "nees_mean", "nees_interval_95", "checks", "ok",
}


def test_crosscheck_command_prints_json_and_exits_by_ok(capsys):
    code = main(["crosscheck", "--seeds", "2", "--duration", "3", "--json"])
    result = json.loads(capsys.readouterr().out)
    assert set(result) == CROSSCHECK_KEYS
    assert code == (0 if result["ok"] else 1)
    assert result["ok"] is True  # these are the documented targets; they hold on this case
    assert result["ok"] == all(result["checks"].values())
    assert set(result["checks"]) == {"prediction", "final_state", "final_cov", "fixed_lag",
                                     "smoothed_at_least_as_accurate", "nees"}
    assert (result["profile"], result["seeds"], result["duration_s"]) == ("gentle", 2, 3.0)
    for key in ("ate_rmse_m", "nees_mean"):
        assert set(result[key]) == {"batch", "fixed-lag", "ekf"}
    np.testing.assert_allclose(result["nees_interval_95"], np.array(stats.nees_bounds(6, 2)) / 6.0, rtol=1e-12)
    # each check is what it says about the figures
    assert result["checks"]["prediction"] == (result["prediction_max_abs_error"] < TARGETS["prediction_max_abs_error"])
    assert result["checks"]["final_state"] == (result["final_state_max_sigma"] < TARGETS["final_state_max_sigma"])
    # the fixed-lag check covers the default sliding window and GTSAM's incremental smoother; the
    # figure kept from before is the sliding window's, the kind the result names
    by_kind = result["fixed_lag_max_sigma_by_kind"]
    assert list(by_kind) == ["sliding", "incremental"] and result["fixed_lag_kind"] == "sliding"
    assert result["fixed_lag_max_sigma"] == by_kind["sliding"]
    assert result["checks"]["fixed_lag"] == all(x < TARGETS["fixed_lag_max_sigma"] for x in by_kind.values())
    assert result["checks"]["smoothed_at_least_as_accurate"] == (
        result["ate_rmse_m"]["batch"] <= result["ate_rmse_m"]["ekf"])
    lo, hi = result["final_cov_trace_ratio_range"]
    assert lo <= result["final_cov_trace_ratio"] <= hi


def test_crosscheck_command_table_names_each_fixed_lag_kind(capsys):
    """The table gives the fixed-lag tracking figure of each kind, by name, and says whose ATE and
    NEES stand for the fixed-lag smoother; the figures are the JSON's."""
    argv = ["crosscheck", "--seeds", "2", "--duration", "1"]
    assert main(argv) == 0
    lines = capsys.readouterr().out.splitlines()
    assert main(argv + ["--json"]) == 0
    result = json.loads(capsys.readouterr().out)
    tracking = [line.split() for line in lines if line.rstrip().endswith(("sliding", "incremental"))]
    assert [(row[-1], float(row[-4])) for row in tracking] == [
        (kind, round(x, 4)) for kind, x in result["fixed_lag_max_sigma_by_kind"].items()]
    assert tracking[0][0] == "fixed_lag_max_sigma"
    assert any(line.split()[:2] == ["fixed-lag", "(sliding)"] for line in lines)


def test_crosscheck_rejects_an_unknown_fixed_lag_kind():
    from smoother.evaluation.crosscheck import CrosscheckOptions, crosscheck

    with pytest.raises(ValueError, match="fixed_lag_kinds: expected one or more of sliding, incremental, batch"):
        crosscheck(CrosscheckOptions(seeds=2, duration=1.0, fixed_lag_kinds=("window",)))


def test_crosscheck_command_exit_code_is_1_when_a_check_fails(capsys, monkeypatch):
    """The exit code follows ``ok``: with a target no estimator can meet, the command says so."""
    monkeypatch.setitem(TARGETS, "prediction_max_abs_error", 0.0)
    code = main(["crosscheck", "--seeds", "2", "--duration", "1", "--json"])
    result = json.loads(capsys.readouterr().out)
    assert result["ok"] is False and result["checks"]["prediction"] is False
    assert code == 1


@pytest.mark.parametrize("argv", [
    ["crosscheck", "--seeds", "1"],
    ["crosscheck", "--profile", "wobbly"],
    ["crosscheck", "--duration", "0"],
    ["crosscheck", "--lag", "-1"],
    ["crosscheck", "--duration", "inf"],
    ["crosscheck", "--lag", "inf", "--seeds", "2", "--duration", "1"],
    ["crosscheck", "--first-seed", "-1", "--seeds", "2", "--duration", "1"],
])
def test_crosscheck_command_rejects_bad_options_in_one_line(argv, capsys):
    assert main(argv) == 2
    err = capsys.readouterr().err
    assert err.startswith("smoother: error: ") and err.count("\n") == 1 and "Traceback" not in err
    assert argv[1] in err
