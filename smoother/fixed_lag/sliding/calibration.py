"""Calibration variables in the sliding window (:mod:`smoother.fixed_lag.sliding.window`): the dense border
of its block-banded system.

The calibration variables of the sensors that ask for them (:mod:`factors.calibration`, ``nc``
error coordinates in all) never leave the window. Ordered after every keyframe, they add a dense
border to the window's normal equations and to its Cholesky factor::

    H = [ A    B ]      L = [ L_A   0  ]      L_A Z = B,
        [ B^T  D ]          [ Z^T  L_D ]      L_D L_D^T = D - Z^T Z.

``A`` is the keyframes' block-banded part (the band is unchanged), ``B`` (15 rows per keyframe,
``nc`` columns) couples each keyframe with the calibrations its measurements read, ``D``
(``nc x nc``) is the calibrations' own. Row ``k`` of ``Z`` depends on the rows of ``L_A`` and
``B`` up to ``k`` only, so an update computes the rows of ``Z`` from the oldest stale row on, as
it does ``L_A``'s, and ``L_D`` -- ``nc`` numbers wide -- anew. The step: the forward solution
``y_A = L_A^-1 (-g_A)`` as before, ``y_c = L_D^-1 (-g_c - Z^T y_A)``, ``delta_c = L_D^-T y_c``,
``delta_A = L_A^-T (y_A - Z delta_c)``.

Each calibration has a linearisation point and an offset like a keyframe's (``c = theta_c [+]
delta_c``, :meth:`factors.calibration.Calibration.boxplus`: the rotation on the left); it is
linearised again when the offset exceeds :data:`CALIBRATION_RELINEARISATION_THRESHOLD` and
:data:`RELINEARISATION_SIGMA_FRACTION` of its marginal sigma, which makes every factor reading it
stale.

Marginalising the oldest keyframes replaces the factors touching them by their Schur complement
onto the keyframes they also touch AND the calibrations: a bordered prior ``e = R ([x [-] x_lin;
c [-] c_lin]) + e0`` (:class:`smoother.fixed_lag.sliding.normal_equations.LinearPrior` with ``c_lin``; a prior on
the calibrations alone, when no keyframe is left that the marginal informs, joins the next
marginal). Eliminating the oldest keyframes first, the rows of ``L_A``
and ``Z`` after them are the factor of that Schur complement already (the trailing part of a
Cholesky factor is its Schur complement's), so no refactorisation follows; ``L_D`` is recomputed
at each update from the ``D`` that now holds the prior's share.

The marginal covariance of a calibration is its block of ``(L_D L_D^T)^-1``; a keyframe's is its
block of ``A^-1`` plus ``W_k (L_D L_D^T)^-1 W_k^T`` with ``W = L_A^-T Z``.

Everything an update evaluates is compiled: the calibrated residuals
(:func:`datasets.kinds.calibrated_into`, :func:`factors.calibration.calibrated_odometry_into`)
and the border's sums in :func:`smoother.fixed_lag.sliding.normal_equations.linearise_calibrated` (each
keyframe's one-keyframe calibrated measurements keep what they add to its rows until it or a
calibration is linearised again), the bordered priors in
:func:`smoother.fixed_lag.sliding.normal_equations.prior_into`, the border's solve
(:func:`smoother.fixed_lag.sliding.banded.border_solve`) and the bordered marginal
(:func:`smoother.fixed_lag.sliding.banded.marginal_prior`). This class holds the variables: their linearisation
points (packed for those kernels), offsets, ``L_D`` and their own priors.
"""
from __future__ import annotations

import numpy as np

from factors import calibration
from factors.calibration import CALIBRATION_DIM, CalibrationSet
from factors.errors import InputError

#: How far a calibration may move from its linearisation point before the factors reading it are
#: linearised again, per coordinate ``(dd [s], rho [rad] x3, dp [m] x3, ds)``, at the least
#: (:data:`RELINEARISATION_SIGMA_FRACTION`). The calibrated residuals are linear in the lever arm,
#: in the scale but for its product with the state's Jacobian, and in a time offset but for the
#: attitude's ``exp(d C w)``; a rotation's ``exp(rho)`` is linear to first order. What a threshold
#: leaves out is second order, and the thresholds hold it to the same fraction of the first-order
#: change it goes with, 0.5 %: ``|rho| / 2`` for a rotation (0.01 rad), ``|ds| / s`` for the
#: scale's product with the state's Jacobian (5e-3), ``|dd| |w| / 2`` for a time offset's
#: attitude (0.01 s at 1 rad/s).
CALIBRATION_RELINEARISATION_THRESHOLD = np.array([0.01] + [0.01] * 3 + [0.05] * 3 + [5e-3])
#: While a calibration coordinate is still uncertain its offset may also reach this fraction of
#: its marginal sigma ``sigma`` (the last solve's, from ``L_D``) before it is linearised again, up
#: to :data:`RELINEARISATION_WIDEST` times its threshold. The offset's own second-order term,
#: ``c delta^2`` with ``c`` its curvature relative to its slope (1/2 for a rotation, ``|w| / 2``
#: for a time offset), moves the estimate by ``c kappa^2 sigma`` sigmas at ``delta = kappa
#: sigma``: 0.0125 sigma at kappa = 0.5 for sigmas up to 0.1 rad (0.1 s at 1 rad/s), the
#: defaults' priors; its products with the keyframes' offsets (the scale's with the state's
#: Jacobian) are measured rather than bounded: against relinearising everything at every update
#: the estimates stay within 0.2 sigma (tests). Early in a recording, where a calibration is
#: still far from what the data will give it and moves at every update, this keeps it from
#: being linearised again -- and the whole window factorised again -- at nearly every update (on
#: the benchmark's minute 31 times instead of 75, the estimates as close to relinearising
#: everything at every update).
RELINEARISATION_SIGMA_FRACTION = 0.5
#: The widest limit, in thresholds (:data:`RELINEARISATION_SIGMA_FRACTION`): half a prior sigma of
#: the defaults' (0.05 rad, 0.05 s, 0.025 of scale), so that a prior written wider does not let
#: the offset grow past where the bound above holds.
RELINEARISATION_WIDEST = 5.0
#: The farthest an update may take a calibration from its linearisation point, per coordinate:
#: the widest limit at the thresholds above (0.05 s, 0.05 rad, 0.25 m, 0.025 of scale), beyond
#: which the linearised factors no longer hold. A step that would go further is shortened to it
#: along its direction (:meth:`WindowCalibration.bounded`), the keyframes' step given the
#: shortened one, and the calibration is linearised again there: it moves at most this far per
#: update. Without the bound a coordinate the data barely observe under a wide prior -- a wheel's
#: roll about its own axis with ``rotation_sigma = 3`` -- swung by tens of degrees per update in
#: the first second (its marginal sigma still 40-170 deg), round past the second minimum at 180
#: deg that a velocity along the axis leaves, and the keyframes leaving at the lag froze its
#: linearisation there (their marginal, :class:`~smoother.fixed_lag.sliding.normal_equations.LinearPrior`,
#: is linear about it): +50 deg +- 7 at the end of 10 s against the batch's +12 +- 9, on a
#: simulated wheel mounted as written; bounded, +13 +- 9.
MAX_CALIBRATION_STEP = RELINEARISATION_WIDEST * CALIBRATION_RELINEARISATION_THRESHOLD


class WindowCalibration:
    """The calibration variables of a :class:`smoother.fixed_lag.sliding.window.SlidingWindow` (module
    docstring): their linearisation points ``theta`` and offsets ``delta`` (one array over the
    border's ``nc`` columns), the window's last ``L_D``, and what the compiled kernels read:
    ``packed`` (one :func:`factors.calibration.packed` row per sensor), ``with_time`` (whether
    its time offset is estimated), ``columns`` (each of its 8 error coordinates' border column,
    -1 where not estimated).

    ``calibrations``: the variables (:class:`factors.calibration.CalibrationSet`, values = the
    starting point), ``kinds``: each sensor's kind name (every calibrated sensor must have one)."""

    def __init__(self, calibrations: CalibrationSet, kinds: dict):
        for name in calibrations.names:
            if name not in kinds:
                raise InputError(f"calibration of sensor {name!r}: no such sensor (sensors: {', '.join(kinds)})")
        self.set = calibrations
        self.index = {name: j for j, name in enumerate(calibrations.names)}
        self.theta = list(calibrations.values)
        self.offsets = np.concatenate([[0], np.cumsum(calibrations.dims)]).astype(int)
        self._columns = [p.columns for p in calibrations.priors]  # each sensor's estimated coordinates
        self._sigmas = [p.sigmas for p in calibrations.priors]
        self.nc = int(self.offsets[-1])
        self.delta = np.zeros(self.nc)
        self.relinearised = 0
        self.with_time = np.array(["time_offset" in p.parts for p in calibrations.priors], dtype=np.bool_)
        #: whether a time offset is estimated (the residuals then step with the IMU reading held)
        self.steps_in_time = bool(self.with_time.any())
        self.columns = np.full((len(calibrations), CALIBRATION_DIM), -1, dtype=np.int64)
        for j, which in enumerate(self._columns):
            self.columns[j, which] = self.offsets[j] + np.arange(len(which))
        #: the Cholesky factor ``L_D`` of the last solve's calibration Schur complement (before
        #: the first: the priors' square-root information)
        self.L_D = np.diag(1.0 / np.concatenate(self._sigmas))
        #: :data:`CALIBRATION_RELINEARISATION_THRESHOLD` over the border's columns
        self.thresholds = np.concatenate([CALIBRATION_RELINEARISATION_THRESHOLD[which] for which in self._columns])
        #: :data:`MAX_CALIBRATION_STEP` over the border's columns (:meth:`bounded`)
        self.widest = np.concatenate([MAX_CALIBRATION_STEP[which] for which in self._columns])
        #: the offsets beyond which the last solve found the border's coordinates due to be linearised
        #: again: the larger of the threshold and :data:`RELINEARISATION_SIGMA_FRACTION` of the
        #: coordinate's marginal sigma, at most :data:`RELINEARISATION_WIDEST` thresholds
        #: (:func:`smoother.fixed_lag.sliding.banded.border_solve`)
        self.limits = self.thresholds.copy()
        #: a bordered prior's ``(dc, Jdc)`` made at the linearisation points (:meth:`border_of`)
        self.at_linearisation = np.zeros(self.nc), np.eye(self.nc)
        self._linearised()

    def _linearised(self) -> None:
        """The packed linearisation points and the calibrations' own priors' share of the normal
        equations there, ``(D, g_c)`` (both change only when a calibration is linearised again)."""
        self.packed = np.stack([calibration.packed(t) for t in self.theta])
        D, gc = np.zeros((self.nc, self.nc)), np.zeros(self.nc)
        for j, (t, mean, sigmas) in enumerate(zip(self.theta, self.set.means, self._sigmas)):
            e, J = calibration.prior_residual(t, mean, self._columns[j])
            Jw, ew = J / sigmas[:, None], e / sigmas
            a, b = self.offsets[j], self.offsets[j + 1]
            D[a:b, a:b] = Jw.T @ Jw
            gc[a:b] = Jw.T @ ew
        self.own_prior = D, gc

    def _full(self, j: int, d: np.ndarray) -> np.ndarray:
        out = np.zeros(CALIBRATION_DIM)
        out[self._columns[j]] = d
        return out

    def estimate(self) -> CalibrationSet:
        """The calibrations ``theta_c [+] delta_c`` after the last update."""
        values = tuple(t.boxplus(self._full(j, self.delta[self.offsets[j]:self.offsets[j + 1]]))
                       for j, t in enumerate(self.theta))
        return CalibrationSet(self.set.names, values, self.set.priors, self.set.means)

    def joint_covariance(self) -> np.ndarray:
        """The calibrations' joint marginal covariance over the border's columns,
        ``(L_D L_D^T)^-1``."""
        inv = np.linalg.inv(self.L_D)
        return inv.T @ inv

    def covariance(self) -> list[np.ndarray]:
        """Each sensor's marginal covariance over its estimated coordinates: blocks of
        :meth:`joint_covariance`."""
        cov = self.joint_covariance()
        return [cov[a:b, a:b] for a, b in zip(self.offsets[:-1], self.offsets[1:])]

    def bounded(self, before: np.ndarray, proposed: np.ndarray) -> np.ndarray | None:
        """The offsets ``proposed`` by a solve, shortened along the step from ``before`` (the last
        update's, each within :attr:`widest`) so that none exceeds :attr:`widest`
        (:data:`MAX_CALIBRATION_STEP`); None when none does."""
        outside = np.abs(proposed) > self.widest
        if not outside.any():
            return None
        step = proposed - before
        bound = np.copysign(self.widest, step)
        fraction = np.min((bound[outside] - before[outside]) / step[outside])
        return before + min(max(fraction, 0.0), 1.0) * step

    def relinearise(self, fraction: float = 1.0) -> bool:
        """Move the linearisation point of each calibration whose offset exceeds ``fraction`` of
        its :attr:`limits` in some coordinate to its estimate; True if any moved (every factor
        reading a calibration is then stale)."""
        limits = fraction * self.limits
        if not (np.abs(self.delta) > limits).any():
            return False
        moved = False
        for j, t in enumerate(self.theta):
            a, b = self.offsets[j], self.offsets[j + 1]
            d = self.delta[a:b]
            if np.any(np.abs(d) > limits[a:b]):
                self.theta[j] = t.boxplus(self._full(j, d))
                self.delta[a:b] = 0.0
                moved = True
        self.relinearised += moved
        if moved:
            self._linearised()
        return moved

    def border_of(self, c_lin: tuple) -> tuple[np.ndarray, np.ndarray]:
        """``(dc, Jdc)`` of a bordered prior made at the calibrations ``c_lin``: its error
        coordinates ``theta [-] c_lin`` over the border's columns and their Jacobian (block
        diagonal, :func:`factors.calibration.prior_residual`)."""
        dc, Jdc = np.zeros(self.nc), np.zeros((self.nc, self.nc))
        for j, (t, c) in enumerate(zip(self.theta, c_lin)):
            a, b = self.offsets[j], self.offsets[j + 1]
            dc[a:b], Jdc[a:b, a:b] = calibration.prior_residual(t, c, self._columns[j])
        return dc, Jdc
