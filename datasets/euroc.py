"""EuRoC MAV / ASL dataset folders: IMU samples, ground truth and (on request) synthetic pose or
position measurements drawn from the ground truth.

Layout read (``folder`` is the sequence folder holding ``mav0/`` or ``mav0/`` itself)::

    mav0/imu0/data.csv                        IMU samples
    mav0/imu0/sensor.yaml                     T_BS of the IMU, noise densities
    mav0/state_groundtruth_estimate0/data.csv ground truth
    mav0/state_groundtruth_estimate0/sensor.yaml   T_BS of the ground truth's frame

CSV files: comma separated, one header line (optional) starting with ``#``, column names with or
without a unit in brackets and with or without spaces after the commas (``#timestamp [ns],w_RS_S_x
[rad s^-1],...``, ``#timestamp, p_RS_R_x [m], ...``, ``#timestamp,...``): columns are found by
name, so their order does not matter; without a header the standard EuRoC order is assumed.
Time stamps are integer nanoseconds (>= 0).

Frames (ASL convention: ``T_BS`` in a sensor's ``sensor.yaml`` maps that sensor's frame S into the
rig's body frame B, ``p_B = T_BS p_S``; ``p_RS_R`` is the position of S in the reference frame R,
``q_RS`` (w, x, y, z, Hamilton) the rotation from S to R; ``v_RS_R`` the velocity of S's origin
in R; ``b_w_RS_S``, ``b_a_RS_S`` the gyro and accelerometer biases in S):

* the project's world frame I is the ground truth's reference frame R (z up, gravity
  ``(0, 0, -9.81)`` by default);
* the project's body frame B is the IMU's sensor frame ``S_imu``: IMU samples are used as they
  are (``w_RS_S`` -> ``gyro``, ``a_RS_S`` -> ``acc``). NOTE: this is not EuRoC's rig frame B;
* the ground truth describes the frame ``S_gt`` of ``state_groundtruth_estimate0`` (identity
  ``T_BS`` in the real dataset, so there it IS the IMU). With ``X = T_{B S_gt}^-1 T_{B S_imu} =
  (R_x, p_x)`` (the IMU in ``S_gt``), the IMU's state is ``C = C_gt R_x``, ``r = r_gt + C_gt
  p_x``, world velocity ``v_gt + (C_gt w_gt) x (C_gt p_x)`` with ``w_gt`` the body rate of the
  ground truth by central differences of its attitudes (one-sided at the ends), then rotated into
  the body frame, ``B_v = C^T I_v`` (the file's velocity is in the WORLD frame; ``ImuState.v``
  is in the BODY frame), and biases ``R_x^T b`` (vectors re-expressed in ``S_imu``).

Times: ``ImuSamples.t_ns`` keeps the integer stamps exactly; ``ImuSamples.t`` and all other
times (ground truth, measurements) are float seconds relative to the FIRST IMU STAMP OF THE
DATASET, ``(t_ns - t_ns[0]) * 1e-9`` computed from integers, so they keep sub-microsecond
precision (seconds since 1970 in a float64 only resolve ~0.2 us). The dataset starts at the first
IMU sample at or after the first ground-truth stamp (the initial state is the truth's) and keeps
every IMU sample after it, also those after the ground truth's end (estimated on, and scored
only where the truth is: :func:`smoother.evaluation.scoring.against_truth`); a warning says how many IMU
samples lie outside the truth's span on either side and how much of the IMU's span the truth
covers. The ground truth is kept over the IMU samples' span (at least two IMU samples and two of
its samples must lie in the other's span). The initial state is the ground truth at the first
IMU stamp, interpolated (:meth:`datasets.types.Trajectory.interpolate`: linearly for vectors,
along the geodesic for the attitude) between the two ground-truth samples around it. A gap in the
ground truth (a step longer than :data:`GROUNDTRUTH_GAP_FACTOR` typical steps) within the IMU's span
is reported in a warning naming its line; the body rates are never differenced across one (one-sided
next to it).

Noise: the densities of ``imu0/sensor.yaml`` (``accelerometer_noise_density``,
``gyroscope_noise_density``, ``accelerometer_random_walk``, ``gyroscope_random_walk``; EuRoC
gives them as continuous-time densities) where present, else :class:`ImuNoise`'s defaults, or
``noise`` if given. Initial covariance: diagonal with sigmas :data:`INITIAL_SIGMAS` (position,
velocity, attitude, accelerometer bias, gyro bias; attitude in the world frame, left
perturbation, as everywhere in the project).

``sensor.yaml`` is read with PyYAML (:mod:`datasets.yamlfile`: OpenCV's ``%YAML:1.0`` first line is
skipped, duplicate keys are an error naming both lines); its ``T_BS`` block is ``cols: 4``,
``rows: 4``, ``data: [16 numbers]`` (row major, block or flow style). ``T_BS`` must be a rigid
transform: last row ``0 0 0 1`` and a rotation part with ``|R R^T - I| <= 1e-5`` and det 1 within
as much (it is then projected onto SO(3)).
"""
from __future__ import annotations

import re
import warnings
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from datasets.errors import (
    DataError,
    check_increasing,
    check_unit_quaternions,
    integer,
    number,
    numbered_lines,
    read_lines,
    require_imu_recording,
    table_fast,
)
from datasets.kalibr import NOISE_KEYS, density_in_range, rigid_problem
from datasets.types import Dataset, ImuSamples, Trajectory
from datasets.yamlfile import YamlDocument, read_yaml
from factors import quaternion, so3
from factors.imu import DEFAULT_GRAVITY, ImuNoise, ImuState

IMU_COLUMNS = ["timestamp", "w_RS_S_x", "w_RS_S_y", "w_RS_S_z", "a_RS_S_x", "a_RS_S_y", "a_RS_S_z"]
GROUNDTRUTH_COLUMNS = [
    "timestamp", "p_RS_R_x", "p_RS_R_y", "p_RS_R_z", "q_RS_w", "q_RS_x", "q_RS_y", "q_RS_z",
    "v_RS_R_x", "v_RS_R_y", "v_RS_R_z", "b_w_RS_S_x", "b_w_RS_S_y", "b_w_RS_S_z",
    "b_a_RS_S_x", "b_a_RS_S_y", "b_a_RS_S_z",
]
#: Accepted deviation of a ground-truth quaternion's norm from 1 (then normalised).
QUATERNION_TOLERANCE = 1e-3
#: A ground-truth step longer than this many typical steps is a gap (warned about, never bridged).
GROUNDTRUTH_GAP_FACTOR = 5.0
#: Accepted deviation of T_BS's rotation part from orthonormality.
ROTATION_TOLERANCE = 1e-5
#: Initial-state sigmas: position [m], velocity [m/s], attitude [rad], acc bias [m/s^2], gyro bias [rad/s].
INITIAL_SIGMAS = (0.01, 0.01, 0.01, 0.05, 0.002)


# ------------------------------------------------------------------------------------------
# sensor.yaml


@dataclass(frozen=True)
class SensorYaml:
    """What is read from a ``sensor.yaml``: ``T_BS`` (4x4) and the whole file, for its other keys."""

    T_BS: np.ndarray
    document: YamlDocument


def read_sensor_yaml(path) -> SensorYaml:
    """Read an ASL ``sensor.yaml``: its ``T_BS`` block (``cols: 4``, ``rows: 4``, ``data:`` 16
    numbers, row major) and the rest of the file."""
    doc = read_yaml(path)
    if not isinstance(doc.data, dict) or "T_BS" not in doc.data:
        raise DataError(doc.path, max(doc.n_lines, 1), "T_BS", "no T_BS block", "a 'T_BS:' block with cols, rows, data")
    if not isinstance(doc.data["T_BS"], dict):
        raise doc.error(("T_BS",), doc.data["T_BS"], "a block of cols, rows, data")
    for key in ("cols", "rows"):
        value = doc.get(("T_BS", key))
        if isinstance(value, bool) or value != 4:
            raise doc.error(("T_BS", key), value, "4")
    data = doc.get(("T_BS", "data"))
    if not isinstance(data, list) or len(data) != 16:
        found = f"{len(data)} numbers" if isinstance(data, list) else repr(data)
        last = doc.line(("T_BS", "data", len(data) - 1)) if isinstance(data, list) and data else None
        raise doc.error(("T_BS", "data"), found, "16 numbers (4 x 4, row major)", last)
    T = np.array([doc.number(("T_BS", "data", i)) for i in range(16)]).reshape(4, 4)
    problem = rigid_problem(T, ROTATION_TOLERANCE)
    if problem is not None:
        where = ("T_BS", "data", 12) if problem.startswith("last row") else ("T_BS", "data")
        raise doc.error(where, problem, f"a rotation (|R R^T - I| <= {ROTATION_TOLERANCE:g}, det 1) "
                                        "and a last row 0, 0, 0, 1")
    T[:3, :3] = so3.project(T[:3, :3])
    return SensorYaml(T, doc)


# ------------------------------------------------------------------------------------------
# CSV files


def _normalise(name: str) -> str:
    return re.sub(r"\[[^\]]*\]", "", name).replace(" ", "").replace("\t", "").lower()


def _read_asl_csv(path, columns: list[str], duplicates: bool = False) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Read an ASL CSV file; returns (int64 stamps, float values of the other columns in the
    order of ``columns[1:]``, 1-based line numbers). With ``duplicates`` a stamp may equal the one
    before."""
    path = Path(path)
    lines = read_lines(path)
    first = next((i for i, text in enumerate(lines) if text.strip()), None)
    if first is None:
        raise DataError(path, max(len(lines), 1), None, "an empty file",
                        f"a header '#{','.join(columns)}' and data lines")
    header_text = lines[first].strip()
    first_token = header_text.split(",")[0].strip()
    has_header = header_text.startswith("#") or not re.fullmatch(r"[+-]?\d+", first_token)
    if has_header:
        names = [_normalise(tok) for tok in header_text.lstrip("#").split(",")]
        if names and names[-1] == "" and len(names) > 1:
            names = names[:-1]
        if not names or names[0] not in ("timestamp", "time", "t"):
            raise DataError(path, first + 1, "header", header_text, "a first column named timestamp")
        order = []
        for col in columns[1:]:
            key = col.lower()
            if key not in names:
                raise DataError(path, first + 1, col, "a header without this column", f"a column named {col}")
            if names.count(key) > 1:
                raise DataError(path, first + 1, col, "this column twice", "each column once")
            order.append(names.index(key))
        width = len(names)
        name_of = {0: columns[0]}
        for col, j in zip(columns[1:], order):
            name_of[j] = col
        start = first + 1
    else:
        order = list(range(1, len(columns)))
        width = len(columns)
        name_of = dict(enumerate(columns))
        start = first
    body, line_numbers = numbered_lines(lines, "#", start)
    fast = table_fast(body, width, ",", stamps=True)
    del body
    if fast is not None and len(fast[1]) >= 2:  # every data line a plain row: NumPy's C parser
        values, stamps = fast
        check_increasing(path, stamps, line_numbers, columns[0] + " [ns]", duplicates)
        return stamps, values[:, order], line_numbers
    stamps, values, line_numbers = [], [], []
    for index in range(start, len(lines)):
        text = lines[index].strip()
        if not text or text.startswith("#"):
            continue
        line = index + 1
        tokens = text.split(",")
        if len(tokens) == width + 1 and tokens[-1].strip() == "":
            tokens = tokens[:-1]
        if len(tokens) != width:
            missing = name_of.get(len(tokens), None) if len(tokens) < width else None
            raise DataError(path, line, missing, f"{len(tokens)} fields", f"{width} comma-separated fields")
        stamp = integer(tokens[0], path, line, columns[0] + " [ns]")
        if stamp < 0:
            raise DataError(path, line, columns[0] + " [ns]", tokens[0], "a time stamp >= 0 (nanoseconds)")
        stamps.append(stamp)
        values.append([number(tokens[j], path, line, name_of.get(j, f"column {j + 1}")) for j in order])
        line_numbers.append(line)
    if len(stamps) < 2:
        found = "no data lines" if not stamps else "1 data line"
        raise DataError(path, len(lines), None, found, "at least 2 data lines")
    stamps, line_numbers = np.array(stamps, dtype=np.int64), np.array(line_numbers)
    check_increasing(path, stamps, line_numbers, columns[0] + " [ns]", duplicates)
    return stamps, np.array(values, dtype=float), line_numbers


def read_imu_csv(path) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``imu0/data.csv``: (stamps [ns] int64, acc (N, 3), gyro (N, 3)) in the IMU frame, a
    recording as long as :func:`datasets.errors.require_imu_recording` asks."""
    stamps, values, _ = _read_asl_csv(path, IMU_COLUMNS)
    require_imu_recording(path, stamps)
    return stamps, values[:, 3:6], values[:, 0:3]


@dataclass(frozen=True)
class GroundTruthCsv:
    """The columns of ``state_groundtruth_estimate0/data.csv`` as read (frame ``S_gt``)."""

    t_ns: np.ndarray
    p: np.ndarray
    q: np.ndarray  # w, x, y, z (normalised)
    v_world: np.ndarray
    b_w: np.ndarray
    b_a: np.ndarray
    lines: np.ndarray  # 1-based line of each row, for messages


def read_groundtruth_csv(path) -> GroundTruthCsv:
    stamps, values, lines = _read_asl_csv(path, GROUNDTRUTH_COLUMNS)
    q = check_unit_quaternions(path, values[:, 3:7], lines, "q_RS_w q_RS_x q_RS_y q_RS_z", QUATERNION_TOLERANCE)
    return GroundTruthCsv(stamps, values[:, 0:3], q, values[:, 7:10], values[:, 10:13], values[:, 13:16], lines)


def read_pose_csv(path, duplicates: bool = False):
    """The poses of an ASL CSV with at least the columns ``timestamp, p_RS_R_xyz, q_RS_wxyz`` (a
    ground truth ``state_groundtruth_estimate0/data.csv``, or an estimate written that way), as
    evo's ``euroc`` mode reads them: ``(t, r, C, lines)`` with ``t`` the nanosecond stamps divided
    by 1e9 (seconds since the stamps' epoch), the frame ``S`` the file describes. With
    ``duplicates`` a stamp may equal the one before."""
    stamps, values, lines = _read_asl_csv(path, GROUNDTRUTH_COLUMNS[:8], duplicates)
    q = check_unit_quaternions(path, values[:, 3:7], lines, "q_RS_w q_RS_x q_RS_y q_RS_z", QUATERNION_TOLERANCE)
    return stamps / 1e9, values[:, 0:3], quaternion.to_matrix(q), lines


# ------------------------------------------------------------------------------------------
# the dataset


def _mav0(folder) -> Path:
    folder = Path(folder)
    if (folder / "mav0").is_dir():
        return folder / "mav0"
    if (folder / "imu0").is_dir():
        return folder
    raise DataError(folder, None, None, "a folder without mav0/ or imu0/", "an EuRoC/ASL sequence folder (with mav0/)")


def _body_rates(t: np.ndarray, C: np.ndarray, gap: np.ndarray) -> np.ndarray:
    """Body angular rate of the attitudes ``C`` at times ``t`` by central differences,
    ``w_k = log(C_a^T C_b) / (t_b - t_a)``, one-sided at the ends and next to a gap (``gap[k]``:
    the step from sample ``k`` to ``k + 1`` is one): never across a gap. A sample with gaps on
    both sides has no neighbour to difference with; its rate is zero."""
    n = len(t)
    k = np.arange(n)
    a = np.where((k > 0) & ~np.r_[True, gap], k - 1, k)
    b = np.where((k < n - 1) & ~np.r_[gap, True], k + 1, k)
    rel = np.swapaxes(C[a], 1, 2) @ C[b]
    span = t[b] - t[a]
    return so3.log(rel) / np.where(span > 0, span, 1.0)[:, None]


def _groundtruth_gaps(path, t_ns: np.ndarray, lines: np.ndarray, first_ns: int, last_ns: int) -> np.ndarray:
    """Which steps of the ground truth are gaps (longer than :data:`GROUNDTRUTH_GAP_FACTOR` typical
    steps). Those that overlap the IMU's span ``[first_ns, last_ns]`` are reported in a warning
    naming the file and the line after the longest: the body rates (hence the lever arm's
    velocity) are never differenced across a gap, but the reference has holes there, and an
    initial state inside one is interpolated across it."""
    step = np.diff(t_ns)
    gap = step > GROUNDTRUTH_GAP_FACTOR * np.median(step)
    reported = gap & (t_ns[1:] > first_ns) & (t_ns[:-1] < last_ns)
    if reported.any():
        longest = int(np.argmax(np.where(reported, step, 0)))
        message = (f"{path}: {int(reported.sum())} gap(s) in the ground truth longer than {GROUNDTRUTH_GAP_FACTOR:g} x "
                   f"its typical step of {np.median(step) * 1e-9:.4g} s; the longest, {step[longest] * 1e-9:.4g} s, "
                   f"ends at line {int(lines[longest + 1])}. Rates are not differenced across a gap")
        k = int(np.searchsorted(t_ns, first_ns, side="right")) - 1
        if k < len(gap) and gap[k] and t_ns[k] < first_ns:
            message += (f"; the initial state (first IMU stamp) lies in the gap that ends at line {int(lines[k + 1])} "
                        f"and is interpolated across it")
        warnings.warn(message, stacklevel=3)
    return gap


def _report_uncovered(imu_csv, gt_csv, imu_ns: np.ndarray, gt_ns: np.ndarray) -> None:
    """Warn of the IMU samples outside the ground truth's span: those before its first stamp are
    left out (the initial state is the truth's), those after its last are kept (estimated on,
    scored nowhere); the warning says how many, and how much of the IMU's span the truth covers."""
    before, after = imu_ns < gt_ns[0], imu_ns > gt_ns[-1]
    if not before.any() and not after.any():
        return
    seconds = lambda a, b: (int(b) - int(a)) * 1e-9  # noqa: E731 (from integers: exact to the ns)
    covered = seconds(max(gt_ns[0], imu_ns[0]), min(gt_ns[-1], imu_ns[-1]))
    parts = []
    if before.any():
        parts.append(f"the {int(before.sum())} IMU samples before its first stamp "
                     f"({seconds(imu_ns[0], gt_ns[0]):.4g} s) are left out (the initial state is the truth's)")
    if after.any():
        parts.append(f"the {int(after.sum())} after its last stamp ({seconds(gt_ns[-1], imu_ns[-1]):.4g} s) are "
                     f"kept: estimated, not scored")
    warnings.warn(f"{gt_csv}: the ground truth covers {covered:.4g} s of the {seconds(imu_ns[0], imu_ns[-1]):.4g} s "
                  f"of {imu_csv}: " + "; ".join(parts), stacklevel=3)


def _noise_from_yaml(yaml: SensorYaml) -> ImuNoise:
    doc = yaml.document
    return ImuNoise(**{field: density_in_range(doc, (key,), field) for key, field in NOISE_KEYS.items()
                       if key in doc.data})


def load_euroc(folder, *, noise: ImuNoise | None = None, gravity=DEFAULT_GRAVITY) -> Dataset:
    """An EuRoC/ASL sequence as a :class:`Dataset` named ``"euroc"`` (see the module docstring).

    It has no aiding sensor of its own: sensors drawn from its ground truth are added with
    :func:`datasets.simulated_sensors.truth_sensors` (``smoother run --pose-from-truth``).
    """
    mav0 = _mav0(folder)
    imu_yaml_path = mav0 / "imu0" / "sensor.yaml"
    gt_yaml_path = mav0 / "state_groundtruth_estimate0" / "sensor.yaml"
    imu_csv = mav0 / "imu0" / "data.csv"
    gt_csv = mav0 / "state_groundtruth_estimate0" / "data.csv"
    imu_yaml = read_sensor_yaml(imu_yaml_path)
    gt_yaml = read_sensor_yaml(gt_yaml_path)
    if noise is None:
        noise = _noise_from_yaml(imu_yaml)
    imu_ns, acc, gyro = read_imu_csv(imu_csv)
    gt = read_groundtruth_csv(gt_csv)

    # The dataset starts at the first IMU sample the ground truth can initialise and keeps every
    # IMU sample after it; what lies outside the truth's span is said, never dropped unsaid.
    inside = (imu_ns >= gt.t_ns[0]) & (imu_ns <= gt.t_ns[-1])
    if np.count_nonzero(inside) < 2:
        raise DataError(
            imu_csv, None, "timestamp", f"{np.count_nonzero(inside)} IMU samples within the ground truth's span "
            f"[{int(gt.t_ns[0])}, {int(gt.t_ns[-1])}] ns of {gt_csv}", "at least 2",
        )
    _report_uncovered(imu_csv, gt_csv, imu_ns, gt.t_ns)
    keep = imu_ns >= gt.t_ns[0]
    imu_ns, acc, gyro = imu_ns[keep], acc[keep], gyro[keep]
    t0_ns = int(imu_ns[0])
    gt_keep = (gt.t_ns >= t0_ns) & (gt.t_ns <= imu_ns[-1])
    if np.count_nonzero(gt_keep) < 2:  # the truth would be empty: no reference, no measurements from it
        raise DataError(
            gt_csv, None, "timestamp", f"{np.count_nonzero(gt_keep)} ground-truth samples within the IMU samples' "
            f"span [{t0_ns}, {int(imu_ns[-1])}] ns of {imu_csv}", "at least 2",
        )
    gap = _groundtruth_gaps(gt_csv, gt.t_ns, gt.lines, t0_ns, int(imu_ns[-1]))

    # Ground truth of S_gt -> the IMU frame.
    X = np.linalg.inv(gt_yaml.T_BS) @ imu_yaml.T_BS
    R_x, p_x = X[:3, :3], X[:3, 3]
    C_gt = quaternion.to_matrix(gt.q)
    t_gt = (gt.t_ns - gt.t_ns[0]) * 1e-9
    w_gt = _body_rates(t_gt, C_gt, gap)
    C = C_gt @ R_x
    lever = C_gt @ p_x
    r = gt.p + lever
    v_world = gt.v_world + np.cross(np.einsum("nij,nj->ni", C_gt, w_gt), lever)
    v_body = np.einsum("nji,nj->ni", C, v_world)
    states = ImuState(r=r, v=v_body, C=C, b_f=gt.b_a @ R_x, b_w=gt.b_w @ R_x)

    k = min(int(np.searchsorted(gt.t_ns, t0_ns, side="right")) - 1, len(gt.t_ns) - 2)  # the samples around t0
    around = Trajectory((gt.t_ns[k:k + 2] - t0_ns) * 1e-9, states[k:k + 2])
    initial = around.interpolate([0.0])[0][0]
    truth_t = (gt.t_ns[gt_keep] - t0_ns) * 1e-9
    if np.any(np.diff(truth_t) <= 0):
        raise DataError(gt_csv, None, "timestamp [ns]", "stamps that coincide in float64 seconds",
                        "stamps that stay distinct relative to the first IMU stamp")
    truth = Trajectory(truth_t, states[gt_keep])
    t = (imu_ns - t0_ns) * 1e-9
    if np.any(np.diff(t) <= 0):  # stamps 1 ns apart more than ~100 days after the first
        raise DataError(imu_csv, None, "timestamp [ns]", "stamps that coincide in float64 seconds",
                        "stamps that stay distinct relative to the first IMU stamp")
    imu = ImuSamples(t, acc, gyro, t_ns=imu_ns)

    sigmas = np.repeat(INITIAL_SIGMAS, 3)
    return Dataset(
        name="euroc", imu=imu, noise=noise, initial=initial, initial_cov=np.diag(sigmas**2),
        gravity=np.asarray(gravity, dtype=float), truth=truth, time_origin_ns=t0_ns,
    )
