"""TUM trajectory files: exact round trip, the scalar-last quaternion, comments, and clear errors."""
from __future__ import annotations

import tempfile
from pathlib import Path

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from datasets.errors import DataError
from datasets.tum import read_tum, write_tum
from datasets.types import Trajectory
from factors import quaternion, so3
from factors.imu import ImuState


def _random_trajectory(n=50, seed=0, t0=1403636579.7585556):
    rng = np.random.default_rng(seed)
    t = t0 + np.cumsum(rng.uniform(0.001, 0.1, n))
    r = rng.normal(scale=100.0, size=(n, 3))
    C = so3.exp(rng.normal(scale=2.0, size=(n, 3)))
    return t, r, C


def test_round_trip_is_exact(tmp_path):
    t, r, C = _random_trajectory()
    path = tmp_path / "traj.txt"
    write_tum(path, t, r, C)
    back = read_tum(path)
    assert np.array_equal(back.t, t)
    assert np.array_equal(back.position, r)
    assert np.abs(back.C - C).max() < 1e-14
    assert np.all(np.isnan(back.states.v)) and np.all(np.isnan(back.states.b_f)) and np.all(np.isnan(back.states.b_w))


def test_write_from_trajectory_equals_write_from_arrays(tmp_path):
    t, r, C = _random_trajectory(seed=3)
    z = np.zeros_like(r)
    write_tum(tmp_path / "a.txt", Trajectory(t, ImuState(r, z, C, z, z)))
    write_tum(tmp_path / "b.txt", t, r, C)
    assert (tmp_path / "a.txt").read_text() == (tmp_path / "b.txt").read_text()


def test_quaternion_is_scalar_last_in_the_file(tmp_path):
    # 90 degrees about z: Hamilton (w, x, y, z) = (cos 45, 0, 0, sin 45); the file has x y z w.
    C = so3.exp(np.array([[0.0, 0.0, np.pi / 2]]))
    write_tum(tmp_path / "q.txt", [1.5], [[1.0, 2.0, 3.0]], C)
    line = [ln for ln in (tmp_path / "q.txt").read_text().splitlines() if not ln.startswith("#")][0]
    values = [float(x) for x in line.split()]
    assert values[:4] == [1.5, 1.0, 2.0, 3.0]
    assert np.allclose(values[4:], [0.0, 0.0, np.sqrt(0.5), np.sqrt(0.5)], atol=1e-15)


def test_reads_comments_blank_lines_tabs_and_normalises_6_decimal_quaternions(tmp_path):
    q = quaternion.exp(np.array([0.3, -0.2, 1.0]))  # w x y z
    q6 = np.round(quaternion.to_xyzw(q), 6)
    text = (
        "# a comment\n\n"
        f"0.0\t1 2 3  {q6[0]} {q6[1]} {q6[2]} {q6[3]}\n"
        "   # indented comment\n"
        "0.5 4 5 6 0 0 0 1\n"
    )
    (tmp_path / "c.txt").write_text(text)
    traj = read_tum(tmp_path / "c.txt")
    assert np.array_equal(traj.t, [0.0, 0.5])
    assert np.array_equal(traj.position, [[1, 2, 3], [4, 5, 6]])
    assert np.abs(traj.C[0] - quaternion.to_matrix(q)).max() < 5e-6
    assert np.allclose(traj.C[1], np.eye(3))
    assert np.abs(traj.C[0] @ traj.C[0].T - np.eye(3)).max() < 1e-14


GOOD = "0.0 0 0 0 0 0 0 1\n0.1 1 0 0 0 0 0 1\n0.2 2 0 0 0 0 0 1\n"


@pytest.mark.parametrize(
    "text, line, field",
    [
        ("0.0 0 0 0 0 0 0 1\n0.1 1 0 0 0 0 1\n", 2, "qw"),  # missing column
        ("0.0 0 0 0 0 0 0 1\n0.1 1 0 0 0 0 0 1 7\n", 2, None),  # extra column
        ("0.0 0 0 0 0 0 0 1\n0.1 nan 0 0 0 0 0 1\n", 2, "tx"),
        ("0.0 0 0 0 0 0 0 1\n0.1 1 inf 0 0 0 0 1\n", 2, "ty"),
        ("0.0 0 0 0 0 0 0 1\n0.1 1 0 x 0 0 0 1\n", 2, "tz"),
        ("0.0 0 0 0 0 0 0 1\n0.0 1 0 0 0 0 0 1\n", 2, "timestamp"),  # duplicate
        ("# c\n0.2 0 0 0 0 0 0 1\n0.1 1 0 0 0 0 0 1\n", 3, "timestamp"),  # decreasing
        ("0.0 0 0 0 0 0 0 1\n0.1 1 0 0 0 0 0 1.2\n", 2, "qx qy qz qw"),  # non-unit quaternion
        ("0.0 0 0 0 0 0 0 0\n", 1, "qx qy qz qw"),  # zero quaternion
        ("", 1, None),  # empty file
        ("# only\n# comments\n", 2, None),
    ],
)
def test_malformed_files_name_file_line_and_field(tmp_path, text, line, field):
    path = tmp_path / "bad.txt"
    path.write_text(text)
    with pytest.raises(DataError) as info:
        read_tum(path)
    message = str(info.value)
    assert str(path) in message
    assert f"line {line}" in message
    assert info.value.line == line
    if field is not None:
        assert f"'{field}'" in message and info.value.field == field


def test_missing_file_and_binary_file(tmp_path):
    with pytest.raises(DataError, match="no such file"):
        read_tum(tmp_path / "absent.txt")
    (tmp_path / "bin.txt").write_bytes(b"0.0 0 0 0 0 0 0 1\n\xff\xfe\n")
    with pytest.raises(DataError, match=r"line 2.*UTF-8"):
        read_tum(tmp_path / "bin.txt")


def test_failed_write_leaves_the_old_file(tmp_path):
    path = tmp_path / "keep.txt"
    path.write_text(GOOD)
    bad_C = np.tile(np.eye(3), (3, 1, 1))
    bad_C[1] *= 2.0  # not a rotation
    with pytest.raises(ValueError):
        write_tum(path, [0.0, 1.0, 2.0], np.zeros((3, 3)), bad_C)
    assert path.read_text() == GOOD
    assert sorted(p.name for p in tmp_path.iterdir()) == ["keep.txt"]


_TOKENS = st.sampled_from(
    ["0", "1", "-1", "0.5", "1e3", "1e400", "nan", "inf", "-inf", "x", "", " ", "#", "\t", "1_0", "0x1f", "1.2.3",
     "\u00e9", "0 0 0 0", "1e-400", ",", "+", "-", "9" * 40]
)
_LINES = st.lists(_TOKENS, min_size=0, max_size=12).map(" ".join)


@settings(max_examples=150, deadline=None, derandomize=True, suppress_health_check=[HealthCheck.too_slow])
@given(lines=st.lists(_LINES, min_size=1, max_size=4), where=st.integers(0, 3))
def test_fuzz_only_data_errors_naming_the_file(lines, where):
    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / "fuzz.txt"
        good = GOOD.splitlines()
        text = "\n".join(good[:where] + lines + good[where:]) + "\n"
        path.write_text(text, encoding="utf-8")
        try:
            traj = read_tum(path)
        except DataError as error:
            assert str(path) in str(error)
            assert error.line is None or 1 <= error.line <= len(text.splitlines()) + 1
        else:
            assert np.all(np.diff(traj.t) > 0)
            assert np.all(np.isfinite(traj.position))


def test_write_tum_in_the_data_clock_keeps_nanosecond_stamps(tmp_path):
    """EuRoC-like stamps: an origin in integer nanoseconds plus small float times, written as the
    exact stamps (evo then associates them with the sequence's own ground truth)."""
    from datasets.tum import format_ns

    origin = 1403715273262142976
    t = np.array([0.0, 0.005, 1.25])
    write_tum(tmp_path / "a.tum", t, np.zeros((3, 3)), np.broadcast_to(np.eye(3), (3, 3, 3)).copy(),
              time_origin_ns=origin)
    stamps = [line.split()[0] for line in (tmp_path / "a.tum").read_text().splitlines()[1:]]
    assert stamps == ["1403715273.262142976", "1403715273.267142976", "1403715274.512142976"]
    assert format_ns(-1_500_000_000) == "-1.500000000"


def test_a_duplicate_stamp_is_shown_whole(tmp_path):
    """EuRoC-sized stamps with all their digits: both are in the message, not cut at 60 characters."""
    path = tmp_path / "dup.txt"
    path.write_text("1403715572.112143039 0 0 0 0 0 0 1\n1403715572.162142992 1 0 0 0 0 0 1\n"
                    "1403715572.162142992 2 0 0 0 0 0 1\n")
    with pytest.raises(DataError) as info:
        read_tum(path)
    message = str(info.value)
    assert "found 1403715572.162143, a duplicate of line 2 (1403715572.162143); expected strictly" in message
