"""EuRoC/ASL loader on synthetic sequence folders written here (no EuRoC data ships anywhere):
header variants, extrinsics that are not the identity, exact nanosecond stamps, and errors."""
from __future__ import annotations

import tempfile
from pathlib import Path

import numpy as np
import pytest
from eurocfiles import (
    B_ACC_GT,
    B_GYRO_GT,
    GT,
    IMU,
    IMU_STEP,
    NOISE_YAML,
    NS0,
    R_X,
    T_B_GT,
    T_B_IMU,
    imu_truth,
    sensor_yaml,
    write_sequence,
)
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from datasets.errors import DataError
from datasets.euroc import load_euroc, read_sensor_yaml

pytestmark = pytest.mark.filterwarnings("ignore:.*the ground truth covers .* s of the:UserWarning")

@pytest.fixture
def sequence(tmp_path):
    imu_ns, readings, gt_ns = write_sequence(tmp_path)
    return tmp_path, imu_ns, readings, gt_ns


# ------------------------------------------------------------------------------------------


def test_frames_times_and_initial_state(sequence):
    root, imu_ns, readings, gt_ns = sequence
    with pytest.warns(UserWarning, match=r"data\.csv: the ground truth covers 1\.845 s of the 2 s of .*imu0/data\.csv: "
                                         r"the 11 IMU samples before its first stamp \(0\.0513 s\) are left out "
                                         r"\(the initial state is the truth's\); the 21 after its last stamp "
                                         r"\(0\.1037 s\) are kept: estimated, not scored$"):
        d = load_euroc(root)
    assert d.name == "euroc"
    # IMU samples from the ground truth's first stamp on, stamps exact, t relative to the first of them.
    keep = imu_ns >= gt_ns[0]
    assert np.array_equal(d.imu.t_ns, imu_ns[keep]) and d.imu.t_ns.dtype == np.int64
    assert d.imu.t_ns[0] == NS0 + 11 * IMU_STEP
    assert np.array_equal(d.imu.t, (imu_ns[keep] - imu_ns[keep][0]) * 1e-9)
    assert d.imu.t[0] == 0.0 and abs(d.imu.t[1] - 0.005) < 1e-15
    assert np.array_equal(d.imu.gyro, readings[keep, 0:3]) and np.array_equal(d.imu.acc, readings[keep, 3:6])
    # Ground truth: of the IMU (not of S_gt), body-frame velocity, biases in the IMU frame.
    t_abs = (d.truth.t * 1e9 + (d.imu.t_ns[0] - NS0)) * 1e-9
    C, r, v_world = imu_truth(t_abs)
    inside = gt_ns[(gt_ns >= d.imu.t_ns[0]) & (gt_ns <= d.imu.t_ns[-1])]
    assert np.array_equal(d.truth.t, (inside - d.imu.t_ns[0]) * 1e-9)
    assert np.abs(d.truth.C - C).max() < 1e-12
    assert np.abs(d.truth.position - r).max() < 1e-12
    assert np.abs(d.truth.states.v - np.einsum("nji,nj->ni", C, v_world)).max() < 1e-9
    assert np.allclose(d.truth.states.b_w, R_X.T @ B_GYRO_GT, atol=1e-15)
    assert np.allclose(d.truth.states.b_f, R_X.T @ B_ACC_GT, atol=1e-15)
    # Initial state: the truth at the first IMU stamp (between two ground-truth samples).
    C0_, r0_, v0_ = imu_truth([(d.imu.t_ns[0] - NS0) * 1e-9])
    assert np.abs(d.initial.C - C0_[0]).max() < 1e-9
    assert np.abs(d.initial.r - r0_[0]).max() < 1e-6
    assert np.abs(d.initial.v - C0_[0].T @ v0_[0]).max() < 1e-6
    assert np.allclose(d.initial.b_f, R_X.T @ B_ACC_GT)
    # Noise densities from imu0/sensor.yaml; gravity z up.
    assert (d.noise.gyro, d.noise.gyro_bias, d.noise.acc, d.noise.acc_bias) == (1.6968e-04, 1.9393e-05, 2.0e-3, 3.0e-3)
    assert np.array_equal(d.gravity, [0.0, 0.0, -9.81])
    assert np.allclose(np.sqrt(np.diag(d.initial_cov)), np.repeat([0.01, 0.01, 0.01, 0.05, 0.002], 3))


def test_plain_files_take_the_fast_parser_and_give_what_the_token_parser_gives(tmp_path, monkeypatch):
    """A file of plain rows is read by NumPy's C parser (exact int64 stamps); a trailing comma on
    one line (accepted) sends it through the token parser, with the same stamps and values."""
    from datasets import euroc

    imu_ns, readings, _ = write_sequence(tmp_path)
    path = tmp_path / IMU
    with monkeypatch.context() as patch:  # the token parser must not be reached
        patch.setattr(euroc, "integer", lambda *args: pytest.fail("token parser used"))
        stamps, acc, gyro = euroc.read_imu_csv(path)
    assert stamps.dtype == np.int64 and np.array_equal(stamps, imu_ns)
    assert np.array_equal(gyro, readings[:, :3]) and np.array_equal(acc, readings[:, 3:])
    lines = path.read_text().splitlines()
    path.write_text("\n".join(lines[:10] + [lines[10] + ","] + lines[11:]) + "\n")
    slow_stamps, slow_acc, slow_gyro = euroc.read_imu_csv(path)
    assert np.array_equal(slow_stamps, stamps) and np.array_equal(slow_acc, acc) and np.array_equal(slow_gyro, gyro)


def test_identity_extrinsics_give_the_file_values(tmp_path):
    write_sequence(tmp_path, T_imu=np.eye(4), T_gt=np.eye(4))
    d = load_euroc(tmp_path / "mav0")  # the mav0 folder itself works too
    assert np.allclose(d.truth.states.b_w, B_GYRO_GT) and np.allclose(d.truth.states.b_f, B_ACC_GT)


def test_wrong_extrinsics_would_be_noticed(tmp_path):
    """Swapping the two T_BS must change the result (guards against ignoring the extrinsics)."""
    write_sequence(tmp_path, T_imu=T_B_GT, T_gt=T_B_IMU)
    d = load_euroc(tmp_path)
    C, _, _ = imu_truth((d.truth.t * 1e9 + (d.imu.t_ns[0] - NS0)) * 1e-9)
    assert np.abs(d.truth.C - C).max() > 0.1


@pytest.mark.parametrize("style, gt_style", [
    ("units", "spaces"), ("plain", "plain"), ("spaces", "units_spaces"), ("units_spaces", "units"),
    ("none", "none"), ("crlf", "crlf"),
])
def test_header_variants_give_the_same_dataset(tmp_path, style, gt_style):
    write_sequence(tmp_path / "ref")
    write_sequence(tmp_path / "var", style=style, gt_style=gt_style)
    a, b = load_euroc(tmp_path / "ref"), load_euroc(tmp_path / "var")
    assert np.array_equal(a.imu.t_ns, b.imu.t_ns) and np.array_equal(a.imu.acc, b.imu.acc)
    assert np.array_equal(a.truth.position, b.truth.position) and np.array_equal(a.truth.C, b.truth.C)


def test_columns_are_found_by_name(tmp_path):
    write_sequence(tmp_path / "ref")
    write_sequence(tmp_path / "shuffled", order=[3, 4, 5, 0, 1, 2])
    a, b = load_euroc(tmp_path / "ref"), load_euroc(tmp_path / "shuffled")
    assert np.array_equal(a.imu.acc, b.imu.acc) and np.array_equal(a.imu.gyro, b.imu.gyro)
    header = (tmp_path / "shuffled/mav0/imu0/data.csv").read_text().splitlines()[0]
    assert header.startswith("#timestamp [ns],a_RS_S_x")


def test_flow_style_yaml_and_the_parser():
    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / "sensor.yaml"
        for flow in (False, True):
            path.write_text(sensor_yaml(T_B_IMU, NOISE_YAML, flow))
            y = read_sensor_yaml(path)
            assert np.abs(y.T_BS - T_B_IMU).max() < 1e-15
            assert y.document.data["rate_hz"] == 200 and y.document.data["gyroscope_random_walk"] == 1.9393e-05


@pytest.mark.parametrize("edit, line, field, found", [
    # a second T_BS block (a leftover of an edit): which one counts would be a guess
    (lambda text: text + "T_BS:\n  cols: 4\n  rows: 4\n  data: [1, 0, 0, 5, 0, 1, 0, 0, 0, 0, 1, 0, 0, 0, 0, 1]\n",
     16, "T_BS", "a second 'T_BS:' (the first at line 7)"),
    (lambda text: text + "rate_hz: 100\n", 16, "rate_hz", "a second 'rate_hz:' (the first at line 14)"),
    (lambda text: text.replace("  rows: 4\n", "  rows: 4\n  rows: 4\n"), 10, "T_BS.rows", "a second 'rows:'"),
    # a list that is never closed: named where the next key starts, not at the end of the file
    (lambda text: text.replace("0.0, 0.0, 0.0, 1.0]", "0.0, 0.0, 0.0, 1.0"), 14, None, "flow sequence"),
])
def test_sensor_yaml_duplicate_keys_and_an_unclosed_list(tmp_path, edit, line, field, found):
    path = tmp_path / "sensor.yaml"
    path.write_text(edit(sensor_yaml(T_B_IMU)))
    with pytest.raises(DataError) as info:
        read_sensor_yaml(path)
    assert (info.value.line, info.value.field) == (line, field) and found in str(info.value.found), str(info.value)


def test_sensors_drawn_from_the_ground_truth(sequence):
    """An EuRoC sequence has no aiding sensor of its own; sensors drawn from its ground truth sit
    on truth samples at their rates with the stated covariance, reproducibly, each with a stream
    of its own."""
    from datasets.simulated_sensors import truth_sensors

    d = load_euroc(sequence[0])
    assert d.sensors == ()

    def drawn(pose, gps, seed):
        return {s.name: s.data for s in truth_sensors(d.truth, d.imu, pose, gps, seed)}

    m = drawn((20, 0.01, 0.005), (10, 0.1), 3)
    assert set(m["pose"].t) <= set(d.truth.t) and set(m["gps"].t) <= set(d.truth.t)
    assert np.allclose(np.diff(m["pose"].t), 0.05) and np.allclose(np.diff(m["gps"].t), 0.1)
    assert np.allclose(m["pose"].cov[0], np.diag([1e-4] * 3 + [2.5e-5] * 3))
    again = drawn((20, 0.01, 0.005), (10, 0.1), 3)
    assert np.array_equal(m["pose"].position, again["pose"].position) and np.array_equal(m["pose"].C, again["pose"].C)
    other = drawn((20, 0.01, 0.005), None, 4)
    assert not np.allclose(m["pose"].position, other["pose"].position) and "gps" not in other
    common, i, j = np.intersect1d(m["pose"].t, m["gps"].t, return_indices=True)
    k = np.searchsorted(d.truth.t, common)
    e_pose = (m["pose"].position[i] - d.truth.position[k]) / 0.01
    e_gps = (m["gps"].position[j] - d.truth.position[k]) / 0.1
    assert not np.allclose(e_pose, e_gps)
    with pytest.raises(ValueError, match="pose_from_truth"):
        truth_sensors(d.truth, d.imu, (20, 0.01), None)


# ------------------------------------------------------------------------------------------
# malformed input


def _edit(path: Path, line: int, func) -> None:
    lines = path.read_text().splitlines()
    lines[line - 1] = func(lines[line - 1])
    path.write_text("\n".join(lines) + "\n")


def _set_field(index, value):
    def f(text):
        fields = text.split(",")
        fields[index] = value
        return ",".join(fields)
    return f


IMU_YAML = "mav0/imu0/sensor.yaml"
GT_YAML = "mav0/state_groundtruth_estimate0/sensor.yaml"


@pytest.mark.parametrize(
    "file, line, edit, field, expected",
    [
        (IMU, 1, lambda s: s.rsplit(",", 1)[0], "a_RS_S_z", "a column named a_RS_S_z"),  # header lacks a column
        (IMU, 5, lambda s: s.rsplit(",", 1)[0], "a_RS_S_z", "7 comma-separated fields"),
        (IMU, 5, _set_field(2, "nan"), "w_RS_S_y", "finite number"),
        (IMU, 5, _set_field(4, "1.5.2"), "a_RS_S_x", "a number"),
        (IMU, 5, _set_field(0, "1403636579.5"), "timestamp [ns]", "an integer"),
        (IMU, 2, _set_field(0, "-5"), "timestamp [ns]", ">= 0"),
        (IMU, 5, _set_field(0, str(NS0 + 2 * IMU_STEP)), "timestamp [ns]", "strictly increasing"),  # duplicate
        (IMU, 5, _set_field(0, str(NS0 + IMU_STEP)), "timestamp [ns]", "strictly increasing"),  # decreasing
        (IMU, 1, lambda s: "#stamp,w_RS_S_x", "header", "timestamp"),
        (GT, 7, _set_field(5, "0.9"), "q_RS_w q_RS_x q_RS_y q_RS_z", "unit quaternion"),
        (GT, 7, _set_field(2, "inf"), "p_RS_R_y", "finite"),
        (GT, 7, _set_field(16, ""), "b_a_RS_S_z", "a number"),
        (GT, 1, lambda s: s.replace("v_RS_R_y", "v_RS_R_q"), "v_RS_R_y", "a column named v_RS_R_y"),
        (IMU_YAML, 13, lambda s: s.replace("0.0, ", "", 1), "T_BS.data", "16 numbers"),
        (IMU_YAML, 8, lambda s: s.replace("4", "3"), "T_BS.cols", "4"),
        (GT_YAML, 10, lambda s: s.replace("[", "[2.0 * ", 1), "T_BS.data[0]", "a number"),
        (IMU_YAML, 13, lambda s: s.replace("1.0]", "2.0]"), "T_BS.data[12]", "0, 0, 0, 1"),
        (IMU_YAML, 19, lambda s: s.replace("2.0000e-3", "fast"), "accelerometer_noise_density", "a number"),
        (IMU_YAML, 7, lambda s: s.replace("T_BS", "T_SB"), "T_BS", "T_BS"),
        (IMU_YAML, 11, lambda s: s.replace("0.28", "0.2.8"), "T_BS.data[4]", "a number"),
        (IMU_YAML, 12, lambda s: s.replace("0.06", "0.06,"), "T_BS.data", "16 numbers"),
    ],
)
def test_malformed_files(tmp_path, file, line, edit, field, expected):
    write_sequence(tmp_path)
    path = tmp_path / file
    _edit(path, line, edit)
    before = {p: p.read_bytes() for p in tmp_path.rglob("*") if p.is_file()}
    with pytest.raises(DataError) as info:
        load_euroc(tmp_path)
    message = str(info.value)
    assert str(path) in message, message
    assert f"line {info.value.line}" in message and info.value.field == field, message
    if field == "T_BS":  # no T_BS block at all: reported at the end of the file
        assert info.value.line == len(path.read_text().splitlines())
    elif field == "T_BS.data" and expected == "16 numbers":  # counted at the closing bracket
        assert info.value.line == 13
    else:
        assert info.value.line == line, message
    assert expected in message, message
    assert before == {p: p.read_bytes() for p in tmp_path.rglob("*") if p.is_file()}  # nothing written


def test_rotation_in_t_bs_must_be_a_rotation(tmp_path):
    T = T_B_IMU.copy()
    T[:3, :3] *= 1.01
    write_sequence(tmp_path, T_imu=T)
    with pytest.raises(DataError, match=r"imu0/sensor\.yaml, line 10, field 'T_BS\.data'.*a rotation"):
        load_euroc(tmp_path)


@pytest.mark.parametrize("file", [IMU, GT])
def test_empty_and_header_only(tmp_path, file):
    write_sequence(tmp_path)
    path = tmp_path / file
    header = path.read_text().splitlines()[0]
    for text in ("", header + "\n", header + "\n" + path.read_text().splitlines()[1] + "\n"):
        path.write_text(text)
        with pytest.raises(DataError) as info:
            load_euroc(tmp_path)
        assert str(path) in str(info.value) and "line" in str(info.value)


def test_no_overlap_and_no_folder(tmp_path):
    write_sequence(tmp_path, n_imu=201, gt_offset=250 * IMU_STEP)  # the IMU ends before the ground truth starts
    with pytest.raises(DataError, match=r"imu0/data\.csv.*0 IMU samples within the ground truth's span"):
        load_euroc(tmp_path)
    with pytest.raises(DataError, match="mav0"):
        load_euroc(tmp_path / "mav0" / "imu0" / "nothing")


def test_a_ground_truth_without_samples_inside_the_imu_span_is_an_error(tmp_path):
    """Its first and last rows span the IMU, so IMU samples remain, but only the last row lies in
    the IMU's span: a reference of one sample (and no measurements from it) would follow silently."""
    write_sequence(tmp_path, n_imu=401, n_gt=390)
    path = tmp_path / GT
    lines = path.read_text().splitlines()
    path.write_text("\n".join([lines[0], lines[1], lines[-1]]) + "\n")
    with pytest.raises(DataError, match=r"state_groundtruth_estimate0/data\.csv.*1 ground-truth samples within the "
                                        r"IMU samples' span"):
        load_euroc(tmp_path)


def test_a_short_ground_truth_keeps_the_imu_and_says_how_much_it_covers(tmp_path):
    """A ground truth cut to its first two rows (on the IMU's grid): every IMU sample from its first
    stamp on is kept (not the two inside its 5 ms), and the warning says the truth covers 0.005 s
    of the 2 s and that the rest is estimated, not scored."""
    imu_ns, _, _ = write_sequence(tmp_path, gt_offset=10 * IMU_STEP)
    path = tmp_path / GT
    path.write_text("\n".join(path.read_text().splitlines()[:3]) + "\n")
    with pytest.warns(UserWarning, match=r"data\.csv: the ground truth covers 0\.005 s of the 2 s of .*imu0/data\.csv: "
                                         r"the 10 IMU samples before its first stamp \(0\.05 s\) are left out .*; the "
                                         r"389 after its last stamp \(1\.945 s\) are kept: estimated, not scored$"):
        d = load_euroc(tmp_path)
    assert np.array_equal(d.imu.t_ns, imu_ns[10:]) and len(d.truth) == 2


def test_a_ground_truth_gap_is_reported_and_never_differenced_across(tmp_path):
    """The lever arm's velocity needs the body rate of the ground truth: differenced across a
    hole of a second it would be off; it is taken one-sided at the hole, and the hole is named."""
    write_sequence(tmp_path, n_imu=801, n_gt=780)
    path = tmp_path / GT
    lines = path.read_text().splitlines()  # line 1 the header, line k + 2 sample k
    path.write_text("\n".join(lines[:302] + lines[502:]) + "\n")  # samples 300 .. 499 removed: 1.005 s
    with pytest.warns(UserWarning, match=r"data\.csv: 1 gap\(s\) in the ground truth .* the longest, 1\.005 s, ends "
                                         r"at line 303\. Rates are not differenced across a gap$"):
        d = load_euroc(tmp_path)
    t_abs = (d.truth.t * 1e9 + (d.imu.t_ns[0] - NS0)) * 1e-9
    C, _, v_world = imu_truth(t_abs)
    error = np.abs(d.truth.states.v - np.einsum("nji,nj->ni", C, v_world)).max(axis=1)
    assert error.max() < 1e-3, error.max()  # one-sided at the gap: first order in 5 ms (across it: ~0.1 m/s)


def test_an_initial_state_inside_a_ground_truth_gap_is_reported(tmp_path):
    write_sequence(tmp_path, n_imu=401, n_gt=390)
    path = tmp_path / GT
    lines = path.read_text().splitlines()
    path.write_text("\n".join(lines[:2] + lines[60:]) + "\n")  # a hole from the first sample to the 59th
    with pytest.warns(UserWarning, match=r"the initial state \(first IMU stamp\) lies in the gap that ends at line 3 "):
        load_euroc(tmp_path)


_TOKENS = st.sampled_from(
    ["0", str(NS0), str(NS0 + 7), "-1", "0.5", "1e400", "nan", "inf", "x", "", " ", "#", "[", "]", ":", "T_BS:",
     "  data:", "cols: 4", "1_0", "9" * 25, "\u00e9", "1,2,3", "%"]
)
_LINE = st.lists(_TOKENS, min_size=0, max_size=10).flatmap(
    lambda toks: st.sampled_from([",", " ", ", "]).map(lambda sep: sep.join(toks)))


@settings(max_examples=100, deadline=None, derandomize=True, suppress_health_check=[HealthCheck.too_slow])
@given(file=st.sampled_from([IMU, GT, IMU_YAML, GT_YAML]), line=_LINE, where=st.integers(0, 14),
       replace=st.booleans())
def test_fuzz_only_data_errors_naming_the_file(file, line, where, replace):
    with tempfile.TemporaryDirectory() as tmp:
        root = Path(tmp)
        write_sequence(root, n_imu=241, n_gt=20)  # 1.2 s: a line cut from the IMU leaves a recording
        path = root / file
        lines = path.read_text().splitlines()
        where = min(where, len(lines))
        lines[where: where + int(replace)] = [line]
        path.write_text("\n".join(lines) + "\n")
        try:
            d = load_euroc(root)
        except DataError as error:
            assert str(path) in str(error), str(error)
        else:
            assert np.all(np.diff(d.imu.t_ns) > 0)
