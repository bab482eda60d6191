"""Scoring estimates against a dataset's reference.

Against a ground truth (simulator, EuRoC), at every state of the estimate in the truth's span
with the truth interpolated to its time (:func:`compare_with_truth`): ``ate_rmse_m`` (position
RMSE, no alignment: truth and estimate share the world frame), ``rot_rmse_deg`` (RMS angle of
``C_true^T C_est``) and ``nees_mean``: the time average of the 6-dim pose NEES (position and
primer-boxminus attitude, :func:`smoother.evaluation.metrics.nees`) divided by 6, so 1 is consistent; over
too few states or too short a part of the run they are null and ``ate_note`` says why
(:func:`against_truth`). Against GPS (KITTI):
``gps_heldout_rmse_m`` over the fixes held out of estimation -- an accuracy -- and
``gps_fit_residual_m`` over the fixes the estimators used -- a residual: how closely the estimate
fits measurements it was fitted to, which a smoother that follows every fix (and the noise in it)
makes small without being accurate; estimators are compared by held-out fixes only. Both with
the estimate at each fix's time taken through the IMU from its states about it: keyframes need
not include the fixes' times. The held-out fixes are scored by the predictions their verdict
judges (:func:`smoother.diagnosis.heldout.heldout_predictions`; the EKF's from its own state at
their times, as its loop predicted them: :func:`score`'s ``predictions``), the used ones by
:func:`position_residuals` with the run's dataset. :func:`interpolation_baseline` is the
yardstick for the held-out figures: the used fixes interpolated to the held-out times, no IMU.

Over time, for the figures (:mod:`smoother.outputs.plots`): the same errors per compared state
or fix with the covariances behind them (:class:`ErrorSeries`): :func:`errors_against_truth` (the
pose errors and NEES of :func:`compare_with_truth`) and :func:`errors_against_fixes` (the residuals
of the GPS figures, :func:`fix_residuals`, and the NEES of the held-out fixes).

What a run writes: :mod:`smoother.outputs.files`.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, replace

import numpy as np

from datasets.euroc import GROUNDTRUTH_GAP_FACTOR
from datasets.types import Dataset, PositionMeasurements, Trajectory
from smoother.diagnosis.heldout import heldout_predictions
from smoother.evaluation import metrics
from smoother.model.between import Following, states_between
from smoother.model.timeline import STATES_CHUNK

#: A figure against the truth needs at least this many compared states ...
MIN_COMPARED_STATES = 10
#: ... spread over at least this fraction of the estimate's time span; short of it the figures
#: are null in metrics.json, with ``ate_note`` saying why.
MIN_TRUTH_COVERAGE = 0.5
#: A scored figure over less than this fraction of the estimate's span carries an ``ate_note``.
FULL_TRUTH_COVERAGE = 0.9
#: A truth step longer than this many typical steps is a gap: no state inside one is compared.
TRUTH_GAP_FACTOR = GROUNDTRUTH_GAP_FACTOR


def truth_at(truth: Trajectory, t: np.ndarray) -> tuple:
    """``(states, inside)``: the truth interpolated to the times ``t`` in its span and not inside
    one of its gaps (a step longer than :data:`TRUTH_GAP_FACTOR` typical ones: never bridged),
    and the mask of those times (:meth:`datasets.types.Trajectory.interpolate`)."""
    step = None if len(truth) < 2 else TRUTH_GAP_FACTOR * float(np.median(np.diff(truth.t)))
    states, _, inside = truth.interpolate(t, max_step=step)
    return states, inside


def compare_with_truth(truth: Trajectory, estimate: Trajectory) -> dict:
    """The estimate against the truth at every state of the estimate in the truth's span, the
    truth interpolated to its time (:func:`truth_at`: a state inside a gap of the truth is not
    compared): ``t`` of the compared states and ``inside``, the mask of them among the estimate's,
    ``ate_rmse_m``, ``rot_rmse_deg`` (NaN when none is compared), ``position_errors`` [m],
    ``pose_errors`` (N, 6): truth minus estimate in position and ``log(C_true C_est^T)``
    (:func:`smoother.evaluation.metrics.pose_error`), and the pose NEES of each state, ``nees``
    (None without covariances). One place for the run's metrics, the Monte Carlo runs, the
    cross-checks and the figures."""
    T, inside = truth_at(truth, estimate.t)
    E = estimate.states[inside]
    result = metrics.ate(T.r, T.C, E.r, E.C)
    nees = None if estimate.cov is None else metrics.nees(T, E, estimate.cov[inside], "pose")
    return {"t": estimate.t[inside], "inside": inside, "ate_rmse_m": result["translation"]["rmse"],
            "rot_rmse_deg": result["rotation"]["rmse"], "position_errors": result["translation_errors"],
            "pose_errors": metrics.pose_error(T.r, T.C, E.r, E.C), "nees": nees}


@dataclass(frozen=True)
class ErrorSeries:
    """One estimate's errors against a reference at times ``t`` (absolute, not shifted): position
    ``dr`` = reference minus estimate [m] with covariance ``P_r`` (the estimate's, plus the fix's
    against fixes), attitude ``dphi = log(C_ref C_est^T)`` [rad] with ``P_phi`` (against the truth
    only), ``nees`` with ``dof`` degrees of freedom (None without covariances; against fixes NaN
    at the fixes the estimator used) and, against fixes, which were held out (``heldout``)."""

    t: np.ndarray
    dr: np.ndarray
    P_r: np.ndarray | None
    dphi: np.ndarray | None = None
    P_phi: np.ndarray | None = None
    nees: np.ndarray | None = None
    dof: int = 6
    heldout: np.ndarray | None = None


def errors_against_truth(truth: Trajectory, estimate: Trajectory) -> ErrorSeries | None:
    """The errors of :func:`compare_with_truth` at the compared states (None if there are none),
    with the estimate's position and attitude covariances; its pose NEES is the one
    ``metrics.json``'s ``nees_mean`` averages (None where a covariance is singular)."""
    try:
        c = compare_with_truth(truth, estimate)
    except np.linalg.LinAlgError:  # a singular covariance: the errors without their NEES
        c = compare_with_truth(truth, replace(estimate, cov=None))
    inside = c["inside"]
    if not inside.any():
        return None
    cov = None if estimate.cov is None else estimate.cov[inside]
    e = c["pose_errors"]
    return ErrorSeries(t=c["t"], dr=e[:, :3], P_r=None if cov is None else cov[:, 0:3, 0:3],
                       dphi=e[:, 3:], P_phi=None if cov is None else cov[:, 6:9, 6:9], nees=c["nees"], dof=6)


def errors_against_fixes(t: np.ndarray, position: np.ndarray, cov: np.ndarray | None, heldout: np.ndarray,
                         estimate: Trajectory) -> ErrorSeries | None:
    """Fix minus estimate at the fixes (times ``t``, positions, covariances ``cov`` or None,
    ``heldout`` flags) inside the estimate's span: the residuals of the GPS figures
    (:func:`fix_residuals`, negated), with covariance ``P_est + R_fix`` (``P_est`` interpolated to
    the fix times); None if no fix lies inside.

    ``P_est + R_fix`` is the residual's covariance only for a HELD-OUT fix (independent of the
    estimate); a fix the estimator used pulled the estimate towards itself, so its residual is
    smaller than that. The NEES is therefore computed over the held-out fixes only (NaN at the
    others, None if there are none or a covariance is singular)."""
    inside, residual = fix_residuals(t, position, estimate)
    if not inside.any():
        return None
    dr = -residual
    held = heldout[inside]
    P = None
    if estimate.cov is not None:
        P = estimate.interpolate(t[inside])[1][:, 0:3, 0:3] + (0.0 if cov is None else cov[inside])
    nees = None
    if P is not None and held.any():
        try:
            values = metrics.nees_from(dr[held], P[held])
        except np.linalg.LinAlgError:
            values = None
        if values is not None:
            nees = np.full(len(dr), np.nan)
            nees[held] = values
    return ErrorSeries(t=t[inside], dr=dr, P_r=P, nees=nees, dof=3, heldout=held)


def against_truth(truth: Trajectory, estimate: Trajectory) -> dict:
    """``ate_rmse_m``, ``rot_rmse_deg``, ``nees_mean`` (pose NEES / 6; NaN without covariances) of
    :func:`compare_with_truth`, ``compared_states`` and ``compared_coverage`` (the compared
    states' time span over the estimate's). Over fewer than :data:`MIN_COMPARED_STATES` states or less
    than :data:`MIN_TRUTH_COVERAGE` of the estimate's span the three figures are NaN (null in
    metrics.json) and ``ate_note`` says why; below :data:`FULL_TRUTH_COVERAGE` the figures stand,
    and ``ate_note`` says over how much of the run."""
    c = compare_with_truth(truth, estimate)
    n = len(c["t"])
    span = float(estimate.t[-1] - estimate.t[0])
    covered = float(c["t"][-1] - c["t"][0]) if n else 0.0
    coverage = covered / span if span > 0 else float(n > 0)
    out = {
        "ate_rmse_m": c["ate_rmse_m"],
        "rot_rmse_deg": c["rot_rmse_deg"],
        "nees_mean": math.nan if c["nees"] is None or not n else float(np.mean(c["nees"]) / 6.0),
        "compared_states": n,
        "compared_coverage": coverage,
    }
    overlap = max(0.0, min(float(truth.t[-1]), float(estimate.t[-1])) - max(float(truth.t[0]), float(estimate.t[0])))
    where = (f"{n} of the estimate's {len(estimate)} states lie in the truth's span, over {covered:.4g} s of the "
             f"estimate's {span:.4g} s" + (f" (the truth covers {overlap:.4g} s of it)"
                                         if overlap < FULL_TRUTH_COVERAGE * span else ""))
    if n < MIN_COMPARED_STATES or coverage < MIN_TRUTH_COVERAGE:
        worst = f" (position errors there up to {float(np.max(c['position_errors'])):.4g} m)" if n else ""
        out.update(ate_rmse_m=math.nan, rot_rmse_deg=math.nan, nees_mean=math.nan,
                   ate_note=f"not scored against the truth: {where}{worst}; a score needs at least "
                            f"{MIN_COMPARED_STATES} states over {MIN_TRUTH_COVERAGE:.0%} of the estimate's span")
    elif coverage < FULL_TRUTH_COVERAGE:
        out["ate_note"] = f"scored over part of the run only: {where} ({coverage:.0%})"
    return out


def position_residuals(positions: PositionMeasurements | None, estimate: Trajectory,
                       dataset: Dataset | None = None, following: Following | None = None) -> tuple:
    """``(t, estimate - measured)``: the times of the measured positions inside the estimate's time
    span and, for each, the estimate's position there minus the measured one (world axes; empty
    arrays when there are none); with a lever arm (``positions.T_BS``) the estimate's antenna,
    ``r + C p_BS``. With the ``dataset`` the estimate was made from, its state at each time is
    taken through the IMU's Euler steps from its states about it (a run's own estimate, whose
    keyframes need not include the fixes' times): bridged between the two with ``following`` (a
    smoother's), else carried from the one before (:func:`smoother.model.between.states_between`);
    without one, a trajectory sampled elsewhere, the estimate is interpolated linearly
    (:func:`fix_residuals`)."""
    if positions is None or len(positions) == 0:
        return np.empty(0), np.empty((0, 3))
    if dataset is None:
        inside, residual = fix_residuals(positions.t, positions.position, estimate, positions.T_BS)
        return positions.t[inside], residual
    t = positions.t
    inside = (t >= estimate.t[0]) & (t <= min(estimate.t[-1], dataset.imu.t[-1]))
    source = estimate if following is not None else replace(estimate, cov=None)
    antennas = [np.empty((0, 3))]
    for lo in range(0, int(inside.sum()), STATES_CHUNK):  # a bridged state comes with its 15x15 covariance
        at = states_between(source, dataset.imu, t[inside][lo:lo + STATES_CHUNK], dataset.noise, dataset.gravity,
                            following).states
        antennas.append(at.r if positions.T_BS is None else at.r + at.C @ positions.T_BS[:3, 3])
    return t[inside], np.concatenate(antennas) - positions.position[inside]


def fix_residuals(t: np.ndarray, position: np.ndarray, estimate: Trajectory, T_BS=None) -> tuple:
    """``(inside, estimate - measured)`` of positions measured at times ``t`` (M,): the mask of
    those inside the estimate's time span and, for each of them, the estimate interpolated
    linearly to its time (its antenna ``r + C p_BS`` with a lever arm ``T_BS``, as
    :func:`position_residuals`) minus ``position``. The one definition of a fix's residual: the
    metrics' and the plots'."""
    inside = (t >= estimate.t[0]) & (t <= estimate.t[-1])
    t = t[inside]
    est = interpolate_positions(t, estimate.t, estimate.position)
    if T_BS is not None:
        k = np.clip(np.searchsorted(estimate.t, t), 1, len(estimate.t) - 1)
        k -= (t - estimate.t[k - 1]) < (estimate.t[k] - t)
        est = est + estimate.C[k] @ T_BS[:3, 3]
    return inside, est - position[inside]


def interpolate_positions(t: np.ndarray, t_known: np.ndarray, positions: np.ndarray) -> np.ndarray:
    """``positions`` (N, 3) known at times ``t_known`` interpolated linearly, per world axis, to
    the times ``t`` inside their span."""
    return np.stack([np.interp(t, t_known, positions[:, a]) for a in range(3)], axis=-1)


def rms_distance(residual: np.ndarray, axes=slice(0, 3)) -> float:
    """The RMS length of the ``residual`` rows (M, 3) in the world ``axes`` (horizontal ``0:2``,
    vertical ``2:3``); NaN without rows."""
    distance = np.linalg.norm(residual[:, axes], axis=1)
    return float(np.sqrt(np.mean(distance**2))) if distance.size else math.nan


def position_errors(positions: PositionMeasurements | None, estimate: Trajectory) -> tuple:
    """``(t, distance)`` of :func:`position_residuals`."""
    t, residual = position_residuals(positions, estimate)
    return t, np.linalg.norm(residual, axis=1)


def position_rmse(positions: PositionMeasurements | None, estimate: Trajectory) -> float:
    """RMS distance between measured positions and the estimate interpolated to their times
    (:func:`position_errors`; fixes outside the estimate's time span are not counted; NaN when
    none is left)."""
    return rms_distance(_residuals([] if positions is None else [positions], estimate))


def position_streams(dataset: Dataset, calibration=None, sensor: str | None = None) -> list[tuple]:
    """Each sensor's stream of position fixes (any kind measuring :class:`PositionMeasurements`:
    KITTI's GPS, a rig's position or GNSS sensor with its lever arm) as ``(name, used, held out)``
    (either may be None); with ``sensor``, that sensor's alone. With an estimator's ``calibration``
    (:class:`factors.calibration.CalibrationSet`), a calibrated sensor's fixes as that estimate
    has them: taken at their stamps plus the estimated time offset, at the estimated lever arm."""
    calibrated = {} if calibration is None else dict(zip(calibration.names, calibration.values))
    out = []
    for s in dataset.sensors:
        if not isinstance(s.heldout if s.data is None else s.data, PositionMeasurements):
            continue
        if sensor is not None and s.name != sensor:
            continue
        c = calibrated.get(s.name)
        if c is None:
            out.append((s.name, s.data, s.heldout))
            continue
        out.append((s.name, *(None if p is None else replace(p, t=p.t + c.time_offset, T_BS=c.T_BS)
                              for p in (s.data, s.heldout))))
    return out


def score(dataset: Dataset, estimate: Trajectory, calibration=None, following: Following | None = None,
          predictions: dict | None = None) -> dict:
    """Every metric the dataset allows for one estimate (the fixes of the sensors it calibrated
    at its ``calibration``, :func:`position_streams`; a smoother's states between keyframes bridged
    with its ``following``, :func:`position_residuals`). The held-out fixes are scored by the
    estimate's prediction of them, the antenna's residual from its state at each fix's time: the
    estimator's own, for a sensor in ``predictions`` (the EKF's, taken in its loop,
    :class:`smoother.model.predicted.HeldoutPrediction`), else the one its verdict judges
    (:func:`smoother.diagnosis.heldout.heldout_predictions`)."""
    out: dict = {}
    if dataset.truth is not None:
        out.update(against_truth(dataset.truth, estimate))
    streams = position_streams(dataset, calibration)
    predictions = dict(predictions or {})
    missing = [name for name, _, h in streams if h is not None and name not in predictions]
    if missing:
        predictions.update(heldout_predictions(dataset, estimate, calibration, following, missing, covariances=False))
    used = [u for _, u, _ in streams if u is not None]
    own = [predictions[name].e for name, _, h in streams if h is not None and name in predictions]
    if used or own:
        held = np.concatenate([np.empty((0, 3)), *own])
        out["gps_heldout_rmse_m"] = rms_distance(held)
        out["gps_heldout_horizontal_rmse_m"] = rms_distance(held, slice(0, 2))
        out["gps_heldout_vertical_rmse_m"] = rms_distance(held, slice(2, 3))
        out["gps_fit_residual_m"] = rms_distance(_residuals(used, estimate, dataset, following))
    return out


def interpolation_baseline(dataset: Dataset) -> dict | None:
    """What connecting the dots gives, the yardstick of the held-out metrics: each position or
    GNSS stream's used fixes interpolated linearly (per world axis) to the times of its held-out
    fixes between its first and last used fix. ``gps_heldout_rmse_m`` and its horizontal and
    vertical parts (as :func:`score`'s) and ``heldout_fixes`` (how many counted); None without
    held-out fixes inside the used ones' span. (An estimator's held-out figure also counts the
    held-out fixes after the last used one, inside its own span.)"""
    residuals = [np.empty((0, 3))]
    for _, used, held in position_streams(dataset):
        if used is None or held is None or len(used) < 2:
            continue
        inside = (held.t >= used.t[0]) & (held.t <= used.t[-1])
        t = held.t[inside]
        residuals.append(interpolate_positions(t, used.t, used.position) - held.position[inside])
    residual = np.concatenate(residuals)
    if not len(residual):
        return None
    return {"gps_heldout_rmse_m": rms_distance(residual), "gps_heldout_horizontal_rmse_m":
            rms_distance(residual, slice(0, 2)), "gps_heldout_vertical_rmse_m": rms_distance(residual, slice(2, 3)),
            "heldout_fixes": int(len(residual))}


def residual_correlation(dataset: Dataset, estimate: Trajectory, calibration=None,
                         sensor: str | None = None, following: Following | None = None) -> float | None:
    """How alike the estimate's residuals at consecutive used fixes are: their lag-one
    autocorrelation (each position or GNSS stream's residual series less its mean, per world
    axis, pooled). Near 0 the fixes' errors are white; well above 0 the receiver's error drifts
    slowly over the fix spacing -- which interpolating the used fixes follows, so that the held-out
    RMSE favours interpolation over an estimator that does not model that drift. None with fewer
    than three fixes. ``calibration`` and ``following`` as :func:`score`'s; with ``sensor``, that
    sensor's fixes alone."""
    num = den = 0.0
    for _, p, _ in position_streams(dataset, calibration, sensor):
        _, residual = position_residuals(p, estimate, dataset, following)  # empty for None
        if len(residual) < 3:
            continue
        residual = residual - residual.mean(axis=0)
        num += float(np.sum(residual[1:] * residual[:-1]))
        den += float(np.sum(residual * residual))
    return num / den if den > 0 else None


def _residuals(parts: list[PositionMeasurements], estimate: Trajectory, dataset: Dataset | None = None,
               following: Following | None = None) -> np.ndarray:
    """The rows of :func:`position_residuals` of every fix of ``parts``, stacked (M, 3)."""
    return np.concatenate([np.empty((0, 3))] + [position_residuals(p, estimate, dataset, following)[1] for p in parts])


