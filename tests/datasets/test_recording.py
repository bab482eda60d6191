"""A rig's recording as a dataset (datasets.recording), from CSV and TUM files the test writes:
stamps in the data's clock, extrinsics and time offsets applied, every-k hold-out, and one clear
line for each way a sensor's data can be unusable."""
from __future__ import annotations

import numpy as np
import pytest
from rigfiles import imu_table, toml_matrix

from datasets.kinds import sensors_of
from datasets.recording import load_recording
from datasets.rig import load_rig
from datasets.simulate import simulate
from datasets.simulated_sensors import SensorSpec
from datasets.tum import write_tum
from factors import quaternion, so3

T0_NS = 1_600_000_000_000_000_000
CAMERA = np.eye(4)
CAMERA[:3, :3], CAMERA[:3, 3] = so3.exp([0.2, -1.0, 0.3]), [0.1, 0.0, -0.2]



@pytest.fixture(scope="module")
def data():
    return simulate("gentle", duration=6, seed=9, pose_rate=None,
                    sensors=[SensorSpec("camera", "pose", 10, (0.02, 0.01), CAMERA)])


def _imu_csv(folder, data):
    """The simulated IMU samples as an EuRoC/ASL ``imu.csv``, stamped from T0_NS."""
    ns = T0_NS + np.round(data.imu.t * 1e9).astype(np.int64)
    rows = ["#timestamp [ns],w_RS_S_x [rad s^-1],w_RS_S_y [rad s^-1],w_RS_S_z [rad s^-1],"
            "a_RS_S_x [m s^-2],a_RS_S_y [m s^-2],a_RS_S_z [m s^-2]"]
    rows += [f"{n},{g[0]:.17g},{g[1]:.17g},{g[2]:.17g},{a[0]:.17g},{a[1]:.17g},{a[2]:.17g}"
             for n, g, a in zip(ns, data.imu.gyro, data.imu.acc)]
    (folder / "imu.csv").write_text("\n".join(rows) + "\n")


def _write(folder, data, camera_sigma=True, camera_offset_s=0.0, extra="", rig_offset_s=None):
    _imu_csv(folder, data)
    cam = data.sensors[0].data
    q = quaternion.from_matrix(cam.C)
    header = "t,x,y,z,qw,qx,qy,qz" + (",sigma_x,sigma_y,sigma_z,sigma_rx,sigma_ry,sigma_rz" if camera_sigma else "")
    lines = [header]
    for t, p, qq in zip(cam.t, cam.position, q):
        sig = ",0.02,0.02,0.02,0.01,0.01,0.01" if camera_sigma else ""
        lines.append(f"{T0_NS * 1e-9 + t - camera_offset_s:.17g},{p[0]:.17g},{p[1]:.17g},{p[2]:.17g},"
                     f"{qq[0]:.17g},{qq[1]:.17g},{qq[2]:.17g},{qq[3]:.17g}{sig}")
    (folder / "camera.csv").write_text("\n".join(lines) + "\n")
    write_tum(folder / "vo.tum", T0_NS * 1e-9 + cam.t, cam.position, cam.C)
    rig = folder / "rig.toml"
    rig.write_text(imu_table("csv:imu.csv", data.noise) + f"""
[[sensor]]
name = "camera"
kind = "pose"
source = "csv:camera.csv"
T_BS = {toml_matrix(CAMERA)}
time_offset = {camera_offset_s if rig_offset_s is None else rig_offset_s}
every = 2
{extra}
""")
    return rig


def test_a_recording_keeps_its_clock_its_extrinsics_and_holds_out(tmp_path, data):
    rig = _write(tmp_path, data, camera_offset_s=0.25)
    recording = load_recording(load_rig(rig))
    assert recording.time_origin_ns == T0_NS
    (camera,) = sensors_of(recording)
    assert camera.kind == "pose" and np.array_equal(camera.data.T_BS, CAMERA)
    truth = data.sensors[0].data
    # the 0.25 s the file was early is added back; every 2nd used, the others held out
    np.testing.assert_allclose(camera.data.t, truth.t[::2], atol=1e-6)
    np.testing.assert_allclose(camera.heldout.t, truth.t[1::2], atol=1e-6)
    np.testing.assert_allclose(camera.data.cov[0].diagonal(), [4e-4] * 3 + [1e-4] * 3)
    # self-initialised at the first pose: the IMU's state there, from the camera and its extrinsic
    k = np.searchsorted(data.truth.t, recording.t0 - 1e-9)
    assert abs(recording.t0 - data.truth.t[k]) < 1e-6
    assert np.linalg.norm(recording.initial.r - data.truth.position[k]) < 0.2
    assert np.linalg.norm(so3.boxminus(recording.initial.C, data.truth.C[k])) < 0.05


@pytest.mark.parametrize("edit, message", [
    (dict(camera_sigma=False), "sensor 'camera' (pose): its messages carry no covariance; give the sensor's sigma"),
    (dict(extra='[[sensor]]\nname = "vo"\nkind = "odometry"\nsource = "tum:vo.tum"'),
     "sensor 'vo' (odometry): give sigma in the rig file, the noise of one step"),
    (dict(rig_offset_s=72_000.0), "sensor 'camera': none of its"),  # stamps in another clock (time zone)
])
def test_unusable_sensor_data_is_one_line_naming_the_sensor(tmp_path, data, edit, message):
    rig = _write(tmp_path, data, **edit)
    with pytest.raises(ValueError) as error:
        load_recording(load_rig(rig))
    assert message in str(error.value) and "\n" not in str(error.value)


def test_a_malformed_sensor_file_is_one_line_naming_the_sensor_and_the_file(tmp_path, data):
    """A reader's DataError (file, line, field) with the sensor's name before it, as one line, no
    traceback."""
    rig = _write(tmp_path, data)
    lines = (tmp_path / "camera.csv").read_text().splitlines()
    lines[3] = lines[3].replace(",", ",x", 1)
    (tmp_path / "camera.csv").write_text("\n".join(lines) + "\n")
    with pytest.raises(ValueError) as error:
        load_recording(load_rig(rig))
    message = str(error.value)
    assert message.startswith("sensor 'camera' (pose): ") and "camera.csv, line 4" in message and "\n" not in message


def test_a_source_without_measurements_is_named(tmp_path, data):
    rig = _write(tmp_path, data)
    (tmp_path / "camera.csv").write_text("t,x,y,z,qw,qx,qy,qz,sigma_x,sigma_y,sigma_z,sigma_rx,sigma_ry,sigma_rz\n")
    with pytest.raises(ValueError, match="camera") as error:
        load_recording(load_rig(rig))
    assert "\n" not in str(error.value) and "zero-size" not in str(error.value)


def test_an_imu_bag_of_one_message_is_refused_before_anything_else(tmp_path, data):
    """One IMU message in the bag: one line naming the bag and the topic, how many samples and
    how many are needed, before any other sensor is looked at (no warning, no NaN)."""
    import warnings

    from bagfiles import Messages, write_bag

    m = Messages("ros1")
    write_bag(tmp_path / "run.bag", "ros1", {"/imu": ("sensor_msgs/msg/Imu", [m.imu(T0_NS, (0, 0, 9.81), (0, 0, 0))])})
    _write(tmp_path, data)
    rig = tmp_path / "rig.toml"
    rig.write_text(rig.read_text().replace('source = "csv:imu.csv"', 'source = "bag:run.bag"\ntopic = "/imu"', 1))
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        with pytest.raises(ValueError) as error:
            load_recording(load_rig(rig))
    assert str(error.value).startswith(f"{tmp_path / 'run.bag'}, field 'topic /imu': found 1 IMU sample over 0 s; "
                                       "expected an IMU recording of at least 50 samples over at least 1 s (")


def _gnss_only(folder):
    """20 s of the figure-eight with 1-Hz GNSS fixes (0.5 m) alone: ``imu.csv`` and ``gnss.csv``
    in ``folder``, fixes in latitude, longitude and altitude about (47, 8, 400); the simulation."""
    from datasets.gnss import Datum, enu_to_geodetic

    data = simulate("gentle", duration=20, seed=5, pose_rate=None, sensors=[SensorSpec("gnss", "gnss", 1, 0.5)])
    _imu_csv(folder, data)
    fixes = data.sensors[0].data
    lat, lon, alt = enu_to_geodetic(fixes.position, Datum(47.0, 8.0, 400.0))
    (folder / "gnss.csv").write_text("t,latitude,longitude,altitude,sigma_e,sigma_n,sigma_u\n" + "".join(
        f"{T0_NS * 1e-9 + t:.17g},{a:.17g},{b:.17g},{c:.17g},0.5,0.5,0.5\n"
        for t, a, b, c in zip(fixes.t, lat, lon, alt)))
    return data


def test_an_every_that_leaves_too_few_fixes_is_named_as_the_cause(tmp_path):
    """GNSS alone gives the heading through the course over ground; `every` = 10^4 leaves the
    first fix only. The error names the sensor's `every` key and the counts, not only the
    heading it could not find; with every = 1 the same recording starts."""
    data = _gnss_only(tmp_path)
    fixes = data.sensors[0].data
    rig = tmp_path / "rig.toml"
    for every in (10_000, 1):
        rig.write_text(imu_table("csv:imu.csv", data.noise) + f"""
[[sensor]]
name = "gnss"
kind = "gnss"
source = "csv:gnss.csv"
every = {every}
""")
        if every == 1:
            assert len(sensors_of(load_recording(load_rig(rig)))[0].data) > 1
            continue
        with pytest.raises(ValueError) as error:
            load_recording(load_rig(rig))
        assert str(error.value) == (
            f'{rig}: sensor[1] "gnss".every: 10000 leaves 1 of the sensor\'s {len(fixes)} measurements for '
            f"estimation: too few to fix the initial heading, which all {len(fixes)} would; use a smaller every "
            "(the measurements between those used are held out)")
        with pytest.raises(ValueError) as error:  # in a part: its counts, said to be the part's
            load_recording(load_rig(rig), part=(None, 12.0))
        inside = int(np.sum(fixes.t - data.imu.t[0] <= 12.0))
        assert f"10000 leaves 1 of the sensor's {inside} measurements in the part up to 12 s for estimation" in str(
            error.value), error.value


def test_a_part_of_a_recording_is_read_split_and_started_as_the_whole_and_then_cut(tmp_path, data):
    """``part = (start, end)``: the IMU samples and the measurements inside it (a relative one with
    both ends), held out by the whole recording's ``every``, self-initialised at its start; a sensor
    with no measurement in it is left out with a warning naming it."""
    from datasets.recording import PartError

    cam = data.sensors[0].data
    early = cam.t < 2.0
    write_tum(tmp_path / "early.tum", T0_NS * 1e-9 + cam.t[early], cam.position[early], cam.C[early])
    rig = _write(tmp_path, data, extra='[[sensor]]\nname = "vo"\nkind = "odometry"\nsource = "tum:vo.tum"\n'
                 'sigma = [0.01, 0.01, 0.01, 0.005, 0.005, 0.005]\n\n'
                 '[[sensor]]\nname = "early"\nkind = "odometry"\nsource = "tum:early.tum"\n'
                 'sigma = [0.01, 0.01, 0.01, 0.005, 0.005, 0.005]')
    whole = load_recording(load_rig(rig))
    with pytest.warns(UserWarning, match=r"none of the measurements used of 'early' lies in the part 3-5 s "
                                         r"\(3\.000-5\.000 s after the recording's first IMU sample\): left out"):
        part = load_recording(load_rig(rig), part=(3.0, 5.0))
    assert whole.sensor_names == ("camera", "vo", "early") and part.sensor_names == ("camera", "vo")
    assert 3.0 <= part.t0 < 3.2 and part.t1 == pytest.approx(5.0)
    assert part.imu.t[-1] <= 5.0 and part.time_origin_ns == whole.time_origin_ns
    for name in ("camera", "vo"):
        for field in ("data", "heldout"):
            inside, outside = getattr(part.sensor(name), field), getattr(whole.sensor(name), field)
            if outside is None:
                assert inside is None
                continue
            first = getattr(outside, "t_from", outside.t)
            expected = outside.t[(first >= part.t0) & (outside.t <= part.t1)]
            np.testing.assert_array_equal(inside.t, expected)
            assert len(expected) > 5 and len(expected) < len(outside.t) / 2
    assert set(np.round(part.sensor("camera").data.t, 6)) <= set(np.round(whole.sensor("camera").data.t, 6))
    k = np.searchsorted(data.truth.t, part.t0 - 1e-9)
    assert np.linalg.norm(part.initial.r - data.truth.position[k]) < 0.2
    assert np.linalg.norm(so3.boxminus(part.initial.C, data.truth.C[k])) < 0.05
    with pytest.raises(PartError, match=r"the part from 100 s on holds 0 IMU samples, at least 2 needed: the "
                                        r"recording's IMU runs from 0 to 6\.000 s after its first sample \(to "
                                        r"1600000006\.000 s"):
        load_recording(load_rig(rig), part=(100.0, None))


def test_a_part_without_a_sensor_s_used_measurements_leaves_it_out_or_is_refused(tmp_path, data):
    """A sensor whose used measurements (every = 100: the first alone) miss the part is left out,
    the warning counting its held-out ones there; a part in which no sensor has a used measurement
    is a PartError naming it."""
    from datasets.recording import PartError

    rig = _write(tmp_path, data, extra='[[sensor]]\nname = "dense"\nkind = "pose"\nsource = "csv:dense.csv"')
    (tmp_path / "dense.csv").write_text((tmp_path / "camera.csv").read_text())
    rig.write_text(rig.read_text().replace("every = 2", "every = 100"))
    with pytest.warns(UserWarning, match=r"none of the measurements used of 'camera' \(its 41 held-out measurements "
                                         r"there not scored\) lies in the part 1-5 s"):
        part = load_recording(load_rig(rig), part=(1.0, 5.0))
    assert part.sensor_names == ("dense",)
    rig.write_text(rig.read_text().replace('[[sensor]]\nname = "dense"', '[[sensor]]\nname = "dense"\nevery = 100'))
    with pytest.raises(PartError, match=r"^the part 1-5 s \(1\.000-5\.000 s after the recording's first IMU sample\) "
                                        r"holds none of the measurements the sensors use \(their `every`\)"):
        load_recording(load_rig(rig), part=(1.0, 5.0))


def test_a_part_too_short_to_start_from_says_so(tmp_path):
    """GNSS alone needs the vehicle's course over ground for the heading: a part with one fix
    cannot give it, and the error names the part before the reason."""
    from datasets.recording import PartError

    data = _gnss_only(tmp_path)
    rig = tmp_path / "rig.toml"
    rig.write_text(imu_table("csv:imu.csv", data.noise) + '[[sensor]]\nname = "gnss"\nkind = "gnss"\n'
                   'source = "csv:gnss.csv"\n')
    assert len(load_recording(load_rig(rig), part=(0.5, None)).sensor("gnss").data) > 2
    with pytest.raises(PartError, match=r"^the part 0\.5-1\.5 s: cannot fix the initial heading"):
        load_recording(load_rig(rig), part=(0.5, 1.5))
