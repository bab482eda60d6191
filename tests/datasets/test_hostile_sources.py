"""Every file the datasets package reads goes through one bounded reader
(:func:`datasets.errors.read_source`): a named pipe, a device or a directory is refused without blocking and
a file beyond its kind's size limit without being read, each with an error naming the file. Every
reader of the package is tried, each in an isolated process (the ``isolated`` fixture) with a
deadline and a memory limit, so that a reader that blocks or reads without end fails its test
instead of hanging the run or exhausting the machine."""
from __future__ import annotations

import ast
import os
import re
from pathlib import Path

import numpy as np
import pytest
import scipy.linalg  # noqa: F401 -- loaded here: OpenBLAS starting under a child's memory limit spins
from bagfiles import Messages, write_bag

from datasets import errors, euroc, kitti, tum
from datasets.bags import read_bag_imu
from datasets.errors import LIMITS
from datasets.kalibr import read_camchain_T_BS, read_kalibr_imu
from datasets.rig import RigError, load_rig
from datasets.sources import (
    read_attitudes,
    read_fixes,
    read_imu,
    read_magnetic_fields,
    read_poses,
    read_positions,
    read_pressures,
    read_twists,
)

pytestmark = pytest.mark.skipif(not hasattr(os, "mkfifo"), reason="named pipes are POSIX")

#: Every reader of a file the package has: (name, kind of file, read(path)).
READERS = [
    ("csv imu", "table", lambda p: read_imu(f"csv:{p}")),
    ("csv poses", "table", lambda p: read_poses(f"csv:{p}")),
    ("csv positions", "table", lambda p: read_positions(f"csv:{p}")),
    ("csv attitudes", "table", lambda p: read_attitudes(f"csv:{p}")),
    ("csv twists", "table", lambda p: read_twists(f"csv:{p}")),
    ("csv fixes", "table", lambda p: read_fixes(f"csv:{p}")),
    ("csv pressures", "table", lambda p: read_pressures(f"csv:{p}")),
    ("csv magnetic fields", "table", lambda p: read_magnetic_fields(f"csv:{p}")),
    ("tum", "table", lambda p: read_poses(f"tum:{p}")),
    ("tum poses", "table", lambda p: tum.read_tum_poses(p, attitudes=True)),
    ("euroc ground truth", "table", euroc.read_groundtruth_csv),
    ("euroc poses", "table", euroc.read_pose_csv),
    ("kitti imu", "table", kitti.read_imu),
    ("kitti gps", "table", kitti.read_gps),
    ("kitti metadata", "table", kitti.read_metadata),
    ("kitti poses", "table", kitti.read_pose_file),
    ("euroc sensor.yaml", "yaml", euroc.read_sensor_yaml),
    ("kalibr imu.yaml", "yaml", read_kalibr_imu),
    ("kalibr camchain", "yaml", lambda p: read_camchain_T_BS(p, "cam0")),
    ("rig", "rig", load_rig),
    ("bag", "bag", lambda p: read_bag_imu(p, "/imu")),
]
NAMES = [name for name, _, _ in READERS]
#: What each kind's error says of a file too large: "the limit of <files>".
LIMIT_TEXT = {kind: f"the limit of {limit.files}" for kind, limit in LIMITS.items()}


def _refused(read, path, isolated, *fragments, errors=("DataError", "RigError")) -> str:
    """``read(path)`` raises one of ``errors`` (quickly, in a bounded process), its one-line
    message naming ``path`` and holding every fragment; returns the message."""
    outcome = isolated(lambda: read(path))
    assert set(outcome.raised) & set(errors), outcome
    message = outcome.message
    assert str(path) in message and "\n" not in message, message
    for fragment in fragments:
        assert fragment in message, message
    return message


def _sparse(path: Path, size: int) -> Path:
    """A file of ``size`` bytes that takes no disk space (a hole)."""
    with open(path, "wb") as handle:
        try:
            handle.truncate(size)
        except OSError as error:
            pytest.skip(f"this file system holds no sparse file of {size} bytes ({error.strerror})")
    return path


@pytest.mark.parametrize("name, kind, read", READERS, ids=NAMES)
def test_a_named_pipe_is_refused_without_blocking(tmp_path, isolated, name, kind, read):
    fifo = tmp_path / "source"
    os.mkfifo(fifo)
    _refused(read, fifo, isolated, "a named pipe (FIFO)", "a regular file")


@pytest.mark.parametrize("name, kind, read", READERS, ids=NAMES)
def test_a_device_is_refused(isolated, name, kind, read):
    if not os.path.exists("/dev/zero"):
        pytest.skip("no /dev/zero")
    _refused(read, Path("/dev/zero"), isolated, "a character device", "a regular file")


@pytest.mark.parametrize("name, kind, read", [r for r in READERS if r[1] != "bag"], ids=NAMES[:-1])
def test_a_directory_is_refused(tmp_path, isolated, name, kind, read):
    _refused(read, tmp_path, isolated, "a directory", "a regular file")


@pytest.mark.parametrize("name, kind, read", READERS, ids=NAMES)
def test_a_file_beyond_its_kinds_limit_is_refused_unread(tmp_path, isolated, name, kind, read):
    """One byte beyond the limit (a sparse file: nothing is written); the error gives the size and
    the limit."""
    size = LIMITS[kind].bytes + 1
    _refused(read, _sparse(tmp_path / "source", size), isolated, f"({size} bytes)", LIMIT_TEXT[kind])


def test_a_six_gigabyte_csv_is_one_error_naming_it_and_the_limit(tmp_path, isolated):
    path = _sparse(tmp_path / "imu.csv", 6 * 2**30)
    message = _refused(lambda p: read_imu(f"csv:{p}"), path, isolated)
    assert message == (f"{path}: found 6 GiB (6442450944 bytes); expected at most 1 GiB, the limit of text tables "
                       f"(CSV, TUM and KITTI files): {LIMITS['table'].why}")


@pytest.mark.parametrize("kind", sorted(LIMITS))
def test_a_file_at_its_limit_is_read(tmp_path, kind):
    """The limit itself is allowed: only what lies beyond is refused (checked on the bytes read,
    without parsing them)."""
    if kind in ("table", "bag", "npz"):  # not read whole here: their limits are gigabytes
        path = _sparse(tmp_path / "source", LIMITS[kind].bytes)
        assert errors.check_source(path, kind).st_size == LIMITS[kind].bytes
        return
    path = tmp_path / "source"
    path.write_bytes(b"#" * LIMITS[kind].bytes)
    assert len(errors.read_source(path, kind)) == LIMITS[kind].bytes


def test_a_file_swapped_for_a_pipe_after_its_check_is_still_refused(tmp_path, isolated, monkeypatch):
    """The file is opened non-blocking and checked again: a pipe that took a regular file's place
    between the check and the opening neither blocks nor reads as an empty file."""
    fifo = tmp_path / "imu.csv"
    os.mkfifo(fifo)
    monkeypatch.setattr(errors, "check_source", lambda path, kind: None)  # the check saw a regular file
    _refused(lambda p: read_imu(f"csv:{p}"), fifo, isolated, "a named pipe (FIFO)")


def test_a_file_longer_than_its_size_says_is_cut_at_the_limit(tmp_path, monkeypatch):
    """A file that grows while it is read (here one that reports size 0, as /proc's do) is read no
    further than the limit and refused."""
    proc = Path("/proc/self/maps")
    if not proc.exists() or proc.stat().st_size != 0:
        pytest.skip("no /proc file of reported size 0")
    monkeypatch.setitem(LIMITS, "rig", errors.SizeLimit("rig files (TOML)", 100, "a test's limit"))
    with pytest.raises(RigError, match=re.escape(f"{proc}: more than 100 bytes once read; expected at most 100 bytes")):
        load_rig(proc)


@pytest.fixture
def ros2_bag(tmp_path):
    """A ROS 2 (sqlite3) bag folder of two seconds of IMU messages; returns the folder and its
    storage file."""
    m = Messages("sqlite3")
    folder = write_bag(tmp_path / "run", "sqlite3", {"/imu": ("sensor_msgs/msg/Imu", [
        m.imu(10**18 + k * 10**7, (0, 0, 9.81), (0, 0, 0)) for k in range(201)])})
    storage = next(folder.glob("*.db3"))
    assert len(read_bag_imu(folder, "/imu")) == 201
    return folder, storage


@pytest.mark.parametrize("which", ["metadata.yaml", "storage"])
@pytest.mark.parametrize("replacement", ["pipe", "too large"])
def test_a_ros2_folders_files_are_checked_before_rosbags_opens_them(ros2_bag, isolated, which, replacement):
    folder, storage = ros2_bag
    path = folder / "metadata.yaml" if which == "metadata.yaml" else storage
    path.unlink()
    if replacement == "pipe":
        os.mkfifo(path)
        expected = "a named pipe (FIFO)"
    else:
        kind = "yaml" if which == "metadata.yaml" else "bag"
        _sparse(path, LIMITS[kind].bytes + 1)
        expected = LIMIT_TEXT[kind]
    message = _refused(lambda p: read_bag_imu(p, "/imu"), folder, isolated, expected, errors=("DataError",))
    assert message.startswith(f"{path}, field 'topic /imu': found "), message


@pytest.mark.parametrize("key, extra", [
    ("imu.kalibr", 'kalibr = "{path}"\n'),
    ('sensor[1] "cam".camchain', None),
])
def test_a_rigs_calibration_file_that_is_a_pipe_is_named_with_its_key(tmp_path, isolated, key, extra):
    fifo = tmp_path / "calibration.yaml"
    os.mkfifo(fifo)
    text = ('[imu]\nsource = "csv:imu.csv"\naccel_noise_density = 2e-3\ngyro_noise_density = 2e-4\n'
            'accel_random_walk = 3e-4\ngyro_random_walk = 2e-5\n')
    if extra is not None:
        text += extra.format(path=fifo)
    else:
        text += (f'[[sensor]]\nname = "cam"\nkind = "pose"\nsource = "tum:cam.txt"\ncamchain = "{fifo}"\n'
                 'camera = "cam0"\n')
    rig = tmp_path / "rig.toml"
    rig.write_text(text)
    message = _refused(load_rig, rig, isolated, f"{key}: {fifo}: found a named pipe (FIFO)")
    assert message.startswith(f"{rig}: {key}: "), message


def test_a_rigs_imu_source_that_is_a_pipe_is_one_error_naming_it(tmp_path, isolated):
    from datasets.recording import load_recording

    os.mkfifo(tmp_path / "imu.csv")
    rig = tmp_path / "rig.toml"
    rig.write_text('[imu]\nsource = "csv:imu.csv"\naccel_noise_density = 2e-3\ngyro_noise_density = 2e-4\n'
                   'accel_random_walk = 3e-4\ngyro_random_walk = 2e-5\n')
    message = _refused(lambda _: load_recording(load_rig(rig)), tmp_path / "imu.csv", isolated, errors=("DataError",))
    assert message.startswith(f"{tmp_path / 'imu.csv'}: found a named pipe (FIFO)"), message


#: The only calls in ``datasets/`` that open a file or hand a path to a library that does, and why.
ALLOWED_OPENERS = {
    ("errors.py", "os.open"): "the bounded reader itself (read_source)",
    ("errors.py", "os.fdopen"): "the bounded reader itself (read_source)",
    ("atomic.py", "os.open"): "writing outputs, not reading input",
    ("atomic.py", "os.fdopen"): "writing outputs, not reading input",
    ("errors.py", "np.loadtxt"): "parses text already read (io.StringIO)",
    ("bags.py", "AnyReader"): "rosbags opens the bag after _check_files checked every file it reads",
    ("bags.py", ".open"): "AnyReader.open, as above",
}
#: Calls that open or read a file: by name, or a method of any object by its attribute.
OPENERS = {"open", "os.open", "os.fdopen", "io.open", "np.loadtxt", "np.genfromtxt", "np.load", "np.fromfile",
           "AnyReader", "Reader", "tomllib.load", "yaml.load", "yaml.safe_load", "yaml.compose", "yaml.full_load"}
OPENER_METHODS = {"read_text", "read_bytes", "open"}


def _dotted(node) -> str | None:
    if isinstance(node, ast.Name):
        return node.id
    if isinstance(node, ast.Attribute):
        base = _dotted(node.value)
        return f"{base}.{node.attr}" if base else None
    return None


def test_every_file_read_goes_through_the_bounded_reader():
    """No module of the package opens a file itself but where listed: a new reader must use
    datasets.errors.read_source, or be listed here with its reason."""
    root = Path(__file__).resolve().parents[2] / "datasets"
    found = set()
    for path in sorted(root.rglob("*.py")):
        for node in ast.walk(ast.parse(path.read_text(), filename=str(path))):
            if not isinstance(node, ast.Call):
                continue
            name = _dotted(node.func)
            if name in OPENERS:
                found.add((path.name, name))
            elif isinstance(node.func, ast.Attribute) and node.func.attr in OPENER_METHODS:
                found.add((path.name, "." + node.func.attr))
    assert found <= set(ALLOWED_OPENERS), sorted(found - set(ALLOWED_OPENERS))


def test_ordinary_files_still_read(tmp_path):
    """The checks refuse nothing an ordinary recording has: a symbolic link to a regular file is
    read as the file."""
    t = np.arange(3.0)
    (tmp_path / "p.csv").write_text("t,x,y,z\n" + "".join(f"{x},1,2,3\n" for x in t))
    (tmp_path / "link.csv").symlink_to(tmp_path / "p.csv")
    assert np.array_equal(read_positions(f"csv:{tmp_path / 'link.csv'}").t, t)


@pytest.mark.parametrize("name, kind, read", READERS, ids=NAMES)
def test_a_path_with_a_nul_is_one_error_naming_it(tmp_path, name, kind, read):
    """The system call's ValueError ("embedded null byte") named no file; a path given in Python
    or in a rig can hold a NUL (TOML's \\u0000)."""
    path = tmp_path / "imu\0.csv"
    with pytest.raises(ValueError) as info:
        read(path)
    message = str(info.value)
    assert "NUL character" in message and repr(str(path))[1:-1] in message and "\n" not in message, message


def _ros1_bag(tmp_path: Path) -> Path:
    """A ROS 1 bag of two seconds of IMU messages."""
    m = Messages("ros1")
    return write_bag(tmp_path / "run.bag", "ros1", {"/imu": ("sensor_msgs/msg/Imu", [
        m.imu(10**18 + k * 10**7, (0, 0, 9.81), (0, 0, 0)) for k in range(201)])})


def _index_pos(bag: Path) -> int:
    """Where a ROS 1 bag's index (its connection records) starts: the bag header's index_pos."""
    data = bag.read_bytes()
    start = len(b"#ROSBAG V2.0\n")
    length = int.from_bytes(data[start:start + 4], "little")
    header, i = data[start + 4:start + 4 + length], 0
    while i < len(header):
        size = int.from_bytes(header[i:i + 4], "little")
        name, _, value = header[i + 4:i + 4 + size].partition(b"=")
        if name == b"index_pos":
            return int.from_bytes(value, "little")
        i += 4 + size
    raise AssertionError("no index_pos")


@pytest.mark.parametrize("damage, fragment", [
    ("sparse", "an unreadable bag (it starts with b'\\x00"),  # no line end: rosbags read it whole for its version
    ("bag header", "an unreadable bag (a bag header of 4294967280 bytes"),
    ("connection record", "out of memory"),  # a record's length field of ~4 GiB, read as it says
])
def test_a_ros1_bag_whose_lengths_lie_is_refused_naming_it_within_the_memory_limit(tmp_path, isolated, damage,
                                                                                     fragment):
    """rosbags trusts a ROS 1 bag's version line and record lengths: a 6 GiB file of zeros named
    .bag was read whole looking for the version's line end (out of memory, the file not named)."""
    if damage == "sparse":
        bag = _sparse(tmp_path / "run.bag", 6 * 2**30)
    else:
        bag = _ros1_bag(tmp_path)
        data = bytearray(bag.read_bytes())
        at = len(b"#ROSBAG V2.0\n") if damage == "bag header" else _index_pos(bag)
        data[at:at + 4] = (0xFFFFFFF0).to_bytes(4, "little")
        bag.write_bytes(bytes(data))
    message = _refused(lambda p: read_bag_imu(p, "/imu"), bag, isolated, fragment, errors=("DataError",))
    assert message.startswith(f"{bag}"), message


#: A table's read may take this many times its size in memory, and a few megabytes (its text once
#: and its lines once as Python strings, some 2.6 times its size, the values as floats): eight
#: before, and a gibibyte more for any table.
TABLE_MEMORY_FACTOR, TABLE_MEMORY_SLACK = 5, 16 << 20


@pytest.mark.parametrize("name", ["csv imu", "csv positions"])
def test_a_table_is_read_within_a_few_times_its_size(tmp_path, isolated, name):
    """The 1 GiB a table may be has to fit the 4 GB a run may take: a read of n bytes took n bytes
    at once (a gibibyte for every table), and the parser held the text twice more, once in an
    io.StringIO at four bytes a character (a 421 MB IMU file took 3.3 GB, a 1 GiB one 8)."""
    n = 200_000
    if name == "csv imu":
        row = ",0.0123456789012345,-0.0234567890123456,0.0345678901234567,0.123456789012345,-0.2345678901234,9.8066\n"
        stamps = (10**18 + np.arange(n, dtype=np.int64) * 5_000_000).tolist()
        text = "#timestamp,w_RS_S_x,w_RS_S_y,w_RS_S_z,a_RS_S_x,a_RS_S_y,a_RS_S_z\n" + row.join(map(str, stamps)) + row
    else:
        row = ",12345.6789012345,-2345.67890123456,345.678901234567,0.11,0.12,0.13\n"
        text = "t,x,y,z,sigma_x,sigma_y,sigma_z\n" + row.join(repr(x) for x in (np.arange(n) * 0.005).tolist()) + row
    path = tmp_path / "table.csv"
    path.write_text(text)
    read = dict((r[0], r[2]) for r in READERS)[name]
    outcome = isolated(lambda: read(path), memory=TABLE_MEMORY_FACTOR * len(text) + TABLE_MEMORY_SLACK)
    assert outcome.raised == (), outcome
