"""Noise identification: the IMU noise densities under which the measurements are most probable.

The EKF's prediction-error decomposition gives the log-likelihood of the measurements under the
model, ``log p(z_1..z_n) = sum_k log N(e_k; 0, S_k)`` over its innovations ``e_k`` with
covariances ``S_k = H P H^T + R`` (:attr:`smoother.ekf.filter.FilterResult.log_likelihood`). Scaling the
four IMU densities -- accelerometer and gyro white noise, accelerometer and gyro bias random walk
-- by factors ``10^x`` and maximising that likelihood over ``x`` is maximum-likelihood
identification of the process noise. It uses the measurements the estimators use and nothing
else: no truth and no held-out data. (The likelihood is that of the linearised filter, so it is an
approximation where the EKF's linearisation is poor.)

Search: a pattern search on ``x`` (four log10 factors, starting at 0 = the dataset's densities):
try ``x_i +- step`` for each density in turn, move to the first significant improvement, halve
``step`` when none improves, stop below ``min_step``; each ``x_i`` stays within
``[-max_log10, max_log10]``. A move must raise the log-likelihood by at least ``min_gain``
(default 1.92, the likelihood-ratio test of one parameter at the 5% level): where the data
cannot tell (a bias walk over a short run is typical) the density stays at the dataset's value
instead of drifting to a bound on noise-level differences. A run whose filter diverges counts as
impossible (likelihood ``-inf``). Densities that are zero (e.g. a bias walk a dataset leaves out)
stay zero. The EKF runs without a gate, so every measurement counts.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, replace

import numpy as np

from datasets.kinds import KINDS, sensors_of
from datasets.types import Dataset
from factors.imu import ImuNoise
from smoother.ekf.filter import FilterDiverged, run_ekf
from smoother.progress import progress_bar
from factors.errors import InputError

#: The :class:`factors.imu.ImuNoise` densities that are scaled, in search order.
TUNED = ("acc", "gyro", "acc_bias", "gyro_bias")


@dataclass
class NoiseTuning:
    """The tuned dataset's noise, its log10 factors relative to the original densities, and the
    log-likelihood before and after (``evaluations`` EKF runs)."""

    noise: ImuNoise
    log10_scale: dict
    log_likelihood: float
    initial_log_likelihood: float
    evaluations: int

    def summary(self) -> dict:
        """The JSON-friendly record written into ``metrics.json``."""
        return {
            "scale": {k: 10.0**v for k, v in self.log10_scale.items()},
            "densities": {k: getattr(self.noise, k) for k in TUNED},
            "log_likelihood": self.log_likelihood,
            "initial_log_likelihood": self.initial_log_likelihood,
            "evaluations": self.evaluations,
        }


#: Smallest log-likelihood gain that moves the search (chi-square(1) 95% quantile / 2).
MIN_GAIN = 1.92


def tune_noise(dataset: Dataset, step: float = 1.0, min_step: float = 0.25, max_log10: float = 3.0,
               min_gain: float = MIN_GAIN, progress: bool | None = None) -> NoiseTuning:
    """Maximum-likelihood factors of the IMU noise densities of ``dataset`` (module docstring)."""
    if all(KINDS[s.kind].relative for s in sensors_of(dataset)):
        raise InputError("noise tuning needs measurements the EKF uses (pose, position, GNSS, orientation or "
                         "velocity): the likelihood is that of the measurements, and this dataset has none")
    if not (0 < min_step <= step and max_log10 > 0):
        raise InputError(f"tune_noise: expected 0 < min_step <= step and max_log10 > 0, got step={step}, "
                         f"min_step={min_step}, max_log10={max_log10}")
    base = dataset.noise
    active = [name for name in TUNED if getattr(base, name) > 0]
    seen: dict = {}

    def noise_at(x: np.ndarray):
        return replace(base, **{name: getattr(base, name) * 10.0**xi for name, xi in zip(active, x)})

    def log_likelihood(x: np.ndarray) -> float:
        key = tuple(np.round(x, 9))
        if key not in seen:
            try:
                value = run_ekf(replace(dataset, noise=noise_at(x)), progress=False).log_likelihood
            except FilterDiverged:
                value = -math.inf
            seen[key] = value if math.isfinite(value) else -math.inf
            bar.update(1)
        return seen[key]

    x = np.zeros(len(active))
    with progress_bar(None, "noise tuning", progress) as bar:
        best = initial = log_likelihood(x)
        while step >= min_step:
            moved = False
            for i in range(len(active)):
                for sign in (1.0, -1.0):
                    trial = x.copy()
                    trial[i] = np.clip(trial[i] + sign * step, -max_log10, max_log10)
                    value = log_likelihood(trial)
                    if value > best + min_gain:
                        x, best, moved = trial, value, True
                        break
            if not moved:
                step /= 2.0
    if not math.isfinite(best):
        raise FilterDiverged("noise tuning: the EKF diverged at every noise level tried; the data or its "
                             "initial state is inconsistent with the model")
    return NoiseTuning(noise_at(x), {name: float(xi) for name, xi in zip(active, x)}, best, initial, len(seen))
