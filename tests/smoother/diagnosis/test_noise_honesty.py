"""Fitted noise that stays honest (smoother/diagnosis/noise_honesty.py): a factor that explains a
model error is reported as that error and not applied."""
from __future__ import annotations

import pytest

from smoother.batch.variance_components import GroupFit, NoiseFit, NoiseGroup
from smoother.diagnosis.noise_honesty import CONTRADICTION, CORRELATED, IMPLAUSIBLE_FACTOR, honest


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


@pytest.mark.parametrize("factor", [IMPLAUSIBLE_FACTOR * 1.5, 1.0 / (IMPLAUSIBLE_FACTOR * 1.5)])
def test_a_factor_orders_of_magnitude_off_is_a_model_error(factor):
    errors = _errors(_fit(("wheels", "forward", (0,), factor, 50.0, 0.0, 300)))
    assert "no sensor's error of its datasheet" in errors["wheels.forward"]


def test_imu_components_that_contradict_each_other_are_a_model_error():
    low = 60.0 / (CONTRADICTION * 1.2)
    errors = _errors(_fit(("imu", "acc", None, 60.0, 30.0, 0.0, 7000), ("imu", "gyro", None, low, 30.0, 0.0, 7000),
                          ("imu", "acc_bias", None, 2.0, 5.0, 0.0, 7000)))
    assert set(errors) == {"imu.acc", "imu.gyro"} and "contradict each other" in errors["imu.acc"]


def test_a_sensor_s_residuals_correlated_in_time_are_a_model_error():
    errors = _errors(_fit(("gnss", "horizontal", (0, 1), 3.0, 80.0, CORRELATED + 0.2, 200)))
    assert "alike from one measurement to the next" in errors["gnss.horizontal"]


def test_a_sensor_grown_until_it_is_discarded_is_a_model_error():
    errors = _errors(_fit(("wheels", "lateral", (1,), 15.0, 298.0, 0.1, 300)))
    assert "hardly uses it" in errors["wheels.lateral"]


def test_a_wrong_mounting_is_the_cause_whatever_the_factor():
    errors = _errors(_fit(("wheels", "forward", (0,), 1.8, 50.0, 0.0, 300), ("gps", "vertical", (2,), 1.5, 40.0,
                                                                             0.0, 100)),
                     mounting_wrong=("wheels",))
    assert set(errors) == {"wheels.forward"} and "mounting is wrong" in errors["wheels.forward"]
