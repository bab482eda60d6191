"""EuRoC/ASL sequence folders written by the tests (no EuRoC data ships anywhere): an IMU turning
and accelerating at known rates, its ground truth in another body frame starting off the IMU's
grid, and their ``sensor.yaml`` files with extrinsics that are not the identity.

Import as ``import eurocfiles`` (``tests/conftest.py`` puts this directory on ``sys.path``)."""
from __future__ import annotations

from pathlib import Path

import numpy as np

from datasets.euroc import GROUNDTRUTH_COLUMNS, IMU_COLUMNS
from factors import quaternion, so3

#: The data files of a sequence, relative to its root.
IMU = "mav0/imu0/data.csv"
GT = "mav0/state_groundtruth_estimate0/data.csv"

NS0 = 1403636579758555392  # a real EuRoC first stamp: far beyond float64's integer precision
IMU_STEP = 5_000_000
GT_OFFSET = 51_300_000  # the ground truth starts 51.3 ms after the IMU, off the IMU's grid
OMEGA = np.array([0.3, -0.2, 0.5])  # world-frame angular rate [rad/s]
C0 = so3.exp([0.4, -1.0, 2.0])
R0, U, A = np.array([4.0, -1.5, 0.8]), np.array([0.5, -0.3, 0.2]), np.array([0.1, 0.2, -0.05])
B_GYRO_GT, B_ACC_GT = np.array([-0.003, 0.021, 0.078]), np.array([-0.025, 0.137, 0.076])


def _transform(phi, p):
    T = np.eye(4)
    T[:3, :3] = so3.exp(phi)
    T[:3, 3] = p
    return T


T_B_IMU = _transform([0.1, -0.2, 0.3], [0.05, -0.02, 0.1])
T_B_GT = _transform([-0.4, 0.2, 1.1], [-0.1, 0.2, 0.03])
X = np.linalg.inv(T_B_GT) @ T_B_IMU  # the IMU in the ground truth's frame
R_X, P_X = X[:3, :3], X[:3, 3]


def imu_truth(t):
    """The IMU's true state at times ``t`` [s after NS0]: C, r, world velocity."""
    t = np.asarray(t, dtype=float)
    C = so3.exp(t[:, None] * OMEGA) @ C0
    r = R0 + t[:, None] * U + 0.5 * t[:, None] ** 2 * A
    v = U + t[:, None] * A
    return C, r, v


def sensor_yaml(T, extra="", flow=False):
    rows = [", ".join(repr(float(x)) for x in T[i]) for i in range(4)]
    if flow:
        block = "T_BS: {cols: 4, rows: 4, data: [" + ", ".join(rows) + "]}\n"
    else:
        block = ("T_BS:\n  cols: 4\n  rows: 4\n  data: [" + ",\n         ".join(rows) + "]\n")
    return ("%YAML:1.0\n# General sensor definitions.\nsensor_type: imu\ncomment: synthetic, for tests\n\n"
            "# Sensor extrinsics wrt. the body-frame.\n" + block + "rate_hz: 200\n\n" + extra)


NOISE_YAML = (
    "# inertial sensor noise model parameters (static)\n"
    "gyroscope_noise_density: 1.6968e-04     # [ rad / s / sqrt(Hz) ]   ( gyro \"white noise\" )\n"
    "gyroscope_random_walk: 1.9393e-05       # [ rad / s^2 / sqrt(Hz) ] ( gyro bias diffusion )\n"
    "accelerometer_noise_density: 2.0000e-3  # [ m / s^2 / sqrt(Hz) ]  ( accel \"white noise\" )\n"
    "accelerometer_random_walk: 3.0000e-3    # [ m / s^3 / sqrt(Hz) ].  ( accel bias diffusion )\n"
)

UNITS = {"timestamp": "ns", "w": "rad s^-1", "a": "m s^-2", "p": "m", "q": "", "v": "m s^-1", "b_w": "rad s^-1",
         "b_a": "m s^-2"}


def _header(columns, style):
    if style == "none":
        return None
    names = []
    for c in columns:
        unit = UNITS["timestamp"] if c == "timestamp" else UNITS[c.split("_R")[0] if c.startswith("b_") else c[0]]
        names.append(f"{c} [{unit}]" if style in ("units", "units_spaces") else c)
    sep = ", " if style in ("spaces", "units_spaces") else ","
    return "#" + sep.join(names)


def _csv(path: Path, columns, stamps, values, style="units", order=None):
    order = list(range(len(columns))) if order is None else order
    lines = []
    header = _header([columns[j] for j in order], style)
    if header is not None:
        lines.append(header)
    for stamp, row in zip(stamps, values):
        fields = [str(int(stamp))] + [repr(float(x)) for x in row]
        lines.append(",".join(fields[j] for j in order))
    path.write_text("\r\n".join(lines) + "\r\n" if style == "crlf" else "\n".join(lines) + "\n")


def write_sequence(root: Path, n_imu=401, n_gt=370, style="units", gt_style=None, order=None, flow=False,
                   T_imu=T_B_IMU, T_gt=T_B_GT, seed=0, gt_offset=GT_OFFSET):
    """An ASL folder ``root/mav0`` with a moving IMU, its ground truth starting ``gt_offset`` ns
    after it (on the IMU's grid when a multiple of IMU_STEP, as in EuRoC); returns the IMU stamps
    and readings."""
    rng = np.random.default_rng(seed)
    mav0 = root / "mav0"
    (mav0 / "imu0").mkdir(parents=True, exist_ok=True)
    (mav0 / "state_groundtruth_estimate0").mkdir(parents=True, exist_ok=True)
    imu_ns = NS0 + IMU_STEP * np.arange(n_imu, dtype=np.int64)
    readings = rng.normal(size=(n_imu, 6))  # gyro (w_RS_S) then acc (a_RS_S)
    readings[:, 5] += 9.81  # a plausible specific force (the loader warns about implausible units)
    _csv(mav0 / "imu0" / "data.csv", IMU_COLUMNS, imu_ns, readings, style,
         order=None if order is None else [0] + [1 + j for j in order[:6]])
    gt_ns = NS0 + gt_offset + IMU_STEP * np.arange(n_gt, dtype=np.int64)
    C, r, v = imu_truth((gt_ns - NS0) * 1e-9)
    C_gt = C @ R_X.T
    lever = C_gt @ P_X
    r_gt = r - lever
    v_gt = v - np.cross(OMEGA, lever)
    q_gt = quaternion.from_matrix(C_gt)
    values = np.hstack([r_gt, q_gt, v_gt, np.tile(B_GYRO_GT, (n_gt, 1)), np.tile(B_ACC_GT, (n_gt, 1))])
    _csv(mav0 / "state_groundtruth_estimate0" / "data.csv", GROUNDTRUTH_COLUMNS, gt_ns, values,
         gt_style or ("spaces" if style == "units" else style))
    (mav0 / "imu0" / "sensor.yaml").write_text(sensor_yaml(T_imu, NOISE_YAML, flow))
    (mav0 / "state_groundtruth_estimate0" / "sensor.yaml").write_text(sensor_yaml(T_gt, flow=flow))
    return imu_ns, readings, gt_ns
