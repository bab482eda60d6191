"""YAML calibration files whose documents expand without bound: nested aliases ("a billion
laughs"), one anchor repeated many times, a huge flat document, a recursive alias, nesting deeper
than a reader follows. Each YAML reader of the package refuses them in one error naming the file,
run in an isolated process (the ``isolated`` fixture: a deadline and a memory limit, so that a
regression fails its test and leaves the machine alone); aliases a real file might hold are read."""
from __future__ import annotations

import re

import numpy as np
import pytest
from bagfiles import Messages, write_bag

from datasets.bags import read_bag_imu
from datasets.errors import DataError
from datasets.euroc import read_sensor_yaml
from datasets.kalibr import read_camchain_T_BS, read_kalibr_imu
from datasets.rig import load_rig
from datasets.yamlfile import MAX_DEPTH, MAX_NODES, read_yaml

DENSITIES = ("accelerometer_noise_density: 2.0e-3\naccelerometer_random_walk: 3.0e-3\n"
             "gyroscope_noise_density: 1.7e-4\ngyroscope_random_walk: 1.9e-5\n")
SENSOR_YAML = "T_BS:\n  cols: 4\n  rows: 4\n  data: [1, 0, 0, 0, 0, 1, 0, 0, 0, 1, 0, 0, 0, 0, 0, 1]\n"
CAMCHAIN = "cam0:\n  T_cam_imu: [[1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1]]\n"


def laughs(levels: int = 9, key: str = "lol") -> str:
    """Nested aliases: ``levels`` lists of ten aliases each of the one before, ``10**levels``
    strings once expanded (a few hundred bytes)."""
    lines = ["l0: &l0 lol"]
    lines += [f"l{i}: &l{i} [{', '.join([f'*l{i - 1}'] * 10)}]" for i in range(1, levels + 1)]
    return "\n".join(lines) + f"\n{key}: *l{levels}\n"


#: Each YAML reader of the package, with a valid file of its kind.
READERS = {
    "kalibr imu.yaml": (read_kalibr_imu, DENSITIES),
    "kalibr camchain": (lambda p: read_camchain_T_BS(p, "cam0"), CAMCHAIN),
    "euroc sensor.yaml": (read_sensor_yaml, SENSOR_YAML),
    "any yaml": (read_yaml, "a: 1\n"),
}


def _refused(isolated, read, path, *fragments) -> str:
    outcome = isolated(lambda: read(path), seconds=15.0, memory=1 << 30)
    assert "DataError" in outcome.raised or "RigError" in outcome.raised, outcome
    assert str(path) in outcome.message and "\n" not in outcome.message, outcome.message
    for fragment in fragments:
        assert fragment in outcome.message, outcome.message
    return outcome.message


@pytest.mark.parametrize("reader", READERS)
@pytest.mark.parametrize("where", ["beside", "read"])
def test_a_billion_laughs_is_refused_naming_the_file(tmp_path, isolated, reader, where):
    """The bomb beside the keys the reader uses, or in place of the one it reads."""
    read, valid = READERS[reader]
    if where == "beside":
        text = valid + laughs()
    else:
        first_key = valid.split(":")[0]
        text = laughs(key=first_key) if reader != "kalibr camchain" else laughs() + "cam0:\n  T_cam_imu: *l9\n"
    path = tmp_path / "calibration.yaml"
    path.write_text(text)
    _refused(isolated, read, path, f"more than {MAX_NODES} nodes once its aliases are expanded")


@pytest.mark.parametrize("reader", READERS)
def test_one_anchor_repeated_past_the_bound_is_refused(tmp_path, isolated, reader):
    """No nesting, only many aliases of one small list: the expansion is counted, not the file."""
    read, valid = READERS[reader]
    path = tmp_path / "calibration.yaml"
    path.write_text(valid + "row: &row [1, 2, 3]\nmany: [" + ", ".join(["*row"] * (MAX_NODES // 4)) + "]\n")
    _refused(isolated, read, path, f"more than {MAX_NODES} nodes")


def test_a_flat_document_past_the_bound_is_refused(tmp_path, isolated):
    path = tmp_path / "imu.yaml"
    path.write_text(DENSITIES + "samples: [" + ", ".join(["0"] * (MAX_NODES + 1)) + "]\n")
    _refused(isolated, read_kalibr_imu, path, f"more than {MAX_NODES} nodes")


@pytest.mark.parametrize("text, fragment", [
    ("cam0: &loop\n  T_cam_imu: [*loop]\n", f"nested deeper than {MAX_DEPTH} levels"),
    ("cam0:\n  T_cam_imu: " + "[" * (MAX_DEPTH + 1) + "]" * (MAX_DEPTH + 1) + "\n", f"deeper than {MAX_DEPTH} levels"),
    ("cam0:\n  T_cam_imu: " + "[" * 50_000 + "]" * 50_000 + "\n", "nested deeper than the reader can follow"),
    ("cam0:\n" + "".join(" " * i + f"k{i}:\n" for i in range(1, 300)), "nested deeper"),
], ids=["recursive alias", "deep lists", "very deep lists", "deep mappings"])
def test_nesting_beyond_the_bound_is_refused(tmp_path, isolated, text, fragment):
    path = tmp_path / "camchain.yaml"
    path.write_text(text)
    _refused(isolated, lambda p: read_camchain_T_BS(p, "cam0"), path, fragment)


def test_a_rig_names_its_kalibr_file_with_the_bomb(tmp_path, isolated):
    (tmp_path / "imu.yaml").write_text(DENSITIES + laughs())
    rig = tmp_path / "rig.toml"
    rig.write_text('[imu]\nsource = "csv:imu.csv"\nkalibr = "imu.yaml"\n')
    message = _refused(isolated, load_rig, rig, f"imu.kalibr: {tmp_path / 'imu.yaml'}", "aliases")
    assert message.startswith(f"{rig}: imu.kalibr: "), message


def test_a_ros2_bags_metadata_with_the_bomb_is_refused_before_rosbags_reads_it(tmp_path, isolated):
    m = Messages("sqlite3")
    folder = write_bag(tmp_path / "run", "sqlite3", {"/imu": ("sensor_msgs/msg/Imu", [
        m.imu(10**18 + k * 10**7, (0, 0, 9.81), (0, 0, 0)) for k in range(101)])})
    metadata = folder / "metadata.yaml"
    metadata.write_text(metadata.read_text() + laughs())
    message = _refused(isolated, lambda p: read_bag_imu(p, "/imu"), folder, "aliases")
    assert message.startswith(f"{metadata}, line "), message


def test_aliases_of_a_real_files_size_are_read(tmp_path):
    """Aliases themselves are YAML: a camchain whose second camera repeats the first's extrinsic
    and a Kalibr file whose densities share an anchor read as written."""
    path = tmp_path / "camchain.yaml"
    path.write_text("cam0:\n  T_cam_imu: &T [[1, 0, 0, 0.1], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1]]\n"
                    "cam1:\n  T_cam_imu: *T\n")
    assert np.array_equal(read_camchain_T_BS(path, "cam1"), read_camchain_T_BS(path, "cam0"))
    assert read_camchain_T_BS(path, "cam1")[0, 3] == -0.1
    path = tmp_path / "imu.yaml"
    path.write_text("accelerometer_noise_density: &n 2.0e-3\naccelerometer_random_walk: *n\n"
                    "gyroscope_noise_density: 1.7e-4\ngyroscope_random_walk: 1.9e-5\n")
    assert read_kalibr_imu(path)["acc_bias"] == 2.0e-3
    assert read_yaml(path).line(("accelerometer_random_walk",)) == 2


@pytest.mark.parametrize("reader", READERS)
def test_an_integer_python_will_not_construct_is_one_error_naming_the_file(tmp_path, reader):
    """PyYAML's ValueError for an integer of more than 4300 digits ("Exceeds the limit ... for
    integer string conversion") named no file, and a rig's reading let it through as it was."""
    read, text = READERS[reader]
    path = tmp_path / "calibration.yaml"
    path.write_text(text + "big: " + "9" * 5000 + "\n")
    with pytest.raises(DataError) as info:
        read(path)
    assert str(info.value).startswith(f"{path}: found Exceeds the limit"), info.value


def test_an_asl_sensor_yamls_densities_are_checked_as_the_rig_keys_they_stand_for(tmp_path):
    """A Kalibr imu.yaml's densities were checked against the rig's ranges, an ASL sensor.yaml's
    (``--dataset euroc:PATH``) not: 1e300 ran."""
    from eurocfiles import write_sequence

    from datasets.euroc import load_euroc

    write_sequence(tmp_path)
    path = tmp_path / "mav0" / "imu0" / "sensor.yaml"
    text = path.read_text()
    assert "gyroscope_noise_density: 1.6968e-04" in text
    path.write_text(text.replace("gyroscope_noise_density: 1.6968e-04", "gyroscope_noise_density: 1.0e+300"))
    with pytest.raises(DataError, match=re.escape(f"{path}, line ") + r"\d+" + re.escape(
            ", field 'gyroscope_noise_density': found 1e+300; expected as the rig's gyro_noise_density: a value "
            "within [1e-08, 0.1] rad/s/sqrt(Hz)")):
        load_euroc(tmp_path)
