"""Rig files: the IMU and the aiding sensors of a recording, in TOML.

:func:`load_rig` parses and checks a rig file into frozen dataclasses WITHOUT reading any data
(only the small calibration files it names: a Kalibr ``imu.yaml``, a camchain). Paths in it are
relative to the rig file's folder (``~`` expands); the :class:`Rig` holds sources with absolute
paths, ready for :mod:`datasets.sources`. Example, with every key::

    [imu]
    source = "bag:run.bag"          # csv:FILE (EuRoC/ASL layout) | bag:FILE.bag (ROS 1)
                                    # | bag:FOLDER or bag:FILE.db3 (ROS 2) | bag:FILE.mcap
    topic = "/imu/data"             # bags only (and required for them)
    accel_noise_density = 2.0e-3    # m/s^2/sqrt(Hz)  continuous-time densities, Kalibr imu.yaml units
    gyro_noise_density = 1.7e-4     # rad/s/sqrt(Hz)
    accel_random_walk = 3.0e-3      # m/s^3/sqrt(Hz)
    gyro_random_walk = 1.9e-5       # rad/s^2/sqrt(Hz)
    gravity = 9.81                  # optional, m/s^2 (magnitude; the world frame is z up)
    kalibr = "imu.yaml"             # optional: the densities from a Kalibr imu.yaml (keys here override)
    forward = [1, 0, 0]             # optional: the vehicle's forward direction in the IMU frame (the
                                    # heading from the GNSS course without a velocity sensor)
    estimate = ["noise"]            # optional: the four densities estimated from the data (the
                                    # values above start it)

    [datum]                         # optional origin of the local ENU frame (GNSS);
    latitude = 47.0                 # default: the first valid GNSS fix
    longitude = 8.0                 # degrees
    altitude = 400.0                # metres above the WGS-84 ellipsoid

    [[sensor]]                      # any number of sensors, each a [[sensor]] table
    name = "gnss"                   # unique; a letter, then letters, digits, _ or - (not imu, prior)
    kind = "gnss"                   # pose | position | gnss | orientation | velocity | odometry
                                    # | altitude | magnetometer
    source = "bag:run.bag"          # bag:..., csv:FILE or tum:FILE (poses only)
    topic = "/fix"                  # bags only (and required for them)
    T_BS = [[1,0,0,0],[0,1,0,0],[0,0,1,0.5],[0,0,0,1]]   # optional, default identity: the sensor
                                    # frame S in the IMU frame B, p_B = T_BS p_S (EuRoC/Kalibr)
    camchain = "camchain.yaml"      # optional instead of T_BS: a Kalibr camchain, with
    camera = "cam0"                 # the camera whose T_cam_imu (= T_SB) is inverted
    time_offset = 0.0               # optional, seconds added to this sensor's stamps
    sigma = 1.0                     # optional: standard deviation(s) overriding the messages'
                                    # covariance, one number (every axis) or a list (per axis)
    sigma_factor = 1.0              # optional instead: a factor on the messages' sigmas, as sigma
    every = 1                       # optional: use every k-th measurement, hold the rest out
    robust = "huber"                # optional: none | huber | cauchy | tukey, each [:threshold]
    correlation_time = 20.0         # optional, s: the errors drift, first-order Gauss-Markov with
                                    # this time constant and sigma as their spread (batch smoother;
                                    # kinds of one state per measurement); "fit": fitted to the
                                    # held-out measurements (needs every = K > 1)
    roll_pitch_only = false         # optional, orientation sensors only: use roll and pitch, not the
                                    # heading (an AHRS without a magnetometer; the kind roll_pitch)
    declination = 2.5               # magnetometers only, and required for them: the world field's
    inclination = 63.0              # declination (east of north) and inclination (down), degrees
    scale = 1.0                     # optional, velocity and odometry only: what the sensor reads
                                    # per unit of the truth (its readings are divided by it)
    estimate = ["rotation", "scale"]  # optional: what of its calibration the batch smoother
                                    # estimates, any of time_offset, rotation, lever_arm, scale,
                                    # and "noise": its sigmas, estimated from the data
    time_offset_sigma = 0.1         # optional priors about the values given: s (default 0.1),
    rotation_sigma = 0.1            # rad (0.1), m (0.2), and about a scale of 1 (0.05)
    lever_arm_sigma = 0.2
    scale_sigma = 0.05

Required: ``[imu]`` with ``source`` and the four densities (here or through ``kalibr``); in a
``[datum]`` all three keys; in a ``[[sensor]]`` ``name``, ``kind`` and ``source``. What a sensor's
kind reads from its source, and how many numbers its ``sigma`` takes in which units, is the
measurement kind's business (:class:`datasets.kinds.base.Kind`): the rig checks ``sigma`` against
what the kind declares.

A bad rig file is one :class:`RigError` (a ``ValueError``) of one line naming the file, the key and
what was expected, e.g. ``rig.toml: sensor[1] "gnss".T_BS: expected a rigid transform ...``.
Sensors are counted from 1 in the order of their tables. Checked: the files read (the rig, a
Kalibr file, a camchain) through :func:`datasets.errors.read_source` (regular files within their
size limits), TOML syntax (with its line), nesting the TOML reader cannot follow, every number
within its plausible range (:data:`datasets.ranges.RANGES`: a lever arm by its length, a Kalibr
file's densities as the keys they stand for, a ``sigma`` per residual axis in the axis's unit,
:data:`datasets.ranges.SIGMA_RANGES`, and as many numbers as the kind takes), sensor names
(:func:`datasets.ranges.sensor_name_problem`),
unknown keys (the closest known one suggested), types, missing required keys, a bag source
without a topic or a file source with one, unknown schemes and kinds, a ``T_BS`` that is not a
4x4 rigid transform (rotation orthonormal with det +1 to :data:`T_BS_TOLERANCE`, last row 0 0 0 1;
within it the rotation is taken to the nearest one), both ``T_BS``
and ``camchain``, duplicate sensor names, more than :data:`datasets.ranges.MAX_SENSORS` sensors,
two sensors reading the same measurements (one file and topic, kinds measuring a same field),
``sigma`` <= 0, ``every`` < 1, a bad ``robust`` spec,
a datum off the globe, an ``estimate`` naming a part that is not one or that the kind cannot
estimate (a rotation of a position sensor), a ``*_sigma`` of the calibration without ``estimate``,
``roll_pitch_only`` that is not a boolean or on a sensor of another kind
than ``orientation``, a magnetometer without ``declination`` (within +-180 degrees) and
``inclination`` (within +-90) or either on another kind.
"""
from __future__ import annotations

import difflib
import math
import os
import sys
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from datasets.errors import DataError, read_source
from datasets.gnss import Datum
from datasets.initialise import FORWARD
from datasets.kalibr import NOISE_KEYS as KALIBR_NOISE_KEYS
from datasets.kalibr import read_camchain_T_BS, read_kalibr_imu, rigid_problem
from datasets.kinds import KIND_NAMES, KINDS, drift_problem
from datasets.kinds.base import kind_sigmas, sigma_counts
from datasets.ranges import MAX_SENSORS, MAX_SENSORS_WHY, RANGES, SIGMA_RANGES, out_of_range, sensor_name_problem
from datasets.robust import robust_spec
from datasets.sources import parse_spec, user_path
from factors import so3
from factors.calibration import PARTS, CalibrationPrior, applicable
from factors.errors import InputError
from factors.imu import DEFAULT_GRAVITY, ImuNoise

if sys.version_info >= (3, 11):
    import tomllib
else:
    import tomli as tomllib

#: Rig keys of the four IMU densities and the :class:`ImuNoise` fields they set.
NOISE_KEYS = {
    "accel_noise_density": "acc",
    "gyro_noise_density": "gyro",
    "accel_random_walk": "acc_bias",
    "gyro_random_walk": "gyro_bias",
}
TOP_KEYS = ("imu", "datum", "sensor")
#: How far a rig file's T_BS rotation may be from orthonormal: written by hand to a few decimals, it
#: is taken to the nearest rotation (a rotation rounded to 6 decimals is ~1e-5 off).
T_BS_TOLERANCE = 1e-4
IMU_KEYS = ("source", "topic", *NOISE_KEYS, "gravity", "kalibr", "forward", "estimate")
DATUM_KEYS = ("latitude", "longitude", "altitude")
#: What ``estimate = [...]`` names besides a calibration's parts: the noise, estimated from the data
#: by the batch smoother (the IMU's four densities; a sensor's sigmas per axis group).
NOISE = "noise"
#: The keys of a sensor's calibration (:func:`_calibration`): what to estimate and the priors' sigmas.
CALIBRATION_KEYS = ("estimate", "time_offset_sigma", "rotation_sigma", "lever_arm_sigma", "scale_sigma")
SENSOR_KEYS = ("name", "kind", "source", "topic", "T_BS", "camchain", "camera", "time_offset", "sigma",
               "sigma_factor", "every", "correlation_time",
               "robust", "roll_pitch_only", "declination", "inclination", "scale", *CALIBRATION_KEYS)


class RigError(InputError):
    """A bad rig file: ``path``, ``key`` (e.g. ``sensor[1] "gnss".T_BS``, or None for the whole
    file) and the message."""

    def __init__(self, path, key: str | None, message: str):
        self.path, self.key = str(path), key
        super().__init__(f"{path}: {key}: {message}" if key else f"{path}: {message}")


@dataclass(frozen=True)
class ImuConfig:
    """The IMU: ``source`` (a spec with an absolute path), ``topic`` (bags) or None, the noise
    densities, the magnitude of gravity [m/s^2] and the vehicle's ``forward`` direction in the IMU
    frame (a unit 3-vector); ``estimate_noise``: whether the densities are estimated from the data."""

    source: str
    topic: str | None
    noise: ImuNoise
    gravity: float
    forward: tuple = FORWARD
    #: ``estimate = ["noise"]``: the densities estimated from the data (the values given start it).
    estimate_noise: bool = False


@dataclass(frozen=True, eq=False)
class SensorConfig:
    """One aiding sensor: ``name``, ``kind`` (one of ``datasets.kinds.KIND_NAMES``), ``source``
    (a spec with an absolute path), ``topic`` or None, ``T_BS`` (4, 4) (``p_B = T_BS p_S``),
    ``time_offset`` [s] added to its stamps, ``sigma`` None or standard deviations of shape (d,)
    (d = 1: the same for every axis), ``every`` (use every k-th measurement) and ``robust``,
    None or a kernel spec ``(name, threshold or None)`` of :func:`datasets.robust.robust_spec`;
    for a magnetometer the world field's ``declination`` and ``inclination`` [deg] (else None);
    ``scale``: what a velocity or odometry sensor reads per unit of the truth (its readings are
    divided by it); ``calibrate``: what of its calibration to estimate (a
    :class:`factors.calibration.CalibrationPrior`), or None; ``estimate_noise``: whether its sigmas
    are estimated from the data (``estimate`` names ``"noise"``); ``sigma_factor``: None or factors
    on the messages' standard deviations, shaped as ``sigma`` (the covariances ``D C D``, ``D`` the
    axes' factors; never with ``sigma``); ``correlation_time``: None, or the time constant [s] of its
    errors as a first-order Gauss-Markov process (:attr:`datasets.types.Sensor.correlation_time`);
    ``fit_correlation_time``: that time constant to be fitted (the rig's ``correlation_time = "fit"``)."""

    name: str
    kind: str
    source: str
    topic: str | None
    T_BS: np.ndarray
    time_offset: float
    sigma: np.ndarray | None
    every: int
    robust: tuple | None
    declination: float | None = None
    inclination: float | None = None
    scale: float = 1.0
    calibrate: CalibrationPrior | None = None
    estimate_noise: bool = False
    sigma_factor: np.ndarray | None = None
    correlation_time: float | None = None
    fit_correlation_time: bool = False


@dataclass(frozen=True)
class Rig:
    """A rig file read: its ``path``, the ``imu``, the ``datum`` (None: the first valid GNSS fix)
    and the ``sensors`` in file order."""

    path: Path
    imu: ImuConfig
    datum: Datum | None
    sensors: tuple[SensorConfig, ...]


class _Table:
    """One TOML table being checked: typed getters that raise :class:`RigError` naming the key.
    ``ranges`` is the table's name in :data:`datasets.ranges.RANGES` (``imu``, ``datum``,
    ``sensor``): a number read whose key is there must lie in its range."""

    def __init__(self, path, folder: Path, where: str, table, allowed: tuple, ranges: str = ""):
        self.path, self.folder, self.where, self.ranges = path, folder, where, ranges
        if not isinstance(table, dict):
            raise RigError(path, where, f"expected a table, got {_kind(table)}")
        for key in table:
            if key not in allowed:
                close = difflib.get_close_matches(key, allowed, n=1)
                hint = f" (did you mean {close[0]!r}?)" if close else ""
                raise RigError(path, self.key(key), f"unknown key{hint}; expected one of {', '.join(allowed)}")
        self.table = table

    def key(self, name: str) -> str:
        return f"{self.where}.{name}" if self.where else name

    def error(self, name: str, message: str) -> RigError:
        return RigError(self.path, self.key(name), message)

    def get(self, name: str, types: tuple, what: str, required: bool = False, default=None):
        if name not in self.table:
            if required:
                raise self.error(name, f"missing; expected {what}")
            return default
        value = self.table[name]
        if isinstance(value, bool) and bool not in types or not isinstance(value, types):
            raise self.error(name, f"expected {what}, got {_kind(value)} {value!r}")
        return value

    def string(self, name: str, required: bool = False) -> str | None:
        value = self.get(name, (str,), "a string", required)
        if value is not None and not value.strip():
            raise self.error(name, "expected a non-empty string")
        return value

    def number(self, name: str, required: bool = False, default=None, minimum=None, positive=False) -> float | None:
        """The number ``name`` (an absent one: ``default``), finite, ``>= minimum`` or ``> 0`` if
        asked, and within its range (:meth:`in_range`) when given."""
        value = self.get(name, (int, float), "a number", required, default)
        if value is None:
            return None
        if not math.isfinite(value):
            raise self.error(name, f"expected a finite number, got {value!r}")
        if minimum is not None and value < minimum or positive and value <= 0:
            raise self.error(name, f"expected a number {'> 0' if positive else f'>= {minimum:g}'}, got {value!r}")
        if name in self.table:
            self.in_range(name, value)
        return float(value)

    def in_range(self, name: str, value, what: str = "") -> None:
        """``value`` of the key ``name`` within its range of :data:`datasets.ranges.RANGES`, else a
        :class:`RigError` naming the key and the range (``what`` says which value of it, if not
        the key's own)."""
        problem = out_of_range(f"{self.ranges}.{name}", value)
        if problem is not None:
            raise self.error(name, what + problem)

    def file(self, name: str) -> Path | None:
        value = self.string(name)
        if value is None:
            return None
        try:
            return user_path(value, self.folder)
        except InputError as error:
            raise self.error(name, str(error)) from None

    def source(self, stream: str | None) -> tuple[str, str | None]:
        """The source spec (absolute path) and its topic, checked together."""
        spec = self.string("source", required=True)
        try:
            scheme, file = parse_spec(spec, self.folder, stream)
        except ValueError as error:
            raise self.error("source", str(error)) from None
        topic = self.string("topic")
        if scheme == "bag" and topic is None:
            raise self.error("topic", f"missing; a bag source ({spec!r}) needs the topic to read")
        if scheme != "bag" and topic is not None:
            raise self.error("topic", f"only bag sources have topics, and {spec!r} is a {scheme}: source")
        return f"{scheme}:{file}", topic


def _kind(value) -> str:
    return {bool: "a boolean", int: "an integer", float: "a number", str: "a string", list: "an array",
            dict: "a table"}.get(type(value), type(value).__name__)


def _imu(path, folder: Path, table) -> ImuConfig:
    t = _Table(path, folder, "imu", table, IMU_KEYS, "imu")
    source, topic = t.source("IMU samples")
    densities = {}
    kalibr = t.file("kalibr")
    if kalibr is not None:
        try:
            densities = read_kalibr_imu(kalibr)
        except DataError as error:
            raise t.error("kalibr", str(error)) from None
    kalibr_key = {field: key for key, field in KALIBR_NOISE_KEYS.items()}
    for key, field in NOISE_KEYS.items():
        value = t.number(key, minimum=0.0)
        if value is not None:
            densities[field] = value
        elif field not in densities:
            raise t.error(key, "missing; expected a density >= 0" + (" (here or in the Kalibr file)" if kalibr else ""))
        else:  # the Kalibr file's, within the range of the key it stands for
            problem = out_of_range(f"imu.{key}", densities[field])
            if problem is not None:
                raise t.error("kalibr", f"{kalibr}: {kalibr_key[field]} (the rig's {key}): {problem}")
    gravity = t.number("gravity", default=float(np.linalg.norm(DEFAULT_GRAVITY)), positive=True)
    estimate = t.get("estimate", (list,), f'["{NOISE}"]', default=[])
    if estimate not in ([], [NOISE]):
        raise t.error("estimate", f'expected ["{NOISE}"] (the IMU estimates its noise densities only), '
                                  f"got {estimate!r}")
    return ImuConfig(source, topic, ImuNoise(**densities), gravity, _forward(t), estimate_noise=bool(estimate))


def _forward(t: _Table) -> tuple:
    value = t.get("forward", (list,), "the vehicle's forward direction in the IMU frame: 3 numbers", default=FORWARD)
    if (len(value) != 3 or not all(isinstance(x, (int, float)) and not isinstance(x, bool) for x in value)
            or not all(math.isfinite(x) for x in value) or math.hypot(*value) == 0.0):
        raise t.error("forward", f"expected the vehicle's forward direction in the IMU frame: 3 finite numbers, not "
                                 f"all zero (e.g. [-1, 0, 0] for an IMU whose x axis points backwards), got {value!r}")
    norm = math.hypot(*value)
    if "forward" in t.table:
        t.in_range("forward", norm, f"its length {norm:g}: ")
    return tuple(float(x) / norm for x in value)


def _datum(path, folder: Path, table) -> Datum:
    t = _Table(path, folder, "datum", table, DATUM_KEYS, "datum")
    return Datum(**{name: t.number(name, required=True) for name in DATUM_KEYS})


def _transform(t: _Table) -> np.ndarray:
    """The sensor's ``T_BS`` (from ``T_BS``, a ``camchain`` or the identity), its lever arm within
    its range."""
    T, key = _extrinsic(t)
    lever = float(np.linalg.norm(T[:3, 3]))
    problem = out_of_range("sensor.T_BS", lever)
    if problem is not None:
        raise t.error(key, f"its lever arm (the translation {T[:3, 3].tolist()}) is {lever:g} m long; {problem}")
    return T


def _extrinsic(t: _Table) -> tuple[np.ndarray, str]:
    """``(T_BS, the key it came from)``."""
    if "T_BS" in t.table and "camchain" in t.table:
        raise t.error("camchain", "give either T_BS or camchain, not both")
    if "camchain" in t.table or "camera" in t.table:
        camchain, camera = t.file("camchain"), t.string("camera")
        if camchain is None or camera is None:
            missing = "camera" if camchain is not None else "camchain"
            raise t.error(missing, "missing; camchain and camera come together")
        try:
            return read_camchain_T_BS(camchain, camera), "camchain"
        except DataError as error:
            raise t.error("camchain", str(error)) from None
    value = t.get("T_BS", (list,), "a 4x4 array of numbers (rows)", default=None)
    if value is None:
        return np.eye(4), "T_BS"
    rows_ok = len(value) == 4 and all(isinstance(row, list) and len(row) == 4 for row in value)
    if not rows_ok or any(isinstance(x, bool) or not isinstance(x, (int, float)) for row in value for x in row):
        raise t.error("T_BS", "expected a 4x4 array of numbers: 4 rows of 4")
    T = np.array(value, dtype=float)
    problem = rigid_problem(T, T_BS_TOLERANCE)
    if problem is not None:
        raise t.error("T_BS", f"expected a rigid transform (rotation orthonormal with det +1 to {T_BS_TOLERANCE:g}, "
                              f"last row 0 0 0 1); got {problem}")
    if rigid_problem(T, 1e-12) is not None:  # rounded: the nearest rotation (an exact one is kept as written)
        T[:3, :3] = so3.project(T[:3, :3])
    return T, "T_BS"


def _sigma(t: _Table, kind: str) -> np.ndarray | None:
    """The sensor's ``sigma``: as many numbers as its kind takes, each within the range of the
    unit of the residual axis it applies to (:data:`datasets.ranges.SIGMA_RANGES`)."""
    value = t.get("sigma", (int, float, list), "a standard deviation > 0 or a list of them", default=None)
    if value is None:
        return None
    items = value if isinstance(value, list) else [value]
    if not items or any(isinstance(x, bool) or not isinstance(x, (int, float)) for x in items):
        raise t.error("sigma", f"expected a standard deviation > 0 or a non-empty list of them, got {value!r}")
    sigma = np.array(items, dtype=float)
    if not np.all(np.isfinite(sigma)) or np.any(sigma <= 0):
        raise t.error("sigma", f"expected standard deviations > 0 (finite), got {value!r}")
    declared = KINDS[kind]
    try:
        axes = kind_sigmas("sigma", sigma, declared.dim)
    except InputError:
        raise t.error("sigma", f"a {kind} sensor's sigma is {sigma_counts(declared.dim)}, got {value!r}") from None
    units = declared.sigma_units
    for axis, (s, unit) in enumerate(zip(axes, units)):
        problem = SIGMA_RANGES[unit].problem(s)
        if problem is not None:
            which = (f"axis {axis + 1} of {declared.dim} ({unit}): " if sigma.size == declared.dim > 1
                     else f"as the sigma of its {unit} axes: " if len(set(units)) > 1 else "")
            raise t.error("sigma", which + problem)
    return sigma


def _sigma_factor(t: _Table, kind: str, sigma) -> np.ndarray | None:
    """The sensor's ``sigma_factor``: factors on its messages' standard deviations, as many as its
    kind's ``sigma`` takes, each within :data:`datasets.ranges.RANGES`' ``sensor.sigma_factor``;
    refused beside ``sigma``, which states the sigmas themselves."""
    value = t.get("sigma_factor", (int, float, list), "a factor > 0 or a list of them", default=None)
    if value is None:
        return None
    if sigma is not None:
        raise t.error("sigma_factor", "scales the sigmas the messages carry; with sigma given, write the sigmas "
                                      "themselves")
    items = value if isinstance(value, list) else [value]
    if not items or any(isinstance(x, bool) or not isinstance(x, (int, float)) for x in items):
        raise t.error("sigma_factor", f"expected a factor > 0 or a non-empty list of them, got {value!r}")
    factor = np.array(items, dtype=float)
    try:
        kind_sigmas("sigma_factor", factor, KINDS[kind].dim)
    except InputError:
        raise t.error("sigma_factor", f"a {kind} sensor's sigma_factor is {sigma_counts(KINDS[kind].dim)}, "
                                      f"got {value!r}") from None
    for x in factor:
        t.in_range("sigma_factor", float(x))
    return factor


def sensor_key(index: int, name, key: str | None = None) -> str:
    """How errors name the ``index``-th sensor table (from 1), ``name`` (if a string) and one of
    its keys: ``sensor[2] "gnss".every``."""
    where = f'sensor[{index}] "{name}"' if isinstance(name, str) else f"sensor[{index}]"
    return where if key is None else f"{where}.{key}"


def _sensor(path, folder: Path, index: int, table) -> SensorConfig:
    name = table.get("name") if isinstance(table, dict) else None
    where = sensor_key(index, name)
    t = _Table(path, folder, where, table, SENSOR_KEYS, "sensor")
    name = t.string("name", required=True)
    problem = sensor_name_problem(name)
    if problem is not None:
        raise t.error("name", problem)
    kind = t.string("kind", required=True)
    if kind not in KIND_NAMES:
        close = difflib.get_close_matches(kind, KIND_NAMES, n=1)
        hint = f" (did you mean {close[0]!r}?)" if close else ""
        raise t.error("kind", f"unknown kind {kind!r}{hint}; expected one of {', '.join(KIND_NAMES)}")
    kind = _roll_pitch_only(t, kind)
    source, topic = t.source(None)
    every = t.get("every", (int,), "an integer >= 1", default=1)
    if every < 1:
        raise t.error("every", f"expected an integer >= 1, got {every!r}")
    t.in_range("every", every)
    try:
        robust = robust_spec(t.string("robust"))
    except ValueError as error:
        raise t.error("robust", str(error)) from None
    time_offset = t.number("time_offset", default=0.0)
    sigma = _sigma(t, kind)
    return SensorConfig(name=name, kind=kind, source=source, topic=topic, T_BS=_transform(t),
                        time_offset=time_offset, sigma=sigma, every=every, robust=robust,
                        **_field_angles(t, kind), scale=_scale(t, kind),
                        calibrate=_calibration(t, kind, time_offset), estimate_noise=_estimates_noise(t),
                        sigma_factor=_sigma_factor(t, kind, sigma), **_correlation_time(t, kind, every))


#: The rig's ``correlation_time`` that asks for it to be fitted.
FIT = "fit"


def _correlation_time(t: "_Table", kind: str, every: int) -> dict:
    """The sensor's ``correlation_time`` [s] (None: white) and whether it is to be fitted (the
    value :data:`FIT`, which needs held-out measurements), on the kinds of one state per
    measurement."""
    value = t.table.get("correlation_time")
    fit = value == FIT
    if isinstance(value, str) and not fit:
        raise t.error("correlation_time", f'expected a number of seconds or "{FIT}", got {value!r}')
    tau = None if fit else t.number("correlation_time", positive=True)
    if (tau is not None or fit) and (problem := drift_problem(kind)) is not None:
        raise t.error("correlation_time", problem)
    if fit and every < 2:
        raise t.error("correlation_time", f'"{FIT}" needs held-out measurements to fit it to (every = K > 1): the '
                      "used ones alone hardly tell it")
    return {"correlation_time": tau, "fit_correlation_time": fit}


def _scale(t: "_Table", kind: str) -> float:
    """The sensor's ``scale`` (default 1), on the kinds with scaled readings only."""
    scale = t.number("scale", default=1.0, positive=True)
    if scale != 1.0 and KINDS[kind].scaled_field is None:
        raise t.error("scale", f"a {kind} sensor has no scale (velocity and odometry sensors have)")
    return scale


def _estimates_noise(t: "_Table") -> bool:
    """Whether the sensor's ``estimate = [...]`` names its noise."""
    parts = t.get("estimate", (list,), f"a list of any of {', '.join((*PARTS, NOISE))}", default=None)
    return NOISE in (parts or ())


def _calibration(t: "_Table", kind: str, time_offset: float) -> CalibrationPrior | None:
    """The sensor's ``estimate = [...]`` (any of time_offset, rotation, lever_arm, scale that its
    kind can estimate, beside ``noise``) with the priors' ``<part>_sigma`` keys; None without a
    calibration part (a sigma key without one is refused: it would do nothing)."""
    parts = t.get("estimate", (list,), f"a list of any of {', '.join((*PARTS, NOISE))}", default=None)
    if parts is not None and all(isinstance(part, str) for part in parts):
        if len(set(parts)) != len(parts):
            raise t.error("estimate", f"expected distinct parts of {', '.join((*PARTS, NOISE))}, got {parts!r}")
        parts = None if parts == [NOISE] else [part for part in parts if part != NOISE]
    sigmas = {key: t.number(key, default=None, positive=True) for key in CALIBRATION_KEYS[1:]}
    if parts is None:
        given = [key for key, value in sigmas.items() if value is not None]
        if given:
            raise t.error(given[0], "has no effect without estimate = [...] naming what to estimate")
        return None
    can = applicable(KINDS[kind].model)
    for part in parts:
        if not isinstance(part, str) or part not in PARTS:
            raise t.error("estimate", f"expected a list of any of {', '.join((*PARTS, NOISE))}, got {parts!r}")
        if part not in can:
            raise t.error("estimate", f"a {kind} sensor cannot estimate its {part}; it can estimate {', '.join(can)}")
    if not parts or len(set(parts)) != len(parts):
        raise t.error("estimate", f"expected a non-empty list of distinct parts of {', '.join(PARTS)}, got {parts!r}")
    given = {key.removesuffix("_sigma"): value for key, value in sigmas.items() if value is not None}
    return CalibrationPrior(tuple(parts), **given, stamp_offset=time_offset)


def roll_pitch_kind(kind: str, roll_pitch_only: bool, error) -> str:
    """The kind of a sensor declared ``kind`` with ``roll_pitch_only``: ``roll_pitch`` for an
    ``orientation`` sensor that uses only its roll and pitch. ``roll_pitch_only`` on another kind
    raises ``error(message)`` (an exception naming the key or field)."""
    if not roll_pitch_only:
        return kind
    if kind != "orientation":
        raise error(f"expected only on an orientation sensor; this one is of kind {kind!r}")
    return "roll_pitch"


def _field_angles(t: _Table, kind: str) -> dict:
    """A magnetometer's ``declination`` and ``inclination`` (required, degrees); none for others."""
    if kind != "magnetometer":
        for key in ("declination", "inclination"):
            if key in t.table:
                raise t.error(key, f"expected only on a magnetometer; this sensor is of kind {kind!r}")
        return {}
    angles = {}
    for key in ("declination", "inclination"):
        value = t.number(key)
        if value is None:
            raise t.error(key, f"missing; a magnetometer needs the world field's {key} in degrees "
                               f"({RANGES['sensor.' + key].why})")
        angles[key] = value
    return angles


def _roll_pitch_only(t: _Table, kind: str) -> str:
    value = t.get("roll_pitch_only", (bool,), "true or false", default=False)
    return roll_pitch_kind(kind, value, lambda message: t.error("roll_pitch_only", message))


def load_rig(path) -> Rig:
    """Read and check the rig file ``path`` (see the module docstring); reads no sensor data."""
    path = Path(path)
    try:
        text = read_source(path, "rig").decode("utf-8-sig")  # a byte-order mark (Windows editors) dropped
    except DataError as error:  # missing, not a regular file, too large, unreadable, a NUL in its name
        raise RigError(error.path, None, f"{error.found}; expected {error.expected}") from None
    except UnicodeDecodeError as error:
        raise RigError(path, None, f"not UTF-8 text (byte {error.start})") from None
    try:
        document = tomllib.loads(text)
    except tomllib.TOMLDecodeError as error:
        raise RigError(path, None, f"TOML syntax error: {error}") from None
    except RecursionError:  # the TOML reader parses nested arrays and tables recursively
        raise RigError(path, None, "arrays or tables nested deeper than the TOML reader can follow") from None
    folder = path.absolute().parent
    top = _Table(path, folder, "", document, TOP_KEYS)
    if "imu" not in document:
        raise RigError(path, "imu", "missing; expected an [imu] table")
    imu = _imu(path, folder, document["imu"])
    datum = _datum(path, folder, document["datum"]) if "datum" in document else None
    sensors_table = top.table.get("sensor", [])
    if not isinstance(sensors_table, list):
        raise RigError(path, "sensor", f"expected an array of tables ([[sensor]]), got {_kind(sensors_table)}")
    if len(sensors_table) > MAX_SENSORS:
        raise RigError(path, "sensor", f"{len(sensors_table)} sensors; expected at most {MAX_SENSORS} "
                                       f"({MAX_SENSORS_WHY})")
    sensors = tuple(_sensor(path, folder, i + 1, table) for i, table in enumerate(sensors_table))
    seen: dict = {}
    for i, sensor in enumerate(sensors):
        if sensor.name in seen:
            raise RigError(path, sensor_key(i + 1, sensor.name, "name"),
                           f"a second sensor named {sensor.name!r}; sensor[{seen[sensor.name]}] has that name")
        seen[sensor.name] = i + 1
    _no_measurements_twice(path, sensors)
    return Rig(path=path, imu=imu, datum=datum, sensors=sensors)


def _file_identity(source: str):
    """What tells two sources' files apart: the file's device and inode where it exists (links and
    other spellings of one path are one file), else its path made absolute."""
    file = source.partition(":")[2]
    try:
        st = os.stat(file)
    except (OSError, ValueError):
        return str(Path(file).absolute())
    return st.st_dev, st.st_ino


def _no_measurements_twice(path, sensors: tuple) -> None:
    """No two sensors read the same file and topic as kinds that measure a same field (two of
    one kind, a position and a pose sensor, an orientation and a roll-and-pitch sensor): the same
    measurements used twice count as independent, and every sigma would come out too small by a
    factor of about 1.4 (a rig file of 1 MiB could name one file ten thousand times)."""
    seen: dict = {}
    for i, sensor in enumerate(sensors, start=1):
        key = (_file_identity(sensor.source), sensor.topic)
        fields = set(KINDS[sensor.kind].fields)
        for j, other in seen.get(key, ()):
            shared = fields & set(KINDS[other.kind].fields)
            if shared:
                topic = f", topic {sensor.topic}," if sensor.topic is not None else ""
                raise RigError(path, sensor_key(i, sensor.name, "source"),
                               f"{sensor.source}{topic} is read by sensor[{j}] {other.name!r} ({other.kind}) too, and "
                               f"both measure its {' and '.join(sorted(shared))}: the same measurements used twice "
                               "count as independent ones, and the estimates' sigmas come out too small; use one "
                               "sensor (a pose sensor uses both positions and attitudes)")
        seen.setdefault(key, []).append((i, sensor))
