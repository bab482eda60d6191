"""Per-sensor consistency: is each sensor's noise, extrinsic and time offset what its data show?

Through the EKF, a measurement's normalised innovation squared ``NIS = e^T S^-1 e`` (``S = H P
H^T + R``) is chi-square distributed with ``dim`` degrees of freedom when the model is right. Over
a sensor's ``N`` updates the sum is chi-square with ``N dim`` degrees of freedom, so the mean NIS
per degree of freedom lies in ``[chi2(0.025; N dim), chi2(0.975; N dim)] / (N dim)`` with 95%
probability. Outside that band the sensor's ``sigma`` is too small (above) or too large (below),
or its lever arm, rotation or time offset is wrong (above: the residuals carry a systematic part).

Only the updates the filter accepted count (a gate's rejections are counted apart: their NIS is
large by construction). Over many updates the band is narrow (about +-1% for 10^4 GNSS fixes), so
a real sensor with slightly correlated errors falls outside it: ``ok`` states the statistics, and
a warning names a sensor only when its NIS per dof is also a factor :data:`WARN_FACTOR` or more
away from 1 -- a sigma, extrinsic or time offset that is actually wrong. When the IMU itself has
findings (:func:`datasets.imu_health.inspect_imu`: clipping, spikes, gaps, wrong units), every
sensor's NIS is a symptom of them first: the warning then names the IMU as the likelier cause.
"""
from __future__ import annotations

import numpy as np

from smoother.ekf import Innovations
from smoother.metrics import chi2_quantile

#: Probability of the band within which a consistent sensor's mean NIS per dof lies.
BAND_PROBABILITY = 0.95
#: A sensor is warned about when its NIS per dof is outside the band and outside
#: ``[1 / WARN_FACTOR, WARN_FACTOR]``.
WARN_FACTOR = 2.0


def sensor_consistency(innovations: Innovations) -> dict[str, dict]:
    """Per sensor: ``nis_per_dof`` (the mean NIS over its updates divided by the dimension),
    ``band`` (:data:`BAND_PROBABILITY` interval of that mean for a consistent sensor), ``ok``
    (inside the band), ``updates`` and ``rejected`` (by the EKF's gate) counts, and ``through``:
    ``"ekf"`` (the figures are the EKF's innovations, a property of the sensor and the model, the
    same in every estimator's block). Only accepted updates count (module docstring); updates after
    a divergence (NaN) not at all."""
    out = {}
    for name in dict.fromkeys(innovations.sensor):
        ours = (innovations.sensor == name) & np.isfinite(innovations.nis)
        mine = ours & innovations.accepted
        if not mine.any():
            continue
        dof = float(innovations.dim[mine].sum())
        lo = chi2_quantile(0.5 * (1 - BAND_PROBABILITY), dof) / dof
        hi = chi2_quantile(0.5 * (1 + BAND_PROBABILITY), dof) / dof
        value = float(innovations.nis[mine].sum() / dof)
        out[str(name)] = {"nis_per_dof": value, "band": [lo, hi], "ok": bool(lo <= value <= hi),
                          "updates": int(mine.sum()), "rejected": int((ours & ~innovations.accepted).sum()),
                          "through": "ekf"}
    return out


def consistency_lines(consistency: dict[str, dict]) -> list[str]:
    """One line per sensor: its NIS per dof against its band, and whether it fits."""
    return [f"sensor {name}: NIS {c['nis_per_dof']:.3g} per dof over {c['updates']} updates, expected "
            f"{c['band'][0]:.2g}-{c['band'][1]:.2g}: {'ok' if c['ok'] else 'OUT OF BAND'}"
            for name, c in consistency.items()]


def consistency_warnings(consistency: dict[str, dict], imu_findings=()) -> list[str]:
    """One line per sensor outside its band by more than :data:`WARN_FACTOR`, naming what to check:
    with ``imu_findings`` (:class:`datasets.imu_health.ImuFinding` s) the IMU first."""
    lines = []
    kinds = ", ".join(dict.fromkeys(f"{f.sensor} {f.what}" if f.what != "gap" else "gap" for f in imu_findings))
    for name, c in consistency.items():
        if c["ok"] or 1.0 / WARN_FACTOR < c["nis_per_dof"] < WARN_FACTOR:
            continue
        lo, hi = c["band"]
        advice = ("check its sigma (too small), lever arm, rotation or time offset" if c["nis_per_dof"] > hi
                  else "its sigma looks too large")
        if kinds:
            advice = (f"the IMU is the likelier cause ({kinds}: see the 'imu:' warnings), this NIS a symptom of "
                      f"it; if the IMU is cleared, {advice}")
        lines.append(f"{name}: NIS {c['nis_per_dof']:.3g} per dof, expected {lo:.2g}-{hi:.2g}: {advice}")
    return lines
