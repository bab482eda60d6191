"""A coarse check of every sensor's mounting rotation before estimating: the rig's ``R_BS``
against the rotation the data give (:mod:`smoother.diagnosis.mounting_data`), in the directions
the data determine.

Axis mix-ups -- ENU against NED, a transform's angles in the wrong order, a sensor mounted
backwards -- are the commonest rig errors, and an estimator run on one blames something else (a
wheel odometry turned 180 degrees about the vertical ends every estimator at the negative of the
right position). Contract of :func:`check_mountings`: for each sensor with a frame whose rotation
enters its measurements (pose, orientation, odometry, velocity, roll_pitch) either a
:class:`MountingFinding` or a :class:`NotChecked` saying why not (the kind has no rotation that
matters, too few measurements, a motion that determines at most one direction of the rotation).

Conventions (docs/design.md, sections 1, 3, 7): ``R_BS`` maps sensor coordinates to IMU
coordinates; a rotation's uncertainty is that of its LEFT perturbation ``exp(rho) R`` with
``rho`` in the IMU frame. The decision, derived in ``docs/mounting.md``:

* a direction of ``rho`` is determined when its sigma is at most :data:`DETERMINED_SIGMA_DEG`;
* with one direction ``a`` undetermined, the data fix ``R`` only up to ``exp(theta a) R``: the
  rig is compared with the member of that family nearest to it (closed form in ``theta``);
* the rig is wrong when that angle exceeds both :data:`WRONG_ANGLE_DEG` and
  :data:`SIGMAS` sigmas of the data in the direction of the difference;
* the message names, for each sensor axis whose image the data determine, the nearest signed IMU
  axis under the data's rotation and under the rig's, where they differ.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from datasets.types import Dataset, Sensor
from factors import so3
from factors.sensor_models import extrinsic_parts
from smoother.diagnosis.imu_integrals import imu_integrals
from smoother.diagnosis.mounting_data import DataRotation, NotDetermined, data_rotation

#: A direction of the rotation is determined when the data's sigma about it is at most this
#: [deg]: the smallest axis mix-up, a quarter turn, then lies at least six sigma away.
DETERMINED_SIGMA_DEG = 15.0
#: A rig rotation is wrong only beyond this angle from the data's [deg]: smaller errors lie within
#: two sigmas of the default rotation-calibration prior (0.1 rad), where ``estimate =
#: ["rotation"]`` corrects them, and far below the quarter turn of an axis mix-up.
WRONG_ANGLE_DEG = 10.0
#: ... and beyond this many of the data's sigmas in the direction of the difference.
SIGMAS = 3.0
#: A sensor axis counts as lying along the one undetermined direction within this angle [deg].
ALONG_DEG = 30.0

#: How a message names a sensor's axes, by kind (a vehicle's twist: REP-103's body axes).
AXIS_NAMES = {"velocity": ("forward axis (x)", "left axis (y)", "up axis (z)")}
_PLAIN_AXES = ("x axis", "y axis", "z axis")


@dataclass(frozen=True, eq=False)
class MountingFinding:
    """What the data say about ``sensor``'s (of ``kind``) mounting rotation.

    ``R_data`` (3x3): the rotation ``R_BS`` the data give; ``cov`` (3x3, [rad^2]): the covariance
    of its LEFT perturbation in the IMU frame over the determined directions (the orthonormal rows
    of ``observable_axes``, IMU frame; along the others the data say nothing and ``cov`` is 0);
    ``R_rig``: the rig's; ``rig_angle_deg``: the angle between the rig's rotation and the data's
    (nearest to the rig along an undetermined direction); ``rig_sigma_deg``: the data's sigma in
    the direction of that difference; ``wrong``: the rig is off by more than
    :data:`WRONG_ANGLE_DEG` and :data:`SIGMAS` sigmas; ``message``: one line naming the sensor and
    the axes; ``rows``: the spans (or epochs) the rotation was found from."""

    sensor: str
    kind: str
    R_data: np.ndarray
    cov: np.ndarray
    observable_axes: np.ndarray
    R_rig: np.ndarray
    rig_angle_deg: float
    rig_sigma_deg: float
    wrong: bool
    message: str
    rows: int

    @property
    def unobservable_axes(self) -> np.ndarray:
        """The orthonormal rows (IMU frame) spanning the directions the data do not determine."""
        _, _, vt = np.linalg.svd(np.vstack([self.observable_axes, np.zeros((3, 3))]))
        return vt[len(self.observable_axes):]


@dataclass(frozen=True)
class NotChecked:
    """A sensor whose mounting rotation the data cannot check, and why (``reason``)."""

    sensor: str
    kind: str
    reason: str

    @property
    def message(self) -> str:
        return f"{self.sensor} ({self.kind}): mounting not checked: {self.reason}"


@dataclass(frozen=True, eq=False)
class MountingCheck:
    """Every sensor's :class:`MountingFinding` or :class:`NotChecked`, in the dataset's order."""

    results: tuple

    @property
    def findings(self) -> tuple[MountingFinding, ...]:
        return tuple(r for r in self.results if isinstance(r, MountingFinding))

    @property
    def wrong(self) -> tuple[MountingFinding, ...]:
        """The findings whose rig rotation is wrong."""
        return tuple(r for r in self.findings if r.wrong)

    @property
    def not_checked(self) -> tuple[NotChecked, ...]:
        return tuple(r for r in self.results if isinstance(r, NotChecked))

    def lines(self) -> list[str]:
        """One message a sensor."""
        return [r.message for r in self.results]

    def record(self) -> dict:
        """``metrics.json``'s ``_run.mounting``: per sensor ``wrong``, ``angle_deg`` (the rig's
        rotation against the data's), ``sigma_deg``, ``R_data`` and ``message``; or ``checked``
        false with the ``reason``."""
        out = {}
        for r in self.results:
            if isinstance(r, NotChecked):
                out[r.sensor] = {"checked": False, "reason": r.reason}
            else:
                out[r.sensor] = {"checked": True, "wrong": r.wrong, "angle_deg": r.rig_angle_deg,
                                 "sigma_deg": r.rig_sigma_deg, "R_data": r.R_data.tolist(), "message": r.message}
        return out


def check_mountings(dataset: Dataset) -> MountingCheck:
    """The mounting check of every sensor of ``dataset`` (module docstring), on its measurements
    used; the IMU is integrated once for all of them."""
    integrals = imu_integrals(dataset)
    results = []
    for sensor in dataset.sensors:
        try:
            results.append(compare(sensor, data_rotation(dataset, sensor, integrals)))
        except NotDetermined as reason:
            results.append(NotChecked(sensor.name, sensor.kind, str(reason)))
    return MountingCheck(tuple(results))


def compare(sensor: Sensor, estimate: DataRotation) -> MountingFinding | NotChecked:
    """The :class:`MountingFinding` of ``sensor`` (its rig rotation from its data's ``T_BS``)
    given the data's :class:`~smoother.diagnosis.mounting_data.DataRotation`; a
    :class:`NotChecked` when fewer than two directions are determined."""
    R_rig, _ = extrinsic_parts(sensor.data.T_BS)
    R_data = estimate.R
    lam, V = np.linalg.eigh(estimate.information)
    sigma = 1.0 / np.sqrt(np.maximum(lam, 1e-300))
    determined = sigma <= np.radians(DETERMINED_SIGMA_DEG)
    if determined.sum() < 2:
        return NotChecked(sensor.name, sensor.kind, "the motion determines at most one direction of its rotation "
                                                    f"(sigmas {_sigmas_text(sigma)} deg)")
    observable = V[:, determined].T
    cov = (observable.T / lam[determined]) @ observable
    undetermined = V[:, ~determined].T
    R_near = R_data if determined.all() else _nearest_about(undetermined[0], R_data, R_rig)
    difference = so3.log(R_rig @ R_near.T)
    angle = float(np.linalg.norm(difference))
    along = difference / angle if angle > 0 else V[:, np.argmax(sigma * determined)]
    sigma_along = float(np.sqrt(along @ cov @ along))
    wrong = angle > max(np.radians(WRONG_ANGLE_DEG), SIGMAS * sigma_along)
    message = _message(sensor, R_near, R_rig, undetermined, np.degrees(angle), np.degrees(sigma_along), along, wrong)
    return MountingFinding(sensor.name, sensor.kind, R_data, cov, observable, R_rig, float(np.degrees(angle)),
                           float(np.degrees(sigma_along)), bool(wrong), message, estimate.rows)


def _nearest_about(a: np.ndarray, R: np.ndarray, target: np.ndarray) -> np.ndarray:
    """The rotation ``exp(theta a) R`` nearest to ``target`` (unit ``a``): it maximises
    ``tr(exp(theta a^x) N)``, ``N = R target^T``, which is ``tr N + sin(theta) tr(a^x N) +
    (1 - cos(theta)) tr(a^x a^x N)`` by Rodrigues' formula."""
    A = so3.skew(a)
    N = R @ target.T
    theta = np.arctan2(np.trace(A @ N), -np.trace(A @ A @ N))
    return so3.exp(theta * a) @ R


def _axis(v: np.ndarray) -> str:
    """The IMU axis nearest to the line along ``v`` (``x``, ``y``, ``z``)."""
    return "xyz"[int(np.argmax(np.abs(v)))]


def _signed_axis(v: np.ndarray) -> str:
    """The IMU axis nearest to the direction ``v``, with its sign (``+x``, ``-z``)."""
    i = int(np.argmax(np.abs(v)))
    return ("+" if v[i] >= 0 else "-") + "xyz"[i]


def _sigmas_text(sigma: np.ndarray) -> str:
    """Sigmas [rad] in degrees, ``inf`` for those without information."""
    return ", ".join("inf" if not np.isfinite(s) or s > 1e6 else f"{np.degrees(s):.3g}" for s in sigma)


def _message(sensor: Sensor, R_near, R_rig, undetermined, angle: float, sigma: float, along, wrong: bool) -> str:
    """The finding's one line: the sensor, the axes the data and the rig put differently (of those
    whose image the data determine), the angle, and the direction not determined, if any."""
    names = AXIS_NAMES.get(sensor.kind, _PLAIN_AXES)
    axes = range(3)
    if len(undetermined):
        cosine = np.abs(undetermined[0] @ R_near)
        axes = [int(np.argmax(cosine))] if cosine.max() >= np.cos(np.radians(ALONG_DEG)) else []
    differ = [(names[i], _signed_axis(R_near[:, i]), _signed_axis(R_rig[:, i])) for i in axes
              if _signed_axis(R_near[:, i]) != _signed_axis(R_rig[:, i])]
    bound = f"{SIGMAS:g} sigma {SIGMAS * sigma:.1f} deg"
    if angle <= SIGMAS * sigma:
        text = f"the rig's mounting agrees with the data's ({angle:.1f} deg apart, {bound})"
    elif not wrong:
        text = (f"the rig's mounting is {angle:.1f} deg off the data's, beyond {bound} but within the "
                f"{WRONG_ANGLE_DEG:g} deg a rotation calibration corrects")
    elif differ:
        text = "the data put " + "; ".join(f"its {name} on the IMU's {data}, the rig on {rig}"
                                           for name, data, rig in differ)
        text += f" ({angle:.0f} deg apart, {bound})"
    else:
        text = f"the rig's mounting is {angle:.0f} deg off the data's about the IMU's {_signed_axis(along)} ({bound})"
    if len(undetermined):
        text += f"; its rotation about the IMU's {_axis(undetermined[0])} axis is not determined by this motion"
    return f"{sensor.name} ({sensor.kind}): {text}"
