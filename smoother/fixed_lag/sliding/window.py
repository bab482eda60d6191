"""The project's own fixed-lag smoother: a sliding window of keyframes solved incrementally on
the compiled residuals, the keyframes that leave it marginalised into a linear prior.

Why: GTSAM's fixed-lag smoothers call every project factor back through Python at each
relinearisation (a ``CustomFactor`` per factor, each handed a copy of the ``Values``); that
overhead, not the mathematics, set the cost of an online update. Here a whole update is a few
compiled calls over flat arrays: the IMU residual (:func:`factors.preintegration.residual_into`),
the sensor kernels (:func:`datasets.kinds.measure_into`,
:func:`factors.sensor_models.odometry_kernel`), the same code the batch solver, the GTSAM factors
and the EKF run. ``docs/design.md`` (fixed-lag smoothing) gives the derivation in full.

The mathematics, in the primer's convention (error state ``(dr, dv, dphi, db_f, db_w)`` of each
window keyframe, LEFT attitude increment ``C <- exp(dphi) C``):

* ISAM2's scheme on a chain: keyframe ``k`` has a linearisation point ``theta_k`` and an offset
  ``delta_k``, its estimate is ``theta_k [+] delta_k``; the factors, linearised at the
  ``theta``s, give ``H = sum J^T J``, ``g = sum J^T e`` over whitened, robustly reweighted
  residuals (GTSAM's Huber, Cauchy and Tukey weights), and each update solves ``H delta = -g``.
  A keyframe is linearised again (``theta <- theta [+] delta``, ``delta <- 0``) when its offset
  exceeds :data:`RELINEARISATION_THRESHOLD` in any component, or :data:`EARLY_RELINEARISATION`
  of it where an update assembles its factors' rows anyway; a step that would turn an attitude
  further than :data:`MAX_ATTITUDE_STEP` is shortened along its direction;
* keyframes in time order and factors that couple keyframes at most ``S`` apart (IMU factors 1,
  a relative pose its span, a drifting sensor's innovation the keyframes between its two
  measurements, :mod:`smoother.model.correlated`; the marginal prior what it ties) make ``H``
  block-banded; its Cholesky factor ``L`` (oldest keyframe first) keeps the band. Row ``k`` of
  ``L`` depends on the rows of ``H`` up to ``k`` only, so an update factorises again from the
  oldest changed row on
  (the new keyframe's factors reach ``S`` back; a relinearised keyframe's as far) and keeps the
  forward solution ``y = L^-1 (-g)`` of the rows before it; one backward solve gives every
  ``delta``;
* a keyframe older than the newest keyframe's time minus the lag is marginalised before the next
  keyframe is added: the factors touching it, linearised at the ``theta``s, are replaced by
  their Schur complement onto the keyframes they also touch, kept as the linear prior
  ``e(x) = R (x [-] x_lin) + e0`` with ``R^T R = H_mm - H_ml H_ll^-1 H_lm`` and ``R^T e0 = g_m -
  H_ml H_ll^-1 g_l`` at ``x_lin = theta`` (GTSAM keeps its marginals the same way, as linear
  factors at their linearisation point); ``[-]`` is the state's boxminus, whose attitude
  Jacobian is ``Gamma^-1(log(C C_lin^T))`` (eqs. 24, 32). The prior at keyframe 0 is such a prior
  too (``R`` the whitening of the initial covariance, ``e0 = 0``). Eliminating the oldest
  keyframes first, the rows of ``L`` after them are already the factor of that Schur complement
  (and ``y``'s rows its forward solution): no new factorisation;
* the newest keyframe never leaves before the next one is added, so an IMU gap longer than the
  lag keeps its IMU factor;
* the marginal covariance of a window keyframe is its block of ``H^-1`` (two banded triangular
  solves with 15 right-hand sides).

The block-banded linear algebra is :mod:`smoother.fixed_lag.sliding.banded`'s, the normal equations
:mod:`smoother.fixed_lag.sliding.normal_equations`'s; this module keeps the window: its keyframes in ring slots, the
update, relinearisation and marginalisation. It keeps the fixed-lag contract
(:class:`smoother.fixed_lag.contract.FixedLagWindow`: ``leaving``, ``taken``, ``add_keyframe``, ``state``,
``covariances``, ...), as GTSAM's windows do, so :class:`smoother.online.smoother.OnlineSmoother` and
:func:`smoother.fixed_lag.offline.run_fixed_lag` drive any of them.
"""
from __future__ import annotations

import time
from collections import deque
from contextlib import nullcontext

import numpy as np

from datasets.kinds import LAYOUTS, quiet_dispatch
from factors import imu, preintegration
from factors.errors import InputError, InternalError
from factors.sensor_models import MAX_ROW_WIDTH
from smoother.fixed_lag.contract import HISTORY, WEAK_PRIOR_SIGMAS, FixedLagFailed, TakenKeyframes
from smoother.fixed_lag.lag import check_lag
from smoother.fixed_lag.sliding.banded import (
    forward_solve,
    marginal_prior,
    no_border,
    semidefinite_square_root,
)
from smoother.fixed_lag.sliding.calibration import (
    RELINEARISATION_SIGMA_FRACTION,
    RELINEARISATION_WIDEST,
    WindowCalibration,
)
from smoother.fixed_lag.sliding.kernels import (
    drop_measurements,
    factorise_forward,
    factorise_forward_border,
    relinearise_offsets,
    step_window,
)
from smoother.fixed_lag.sliding.normal_equations import (
    MAX_DIM,
    ROBUST_CODES,
    LinearPrior,
    linearise,
    linearise_calibrated,
    prior_into,
    whitening_into,
)
from smoother.model.blocks import whitening
from smoother.model.robust import robust_threshold

DIM = imu.STATE_DIM
#: The most keyframes a drifting sensor's innovation may reach back (:meth:`SlidingWindow._innovation`):
#: the factor joins the keyframes of two consecutive measurements, so it widens the band of ``H``
#: to their distance, and each update refactorises that many rows of that width -- across a gap
#: in the measurements, under a lag longer than it, a window's work grows with the gap's square
#: (an 8 s gap at 10 Hz keyframes: 60 times the white window's). Further apart, the measurement is
#: weighed alone and counted: at 64 keyframes (6.4 s on a 10 Hz grid) a GNSS used every 5 s keeps
#: its innovations.
MAX_INNOVATION_SPAN = 64
#: How far a keyframe's estimate may move from its linearisation point before its factors are
#: linearised again, per error-state component ``(dr [m], dv [m/s], dphi [rad], db_f [m/s^2],
#: db_w [rad/s])`` (ISAM2's relinearisation threshold, per component). The residuals are linear in
#: position and accelerometer bias, bilinear in velocity and attitude and nearly linear in the gyro
#: bias, so what is left out is second order in these offsets: on the benchmark's run the
#: estimates stay within 0.02 sigma of relinearising every keyframe at every update
#: (``docs/performance.md``), with about 0.1 keyframes relinearised per update instead of all 20.
RELINEARISATION_THRESHOLD = np.array([0.05] * 3 + [0.05] * 3 + [5e-3] * 3 + [0.05] * 3 + [2e-3] * 3)
#: An update that assembles the rows from some keyframe on anyway first linearises again, at no
#: assembly of its own, what those rows hold and has moved this fraction of the way to being
#: linearised again: each keyframe whose factors lie wholly in them with an offset beyond this
#: fraction of :data:`RELINEARISATION_THRESHOLD`, and, when they are the whole window, each
#: calibration beyond this fraction of its limit
#: (:data:`smoother.fixed_lag.sliding.calibration.CALIBRATION_RELINEARISATION_THRESHOLD`). A keyframe
#: or a calibration so reset no longer forces a deeper update of its own a few updates later. On
#: the benchmark's minute with the wheels calibrated, the share of updates that assemble more than
#: three rows falls from 0.20 to 0.13; without calibration from 0.13 to 0.085.
EARLY_RELINEARISATION = 0.5
#: No update turns an attitude further than this [rad]: a longer Gauss-Newton step -- a large
#: correction, such as a fix after a long dead-reckoned gap, taken from linearisation points that
#: far off -- is shortened to it along its direction (every offset scaled alike), and the next
#: updates go on from there. Without it a start whose heading nothing observed for minutes, then
#: fixes 10 s apart with a 2-s lag, swung the heading round and ran 190 m off (a real recording;
#: with it 7.6 m, GTSAM's ISAM2 7.2 m).
MAX_ATTITUDE_STEP = 0.2


_compiled = False


def keeps_innovation(earlier, reads, first):
    """Whether a window whose oldest keyframe is ``first`` makes a drifting measurement's innovation
    on the one before it, whose keyframe is ``earlier``, the measurement reading keyframes up to
    ``reads`` (arrays or numbers alike): the earlier keyframe is still in the window and at most
    :data:`MAX_INNOVATION_SPAN` keyframes back. Otherwise the window weighs the measurement alone
    (:meth:`SlidingWindow._innovation`; :mod:`smoother.diagnosis.residual_windowed` judges by it)."""
    return (np.asarray(reads) - earlier <= MAX_INNOVATION_SPAN) & (np.asarray(earlier) >= first)


def _compiling():
    """:func:`datasets.kinds.quiet_dispatch` around the first call (which compiles or loads
    :func:`linearise`), nothing after: the warning filters cost more than an update's mathematics."""
    global _compiled
    if _compiled:
        return nullcontext()
    _compiled = True
    return quiet_dispatch()


class SlidingWindow:
    """The compiled fixed-lag smoother (module docstring), fed one keyframe at a time: a window of the
    fixed-lag contract (:class:`smoother.fixed_lag.contract.FixedLagWindow`: the keyframes, the lag,
    :meth:`leaving` and :meth:`taken` and the order of the calls).

    ``lag_s``: keyframes older than the new keyframe's time minus the lag leave at its update;
    ``gravity`` (world, m/s^2) and ``reintegration_threshold`` (rad/s) as the IMU factor's;
    ``relinearisation_threshold`` (15 numbers in the error state's units, or one for all): a
    keyframe is linearised again when its offset from its linearisation point exceeds it in any
    component (0: every keyframe at every update). ``calibration``: the calibration variables
    (:class:`smoother.fixed_lag.sliding.calibration.WindowCalibration`), the window's dense border, or None."""

    kind = "sliding"

    def __init__(self, lag_s: float, gravity=imu.DEFAULT_GRAVITY,
                 reintegration_threshold: float = preintegration.REINTEGRATION_THRESHOLD,
                 relinearisation_threshold=None, calibration: WindowCalibration | None = None):
        lag_s = check_lag(lag_s)
        threshold = RELINEARISATION_THRESHOLD if relinearisation_threshold is None else relinearisation_threshold
        threshold = np.broadcast_to(np.asarray(threshold, dtype=float), (DIM,)).copy()
        if not np.all(threshold >= 0):
            raise InputError(f"relinearisation_threshold: expected numbers >= 0, got {threshold.tolist()}")
        self.lag_s = float(lag_s)
        self.gravity = np.asarray(gravity, dtype=float)
        self.reintegration_threshold = float(reintegration_threshold)
        self.relinearisation_threshold = threshold
        self.first, self.newest = 0, -1
        self.recovered: list[int] = []
        self.skipped = 0
        #: measurements of drifting sensors weighed as independent of the one before
        #: (:meth:`_innovation`): it had left the window, or lay too many keyframes before
        self.weighed_alone = 0
        self.update_s: deque[float] = deque(maxlen=HISTORY)
        #: keyframes linearised again, one entry each time any were: at the end of an update, or early,
        #: before its assembly (an update can have two)
        self.relinearised: deque[int] = deque(maxlen=HISTORY)
        #: updates whose step was shortened (MAX_ATTITUDE_STEP)
        self.shortened = 0
        self._taken = TakenKeyframes()
        self._priors: list[LinearPrior] = []
        self._S = 1  # the band L is factorised with (at least the factors' reach; narrowed at whole factorisations)
        self._spans = [0, 0]  # the longest span of the measurements, of the priors
        self._stale = 0  # the rows of L (and of the forward solution) from this keyframe on are stale
        self._cal = calibration
        nc = 0 if calibration is None else calibration.nc
        # the border's rows of L by slot (module smoother.fixed_lag.sliding.calibration)
        self._Z = np.zeros((0, DIM, nc))
        self._ZZ = np.zeros((0, nc, nc + 1))  # their products Z_k^T [Z_k, y_k] by slot (banded.border_solve)
        self._K = 1  # the steps an interval's samples hold room for (_sacc, _sgyro, _sdt), grown as needed
        self._allocate_keyframes(64)
        self._allocate_measurements(64)
        self._m = 0

    # -- storage ----------------------------------------------------------------------------------

    def _allocate_keyframes(self, cap: int) -> None:
        """Ring arrays for ``cap`` keyframes (slot ``k % cap``), the window's moved over."""
        shapes = {"_t": (), "_r": (3,), "_v": (3,), "_C": (3, 3), "_bf": (3,), "_bw": (3,),
                  "_xr": (3,), "_xv": (3,), "_xC": (3, 3), "_xbf": (3,), "_xbw": (3,), "_dx": (DIM, 1), "_y": (DIM, 1),
                  "_L": (self._L.shape[1] if hasattr(self, "_L") else self._S + 1, DIM, DIM), "_dC": (3, 3),
                  "_Wp": (3, 10), "_Rm": (3, 10), "_JC": (3, 3), "_dW": (3, 10, 3), "_dRm": (3, 10, 3),
                  "_bwbar": (3,), "_Wimu": (DIM, DIM), "_hacc": (3,), "_hgyro": (3,), "_Z": (DIM, self._Z.shape[2]),
                  "_ZZ": self._ZZ.shape[1:], "_kH": (1, 1, DIM, DIM), "_kg": (DIM,), "_kB": (1, DIM, self._Z.shape[2]),
                  "_sacc": (self._K, 3), "_sgyro": (self._K, 3), "_sdt": (self._K,)}
        old = {name: getattr(self, name, None) for name in shapes}
        old_imu, old_pre, old_cap = (getattr(self, "_has_imu", None), getattr(self, "_pre", None),
                                     getattr(self, "_cap", 0))
        old_kept = getattr(self, "_kept", None)
        self._cap = cap
        for name, tail in shapes.items():
            setattr(self, name, np.zeros((cap,) + tail))
        self._has_imu = np.zeros(cap, dtype=np.bool_)
        # whether _kH, _kg, _kB hold the keyframe's sums (linearise_calibrated)
        self._kept = np.zeros(cap, dtype=np.bool_)
        self._moved = np.zeros(cap, dtype=np.bool_)
        self._pre = [None] * cap
        for k in range(self.first, self.newest + 1):  # the window, moved to its new slots
            a, b = k % old_cap, k % cap
            for name in shapes:  # (an interval's samples into the leading steps of wider rows)
                getattr(self, name)[(b, *(slice(0, n) for n in old[name].shape[1:]))] = old[name][a]
            self._has_imu[b], self._pre[b], self._kept[b] = old_imu[a], old_pre[a], old_kept[a]

    def _allocate_measurements(self, cap: int) -> None:
        """Measurement tables for ``cap`` rows, the current ones kept."""
        m = getattr(self, "_m", 0)
        shapes = {"_mk": ((2,), np.int64), "_model": ((), np.int64), "_rows": ((MAX_ROW_WIDTH,), float),
                  "_dims": ((), np.int64), "_Wm": ((MAX_DIM, MAX_DIM), float), "_rcode": ((), np.int64),
                  "_rk": ((), float), "_mcal": ((), np.int64), "_mD": ((8, 8), float), "_mg": ((8,), float),
                  "_mstep": ((), np.int64), "_mlast": ((), float), "_macc": ((3,), float), "_mgyro": ((3,), float),
                  # a drifting sensor's innovation (linearise): its weights, the earlier measurement's
                  # row, whitening and attachment
                  "_dc": ((), float), "_ds": ((), float), "_drow": ((MAX_ROW_WIDTH,), float),
                  "_dWm": ((MAX_DIM, MAX_DIM), float), "_dstep": ((), np.int64), "_dlast": ((), float),
                  "_dacc": ((3,), float), "_dgyro": ((3,), float)}
        for name, (tail, dtype) in shapes.items():
            fresh = np.zeros((cap,) + tail, dtype=dtype)
            if m:
                fresh[:m] = getattr(self, name)[:m]
            setattr(self, name, fresh)

    def _linearisation_points(self):
        """The ``theta`` arrays ``(r, v, C, b_f, b_w)`` by slot."""
        return self._r, self._v, self._C, self._bf, self._bw

    def _estimates(self):
        """The estimate arrays ``theta [+] delta`` by slot."""
        return self._xr, self._xv, self._xC, self._xbf, self._xbw

    # -- the fixed-lag contract ------------------------------------------------------------------

    def time(self, k: int) -> float:
        """The time stamp of window keyframe ``k``."""
        return float(self._t[k % self._cap])

    def leaving(self, t_next: float) -> list[int]:
        """The window keyframes an update at ``t_next`` marginalises: older than ``t_next`` minus the
        lag (as GTSAM's smoothers count it), never the newest."""
        boundary = t_next - self.lag_s
        out = []
        for j in range(self.first, self.newest):
            if self.time(j) >= boundary:
                break
            out.append(j)
        return out

    def taken(self, keyframes) -> None:
        """Record that the estimates of ``keyframes`` were read after the last update."""
        self._taken.record(keyframes, self.newest)

    def state(self, k: int) -> imu.ImuState:
        """Window keyframe ``k``'s estimate after the last update."""
        s = k % self._cap
        return imu.ImuState(self._xr[s].copy(), self._xv[s].copy(), self._xC[s].copy(), self._xbf[s].copy(),
                            self._xbw[s].copy())

    @property
    def newest_state(self) -> imu.ImuState:
        """The newest keyframe's estimate after the last update."""
        return self.state(self.newest)

    def add_keyframe(self, t: float, guess: imu.ImuState, pre=None, measurements=(), prior=None,
                     held=None) -> imu.ImuState:
        """Add keyframe ``newest + 1`` at ``t`` with the initial value ``guess``, the preintegrated
        interval ``pre`` from the newest keyframe (one :class:`factors.preintegration.Preintegrated`
        interval with its covariance; None: no IMU factor), ``measurements`` (``(spec, m,
        keyframes, robust)``: measurement ``m`` of a :class:`smoother.model.problem.MeasurementSpec`, the
        keyframes it reads, a robust spec or None), ``prior`` ``(state, cov)`` on the new
        keyframe and ``held`` ``(acc, gyro)``, the IMU reading held at ``t`` (what a calibrated
        time offset steps with; None: zero); one update (module docstring); returns the new
        keyframe's estimate.
        Measurements reading a keyframe that leaves are skipped and counted in ``skipped``. What
        can be refused (a covariance that is not positive definite, an unknown robust kernel) is
        refused before the window changes."""
        tick = time.perf_counter()
        k = self.newest + 1
        leaving = self.leaving(t)
        first = leaving[-1] + 1 if leaving else self.first
        interval = None
        if pre is not None and k > 0:
            interval = np.zeros((DIM, DIM))
            if not whitening_into(pre.cov, interval):
                raise InputError("the IMU interval's covariance is not positive definite")
        taken = [(measurement, *self._innovation(measurement, first)) for measurement in measurements
                 if min(measurement[2]) >= first]
        factors = [self._measurement_row(*measurement[:5], innovation) for measurement, innovation, _ in taken]
        priors = [] if prior is None else [(prior[0], whitening(prior[1]))]
        self.skipped += len(measurements) - len(factors)
        self.weighed_alone += sum(alone for _, _, alone in taken)
        self._marginalise(leaving)
        if interval is not None and len(pre.samples[2]) > self._K:  # room for the interval's samples
            self._K = max(len(pre.samples[2]), 2 * self._K)
            self._allocate_keyframes(self._cap)
        if k - self.first + 1 > self._cap:
            self._allocate_keyframes(2 * self._cap)
        s = k % self._cap
        self._t[s] = t
        for arrays in (self._linearisation_points(), self._estimates()):
            for a, value in zip(arrays, (guess.r, guess.v, guess.C, guess.b_f, guess.b_w)):
                a[s] = value
        self._dx[s] = 0.0
        if held is None and self._cal is not None and self._cal.steps_in_time:
            raise InputError("add_keyframe: held: a calibrated time offset needs the IMU reading held at the keyframe")
        self._hacc[s], self._hgyro[s] = (0.0, 0.0) if held is None else held
        self._has_imu[s] = self._kept[s] = False
        self._pre[s] = None
        linked = k == 0 or interval is not None
        if interval is not None:
            self._store_interval(s, pre, interval)
        for row in factors:
            self._add_measurement(*row[1:], -1 if self._cal is None else self._cal.index.get(row[0].name, -1))
            keyframes = row[7]
            linked = linked or (len(keyframes) > 1 and min(keyframes) < k == max(keyframes))
        self.newest = k
        if not linked:  # nothing ties the new keyframe to the window: a weak prior around its guess
            priors.append((guess, whitening(np.diag(WEAK_PRIOR_SIGMAS ** 2))))
            self.recovered.append(k)
        for state, R in priors:
            self._add_prior(k, state, R)
        self._solve(t)
        self.update_s.append(time.perf_counter() - tick)
        return self.newest_state

    def add_problem_keyframe(self, t: float, guess: imu.ImuState, made, blocks=None) -> imu.ImuState:
        """:meth:`add_keyframe` with what the factors a problem makes at the keyframe are made of
        (``made``, :class:`smoother.model.problem.KeyframeFactors`: its IMU factor's interval, its
        measurements, its prior); the window linearises them itself (``blocks`` is not used) and
        estimates no calibration (the values given are used, as in the problem's factors)."""
        return self.add_keyframe(t, guess, None if made.imu is None else made.imu.pre, made.measurements, made.prior)

    def covariances(self, wanted) -> np.ndarray:
        """The 15x15 marginal covariances (primer convention) of window keyframes ``wanted``: blocks
        of ``H^-1`` with ``H`` at the linearisation points of the last update's solve (before the
        keyframes it moved far enough were linearised again; with calibrations, ``A^-1`` plus their
        share, :mod:`smoother.fixed_lag.sliding.calibration`). With ``X = L_A^-1 E_k`` (``E_k`` keyframe
        ``k``'s columns of the identity; its blocks before ``k`` are zero) keyframe ``k``'s block
        of ``A^-1 = L_A^-T L_A^-1`` is ``X^T X``, and its row of ``W = L_A^-T Z`` is ``X^T Z``: one
        forward solve over the keyframes ``k .. newest`` and two products -- the newest keyframe's
        costs a block, the oldest's the window."""
        return self._joint(wanted, 1)

    def joint_with_next(self, wanted) -> np.ndarray:
        """The 30x30 joint covariances of window keyframes ``wanted`` (each before ``newest``) with
        the keyframe after each (:meth:`smoother.fixed_lag.contract.FixedLagWindow.joint_with_next`):
        :meth:`covariances`' solve with the columns of both keyframes, ``X = L_A^-1 [E_k E_(k+1)]``,
        and ``X^T X`` (with the calibrations' share ``W Sigma_cc W^T``, ``W = X^T Z``)."""
        if any(int(k) >= self.newest for k in wanted):
            raise InternalError(f"joint_with_next: keyframes {list(wanted)} include the newest, {self.newest}")
        return self._joint(wanted, 2)

    def joint_span(self, k: int, count: int) -> np.ndarray:
        """The joint covariance ``(15 count, 15 count)`` of window keyframes ``k .. k + count - 1``
        after the last update (:meth:`covariances`' solve with their columns)."""
        if not (self.first <= k and k + count - 1 <= self.newest and count >= 1):
            raise InternalError(f"joint_span: keyframes {k}..{k + count - 1} are not all in the window "
                                f"({self.first}..{self.newest})")
        return self._joint([k], count)[0]

    def _joint(self, wanted, count: int) -> np.ndarray:
        """The joint covariances of the ``count`` keyframes from each of ``wanted`` on."""
        cap = self._cap
        Sigma_cc = None if self._cal is None else self._cal.joint_covariance()
        width = count * DIM
        b = np.empty((cap, DIM, width))
        out = []
        for k in (int(k) for k in wanted):
            slots = np.arange(k, self.newest + 1) % cap
            b[slots] = 0.0
            for i in range(count):
                b[(k + i) % cap, :, i * DIM:(i + 1) * DIM] = np.eye(DIM)
            forward_solve(self._L, b, self.first, k, k, self.newest, cap, self._S)
            X = b[slots].reshape(-1, width)
            cov = X.T @ X
            if Sigma_cc is not None:
                W = X.T @ self._Z[slots].reshape(-1, self._Z.shape[2])
                cov = cov + W @ Sigma_cc @ W.T
            out.append(0.5 * (cov + cov.T))
        return np.stack(out) if out else np.zeros((0, width, width))

    @property
    def calibration(self):
        """The calibration variables after the last update and their marginal covariances
        (:meth:`smoother.fixed_lag.sliding.calibration.WindowCalibration.estimate`, ``.covariance``), or None."""
        if self._cal is None:
            return None
        return self._cal.estimate(), self._cal.covariance()

    # -- inside -----------------------------------------------------------------------------------

    def _store_interval(self, s: int, pre, whitening_matrix=None) -> None:
        """Keep interval ``pre`` at slot ``s``, with the whitening of its covariance (None: keep the
        slot's: an interval integrated again keeps its covariance), and its samples (what the
        measurements attached to its first keyframe are predicted through)."""
        self._has_imu[s] = True
        self._pre[s] = pre
        for name, value in (("_dC", pre.dC), ("_Wp", pre.W), ("_Rm", pre.Rm), ("_JC", pre.JC), ("_dW", pre.dW),
                            ("_dRm", pre.dRm), ("_bwbar", pre.b_w_bar)):
            getattr(self, name)[s] = value
        if whitening_matrix is not None:
            self._Wimu[s] = whitening_matrix
            acc, gyro, dt = pre.samples  # (add_keyframe made room for them)
            self._sacc[s, :len(dt)], self._sgyro[s, :len(dt)], self._sdt[s, :len(dt)] = acc, gyro, dt
            self._sdt[s, len(dt):] = 0.0

    def _innovation(self, measurement, first: int):
        """The :class:`smoother.model.correlated.Innovation` of a problem's ``measurement`` (its sixth
        entry, where it has one) that this window can make, or None; with whether it was one the
        window weighs alone instead (its own white factor, counted in :attr:`weighed_alone`): the
        measurement before it reads a keyframe before ``first`` (gone, with the update) or more
        than :data:`MAX_INNOVATION_SPAN` keyframes before the one it reads."""
        innovation = measurement[5] if len(measurement) > 5 else None
        if innovation is None:
            return None, False
        if not keeps_innovation(innovation.keyframe, max(measurement[2]), first):
            return None, True
        return innovation, False

    @staticmethod
    def _whitening(spec, m: int) -> np.ndarray:
        """The whitening of measurement ``m`` of ``spec`` in a ``(MAX_DIM, MAX_DIM)`` array; an
        InputError if its covariance is not positive definite."""
        cov = np.ascontiguousarray(spec.cov[m], dtype=float)
        W = np.zeros((MAX_DIM, MAX_DIM))
        if not whitening_into(cov, W):
            raise InputError(f"a measurement's covariance is not positive definite: {cov.tolist()}")
        return W

    @classmethod
    def _measurement_row(cls, spec, m: int, keyframes, robust, attached=None, innovation=None) -> tuple:
        """Measurement ``m`` of ``spec`` as ``spec`` and the arguments of :meth:`_add_measurement`, checked:
        its covariance's whitening (an InputError if it is not positive definite) and robust code;
        ``attached``: where it lies in the interval after its keyframe
        (:class:`smoother.model.problem.AttachedAt`), None at its keyframe's time; ``innovation``:
        None, or the measurement as its innovation on the one before
        (:class:`smoother.model.correlated.Innovation`), whose keyframe it then reads too."""
        W = cls._whitening(spec, m)
        d = spec.cov.shape[-1]
        if robust is not None and robust[0] not in ROBUST_CODES:
            raise InputError(f"robust kernel {robust[0]!r}: expected one of {', '.join(ROBUST_CODES)}")
        code, k = (0, 0.0) if robust is None else (ROBUST_CODES[robust[0]], robust_threshold(robust, d))
        drift = None
        if innovation is not None:
            keyframes = [innovation.keyframe, *keyframes]
            drift = (innovation.c, innovation.s, innovation.spec.rows[innovation.row],
                     cls._whitening(innovation.spec, innovation.row), innovation.attached)
        return spec, spec.model, spec.rows[m], W, d, code, k, keyframes, attached, drift

    def _add_measurement(self, model: int, row, W, d: int, code: int, k: float, keyframes, attached, drift,
                         calibration: int) -> None:
        """Append a checked measurement (:meth:`_measurement_row`) that reads ``calibration`` (its
        index in the window's calibrations, -1: none); the rows of ``L`` from its oldest keyframe
        on are stale, and the sums that keyframe's calibrated measurements keep are dropped.
        ``drift``: None, or ``(c, s, row, W, attached)`` of its innovation on the measurement before
        it (that one's packed row, whitening and attachment), on ``keyframes`` (the earlier one's
        keyframe first)."""
        if self._m == len(self._mk):
            self._allocate_measurements(2 * len(self._mk))
        f = self._m
        self._mk[f] = (min(keyframes), max(keyframes))
        self._spans[0] = max(self._spans[0], max(keyframes) - min(keyframes))
        self._model[f] = model
        self._rows[f, :len(row)] = row
        self._dims[f] = d
        self._Wm[f] = W
        self._rcode[f] = code
        self._rk[f] = k
        self._mcal[f] = calibration
        if attached is None:
            self._mstep[f], self._mlast[f] = 0, 0.0
        else:
            self._mstep[f], self._mlast[f] = attached.steps, attached.last_dt
            self._macc[f], self._mgyro[f] = attached.held
        self._dc[f], self._ds[f], self._dstep[f], self._dlast[f] = 0.0, 1.0, 0, 0.0
        if drift is not None:
            self._dc[f], self._ds[f], self._drow[f, :len(drift[2])], self._dWm[f] = drift[:4]
            if drift[4] is not None:
                self._dstep[f], self._dlast[f] = drift[4].steps, drift[4].last_dt
                self._dacc[f], self._dgyro[f] = drift[4].held
        self._m = f + 1
        self._stale = min(self._stale, min(keyframes))
        self._kept[min(keyframes) % self._cap] = False

    def _add_prior(self, k: int, state: imu.ImuState, R: np.ndarray) -> None:
        """A prior ``R (x_k [-] state)`` on keyframe ``k`` (``R`` the whitening of its covariance)."""
        self._priors.append(LinearPrior(np.array([k]), state.r[None].copy(), state.v[None].copy(),
                                         state.C[None].copy(), state.b_f[None].copy(), state.b_w[None].copy(),
                                         R, np.zeros(DIM)))
        self._stale = min(self._stale, k)

    def _relinearised(self, oldest: int) -> None:
        """After keyframes ``oldest ..`` (those flagged in ``_moved``) were linearised again, at the end
        of an update (:func:`_step`) or before its assembly (:meth:`_relinearise_early`):
        integrate again the intervals out of those whose gyro bias moved beyond the reintegration
        threshold, drop the sums their calibrated measurements keep (``_kept``) and mark the rows
        of ``L`` their factors change as stale."""
        moved = [k for k in range(oldest, self.newest + 1) if self._moved[k % self._cap]]
        self.relinearised.append(len(moved))
        self._kept[self._moved] = False
        for i in moved:
            j = (i + 1) % self._cap
            drift = np.max(np.abs(self._bw[i % self._cap] - self._bwbar[j]))
            if i < self.newest and self._has_imu[j] and drift > self.reintegration_threshold:
                self._store_interval(j, self._pre[j].relinearized(self._bw[i % self._cap]))
        # the factors of a moved keyframe reach at most the bandwidth back
        self._stale = min(self._stale, oldest - self._bandwidth())

    def _bandwidth(self) -> int:
        """How many keyframes back the longest factor reaches (IMU factors: 1)."""
        return max(1, *self._spans)

    def _states(self, keyframes) -> imu.ImuState:
        """The linearisation points of window keyframes ``keyframes`` (an array)."""
        slots = np.asarray(keyframes) % self._cap
        return imu.ImuState(*(a[slots] for a in self._linearisation_points()))

    def _attachments(self) -> tuple:
        """What the kernels read of the measurements attached to a keyframe: per measurement the
        steps of its keyframe's interval and the last one's length (0 steps: at its keyframe's
        time) and the IMU reading held at its stamp; per slot the samples of the interval into it."""
        return self._mstep, self._mlast, self._macc, self._mgyro, self._sacc, self._sgyro, self._sdt

    def _innovations(self) -> tuple:
        """What :func:`smoother.fixed_lag.sliding.normal_equations.linearise` reads of the drifting
        sensors' innovations: per measurement the weights ``c``, ``s`` (``c = 0``: its own factor),
        the earlier measurement's row, whitening and attachment."""
        return self._dc, self._ds, self._drow, self._dWm, self._dstep, self._dlast

    def _calibrated_innovations(self) -> tuple:
        """:meth:`_innovations` and the IMU reading held at each earlier measurement's stamp, what
        :func:`smoother.fixed_lag.sliding.normal_equations.linearise_calibrated` reads."""
        return *self._innovations(), self._dacc, self._dgyro

    def _normal_equations(self, lo: int, cut: int, n: int, S: int, solving: bool = True):
        """Rows ``lo .. lo + n - 1`` of the normal equations at the linearisation points, of the
        factors that begin before keyframe ``cut``: block-banded ``Hb (n, S + 1, 15, 15)``, ``g``
        and their border ``(B, D, g_c)`` on the calibrations (``nc = 0`` columns without;
        :mod:`smoother.fixed_lag.sliding.calibration`): ``D``, ``g_c`` of every factor reading a calibration
        that begins before ``cut``, whichever rows it reaches, and of the priors on the
        calibrations alone; when ``solving``, of every bordered prior and of the calibrations'
        own priors too."""
        Hb = np.zeros((n, S + 1, DIM, DIM))
        g = np.zeros(n * DIM)
        cal = self._cal
        if cal is None:
            B, D, gc = no_border(n)
        else:  # D, g_c from the calibrations' own priors when solving
            B = np.zeros((n, DIM, cal.nc))
            D, gc = (cal.own_prior[0].copy(), cal.own_prior[1].copy()) if solving else (np.zeros((cal.nc, cal.nc)),
                                                                                        np.zeros(cal.nc))
        with _compiling():
            linearise(self.first, lo, cut, self._cap, *self._linearisation_points(), self._has_imu, self._dC,
                       self._Wp, self._Rm, self._JC, self._dW, self._dRm, self._bwbar, self._Wimu, self.gravity,
                       self._m, self._mk, self._model, self._rows, self._dims, self._Wm, self._rcode, self._rk,
                       self._mcal, *self._attachments(), *self._innovations(), Hb, g)
            if cal is not None:
                linearise_calibrated(lo, cut, self._cap, *self._linearisation_points(), self.gravity, self._m,
                                      self._mk, self._model, self._rows, self._dims, self._Wm, self._rcode, self._rk,
                                      self._mcal, self._mD, self._mg, self._kH, self._kg, self._kB, self._kept,
                                      cal.packed, cal.with_time, cal.columns, LAYOUTS,
                                      self._hacc, self._hgyro, *self._attachments(), *self._calibrated_innovations(),
                                      Hb, g, B, D, gc)
        plain = None if cal is not None else (B, D, gc)
        for p in self._priors:
            bordered = p.c_lin is not None
            reaches = p.keyframes.size and p.keyframes[0] < cut and p.keyframes[-1] >= lo
            if not (reaches or (bordered and (solving or not p.keyframes.size))):
                continue
            # a bordered prior's share of D, g_c is kept as a calibrated row's is, but for one the
            # marginal being made replaces
            keeps = bordered and (solving or not reaches)
            if not bordered:
                plain = into = no_border(n) if plain is None else plain
            elif not keeps:
                into = B, D, gc
            elif reaches or p.own is None:
                p.own = np.zeros((cal.nc, cal.nc)), np.zeros(cal.nc)
                into = (B, *p.own)
            else:
                into = None
            if into is not None:
                prior_into(p.keyframes, p.r, p.v, p.C, p.b_f, p.b_w, p.R, p.e0, p.dc, p.Jdc, self._cap,
                            *self._linearisation_points(), lo, Hb, g, *into)
            if keeps:
                D += p.own[0]
                gc += p.own[1]
        return Hb, g, (B, D, gc)

    def _solve(self, t: float) -> None:
        """Factorise the rows of ``H`` that changed (those of the new keyframe's factors and of the
        keyframes linearised again, and everything after them), solve ``H delta = -g`` at the
        linearisation points, set the estimates to ``theta [+] delta``. A keyframe whose
        information is not positive definite (nothing in the window determines some part of it)
        gets a weak prior about its estimate (:data:`WEAK_PRIOR_SIGMAS`, recorded in
        ``recovered``) and the window is factorised again; if it still fails, the update does."""
        for attempt in range(2):
            failed = self._solve_once()
            if failed < 0:
                return
            self._stale = self.first  # the next factorisation covers the whole window again
            if attempt == 0:
                self._add_prior(failed, self.state(failed), whitening(np.diag(WEAK_PRIOR_SIGMAS ** 2)))
                self.recovered.append(failed)
        raise FixedLagFailed(f"the fixed-lag smoother failed at keyframe {self.newest} (t = {t:.6f} s): the "
                             f"information of keyframe {failed} (t = {self.time(failed):.6f} s) is not positive "
                             "definite even with a weak prior on it: the window's information spans more orders of "
                             "magnitude than double precision holds (keyframes a few microseconds apart, or a sensor "
                             "many orders more precise than the rest)")

    def _solve_once(self) -> int:
        """One factorisation and solve of :meth:`_solve`; returns -1, or the keyframe whose pivot
        failed (the estimates then unchanged)."""
        reach = self._bandwidth()
        if reach > self._S:  # a wider band: L anew, the whole window factorised
            self._L = np.zeros((self._cap, reach + 1, DIM, DIM))
            self._S, self._stale = reach, self.first
        start = max(min(self._stale, self.newest - reach), self.first)
        self._relinearise_early(start, reach)
        if start == self.first:  # factorised whole: the band the factors need now (it narrows as they leave)
            self._S = reach
        S = self._S
        Hr, g, border = self._normal_equations(start, self.newest + 1, self.newest - start + 1, S)
        before = self._dx.copy()
        if self._cal is None:
            failed = factorise_forward(Hr, g, self._L, self._y, self.first, start, self.newest, self._cap, S)
            if failed >= 0:
                return failed
            self._dx[:] = self._y
            exceeds = False
        else:
            before_c, delta_c = self._cal.delta.copy(), np.empty(self._cal.nc)
            failed, code = factorise_forward_border(Hr, g, self._L, self._y, self.first, start, self.newest,
                                                     self._cap, S, self._Z, self._ZZ, *border, self._dx,
                                                     self._cal.L_D, delta_c, self._cal.thresholds,
                                                     RELINEARISATION_SIGMA_FRACTION, RELINEARISATION_WIDEST,
                                                     self._cal.limits)
            if failed >= 0:
                return failed
            exceeds, shortened = code == 1, False
            if code < 0:
                self._dx[:] = before  # the estimates unchanged
                self._stale = self.first
                raise FixedLagFailed(
                    f"the fixed-lag smoother failed at keyframe {self.newest} (t = {self.time(self.newest):.6f} s): "
                    f"the calibrations of {', '.join(self._cal.set.names)} have an information that is not positive "
                    "definite after the keyframes' share (their priors' sigmas span more orders of magnitude than "
                    "the data determine them to, or a sensor is many orders more precise than the rest)")
            bounded = self._cal.bounded(before_c, delta_c)
            if bounded is not None:  # the keyframes' step given the calibrations' shortened one: dx = y - Z delta_c
                slots = np.arange(self.first, self.newest + 1) % self._cap
                self._dx[slots] += self._Z[slots] @ (delta_c - bounded)[:, None]
                delta_c, exceeds, shortened = bounded, True, True
            self._cal.delta = delta_c
        oldest, a = step_window(self._L, self._dx, before, self.first, self.newest, self._cap, S,
                          self.relinearisation_threshold, MAX_ATTITUDE_STEP, self._moved, *self._linearisation_points(),
                          *self._estimates())
        self._stale = self.newest + 1
        self.shortened += a < 1.0
        if self._cal is not None:
            if a < 1.0:  # the calibrations' step shortened with the keyframes'
                self._cal.delta = before_c + a * (self._cal.delta - before_c)
            # every factor reading a calibration changes; a shortened one is linearised again where it stopped
            if (exceeds or a < 1.0) and self._cal.relinearise(0.0 if shortened else 1.0):
                self._calibrations_moved()
        if oldest >= 0:
            self._relinearised(oldest)
        return -1

    def _relinearise_early(self, start: int, reach: int) -> None:
        """Before the rows from keyframe ``start`` on are assembled: linearise again the keyframes
        whose factors lie wholly in them (``start + reach ..``, ``reach`` the factors' reach) and
        whose offset exceeds :data:`EARLY_RELINEARISATION` of the threshold, and, when they are
        the whole window, the calibrations whose offset exceeds that fraction of their limits;
        no row before ``start`` becomes stale (nor anything moves when those keyframes are the newest
        alone: it was added at its estimate)."""
        if start + reach < self.newest:
            oldest = relinearise_offsets(start + reach, self.newest, self._cap, self._dx,
                                  EARLY_RELINEARISATION * self.relinearisation_threshold,
                                  *self._linearisation_points(), *self._estimates(), self._moved)
            if oldest >= 0:
                self._relinearised(oldest)
        if self._cal is not None and start == self.first and self._cal.relinearise(EARLY_RELINEARISATION):
            self._calibrations_moved()

    def _calibrations_moved(self) -> None:
        """After calibrations were linearised again: the bordered priors' calibration coordinates
        anew, the sums the calibrated measurements keep dropped, and the rows of ``L`` (and of the
        border) of every keyframe a factor reading a calibration reads are stale."""
        oldest = self.newest + 1
        for p in self._priors:
            if p.c_lin is not None:
                p.dc, p.Jdc = self._cal.border_of(p.c_lin)
                p.own = None
                if p.keyframes.size:
                    oldest = min(oldest, int(p.keyframes[0]))
        self._kept[:] = False
        reads = self._mcal[:self._m] >= 0
        if reads.any():
            oldest = min(oldest, int(self._mk[:self._m][reads, 0].min()))
        self._stale = min(self._stale, max(oldest, self.first))

    def _marginalise(self, leaving: list[int]) -> None:
        """Replace the factors touching ``leaving`` (the oldest window keyframes) by their Schur
        complement onto the keyframes they also touch, a :class:`LinearPrior` at their
        linearisation points -- on the calibrations too when it informs them, which also takes
        in the priors on the calibrations alone. The rows of ``L`` (and of the border ``Z``) after
        ``leaving`` stay: eliminating the oldest keyframes first, they are the factor of that
        Schur complement already."""
        if not leaving:
            return
        for j in leaving:
            self._taken.leave(j, self.time(j), self.newest)
        cut = leaving[-1] + 1
        S = self._bandwidth()
        nl = cut - self.first
        n = min(self.newest - self.first + 1, nl + S)
        Hb, g, (B, D, gc) = self._normal_equations(self.first, cut, n, S, solving=False)
        bordered = self._cal is not None and np.count_nonzero(D) > 0  # (B != 0 puts its J_c^T J_c != 0 in D)
        if not bordered:
            B, D, gc = no_border(n)
        status, touched, A, b, own_D, own_g = marginal_prior(Hb, g, B, D, gc, nl)
        if status == 1:
            raise FixedLagFailed(f"the fixed-lag smoother cannot marginalise keyframes {self.first}..{cut - 1} "
                                 f"(t = {self.time(self.first):.6f}..{self.time(cut - 1):.6f} s): their information "
                                 "is not positive definite. Check the data around that time.")
        # the priors it replaced: those reaching a leaving keyframe, and those on the calibrations alone
        self._priors = [p for p in self._priors
                        if p.keyframes.size and p.keyframes[0] >= cut or not (p.keyframes.size or bordered)]
        if self._dc[:self._m].any():  # (the measurements' own tables compiled, these beside them)
            staying = self._mk[:self._m, 0] >= cut
            for a in self._calibrated_innovations():
                a[:np.count_nonzero(staying)] = a[:self._m][staying]
        self._m, self._spans[0] = drop_measurements(cut, self._m, self._mk, self._model, self._rows, self._dims,
                                                     self._Wm, self._rcode, self._rk, self._mcal, self._mD, self._mg,
                                                     self._mstep, self._mlast, self._macc, self._mgyro)
        for k in range(self.first + 1, cut + 1):  # the IMU factors into and out of the leaving keyframes
            self._has_imu[k % self._cap] = False
            self._pre[k % self._cap] = None
        self.first = cut
        if touched.size or bordered:  # keep what the marginal ties (non-zero information)
            R, e0 = (A, b) if status == 0 else semidefinite_square_root(A, b)
            keyframes = cut + touched
            slots = keyframes % self._cap
            prior = LinearPrior(keyframes, *(a[slots] for a in self._linearisation_points()), R, e0)
            if bordered:  # at the calibrations' linearisation points: dc = 0, its Jacobian I
                prior.c_lin, (prior.dc, prior.Jdc) = tuple(self._cal.theta), self._cal.at_linearisation
                prior.own = own_D, own_g
            self._priors.append(prior)
        self._spans[1] = max((int(p.keyframes[-1] - p.keyframes[0]) for p in self._priors if p.keyframes.size),
                             default=0)
