"""The data types: validation at construction, and the documented behaviour for data a user can
reasonably feed (out-of-span measurements, IMU gaps) -- a warning and a documented action."""
import re
import warnings

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st
from hypothesis.extra import numpy as hnp

from datasets.kinds import sensors_of
from datasets.types import (
    SAME_INSTANT_S,
    Dataset,
    ImuSamples,
    PoseMeasurements,
    PositionMeasurements,
    RelativePoseMeasurements,
    Sensor,
    Trajectory,
)
from factors import imu, so3
from factors.errors import InputError


def _imu(n=101, rate=100.0, t0=0.0):
    t = t0 + np.arange(n) / rate
    return ImuSamples(t, np.tile([0.0, 0.0, 9.81], (n, 1)), np.zeros((n, 3)))


def _dataset(**kw):
    base = dict(name="test", imu=_imu(), noise=imu.ImuNoise(), initial=imu.ImuState.identity(),
                initial_cov=np.eye(15) * 0.01)
    base.update(kw)
    return Dataset(**base)


def test_measurements_outside_the_imu_span_are_dropped_with_a_warning():
    t = np.array([-0.5, 0.0, 0.5, 1.0, 1.5])
    gps = PositionMeasurements(t, np.zeros((5, 3)), np.eye(3))
    with pytest.warns(UserWarning, match=r"sensor 'gps': 2 of 5 .* outside the IMU span"):
        d = _dataset(sensors=(Sensor("gps", "position", gps),))
    np.testing.assert_array_equal(d.sensor("gps").data.t, [0.0, 0.5, 1.0])


def test_relative_poses_reaching_outside_the_span_are_dropped():
    rel = RelativePoseMeasurements([0.0, 0.8], [0.5, 1.2], np.zeros((2, 3)), np.tile(np.eye(3), (2, 1, 1)),
                                   np.eye(6))
    with pytest.warns(UserWarning, match="sensor 'wheels': 1 of 2"):
        d = _dataset(sensors=(Sensor("wheels", "odometry", rel),))
    assert len(d.sensor("wheels").data) == 1


def test_an_imu_gap_is_reported_with_its_time_and_length():
    t = np.concatenate([np.arange(50) / 100.0, 1.0 + np.arange(50) / 100.0])
    samples = ImuSamples(t, np.tile([0.0, 0.0, 9.81], (100, 1)), np.zeros((100, 3)))
    with pytest.warns(UserWarning, match=r"longest is 0.51 s after t = 0.490000 s \(row 49\)"):
        _dataset(imu=samples)


def test_clean_data_gives_no_warning():
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        pose = PoseMeasurements([0.0, 1.0], np.zeros((2, 3)), np.tile(np.eye(3), (2, 1, 1)), np.eye(6))
        _dataset(sensors=(Sensor("pose", "pose", pose),))


def test_sensors_are_named_once_and_found_by_name():
    pose = PoseMeasurements([0.0, 1.0], np.zeros((2, 3)), np.tile(np.eye(3), (2, 1, 1)), np.eye(6))
    d = _dataset(sensors=[Sensor("a", "pose", pose)])
    assert d.sensors == (d.sensor("a"),) and d.sensor_names == ("a",)
    with pytest.raises(InputError, match="no sensor 'b'; its sensors: a"):
        d.sensor("b")
    with pytest.raises(InputError, match="sensor name 'a' is used twice"):
        _dataset(sensors=(Sensor("a", "pose", pose), Sensor("a", "pose", pose)))
    with pytest.raises(InputError, match=r"Dataset.sensors\[0\]: expected a Sensor"):
        _dataset(sensors=(pose,))
    thinned = d.with_sensor("a", data=pose.subset(np.array([True, False])))
    assert len(thinned.sensor("a").data) == 1 and len(d.sensor("a").data) == 2


@pytest.mark.parametrize("tau, fragment", [
    (0.0, "expected a value within [0.01, 86400] s"),
    (1e-300, "got 1e-300"),
    (1e300, "got 1e+300"),
    (float("nan"), "got nan"),
    (True, "expected a number of seconds, got True"),
    ("5", "expected a number of seconds, got '5'"),
])
def test_a_correlation_time_is_checked_as_the_rig_checks_it_naming_the_sensor(tau, fragment):
    """The range of the rig key ``correlation_time`` holds for a dataset built in code too, as the rig
    and the command line hold it (1e300 would run the EKF silently)."""
    pose = PoseMeasurements([0.0, 1.0], np.zeros((2, 3)), np.tile(np.eye(3), (2, 1, 1)), np.eye(6))
    with pytest.raises(InputError, match=re.escape("sensor 'a': correlation_time: ") + ".*" + re.escape(fragment)):
        _dataset(sensors=(Sensor("a", "pose", pose, correlation_time=tau),))
    assert _dataset(sensors=(Sensor("a", "pose", pose, correlation_time=np.float32(5.0)),))


def test_a_correlation_time_to_fit_needs_held_out_measurements_and_no_time_given():
    """A fit of the correlation time (:attr:`Sensor.fit_correlation_time`) reads the held-out
    measurements between used ones: a sensor without both, or with a time given as well, is refused."""
    pose = PoseMeasurements([0.0, 1.0], np.zeros((2, 3)), np.tile(np.eye(3), (2, 1, 1)), np.eye(6))
    with pytest.raises(InputError, match="sensor 'a': correlation_time: fitting it needs measurements used and held "
                                         "out"):
        _dataset(sensors=(Sensor("a", "pose", pose, fit_correlation_time=True),))
    with pytest.raises(InputError, match=r"sensor 'a': correlation_time: given \(5 s\) and to be fitted"):
        _dataset(sensors=(Sensor("a", "pose", pose, pose, correlation_time=5.0, fit_correlation_time=True),))
    d = _dataset(sensors=(Sensor("a", "pose", pose, pose, fit_correlation_time=True), Sensor("b", "pose", pose)))
    assert d.correlation_to_fit == ("a",) and d.correlation_times == {}


def test_a_relative_kind_with_a_correlation_time_is_refused_by_every_estimator_naming_it():
    """Where kinds are checked (:func:`datasets.kinds.sensors_of`, which every estimator calls), as
    the rig and ``SensorSetup`` refuse it: the drift model chains measurements of one state each."""
    rel = RelativePoseMeasurements([0.0, 0.5], [0.4, 0.9], np.zeros((2, 3)), np.tile(np.eye(3), (2, 1, 1)), np.eye(6))
    d = _dataset(sensors=(Sensor("wheels", "odometry", rel, correlation_time=5.0),))
    with pytest.raises(InputError, match="sensor 'wheels': correlation_time: odometry measurements are relative"):
        sensors_of(d)


def test_an_empty_set_of_measurements_is_none():
    """A sensor whose every measurement is held out, given as an empty set of used ones, is one with
    none (``data`` None: it only scores), as an empty held-out set is none held out -- not numpy's
    error from the message about the IMU span, which has no stamps to name."""
    pose = PoseMeasurements([0.0, 1.0], np.zeros((2, 3)), np.tile(np.eye(3), (2, 1, 1)), np.eye(6))
    nothing = pose.subset(np.array([False, False]))
    d = _dataset(sensors=(Sensor("a", "pose", nothing, heldout=pose), Sensor("b", "pose", pose, heldout=nothing)))
    assert d.sensor("a").data is None and len(d.sensor("a").heldout) == 2
    assert d.sensor("b").heldout is None and len(d.sensor("b").data) == 2


@pytest.mark.parametrize("field, value, fragment", [
    ("initial", imu.ImuState.identity().replace(r=np.array([np.nan, 0, 0])), "non-finite"),
    ("initial", imu.ImuState.identity().replace(C=np.diag([1.0, 1.0, -1.0])), "not a rotation"),
    ("initial_cov", -np.eye(15), "positive definite"),
    ("initial_cov", np.eye(14), "(15, 15)"),
    ("gravity", np.array([0.0, np.inf, 0.0]), "gravity"),
])
def test_bad_dataset_fields_raise_naming_the_field(field, value, fragment):
    with pytest.raises(ValueError, match="Dataset") as info:
        _dataset(**{field: value})
    assert fragment in str(info.value)


@given(hnp.arrays(np.float64, st.tuples(st.integers(0, 6), st.integers(0, 5)),
                  elements=st.floats(allow_nan=True, allow_infinity=True, width=64)),
       hnp.arrays(np.float64, st.integers(0, 6), elements=st.floats(allow_nan=True, allow_infinity=True)))
def test_fuzzed_arrays_give_value_errors_or_valid_objects(values, times):
    """Any array shape and content fed to the constructors: either a ValueError naming the class,
    or an object whose arrays have the documented shapes and are finite -- never another exception
    and never silently wrong data."""
    for make in (
        lambda: ImuSamples(times, values, values),
        lambda: PositionMeasurements(times, values, np.eye(3)),
        lambda: PoseMeasurements(times, values, np.tile(np.eye(3), (len(times), 1, 1)), np.eye(6)),
    ):
        try:
            obj = make()
        except ValueError as error:
            assert any(name in str(error) for name in ("ImuSamples", "PositionMeasurements", "PoseMeasurements"))
        else:
            assert obj.t.shape == (len(times),) and np.all(np.isfinite(obj.t))
            assert np.all(np.diff(obj.t) > 0)
            for arr in (getattr(obj, a) for a in ("acc", "gyro", "position") if hasattr(obj, a)):
                assert arr.shape == (len(times), 3) and np.all(np.isfinite(arr))


def test_rotation_check_names_the_row():
    C = np.tile(np.eye(3), (3, 1, 1))
    C[2] = so3.exp([0.1, 0, 0]) * 1.01
    with pytest.raises(ValueError, match="row 2 is not a rotation matrix"):
        PoseMeasurements([0.0, 1.0, 2.0], np.zeros((3, 3)), C, np.eye(6))


def test_an_accelerometer_in_g_is_reported():
    n = 101
    t = np.arange(n) / 100.0
    samples = ImuSamples(t, np.tile([0.0, 0.0, 1.0], (n, 1)), np.tile([0.0, 0.0, 1.0], (n, 1)))
    with pytest.warns(UserWarning, match=re.escape("is the data in g")):
        _dataset(imu=samples)


def test_samples_beyond_any_imu_range_are_refused_with_their_time_and_field():
    """An accelerometer in mm/s^2 (9810 on z at rest), one absurd accelerometer sample and one gyro
    sample beyond the full scale of the rate limit: refused, naming the field, row and time."""
    n = 101
    t = np.arange(n) / 100.0
    acc, gyro = np.tile([0.0, 0.0, 9.81], (n, 1)), np.zeros((n, 3))
    with pytest.warns(UserWarning, match=re.escape("mm/s^2")), pytest.raises(
            InputError, match=re.escape("Dataset.imu.acc: 9810 m/s^2 at row 0 (t = 0.000000 s) is beyond the "
                                        "plausible +-2000 m/s^2")):
        _dataset(imu=ImuSamples(t, acc * 1000.0, gyro))
    bad = acc.copy()
    bad[40, 1] = 1e31
    with pytest.raises(InputError, match=re.escape("Dataset.imu.acc: 1e+31 m/s^2 at row 40 (t = 0.400000 s)")):
        _dataset(imu=ImuSamples(t, bad, gyro))
    bad = gyro.copy()
    bad[7, 2] = -40.0
    with pytest.raises(InputError, match=re.escape("Dataset.imu.gyro: -40 rad/s at row 7 (t = 0.070000 s) is beyond "
                                                   "the plausible +-35 rad/s")):
        _dataset(imu=ImuSamples(t, acc, bad))


def test_gyro_rates_no_vehicle_reaches_are_refused_unless_allowed():
    """A turn at 1 rad/s written in deg/s (57.3 "rad/s", beyond the 35 rad/s limit): refused with
    the likely cause; inside ``max_gyro_rate(100)`` accepted; at 30 rad/s accepted as is."""
    from datasets.types import max_gyro_rate

    n = 101
    t = np.arange(n) / 100.0
    acc = np.tile([0.0, 0.0, 9.81], (n, 1))
    with pytest.raises(ValueError, match=re.escape("Dataset.imu.gyro: 99th percentile angular rate 57.3, above 35 "
                                                   "rad/s that no vehicle reaches; the data are probably in deg/s")):
        _dataset(imu=ImuSamples(t, acc, np.tile([0.0, 0.0, 57.3], (n, 1))))
    with max_gyro_rate(100.0):
        _dataset(imu=ImuSamples(t, acc, np.tile([0.0, 0.0, 57.3], (n, 1))))
    _dataset(imu=ImuSamples(t, acc, np.tile([0.0, 0.0, 30.0], (n, 1))))


def _cov_cases():
    good = np.tile(np.eye(15) * 0.01, (3, 1, 1))
    nan, negative, asymmetric, indefinite = (good.copy() for _ in range(4))
    nan[1, 0, 0] = np.nan
    negative[1, 0, 0] = -1.0
    asymmetric[1, 0, 5] = 0.005
    indefinite[1, 0, 1] = indefinite[1, 1, 0] = 0.02  # |off-diagonal| > diagonal: one negative eigenvalue
    return [(nan, "non-finite value (NaN or inf) at row 1"), (negative, "row 1 is not positive definite"),
            (asymmetric, "row 1 is not symmetric"), (indefinite, "row 1 is not positive definite")]


@pytest.mark.parametrize("cov, fragment", _cov_cases())
def test_trajectory_covariances_are_checked(cov, fragment):
    """An estimate's covariances feed NEES: NaN, asymmetric or indefinite ones are refused by
    name instead of giving a silently wrong consistency figure."""
    from datasets.types import Trajectory
    states = imu.ImuState(np.zeros((3, 3)), np.zeros((3, 3)), np.tile(np.eye(3), (3, 1, 1)), np.zeros((3, 3)),
                          np.zeros((3, 3)))
    Trajectory(np.arange(3.0), states, np.tile(np.eye(15) * 0.01, (3, 1, 1)))  # a good one passes
    with pytest.raises(ValueError, match=re.escape("Trajectory.cov")) as info:
        Trajectory(np.arange(3.0), states, cov)
    assert fragment in str(info.value)


def _two_states(t=(0.0, 1.0), phi=(0.0, 0.0, 0.8)):
    C = np.stack([np.eye(3), so3.exp(phi)])
    states = imu.ImuState(r=np.array([[0.0, 0, 0], [2.0, 0, 0]]), v=np.zeros((2, 3)), C=C,
                          b_f=np.zeros((2, 3)), b_w=np.zeros((2, 3)))
    return Trajectory(np.array(t), states, np.stack([np.eye(15), 3 * np.eye(15)]))


def test_interpolate_is_exact_at_samples_and_geodesic_between():
    traj = _two_states()
    s, cov, inside = traj.interpolate(np.array([-1.0, 0.0, 0.25, 1.0 + 0.5 * SAME_INSTANT_S, 2.0]))
    assert inside.tolist() == [False, True, True, True, False]
    np.testing.assert_allclose(s.r[:, 0], [0.0, 0.5, 2.0])
    np.testing.assert_allclose(s.C[0], traj.C[0], atol=0)
    np.testing.assert_allclose(s.C[2], traj.C[1], atol=0)
    np.testing.assert_allclose(s.C[1], so3.exp(0.25 * np.array([0.0, 0.0, 0.8])), atol=1e-12)
    np.testing.assert_allclose(cov[1], 1.5 * np.eye(15))


def test_interpolate_bridges_no_step_longer_than_max_step():
    traj = _two_states()
    _, _, inside = traj.interpolate(np.array([0.0, 0.5, 1.0]), max_step=0.5)
    assert inside.tolist() == [True, False, True]  # the samples themselves stay
    assert traj.interpolate(np.array([0.5]), max_step=1.0)[2].tolist() == [True]
