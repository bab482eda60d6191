"""Allan deviation of a static IMU recording, and the four noise densities fitted to it.

The overlapping Allan variance of a signal ``x`` sampled every ``dt`` at cluster time
``tau = m dt`` is ``AVAR(tau) = < (theta[k + 2m] - 2 theta[k + m] + theta[k])^2 > / (2 tau^2)`` over
every start ``k``, with ``theta`` the running integral of ``x`` (one cumulative sum, so each
``tau`` costs one vectorised pass). Cluster sizes ``m`` are log-spaced from 1 to a quarter of the
recording (:data:`POINTS` of them at most).

On a log-log plot, white noise of density ``N`` gives the line ``ADEV = N / sqrt(tau)`` (slope
-1/2) and a random walk of density ``K`` the line ``ADEV = K sqrt(tau / 3)`` (slope +1/2), so
``N`` is the -1/2 line's value at ``tau = 1 s`` and ``K`` the +1/2 line's value at ``tau = 3 s``
(the reading Kalibr's documentation and allan_variance_ros use). Each line is placed through the
curve where its local slope (between neighbouring points) matches: left of the curve's minimum
for the white noise, right of it for the random walk, at the first such point (the smallest
``tau``: the most clusters, the least scatter) whose slope is within :data:`SLOPE_TOLERANCE` of the
line's; for the white noise else at the point whose slope is closest.

What the data support: at cluster time ``tau`` a recording of length ``T`` holds ``K = T / tau``
independent clusters, and the Allan deviation there is uncertain by about ``1 / sqrt(2 (K - 1))``.
Both lines are placed only where ``K >= MIN_CLUSTERS`` (``tau <= T / 10``: 24 %). A random walk
shows as the +1/2 slope right of the minimum; for white noise plus a random walk the slope comes
within :data:`SLOPE_TOLERANCE` of +1/2 at :data:`WALK_ONSET` times the minimum's ``tau``. Where the
supported part of the curve has no such slope the random walk is not estimated (NaN), and
:attr:`AllanResult.walk_record_s` says how long a recording would need to be to show it: at least
``MIN_CLUSTERS * WALK_ONSET`` times the ``tau`` of the supported curve's minimum (a lower bound
when the curve still falls there).

Units: accelerometer ``N`` in m/s^2/sqrt(Hz) and ``K`` in m/s^3/sqrt(Hz); gyro ``N`` in
rad/s/sqrt(Hz) and ``K`` in rad/s^2/sqrt(Hz): continuous-time densities as Kalibr's ``imu.yaml``
and :class:`factors.imu.ImuNoise` hold them. The samples are taken as evenly spaced at the median
step. The recording must be static (the IMU at rest, ideally for hours: the random-walk line needs
cluster times well beyond the curve's minimum); what it measures are the sensor's densities, which
are commonly inflated for estimation to cover unmodelled effects.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from datasets.types import ImuSamples
from factors.errors import InputError
from factors.imu import ImuNoise

#: Largest number of cluster times.
POINTS = 100
#: How close a local slope must be to a line's (-1/2 or +1/2) to place the line there.
SLOPE_TOLERANCE = 0.1
#: Where the white-noise and random-walk lines are read [s].
WHITE_TAU, WALK_TAU = 1.0, 3.0
#: Fewest independent clusters at a cluster time for a line to be placed there (module docstring).
MIN_CLUSTERS = 10
#: How many times the minimum's cluster time white noise plus a random walk needs for its local
#: slope, ``(r - 1) / (2 (r + 1))`` with ``r = (tau / tau_min)^2``, to come within
#: :data:`SLOPE_TOLERANCE` of +1/2 (3 for a tolerance of 0.1).
WALK_ONSET = float(np.sqrt((2.0 - 2.0 * SLOPE_TOLERANCE) / (2.0 * SLOPE_TOLERANCE)))


def allan_deviation(x, dt: float, points: int = POINTS) -> tuple[np.ndarray, np.ndarray]:
    """Overlapping Allan deviation of the columns of ``x`` (N,) or (N, k) sampled every ``dt``
    [s]: ``(tau (M,), adev (M,) or (M, k))``."""
    x = np.asarray(x, dtype=float)
    n = len(x)
    if n < 4:
        raise InputError(f"Allan deviation: expected at least 4 samples, got {n}")
    theta = np.concatenate([np.zeros((1,) + x.shape[1:]), np.cumsum(x, axis=0)]) * dt
    m = np.unique(np.floor(np.logspace(0, np.log10(max(n // 4, 1)), points)).astype(np.int64))
    adev = np.empty((len(m),) + x.shape[1:])
    for j, size in enumerate(m):
        d = theta[2 * size:] - 2 * theta[size:-size] + theta[: -2 * size]
        adev[j] = np.sqrt(np.mean(d**2, axis=0) / (2 * (size * dt) ** 2))
    return m * dt, adev


def fit_line(tau: np.ndarray, adev: np.ndarray, slope: float) -> float | None:
    """The offset ``c`` of the line ``log10 ADEV = slope log10 tau + c`` placed on the curve as
    the module docstring says (``slope`` -1/2: left of the minimum; +1/2: right of it, None when
    no local slope there is within :data:`SLOPE_TOLERANCE` of it)."""
    lt, la = np.log10(tau), np.log10(adev)
    local = np.diff(la) / np.diff(lt)
    index = np.arange(len(local))
    lowest = int(np.argmin(la))
    region = index[index < lowest] if slope < 0 else index[index >= lowest]
    if region.size == 0:
        if slope > 0:
            return None
        region = index
    error = np.abs(local[region] - slope)
    close = np.flatnonzero(error <= SLOPE_TOLERANCE)
    if not close.size and slope > 0:
        return None
    i = region[close[0]] if close.size else region[np.argmin(error)]
    return 0.5 * (la[i] + la[i + 1]) - slope * 0.5 * (lt[i] + lt[i + 1])


def supported(tau: np.ndarray, record_s: float) -> np.ndarray:
    """Which cluster times a recording of ``record_s`` seconds holds at least
    :data:`MIN_CLUSTERS` independent clusters of."""
    return record_s / tau >= MIN_CLUSTERS


def densities(tau: np.ndarray, adev: np.ndarray, record_s: float) -> tuple[float, float, float, bool]:
    """``(white-noise density N, random-walk density K, record, beyond)`` of one Allan-deviation
    curve of a recording of ``record_s`` seconds, the lines placed on its :func:`supported` part.
    ``K`` is NaN where no random walk shows there; ``record`` is then the recording length [s]
    that would show it at least (module docstring; NaN when ``K`` was estimated), and ``beyond``
    says that the supported curve still falls at its end, so that its minimum lies further out."""
    keep = supported(tau, record_s)
    tau, adev = tau[keep], adev[keep]
    white = 10 ** (-0.5 * np.log10(WHITE_TAU) + fit_line(tau, adev, -0.5))
    offset = fit_line(tau, adev, 0.5)
    if offset is None:
        lowest = int(np.argmin(adev))
        return float(white), math.nan, MIN_CLUSTERS * WALK_ONSET * float(tau[lowest]), lowest == len(tau) - 1
    return float(white), float(10 ** (0.5 * np.log10(WALK_TAU) + offset)), math.nan, False


@dataclass(frozen=True)
class AllanResult:
    """Allan deviations and fitted densities of a static IMU recording, per axis: ``tau`` (M,)
    [s], ``acc_adev``, ``gyro_adev`` (M, 3), and ``acc_white``, ``acc_walk``, ``gyro_white``,
    ``gyro_walk`` (3,) (units in the module docstring; a random walk the data do not show is
    NaN); ``dt`` the sample period used, ``record_s`` the recording's length and ``walk_record_s``
    the length [s] a recording would need at least to show every axis's random walk (None when
    all were estimated), ``walk_beyond`` whether that is a lower bound only (the curve of the axis
    that needs it longest still falls where the data end)."""

    tau: np.ndarray
    acc_adev: np.ndarray
    gyro_adev: np.ndarray
    acc_white: np.ndarray
    acc_walk: np.ndarray
    gyro_white: np.ndarray
    gyro_walk: np.ndarray
    dt: float
    record_s: float
    walk_record_s: float | None = None
    walk_beyond: bool = False
    #: The axes whose every sample is the same (``"accelerometer x"``, ...): no density can be read
    #: from them (their densities are NaN).
    still: tuple = ()

    def largest(self) -> dict:
        """The densities for a rig file by :class:`ImuNoise` field, the largest of the three axes
        for each (NaN for a random walk not estimated on some axis: its largest is unknown)."""
        return {"acc": float(self.acc_white.max()), "gyro": float(self.gyro_white.max()),
                "acc_bias": float(self.acc_walk.max()), "gyro_bias": float(self.gyro_walk.max())}

    def noise(self) -> ImuNoise:
        """:meth:`largest` as an :class:`ImuNoise`; an ``InputError`` saying what is missing when a
        random walk was not estimated."""
        if self.walk_record_s is not None:
            raise InputError(self.walk_note())
        return ImuNoise(**self.largest())

    def still_note(self) -> str | None:
        """What the axes that do not vary say, or None when every axis varies."""
        if not self.still:
            return None
        return (f"{', '.join(self.still)} read the same value in every sample: a stuck axis, or readings written "
                "rounded coarser than the noise; no density can be read from them")

    def walk_note(self) -> str | None:
        """Why random walks were not estimated and how long a recording they need; None when all were."""
        if self.walk_record_s is None:
            return None
        axes = [f"{sensor} {axis}" for sensor, walk in (("accelerometer", self.acc_walk), ("gyro", self.gyro_walk))
                for axis, value in zip("xyz", walk) if np.isnan(value) and f"{sensor} {axis}" not in self.still]
        reach = self.record_s / MIN_CLUSTERS
        return (f"random walk not estimated ({', '.join(axes)}): {self.record_s:.4g} s of data hold "
                f"{MIN_CLUSTERS} independent clusters up to a cluster time of {reach:.3g} s, and up to there the "
                f"Allan deviation does not rise with slope +1/2; a random walk shows from {WALK_ONSET:.3g} times "
                f"the curve's minimum on: record at least {self.walk_record_s:.4g} s at rest"
                + (" (a lower bound: the curve still falls where the data end, its minimum lies further out; "
                   "IMUs are commonly recorded for hours)" if self.walk_beyond else ""))


#: The most the recording's span may differ from its samples at the median step, and the most
#: the 90th percentile of the steps may exceed the 10th, as a ratio (:func:`evenly_spaced`).
SPAN_TOLERANCE, STEP_SPREAD = 0.1, 2.0
AXES = tuple(f"{sensor} {axis}" for sensor in ("accelerometer", "gyro") for axis in "xyz")


def evenly_spaced(t: np.ndarray) -> str | None:
    """None when the stamps ``t`` are evenly spaced as the Allan deviation takes them (jitter of a
    few tens of per cent is), else what is wrong: gaps that hold more than :data:`SPAN_TOLERANCE`
    of the span (dropped samples, pauses), or steps spread beyond :data:`STEP_SPREAD` (stamps of
    a software clock, a varying rate)."""
    steps = np.diff(t)
    dt = float(np.median(steps))
    span, even = float(t[-1] - t[0]), (len(t) - 1) * dt
    if abs(span - even) > SPAN_TOLERANCE * even:
        return (f"{len(t)} samples at the median step of {dt:.4g} s would span {even:.4g} s, the stamps span "
                f"{span:.4g} s (gaps, or a varying rate)")
    low, high = np.percentile(steps, [10, 90])
    if high > STEP_SPREAD * low:
        return f"the steps between samples range from {low:.4g} s to {high:.4g} s (10th to 90th percentile)"
    return None


def allan(imu: ImuSamples, points: int = POINTS) -> AllanResult:
    """Allan deviations of every accelerometer and gyro axis of ``imu`` and their densities. An
    InputError when the samples are not evenly spaced (:func:`evenly_spaced`: the deviation's
    cluster times would be wrong, and so every density); an axis whose samples are all one value
    has NaN densities (:attr:`AllanResult.still`: a curve of zeros has no line to fit)."""
    dt = float(np.median(np.diff(imu.t))) if len(imu) > 1 else 0.0
    if not dt > 0:
        raise InputError("Allan deviation: expected at least two IMU samples")
    uneven = evenly_spaced(imu.t)
    if uneven is not None:
        raise InputError(f"Allan deviation: expected evenly spaced samples; {uneven}")
    x = np.concatenate([imu.acc, imu.gyro], axis=1)
    tau, adev = allan_deviation(x, dt, points)
    record_s = len(imu) * dt
    if supported(tau, record_s).sum() < 3:
        raise InputError(f"Allan deviation: {len(imu)} IMU samples give too few cluster times with {MIN_CLUSTERS} "
                         f"independent clusters each; record at least {3 * MIN_CLUSTERS} samples, far more for the "
                         "random walk")
    still = np.all(x == x[0], axis=0)
    fitted = np.array([(math.nan, math.nan, math.nan, False) if still[k] else densities(tau, adev[:, k], record_s)
                       for k in range(6)])
    needs = np.where(np.isnan(fitted[:, 2]), -np.inf, fitted[:, 2])
    longest = int(np.argmax(needs))
    return AllanResult(tau, adev[:, :3], adev[:, 3:], fitted[:3, 0], fitted[:3, 1], fitted[3:, 0], fitted[3:, 1], dt,
                       record_s, float(needs[longest]) if np.isfinite(needs[longest]) else None,
                       bool(fitted[longest, 3]), tuple(a for a, s in zip(AXES, still) if s))


#: A recording moves when a 1-s mean angular rate exceeds this [rad/s] or a 1-s mean specific
#: force departs from the recording's mean by more than this [m/s^2] (a bias walk does neither).
MOVING_RATE = 0.1
MOVING_FORCE = 1.0


def motion(imu: ImuSamples) -> str | None:
    """What shows that ``imu`` was not at rest (turning or accelerating, judged on 1-s means), or
    None: the Allan deviation of a moving IMU describes its motion, not its noise."""
    per_second = max(int(round(1.0 / float(np.median(np.diff(imu.t))))), 1)
    n = len(imu) // per_second
    if n < 2:
        return None
    gyro = imu.gyro[:n * per_second].reshape(n, per_second, 3).mean(axis=1)
    acc = imu.acc[:n * per_second].reshape(n, per_second, 3).mean(axis=1)
    rate = float(np.linalg.norm(gyro, axis=1).max())
    force = float(np.linalg.norm(acc - acc.mean(axis=0), axis=1).max())
    if rate > MOVING_RATE:
        return f"a 1-s mean angular rate of {rate:.3g} rad/s (turning)"
    if force > MOVING_FORCE:
        return f"1-s mean specific forces {force:.3g} m/s^2 from their mean (accelerating or tilting)"
    return None
