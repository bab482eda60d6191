"""A sensor's mounting rotation as the data give it: ``R_BS`` found in closed form from what the
sensor and the IMU both observe, with the information the data carry about it.

Derivations: ``docs/mounting.md``. Conventions (docs/design.md, sections 1, 3 and 7): ``C = C_IB``
body to world, ``R = R_BS`` sensor to IMU, LEFT perturbations ``R [+] rho = exp(rho) R`` with
``rho`` in the IMU frame; identities used: ``exp(phi) C = C exp(C^T phi)``, hence
``R^T exp(phi) R = exp(R^T phi)`` (eq. 24), ``exp(phi + d) ~= exp(Gamma(phi) d) exp(phi)`` (eq. 31),
``log(exp(d) A) ~= log(A) + Gamma^-1(log A) d`` (eq. 32), ``exp(rho) x ~= x - x^x rho`` (eqs. 22,
1), ``(R x)^x = R x^x R^T`` (eq. 3).

Three families, each a least-squares problem in 3-vector rows ``e_k(R, x) ~ 0`` (``x``: nuisance
parameters with Gaussian priors), started in closed form and refined by a few Gauss-Newton steps
on ``(rho, x)``:

* attitudes (``pose``, ``orientation``, ``odometry``): over a span ``a -> b`` the sensor turns by
  ``alpha_S = log(Z_a^T Z_b) = R^T alpha_B`` (a constant world offset of ``Z`` cancels), ``alpha_B``
  the gyro's turn; Wahba's problem ``alpha_B ~= R alpha_S``, solved by SVD (Kabsch), then jointly
  with the gyro bias ``b_w`` (``alpha_B(b_w) ~= alpha_B - Gamma^-1(alpha_B) J b_w``);
* velocity: the body velocity ``v`` and the specific force obey ``A_b v_b - A_a v_a =
  int A (f - b_f) dt + (t_b - t_a) g_w`` with ``A`` the gyro's attitude and ``g_w`` gravity in a
  window's frame; with the sensor's reading ``nu = R^T (v + w x p) / s`` (``s`` its scale) it is
  linear in ``(R / s, b_f, g_w)``: the free matrix is projected onto the rotations, then refined
  jointly with ``s`` (kept on the specific force's side, which the velocities' noise cannot
  shrink), ``b_f`` and ``b_w``, the gyro integrated again while its bias correction is large;
* tilt (``roll_pitch``): at low dynamics the mean specific force is ``|g| R u_S + b_f`` with
  ``u_S = Z^T e_z`` the vertical the sensor reports in its own frame; Wahba again.

The information of ``rho`` is the Schur complement of the normal equations onto it, less what the
noise of the measured vectors alone would put into ``J^T J`` (at most ``2 n s^2`` per direction
for ``n`` rows of scatter ``s^2`` per component), scaled by that scatter plus a model-error floor
``eps`` that more data do not average away: ``cov = (s^2 / n + eps^2) Mbar^-1`` with ``Mbar`` the
mean information of a row. A direction the motion does not excite has no information:
:mod:`smoother.diagnosis.mounting` decides which are determined.

Everything is vectorised and linear in the data's size: the gyro's attitude and its integrals are
prefix products and cumulative sums over the IMU samples
(:class:`~smoother.diagnosis.imu_integrals.ImuIntegrals`), computed once per dataset; the rows
are subsampled to spans long enough to carry a signal.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Callable

import numpy as np

from datasets.kinds.roll_pitch import RollPitchMeasurements
from datasets.types import (
    SAME_INSTANT_S,
    Dataset,
    ImuSamples,
    OrientationMeasurements,
    PoseMeasurements,
    RelativePoseMeasurements,
    Sensor,
    VelocityMeasurements,
)
from factors import so3
from factors.errors import SolverError
from factors.sensor_models import extrinsic_parts
from smoother.diagnosis.imu_integrals import ImuIntegrals, chained, imu_integrals

#: Attitude rows: a span is as many measurements long as the gyro's median rate needs to turn the
#: body by this much [rad]; then the attitude noise at the two ends is a small part of a turn.
TARGET_TURN = 0.3
#: Attitude rows: spans turning more than this [rad] (by the gyro or the sensor) are left out: the
#: rotation vector of a turn near pi is ill-defined (and flips with the noise).
MAX_TURN = 2.0
#: Attitude rows: the longest span [s] (a bias of 0.01 rad/s turns the gyro by 0.05 rad over it).
MAX_SPAN_S = 5.0
#: Velocity rows: the span over which a velocity change is compared with the integrated specific
#: force [s] (at most; a short recording takes a fiftieth of its length, at least one sample step).
VELOCITY_SPAN_S = 1.0
#: Velocity rows: the windows [s] of one gravity vector each; within one the gyro bias's effect on
#: the gravity direction is linearised about the window's middle.
GRAVITY_WINDOW_S = 10.0
#: Velocity rows: while the gyro-bias correction turns gravity by more than this over half a
#: window [rad] (from the window's middle, where its first-order model is anchored; beyond, the
#: model errs by more than 0.012 m/s^2, half the velocity model error over a span of a second),
#: the gyro is integrated again about the corrected bias, at most :data:`REINTEGRATIONS` times.
REINTEGRATION_TURN = 0.05
REINTEGRATIONS = 3
#: Tilt rows: the specific force is averaged over this window [s] about each measurement.
TILT_WINDOW_S = 0.5
#: Tilt rows are kept only at low dynamics: the mean specific force's magnitude within this of
#: ``|g|`` [m/s^2] (plus two of the accelerometer bias's sigmas, which move it as much) and the
#: mean angular rate below :data:`LOW_DYNAMICS_RATE` [rad/s].
LOW_DYNAMICS_ACC = 0.2
LOW_DYNAMICS_RATE = 0.3
#: Model errors that more data do not average away (a per-row systematic error, in each family's
#: units): a 10 ms time offset turns 1 rad/s^2 of angular acceleration into 0.01 rad of turn; it
#: turns 2 m/s^2 into 0.02 m/s of velocity; at low dynamics the mean acceleration a vehicle keeps
#: up (a slow turn's) is some 0.3 m/s^2.
ATTITUDE_MODEL_ERROR = 0.01
VELOCITY_MODEL_ERROR = 0.02
TILT_MODEL_ERROR = 0.3
#: The fewest rows a rotation is found from (each row has 3 equations).
MIN_ROWS = 10
#: Rows whose residual exceeds this many robust sigmas are dropped as outliers.
OUTLIER_SIGMAS = 6.0
#: A parameter whose information (the square root of its diagonal of the normal equations) is below this
#: share of the largest one's is read by nothing: left at zero (:func:`minimum_norm_solution`).
NO_INFORMATION = 1e-8
#: Gauss-Newton steps after the closed-form start.
ITERATIONS = 4
#: Median of the chi-square distribution with 3 degrees of freedom (robust scale of a 3-vector).
_CHI2_3_MEDIAN = 2.365974


class NotDetermined(SolverError):
    """The data cannot give the sensor's mounting rotation; the message says why."""


@dataclass(frozen=True, eq=False)
class DataRotation:
    """``R`` (3x3): the sensor-to-IMU rotation ``R_BS`` the data give; ``information`` (3x3,
    [1/rad^2]): of its LEFT perturbation ``rho`` (``exp(rho) R``, IMU frame), singular along the
    directions the motion does not excite; ``rows``: how many spans (or epochs) it was found from;
    ``rms``: the residuals' scatter per component, in the family's ``units``."""

    R: np.ndarray
    information: np.ndarray
    rows: int
    rms: float
    units: str


def bias_sigmas(dataset: Dataset) -> tuple[np.ndarray, np.ndarray]:
    """The accelerometer's and the gyro's bias sigmas (3 each) the dataset declares for its initial
    state: the priors of the bias corrections the fits estimate."""
    sigma = np.sqrt(np.diag(dataset.initial_cov))
    return sigma[9:12], sigma[12:15]


# ------------------------------------------------------------------------------------------------
# the shared least-squares machinery


@dataclass(frozen=True)
class _Rows:
    """A family's problem: ``linearise(R, x) -> (e (n, 3), J (n, 3, 3 + q))``, the rows'
    residuals and their Jacobians with respect to ``(rho, x)``; ``prior`` (q,): the nuisance
    parameters' prior information, about ``prior_mean`` (None: 0); ``window`` (n,) and ``column``
    (n,): where given, row ``k`` also holds ``-column_k g_window_k`` with a free 3-vector per window
    (rows sorted by window); ``model_error``: the per-row floor of the covariance; ``units`` of a
    residual."""

    linearise: Callable
    prior: np.ndarray
    model_error: float
    units: str
    prior_mean: np.ndarray | None = None
    window: np.ndarray | None = None
    column: np.ndarray | None = None


def _without_windows(rows: _Rows, keep: np.ndarray, *arrays):
    """``arrays`` (rows first) restricted to ``keep`` with each window's free vector eliminated:
    a row ``Y_k`` less ``c_k sum_j(c_j Y_j) / sum_j(c_j^2)`` over its window (the least-squares
    projection onto the complement of the window's columns); and the number of windows."""
    arrays = [a[keep] for a in arrays]
    if rows.window is None:
        return arrays, 0
    window, c = rows.window[keep], rows.column[keep]
    starts = np.flatnonzero(np.r_[True, window[1:] != window[:-1]])
    count = np.diff(np.r_[starts, len(window)])
    cc = np.add.reduceat(c * c, starts)
    out = []
    for a in arrays:
        shape = (-1,) + (1,) * (a.ndim - 1)
        mean = np.add.reduceat(c.reshape(shape) * a, starts, axis=0) / cc.reshape(shape)
        out.append(a - c.reshape(shape) * np.repeat(mean, count, axis=0))
    return out, len(starts)


def _normal(J: np.ndarray, e: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    A = J.reshape(-1, J.shape[-1])
    return A.T @ A, A.T @ e.reshape(-1)


def minimum_norm_solution(N: np.ndarray, g: np.ndarray) -> np.ndarray:
    """The minimum-norm solution of ``N x = g`` (``N`` symmetric, positive semi-definite; ``g`` a
    vector or columns) with ``N``'s columns scaled to a unit diagonal first, so that a stiff prior
    on one parameter does not hide the others from the rank decision; directions with less than
    1e-10 of the largest scaled information are left at zero, and so are parameters that nothing
    reads at all (a diagonal below :data:`NO_INFORMATION` of the largest: a wheel odometer's
    lateral and vertical velocities, exactly zero in every message), which the scaling would
    otherwise blow up from round-off."""
    d = np.sqrt(np.maximum(np.diag(N), 0.0))
    live = d > NO_INFORMATION * d.max() if d.max() > 0 else np.zeros(len(d), bool)
    x = np.zeros(np.shape(g))
    if live.any():
        column = d[live].reshape((-1,) + (1,) * (np.ndim(g) - 1))
        scaled = N[np.ix_(live, live)] / np.outer(d[live], d[live])
        x[live] = np.linalg.lstsq(scaled, g[live] / column, rcond=1e-10)[0] / column
    return x


def _fit(rows: _Rows, R: np.ndarray, x: np.ndarray) -> tuple[DataRotation, np.ndarray]:
    """Gauss-Newton on ``(rho, x)`` from ``(R, x)``, the rows weighted by their current scatter
    plus the model error (so that the nuisance priors weigh what they should), with no step along
    directions without information (:func:`minimum_norm_solution`) and gross outliers dropped after the first
    step; then the information of ``rho`` (module docstring) and the nuisance parameters."""
    q = len(x)
    prior_mean = np.zeros(q) if rows.prior_mean is None else rows.prior_mean
    keep = None
    for iteration in range(ITERATIONS + 1):
        e, J = rows.linearise(R, x)
        if keep is None:
            keep = np.ones(len(e), bool)
        (e_p, J_p), windows = _without_windows(rows, keep, e, J)
        if iteration == 1:
            scale2 = np.median(np.sum(e_p**2, axis=1)) / _CHI2_3_MEDIAN
            keep[keep] = np.sum(e_p**2, axis=1) <= OUTLIER_SIGMAS**2 * scale2
            (e_p, J_p), windows = _without_windows(rows, keep, e, J)
        n = int(keep.sum())
        dof = 3 * n - 3 * windows - 3 - q
        if n < MIN_ROWS or dof < 3:
            raise NotDetermined(f"too few usable rows ({n}) after dropping outliers")
        s2 = float(np.sum(e_p**2)) / dof
        if iteration == ITERATIONS:
            break
        N, g = _normal(J_p, e_p)
        N, g = N / (s2 + rows.model_error**2), g / (s2 + rows.model_error**2)
        N[3:, 3:] += np.diag(rows.prior)
        g[3:] += rows.prior * (x - prior_mean)
        step = -minimum_norm_solution(N, g)
        R = so3.exp(step[:3]) @ R
        x = x + step[3:]
    N, _ = _normal(J_p, e_p)
    lam, V = np.linalg.eigh(N[:3, :3] - 2.0 * n * s2 * np.eye(3))
    N[:3, :3] = (V * np.maximum(lam, 0.0)) @ V.T
    N = N / (s2 + n * rows.model_error**2)
    N[3:, 3:] += np.diag(rows.prior)
    information = N[:3, :3] - N[:3, 3:] @ minimum_norm_solution(N[3:, 3:], N[3:, :3]) if q else N[:3, :3]
    return DataRotation(R, 0.5 * (information + information.T), n, float(np.sqrt(s2)), rows.units), x


def _wahba(targets: np.ndarray, sources: np.ndarray) -> np.ndarray:
    """The rotation ``R`` minimising ``sum |targets_k - R sources_k|^2`` (Kabsch: the nearest
    rotation to ``sum targets sources^T``)."""
    return so3.project(np.einsum("ki,kj->ij", targets, sources))


# ------------------------------------------------------------------------------------------------
# attitudes: pose, orientation, odometry


def _spans(segment: np.ndarray, stride: int) -> tuple[np.ndarray, np.ndarray]:
    """Consecutive, non-overlapping spans ``(a, b = a + stride)`` of nodes within a segment
    (nodes sorted by segment, then time)."""
    first = np.flatnonzero(np.r_[True, segment[1:] != segment[:-1]])
    position = np.arange(len(segment)) - np.repeat(first, np.diff(np.r_[first, len(segment)]))
    a = np.flatnonzero(position % stride == 0)
    a = a[a + stride < len(segment)]
    a = a[segment[a + stride] == segment[a]]
    return a, a + stride


def attitude_rotation(integrals: ImuIntegrals, t: np.ndarray, Z: np.ndarray, segment: np.ndarray,
                      gyro_bias_sigma: np.ndarray) -> DataRotation:
    """``R_BS`` from the sensor frame's attitudes ``Z`` (N, 3, 3) at times ``t``, each segment
    (``segment`` (N,), sorted, then by time) in a world of its own: spans of the sensor's turn
    ``alpha_S = log(Z_a^T Z_b)`` against the gyro's over the same times, with a gyro-bias
    correction of prior ``gyro_bias_sigma`` (rad/s, 3)."""
    rate = float(np.median(np.linalg.norm(integrals.imu.gyro - integrals.b_w, axis=1)))
    step = float(np.median(np.diff(t)))
    stride = int(np.clip(TARGET_TURN / max(rate * step, 1e-12), 1, max(1.0, MAX_SPAN_S / step)))
    stride = max(1, min(stride, len(t) // (2 * MIN_ROWS)))
    a, b = _spans(segment, stride)
    G, Sigma, _, _ = integrals.at(np.r_[t[a], t[b]])
    G_a, G_b, Sigma_a, Sigma_b = G[:len(a)], G[len(a):], Sigma[:len(a)], Sigma[len(a):]
    D = np.swapaxes(G_a, 1, 2) @ G_b
    alpha_S = so3.log(np.swapaxes(Z[a], 1, 2) @ Z[b])
    inside = (np.linalg.norm(so3.log(D), axis=1) < MAX_TURN) & (np.linalg.norm(alpha_S, axis=1) < MAX_TURN)
    if inside.sum() < MIN_ROWS:
        raise NotDetermined(f"only {int(inside.sum())} spans of {stride} attitudes turning less than {MAX_TURN:g} rad")
    D, alpha_S = D[inside], alpha_S[inside]
    J_b = np.swapaxes(G_a[inside], 1, 2) @ (Sigma_b[inside] - Sigma_a[inside])

    def linearise(R, b_w):
        alpha = so3.log(so3.exp(-J_b @ b_w) @ D)
        R_alpha = alpha_S @ R.T
        jac = np.concatenate([so3.skew(R_alpha), -so3.gamma_inv(alpha) @ J_b], axis=2)
        return alpha - R_alpha, jac

    R0 = _wahba(so3.log(D), alpha_S)
    rows = _Rows(linearise, 1.0 / gyro_bias_sigma**2, ATTITUDE_MODEL_ERROR, "rad")
    return _fit(rows, R0, np.zeros(3))[0]


def odometry_chain(m: RelativePoseMeasurements) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Relative poses chained into attitudes: ``(t, Z, segment)``, a segment for each run of
    measurements where one starts when the one before ends (Z the product of the relative
    rotations from the run's start; only turns within a segment are meaningful)."""
    P = chained(m.dC)
    breaks = np.abs(m.t_from[1:] - m.t_to[:-1]) > SAME_INSTANT_S
    segment = np.r_[0, np.cumsum(breaks)]
    first = np.flatnonzero(np.r_[True, breaks])
    before = np.concatenate([np.eye(3)[None], P[:-1]])[first]
    t = np.r_[m.t_to, m.t_from[first]]
    Z = np.concatenate([P, before])
    seg = np.r_[segment, segment[first]]
    order = np.lexsort((t, seg))
    return t[order], Z[order], seg[order]


# ------------------------------------------------------------------------------------------------
# velocity


def velocity_rotation(integrals: ImuIntegrals, m: VelocityMeasurements, acc_bias_sigma: np.ndarray,
                      gyro_bias_sigma: np.ndarray) -> DataRotation:
    """``R_BS`` of a velocity sensor: over spans ``a -> b`` of about :data:`VELOCITY_SPAN_S`, its
    velocity change against the specific force integrated in the gyro's frame, with a free gravity
    vector per :data:`GRAVITY_WINDOW_S` window, its scale ``s`` and corrections of the biases
    (priors ``acc_bias_sigma``, ``gyro_bias_sigma``). The rig's lever arm ``p_BS`` is taken as it
    is (``s v = R nu - s w x p``). While the gyro-bias correction would turn the gravity by more
    than :data:`REINTEGRATION_TURN` over a window, the gyro is integrated again about it."""
    spans = _velocity_spans(m.t)
    prior_mean = np.zeros(7)
    R = x = None
    for _ in range(REINTEGRATIONS + 1):
        rows, start = _velocity_rows(integrals, m, spans, acc_bias_sigma, gyro_bias_sigma, prior_mean)
        estimate, x = _fit(rows, *(start if R is None else (R, np.r_[x[:4], 0.0, 0.0, 0.0])))
        R, correction = estimate.R, x[4:7]
        if np.linalg.norm(correction) * 0.5 * GRAVITY_WINDOW_S <= REINTEGRATION_TURN:
            break
        integrals = ImuIntegrals(integrals.imu, integrals.b_f, integrals.b_w + correction)
        prior_mean[4:7] -= correction
    if not x[0] > 0:
        raise NotDetermined(f"the velocities fit the specific force only with a negative scale ({x[0]:.3g})")
    return estimate


def _velocity_spans(t: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``(a, b, window)``: consecutive spans of about :data:`VELOCITY_SPAN_S` (at most a fiftieth
    of the recording, at least a sample step; none across a gap of three), and each span's
    :data:`GRAVITY_WINDOW_S` window (windows of fewer than three spans left out)."""
    if len(t) < 2:
        raise NotDetermined("fewer than two velocities")
    step = float(np.median(np.diff(t)))
    stride = max(1, int(round(min(VELOCITY_SPAN_S, (t[-1] - t[0]) / 50.0) / step)))
    a, b = _spans(np.zeros(len(t), int), stride)
    whole = t[b] - t[a] <= 3 * stride * step
    a, b = a[whole], b[whole]
    window = np.floor((t[a] - t[0]) / GRAVITY_WINDOW_S).astype(int)
    usable = np.bincount(window)[window] >= 3
    if usable.sum() < MIN_ROWS:
        raise NotDetermined(f"too few velocity spans ({int(usable.sum())})")
    return a[usable], b[usable], window[usable]


def _velocity_rows(integrals: ImuIntegrals, m: VelocityMeasurements, spans, acc_bias_sigma, gyro_bias_sigma,
                   prior_mean) -> tuple[_Rows, tuple]:
    """The velocity family's :class:`_Rows` about the ``integrals``' biases, with the nuisance
    ``x = (s, s db_f, db_w)`` (the scale, the accelerometer-bias correction times it, the gyro's),
    and its closed-form start ``(R, x)``."""
    _, p = extrinsic_parts(m.T_BS)
    t = m.t
    a, b, window = spans
    n = len(a)
    first = np.flatnonzero(np.r_[True, window[1:] != window[:-1]])
    last = np.r_[first[1:], n] - 1
    anchor = 0.5 * (t[a[first]] + t[b[last]])
    G, Sigma, F, K = integrals.at(np.r_[t[a], t[b], anchor], with_K=True)
    ends = [slice(0, n), slice(n, 2 * n)]
    Sigma_w = Sigma[2 * n:][np.repeat(np.arange(len(first)), np.diff(np.r_[first, n]))]
    dF = F[ends[1]] - F[ends[0]]
    dSigma = Sigma[ends[1]] - Sigma[ends[0]]
    bias_drift = K[ends[1]] - K[ends[0]] - so3.skew(dF) @ Sigma_w
    nu = [m.velocity[a], m.velocity[b]]
    lever = [np.cross(m.gyro[a] - integrals.b_w, p), np.cross(m.gyro[b] - integrals.b_w, p)]
    S = [Sigma[end] - Sigma_w for end in ends]

    def linearise(R, x):
        scale, beta_f, b_w = x[0], x[1:4], x[4:7]
        e = dSigma @ beta_f - scale * (dF + bias_drift @ b_w)
        J = np.zeros((n, 3, 10))
        J[:, :, 3] = -(dF + bias_drift @ b_w)
        J[:, :, 4:7] = dSigma
        J[:, :, 7:10] = -scale * bias_drift
        for sign, end, nu_end, lever_end, S_end in zip((-1.0, 1.0), ends, nu, lever, S):
            A = so3.exp(-S_end @ b_w) @ G[end]
            R_nu = nu_end @ R.T
            A_x = np.einsum("kij,kj->ki", A, R_nu - scale * lever_end)
            e += sign * A_x
            J[:, :, 0:3] -= sign * (A @ so3.skew(R_nu))
            J[:, :, 3] -= sign * np.einsum("kij,kj->ki", A, lever_end)
            J[:, :, 7:10] += sign * (so3.skew(A_x) @ S_end)
        return e, J

    rows = _Rows(linearise, np.r_[0.0, 1.0 / acc_bias_sigma**2, 1.0 / gyro_bias_sigma**2], VELOCITY_MODEL_ERROR,
                 "m/s", prior_mean, window, t[b] - t[a])
    M, k = _linear_start(rows, G, ends, nu, lever, dF, dSigma, bias_drift)
    return rows, (so3.project(M), np.r_[1.0 / k, np.zeros(6)])


def _linear_start(rows: _Rows, G, ends, nu, lever, dF, dSigma, bias_drift) -> tuple[np.ndarray, float]:
    """The velocity family's closed-form start: ``M = R / s`` as a free 3x3 matrix with the bias
    corrections and the windows' gravity, by linear least squares (minimum norm where the motion
    leaves ``M`` undetermined; the gyro bias only where it turns gravity, its turn of the velocity
    left out), the rows weighted as :func:`_fit` weighs them; ``(M, k)`` with ``k = 1 / s`` the
    largest singular value of ``M``."""
    n = len(dF)
    A = np.zeros((n, 3, 15))
    y = dF.copy()
    for sign, end, nu_end, lever_end in zip((-1.0, 1.0), ends, nu, lever):
        # G M nu = (nu^T kron G) vec(M), vec column-major
        A[:, :, :9] += sign * np.einsum("kj,kab->kajb", nu_end, G[end]).reshape(n, 3, 9)
        y += sign * np.einsum("kij,kj->ki", G[end], lever_end)
    A[:, :, 9:12] = dSigma
    A[:, :, 12:] = -bias_drift
    (A_p, y_p), windows = _without_windows(rows, np.ones(n, bool), A, y)
    prior, mean = np.r_[np.zeros(9), rows.prior[1:]], np.r_[np.zeros(9), rows.prior_mean[1:]]
    N, g = _normal(A_p, y_p)
    s2 = 0.0
    for _ in range(2):
        weight = 1.0 / (s2 + rows.model_error**2)
        solution = minimum_norm_solution(weight * N + np.diag(prior), weight * g + prior * mean)
        s2 = float(np.sum((y_p - A_p @ solution) ** 2)) / max(3 * n - 3 * windows - 15, 1)
    M = solution[:9].reshape(3, 3, order="F")
    k = float(np.linalg.svd(M, compute_uv=False)[0])
    if not k > 0:
        raise NotDetermined("the velocities do not change with the specific force (no motion)")
    return M, k


# ------------------------------------------------------------------------------------------------
# tilt: roll_pitch


def tilt_rotation(imu: ImuSamples, t: np.ndarray, Z: np.ndarray, gravity: np.ndarray, b_f: np.ndarray,
                  acc_bias_sigma: np.ndarray) -> DataRotation:
    """``R_BS`` from the vertical ``u_S = Z^T e_z`` a sensor reports in its own frame (its
    heading is never used) against the specific force averaged over :data:`TILT_WINDOW_S` at low
    dynamics, ``f_mean - b_f ~= |g| R u_S + db_f``, with an accelerometer-bias correction of prior
    ``acc_bias_sigma`` about the estimate ``b_f``; one attitude a window (their rows do not share
    IMU samples)."""
    apart = np.flatnonzero(np.r_[True, np.diff(np.floor((t - t[0]) / TILT_WINDOW_S)) > 0])
    t, Z = t[apart], Z[apart]
    half = 0.5 * TILT_WINDOW_S
    lo = np.searchsorted(imu.t, t - half, side="left")
    hi = np.searchsorted(imu.t, t + half, side="right")
    count = hi - lo
    sums = np.concatenate([np.zeros((1, 6)), np.cumsum(np.hstack([imu.acc, imu.gyro]), axis=0)])
    mean = (sums[hi] - sums[lo]) / np.maximum(count, 1)[:, None]
    f = mean[:, :3] - b_f
    g = float(np.linalg.norm(gravity))
    tolerance = LOW_DYNAMICS_ACC + 2.0 * float(np.max(acc_bias_sigma))
    calm = ((count >= 2) & (np.abs(np.linalg.norm(f, axis=1) - g) <= tolerance)
            & (np.linalg.norm(mean[:, 3:], axis=1) <= LOW_DYNAMICS_RATE))
    if calm.sum() < MIN_ROWS:
        raise NotDetermined(f"only {int(calm.sum())} of {len(t)} attitudes at low dynamics (specific force within "
                            f"{tolerance:.2g} m/s^2 of |g|, rate below {LOW_DYNAMICS_RATE:g} rad/s)")
    f, u_S = f[calm], Z[calm, 2, :]

    def linearise(R, db_f):
        R_u = g * u_S @ R.T
        jac = np.concatenate([so3.skew(R_u), np.broadcast_to(-np.eye(3), (len(f), 3, 3))], axis=2)
        return f - R_u - db_f, jac

    rows = _Rows(linearise, 1.0 / acc_bias_sigma**2, TILT_MODEL_ERROR, "m/s^2")
    return _fit(rows, _wahba(f, u_S), np.zeros(3))[0]


# ------------------------------------------------------------------------------------------------
# by kind


#: Why a kind's mounting rotation is not checked.
NOT_CHECKED = {
    "position": "a position's model holds the sensor's lever arm, not its rotation",
    "gnss": "a position's model holds the antenna's lever arm, not its rotation",
    "altitude": "a height's model holds the sensor's lever arm, not its rotation",
    "magnetometer": "the field's direction in the sensor is bent by the vehicle's own iron as much as by a "
                    "mounting error",
}


def data_rotation(dataset: Dataset, sensor: Sensor, integrals: ImuIntegrals | None = None) -> DataRotation:
    """The :class:`DataRotation` of ``sensor`` (of ``dataset``) from its measurements used
    (``integrals``: the dataset's :class:`ImuIntegrals`, shared between sensors); a
    :class:`NotDetermined` saying why when the data cannot give it."""
    if sensor.kind in NOT_CHECKED:
        raise NotDetermined(NOT_CHECKED[sensor.kind])
    data = sensor.data
    if data is None or len(data) < 2:
        raise NotDetermined("fewer than two measurements")
    integrals = imu_integrals(dataset) if integrals is None else integrals
    acc_sigma, gyro_sigma = bias_sigmas(dataset)
    if isinstance(data, (PoseMeasurements, OrientationMeasurements)):
        return attitude_rotation(integrals, data.t, data.C, np.zeros(len(data), int), gyro_sigma)
    if isinstance(data, RelativePoseMeasurements):
        return attitude_rotation(integrals, *odometry_chain(data), gyro_sigma)
    if isinstance(data, VelocityMeasurements):
        return velocity_rotation(integrals, data, acc_sigma, gyro_sigma)
    if isinstance(data, RollPitchMeasurements):
        return tilt_rotation(dataset.imu, data.t, data.C, dataset.gravity, integrals.b_f, acc_sigma)
    raise NotDetermined(f"no mounting check for a {sensor.kind} sensor")
