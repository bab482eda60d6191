"""The noise of the IMU and of the aiding sensors estimated by the batch smoother: variance
components (Helmert/Foerstner), equivalent to restricted maximum likelihood (docs/design.md,
"Noise from the data").

Model. Every factor ``k`` has a residual ``e_k`` whose covariance is a known function of a few
positive scale factors ``theta_g`` (one per noise group ``g``), at ``theta = 1`` the covariance
the rig states:

* an IMU factor, ``Sigma_k = sum_c theta_c N_kc + N_k0``: the preintegrated covariance is linear
  in the four densities squared (accelerometer and gyro white noise, accelerometer and gyro bias
  random walk), so it splits into four parts ``N_kc`` -- each the same propagation with one
  density alone (:func:`factors.preintegration.noise_covariance`) -- and the rest ``N_k0`` (the
  velocity noise of the Euler step and the floor), which is not estimated;
* a sensor's measurement, ``R_k = D R_k0 D`` with ``D = diag(sqrt(theta_g(a)))`` over the
  residual's axes ``a``, each axis in one of its kind's groups
  (:attr:`datasets.kinds.base.Kind.axis_groups`: a GNSS's horizontal and vertical, ...).

With ``psi_g = log theta_g``, ``V_kg = dSigma_k / dpsi_g`` (``theta_c N_kc``;
``(S_g R_k + R_k S_g) / 2`` with ``S_g`` the group's axes). The restricted likelihood's score at
the batch optimum is

    s_g = 1/2 (sum_k w_k^T V_kg w_k  -  tr(P_R V_g)),          w_k = Sigma_k^-1 e_k,
    P_R = Sigma^-1 - Sigma^-1 J P J^T Sigma^-1

with ``J`` the system's Jacobian and ``P`` the estimate's covariance. In whitened coordinates
(``W_k`` the whitening of ``Sigma_k``, ``u_k = W_k e_k``, ``U_kg = W_k V_kg W_k^T``,
``H_k = W_k J_k P J_k^T W_k^T`` the factor's hat block, whose trace is its leverage):

    s_g = 1/2 (q_g - r_g),    q_g = sum_k u_k^T U_kg u_k,    r_g = sum_k tr((I - H_k) U_kg)

``r_g`` is the group's redundancy, and ``tr(P_R V_g)`` needs only the diagonal blocks of ``P_R``,
so the score is exact. At the estimate ``q_g = r_g``: each group's weighted squared residuals
equal its redundancy (Foerstner's condition).

The information ``F_gh = 1/2 tr(P_R V_g P_R V_h)`` needs ``P_R`` whole. Its diagonal blocks alone
(``1/2 sum_k tr((I - H_k) U_kg (I - H_k) U_kh)``) are close for a sensor's measurements, which
carry little leverage each, and far too small for the IMU's factors, chained through the
keyframes (a tenth of the curvature of a gyro's white noise on a simulated rig). The IMU
components' columns are exact instead, from the system the score came from: with ``A`` the
whitened Jacobian and ``B_g = A^T U_g A`` (the information ``A^T A`` falls by it for a unit rise
of ``psi_g``), ``tr(P_R V_g P_R V_h) = sum_k (tr(U_kg U_kh) - 2 tr(H_k U_kg U_kh)) + tr(X_g B_h)``
with ``X_g = P B_g P = dP / dpsi_g``, needed only on the pairs of variables of a factor -- a
conditional and its parent -- where one forward-mode sweep of the elimination and its selected
inversion gives it for every IMU component at once (:meth:`_NoiseModel._exact`,
:func:`smoother.model.covariances.covariance_tangent`; no other elimination; it matched the dense
matrix to 1e-5).
The iterations: far from the estimate (some ``q_g / r_g`` beyond ``exp(+-NEAR)``), Fisher scoring
on the variance factors with the local information's correlations and ``r / 2`` on its diagonal,
which for a group alone is Foerstner's ``theta <- theta q / r`` and never overshoots; near it,
damped Newton steps with that information, which follow
the ridges of correlated components (white noise against random walk) that Foerstner's step
crawls along; where groups leave the fit at the rig's value (below) and the rest are near, the
rest take the Newton step to where the linearised score vanishes with those back at it. Each
iteration re-weights, takes one Gauss-Newton step of the batch problem to the optimum of the new
weights and evaluates the score there. ``sd(psi_g) = sqrt((F^-1)_gg)``.

Groups the data cannot tell apart -- white noise against random walk over a short run, an
accelerometer's noise against sparse fixes' -- where their estimates' correlation exceeds
:data:`MERGE_CORRELATION`, share one factor and are reported merged (two of one sensor first); a
group whose residuals carry less than :data:`MIN_REDUNDANCY` degrees of freedom, or whose factor the
data fix no better than :data:`MAX_LOG_SD`, keeps the rig's value and is reported as not estimable
(also where the iterations stop before they settle: its factor there is no estimate).
A factor within :data:`SIGNIFICANCE` sd of the rig's value is reported and not applied; where every
factor is sure to end so -- where its Newton step leads, by more than that step -- the iterations
end there, each reported where its step leads. The groups of ``profiled`` sensors are applied
wherever they settle (a profile over another parameter, a correlation time, must be continuous
in it: a factor that snaps back to the rig's value when it nears it is not).

Outliers. In a group with a robust kernel a factor whose whitened squared residual exceeds the
:data:`TRUNCATION_PROBABILITY` quantile of chi-square with its dimension is left out of the sums
(a gross outlier says nothing about the inliers' noise; the kernel's own weights would still let
it inflate the factor), and the remaining redundancy is scaled by the truncated chi-square's
mean, so that the estimate stays consistent for inliers.
"""
from __future__ import annotations

import math
import time
import warnings
from dataclasses import dataclass, replace

import numpy as np

from datasets.kinds import KINDS, sensors_of
from datasets.types import Dataset
from factors import imu, preintegration
from factors.errors import InputError
from smoother.batch.solve import SmootherResult, solve_batch
from smoother.model.blocks import CHUNK, Block, Layout, block_residual, linearize, whitening
from smoother.model.covariances import covariance_tangent, hat_blocks, marginal_covariances
from smoother.model.problem import Problem
from smoother.model.timeline import imu_steps
from smoother.stats import chi2_quantile, dof_means_apart, lag_one_correlation

#: The IMU's four estimated densities: ``(ImuNoise field, name, rig key, unit)``.
IMU_COMPONENTS = (
    ("acc", "accelerometer white noise", "accel_noise_density", "m/s^2/sqrt(Hz)"),
    ("gyro", "gyro white noise", "gyro_noise_density", "rad/s/sqrt(Hz)"),
    ("acc_bias", "accelerometer bias random walk", "accel_random_walk", "m/s^3/sqrt(Hz)"),
    ("gyro_bias", "gyro bias random walk", "gyro_random_walk", "rad/s^2/sqrt(Hz)"),
)
#: The block of the IMU factors (:func:`smoother.model.problem.build_problem`).
IMU_BLOCK = "imu"
#: Two groups whose log-factors' estimates correlate beyond this share one factor.
MERGE_CORRELATION = 0.9
#: A group whose residuals carry fewer degrees of freedom than this keeps the rig's value ...
MIN_REDUNDANCY = 2.0
#: ... and so does one whose log-variance factor's standard deviation exceeds this (its sigma
#: known only within a factor of 2.1: a flat likelihood, often heading for a zero variance).
MAX_LOG_SD = 1.5
#: Robust groups: a factor beyond this quantile of chi-square (its dimension) is an outlier.
TRUNCATION_PROBABILITY = 0.999
#: A fitted factor within this many of its standard deviations of the rig's value is reported and
#: not applied: what the data do not tell from the rig stays the rig's, so a rig already right keeps
#: its noise and its trajectory.
SIGNIFICANCE = 3.0
#: A group's residuals in each half of the run (by time) carrying this much redundancy are compared
#: (:func:`_halves`) ...
MIN_HALF_REDUNDANCY = 10.0
#: ... and its noise is not steady when the halves' factors differ by more than this ratio and by more
#: than :data:`SIGNIFICANCE` of the difference's standard deviations.
UNSTEADY_RATIO = 1.5
#: Iterations end when no log-factor moves by more than this fraction of its standard deviation
#: (what is left of the way adds about 2 % to the estimate's spread, ``sqrt(1 + 0.2^2)``) ...
STEP_TOLERANCE = 0.2
#: ... or by more than this (half a per cent on a sigma): a factor the data fix to a fraction of a
#: per cent (a sensor of thousands of measurements) need not be iterated to a fifth of that.
STEP_FLOOR = 0.01
#: ... or after this many.
MAX_ITERATIONS = 25
#: No Fisher-scoring step changes a variance factor by more than ``exp`` of this.
MAX_LOG_STEP = 3.0
#: Near the optimum (every parameter's ``q / r`` within ``exp(+-NEAR)``) the steps are Newton's.
NEAR = 0.5
#: The share of a Newton step taken first (the information is exact only where it was
#: computed); it grows by half at each step that does not turn back, and halves at each that does.
FIRST_DAMPING = 1.0
#: The exact information is computed again once a parameter has moved this many of its standard
#: deviations from where it was (it costs a sweep of the system's conditionals; at two, one
#: component's factor came out beyond two of its sds of the truth on 5 of 20 simulated seeds).
RECOMPUTE_SD = 1.0
#: ... and by more than this: the information changes by about as much as the log-factors move
#: (relatively), so within this it holds to some ten per cent and the sds to five, however many
#: standard deviations that is for a group of thousands of measurements.
RECOMPUTE_FLOOR = 0.1


@dataclass(frozen=True)
class NoiseGroup:
    """One estimated noise group: ``sensor`` (the block's name; ``"imu"`` for the IMU), ``part``
    (an IMU density, :data:`IMU_COMPONENTS`, or a kind's axis group), ``axes`` (a sensor
    group's residual axes; None for the IMU) and ``unit`` (of its density or sigma)."""

    sensor: str
    part: str
    axes: tuple | None = None
    unit: str = ""

    @property
    def name(self) -> str:
        return f"{self.sensor}.{self.part}"


@dataclass(frozen=True)
class GroupFit:
    """What the data say of one group: ``factor`` on its density or sigma (the variance's square
    root: 2 means the noise is twice what the rig states) with its standard deviation
    ``factor_sd``, ``redundancy`` (the degrees of freedom its residuals carry), ``value`` (the
    density or sigma in the rig's units, the rig's times ``factor``; a sensor whose covariances
    vary gives its median), ``merged_with`` (groups sharing its factor), ``estimable`` (False:
    the rig's value kept, ``factor`` 1), ``applied`` (False: the factor, consistent with 1 within
    :data:`SIGNIFICANCE` sd, is reported and the rig's value kept) and ``note`` (why either)."""

    group: NoiseGroup
    factor: float
    factor_sd: float
    redundancy: float
    value: float | None
    unit: str
    merged_with: tuple[str, ...] = ()
    estimable: bool = True
    note: str = ""
    applied: bool = True
    #: The lag-one correlation of its whitened residuals in time order, and their degrees of
    #: freedom (measurements times axes): what tells a systematic error from noise
    #: (:mod:`smoother.diagnosis.noise_honesty`).
    correlation: float = 0.0
    dof: int = 0
    #: The factors on the rig's value that the residuals of the run's first and second half say
    #: (None: too little redundancy in one of them), and whether one noise fits both (:func:`_halves`).
    halves: tuple[float, float] | None = None
    steady: bool = True

    def record(self) -> dict:
        """``metrics.json``'s record of the group."""
        return {"sensor": self.group.sensor, "factor": self.factor, "factor_sd": self.factor_sd,
                "redundancy": self.redundancy,
                **({} if self.group.axes is None else {"axes": list(self.group.axes)}),
                "value": self.value, "unit": self.unit, "merged_with": list(self.merged_with),
                "estimable": self.estimable, "applied": self.applied, "residual_correlation": self.correlation,
                "halves": None if self.halves is None else list(self.halves), "steady": self.steady,
                **({"note": self.note} if self.note else {})}


@dataclass
class NoiseFit:
    """The fitted noise: each group's :class:`GroupFit`, the iterations, whether they converged,
    and the factors to apply (:meth:`applied`); ``fits``: how many fits its groups come from (a
    run fits again with the groups found model errors held, :mod:`smoother.pipeline`)."""

    groups: list[GroupFit]
    iterations: int
    converged: bool
    runtime_s: float = 0.0
    fits: int = 1

    def factor_of(self, sensor: str, part: str) -> float:
        """The factor applied to a group (1 where none is)."""
        for g in self.groups:
            if g.group.sensor == sensor and g.group.part == part and g.applied and g.estimable:
                return g.factor
        return 1.0

    def noise(self, noise: imu.ImuNoise) -> imu.ImuNoise:
        """The IMU's densities with the fitted factors."""
        return replace(noise, **{field: getattr(noise, field) * self.factor_of(IMU_BLOCK, field)
                                 for field, *_ in IMU_COMPONENTS})

    def axis_factors(self, sensor: str, dim: int) -> np.ndarray:
        """The factor on each of the sensor's residual axes (ones where none was fitted)."""
        out = np.ones(dim)
        for g in self.groups:
            if g.group.sensor == sensor and g.group.axes is not None:
                out[list(g.group.axes)] = self.factor_of(sensor, g.group.part)
        return out

    def applied(self, dataset: Dataset) -> Dataset:
        """``dataset`` with the fitted noise: the IMU's densities and every fitted sensor's
        covariances (used and held out) scaled, ``D R D`` with ``D`` the axes' factors."""
        sensors = []
        for sensor in dataset.sensors:
            f = self.axis_factors(sensor.name, KINDS[sensor.kind].dim)
            if np.all(f == 1.0):
                sensors.append(sensor)
                continue
            scale = f[:, None] * f[None, :]
            data = replace(sensor.data, cov=sensor.data.cov * scale)
            heldout = None if sensor.heldout is None else replace(sensor.heldout, cov=sensor.heldout.cov * scale)
            sensors.append(replace(sensor, data=data, heldout=heldout))
        return replace(dataset, noise=self.noise(dataset.noise), sensors=tuple(sensors))

    def not_grown(self) -> "NoiseFit":
        """The fit with every factor above 1 back at 1 (the rig's value): the noise under which a
        misfit that the grown groups took up shows in the residuals again (a gyro's white noise grown
        to follow an AHRS's delay hides the delay from the AHRS's residuals)."""
        return replace(self, groups=[replace(g, factor=min(g.factor, 1.0)) for g in self.groups])

    def record(self) -> dict:
        """``metrics.json``'s ``noise`` record: ``{group name: GroupFit.record()}``, and ``_fit``."""
        return {**{g.group.name: g.record() for g in self.groups},
                "_fit": {"iterations": self.iterations, "converged": self.converged, "runtime_s": self.runtime_s,
                         "fits": self.fits}}


def noise_groups(dataset: Dataset, which) -> list[NoiseGroup]:
    """The groups of the sensors named in ``which`` (``"imu"`` for the IMU's four densities; a
    sensor's name for its kind's axis groups); an InputError naming an unknown one."""
    names = {s.name: s for s in sensors_of(dataset)}
    groups = []
    for name in which:
        if name == IMU_BLOCK:
            groups += [NoiseGroup(IMU_BLOCK, field, None, unit) for field, _, _, unit in IMU_COMPONENTS]
        elif name in names:
            axis_groups = KINDS[names[name].kind].axis_groups
            _check_correlated_axes(names[name], axis_groups)
            groups += [NoiseGroup(name, part, tuple(axes), unit) for part, axes, unit in axis_groups]
        else:
            raise InputError(f"noise estimation: no sensor {name!r}; expected imu or one of {', '.join(names)}")
    return groups


def _check_correlated_axes(sensor, axis_groups) -> None:
    """An InputError where ``sensor`` has a correlation time, more than one axis group and a
    covariance that is not diagonal: its factors (:mod:`smoother.model.correlated`) whiten each
    measurement whole, and a factor per axis group on those whitened rows is not the factor on its
    axes' sigmas (``D R D``) that the fit reports, applies and writes."""
    if sensor.correlation_time is None or len(axis_groups) < 2 or sensor.data is None:
        return
    cov = sensor.data.cov
    off = cov - np.einsum("...ii->...i", cov)[..., None] * np.eye(cov.shape[-1])
    if np.any(np.abs(off) > 1e-12 * np.abs(cov).max()):
        parts = ", ".join(part for part, _, _ in axis_groups)
        raise InputError(f"noise estimation: sensor {sensor.name!r} has a correlation_time and covariances that are "
                         f"not diagonal: its {parts} cannot be fitted apart under that model; give it a diagonal "
                         "sigma, or fit its noise without the correlation_time")


def estimate_noise(dataset: Dataset, problem: Problem, result: SmootherResult, which, optimizer: str = "lm",
                   max_iterations: int = 100, fixed=frozenset(),
                   profiled=frozenset()) -> tuple[NoiseFit, SmootherResult, Problem]:
    """The noise groups of ``which`` (:func:`noise_groups`) fitted by restricted maximum likelihood
    (module docstring), starting from the batch estimate ``result`` of ``problem`` (built from
    ``dataset``, with covariances). Returns the fit, the batch estimate with the fitted noise
    (with covariances) and the problem with it: ``result`` (without a kept elimination) and
    ``problem`` where no factor is applied. Every other group keeps the rig's noise, and so do the
    groups named in ``fixed`` (:attr:`NoiseGroup.name`; left out of the fit and of its groups: a
    model error's, :mod:`smoother.diagnosis.noise_honesty`). The groups of the sensors named in
    ``profiled`` are applied however near the rig's value they settle (module docstring). Where
    ``result`` kept its covariances' elimination (:func:`smoother.batch.solve.solve_batch`'s
    ``square_root``), the first evaluation reads it instead of making it again."""
    start = time.perf_counter()
    if result.joint is None or result.trajectory.cov is None:
        raise InputError("noise estimation needs the batch estimate's covariances (covariances=True)")
    every = noise_groups(dataset, which)
    if unknown := set(fixed) - {g.name for g in every}:
        raise InputError(f"noise estimation: no group {', '.join(sorted(unknown))} to hold; expected among "
                         f"{', '.join(g.name for g in every)}")
    groups = [g for g in every if g.name not in fixed]
    if not groups:
        raise InputError(f"noise estimation: every group of {', '.join(which)} is held at the rig's value")
    model = _NoiseModel(dataset, problem, groups)
    psi = np.zeros(len(groups))
    ties = [[g] for g in range(len(groups))]  # the parameters: groups sharing one factor (the rest: the rig's)
    notes: dict[int, str] = {}
    held: dict[int, tuple] = {}  # groups kept at the rig's value: (factor, sd, merged with) as estimated
    left: dict[int, float] = {}  # groups out of the fit: how far their log-factor may be from where the
    # information was computed for it to hold (_unmoved, with the sd they left with)
    converged, iterations = False, 0
    states, calibration = result.trajectory.states, result.calibration

    def evaluate(psi, states, calibration, batch=None):
        """One Gauss-Newton step to the optimum of the weights of ``psi`` (the weights change
        little from one evaluation to the next), solved by the elimination the covariances come
        from, and the statistics there. ``batch``: the batch smoother's own covariances and their
        elimination at ``states`` (``psi = 0``: the problem's weights), read instead of made again."""
        blocks = model.blocks(psi)
        layout = Layout.of(states, calibration, blocks)
        if batch is None:
            graph, _ = linearize(blocks, states, calibration)
            cov, joint, root = marginal_covariances(graph, len(states), None, True, layout, square_root=True)
        else:
            cov, joint, root = batch
        delta = root.solution
        moved, moved_calibration = layout.apply(states, calibration, delta)
        # the residuals of the linear system at its solution: every statistic from that one system
        n = len(states)
        bounds = np.cumsum([n * imu.STATE_DIM, *layout.extra])
        step = (delta[:n * imu.STATE_DIM].reshape(n, imu.STATE_DIM),
                np.split(delta[bounds[0]:], bounds[1:-1] - bounds[0]))
        return moved, moved_calibration, model.statistics(blocks, states, calibration, cov, joint, psi, step=step,
                                                          root=root)

    information = None  # the groups' information once near the estimate (the IMU's columns exact), else None
    last = None  # (psi, score, step) of the last Newton step
    at = None  # the log-factors where the information was computed
    damping = FIRST_DAMPING
    for iterations in range(1, MAX_ITERATIONS + 1):
        before = (states, calibration)
        batch = None
        if iterations == 1 and result.square_root is not None:
            batch = (result.trajectory.cov, result.joint, result.square_root)
        at_evaluation = psi.copy()
        states, calibration, (quadratic, expected, approximate, redundancy, exact, halves) = evaluate(psi, *before,
                                                                                                      batch)
        q, r = _per_parameter(quadratic, ties), _per_parameter(expected, ties)
        close = np.abs(np.log(np.maximum(q, 1e-300) / np.maximum(r, 1e-300))) <= NEAR
        near = bool(np.all(close))
        moved = None if information is None else np.abs(psi_of(psi, ties) - psi_of(at, ties))
        if near and (moved is None or not np.all(_unmoved(moved, np.sqrt(np.diag(_pseudo_inverse(
                _parameter_information(information, ties)))))) or any(
                abs(psi[g] - at[g]) > allowed for g, allowed in left.items())):
            # the groups' exact information where it is first needed, and again once the parameters
            # have moved from where it was computed by more than _unmoved allows -- or a group that
            # left the fit, back at the rig's value, did (a merge only changes which of its rows and
            # columns the parameters take)
            information, at = exact([g for tie in ties for g in tie]), psi.copy()
        F = _parameter_information(information if near else approximate, ties)
        cov_psi = _pseudo_inverse(F)
        sd = np.sqrt(np.maximum(np.diag(cov_psi), 0.0))
        s = 0.5 * (q - r)
        # Newton's step over the parameters with redundancy; one without takes Foerstner's
        share = _per_parameter(redundancy, ties)
        active = share >= MIN_REDUNDANCY
        newton = np.clip(np.log(np.maximum(q, 1e-300) / np.maximum(r, 1e-300)), -MAX_LOG_STEP, MAX_LOG_STEP)
        newton[active] = np.clip(_pseudo_inverse(F[np.ix_(active, active)]) @ s[active], -MAX_LOG_STEP, MAX_LOG_STEP)
        turned = False
        if near:
            # a step turned back by more than half the last, by more than STEP_TOLERANCE sd
            turned = last is not None and np.any((newton * last[2] < 0.0) & (np.abs(newton) > 0.5 * np.abs(last[2]))
                                                 & ~_small(newton, sd))
            if turned:
                damping *= 0.5  # the step turned back: the information is off along it
            else:
                damping = min(1.0, 1.5 * damping)
            step = damping * newton
            last = (psi_of(psi, ties), s, step)
        else:
            step = far_step(F, q, r)
        settled = near and np.all(_small(newton, sd))
        values = psi_of(psi, ties)  # the parameters before this iteration's step
        # near the estimate, with the exact information: two parameters the data do not tell apart
        # share one factor from here on (before anything else: such a pair leaves every parameter
        # tied to it with a standard deviation that says nothing). A parameter with too little
        # redundancy keeps the rig's value once it falls (heading for a zero variance, it would move
        # on for ever; one that rises may be a density the rig states far too small) or the rest
        # settle, and so does one the data fix no better than MAX_LOG_SD near the estimate (falling,
        # its information only shrinks on the way to where it would settle); then what the data do
        # not tell from the rig's value stays the rig's. Whether a parameter falls is read from the
        # first iteration on only near the estimate (the exact information's step): far from it, a
        # group's first step may follow the other groups' misfit
        merged = _merge_candidate(F, ties, groups) if near else None
        kept = []
        falls = (step <= 0.0) & (iterations > 1 or near)
        weak = [] if merged is not None else [
            j for j in range(len(ties))
            if (share[j] < MIN_REDUNDANCY and (settled or falls[j]))
            or (near and sd[j] > MAX_LOG_SD and (settled or falls[j]))]
        rest_stepped = bool(weak) and merged is None and information is not None and np.all(np.delete(close, weak))
        # the weak's way back to the rig's value: within _unmoved the information still holds
        back = _unmoved(np.abs(psi_of(psi, ties)[weak]), sd[weak])
        if merged is None:
            if rest_stepped:
                # the rest, near the estimate without the weak: their Newton step to where the score
                # vanishes with the weak back at the rig's value
                step[:] = _step_without(_parameter_information(information, ties), s, psi_of(psi, ties), weak, active,
                                        step)
            psi = _with_step(psi, ties, step)
        if merged is not None:
            a, b = merged
            ties[a] = ties[a] + ties.pop(b)
            psi[ties[a]] = np.mean(psi[ties[a]])
        elif weak:
            rest = (np.delete(step, weak), np.delete(share, weak))
            for j in sorted(weak, reverse=True):
                for g in ties[j]:
                    psi[g] = 0.0
                    notes[g] = _not_estimable(sd[j], share[j])
                    left[g] = max(RECOMPUTE_SD * sd[j], RECOMPUTE_FLOOR)
                del ties[j]
            # the rest settled already where their step says what the next iteration would find
            settled = False
            if rest_stepped and np.all(back) and ties:
                rest_sd = _settled_rest(_parameter_information(information, ties), *rest,
                                        np.abs(psi_of(psi, ties) - psi_of(at, ties)), ties, groups)
                settled = rest_sd is not None
                sd = sd if rest_sd is None else rest_sd
        if merged is None and settled and ties:
            # what the data do not tell from the rig's value stays the rig's; the rest fitted again --
            # or settled already, where their Newton step with those back at it says so (_held_rest)
            if kept := [j for j in range(len(ties)) if abs(psi[ties[j][0]]) < SIGNIFICANCE * sd[j]
                        and not all(groups[g].sensor in profiled for g in ties[j])]:
                ahead = _held_rest(_parameter_information(information, ties), sd, s, values, kept, active, newton,
                                   share, psi_of(at, ties), ties, groups)
                _hold(kept, psi_of(psi, ties), sd, ties, psi, held, left, groups)
                if ahead is not None:
                    for tie, value in zip(ties, ahead):
                        psi[tie] = value
                    converged = True
                    break
            else:
                converged = True
                break
        elif merged is None and not weak and near and not turned and ties:
            # ... and before they settle, where every parameter is sure to stay within SIGNIFICANCE sd
            # of it -- where its Newton step leads, by more than that step (what is left of its way,
            # the steps shrinking; a step that turned back says the information is off along it),
            # with the information holding there (_unmoved) and the data fixing it (redundancy,
            # MAX_LOG_SD) -- all stay the rig's: the end the iterations would reach
            projected = values + newton
            if all(active[j] and sd[j] <= MAX_LOG_SD and abs(projected[j]) + abs(newton[j]) < SIGNIFICANCE * sd[j]
                   and not all(groups[g].sensor in profiled for g in ties[j])
                   for j in range(len(ties))) and np.all(_unmoved(np.abs(projected - psi_of(at, ties)), sd)):
                _hold(list(range(len(ties))), projected, sd, ties, psi, held, left, groups)
        if merged is not None or weak or kept:
            last, damping = None, FIRST_DAMPING
        if not ties:
            converged = True
            break
    else:
        warnings.warn(f"noise estimation: not converged after {MAX_ITERATIONS} iterations; the last estimate is "
                      "used", stacklevel=2)
        _leave_unsettled(ties, psi, redundancy, information if information is not None else approximate, notes)
    fitted = problem
    if psi.any():  # some factor applied: the estimate with it (else the rig's noise and the given estimate)
        fitted = replace(problem, blocks=model.blocks(psi), initial_states=states, calibration=calibration)
        result = solve_batch(fitted, optimizer, max_iterations)
    if ties:
        cov_psi = _pseudo_inverse(_parameter_information(information if information is not None else approximate,
                                                         ties))
    summary = model.residual_summary(result.trajectory.states, result.calibration, psi)
    fits = []
    for g, group in enumerate(groups):
        j = next((j for j, tie in enumerate(ties) if g in tie), None)
        factor = math.exp(0.5 * psi[g])
        extra = {"correlation": summary[g][0], "dof": summary[g][1], **_halves(halves[:, :, g], at_evaluation[g])}
        if g in held:
            factor, sd_factor, others = held[g]
            fits.append(GroupFit(group, factor, sd_factor, float(redundancy[g]), model.value(group, 1.0), group.unit,
                                 others, applied=False, note=f"the rig's value kept: within {SIGNIFICANCE:g} sd of it",
                                 **extra))
            continue
        if j is None:
            fits.append(GroupFit(group, 1.0, float("nan"), float(redundancy[g]), model.value(group, 1.0),
                                 group.unit, (), False, notes.get(g, "not estimated"), **extra))
            continue
        sd_psi = math.sqrt(max(cov_psi[j, j], 0.0))
        others = tuple(groups[t].name for t in ties[j] if t != g)
        fits.append(GroupFit(group, factor, 0.5 * factor * sd_psi, float(redundancy[g]), model.value(group, factor),
                             group.unit, others, **extra))
    fit = NoiseFit(fits, iterations, converged, time.perf_counter() - start)
    return fit, replace(result, square_root=None), fitted  # the elimination's memory let go


def _leave_unsettled(ties: list[list[int]], psi: np.ndarray, redundancy: np.ndarray, information: np.ndarray,
                     notes: dict) -> None:
    """A fit stopped before it settled: each parameter whose residuals carry less than
    :data:`MIN_REDUNDANCY` at the last evaluation (``redundancy`` per group) is no estimate -- the
    iterations would have kept it at the rig's value once it fell or the rest settled, and a factor
    heading for a vanishing variance has no end -- so its groups go back to the rig's value with the
    not-estimable note, in place (``ties``, ``psi``, ``notes``; their sd from ``information`` over the
    parameters as they stand)."""
    share = _per_parameter(redundancy, ties)
    sd = np.sqrt(np.maximum(np.diag(_pseudo_inverse(_parameter_information(information, ties))), 0.0))
    for j in sorted(np.flatnonzero(share < MIN_REDUNDANCY), reverse=True):
        for g in ties[j]:
            psi[g] = 0.0
            notes[g] = _not_estimable(sd[j], share[j])
        del ties[j]


def _hold(kept: list[int], values: np.ndarray, sd: np.ndarray, ties: list[list[int]], psi: np.ndarray, held: dict,
          left: dict, groups: list[NoiseGroup]) -> None:
    """The parameters ``kept`` (indices into ``ties``) back at the rig's value and out of the fit, in
    place: each of their groups' ``held`` entry ``(factor, sd, merged with)`` from the parameter's
    log-factor ``values[j]`` and its ``sd[j]``, its ``psi`` 0, its ``left`` entry (how far from where
    the information was computed its log-factor may be for it to hold, :func:`_unmoved`), its tie
    deleted."""
    for j in sorted(kept, reverse=True):
        factor = math.exp(0.5 * values[j])
        for g in ties[j]:
            held[g] = (factor, 0.5 * factor * sd[j], tuple(groups[t].name for t in ties[j] if t != g))
            psi[g] = 0.0
            left[g] = max(RECOMPUTE_SD * sd[j], RECOMPUTE_FLOOR)
        del ties[j]


def _halves(halves: np.ndarray, psi: float) -> dict:
    """``{"halves": (f_1, f_2), "steady": ...}`` of a group from its weighted squared residuals and
    their expectations in the run's two halves, ``halves = ((q_1, q_2), (r_1, r_2))`` at the
    log-factor ``psi``: each half's factor on the rig's value, ``f_h = exp(psi / 2) sqrt(q_h /
    r_h)`` (the whole run's estimate makes ``q = r``). The noise is not steady when the two differ by
    more than :data:`UNSTEADY_RATIO` and by more than :data:`SIGNIFICANCE` standard deviations of
    ``log(q_1 / r_1) - log(q_2 / r_2)``, ``sqrt(2 / r_1 + 2 / r_2)`` (each ``q_h`` about ``r_h``
    times a chi-square over ``r_h`` degrees of freedom). ``{}`` where a half carries less than
    :data:`MIN_HALF_REDUNDANCY`."""
    (q1, q2), (r1, r2) = halves
    if min(r1, r2) < MIN_HALF_REDUNDANCY or min(q1, q2) <= 0.0:
        return {}
    f1, f2 = (math.exp(0.5 * psi) * math.sqrt(q / r) for q, r in ((q1, r1), (q2, r2)))
    # the factors' ratio beyond UNSTEADY_RATIO: their variances' beyond its square
    apart = dof_means_apart(q1 / r1, r1, q2 / r2, r2, UNSTEADY_RATIO**2, SIGNIFICANCE)
    return {"halves": (f1, f2), "steady": apart == 0.0}


def _tie_matrix(ties: list[list[int]], n: int) -> np.ndarray:
    """``(groups, parameters)``: 1 where a group takes a parameter."""
    T = np.zeros((n, len(ties)))
    for j, tie in enumerate(ties):
        T[tie, j] = 1.0
    return T


def _pseudo_inverse(F: np.ndarray) -> np.ndarray:
    """The (pseudo-)inverse of a symmetric information matrix."""
    return np.linalg.pinv(0.5 * (F + F.T), rcond=1e-12)


def _with_step(psi: np.ndarray, ties: list[list[int]], step: np.ndarray) -> np.ndarray:
    """``psi`` with each parameter's ``step`` added to the groups of its tie."""
    out = psi.copy()
    for j, tie in enumerate(ties):
        out[tie] += step[j]
    return out


def _step_without(F: np.ndarray, s: np.ndarray, values: np.ndarray, weak: list[int], active: np.ndarray,
                  step: np.ndarray) -> np.ndarray:
    """``step`` with the Newton step of the ``active`` parameters not in ``weak`` (those with
    redundancy) taken to where the linearised score ``s - F d`` vanishes once the ``weak`` ones are
    back at the rig's value: ``d``, the parameters' change, is ``-values`` on ``weak`` (``values``
    their log-factors) and nothing on the rest without redundancy."""
    rest = active.copy()
    rest[weak] = False
    out = step.copy()
    if rest.any():
        d = np.zeros(len(s))
        d[weak] = -values[weak]
        score = s[rest] - F[np.ix_(rest, ~rest)] @ d[~rest]
        out[rest] = np.clip(FIRST_DAMPING * _pseudo_inverse(F[np.ix_(rest, rest)]) @ score, -MAX_LOG_STEP,
                            MAX_LOG_STEP)
    return out


def _settled_rest(F: np.ndarray, step: np.ndarray, share: np.ndarray, moved: np.ndarray, ties: list,
                  groups: list[NoiseGroup]) -> np.ndarray | None:
    """The standard deviations of the parameters left after some were dropped, if they settled with
    ``step`` -- the Newton step of their linearised score, with their information ``F``, from the
    evaluation they were dropped at (:func:`_step_without`; the caller takes it only where the
    dropped ones were near enough the rig's value for ``F`` to hold there, :func:`_unmoved`) -- as
    the next iteration would find them settled: each step small (:func:`_small`), none ``moved``
    (from where ``F`` was computed) beyond what :func:`_unmoved` allows, and none to be merged or
    dropped there (two correlating beyond :data:`MERGE_CORRELATION`, a ``share`` of redundancy
    below :data:`MIN_REDUNDANCY`, an sd beyond :data:`MAX_LOG_SD`); None otherwise."""
    sd = np.sqrt(np.maximum(np.diag(_pseudo_inverse(F)), 0.0))
    settled = np.all(_small(step, sd)) and np.all(_unmoved(moved, sd))
    kept = np.all(share >= MIN_REDUNDANCY) and np.all(sd <= MAX_LOG_SD) and _merge_candidate(F, ties, groups) is None
    return sd if settled and kept else None


def _held_rest(F: np.ndarray, sd: np.ndarray, s: np.ndarray, values: np.ndarray, kept: list[int],
               active: np.ndarray, newton: np.ndarray, share: np.ndarray, at: np.ndarray, ties: list,
               groups: list[NoiseGroup]):
    """The log-factors of the parameters left once ``kept`` go back to the rig's value, if the next
    iteration would find them settled and none of them kept, else None: their Newton step from the
    evaluation at ``values`` (score ``s``, information ``F`` computed at ``at``, the parameters'
    standard deviations ``sd`` from it; :func:`_step_without`) with ``kept`` at 0 -- within what
    :func:`_unmoved` allows of ``at`` -- small, and each then beyond :data:`SIGNIFICANCE` of its sd
    (:func:`_settled_rest`)."""
    rest = [j for j in range(len(ties)) if j not in kept]
    if not rest or not np.all(_unmoved(np.abs(at[kept]), sd[kept])):
        return None
    step = _step_without(F, s, values, kept, active, newton)[rest]
    ahead = values[rest] + step
    sd = _settled_rest(F[np.ix_(rest, rest)], step, share[rest], np.abs(ahead - at[rest]), [ties[j] for j in rest],
                       groups)
    if sd is None or np.any(np.abs(ahead) < SIGNIFICANCE * sd):
        return None
    return ahead


def _small(step: np.ndarray, sd: np.ndarray) -> np.ndarray:
    """Per parameter, whether a step of its log-factor is small enough to end the iterations:
    within :data:`STEP_TOLERANCE` of its ``sd`` or :data:`STEP_FLOOR`."""
    return np.abs(step) <= np.maximum(STEP_TOLERANCE * sd, STEP_FLOOR)


def _unmoved(moved: np.ndarray, sd: np.ndarray) -> np.ndarray:
    """Per parameter, whether the information computed ``moved`` away (in its log-factor) still
    holds: within :data:`RECOMPUTE_SD` of its ``sd`` or :data:`RECOMPUTE_FLOOR`."""
    return moved <= np.maximum(RECOMPUTE_SD * sd, RECOMPUTE_FLOOR)


def _not_estimable(sd: float, redundancy: float) -> str:
    """Why a group keeps the rig's value, from its log-variance factor's standard deviation."""
    how = (f"the data fix its sigma only within a factor of {math.exp(0.5 * sd):.2g}" if sd < 10.0
           else "the data do not determine it")
    return f"not estimable: {how} (redundancy {redundancy:.2g})"


def psi_of(psi: np.ndarray, ties: list[list[int]]) -> np.ndarray:
    """The parameters' values: each tie's log-factor."""
    return np.array([psi[tie[0]] for tie in ties])


def _per_parameter(values: np.ndarray, ties: list[list[int]]) -> np.ndarray:
    """The groups' ``values`` summed over each tie."""
    return np.array([sum(values[g] for g in tie) for tie in ties])


def far_step(F: np.ndarray, q: np.ndarray, r: np.ndarray) -> np.ndarray:
    """The log-factors' step far from the optimum (some ``q / r`` beyond ``exp(+-NEAR)``): Fisher
    scoring on the variance factors themselves, ``theta_new / theta = 1 + F~^-1 (q - r) / 2``, with
    the approximate information's correlations and the diagonal ``r / 2``. A group alone then
    takes Foerstner's step ``theta <- theta q / r`` exactly, which does not overshoot (it is how far
    off a single dominant variance is), and correlated groups move together. A ratio below 0.05
    is Foerstner's instead (the linear step leaves the positive factors there); every step within
    ``exp(+-MAX_LOG_STEP)``."""
    q, r = np.maximum(q, 1e-300), np.maximum(r, 1e-300)
    d = np.sqrt(np.maximum(np.diag(F), 1e-300))
    scaled = np.sqrt(0.5 * r)
    ratio = 1.0 + _pseudo_inverse((F / np.outer(d, d)) * np.outer(scaled, scaled)) @ (0.5 * (q - r))
    fallback = ~(ratio > 0.05)
    ratio[fallback] = q[fallback] / r[fallback]
    return np.clip(np.log(ratio), -MAX_LOG_STEP, MAX_LOG_STEP)


def _positive_definite(F: np.ndarray) -> np.ndarray:
    """``F`` symmetrised with its eigenvalues kept above 1e-6 of the largest: exact columns in the
    approximate rest can lose definiteness along directions the data hardly fix, and an
    indefinite information gives negative variances and meaningless correlations."""
    values, vectors = np.linalg.eigh(0.5 * (F + F.T))
    floor = 1e-6 * max(float(values.max()), 1e-300)
    return (vectors * np.maximum(values, floor)) @ vectors.T


def _parameter_information(information: np.ndarray, ties: list[list[int]]) -> np.ndarray:
    """The information of the parameters, each shared by the groups of its tie."""
    T = _tie_matrix(ties, len(information))
    return T.T @ information @ T


def _merge_candidate(F: np.ndarray, ties: list, groups: list[NoiseGroup]) -> tuple[int, int] | None:
    """The two parameters whose estimates correlate most beyond :data:`MERGE_CORRELATION`, two of
    one sensor (the IMU's components, a sensor's axis groups) first; None if none do."""
    if len(ties) < 2:
        return None
    C = _pseudo_inverse(F)
    d = np.sqrt(np.maximum(np.diag(C), 1e-300))
    rho = np.abs(C / np.outer(d, d))
    np.fill_diagonal(rho, 0.0)
    sensor = np.array([groups[tie[0]].sensor for tie in ties])
    same = sensor[:, None] == sensor[None, :]
    for candidates in (np.where(same, rho, 0.0), rho):
        a, b = np.unravel_index(np.argmax(candidates), candidates.shape)
        if candidates[a, b] > MERGE_CORRELATION:
            return (int(min(a, b)), int(max(a, b)))
    return None


class _NoiseModel:
    """The factors' covariances as functions of the log-factors ``psi``, and the restricted
    likelihood's score and information at a batch estimate (module docstring)."""

    def __init__(self, dataset: Dataset, problem: Problem, groups: list[NoiseGroup]):
        self.dataset, self.problem, self.groups = dataset, problem, groups
        self.block_index = {b.name: i for i, b in enumerate(problem.blocks)}
        self.kinds = {s.name: s.kind for s in sensors_of(dataset)}
        for g in groups:
            if g.sensor not in self.block_index:
                raise InputError(f"noise estimation: sensor {g.sensor!r} has no factors in the problem")
        # each sensor block's whitening as the rig states it, W_0, and its inverse L_0 (R_0 = L_0 L_0^T)
        self.rig = {}
        for g in groups:
            if g.axes is not None and g.sensor not in self.rig:
                W = problem.blocks[self.block_index[g.sensor]].whiten
                self.rig[g.sensor] = (W, np.linalg.inv(W))
        self.sensor_derivatives = {i: self._rig_derivative(g) for i, g in enumerate(groups) if g.axes is not None}
        self.imu_parts = None  # (N_kc per component (C, J, 15, 15), N_k0 (J, 15, 15)): parts()
        steps = imu_steps(dataset.imu, problem.times)
        self.samples = steps.segments()

    def leveraged(self, g: int) -> bool:
        """Whether group ``g``'s factors carry much leverage each (the IMU's, a relative sensor's:
        factors on two keyframes in a chain), so the approximate information is far off for it."""
        group = self.groups[g]
        return group.axes is None or KINDS[self.kinds[group.sensor]].relative

    def value(self, group: NoiseGroup, factor: float) -> float | None:
        """The group's density or (median) sigma with ``factor`` applied, in the rig's units: its
        measurements' own, as the rig states them (not the factors' covariances, which may add the
        process noise of attached measurements or compose several relative ones)."""
        if group.axes is None:
            return float(getattr(self.dataset.noise, group.part) * factor)
        cov = next(s.data.cov for s in sensors_of(self.dataset) if s.name == group.sensor)
        sigma = np.sqrt(np.diagonal(cov, axis1=-2, axis2=-1)[..., list(group.axes)])
        return float(np.median(sigma) * factor)

    def residual_summary(self, states, calibration, psi: np.ndarray) -> list[tuple[float, int]]:
        """Per group, ``(lag-one correlation, degrees of freedom)`` of its whitened residuals at
        ``states`` (a sensor group's axes; the IMU's whole residual for each of its components)."""
        blocks = self.blocks(psi)
        out = []
        for group in self.groups:
            block = blocks[self.block_index[group.sensor]]
            kf = block.keyframes
            slots = [states[kf[:, s]] for s in range(kf.shape[1])]
            e = block_residual(block, slots, False, slice(None), calibration)
            u = np.einsum("mab,mb->ma", block.whiten, e)
            axes = slice(None) if group.axes is None else list(group.axes)
            order = np.argsort(kf.max(axis=1), kind="stable")
            out.append((lag_one_correlation(u[order][:, axes]), int(u[:, axes].size)))
        return out

    def _imu_parts(self):
        """The IMU factors' covariance parts ``(N (4, J, 15, 15), N_0)`` along the problem's
        initial states, along which it made its own IMU covariances, so that ``psi = 0`` is the
        problem itself (to round-off)."""
        noise = self.dataset.noise
        zero = replace(noise, acc=0.0, gyro=0.0, acc_bias=0.0, gyro_bias=0.0)
        reference = self.problem.initial_states[:-1]
        rest = preintegration.noise_covariance(self.samples, reference, zero, self.dataset.gravity)
        parts = []
        for field, *_ in IMU_COMPONENTS:
            alone = replace(zero, velocity=0.0, **{field: getattr(noise, field)})
            floor = preintegration.COVARIANCE_FLOOR**2 * np.eye(imu.STATE_DIM)
            parts.append(preintegration.noise_covariance(self.samples, reference, alone, self.dataset.gravity) - floor)
        return np.stack(parts), rest

    def parts(self):
        """:meth:`_imu_parts`, made when first asked for."""
        if self.imu_parts is None:
            self.imu_parts = self._imu_parts()
        return self.imu_parts

    def blocks(self, psi: np.ndarray) -> list[Block]:
        """The problem's blocks with the covariances of ``psi`` (:meth:`_imu_parts` for the IMU's):
        a block whose groups' log-factors are all 0 is the problem's own, which the covariances of
        ``psi`` equal to round-off there."""
        theta = np.exp(psi)
        blocks = list(self.problem.blocks)
        imu_groups = [i for i, g in enumerate(self.groups) if g.axes is None]
        if np.any(psi[imu_groups]):
            parts, rest = self.parts()
            factors = np.ones(len(IMU_COMPONENTS))
            for i in imu_groups:
                factors[[f for f, *_ in IMU_COMPONENTS].index(self.groups[i].part)] = theta[i]
            cov = np.einsum("c,cjab->jab", factors, parts) + rest
            b = self.block_index[IMU_BLOCK]
            blocks[b] = replace(blocks[b], whiten=whitening(cov))
        for sensor, (W0, _) in self.rig.items():
            f = np.ones(W0.shape[-1])
            for i, g in enumerate(self.groups):
                if g.sensor == sensor:
                    f[list(g.axes)] = np.sqrt(theta[i])
            if np.any(f != 1.0):
                # (D R_0 D)^-1 = (W_0 D^-1)^T (W_0 D^-1): the rig's whitening, its columns scaled
                b = self.block_index[sensor]
                blocks[b] = replace(blocks[b], whiten=W0 / f[None, None, :])
        return blocks

    def _derivatives(self, block_name: str, rows: slice, psi: np.ndarray, W: np.ndarray) -> dict[int, np.ndarray]:
        """``{group: U_kg (M, d, d)}``: the whitened derivatives of the factors ``rows``' covariances."""
        theta = np.exp(psi)
        out = {}
        if block_name == IMU_BLOCK:
            parts, _ = self.parts()
            for i, g in enumerate(self.groups):
                if g.axes is None:
                    c = [f for f, *_ in IMU_COMPONENTS].index(g.part)
                    V = theta[i] * parts[c][rows]
                    out[i] = W @ V @ np.swapaxes(W, -1, -2)
            return out
        return {i: U[rows] for i, U in self.sensor_derivatives.items() if self.groups[i].sensor == block_name}

    def _rig_derivative(self, group: NoiseGroup) -> np.ndarray:
        """A sensor group's whitened derivatives ``U_kg (M, d, d)`` over all of its sensor's factors,
        the same at every ``psi``: ``(W S W^-1 + W^-T S W^T) / 2`` with ``W = W_0 D^-1``, which is
        ``W_0 S L_0`` symmetrised (``D`` and the group's axes ``S`` diagonal)."""
        W0, L0 = self.rig[group.sensor]
        S = np.zeros(W0.shape[-1])
        S[list(group.axes)] = 1.0
        A = W0 * S[None, None, :] @ L0
        return 0.5 * (A + np.swapaxes(A, -1, -2))

    def statistics(self, blocks: list[Block], states, calibration, cov: np.ndarray, joint: dict, psi: np.ndarray,
                   step: tuple | None = None, root=None):
        """``(quadratic (G,), expected (G,), information (G, G), redundancy (G,), exact, halves)`` at the
        estimate ``states`` and the calibration variables' values ``calibration`` (marginal
        covariances ``cov`` and joint blocks ``joint``): each group's ``sum_k u_k^T U_kg u_k``, its
        expectation ``tr(P_R V_g)`` (scaled by the truncated mean where outliers are left out: the
        score is half their difference), the approximate information and the redundancy
        ``tr(P_R V_g)``, ``V_g`` the derivative at ``psi``. ``step``: ``(dx (n, 15), [dc_j])``, the
        solution of the linear system the covariances are of: the residuals are that system's at
        its solution, ``e + J (dx, dc)``, so that every statistic comes from one system. ``root``:
        that system's :class:`~smoother.model.covariances.SquareRoot`; given, ``exact`` is a
        function of the groups still estimated returning the information with their columns exact
        where their factors carry much leverage (:meth:`leveraged`; :meth:`_exact`), else None.
        ``halves`` ``(2, 2, G)``: ``quadratic`` and ``expected`` summed over the factors of the
        run's first and of its second half (by their last keyframe's time; :func:`_halves`).
        """
        G = len(self.groups)
        quadratic, expected, information, redundancy = np.zeros(G), np.zeros(G), np.zeros((G, G)), np.zeros(G)
        halves = np.zeros((2, 2, G))  # (q, r) x (first half, second) x groups
        times = self.problem.times
        middle = int(np.searchsorted(times, 0.5 * (times[0] + times[-1])))  # the second half's first keyframe
        columns = [g for g in range(G) if self.leveraged(g)]
        factors = []  # each chunk's kept factors' (keys per slot, A, U, H): what _exact reads
        n = len(states)
        for name in dict.fromkeys(g.sensor for g in self.groups):
            block = blocks[self.block_index[name]]
            kf = block.keyframes
            d = None
            for start in range(0, len(kf), CHUNK):
                rows = slice(start, min(start + CHUNK, len(kf)))
                chunk = kf[rows]
                slots = [states[chunk[:, s]] for s in range(chunk.shape[1])]
                e, Js = block_residual(block, slots, True, rows, calibration)
                if step is not None:
                    dx, dc = step
                    e = e + sum(np.einsum("mab,mb->ma", J, dx[chunk[:, s]]) for s, J in enumerate(Js[:chunk.shape[1]]))
                    if block.calibration is not None:
                        e = e + Js[-1] @ dc[block.calibration]
                W = block.whiten[rows]
                u = np.einsum("mab,mb->ma", W, e)
                d = u.shape[1]
                A = [W @ J for J in Js]
                calibration_key = n + block.calibration if block.calibration is not None else None
                H = hat_blocks(A, chunk, calibration_key, cov, joint)
                Q = np.eye(d)[None] - H
                keep = np.ones(len(u), dtype=bool)
                correction = 1.0
                if block.robust is not None:
                    c = chi2_quantile(TRUNCATION_PROBABILITY, d)
                    keep = np.einsum("ma,ma->m", u, u) <= c
                    correction = truncated_mean(d, c)
                U = self._derivatives(name, rows, psi, W)
                at = list(U)
                quad, r, info = _chunk_terms(u[keep], Q[keep], np.stack([U[g][keep] for g in at], axis=1))
                quadratic[at] += quad.sum(axis=0)
                expected[at] += correction * r.sum(axis=0)
                redundancy[at] += r.sum(axis=0)
                information[np.ix_(at, at)] += info
                late = chunk[keep].max(axis=1) >= middle
                for h, part in enumerate((~late, late)):
                    halves[0, h, at] += quad[part].sum(axis=0)
                    halves[1, h, at] += correction * r[part].sum(axis=0)
                if root is not None:
                    keys = [chunk[:, s] for s in range(chunk.shape[1])]
                    if calibration_key is not None:
                        keys.append(np.full(len(chunk), calibration_key))
                    factors.append(([k[keep] for k in keys], [a[keep] for a in A],
                                    {g: Ug[keep] for g, Ug in U.items()}, H[keep]))
        exact = None if root is None else (
            lambda estimated: self._exact(information, [g for g in columns if g in estimated], factors, root, joint))
        return quadratic, expected, information, redundancy, exact, halves

    @staticmethod
    def _exact(approximate: np.ndarray, columns: list[int], factors: list, root, joint: dict) -> np.ndarray:
        """The information ``F_gh = 1/2 tr(P_R V_g P_R V_h)``: ``approximate`` with the ``columns``
        (and rows) exact -- those of the groups of factors with much leverage.

        In whitened coordinates (``M = I - A P A^T`` the whitened ``P_R``, ``A`` the whitened
        Jacobian, ``U_g`` block-diagonal over the factors, ``B_g = A^T U_g A``: the information
        ``A^T A`` falls by ``B_g`` for a unit increase of ``psi_g``), ``tr(M U_g M U_h) = own_hg +
        tr(P B_g P B_h)``: the factors' own terms ``own_hg = sum_k tr(U_kg U_kh) - 2 tr(H_k U_kg
        U_kh)``, from their hat blocks (:func:`_own_terms`), and ``tr(X_g B_h)`` with ``X_g = P B_g P``
        the change of the covariance for a unit increase of ``psi_g``, needed only on the pairs of
        variables ``B_h`` is on: those of a factor, a conditional and its parent. That is what
        :func:`~smoother.model.covariances.covariance_tangent` differentiates, from the system's
        conditionals ``root`` and covariance blocks ``joint``, for all columns in one sweep: no
        other elimination. ``factors``: each chunk's kept factors' ``(keys per slot, A per slot,
        {group: U}, H)`` (:meth:`statistics`), whose pairs' ``B_g`` :func:`_information_blocks` sums."""
        if not columns:
            return approximate
        # the blocks of the chunks that carry a column, let go once summed into the falls; then every
        # chunk's, one chunk at a time (a long run's blocks are never all held at once)
        falls = _falls([part for keys, A, U, _ in factors if any(g in U for g in columns)
                        for part in _information_blocks(keys, A, U)], columns)
        tangent = covariance_tangent(root, joint, falls)
        del falls
        cross = np.zeros((len(approximate), len(columns)))
        for keys, A, U, _ in factors:
            for groups, lo, hi, blocks in _information_blocks(keys, A, U):
                X = np.stack([tangent[(a, b)] for a, b in zip(lo.tolist(), hi.tolist())])
                P, G = blocks.shape[:2]
                per = blocks.reshape(P, G, -1) @ np.swapaxes(X.reshape(P, X.shape[1], -1), 1, 2)  # tr(B_pg X_px^T)
                cross[groups] += np.einsum("p,pgx->gx", np.where(lo == hi, 1.0, 2.0), per)
        exact = 0.5 * (_own_terms(factors, columns, len(approximate)) + cross)
        F = approximate.copy()
        F[:, columns] = exact
        F[columns, :] = exact.T
        return _positive_definite(F)


def _chunk_terms(u: np.ndarray, Q: np.ndarray, U: np.ndarray) -> tuple:
    """Over factors with whitened residuals ``u (M, d)``, residual covariances ``Q = I - H``
    ``(M, d, d)`` and whitened derivatives ``U (M, groups, d, d)``: per factor and group ``g``
    ``u^T U_g u`` and ``tr(Q U_g)`` (``(M, groups)`` each) and, per two groups, ``1/2 sum tr(Q U_g
    Q U_h)``."""
    M, G, d = U.shape[:3]
    QU = Q[:, None] @ U
    quad = np.einsum("ma,mgab,mb->mg", u, U, u)
    r = np.einsum("mgaa->mg", QU)
    flat, transposed = QU.reshape(M, G, d * d), np.swapaxes(QU, -1, -2).reshape(M, G, d * d)
    info = 0.5 * (flat @ np.swapaxes(transposed, 1, 2)).sum(axis=0)  # tr(A B) = vec(A) . vec(B^T)
    return quad, r, info


def _own_terms(factors: list, columns: list[int], G: int) -> np.ndarray:
    """``(G, columns)``: ``sum_k tr(U_kh U_kg) - 2 tr(H_k U_kg U_kh)`` over the factors ``k`` of
    every chunk of ``factors`` (:meth:`_NoiseModel._exact`), ``h`` any group, ``g`` a column."""
    own = np.zeros((G, len(columns)))
    for _, _, U, H in factors:
        into = [x for x, g in enumerate(columns) if g in U]
        if not into:
            continue
        groups = list(U)
        Us = np.stack([U[g] for g in groups], axis=1)
        Uc = np.stack([U[columns[x]] for x in into], axis=1)
        HU = H[:, None] @ Uc
        own[np.ix_(groups, into)] += np.einsum("mhab,mgba->hg", Us, Uc) - 2.0 * np.einsum("mgab,mhba->hg", HU, Us)
    return own


def _falls(B: list, columns: list[int]) -> dict:
    """``{(a, b): -B_g}`` stacked over the groups ``columns`` (``(columns, da, db)``): how the
    information falls on each pair of variables for a unit rise of each column's ``psi_g``, from the
    pairs' blocks ``B`` (:func:`_information_blocks`, each entry's pairs distinct);
    :func:`covariance_tangent`'s directions."""
    parts: dict = {}  # (da, db) -> [(a, b, into, blocks over take)] of the pairs of that shape
    for groups, lo, hi, blocks in B:
        where = [(x, groups.index(g)) for x, g in enumerate(columns) if g in groups]
        if where:
            into, take = (list(t) for t in zip(*where))
            every = take == list(range(len(groups)))  # the blocks as they are: no copy of them
            parts.setdefault(blocks.shape[2:], []).append((lo, hi, into, blocks if every else blocks[:, take]))
    out: dict = {}
    for shape, entries in parts.items():
        lo, hi = (np.concatenate(keys) for keys in zip(*((lo, hi) for lo, hi, *_ in entries)))
        width = int(hi.max()) + 1
        pairs, at = np.unique(lo * width + hi, return_inverse=True)
        total = np.zeros((len(pairs), len(columns), *shape))
        start = 0
        for a, _, into, blocks in entries:
            rows = at[start:start + len(a)]  # distinct pairs: no index twice
            if len(into) == len(columns):
                total[rows] -= blocks
            else:
                total[np.ix_(rows, into)] -= blocks
            start += len(a)
        out.update(zip(zip((pairs // width).tolist(), (pairs % width).tolist()), total))
    return out


def _summed_by_pair(lo: np.ndarray, hi: np.ndarray, blocks: np.ndarray) -> tuple:
    """``(lo, hi, blocks)`` with the blocks of each pair ``(lo, hi)`` summed: the pairs once each,
    in order."""
    order = np.lexsort((hi, lo))
    if np.any(order[1:] < order[:-1]):
        lo, hi, blocks = lo[order], hi[order], blocks[order]
    starts = np.flatnonzero(np.r_[True, (lo[1:] != lo[:-1]) | (hi[1:] != hi[:-1])])
    if len(starts) < len(lo):
        blocks = np.add.reduceat(blocks, starts, axis=0)
    return lo[starts], hi[starts], blocks


def _information_blocks(keys: list, A: list, U: dict) -> list:
    """The factors' ``A_ka^T U_kg A_kb`` summed over the factors on each pair of their variables
    ``(a, b)``, ``a <= b``: ``keys`` and ``A``, a key array ``(M,)`` and the whitened Jacobians
    ``(M, d, da)`` per slot, ``U`` ``{group: (M, d, d)}``. Returns ``[(groups, a (P,), b (P,),
    blocks (P, groups, da, db))]``, one entry per pair of slots and orientation."""
    groups = list(U)
    Us = np.stack([U[g] for g in groups], axis=1)
    out = []
    for s, (As, ks) in enumerate(zip(A, keys)):
        AU = np.swapaxes(As, -1, -2)[:, None] @ Us
        for At, kt in zip(A[s:], keys[s:]):
            blocks = AU @ At[:, None]
            for flip in (False, True):
                which = (ks > kt) if flip else (ks <= kt)
                if not which.any():
                    continue
                a, b, part = (ks, kt, blocks) if which.all() else (ks[which], kt[which], blocks[which])
                lo, hi = (b, a) if flip else (a, b)
                part = np.swapaxes(part, -1, -2) if flip else part
                out.append((groups, *_summed_by_pair(lo, hi, part)))
    return out


def truncated_mean(d: int, c: float) -> float:
    """``E[X | X <= c] / d`` for ``X`` chi-square with ``d`` degrees of freedom:
    ``P(chi2_{d+2} <= c) / P(chi2_d <= c)``."""
    from scipy.special import gammainc

    return float(gammainc(0.5 * (d + 2), 0.5 * c) / gammainc(0.5 * d, 0.5 * c))

