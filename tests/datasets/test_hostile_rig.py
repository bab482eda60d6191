"""Absurd numbers in a rig file are refused when it is read, each by the one range table
(:data:`datasets.ranges.RANGES`) with an error naming the file, the key (as
``datasets.rig.sensor_key`` spells it) and the range; sensor names are checked against the one
name syntax. Every numeric key is tried just beyond each bound and at it, not only the values
first found to get through."""
from __future__ import annotations

import ast
import math
import re
from pathlib import Path

import numpy as np
import pytest

from datasets.kinds import KINDS
from datasets.ranges import RANGES, RESERVED_SENSOR_NAMES, SIGMA_RANGES, sensor_name_problem
from datasets.rig import DATUM_KEYS, IMU_KEYS, SENSOR_KEYS, RigError, load_rig, sensor_key
from datasets.robust import check_robust, robust_spec
from factors.calibration import CalibrationPrior
from factors.imu import DEFAULT_GRAVITY, ImuNoise

IMU = """[imu]
source = "csv:imu.csv"
accel_noise_density = 2.0e-3
gyro_noise_density = 1.7e-4
accel_random_walk = 3.0e-3
gyro_random_walk = 1.9e-5
gravity = 9.81
forward = [1, 0, 0]
"""
DATUM = """
[datum]
latitude = 47.0
longitude = 8.0
altitude = 400.0
"""
WHEEL = """
[[sensor]]
name = "wheel"
kind = "velocity"
source = "csv:wheel.csv"
T_BS = [[1, 0, 0, 0.5], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1]]
time_offset = 0.01
sigma = 0.05
every = 2
correlation_time = 5.0
robust = "huber:2"
scale = 1.01
estimate = ["time_offset", "rotation", "lever_arm", "scale"]
time_offset_sigma = 0.1
rotation_sigma = 0.1
lever_arm_sigma = 0.2
scale_sigma = 0.05
"""
MAG = """
[[sensor]]
name = "mag"
kind = "magnetometer"
source = "csv:mag.csv"
declination = 2.5
inclination = 63.0
"""
RIG = IMU + DATUM + WHEEL + MAG

#: The keys a rig file gives that are not numbers (``sigma``'s ranges are per unit: SIGMA_RANGES).
NOT_NUMBERS = {"source", "topic", "kalibr", "name", "kind", "camchain", "camera", "roll_pitch_only", "estimate",
               "sigma"}


def _rig(tmp_path: Path, text: str) -> Path:
    path = tmp_path / "rig.toml"
    path.write_text(text)
    return path


def _with(key: str, value) -> tuple[str, str]:
    """The rig with the key of RANGES set to ``value``, and the key as the rig's errors name it."""
    table, name = key.split(".")
    line = f"{name} = {value!r}"
    if key == "imu.forward":
        line = f"forward = [{value!r}, 0, 0]"
    elif key == "sensor.T_BS":
        line = f"T_BS = [[1, 0, 0, {value!r}], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1]]"
    elif key == "sensor.robust":
        line = f'robust = "huber:{value!r}"'
    elif key == "sensor.every":
        line = f"every = {int(value)}"
    # a factor on the messages' sigmas takes the place of the sigma (the two are never given together)
    stated = "sigma" if key == "sensor.sigma_factor" else name
    text = re.sub(rf"^{stated} = .*$", line, RIG, count=1, flags=re.M)
    assert text != RIG or f"\n{line}\n" in RIG, key
    if table == "sensor":
        index, sensor = (2, "mag") if name in ("declination", "inclination") else (1, "wheel")
        return text, sensor_key(index, sensor, name)
    return text, key


def _beyond(r) -> list:
    """Values just beyond each bound of the range ``r`` (a lever arm's length has no below)."""
    out = [r.high + max(abs(r.high), 1.0) * 0.5]
    if r.low > 0:
        out.append(r.low / 2)
    elif r.low < 0:
        out.append(r.low * 1.5)
    return out


def test_every_numeric_rig_key_has_a_range_and_every_range_a_key():
    keys = {f"imu.{k}" for k in IMU_KEYS} | {f"datum.{k}" for k in DATUM_KEYS} | {f"sensor.{k}" for k in SENSOR_KEYS}
    numeric = {k for k in keys if k.split(".")[1] not in NOT_NUMBERS}
    assert numeric == set(RANGES)


def test_the_range_table_imports_nothing_of_the_project():
    """The command line may use the table without pulling in anything (smoother -> datasets only)."""
    tree = ast.parse((Path(__file__).resolve().parents[2] / "datasets" / "ranges.py").read_text())
    imported = {alias.name.split(".")[0] for node in ast.walk(tree) if isinstance(node, ast.Import)
                for alias in node.names}
    imported |= {node.module.split(".")[0] for node in ast.walk(tree) if isinstance(node, ast.ImportFrom)}
    assert imported <= {"__future__", "math", "numbers", "re", "dataclasses"}, imported


def test_the_defaults_lie_in_their_ranges():
    noise, prior = ImuNoise(), CalibrationPrior(("time_offset",))
    for key, value in {"imu.accel_noise_density": noise.acc, "imu.gyro_noise_density": noise.gyro,
                       "imu.accel_random_walk": noise.acc_bias, "imu.gyro_random_walk": noise.gyro_bias,
                       "imu.gravity": float(np.linalg.norm(DEFAULT_GRAVITY)), "sensor.time_offset_sigma":
                       prior.time_offset, "sensor.rotation_sigma": prior.rotation, "sensor.lever_arm_sigma":
                       prior.lever_arm, "sensor.scale_sigma": prior.scale, "sensor.scale": 1.0, "sensor.every": 1,
                       "sensor.time_offset": 0.0, "sensor.T_BS": 0.0, "imu.forward": 1.0}.items():
        assert value in RANGES[key], key


def test_the_full_rig_reads(tmp_path):
    rig = load_rig(_rig(tmp_path, RIG))
    assert rig.sensors[0].robust == ("huber", 2.0) and rig.imu.gravity == 9.81


@pytest.mark.parametrize("key", sorted(RANGES))
def test_a_value_beyond_either_bound_is_refused_naming_file_key_and_range(tmp_path, key):
    r = RANGES[key]
    for value in _beyond(r):
        if key == "sensor.every" and value < 1:
            continue  # below 1 is not an integer >= 1: its own error
        text, where = _with(key, value)
        path = _rig(tmp_path, text)
        with pytest.raises(RigError) as info:
            load_rig(path)
        message = str(info.value)
        assert message.startswith(f"{path}: {where}: "), message
        assert f"within {r.text()}" in message and r.why in message, message


@pytest.mark.parametrize("key", sorted(RANGES))
def test_each_bound_itself_is_accepted(tmp_path, key):
    r = RANGES[key]
    for value in (r.low, r.high):
        if key == "sensor.T_BS" and value == 0:
            continue  # the identity's lever arm: read in the full rig with another
        text, _ = _with(key, int(value) if key == "sensor.every" else value)
        load_rig(_rig(tmp_path, text))


@pytest.mark.parametrize("edit, where", [
    (("accel_noise_density = 2.0e-3", "accel_noise_density = 1e300"), "imu.accel_noise_density"),
    (("gyro_random_walk = 1.9e-5", "gyro_random_walk = 0.0"), "imu.gyro_random_walk"),
    (("gravity = 9.81", "gravity = 1e-300"), "imu.gravity"),
    (("gravity = 9.81", "gravity = 1.0"), "imu.gravity"),  # in g
    (("[1, 0, 0, 0.5]", "[1, 0, 0, 1e12]"), 'sensor[1] "wheel".T_BS'),
    (("[0, 1, 0, 0]", "[0, 1, 0, -199.9999]"), 'sensor[1] "wheel".T_BS'),  # the length counts, not an axis
    (("scale_sigma = 0.05", "scale_sigma = 1e9"), 'sensor[1] "wheel".scale_sigma'),
    (("lever_arm_sigma = 0.2", "lever_arm_sigma = 1e-12"), 'sensor[1] "wheel".lever_arm_sigma'),
    (("rotation_sigma = 0.1", "rotation_sigma = 100"), 'sensor[1] "wheel".rotation_sigma'),
    (("rotation_sigma = 0.1", "rotation_sigma = 3.2"), 'sensor[1] "wheel".rotation_sigma'),
    (("altitude = 400.0", "altitude = 1e12"), "datum.altitude"),
    (("time_offset = 0.01", "time_offset = 1e300"), 'sensor[1] "wheel".time_offset'),
    (('robust = "huber:2"', 'robust = "huber:inf"'), 'sensor[1] "wheel".robust'),
    (('robust = "huber:2"', 'robust = "cauchy:1e-9"'), 'sensor[1] "wheel".robust'),
    (("sigma = 0.05", "sigma = 1e-300"), 'sensor[1] "wheel".sigma'),
    (("sigma = 0.05", "sigma = 1e300"), 'sensor[1] "wheel".sigma'),
    (("scale = 1.01", "scale = 1e9"), 'sensor[1] "wheel".scale'),
    (("every = 2", "every = 9223372036854775807"), 'sensor[1] "wheel".every'),
    (("forward = [1, 0, 0]", "forward = [1e300, 1e300, 0]"), "imu.forward"),
])
def test_the_absurd_values_found_are_refused_at_load(tmp_path, edit, where):
    old, new = edit
    assert old in RIG
    path = _rig(tmp_path, RIG.replace(old, new, 1))
    with pytest.raises(RigError, match=re.escape(f"{path}: {where}: ") + ".*expected a value within"):
        load_rig(path)


@pytest.mark.parametrize("kind", sorted(KINDS))
def test_a_sigma_is_checked_per_axis_in_its_unit(tmp_path, kind):
    """Each residual axis of each kind in turn gets a sigma beyond its unit's range (the others
    plausible); a wrong count is refused at load too."""
    declared = KINDS[kind]
    extra = {"magnetometer": "declination = 2.5\ninclination = 63.0\n", "roll_pitch": "roll_pitch_only = true\n"}
    table = f'\n[[sensor]]\nname = "s"\nkind = "{"orientation" if kind == "roll_pitch" else kind}"\n' \
            f'source = "csv:s.csv"\n{extra.get(kind, "")}'
    plausible = [math.sqrt(SIGMA_RANGES[u].low * SIGMA_RANGES[u].high) for u in declared.sigma_units]
    load_rig(_rig(tmp_path, IMU + table + f"sigma = {plausible}\n"))
    for axis, unit in enumerate(declared.sigma_units):
        for bad in (SIGMA_RANGES[unit].low / 2, SIGMA_RANGES[unit].high * 2):
            sigma = list(plausible)
            sigma[axis] = bad
            path = _rig(tmp_path, IMU + table + f"sigma = {sigma}\n")
            expected = (f"{path}: sensor[1] \"s\".sigma: " + (f"axis {axis + 1} of {declared.dim} ({unit}): "
                        if declared.dim > 1 else "") + f"expected a value within {SIGMA_RANGES[unit].text()}")
            with pytest.raises(RigError, match=re.escape(expected)):
                load_rig(path)
    path = _rig(tmp_path, IMU + table + f"sigma = {[0.1] * (declared.dim + 1)}\n")
    with pytest.raises(RigError, match=re.escape(f'sensor[1] "s".sigma: a {kind} sensor\'s sigma is 1 or '
                                                 f'{declared.dim}')):
        load_rig(path)


def test_a_kalibr_files_densities_are_checked_as_the_keys_they_stand_for(tmp_path):
    (tmp_path / "imu.yaml").write_text("accelerometer_noise_density: 1.0e+300\naccelerometer_random_walk: 3.0e-3\n"
                                       "gyroscope_noise_density: 1.7e-4\ngyroscope_random_walk: 0\n")
    text = IMU.replace("accel_noise_density = 2.0e-3\n", "").replace("gyro_random_walk = 1.9e-5\n", "")
    path = _rig(tmp_path, text + 'kalibr = "imu.yaml"\n')
    with pytest.raises(RigError, match=re.escape(f"{path}: imu.kalibr: {tmp_path / 'imu.yaml'}: "
                                                 "accelerometer_noise_density (the rig's accel_noise_density): "
                                                 "expected a value within [1e-06, 1] m/s^2/sqrt(Hz)")):
        load_rig(path)
    path = _rig(tmp_path, text + 'kalibr = "imu.yaml"\naccel_noise_density = 2e-3\n')  # the rig's key wins
    with pytest.raises(RigError, match=re.escape("gyroscope_random_walk (the rig's gyro_random_walk): expected")):
        load_rig(path)


def test_a_camchains_lever_arm_is_checked(tmp_path):
    (tmp_path / "camchain.yaml").write_text("cam0:\n  T_cam_imu: [[1, 0, 0, 1e12], [0, 1, 0, 0], [0, 0, 1, 0], "
                                            "[0, 0, 0, 1]]\n")
    path = _rig(tmp_path, IMU + '\n[[sensor]]\nname = "cam"\nkind = "pose"\nsource = "tum:cam.txt"\n'
                                'camchain = "camchain.yaml"\ncamera = "cam0"\n')
    with pytest.raises(RigError, match=re.escape(f'{path}: sensor[1] "cam".camchain: its lever arm (the translation '
                                                 '[-1000000000000.0, 0.0, 0.0]) is 1e+12 m long; expected a value '
                                                 'within [0, 200] m')):
        load_rig(path)


def test_a_rig_nested_deeper_than_the_toml_reader_follows_is_one_error(tmp_path):
    path = _rig(tmp_path, IMU + "deep = " + "[" * 100_000 + "]" * 100_000 + "\n")
    with pytest.raises(RigError, match=re.escape(f"{path}: arrays or tables nested deeper than the TOML reader")):
        load_rig(path)


REFUSED_NAMES = ["gps=rtk", "gps:rtk", "gps rtk", "gps.rtk", "gps/rtk", "1gps", "_gps", "-gps", "", "g" * 65,
                 "gnss\u00e9", "gps\n", *RESERVED_SENSOR_NAMES]
ACCEPTED_NAMES = ["gps", "GPS", "gps_rtk", "gps-2", "rtk2", "g" * 64, "Imu2", "imu_front", "priors"]


@pytest.mark.parametrize("name", REFUSED_NAMES)
def test_a_sensor_name_nothing_can_address_is_refused_at_load(tmp_path, name):
    path = _rig(tmp_path, IMU + MAG.replace('name = "mag"', f"name = {name!r}".replace("'", '"')))
    with pytest.raises(RigError) as info:
        load_rig(path)
    message = str(info.value)
    assert message.startswith(f"{path}: {sensor_key(1, name, 'name')}: "), message
    expected = ("is reserved: the outputs give it to the" if name in RESERVED_SENSOR_NAMES
                else "expected a non-empty string" if not name
                else "expected a name of a letter followed by")
    assert expected in message, message


@pytest.mark.parametrize("name", ACCEPTED_NAMES)
def test_an_accepted_name_is_addressable_by_the_command_line(tmp_path, name):
    """``--robust NAME=KERNEL`` splits at the first ``=``, a kernel at ``:``; outputs key by name."""
    assert load_rig(_rig(tmp_path, IMU + MAG.replace('name = "mag"', f'name = "{name}"'))).sensors[0].name == name
    target, _, kernel = f"{name}=cauchy:2".partition("=")
    assert target == name and robust_spec(kernel) == ("cauchy", 2.0)


def test_the_name_rule_is_one_rule_for_rigs_and_datasets():
    from datasets.simulate import simulate
    from datasets.simulated_sensors import SensorSpec

    for name in REFUSED_NAMES:
        assert sensor_name_problem(name) is not None, name
    for name in ACCEPTED_NAMES:
        assert sensor_name_problem(name) is None, name
    with pytest.raises(ValueError, match=r"Dataset.sensors\[0\].name: the name 'imu' is reserved: "
                                         r"the outputs give it to the IMU"):
        simulate("gentle", duration=2, seed=1, pose_rate=None, sensors=[SensorSpec("imu", "position", 1, 0.5)])


def test_a_duplicate_name_is_still_refused(tmp_path):
    path = _rig(tmp_path, IMU + MAG + MAG)
    with pytest.raises(RigError, match=re.escape(f'{path}: sensor[2] "mag".name: a second sensor named \'mag\'')):
        load_rig(path)


@pytest.mark.parametrize("text", ["huber:inf", "huber:nan", "tukey:1e-9", "cauchy:1e9", "huber:-1", "huber:0"])
def test_a_robust_threshold_out_of_range_is_refused_wherever_it_is_parsed(text):
    with pytest.raises(ValueError, match="robust kernel threshold"):
        robust_spec(text)
    name, _, value = text.partition(":")
    with pytest.raises(ValueError, match="SensorSetup.robust: threshold"):
        check_robust("SensorSetup.robust", (name, float(value)))
    assert robust_spec(f"{name}:2") == (name, 2.0)
    check_robust("SensorSetup.robust", (name, 2.0))


def _table_rows(text: str, first_cell: str) -> list[list[str]]:
    """The cells of the rows of the markdown tables in ``text`` whose first cell is ``first_cell``."""
    rows = [[cell.strip() for cell in line.strip().strip("|").split("|")] for line in text.splitlines()
            if line.startswith("|")]
    return [row for row in rows if row[0] == first_cell]


def test_the_users_reference_states_every_limit_as_the_code_has_it():
    """docs/rig.md's Limits: each range's bounds, each unit's sigma range, each file size, the YAML
    bounds and the shortest IMU recording, as the modules define them."""
    from datasets.errors import GIB, LIMITS, MIB
    from datasets.types import MIN_RECORDING_SAMPLES, MIN_RECORDING_SECONDS
    from datasets.yamlfile import MAX_DEPTH, MAX_NODES

    docs = (Path(__file__).resolve().parents[2] / "docs" / "rig.md").read_text()
    section = docs[docs.index("## Limits"):]
    section = section[:section.index("\n## ", 1)]

    def bounds(cell: str) -> tuple[float, float]:
        low, high = cell.split(" to ")
        return float(low), math.pi if high == "π" else float(high)

    for key, r in RANGES.items():
        (row,) = _table_rows(section, f"`{key}`")
        assert bounds(row[1]) == (r.low, r.high), key
    for unit, r in SIGMA_RANGES.items():
        (row,) = _table_rows(section, unit)
        assert bounds(row[1]) == (r.low, r.high), unit
    unit = {"MiB": MIB, "GiB": GIB}
    sizes = [int(number) * unit[name] for line in section.splitlines() if line.startswith("|")
             for number, name in re.findall(r"^\|[^|]*\| (\d+) (MiB|GiB) \|", line)]
    assert sizes == [LIMITS[kind].bytes for kind in ("rig", "yaml", "table", "npz", "json", "bag")]
    flat = " ".join(section.split())
    assert f"at most {MAX_NODES:,} nodes".replace(",", " ") in flat and f"nested at most {MAX_DEPTH} levels" in flat
    assert f"at least {MIN_RECORDING_SAMPLES} samples over at least {MIN_RECORDING_SECONDS:g} s" in flat


@pytest.mark.parametrize("sigma, which", [
    ("4.0", "as the sigma of its rad axes: expected a value within [1e-06, 3.14159] rad"),
    ("[0.1, 4.0]", "as the sigma of its rad axes: "),
    ("[1e5, 0.1]", "as the sigma of its m axes: expected a value within [0.0001, 10000] m"),
])
def test_a_short_sigma_of_a_pose_names_the_unit_it_failed_in(tmp_path, sigma, which):
    path = _rig(tmp_path, IMU + f'\n[[sensor]]\nname = "cam"\nkind = "pose"\nsource = "csv:cam.csv"\nsigma = {sigma}\n')
    with pytest.raises(RigError, match=re.escape(f'{path}: sensor[1] "cam".sigma: {which}')):
        load_rig(path)


@pytest.mark.parametrize("key, line", [
    ("imu.source", 'source = "csv:{path}"'),
    ("imu.kalibr", 'kalibr = "{path}"'),
    ('sensor[2] "mag".source', 'source = "csv:{path}"'),
])
@pytest.mark.parametrize("path, why", [
    ("~no-such-user-here/imu.csv", "~no-such-user-here names no home folder"),
    ("imu\\u0000.csv", "a NUL character (\\x00) cannot be part of a file name"),
])
def test_a_path_that_cannot_be_one_is_refused_at_load_naming_its_key(tmp_path, key, line, path, why):
    """``~user`` of no user made Path.expanduser raise a RuntimeError (an "internal failure", exit
    code 3); a NUL reached the system call, whose "embedded null byte" named neither file nor key."""
    text = RIG
    if key == "imu.kalibr":
        text = RIG.replace("[datum]", line.format(path=path) + "\n[datum]", 1)
    elif key == "imu.source":
        text = RIG.replace('source = "csv:imu.csv"', line.format(path=path), 1)
    else:
        text = RIG.replace('source = "csv:mag.csv"', line.format(path=path), 1)
    rig = _rig(tmp_path, text)
    with pytest.raises(RigError) as info:
        load_rig(rig)
    message = str(info.value)
    assert message.startswith(f"{rig}: {key}: ") and why in message and "\n" not in message, message


def _sensors(n: int, source=lambda i: f"csv:p{i}.csv") -> str:
    return "".join(f'\n[[sensor]]\nname = "s{i}"\nkind = "position"\nsource = "{source(i)}"\n' for i in range(n))


def test_a_rig_of_more_sensors_than_the_limit_is_refused_at_load(tmp_path):
    """Ten thousand sensors (700 kB of rig file) took 276 s on 20 s of data; the limit itself reads."""
    from datasets.ranges import MAX_SENSORS

    assert len(load_rig(_rig(tmp_path, IMU + _sensors(MAX_SENSORS))).sensors) == MAX_SENSORS
    path = _rig(tmp_path, IMU + _sensors(MAX_SENSORS + 1))
    with pytest.raises(RigError, match=re.escape(f"{path}: sensor: {MAX_SENSORS + 1} sensors; expected at most "
                                                 f"{MAX_SENSORS} (")):
        load_rig(path)


@pytest.mark.parametrize("first, second, shared", [
    ('kind = "position"\nsource = "csv:p.csv"', 'kind = "position"\nsource = "csv:p.csv"', "position"),
    ('kind = "pose"\nsource = "csv:p.csv"', 'kind = "position"\nsource = "csv:./p.csv"', "position"),
    ('kind = "orientation"\nsource = "csv:p.csv"', 'kind = "orientation"\nsource = "csv:link.csv"\n'
                                                  'roll_pitch_only = true', "C"),
    ('kind = "gnss"\nsource = "bag:run.bag"\ntopic = "/fix"', 'kind = "gnss"\nsource = "bag:run.bag"\n'
                                                             'topic = "/fix"', "position"),
    ('kind = "position"\nsource = "csv:p.csv"', 'kind = "orientation"\nsource = "csv:p.csv"', None),  # a pose file
    ('kind = "gnss"\nsource = "bag:run.bag"\ntopic = "/fix"', 'kind = "gnss"\nsource = "bag:run.bag"\n'
                                                             'topic = "/fix2"', None),
])
def test_the_same_measurements_read_by_two_sensors_are_refused_at_load(tmp_path, first, second, shared):
    """Two sensors of one file and topic that measure a same field count each measurement twice,
    as independent ones: every sigma of the estimates came out too small (by 1.4), silently; ten
    thousand copies of one sensor made a run of minutes. A link, or another spelling of the path,
    is the same file."""
    (tmp_path / "p.csv").write_text("t,x,y,z,qw,qx,qy,qz\n")
    (tmp_path / "link.csv").symlink_to(tmp_path / "p.csv")
    path = _rig(tmp_path, IMU + f'\n[[sensor]]\nname = "a"\n{first}\n' + f'\n[[sensor]]\nname = "b"\n{second}\n')
    if shared is None:
        assert len(load_rig(path).sensors) == 2
        return
    with pytest.raises(RigError, match=re.escape(f'{path}: sensor[2] "b".source: ') + ".* is read by sensor\\[1\\] "
                       f"'a' .* too, and both measure its {shared}: the same measurements used twice"):
        load_rig(path)


def test_a_rig_saved_with_a_byte_order_mark_reads(tmp_path):
    """Windows editors save UTF-8 with a byte-order mark: the rig was "TOML syntax error: Invalid
    statement (at line 1, column 1)", as the CSV readers already drop it."""
    path = tmp_path / "rig.toml"
    path.write_bytes("\ufeff".encode() + RIG.encode())
    assert load_rig(path).imu.gravity == 9.81
