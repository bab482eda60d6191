"""Every kind of the registry, with no list of kinds in this file: what a kind declares is what the
registry checks, the simulator draws it, the online smoother takes it field by field, the
estimators use it, and ``smoother check-jacobians`` checks its model in a fresh process."""
from __future__ import annotations

import dataclasses
import json
import subprocess
import sys
import warnings

import numpy as np
import pytest

from datasets.kinds import KINDS, registered
from datasets.kinds.base import kind_sigmas
from datasets.simulate import simulate
from datasets.simulated_sensors import SensorSpec
from factors import sensor_models as sm
from factors.selfcheck import random_extrinsic
from smoother.model.problem import measurement_spec
from smoother.online.smoother import OnlineSmoother, SensorSetup
from smoother.pipeline import RunOptions, run_estimators

EVERY_KIND = pytest.mark.parametrize("kind", KINDS.values(), ids=lambda k: k.name)


def _mounting(seed: int) -> np.ndarray:
    """A random mounting with a lever arm of some 0.3 m."""
    T = random_extrinsic(np.random.default_rng(seed))
    T[:3, 3] *= 0.3
    return T


def _mounted(kind, seed: int = 0, duration: float = 3.0):
    """A gentle run with a 10 Hz sensor of ``kind`` on a random mounting, and a 2 Hz pose sensor
    at the IMU so that every kind's run is observable."""
    spec = SensorSpec("sensor", kind.name, 10.0, kind.default_sigma, _mounting(seed))
    return simulate("gentle", duration=duration, seed=seed, pose_rate=2.0, sensors=(spec,))


# -------------------------------------------------------------------------- the registry's rules


def _variant(kind, **changes):
    return dataclasses.replace(kind, name="variant", **changes)


@EVERY_KIND
def test_the_registry_refuses_a_kind_that_breaks_a_rule(kind):
    registered(_variant(kind))  # the kind as declared passes
    bad = {
        "twice": (lambda: registered(kind, kind), "registered twice"),
        "dimension": (lambda: registered(_variant(kind, dim=sm.MAX_RESIDUAL_DIM + 1)), "residual dimension"),
        "fields": (lambda: registered(_variant(kind, fields=kind.fields[::-1] + ("extra",))), "fields"),
        "sigma": (lambda: registered(_variant(kind, default_sigma=(-1.0,))), "default_sigma"),
        "row": (lambda: registered(_variant(kind, random_row=lambda rng: (None, np.zeros(kind.width + 1)))),
                "random_row"),
    }
    for what, (call, message) in bad.items():
        with pytest.raises(ValueError, match=message):
            call()


def test_the_registry_refuses_rows_wider_than_the_estimators_hold():
    kind = next(iter(KINDS.values()))
    wide = sm.SensorModel("wide", kind.dim, sm.MAX_ROW_WIDTH + 1, kind.model.kernel, kind.model.variables)
    with pytest.raises(ValueError, match="row width"):
        registered(_variant(kind, model=wide, random_row=lambda rng: (None, np.zeros(wide.width))))


# -------------------------------------------------------------------------- what each kind declares


@EVERY_KIND
def test_the_simulator_draws_the_kind_and_its_rows_have_the_declared_width(kind):
    data = _mounted(kind).sensor("sensor").data
    assert isinstance(data, kind.data_type) and len(data) >= 29
    kind_sigmas("default_sigma", kind.default_sigma, kind.dim)
    if not kind.relative:
        assert kind.pack(data).shape == (len(data), kind.width)
    rebuilt = kind.data_type(*(getattr(data, f) for f in (*kind.times, *kind.fields)), data.cov, data.T_BS)
    for f in (*kind.times, *kind.fields, "cov"):  # a type may normalise (unit directions): to round-off
        np.testing.assert_allclose(getattr(rebuilt, f), getattr(data, f), rtol=0, atol=1e-14)


@EVERY_KIND
def test_the_simulators_shorthand_adds_a_sensor_named_after_the_kind(kind):
    d = simulate("gentle", duration=2.0, **{"pose_rate": None, f"{kind.name}_rate": 5.0})
    assert d.sensor_names == (kind.name,) and isinstance(d.sensor(kind.name).data, kind.data_type)


@EVERY_KIND
def test_the_online_smoother_takes_the_kinds_fields_in_their_declared_order(kind):
    """``add(name, *times, *fields, cov=...)`` of every measurement gives the window the same
    estimate as ``add_measurements`` of the data at once."""
    d = _mounted(kind, duration=2.0)
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
    spec = SensorSpec("sensor", kind.name, 10.0, 0.1 * kind_sigmas("", kind.default_sigma, kind.dim), _mounting(1))
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


def test_check_jacobians_in_a_fresh_process_checks_every_kind():
    done = subprocess.run([sys.executable, "-m", "smoother.cli", "check-jacobians", "--samples", "20", "--json"],
                          capture_output=True, text=True)
    assert done.returncode == 0, done.stderr[-2000:]
    results = {r["name"]: r for r in json.loads(done.stdout)}
    for name, kind in KINDS.items():  # its model, through its calibration; a one-state kind attached too, both ways
        checks = [r for n, r in results.items() if n.startswith(f"{name} measurement")]
        assert len(checks) == (2 if kind.relative else 4) and all(c["ok"] for c in checks), (name, sorted(results))
