"""Per-sensor consistency: is each sensor's noise, extrinsic and time offset what its data show?

Through the EKF, a measurement's normalised innovation squared ``NIS = e^T S^-1 e`` (``S = H P
H^T + R``) is chi-square distributed with ``dim`` degrees of freedom when the model is right. Over
a sensor's ``N`` updates the sum is chi-square with ``N dim`` degrees of freedom, so the mean NIS
per degree of freedom lies in ``[chi2(0.025; N dim), chi2(0.975; N dim)] / (N dim)`` with 95%
probability. Outside that band the sensor's ``sigma`` is too small (above) or too large (below),
or a part of its calibration its kind has (a lever arm, rotation, time offset or scale) is wrong (above: the
residuals carry a systematic part).
Only the updates the filter accepted count (a gate's rejections are counted apart: their NIS is
large by construction). A sensor whose every update was rejected has a verdict of none (no
figure), and an EKF that rejected most of a sensor's updates shows mostly the IMU's dead
reckoning there, whatever its table says: it is doubtful (:func:`rejections`), and one that used
no aiding measurement at all is said to be dead reckoning.

The smoothers' own residuals are judged the same way, with the degrees of freedom their fit leaves
them (:mod:`smoother.diagnosis.residual_consistency`), and the IMU factors' among them:
:func:`consistency_lines` shows each sensor through every estimator.

Over many updates the band is narrow (about +-1% for 10^4 GNSS fixes), so a real sensor with
slightly correlated errors falls outside it: ``ok`` states the statistics, and a warning names a
sensor only when its figure is also a factor :data:`WARN_FACTOR` or more away from 1 -- a sigma,
extrinsic or time offset that is actually wrong. Such a warning names first the calibration the
sensor's residuals point at, where :mod:`smoother.diagnosis.misfit_causes` finds one (a scale, a time
offset, a rotation or a lever arm, with its fitted value), and the sigma after it: a systematic
pattern makes a sigma look too small or, beside a sigma stated too large, hides behind it. A
sensor with such a finding is warned of however near its band it is: the states may have
followed its error, which then shows in the other sensors.
A verdict needs :data:`MIN_DOF` degrees of freedom (:func:`judgeable`): residuals that the fit
leaves less than one independent square's worth of carry no test, and the band of their mean
collapses towards zero -- a GNSS-only rig's IMU factors, whose residuals the fixes leave 0.0007
degrees of freedom, would be "out of" a band of 0 to 5e-30. Such a verdict keeps its figure and
degrees of freedom, has no band and no ``ok``, is printed as :data:`TOO_FEW_DOF`, and counts
towards no warning, doubt or advice. From one degree of freedom on the band is a real one (0.001
to 5 at one, 0.013 to 3.7 at two): a rig with GNSS and wheels leaves its IMU factors about two,
on which a gyro read in deg/s is judged at 7e6 per dof.
When the IMU itself has findings
(:func:`datasets.imu_health.inspect_imu`: clipping, spikes, gaps, wrong units), or its own
residuals are further out than a sensor's, that sensor's misfit is a symptom first: the warning
names the IMU as the likelier cause.
"""
from __future__ import annotations

import numpy as np

from datasets.kinds import KINDS
from factors.calibration import PARTS, applicable
from smoother.ekf.filter import Innovations
from smoother.stats import per_dof_band

#: Probability of the band within which a consistent sensor's mean NIS per dof lies.
BAND_PROBABILITY = 0.95
#: A sensor is warned about when its NIS per dof is outside the band and outside
#: ``[1 / WARN_FACTOR, WARN_FACTOR]``.
WARN_FACTOR = 2.0
#: The fewest degrees of freedom a verdict is formed on (module docstring).
MIN_DOF = 1.0
#: What is printed of a verdict on fewer than :data:`MIN_DOF` degrees of freedom.
TOO_FEW_DOF = "too few degrees of freedom to judge"
#: An EKF that rejected more than this share of a sensor's updates is doubtful (:func:`rejections`).
MOST_REJECTED = 0.5


def verdict(total: float, dof: float, count: int, statistic: str, *, band_dof: float | None = None) -> dict:
    """A sum of squared normalised errors against its chi-square distribution: ``per_dof``
    (``total / dof``), ``band`` (the :data:`BAND_PROBABILITY` interval of ``per_dof`` for a model
    that fits), ``ok`` (inside it), ``measurements`` (``count``), ``dof`` and ``statistic``:
    ``"nis"`` (the EKF's innovations) or ``"residual"`` (a smoother's own residuals,
    :mod:`smoother.diagnosis.residual_consistency`). On fewer than :data:`MIN_DOF` degrees of
    freedom ``band`` and ``ok`` are None: not judged (:func:`judgeable`); on none, ``per_dof``
    is None too (a sensor whose every update the EKF's gate rejected). ``band_dof``: the degrees of
    freedom of the band where the errors are correlated (fewer than ``dof``: a sum of correlated
    squares spreads as one of fewer independent ones, :func:`smoother.diagnosis.heldout.effective_dof`),
    recorded beside it."""
    value = total / dof if dof > 0 else None
    out = {"per_dof": value, "band": None, "ok": None, "measurements": int(count), "dof": dof, "statistic": statistic}
    if dof >= MIN_DOF:
        lo, hi = per_dof_band(dof if band_dof is None else band_dof, BAND_PROBABILITY)
        out["band"], out["ok"] = [lo, hi], bool(lo <= value <= hi)
    if band_dof is not None:
        out["band_dof"] = band_dof
    return out


def judgeable(c: dict) -> bool:
    """Whether the verdict ``c`` (:func:`verdict`, or its record in ``metrics.json``) was formed:
    it has a band (at least :data:`MIN_DOF` degrees of freedom)."""
    return c.get("band") is not None


def out_of_band(c: dict) -> bool:
    """``c`` (a :func:`verdict`) was formed and lies outside its band."""
    return judgeable(c) and not c["ok"]


def shown(c: dict) -> str:
    """A verdict's figure as printed: ``1.03 (0.94-1.1) ok``, ``14.1 (0.82-1.2) OUT OF BAND``;
    not judged, ``1.21: too few degrees of freedom to judge (0.0007)``; of no update, ``none used
    (301 rejected by the gate)``; held-out predictions out of band with the factor on the sensor's
    sigma that would fit them (:func:`smoother.diagnosis.heldout.sigma_factor`), ``0.613 (0.92-1.1)
    OUT OF BAND: 1 per dof at its sigma x0.19``, or, where the errors near the used measurements lie
    below those far from them (:func:`smoother.diagnosis.heldout.near_and_far`), both figures; a
    drifting sensor's predicted without the used errors, that they judge no model."""
    if c["per_dof"] is None:
        return f"none used ({c.get('rejected', 0)} rejected by the gate)"
    if not judgeable(c):
        return f"{c['per_dof']:.3g}: {TOO_FEW_DOF} ({c['dof']:.2g})"
    text = f"{c['per_dof']:.3g} ({c['band'][0]:.2g}-{c['band'][1]:.2g}) {'ok' if c['ok'] else 'OUT OF BAND'}"
    if not c["ok"] and c["statistic"] == "heldout" and c.get("correlated"):
        near, far = c["near_far"]
        text += (f": {near:.2g} near the used measurements, {far:.2g} far from them -- the sensor's errors are "
                 + ("more alike in time than its correlation_time says (a longer one models them)"
                    if c.get("given_used_errors") else
                    "correlated in time, and this estimator predicts them without the used ones' errors (the batch "
                    "smoother's and the EKF's predictions are given them)" if c.get("not_given_used_errors") else
                    "correlated in time, which no white sigma fits (a correlation_time models them)"))
    elif not c["ok"] and c.get("not_given_used_errors"):
        text += (": not judged -- the sensor's errors drift and this estimator predicts them without the used "
                 "ones' errors, where its estimate follows them")
    elif not c["ok"] and c["statistic"] == "heldout" and c.get("sigma_factor") is not None:
        text += f": 1 per dof at its sigma x{c['sigma_factor']:.2g}"
    return text


def rejections(consistency: dict[str, dict]) -> str | None:
    """Why an EKF whose gate rejected more than :data:`MOST_REJECTED` of some sensor's updates
    (``consistency``: its verdicts, :func:`sensor_consistency`) is doubtful, naming each such
    sensor -- an estimate that used none of its aiding measurements is the IMU's dead reckoning
    -- or None."""
    most = {s: c["rejected"] for s, c in consistency.items()
            if "rejected" in c and c["rejected"] > MOST_REJECTED * (c["rejected"] + c["measurements"])}
    if not most:
        return None
    counts = ", ".join(f"{rejected} of {rejected + consistency[s]['measurements']} {s} measurements"
                       for s, rejected in most.items())
    if not any(c["measurements"] for c in consistency.values()):
        return (f"its gate rejected {counts}: it used no aiding measurement, so it is dead reckoning (the IMU "
                "alone), not a fused estimate, and its errors grow without bound")
    return (f"its gate rejected {counts}: there it shows mostly the IMU's dead reckoning, not those sensors "
            "(a gate that tight, or measurements that contradict the rest)")


def sensor_consistency(innovations: Innovations) -> dict[str, dict]:
    """Per sensor, the :func:`verdict` of its NIS through the EKF, and ``rejected``: the updates
    the EKF's gate refused. Only accepted updates count (module docstring; a sensor with none has
    a verdict of none); updates after a divergence (NaN) not at all."""
    names, first, which = np.unique(innovations.sensor, return_index=True, return_inverse=True)
    finite = np.isfinite(innovations.nis)
    accepted = finite & innovations.accepted

    def per_sensor(weights, mask) -> np.ndarray:  # sums over each sensor's updates, in one pass
        return np.bincount(which[mask], weights=None if weights is None else weights[mask], minlength=len(names))

    updates, used = per_sensor(None, finite), per_sensor(None, accepted)
    dof, total = per_sensor(innovations.dim.astype(float), accepted), per_sensor(innovations.nis, accepted)
    out = {}
    for j in np.argsort(first):  # in the order the sensors first updated
        if updates[j]:
            out[str(names[j])] = {**verdict(float(total[j]), float(dof[j]), int(used[j]), "nis"),
                                  "rejected": int(updates[j] - used[j])}
    return out


def overall(consistency: dict[str, dict]) -> dict | None:
    """The :func:`verdict` of all of one estimator's verdicts together (their sums and degrees of
    freedom added), of those formed (:func:`judgeable`: one on too few degrees of freedom counts
    for nothing, here neither), or None without any."""
    parts = [c for c in consistency.values() if judgeable(c)]
    if not parts:
        return None
    total = sum(c["per_dof"] * c["dof"] for c in parts)
    return verdict(total, sum(c["dof"] for c in parts), sum(c["measurements"] for c in parts), parts[0]["statistic"])


def far_above(c: dict) -> bool:
    """``c`` (a :func:`verdict`) was formed, is above its band and :data:`WARN_FACTOR` or more above 1."""
    return judgeable(c) and c["per_dof"] > max(c["band"][1], WARN_FACTOR)


def far_below(c: dict) -> bool:
    """``c`` (a :func:`verdict`) was formed, is below its band and :data:`WARN_FACTOR` or more below 1."""
    return judgeable(c) and c["per_dof"] < min(c["band"][0], 1.0 / WARN_FACTOR)


def with_heldout(verdicts: dict[str, dict], heldout: dict[str, dict]) -> dict[str, dict]:
    """Each sensor's record: its own :func:`verdict` with its held-out one's figures beside it
    (``heldout_per_dof``, ``heldout_band``, ``heldout_ok``, ``heldout_measurements``,
    ``heldout_dof``, ``heldout_band_dof``, ``heldout_state_share``, ``heldout_sigma_factor``, ``heldout_near_far``,
    ``heldout_correlated``, ``heldout_given_used_errors``, ``heldout_not_given_used_errors``;
    :mod:`smoother.diagnosis.heldout`);
    a sensor judged on held-out measurements alone has that verdict as its own (statistic ``heldout``)."""
    out = {name: dict(c) for name, c in verdicts.items()}
    for name, h in heldout.items():
        own = out.setdefault(name, {k: v for k, v in h.items() if k != "state_share"})
        own.update({"heldout_per_dof": h["per_dof"], "heldout_band": h["band"], "heldout_ok": h["ok"],
                    "heldout_measurements": h["measurements"], "heldout_dof": h["dof"],
                    "heldout_band_dof": h.get("band_dof"),
                    "heldout_state_share": h["state_share"], "heldout_sigma_factor": h.get("sigma_factor"),
                    "heldout_near_far": h.get("near_far"), "heldout_correlated": h.get("correlated", False),
                    "heldout_given_used_errors": h.get("given_used_errors", False),
                    "heldout_not_given_used_errors": h.get("not_given_used_errors", False)})
    return out


def far_off(c: dict) -> bool:
    """``c`` (a :func:`verdict`) was formed, is outside its band and :data:`WARN_FACTOR` or more
    from 1 (a warning's condition)."""
    return out_of_band(c) and not 1.0 / WARN_FACTOR < c["per_dof"] < WARN_FACTOR


def _by_sensor(by_estimator: dict[str, dict]) -> dict[str, dict]:
    """``{estimator: {sensor: verdict}}`` -> ``{sensor: {estimator: verdict}}``, sensors in the
    order first met, the IMU last."""
    out: dict[str, dict] = {}
    for estimator, consistency in by_estimator.items():
        for sensor, c in consistency.items():
            out.setdefault(sensor, {})[estimator] = c
    return dict(sorted(out.items(), key=lambda item: item[0] == IMU))


#: The name the IMU factors' verdict goes by (:mod:`smoother.diagnosis.residual_consistency`).
IMU = "imu"
_STATISTIC = {"nis": "NIS", "residual": "residuals", "heldout": "held-out predictions"}


def heldout_part(c: dict) -> dict | None:
    """The held-out verdict that :func:`with_heldout` put beside a sensor's own ``c``, as a
    :func:`verdict` of its own, or None."""
    if "heldout_per_dof" not in c or c.get("statistic") == "heldout":
        return None
    return {"per_dof": c["heldout_per_dof"], "band": c["heldout_band"], "ok": c["heldout_ok"],
            "measurements": c["heldout_measurements"], "dof": c.get("heldout_dof"), "statistic": "heldout",
            "band_dof": c.get("heldout_band_dof"),
            "sigma_factor": c.get("heldout_sigma_factor"), "near_far": c.get("heldout_near_far"),
            "correlated": c.get("heldout_correlated", False),
            "given_used_errors": c.get("heldout_given_used_errors", False),
            "not_given_used_errors": c.get("heldout_not_given_used_errors", False)}


def consistency_lines(by_estimator: dict[str, dict]) -> list[str]:
    """One line per sensor (the IMU last): each estimator's figure per dof with its statistic and
    band, and whether it fits (:func:`shown`; one on too few degrees of freedom says so); where a
    sensor holds measurements out (:func:`with_heldout`), the held-out predictions' figure beside
    its own."""
    lines = []
    for sensor, verdicts in _by_sensor(by_estimator).items():
        count = max(c["measurements"] + c.get("rejected", 0) for c in verdicts.values())
        parts = []
        for estimator, c in verdicts.items():
            held = heldout_part(c)
            parts.append(f"{estimator} {_STATISTIC[c['statistic']]} {shown(c)}"
                         + ("" if held is None else f", held-out predictions ({held['measurements']}) {shown(held)}"))
        name = "imu" if sensor == IMU else f"sensor {sensor}"
        lines.append(f"{name} ({count} {'factors' if sensor == IMU else 'measurements'}), per dof: " + "; ".join(parts))
    return lines


#: How the advice names each calibration part (:data:`factors.calibration.PARTS`), in the order it names them.
_SUSPECTS = {"lever_arm": "lever arm", "rotation": "rotation", "time_offset": "time offset", "scale": "scale"}


def suspects(kind: str | None) -> str:
    """The calibration parts a sensor of ``kind`` has, as a warning names them when its residuals
    are far above their band: ``"lever arm or time offset"`` for a GNSS (its fixes have no
    rotation), all four for a relative kind or an unknown one (None)."""
    parts = PARTS if kind is None else applicable(KINDS[kind].model)
    named = [text for part, text in _SUSPECTS.items() if part in parts]
    return ", ".join(named[:-1]) + f" or {named[-1]}" if len(named) > 1 else named[0]


def consistency_warnings(by_estimator: dict[str, dict], imu_findings=(),
                         causes: dict[str, str] | None = None, fitted: dict[str, str] | None = None,
                         sensor_kinds: dict[str, str] | None = None,
                         follow_imu: dict[str, str] | None = None, *,
                         correlation_times: dict[str, float] | None = None) -> list[str]:
    """One line per sensor outside its band by more than :data:`WARN_FACTOR` in some estimator,
    with the figure of every estimator outside its band, naming what to check, and one per sensor
    with an entry in ``causes`` (per sensor, the calibration its residuals point at,
    :func:`smoother.diagnosis.misfit_causes.hints`) however near its band: a sensor's line names
    that first, before its sigma (a systematic pattern also makes a sigma look too large or too
    small). When the IMU's own residuals are far above their band, or its raw data have ``imu_findings``
    (:class:`datasets.imu_health.ImuFinding` s), the IMU is named first and the other sensors'
    lines say that their misfit may follow from it -- but for a sensor with a cause, whose
    calibration error bends the estimate and so the IMU's residuals too: the IMU's line names
    those sensors instead (its findings still come first). ``fitted``: per sensor whose noise the
    run fitted, what became of it (:func:`smoother.diagnosis.noise_report.fitted_sensors`): such a
    sensor's line says what the fit did, and a sigma that looks too large is not advised to be
    fitted. ``sensor_kinds``: per sensor, its kind (:data:`datasets.kinds.KINDS`): a sensor's residuals far
    above their band name the calibration parts its kind has (:func:`suspects`), all four without.
    ``follow_imu``: per sensor whose errors may follow the IMU's, why
    (:func:`smoother.pipeline.imu_followers`): a sigma that looks too large by such a sensor's
    errors is not said to be so alone. ``correlation_times``: per drifting sensor, its
    ``correlation_time`` [s], named beside its sigma: a time longer than its errors' makes the
    innovations between consecutive measurements look too large (their weight grows as the two
    errors are taken to be more alike), a shorter one too small."""
    by_sensor = dict(sorted(_by_sensor(by_estimator).items(), key=lambda item: item[0] != IMU))  # the IMU first
    imu_off = [e for e, c in by_sensor.get(IMU, {}).items() if far_above(c)]
    kinds = ", ".join(dict.fromkeys(f"{f.sensor} {f.what}" if f.what != "gap" else "gap" for f in imu_findings))
    lines = []
    causes = {name: text for name, text in (causes or {}).items() if name in by_sensor and name != IMU}
    for sensor, verdicts in by_sensor.items():
        off = {e: c for e, c in verdicts.items() if far_off(c)}
        pattern = causes.get(sensor)
        if not off and pattern is None:
            continue
        # once a sensor warns, every estimator whose figure is out of its band is named, not only
        # those far enough off to raise the warning
        named = {e: c for e, c in verdicts.items() if out_of_band(c)} if off else verdicts
        figures = ", ".join(f"{e} {c['per_dof']:.3g} (expected {c['band'][0]:.2g}-{c['band'][1]:.2g})"
                            if judgeable(c) else f"{e} {shown(c)}" for e, c in named.items())
        if not off:  # near its band: the calibration it points at is the finding
            lines.append(f"{sensor}: per dof {figures}: its residuals point at {pattern}")
            continue
        if sensor == IMU:
            symptom = f", or see the calibration of {', '.join(causes)} below (it bends the motion)" if causes else ""
            lines.append(f"imu: residuals per dof {figures}: the IMU's data do not fit its model -- check its units "
                         f"(rad/s and m/s^2, not deg/s or g), saturation and spikes, and its noise densities{symptom}")
            continue
        high = any(c["per_dof"] > c["band"][1] for c in off.values())
        lowest = min(c["per_dof"] for c in off.values())
        following = f", or they follow the IMU's ({follow_imu[sensor]})" if sensor in (follow_imu or {}) else ""
        looks = f"its sigma looks {(1.0 / max(lowest, 1e-12)) ** 0.5:.2g}x too large by its errors{following}"
        outcome = (fitted or {}).get(sensor)
        fit_said = "" if outcome is None else f"its noise was fitted ({outcome}: the noise table says why)"
        tau = (correlation_times or {}).get(sensor)
        if high:
            drift = "" if tau is None else f", its correlation_time ({tau:g} s: too long?)"
            advice = (f"check its sigma (too small){drift}, {suspects((sensor_kinds or {}).get(sensor))}"
                      + (f"; {fit_said}" if fit_said else ""))
        else:
            drift = "" if tau is None else f" or its correlation_time ({tau:g} s) too short"
            advice = (f"{looks}{drift}, though {fit_said}" if outcome is not None else f'{looks}{drift}; estimate = '
                      '["noise"] on it (or smoother run --estimate-noise) fits it to the data')
        if pattern is not None:
            advice = (f"its residuals point at {pattern}; " +
                      ("if that is not it, check its sigma (too small)" if high
                       else f"then judge its sigma again (it looks too large{following})")
                      + (f"; {fit_said}" if fit_said else ""))
        if kinds:
            advice = (f"the IMU is the likelier cause ({kinds}: see the 'imu:' warnings), this misfit a symptom "
                      f"of it; if the IMU is cleared, {advice}")
        elif high and imu_off and pattern is None:
            imu_worst = max(by_sensor[IMU][e]["per_dof"] for e in imu_off)
            if imu_worst >= max(c["per_dof"] for c in off.values()):
                advice += "; the IMU's own residuals are further out of band, so the IMU is the likelier cause"
            else:
                advice += f"; the IMU's own residuals are out of band too ({imu_worst:.3g} per dof): check both"
        lines.append(f"{sensor}: per dof {figures}: {advice}")
    return lines
