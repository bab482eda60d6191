"""The IMU's own faults, found in its raw samples, so that an IMU fault is named as one.

A faulty IMU shows downstream as every other sensor disagreeing with the estimate (their NIS far
out of band): :func:`inspect_imu` looks at the samples themselves, before any estimator, for

* ``saturation``: runs of at least :data:`SATURATION_RUN` samples stuck at the same value on an
  axis, that value being the axis's extreme over the recording and far (more than
  :data:`SATURATION_EXCURSION` robust spreads) from its median: a sensor at its range limit
  (clipping) reads exactly that;
* ``spike``: single samples far from both neighbours while the neighbours agree with each other:
  ``|x_k - (x_{k-1} + x_{k+1}) / 2|`` above :data:`SPIKE_FACTOR` times the local robust scale of
  the first differences (1.4826 times their median absolute value in blocks of
  :data:`SPIKE_BLOCK` samples, the largest of a block and its neighbours: a scale that follows
  the motion, so that rest and a trot are judged each by its own) and above :data:`MIN_SPIKE`
  (smaller ones move the estimate less than the noise does), with ``|x_{k+1} - x_{k-1}|`` under
  half of it, and the other sensor calm there (no first difference within a sample of it beyond
  :data:`CALM_FACTOR` local scales): a corrupt sample is one sensor's, while an impact (a legged
  robot's foot, a collision) jolts the accelerometer and the gyro together;
* ``gap``: intervals longer than :data:`datasets.types.IMU_GAP_FACTOR` typical periods (the
  offline and online rule, :func:`datasets.types.imu_gaps`);
* ``gyro units``: a gyro recorded in deg/s. What is decidable from an IMU alone: while the
  specific force is gravity's (quasi-static stretches: its magnitude steady near its value at
  rest), its direction in the body frame turns only as the body tilts, and the gyro's rates
  perpendicular to it predict that turning (``u_b ~ u_a - theta x u_a``). Over windows of
  :data:`TILT_WINDOW_S` the observed tilt is compared with the gyro's, read once in rad/s and
  once in deg/s, each with the constant bias that fits best; the data are called deg/s when that
  reading explains the tilts :data:`UNITS_EVIDENCE` times better (in squared residual) and the
  rad/s reading predicts tilts the accelerometer does not see. Rates about gravity (a car's yaw)
  say nothing of their units, nor does an IMU that never tilts: then nothing is claimed. (A
  gyro in deg/s that turns fast is refused earlier: :data:`datasets.types.MAX_PLAUSIBLE_RATE`.)
* ``accelerometer scale``: the specific force's magnitude at rest more than
  :data:`SCALE_TOLERANCE` from ``|g|`` (an accelerometer in g reads 1 there). At rest: the
  median over the windows of :data:`TILT_WINDOW_S` whose specific force is steady (its vector's
  spread within :data:`REST_SPREAD` of its magnitude: neither turning nor shaking); an IMU that
  is never steady (tumbling) gives no verdict.

Each finding (:class:`ImuFinding`) says what, on which sensor, where (the time span of its first
to last event, with up to :data:`MAX_SPANS` events' spans), how many samples and a one-line
message. Arrays in, findings out; vectorised throughout (a block median, cumulative sums, one
small least-squares fit).
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from datasets.types import check_array, check_times, imu_gaps

#: A run of at least this many equal samples at an axis's extreme is clipping.
SATURATION_RUN = 5
#: ... when the extreme lies more than this many robust spreads (1.4826 MAD) from the axis's median.
SATURATION_EXCURSION = 5.0
#: A spike stands out from both neighbours by this many local robust scales of the first differences.
SPIKE_FACTOR = 40.0
#: The other sensor is calm at a spike when none of its first differences within a sample of it
#: exceeds this many local scales.
CALM_FACTOR = 10.0
#: Samples per block of the local scale.
SPIKE_BLOCK = 100
#: The smallest spike reported, per sensor [m/s^2, rad/s].
MIN_SPIKE = {"accelerometer": 0.5, "gyro": 0.05}
#: The windows [s] over which tilts (and the specific force at rest) are compared.
TILT_WINDOW_S = 1.0
#: A window is quasi-static when its mean |f| lies within this fraction of the value at rest and
#: its spread (as for :data:`REST_SPREAD`) under five times that fraction (no shaking).
QUASI_STATIC = 0.1
#: The deg/s reading must explain the tilts this many times better than the rad/s one.
UNITS_EVIDENCE = 10.0
#: ... and the rad/s reading must miss by at least this RMS tilt per window [rad].
MIN_TILT_MISS = 0.02
#: A window is steady (at rest, or moving uniformly) when its specific force's spread (the root of
#: the axes' variances) is under this fraction of its mean's magnitude.
REST_SPREAD = 0.05
#: The specific force at rest may differ from |g| by this fraction.
SCALE_TOLERANCE = 0.1
#: Spans kept per finding.
MAX_SPANS = 10

_SENSORS = ("accelerometer", "gyro")
_UNITS = {"accelerometer": "m/s^2", "gyro": "rad/s"}
_AXES = "xyz"


@dataclass(frozen=True)
class ImuFinding:
    """One fault of the IMU: ``what`` (``saturation``, ``spike``, ``gap``, ``gyro units``,
    ``accelerometer scale``), ``sensor`` (``accelerometer``, ``gyro`` or ``timing``), ``t_start``
    and ``t_end`` [s] from its first event's start to its last's end, ``samples`` affected (for a
    gap: missing), ``message`` (one line) and ``spans``: the first :data:`MAX_SPANS` events'
    ``(start, end)``."""

    what: str
    sensor: str
    t_start: float
    t_end: float
    samples: int
    message: str
    spans: tuple = field(default=())

    def record(self) -> dict:
        """The finding as JSON-ready values."""
        return {"what": self.what, "sensor": self.sensor, "t_start": self.t_start, "t_end": self.t_end,
                "samples": self.samples, "message": self.message, "spans": [list(s) for s in self.spans]}


def inspect_imu(t, acc, gyro, gravity: float = 9.80665) -> list[ImuFinding]:
    """The faults of the IMU samples ``t (N,)``, ``acc``, ``gyro (N, 3)`` [s, m/s^2, rad/s] under
    gravity of magnitude ``gravity`` [m/s^2] (module docstring); an empty list for a healthy IMU."""
    t = check_times("inspect_imu: t", t)
    signals = {"accelerometer": check_array("inspect_imu: acc", acc, (3,), len(t), t),
               "gyro": check_array("inspect_imu: gyro", gyro, (3,), len(t), t)}
    findings = []
    jumps = {sensor: _jumps(x) for sensor, x in signals.items()}
    for sensor, other in zip(_SENSORS, _SENSORS[::-1]):
        findings += _saturation(t, signals[sensor], sensor)
        findings += _spikes(t, signals[sensor], sensor, *jumps[sensor], _disturbed(jumps[other][0]))
    findings += _gaps(t)
    if len(t) >= 3:
        findings += _gravity_checks(t, signals["accelerometer"], signals["gyro"], gravity)
    return findings


def findings_record(findings: list[ImuFinding]) -> dict:
    """For ``metrics.json``: ``ok`` (no finding) and the ``findings`` as records."""
    return {"ok": not findings, "findings": [f.record() for f in findings]}


def _finding(what: str, sensor: str, t0: np.ndarray, t1: np.ndarray, samples: int, message: str) -> ImuFinding:
    order = np.argsort(t0, kind="stable")
    t0, t1 = t0[order], t1[order]
    return ImuFinding(what, sensor, float(t0[0]), float(t1.max()), int(samples), message,
                      tuple((float(a), float(b)) for a, b in zip(t0[:MAX_SPANS], t1[:MAX_SPANS])))


def _runs(mask: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The ``(start, stop)`` indices (stop exclusive) of the runs of True in ``mask``."""
    edges = np.diff(np.r_[0, mask.astype(np.int8), 0])
    return np.flatnonzero(edges == 1), np.flatnonzero(edges == -1)


def _saturation(t: np.ndarray, x: np.ndarray, sensor: str) -> list[ImuFinding]:
    starts, stops, values, axes = [], [], [], []
    median = np.median(x, axis=0)
    spread = 1.4826 * np.median(np.abs(x - median), axis=0)
    for a in range(3):
        for extreme in (x[:, a].max(), x[:, a].min()):
            if not abs(extreme - median[a]) > SATURATION_EXCURSION * spread[a]:
                continue
            start, stop = _runs(x[:, a] == extreme)
            long = stop - start >= SATURATION_RUN
            starts += list(start[long])
            stops += list(stop[long])
            values += [extreme] * int(long.sum())
            axes += [_AXES[a]] * int(long.sum())
    if not starts:
        return []
    starts, stops = np.array(starts), np.array(stops)
    samples = int((stops - starts).sum())
    longest = int(np.argmax(stops - starts))
    which = ", ".join(f"{axis} at {value:.6g}" for axis, value in dict(zip(axes, values)).items())
    message = (f"{sensor}: {len(starts)} run(s) of samples stuck at the axis's extreme ({which} {_UNITS[sensor]}), "
               f"{samples} samples, the longest {t[stops[longest] - 1] - t[starts[longest]]:.3g} s from "
               f"t = {t[starts[longest]]:.6f} s: saturated (clipped at its range limit); the motion there is not "
               "measured")
    return [_finding("saturation", sensor, t[starts], t[stops - 1], samples, message)]


def _local_scale(d: np.ndarray) -> np.ndarray:
    """Per first difference (rows of ``d``), the robust scale of the differences around it: 1.4826
    times the median absolute difference of its block of :data:`SPIKE_BLOCK`, the largest of
    that block and its two neighbours."""
    n = len(d)
    blocks = -(-n // SPIKE_BLOCK)
    padded = np.full((blocks * SPIKE_BLOCK, 3), np.nan)
    padded[:n] = np.abs(d)
    scale = 1.4826 * np.nanmedian(padded.reshape(blocks, SPIKE_BLOCK, 3), axis=1)
    scale = np.maximum(scale, np.maximum(np.r_[scale[:1], scale[:-1]], np.r_[scale[1:], scale[-1:]]))
    return np.repeat(scale, SPIKE_BLOCK, axis=0)[:n]


def _jumps(x: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The first differences of ``x`` in units of their local scale, and that scale."""
    d = np.diff(x, axis=0)
    scale = _local_scale(d) if len(d) else np.zeros((0, 3))
    with np.errstate(divide="ignore", invalid="ignore"):
        return np.where(scale > 0, np.abs(d) / scale, np.where(d == 0, 0.0, np.inf)), scale


def _disturbed(jumps: np.ndarray) -> np.ndarray:
    """Per sample ``k`` (1 .. N-2), whether a first difference within a sample of it (``k-2 .. k+1``)
    exceeds :data:`CALM_FACTOR` local scales."""
    big = np.r_[False, jumps.max(axis=1, initial=0.0) > CALM_FACTOR, False]  # big[j + 1]: difference j
    near = big[:-3] | big[1:-2] | big[2:-1] | big[3:]  # differences k-2 .. k+1 for k = 1 .. N-2
    return near


def _spikes(t: np.ndarray, x: np.ndarray, sensor: str, jumps: np.ndarray, scale: np.ndarray,
            other_disturbed: np.ndarray) -> list[ImuFinding]:
    if len(x) < 3:
        return []
    out = x[1:-1] - 0.5 * (x[:-2] + x[2:])  # how far each sample stands out from its neighbours
    between = np.abs(x[2:] - x[:-2])  # how far the neighbours are apart
    size = np.abs(out)
    spike = ((size > SPIKE_FACTOR * np.maximum(scale[:-1], scale[1:])) & (size > MIN_SPIKE[sensor])
             & (between < 0.5 * size) & ~other_disturbed[:, None])
    rows, axes = np.nonzero(spike)
    if not rows.size:
        return []
    k = np.unique(rows) + 1
    largest = int(np.argmax(size[rows, axes]))
    i, a = rows[largest] + 1, axes[largest]
    message = (f"{sensor}: {k.size} spike(s), single samples far from both neighbours (beyond {SPIKE_FACTOR:g} "
               f"local robust scales), the largest {out[rows[largest], a]:+.4g} {_UNITS[sensor]} on {_AXES[a]} at "
               f"t = {t[i]:.6f} s: a corrupt sample kicks the estimate")
    return [_finding("spike", sensor, t[k], t[k], k.size, message)]


def _gaps(t: np.ndarray) -> list[ImuFinding]:
    gaps, text = imu_gaps(t, where="samples", rows=False)
    if text is None:
        return []
    typical = float(np.median(np.diff(t)))
    i = np.flatnonzero(np.diff(t) > gaps.min() * (1 - 1e-12))
    missing = int(np.sum(np.round(gaps / typical) - 1))
    return [_finding("gap", "timing", t[i], t[i + 1], missing, f"timing: {text}")]


def _windows(t: np.ndarray) -> np.ndarray:
    """Sample indices bounding consecutive windows of about :data:`TILT_WINDOW_S`."""
    edges = np.searchsorted(t, np.arange(t[0], t[-1], TILT_WINDOW_S))
    return np.unique(np.r_[edges, len(t)])


def _gravity_checks(t: np.ndarray, acc: np.ndarray, gyro: np.ndarray, gravity: float) -> list[ImuFinding]:
    """The accelerometer's scale at rest and the gyro's units against the tilts (module docstring)."""
    edges = _windows(t)
    if len(edges) < 5:  # too short a recording to judge
        return []
    counts = np.diff(edges)
    keep = counts >= 10
    lo, hi, n = edges[:-1][keep], edges[1:][keep], counts[keep][:, None]
    mean = np.add.reduceat(acc, edges[:-1])[keep] / n
    spread = np.sqrt(np.maximum(np.add.reduceat(acc * acc, edges[:-1])[keep] / n - mean**2, 0.0).sum(axis=1))
    magnitude = np.linalg.norm(np.add.reduceat(np.linalg.norm(acc, axis=1), edges[:-1])[keep][:, None] / n, axis=1)
    steady = spread < REST_SPREAD * np.linalg.norm(mean, axis=1)
    findings = []
    at_rest = float(np.median(magnitude[steady])) if steady.sum() >= 3 else None
    if at_rest is not None and gravity > 0 and abs(at_rest / gravity - 1) > SCALE_TOLERANCE:
        likely = ("in g rather than m/s^2 (multiply by 9.80665)" if abs(at_rest - 1) < SCALE_TOLERANCE
                  else "a scale error, or other units")
        findings.append(_finding(
            "accelerometer scale", "accelerometer", t[lo[steady]], t[hi[steady] - 1], int(n[steady].sum()),
            f"accelerometer: specific force {at_rest:.4g} at rest ({int(steady.sum())} steady {TILT_WINDOW_S:g}-s "
            f"windows), expected |g| = {gravity:.4g} m/s^2: {likely}"))
    reference = at_rest if at_rest is not None else float(np.median(magnitude))
    quasi = ((np.abs(magnitude - reference) < QUASI_STATIC * reference)
             & (spread < 5 * QUASI_STATIC * np.linalg.norm(mean, axis=1)))
    return findings + _gyro_units(t, acc, gyro, lo[quasi], hi[quasi])


def _gyro_units(t, acc, gyro, lo, hi) -> list[ImuFinding]:
    """The deg/s test of the module docstring over the quasi-static windows ``[lo, hi)``: the
    direction ``u = f / |f|`` obeys ``du/dt = -s (w - b) x u`` while ``f`` is gravity's, ``s`` the
    gyro's unit in rad/s; summed over a window, ``Delta u = -s G - s [U]x b`` with
    ``G = sum dt w x u`` and ``U = sum dt u`` -- first order in each sample's step, not in the
    window's rotation, so valid for any rotation -- is fitted for ``s = 1`` and ``s = pi/180``, each
    with its best bias ``b``."""
    if len(lo) < 5:
        return []
    h = np.maximum((hi - lo) // 10, 1)  # the ends: u averaged over a tenth of the window each
    u = acc / np.maximum(np.linalg.norm(acc, axis=1, keepdims=True), 1e-300)
    dt = np.r_[np.diff(t), 0.0][:, None]
    total_u = np.r_[np.zeros((1, 3)), np.cumsum(u, axis=0)]
    G = np.r_[np.zeros((1, 3)), np.cumsum(dt * np.cross(gyro, u), axis=0)]
    U = np.r_[np.zeros((1, 3)), np.cumsum(dt * u, axis=0)]
    observed = ((total_u[hi] - total_u[hi - h]) - (total_u[lo + h] - total_u[lo])) / h[:, None]
    a_mid, b_mid = lo + h // 2, hi - h + h // 2
    G_w, U_w = G[b_mid] - G[a_mid], U[b_mid] - U[a_mid]
    skew = np.zeros((len(lo), 3, 3))  # [U]x
    skew[:, 0, 1], skew[:, 0, 2], skew[:, 1, 2] = -U_w[:, 2], U_w[:, 1], -U_w[:, 0]
    skew -= skew.transpose(0, 2, 1)

    def misfit(scale: float) -> float:
        """The squared residual of the direction changes with the gyro read as ``scale`` rad/s per
        unit, its best bias fitted."""
        rhs = observed + scale * G_w
        A = scale * skew
        b = np.linalg.lstsq(A.reshape(-1, 3), -rhs.reshape(-1), rcond=None)[0]
        return float(np.sum((rhs + A @ b) ** 2))

    as_rad, as_deg = misfit(1.0), misfit(np.pi / 180)
    if not (as_rad > UNITS_EVIDENCE * as_deg and as_rad > len(lo) * MIN_TILT_MISS**2):
        return []
    message = (f"gyro: its rates read in rad/s predict tilts the accelerometer does not see (RMS miss "
               f"{np.sqrt(as_rad / len(lo)):.3g} rad per {TILT_WINDOW_S:g}-s window; read in deg/s "
               f"{np.sqrt(as_deg / len(lo)):.3g} rad) over {len(lo)} quasi-static windows: the gyro is probably in "
               "deg/s (multiply by pi/180)")
    return [_finding("gyro units", "gyro", t[lo], t[hi - 1], int((hi - lo).sum()), message)]
