"""The mounting check (smoother/diagnosis/mounting.py, mounting_data.py, imu_integrals.py) on
simulated rigs whose data were made with the true mounting and whose rig states another one:

* a rig off by a quarter or a half turn about any sensor axis is named, with exactly the sensor
  axes that the two rotations put on different IMU axes, for a velocity, a pose, an orientation,
  an odometry and a roll_pitch sensor; wheels turned about the vertical on a drive are named by
  their forward axis, also when they read exact zeros across it (a differential-drive odometer);
* a rig mounted right gives no warning over 20 seeds with random mountings, and the data's
  rotation is within a few degrees of the truth, also with a poor gyro, an accelerometer bias or
  outliers in the attitudes;
* a motion that excites one axis only (yawing in place, driving in a straight line, standing
  still) reports the rotation about it as not determined, does not flag a rig that differs only
  there, and still flags one that differs elsewhere; without motion, or only in a steady turn for
  the vertical, nothing is checked;
* the closed forms (the nearest rotation along an undetermined direction, the verdict's two
  bounds, the IMU's integrals inside a step, the blocked prefix products) hold for arbitrary
  inputs.
"""
from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest
import strategies
from hypothesis import given, settings
from hypothesis import strategies as st

from datasets.simulate import simulate
from datasets.simulated_sensors import SensorSpec
from datasets.trajectories import Sinusoids, sinusoid_profile
from datasets.types import ImuSamples, OrientationMeasurements, Sensor, VelocityMeasurements
from factors import so3
from factors.scan import prefix_products
from smoother.diagnosis.imu_integrals import ImuIntegrals, chained
from smoother.diagnosis.mounting import (
    AXIS_NAMES,
    WRONG_ANGLE_DEG,
    MountingFinding,
    NotChecked,
    check_mountings,
    compare,
)
from smoother.diagnosis.mounting_data import DataRotation, minimum_norm_solution

#: A camera-like mounting, a little off the axes: the sensor's z on the IMU's x, its x on -y, its
#: y on -z, turned by 4 degrees about a skew axis.
R_TRUE = so3.exp(np.array([0.05, -0.03, 0.04])) @ np.array([[0.0, 0.0, 1.0], [-1.0, 0.0, 0.0], [0.0, -1.0, 0.0]])
LEVER = np.array([0.2, -0.1, 0.3])

#: Rocking in place, slowly enough for the vertical to be seen at low dynamics, over tilts that
#: determine the rotation about the vertical too.
ROCKING = sinusoid_profile(
    "rocking", "rocking in place by up to 0.5 rad in roll and pitch",
    position=(Sinusoids(), Sinusoids(), Sinusoids(offset=1.0)),
    attitude=(Sinusoids(terms=((0.5, 0.5, 0.0),)), Sinusoids(terms=((0.5, 0.4, 1.5),)),
              Sinusoids(offset=0.3, terms=((0.3, 0.3, 0.0),))))
#: Turning back and forth about the vertical in place: only the IMU's z axis turns.
YAWING = sinusoid_profile(
    "yawing", "turning about the vertical in place, both ways",
    position=(Sinusoids(), Sinusoids(), Sinusoids(offset=1.0)),
    attitude=(Sinusoids(), Sinusoids(), Sinusoids(terms=((1.0, 0.9, 0.0), (0.4, 2.3, 0.5)))))
#: Wandering over a few metres, turning slowly about every axis (spans of a second and more).
WANDERING = sinusoid_profile(
    "wandering", "a 6 m x 4 m x 1 m Lissajous at up to 1 m/s, turning by up to 1 rad at 0.2-0.3 rad/s",
    position=(Sinusoids(terms=((3.0, 0.35, 0.0),)), Sinusoids(terms=((2.0, 0.5, 0.7),)),
              Sinusoids(offset=1.0, terms=((0.5, 0.6, 1.1),))),
    attitude=(Sinusoids(terms=((0.6, 0.3, 0.0),)), Sinusoids(terms=((0.5, 0.25, 1.0),)),
              Sinusoids(terms=((1.0, 0.2, 0.5),))))
#: Driving in a circle of 6 m at 3 m/s: a centripetal acceleration of 1.5 m/s^2 throughout.
CIRCLING = sinusoid_profile(
    "circling", "a circle of 6 m radius at 3 m/s, heading along it",
    position=(Sinusoids(terms=((6.0, 0.5, np.pi / 2),)), Sinusoids(terms=((6.0, 0.5, 0.0),)), Sinusoids(offset=1.0)),
    attitude=(Sinusoids(), Sinusoids(), Sinusoids(offset=np.pi, slope=0.5)))
#: Back and forth along the world's (and the body's) x without turning.
LINE = sinusoid_profile(
    "line", "back and forth along x, never turning",
    position=(Sinusoids(terms=((3.0, 0.8, 0.0), (0.5, 2.1, 0.3))), Sinusoids(), Sinusoids(offset=1.0)),
    attitude=(Sinusoids(), Sinusoids(), Sinusoids()))

#: The sensors of the tumbling rig (every kind with a rotation but roll_pitch, which needs calm).
TUMBLING_KINDS = {"wheels": ("velocity", 50.0, 0.05), "camera": ("pose", 20.0, (0.05, 0.01)),
                  "ahrs": ("orientation", 50.0, 0.01), "visual_odometry": ("odometry", 20.0, (0.02, 0.005))}
ROCKING_KINDS = {"inclinometer": ("roll_pitch", 20.0, 0.01)}


def _T(R, p=LEVER):
    T = np.eye(4)
    T[:3, :3], T[:3, 3] = R, p
    return T


def _rig(profile, duration, kinds, seed=0, R=R_TRUE, **options):
    """A simulated dataset whose sensors of ``kinds`` are mounted at ``R`` (and :data:`LEVER`);
    ``options`` go to the simulator."""
    specs = [SensorSpec(name, kind, rate, sigma, _T(R)) for name, (kind, rate, sigma) in kinds.items()]
    return simulate(profile, duration=duration, seed=seed, imu_rate=200.0, sensors=specs, pose_rate=None, **options)


def _with_rig_rotation(dataset, R_rig):
    """``dataset`` with every sensor's stated mounting rotation replaced by ``R_rig`` (the data
    were made with the true one)."""
    sensors = tuple(replace(s, data=replace(s.data, T_BS=_T(R_rig))) for s in dataset.sensors)
    return replace(dataset, sensors=sensors)


def _signed_axis(v) -> str:
    i = int(np.argmax(np.abs(v)))
    return ("+" if v[i] >= 0 else "-") + "xyz"[i]


@pytest.fixture(scope="module")
def tumbling():
    return _rig("tumbling", 5.0, TUMBLING_KINDS)


@pytest.fixture(scope="module")
def rocking():
    return _rig(ROCKING, 8.0, ROCKING_KINDS)


# ------------------------------------------------------------------------------------------------
# a rig off by a quarter or a half turn


@pytest.mark.parametrize("angle", [90.0, 180.0])
@pytest.mark.parametrize("axis", [0, 1, 2])
@pytest.mark.parametrize("rig", ["tumbling", "rocking"])
def test_a_rig_turned_about_a_sensor_axis_is_named_with_the_axes_it_moves(rig, axis, angle, request):
    dataset = request.getfixturevalue(rig)
    turn = np.zeros(3)
    turn[axis] = np.radians(angle)
    R_rig = R_TRUE @ so3.exp(turn)
    results = check_mountings(_with_rig_rotation(dataset, R_rig)).results
    assert [r.sensor for r in results] == list(dataset.sensor_names)
    for finding in results:
        assert isinstance(finding, MountingFinding), finding.message
        assert finding.wrong, finding.message
        assert abs(finding.rig_angle_deg - angle) < 5.0, finding.message
        assert finding.message.startswith(f"{finding.sensor} ({finding.kind}): the data put its ")
        names = AXIS_NAMES.get(finding.kind, ("x axis", "y axis", "z axis"))
        for i, name in enumerate(names):
            said = f"its {name} on the IMU's {_signed_axis(R_TRUE[:, i])}, the rig on {_signed_axis(R_rig[:, i])}"
            assert (said in finding.message) == (i != axis), finding.message


@pytest.mark.parametrize("seed", range(3))
def test_wheels_turned_about_the_vertical_on_a_drive_are_named_by_their_forward_axis(seed):
    """A car's figure-eight excites the wheels' forward axis only; a rig turned by half a turn
    about the vertical puts it backwards, which every estimator would follow to the negative of the
    right position."""
    dataset = _rig("gentle", 60.0, {"wheels": TUMBLING_KINDS["wheels"]}, seed, np.eye(3))
    (finding,) = check_mountings(_with_rig_rotation(dataset, so3.exp(np.array([0.0, 0.0, np.pi])))).results
    assert finding.wrong
    assert finding.message.startswith("wheels (velocity): the data put its forward axis (x) on the IMU's +x, "
                                      "the rig on -x ("), finding.message
    assert finding.message.endswith("its rotation about the IMU's x axis is not determined by this motion")


@pytest.mark.parametrize("turn", [0.0, np.pi / 2, np.pi])
def test_wheels_whose_lateral_and_vertical_readings_are_exact_zeros_are_checked(turn):
    """A differential-drive controller's odometry reports its lateral and vertical velocities as
    exact zeros in every message: the columns of the closed form that they multiply carry no
    information at all (not merely little), are left at zero, and the forward axis is found as
    with noisy readings -- the rig right agrees, turned about the vertical by a quarter or a half
    turn it is wrong."""
    dataset = _rig("gentle", 60.0, {"wheels": TUMBLING_KINDS["wheels"]}, 0, np.eye(3))
    (wheels,) = dataset.sensors
    velocity = wheels.data.velocity * np.array([1.0, 0.0, 0.0])
    dataset = replace(dataset, sensors=(replace(wheels, data=replace(wheels.data, velocity=velocity)),))
    (finding,) = check_mountings(_with_rig_rotation(dataset, so3.exp(np.array([0.0, 0.0, turn])))).results
    assert isinstance(finding, MountingFinding), finding
    assert finding.wrong == (turn > 0.0), finding.message
    # its forward axis on the IMU's x, as close as from the noisy readings (3.2 deg; the sigma is 7)
    assert np.degrees(np.arccos(finding.R_data[0, 0])) < 6.0, finding.R_data


def test_the_check_runs_on_the_dataset_as_given(tumbling):
    """The rig's rotation is read from each sensor's data (``T_BS``), the measurements used only."""
    check = check_mountings(tumbling)
    assert not check.wrong and not check.not_checked
    for finding in check.findings:
        assert np.allclose(finding.R_rig, R_TRUE)
        assert "agrees with the data's" in finding.message


# ------------------------------------------------------------------------------------------------
# a rig mounted right


def _random_mounting(rng):
    return so3.exp(rng.normal(size=3) * np.pi / np.sqrt(3.0))


@pytest.mark.parametrize("seed", range(20))
def test_a_rig_mounted_right_gives_no_warning(seed):
    R = _random_mounting(np.random.default_rng(seed))
    for dataset in (_rig("tumbling", 5.0, TUMBLING_KINDS, seed, R), _rig(ROCKING, 8.0, ROCKING_KINDS, seed, R)):
        check = check_mountings(dataset)
        assert not check.not_checked, check.lines()
        assert not check.wrong, check.lines()
        for finding in check.findings:
            assert len(finding.observable_axes) == 3, finding.message
            error = np.degrees(np.linalg.norm(so3.boxminus(finding.R_data, R)))
            assert error < 4.0, (finding.sensor, error)
            assert finding.rig_angle_deg < WRONG_ANGLE_DEG


@pytest.mark.parametrize("seed", range(3))
def test_a_poor_gyro_is_corrected_on_slow_turns(seed):
    """A gyro bias of some 0.05 rad/s turns the body by 0.05 rad over a span and gravity by 0.5
    rad over a window: the attitude family estimates it with the mounting, the velocity family
    integrates the gyro again about it."""
    kinds = {"wheels": TUMBLING_KINDS["wheels"], "camera": TUMBLING_KINDS["camera"]}
    check = check_mountings(_rig(WANDERING, 20.0, kinds, seed, initial_bias_sigma=(0.1, 0.05)))
    assert len(check.findings) == 2 and not check.wrong, check.lines()
    for finding in check.findings:
        assert len(finding.observable_axes) == 3, finding.message
        assert np.degrees(np.linalg.norm(so3.boxminus(finding.R_data, R_TRUE))) < 6.0, finding.sensor


@pytest.mark.parametrize("seed", range(3))
def test_an_accelerometer_bias_is_estimated_with_the_tilt(seed):
    """An accelerometer bias of some 0.5 m/s^2 would tilt the vertical by 3 degrees."""
    (finding,) = check_mountings(_rig(ROCKING, 8.0, ROCKING_KINDS, seed, initial_bias_sigma=(0.5, 0.01))).results
    assert isinstance(finding, MountingFinding), finding.message
    assert np.degrees(np.linalg.norm(so3.boxminus(finding.R_data, R_TRUE))) < 1.5


def test_outliers_are_dropped():
    """One attitude in twenty turned by a radian (the simulator's outliers)."""
    kinds = {"camera": TUMBLING_KINDS["camera"], "ahrs": TUMBLING_KINDS["ahrs"]}
    dataset = _rig("tumbling", 5.0, kinds, outlier_fraction=0.05)
    assert all(len(indices) for indices in dataset.outliers.values())
    for finding in check_mountings(dataset).findings:
        assert np.degrees(np.linalg.norm(so3.boxminus(finding.R_data, R_TRUE))) < 1.5, finding.sensor


@settings(max_examples=15)
@given(R=strategies.rotations(), seed=st.integers(0, 2**16))
def test_the_data_rotation_follows_any_mounting(R, seed):
    for finding in check_mountings(_rig("tumbling", 5.0, {"wheels": TUMBLING_KINDS["wheels"],
                                                          "camera": TUMBLING_KINDS["camera"]}, seed, R)).findings:
        assert np.degrees(np.linalg.norm(so3.boxminus(finding.R_data, R))) < 4.0, finding.sensor


# ------------------------------------------------------------------------------------------------
# motions that excite one axis only


def _turned_about(R, imu_axis, angle):
    """``R`` turned about the sensor axis that ``R`` puts along the IMU axis ``imu_axis``."""
    i = int(np.argmax(np.abs(R[imu_axis, :])))
    turn = np.zeros(3)
    turn[i] = angle
    return R @ so3.exp(turn)


@pytest.mark.parametrize("profile, duration, kinds, imu_axis", [
    (YAWING, 6.0, {"camera": TUMBLING_KINDS["camera"], "ahrs": TUMBLING_KINDS["ahrs"]}, 2),
    (LINE, 8.0, {"wheels": TUMBLING_KINDS["wheels"]}, 0),
    ("static_level", 5.0, ROCKING_KINDS, 2),
])
def test_a_motion_about_one_axis_leaves_the_rotation_about_it_undetermined(profile, duration, kinds, imu_axis):
    dataset = _rig(profile, duration, kinds)
    axis_word = f"its rotation about the IMU's {'xyz'[imu_axis]} axis is not determined"
    for finding in check_mountings(dataset).results:
        assert isinstance(finding, MountingFinding), finding.message
        assert not finding.wrong and axis_word in finding.message, finding.message
        assert len(finding.observable_axes) == 2
        assert abs(finding.unobservable_axes[0][imu_axis]) > 0.99
        assert np.allclose(finding.cov @ finding.unobservable_axes[0], 0.0)
    spun = check_mountings(_with_rig_rotation(dataset, _turned_about(R_TRUE, imu_axis, np.pi)))
    assert not spun.wrong, spun.lines()
    tipped = check_mountings(_with_rig_rotation(dataset, _turned_about(R_TRUE, (imu_axis + 1) % 3, np.pi)))
    assert len(tipped.wrong) == len(dataset.sensors), tipped.lines()
    for finding in tipped.findings:
        assert abs(finding.rig_angle_deg - 180.0) < 3 * finding.rig_sigma_deg, finding.message
        assert axis_word in finding.message, finding.message


def test_without_motion_nothing_that_needs_it_is_checked():
    kinds = {**TUMBLING_KINDS, "gps": ("gnss", 5.0, 0.5)}
    check = check_mountings(_rig("static", 5.0, kinds))
    assert not check.findings
    assert [r.sensor for r in check.not_checked] == list(kinds)
    for refused in check.not_checked:
        assert refused.message.startswith(f"{refused.sensor} ({refused.kind}): mounting not checked: ")
    assert "lever arm" in check.not_checked[-1].reason


def test_a_steady_turn_is_not_taken_for_calm():
    """In a steady turn the mean specific force leans by the centripetal acceleration (9 degrees
    here) and its magnitude barely changes: the turn rate keeps those epochs out."""
    (refused,) = check_mountings(_rig(CIRCLING, 8.0, ROCKING_KINDS)).results
    assert isinstance(refused, NotChecked) and "low dynamics" in refused.reason


def test_odometry_with_gaps_is_chained_piecewise(tumbling):
    odometry = tumbling.sensor("visual_odometry").data
    kept = np.ones(len(odometry), bool)
    kept[10::17] = False
    check = check_mountings(replace(tumbling, sensors=(replace(tumbling.sensor("visual_odometry"),
                                                               data=odometry.subset(kept)),)))
    (finding,) = check.findings
    assert not finding.wrong and np.degrees(np.linalg.norm(so3.boxminus(finding.R_data, R_TRUE))) < 4.0


# ------------------------------------------------------------------------------------------------
# the closed forms


def _sensor(R_rig, kind="orientation"):
    """A sensor ``s`` of ``kind`` (orientation or velocity) whose rig states the rotation ``R_rig``
    (None: no extrinsic)."""
    T_BS = None if R_rig is None else _T(R_rig)
    if kind == "velocity":
        return Sensor("s", kind, VelocityMeasurements([0.0], np.zeros((1, 3)), np.zeros((1, 3)), np.eye(3), T_BS))
    return Sensor("s", kind, OrientationMeasurements([0.0], np.eye(3)[None], np.eye(3), T_BS))


@settings(max_examples=200)
@given(R_data=strategies.rotations(), R_rig=strategies.rotations(), a=strategies.unit_vectors())
def test_an_undetermined_direction_is_turned_to_the_rig(R_data, R_rig, a):
    """With the data silent about ``a``, the angle reported is the least over ``exp(theta a)
    R_data``, and it is the full angle when nothing is undetermined."""
    basis = np.linalg.svd(np.outer(a, a))[0]
    information = basis[:, 1:] @ basis[:, 1:].T / np.radians(1.0) ** 2
    finding = compare(_sensor(R_rig), DataRotation(R_data, information, 100, 0.01, "rad"))
    thetas = np.linspace(-np.pi, np.pi, 721)
    angles = np.linalg.norm(so3.log(R_rig[None] @ np.swapaxes(so3.exp(thetas[:, None] * a) @ R_data, 1, 2)), axis=1)
    assert np.radians(finding.rig_angle_deg) <= angles.min() + 1e-6  # an angle near pi has half the digits
    assert np.radians(finding.rig_angle_deg) >= angles.min() - 0.01
    assert np.allclose(finding.cov @ a, 0.0, atol=1e-12)
    full = compare(_sensor(R_rig), DataRotation(R_data, np.eye(3) / np.radians(1.0) ** 2, 100, 0.01, "rad"))
    assert np.isclose(np.radians(full.rig_angle_deg), np.linalg.norm(so3.boxminus(R_rig, R_data)))


@given(R=strategies.rotations(), axis=st.integers(0, 2), quarter_turns=st.integers(1, 3))
def test_a_sharp_estimate_flags_every_axis_turn(R, axis, quarter_turns):
    turn = np.zeros(3)
    turn[axis] = quarter_turns * np.pi / 2
    R_rig = R @ so3.exp(turn)
    finding = compare(_sensor(R_rig, "velocity"), DataRotation(R, np.eye(3) / np.radians(1.0) ** 2, 100, 0.01, "m/s"))
    assert finding.wrong and finding.message.startswith("s (velocity): ")
    assert abs(finding.rig_angle_deg - (90.0 if quarter_turns != 2 else 180.0)) < 1e-6
    assert not compare(_sensor(R), DataRotation(R, np.eye(3) / np.radians(1.0) ** 2, 100, 0.01, "rad")).wrong


@given(R=strategies.rotations(), axis=strategies.unit_vectors())
def test_a_difference_is_wrong_beyond_both_the_tolerance_and_three_sigma(R, axis):
    def finding(sigma_deg, off_deg):
        information = np.eye(3) / np.radians(sigma_deg) ** 2
        return compare(_sensor(so3.exp(np.radians(off_deg) * axis) @ R), DataRotation(R, information, 100, 0.01, "rad"))

    assert not finding(10.0, 20.0).wrong and "agrees with the data's (20.0 deg apart" in finding(10.0, 20.0).message
    assert finding(1.0, 20.0).wrong
    within = finding(1.0, 5.0)
    assert not within.wrong and "beyond 3 sigma 3.0 deg but within the 10 deg" in within.message


@given(seed=st.integers(0, 2**16))
def test_parameters_nothing_reads_are_left_at_zero(seed):
    """Columns of the normal equations that are exactly zero (a wheel odometer's lateral and vertical
    readings, zero in every message) stay at zero, and the rest is solved as without them, also
    where the rest has a nearly dependent pair (the scaling to a unit diagonal used to divide the
    round-off the least-squares solver leaves there by 1e-150)."""
    rng = np.random.default_rng(seed)
    J = rng.normal(size=(40, 6)) * rng.uniform(1e-3, 1e3, 6)
    J[:, 4] = 2.0 * J[:, 3] + 1e-9 * rng.normal(size=40)
    J[:, 1:3] = 0.0
    N, g = J.T @ J, J.T @ rng.normal(size=40)
    x = minimum_norm_solution(N, g)
    assert np.all(x[1:3] == 0.0)
    rest = [0, 3, 4, 5]
    assert np.allclose(x[rest], minimum_norm_solution(N[np.ix_(rest, rest)], g[rest]), rtol=1e-9, atol=0.0)


def test_a_finding_needs_two_determined_directions():
    information = np.diag([1.0 / np.radians(1.0) ** 2, 0.0, 0.0])
    refused = compare(_sensor(np.eye(3)), DataRotation(np.eye(3), information, 100, 0.01, "rad"))
    assert isinstance(refused, NotChecked) and "at most one direction" in refused.reason


@given(seed=st.integers(0, 2**16), fraction=st.floats(0.01, 0.99))
def test_a_time_between_samples_continues_its_samples_step(seed, fraction):
    """The attitude and the integrals of the attitude and the specific force at a time inside a
    step equal those of the same IMU with the step split there (the reading held on both sides),
    and so do all later ones (``K``, of first order in the step, is not exact)."""
    rng = np.random.default_rng(seed)
    n = 40
    t = np.cumsum(rng.uniform(0.005, 0.02, n))
    acc, gyro = rng.normal(size=(n, 3)) + [0.0, 0.0, 9.81], rng.normal(size=(n, 3))
    k = int(rng.integers(0, n - 1))
    t_split = t[k] + fraction * (t[k + 1] - t[k])
    split = ImuSamples(np.insert(t, k + 1, t_split), np.insert(acc, k + 1, acc[k], axis=0),
                       np.insert(gyro, k + 1, gyro[k], axis=0))
    b_f, b_w = rng.normal(size=3) * 0.1, rng.normal(size=3) * 0.01
    times = np.r_[t_split, t[k + 1:], rng.uniform(t_split, t[-1], 5)]
    whole = ImuIntegrals(ImuSamples(t, acc, gyro), b_f, b_w).at(times)
    parts = ImuIntegrals(split, b_f, b_w).at(times)
    for one, other in zip(whole[:3], parts[:3]):
        assert np.allclose(one, other, rtol=1e-12, atol=1e-12)


@given(n=st.integers(1, 300), seed=st.integers(0, 2**16))
def test_the_blocked_prefix_products_equal_one_scan(n, seed):
    M = so3.exp(np.random.default_rng(seed).normal(size=(n, 3)))
    assert np.allclose(chained(M), prefix_products(M, later_on_left=False), atol=1e-12)


def test_a_sensor_without_an_extrinsic_is_at_the_imu():
    sharp = np.eye(3) / np.radians(1.0) ** 2
    assert not compare(_sensor(None), DataRotation(np.eye(3), sharp, 100, 0.01, "rad")).wrong
    upside_down = compare(_sensor(None), DataRotation(so3.exp(np.array([np.pi, 0, 0])), sharp, 100, 0.01, "rad"))
    assert upside_down.wrong and "its y axis on the IMU's -y, the rig on +y" in upside_down.message
