"""Simulated sensors of any kind, mounted anywhere on the body, drawn from a ground truth: the
one place where measurements are generated from a truth (the simulator, and EuRoC's
``pose_from_truth`` / ``gps_from_truth``).

Each :class:`SensorSpec` names a kind of :data:`datasets.kinds.KINDS`, a rate, a noise and an
extrinsic; :func:`sensors_from_truth` draws its measurements with the kind's own simulator
(:attr:`datasets.kinds.base.Kind.simulate`) at truth samples (:func:`measurement_indices`), each
sensor with a noise stream of its own (:func:`sensor_stream`).

Times: a measurement is taken at a truth sample, never interpolated, so its value is exactly
the truth plus noise. For a rate ``f`` the ticks are ``t_0 + k / f`` (``t_0`` the first truth
time) and each tick takes the first truth sample at or after it (a tolerance of 1e-6 of the
median truth step absorbs round-off in the ticks); a truth sample is used at most once. A rate
above the truth's own rate is refused (it could not be delivered).
"""
from __future__ import annotations

import zlib
from dataclasses import dataclass, replace

import numpy as np

from datasets.kinds import KINDS, kind_sigmas, pose, position
from datasets.kinds.base import ImuAt
from datasets.types import Dataset, ImuSamples, Sensor, Trajectory, VelocityMeasurements
from factors.errors import InputError


def _positive(name: str, value) -> float:
    try:
        value = float(value)
    except (TypeError, ValueError):
        raise InputError(f"{name}: expected a number > 0, got {value!r}") from None
    if not np.isfinite(value) or value <= 0:
        raise InputError(f"{name}: expected a finite number > 0, got {value!r}")
    return value


def measurement_indices(t: np.ndarray, rate_hz: float) -> np.ndarray:
    """Indices into the truth times ``t`` (strictly increasing) of measurements at ``rate_hz``."""
    rate_hz = _positive("rate_hz", rate_hz)
    t = np.asarray(t, dtype=float)
    if t.size == 0:
        return np.zeros(0, dtype=int)
    if t.size == 1:
        return np.zeros(1, dtype=int)
    step = float(np.median(np.diff(t)))
    if rate_hz * step > 1.0 + 1e-6:
        raise InputError(
            f"rate_hz: {rate_hz:g} Hz is above the rate of the ground truth ({1.0 / step:g} Hz); "
            "measurements are taken at truth samples"
        )
    count = int(np.floor((t[-1] - t[0]) * rate_hz + 1e-9)) + 1
    ticks = t[0] + np.arange(count) / rate_hz
    index = np.searchsorted(t, ticks - 1e-6 * step, side="left")
    index = index[index < t.size]
    return np.unique(index)


@dataclass(frozen=True)
class SensorSpec:
    """A simulated sensor: ``name``, ``kind`` (a name of :data:`datasets.kinds.KINDS`), rate
    [Hz], noise ``sigma`` (one number, one per residual dimension, or for 6-dim kinds the pair
    ``(translation [m], rotation [rad])``) and extrinsic ``T_BS`` (None: at the IMU)."""

    name: str
    kind: str
    rate_hz: float
    sigma: object
    T_BS: np.ndarray | None = None


def sensor_stream(root: np.random.SeedSequence, name: str) -> np.random.SeedSequence:
    """The noise stream of the sensor called ``name``: a child of ``root`` keyed by the name's
    CRC-32, so a sensor's draws do not depend on which other sensors there are or their order."""
    return np.random.SeedSequence(root.entropy, spawn_key=(*root.spawn_key, zlib.crc32(name.encode())))


def sensors_from_truth(truth: Trajectory, imu: ImuSamples, specs, seed=0, true_rate=None,
                       gyro_density: float = 0.0) -> tuple[Sensor, ...]:
    """The measurements of each simulated sensor in ``specs`` (:class:`SensorSpec`) drawn from
    ``truth`` by its kind's simulator (:attr:`datasets.kinds.Kind.simulate`), at truth samples as
    :func:`measurement_indices` picks them, each sensor with its own noise stream from ``seed``
    (an integer or a ``numpy.random.SeedSequence``) and its name (:func:`sensor_stream`). ``imu``
    gives the gyro readings a velocity sensor keeps (the sample held at each measurement time),
    ``true_rate`` (the body rates at the IMU's times; default the readings minus the true bias) the
    motion it measures, ``gyro_density`` [rad/s/sqrt(Hz)] the readings' white noise its covariance
    accounts for."""
    specs = list(specs)
    root = seed if isinstance(seed, np.random.SeedSequence) else np.random.SeedSequence(seed)
    out = []
    for spec in specs:
        stream = sensor_stream(root, spec.name)
        if spec.kind not in KINDS:
            raise InputError(f"sensor {spec.name!r}: unknown kind {spec.kind!r}; expected one of {', '.join(KINDS)}")
        kind = KINDS[spec.kind]
        try:
            k = measurement_indices(truth.t, spec.rate_hz)
        except ValueError as error:
            raise InputError(f"sensor {spec.name!r}: {error}") from None
        held = imu.held(truth.t[k])
        rate = imu.gyro[held] - truth.states.b_w[k] if true_rate is None else np.asarray(true_rate)[held]
        at = ImuAt(imu.gyro[held], rate, gyro_density**2 / float(np.median(np.diff(imu.t))))
        data = kind.simulate(truth, k, at, spec.T_BS, kind_sigmas(f"sensor {spec.name!r}", spec.sigma, kind.dim),
                             np.random.default_rng(stream))
        out.append(Sensor(spec.name, spec.kind, data))
    return tuple(out)


def truth_sensors(truth: Trajectory, imu: ImuSamples, pose_from_truth=None, gps_from_truth=None,
                  seed=0) -> tuple[Sensor, ...]:
    """Sensors at the IMU drawn from ``truth``: ``pose_from_truth = (rate_hz, pos_sigma,
    rot_sigma)`` a sensor ``pose`` of kind ``pose``, ``gps_from_truth = (rate_hz, pos_sigma)`` a
    sensor ``gps`` of kind ``position`` (None: not that one), with noise streams from ``seed``.
    An InputError names the option that is wrong."""
    specs = []
    for option, value, name, kind, size in (("pose_from_truth", pose_from_truth, "pose", pose.KIND.name, 3),
                                            ("gps_from_truth", gps_from_truth, "gps", position.POSITION.name, 2)):
        if value is None:
            continue
        if np.ndim(value) != 1 or len(value) != size:
            raise InputError(f"{option}: expected {size} numbers (rate [Hz], then the sigmas), got {value!r}")
        try:
            specs.append(SensorSpec(name, kind, value[0], tuple(value[1:])))
            sensors_from_truth(truth, imu, specs[-1:], seed)
        except ValueError as error:
            raise InputError(f"{option}: {str(error).removeprefix(f'sensor {name!r}: ')}") from None
    return sensors_from_truth(truth, imu, specs, seed)


def scaled_speeds(data: Dataset, sensor: str, scale: float) -> Dataset:
    """``data`` with the velocity sensor ``sensor`` reading ``scale`` times the true velocity (a
    wheel radius off: what a ``scale`` calibration is to find), its covariance scaled with it."""
    speeds = data.sensor(sensor).data
    if not isinstance(speeds, VelocityMeasurements):
        raise InputError(f"scaled_speeds: {sensor!r} is a {data.sensor(sensor).kind} sensor; expected a velocity one")
    return data.with_sensor(sensor, data=replace(speeds, velocity=scale * speeds.velocity, cov=scale**2 * speeds.cov))


def stamped_late(data: Dataset, sensor: str, delay: float) -> Dataset:
    """``data`` with the one-state sensor ``sensor``'s measurements stamped ``delay`` [s] after
    their true times (a latency or another clock: what a ``time_offset`` calibration is to find),
    those then stamped after the IMU's last sample left out."""
    measured = data.sensor(sensor).data
    kept = measured.t + delay <= data.imu.t[-1]
    return data.with_sensor(sensor, data=replace(measured.subset(kept), t=measured.t[kept] + delay))
