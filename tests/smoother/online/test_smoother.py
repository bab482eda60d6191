"""Online fixed-lag smoothing (smoother/online/smoother.py): streamed sample by sample it equals the
replay and the offline smoother, late measurements within ``max_delay_s`` change nothing and later
ones are dropped and counted, ``estimate()`` is the EKF's prediction from the newest keyframe, the
lag-versus-gap warning, and clear errors for bad input."""
from __future__ import annotations

import re
import warnings
from dataclasses import replace

import estimator_cases as cases
import numpy as np
import pytest

from datasets.kinds import sensors_of
from smoother.ekf.filter import Ekf
from smoother.fixed_lag.offline import run_fixed_lag
from smoother.model.problem import build_problem
from smoother.model.timeline import keyframe_times
from smoother.online.replay import replay
from smoother.online.smoother import OnlineSmoother, SensorSetup

LAG = 0.5
NAMES = ("r", "v", "C", "b_f", "b_w")


def _arrivals(data, delays=None):
    """``(arrival time, row)`` of each pose measurement of ``data`` (arriving at its time plus
    ``delays``), in order of arrival."""
    t = data.sensor("pose").data.t + (0.0 if delays is None else delays)
    order = np.argsort(t, kind="stable")
    return [(float(t[m]), int(m)) for m in order]


def _stream(data, online, arrivals, estimates=None, knots=None):
    """Feed ``data``'s IMU sample by sample and its poses at their ``arrivals`` (each before the
    IMU sample of the same time), then finish, with keyframes at ``knots`` (default
    ``keyframe_times(data)``); ``estimates`` collects ``estimate()`` after each sample."""
    online.keyframe_at(keyframe_times(data) if knots is None else knots)
    a = 0
    for i, t in enumerate(np.append(data.imu.t, np.inf)):
        while a < len(arrivals) and arrivals[a][0] <= t:
            m = arrivals[a][1]
            online.add("pose", data.sensor("pose").data.t[m], data.sensor("pose").data.position[m],
                       data.sensor("pose").data.C[m], cov=data.sensor("pose").data.cov[m])
            a += 1
        if i == len(data.imu):
            break
        online.add_imu(t, data.imu.acc[i], data.imu.gyro[i])
        if estimates is not None:
            estimates.append(online.estimate())
    online.finish()
    return list(online.smoothed())


def _smoother(data, **options):
    return OnlineSmoother(data.initial, data.initial_cov, data.noise, gravity=data.gravity, lag_s=LAG, **options)


def _assert_same_states(a, b):
    for name in NAMES:
        np.testing.assert_array_equal(getattr(a, name), getattr(b, name))


#: How far (in sigmas) each kind's online estimates may be from GTSAM's incremental smoother run
#: offline on the whole problem: the incremental kind's differ only in the IMU factors' noise
#: covariances, evaluated along the smoother's prediction instead of the offline initial trajectory
#: (measured 9e-4); the sliding window relinearises a keyframe beyond its own per-component
#: thresholds where ISAM2 relinearises those that moved more than 0.05 (measured 0.055).
OFFLINE_SIGMAS = {"incremental": 5e-3, "sliding": 0.15}


@pytest.mark.parametrize("kind", ["sliding", "incremental"])
def test_streamed_sample_by_sample_equals_the_replay_and_the_offline_smoother(gentle, kind):
    """Fed one IMU sample and one measurement at a time, each keyframe's smoothed estimate and
    covariance equal those of ``replay`` (IMU in chunks) bit for bit, and those of GTSAM's
    incremental ``run_fixed_lag`` on the whole problem within :data:`OFFLINE_SIGMAS` and
    covariances within 0.05 in correlation units (measured 0.016 for both kinds: the covariances
    are taken at the linearisation point rather than at the estimate)."""
    data = cases.dataset(gentle)
    out = _stream(data, _smoother(data, covariances=True, kind=kind), _arrivals(data))
    whole = replay(data, LAG, kind, covariances=True, progress=False).smoothed
    np.testing.assert_array_equal([e.t for e in out], whole.t)
    _assert_same_states(type(whole.states).stack([e.state for e in out]), whole.states)
    np.testing.assert_array_equal(np.stack([e.cov for e in out]), whole.cov)

    offline = run_fixed_lag(build_problem(data), LAG, "incremental", covariances=True, progress=False).lagged
    np.testing.assert_array_equal(whole.t, offline.t)
    diff = cases.sigma_difference(whole.states, offline.states, offline.cov)
    assert diff.max() < OFFLINE_SIGMAS[kind], diff.max()
    scale = np.sqrt(np.einsum("nii->ni", offline.cov))
    correlation_diff = np.abs(whole.cov - offline.cov) / (scale[:, :, None] * scale[:, None, :])
    assert correlation_diff.max() < 0.05, correlation_diff.max()


@pytest.mark.parametrize("max_delay_s", [0.0, 0.05])
def test_the_replays_blocks_equal_the_stream_sample_by_sample_with_each_measurement_at_its_arrival(max_delay_s):
    """Wheel speeds at 83 Hz and fixes at 10 Hz (attached to the 10 Hz grid's keyframes) with
    odometry at 4 Hz (keyframes of its own): ``replay`` -- the IMU in blocks, the attached
    measurements arriving early, together at their keyframe's time -- gives each keyframe's
    smoothed estimate and covariance and the calibrations of the stream fed one IMU sample at a
    time with each measurement at its own arrival, bit for bit."""
    from datasets.simulate import simulate
    from datasets.simulated_sensors import SensorSpec
    from factors.calibration import CalibrationPrior
    from smoother.online.replay import arrivals, replaying

    data = simulate("gentle", duration=6.0, seed=3, imu_rate=100.0, pose_rate=0, sensors=[
        SensorSpec("wheels", "velocity", 83.0, 0.05), SensorSpec("gnss", "gnss", 10.0, 0.2),
        SensorSpec("odo", "odometry", 4.0, 0.05)])
    data = data.with_sensor("wheels", calibrate=CalibrationPrior(("scale",)))
    smoothed = []
    online = replaying(data, lag_s=1.0, max_delay_s=max_delay_s, covariances=True, on_smoothed=smoothed.append)
    imu_data, fed = data.imu, 0
    for _, upto, arrived in arrivals(data):
        for m in range(fed, upto):
            online.add_imu(float(imu_data.t[m]), imu_data.acc[m], imu_data.gyro[m])
        fed = upto
        for name, measurements in arrived:
            online.add_measurements(name, measurements)
    for m in range(fed, len(imu_data.t)):
        online.add_imu(float(imu_data.t[m]), imu_data.acc[m], imu_data.gyro[m])
    online.finish()
    smoothed.sort(key=lambda e: e.t)
    whole = replay(data, 1.0, max_delay_s=max_delay_s, covariances=True, progress=False)
    assert len(whole.smoothed.t) > 60 and not whole.dropped and not whole.skipped
    np.testing.assert_array_equal([e.t for e in smoothed], whole.smoothed.t)
    _assert_same_states(type(whole.smoothed.states).stack([e.state for e in smoothed]), whole.smoothed.states)
    np.testing.assert_array_equal(np.stack([e.cov for e in smoothed]), whole.smoothed.cov)
    (values, covariances), (whole_values, whole_covariances) = online.calibration, whole.calibration
    assert [c.scale for c in values.values] == [c.scale for c in whole_values.values]
    assert len(covariances) == len(whole_covariances) == 1
    np.testing.assert_array_equal(covariances[0], whole_covariances[0])


def test_measurements_late_within_max_delay_change_nothing_later_ones_are_dropped_and_counted(gentle):
    """Poses arriving up to 0.3 s late in shuffled order (``max_delay_s`` 0.3) give the same
    smoothed estimates, bit for bit, as all in time order; five that arrive 0.5 s late are
    dropped with a warning, counted, and the result is that of the data without them (keyframes
    at the same times), bit for bit."""
    data = cases.dataset(gentle)
    in_order = _stream(data, _smoother(data), _arrivals(data))
    rng = np.random.default_rng(3)
    late = rng.uniform(0.0, 0.29, len(data.sensor("pose").data))
    shuffled = _stream(data, _smoother(data, max_delay_s=0.3), _arrivals(data, late))
    assert [e.t for e in shuffled] == [e.t for e in in_order]
    for a, b in zip(shuffled, in_order):
        _assert_same_states(a.state, b.state)

    too_late = np.sort(rng.choice(np.arange(5, len(data.sensor("pose").data) - 5), 5, replace=False))
    late[too_late] = 0.5
    online = _smoother(data, max_delay_s=0.3)
    with pytest.warns(UserWarning, match="'pose' arrived after its keyframe time had been processed"):
        dropped = _stream(data, online, _arrivals(data, late))
    assert online.dropped == {"pose": 5}
    kept = data.with_sensor("pose", data=data.sensor("pose").data.subset(
        np.setdiff1d(np.arange(len(data.sensor("pose").data)), too_late)))
    without = _stream(kept, _smoother(kept), _arrivals(kept), knots=keyframe_times(data))
    assert [e.t for e in dropped] == [e.t for e in without]
    for a, b in zip(dropped, without):
        _assert_same_states(a.state, b.state)


def test_estimate_between_keyframes_is_the_ekf_prediction_from_the_newest_keyframe(gentle):
    """At a keyframe ``estimate()`` is its smoothed state and marginal covariance; between
    keyframes it is the EKF's per-sample prediction from there (``Ekf.predict`` over the same
    samples), state and covariance, to rounding."""
    data = cases.dataset(gentle)
    estimates = []
    _stream(data, _smoother(data, covariances=True), _arrivals(data), estimates)
    keyframes = set(keyframe_times(data))
    checked = 0
    ekf = None
    for i, (t, e) in enumerate(zip(data.imu.t, estimates)):
        assert e.t == t
        if t in keyframes:
            ekf = Ekf(e.state, e.cov, data.noise, data.gravity)
            continue
        ekf.predict(data.imu.acc[i - 1], data.imu.gyro[i - 1], t - data.imu.t[i - 1])
        for name in NAMES:
            np.testing.assert_allclose(getattr(e.state, name), getattr(ekf.state, name), rtol=0, atol=1e-12)
        np.testing.assert_allclose(e.cov, ekf.P, rtol=1e-12, atol=1e-15)
        checked += 1
    assert checked > 0.8 * len(estimates)


def test_the_lag_warning_fires_on_kitti_with_every_20th_fix_and_not_on_the_default_simulation():
    """KITTI with every 20th GPS fix (19 s apart): at a 2-s or a 0.5-s lag the smoothed keyframes
    are dead reckoning between fixes (tens of metres off the held-out fixes), and the replay says
    so, naming the lag that would cover the gaps; the default simulated run (poses at 10 Hz, lag
    2 s) runs without a warning."""
    from smoother.commands import dataset_specs as sources

    kitti = sources.load("kitti", sources.SourceOptions(gps_every=20))
    for lag in (2.0, 0.5):
        with pytest.warns(UserWarning, match=rf"fixed-lag \(sliding\): absolute measurements \(fixes, poses, "
                                             rf"attitudes\) up to 19 s apart, longer than the lag \({lag:g} s\)"
                                             rf".*Choose a lag of at least 19 s"):
            result = replay(kitti, lag, covariances=False, progress=False)
        assert result.longest_gap_s > 18.0
    simulated = sources.load("synthetic:gentle", sources.SourceOptions())
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        result = replay(simulated, 2.0, covariances=False, progress=False)
    assert result.longest_gap_s < 2.0


def test_bad_input_is_refused_with_one_clear_error(gentle):
    """IMU samples out of order, unknown sensors, a measurement without a covariance from a
    sensor without sigma, the wrong number of fields, and an estimate before any data: each a
    ValueError naming what was wrong."""
    data = cases.dataset(gentle)
    online = _smoother(data, sensors={"gps": SensorSetup("position")})
    with pytest.raises(ValueError, match="estimate: no keyframe yet"):
        online.estimate()
    online.add_imu(data.imu.t[:3], data.imu.acc[:3], data.imu.gyro[:3])
    with pytest.raises(ValueError, match=r"add_imu: t: IMU samples must come in strictly increasing time"):
        online.add_imu(data.imu.t[1], data.imu.acc[1], data.imu.gyro[1])
    with pytest.raises(ValueError, match=re.escape("add_imu: acc: expected shape (3,) for one sample (t a number), "
                                                   "got (2,)")):
        online.add_imu(data.imu.t[3], [1.0, 2.0], data.imu.gyro[3])
    with pytest.raises(ValueError, match="sensor: unknown sensor 'lidar'"):
        online.add("lidar", 0.1, [0.0, 0.0, 0.0])
    with pytest.raises(ValueError, match=r"add\('gps'\): cov: expected a covariance"):
        online.add("gps", 0.1, [0.0, 0.0, 0.0])
    with pytest.raises(ValueError, match=r"add\('gps'\): expected t, position \(and cov\)"):
        online.add("gps", 0.1, [0.0, 0.0, 0.0], [1.0, 2.0, 3.0], cov=np.eye(3))
    with pytest.raises(ValueError, match=r"max_delay_s: expected a value within \[0, 60\] s"):
        _smoother(data, max_delay_s=-1.0)
    assert [s.name for s in sensors_of(data)] == ["pose"]


def test_a_rig_gives_its_sensors_their_extrinsic_time_offset_and_sigma(gentle, tmp_path):
    """``OnlineSmoother.from_rig``: a pose sensor 0.3 m along the IMU's x axis, 0.25 s late on the
    IMU clock, with sigmas in the rig and none in the stream; fed its own stamps, sensor-frame
    poses and no covariance it gives the estimates of a smoother told the extrinsic and sigmas
    directly and fed the IMU-clock stamps."""
    from datasets.rig import ImuConfig, Rig, SensorConfig
    from datasets.types import PoseMeasurements

    data = cases.dataset(gentle)
    T_BS = np.eye(4)
    T_BS[0, 3] = 0.3
    sigma = np.array([0.02, 0.02, 0.02, 0.005, 0.005, 0.005])
    rig = Rig(tmp_path / "rig.toml", ImuConfig("csv:imu.csv", None, data.noise, float(-data.gravity[2])), None,
              (SensorConfig("cam", "pose", "csv:cam.csv", None, T_BS, 0.25, sigma, 1, None),))
    pose = data.sensor("pose").data
    sensor_position = pose.position + np.einsum("nab,b->na", pose.C, T_BS[:3, 3])
    from_rig = OnlineSmoother.from_rig(rig, data.initial, data.initial_cov, lag_s=LAG)
    direct = _smoother(data, sensors={"cam": SensorSetup("pose", T_BS)})
    direct.add_measurements("cam", PoseMeasurements(pose.t, sensor_position, pose.C,
                                                    np.broadcast_to(np.diag(sigma**2), (len(pose), 6, 6)), T_BS))
    stamps = pose.t - 0.25
    from_rig.add("cam", stamps, sensor_position, pose.C)
    for online in (from_rig, direct):
        online.add_imu(data.imu.t, data.imu.acc, data.imu.gyro)
        online.finish()
    a, b = list(from_rig.smoothed()), list(direct.smoothed())
    np.testing.assert_allclose([e.t for e in a], [e.t for e in b], rtol=0, atol=1e-12)
    assert len(a) == len(pose)  # the measurements' keyframes (the first at the start)
    for x, y in zip(a, b):
        for name in NAMES:
            np.testing.assert_allclose(getattr(x.state, name), getattr(y.state, name), rtol=0, atol=1e-6)


def test_a_rig_s_sigma_factor_scales_the_covariances_the_measurements_bring(gentle, tmp_path):
    """``sigma_factor`` in the rig (the noise fit's factors on a sensor whose messages carry its
    covariance): the covariances fed with the measurements are scaled per axis, as the offline
    run scales the messages'; a smoother fed the scaled covariances itself gives the same
    estimates. With ``sigma`` beside it a SensorSetup is refused."""
    from datasets.rig import ImuConfig, Rig, SensorConfig

    data = cases.dataset(gentle)
    pose = data.sensor("pose").data
    factor = np.array([2.0, 2.0, 3.0, 0.5, 0.5, 1.0])
    rig = Rig(tmp_path / "rig.toml", ImuConfig("csv:imu.csv", None, data.noise, float(-data.gravity[2])), None,
              (SensorConfig("pose", "pose", "csv:cam.csv", None, np.eye(4), 0.0, None, 1, None,
                            sigma_factor=factor),))
    from_rig = OnlineSmoother.from_rig(rig, data.initial, data.initial_cov, lag_s=LAG)
    direct = _smoother(data, sensors={"pose": SensorSetup("pose")})
    from_rig.add("pose", pose.t, pose.position, pose.C, cov=pose.cov)
    direct.add("pose", pose.t, pose.position, pose.C, cov=pose.cov * np.outer(factor, factor))
    for online in (from_rig, direct):
        online.add_imu(data.imu.t, data.imu.acc, data.imu.gyro)
        online.finish()
    for x, y in zip(from_rig.smoothed(), direct.smoothed(), strict=True):
        for name in NAMES:
            np.testing.assert_allclose(getattr(x.state, name), getattr(y.state, name), rtol=0, atol=1e-9)
    with pytest.raises(ValueError, match=r"SensorSetup.sigma_factor: .*with sigma given"):
        SensorSetup("pose", sigma=np.full(6, 0.1), sigma_factor=factor)


def test_relative_measurements_reaching_beyond_the_window_are_skipped_and_counted():
    """Odometry between keyframes 1 s apart: with a 0.3-s lag its earlier keyframe has left the
    window when it arrives (or, given in advance, when its later keyframe is made), so it is
    skipped, counted and warned of; with a 2-s lag every one is used, and the estimates are the
    offline smoother's (within 5e-3 sigma)."""
    from datasets.simulate import simulate

    data = simulate(profile="gentle", duration=2.0, seed=1, imu_rate=cases.IMU_RATE, pose_rate=cases.POSE_RATE,
                    odometry_rate=1.0)
    assert len(data.sensor("odometry").data) == 2
    with pytest.warns(UserWarning, match="'odometry' refers to a time that has left the window"):
        short = replay(data, 0.3, covariances=False, progress=False)
    assert short.skipped == {"odometry": 2} and short.dropped == {}
    # given before the IMU reaches them, they wait; their earlier keyframes leave all the same
    ahead = OnlineSmoother(data.initial, data.initial_cov, data.noise, gravity=data.gravity, lag_s=0.3)
    ahead.add_measurements("odometry", data.sensor("odometry").data)
    ahead.add_measurements("pose", data.sensor("pose").data)
    with pytest.warns(UserWarning, match="'odometry' refers to a time that has left the window"):
        ahead.add_imu(data.imu.t, data.imu.acc, data.imu.gyro)
    assert ahead.skipped == {"odometry": 2}
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        long = replay(data, 2.0, "incremental", covariances=False, progress=False)
    assert long.skipped == {}
    offline = run_fixed_lag(build_problem(data), 2.0, "incremental", covariances=True, progress=False).lagged
    np.testing.assert_array_equal(long.smoothed.t, offline.t)
    assert cases.sigma_difference(long.smoothed.states, offline.states, offline.cov).max() < 5e-3
    sliding = replay(data, 2.0, "sliding", covariances=False, progress=False)
    assert sliding.skipped == {}
    assert (cases.sigma_difference(sliding.smoothed.states, offline.states, offline.cov).max()
            < OFFLINE_SIGMAS["sliding"])


def test_keyframes_at_the_measurements_on_a_grid_and_at_the_end(gentle):
    """With ``keyframe_rate`` and no keyframe asked for, the keyframes are those of the offline
    graph with the same rate (``keyframe_times``: the measurement times, the grid, the start and
    the end of the data)."""
    data = cases.dataset(gentle)
    online = _smoother(data, keyframe_rate=25.0)
    for i, t in enumerate(data.imu.t):
        hit = np.flatnonzero(data.sensor("pose").data.t == t)
        if hit.size:
            m = int(hit[0])
            online.add("pose", t, data.sensor("pose").data.position[m], data.sensor("pose").data.C[m],
                       cov=data.sensor("pose").data.cov[m])
        online.add_imu(t, data.imu.acc[i], data.imu.gyro[i])
    online.finish()
    np.testing.assert_array_equal([e.t for e in online.smoothed()], keyframe_times(data, 25.0))


def test_bad_settings_are_one_line_and_what_finish_cannot_place_is_dropped_and_counted(recwarn):
    """Bad input is one clear InputError: an infinite grid rate, a covariance that is not positive
    definite, a sigma of the wrong length, a NaN keyframe time, no samples; what finish() cannot
    place (a measurement after the last IMU sample) is dropped and counted; a run without
    measurements reports its whole span as the gap."""
    import numpy as np
    import pytest as _pytest

    from factors.errors import InputError
    from factors.imu import ImuNoise, ImuState
    from smoother.online.smoother import OnlineSmoother, SensorSetup

    x0, P0 = ImuState.identity(), np.eye(15) * 0.01
    with _pytest.raises(InputError, match="keyframe_rate"):
        OnlineSmoother(x0, P0, ImuNoise(), keyframe_rate=np.inf)
    with _pytest.raises(InputError, match="initial_cov"):
        OnlineSmoother(x0, -np.eye(15), ImuNoise())
    with _pytest.raises(InputError, match=r"SensorSetup: sigma"):
        OnlineSmoother(x0, P0, ImuNoise(), sensors={"gps": SensorSetup("position", sigma=[1.0, 2.0])})
    online = OnlineSmoother(x0, P0, ImuNoise(), lag_s=0.5)
    with _pytest.raises(InputError, match="keyframe_at: t: expected finite times"):
        online.keyframe_at([np.nan, 0.5])
    with _pytest.raises(InputError, match="at least one sample"):
        online.add_imu(np.zeros(0), np.zeros((0, 3)), np.zeros((0, 3)))
    t = np.arange(0, 3.0, 0.01)
    online.add_imu(t, np.tile([0, 0, 9.81], (len(t), 1)), np.zeros((len(t), 3)))
    online.add("position", 5.0, np.zeros(3), cov=np.eye(3))  # after the last IMU sample
    online.finish()
    assert online.dropped == {"position": 1}
    assert online.longest_gap_s == _pytest.approx(t[-1])


def test_a_callback_that_raises_once_leaves_the_smoother_consistent(gentle):
    """on_smoothed is called after the smoother's own state has moved on: a caller that catches
    its callback's error and goes on gets the estimates of a run without the error (to 1e-9 m)."""
    data = cases.dataset(gentle)

    def run(fail_at):
        out, calls = {}, [0]

        def publish(e):
            calls[0] += 1
            if calls[0] == fail_at:
                raise OSError("publisher down")
            out[round(e.t, 6)] = e.state.r

        online = OnlineSmoother(data.initial, data.initial_cov, data.noise, gravity=data.gravity, lag_s=0.3,
                                on_smoothed=publish)
        online.keyframe_at(data.sensor("pose").data.t)
        online.add_measurements("pose", data.sensor("pose").data)
        for i, t in enumerate(data.imu.t):
            try:
                online.add_imu(t, data.imu.acc[i], data.imu.gyro[i])
            except OSError:
                pass
        online.finish()
        return out

    clean, caught = run(None), run(3)
    assert len(clean) - len(caught) <= 1  # only the estimate whose hand-over raised is missing
    assert max(np.linalg.norm(clean[t] - caught[t]) for t in caught) < 1e-9


def test_the_lag_warning_counts_the_gaps_between_fixes_not_between_wheel_speeds():
    """Wheel speeds at 10 Hz do not end dead reckoning: with fixes 2 s apart a 0.5-s lag is
    warned of (the wheel speeds' 0.1 s do not count as measurements' spacing), both offline and
    online; with a lag over the fixes' gap it is not."""
    from datasets.simulate import simulate
    from datasets.simulated_sensors import SensorSpec

    data = simulate("gentle", duration=8, seed=1, pose_rate=None, sensors=[
        SensorSpec("gnss", "gnss", 0.5, 0.3), SensorSpec("wheel", "velocity", 10, 0.05)])
    for lag, warned in ((0.5, True), (3.0, False)):
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always")
            run_fixed_lag(build_problem(data), lag, "incremental", progress=False)
            replay(data, lag, progress=False)
        hits = [w for w in caught if "longer than the lag" in str(w.message)]
        assert (len(hits) >= 2) == warned, (lag, [str(w.message) for w in caught])


def test_the_timing_records_keep_only_the_latest_entries(gentle, monkeypatch):
    """A robot runs for weeks: ``update_s`` and ``latency_s`` keep the latest
    :data:`smoother.fixed_lag.contract.HISTORY` entries (here 5), not every update since the start."""
    from smoother.fixed_lag import gtsam_window as fixed_lag
    from smoother.fixed_lag.sliding import window as sliding_window
    from smoother.online import smoother as online_module

    for module in (fixed_lag, online_module, sliding_window):
        monkeypatch.setattr(module, "HISTORY", 5)
    data = cases.dataset(gentle)
    result = replay(data, LAG, "sliding", covariances=False, progress=False)
    assert len(result.update_s) == 5 and len(result.latency_s) == 5
    assert len(result.smoothed.t) > 30  # far more updates than that


def _resting(n: int, rate: float = 200.0, t0: float = 0.0):
    """``n`` samples of an IMU at rest at ``rate`` Hz from ``t0``: times, specific force, rates."""
    return t0 + np.arange(n) / rate, np.tile([0.0, 0.0, 9.81], (n, 1)), np.zeros((n, 3))


def _plain(**options):
    from factors.imu import ImuNoise, ImuState

    return OnlineSmoother(ImuState.identity(), np.eye(15) * 0.01, ImuNoise(), lag_s=0.5, **options)


def test_imu_arrays_of_any_other_shape_are_refused_never_reshaped():
    """One sample is ``t`` a number with 3-vectors, N samples ``t (N,)`` with ``(N, 3)`` arrays:
    samples given as (3, N) (which a reshape would scramble), a single time with (1, 3) rows or
    (N,) times with one 3-vector are refused naming the argument and both shapes, and nothing is
    taken."""
    from factors.errors import InputError

    t, acc, gyro = _resting(5)
    online = _plain()
    with pytest.raises(InputError, match=re.escape("add_imu: acc: expected shape (5, 3) for 5 samples (t of shape "
                                                   "(5,)), got (3, 5)")):
        online.add_imu(t, acc.T, gyro)
    with pytest.raises(InputError, match=re.escape("add_imu: gyro: expected shape (5, 3) for 5 samples")):
        online.add_imu(t, acc, gyro.T)
    with pytest.raises(InputError, match=re.escape("add_imu: acc: expected shape (3,) for one sample (t a number), "
                                                   "got (1, 3)")):
        online.add_imu(t[0], acc[:1], gyro[0])
    with pytest.raises(InputError, match=re.escape("add_imu: acc: expected shape (1, 3) for 1 samples (t of shape "
                                                   "(1,)), got (3,)")):
        online.add_imu(t[:1], acc[0], gyro[0])
    with pytest.raises(InputError, match=re.escape("add_imu: t: expected a number (one sample) or shape (N,)")):
        online.add_imu(t.reshape(5, 1), acc, gyro)
    with pytest.raises(InputError, match="add_imu: acc: expected numbers"):
        online.add_imu(t[0], ["a", "b", "c"], gyro[0])
    assert online._n == 0
    online.add_imu(t[:3], acc[:3], gyro[:3])  # three samples, (3, 3): rows are samples, by the contract
    online.add_imu(t[3], acc[3], gyro[3])
    assert online._n == 4


def test_the_initial_state_covariance_and_sensor_setups_are_checked_at_construction():
    """An initial attitude 2 I (no rotation), a non-symmetric or non-positive-definite initial
    covariance, wrong shapes, a wrong gravity or noise, and sensor setups with a skewed
    extrinsic, a NaN time offset or a malformed robust kernel: refused at construction naming the
    field."""
    from factors.errors import InputError
    from factors.imu import ImuNoise, ImuState

    x0, P0, noise = ImuState.identity(), np.eye(15) * 0.01, ImuNoise()
    cases_ = [
        (dict(initial=replace(x0, C=2 * np.eye(3))), r"initial.C: row 0 is not a rotation matrix"),
        (dict(initial=replace(x0, r=np.zeros(2))), re.escape("initial.r: expected shape (3,), got (2,)")),
        (dict(initial=replace(x0, v=np.array([0, np.nan, 0]))), r"initial.v: non-finite value"),
        (dict(initial="identity"), "initial: expected an ImuState, got str"),
        (dict(initial_cov=P0 + np.triu(np.full((15, 15), 1e-3), 1)),
         "initial_cov: covariance at row 0 is not symmetric"),
        (dict(initial_cov=P0 - 0.02 * np.eye(15)), "initial_cov: covariance at row 0 is not positive definite"),
        (dict(initial_cov=np.eye(14)), re.escape("initial_cov: expected shape (15, 15), got (14, 14)")),
        (dict(noise=(1e-3, 1e-4)), "noise: expected an ImuNoise, got tuple"),
        (dict(gravity=[0, 0]), re.escape("gravity: expected shape (3,), got (2,)")),
        (dict(lag_s=np.inf), r"lag_s: expected a lag in seconds > 0 \(finite\), got inf"),
    ]
    for change, message in cases_:
        arguments = dict(initial=x0, initial_cov=P0, noise=noise) | change
        with pytest.raises(InputError, match=message):
            OnlineSmoother(arguments.pop("initial"), arguments.pop("initial_cov"), arguments.pop("noise"), **arguments)
    skewed = np.eye(4)
    skewed[0, 1] = 0.1
    with pytest.raises(InputError, match="SensorSetup.T_BS: expected a 4x4 rigid transform"):
        SensorSetup("position", T_BS=skewed)
    with pytest.raises(InputError, match="SensorSetup.time_offset: non-finite value"):
        SensorSetup("position", time_offset=np.nan)
    with pytest.raises(InputError, match="SensorSetup.robust: expected None or"):
        SensorSetup("position", robust="huber")
    with pytest.raises(InputError, match="SensorSetup.kind: expected one of"):
        SensorSetup("lidar")


def test_nan_inf_and_absurd_samples_are_refused_with_their_time_and_field():
    """NaN, inf and 1e31 in one sample or in a batch, and in a measurement's fields: refused,
    naming the field and the sample's time; the limits are the offline data types' (an axis
    beyond 2000 m/s^2 or beyond the gyro rate limit, positions beyond the distance limit); the
    refused sample is not taken and the stream goes on."""
    from datasets.types import max_gyro_rate
    from factors.errors import InputError

    t, acc, gyro = _resting(40)
    online = _plain()
    online.add_imu(t[:10], acc[:10], gyro[:10])
    for field, value, message in (("acc", np.nan, "non-finite value (NaN or inf) at row 0 (t = 0.050000 s)"),
                                  ("gyro", np.inf, "non-finite value (NaN or inf) at row 0 (t = 0.050000 s)"),
                                  ("acc", 1e31, "1e+31 m/s^2 at row 0 (t = 0.050000 s) is beyond the plausible "
                                                "+-2000 m/s^2"),
                                  ("gyro", -40.0, "-40 rad/s at row 0 (t = 0.050000 s) is beyond the plausible "
                                                  "+-35 rad/s")):
        sample = {"acc": acc[10].copy(), "gyro": gyro[10].copy()}
        sample[field][1] = value
        with pytest.raises(InputError, match=re.escape(f"add_imu: {field}: {message}")):
            online.add_imu(t[10], sample["acc"], sample["gyro"])
    with pytest.raises(InputError, match=re.escape("add_imu: t: non-finite value")):
        online.add_imu(np.nan, acc[10], gyro[10])
    batch = acc[10:20].copy()
    batch[4, 2] = 1e31
    with pytest.raises(InputError, match=re.escape("add_imu: acc: 1e+31 m/s^2 at row 4 (t = 0.070000 s)")):
        online.add_imu(t[10:20], batch, gyro[10:20])
    assert online._n == 10
    online.add_imu(t[10], acc[10], gyro[10])  # the stream goes on
    online.add_imu(t[11:20], acc[11:20], gyro[11:20])
    assert online._n == 20
    with pytest.raises(InputError, match=re.escape("add('position'): PositionMeasurements.position: 1e+31 m at row 0 "
                                                   "(t = 0.080000 s) is beyond the plausible")):
        online.add("position", t[16], [1e31, 0.0, 0.0], cov=np.eye(3))
    with pytest.raises(InputError, match=re.escape("add('position'): PositionMeasurements.position: non-finite value "
                                                   "(NaN or inf) at row 0 (t = 0.080000 s)")):
        online.add("position", t[16], [0.0, np.nan, 0.0], cov=np.eye(3))
    with pytest.raises(InputError, match=re.escape("add('velocity'): VelocityMeasurements.velocity: 1e+31 m/s")):
        online.add("velocity", t[16], [1e31, 0.0, 0.0], np.zeros(3), cov=np.eye(3))
    with max_gyro_rate(100.0):  # the limit in force when the smoother is made
        fast = _plain()
    fast.add_imu(t[0], acc[0], [0.0, 0.0, 60.0])
    with pytest.raises(InputError, match=re.escape("add_imu: gyro: 120 rad/s at row 0 (t = 0.005000 s) is beyond the "
                                                   "plausible +-100 rad/s")):
        fast.add_imu(t[1], acc[1], [0.0, 0.0, 120.0])


def test_a_step_back_in_time_is_an_error_and_a_measurement_from_another_clock_is_refused():
    """IMU samples are never reordered: a sample at or before the newest (one sample, or inside
    or at the start of a batch) is an error naming both times and the step back; measurements
    within ``max_delay_s`` are sorted into time, later ones dropped and counted (as documented),
    one stamped an hour after the IMU is refused."""
    from factors.errors import InputError

    t, acc, gyro = _resting(60)
    online = _plain()
    online.add_imu(t[:30], acc[:30], gyro[:30])
    with pytest.raises(InputError, match=re.escape(f"add_imu: t: IMU samples must come in strictly increasing time; "
                                                   f"got t = {float(t[28])!r} after {float(t[29])!r} (a step back of "
                                                   "0.005 s; samples are never reordered)")):
        online.add_imu(t[28], acc[28], gyro[28])
    with pytest.raises(InputError, match="add_imu: t: IMU samples must come in strictly increasing time"):
        online.add_imu(t[29], acc[29], gyro[29])
    with pytest.raises(InputError, match="add_imu: t: IMU samples must come in strictly increasing time"):
        online.add_imu(t[25:35], acc[25:35], gyro[25:35])
    inside = t[30:40].copy()
    inside[[4, 5]] = inside[[5, 4]]
    with pytest.raises(InputError, match=re.escape("add_imu: t: timestamps must increase strictly; row 5")):
        online.add_imu(inside, acc[30:40], gyro[30:40])
    online.add("position", t[10], np.zeros(3), cov=np.eye(3))  # older than the newest keyframe (t = 0)? no: kept
    online.add_imu(t[30:], acc[30:], gyro[30:])
    with pytest.warns(UserWarning, match="was dropped"):
        online.add("position", t[5], np.zeros(3), cov=np.eye(3))  # its keyframe time has been processed
    assert online.dropped == {"position": 1}
    with pytest.raises(InputError, match=r"add_measurements\('position'\): t: 3600.3.* s on the IMU clock lies "
                                         r"3600.* s after the newest IMU sample"):
        online.add("position", t[-1] + 3600.01, np.zeros(3), cov=np.eye(3))


def test_an_imu_gap_is_warned_of_as_offline_and_a_clock_jump_is_refused():
    """A 10-s gap in a 200 Hz stream is bridged with the offline path's warning (the same rule and
    text from :func:`datasets.types.imu_gaps`: its length and start) and counted, fed sample by
    sample or in one batch, also inside the first samples (before the typical period is known);
    a step of more than an hour is refused, online and offline."""
    from datasets.types import Dataset, ImuSamples
    from factors.errors import InputError
    from factors.imu import ImuNoise, ImuState

    t, acc, gyro = _resting(400)
    t[300:] += 10.0
    expected = ("1 gap(s) longer than 5 x the typical period (0.005 s); the longest is 10 s after t = 1.495000 s; "
                "each is bridged by holding the sample before it")
    for feed in ("one by one", "in a batch", "early"):
        online = _plain()
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always")
            if feed == "one by one":
                for k in range(len(t)):
                    online.add_imu(t[k], acc[k], gyro[k])
            elif feed == "in a batch":
                online.add_imu(t[:200], acc[:200], gyro[:200])
                online.add_imu(t[200:], acc[200:], gyro[200:])
            else:
                early = np.r_[t[:10], t[10:30] + 10.0]
                for k in range(len(early)):
                    online.add_imu(early[k], acc[k], gyro[k])
        texts = [str(w.message) for w in caught]
        assert len(texts) == 1 and online.imu_gaps == 1, (feed, texts)
        if feed != "early":
            assert texts[0] == f"online smoother: add_imu: {expected} (gaps are counted in .imu_gaps)"
            assert online.longest_imu_gap_s == pytest.approx(10.005)
    with pytest.warns(UserWarning, match=re.escape(f"Dataset.imu: {expected.replace('; each', ' (row 299); each')}")):
        Dataset("gap", ImuSamples(t, acc, gyro), ImuNoise(), ImuState.identity(), np.eye(15))
    online = _plain()
    online.add_imu(t[:50], acc[:50], gyro[:50])
    with pytest.raises(InputError, match=re.escape("online smoother: add_imu: t: a step of 7200 s after "
                                                   "t = 0.245000 s, beyond any plausible gap (3600 s): "
                                                   "a jump of the clock")):
        online.add_imu(t[49] + 7200.0, acc[50], gyro[50])
    with pytest.raises(InputError, match="a jump of the clock"):
        online.add_imu(t[50:60] + 7200.0, acc[50:60], gyro[50:60])
    online.add_imu(t[50], acc[50], gyro[50])  # nothing was taken
    t[300:] += 7200.0
    with pytest.raises(InputError, match=re.escape("Dataset.imu: t: a step of 7210.01 s after t = 1.495000 s "
                                                   "(row 299)")):
        Dataset("jump", ImuSamples(t, acc, gyro), ImuNoise(), ImuState.identity(), np.eye(15))
