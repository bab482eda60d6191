"""Scoring (:mod:`smoother.evaluation.scoring`): metrics against known errors, what too little or
gappy truth leaves, GPS RMSE held out and fitted, the residuals' correlation."""
from __future__ import annotations

import math
from dataclasses import replace

import estimator_cases as cases
import numpy as np
import pytest
from drifting_fixes import fixes_with_noise

from datasets.simulate import simulate
from datasets.types import PositionMeasurements, Trajectory
from smoother.evaluation import scoring as report


def test_against_truth_on_a_known_error():
    """ATE 0.5 m, rotation RMSE 2 deg, pose NEES = 0.25 / 0.01 + a^2 / 1e-4 (a = 2 deg in rad),
    /6, at every state."""
    truth = cases.scored_truth()
    m = report.against_truth(truth, cases.offset_estimate(truth))
    assert m["ate_rmse_m"] == pytest.approx(0.5, rel=1e-12)
    assert m["rot_rmse_deg"] == pytest.approx(2.0, rel=1e-9)
    assert m["nees_mean"] == pytest.approx((0.25 / 0.01 + cases.OFFSET_ANGLE**2 / 1e-4) / 6.0, rel=1e-9)
    assert m["compared_states"] == 12 and m["compared_coverage"] == 1.0 and "ate_note" not in m


def test_against_truth_needs_covariances_for_nees():
    truth = cases.scored_truth()
    m = report.against_truth(truth, cases.offset_estimate(truth, with_cov=False))
    assert math.isnan(m["nees_mean"]) and m["ate_rmse_m"] == pytest.approx(0.5)


def test_states_between_truth_samples_are_compared_with_the_truth_interpolated_to_them():
    """An estimate whose states fall between the truth's samples (an EKF's at measurement times)
    is compared at every one of them, the truth interpolated (linearly, geodesically): the known
    0.5 m / 2 deg error is found to the interpolation's error, not missed for want of equal stamps."""
    dense = simulate(profile="gentle", duration=3.0, seed=0, imu_rate=cases.IMU_RATE, pose_rate=None).truth
    truth = dense.subset(slice(0, None, 5))  # 20 Hz
    between = dense.subset(np.flatnonzero(np.arange(len(dense)) % 5 == 2)[:-1])  # none on a 20 Hz sample
    m = report.against_truth(truth, cases.offset_estimate(between, with_cov=False))
    assert m["compared_states"] == len(between) > 50
    assert m["ate_rmse_m"] == pytest.approx(0.5, abs=1e-3) and m["rot_rmse_deg"] == pytest.approx(2.0, abs=0.01)


def test_an_ate_over_too_few_states_is_no_number_and_says_why():
    """Dead reckoning through an EKF that reports only its first and last states: the first on a
    truth sample (error 0), the last between two, 31 m off. The figures are NaN (null in
    metrics.json) and the note gives the count, the span and the error at those states -- not an
    ATE from the one state that lies on a truth sample."""
    truth = cases.scored_truth()
    t = np.array([truth.t[0], 0.5 * (truth.t[-2] + truth.t[-1])])
    est = Trajectory(t, truth.interpolate(t)[0])
    est = Trajectory(t, est.states.replace(r=est.states.r + [[0.0, 0.0, 0.0], [31.0, 0.0, 0.0]]))
    m = report.against_truth(truth, est)
    assert m["compared_states"] == 2
    assert all(math.isnan(m[k]) for k in ("ate_rmse_m", "rot_rmse_deg", "nees_mean"))
    assert m["ate_note"].startswith("not scored against the truth: 2 of the estimate's 2 states lie in the truth's "
                                    "span")
    assert "position errors there up to 31 m" in m["ate_note"] and "at least 10 states over 50%" in m["ate_note"]


def test_an_ate_over_part_of_the_run_says_so_and_below_half_is_no_number():
    """A truth that ends before the estimate: over 60% of its span the figures stand with a note,
    over 30% they are not scored."""
    truth = cases.scored_data().truth
    est = cases.offset_estimate(truth, with_cov=False)
    for share, scored in ((0.6, True), (0.3, False)):
        short = truth.subset(truth.t <= truth.t[0] + share * (truth.t[-1] - truth.t[0]))
        m = report.against_truth(short, est)
        assert m["compared_coverage"] == pytest.approx(share, abs=0.03)
        assert (m["ate_rmse_m"] == pytest.approx(0.5)) if scored else math.isnan(m["ate_rmse_m"])
        assert m["ate_note"].startswith("scored over part of the run only" if scored else "not scored")


def test_states_inside_a_gap_of_the_truth_are_not_compared():
    """The truth across a hole of half a second is not interpolated: a state inside it would be
    scored against a straight line the motion never took."""
    truth = cases.scored_data().truth
    holed = truth.subset((truth.t < 0.3) | (truth.t > 0.8))
    between = truth.subset(slice(0, -1))
    between = Trajectory(between.t + 0.004, between.states)  # 4 ms after each 100 Hz sample
    m = report.against_truth(holed, cases.offset_estimate(between, with_cov=False))
    assert m["compared_states"] == np.count_nonzero((between.t < 0.29) | (between.t > 0.81)) == len(holed) - 2
    assert m["ate_rmse_m"] == pytest.approx(0.5, abs=0.01)


def test_position_rmse_interpolates_and_ignores_fixes_outside_the_estimate():
    truth = cases.scored_truth()
    est = Trajectory(truth.t, truth.states.replace(r=np.outer(truth.t, [1.0, 0.0, 0.0])))
    t = np.array([truth.t[0] - 1.0, 0.5 * (truth.t[1] + truth.t[2]), truth.t[3], truth.t[-1] + 1.0])
    position = np.outer(t, [1.0, 0.0, 0.0]) + [[0, 0, 0], [0, 3.0, 0], [0, 0, 4.0], [0, 0, 0]]
    fixes = PositionMeasurements(t, position, np.eye(3))
    # inside: errors 3 and 4 (the estimate interpolates linearly in between), outside: ignored
    assert report.position_rmse(fixes, est) == pytest.approx(math.sqrt((9 + 16) / 2), rel=1e-12)
    t_in, distance = report.position_errors(fixes, est)
    np.testing.assert_array_equal(t_in, t[1:3])
    np.testing.assert_allclose(distance, [3.0, 4.0], rtol=1e-12)
    assert math.isnan(report.position_rmse(None, est))
    assert math.isnan(report.position_rmse(fixes.subset([0, 3]), est))


def test_score_reports_the_heldout_rmse_and_the_fit_residual_apart():
    """Held-out fixes give the accuracy; the used ones only a fit residual, under its own name
    (no figure mixes the two, as the distance to every fix did)."""
    data = simulate(profile="gentle", duration=1.0, seed=0, imu_rate=cases.IMU_RATE, pose_rate=None,
                    position_rate=10.0, position_sigma=0.5)
    fixes = data.sensor("position").data
    used, held = fixes.subset(slice(0, None, 2)), fixes.subset(slice(1, None, 2))
    data = data.with_sensor("position", data=used, heldout=held)
    m = report.score(data, data.truth)  # the truth itself as the estimate: errors = GPS noise
    assert set(m) >= {"ate_rmse_m", "rot_rmse_deg", "nees_mean", "gps_fit_residual_m", "gps_heldout_rmse_m"}
    assert "gps_rmse_m" not in m
    assert m["ate_rmse_m"] == 0.0
    for key, fixes in (("gps_fit_residual_m", used), ("gps_heldout_rmse_m", held)):
        noise = np.sqrt(np.mean(np.sum((cases.truth_at(data, fixes.t).r - fixes.position) ** 2, axis=1)))
        assert m[key] == pytest.approx(noise, rel=1e-9)
    assert 0.3 < m["gps_heldout_rmse_m"] < 2.0  # 3-D noise of 0.5 m per axis: ~0.87 m expected


def test_the_fixes_of_a_calibrated_sensor_are_scored_at_its_estimated_offset_and_lever_arm():
    """Fixes stamped 0.2 s late from an antenna 1 m ahead, scored against the truth: at the stamps
    and mounting given they are metres off; at a calibration that has the delay and the lever arm
    (as the estimate reports them) exactly on, held-out and used alike."""
    from factors.calibration import CalibrationPrior, CalibrationSet

    data = simulate(profile="gentle", duration=4.0, seed=0, imu_rate=cases.IMU_RATE, pose_rate=None,
                    position_rate=10.0, position_sigma=0.5)
    x = cases.truth_at(data, data.sensor("position").data.t)
    lever = np.array([1.0, 0.0, 0.0])
    t = data.sensor("position").data.t
    fixes = PositionMeasurements(t + 0.2, x.r + x.C @ lever, np.eye(3))
    data = data.with_sensor("position", data=fixes.subset(slice(0, None, 2)), heldout=fixes.subset(slice(1, None, 2)))
    given = report.score(data, data.truth)
    prior = CalibrationPrior(("time_offset", "lever_arm"))
    found = CalibrationSet.given(["position"], [None], [prior])
    found = replace(found, values=(replace(found.values[0], time_offset=-0.2, p=lever),))
    calibrated = report.score(data, data.truth, found)
    assert given["gps_fit_residual_m"] > 0.3 and given["gps_heldout_rmse_m"] > 0.3
    assert calibrated["gps_fit_residual_m"] < 1e-2 and calibrated["gps_heldout_rmse_m"] < 1e-2


def test_interpolation_is_the_yardstick_and_drifting_fixes_favour_it():
    """Interpolating the used fixes at the held-out times: with white fix errors the truth itself
    beats it; with errors that drift slowly (correlation 0.98 from fix to fix, 0.92 over the used
    fixes' spacing) interpolation beats even the truth, and the residuals at consecutive used fixes
    say so (their correlation near 0.92, against near 0 for white errors)."""
    for phi, truth_wins, rho in ((0.0, True, 0.0), (0.98, False, 0.98**4)):
        data, truth = fixes_with_noise(phi)
        baseline = report.interpolation_baseline(data)
        assert baseline["heldout_fixes"] == len(data.sensor("gps").heldout) - 3  # those after the last used fix
        assert (report.score(data, truth)["gps_heldout_rmse_m"] < baseline["gps_heldout_rmse_m"]) == truth_wins
        assert report.residual_correlation(data, truth) == pytest.approx(rho, abs=0.08)


def test_each_position_sensor_has_its_own_residual_correlation():
    """Two position sensors, one drifting (0.98 from fix to fix, 0.92 over the used fixes'
    spacing), one white: each sensor's correlation is its own, the pooled one between them."""
    drifting, truth = fixes_with_noise(0.98)
    white, _ = fixes_with_noise(0.0)
    data = replace(drifting, sensors=(drifting.sensor("gps"), replace(white.sensor("gps"), name="rtk")))
    own = {name: report.residual_correlation(data, truth, sensor=name) for name in ("gps", "rtk")}
    assert own["gps"] == pytest.approx(0.98 ** 4, abs=0.08) and own["rtk"] == pytest.approx(0.0, abs=0.08), own
    assert own["rtk"] + 0.1 < report.residual_correlation(data, truth) < own["gps"] - 0.1
    assert report.residual_correlation(data, truth, sensor="wheels") is None


def test_a_run_s_estimate_is_carried_to_fixes_between_its_keyframes_through_the_imu():
    """Fixes between keyframes 0.5 s apart, exactly on the truth: the truth's own states at the
    keyframes, carried to each fix through the IMU (the dataset given, as a run's metrics do),
    miss it by the IMU noise of half a second (0.3 mm RMS here), where the keyframes interpolated
    linearly cut the figure-eight's curves by 8 mm RMS."""
    data = simulate("gentle", duration=10.0, seed=3, imu_rate=100.0, pose_rate=None, position_rate=20.0)
    truth = data.truth
    keyframes = truth.subset(slice(0, None, 50))  # 2 Hz
    fixes = data.sensor("position").data
    on_truth = replace(fixes, position=truth.interpolate(fixes.t)[0].r)
    _, carried = report.position_residuals(on_truth, keyframes, data)
    _, interpolated = report.position_residuals(on_truth, keyframes)
    assert len(carried) == len(interpolated) == len(fixes)
    assert report.rms_distance(carried) < 1e-3 < 5e-3 < report.rms_distance(interpolated)


def test_the_ekf_s_held_out_fixes_are_scored_from_its_own_state_at_their_times():
    """Held-out positions between the 10-Hz keyframes the EKF keeps: its held-out RMS is that of
    the residuals its loop predicted from its state at each fix's time (the updates up to it
    included), not of its keyframe state carried there; the fit residual is unchanged."""
    from smoother.ekf.filter import run_ekf
    from smoother.model.timeline import keyframe_times

    data = simulate("gentle", duration=10.0, seed=4, imu_rate=100.0, pose_rate=None, position_rate=50.0,
                    position_sigma=0.05)
    fixes = data.sensor("position").data
    used = np.arange(len(fixes.t)) % 2 == 0
    data = data.with_sensor("position", data=fixes.subset(used), heldout=fixes.subset(~used))
    result = run_ekf(data, kept_at=keyframe_times(data), progress=False)
    own = report.score(data, result.trajectory, predictions=result.heldout)
    carried = report.score(data, result.trajectory)
    assert own["gps_heldout_rmse_m"] == pytest.approx(report.rms_distance(result.heldout["position"].e), rel=1e-12)
    assert own["gps_fit_residual_m"] == carried["gps_fit_residual_m"]
    assert abs(own["gps_heldout_rmse_m"] - carried["gps_heldout_rmse_m"]) > 1e-4
