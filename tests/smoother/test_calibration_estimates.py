"""The batch smoother's calibration of simulated rigs with known errors: each error recovered
within 3 posterior sigma, the calibration's NEES in its chi-square band over 20 seeds, what the
data cannot fix left at its prior and said so, a right calibration left (nearly) alone; on
KITTI's real GPS, whose residuals are far out of band, the sigmas said to be understated."""
from __future__ import annotations

import functools
import warnings
from dataclasses import replace

import numpy as np
import pytest
from miscalibrated_rig import PITCHED, miscalibrated_rig

from datasets.simulate import simulate
from datasets.simulated_sensors import SensorSpec
from datasets.trajectories import Sinusoids, sinusoid_profile
from factors import imu, so3
from factors.calibration import CalibrationPrior
from smoother.batch.solve import solve_batch
from smoother.diagnosis.calibration_report import UNOBSERVED_RATIO, calibration_records
from smoother.model.problem import build_problem
from smoother.stats import chi2_quantile

#: Straight along the IMU's x axis with a varying speed, never turning: a lever arm and a speed
#: sensor's roll about its own axis are not observable on it.
STRAIGHT = sinusoid_profile("straight", "along x at 1.5-2.5 m/s, level, never turning",
                            (Sinusoids(slope=2.0, terms=((1.0, 0.5, 0.0),)), Sinusoids(), Sinusoids()),
                            (Sinusoids(), Sinusoids(), Sinusoids()))


def _solve(dataset):
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        result = solve_batch(build_problem(dataset))
    records, against = calibration_records(result.calibration, result.calibration_cov)
    return result, records, against


#: The true errors in the calibration's coordinates about the values written: wheels' rotation
#: (log(R_true R_given^T)) and scale; the fixes' time offset (taken 0.1 s before their stamps) and
#: the antenna's lever arm.
TRUE_ROTATION = so3.log(PITCHED[:3, :3])


def test_batch_recovers_a_delay_a_mounting_a_lever_arm_and_a_scale_within_3_sigma():
    data = miscalibrated_rig(1)
    data = data.with_sensor("wheels", calibrate=CalibrationPrior(("rotation", "scale")))
    data = data.with_sensor("gnss", calibrate=CalibrationPrior(("time_offset", "lever_arm")))
    result, records, against = _solve(data)
    wheels, gnss = records["wheels"], records["gnss"]
    rotation = np.array(against["wheels"]["rotation_change_rad"])
    # pitch and yaw of the speed sensor; its roll about its own axis is weakly observable here
    assert np.all(np.abs(rotation[1:] - TRUE_ROTATION[1:]) < 3 * np.array(wheels["rotation_sigma_rad"])[1:]), records
    assert abs(wheels["scale"] - 0.99) < 3 * wheels["scale_sigma"] and wheels["scale_sigma"] < 0.01
    assert abs(gnss["time_offset_s"] + 0.1) < 3 * gnss["time_offset_sigma_s"] and gnss["time_offset_sigma_s"] < 0.05
    assert np.all(np.abs(np.array(gnss["lever_arm_m"]) - [0, 0, 0.5]) < 3 * np.array(gnss["lever_arm_sigma_m"]))
    assert np.array(gnss["lever_arm_sigma_m"]).max() < 0.1
    assert set(wheels) == {"T_BS", "rotation_sigma_rad", "scale", "scale_sigma"}
    assert set(gnss) == {"time_offset_s", "time_offset_sigma_s", "T_BS", "lever_arm_m", "lever_arm_sigma_m"}


def test_calibration_nees_over_20_seeds_is_in_its_chi_square_band():
    """The wheels' pitch, yaw and scale and the fixes' delay (4 dof per seed): the sum of their
    normalised squared errors over 20 seeds lies in the 99 % chi-square band of 80 dof."""
    total, dof = 0.0, 0
    for seed in range(20):
        data = miscalibrated_rig(100 + seed, duration=15.0)
        data = data.with_sensor("wheels", calibrate=CalibrationPrior(("rotation", "scale")))
        data = data.with_sensor("gnss", calibrate=CalibrationPrior(("time_offset",)))
        result, _, _ = _solve(data)
        wheels, gnss = result.calibration.values
        P_w, P_g = result.calibration_cov
        error = np.r_[so3.boxminus(wheels.R, PITCHED[:3, :3]), wheels.scale - 0.99]
        keep = [1, 2, 3]  # pitch, yaw, scale (the roll about the sensor's axis is barely observed)
        total += float(error[keep] @ np.linalg.solve(P_w[np.ix_(keep, keep)], error[keep]))
        total += float((gnss.time_offset + 0.1) ** 2 / P_g[0, 0])
        dof += 4
    assert chi2_quantile(0.005, dof) <= total <= chi2_quantile(0.995, dof), (total, dof)


def test_the_fixes_delay_and_lever_arm_together_are_consistent_over_20_seeds():
    """The fixes' delay and the antenna's lever arm estimated together (4 dof per seed, strongly
    correlated: a lever arm along the way looks like a delay). The antenna sits 2.5 prior sigmas
    from the prior's mean, so the estimate is pulled towards it, by ``-P Lambda_0 (c - c_0)`` on
    average (``P`` its covariance, ``Lambda_0`` the prior's information; ~1 sigma on the height
    here): once that pull is taken off, the errors' normalised squares over 20 seeds, with the
    estimate's covariance over the noise ``P - P Lambda_0 P``, lie in the 99 % chi-square band of
    80 dof."""
    prior = CalibrationPrior(("time_offset", "lever_arm"))
    truth, mean = np.array([-0.1, 0.0, 0.0, 0.5]), np.zeros(4)
    information = np.diag(1.0 / prior.sigmas ** 2)
    total, dof = 0.0, 0
    for seed in range(20):
        data = miscalibrated_rig(100 + seed, duration=15.0)
        data = data.with_sensor("wheels", calibrate=CalibrationPrior(("rotation", "scale")))
        result, _, _ = _solve(data.with_sensor("gnss", calibrate=prior))
        gnss, P = result.calibration.values[1], result.calibration_cov[1]
        pull = -P @ information @ (truth - mean)
        error = np.r_[gnss.time_offset, gnss.p] - truth - pull
        total += float(error @ np.linalg.solve(P - P @ information @ P, error))
        dof += 4
    assert chi2_quantile(0.005, dof) <= total <= chi2_quantile(0.995, dof), (total, dof)


def test_what_the_data_cannot_fix_stays_at_its_prior_and_is_reported():
    """Driving straight without turning: the antenna's lever arm along the way and the speed
    sensor's roll about its own axis are not observable; standing still, no time offset is."""
    data = miscalibrated_rig(2, duration=20.0, profile=STRAIGHT, initial_sigma=(5.0, 0.1, 0.01))
    data = data.with_sensor("wheels", data=replace(data.sensor("wheels").data, T_BS=PITCHED),
                            calibrate=CalibrationPrior(("rotation",)))
    data = data.with_sensor("gnss", calibrate=CalibrationPrior(("lever_arm",)))
    result, records, against = _solve(data)
    assert "rotation x" in against["wheels"]["unobserved"], against
    assert not {"rotation y", "rotation z"} & set(against["wheels"]["unobserved"]), against
    assert {"lever_arm x", "lever_arm y", "lever_arm z"} <= set(against["gnss"]["unobserved"]), against
    assert np.allclose(against["gnss"]["lever_arm_change_m"], 0.0, atol=0.1 * 0.2)

    still = simulate("static", duration=10.0, seed=3, pose_rate=0, sensors=(SensorSpec("gnss", "gnss", 5.0, 0.2),))
    still = still.with_sensor("gnss", calibrate=CalibrationPrior(("time_offset",)))
    _, records, against = _solve(still)
    assert against["gnss"]["unobserved"] == ["time_offset"]
    assert against["gnss"]["sigma_ratio"]["time_offset"] >= UNOBSERVED_RATIO
    assert abs(records["gnss"]["time_offset_s"]) < 0.01


def test_calibrating_a_wheel_time_offset_that_is_right_changes_the_trajectory_by_less_than_a_tenth_sigma():
    """Two minutes with GNSS and wheels whose values are right: estimating the wheels' time offset
    moves the trajectory by less than 0.1 of its sigma (RMS over the keyframes, each position,
    velocity and attitude component). A calibration that carries information of its own -- a
    mounting rotation, through which the wheels tell the attitude -- moves the states it was
    correlated with by up to about their sigma when freed (``P_xc P_cc^-1`` times its error), as
    any least-squares fit does; that is not tested against 0.1."""
    data = simulate("gentle", duration=120.0, seed=4, pose_rate=0,
                    sensors=(SensorSpec("wheels", "velocity", 10.0, 0.05, PITCHED),
                             SensorSpec("gnss", "gnss", 5.0, 0.2)))
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        given = solve_batch(build_problem(data))
    calibrated, _, _ = _solve(data.with_sensor("wheels", calibrate=CalibrationPrior(("time_offset",))))
    sigma = np.sqrt(np.diagonal(given.trajectory.cov, axis1=1, axis2=2))
    moved = imu.boxminus(calibrated.trajectory.states, given.trajectory.states) / sigma
    assert np.sqrt(np.mean(moved[:, :9] ** 2, axis=0)).max() < 0.1


@pytest.mark.parametrize("parts, kind, message", [
    (("rotation",), "gnss", "cannot estimate rotation"),
    (("scale",), "gnss", "cannot estimate scale"),
])
def test_a_part_the_kind_cannot_estimate_is_refused_naming_the_sensor(parts, kind, message):
    from factors.errors import InputError

    data = simulate("gentle", duration=3.0, seed=0, pose_rate=0, sensors=(SensorSpec("antenna", kind, 5.0, 0.2),))
    with pytest.raises(InputError, match=f"sensor 'antenna' .*{message}"):
        build_problem(data.with_sensor("antenna", calibrate=CalibrationPrior(parts)))


@pytest.mark.parametrize("estimator", ["ekf", "fixed-lag"])
def test_the_ekf_and_the_fixed_lag_smoother_estimate_the_batch_calibration_within_2_sigma(estimator):
    """The EKF with the calibrations as augmented states, the fixed-lag smoother with them as the
    window's border: every error recovered within 3 of the estimator's sigmas, and each value
    within 2 of them of the batch smoother's."""
    from smoother.pipeline import run_estimators

    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        found = run_estimators(_calibrating_rig(), [estimator])[estimator].details
    batch = _batch_details()
    w, g = found["calibration"]["wheels"], found["calibration"]["gnss"]
    rotation = np.array(found["calibration_against_prior"]["wheels"]["rotation_change_rad"])
    assert np.all(np.abs(rotation[1:] - TRUE_ROTATION[1:]) < 3 * np.array(w["rotation_sigma_rad"])[1:])
    assert abs(w["scale"] - 0.99) < 3 * w["scale_sigma"]
    assert abs(g["time_offset_s"] + 0.1) < 3 * g["time_offset_sigma_s"]
    assert np.all(np.abs(np.array(g["lever_arm_m"]) - [0, 0, 0.5]) < 3 * np.array(g["lever_arm_sigma_m"]))
    b_rotation = np.array(batch["calibration_against_prior"]["wheels"]["rotation_change_rad"])
    assert np.all(np.abs(rotation - b_rotation) < 2 * np.array(w["rotation_sigma_rad"]))
    assert abs(w["scale"] - batch["calibration"]["wheels"]["scale"]) < 2 * w["scale_sigma"]
    assert abs(g["time_offset_s"] - batch["calibration"]["gnss"]["time_offset_s"]) < 2 * g["time_offset_sigma_s"]
    assert np.all(np.abs(np.subtract(g["lever_arm_m"], batch["calibration"]["gnss"]["lever_arm_m"]))
                  < 2 * np.array(g["lever_arm_sigma_m"]))
    assert set(w) == set(batch["calibration"]["wheels"]) and set(g) == set(batch["calibration"]["gnss"])


@functools.cache
def _calibrating_rig():
    """:func:`miscalibrated_rig` (seed 1, 30 s) with the wheels' rotation and scale and the fixes'
    delay and lever arm to estimate."""
    data = miscalibrated_rig(1, duration=30.0)
    data = data.with_sensor("wheels", calibrate=CalibrationPrior(("rotation", "scale")))
    return data.with_sensor("gnss", calibrate=CalibrationPrior(("time_offset", "lever_arm")))


@functools.cache
def _batch_details() -> dict:
    """The batch smoother's details on :func:`_calibrating_rig` (run once)."""
    from smoother.pipeline import run_estimators

    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        return run_estimators(_calibrating_rig(), ["batch"])["batch"].details


@pytest.mark.parametrize("every", [10, 1])
def test_kitti_s_gps_calibrated_with_its_sigma_as_given_is_said_to_be_overconfident(every):
    """GTSAM's KITTI example data, every 10th fix used or all of them, its GPS's time offset and
    lever arm estimated: the OXTS unit gives its fixes at the IMU, in its own clock (the truth:
    zero), but the fixes' residuals are far out of band of the example's 0.26-m sigma (~20 per
    dof with every 10th fix) or, at 1 Hz, 0.9 alike from fix to fix, and the calibration leans on
    them: it lands over 3 of its sigmas from zero, within 3 of the sigmas its residuals give it,
    and the printed line says by how much they are understated."""
    from datasets import kitti
    from smoother.diagnosis.calibration_report import calibration_lines
    from smoother.evaluation import scoring as report
    from smoother.pipeline import RunOptions, estimate_each, verdicts_by_estimator

    gps = kitti.GPS_SENSOR
    data = kitti.load_kitti(gps_every=every).with_sensor(gps, calibrate=CalibrationPrior(("time_offset", "lever_arm")))
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        estimates = dict(estimate_each(data, ["batch"], RunOptions()))
    batch = estimates["batch"]
    verdict = verdicts_by_estimator(data, estimates)["batch"][gps]
    rho = report.residual_correlation(data, batch.trajectory, batch.calibration, gps)
    record = batch.details["calibration"][gps]
    value = np.array([record["time_offset_s"], *record["lever_arm_m"][:2]])
    sigma = np.array([record["time_offset_sigma_s"], *record["lever_arm_sigma_m"][:2]])
    assert not verdict["ok"], verdict
    correlated = np.sqrt((1 + rho) / (1 - rho))
    factor = np.sqrt(verdict["per_dof"]) * (correlated if correlated >= 1.5 else 1.0)
    assert (rho > 0.8) == (every == 1), rho
    assert factor > 3.0 and np.max(np.abs(value) / sigma) > 3.0, (value, sigma, factor)
    assert np.all(np.abs(value) / (factor * sigma) < 3.0), (value, sigma, factor)
    line, = calibration_lines(batch.details["calibration"], batch.details["calibration_against_prior"], {gps: verdict},
                              {gps: rho})
    assert f"they would be {'about ' if every == 1 else ''}{factor:.2g}x these" in line, line
    assert (f"lag-one correlation is {rho:.2f}" in line) == (every == 1), line


def test_a_calibration_line_says_what_its_sensor_s_residuals_say_of_its_sigmas():
    """Nothing while the residuals fit as far as a warning goes (in band, or out of it by less
    than 2x) and their lag-one correlation puts less than 1.5x on the sigmas (rho < 0.385);
    4 per dof: 2x, and the warnings to follow; 0.2 per dof: 0.45x; the EKF's innovations at 4
    per dof: at least about 2x; 0.8 alike from fix to fix: about 3x (sqrt(1.8 / 0.2)), and fixes
    further apart."""
    from smoother.diagnosis.calibration_report import calibration_lines

    records = {"gnss": {"time_offset_s": 0.1, "time_offset_sigma_s": 0.01}}
    fits = {"per_dof": 1.0, "band": [0.8, 1.2], "ok": True, "statistic": "residual"}

    def line(verdict, rho=None):
        return calibration_lines(records, {}, {"gnss": verdict}, {"gnss": rho})[0]

    plain = "calibration gnss: time offset +0.1000 +- 0.0100 s"
    assert line(None) == line(fits, 0.35) == line({**fits, "per_dof": 1.6, "ok": False}) == plain
    assert line({**fits, "per_dof": 4.0, "ok": False}).endswith(
        "its residuals are 4 per dof (band 0.8-1.2), the sigmas take its noise as given: by its residuals they would "
        "be 2x these -- trust this calibration once they fit (the run's warnings say what to check)")
    assert "they would be 0.45x these" in line({**fits, "per_dof": 0.2, "ok": False})
    ekf = line({**fits, "per_dof": 4.0, "ok": False, "statistic": "nis"})
    assert "its innovations are 4 per dof" in ekf and "they would be at least about 2x these" in ekf, ekf
    correlated = line(fits, 0.8)
    assert "lag-one correlation is 0.80" in correlated and "they would be about 3x these if its errors drift as AR(1)" \
        in correlated, correlated
    assert "`every`" in correlated and "per dof" not in correlated
    assert "lag-one correlation is 0.40" in line(fits, 0.4)
    assert "about 6x these" in line({**fits, "per_dof": 4.0, "ok": False}, 0.8)


def test_a_calibrated_attitude_whose_errors_may_follow_the_imu_is_not_said_to_be_overstated_alone():
    """Residuals far below their band make the calibration's sigmas too large only where the
    sensor's errors are its own; read from the IMU's messages they may follow the IMU's, and then
    the sigmas are too small. Far above, the note is as before."""
    from smoother.diagnosis.calibration_report import calibration_lines

    records = {"ahrs": {"time_offset_s": 0.02, "time_offset_sigma_s": 0.0003}}
    low = {"per_dof": 0.133, "band": [0.93, 1.07], "ok": False, "statistic": "residual"}
    followers = {"ahrs": "it reads the IMU's own messages, bag:x.bag, topic /imu/data"}
    [line] = calibration_lines(records, {}, {"ahrs": low}, None, followers)
    assert ("by its residuals they would be 0.36x these, unless its errors follow the IMU's (it reads the IMU's own "
            "messages, bag:x.bag, topic /imu/data), which makes these too small instead -- trust") in line, line
    assert "unless" not in calibration_lines(records, {}, {"ahrs": low})[0]
    assert "unless" not in calibration_lines(records, {}, {"ahrs": {**low, "per_dof": 4.0}}, None, followers)[0]


def test_an_estimator_without_its_own_verdict_on_a_sensor_takes_the_batch_s_then_the_ekf_s_and_says_whose():
    from smoother.diagnosis.calibration_report import calibration_lines, verdicts_for

    mine, batch, ekf = ({"per_dof": x, "band": [0.8, 1.2], "ok": False, "statistic": s}
                        for x, s in ((4.0, "residual"), (9.0, "residual"), (16.0, "nis")))
    every = {"fixed-lag": {"wheel": mine}, "batch": {"gnss": batch}, "ekf": {"gnss": ekf, "ahrs": ekf}}
    got = verdicts_for("fixed-lag", every)
    assert got == {"wheel": mine, "gnss": {**batch, "by": "batch"}, "ahrs": {**ekf, "by": "ekf"}}
    assert verdicts_for("batch", every)["gnss"] is batch and "by" not in verdicts_for("ekf", every)["gnss"]
    records = {"gnss": {"time_offset_s": 0.1, "time_offset_sigma_s": 0.01}}
    assert "its residuals by the batch are 9 per dof" in calibration_lines(records, {}, got)[0]


def test_an_estimator_is_doubtful_by_another_s_verdict_only_on_a_sensor_it_calibrated_and_could_not_judge():
    """The fixed-lag smoother estimated the GNSS's calibration and judged only the wheel: the
    batch's verdict on the GNSS far above its band makes it doubtful, saying whose; the AHRS,
    which it did not calibrate, and the batch's own verdicts count for nothing here."""
    from types import SimpleNamespace

    from smoother.pipeline import judged

    def verdict(x, s="residual"):
        return {"per_dof": x, "band": [0.8, 1.2], "ok": 0.8 <= x <= 1.2, "statistic": s, "measurements": 100,
                "dof": 100.0}

    def estimate(calibrated):
        return SimpleNamespace(details={}, calibration=SimpleNamespace(names=calibrated) if calibrated else None)

    for gnss, doubtful in ((9.0, True), (1.0, False)):
        every = {"fixed-lag": {"wheel": verdict(1.0)}, "batch": {"gnss": verdict(gnss), "ahrs": verdict(9.0)}}
        estimates = {"fixed-lag": estimate(("gnss",)), "batch": estimate(())}
        judged(estimates, every)
        said = estimates["fixed-lag"].details.get("doubtful", "")
        assert ("its calibrated gnss, which it does not judge itself, is 9 per dof by the batch (expected 0.8-1.2)"
                in said) == doubtful, said
        assert "ahrs" not in said
