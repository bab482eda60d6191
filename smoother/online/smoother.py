"""Online fixed-lag smoothing: IMU samples and measurements fed as they arrive, the state at IMU
rate, each keyframe's smoothed estimate as it leaves the window.

:class:`OnlineSmoother` is a fixed-lag smoother fed from streams: of ``kind`` ``"sliding"`` (the
default; the compiled window of :mod:`smoother.fixed_lag.sliding.window`) or GTSAM's ``"incremental"`` /
``"batch"`` (:class:`smoother.fixed_lag.gtsam_window.KeyframeWindow`); every window keeps the fixed-lag
contract (:class:`smoother.fixed_lag.contract.FixedLagWindow`, which
:func:`smoother.fixed_lag.offline.run_fixed_lag` drives too) and takes a keyframe as its IMU interval, its
measurements and its initial value (``add_keyframe``). Conventions are the
project's: state ``x = (r, v, C, b_f, b_w)`` (world position, BODY velocity, body-to-world
attitude, accelerometer and gyro biases), 15x15 covariances in the primer's error state
``(dr, dv, dphi, db_f, db_w)`` with the LEFT perturbation ``C <- exp(dphi) C``, times in seconds
on the IMU's clock.

Keyframes. Keyframe 0 is at the first IMU sample, with the prior ``(initial, initial_cov)``. With
``keyframe_rate`` None every measurement time is a keyframe; with a rate the keyframes are the
grid ``t0 + m / rate`` (grid times within half an IMU interval of another keyframe are left
out), and a measurement between two of them is attached to the one before it (its state the
IMU's exact Euler steps from that keyframe to its time, its covariance grown by their process
noise: ``docs/design.md``, keyframes) and reaches the window with the one after it. Both ends of
a relative pose, every time given to :meth:`OnlineSmoother.keyframe_at` and the last IMU sample
at :meth:`OnlineSmoother.finish` are keyframes either way. Consecutive keyframes are
joined by the project's IMU factor, preintegrated when the later keyframe is made, its noise
covariance evaluated along the prediction from the smoother's newest estimate.

Time order. IMU samples must come in strictly increasing time: a sample at or before the newest
one is an error (an :class:`factors.errors.InputError`, a ValueError; IMU samples are never
reordered). An interval longer than :data:`datasets.types.IMU_GAP_FACTOR` typical periods (the
median interval of the samples seen, once there are
:data:`smoother.online.imu_buffer.TYPICAL_INTERVALS`) is a gap, bridged by holding the sample before it
as the offline path does (:func:`datasets.types.imu_gaps`, the same rule and message): counted
in ``imu_gaps`` with the longest in ``longest_imu_gap_s``, a warning at the first and at each
longer than all before; one longer than :data:`datasets.types.MAX_IMU_GAP_S` is a jump of the
clock, refused, as is a measurement stamped that far after the newest IMU sample. A keyframe at
time ``t`` is made -- and the smoother updated with it -- once the IMU stream has reached
``t + max_delay_s``; until then measurements up to ``t`` may still arrive in any order
and are sorted into time. A measurement whose time is at or before the newest keyframe already
made is dropped: counted per sensor in ``dropped``, with a warning at its sensor's first drop.
So a measurement at most ``max_delay_s`` behind the IMU stream is always used, and one later than
that is used only while no keyframe has been made at or after its time (none was due: no other
measurement, grid time or :meth:`OnlineSmoother.keyframe_at` since); it is the newest keyframe,
not the delay, that decides. ``max_delay_s`` (:data:`smoother.online.delay.MAX_DELAY_RANGE`) is thus also
the delay of every measurement's effect on the estimates.

Outputs. :meth:`OnlineSmoother.estimate` is the state at the newest IMU time: the EKF's
per-sample prediction (:func:`factors.imu.predict_into`, the filter's own step) from the
newest keyframe's estimate, no re-solve; with ``covariances`` its 15x15 covariance too, from the
keyframe's marginal. A keyframe's smoothed estimate is the one it has just before the update that
marginalises it (older than the new keyframe's time minus ``lag_s``), handed to ``on_smoothed``
or queued for :meth:`OnlineSmoother.smoothed`; :meth:`OnlineSmoother.finish` makes the pending
keyframes and hands over the rest of the window.

A relative measurement (odometry) whose earlier time is no keyframe in the window when it arrives
or when its later keyframe is made (it is older than the lag) is skipped: counted per sensor in
``skipped``, with a warning at the first.

No silent failures: besides the dropped and skipped measurements, a warning when measurements are further
apart than the lag (:func:`smoother.fixed_lag.lag.sparse_measurement_warning`: keyframes then leave
the window before the next measurement reaches them).

Bad input. Every value is checked as the offline data types check it (:mod:`datasets.types`):
the initial state (a rotation matrix ``C``, finite 3-vectors), a symmetric positive definite
initial covariance, each sensor's setup, and every sample: finite, and no axis beyond the
plausible ranges (:data:`datasets.types.MAX_PLAUSIBLE_SPECIFIC_FORCE`, the gyro rate limit of
:func:`datasets.types.max_gyro_rate` in force when the smoother is made, the measurements'
distance and speed limits). What fails is refused with an InputError naming the argument or
field, the expected and found shape or the sample's time; the sample is not taken and the smoother
stays usable.

The parts, one job each: :mod:`smoother.online.imu_buffer` (the IMU stream and its checks),
:mod:`smoother.online.schedule` (the keyframe times), :mod:`smoother.online.pending` (the
measurements waiting for their keyframe, late ones sorted into time, those too old refused),
:mod:`smoother.online.handover` (the keyframes leaving the window, to the caller) and
:mod:`smoother.online.prediction` (the state at IMU rate); :class:`OnlineSmoother` composes them
with the keyframe window.

The first :class:`OnlineSmoother` of a process loads (or compiles) every compiled kernel of the
loop by feeding a throwaway smoother 0.8 s of made-up data, so that a robot's first keyframes and
first marginalisation do not stall on it.

:func:`replay` feeds a whole :class:`datasets.types.Dataset` through an :class:`OnlineSmoother`,
at once or at the data's own pace (``realtime``), measuring each measurement's latency from its
arrival to the update that used it.
"""
from __future__ import annotations

import math
import time
import warnings
from collections import deque
from dataclasses import dataclass, replace

import numpy as np

from datasets.kinds import KINDS, attached_noise, drift_problem, kind_sigmas, sensors_of, with_sigma_factor
from datasets.ranges import correlation_time_problem
from datasets.robust import check_robust
from datasets.types import (
    MAX_IMU_GAP_S,
    Dataset,
    Sensor,
    check_array,
    check_extrinsic,
    check_state,
    check_state_covariance,
)
from factors import calibration, imu, preintegration
from factors.errors import InputError
from smoother.fixed_lag.contract import HISTORY
from smoother.fixed_lag.kinds import GTSAM_KINDS
from smoother.fixed_lag.lag import check_lag, check_lag_spans_keyframes, sparse_measurement_warning
from smoother.fixed_lag.windows import make_window
from smoother.model.correlated import weighed_alone_warning
from smoother.model.problem import AttachedAt, measurement_spec
from smoother.model.timeline import interval_attachment, interval_steps
from smoother.online import warm_up
from smoother.online.delay import MAX_DELAY_RANGE
from smoother.online.drift import DriftChains
from smoother.online.handover import HandOver, OnlineEstimate
from smoother.online.imu_buffer import ImuBuffer
from smoother.online.pending import PendingMeasurements
from smoother.online.prediction import ImuRatePrediction
from smoother.online.schedule import KeyframeSchedule


@dataclass(frozen=True)
class SensorSetup:
    """An aiding sensor of an :class:`OnlineSmoother`: its ``kind`` (a name of
    :data:`datasets.kinds.KINDS`), extrinsic ``T_BS`` (4x4, ``p_B = T_BS p_S``; None: at the IMU),
    ``time_offset`` [s] added to its stamps, ``sigma`` (the noise standard deviations used when a
    measurement comes without a covariance; None: every measurement brings one), ``sigma_factor``
    (instead of ``sigma``: factors per axis on the standard deviations the measurements bring, the
    rig file's key) and ``robust`` (None or a kernel spec of
    :func:`datasets.robust.robust_spec`); ``roll_pitch_only`` makes an
    ``orientation`` sensor one of kind ``roll_pitch`` (its heading unused), as in a rig file;
    ``calibrate`` (a :class:`factors.calibration.CalibrationPrior`, the rig file's ``estimate``
    and ``*_sigma`` keys) makes parts of its calibration variables, estimated about ``T_BS`` and
    ``time_offset`` (the ``"sliding"`` window only); ``correlation_time`` [s] (None: white) makes
    its errors drift as a first-order Gauss-Markov process (:mod:`smoother.model.correlated`; the
    ``"sliding"`` window models it, GTSAM's take the errors as white and say so). Each is checked
    when made: an InputError naming the field otherwise."""

    kind: str
    T_BS: np.ndarray | None = None
    time_offset: float = 0.0
    sigma: np.ndarray | None = None
    robust: tuple | None = None
    roll_pitch_only: bool = False
    calibrate: calibration.CalibrationPrior | None = None
    sigma_factor: np.ndarray | None = None
    correlation_time: float | None = None

    def __post_init__(self):
        from datasets.rig import roll_pitch_kind

        object.__setattr__(self, "kind", roll_pitch_kind(
            self.kind, self.roll_pitch_only, lambda message: InputError(f"SensorSetup.roll_pitch_only: {message}")))
        if self.kind not in KINDS:
            raise InputError(f"SensorSetup.kind: expected one of {', '.join(KINDS)}, got {self.kind!r}")
        object.__setattr__(self, "T_BS", check_extrinsic("SensorSetup.T_BS", self.T_BS))
        offset = check_array("SensorSetup.time_offset", [self.time_offset], ())[0]
        if not abs(offset) <= MAX_IMU_GAP_S:
            raise InputError(f"SensorSetup.time_offset: expected at most {MAX_IMU_GAP_S:g} s either way, "
                             f"got {offset!r}")
        object.__setattr__(self, "time_offset", float(offset))
        if self.sigma is not None:
            kind_sigmas("SensorSetup", self.sigma, KINDS[self.kind].dim)
        if self.sigma_factor is not None:
            if self.sigma is not None:
                raise InputError("SensorSetup.sigma_factor: scales the sigmas the measurements bring; with sigma "
                                 "given, give the sigmas themselves")
            object.__setattr__(self, "sigma_factor", kind_sigmas("SensorSetup.sigma_factor", self.sigma_factor,
                                                                 KINDS[self.kind].dim))
        check_robust("SensorSetup.robust", self.robust)
        if self.correlation_time is not None:
            problem = drift_problem(self.kind) or correlation_time_problem(self.correlation_time)
            if problem is not None:
                raise InputError(f"SensorSetup.correlation_time: {problem}")
            object.__setattr__(self, "correlation_time", float(self.correlation_time))
        if self.calibrate is not None:
            calibration.checked_prior(self.calibrate, self.kind, KINDS[self.kind].model, "SensorSetup.calibrate")
            given = self.calibrate.stamp_offset
            if self.time_offset != 0.0 and given != self.time_offset:  # the offset its stamps get
                if given != 0.0:
                    raise InputError(f"SensorSetup.calibrate: stamp_offset {given!r} differs from time_offset "
                                     f"{self.time_offset!r}")
                object.__setattr__(self, "calibrate", replace(self.calibrate, stamp_offset=self.time_offset))


class OnlineSmoother:
    """Fixed-lag smoothing fed sample by sample (module docstring).

    ``initial``, ``initial_cov``: the state at the first IMU sample and its 15x15 covariance;
    ``noise`` (:class:`factors.imu.ImuNoise`) and ``gravity`` (world frame, m/s^2); ``sensors``:
    name -> :class:`SensorSetup` (a kind's name can always be used as a sensor at the IMU with no
    time offset); ``lag_s`` the window [s]; ``kind`` the compiled ``"sliding"`` window or GTSAM's
    ``"incremental"`` or ``"batch"`` smoother; ``keyframe_rate`` [Hz] or None; ``max_delay_s`` how
    late a measurement may arrive behind the IMU stream (within
    :data:`smoother.online.delay.MAX_DELAY_RANGE`; one later is used only while no keyframe has
    been made at or after its time: module docstring); ``covariances``: compute keyframe
    covariances (the newest keyframe's, for :meth:`estimate`, and each smoothed keyframe's);
    ``on_smoothed(OnlineEstimate)``: called with each keyframe leaving the window (None: they are
    queued for :meth:`smoothed`); ``joint_with_next`` (with ``covariances``): each smoothed
    keyframe also carries the window's estimate of the keyframe after it and the two's joint
    covariance (``OnlineEstimate.following``, where the window computes it: the states between
    them, :mod:`smoother.model.between`; it doubles the covariances' cost); ``before_leaving(window,
    keyframes)``: called with the window and the keyframes an update is about to marginalise (and at
    :meth:`finish`, the whole window), while the window still holds them (what reads more of it than
    the hand-over does: :mod:`smoother.diagnosis.heldout_windowed`).

    It composes the parts, one job each: the IMU stream (:class:`smoother.online.imu_buffer.ImuBuffer`),
    the keyframe times (:class:`smoother.online.schedule.KeyframeSchedule`), the measurements
    waiting for their keyframe (:class:`smoother.online.pending.PendingMeasurements`), the
    keyframe window (:func:`smoother.fixed_lag.windows.make_window`), the hand-over of the keyframes leaving it
    (:class:`smoother.online.handover.HandOver`) and the state at IMU rate
    (:class:`smoother.online.prediction.ImuRatePrediction`)."""

    def __init__(self, initial: imu.ImuState, initial_cov, noise: imu.ImuNoise, sensors: dict | None = None,
                 lag_s: float = 2.0, kind: str = "sliding", keyframe_rate: float | None = None,
                 max_delay_s: float = 0.0, gravity=imu.DEFAULT_GRAVITY, covariances: bool = False,
                 on_smoothed=None, reintegration_threshold: float = preintegration.REINTEGRATION_THRESHOLD,
                 joint_with_next: bool = False, *, before_leaving=None):
        problem = MAX_DELAY_RANGE.problem(max_delay_s) if isinstance(max_delay_s, (int, float)) else \
            f"expected a number of seconds, got {max_delay_s!r}"
        if problem is not None:
            raise InputError(f"max_delay_s: {problem}")
        if keyframe_rate is not None and not (keyframe_rate > 0 and math.isfinite(keyframe_rate)):
            raise InputError(f"keyframe_rate must be positive and finite, or None, got {keyframe_rate}")
        lag_s = check_lag(lag_s)
        check_lag_spans_keyframes(lag_s, keyframe_rate)
        check_state("initial", initial)  # a rotation, finite 3-vectors
        initial_cov = check_state_covariance("initial_cov", initial_cov)  # symmetric, positive definite
        if not isinstance(noise, imu.ImuNoise):
            raise InputError(f"noise: expected an ImuNoise, got {type(noise).__name__}")
        self._sensors = dict(sensors or {})
        for name, setup in self._sensors.items():
            if not isinstance(setup, SensorSetup):
                raise InputError(f"sensors[{name!r}]: expected a SensorSetup, got {setup!r}")
        self.initial, self.initial_cov, self.noise = initial, initial_cov, noise
        self.gravity = check_array("gravity", gravity, (), 3)
        calibrations = self._calibrations()
        self._window = make_window(lag_s, kind, self.gravity, reintegration_threshold, calibrations)
        self._window_calibrates = calibrations is not None
        self.lag_s, self.kind, self.max_delay_s = lag_s, kind, float(max_delay_s)
        self.keyframe_rate = keyframe_rate
        self.covariances = covariances
        self.reintegration_threshold = reintegration_threshold
        self._before_leaving = before_leaving
        #: wall time [s] from each used measurement's arrival to the end of the update that used it
        #: (the latest :data:`smoother.fixed_lag.contract.HISTORY`)
        self.latency_s: deque[float] = deque(maxlen=HISTORY)
        #: the longest time between absolute measurements (they fix a position or an attitude) seen so
        #: far [s] (the start counts as one)
        self.longest_gap_s = 0.0
        self._warned_gap = False
        self._finished = False
        self._imu = ImuBuffer(stacklevel=2)  # warnings name add_imu's caller
        self._schedule = KeyframeSchedule(keyframe_rate)
        self._pending = PendingMeasurements(self.max_delay_s, self.lag_s)
        drifting = {name: setup.correlation_time for name, setup in self._sensors.items()
                    if setup.correlation_time is not None}
        if drifting and kind in GTSAM_KINDS:
            warnings.warn(f"online smoother ({kind}): the errors of {', '.join(drifting)} are taken as white: GTSAM's "
                          "windows hold each measurement's own factor (the 'sliding' window models their "
                          "correlation_time), and their covariances are too small where the errors drift", stacklevel=2)
        self._drift = DriftChains({} if kind in GTSAM_KINDS else drifting)
        self._hand = HandOver(self._window, covariances, on_smoothed, joint_with_next)
        self._prediction = ImuRatePrediction(noise, self.gravity, covariances)
        self._keyframe_t: dict[float, int] = {}  # the window's keyframes by time
        self._last_t = None  # the newest keyframe's time
        self._last_measured_t = None
        self._newest = None  # the newest keyframe's estimate (what the next IMU interval starts from)
        warm_up.in_this_process(OnlineSmoother)

    @classmethod
    def for_dataset(cls, dataset: Dataset, robust: dict | None = None, **options) -> "OnlineSmoother":
        """A smoother with ``dataset``'s IMU noise, gravity, initial state and covariance and its
        sensors (:func:`datasets.kinds.sensors_of`: kinds, extrinsics and, for the ``"sliding"``
        window, what of their calibrations to estimate; their time offsets are in the dataset's
        stamps already), ``robust`` kernels by sensor name; ``options`` as the constructor's. The
        data themselves are not fed (:func:`replay` does). A sensor whose correlation time is still
        to be fitted is refused (:func:`_fit_first`)."""
        _fit_first(dataset.correlation_to_fit)
        robust = robust or {}
        calibrating = options.get("kind", "sliding") == "sliding"
        sensors = {s.name: SensorSetup(s.kind, getattr(s.data, "T_BS", None), robust=robust.get(s.name),
                                       calibrate=s.calibrate if calibrating else None,
                                       correlation_time=s.correlation_time)
                   for s in sensors_of(dataset)}
        return cls(dataset.initial, dataset.initial_cov, dataset.noise, sensors, gravity=dataset.gravity, **options)

    @classmethod
    def from_rig(cls, rig, initial: imu.ImuState, initial_cov, **options) -> "OnlineSmoother":
        """A smoother for the sensors of a rig file (:func:`datasets.rig.load_rig`: IMU noise and
        gravity, each sensor's kind, extrinsic, time offset, sigma, robust kernel and calibrations
        to estimate), starting from ``initial`` with ``initial_cov`` at the first IMU sample;
        ``options`` as the constructor's; each sensor's ``correlation_time`` too (one still to be
        fitted, ``"fit"``, is refused: :func:`_fit_first`)."""
        _fit_first(tuple(s.name for s in rig.sensors if s.fit_correlation_time))
        sensors = {s.name: SensorSetup(s.kind, s.T_BS, s.time_offset, s.sigma, s.robust, calibrate=s.calibrate,
                                       sigma_factor=s.sigma_factor, correlation_time=s.correlation_time)
                   for s in rig.sensors}
        return cls(initial, initial_cov, rig.imu.noise, sensors, gravity=np.array([0.0, 0.0, -rig.imu.gravity]),
                   **options)

    # -- input ------------------------------------------------------------------------------------

    def add_imu(self, t, acc, gyro) -> None:
        """One IMU sample (``t`` a number, ``acc``, ``gyro`` of shape (3,): specific force [m/s^2]
        and angular rate [rad/s] in the body frame) or N samples (``t`` of shape (N,), ``acc``,
        ``gyro`` of shape (N, 3)), in strictly increasing time after every sample before; other
        shapes, non-finite or implausible values and time steps back are refused (module
        docstring), with nothing taken. Makes the keyframes the stream has passed by
        ``max_delay_s``, each at the sample that passed it, so that N samples at once give the
        estimates they give one by one (only checked at once: one warning for the gaps among
        them)."""
        self._open()
        stream = self._imu
        if (type(t) is float or np.ndim(t) == 0) and np.shape(acc) == (3,) and np.shape(gyro) == (3,):
            stream.add_one(float(t), acc, gyro)  # one sample: kept lean
            taken = 1
        else:
            taken = stream.add(t, acc, gyro)
        if self._schedule.t0 is None:  # the first sample: the first keyframe's time
            self._schedule.start(float(stream.t[0]))
        if stream.t_last - self.max_delay_s < self._schedule.next_time():  # no keyframe passed
            return
        first = stream.n - taken
        horizons = stream.t[first:stream.n] - self.max_delay_s
        i = 0
        while (i := i + int(np.searchsorted(horizons[i:], self._schedule.next_time()))) < taken:
            self._make_keyframes(float(horizons[i]), first + i)  # sample first + i passed a keyframe's time
            i += 1

    def add(self, sensor: str, t, *values, cov=None) -> None:
        """Measurements of ``sensor`` (a name of ``sensors``, or a kind's name for a sensor at the
        IMU): the fields of its kind's data type after the time(s) (:mod:`datasets.types`; e.g.
        ``add("pose", t, position, C)``, ``add("position", t, position)``, ``add("velocity", t,
        velocity, gyro)``, ``add("odometry", t_from, t_to, dr, dC)``), one measurement or arrays
        of them, with ``cov`` ((d, d) or (N, d, d); default from the sensor's sigma; times its
        ``sigma_factor`` on each axis's sigma where it has one). Stamps are the sensor's, its time
        offset is added here."""
        self._open()
        setup, kind = self._setup(sensor)
        single = np.ndim(t) == 0
        data_fields = (*kind.times, *kind.fields)
        if len(values) != len(data_fields) - 1:
            raise InputError(f"add({sensor!r}): expected {', '.join(data_fields)} (and cov), got "
                             f"{len(values) + 1} values")
        columns = [np.atleast_1d(np.asarray(t, dtype=float))] + [np.asarray(v, dtype=float) for v in values]
        if single:
            columns = [columns[0]] + [v[None] for v in columns[1:]]
        if cov is None:
            if setup.sigma is None:
                raise InputError(f"add({sensor!r}): cov: expected a covariance (the sensor has no sigma)")
            cov = np.diag(kind_sigmas(f"sensors[{sensor!r}]", setup.sigma, kind.dim) ** 2)
        try:
            data = kind.data_type(*columns, cov, setup.T_BS)
        except ValueError as error:
            raise InputError(f"add({sensor!r}): {error}") from None
        self.add_measurements(sensor, data)

    def add_measurements(self, sensor: str, data) -> None:
        """Measurements of ``sensor`` given as its kind's data type (:mod:`datasets.types`, the
        sensor's extrinsic inside it; stamps the sensor's, its time offset added here; their
        covariances times the sensor's ``sigma_factor`` on each axis's sigma where it has one)."""
        self._open()
        setup, kind = self._setup(sensor)
        if not isinstance(data, kind.data_type):
            raise InputError(f"add_measurements({sensor!r}): data: expected {kind.data_type.__name__}, "
                             f"got {type(data).__name__}")
        if setup.sigma_factor is not None:
            data = replace(data, cov=with_sigma_factor(data.cov, setup.sigma_factor))
        spec = measurement_spec(Sensor(sensor, setup.kind, data))
        stamps = np.stack([np.asarray(ts, dtype=float) + setup.time_offset for ts in spec.times], axis=1)
        if not np.isfinite(stamps).all():
            raise InputError(f"add_measurements({sensor!r}): t: expected finite times")
        stream = self._imu
        if stream.n and stamps.max() > stream.t_last + MAX_IMU_GAP_S:
            raise InputError(f"add_measurements({sensor!r}): t: {stamps.max():.6f} s on the IMU clock lies "
                             f"{stamps.max() - stream.t_last:.6g} s after the newest IMU sample, beyond any plausible "
                             f"delay ({MAX_IMU_GAP_S:g} s): a stamp of another clock, or a wrong time offset")
        arrived = time.perf_counter()
        asks = self.asks_keyframes(sensor)
        for m, times in enumerate(stamps):
            times = tuple(float(x) for x in times)
            if self._pending.offer(sensor, times, spec, m, arrived, self._last_t, self._keyframe_t) and asks:
                for x in times:
                    if self._last_t is None or x > self._last_t:
                        self._schedule.ask(x)

    def asks_keyframes(self, sensor: str) -> bool:
        """Whether the measurements of ``sensor`` ask for keyframes at their times (every
        measurement without ``keyframe_rate``, a relative one always) rather than being attached to
        the keyframe before them (module docstring): only those change which keyframes are made."""
        return self.keyframe_rate is None or self._setup(sensor)[1].relative

    def keyframe_at(self, t) -> None:
        """Ask for keyframes (estimates) at the times ``t`` (IMU clock); those at or before the
        newest keyframe already made are ignored."""
        self._open()
        t = np.atleast_1d(np.asarray(t, dtype=float))
        if not np.all(np.isfinite(t)):
            raise InputError(f"keyframe_at: t: expected finite times, got {t[~np.isfinite(t)][:3].tolist()}")
        for x in t:
            if self._last_t is None or x > self._last_t:
                self._schedule.ask(float(x))

    @property
    def weighed_alone(self) -> int:
        """How many drifting measurements it weighed alone, as independent of the one before: their
        chain restarted (:class:`smoother.online.drift.DriftChains`) or the window could not make
        their innovation (:attr:`smoother.fixed_lag.contract.FixedLagWindow.weighed_alone`)."""
        return self._drift.restarted + self._window.weighed_alone

    def finish(self) -> None:
        """End of the streams: make every keyframe up to the last IMU sample and one there (the
        end of the data), then hand over the whole window (each keyframe as smoothed as it gets);
        a warning if the data ended further from the last measurement than the lag. Nothing can
        be added afterwards."""
        self._open()
        stream = self._imu
        if stream.n:
            end = float(stream.t[stream.n - 1])
            if self._last_t is None or end > self._last_t:
                self._schedule.ask(end)
            self._make_keyframes(end, stream.n - 1)
        # after the last IMU sample (or no IMU at all): nothing to anchor them
        self._pending.drop_all("lies after the last IMU sample and was dropped")
        if self._last_t is not None:
            if self._last_measured_t is None:  # nothing measured at all: the whole run is one gap
                self._last_measured_t = self._schedule.t0
            self._gap(self._last_t)
        if self._window.newest >= 0:
            if self._before_leaving is not None:
                self._before_leaving(self._window, list(range(self._window.first, self._window.newest + 1)))
            self._hand.give([e for _, e in self._hand.read(range(self._window.first, self._window.newest + 1))])
        alone = weighed_alone_warning("online smoother", self.weighed_alone, self.lag_s)
        if alone is not None:
            warnings.warn(alone, stacklevel=2)
        self._finished = True

    # -- output -----------------------------------------------------------------------------------

    def estimate(self) -> OnlineEstimate:
        """The state at the newest IMU sample: the per-sample prediction from the newest
        keyframe's estimate (the EKF's step, through the samples since), and its covariance
        with ``covariances``. A ValueError before the first keyframe."""
        return self._prediction.at(self._imu)

    @property
    def started(self) -> bool:
        """Whether the first keyframe has been made, so that :meth:`estimate` has a state to
        predict from: with ``max_delay_s`` > 0 not before the IMU stream is that far past it."""
        return self._prediction.started

    def smoothed(self):
        """The keyframes that left the window since the last call (oldest first), as
        :class:`OnlineEstimate` s; empty when ``on_smoothed`` takes them."""
        return self._hand.smoothed()

    @property
    def on_smoothed(self):
        """Called with each keyframe's :class:`OnlineEstimate` as it leaves the window (None: queued)."""
        return self._hand.on_smoothed

    @on_smoothed.setter
    def on_smoothed(self, callback) -> None:
        self._hand.on_smoothed = callback

    @property
    def calibration(self):
        """``(values, covariances)`` of the calibration variables after the last update (a
        :class:`factors.calibration.CalibrationSet` and each sensor's marginal covariance over its
        estimated coordinates), or None when no sensor asks for one."""
        return self._window.calibration

    @property
    def dropped(self) -> dict[str, int]:
        """Measurements dropped for arriving too late (or outside the IMU's span), per sensor."""
        return self._pending.dropped

    @property
    def skipped(self) -> dict[str, int]:
        """Relative measurements skipped because their earlier time had left the window, per sensor."""
        return self._pending.skipped

    @property
    def imu_gaps(self) -> int:
        """IMU gaps bridged so far (:func:`datasets.types.imu_gaps`)."""
        return self._imu.imu_gaps

    @property
    def longest_imu_gap_s(self) -> float:
        """The longest IMU gap bridged so far [s]."""
        return self._imu.longest_imu_gap_s

    @property
    def update_s(self) -> deque[float]:
        """Wall time of each smoother update [s] (the latest :data:`smoother.fixed_lag.contract.HISTORY`)."""
        return self._window.update_s

    @property
    def recovered(self) -> list[int]:
        """Keyframes (by number) that needed a weak prior."""
        return self._window.recovered

    @property
    def _n(self) -> int:
        """The IMU samples kept."""
        return self._imu.n

    # -- inside -----------------------------------------------------------------------------------

    def _open(self) -> None:
        if self._finished:
            raise InputError("the smoother has finished: nothing can be added")

    def _setup(self, sensor: str):
        setup = self._sensors.get(sensor)
        if setup is None:
            if sensor not in KINDS:
                raise InputError(f"sensor: unknown sensor {sensor!r}; expected one of "
                                 f"{', '.join(list(self._sensors) + list(KINDS))}")
            setup = SensorSetup(sensor)
        return setup, KINDS[setup.kind]

    def _calibrations(self):
        """The window's calibration variables for the sensors whose setup asks for them, about
        their extrinsics given (:class:`smoother.fixed_lag.sliding.calibration.WindowCalibration`), or None."""
        asking = {name: setup for name, setup in self._sensors.items() if setup.calibrate is not None}
        if not asking:
            return None
        from smoother.fixed_lag.sliding.calibration import WindowCalibration

        chosen = calibration.CalibrationSet.given(asking, [s.T_BS for s in asking.values()],
                                                  [s.calibrate for s in asking.values()])
        return WindowCalibration(chosen, {name: setup.kind for name, setup in asking.items()})

    def _make_keyframes(self, horizon: float, newest: int) -> None:
        """Make every keyframe asked for at or before ``horizon`` and the sample ``newest`` (an
        index into the samples kept: the one the stream has reached), the grid's among them."""
        stream = self._imu
        step = 0.5 * (stream.t[newest] - stream.t[newest - 1]) if newest > 0 else 0.0
        self._schedule.grid_up_to(horizon, step, self._last_t)
        end = stream.t[newest]
        while (t := self._schedule.next_due(horizon, end)) is not None:
            self._keyframe(t)

    def _keyframe(self, t: float) -> None:
        """Make the keyframe at ``t``: its IMU interval, the measurements at ``t`` and those attached
        to the keyframe before it, one update."""
        window, stream = self._window, self._imu
        k = window.newest + 1
        pre, prior = None, None
        if k == 0:
            guess = self.initial
            prior = (self.initial, self.initial_cov)
        else:
            acc, gyro, dt = interval_steps(stream.t[:stream.n], stream.acc, stream.gyro, self._last_t, t)
            pre, guess = preintegration.integrate_interval(acc, gyro, dt, self._newest, self.noise, self.gravity)
        at_t, between = self._pending.due(t, k == 0, self._keyframe_t)
        measurements = [(item.spec, item.row, [k if x == t else self._keyframe_t[x] for x in item.times],
                         self._setup(item.sensor)[0].robust, None) for item in at_t]
        if between:
            measurements += self._attached(between, k - 1, pre.samples, t)
        used = at_t + between
        if self._drift:  # in time order: the attached ones came before those at t
            for i in sorted(range(len(used)), key=lambda i: used[i].latest):
                measurements[i] = self._drift.chained(used[i].sensor, used[i].latest, measurements[i])
        if self._before_leaving is not None:
            self._before_leaving(window, window.leaving(t))
        leaving = self._hand.read(window.leaving(t))
        extra = {}
        if self._window_calibrates:  # what a calibrated time offset steps with
            i = stream.held_at(t)
            extra["held"] = (stream.acc[i], stream.gyro[i])
        chained = self._drift.saved()
        try:
            self._newest = window.add_keyframe(t, guess, pre, measurements, prior, **extra)  # its estimate after it
        except InputError:  # refused before the window changed: the chains as they were
            self._drift.restore(chained)
            raise
        # every piece of state follows the update before anything is handed over: a caller's
        # on_smoothed that raises leaves the smoother consistent
        self._keyframe_t[t] = k
        while next(iter(self._keyframe_t.values())) < window.first:  # the window's only (in time order)
            del self._keyframe_t[next(iter(self._keyframe_t))]
        self._last_t = t
        stream.keep_from = t  # the next IMU interval and the prediction start at the sample held here
        if any(self._setup(item.sensor)[1].absolute for item in used):  # dead reckoning ends here
            if self._last_measured_t is None:
                self._last_measured_t = self._schedule.t0
            self._gap(t)
            self._last_measured_t = t
        self._prediction.restart(t, self._newest, window.covariances([k])[0] if self.covariances else None,
                                 stream.released + stream.held_at(t))
        done = time.perf_counter()  # the updated estimate is ready (its covariance included)
        self.latency_s += [done - item.arrived for item in used]
        self._hand.give([e for j, e in leaving if j < window.first])  # read in time: they have left

    def _attached(self, items: list, keyframe: int, samples: tuple, t: float) -> list:
        """The measurements ``items`` between the newest keyframe (``keyframe``, at ``_last_t``, its
        estimate ``_newest``) and ``t`` as the window takes them, attached to it: each where it lies
        in the interval's steps ``samples`` (:func:`smoother.model.timeline.interval_attachment`)
        with the IMU reading held at its stamp, its covariance grown by the process noise from the
        keyframe (:func:`datasets.kinds.attached_noise`, along ``_newest``, one call per kind; a
        spec of its one row)."""
        stream = self._imu
        stamps = np.array([item.latest for item in items])
        steps, last_dt = interval_attachment(stream.t[:stream.n], self._last_t, t, stamps)
        held = stream.held_at(stamps)
        padded = tuple(a[None] for a in samples)
        grown = [None] * len(items)
        for kind in dict.fromkeys(item.spec.kind for item in items):
            of = [m for m, item in enumerate(items) if item.spec.kind == kind]
            rows = np.stack([items[m].spec.rows[items[m].row] for m in of])
            noise = attached_noise(KINDS[kind], self._newest, padded, np.zeros(len(of), dtype=int), steps[of],
                                   last_dt[of], rows, self.noise, self.gravity)
            for m, process in zip(of, noise):
                grown[m] = items[m].spec.cov[items[m].row] + process
        out = []
        for item, n, last, i, cov in zip(items, steps, last_dt, held, grown):
            spec = item.spec
            one = replace(spec, rows=spec.rows[item.row:item.row + 1], cov=cov[None])
            out.append((one, 0, [keyframe], self._setup(item.sensor)[0].robust,
                        AttachedAt(int(n), float(last), (stream.acc[i], stream.gyro[i]))))
        return out

    def _gap(self, t: float) -> None:
        gap = t - self._last_measured_t
        self.longest_gap_s = max(self.longest_gap_s, gap)
        if not self._warned_gap:
            text = sparse_measurement_warning(gap, self.lag_s, self.kind)
            if text is not None:
                self._warned_gap = True
                warnings.warn(text, stacklevel=5)


def _fit_first(names: tuple) -> None:
    """An InputError naming the sensors ``names`` whose correlation time is still to be fitted: the
    fit needs the whole recording's held-out measurements (``smoother run``), and the run's
    ``calibrated.toml`` then carries the time for the online smoother."""
    if names:
        raise InputError(f"sensor {', '.join(map(repr, names))}: correlation_time = \"fit\" is fitted by a batch run "
                         "over a recording with held-out measurements (smoother run); start the online smoother from "
                         "that run's calibrated.toml, which carries the fitted time")
