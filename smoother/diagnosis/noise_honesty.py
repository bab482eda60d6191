"""Fitted noise that stays honest: a noise factor that explains a model error is reported as that
error, not applied as noise.

Variance components (:mod:`smoother.batch.variance_components`) fit whatever the residuals hold:
a wheel odometry mounted backwards, a gyro in degrees, a time offset left out all leave residuals
that a large enough "noise" explains, and the run then looks consistent while its estimate is
wrong. A fitted group is therefore a model error, with its likely cause, when

* its sensor's mounting is wrong by the closed-form check (:mod:`smoother.diagnosis.mounting`):
  the mounting is the cause, whatever the factor;
* it shrank the sigma of a sensor that reads the IMU's own messages
  (:attr:`datasets.types.Sensor.imu_stream`: a ROS ``sensor_msgs/Imu`` topic's orientation, a
  filter's output on the same gyro and accelerometer): its residuals measure how closely it
  follows the IMU, not its own error, and a sigma shrunk to them would count the IMU's information
  twice. A factor above 1 stays a noise to judge as any other's;
* its factor is implausible for a noise: beyond :data:`IMPLAUSIBLE_FACTOR` from the rig's value
  either way (a datasheet or an Allan variance is not off by that much; a unit or a frame is). A
  noise that large is a misfit: a unit, a frame, a mounting or a time offset. One that small is no
  misfit, since a wrong model only ever adds to the residuals: the value the rig states is far too
  large (a driver's placeholder covariance, millimetres read as metres), or the measurements are not
  independent of the rest (an AHRS's attitudes, filtered from the IMU's own gyro, follow the
  propagated attitude more closely than independent errors would). Neither is fixed by applying it:
  a factor fitted to measurements that share the IMU's errors over-trusts them;
* the IMU's components contradict each other: two estimated factors more than
  :data:`CONTRADICTION` apart in ratio (an accelerometer's white noise x67 beside a gyro's x0.03 is
  not an IMU, it is a misfit shared out). Beside a sensor whose error drifts (below), an IMU's
  factor this far off may also be that drift, which the IMU's noise grew to follow, and the cause
  says so;
* a sensor's whitened residuals are alike from one measurement to the next (lag-one correlation
  beyond :data:`CORRELATED`) and a calibration explains them: a lever arm, a time offset, a rotation
  or a scale left out leaves residuals that follow the motion, which the sensor's misfit causes
  (:mod:`smoother.diagnosis.misfit_causes`, fitted with the noise applied but every factor that grew
  held at 1, :meth:`smoother.batch.variance_components.NoiseFit.not_grown`: a grown factor lets the
  trajectory follow the misfit and hides it) name. Residuals alike in
  time that no calibration explains are the sensor's own drifting error (a GNSS receiver's, over
  seconds to minutes): the factor is their size and is applied, with a note that the estimate takes
  them as independent. A sensor estimating part of its calibration has the other parts analysed at
  its estimate; one whose causes were not analysed (a relative kind, or no causes given) counts as a
  systematic error, as without the analysis. The IMU's factors share their keyframes, so theirs are
  correlated by construction and not judged so;
* a drifting sensor's innovations alternate from one measurement to the next (lag-one correlation
  below ``-ALTERNATING`` and :data:`ALTERNATING_SIGMAS` standard deviations, ``1 / sqrt(dof)``,
  from 0): its correlation time is longer than its errors' (white errors taken to drift with
  ``phi`` leave innovations correlated ``-phi / (1 + phi^2)``, -0.5 as ``phi`` nears 1), or its
  errors have a white part beside the drift (a receiver's noise), which no one correlation time
  models (with fixes far closer than the time, a white part of 5 % of the variance alternates them
  at -0.44). The factor, fitted to put the innovations in band (5.4x on the simulator's white poses
  taken to drift over 3 s at 10 Hz), is applied -- the model is the user's, and a drifting receiver
  has such a part -- with a note that it fits the model, not the sensor's noise, and that held-out
  measurements judge it, unless another finding here refuses it;
* the fit grew its sigma until the estimate hardly uses it (a factor beyond
  :data:`DISCARDED_FACTOR` with a redundancy of nearly every degree of freedom its residuals have):
  its verdict no longer responds to its sigma, and the sensor is dropped, not weighed;
* it grew beside a calibration the rig leaves out: a sensor's misfit causes (analysed wherever a
  factor grew, :func:`to_analyse`) name one that explains at least :data:`EXPLAINED` of its
  residuals. Its misfit is then shared out over every noise the fit could grow to follow it -- the
  IMU's, whose states every sensor reads, and the sensor's own -- whether or not the residuals are
  alike in time: an AHRS whose attitudes lag the gyro by 20 ms left residuals the gyro's white
  noise, grown 24x, took up, far beside its datasheet and gone once the delay was estimated (2.7x).
  Every grown IMU component and the sensor's grown groups are that misfit, not noise.

Each such group keeps the rig's value, and the run stays doubtful with the cause; the run's other
groups are fitted again with it held (by the run, :mod:`smoother.pipeline`), since they took up
part of the same misfit.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, replace

from smoother.batch.variance_components import IMU_BLOCK, NoiseFit
from smoother.diagnosis.misfit_causes import hint

#: A factor beyond this (or below its inverse) on a density or sigma is not a noise.
IMPLAUSIBLE_FACTOR = 100.0
#: Two of the IMU's estimated factors further apart than this ratio contradict each other.
CONTRADICTION = 100.0
#: Residuals correlated beyond this from one measurement to the next are not white noise.
CORRELATED = 0.5
#: A drifting sensor's innovations correlated below minus this from one measurement to the next ...
ALTERNATING = 0.3
#: ... and by this many standard deviations of a correlation of white ones alternate: its correlation time is too long.
ALTERNATING_SIGMAS = 3.0
#: A group grown beyond this factor ...
DISCARDED_FACTOR = 10.0
#: ... whose redundancy is at least this share of its residuals' degrees of freedom is discarded.
DISCARDED_SHARE = 0.95
#: A calibration left out that explains at least this share of a sensor's residuals (a suggested
#: misfit cause) is a wrong rig: the noise grown beside it is that misfit.
EXPLAINED = 0.5


@dataclass(frozen=True)
class ModelError:
    """A fitted noise group that is a model error: ``group`` (its name), ``cause`` (one line)."""

    group: str
    cause: str


def _alike(g) -> bool:
    """Whether a sensor's group (not the IMU's) has residuals alike in time, beyond :data:`CORRELATED`."""
    return g.group.sensor != IMU_BLOCK and g.correlation > CORRELATED


def _alternating(g) -> bool:
    """Whether a drifting sensor's group has innovations alternating in time (module docstring)."""
    return g.correlation < -max(ALTERNATING, ALTERNATING_SIGMAS / math.sqrt(max(g.dof or 0, 1)))


def correlated(fit: NoiseFit) -> list[str]:
    """The sensors with an applied group whose residuals are alike in time (:func:`_alike`):
    those whose misfit causes :func:`honest` needs."""
    return sorted({g.group.sensor for g in fit.groups if g.estimable and g.applied and _alike(g)})


def to_analyse(fit: NoiseFit) -> bool:
    """Whether the fit needs its sensors' misfit causes (:func:`honest`): a group's residuals are
    alike in time (:func:`correlated`), or an applied factor grew, which a calibration the rig
    leaves out may have grown."""
    return bool(correlated(fit)) or any(g.estimable and g.applied and g.factor > 1.0 for g in fit.groups)


def _left_out(causes: dict | None) -> dict[str, list]:
    """Per sensor, its suggested misfit causes explaining at least :data:`EXPLAINED` of its residuals
    (only sensors with one)."""
    out = {}
    for sensor, found in (causes or {}).items():
        if material := [c for c in found if c.suggested and c.share >= EXPLAINED]:
            out[sensor] = material
    return out


def honest(fit: NoiseFit, mounting_wrong=(), causes: dict | None = None,
           imu_streams: dict[str, str] | None = None, *,
           correlation_times: dict[str, float] | None = None) -> tuple[NoiseFit, list[ModelError]]:
    """``fit`` with every group that is a model error (module docstring) kept at the rig's value,
    and those errors. ``mounting_wrong``: the sensors whose mounting the closed-form check found
    wrong. ``imu_streams``: per sensor that reads the IMU's own messages, that stream.
    ``correlation_times``: per drifting sensor, its ``correlation_time`` [s].
    ``causes``: per sensor analysed, its misfit causes
    (:func:`smoother.diagnosis.misfit_causes.causes_at` with the fitted noise applied, no factor
    grown: :meth:`~smoother.batch.variance_components.NoiseFit.not_grown`), which tell a
    systematic error from a drifting one among residuals alike in time."""
    errors: dict[str, str] = {}
    drifting: dict[str, str] = {}
    alternating: dict[str, str] = {}
    too_small: set[str] = set()
    for g in fit.groups:
        if not (g.estimable and g.applied):
            continue
        name, sensor = g.group.name, g.group.sensor
        if sensor in mounting_wrong:
            errors[name] = (f"its mounting is wrong (the mounting check): a noise {g.factor:.3g}x the rig's would "
                            "hide it")
        elif sensor in (imu_streams or {}) and g.factor < 1.0:
            too_small.add(name)
            errors[name] = (f"it reads the IMU's own messages ({imu_streams[sensor]}): its residuals measure how "
                            "closely it follows the IMU, not its own error, and a sigma "
                            f"{g.factor:.3g}x the rig's would count the IMU's information twice")
        elif g.factor > IMPLAUSIBLE_FACTOR:
            errors[name] = (f"a noise {g.factor:.3g}x the rig's is no sensor's error of its datasheet: a unit, a "
                            "frame, a mounting or a time offset is wrong")
        elif g.factor < 1.0 / IMPLAUSIBLE_FACTOR:
            too_small.add(name)
            errors[name] = (f"a noise {g.factor:.3g}x the rig's is below any sensor's datasheet, which no model "
                            "error makes (it only adds to the residuals): the rig's value is far too large (a "
                            "driver's placeholder covariance, a unit: state the datasheet's), or the measurements "
                            "follow the IMU closer than independent errors would (an AHRS's attitudes filtered from "
                            "its own gyro), and a sigma fitted to them would over-trust them")
        elif _alike(g):
            alike = f"its residuals are alike from one measurement to the next (correlation {g.correlation:.2f})"
            if causes is None or sensor not in causes:
                errors[name] = f"{alike}: a systematic error (a lever arm, a time offset, a scale), not noise"
            elif found := [c for c in causes[sensor] if c.suggested]:
                errors[name] = (f"{alike} and point at {', '.join(c.text() for c in found)}: a systematic error, "
                                "not noise")
            else:
                drifting[name] = (f"{alike}, and no calibration explains them: the sensor's error drifts, the "
                                  "factor is its size, and the estimate takes its measurements as independent "
                                  "(measurements further apart, `every`, are nearer so; a correlation_time, or a "
                                  "longer one, models the drift)")
        elif g.factor > DISCARDED_FACTOR and g.dof and g.redundancy >= DISCARDED_SHARE * g.dof:
            errors[name] = (f"the fit grew its sigma {g.factor:.3g}x until the estimate hardly uses it: its "
                            "measurements disagree with the rest of the model")
        elif sensor in (correlation_times or {}) and _alternating(g):
            alternating[name] = (f"its innovations alternate from one measurement to the next "
                                 f"(correlation {g.correlation:.2f}): its errors are less alike than its "
                                 f"correlation_time ({correlation_times[sensor]:g} s) says -- a shorter one, or "
                                 "none, models them; with a white part beside the drift (a receiver's noise), no "
                                 "one time does -- and the factor is fitted to the model, not to the sensor's "
                                 "noise: judge it by held-out measurements (`every`)")
    if left_out := _left_out(causes):
        named = "; ".join(f"{sensor}'s residuals point at {hint(found)}" for sensor, found in left_out.items())
        for g in fit.groups:
            if (g.estimable and g.applied and g.factor > 1.0 and g.group.name not in errors
                    and (g.group.sensor == IMU_BLOCK or g.group.sensor in left_out)):
                errors[g.group.name] = (f"a noise {g.factor:.3g}x the rig's grown beside a calibration the rig "
                                        f"leaves out ({named}): that misfit, not noise")
    imu = [g for g in fit.groups if g.group.sensor == IMU_BLOCK and g.estimable and g.applied
           and g.group.name not in errors]
    if len(imu) >= 2:
        high, low = max(imu, key=lambda g: g.factor), min(imu, key=lambda g: g.factor)
        if high.factor / low.factor > CONTRADICTION:
            cause = (f"the IMU's components contradict each other ({high.group.part} x{high.factor:.3g} beside "
                     f"{low.group.part} x{low.factor:.3g}): a misfit shared out, not an IMU's noise")
            errors.setdefault(high.group.name, cause)
            errors.setdefault(low.group.name, cause)
    drifters = sorted({g.group.sensor for g in fit.groups if g.group.name in drifting})
    if drifters:  # the IMU's noise grown to let the trajectory follow a sensor's drift
        also = (f", or the IMU follows the drift of {' and '.join(drifters)}'s errors: measurements further "
                "apart (`every`) keep it out")
        imu_groups = {g.group.name for g in fit.groups if g.group.sensor == IMU_BLOCK}
        imu_groups -= too_small  # a drift is followed by a noise grown, not shrunk
        errors = {name: cause + also if name in imu_groups else cause for name, cause in errors.items()}
    noted = {**drifting, **alternating}
    if not errors and not noted:
        return fit, []
    groups = [replace(g, applied=False, note=f"not applied: {errors[g.group.name]}") if g.group.name in errors
              else replace(g, note=noted[g.group.name]) if g.group.name in noted else g for g in fit.groups]
    return replace(fit, groups=groups), [ModelError(name, cause) for name, cause in errors.items()]

