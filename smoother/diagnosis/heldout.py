"""A verdict from data the fit did not use: each sensor's held-out measurements (a rig's
``every = K``: every K-th measurement used, the rest held out) predicted by an estimate.

A held-out measurement ``z`` at time ``t`` is predicted from the estimate's state there (every
held-out time is one of the estimators' states: :func:`smoother.model.timeline.keyframe_times`)
through the sensor's model and the estimator's calibration, ``e = h(x^) - z`` (with a calibration,
the calibrated residual of :func:`datasets.kinds.calibrated_rows`), with the covariance

    S = H P H^T + R

(``P`` the state's marginal covariance, ``R`` the measurement's). The estimate did not use ``z``,
so for a model that fits ``e^T S^-1 e`` is chi-square with the measurement's dimension, and a
sensor's mean per degree of freedom has the band of :func:`smoother.stats.per_dof_band` -- unlike
the residuals of the measurements it used, which a fitted noise puts in band by construction.
(A calibration's own uncertainty is left out of ``S``: it is small beside the state's where the
data fix the calibration.)

The share of ``S`` that is the state's, ``tr(S^-1 H P H^T) / d``, says what a verdict below its
band means: where the state's uncertainty dominates (a yaw the data do not fix inflates ``S``),
low errors say nothing of the sensor's sigma; where ``R`` dominates, its sigma is stated too
large. Relative measurements (odometry) are not judged here: they need two states' joint
covariance.
"""
from __future__ import annotations

import numpy as np

from datasets.kinds import KINDS, calibrated_rows, measure_rows, sensors_of
from datasets.types import Dataset, Trajectory
from smoother.diagnosis.verdicts import verdict

#: A held-out time matches an estimate's state within this [s].
MATCH_TOLERANCE = 1e-9


def heldout_consistency(dataset: Dataset, trajectory: Trajectory, calibration=None) -> dict[str, dict]:
    """Per sensor with held-out measurements of an absolute kind, the :func:`verdict` of their
    normalised prediction errors through ``trajectory`` (with its covariances) and the
    estimator's calibration variables ``calibration`` (a :class:`factors.calibration.CalibrationSet`
    or None: the values given), statistic ``"heldout"``, with ``state_share``: the mean share of
    the prediction's covariance that is the state's (module docstring). Held-out measurements at
    no state of the estimate are left out; a sensor with none left has no verdict."""
    if trajectory.cov is None:
        return {}
    out = {}
    for sensor in sensors_of(dataset):
        kind = KINDS[sensor.kind]
        held = sensor.heldout
        if held is None or kind.relative or len(held.t) == 0:
            continue
        k = np.searchsorted(trajectory.t, held.t)
        k = np.clip(k, 0, len(trajectory.t) - 1)
        below = np.clip(k - 1, 0, len(trajectory.t) - 1)
        k = np.where(np.abs(trajectory.t[below] - held.t) < np.abs(trajectory.t[k] - held.t), below, k)
        found = np.abs(trajectory.t[k] - held.t) <= MATCH_TOLERANCE
        if not found.any():
            continue
        k = k[found]
        states, P = trajectory.states[k], trajectory.cov[k]
        rows = kind.pack(held)[found]
        R = held.cov[found]
        calibrated = calibration is not None and sensor.name in calibration.names
        j = calibration.names.index(sensor.name) if calibrated else None
        if j is None:
            e, H = measure_rows(kind, states, rows)
        else:
            c, readings = calibration.values[j], None
            if "time_offset" in calibration.priors[j].parts:
                steps = dataset.imu.held(held.t[found])
                readings = (dataset.imu.acc[steps], dataset.imu.gyro[steps])
            e, H, _ = calibrated_rows(kind, states, rows, c, readings, dataset.gravity)
        state_part = H @ P @ np.swapaxes(H, -1, -2)
        S = state_part + R
        nis = np.einsum("ma,ma->m", e, np.linalg.solve(S, e[..., None])[..., 0])
        good = np.isfinite(nis)
        if not good.any():
            continue
        d = kind.dim
        share = np.einsum("mab,mba->m", np.linalg.inv(S[good]), state_part[good]) / d
        record = verdict(float(nis[good].sum()), float(d * good.sum()), int(good.sum()), "heldout")
        out[sensor.name] = {**record, "state_share": float(np.mean(share))}
    return out
