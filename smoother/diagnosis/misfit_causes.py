"""Which calibration a sensor's misfit points at: its residuals regressed on the pattern that each
calibration error leaves in them.

Model. A sensor's residual at the estimate is ``e_i = h(x_i; c) - z_i`` (``d`` numbers per
measurement ``i``, the kind's kernel, :mod:`factors.sensor_models`) with the calibration ``c``
the rig states (where the sensor estimates some of its calibration, with that estimate). Were
the measurements made with ``c + dc``, then to first order

    e_i = X_i dc + n_i,        X_i = -de_i/dc,

each candidate calibration with its own columns of ``X_i`` (``d x k``), in the units of the rig's
``estimate = [...]`` keys:

* ``scale`` ``s`` (what the sensor reads per unit of the truth; the correction is ``s - 1``):
  ``z = s h`` gives ``e = -(s - 1) h``: the pattern is minus the prediction ``h_i = e_i + z_i``
  (a wheel speed reading 1 % low, ``s = 0.99``: the residual is +1 % of the speed, along the
  direction of travel). Kinds with scaled rows (a velocity).
* ``time_offset`` ``d`` [s] (the measurement was taken at ``t_stamp + d``; ``d`` is what to add to
  the rig's ``time_offset``): ``z = h(x(t + d))`` gives ``e = -d dh/dt`` with ``dh/dt = H_i
  xdot_i``, ``H_i`` the residual's error-state Jacobian and ``xdot`` the state's rate in the
  error-state chart, ``(C v, C^T g + f - w x v, C w, 0, 0)`` (:func:`factors.imu.state_derivative`,
  the model's own): a position through the velocity, an attitude through the angular rate, a
  velocity through the specific force. ``f, w`` are the IMU's readings less the estimate's biases,
  the readings averaged over :data:`AVERAGE_S` about ``t_i`` (one sample's noise in a regressor
  would bias the fit towards 0). A velocity sensor's lever-arm term
  ``w x p`` also changes with the angular acceleration; that part is neglected.
* ``rotation`` ``phi`` [rad] (``R_BS <- exp(phi) R_BS``, ``phi`` in the IMU frame): for a
  velocity sensor ``e = -R_BS^T u^x phi`` with ``u = v + w x p_BS`` the sensor's velocity in the
  IMU frame: a pitched sensor reads a constant fraction of the speed vertically, a yawed one
  laterally; an attitude sensor's residual is moved by ``phi`` (seen in the world frame). Kinds
  with a frame.
* ``lever_arm`` ``dp`` [m] (``p_BS <- p_BS + dp``, IMU frame): a position's residual is ``-C dp``
  (an offset fixed in the IMU frame, which turns with the vehicle), a velocity's ``-R_BS^T (w x
  dp)`` (with the angular rate). Kinds with a position, or a velocity through the lever arm.

These are the error coordinates of :mod:`factors.calibration`, so every candidate's columns are
minus the calibrated kernel's own Jacobian (the estimators' model, its analytic derivatives,
checked against numerical ones there). A candidate whose columns are zero for every measurement
does not enter the kind's residual and is no candidate; nor is a part the sensor estimates
already (its calibration variable is free in the fit below, at its estimate). Relative kinds
(odometry, two states per measurement) are not analysed.

Fit. A sensor's residuals at an estimate hold only the part of a calibration error that the
states could not follow: a filter leans its velocity on a wheel speed read 1 % low (on a
simulated car its innovations keep 0.08 % of it, and point at a scale for a pitched sensor); a
smoother's residuals keep a share that depends on what else fixes the motion. So the
corrections of every sensor are fitted together with the states, as one Gauss-Newton step of
the batch smoother's whole problem linearised at the estimate
(:func:`fit_in_problem`): with ``W_i`` the whitening of a measurement factor's covariance (grown
by the process noise where the measurement is attached to the keyframe before it) the sensor's
rows ``W_i (e_i + H_i dx_i) - W_i X_i dc`` beside every other factor's, ``H_i`` the factor's own
Jacobian of the keyframe it reads and ``X_i`` taken at the state the measurement saw (carried from
that keyframe to its stamp), a weak prior ``dc ~ N(0,
PRIOR_SIGMA^2)`` (a calibration the data do not fix keeps about its prior's sigma instead of
making the system singular), solved by sparse QR through GTSAM with the calibrations eliminated
last, whose conditionals give their joint covariance. A misfit that one sensor's calibration
explains is then not put on another's, and the states give back what they had absorbed. From
the batch's optimum this is the first step of the calibrated problem; from the EKF's estimate,
one step of the batch problem from it (:func:`causes_at`). The values are first-order: a rotation
``phi`` leaves errors of order ``phi^2 / 2`` in the others (a wheel pitched by 3.8 deg reads
``cos(phi)`` of its speed forward: 0.22 % beside its scale), which the calibrated run removes.

Sigmas. The formal covariance assumes the stated sigmas and white errors; both are what is in
doubt, so it is scaled by the variance per degree of freedom of the sensor's whitened residuals
after the fit (either way: a sigma stated too large is the case to see through), its degrees of
freedom those that the batch smoother's verdict counts at the estimate (each measurement's ``d``
less its leverage, :mod:`smoother.diagnosis.residual_consistency`) less the corrections fitted -- where
another estimator's verdict does not count them, ``n d`` would overstate them for a sensor that
pins the states (its residuals are small by leverage, not by precision), and the variance is
taken as at least 1 instead -- and by ``(1 + rho) / (1 - rho)`` with ``rho > 0`` the lag-1
autocorrelation of those residuals from one measurement to the next (the variance of a mean of
AR(1) errors; ``rho`` at most :data:`MAX_RHO`).

Shares. A candidate's ``gain`` is the decrease of the step's cost it adds to the sensor's other
significant candidates (every other sensor's calibration held at 0, :func:`_gains`), its
``share`` ``gain / (gain + sum |r_i|^2)`` with ``r_i`` the sensor's whitened residuals after the
fit: the part of what is left without it that it explains. A pitch that explains most of a
wheel's residuals leaves its scale a share of the rest, and two candidates that cancel each other
(a time offset and a lever arm along the direction of travel, at the usual speed) have little
gain each. A cause is ``suggested`` when some component is significant -- ``|dc| > SIGNIFICANCE
sigma`` and at least :data:`SMALLEST`, the finest prior a rig can write for that part (a
correction below it is no advice a rig can take: on model-exact data a lever arm of 1e-17 m is
"significant" against a sigma of 1e-18) -- and its share is at least :data:`MATERIAL_SHARE`, and
the sensor's residuals leave at least :data:`smoother.diagnosis.verdicts.MIN_DOF` degrees of
freedom once the candidates are fitted (on fewer, their variance, and so the sigmas, are a few
squares' noise: ``judged`` False).

Cost. The candidates of every sensor fitted together are a dense block the states' elimination
carries along, its width squared per keyframe: so at most :data:`MAX_ANALYSED` sensors are fitted
together, of more the :func:`suspects` (a screen linear in the measurements), and the elimination
runs :data:`ELIMINATION_CHUNK` keys per GTSAM call, so that a Ctrl-C or SIGTERM, which Python
handles between calls, stops it promptly. The whole is linear in the sensors and the keyframes.
"""
from __future__ import annotations

from dataclasses import dataclass

import gtsam
import numpy as np

from datasets.kinds import KINDS, calibrated_rows, sensors_of
from datasets.ranges import RANGES
from datasets.types import ImuSamples, Sensor, Trajectory
from factors import imu
from factors.calibration import PART_COLUMNS, Calibration, applicable
from smoother.diagnosis.figures import plus_minus
from smoother.diagnosis.verdicts import MIN_DOF, out_of_band
from smoother.estimators import ESTIMATORS
from smoother.model.blocks import Block, evaluate_block, linearize
from smoother.model.problem import Problem, build_problem
from smoother.model.timeline import carry

#: The candidate calibrations, by the rig's ``estimate`` keys, with the sigma of the weak prior on
#: each correction (scale - 1, s, rad, m).
PRIOR_SIGMA = {"scale": 1.0, "time_offset": 1.0, "rotation": 1.0, "lever_arm": 10.0}
#: At most this many sensors' candidates are fitted together (:func:`suspects`): the candidates'
#: dense block costs their number squared per keyframe and their cube once; with more sensors the
#: whole fit took 3 s at 100 and 99 s and 3.7 GB at 300 (20 s of data).
MAX_ANALYSED = 8
#: Keys eliminated per GTSAM call (:func:`_eliminated`): a call runs some tens of milliseconds,
#: and Ctrl-C or SIGTERM, which Python handles between calls only, stops the fit promptly.
ELIMINATION_CHUNK = 200
#: A component is significant beyond this many sigmas.
SIGNIFICANCE = 5.0
#: The smallest correction of each candidate that is advice: the finest prior sigma a rig can
#: write for the part (``datasets.ranges``: ``sensor.<part>_sigma``'s lower bound).
SMALLEST = {part: RANGES[f"sensor.{part}_sigma"].low for part in PRIOR_SIGMA}
#: A suggested cause explains at least this fraction of the sensor's residual sum of squares.
MATERIAL_SHARE = 0.1
#: Half the window [s] over which the IMU's readings are averaged for the time-offset pattern.
AVERAGE_S = 0.05
#: The largest lag-1 autocorrelation the sigmas are inflated for.
MAX_RHO = 0.95
#: The states at the measurements are carried without their covariance (:func:`measurement_states`).
_NO_NOISE = imu.ImuNoise(0.0, 0.0, 0.0, 0.0, 0.0)


@dataclass(frozen=True)
class Cause:
    """One candidate calibration's fit: ``calibration`` (a key of :data:`PRIOR_SIGMA`), the
    correction ``value`` and its ``sigma`` (``(1,)`` for scale, as ``s - 1``, and time offset
    [s]; ``(3,)`` for rotation [rad] and lever arm [m], IMU frame), ``share`` and ``judged``
    (whether the sensor's residuals left enough degrees of freedom to judge it; module
    docstring)."""

    calibration: str
    value: np.ndarray
    sigma: np.ndarray
    share: float
    judged: bool = True

    @property
    def significant(self) -> np.ndarray:
        """Per component: :func:`significant`."""
        return significant(self.calibration, self.value, self.sigma)

    @property
    def suggested(self) -> bool:
        return self.judged and bool(self.significant.any()) and self.share >= MATERIAL_SHARE

    def text(self) -> str:
        """The fit in the rig's units, e.g. ``scale 0.9900 +- 0.0004``, ``time offset -0.100 s +-
        0.004 s``, ``rotation about y +3.00 deg +- 0.05 deg``, ``lever arm x +0.50 m +- 0.01 m``
        (rotation and lever arm: the significant axes of the IMU frame)."""
        if self.calibration == "scale":
            return f"scale {plus_minus(1.0 + self.value[0], self.sigma[0], '', signed=False)}"
        if self.calibration == "time_offset":
            return f"time offset {plus_minus(self.value[0], self.sigma[0], ' s')}"
        axes = np.flatnonzero(self.significant)
        if self.calibration == "rotation":
            degrees, sigmas = np.degrees(self.value), np.degrees(self.sigma)
            return "rotation " + ", ".join(f"about {'xyz'[a]} {plus_minus(degrees[a], sigmas[a], ' deg')}"
                                           for a in axes)
        return "lever arm " + ", ".join(f"{'xyz'[a]} {plus_minus(self.value[a], self.sigma[a], ' m')}" for a in axes)


def significant(calibration: str, value: np.ndarray, sigma: np.ndarray) -> np.ndarray:
    """Per component of a ``calibration`` candidate's correction ``value``: beyond
    :data:`SIGNIFICANCE` times its ``sigma`` and at least :data:`SMALLEST`."""
    size = np.abs(value)
    return (size > SIGNIFICANCE * sigma) & (size >= SMALLEST[calibration])


def hint(causes: list[Cause]) -> str | None:
    """The suggested ``causes`` in one phrase with the rig key that estimates them, e.g. ``scale
    0.9900 +- 0.0004 (explains 93 % of its residuals): add estimate = ["scale"]``; None without
    any."""
    chosen = [c for c in causes if c.suggested]
    if not chosen:
        return None
    keys = ", ".join(f'"{c.calibration}"' for c in chosen)
    return (", ".join(f"{c.text()} (explains {100 * min(c.share, 1.0):.0f} % of its residuals)" for c in chosen)
            + f": add estimate = [{keys}]")


def patterns(sensor: Sensor, states: imu.ImuState, imu_samples: ImuSamples, gravity, sums=None,
             value: Calibration | None = None) -> tuple:
    """``(e (N, d), {calibration: X (N, d, k)})``: the kernel's residuals of ``sensor``'s
    measurements at ``states`` (one per measurement) through its calibration ``value`` (its
    estimate where the sensor estimates one; None: the values the rig gives), and each
    candidate's columns ``X = -de/dc`` there: minus the calibrated kernel's own Jacobian
    (:func:`datasets.kinds.calibrated_rows`), whose error coordinates are the candidates'
    (module docstring), with the IMU's readings averaged over :data:`AVERAGE_S` for the time
    offset. The candidates are the parts the kind can estimate (:func:`factors.calibration.applicable`)
    less those the sensor estimates; one whose columns are zero for every measurement does not
    enter the residual and is left out. ``sums``: the samples' :func:`imu_sums`, when the caller
    made them once for many sensors."""
    kind, m = KINDS[sensor.kind], sensor.data
    estimated = () if sensor.calibrate is None else sensor.calibrate.parts
    wanted = [p for p in applicable(kind.model) if p not in estimated]
    averaged = _averaged_imu(imu_samples, m.t, AVERAGE_S, imu_sums(imu_samples) if sums is None else sums)
    c = Calibration.of(m.T_BS) if value is None else value
    e, _, Hc = calibrated_rows(kind, states, kind.pack(m), c, averaged, gravity)
    out = {}
    for part in wanted:
        columns = -Hc[:, :, PART_COLUMNS[part]]
        if np.any(columns != 0.0):
            out[part] = columns
    return e, out


def imu_sums(samples: ImuSamples) -> tuple[np.ndarray, np.ndarray]:
    """The cumulative sums of the specific force and of the angular rate, each ``(len + 1, 3)``
    from 0, of which :func:`patterns` takes the readings' means over windows."""
    return tuple(np.concatenate([np.zeros((1, 3)), np.cumsum(x, axis=0)]) for x in (samples.acc, samples.gyro))


def _averaged_imu(samples: ImuSamples, t: np.ndarray, half: float, sums) -> tuple[np.ndarray, np.ndarray]:
    """The mean specific force and angular rate of the samples in ``[t - half, t + half]`` (at
    least the sample held at ``t``), from their cumulative ``sums`` (:func:`imu_sums`)."""
    held = samples.held(t)
    lo = np.minimum(np.searchsorted(samples.t, t - half, side="left"), held)
    hi = np.maximum(np.searchsorted(samples.t, t + half, side="right"), held + 1)
    acc, gyro = ((total[hi] - total[lo]) / (hi - lo)[:, None] for total in sums)
    return acc, gyro


def measurement_states(problem: Problem, block: Block, sensor: Sensor, imu_samples: ImuSamples) -> imu.ImuState:
    """The states at ``sensor``'s measurement stamps, each carried from the keyframe its factor
    reads (``block``'s, in ``problem`` at its ``initial_states``) through the IMU's Euler steps
    (:func:`smoother.model.timeline.carry`): a measurement attached to the keyframe before it is
    evaluated there, as its factor evaluates it; one at a keyframe takes the keyframe's state. A
    calibration's pattern is the kernel's Jacobian at the state the measurement saw: at the keyframe
    before it, an attitude sensor's time offset would be fitted to residuals 0.1 s stale."""
    kf = block.keyframes[:, 0]
    states, _, _ = carry(problem.initial_states[kf], imu_samples, problem.times[kf], sensor.data.t, _NO_NOISE,
                         problem.gravity)
    return states


def _whitened(block: Block, X: dict, scale: np.ndarray) -> np.ndarray:
    """``A = W X (N, d, k)``, the candidates' columns side by side, whitened as ``block``'s rows are
    (``W`` its whitening: the measurement's covariance, grown by the process noise where the
    measurement is attached to a keyframe) and scaled by a robust kernel's row weights ``scale (N,
    d)`` (ones without one)."""
    A = np.einsum("nab,nbk->nak", block.whiten, np.concatenate(list(X.values()), axis=2))
    return A * scale[..., None]


def _row_scale(block: Block, states: imu.ImuState, calibration, jacobians: bool = True) -> tuple:
    """``(evaluated, scale)``: ``block`` evaluated at ``states`` (with its Jacobians where asked;
    reweighted by its robust kernel, as the batch's system has it) and the kernel's row scale
    ``sqrt(w)`` per residual entry (:attr:`smoother.model.blocks.Evaluated.scale`; 1 without a
    kernel)."""
    ev = evaluate_block(block, states, jacobians, calibration=calibration)
    return ev, np.ones_like(ev.e) if ev.scale is None else np.broadcast_to(ev.scale, ev.e.shape)


def _prior(X: dict) -> np.ndarray:
    """The weak prior's sigma per column of the candidates ``X``."""
    return np.concatenate([np.full(x.shape[2], PRIOR_SIGMA[name]) for name, x in X.items()])


def fit_in_problem(problem: Problem, sensors: list[Sensor], imu_samples: ImuSamples,
                   dof: dict[str, float] | None = None, calibration=None) -> dict[str, list[Cause]]:
    """Every candidate of each of ``sensors`` (their blocks among ``problem``'s, the batch problem
    at its ``initial_states``; relative kinds left out; each candidate's columns at the state its
    measurement saw, :func:`measurement_states`) fitted together as one Gauss-Newton
    step of the whole problem with each sensor's calibration added to its factors (module
    docstring): a misfit that one sensor's calibration explains is not put on another's. ``dof``:
    per sensor, the degrees of freedom its residuals leave at ``states`` (the batch smoother's
    verdict, :mod:`smoother.diagnosis.residual_consistency`); a sensor without it has its variance taken as
    at least the one its sigma states. ``calibration``: the values of the calibration variables
    the blocks read (:class:`factors.calibration.CalibrationSet`; keys ``n + j``, free in the step
    like the states), or None: a sensor estimating its own calibration has its candidates (the
    parts it does not estimate) at that estimate, its factors on its calibration variable too.
    By sensor name; a sensor left no candidate (it estimates every part its kind can) has none."""
    blocks, states = problem.blocks, problem.initial_states
    sums = imu_sums(imu_samples)
    by_name = {b.name: b for b in blocks}
    estimated = 0 if calibration is None else len(calibration)
    out: dict[str, list[Cause]] = {}
    found = {}  # name: (sensor, keyframes, candidates' columns)
    for sensor in (s for s in sensors if not KINDS[s.kind].relative):
        block = by_name[sensor.name]
        value = None if block.calibration is None else calibration.values[block.calibration]
        _, X = patterns(sensor, measurement_states(problem, block, sensor, imu_samples), imu_samples,
                        problem.gravity, sums, value)
        if X:
            found[sensor.name] = (sensor, block.keyframes[:, 0], X)
        else:
            out[sensor.name] = []
    graph, _ = linearize([b for b in blocks if b.name not in found], states, calibration)
    parts = {}  # name: (key, X, keyframes, evaluated block, whitened columns)
    for name, (sensor, kf, X) in found.items():
        block = by_name[name]
        ev, scale = _row_scale(block, states, calibration)
        A = _whitened(block, X, scale)
        key = len(states) + estimated + len(parts)
        unit = gtsam.noiseModel.Unit.Create(A.shape[1])
        for i in range(len(kf)):
            if block.calibration is None:  # de/dc = -X
                graph.add(gtsam.JacobianFactor(int(kf[i]), ev.A[0][i], key, -A[i], -ev.e[i], unit))
            else:
                graph.add(gtsam.JacobianFactor(int(kf[i]), ev.A[0][i], len(states) + block.calibration, ev.A[1][i],
                                               key, -A[i], -ev.e[i], unit))
        prior = _prior(X)
        graph.add(gtsam.JacobianFactor(key, np.diag(1.0 / prior), np.zeros(len(prior)),
                                       gtsam.noiseModel.Unit.Create(len(prior))))
        parts[name] = (key, X, kf, ev, A)
    if not parts:
        return out
    keys = [part[0] for part in parts.values()]
    colamd = gtsam.Ordering.ColamdGaussianFactorGraph(graph)
    last = set(keys)
    net = _eliminated(graph, [k for k in (colamd.at(j) for j in range(colamd.size())) if k not in last] + keys)
    step = net.optimize()
    # the calibrations, eliminated last, are the last conditionals: their joint square-root information
    tail = [net.at(j) for j in range(net.size() - len(keys), net.size())]
    R = _square_root(tail, {part[0]: part[4].shape[2] for part in parts.values()})
    R_inv = np.linalg.inv(R)
    cov = R_inv @ R_inv.T
    flat = step.vector()  # by key: the keyframes' steps, the calibration variables', then the candidates
    n = len(states) * imu.STATE_DIM
    dims = [] if calibration is None else calibration.dims
    dx_all, value = flat[:n].reshape(len(states), imu.STATE_DIM), flat[n + sum(dims):]
    dc_all = np.split(flat[n:n + sum(dims)], np.cumsum(dims)[:-1]) if dims else []
    information = R.T @ R
    gradient = information @ value
    at = 0
    for name, (key, X, kf, ev, A) in parts.items():
        mine = slice(at, at + A.shape[2])
        after = ev.e + np.einsum("nas,ns->na", ev.A[0], dx_all[kf]) - np.einsum("nak,k->na", A, value[mine])
        if by_name[name].calibration is not None:
            after = after + ev.A[1] @ dc_all[by_name[name].calibration]
        out[name] = candidate_causes(X, value[mine], cov[mine, mine], information[mine, mine], gradient[mine],
                                     after, (dof or {}).get(name))
        at = mine.stop
    return out


def _eliminated(graph: gtsam.GaussianFactorGraph, order: list[int]) -> gtsam.GaussianBayesNet:
    """``graph`` eliminated by QR in the order ``order``, as :data:`ELIMINATION_CHUNK` keys per
    GTSAM call (GTSAM holds the interpreter for a whole call: signals wait until it returns): the
    Bayes net of one ``eliminateSequential`` over the same order."""
    net, rest = gtsam.GaussianBayesNet(), graph
    for at in range(0, len(order), ELIMINATION_CHUNK):
        ordering = gtsam.Ordering()
        for key in order[at:at + ELIMINATION_CHUNK]:
            ordering.push_back(key)
        part, rest = rest.eliminatePartialSequential(ordering, gtsam.EliminateQR)
        for j in range(part.size()):
            net.push_back(part.at(j))
    return net


def candidates(dataset) -> list[Sensor]:
    """The sensors of ``dataset`` whose calibration the fit can suggest: those of an absolute kind
    (one estimating some of its calibration has the other parts as candidates, :func:`patterns`)."""
    return [s for s in sensors_of(dataset) if not KINDS[s.kind].relative]


def suspects(problem: Problem, sensors: list[Sensor], imu_samples: ImuSamples, calibration=None) -> list[Sensor]:
    """The :data:`MAX_ANALYSED` of ``sensors`` (all of them when as few) whose candidates explain
    most of their own residuals at ``problem``'s ``initial_states`` (their blocks among its;
    ``calibration`` the values of the calibration variables they read, as :func:`fit_in_problem`
    takes them), each
    sensor alone and the states held: the decrease ``g^T (A^T A + P^-1)^-1 g`` of its whitened
    cost (``A`` its whitened candidates' columns, ``g = A^T b``, ``P`` the weak prior). A screen,
    linear in the measurements: the fit proper (:func:`fit_in_problem`) then gives back what the
    states absorbed, and puts each misfit on one sensor."""
    if len(sensors) <= MAX_ANALYSED:
        return list(sensors)
    by_name, sums = {b.name: b for b in problem.blocks}, imu_sums(imu_samples)

    def explained(sensor) -> float:
        block = by_name[sensor.name]
        value = None if block.calibration is None else calibration.values[block.calibration]
        _, X = patterns(sensor, measurement_states(problem, block, sensor, imu_samples), imu_samples, problem.gravity,
                        sums, value)
        if not X:
            return 0.0
        ev, scale = _row_scale(block, problem.initial_states, calibration, jacobians=False)  # a screen: residuals
        A, b = _whitened(block, X, scale), ev.e
        A, b = A.reshape(-1, A.shape[2]), b.reshape(-1)
        g = A.T @ b
        return float(g @ np.linalg.solve(A.T @ A + np.diag(1.0 / _prior(X) ** 2), g))

    return sorted(sensors, key=explained, reverse=True)[:MAX_ANALYSED]


def causes_at(dataset, estimate: Trajectory, keyframe_rate: float | None = None, robust: dict | None = None,
              dof: dict[str, float] | None = None, calibration=None) -> dict[str, list[Cause]]:
    """:func:`fit_in_problem` of the :func:`candidates` of ``dataset`` (of more than
    :data:`MAX_ANALYSED`, the :func:`suspects`), in its batch problem
    (:func:`smoother.model.problem.build_problem` with ``keyframe_rate`` and ``robust``) started
    from ``estimate`` (any estimator's, over the same data) and from the calibrations it estimated
    (``calibration``; None: the values given): one Gauss-Newton step from there, the states, the
    estimated calibrations and the candidates together; ``dof`` as :func:`fit_in_problem` takes
    it."""
    problem = build_problem(dataset, keyframe_rate, robust, start=estimate)
    values = problem.calibration
    if values is not None and calibration is not None:
        values = calibration
    chosen = suspects(problem, candidates(dataset), dataset.imu, values)
    return fit_in_problem(problem, chosen, dataset.imu, dof, values)


def hints(dataset, estimates: dict, consistency: dict, keyframe_rate: float | None = None,
          robust: dict | None = None) -> dict[str, str]:
    """Per sensor of ``dataset`` with a suggested cause, its :func:`hint` from :func:`causes_at`
    the first estimate that ran in the order of :data:`smoother.estimators.ESTIMATORS` (``estimates`` as
    :func:`smoother.pipeline.run_estimators` returns them), saying which; ``{}`` when every verdict
    of ``consistency`` (the IMU's too) is in its band (nothing to explain) or without an estimate.
    The sensor suggested need not be the one out of its band: a wheel's pitch that the states
    absorb shows in the fixes'. Of a larger rig, the :data:`MAX_ANALYSED` :func:`suspects` are
    fitted: the cost is linear in the number of sensors and of keyframes."""
    if not any(out_of_band(c) for verdicts in consistency.values() for c in verdicts.values()):
        return {}
    ran = [name for name in ESTIMATORS if name in estimates and estimates[name].failed is None]
    if not ran:
        return {}
    # the batch's verdicts count each measurement's leverage at its estimate (fit_in_problem)
    dof = {name: c["dof"] for name, c in consistency.get("batch", {}).items()} if ran[0] == "batch" else None
    causes = causes_at(dataset, estimates[ran[0]].trajectory, keyframe_rate, robust, dof,
                       estimates[ran[0]].calibration)
    out = {}
    for name, fits in causes.items():
        text = hint(fits)
        if text is not None:
            out[name] = f"{text} (fitted from the {ran[0]}'s estimate)"
    return out


def _square_root(conditionals: list, sizes: dict[int, int]) -> np.ndarray:
    """The upper-triangular square-root information of the variables eliminated last, from their
    ``conditionals`` (in elimination order; each one's parents among the variables after it) and
    each variable's dimension by key (``sizes``, in the same order)."""
    offset = dict(zip(sizes, np.cumsum([0, *sizes.values()])))
    n = sum(sizes.values())
    out = np.zeros((n, n))
    for c in conditionals:
        frontal, *parents = [int(k) for k in c.keys()]
        rows = slice(offset[frontal], offset[frontal] + sizes[frontal])
        out[rows, rows] = c.R()
        column = 0
        S = c.S()
        for parent in parents:
            out[rows, offset[parent]:offset[parent] + sizes[parent]] = S[:, column:column + sizes[parent]]
            column += sizes[parent]
    return out


def _gains(information: np.ndarray, g: np.ndarray, X: dict, significant: list[bool]) -> np.ndarray:
    """Per candidate of ``X``, the decrease of the fit's quadratic cost ``c^T information c - 2 g^T
    c`` from ``c = 0`` that it adds to the ``significant`` candidates' but its own, every other
    component held at 0: with ``D(S) = g_S^T information_SS^-1 g_S``, ``D(S + j) - D(S - j)``."""
    bounds = np.cumsum([0, *(x.shape[2] for x in X.values())])
    columns = [np.arange(bounds[j], bounds[j + 1]) for j in range(len(X))]

    def decrease(members):
        if not members:
            return 0.0
        cols = np.concatenate([columns[m] for m in members])
        return float(g[cols] @ np.linalg.solve(information[np.ix_(cols, cols)], g[cols]))

    chosen = [j for j, yes in enumerate(significant) if yes]
    out = []
    for j in range(len(X)):
        others = [m for m in chosen if m != j]
        out.append(decrease(others + [j]) - decrease(others))
    return np.array(out)


def candidate_causes(X: dict, value: np.ndarray, cov: np.ndarray, information: np.ndarray,
                     gradient: np.ndarray, after: np.ndarray, dof: float | None) -> list[Cause]:
    """One :class:`Cause` per candidate of ``X`` from the fit's ``value`` and formal ``cov``, the
    quadratic model of the cost in the sensor's candidates (``information``, ``gradient``: every
    other calibration held at 0), the sensor's whitened residuals ``after`` the fit ``(N, d)`` and
    the degrees of freedom of its residuals before it (None: unknown), for the sigmas and the
    shares (module docstring)."""
    n, d = after.shape
    k = len(value)
    squares = float(np.sum(after * after))
    variance = squares / max(dof - k, 1.0) if dof is not None else max(squares / max(n * d - k, 1), 1.0)
    lag = float(np.sum(after[1:] * after[:-1]))
    rho = min(max(lag / squares, 0.0), MAX_RHO) if n > 1 and squares > 0 else 0.0
    sigma = np.sqrt(np.diag(cov) * variance * (1.0 + rho) / (1.0 - rho))
    bounds = np.cumsum([0, *(x.shape[2] for x in X.values())])
    parts = [slice(bounds[j], bounds[j + 1]) for j in range(len(X))]
    chosen = [bool(significant(name, value[S], sigma[S]).any()) for name, S in zip(X, parts)]
    gains = _gains(information, gradient, X, chosen)
    judged = (dof if dof is not None else n * d) - k >= MIN_DOF
    return [Cause(name, value[S].copy(), sigma[S], gain / (gain + squares) if gain + squares > 0 else 0.0, judged)
            for name, S, gain in zip(X, parts, gains)]
