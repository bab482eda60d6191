"""KITTI IMU + GPS as shipped in GTSAM's example data (``IMUKittiExampleGPS``).

Files (found with ``gtsam.findExampleDataFile`` unless explicit paths are given):

``KittiEquivBiasedImu.txt``
    header ``Time dt accelX accelY accelZ omegaX omegaY omegaZ`` then one sample per line,
    space separated: time [s], ``dt`` = time since the previous sample [s], specific force
    [m/s^2] and angular rate [rad/s] in the IMU frame (x forward, y left, z up: at rest the
    accelerometer reads about +9.8 on z). The first data line's ``dt`` is meaningless (it
    repeats the time) and is ignored; every other ``dt`` must equal the difference of the time
    stamps within :data:`DT_TOLERANCE` (it then carries no extra information). The project's
    convention (``ImuSamples``) holds sample k over ``[t_k, t_k+1]``; GTSAM's example
    integrates sample k over its own ``dt``, the interval ending at ``t_k``: the two differ by a
    shift of one sample period (10 ms) of the IMU signal.
``KittiEquivBiasedImu_metadata.txt``
    a header of 12 names and one line of 12 numbers: ``BodyPtx BodyPty BodyPtz BodyPrx BodyPry
    BodyPrz`` (the IMU pose in the body frame; only the identity is supported, as in GTSAM's
    example), ``AccelerometerSigma GyroscopeSigma IntegrationSigma AccelerometerBiasSigma
    GyroscopeBiasSigma`` and ``AverageDeltaT`` (checked against the IMU file within 10%).
``KittiGps_converted.txt``
    header ``Time,X,Y,Z`` then comma-separated GPS fixes: time [s] and position [m] in a local
    Cartesian frame with z up (altitude), right-handed. GTSAM's example uses these positions
    directly as its navigation frame with gravity along -z; the IMU's integrated yaw rate
    matches the turning of the GPS course (tested), so the frame is consistent with the IMU's.
    In the shipped file every fix time is also an IMU sample time.

Noise (:class:`factors.imu.ImuNoise`), the metadata sigmas taken as the continuous-time
densities GTSAM uses them as (``PreintegrationParams`` covariances are continuous-time):
``acc = AccelerometerSigma`` [m/s^2/sqrt(Hz)], ``gyro = GyroscopeSigma`` [rad/s/sqrt(Hz)],
``velocity = IntegrationSigma`` (GTSAM's integration covariance adds ``sigma^2 dt`` to the
position, exactly what the primer's velocity noise ``n_v`` does in ``r' = r + dt C (v + n_v)``).
The two bias sigmas are read as the standard deviation of the bias random walk's step PER IMU
SAMPLE -- the way GTSAM's example uses them (its bias between factor over ``n`` samples has sigma
``sqrt(n) * sigma``) -- so the densities are ``acc_bias = AccelerometerBiasSigma / sqrt(dt)`` and
``gyro_bias = GyroscopeBiasSigma / sqrt(dt)`` with ``dt = AverageDeltaT`` (10x the raw values at
100 Hz). Reading them as densities directly makes the bias far too stiff for this data: the
held-out GPS error of the batch smoother is 2.2 m that way, 1.43 m this way, the same as GTSAM's
C++ example with this model (1.41 m, ``benchmarks/kitti_native.py``). (GTSAM's Python example
counts ``n`` from the start of the run instead of per interval, a bias walk that loosens over the
run.)

Gravity: ``(0, 0, -9.8)``, GTSAM's example's ``PreintegrationParams.MakeSharedU(9.8)``.

GPS fixes: covariance ``gps_sigma^2 I`` with ``gps_sigma = sqrt(0.07)`` m by default (the
example's GPS prior has precision ``1 / 0.07`` on each position axis). Fix number
``first_gps`` (0-based, default 1 like the example, because the IMU record has a lone first
sample followed by a 1.9 s gap) is the start: it defines the initial position and the dataset
begins at its time. Of the later fixes, fix number ``i`` of the file (0-based, counted as GTSAM's
example counts them) is a measurement of the sensor ``gps`` (kind ``position``) when
``i % gps_every == 0`` -- the example's rule, so ``gps_every=10`` uses the same fixes 10, 20, ...
as the example -- and held out (the sensor's ``heldout``) otherwise; the first fix itself is in neither (it is the
initial position's prior). Fixes after the last IMU sample are dropped.

Times: measurement times are kept exactly as in the file; a fix between two IMU samples is not
moved to a sample: the estimators put keyframes at measurement times and split the IMU interval
there. The IMU samples start exactly at the first fix's time: if that time falls between samples
k and k+1, a sample at the fix time with sample k's values is put first (under the project's
zero-order hold that is the same signal, cut at the fix time) and samples up to k are dropped.
A gap between IMU samples larger than ``max_imu_gap`` seconds inside the used span is an error.

Initial state (at the first fix; GTSAM's example starts from the identity attitude with NO
attitude information (precision 0), zero velocity with sigma 1000 m/s although the car is
driving at about 9 m/s, zero biases): here

* position: the first fix, sigma 1 m per axis (the example's pose prior);
* attitude: roll = pitch = 0, yaw = the GPS course from the first fix to the next one (the IMU's
  x axis points forward), sigmas (0.05, 0.05, 0.1) rad about the world x, y, z axes (the
  error-state convention of ``factors.imu``: left perturbation, world frame). With a course
  undefined (less than 1 m between the fixes) yaw is 0 with sigma pi;
* body velocity: ``C^T`` times the mean GPS velocity between those two fixes, sigma 1 m/s;
* biases zero, sigmas 0.1 m/s^2 (accelerometer) and 5e-5 rad/s (gyro), the example's bias prior.

``initial_cov`` is diagonal in the error-state order ``(r, v, phi, b_f, b_w)`` with the
squares of these sigmas.
"""
from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from datasets.errors import (
    DataError,
    check_increasing,
    data_rows,
    parse_rows,
    read_lines,
    read_table,
    require_imu_recording,
    require_rows,
)
from datasets.kinds.position import POSITION
from datasets.types import Dataset, ImuSamples, PositionMeasurements, Sensor
from factors import euler, so3
from factors.errors import InputError
from factors.imu import ImuNoise, ImuState

IMU_FILE = "KittiEquivBiasedImu.txt"
METADATA_FILE = "KittiEquivBiasedImu_metadata.txt"
GPS_FILE = "KittiGps_converted.txt"

IMU_FIELDS = ["Time", "dt", "accelX", "accelY", "accelZ", "omegaX", "omegaY", "omegaZ"]
GPS_FIELDS = ["Time", "X", "Y", "Z"]
METADATA_FIELDS = [
    "BodyPtx", "BodyPty", "BodyPtz", "BodyPrx", "BodyPry", "BodyPrz", "AccelerometerSigma",
    "GyroscopeSigma", "IntegrationSigma", "AccelerometerBiasSigma", "GyroscopeBiasSigma", "AverageDeltaT",
]

#: Gravity of GTSAM's KITTI example (``MakeSharedU(9.8)``).
GRAVITY = np.array([0.0, 0.0, -9.8])
#: The name of the GPS receiver's sensor (what ``--robust gps=...`` and the outputs call it).
GPS_SENSOR = "gps"
#: GPS position variance of GTSAM's example (precision 1/0.07 per axis).
GPS_VARIANCE = 0.07
#: Largest accepted |dt - (t_k - t_{k-1})| [s].
DT_TOLERANCE = 1e-6
#: Initial-state sigmas (see the module docstring).
INITIAL_POSITION_SIGMA = 1.0
INITIAL_VELOCITY_SIGMA = 1.0
INITIAL_ATTITUDE_SIGMA = (0.05, 0.05, 0.1)
INITIAL_ACC_BIAS_SIGMA = 0.1
INITIAL_GYRO_BIAS_SIGMA = 5e-5
#: Below this distance [m] between the first two fixes the course (and so yaw) is undefined.
MIN_COURSE_DISTANCE = 1.0


@dataclass(frozen=True)
class KittiMetadata:
    """The metadata line of ``KittiEquivBiasedImu_metadata.txt``."""

    body_ptx: float
    body_pty: float
    body_ptz: float
    body_prx: float
    body_pry: float
    body_prz: float
    accelerometer_sigma: float
    gyroscope_sigma: float
    integration_sigma: float
    accelerometer_bias_sigma: float
    gyroscope_bias_sigma: float
    average_delta_t: float
    #: 1-based line of the values in the file (for messages).
    line: int = field(default=2, compare=False)

    def noise(self) -> ImuNoise:
        """The densities as :class:`ImuNoise` (mapping in the module docstring)."""
        return ImuNoise(
            acc=self.accelerometer_sigma,
            gyro=self.gyroscope_sigma,
            acc_bias=self.accelerometer_bias_sigma / np.sqrt(self.average_delta_t),
            gyro_bias=self.gyroscope_bias_sigma / np.sqrt(self.average_delta_t),
            velocity=self.integration_sigma,
        )


def _default(path, name: str) -> Path:
    if path is not None:
        return Path(path)
    import gtsam

    return Path(gtsam.findExampleDataFile(name))


def _check_header(path, lines: list[str], expected: list[str], split) -> None:
    if not lines:
        raise DataError(path, 1, None, "an empty file", f"a header line '{' '.join(expected)}'")
    found = [token.strip() for token in split(lines[0].strip())]
    if [f.lower() for f in found] != [e.lower() for e in expected]:
        raise DataError(path, 1, "header", lines[0].strip(), f"the column names {' '.join(expected)}")


def read_metadata(path=None) -> KittiMetadata:
    """Read and check the metadata file (12 names, 12 numbers; sigmas >= 0, identity body pose)."""
    path = _default(path, METADATA_FILE)
    lines = read_lines(path)
    _check_header(path, lines, METADATA_FIELDS, str.split)
    rows = data_rows(lines, str.split, comment="", skip=1)
    require_rows(path, rows, len(lines), 1, "line of metadata values after the header")
    if len(rows) > 1:
        raise DataError(path, rows[1][0], None, "a second line of values", "one line of values")
    values, _ = parse_rows(path, rows, METADATA_FIELDS)
    line = rows[0][0]
    meta = KittiMetadata(*map(float, values[0]), line=line)
    for name, value in zip(METADATA_FIELDS[:6], values[0, :6]):
        if value != 0.0:
            raise DataError(path, line, name, value, "0 (only the identity IMU-in-body pose is supported)")
    for name, value in zip(METADATA_FIELDS[6:11], values[0, 6:11]):
        if value < 0:
            raise DataError(path, line, name, value, "a sigma >= 0")
    if values[0, 11] <= 0:
        raise DataError(path, line, "AverageDeltaT", values[0, 11], "a time step > 0")
    return meta


def read_imu(path=None) -> tuple[ImuSamples, np.ndarray]:
    """Read the IMU file; returns the samples and the 1-based line number of each sample (a
    recording as long as :func:`datasets.errors.require_imu_recording` asks)."""
    path = _default(path, IMU_FILE)
    lines = read_lines(path)
    _check_header(path, lines, IMU_FIELDS, str.split)
    values, line_numbers = read_table(path, lines, IMU_FIELDS, 2, "IMU sample lines", skip=1)
    t = values[:, 0]
    check_increasing(path, t, line_numbers, "Time")
    dt_err = np.abs(values[1:, 1] - np.diff(t))
    bad = np.flatnonzero(dt_err > DT_TOLERANCE)
    if bad.size:
        i = int(bad[0]) + 1
        raise DataError(
            path, int(line_numbers[i]), "dt", values[i, 1],
            f"the time since the previous sample, {t[i] - t[i - 1]!r} (within {DT_TOLERANCE:g} s)",
        )
    require_imu_recording(path, t)
    return ImuSamples(t, values[:, 2:5], values[:, 5:8]), line_numbers


def read_gps(path=None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Read the GPS file; returns times, positions (N, 3) and 1-based line numbers."""
    path = _default(path, GPS_FILE)
    lines = read_lines(path)

    def split(text):
        return text.split(",")

    _check_header(path, lines, GPS_FIELDS, split)
    values, line_numbers = read_table(path, lines, GPS_FIELDS, 2, "GPS fix lines", delimiter=",", skip=1)
    check_increasing(path, values[:, 0], line_numbers, "Time")
    return values[:, 0], values[:, 1:4], line_numbers


#: Fields of a KITTI odometry pose file line: the 3x4 matrix ``[R | p]`` row by row.
POSE_FIELDS = [f"r{i}{j}" for i in range(1, 4) for j in range(1, 5)]
#: Accepted deviation of a pose file's rotation from orthonormality (files carry 6-9 digits).
POSE_ROTATION_TOLERANCE = 1e-4


def read_pose_file(path) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """A KITTI odometry pose file (evo's ``kitti`` mode): one pose per line, the 12 numbers of the
    3x4 matrix ``[C | r]`` row by row, space separated -- the body-to-world rotation and the
    position, with no time stamp (poses are paired by their line). Returns ``(r, C, lines)``;
    each ``C`` must be a rotation within :data:`POSE_ROTATION_TOLERANCE` (``|C C^T - I|``,
    det > 0) and is then projected onto SO(3)."""
    path = Path(path)
    lines = read_lines(path)
    values, line_numbers = read_table(path, lines, POSE_FIELDS, 1, "pose line (12 numbers: a 3x4 matrix by rows)")
    M = values.reshape(-1, 3, 4)
    C = M[:, :, :3]
    error = np.abs(C @ np.swapaxes(C, 1, 2) - np.eye(3)).max(axis=(1, 2))
    bad = np.flatnonzero((error > POSE_ROTATION_TOLERANCE) | (np.linalg.det(C) <= 0))
    if bad.size:
        i = int(bad[0])
        raise DataError(path, int(line_numbers[i]), "r11 ... r33", f"a matrix {error[i]:.3g} from orthonormal "
                        f"(det {np.linalg.det(C[i]):.6g})",
                        f"a rotation (|R R^T - I| <= {POSE_ROTATION_TOLERANCE:g}, det > 0)", whole=True)
    return M[:, :, 3].copy(), so3.project(C), line_numbers


def _initial_state(t_gps: np.ndarray, p_gps: np.ndarray) -> tuple[ImuState, np.ndarray]:
    """Initial state at fix 0 from fixes 0 and 1 (module docstring) and its covariance."""
    v_world = (p_gps[1] - p_gps[0]) / (t_gps[1] - t_gps[0])
    horizontal = p_gps[1, :2] - p_gps[0, :2]
    yaw_sigma = INITIAL_ATTITUDE_SIGMA[2]
    if np.hypot(*horizontal) >= MIN_COURSE_DISTANCE:
        yaw = float(np.arctan2(horizontal[1], horizontal[0]))
    else:
        yaw, yaw_sigma = 0.0, np.pi
    C = euler.rpy_to_matrix(np.array([0.0, 0.0, yaw]))
    state = ImuState(r=p_gps[0].copy(), v=C.T @ v_world, C=C, b_f=np.zeros(3), b_w=np.zeros(3))
    sigmas = np.concatenate([
        np.full(3, INITIAL_POSITION_SIGMA), np.full(3, INITIAL_VELOCITY_SIGMA),
        [INITIAL_ATTITUDE_SIGMA[0], INITIAL_ATTITUDE_SIGMA[1], yaw_sigma],
        np.full(3, INITIAL_ACC_BIAS_SIGMA), np.full(3, INITIAL_GYRO_BIAS_SIGMA),
    ])
    return state, np.diag(sigmas**2)


def load_kitti(imu_path=None, gps_path=None, metadata_path=None, *, gps_every: int = 1, first_gps: int = 1,
               gps_sigma: float = float(np.sqrt(GPS_VARIANCE)), max_imu_gap: float | None = 0.1) -> Dataset:
    """The KITTI example data as a :class:`Dataset` named ``"kitti"`` (see the module docstring).

    ``gps_every=K``: the fixes after the first whose number in the file is a multiple of ``K``
    are measurements (GTSAM's example's rule), the others are held out.
    Paths default to GTSAM's installed example files.
    """
    if isinstance(gps_every, bool) or not isinstance(gps_every, (int, np.integer)) or gps_every < 1:
        raise InputError(f"gps_every: expected an integer >= 1, got {gps_every!r}")
    if isinstance(first_gps, bool) or not isinstance(first_gps, (int, np.integer)) or first_gps < 0:
        raise InputError(f"first_gps: expected an integer >= 0, got {first_gps!r}")
    gps_sigma = float(gps_sigma)
    if not np.isfinite(gps_sigma) or gps_sigma <= 0:
        raise InputError(f"gps_sigma: expected a finite sigma > 0, got {gps_sigma!r}")
    imu_path = _default(imu_path, IMU_FILE)
    gps_path = _default(gps_path, GPS_FILE)
    metadata_path = _default(metadata_path, METADATA_FILE)

    meta = read_metadata(metadata_path)
    imu, imu_lines = read_imu(imu_path)
    t_gps, p_gps, gps_lines = read_gps(gps_path)

    span = (imu.t[-1] - imu.t[0]) / (len(imu) - 1)
    if abs(span - meta.average_delta_t) > 0.1 * meta.average_delta_t:
        raise DataError(
            metadata_path, meta.line, "AverageDeltaT", meta.average_delta_t,
            f"the mean IMU step of {imu_path} ({span:.6g} s) within 10%",
        )

    # GPS: from fix first_gps on, within the IMU span.
    if first_gps > len(t_gps) - 2:
        raise DataError(gps_path, int(gps_lines[-1]), None, f"{len(t_gps)} GPS fixes",
                        f"at least first_gps + 2 = {first_gps + 2} fixes")
    t_gps, p_gps, gps_lines = t_gps[first_gps:], p_gps[first_gps:], gps_lines[first_gps:]
    t0 = t_gps[0]
    if not imu.t[0] <= t0 < imu.t[-1]:
        raise DataError(
            gps_path, int(gps_lines[0]), "Time", t0,
            f"a time within the IMU samples of {imu_path} ([{imu.t[0]!r}, {imu.t[-1]!r}))",
        )
    keep = t_gps <= imu.t[-1]
    t_gps, p_gps, gps_lines = t_gps[keep], p_gps[keep], gps_lines[keep]
    if len(t_gps) < 2:
        raise DataError(gps_path, int(gps_lines[0]), "Time", "a single fix within the IMU span",
                        "at least two GPS fixes between the first and last IMU sample")

    # IMU: start exactly at the first fix (zero-order hold, see the module docstring).
    k = int(np.searchsorted(imu.t, t0, side="right")) - 1
    t = imu.t[k:].copy()
    t[0] = t0
    acc, gyro = imu.acc[k:], imu.gyro[k:]
    lines = imu_lines[k:]
    if max_imu_gap is not None:
        gaps = np.diff(t)
        bad = np.flatnonzero(gaps > max_imu_gap)
        if bad.size:
            i = int(bad[0]) + 1
            raise DataError(
                imu_path, int(lines[i]), "Time", f"{t[i]!r}, {gaps[i - 1]:.6g} s after the previous sample",
                f"samples at most {max_imu_gap:g} s apart after the first GPS fix used",
            )
    samples = ImuSamples(t, acc, gyro)

    initial, initial_cov = _initial_state(t_gps, p_gps)
    if not (np.all(np.isfinite(initial.v)) and np.all(np.isfinite(initial.r))):
        raise DataError(gps_path, int(gps_lines[1]), None, "a velocity from the first two fixes that overflows",
                        "finite positions and times")
    j = np.arange(1, len(t_gps))  # index after the first; fix number first_gps + j in the file
    used = j[(first_gps + j) % gps_every == 0]
    held = j[(first_gps + j) % gps_every != 0]
    cov = gps_sigma**2 * np.eye(3)
    position = PositionMeasurements(t_gps[used], p_gps[used], cov) if used.size else None
    heldout = PositionMeasurements(t_gps[held], p_gps[held], cov) if held.size else None
    return Dataset(
        name="kitti", imu=samples, noise=meta.noise(), initial=initial, initial_cov=initial_cov,
        gravity=GRAVITY.copy(), sensors=(Sensor(GPS_SENSOR, POSITION.name, position, heldout),),
    )
