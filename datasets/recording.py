"""A recording described by a rig file, as a :class:`datasets.types.Dataset`.

:func:`load_recording` reads the IMU and every sensor of a :class:`datasets.rig.Rig`
(:mod:`datasets.sources`), turns each stream into its kind's measurements
(:data:`datasets.kinds.KINDS`) with the sensor's extrinsic, and finds the initial state from the
data (:mod:`datasets.initialise`); no ground truth is needed.

* **Clock**: stamps are the data's own (bag header stamps, seconds since the epoch; CSV files'
  nanoseconds). Inside, times count from the first IMU stamp (``Dataset.time_origin_ns``), so
  float64 keeps sub-microsecond steps; outputs are written in the data's clock again. A sensor's
  ``time_offset`` is added to its stamps first.
* **Streams per kind**: each kind reads its sensors (:attr:`datasets.kinds.base.Kind.read`):
  ``pose`` poses, ``position`` positions (of poses, or a file of positions alone),
  ``orientation`` attitudes (of an AHRS, of poses, or a file of attitudes alone), ``odometry``
  consecutive poses as relative poses in the earlier pose's frame, ``velocity`` twists (their
  linear part, the sensor frame's velocity in its own frame), ``gnss`` fixes, in the local ENU
  frame about the rig's datum (default: the first valid fix), fixes without a position dropped
  and counted.
* **The IMU first**: its rates and ranges are checked (:func:`datasets.types.check_imu_rates`,
  :func:`datasets.types.check_imu_range`) before any sensor is read: a velocity sensor's rows
  carry the IMU's gyro for its lever arm, and an IMU in deg/s would otherwise be reported as that
  sensor's fault.
* **Noise**: a sensor's ``sigma`` overrides; otherwise the messages' covariances where every
  message has one (:func:`datasets.kinds.base.noise`; ``odometry`` always needs ``sigma``).
* **every = k**: measurements ``0, k, 2k, ...`` are used; the others are held out for evaluation
  (``Sensor.heldout``; for positions and GNSS the held-out error of ``metrics.json``). When the
  start cannot be found from the measurements used but can from all of one sensor's, the error
  is a :class:`~datasets.rig.RigError` naming that sensor's ``every``.
* **Gravity**: ``(0, 0, -g)`` in the world frame (z up; ENU with GNSS).
* **A part of it** (``part = (start, end)``, seconds after the first IMU sample; either None for
  that end of the recording): the IMU samples and the measurements (used and held out; a relative
  one with both ends) inside it, read and split by ``every`` as the whole recording is (the GNSS
  datum and the held-out measurements are the whole recording's), then self-initialised there --
  as a robot started at ``start`` would be. Fitting a rig's calibration and noise on one part and
  checking the ``calibrated.toml`` on another is the test that the fit holds beyond the data it
  was fitted to. A sensor none of whose used measurements lies in the part is left out, and said
  so; a part that holds none of any sensor's, or from which the start cannot be found, is a
  :class:`PartError` naming it.
"""
from __future__ import annotations

import warnings
from dataclasses import dataclass, replace
from os import PathLike

import numpy as np

from datasets.gnss import Datum
from datasets.initialise import InitialisationError, imu_from, initial_state
from datasets.kinds import KINDS, Clock
from datasets.rig import Rig, RigError, sensor_key
from datasets.sources import read_imu
from datasets.types import Dataset, ImuSamples, Sensor, check_imu_range, check_imu_rates
from factors.errors import InputError


@dataclass(frozen=True, eq=False)
class RecordedDataset(Dataset):
    """A :class:`Dataset` read through a rig file: also its ``datum`` (None without GNSS), the
    local ENU frame's origin, with which outputs are also given in latitude and longitude."""

    datum: Datum | None = None


def _relative(t: np.ndarray, t_ns, origin_ns: int, offset: float) -> np.ndarray:
    """Stamps as seconds since ``origin_ns`` plus ``offset`` (exact from integer nanoseconds where
    the source has them)."""
    if t_ns is not None:
        return (np.asarray(t_ns, dtype=np.int64) - origin_ns) * 1e-9 + offset
    return np.asarray(t, dtype=float) - origin_ns * 1e-9 + offset


def _check_overlap(name: str, data, imu: ImuSamples, origin_ns: int) -> None:
    """A sensor none of whose measurements lies in the IMU's span is an error naming both spans in
    the data's clock (another clock, or a wrong time offset, is the usual cause)."""
    if len(data) == 0:
        raise InputError(f"sensor {name!r}: its source holds no measurement")
    first = getattr(data, "t_from", data.t)
    if np.any((first >= imu.t[0]) & (data.t <= imu.t[-1])):
        return
    clock = origin_ns * 1e-9
    raise InputError(f"sensor {name!r}: none of its {len(data)} measurements ([{clock + first.min():.3f}, "
                     f"{clock + data.t.max():.3f}] s, time offset included) lies in the IMU's span "
                     f"[{clock + imu.t[0]:.3f}, {clock + imu.t[-1]:.3f}] s: stamps in another clock, or a wrong "
                     "time_offset?")


class PartError(InputError):
    """The part of the recording asked for (:func:`load_recording`'s ``part``) holds no data to
    estimate from."""


def _inside(data, t0: float, t1: float):
    """The rows of ``data`` (or None) with their times (both ends of a relative one) in ``[t0, t1]``;
    None where none are."""
    if data is None:
        return None
    keep = (getattr(data, "t_from", data.t) >= t0) & (data.t <= t1)
    return data if keep.all() else (data.subset(keep) if keep.any() else None)


def _described(part) -> str:
    """``part = (start, end)`` as the user asked for it: ``"the part 10-20 s"``, ``"the part from 10
    s on"``, ``"the part up to 20 s"``."""
    start, end = part
    if start is None and end is None:
        return "the whole recording"
    if start is None:
        return f"the part up to {end:g} s"
    return f"the part from {start:g} s on" if end is None else f"the part {start:g}-{end:g} s"


def _part(imu: ImuSamples, sensors: list[Sensor], whole: list, part, origin_ns: int) -> tuple:
    """``(imu, sensors, whole)`` within ``part = (start, end)`` seconds after the first IMU sample
    (module docstring); a sensor none of whose used measurements lies there is left out, with a
    warning naming it (and how many of its held-out ones there go unscored). A :class:`PartError`
    where the part holds fewer than two IMU samples, or no used measurement of any sensor."""
    start, end = (imu.t[0] if part[0] is None else part[0]), (imu.t[-1] if part[1] is None else part[1])
    a, b = int(np.searchsorted(imu.t, start, side="left")), int(np.searchsorted(imu.t, end, side="right"))
    if b - a < 2:
        raise PartError(f"{_described(part)} holds {max(b - a, 0)} IMU samples, at least 2 needed: the "
                        f"recording's IMU runs from 0 to {imu.t[-1]:.3f} s after its first sample (to "
                        f"{(origin_ns * 1e-9 + imu.t[-1]):.3f} s in its clock)")
    imu = imu.slice(a, b)
    t0, t1 = imu.t[0], imu.t[-1]
    kept, left = [], []
    for sensor, data in zip(sensors, whole):
        used, heldout = _inside(sensor.data, t0, t1), _inside(sensor.heldout, t0, t1)
        if used is None:
            left.append(repr(sensor.name) + ("" if heldout is None else
                                             f" (its {len(heldout)} held-out measurements there not scored)"))
            continue
        kept.append((replace(sensor, data=used, heldout=heldout), _inside(data, t0, t1)))
    where = f"{_described(part)} ({t0:.3f}-{t1:.3f} s after the recording's first IMU sample)"
    if sensors and not kept:
        raise PartError(f"{where} holds none of the measurements the sensors use (their `every`); a longer part, or "
                        "a smaller every")
    if left:
        warnings.warn(f"none of the measurements used of {', '.join(left)} lies in {where}: left out", stacklevel=3)
    return imu, [s for s, _ in kept], [w for _, w in kept]


def _split_every(data, every: int):
    """``(used, held out)``: rows ``0, every, 2 every, ...`` and the rest (None if none)."""
    if every == 1:
        return data, None
    used = np.arange(len(data)) % every == 0
    return data.subset(used), (data.subset(~used) if (~used).any() else None)


def _every_is_why(rig: Rig, error: InitialisationError, sensors: list[Sensor], whole: list, start,
                  part: tuple | None = None) -> ValueError:
    """The error to give when ``start`` (the initialisation, on a list of sensors) failed with
    ``error``: if using all of one sensor's measurements, not only every k-th, lets it succeed,
    a :class:`~datasets.rig.RigError` naming that sensor's ``every`` key, how many measurements
    it leaves and how many there are (in the ``part`` of the recording run, when one is); else
    ``error`` itself."""
    numbered = {config.name: (index, config) for index, config in enumerate(rig.sensors)}
    for position, (sensor, data) in enumerate(zip(sensors, whole)):
        index, config = numbered[sensor.name]
        if config.every == 1:
            continue
        trial = list(sensors)
        trial[position] = Sensor(sensor.name, sensor.kind, data, None)
        try:
            start(trial)
        except InitialisationError:
            continue
        failed = str(error).split(":")[0]  # "cannot fix the initial heading"
        need = failed[len("cannot "):] if failed.startswith("cannot ") else "start the estimate"
        within = "" if part is None else f" in {_described(part)}"
        return RigError(rig.path, sensor_key(index + 1, config.name, "every"),
                        f"{config.every} leaves {len(sensor.data)} of the sensor's {len(data)} measurements{within} "
                        f"for estimation: too few to {need}, which all {len(data)} would; use a smaller every (the "
                        "measurements between those used are held out)")
    return error


def _from(sensors: list[Sensor], t_s: float) -> list[Sensor]:
    """The sensors' measurements from the start time on (the estimate starts at the first position
    fix); how many earlier ones are left out is said once."""
    out, left = [], {}
    for s in sensors:
        parts = []
        for m in (s.data, s.heldout):
            keep = None if m is None else getattr(m, "t_from", m.t) >= t_s
            if m is not None and not keep.all():
                left[s.name] = left.get(s.name, 0) + int((~keep).sum())
            parts.append(None if m is None or not keep.any() else (m if keep.all() else m.subset(keep)))
        if parts[0] is not None:  # a sensor with nothing left is dropped (counted above)
            out.append(replace(s, data=parts[0], heldout=parts[1]))
    if left:
        counts = ", ".join(f"{n} of {name!r}" for name, n in left.items())
        warnings.warn(f"the estimate starts at the first position fix, {t_s:.3f} s after the first IMU sample; "
                      f"the measurements before it are not used ({counts})", stacklevel=3)
    return out


def load_recording(rig: Rig, bias_sigma=(0.1, 0.01), part: tuple | None = None) -> RecordedDataset:
    """The recording of ``rig`` (module docstring), self-initialised; with ``part = (start, end)``,
    that part of it alone (seconds after the first IMU sample, either None for that end). Errors
    name the sensor (and through the readers the file, topic, line or field).

    ``rig`` is a :class:`~datasets.rig.Rig` as :func:`datasets.rig.load_rig` returns it, not the
    path of a rig file: ``load_recording(load_rig("rig.toml"))``. Anything else is an InputError
    saying so (the rig file is read and checked once, where its errors are named)."""
    if not isinstance(rig, Rig):
        shown = f" {str(rig)!r}" if isinstance(rig, (str, PathLike)) else ""
        raise InputError(f"load_recording: expected a Rig, got a {type(rig).__name__}{shown}; read a rig file first "
                         "with datasets.load_rig(path), then load_recording(rig)")
    imu = read_imu(rig.imu.source, rig.imu.topic)
    # the IMU's own units first: a velocity sensor's rows carry its gyro, and would be blamed for them
    stream = f"{rig.imu.source}{'' if rig.imu.topic is None else ', topic ' + rig.imu.topic}"
    where = f"imu ({stream}): "
    check_imu_rates(where, imu.gyro)
    check_imu_range(where, imu.t, imu.acc, imu.gyro)
    origin_ns = int(imu.t_ns[0]) if imu.t_ns is not None else int(round(float(imu.t[0]) * 1e9))
    imu = ImuSamples(_relative(imu.t, imu.t_ns, origin_ns, 0.0), imu.acc, imu.gyro, imu.t_ns)

    def gyro_at(t):  # the gyro sample held at each time (the lever arm's rate of a velocity sensor)
        return imu.gyro[imu.held(t)]

    gyro_variance = rig.imu.noise.gyro**2 / float(np.median(np.diff(imu.t)))
    clock = Clock(lambda t, t_ns, offset: _relative(t, t_ns, origin_ns, offset), gyro_at, gyro_variance, rig.datum)
    sensors, whole = [], []  # each sensor's measurements split by its `every`, and all of them
    for config in rig.sensors:
        try:
            data, clock.datum = KINDS[config.kind].read(config, clock)
            data = KINDS[config.kind].unscaled(data, config.scale)
        except ValueError as error:  # a reader's DataError names its file; say which sensor it was
            message = str(error)
            raise InputError(message if message.startswith("sensor ") else
                             f"sensor {config.name!r} ({config.kind}): {message}") from error
        _check_overlap(config.name, data, imu, origin_ns)
        used, heldout = _split_every(data, config.every)
        # a bag topic is one message stream: a sensor_msgs/Imu carries the samples and its filter's orientation
        shared = config.topic is not None and (config.source, config.topic) == (rig.imu.source, rig.imu.topic)
        sensors.append(Sensor(config.name, config.kind, used, heldout, config.calibrate, config.estimate_noise,
                              stream if shared else None, config.correlation_time, config.fit_correlation_time))
        whole.append(data)
    if part is not None:
        imu, sensors, whole = _part(imu, sensors, whole, part, origin_ns)
    gravity = np.array([0.0, 0.0, -rig.imu.gravity])
    try:
        t_s, state, cov = initial_state(imu, sensors, gravity, bias_sigma, rig.imu.forward)
    except InitialisationError as error:
        why = _every_is_why(rig, error, sensors, whole, lambda s: initial_state(imu, s, gravity, bias_sigma,
                                                                                 rig.imu.forward), part)
        raise (PartError(f"{_described(part)}: {why}") if part is not None and why is error else why) from None
    sensors = _from(sensors, t_s)
    return RecordedDataset(name=rig.path.stem, imu=imu_from(imu, t_s), noise=rig.imu.noise, initial=state,
                           initial_cov=cov, gravity=gravity, sensors=tuple(sensors), time_origin_ns=origin_ns,
                           estimate_imu_noise=rig.imu.estimate_noise, datum=clock.datum)
