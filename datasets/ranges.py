"""The plausible range of every number a rig file gives, and the syntax of a sensor's name.

A value outside its range is not a measurement of a real rig but a typing or units mistake
(``1e300``, a density in the wrong unit, a lever arm in millimetres), and one that would surface
later as something else: a singular covariance, a prior the estimators cannot linearise, a run
that "converges" to nonsense. :func:`datasets.rig.load_rig` checks every key against this table
when it reads the file; the command line can check its options against the same ranges.

:data:`RANGES` maps each key, spelled ``<table>.<key>`` as a rig file writes it (``imu.gravity``,
``sensor.time_offset``), to a :class:`Range`: closed bounds, the unit, and why the bounds are
where they are. A sensor's ``sigma`` is in the unit of the residual axis it applies to (metres,
radians, metres per second: each kind declares its axes' units), so its ranges are per unit,
:data:`SIGMA_RANGES`. ``docs/rig.md`` ("Limits") lists them all for users.

Sensor names (:func:`sensor_name_problem`): :data:`SENSOR_NAME_SYNTAX`, not one of
:data:`RESERVED_SENSOR_NAMES`. A name is how ``--robust NAME=KERNEL``, ``metrics.json``'s
``sensors.<name>`` and the tables address a sensor; ``=``, ``:``, ``.``, blanks or a leading
digit break one of them, and ``imu`` and ``prior`` are the names of the IMU's and the initial
prior's own blocks and verdicts.

This module imports nothing of the project: any layer may use it.
"""
from __future__ import annotations

import math
import numbers
import re
from dataclasses import dataclass


@dataclass(frozen=True)
class Range:
    """A closed interval ``[low, high]`` of plausible values, in ``unit``, and ``why`` it is
    that: what real rigs need, and what lies beyond."""

    low: float
    high: float
    unit: str
    why: str

    def __contains__(self, value) -> bool:
        try:
            value = float(value)
        except OverflowError:  # an integer beyond any float
            return False
        return math.isfinite(value) and self.low <= value <= self.high

    def problem(self, value) -> str | None:
        """None when ``value`` lies in the range, else what was expected, for an error naming the
        key: ``expected a value within [9.7, 9.9] m/s^2 (the Earth's gravity, ...), got 1e-300``."""
        if value in self:
            return None
        shown = repr(value) if type(value) is int else repr(float(value))  # not numpy's repr of its scalars
        return f"expected a value within {self.text()} ({self.why}), got {shown}"

    def text(self) -> str:
        """``[1e-06, 1] m/s^2/sqrt(Hz)`` (no unit for a pure number)."""
        bounds = f"[{self.low:g}, {self.high:g}]"
        return f"{bounds} {self.unit}" if self.unit else bounds


#: Every numeric rig key and its plausible range (the module docstring).
RANGES: dict[str, Range] = {
    "imu.accel_noise_density": Range(
        1e-6, 1.0, "m/s^2/sqrt(Hz)",
        "a navigation-grade accelerometer's is ~2e-5, a consumer MEMS part's ~3e-3; room below the one and for "
        "the other inflated a hundredfold by a vehicle's vibration"),
    "imu.gyro_noise_density": Range(
        1e-8, 0.1, "rad/s/sqrt(Hz)",
        "a navigation-grade ring-laser gyro's is ~1.5e-7 (0.0005 deg/sqrt(h)), a consumer MEMS gyro's ~3e-4; "
        "room below the one and for the other inflated a hundredfold"),
    "imu.accel_random_walk": Range(
        1e-9, 1.0, "m/s^3/sqrt(Hz)",
        "a navigation-grade accelerometer's bias drift is ~1e-7, a consumer MEMS part's ~1e-2; room below the "
        "one and for the other inflated a hundredfold"),
    "imu.gyro_random_walk": Range(
        1e-12, 0.1, "rad/s^2/sqrt(Hz)",
        "a navigation-grade gyro's bias drift is ~1e-10 (0.001 deg/h in an hour), a consumer MEMS gyro's ~1e-4; "
        "room below the one and for the other inflated a hundredfold"),
    "imu.gravity": Range(
        9.7, 9.9, "m/s^2",
        "the Earth's gravity: 9.78 on the equator, 9.83 at the poles, 9.74 at an airliner's altitude; the "
        "estimators model the Earth only, and a value far off is a unit mistake (1 for g)"),
    "imu.forward": Range(
        1e-6, 1e6, "",
        "the length of the forward vector: only its direction is used, and a length beyond these is a typing "
        "mistake"),
    "datum.latitude": Range(-90.0, 90.0, "deg", "the globe"),
    "datum.longitude": Range(-180.0, 180.0, "deg", "the globe"),
    "datum.altitude": Range(
        -1000.0, 50_000.0, "m",
        "above the WGS-84 ellipsoid: below the Dead Sea's shore (about -410 m) to above a stratospheric "
        "balloon (40 km)"),
    "sensor.T_BS": Range(
        0.0, 200.0, "m",
        "the length of the lever arm, T_BS's translation: on the largest ships, 400 m long, a sensor is at most "
        "some 200 m from an IMU amidships"),
    "sensor.time_offset": Range(
        -86_400.0, 86_400.0, "s",
        "clocks of one recording differ by milliseconds to seconds (delays, GPS time's leap seconds) or by "
        "whole hours (a time zone); stamps a day apart are in another epoch, to convert in the data"),
    "sensor.correlation_time": Range(
        0.01, 86_400.0, "s",
        "how long a sensor's errors stay alike: a GNSS receiver's multipath and atmosphere drift over seconds "
        "to tens of minutes; shorter than 10 ms is white at any rate a sensor measures, longer than a day an "
        "offset (estimate it, or hold the sensor out)"),
    "sensor.every": Range(
        1, 10_000, "",
        "a 100 Hz source used once in 100 s; beyond, too little is left to estimate with"),
    "sensor.robust": Range(
        0.1, 100.0, "sigma",
        "the kernel's threshold on the whitened residual's norm: below 0.1 every measurement is an outlier, "
        "above 100 none is (that is robust = \"none\")"),
    "sensor.declination": Range(-180.0, 180.0, "deg", "an angle east of true north"),
    "sensor.inclination": Range(-90.0, 90.0, "deg", "an angle below the horizontal"),
    "sensor.scale": Range(
        0.1, 10.0, "",
        "what the sensor reads per unit of the truth: a worn tyre is off by per cents, and km/h (3.6), mph "
        "(2.24) or knots (1.94) read as m/s lie inside; a factor of ten is data in other units"),
    "sensor.sigma_factor": Range(
        0.01, 100.0, "",
        "a factor on the standard deviations the messages carry (a driver's covariance off by tens of times "
        "either way, as the noise fit writes it); a hundredfold is a unit or a model, not a noise: give sigma"),
    "sensor.time_offset_sigma": Range(
        1e-5, 1.0, "s",
        "a hardware-synchronised clock's jitter (10 us) to a software stamp's delay (tenths of a second); an "
        "offset unknown by more than a second is beyond the estimate's linearisation: find it from the stamps "
        "first"),
    "sensor.rotation_sigma": Range(
        1e-5, 1.0, "rad",
        "a calibrated mount (2 arcsec) to one known to tens of degrees; wider is no prior (the rotation's chart "
        "ends at pi) and beyond what the linearised estimate finds: write T_BS closer first"),
    "sensor.lever_arm_sigma": Range(
        1e-4, 10.0, "m",
        "a lever arm measured to 0.1 mm to one guessed to metres; unknown by more than ten metres, it is not "
        "measured at all"),
    "sensor.scale_sigma": Range(
        1e-5, 0.5, "",
        "about a scale of 1: a calibrated odometer's 10 ppm to a scale unknown by half (more is a units "
        "mistake: set scale)"),
}

#: The range of a sensor's ``sigma`` by the unit of its residual axis (a kind's ``sigma_units``).
SIGMA_RANGES: dict[str, Range] = {
    "m": Range(1e-4, 1e4, "m", "motion capture's 0.1 mm to a position that says nothing (10 km)"),
    "rad": Range(1e-6, math.pi, "rad", "finer than a star tracker's arcsecond (5e-6) to pi, where a rotation's chart "
                                       "ends"),
    "m/s": Range(1e-4, 100.0, "m/s", "a Doppler log's 0.1 mm/s to a velocity that says nothing (100 m/s)"),
}

#: The most ``[[sensor]]`` tables a rig file may have, and why. Every stage of a run costs time in
#: proportion to the sensors (``docs/rig.md``, Limits: a thousand take some 25 s over a minute of
#: data); ten thousand took 276 s on 20 s of data, and a rig file of 1 MiB holds that many.
MAX_SENSORS = 1000
MAX_SENSORS_WHY = ("a real rig has tens of sensors, a test rig of simulated ones a thousand; every stage of a run "
                   "costs time in proportion to them, and ten thousand took minutes on seconds of data")

#: What a sensor's name must match (whole): a letter, then letters, digits, ``_`` or ``-``; at
#: most 64 characters.
SENSOR_NAME_SYNTAX = re.compile(r"[A-Za-z][A-Za-z0-9_-]{0,63}")
#: Names the outputs already give the estimators' own blocks: the IMU's (its verdict in
#: ``metrics.json``) and the initial state's prior.
RESERVED_SENSOR_NAMES = ("imu", "prior")


def out_of_range(key: str, value) -> str | None:
    """:meth:`Range.problem` of ``value`` for the rig key ``key`` of :data:`RANGES`."""
    return RANGES[key].problem(value)


def correlation_time_problem(tau) -> str | None:
    """None for a usable ``correlation_time`` [s] of a sensor's drifting errors (a number within
    ``RANGES["sensor.correlation_time"]``), else what is wrong with it; whether the sensor's kind can
    drift is the kind's to say (:func:`datasets.kinds.drift_problem`)."""
    if isinstance(tau, bool) or not isinstance(tau, numbers.Real):
        return f"expected a number of seconds, got {tau!r}"
    return out_of_range("sensor.correlation_time", tau)


def sensor_name_problem(name) -> str | None:
    """None for a usable sensor name (module docstring), else what is wrong with it."""
    if not isinstance(name, str) or not SENSOR_NAME_SYNTAX.fullmatch(name):
        return (f"expected a name of a letter followed by letters, digits, _ or - (at most 64 characters; "
                f"--robust NAME=KERNEL and metrics.json address a sensor by it), got {name!r}")
    if name in RESERVED_SENSOR_NAMES:
        return (f"the name {name!r} is reserved: the outputs give it to the "
                f"{'IMU (its verdict in metrics.json)' if name == 'imu' else 'initial state prior'}; reserved are "
                f"{', '.join(RESERVED_SENSOR_NAMES)}")
    return None
