"""Fitted noise that stays honest (smoother/diagnosis/noise_honesty.py): a factor that explains a
model error is reported as that error and not applied."""
from __future__ import annotations

import numpy as np

from smoother.batch.variance_components import GroupFit, NoiseFit, NoiseGroup
from smoother.diagnosis.misfit_causes import Cause
from smoother.diagnosis.noise_honesty import (
    CONTRADICTION,
    CORRELATED,
    EXPLAINED,
    IMPLAUSIBLE_FACTOR,
    correlated,
    honest,
    to_analyse,
)


def _fit(*groups) -> NoiseFit:
    return NoiseFit([GroupFit(NoiseGroup(sensor, part, axes, ""), factor, 0.05 * factor, redundancy, None, "",
                              correlation=correlation, dof=dof)
                     for sensor, part, axes, factor, redundancy, correlation, dof in groups], 3, True)


def _errors(fit, **options):
    out, errors = honest(fit, **options)
    assert {e.group for e in errors} == {g.group.name for g in out.groups if not g.applied}
    return {e.group: e.cause for e in errors}


def test_a_plausible_fit_is_applied_as_it_is():
    fit = _fit(("imu", "gyro", None, 27.0, 80.0, 0.9, 7000), ("gps", "horizontal", (0, 1), 0.5, 50.0, 0.1, 92))
    out, errors = honest(fit)
    assert errors == [] and out is fit  # the IMU's chained residuals are not judged by their correlation


def test_a_factor_orders_of_magnitude_above_is_a_model_error():
    errors = _errors(_fit(("wheels", "forward", (0,), IMPLAUSIBLE_FACTOR * 1.5, 50.0, 0.0, 300)))
    assert "no sensor's error of its datasheet: a unit, a frame, a mounting" in errors["wheels.forward"]


def test_a_factor_orders_of_magnitude_below_is_refused_as_a_stated_value_or_dependent_data_not_a_misfit():
    """A wrong model only adds to the residuals: a factor far below 1 names the value the rig states
    and data that follow the IMU, not a unit or a mounting of the measurements."""
    errors = _errors(_fit(("ahrs", "tilt", (0, 1), 1.0 / (IMPLAUSIBLE_FACTOR * 1.5), 50.0, 0.0, 300)))
    cause = errors["ahrs.tilt"]
    assert "below any sensor's datasheet" in cause and "far too large" in cause, cause
    assert "mounting" not in cause and "time offset" not in cause, cause


def test_a_sensor_reading_the_imu_s_own_messages_is_never_shrunk_but_may_grow():
    """Its residuals say how closely it follows the IMU, not its error: x0.3 is refused (no
    implausible factor needed); x1.8 is a noise like any other's."""
    streams = {"ahrs": "bag:run.bag, topic /imu/data"}
    errors = _errors(_fit(("ahrs", "tilt", (0, 1), 0.3, 50.0, 0.0, 300)), imu_streams=streams)
    assert errors["ahrs.tilt"].startswith("it reads the IMU's own messages (bag:run.bag, topic /imu/data)"), errors
    assert "count the IMU's information twice" in errors["ahrs.tilt"]
    assert _errors(_fit(("ahrs", "tilt", (0, 1), 0.3, 50.0, 0.0, 300))) == {}  # a topic of its own: applied
    out, refused = honest(_fit(("ahrs", "tilt", (0, 1), 1.8, 50.0, 0.0, 300)), imu_streams=streams)
    assert refused == [] and out.groups[0].applied


def test_an_imu_factor_shrunk_beside_a_drifting_sensor_is_not_said_to_follow_the_drift():
    shrunk = ("imu", "gyro", None, 1.0 / (IMPLAUSIBLE_FACTOR * 2), 20.0, 0.9, 7000)
    grown = ("imu", "acc_bias", None, IMPLAUSIBLE_FACTOR * 1.6, 20.0, 0.9, 7000)
    gnss = ("gnss", "horizontal", (0, 1), 1.5, 80.0, CORRELATED + 0.1, 2400)
    errors = _errors(_fit(shrunk, grown, gnss), causes={"gnss": []})
    assert "follows the drift" not in errors["imu.gyro"], errors
    assert "follows the drift of gnss's errors" in errors["imu.acc_bias"], errors


def test_the_run_names_each_sensor_s_groups_whose_shrinking_it_refused():
    from smoother.pipeline import unshrunk_groups

    tiny = 1.0 / (IMPLAUSIBLE_FACTOR * 1.5)
    out, _ = honest(_fit(("ahrs", "tilt", (0, 1), tiny, 50.0, 0.0, 300), ("ahrs", "yaw", (2,), 0.7, 50.0, 0.0, 150),
                         ("wheels", "forward", (0,), IMPLAUSIBLE_FACTOR * 2, 50.0, 0.0, 300)))
    assert unshrunk_groups({"noise": out}) == {"ahrs": ["ahrs.tilt"]}  # the refused growth is not among them
    assert unshrunk_groups({}) == {}


def test_imu_components_that_contradict_each_other_are_a_model_error():
    low = 60.0 / (CONTRADICTION * 1.2)
    errors = _errors(_fit(("imu", "acc", None, 60.0, 30.0, 0.0, 7000), ("imu", "gyro", None, low, 30.0, 0.0, 7000),
                          ("imu", "acc_bias", None, 2.0, 5.0, 0.0, 7000)))
    assert set(errors) == {"imu.acc", "imu.gyro"} and "contradict each other" in errors["imu.acc"]


def test_the_run_s_doubt_names_the_groups_of_one_cause_together():
    """The contradicting pair is one doubt naming both; a group refused for a cause of its own is
    another."""
    from smoother.pipeline import run_doubts

    low = 60.0 / (CONTRADICTION * 1.2)
    out, _ = honest(_fit(("imu", "acc", None, 60.0, 30.0, 0.0, 7000), ("imu", "gyro", None, low, 30.0, 0.0, 7000),
                         ("wheels", "forward", (0,), IMPLAUSIBLE_FACTOR * 2, 50.0, 0.0, 300)))
    doubts = run_doubts({"noise": out})
    assert len(doubts) == 2, doubts
    assert doubts[0].startswith("the noise fitted to imu.acc and imu.gyro are a model error") and doubts[0].count(
        "contradict each other") == 1, doubts
    assert doubts[1].startswith("the noise fitted to wheels.forward is a model error"), doubts


def test_a_sensor_s_residuals_correlated_in_time_are_a_model_error_unless_analysed():
    fit = _fit(("gnss", "horizontal", (0, 1), 3.0, 80.0, CORRELATED + 0.2, 200),
               ("wheels", "forward", (0,), 1.2, 80.0, CORRELATED - 0.2, 200))
    assert correlated(fit) == ["gnss"]
    errors = _errors(fit)
    assert set(errors) == {"gnss.horizontal"} and "alike from one measurement to the next" in errors["gnss.horizontal"]
    assert set(_errors(fit, causes={"wheels": []})) == {"gnss.horizontal"}  # gnss not analysed


def test_correlated_residuals_that_a_calibration_explains_name_it():
    lever = Cause("lever_arm", np.array([0.0, 1.5, 0.0]), np.full(3, 0.01), 0.8)
    errors = _errors(_fit(("gnss", "horizontal", (0, 1), 3.0, 80.0, CORRELATED + 0.2, 200)), causes={"gnss": [lever]})
    assert "and point at lever arm y +1.500 m +- 0.010 m: a systematic error" in errors["gnss.horizontal"]


def test_correlated_residuals_that_no_calibration_explains_are_a_drift_and_applied():
    weak = Cause("lever_arm", np.array([0.0, 0.02, 0.0]), np.full(3, 0.01), 0.01)
    fit = _fit(("gnss", "horizontal", (0, 1), 3.0, 80.0, CORRELATED + 0.2, 200))
    out, errors = honest(fit, causes={"gnss": [weak]})
    (g,) = out.groups
    assert errors == [] and g.applied and "no calibration explains them: the sensor's error drifts" in g.note


def test_an_imu_factor_beside_a_drifting_sensor_may_be_that_drift_and_says_so():
    """Bias random walks far beyond a datasheet beside fixes whose error drifts: the cause names the
    drift and what keeps it out; without a drifting sensor, it does not."""
    imu = ("imu", "acc_bias", None, IMPLAUSIBLE_FACTOR * 1.6, 20.0, 0.9, 7000)
    gnss = ("gnss", "horizontal", (0, 1), 1.5, 80.0, CORRELATED + 0.1, 2400)
    errors = _errors(_fit(imu, gnss), causes={"gnss": []})
    assert set(errors) == {"imu.acc_bias"}, errors
    cause = errors["imu.acc_bias"]
    assert "no sensor's error of its datasheet" in cause, cause
    assert "the IMU follows the drift of gnss's errors" in cause and "`every`" in cause, cause
    alone = _errors(_fit(imu, gnss[:5] + (CORRELATED - 0.3, 2400)), causes={"gnss": []})
    assert "drift" not in alone["imu.acc_bias"], alone


def test_a_sensor_grown_until_it_is_discarded_is_a_model_error():
    errors = _errors(_fit(("wheels", "lateral", (1,), 15.0, 298.0, 0.1, 300)))
    assert "hardly uses it" in errors["wheels.lateral"]


def test_a_wrong_mounting_is_the_cause_whatever_the_factor():
    errors = _errors(_fit(("wheels", "forward", (0,), 1.8, 50.0, 0.0, 300), ("gps", "vertical", (2,), 1.5, 40.0,
                                                                             0.0, 100)),
                     mounting_wrong=("wheels",))
    assert set(errors) == {"wheels.forward"} and "mounting is wrong" in errors["wheels.forward"]


def test_noise_grown_beside_a_calibration_the_rig_leaves_out_is_that_misfit():
    """An AHRS whose residuals a time offset explains (a filter's delay the rig leaves out) beside a
    gyro noise grown 24x, its residuals not alike in time: every grown IMU component and the AHRS's
    grown sigma are that misfit, named with the rig key that estimates it; what shrank, and a
    sensor no cause explains, stay applied. A cause explaining less than EXPLAINED does not count."""
    fit = _fit(("imu", "gyro", None, 24.0, 1300.0, 0.9, 7000), ("imu", "acc", None, 0.5, 30.0, 0.9, 7000),
               ("ahrs", "attitude", (0, 1, 2), 1.8, 480.0, CORRELATED - 0.2, 1800),
               ("wheels", "forward", (0,), 3.0, 500.0, CORRELATED - 0.3, 2400))
    assert to_analyse(fit) and not correlated(fit)
    delay = Cause("time_offset", np.array([0.02]), np.array([0.0003]), 0.97)
    errors = _errors(fit, causes={"ahrs": [delay], "wheels": []})
    assert set(errors) == {"imu.gyro", "ahrs.attitude"}, errors
    assert ("a noise 24x the rig's grown beside a calibration the rig leaves out (ahrs's residuals point at time "
            "offset +0.02000 s +- 0.00030 s (explains 97 % of its residuals): add estimate = [\"time_offset\"]): that "
            "misfit, not noise" == errors["imu.gyro"]), errors["imu.gyro"]
    minor = Cause("time_offset", np.array([0.02]), np.array([0.0003]), EXPLAINED - 0.1)
    assert _errors(fit, causes={"ahrs": [minor], "wheels": []}) == {}
    assert not to_analyse(_fit(("imu", "gyro", None, 0.5, 1300.0, 0.9, 7000)))


def test_a_drifting_sensor_s_alternating_innovations_are_applied_with_a_note_naming_its_correlation_time():
    """Innovations correlated -0.53 from one measurement to the next (white errors taken to drift
    over 3 s at 10 Hz: the fit grew the sigma 5.4x): applied -- the model is the user's -- with a
    note; -0.15 over 243 values (within 3 sd of white, 0.19), or a sensor without a correlation
    time (its residuals are not innovations), says nothing."""
    for correlation, dof, times, said in ((-0.53, 243, {"pose": 3.0}, True), (-0.15, 243, {"pose": 3.0}, False),
                                          (-0.53, 243, {}, False), (-0.25, 40, {"pose": 3.0}, False)):
        out, errors = honest(_fit(("pose", "position", (0, 1, 2), 5.45, 237.0, correlation, dof)),
                             correlation_times=times)
        (g,) = out.groups
        assert errors == [] and g.applied
        assert ("its innovations alternate from one measurement to the next (correlation -0.53): its errors are "
                "less alike than its correlation_time (3 s) says" in g.note) == said, (correlation, dof, times)


def test_a_correlation_time_does_not_turn_a_refused_factor_into_a_noted_one():
    """Implausibly large or small, or grown until the estimate hardly uses the sensor: refused with
    alternating innovations and a correlation time as without them."""
    for factor, redundancy, said in ((IMPLAUSIBLE_FACTOR * 5, 200.0, "no sensor's error of its datasheet"),
                                     (0.5 / IMPLAUSIBLE_FACTOR, 200.0, "below any sensor's datasheet"),
                                     (20.0, 240.0, "until the estimate hardly uses it")):
        errors = _errors(_fit(("pose", "position", (0, 1, 2), factor, redundancy, -0.53, 243)),
                         correlation_times={"pose": 3.0})
        assert said in errors["pose.position"], (factor, errors)
