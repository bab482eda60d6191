"""A verdict from data the fit did not use: each sensor's held-out measurements (a rig's
``every = K``: every K-th measurement used, the rest held out) predicted by an estimate.

A held-out measurement ``z`` at time ``t`` (its stamp, plus the time offset where the estimator
estimated one) is predicted from the estimate's state there -- its own where ``t`` is one of its
states; between two of them (held-out times are no keyframes), a smoother's bridged between both
through the IMU's Euler steps with the joint covariance of the two, else carried from the one
before with the EKF's covariance step (:func:`smoother.model.between.states_between`) -- through
the sensor's model and the estimator's calibration, ``e = h(x^) - z`` (with a calibration, the
calibrated residual of :func:`datasets.kinds.calibrated_rows`), with the covariance

    S = H P H^T + R

(``P`` the state's marginal covariance there, ``R`` the measurement's). The EKF predicts its
held-out measurements in its own loop (:class:`smoother.model.predicted.HeldoutPrediction`): from its
state at ``t`` after the updates before and at ``t``, with its calibrations then and their
uncertainty in ``P`` -- the filter's innovation of ``z``, not used. The estimate did not use ``z``,
so for a model that fits ``e^T S^-1 e`` is chi-square with the measurement's dimension, and a
sensor's mean per degree of freedom has the band of :func:`smoother.stats.per_dof_band` -- unlike
the residuals of the measurements it used, which a fitted noise puts in band by construction.
The held-out errors are not independent, though: those between two used measurements share the
estimate's error there (an EKF's dead reckoning from the same update, a smoother's bridge between
the same keyframes), so their sum spreads as one of fewer independent squares, and a band on all
their degrees of freedom is too narrow (a consistent EKF's verdict, fixes at 5 Hz one in five
used, spreads with a standard deviation of 0.11 over seeds where that band's is 0.05). The band's
degrees of freedom are estimated from the spread of the gaps' sums (:func:`effective_dof`, held
between those of errors alike within each gap and all of them; ``band_dof``).
(A smoother's calibration's own uncertainty is left out of ``S``: it is small beside the state's
where the data fix the calibration. The EKF's is in its augmented ``P``.)

A verdict below its band says the prediction's covariance is too large: the sensor's sigma stated
too large, or the state's covariance (a sigma that also inflates it, a state the data do not fix).
The mean of ``e^T (H P H^T + k^2 R)^-1 e`` per dof falls monotonically as a factor ``k`` on the
sensor's sigma grows (``S`` grows in the positive semi-definite order), so the one ``k`` at which it
is 1 is found by bisection (:func:`sigma_factor`) -- how far the sigma is off at most: ``P`` is
held, and a smaller sigma makes it smaller too (it is monotone in ``R``), so re-solved with ``k``
the errors would lie above 1 per dof, and the sigma that fits lies between ``k`` and 1 times the
stated one. Where there is none, the errors lie below even the state's covariance alone: with ``P``
held no sigma explains them, which does not tell a state the data do not fix from a sigma that
inflates ``P`` too. (Such a ``k`` is fitted to the held-out measurements: a value to try, judged on
other data.) The share of ``S`` that is the state's, ``tr(S^-1 H P H^T) / d``, is recorded beside it.
Relative measurements (odometry) are not judged here: they need two states' joint
covariance.

Errors correlated in time. A held-out measurement close to a used one shares the used one's
error where the sensor's errors drift (a GNSS receiver's, a fused solution's): the estimate
followed it there, so the prediction error is far smaller than ``S``, which takes the two as
independent, while one far from any used measurement is not. So the held-out measurements are
also split at the median of their time to the nearest used one, and each half's mean per dof is
recorded (``near_far``); where the near half's lies below the far half's by more than
:data:`NEAR_FAR_RATIO` and by more than :data:`NEAR_FAR_SIGMAS` standard deviations of the
difference of their logarithms (``sqrt(2 / dof_near + 2 / dof_far)``), the sensor's errors are
correlated in time (``correlated``): no white sigma fits both halves, and the verdict says so
rather than blame the sigma.
"""
from __future__ import annotations

from dataclasses import replace

import numpy as np

from datasets.kinds import KINDS, calibrated_rows, measure_rows, sensors_of
from datasets.types import Dataset, Trajectory
from smoother.diagnosis.verdicts import verdict
from smoother.model.between import Following, states_between
from smoother.model.predicted import HeldoutPrediction
from smoother.model.timeline import STATES_CHUNK
from smoother.stats import dof_means_apart

#: :func:`sigma_factor` searches this range of factors on a sensor's sigma ...
SIGMA_FACTOR_RANGE = (1e-3, 1e3)
#: ... by this many bisections of its logarithm (to a relative precision of about 1e-6).
BISECTIONS = 45
#: The fewest gaps between used measurements with held-out ones in them over which the held-out
#: verdict's spread is estimated (:func:`effective_dof`); with fewer, its band takes each gap's errors as one.
MIN_GAPS = 8
#: Held-out errors near the used measurements are correlated with theirs when their mean per dof
#: lies below that of those far from them by more than this ratio ...
NEAR_FAR_RATIO = 1.5
#: ... and by more than this many standard deviations (module docstring).
NEAR_FAR_SIGMAS = 3.0


def near_and_far(nis: np.ndarray, distance: np.ndarray, d: int) -> dict:
    """``{"near_far": (near, far), "correlated": bool}``: the mean per dof of the held-out
    normalised errors ``nis (M,)`` (dimension ``d`` each) closer to a used measurement than the
    median of their times to the nearest one ``distance (M,)``, and of the rest; correlated where
    the near ones lie below the far ones as the module docstring says. ``{}`` with fewer than four
    measurements or no spread of distances."""
    near = distance < np.median(distance)
    if near.sum() < 2 or (~near).sum() < 2:
        return {}
    per_dof = [float(nis[part].mean()) / d for part in (near, ~near)]
    if min(per_dof) <= 0.0:
        return {}
    apart = dof_means_apart(per_dof[0], d * near.sum(), per_dof[1], d * (~near).sum(), NEAR_FAR_RATIO,
                            NEAR_FAR_SIGMAS)
    return {"near_far": tuple(per_dof), "correlated": apart > 0.0}


def effective_dof(nis: np.ndarray, d: int, gap: np.ndarray) -> float:
    """The degrees of freedom of the held-out verdict's band: its normalised errors ``nis (M,)``
    (dimension ``d`` each) are correlated within each gap between two used measurements (``gap
    (M,)``: which gap each lies in; module docstring), so their sum spreads as a chi-square of
    fewer degrees of freedom than ``D = M d``. By Satterthwaite's match of the first two moments, a
    sum ``Q = m chi2_nu D / nu`` has ``Var Q = 2 m^2 D^2 / nu``, so

        nu = 2 m^2 D^2 / Var Q,   Var Q ~ sum_g (Q_g - m_(-g) D_g)^2

    over the gaps' sums ``Q_g`` (of ``D_g`` degrees of freedom, ``n_g`` errors; independent from
    one gap to the next), ``m = Q / D``, each gap's deviation from the mean of the others,
    ``m_(-g)`` (its own excursion stays in it, however large the gap), held within
    ``[d (sum n_g)^2 / sum n_g^2, D]``: from errors alike within each gap (``n_g`` copies of one
    chi-square each) to independent ones. With fewer than :data:`MIN_GAPS` gaps, too few to tell a
    spread, the first: a band that takes each gap's errors as one."""
    _, which = np.unique(gap, return_inverse=True)
    n_g = np.bincount(which).astype(float)
    Q_g, D_g = np.bincount(which, weights=nis), d * n_g
    D, Q = float(D_g.sum()), float(Q_g.sum())
    alike = d * float(n_g.sum()) ** 2 / float(np.sum(n_g * n_g))
    if len(n_g) < MIN_GAPS:
        return alike
    m = Q / D
    spread = float(np.sum((Q_g - (Q - Q_g) / (D - D_g) * D_g) ** 2))
    if not (m > 0.0 and spread > 0.0):
        return D
    return float(np.clip(2.0 * m * m * D * D / spread, alike, D))


def sigma_factor(e: np.ndarray, state_part: np.ndarray, R: np.ndarray) -> float | None:
    """The factor ``k`` on a sensor's sigma (``R -> k^2 R``) at which its held-out prediction
    errors ``e (M, d)``, with the state's part ``H P H^T (M, d, d)`` of their covariance and the
    measurements' ``R (M, d, d)``, are 1 per dof: ``sum e^T (H P H^T + k^2 R)^-1 e = M d``
    (module docstring). None where no ``k`` within :data:`SIGMA_FACTOR_RANGE` is: the errors lie
    below even the state's covariance (a state the data do not fix) or above even the largest."""
    target = e.size

    def excess(log_k: float) -> float:
        S = state_part + np.exp(2.0 * log_k) * R
        return float(np.einsum("ma,ma->", e, np.linalg.solve(S, e[..., None])[..., 0])) - target

    lo, hi = np.log(SIGMA_FACTOR_RANGE)
    if not excess(lo) >= 0.0 or not excess(hi) <= 0.0:
        return None
    for _ in range(BISECTIONS):
        mid = 0.5 * (lo + hi)
        if excess(mid) > 0.0:
            lo = mid
        else:
            hi = mid
    return float(np.exp(0.5 * (lo + hi)))


def heldout_consistency(dataset: Dataset, trajectory: Trajectory, calibration=None,
                        following: Following | None = None,
                        predictions: dict[str, HeldoutPrediction] | None = None) -> dict[str, dict]:
    """Per sensor with held-out measurements of an absolute kind (one that holds every measurement
    out, a sensor only checking the estimate, too), the :func:`verdict` of their
    normalised prediction errors through ``trajectory`` (with its covariances) and the
    estimator's calibration variables ``calibration`` (a :class:`factors.calibration.CalibrationSet`
    or None: the values given), statistic ``"heldout"``, with ``state_share``: the mean share of
    the prediction's covariance that is the state's, and ``sigma_factor``: the factor on the
    sensor's sigma at which the errors would be 1 per dof (:func:`sigma_factor`; None where no
    sigma would do; module docstring), and the errors near the used measurements against those far
    from them (:func:`near_and_far`). The states at the held-out times are the trajectory's
    through ``dataset``'s IMU with its noise (a run's dataset as its estimators ran on it, the
    fitted noise included): bridged between its states with ``following``, each state's next
    with their joint covariance (a smoother's), else carried from the one before
    (:func:`smoother.model.between.states_between`; :func:`heldout_predictions`) -- or, for a
    sensor in ``predictions`` with their ``H P H^T`` (a filter's,
    :class:`smoother.model.predicted.HeldoutPrediction`), its residuals and ``H P H^T`` as the
    filter predicted them in its loop, from its own state at each held-out time. Held-out
    measurements outside the trajectory's span are left out; a sensor with none left has no
    verdict."""
    if trajectory.cov is None or not len(trajectory.t):
        return {}
    out = {}
    for sensor in _holding_out(dataset):
        kind, held = KINDS[sensor.kind], sensor.heldout
        own = (predictions or {}).get(sensor.name)
        if own is None or own.state_part is None:
            own = _predicted(dataset, trajectory, calibration, following, sensor)
        index = own.index
        e, state_part, R = judged_errors(own, held.cov)
        if not len(index):
            continue
        S = state_part + R
        nis = np.einsum("ma,ma->m", e, np.linalg.solve(S, e[..., None])[..., 0])
        good = np.isfinite(nis)
        if not good.any():
            continue
        d = kind.dim
        share = np.einsum("mab,mba->m", np.linalg.inv(S[good]), state_part[good]) / d
        used = np.sort(sensor.data.t) if sensor.data is not None else np.zeros(0)
        at = held.t[index][good]
        band_dof = effective_dof(nis[good], d, np.searchsorted(used, at)) if len(used) else None
        record = verdict(float(nis[good].sum()), float(d * good.sum()), int(good.sum()), "heldout", band_dof=band_dof)
        out[sensor.name] = {**record, "state_share": float(np.mean(share)),
                            "sigma_factor": sigma_factor(e[good], state_part[good], R[good])}
        if own.conditioned is not None:
            out[sensor.name]["given_used_errors"] = True
        elif sensor.correlation_time is not None:  # predicted without the used errors (the fixed-lag smoother)
            out[sensor.name]["not_given_used_errors"] = True
        if len(used):
            i = np.searchsorted(used, at)
            before, after = used[np.clip(i - 1, 0, len(used) - 1)], used[np.clip(i, 0, len(used) - 1)]
            out[sensor.name].update(near_and_far(nis[good], np.minimum(np.abs(at - before), np.abs(after - at)), d))
    return out


def judged_errors(own: HeldoutPrediction, cov: np.ndarray) -> tuple:
    """``(e, H P H^T, R)`` by which a held-out prediction ``own`` is judged: its residuals with
    the state's part of their covariance and the measurements' own (``cov``, the held-out
    measurements' covariances, indexed by ``own.index``) -- or, for errors correlated in time, the
    prediction given the used ones' errors (:class:`smoother.model.predicted.Conditioned`, in
    whitened units: the measurement's ``R = L L^T``, ``e = L^-1 (...)``)."""
    if own.conditioned is not None:
        return own.conditioned.e, own.conditioned.state_part, own.conditioned.noise
    return own.e, own.state_part, cov[own.index]


def heldout_predictions(dataset: Dataset, trajectory: Trajectory, calibration=None, following: Following | None = None,
                        sensors=None, covariances: bool = True) -> dict[str, HeldoutPrediction]:
    """Per sensor of ``dataset`` (of ``sensors``, names, when given) with held-out measurements of
    an absolute kind, their prediction through ``trajectory`` (:class:`HeldoutPrediction`): the
    held-out measurements inside its span, each predicted from its state at that time -- bridged
    between its states with ``following``, else carried from the one before
    (:func:`smoother.model.between.states_between`, through ``dataset``'s IMU and noise) -- through
    the sensor's model and the estimator's ``calibration`` (module docstring). With
    ``covariances`` (and a trajectory that has them) each one's ``H P H^T`` too; without, only
    the residuals (``state_part`` None): what a metric needs."""
    if not covariances and following is None:
        trajectory = replace(trajectory, cov=None)  # carried without the covariance step
    return {sensor.name: _predicted(dataset, trajectory, calibration, following, sensor, covariances)
            for sensor in _holding_out(dataset) if sensors is None or sensor.name in sensors}


def _holding_out(dataset: Dataset) -> list:
    """The sensors of ``dataset`` of an absolute kind with held-out measurements, those it holds out
    whole (no measurement used: a sensor that only checks the estimate) among them, their kinds
    checked (:func:`datasets.kinds.sensors_of`)."""
    sensors_of(dataset)
    return [s for s in dataset.sensors
            if s.heldout is not None and len(s.heldout.t) and not KINDS[s.kind].relative]


def _predicted(dataset: Dataset, trajectory: Trajectory, calibration, following: Following | None, sensor,
               covariances: bool = True) -> HeldoutPrediction:
    """:func:`heldout_predictions` of one ``sensor``, a chunk of its held-out measurements at a
    time (``P`` is 15x15 each). A sensor whose time offset the estimator has is predicted at the
    time it gives each measurement, its stamp plus that offset, with the rest of its calibration."""
    kind, held = KINDS[sensor.kind], sensor.heldout
    c = None if calibration is None else calibration.value_of(sensor.name)
    times = held.t if c is None else held.t + c.time_offset
    if c is not None:
        c = replace(c, time_offset=0.0)  # taken at the time it gives: no extrapolation through the IMU reading
    index = np.flatnonzero((times >= trajectory.t[0]) & (times <= min(trajectory.t[-1], dataset.imu.t[-1])))
    rows = kind.pack(held)[index]
    covariances = covariances and trajectory.cov is not None
    errors, shares = [np.zeros((0, kind.dim))], [np.zeros((0, kind.dim, kind.dim))]
    for lo in range(0, len(index), STATES_CHUNK):
        part = slice(lo, lo + STATES_CHUNK)
        at = states_between(trajectory, dataset.imu, times[index[part]], dataset.noise, dataset.gravity, following)
        if c is None:
            e, H = measure_rows(kind, at.states, rows[part])
        else:
            e, H, _ = calibrated_rows(kind, at.states, rows[part], c, None, dataset.gravity)
        errors.append(e)
        if covariances:
            shares.append(H @ at.cov @ np.swapaxes(H, -1, -2))
    return HeldoutPrediction(index, np.concatenate(errors), np.concatenate(shares) if covariances else None)
