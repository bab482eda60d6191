"""Every kind of the registry in the estimators, with no list of kinds in this file: the online
smoother takes a kind's fields in their declared order, and every estimator that can use the kind
estimates better with it than the IMU alone (what the registry and the simulator do with a kind:
``tests/datasets/test_every_kind.py``)."""
from __future__ import annotations

import dataclasses
import warnings

import numpy as np
from mounted_kinds import EVERY_KIND, mounted, mounting

from datasets.kinds.base import kind_sigmas
from datasets.simulate import simulate
from datasets.simulated_sensors import SensorSpec
from smoother.model.problem import measurement_spec
from smoother.online.smoother import OnlineSmoother, SensorSetup
from smoother.pipeline import RunOptions, run_estimators


@EVERY_KIND
def test_the_online_smoother_takes_the_kinds_fields_in_their_declared_order(kind):
    """``add(name, *times, *fields, cov=...)`` of every measurement gives the window the same
    estimate as ``add_measurements`` of the data at once."""
    d = mounted(kind, duration=2.0)
    pose, data = d.sensor("pose").data, d.sensor("sensor").data
    finals = []
    for one_by_one in (False, True):
        online = OnlineSmoother(d.initial, d.initial_cov, d.noise, {
            "sensor": SensorSetup(kind.name, T_BS=data.T_BS), "pose": SensorSetup("pose")}, lag_s=1.0)
        online.add_measurements("pose", pose)
        if one_by_one:
            for i in range(len(data)):
                online.add("sensor", *(getattr(data, f)[i] for f in (*kind.times, *kind.fields)), cov=data.cov[i])
        else:
            online.add_measurements("sensor", data)
        online.add_imu(d.imu.t, d.imu.acc, d.imu.gyro)
        online.finish()
        finals.append(np.array([e.state.r for e in online.smoothed()]))
    assert len(finals[0]) > 10
    np.testing.assert_allclose(finals[1], finals[0], atol=1e-9)


@EVERY_KIND
def test_every_estimator_uses_the_kind_on_a_mounted_sensor(kind):
    """Batch, fixed-lag and (for a one-state kind) the EKF, with a precise sensor of the kind as
    the only aid: what the sensor observes is estimated better than the IMU alone does -- the
    RMS of ``h(estimate) - h(truth)`` over its measurements (the model's residual at the estimate
    less that at the truth, whatever the kind observes) at most half the dead-reckoned one."""
    spec = SensorSpec("sensor", kind.name, 10.0, 0.1 * kind_sigmas("", kind.default_sigma, kind.dim), mounting(1))
    d = simulate("gentle", duration=8.0, seed=3, pose_rate=None, sensors=(spec,))
    names = ["batch", "fixed-lag"] + ([] if kind.relative else ["ekf"])
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # dead reckoning is warned about
        aided = run_estimators(d, names, RunOptions(lag_s=1.0, progress=False))
        alone = run_estimators(dataclasses.replace(d, sensors=()), names, RunOptions(lag_s=1.0, progress=False))
    model = measurement_spec(d.sensor("sensor"))
    every = np.arange(len(model.cov))

    def observed_error(trajectory):
        at = [trajectory.interpolate(t)[0] for t in model.times]
        truth = [d.truth.interpolate(t)[0] for t in model.times]
        return float(np.sqrt(np.mean((model.residual(at, False, every) - model.residual(truth, False, every)) ** 2)))

    for name in names:
        with_it, without = observed_error(aided[name].trajectory), observed_error(alone[name].trajectory)
        assert with_it < 0.5 * without, (name, with_it, without)
