"""Figures presented as normal that are not: a verdict on less than one degree of freedom (a band
of 0 to 5e-30), an EKF whose gate rejected every measurement (dead reckoning shown as fused), and
advice fitted to a few squares of noise. One rule forms a verdict (``verdicts.MIN_DOF``,
``judgeable``), everywhere one is formed or printed; the gate's rejections make the EKF
doubtful; the misfit causes need that rule, significance and a correction a rig can write."""
from __future__ import annotations

import warnings

import numpy as np
import pytest

from datasets.simulate import simulate
from datasets.simulated_sensors import SensorSpec
from factors.imu import ImuNoise
from smoother.diagnosis import verdicts as v
from smoother.diagnosis.misfit_causes import SMALLEST, Cause, candidate_causes, hint


@pytest.mark.parametrize("dof", [0.0007, 0.5, v.MIN_DOF * 0.999])
def test_a_verdict_on_too_few_degrees_of_freedom_has_no_band_and_counts_for_nothing(dof):
    """The GNSS-only rig's IMU: 1.21 per dof on 0.0007 dof was printed "OUT OF BAND" of 0-4.9e-30;
    now no band and no ``ok``, printed as too few to judge, neither far above nor far off, not
    counted by ``overall``'s band nor by a warning or the doubt mark, whatever its figure."""
    for figure in (1.21, 1e6):
        c = v.verdict(figure * dof, dof, 200, "residual")
        assert c["band"] is None and c["ok"] is None and not v.judgeable(c)
        assert not v.far_above(c) and not v.far_off(c) and not v.out_of_band(c)
        by = {"batch": {"imu": c}}
        [line] = v.consistency_lines(by)
        assert v.TOO_FEW_DOF in line and "OUT OF BAND" not in line and "e-" not in line.split("(")[-1], line
        assert v.consistency_warnings(by) == []


def test_from_one_degree_of_freedom_a_verdict_is_formed():
    c = v.verdict(50.0 * v.MIN_DOF, v.MIN_DOF, 3, "residual")
    assert v.judgeable(c) and c["ok"] is False and v.far_above(c)
    assert "OUT OF BAND" in v.shown(c) and v.TOO_FEW_DOF not in v.shown(c)


def test_the_doubt_mark_ignores_a_verdict_that_was_not_formed():
    from types import SimpleNamespace

    from smoother.pipeline import judged

    estimates = {"batch": SimpleNamespace(details={}, calibration=None)}
    few = v.verdict(1e6 * 0.01, 0.01, 100, "residual")
    fine = v.verdict(100.0, 100.0, 100, "residual")
    judged(estimates, {"batch": {"imu": few, "gnss": fine}})
    assert "doubtful" not in estimates["batch"].details


def test_held_out_predictions_made_without_a_drifting_sensor_s_used_errors_judge_no_model():
    """The fixed-lag smoother's where it cannot give them (GTSAM's windows, an estimated
    calibration): far below their band, because its estimate follows the drift it did not model
    in the prediction -- not a sigma to blame, and no doubt; the same figure given the used
    errors is one."""
    from types import SimpleNamespace

    from smoother.pipeline import judged

    low = {**v.verdict(0.2 * 300.0, 300.0, 100, "heldout"), "sigma_factor": 0.2, "state_share": 0.3}
    for given, doubtful in ((False, False), (True, True)):
        record = {**low, "given_used_errors": True} if given else {**low, "not_given_used_errors": True}
        estimates = {"fixed-lag": SimpleNamespace(details={}, calibration=None)}
        judged(estimates, {"fixed-lag": {}}, {"fixed-lag": {"gnss": record}})
        assert ("doubtful" in estimates["fixed-lag"].details) == doubtful
        text = v.shown(record)
        assert ("not judged -- the sensor's errors drift and this estimator predicts them without the used ones' "
                "errors" in text) != given, text


def test_a_drifting_sensor_s_warning_names_its_correlation_time_beside_its_sigma():
    """Too long a correlation time takes consecutive errors for more alike than they are, and their
    innovations look too large; too short, too small: named beside the sigma, not the sigma (or the
    IMU) alone."""
    high = v.verdict(50.0 * 300.0, 300.0, 100, "residual")
    low = v.verdict(0.05 * 300.0, 300.0, 100, "residual")
    line = v.consistency_warnings({"batch": {"gnss": high}}, correlation_times={"gnss": 2000.0})[0]
    assert "check its sigma (too small), its correlation_time (2000 s: too long?)" in line
    line = v.consistency_warnings({"batch": {"gnss": low}}, correlation_times={"gnss": 3.0})[0]
    assert "too large by its errors or its correlation_time (3 s) too short" in line
    assert "correlation_time" not in v.consistency_warnings({"batch": {"gnss": high}})[0]


def test_a_gnss_only_rig_on_model_exact_data_prints_no_band_from_a_fraction_of_a_degree_of_freedom():
    """Fixes that determine the trajectory leave the IMU factors a fraction of a degree of
    freedom: their verdict is said to be too few to judge, and nothing is warned of or advised."""
    from smoother.diagnosis.misfit_causes import hints
    from smoother.pipeline import judged, run_estimators, verdicts_by_estimator

    exact = ImuNoise(acc=1e-6, gyro=1e-8, acc_bias=1e-9, gyro_bias=1e-12)
    data = simulate("gentle", duration=5.0, seed=0, pose_rate=0, noise=exact,
                    sensors=[SensorSpec("gnss", "gnss", 5.0, 0.5)])
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        estimates = run_estimators(data, ["ekf", "batch"])
        consistency = verdicts_by_estimator(data, estimates)
    judged(estimates, consistency)
    imu = consistency["batch"]["imu"]
    assert imu["dof"] < v.MIN_DOF and not v.judgeable(imu), imu
    assert any(v.TOO_FEW_DOF in line for line in v.consistency_lines(consistency))
    assert not any("e-" in line and "OUT OF BAND" in line for line in v.consistency_lines(consistency))
    assert v.consistency_warnings(consistency) == [] and hints(data, estimates, consistency) == {}
    assert not any("doubtful" in e.details for e in estimates.values())


@pytest.fixture(scope="module")
def gated():
    """The gentle case's EKF with a gate at 1e-300 (everything rejected) and at 0.999 (a few)."""
    from smoother.pipeline import RunOptions, run_estimators, verdicts_by_estimator

    data = simulate("gentle", duration=5.0, seed=0, outlier_fraction=0.05)
    out = {}
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        for gate in (1e-300, 0.999):
            estimates = run_estimators(data, ["ekf"], RunOptions(ekf_gate=gate))
            out[gate] = estimates, verdicts_by_estimator(data, estimates)
    return out


def test_an_ekf_that_used_no_measurement_says_it_is_dead_reckoning_and_is_doubtful(gated):
    """ATE 14.5 m with no sensor line, no (?) and no warning was the EKF's dead reckoning shown
    as fused: now the sensor has a line saying none was used, and the EKF is doubtful, saying so."""
    from smoother.pipeline import judged

    estimates, consistency = gated[1e-300]
    pose = consistency["ekf"]["pose"]
    assert pose["per_dof"] is None and pose["measurements"] == 0 and pose["rejected"] > 0
    [line] = [line for line in v.consistency_lines(consistency) if line.startswith("sensor pose")]
    assert f"none used ({pose['rejected']} rejected by the gate)" in line, line
    judged(estimates, consistency)
    why = estimates["ekf"].details["doubtful"]
    assert f"rejected {pose['rejected']} of {pose['rejected']} pose measurements" in why and "dead reckoning" in why


def test_an_ekf_that_rejected_a_few_outliers_is_not_doubtful_and_one_that_rejected_most_of_a_sensor_is(gated):
    from smoother.pipeline import judged

    estimates, consistency = gated[0.999]
    pose = consistency["ekf"]["pose"]
    assert 0 < pose["rejected"] < v.MOST_REJECTED * pose["measurements"], pose
    assert v.rejections(consistency["ekf"]) is None
    judged(estimates, consistency)
    assert "doubtful" not in estimates["ekf"].details
    most = {"pose": {**pose, "measurements": 40, "rejected": 60}, "gnss": {**pose, "rejected": 0}}
    said = v.rejections(most)
    assert said.startswith("its gate rejected 60 of 100 pose measurements: there it shows mostly the IMU's dead "
                           "reckoning"), said


def test_the_fleet_table_shows_a_verdict_not_formed_and_one_of_no_update():
    from smoother.commands.fleet import format_table

    few = v.verdict(1.21 * 0.0007, 0.0007, 200, "residual")
    none = {**v.verdict(0.0, 0.0, 0, "nis"), "rejected": 101}
    table = format_table([{"recording": "r", "failure": None, "estimators": {
        "batch": {"fit": v.verdict(10.0, 10.0, 5, "residual"), "sensors": {"imu": few}},
        "ekf": {"sensors": {"pose": none}}}}])
    assert "imu 1.21 few-dof" in table and "pose none" in table and v.TOO_FEW_DOF in table, table


def _cause(value, sigma, share=0.9, judged=True, calibration="lever_arm") -> Cause:
    return Cause(calibration, np.atleast_1d(np.asarray(value, float)), np.atleast_1d(np.asarray(sigma, float)),
                 share, judged)


@pytest.mark.parametrize("calibration, tiny", [("lever_arm", [1e-17, 0, 0]), ("rotation", [1e-9, 0, 0]),
                                               ("time_offset", 1e-8), ("scale", 1e-7)])
def test_a_correction_below_what_a_rig_can_write_is_no_advice(calibration, tiny):
    """A 2-sample IMU file advised ``estimate = ["lever_arm"]`` for a 1e-17 m lever arm: at 1e4
    sigmas, but below the finest prior a rig can write (``datasets.ranges``: 1e-4 m, 1e-5 rad,
    1e-5 s, 1e-5 of scale) it is not advice; the same significance at the floor is."""
    sigma = np.abs(np.asarray(tiny, float)) * 1e-4 + 1e-30
    assert not _cause(tiny, sigma, calibration=calibration).suggested
    assert hint([_cause(tiny, sigma, calibration=calibration)]) is None
    floor = np.where(np.asarray(tiny, float) != 0, SMALLEST[calibration] * 2, 0.0)
    assert _cause(floor, sigma, calibration=calibration).suggested


def test_a_cause_fitted_on_too_few_degrees_of_freedom_is_no_advice():
    """The fit's variance from fewer than ``MIN_DOF`` degrees of freedom left: ``judged`` False,
    nothing suggested however significant; from more, judged."""
    X = {"lever_arm": np.zeros((2, 3, 3))}
    value, cov = np.array([0.5, 0.0, 0.0]), np.eye(3) * 1e-6
    after = np.full((2, 3), 1e-3)
    few = candidate_causes(X, value, cov, np.eye(3), value, after, dof=3.0 + v.MIN_DOF * 0.5)
    assert not few[0].judged and not few[0].suggested
    enough = candidate_causes(X, value, cov, np.eye(3), value, after, dof=3.0 + v.MIN_DOF)
    assert enough[0].judged and enough[0].suggested
