"""The contract of a fixed-lag window: what :class:`smoother.online.smoother.OnlineSmoother` and the
offline driver (:func:`smoother.fixed_lag.offline.run_fixed_lag`) call on a window, whatever its kind
(:data:`smoother.fixed_lag.kinds.FIXED_LAG_KINDS`). Two windows keep it: the project's compiled
:class:`smoother.fixed_lag.sliding.window.SlidingWindow` and GTSAM's fixed-lag smoothers behind
:class:`smoother.fixed_lag.gtsam_window.KeyframeWindow`; :func:`smoother.fixed_lag.windows.make_window` makes the
window of a kind.

Keyframes. A window takes keyframes one at a time, in time order: keyframe ``k`` (0, 1, ... in the
order given) has a time stamp (:meth:`FixedLagWindow.time`) and, once added, an estimate
(:meth:`FixedLagWindow.state`) and a 15x15 marginal covariance (:meth:`FixedLagWindow.covariances`,
primer convention: error state ``(dr, dv, dphi, db_f, db_w)``, LEFT attitude perturbation
``C <- exp(dphi) C``). Adding a keyframe is one update of the smoother
(:meth:`FixedLagWindow.add_keyframe` from its ingredients, :meth:`FixedLagWindow.add_problem_keyframe`
from a :class:`smoother.model.problem.Problem`'s factors). The window is the keyframes ``first ..
newest`` that the smoother still holds; ``newest`` is -1 before the first update.

The lag. An update at time ``t`` marginalises the window keyframes older than ``t`` minus the lag
``lag_s`` (strictly older, GTSAM's rule): what they contribute stays as a linear prior on the
keyframes they were tied to, and their own estimates are no longer available.

Bookkeeping, the order of the calls. A keyframe's fixed-lag (smoothed) estimate is the one it has
after the last update that holds it, so the caller reads it in between:

1. after an update, before adding keyframe ``newest + 1`` at ``t_next``, the caller asks
   :meth:`FixedLagWindow.leaving` ``(t_next)`` which window keyframes that update will marginalise;
2. it reads their estimates (:meth:`~FixedLagWindow.state`, :meth:`~FixedLagWindow.covariances`)
   and records that it did with :meth:`FixedLagWindow.taken` ``(keyframes)`` -- it may take others
   too (the newest, the whole window at the end of the data);
3. it adds the keyframe at ``t_next``. A keyframe that this update marginalises without having been
   taken after the update before it is an error (a RuntimeError naming it and its time): an
   estimate older than the one the keyframe left with is never handed out.

Both windows marginalise by that rule; they differ in the newest keyframe when the next one is more
than the lag later (an IMU gap): the sliding window keeps it until the next one is added (its
``leaving`` never names the newest), GTSAM's smoothers marginalise it in the update that adds the
next one (``leaving`` names it), after adding the factors between them. Either way an IMU gap longer
than the lag keeps its IMU factor. GTSAM's windows also name the keyframes within
:data:`smoother.fixed_lag.gtsam_window.LAG_MARGIN_S` of the boundary, which may stay for one more
update: a keyframe may be taken more than once, and its estimate is the one taken last.

Failures. A keyframe that nothing ties to the window, or whose update the solver calls
indeterminant, gets a weak prior (:data:`WEAK_PRIOR_SIGMAS`) around its initial value or estimate
and is listed in ``recovered``; an update that fails beyond that raises :class:`FixedLagFailed`,
naming the keyframe and its time. Measurement factors that read a keyframe already marginalised
are skipped and counted in ``skipped``.
"""
from __future__ import annotations

from collections import deque
from typing import TYPE_CHECKING, Protocol, runtime_checkable

import numpy as np

from factors.errors import InternalError, SolverError

if TYPE_CHECKING:
    from factors import imu
    from smoother.model.problem import KeyframeFactors

#: How many of the latest entries the timing records keep (a window's ``update_s``, an online
#: smoother's ``latency_s``): every update of a day at 10 Hz (~30 MB), and no more on a robot that
#: runs for weeks.
HISTORY = 1_000_000

#: Standard deviations of the weak prior a window adds on a keyframe that nothing ties to it, or
#: whose information the solver cannot factorise (error-state order: m, m/s, rad, m/s^2, rad/s).
WEAK_PRIOR_SIGMAS = np.array([1e2] * 3 + [1e1] * 3 + [np.pi] * 3 + [1.0] * 3 + [0.1] * 3)


class FixedLagFailed(SolverError, ValueError):
    """A fixed-lag smoother failed at an update in a way that cannot be recovered."""


@runtime_checkable
class FixedLagWindow(Protocol):
    """A fixed-lag window (module docstring: the keyframes, the lag, the order of the calls).

    ``kind`` (:data:`smoother.fixed_lag.kinds.FIXED_LAG_KINDS`), ``lag_s`` [s]; the window is the
    keyframes ``first .. newest``; ``recovered``: keyframes that needed a weak prior; ``skipped``:
    factors left out because they read a keyframe already marginalised; ``weighed_alone``: measurements
    of sensors whose errors drift weighed as independent of the one before (a problem's keyframe
    factors' :class:`smoother.model.correlated.Innovation` that the window could not make, or does
    not: GTSAM's windows hold the measurements' own factors); ``update_s``: the wall time
    of each update [s] (the latest :data:`HISTORY`)."""

    kind: str
    lag_s: float
    first: int
    newest: int
    recovered: list[int]
    skipped: int
    weighed_alone: int
    update_s: deque[float]

    @property
    def newest_state(self) -> imu.ImuState:
        """The newest keyframe's estimate after the last update."""

    @property
    def calibration(self):
        """``(values, covariances)`` of the calibration variables the window estimates, after the
        last update, or None (GTSAM's windows estimate none)."""

    def time(self, k: int) -> float:
        """The time stamp of window keyframe ``k``."""

    def leaving(self, t_next: float) -> list[int]:
        """The window keyframes, oldest first, that an update at ``t_next`` marginalises: older
        than ``t_next`` minus the lag."""

    def taken(self, keyframes) -> None:
        """Record that the estimates of ``keyframes`` were read after the last update."""

    def add_keyframe(self, t: float, guess: imu.ImuState, pre=None, measurements=(), prior=None,
                     held=None) -> imu.ImuState:
        """Add keyframe ``newest + 1`` at ``t`` with the initial value ``guess``: the IMU factor of
        the preintegrated interval ``pre`` from the newest keyframe (one
        :class:`factors.preintegration.Preintegrated` interval with its covariance; None: none),
        the factors of ``measurements`` (``(spec, m, keyframes, robust, attached)``: measurement
        ``m`` of a :class:`smoother.model.problem.MeasurementSpec`, the keyframes it reads, a robust
        kernel spec or None, and where it lies in ``pre``'s interval when it is attached to the
        newest keyframe before this one -- :class:`smoother.model.problem.AttachedAt` -- or None),
        a ``prior`` ``(state, cov)`` on the new keyframe (or None) and ``held``
        ``(acc, gyro)``, the IMU reading held at ``t`` (what a calibrated time offset steps with;
        None: none). One update; returns the new keyframe's estimate."""

    def add_problem_keyframe(self, t: float, guess: imu.ImuState, made: KeyframeFactors,
                             blocks: list) -> imu.ImuState:
        """Add keyframe ``newest + 1`` of a problem at ``t`` with the initial value ``guess`` and
        the factors that become available there, ``made`` (:meth:`smoother.model.problem.Problem.keyframe_factors`;
        ``made.rows`` their rows in ``blocks``, the problem's). One update; returns the new
        keyframe's estimate."""

    def state(self, k: int) -> imu.ImuState:
        """Window keyframe ``k``'s estimate after the last update."""

    def covariances(self, wanted) -> np.ndarray:
        """The 15x15 marginal covariances (primer convention) of window keyframes ``wanted`` after
        the last update, ``(len(wanted), 15, 15)``."""

    def joint_with_next(self, wanted) -> np.ndarray | None:
        """The 30x30 joint covariances of window keyframes ``wanted`` (each before ``newest``) with
        the keyframe after each, after the last update, ``(len(wanted), 30, 30)``: the first 15
        rows and columns :meth:`covariances`', the last the next keyframe's, the blocks between
        their cross covariance (what :func:`smoother.model.between.states_between` bridges a state
        between keyframes with). None where the window does not compute them (GTSAM's)."""


class TakenKeyframes:
    """The bookkeeping of :meth:`FixedLagWindow.taken` (module docstring): which keyframe's estimate
    was read after which update."""

    def __init__(self):
        self._after: dict[int, int] = {}

    def record(self, keyframes, newest: int) -> None:
        """``keyframes`` were read after the update that added keyframe ``newest``."""
        self._after.update((j, newest) for j in keyframes)

    def leave(self, k: int, t: float, newest: int) -> None:
        """Keyframe ``k`` (at ``t``) leaves the window with the update after the one that added
        keyframe ``newest``: a RuntimeError unless it was read after that one."""
        if self._after.pop(k, None) != newest:
            raise InternalError(f"fixed-lag: keyframe {k} (t = {t:.6f} s) left the window before its estimate was "
                               "taken")
