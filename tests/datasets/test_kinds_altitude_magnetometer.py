"""The ``altitude`` kind (a barometer's standard-atmosphere height relative to its first reading)
and the ``magnetometer`` kind (the field's direction against the rig's declination and
inclination): conversions, noise propagation, CSV layouts and the rig keys."""
from __future__ import annotations

import numpy as np
import pytest

from datasets.csv_sources import read_csv_magnetic_fields, read_csv_pressures
from datasets.errors import DataError
from datasets.kinds import KINDS, altitude, magnetometer
from datasets.rig import RigError, load_rig
from factors import imu, selfcheck, so3
from factors import sensor_models as sm


def test_standard_atmosphere_heights():
    """The ISA table (geopotential heights): 1013.25 hPa at 0 m, 898.7457 hPa at 1000 m, 794.952
    hPa at 2000 m, 540.199 hPa at 5000 m; the inverse and the slope (-8.32 m/hPa at sea level)
    agree with it."""
    np.testing.assert_allclose(altitude.pressure_height([101_325.0, 89_874.57, 79_495.2, 54_019.9]),
                               [0.0, 1000.0, 2000.0, 5000.0], atol=0.1)
    h = np.linspace(-300, 4000, 30)
    np.testing.assert_allclose(altitude.pressure_height(altitude.height_pressure(h)), h, atol=1e-9)
    p = altitude.height_pressure(h)
    step = 1e-3
    numerical = (altitude.pressure_height(p + step) - altitude.pressure_height(p - step)) / (2 * step)
    np.testing.assert_allclose(altitude.height_per_pascal(p), numerical, rtol=1e-7)
    assert abs(altitude.height_per_pascal(101_325.0) * 100 + 8.32) < 0.01


def test_heights_are_relative_to_the_first_reading_with_the_variance_carried():
    p = altitude.height_pressure(np.array([412.0, 415.0, 409.5]))
    h, var = altitude.heights_from_pressures(p, np.full(3, 25.0))
    np.testing.assert_allclose(h, [0.0, 3.0, -2.5], atol=1e-9)
    np.testing.assert_allclose(var, 25.0 * altitude.height_per_pascal(p) ** 2)


def test_field_direction_of_declination_and_inclination():
    np.testing.assert_allclose(magnetometer.field_direction(0.0, 0.0), [0.0, 1.0, 0.0], atol=1e-15)  # north
    np.testing.assert_allclose(magnetometer.field_direction(90.0, 0.0), [1.0, 0.0, 0.0], atol=1e-15)  # east
    np.testing.assert_allclose(magnetometer.field_direction(0.0, 90.0), [0.0, 0.0, -1.0], atol=1e-15)  # down
    d = magnetometer.field_direction(3.0, 63.0)
    assert abs(np.linalg.norm(d) - 1) < 1e-15 and d[2] < 0 and d[0] > 0


def test_magnetometer_residual_covariance_from_the_field_covariance():
    """Noise ``n`` on the field vector: the residual's covariance is ``B^T cov B / |f|^2``
    (Monte Carlo, 40 000 draws at a random attitude and extrinsic)."""
    rng = np.random.default_rng(5)
    x = imu.ImuState.identity().replace(C=selfcheck.random_rotation(rng))
    T = selfcheck.random_extrinsic(rng)
    m = magnetometer.field_direction(2.0, 60.0)
    f = 4.8e-5 * (T[:3, :3].T @ x.C.T @ m)  # the true field in the sensor frame [T]
    A = rng.normal(size=(3, 3)) * 4e-7
    cov = A @ A.T
    fields = f + rng.multivariate_normal(np.zeros(3), cov, size=40_000)
    rows = sm.pack_magnetometer(fields, m, T)
    e = np.array([sm.evaluate_one(sm.MAGNETOMETER, x, row)[0] for row in rows])
    predicted = magnetometer.direction_covariance(f[None], cov[None])[0]
    # the residual's basis moves with each measured direction; its covariance is that of the mean one
    np.testing.assert_allclose(np.cov(e.T), predicted, rtol=0.05, atol=1e-3 * predicted.max())


def test_magnetometer_fixes_the_heading_and_not_the_field_axis():
    """The residual changes with a turn about the vertical (it measures the heading) and not
    with a turn about the world field's own direction."""
    rng = np.random.default_rng(6)
    x = imu.ImuState.identity().replace(C=selfcheck.random_rotation(rng))
    m = magnetometer.field_direction(-7.0, 55.0)
    row = sm.pack_magnetometer((x.C.T @ m)[None], m)[0]
    assert np.allclose(sm.evaluate_one(sm.MAGNETOMETER, x, row)[0], 0.0, atol=1e-15)
    turned = x.replace(C=so3.exp(np.array([0.0, 0.0, 0.1])) @ x.C)
    assert np.linalg.norm(sm.evaluate_one(sm.MAGNETOMETER, turned, row)[0]) > 0.04
    about_field = x.replace(C=so3.exp(0.7 * m) @ x.C)
    assert np.allclose(sm.evaluate_one(sm.MAGNETOMETER, about_field, row)[0], 0.0, atol=1e-15)


@pytest.mark.parametrize("kind", ["altitude", "magnetometer"])
def test_simulated_measurements_have_the_declared_noise(kind):
    """The simulator's draws at the truth have residuals of the declared covariance (4000 draws)."""
    from datasets.simulate import simulate

    rng = np.random.default_rng(7)
    truth = simulate(duration=20, imu_rate=200.0, seed=1).truth
    k = np.arange(len(truth))
    sigma = np.full(KINDS[kind].dim, 0.05)
    T = selfcheck.random_extrinsic(rng)
    data = KINDS[kind].simulate(truth, k, None, T, sigma, rng)
    rows = KINDS[kind].pack(data)
    e = np.array([sm.evaluate_one(KINDS[kind].model, truth.states[i], rows[i])[0] for i in k])
    np.testing.assert_allclose(e.std(axis=0), sigma, rtol=0.06)
    assert np.abs(e.mean(axis=0)).max() < 0.006


def test_csv_layouts(tmp_path):
    baro = tmp_path / "baro.csv"
    baro.write_text("t,pressure,sigma_pressure\n0.0,96000,2\n0.1,95990,2\n")
    stream = read_csv_pressures(baro)
    assert np.array_equal(stream.pressure, [96000, 95990]) and np.array_equal(stream.variance, [4.0, 4.0])
    mag = tmp_path / "mag.csv"
    mag.write_text("t,mx,my,mz\n0.0,2e-5,1e-5,-4e-5\n0.1,2e-5,1e-5,-4e-5\n")
    assert read_csv_magnetic_fields(mag).cov is None
    baro.write_text("t,pressure\n0.0,96000\n0.1,-3\n")
    with pytest.raises(DataError, match=r"baro\.csv, line 3, field 'pressure'.*a pressure > 0"):
        read_csv_pressures(baro)


def _rig(tmp_path, extra: str, kind: str = "magnetometer") -> str:
    (tmp_path / "imu.csv").write_text("#timestamp [ns],w_RS_S_x,w_RS_S_y,w_RS_S_z,a_RS_S_x,a_RS_S_y,a_RS_S_z\n"
                                      "0,0,0,0,0,0,9.81\n5000000,0,0,0,0,0,9.81\n")
    path = tmp_path / "rig.toml"
    path.write_text(f"""[imu]
source = "csv:imu.csv"
accel_noise_density = 1e-3
gyro_noise_density = 1e-4
accel_random_walk = 1e-4
gyro_random_walk = 1e-5

[[sensor]]
name = "mag"
kind = "{kind}"
source = "csv:mag.csv"
{extra}
""")
    return path


def test_rig_keys_of_the_magnetometer(tmp_path):
    rig = load_rig(_rig(tmp_path, "declination = 2.5\ninclination = 63"))
    assert (rig.sensors[0].declination, rig.sensors[0].inclination) == (2.5, 63.0)
    with pytest.raises(RigError, match=r'sensor\[1\] "mag"\.inclination: missing; a magnetometer needs'):
        load_rig(_rig(tmp_path, "declination = 2.5"))
    with pytest.raises(RigError, match=r'sensor\[1\] "mag"\.inclination: expected a value within \[-90, 90\] deg'
                                       r'.*got 95'):
        load_rig(_rig(tmp_path, "declination = 2.5\ninclination = 95"))
    with pytest.raises(RigError, match=r'sensor\[1\] "mag"\.declination: expected only on a magnetometer'):
        load_rig(_rig(tmp_path, "declination = 2.5", kind="altitude"))
