"""Self-initialisation (datasets.initialise): the initial state, its sigmas and its refusals, with no
ground truth (the estimators started from it: ``tests/smoother/test_self_initialisation.py``)."""
import numpy as np
import pytest
from initialisation_rig import CAMERA, GNSS, WHEEL

from datasets.initialise import InitialisationError, imu_from, initial_state, self_initialised
from datasets.kinds import sensors_of
from datasets.simulate import simulate
from factors import so3


def test_at_rest_the_velocity_is_zero_and_roll_pitch_come_from_gravity():
    data = simulate("static", duration=5, seed=1, pose_rate=None, sensors=[CAMERA])
    _, state, cov = initial_state(data.imu, sensors_of(data), data.gravity)
    assert np.allclose(state.v, 0) and np.sqrt(cov[3, 3]) <= 0.05


def test_without_a_heading_source_one_line_says_what_is_missing():
    data = simulate("static", duration=5, seed=1, pose_rate=None, sensors=[GNSS])  # never moves 5 m
    with pytest.raises(InitialisationError, match="cannot fix the initial heading: no pose or orientation sensor"):
        self_initialised(data)


def test_imu_from_a_time_between_samples_holds_the_sample_before():
    data = simulate("gentle", duration=1, seed=0)
    t_s = 0.5 * (data.imu.t[10] + data.imu.t[11])
    cut = imu_from(data.imu, t_s)
    assert cut.t[0] == t_s and np.array_equal(cut.t[1:], data.imu.t[11:])
    assert np.array_equal(cut.gyro[0], data.imu.gyro[10]) and np.array_equal(cut.acc[1:], data.imu.acc[11:])


def _remounted(data, R):
    """``data`` as recorded by the same IMU mounted rotated by ``R`` (``C' = C R``): readings in
    the new axes, the sensors' extrinsics re-expressed (the sensors stay where they are)."""
    from dataclasses import replace

    from datasets.types import ImuSamples, Sensor

    T = np.eye(4)
    T[:3, :3] = R.T
    sensors = []
    for s in data.sensors:
        m = replace(s.data, T_BS=T @ s.data.T_BS)
        if s.kind == "velocity":
            m = replace(m, gyro=m.gyro @ R)
        sensors.append(Sensor(s.name, s.kind, m))
    imu = ImuSamples(data.imu.t, data.imu.acc @ R, data.imu.gyro @ R)
    return replace(data, imu=imu, sensors=tuple(sensors))


def test_an_imu_on_its_side_gets_its_heading_from_the_wheels():
    """The IMU's z axis horizontal (x pointing down): the wheel speed's direction, levelled in the
    world, gives the heading, not the IMU's x axis (90 deg off on a real Husky recording)."""
    data = simulate("gentle", duration=20, seed=2, pose_rate=None, sensors=[GNSS, WHEEL])
    R = so3.exp([0.0, np.pi / 2, 0.0])  # body x -> world down
    started = self_initialised(_remounted(data, R))
    k = np.searchsorted(data.truth.t, started.t0)
    error = np.linalg.norm(so3.boxminus(started.initial.C, data.truth.C[k] @ R))
    assert error < 3 * np.sqrt(started.initial_cov[6:9, 6:9].diagonal().max()), np.rad2deg(error)
    no_wheels = replace_sensors(_remounted(data, R), keep=("gnss",))
    with pytest.raises(InitialisationError, match="is not horizontal; it is the vehicle's forward direction in the "
                                                  r"IMU frame, \[1.0, 0.0, 0.0\] \(the rig's \[imu\] forward\)"):
        self_initialised(no_wheels)
    from dataclasses import replace as _replace

    sideways = _remounted(data, R)
    wheel = sideways.sensors[1]  # its T_BS left as if the IMU were not remounted: the wheel frame turned up
    wrong = _replace(sideways, sensors=(sideways.sensors[0], _replace(wheel, data=_replace(
        wheel.data, T_BS=data.sensors[1].data.T_BS))))
    with pytest.raises(InitialisationError, match="velocity sensor 'wheel'.s measured direction: check the rotation"):
        self_initialised(wrong)


def test_an_imu_mounted_backwards_needs_the_vehicles_forward_direction():
    """GNSS only, the IMU turned 180 deg about its z axis (x pointing backwards): taking the IMU's
    x axis as the direction of travel starts the heading 180 deg off; given ``forward = (-1, 0,
    0)`` the start is within its own 3 sigma."""
    data = simulate("gentle", duration=20, seed=2, pose_rate=None, sensors=[GNSS])
    R = so3.exp([0.0, 0.0, np.pi])
    backwards = _remounted(data, R)
    k = np.searchsorted(data.truth.t, self_initialised(backwards).t0)
    wrong = np.linalg.norm(so3.boxminus(self_initialised(backwards).initial.C, data.truth.C[k] @ R))
    assert wrong > np.deg2rad(150.0), np.rad2deg(wrong)
    started = self_initialised(backwards, forward=(-1.0, 0.0, 0.0))
    error = np.linalg.norm(so3.boxminus(started.initial.C, data.truth.C[k] @ R))
    assert error < 3 * np.sqrt(started.initial_cov[6:9, 6:9].diagonal().max()), np.rad2deg(error)


def replace_sensors(data, keep):
    from dataclasses import replace

    return replace(data, sensors=tuple(s for s in data.sensors if s.name in keep))


# Hand-made level straight-line drives (IMU at rest in its own axes: constant velocity), true
# heading 30 deg: the cases a review found the first version of the initialisation got wrong.

GRAVITY = np.array([0.0, 0.0, -9.81])
YAW = np.deg2rad(30.0)


def _straight_drive(speed, t_imu=(0.0, 60.0), t_gnss=(0.0, 60.0), gnss_rate=1.0, gnss_sigma=0.1, wheels=True):
    """``(imu, sensors)``: a vehicle along the 30-deg line at ``speed(t)`` [m/s] (body x forward),
    fixes of ``gnss_sigma`` (one for all axes, or east, north, up) at ``gnss_rate`` over ``t_gnss``,
    wheel speeds at 10 Hz over the IMU's span."""
    from datasets.types import ImuSamples, PositionMeasurements, Sensor, VelocityMeasurements

    t = np.arange(*t_imu, 0.01)
    imu = ImuSamples(t, np.tile([0.0, 0.0, 9.81], (len(t), 1)), np.zeros((len(t), 3)))
    fine = np.arange(min(t_imu[0], t_gnss[0]) - 1.0, max(t_imu[1], t_gnss[1]) + 1.0, 0.001)
    travelled = np.cumsum(speed(fine)) * 0.001
    heading = np.array([np.cos(YAW), np.sin(YAW), 0.0])
    tf = np.arange(*t_gnss, 1.0 / gnss_rate)
    sigma = np.broadcast_to(np.asarray(gnss_sigma, dtype=float), (3,))
    z = np.interp(tf, fine, travelled)[:, None] * heading + np.random.default_rng(0).normal(size=(len(tf), 3)) * sigma
    sensors = [Sensor("gnss", "gnss", PositionMeasurements(tf, z, np.diag(sigma**2)))]
    if wheels:
        tv = t[::10]
        sensors.append(Sensor("wheel", "velocity", VelocityMeasurements(
            tv, np.stack([speed(tv), 0 * tv, 0 * tv], axis=1), np.zeros((len(tv), 3)), np.eye(3) * 0.01)))
    return imu, sensors


def _yaw_deg(C):
    return np.rad2deg(np.arctan2(C[1, 0], C[0, 0]))


def test_cruising_at_constant_speed_is_not_taken_for_rest():
    imu, sensors = _straight_drive(lambda t: np.full_like(t, 10.0))
    _, state, cov = initial_state(imu, sensors, GRAVITY)
    assert np.allclose(state.v, [10.0, 0, 0], atol=0.2) and abs(_yaw_deg(state.C) - 30.0) < 2.0


def test_reversing_out_of_a_parking_spot_gives_the_right_heading_with_wheels():
    imu, sensors = _straight_drive(lambda t: np.where(t < 10, -2.0, 5.0))
    _, state, _ = initial_state(imu, sensors, GRAVITY)
    assert abs(_yaw_deg(state.C) - 30.0) < 2.0, _yaw_deg(state.C)


def test_noisy_fixes_give_a_velocity_with_an_honest_sigma():
    """Parked with 10 Hz fixes of 1.5 m: the first two fixes' difference was 44 m/s with a sigma
    of 1 m/s; the line through 2 s of fixes is within its own sigma."""
    from datasets.initialise import initial_velocity

    imu, sensors = _straight_drive(lambda t: np.zeros_like(t), gnss_rate=10.0, gnss_sigma=1.5, wheels=False)
    v, sigma = initial_velocity(imu, 0.0, GRAVITY, np.eye(3), [], [(s, s.data) for s in sensors])
    assert np.linalg.norm(v) < 3 * sigma and sigma < 2.0


@pytest.mark.parametrize("speed", [10.0, 3.0])
def test_cruising_with_a_receivers_vertical_sigma_twice_its_horizontal_is_not_taken_for_rest(speed):
    """A smooth cruise (the IMU reads as at rest) with 10 Hz fixes of 2.5 m horizontal, 5 m
    vertical sigma: 2 s of fixes move 20 m at 10 m/s -- less than three times the vertical sigma
    times sqrt(2), the threshold the largest sigma once set, which took the car for parked with
    0.05 m/s -- but forty horizontal sigmas of the line's slope. At 3 m/s the slope is still many
    of its sigmas from zero. Either way the velocity is within its sigma of the truth."""
    from datasets.initialise import REST_VELOCITY_SIGMA, initial_velocity

    imu, sensors = _straight_drive(lambda t: np.full_like(t, speed), gnss_rate=10.0, gnss_sigma=(2.5, 2.5, 5.0),
                                   wheels=False)
    truth = speed * np.array([np.cos(YAW), np.sin(YAW), 0.0])
    v, sigma = initial_velocity(imu, 0.0, GRAVITY, np.eye(3), [], [(s, s.data) for s in sensors])
    assert sigma > REST_VELOCITY_SIGMA and np.linalg.norm(v - truth) < 3 * sigma, (v, sigma)
    _, state, cov = initial_state(imu, sensors, GRAVITY)
    assert np.abs(state.C @ state.v - truth).max() < 3 * np.sqrt(cov[3, 3])


def test_parked_with_a_quiet_imu_and_fixes_that_cannot_tell_the_velocity_is_zero_within_what_they_allow():
    """Parked, fixes of 2.5 / 5 m: zero, with a sigma of the fixes' slope (not the 0.05 m/s of a
    rest the fixes cannot confirm); with centimetre fixes, the rest's own 0.05 m/s."""
    from datasets.initialise import REST_VELOCITY_SIGMA, initial_velocity

    for gnss_sigma, most in (((2.5, 2.5, 5.0), 10.0), (0.02, REST_VELOCITY_SIGMA)):
        imu, sensors = _straight_drive(lambda t: np.zeros_like(t), gnss_rate=10.0, gnss_sigma=gnss_sigma, wheels=False)
        v, sigma = initial_velocity(imu, 0.0, GRAVITY, np.eye(3), [], [(s, s.data) for s in sensors])
        assert np.all(v == 0) and REST_VELOCITY_SIGMA <= sigma <= most, (gnss_sigma, sigma)


@pytest.mark.parametrize("speed", [10.0, 0.0])
def test_fixes_further_apart_than_the_velocity_window_give_their_mean_velocity_not_a_rest(speed):
    """A smooth cruise (the IMU reads as at rest) with one fix every 10 s (a sensor's ``every``
    thinning 1-Hz fixes, as on KITTI): the two first fixes' mean velocity with the unknown
    velocity's sigma, not a rest of 0.05 m/s that took a car at 9 m/s for parked; parked, the
    same fixes still say zero."""
    from datasets.initialise import REST_VELOCITY_SIGMA, UNKNOWN_VELOCITY_SIGMA, initial_velocity

    imu, sensors = _straight_drive(lambda t: np.full_like(t, speed), gnss_rate=0.1, wheels=False)
    truth = speed * np.array([np.cos(YAW), np.sin(YAW), 0.0])
    v, sigma = initial_velocity(imu, 0.0, GRAVITY, np.eye(3), [], [(s, s.data) for s in sensors])
    assert np.linalg.norm(v - truth) < 0.1, v
    assert sigma == (UNKNOWN_VELOCITY_SIGMA if speed else REST_VELOCITY_SIGMA), sigma
    if speed:  # (parked, nothing gives the heading: refused, as it should be)
        _, state, cov = initial_state(imu, sensors, GRAVITY)
        assert np.abs(state.C @ state.v - truth).max() < 0.1 and np.sqrt(cov[3, 3]) >= UNKNOWN_VELOCITY_SIGMA


def test_fixes_before_the_imu_starts_are_not_taken_for_its_position():
    imu, sensors = _straight_drive(lambda t: np.full_like(t, 10.0), t_imu=(10.0, 60.0), t_gnss=(0.0, 60.0))
    t_s, state, _ = initial_state(imu, sensors, GRAVITY)
    fixes = sensors[0].data
    assert t_s == 10.0 and np.allclose(state.r, fixes.position[fixes.t == t_s][0])  # not the fix at 0 s, 100 m back
