"""Simulated sensors of any kind, mounted anywhere on the body, drawn from a ground truth.

Each :class:`SensorSpec` names a kind of :data:`datasets.kinds.KINDS`, a rate, a noise and an
extrinsic; :func:`sensors_from_truth` draws its measurements with the kind's own stream
(:attr:`datasets.kinds.base.Kind.simulate`) at truth samples (:func:`datasets.from_truth.
measurement_indices`), each sensor with a noise stream of its own.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from datasets.from_truth import measurement_indices
from datasets.kinds import KINDS, kind_sigmas
from datasets.kinds.base import ImuAt
from datasets.types import ImuSamples, Sensor, Trajectory
from factors.errors import InputError


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


def sensors_from_truth(truth: Trajectory, imu: ImuSamples, specs, seed=0, true_rate=None,
                       gyro_density: float = 0.0) -> tuple[Sensor, ...]:
    """The measurements of each simulated sensor in ``specs`` (:class:`SensorSpec`) drawn from
    ``truth`` by its kind's stream (:attr:`datasets.kinds.Kind.simulate`), at truth samples as
    :func:`measurement_indices` picks them, each sensor with its own noise stream spawned from
    ``seed`` (an integer or a ``numpy.random.SeedSequence``). ``imu`` gives the gyro readings a
    velocity sensor keeps (the sample held at each measurement time), ``true_rate`` (the body
    rates at the IMU's times; default the readings minus the true bias) the motion it measures,
    ``gyro_density`` [rad/s/sqrt(Hz)] the readings' white noise its covariance accounts for."""
    specs = list(specs)
    root = seed if isinstance(seed, np.random.SeedSequence) else np.random.SeedSequence(seed)
    streams = root.spawn(len(specs))
    out = []
    for spec, stream in zip(specs, streams):
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
