"""The fixed-lag smoother on a sensor whose errors drift (:mod:`smoother.model.correlated`): the
sliding window makes the batch smoother's factors (each measurement's innovation on the one
before), offline from a problem's keyframe factors and online as measurements arrive, so with a
lag longer than the run it is the batch smoother; where the measurement before has left the window
the measurement is weighed alone, and the run says how many were; GTSAM's windows say they take
the errors as white."""
from __future__ import annotations

import re

import numpy as np
import pytest
from drifting_fixes import drifting_run, lever_arm_run

from datasets.rig import ImuConfig, Rig, SensorConfig
from factors.calibration import CalibrationPrior
from factors.errors import InputError
from smoother.batch.solve import solve_batch
from smoother.fixed_lag.offline import run_fixed_lag
from smoother.model.correlated import with_correlated_errors
from smoother.model.problem import build_problem
from smoother.online.replay import replay
from smoother.online.smoother import OnlineSmoother, SensorSetup

WHOLE_RUN = 100.0  # a lag [s] longer than the runs here: the window holds them whole


def _batch(data):
    return solve_batch(with_correlated_errors(build_problem(data), data), max_iterations=200).trajectory


def _apart(trajectory, batch) -> float:
    """The largest position difference of ``trajectory`` from ``batch``, in ``batch``'s sigmas."""
    sd = np.sqrt(np.einsum("kii->ki", batch.cov[:, :3, :3]))
    return float(np.max(np.abs(trajectory.states.r - batch.states.r) / sd))


@pytest.mark.parametrize("hz", [5.0, 20.0])  # one measurement per keyframe; two, attached between keyframes
def test_a_window_holding_the_whole_run_is_the_batch_smoother_on_drifting_errors(hz):
    data = lever_arm_run(hz)
    batch = _batch(data)
    offline = run_fixed_lag(build_problem(data), WHOLE_RUN).lagged
    online = replay(data, WHOLE_RUN, "sliding", covariances=True, progress=False).smoothed
    white = run_fixed_lag(build_problem(data.with_sensor("gnss", correlation_time=None)), WHOLE_RUN).lagged
    assert _apart(offline, batch) < 0.01 and _apart(online, batch) < 0.01
    assert _apart(white, batch) > 0.5  # the model, not the data, makes them agree
    sd = [np.sqrt(np.einsum("kii->ki", t.cov[:, :9, :9])) for t in (offline, online, batch)]  # r, v, C
    np.testing.assert_allclose(sd[0], sd[2], rtol=5e-3)
    np.testing.assert_allclose(sd[1], sd[2], rtol=5e-3)


def test_a_lag_shorter_than_the_measurements_spacing_weighs_them_alone_and_says_how_many():
    data = drifting_run(0, 10.0, duration=12.0, hz=1.0, every=1)  # fixes 1 s apart, keyframes 0.1 s
    with pytest.warns(UserWarning, match=r"fixed-lag \(sliding\): 10 measurement\(s\) of sensors with a "
                                         r"correlation_time were weighed as independent of the one before"):
        run_fixed_lag(build_problem(data, 10.0), 0.5)
    with pytest.warns(UserWarning, match=re.escape("online smoother: 10 measurement(s) of sensors with a "
                                                   "correlation_time were weighed as independent of the one before, "
                                                   "where it had left the window (a lag, 0.5 s,")):
        replay(data, 0.5, "sliding", keyframe_rate=10.0, progress=False)


def test_a_lag_spanning_the_spacing_makes_every_innovation(recwarn):
    data = drifting_run(0, 10.0, duration=12.0, hz=1.0, every=1)
    drifting = run_fixed_lag(build_problem(data, 10.0), 1.5).lagged
    online = replay(data, 1.5, "sliding", keyframe_rate=10.0, progress=False).smoothed
    white = run_fixed_lag(build_problem(data.with_sensor("gnss", correlation_time=None), 10.0), 1.5).lagged
    assert not [w for w in recwarn if "weighed as independent" in str(w.message)]
    assert _apart(online, drifting) < 0.01 and _apart(white, drifting) > 0.1  # the innovations were made


def test_a_measurement_too_many_keyframes_after_the_one_before_is_weighed_alone():
    """An 8 s gap in fixes at 5 Hz, keyframes at 10 Hz, a lag of 12 s: the innovation across the gap
    would widen the window's band to 80 keyframes; the measurement after it is weighed alone, and said."""
    data = drifting_run(0, 3.0, duration=30.0, hz=5.0, every=1)
    gnss = data.sensor("gnss")
    data = data.with_sensor("gnss", data=gnss.data.subset((gnss.data.t < 8.0) | (gnss.data.t > 16.0)))
    with pytest.warns(UserWarning, match=r"fixed-lag \(sliding\): 1 measurement\(s\) of sensors with a "
                                         "correlation_time were weighed as independent"):
        run_fixed_lag(build_problem(data, 10.0), 12.0, covariances=False)


@pytest.mark.parametrize("parts", [("lever_arm",), ("time_offset", "lever_arm")])
def test_a_window_holding_the_whole_run_estimates_a_drifting_sensor_s_calibration_as_the_batch_smoother(parts,
                                                                                                      recwarn):
    data = lever_arm_run(20.0, calibrate=CalibrationPrior(parts))  # attached between keyframes, two per keyframe
    batch = solve_batch(with_correlated_errors(build_problem(data), data), max_iterations=200)
    online = replay(data, WHOLE_RUN, "sliding", covariances=True, progress=False)
    white = replay(data.with_sensor("gnss", correlation_time=None), WHOLE_RUN, "sliding", progress=False).smoothed
    assert not [w for w in recwarn if "weighed as independent" in str(w.message)]
    assert _apart(online.smoothed, batch.trajectory) < 0.02 and _apart(white, batch.trajectory) > 0.5
    values, cov = online.calibration
    mine, theirs = values.values[0], batch.calibration.values[0]
    sd = np.sqrt(np.diag(batch.calibration_cov[0]))  # the error coordinates: time offset first where estimated
    np.testing.assert_allclose(mine.p, theirs.p, atol=0.05 * sd[-3:].min())
    if "time_offset" in parts:
        assert abs(mine.time_offset - theirs.time_offset) < 0.05 * sd[0]


def test_gtsam_s_windows_say_they_take_the_errors_as_white():
    data = drifting_run(0, 10.0, duration=6.0, hz=1.0, every=1)
    with pytest.warns(UserWarning, match=r"online smoother \(incremental\): the errors of gnss are taken as white"):
        replay(data, 3.0, "incremental", progress=False)
    with pytest.warns(UserWarning, match=r"fixed-lag \(incremental\): \d+ measurement\(s\) of sensors with a "
                                         "correlation_time were weighed as independent"):
        run_fixed_lag(build_problem(data), 3.0, kind="incremental")


def test_a_rig_s_correlation_time_reaches_the_online_smoother(tmp_path, recwarn):
    data = drifting_run(0, 10.0, duration=6.0, hz=1.0, every=1)
    rig = Rig(tmp_path / "rig.toml", ImuConfig("csv:imu.csv", None, data.noise, float(-data.gravity[2])), None,
              (SensorConfig("gnss", "position", "csv:gnss.csv", None, np.eye(4), 0.0, np.array([0.5]), 1, None,
                            correlation_time=20.0),))
    OnlineSmoother.from_rig(rig, data.initial, data.initial_cov, lag_s=3.0)  # modelled: nothing to say
    assert not [w for w in recwarn if "correlation" in str(w.message) or "white" in str(w.message)]
    with pytest.warns(UserWarning, match=r"online smoother \(batch\): the errors of gnss are taken as white"):
        OnlineSmoother.from_rig(rig, data.initial, data.initial_cov, lag_s=3.0, kind="batch")


def test_a_correlation_time_still_to_fit_is_refused_online_pointing_at_the_batch_run(tmp_path):
    """The fit reads a whole recording's held-out measurements: the online smoother, from a rig or a
    dataset that still asks for it, says where the time comes from instead of taking the errors as white."""
    data = drifting_run(0, None, duration=12.0, hz=1.0, every=2)
    rig = Rig(tmp_path / "rig.toml", ImuConfig("csv:imu.csv", None, data.noise, float(-data.gravity[2])), None,
              (SensorConfig("gnss", "position", "csv:gnss.csv", None, np.eye(4), 0.0, np.array([0.5]), 2, None,
                            fit_correlation_time=True),))
    said = "sensor 'gnss': correlation_time = \"fit\" is fitted by a batch run over a recording with held-out"
    with pytest.raises(InputError, match=re.escape(said)):
        OnlineSmoother.from_rig(rig, data.initial, data.initial_cov, lag_s=3.0)
    with pytest.raises(InputError, match=re.escape(said)):
        OnlineSmoother.for_dataset(data.with_sensor("gnss", fit_correlation_time=True), lag_s=3.0)


@pytest.mark.parametrize("kind, tau, expected", [
    ("odometry", 5.0, "odometry measurements are relative (two states each)"),
    ("position", 0.0, "expected a value within"),
    ("position", float("nan"), "expected a value within"),
    ("position", True, "expected a number of seconds, got True"),
    ("position", "5", "expected a number of seconds, got '5'"),
])
def test_a_sensor_setup_refuses_a_correlation_time_it_cannot_model(kind, tau, expected):
    with pytest.raises(InputError, match=re.escape(f"SensorSetup.correlation_time: {expected}")):
        SensorSetup(kind, correlation_time=tau)
