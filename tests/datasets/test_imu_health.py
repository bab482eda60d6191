"""The IMU's own faults (datasets/imu_health.py): each fault injected into simulated samples is
named as what it is, on the right sensor and at the right time; the clean simulator profiles and
two real recordings shipped with GTSAM (KITTI's IMU, a quadruped's) give no finding at all."""
from __future__ import annotations

import re
import warnings

import numpy as np
import pytest

from datasets.imu_health import ImuFinding, findings_record, inspect_imu
from datasets.simulate import PROFILES, simulate

G = 9.80665


def _samples(profile="gentle", seed=0, duration=60.0):
    d = simulate(profile, duration=duration, seed=seed)
    return d.imu.t, d.imu.acc.copy(), d.imu.gyro.copy()


@pytest.mark.parametrize("profile", sorted(PROFILES))
@pytest.mark.parametrize("seed", [0, 1])
def test_the_clean_simulator_profiles_have_no_findings(profile, seed):
    assert inspect_imu(*_samples(profile, seed)) == []


def _quadruped():
    """GTSAM's ``quadraped_imu_data.csv`` (a ROS ``sensor_msgs/Imu`` dump: 6.6 s at 400 Hz, a robot
    at rest, then a few violent steps with foot impacts of 14 g): header stamps [ns], rates, specific force."""
    import gtsam

    path = gtsam.findExampleDataFile("quadraped_imu_data.csv")
    with open(path) as handle:
        names = handle.readline().lstrip("%").strip().split(",")
    columns = [names.index(n) for n in ("field.header.stamp", "field.angular_velocity.x", "field.angular_velocity.y",
                                        "field.angular_velocity.z", "field.linear_acceleration.x",
                                        "field.linear_acceleration.y", "field.linear_acceleration.z")]
    data = np.loadtxt(path, delimiter=",", skiprows=1, usecols=columns)
    return data[:, 0] * 1e-9, data[:, 4:7], data[:, 1:4]


def test_real_recordings_have_no_findings():
    """KITTI's IMU as the loader gives it (a car: vibration, potholes, 10 ms with jitter) and the
    quadruped's (stillness to 1e-6 m/s^2, then impacts that jolt both sensors at once)."""
    from datasets.kitti import load_kitti

    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        kitti = load_kitti()
    assert inspect_imu(kitti.imu.t, kitti.imu.acc, kitti.imu.gyro, 9.8) == []
    t, acc, gyro = _quadruped()
    assert len(t) > 2000 and np.abs(acc).max() > 100  # the impacts are in it
    assert inspect_imu(t, acc, gyro, 9.81) == []


def _only(findings: list[ImuFinding], what: str, sensor: str) -> ImuFinding:
    assert [(f.what, f.sensor) for f in findings] == [(what, sensor)], [f.message for f in findings]
    return findings[0]


def test_a_gyro_in_deg_per_s_on_a_slow_vehicle_is_named():
    """The gentle profile turns at 0.7 rad/s at most: in deg/s its 99th percentile (40 "rad/s"
    at most) passes the rate limit of the data types, but its rates predict tilts the
    accelerometer does not see."""
    t, acc, gyro = _samples()
    assert np.percentile(np.linalg.norm(gyro * 180 / np.pi, axis=1), 99) < 40
    finding = _only(inspect_imu(t, acc, gyro * 180 / np.pi), "gyro units", "gyro")
    assert "probably in deg/s" in finding.message
    assert finding.t_start == t[0] and finding.t_end == pytest.approx(t[-1], abs=1.0)


def test_an_imu_that_never_tilts_says_nothing_of_its_gyro_units():
    """At rest (only noise and bias on the gyro) deg/s and rad/s explain the accelerometer alike:
    no verdict is claimed."""
    t, acc, gyro = _samples("static")
    assert inspect_imu(t, acc, gyro * 180 / np.pi) == []


@pytest.mark.parametrize("sensor, axis, size", [("accelerometer", 0, 30.0), ("gyro", 2, -2.0)])
def test_one_spike_is_named_with_its_time_and_size(sensor, axis, size):
    t, acc, gyro = _samples()
    (acc if sensor == "accelerometer" else gyro)[3001, axis] += size
    finding = _only(inspect_imu(t, acc, gyro), "spike", sensor)
    assert (finding.t_start, finding.t_end, finding.samples) == (t[3001], t[3001], 1)
    assert "1 spike(s)" in finding.message and f"t = {t[3001]:.6f} s" in finding.message
    largest = float(re.search(r"the largest ([-+][0-9.]+) ", finding.message).group(1))
    assert largest == pytest.approx(size, rel=0.05)  # its height above its neighbours


def test_an_impact_on_both_sensors_is_no_spike():
    """A sample far from its neighbours in the accelerometer and in the gyro at once is a jolt of
    the body (the quadruped's feet), not a corrupt sample."""
    t, acc, gyro = _samples()
    acc[3001, 2] += 30.0
    gyro[3001:3011, 0] += 1.0  # the rate jumps with it
    assert inspect_imu(t, acc, gyro) == []


def test_three_seconds_of_a_clipped_accelerometer_are_named_as_saturation():
    """A 5 Hz vibration of 6 g on x for 3 s through an accelerometer of +-4 g range: the samples
    beyond the range read the limit, runs of them at +4 g and -4 g."""
    t, acc, gyro = _samples()
    during = (t >= 20.0) & (t < 23.0)
    acc[during, 0] += 6 * G * np.sin(2 * np.pi * 5 * t[during])
    acc = np.clip(acc, -4 * G, 4 * G)
    finding = _only(inspect_imu(t, acc, gyro), "saturation", "accelerometer")
    assert 20.0 <= finding.t_start < 20.1 and 22.9 < finding.t_end < 23.0
    assert finding.samples == int(np.sum(np.abs(acc[:, 0]) == 4 * G))
    assert f"x at {4 * G:.6g}" in finding.message or f"x at {-4 * G:.6g}" in finding.message
    assert finding.spans[0][0] == finding.t_start


def test_an_accelerometer_in_g_is_named():
    t, acc, gyro = _samples()
    finding = _only(inspect_imu(t, acc / G, gyro), "accelerometer scale", "accelerometer")
    assert "in g rather than m/s^2" in finding.message


def test_a_ten_second_gap_is_named_by_the_offline_rule():
    t, acc, gyro = _samples()
    keep = (t < 20.0) | (t >= 30.0)
    finding = _only(inspect_imu(t[keep], acc[keep], gyro[keep]), "gap", "timing")
    assert (finding.t_start, finding.t_end) == (pytest.approx(19.995), pytest.approx(30.0))
    assert finding.samples == 2000
    assert "1 gap(s) longer than 5 x the typical period (0.005 s); the longest is 10 s after t = 19.995000 s" in \
        finding.message


def test_the_record_is_json_ready():
    t, acc, gyro = _samples(duration=20.0)
    acc[1001, 1] += 30.0
    record = findings_record(inspect_imu(t, acc, gyro))
    assert record["ok"] is False and record["findings"][0]["what"] == "spike"
    assert record["findings"][0]["spans"] == [[t[1001], t[1001]]]
    assert findings_record([]) == {"ok": True, "findings": []}
