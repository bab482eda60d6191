"""What a run says of the calibrations it estimated: ``metrics.json``'s record, the printed table,
and which coordinates the data did not fix.

A calibrated sensor's record (``metrics.json``: ``<estimator>.calibration.<sensor>``) has, for
each part estimated, exactly these keys (conventions of :mod:`factors.calibration`):
``time_offset_s`` (the whole offset to add to the sensor's stamps: the one given plus the one
estimated) and ``time_offset_sigma_s``; ``T_BS`` (the estimated extrinsic, 4x4 rows, ``p_B = T_BS
p_S``) with ``rotation_sigma_rad`` (3, about the IMU frame's axes of the left chart) and/or
``lever_arm_m`` (= the translation of ``T_BS``) with ``lever_arm_sigma_m`` (3); ``scale`` and
``scale_sigma``. Nothing estimated is recorded without its sigma.

Against the prior (``<estimator>.calibration_against_prior.<sensor>``): ``sigma_ratio``, each
estimated coordinate's posterior sigma over its prior's; ``unobserved``, the coordinates whose
ratio is at least :data:`UNOBSERVED_RATIO` -- the data did not fix them (a lever arm without
rotation of the vehicle, the roll of a speed sensor about its own axis, a time offset while
standing still) and they stay at their prior; ``rotation_change_rad`` and
``lever_arm_change_m``, how far the estimate moved from the values given (the rotation as
``log(R R_given^T)``, IMU frame).

The sigmas are the model's: they take each sensor's noise as given. Where the estimator's own
residuals (or the EKF's innovations) of a calibrated sensor are out of their band as far as a
warning takes (:func:`smoother.diagnosis.verdicts.far_off`), the printed line says by how much they would
scale the sigmas: the square root of their figure per dof, least squares' a-posteriori variance
factor (for innovations, whose covariance holds the state's share too, at least that). A
calibration fitted to a sensor whose residuals are several times larger than its sigma says --
the sigma written too small, or the IMU's noise -- is as overconfident as they are. The sigmas
also take the sensor's errors as independent: where its residuals at consecutive fixes are alike
(a receiver's error drifting slower than its fixes come, lag-one correlation ``rho``), the fixes
carry less information than that, and the line gives the factor ``sqrt((1 + rho) / (1 - rho))``
when it is :data:`CORRELATION_FACTOR` or more: an AR(1) error's variance inflation for a slowly
varying regressor (a constant lever arm, a time offset read through a smooth velocity); an
error drifting otherwise, or one the estimate partly follows, can inflate it more.

Across estimators (:func:`disagreements`): the batch smoother, the fixed-lag smoother and the EKF
estimate the same calibration from the same data, so each coordinate's values must agree within
what their sigmas allow. Two values ``a``, ``b`` disagree when ``|a - b| > DISAGREEMENT_SIGMAS
sqrt(sigma_a^2 + sigma_b^2)`` (a rotation's difference ``log(R_a R_b^T)``, about the IMU frame's
axes); estimates of the same data are correlated, which only makes the difference's true sigma
smaller, so the test errs towards silence. A calibration the data barely fix, under a wide prior,
can settle in a wrong minimum in one estimator and not in the others; a disagreement says that one
of them has, not which: agreement is no vote (the EKF and the sliding window, which both linearise
early, settled 11 and 12 degrees from a wheel's true mounting, agreeing with each other and 8
sigmas from the batch, within 1.5 degrees of it), so every estimator party to a disagreement is
named.
"""
from __future__ import annotations

import numpy as np

from factors import so3
from factors.calibration import PART_COLUMNS
from smoother.diagnosis.figures import plus_minus
from smoother.diagnosis.verdicts import far_off

#: Posterior over prior sigma from which a coordinate counts as not observed (the data shrank
#: its uncertainty by less than 10 %).
UNOBSERVED_RATIO = 0.9

#: From how large a factor on the sigmas the correlation of a sensor's residuals is said
#: (``rho`` 0.38 and more).
CORRELATION_FACTOR = 1.5

#: Two estimators' values of a calibrated coordinate disagree beyond this many sigmas of their
#: difference (module docstring).
DISAGREEMENT_SIGMAS = 3.0

_AXES = ("x", "y", "z")


def _coordinate_names(parts) -> list[str]:
    names = []
    for part in parts:
        width = PART_COLUMNS[part].stop - PART_COLUMNS[part].start
        names += [part] if width == 1 else [f"{part} {a}" for a in _AXES]
    return names


def calibration_records(calibration, covariances) -> tuple[dict, dict]:
    """``({sensor: record}, {sensor: against the prior})`` (module docstring) of a solution's
    calibration variables (:class:`factors.calibration.CalibrationSet`) with their marginal
    covariances (one per sensor over its estimated coordinates)."""
    records, against = {}, {}
    for name, value, prior, mean, cov in zip(calibration.names, calibration.values, calibration.priors,
                                             calibration.means, covariances):
        sigma = np.sqrt(np.clip(np.diag(cov), 0.0, None))
        at = dict(zip(prior.parts, np.split(sigma, np.cumsum([PART_COLUMNS[p].stop - PART_COLUMNS[p].start
                                                              for p in prior.parts])[:-1])))
        record: dict = {}
        if "time_offset" in at:
            record["time_offset_s"] = prior.stamp_offset + value.time_offset
            record["time_offset_sigma_s"] = float(at["time_offset"][0])
        if "rotation" in at or "lever_arm" in at:
            record["T_BS"] = value.T_BS.tolist()
        if "rotation" in at:
            record["rotation_sigma_rad"] = at["rotation"].tolist()
        if "lever_arm" in at:
            record["lever_arm_m"] = value.p.tolist()
            record["lever_arm_sigma_m"] = at["lever_arm"].tolist()
        if "scale" in at:
            record["scale"] = value.scale
            record["scale_sigma"] = float(at["scale"][0])
        records[name] = record
        ratios = dict(zip(_coordinate_names(prior.parts), (sigma / prior.sigmas).tolist()))
        change = value.boxminus(mean)
        against[name] = {"sigma_ratio": ratios, "unobserved": [c for c, r in ratios.items() if r >= UNOBSERVED_RATIO]}
        if "rotation" in prior.parts:
            against[name]["rotation_change_rad"] = change[1:4].tolist()
        if "lever_arm" in prior.parts:
            against[name]["lever_arm_change_m"] = change[4:7].tolist()
    return records, against


def calibration_lines(records: dict, against: dict, verdicts: dict | None = None,
                      correlations: dict | None = None, follow_imu: dict | None = None) -> list[str]:
    """The printed table of one estimator's calibrations: a line per sensor, each value with its
    sigma (a rotation as its change from the one given, in degrees about the IMU frame's axes),
    the coordinates that stayed at their prior, and what its residuals say of those sigmas
    (module docstring): where the estimator's verdict on the sensor (``verdicts``: ``{sensor:
    verdict}``, :func:`smoother.diagnosis.verdicts.verdict`) is out of its band, and where its residuals'
    lag-one correlation (``correlations``: ``{sensor: rho}``, position fixes,
    :func:`smoother.evaluation.scoring.residual_correlation`) is high, and for the sensors whose
    errors may follow the IMU's (``follow_imu``: ``{sensor: why}``,
    :func:`smoother.pipeline.imu_followers`) what that would make of them."""
    verdicts, correlations, follow_imu = verdicts or {}, correlations or {}, follow_imu or {}
    lines = []
    for name, r in records.items():
        a = against.get(name, {})
        parts = []
        if "time_offset_s" in r:
            parts.append(f"time offset {plus_minus(r['time_offset_s'], r['time_offset_sigma_s'], digits=4)} s")
        if "rotation_sigma_rad" in r:
            angles = np.degrees(a.get("rotation_change_rad", [np.nan] * 3))
            sig = np.degrees(r["rotation_sigma_rad"])
            parts.append("rotation turned by (" + ", ".join(plus_minus(x, s, digits=3) for x, s in zip(angles, sig))
                         + ") deg")
        if "lever_arm_m" in r:
            parts.append("lever arm (" + ", ".join(plus_minus(a, s, digits=4) for a, s in
                                                   zip(r["lever_arm_m"], r["lever_arm_sigma_m"])) + ") m")
        if "scale" in r:
            parts.append(f"scale {plus_minus(r['scale'], r['scale_sigma'], signed=False, digits=5)}")
        left = a.get("unobserved", [])
        note = (f"; not fixed by the data, at its prior (posterior/prior sigma >= {UNOBSERVED_RATIO:g}): "
                f"{', '.join(left)}") if left else ""
        fit = fit_note(verdicts.get(name), correlations.get(name), follow_imu.get(name))
        lines.append(f"calibration {name}: " + "; ".join(parts) + note + (f"; {fit}" if fit else ""))
    return lines


def verdicts_for(estimator: str, verdicts: dict) -> dict:
    """``estimator``'s verdicts ``{sensor: verdict}`` out of every estimator's (``{estimator:
    {sensor: verdict}}``), a sensor it judged none of (the fixed-lag smoother, which keeps no
    covariances of the states with the calibrations, judges no calibrated sensor) taken from the
    batch smoother's, else the EKF's, marked ``by`` with whose: the sensor's misfit is the data's
    and the model's, and it says as much of this estimator's sigmas. A held-out verdict made
    without a drifting sensor's used errors (``not_given_used_errors``) judges no model: none."""
    out = {sensor: v for sensor, v in (verdicts.get(estimator) or {}).items() if not v.get("not_given_used_errors")}
    for other in ("batch", "ekf"):
        for sensor, v in (verdicts.get(other) or {}).items():
            if other != estimator and sensor not in out:
                out[sensor] = {**v, "by": other}
    return out


def fit_note(verdict: dict | None, rho: float | None, follows_imu: str | None = None) -> str:
    """What an estimator's verdict on a calibrated sensor (:func:`smoother.diagnosis.verdicts.verdict`)
    and its residuals' lag-one correlation ``rho`` (position fixes; None otherwise) say of its
    calibration's sigmas (module docstring), or '' when neither says anything. ``follows_imu``: why
    the sensor's errors may follow the IMU's, or None: residuals far below their band then do not
    make its sigmas too large alone -- errors that follow the IMU's make them too small."""
    said, factor, qualifier = [], 1.0, ""
    misfit = bool(verdict) and far_off(verdict)
    if misfit:
        lo, hi = verdict["band"]
        what = {"residual": "residuals", "heldout": "held-out predictions"}.get(verdict["statistic"], "innovations")
        whose = f"its {what} by the {verdict['by']}" if "by" in verdict else f"its {what}"
        said.append(f"{whose} are {verdict['per_dof']:.3g} per dof (band {lo:.3g}-{hi:.3g}), the sigmas take its "
                    "noise as given")
        factor *= float(np.sqrt(verdict["per_dof"]))
        if verdict["statistic"] != "residual":  # S = H P H^T + R: R is off by more than S
            qualifier = "at least about "
    correlated = float(np.sqrt((1.0 + rho) / (1.0 - rho))) if rho is not None and 0.0 < rho < 1.0 else 1.0
    if correlated >= CORRELATION_FACTOR:
        said.append(f"its residuals' lag-one correlation is {rho:.2f}, the sigmas take its errors as independent")
        factor *= correlated
        qualifier = "about "
    if not said:
        return ""
    advice = ("trust this calibration once they fit (the run's warnings say what to check)" if misfit
              else "fixes further apart (a rig's `every`, `--gps-every`) carry nearly as much and are nearer "
                   "independent")
    ar1 = " if its errors drift as AR(1)" if correlated >= CORRELATION_FACTOR else ""
    if misfit and follows_imu is not None and verdict["per_dof"] < verdict["band"][0]:
        ar1 += f", unless its errors follow the IMU's ({follows_imu}), which makes these too small instead"
    return f"{'; '.join(said)}: by its residuals they would be {qualifier}{factor:.2g}x these{ar1} -- {advice}"


def _coordinates(record: dict, against: dict) -> dict[str, tuple]:
    """A calibration record's estimated coordinates (module docstring), ``{name: (value, sigma,
    shown, unit)}``: ``value`` what differences are taken of (a rotation matrix's row for each of
    its axes), ``shown`` the value as printed (a rotation's turn from the one given, in degrees)."""
    out = {}
    if "time_offset_s" in record:
        out["time offset"] = (record["time_offset_s"], record["time_offset_sigma_s"], record["time_offset_s"], "s")
    if "rotation_sigma_rad" in record:
        R = np.asarray(record["T_BS"], dtype=float)[:3, :3]
        turned = np.degrees(against.get("rotation_change_rad", [np.nan] * 3))
        for i, axis in enumerate(_AXES):
            out[f"rotation about {axis}"] = ((R, i), record["rotation_sigma_rad"][i], turned[i], "deg")
    if "lever_arm_m" in record:
        for i, axis in enumerate(_AXES):
            value = record["lever_arm_m"][i]
            out[f"lever arm {axis}"] = (value, record["lever_arm_sigma_m"][i], value, "m")
    if "scale" in record:
        out["scale"] = (record["scale"], record["scale_sigma"], record["scale"], "")
    return out


def _difference(a, b) -> float:
    """Two coordinates' values apart: a rotation's axis of ``log(R_a R_b^T)``, else ``a - b``."""
    if isinstance(a, tuple):
        (Ra, axis), (Rb, _) = a, b
        return float(so3.log(Ra @ Rb.T)[axis])
    return float(a - b)


def _shown(value: float, sigma: float, unit: str) -> str:
    if unit == "deg":
        return f"{value:+.3g} +- {np.degrees(sigma):.2g} deg"
    return f"{value:+.4g} +- {sigma:.2g}" + (f" {unit}" if unit else "")


def disagreements(details: dict[str, dict], model_errors: bool = False) -> dict[str, str]:
    """Which estimators' calibrations disagree with the others' (module docstring), ``{estimator:
    why}`` in one phrase naming each sensor and coordinate, from each estimator's ``details``
    (``{estimator: details}``, with ``calibration`` and ``calibration_against_prior`` as
    :func:`calibration_records` makes them; an estimator without them, or that failed, has none). Costs one
    comparison per pair of estimators and coordinate. ``model_errors``: the run found its model
    wrong (a mounting, a noise fitted to a misfit), which the estimators -- a smoother, a window
    that linearises early, a filter -- weigh differently: the phrase names that cause beside a
    wrong minimum."""
    coordinates = {}
    for name, d in details.items():
        against = d.get("calibration_against_prior", {})
        coordinates[name] = {(sensor, c): v for sensor, record in d.get("calibration", {}).items()
                             for c, v in _coordinates(record, against.get(sensor, {})).items()}
    said: dict[str, list[str]] = {}
    for key in dict.fromkeys(k for c in coordinates.values() for k in c):
        have = {name: c[key] for name, c in coordinates.items() if key in c}
        apart = {name: {} for name in have}  # estimator: {other: sigmas apart}
        for a in have:
            for b in have:
                if a < b:
                    (va, sa, _, _), (vb, sb, _, _) = have[a], have[b]
                    sigmas = abs(_difference(va, vb)) / max(float(np.hypot(sa, sb)), np.finfo(float).tiny)
                    if sigmas > DISAGREEMENT_SIGMAS:
                        apart[a][b] = apart[b][a] = sigmas
        for name, others in apart.items():
            if not others:
                continue
            sensor, coordinate = key
            _, sigma, shown, unit = have[name]
            theirs = " and ".join(f"the {o}'s {_shown(have[o][2], have[o][1], unit)}" for o in others)
            said.setdefault(name, []).append(
                f"its {sensor} {coordinate}, {_shown(shown, sigma, unit)}, disagrees with {theirs} "
                f"({' and '.join(f'{x:.1f}' for x in others.values())} sigmas of their difference)")
    why = (": estimates of one calibration from the same data must agree within their sigmas, so this one (or the "
           "other) may have settled in a wrong minimum"
           + (", or the model errors this run found pull the estimators apart" if model_errors else ""))
    return {name: "; ".join(lines) + why for name, lines in said.items()}
