"""Noise fitted in a run whose rig is wrong (smoother/pipeline.py with
smoother/diagnosis/noise_honesty.py, misfit_causes.py and smoother/batch/variance_components.py):
an attitude sensor stamped 0.04 s late, its delay not estimated. The IMU's noise grows to follow
it, one component after another as each is held; every one that grew is refused with the delay
named, and the groups still fitted are fitted with the refused ones at the rig's value."""
from __future__ import annotations

import re
from dataclasses import replace

import numpy as np
import pytest

from datasets import trajectories
from datasets.simulate import simulate
from datasets.simulated_sensors import SensorSpec
from smoother.batch.solve import solve_batch
from smoother.batch.variance_components import GroupFit, NoiseGroup, estimate_noise
from smoother.model.problem import build_problem
from smoother.pipeline import RunOptions, held_as_reported, run_estimators

NOISE = ("imu", "ahrs", "gnss")
#: A car-like figure-eight (100 m x 50 m, 7-15 m/s), heading along the path.
CAR = trajectories.Profile(
    "car", "figure-eight 100 m x 50 m, 7-15 m/s",
    lambda t: tuple(x * np.array([10.0, 10.0, 1.0]) for x in trajectories.GENTLE.position(t)),
    trajectories.GENTLE.attitude)


def _delayed_ahrs():
    """30 s of the car at 100 Hz: 10-Hz fixes (0.3 m, stated right) and a 50-Hz attitude sensor
    (0.002 rad, stated right) whose every measurement is stamped two samples (0.04 s) late."""
    data = simulate(CAR, duration=30.0, seed=1, imu_rate=100.0, pose_rate=None, sensors=[
        SensorSpec("gnss", "gnss", 10.0, 0.3), SensorSpec("ahrs", "orientation", 50.0, 0.002)])
    a = data.sensor("ahrs").data
    return data.with_sensor("ahrs", data=replace(a, t=a.t[2:], C=a.C[:-2], cov=a.cov[2:]))


def test_noise_grown_beside_a_delay_is_refused_and_the_rest_fitted_with_it_held():
    """Every IMU component that grew, and the attitude sensor's sigma, are refused; each refusal
    that names a cause names the delay within 3 of its sigmas (measured -0.0398 s +- 0.0002 s).
    The misfit causes are fitted with no factor grown (at the fitted noise a grown gyro follows the
    delay, which then explains too little of the sensor's residuals to be suggested). Each refused
    group is held at the rig's value and the rest fitted again (measured: four fits, the IMU's
    components refused in turn, then the attitude sensor's sigma): the groups the run reports as
    fitted are those of a fit from the rig's noise with the refused ones held."""
    data = _delayed_ahrs()
    batch = run_estimators(data, ["batch"], RunOptions(progress=False, estimate_noise=NOISE))["batch"]
    fit, errors = batch.noise, batch.details["noise_model_errors"]
    refused = {g.group.name for g in fit.groups if g.note.startswith("not applied")}
    assert refused == set(errors) and fit.fits == 4 and fit.record()["_fit"]["fits"] == 4
    grown = {g.group.name for g in fit.groups if g.estimable and g.factor > 1.5 and g.group.sensor != "gnss"}
    assert {"imu.gyro", "ahrs.attitude"} <= grown <= refused, (grown, refused)
    named = [re.search(r"time offset ([-+]\d\.\d+) s \+- (\d\.\d+) s", cause) for cause in errors.values()]
    assert sum(m is not None for m in named) >= 3, errors
    for m in filter(None, named):
        assert abs(float(m.group(1)) + 0.04) < 3 * float(m.group(2)), m.group(0)
    start = run_estimators(data, ["batch"], RunOptions(progress=False))["batch"]
    problem = build_problem(data, start=start.trajectory)
    again, _, _ = estimate_noise(data, problem, solve_batch(problem, square_root=True), NOISE, fixed=refused)
    reported = {g.group.name: g for g in fit.groups}
    assert {g.group.name for g in again.groups} == set(reported) - refused
    for g in again.groups:
        assert g.applied == reported[g.group.name].applied, g
        assert abs(g.factor - reported[g.group.name].factor) < 0.01 * g.factor_sd, (g, reported[g.group.name])


def test_a_fit_whose_last_allowed_refit_still_finds_a_model_error_is_not_converged(monkeypatch):
    """With one fit again allowed, the second fit still refuses groups (the gyro's white noise and
    the accelerometer's bias walk, grown beside the delay once the first fit's were held): the
    groups it applied were fitted beside them, and the fit says it did not converge."""
    import smoother.pipeline as pipeline

    monkeypatch.setattr(pipeline, "MAX_REFITS", 1)
    fit = run_estimators(_delayed_ahrs(), ["batch"], RunOptions(progress=False, estimate_noise=NOISE))["batch"].noise
    assert fit.fits == 2 and not fit.converged and not fit.record()["_fit"]["converged"]
    assert "imu.gyro" in {g.group.name for g in fit.groups if g.note.startswith("not applied")}


def test_a_fit_again_that_fails_leaves_the_last_fit_standing_and_says_so(monkeypatch):
    """The second fit fails in the solver: a warning names the groups held, the first fit's
    refusals stand, the groups it applied keep their values (not converged), and the run goes on."""
    import smoother.batch.variance_components as vc
    from factors.errors import SolverError

    fit_once = vc.estimate_noise
    calls = []

    def failing_again(*args, **kwargs):
        calls.append(kwargs.get("fixed"))
        if kwargs.get("fixed"):
            raise SolverError("the covariances' elimination failed")
        return fit_once(*args, **kwargs)

    monkeypatch.setattr(vc, "estimate_noise", failing_again)
    with pytest.warns(UserWarning, match=r"fitting again with imu\.\w+, imu\.\w+ at the rig's value failed \(the "
                                         r"covariances' elimination failed\)"):
        batch = run_estimators(_delayed_ahrs(), ["batch"], RunOptions(progress=False, estimate_noise=NOISE))["batch"]
    fit = batch.noise
    assert len(calls) == 2 and fit.fits == 1 and not fit.converged
    assert {g.group.name for g in fit.groups if g.note.startswith("not applied")} == set(calls[1])
    assert batch.trajectory is not None and batch.failed is None


def test_a_refused_group_that_shared_its_factor_with_groups_fitted_again_says_so():
    """A group refused in a fit where it shared one factor with others keeps that fit's factor and
    its own redundancy; the partners fitted again since are no longer named as sharing it, and its
    note says the factor was one with them. Partners held with it stay named."""
    acc = GroupFit(NoiseGroup("imu", "acc"), 0.049, 0.0012, 0.005, 1e-4, "m/s^2/sqrt(Hz)",
                   merged_with=("wheels.lateral", "imu.gyro_bias"), applied=False, note="not applied: contradiction")
    out = held_as_reported(acc, {"imu.acc", "imu.gyro_bias"})
    assert out.merged_with == ("imu.gyro_bias",)
    assert out.note == ("not applied: contradiction (its factor was one with wheels.lateral, fitted again "
                        "without it since)"), out.note
    assert (out.factor, out.redundancy) == (acc.factor, acc.redundancy)
    assert held_as_reported(acc, {"imu.acc", "imu.gyro_bias", "wheels.lateral"}).note == acc.note
