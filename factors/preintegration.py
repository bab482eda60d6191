"""Exact preintegration of the primer's Euler-forward IMU model between keyframes.

Between keyframes ``i`` and ``j`` the model of :mod:`factors.imu` (eqs. 54-60) integrates into
quantities that depend only on the IMU samples and the gyro bias. With ``dC_k`` the attitude
relative to keyframe ``i`` (``C_k = C_i dC_k``), ``gamma = C_i^T g`` (gravity in body frame
``i``) and the 10-vector ``z = (v_i, gamma, 1, -b_f)``::

    v_k = W_k z                       W = [M | N | d | D]   (3 x 10)
    r_k = r_i + C_i Rm_k z            Rm = [P | Q | e | E]  (3 x 10)
    C_k = C_i dC_k

with, for each sample ``(f~_k, w~_k, dt_k)``, ``w_k = w~_k - b_w`` and ``A_k = I - dt_k w_k^x``::

    W_0 = [I | 0 | 0 | 0],  W_{k+1} = A_k W_k + dt_k [0 | dC_k^T | f~_k | I]
    Rm_0 = 0,               Rm_{k+1} = Rm_k + dt_k dC_k W_k
    dC_0 = I,               dC_{k+1} = dC_k exp(dt_k w_k)

This is the primer's recursion rewritten, not an approximation: the prediction equals
:func:`factors.imu.propagate` applied sample by sample to round-off. The accelerometer bias
enters linearly through ``z`` (exact). The gyro bias enters ``A_k`` and ``dC_k``; its effect is
kept to first order around the linearisation point ``b_w_bar`` with the Jacobians (primer sense,
``dC(b_w_bar + d) ~= exp(JC d) dC``)::

    JC_0 = 0,  JC_{k+1} = JC_k - dt_k dC_k Gamma(dt_k w_k)
    dW_{k+1}[d] = A_k dW_k[d] + dt_k d^x W_k + dt_k [0 | -dC_k^T (JC_k d)^x | 0 | 0]
    dRm_{k+1}[d] = dRm_k[d] + dt_k ((JC_k d)^x dC_k W_k + dC_k dW_k[d])

(``A_k`` gains ``dt d^x`` when ``b_w`` grows by ``d``; ``dC_k^T`` gains ``-dC_k^T (JC_k d)^x``.)
When the gyro bias moves far from ``b_w_bar``, the interval is integrated again
(:meth:`Preintegrated.relinearized`).

The noise covariance of the prediction is the EKF's own: the primer's ``F`` and ``G`` propagated
along the reference trajectory from keyframe ``i`` with zero initial covariance,
``S_{k+1} = F S F^T + G Q_d G^T``, expressed in the residual's body-``i`` coordinates. It is
propagated in those coordinates directly (``dC_k`` in place of ``C_k``, ``gamma`` in place of
``g``: the model is invariant under a rotation of the world), by the EKF's own prediction code
(:func:`factors.imu.predict_flat`); the reference trajectory is the dead reckoning from keyframe
to keyframe, reset where measurements anchor it (:func:`integrate_with_covariance`).

Everything is vectorised over intervals: arrays of shape ``(J, K, ...)`` hold ``J`` intervals of
up to ``K`` samples; padding samples have ``dt = 0``, which is exactly the identity step. The
recursions are compiled loops over all samples (:mod:`factors.compiled`), with no Python per
sample or per interval. Intervals are independent of each other except through the reference
trajectory, so a whole run is one pipeline over ranges of intervals
(:func:`factors.threads.in_parallel` with a scan): the recursions of each range, on whichever
core is free; the reference chain through it, in order, a few operations per interval; the
covariances along it, on whichever core is free. Each interval's arithmetic is the same whichever
thread runs it, so the results do not depend on the number of cores.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from factors import imu, so3
from factors.compiled import block_operation, leaf, recursion
from factors.errors import InputError
from factors.rows import as_trailing, common_shape
from factors.rows import rows as rows_of
from factors.small_linalg import matmul_into
from factors.threads import in_parallel

#: Standard deviation (in each error-state unit: m, m/s, rad, m/s^2, rad/s) added to every
#: IMU residual's covariance so that it is positive definite even for one-sample intervals.
COVARIANCE_FLOOR = 1e-7

#: Default gyro-bias change (rad/s) beyond which an interval is integrated again.
REINTEGRATION_THRESHOLD = 0.02



@dataclass
class Preintegrated:
    """Preintegrated quantities of ``J`` intervals (leading dimension ``J`` on every array).

    ``dC (J,3,3)``, ``W (J,3,10)``, ``Rm (J,3,10)``, their gyro-bias Jacobians
    ``JC (J,3,3)``, ``dW (J,3,10,3)``, ``dRm (J,3,10,3)``, the linearisation point ``b_w_bar
    (J,3)`` and, if computed, the residual covariance ``cov (J,15,15)`` in body-``i``
    coordinates. ``samples`` keeps the IMU samples ``(acc, gyro, dt)`` padded to ``(J, K, ...)``
    so an interval can be integrated again (and gives the interval lengths, :attr:`duration`).
    """

    dC: np.ndarray
    W: np.ndarray
    Rm: np.ndarray
    JC: np.ndarray
    dW: np.ndarray
    dRm: np.ndarray
    b_w_bar: np.ndarray
    samples: tuple
    cov: np.ndarray | None = None

    def __len__(self) -> int:
        return len(self.b_w_bar)

    @property
    def duration(self) -> np.ndarray:
        """The interval lengths ``(J,)`` (sums of the samples' ``dt``; computed when asked)."""
        return self.samples[2].sum(axis=-1)

    def __getitem__(self, index) -> "Preintegrated":
        if not isinstance(index, (int, np.integer, slice)):  # a slice gives views, no copies
            index = np.arange(len(self))[index]
        pick = lambda a: None if a is None else a[index]  # noqa: E731
        return Preintegrated(
            self.dC[index], self.W[index], self.Rm[index], self.JC[index], self.dW[index],
            self.dRm[index], self.b_w_bar[index], tuple(s[index] for s in self.samples), pick(self.cov),
        )

    def assign(self, index, other: "Preintegrated") -> None:
        """Overwrite intervals ``index`` with ``other``'s (same count), the same intervals integrated
        again (:meth:`relinearized`): the samples and the covariance are kept."""
        for name in ("dC", "W", "Rm", "JC", "dW", "dRm", "b_w_bar"):
            getattr(self, name)[index] = getattr(other, name)

    def corrected(self, b_w: np.ndarray):
        """``(dC, W, Rm)`` at gyro bias ``b_w`` (first order around ``b_w_bar``) and the offset
        ``d = b_w - b_w_bar`` (compiled, :func:`_correct`)."""
        lead = common_shape(self.b_w_bar.shape[:-1], np.shape(b_w)[:-1])
        n = math.prod(lead)
        rows = rows_of(lead, (self.dC, self.W, self.Rm, self.JC, self.dW, self.dRm, self.b_w_bar, b_w),
                     _PRE_TAILS + ((3,),))
        dC, W, Rm = np.empty((n, 3, 3)), np.empty((n, 3, 10)), np.empty((n, 3, 10))
        _corrected_rows(*rows, dC, W, Rm)
        d = rows[-1] - rows[-2]
        return dC.reshape(lead + (3, 3)), W.reshape(lead + (3, 10)), Rm.reshape(lead + (3, 10)), d.reshape(lead + (3,))

    def relinearized(self, b_w: np.ndarray) -> "Preintegrated":
        """The same interval(s) integrated again around gyro bias ``b_w``; the covariance is
        kept (it is a factor's noise model and does not move). Works on one interval (no
        leading dimension) or on ``J``."""
        acc, gyro, dt = self.samples
        single = dt.ndim == 1
        if single:
            acc, gyro, dt = acc[None], gyro[None], dt[None]
        b_w = np.broadcast_to(np.asarray(b_w, dtype=float), (len(dt), 3))
        fresh = integrate(acc, gyro, dt, b_w)
        if single:
            fresh = fresh[0]
        fresh.cov = self.cov
        return fresh


#: Row width of the kernel's flat work rows: W, Rm and each slice of their bias Jacobians have
#: 10 columns, held in rows of 12 (three 4-wide SIMD registers) so that every column loop has a
#: compile-time length over contiguous memory, which LLVM turns into SIMD instructions. The rows
#: are slices of ONE work array: LLVM then sees that they cannot overlap, and the 12-wide loops
#: vectorise without run-time overlap checks (as separate arrays, 12-wide rows ran 1.6x slower
#: than 16-wide ones; as slices, 13-20% faster).
_IW = 12


@dataclass(frozen=True)
class Anchors:
    """Known values at the keyframes that reset the dead-reckoned reference trajectory of
    :func:`integrate_with_covariance`: position ``r (J+1, 3)``, attitude ``C (J+1, 3, 3)`` and
    WORLD velocity ``world_v (J+1, 3)``; NaN in a row means unknown (keep the prediction)."""

    r: np.ndarray
    C: np.ndarray
    world_v: np.ndarray

    @staticmethod
    def of_states(states: imu.ImuState) -> "Anchors":
        """Every keyframe anchored at ``states`` (position, attitude and velocity known)."""
        return Anchors(states.r, states.C, states.world_velocity())

    @staticmethod
    def none(n: int) -> "Anchors":
        """``n`` keyframes, none anchored."""
        return Anchors(np.full((n, 3), np.nan), np.full((n, 3, 3), np.nan), np.full((n, 3), np.nan))


@leaf
def _reference_at(j, r, v, C, anchor_r, anchor_C, anchor_v) -> None:
    """The reference state of keyframe ``j``: the prediction ``(r, v, C)`` (in place) replaced
    by the anchors that are known (finite): position, attitude, then body velocity ``C^T v_world``
    with the (possibly replaced) attitude."""
    if np.isfinite(anchor_r[j, 0]):
        for a in range(3):
            r[a] = anchor_r[j, a]
    if np.isfinite(anchor_C[j, 0, 0]):
        for a in range(3):
            for b in range(3):
                C[a, b] = anchor_C[j, a, b]
    if np.isfinite(anchor_v[j, 0]):
        for a in range(3):
            v[a] = C[0, a] * anchor_v[j, 0] + C[1, a] * anchor_v[j, 1] + C[2, a] * anchor_v[j, 2]


@block_operation
def _unit_cross(axis, x0, x1, x2) -> tuple:
    """``e_axis x (x0, x1, x2)`` written out (no products with zero: with ``axis`` a constant the
    branch disappears and the vector has two entries to compute, not six products)."""
    if axis == 0:
        return 0.0, -x2, x1
    if axis == 1:
        return x2, 0.0, -x0
    return -x1, x0, 0.0


@block_operation
def _bias_slice_step(l, h, w0, w1, w2, D, JCj, Wf, dCW, dWf, dRf) -> None:  # noqa: E741 -- the docstring's axis l
    """One sample's step of the gyro-bias Jacobians along bias axis ``l`` (a constant where it is
    inlined), slices ``dW[..., l]``, ``dRm[..., l]`` (rows ``3 l ..`` of ``dWf``, ``dRf``; module
    docstring)::

        dRm[l] += dt ((JC e_l)^x dC W + dC dW[l])            (dW at step k)
        dW[l] <- A dW[l] + dt e_l x W - dt [0 | dC^T (JC e_l)^x | 0 | 0]
    """
    u0, u1, u2 = JCj[0, l], JCj[1, l], JCj[2, l]
    d00, d01, d02, d10, d11, d12, d20, d21, d22 = (D[0, 0], D[0, 1], D[0, 2], D[1, 0], D[1, 1], D[1, 2],
                                                   D[2, 0], D[2, 1], D[2, 2])
    row = 3 * l * _IW
    for c in range(_IW):
        x0, x1, x2 = dCW[c], dCW[_IW + c], dCW[2 * _IW + c]
        y0, y1, y2 = dWf[row + c], dWf[row + _IW + c], dWf[row + 2 * _IW + c]
        dRf[row + c] += h * (u1 * x2 - u2 * x1 + d00 * y0 + d01 * y1 + d02 * y2)
        dRf[row + _IW + c] += h * (u2 * x0 - u0 * x2 + d10 * y0 + d11 * y1 + d12 * y2)
        dRf[row + 2 * _IW + c] += h * (u0 * x1 - u1 * x0 + d20 * y0 + d21 * y1 + d22 * y2)
        c0, c1, c2 = _unit_cross(l, Wf[c], Wf[_IW + c], Wf[2 * _IW + c])
        dWf[row + c] = y0 + h * (c0 - (w1 * y2 - w2 * y1))
        dWf[row + _IW + c] = y1 + h * (c1 - (w2 * y0 - w0 * y2))
        dWf[row + 2 * _IW + c] = y2 + h * (c2 - (w0 * y1 - w1 * y0))
    # dC^T (JC e_l)^x: column m is dC^T (u x e_m) = -dC^T (e_m x u), into columns 3..5
    for m in range(3):
        x0, x1, x2 = _unit_cross(m, u0, u1, u2)
        for a in range(3):
            dWf[row + a * _IW + 3 + m] += h * (D[0, a] * x0 + D[1, a] * x1 + D[2, a] * x2)


@recursion
def _integrate_kernel(acc, gyro, dt, b_w_bar, lo, hi, dC, W, Rm, JC, dW, dRm):
    """The recursions of the module docstring with the gyro-bias Jacobians ``JC, dW, dRm``, for
    intervals ``lo <= j < hi``, sample by sample, into the outputs' rows ``lo .. hi - 1`` (whatever
    they held before). Intervals do not depend on each other, so disjoint ranges can run on
    different threads.

    Layout: ``W``, ``Rm`` and the slices ``dW[..., l]``, ``dRm[..., l]`` live in flat rows of
    ``_IW`` columns while an interval is integrated (row ``a`` of ``W``; row ``3 l + a`` of
    ``dW``), and every update is a column loop; ``A x = x - dt w x x`` is applied as a cross
    product. ``dC`` and ``JC`` of the interval live in the same work array (copied out at its
    end), so LLVM knows that no store into one of them changes another. Samples with ``dt = 0``
    are identity steps and skipped."""
    rows = np.empty(27 * _IW + 27)  # one array (see _IW)
    Wf, Rf, dCW = rows[:3 * _IW], rows[3 * _IW:6 * _IW], rows[6 * _IW:9 * _IW]
    dWf, dRf = rows[9 * _IW:18 * _IW], rows[18 * _IW:27 * _IW]
    D = rows[27 * _IW:27 * _IW + 9].reshape((3, 3))
    JCj = rows[27 * _IW + 9:27 * _IW + 18].reshape((3, 3))
    tmp = rows[27 * _IW + 18:].reshape((3, 3))
    for j in range(lo, hi):
        rows[:] = 0.0  # W_0 = [I | 0 | 0 | 0], Rm_0 = 0, dW_0 = dRm_0 = 0, dC_0 = I, JC_0 = 0
        for a in range(3):
            Wf[a * _IW + a] = 1.0
            D[a, a] = 1.0
        for k in range(dt.shape[1]):
            h = dt[j, k]
            if h <= 0.0:
                continue
            w0, w1, w2 = gyro[j, k, 0] - b_w_bar[j, 0], gyro[j, k, 1] - b_w_bar[j, 1], gyro[j, k, 2] - b_w_bar[j, 2]
            Em, Gm = so3.exp_and_gamma_entries(h * w0, h * w1, h * w2)  # row-major entries
            d00, d01, d02, d10, d11, d12, d20, d21, d22 = (D[0, 0], D[0, 1], D[0, 2], D[1, 0], D[1, 1], D[1, 2],
                                                           D[2, 0], D[2, 1], D[2, 2])
            for c in range(_IW):  # dC W
                x0, x1, x2 = Wf[c], Wf[_IW + c], Wf[2 * _IW + c]
                dCW[c] = d00 * x0 + d01 * x1 + d02 * x2
                dCW[_IW + c] = d10 * x0 + d11 * x1 + d12 * x2
                dCW[2 * _IW + c] = d20 * x0 + d21 * x1 + d22 * x2
            # the three bias axes, each inlined with its axis a constant
            _bias_slice_step(0, h, w0, w1, w2, D, JCj, Wf, dCW, dWf, dRf)
            _bias_slice_step(1, h, w0, w1, w2, D, JCj, Wf, dCW, dWf, dRf)
            _bias_slice_step(2, h, w0, w1, w2, D, JCj, Wf, dCW, dWf, dRf)
            # Rm += dt dC W;  W <- A W + dt [0 | dC^T | f~ | I]
            for c in range(_IW):
                x0, x1, x2 = Wf[c], Wf[_IW + c], Wf[2 * _IW + c]
                Rf[c] += h * dCW[c]
                Rf[_IW + c] += h * dCW[_IW + c]
                Rf[2 * _IW + c] += h * dCW[2 * _IW + c]
                Wf[c] = x0 - h * (w1 * x2 - w2 * x1)
                Wf[_IW + c] = x1 - h * (w2 * x0 - w0 * x2)
                Wf[2 * _IW + c] = x2 - h * (w0 * x1 - w1 * x0)
            for a in range(3):
                for b in range(3):
                    Wf[a * _IW + 3 + b] += h * D[b, a]
                Wf[a * _IW + 6] += h * acc[j, k, a]
                Wf[a * _IW + 7 + a] += h
            # JC <- JC - dt dC Gamma(dt w);  dC <- dC exp(dt w)
            for a in range(3):
                for b in range(3):
                    JCj[a, b] -= h * (D[a, 0] * Gm[b] + D[a, 1] * Gm[3 + b] + D[a, 2] * Gm[6 + b])
                    tmp[a, b] = D[a, 0] * Em[b] + D[a, 1] * Em[3 + b] + D[a, 2] * Em[6 + b]
            for a in range(3):
                for b in range(3):
                    D[a, b] = tmp[a, b]
        for a in range(3):
            for b in range(3):
                dC[j, a, b], JC[j, a, b] = D[a, b], JCj[a, b]
            for c in range(10):
                W[j, a, c], Rm[j, a, c] = Wf[a * _IW + c], Rf[a * _IW + c]
                for l in range(3):  # noqa: E741 -- the bias axis l of the module docstring
                    dW[j, a, c, l], dRm[j, a, c, l] = dWf[(3 * l + a) * _IW + c], dRf[(3 * l + a) * _IW + c]


@recursion
def _reference_chain(dC, W, Rm, b_f, anchor_r, anchor_C, anchor_v, g, lo, hi, ref_r, ref_v, ref_C):
    """The reference states ``ref_* [j + 1]`` at keyframes ``j + 1`` for ``lo <= j < hi``: the
    prediction from keyframe ``j`` (``ref_*[j]``, which must be set) through the integrated
    interval ``j`` (module docstring: ``r + C Rm z``, ``W z``, ``C dC``), replaced by the known
    anchors (:func:`_reference_at`). Sequential, but a few operations per interval."""
    work = np.empty(3 + 3 + 9 + 9 + 10 + 3)  # views made once: the loop touches scalars only (views and
    # slice assignments inside it, with their reference counting, made the chain 5x slower)
    r, v, z, u = work[:3], work[3:6], work[24:34], work[34:]
    C, tmp = work[6:15].reshape((3, 3)), work[15:24].reshape((3, 3))
    z[6] = 1.0
    for j in range(lo, hi):
        for a in range(3):
            r[a], v[a] = ref_r[j, a], ref_v[j, a]
            for b in range(3):
                C[a, b] = ref_C[j, a, b]
        for a in range(3):
            z[a], z[3 + a], z[7 + a] = v[a], C[0, a] * g[0] + C[1, a] * g[1] + C[2, a] * g[2], -b_f[j, a]
        for a in range(3):
            rz, wz = 0.0, 0.0
            for c in range(10):
                rz += Rm[j, a, c] * z[c]
                wz += W[j, a, c] * z[c]
            u[a], v[a] = rz, wz
        for a in range(3):
            r[a] += C[a, 0] * u[0] + C[a, 1] * u[1] + C[a, 2] * u[2]
            for b in range(3):
                tmp[a, b] = C[a, 0] * dC[j, 0, b] + C[a, 1] * dC[j, 1, b] + C[a, 2] * dC[j, 2, b]
        _reference_at(j + 1, r, v, tmp, anchor_r, anchor_C, anchor_v)
        for a in range(3):
            ref_r[j + 1, a], ref_v[j + 1, a] = r[a], v[a]
            for b in range(3):
                ref_C[j + 1, a, b] = tmp[a, b]


@recursion
def _covariance_kernel(acc, gyro, dt, b_w_bar, b_f, ref_v, ref_C, g, q, floor, lo, hi, S):
    """The covariance ``S[j]`` of intervals ``lo <= j < hi``: the EKF's prediction
    (:func:`factors.imu.predict_flat`, ``S <- F S F^T + G Q_d G^T`` from ``S = 0``) along the
    reference trajectory from ``ref_v[j], ref_C[j]``, run directly in the residual's body-``i``
    coordinates: the primer's model is invariant under a rotation of the world, so starting at
    attitude ``I`` with gravity ``gamma = C_i^T g`` steps through ``dC_k`` in place of ``C_k``, and
    ``F``, ``G`` are ``T F T^-1`` and ``T G`` of the world-frame step (``T = diag(C_i^T, I,
    C_i^T, I, I)``): ``S`` is the world-frame covariance ``T S T^T`` without a rotation pass.
    ``floor`` is added on the diagonal. Intervals are independent given the reference."""
    r, v, C, gamma = np.empty(3), np.empty(3), np.empty((3, 3)), np.empty(3)
    work = imu.prediction_work()
    for j in range(lo, hi):
        for a in range(3):
            gamma[a] = ref_C[j, 0, a] * g[0] + ref_C[j, 1, a] * g[1] + ref_C[j, 2, a] * g[2]
            r[a], v[a] = 0.0, ref_v[j, a]
            for b in range(3):
                C[a, b] = 1.0 if a == b else 0.0
        imu.clear_flat(work)
        imu.predict_flat(r, v, C, b_f[j], b_w_bar[j], acc[j], gyro[j], dt[j], q, gamma, work)
        imu.symmetric_from_flat(work, S[j], floor)


def _kernel_array(a, lead: tuple, tail: tuple, name: str, broadcast: bool = True) -> np.ndarray:
    """``a`` of trailing shape ``tail`` (checked), its leading dimensions broadcast to ``lead``
    (with ``broadcast``; else they must be ``lead``), C-contiguous and writable, so the kernel is
    compiled (and cached) for one layout only: ``a`` itself when it already is that (the kernels
    only read their inputs), else a copy. A ValueError names ``name`` otherwise."""
    a = as_trailing(a, tail, name)
    shape = tuple(lead) + tuple(tail)
    if a.shape == shape:
        return np.require(a, float, ["C", "W"])
    if not broadcast:
        raise InputError(f"{name}: expected shape {shape}, got {a.shape}")
    out = np.empty(shape)
    try:
        out[...] = a  # broadcasts, as np.broadcast_to would, at a fraction of its cost
    except ValueError:
        raise InputError(f"{name}: expected shape {shape} (or one that broadcasts to it), got {a.shape}") from None
    return out


#: Fewest intervals worth handing to a thread of their own (~0.2 ms of work; a hand-over costs
#: tens of microseconds): shorter runs, such as one new keyframe, stay on the calling thread.
_MIN_INTERVALS_PER_THREAD = 32


def _ready_samples(acc, gyro, dt, b_w_bar, bias_name: str) -> tuple:
    """The samples and gyro biases checked (shapes; finite biases, named ``bias_name`` in the
    error) and laid out for the kernels: ``(acc, gyro, dt, b_w_bar)``, the samples as given when
    they already are float and C-contiguous (the kernels only read them; :func:`_integration`
    copies them)."""
    acc, gyro = as_trailing(acc, (3,), "acc"), as_trailing(gyro, (3,), "gyro")
    dt = np.asarray(dt, dtype=float)
    if dt.ndim != 2 or acc.shape != dt.shape + (3,) or gyro.shape != dt.shape + (3,):
        raise InputError(f"expected acc, gyro (J, K, 3) and dt (J, K), got {acc.shape}, {gyro.shape}, {dt.shape}")
    b_w_bar = _kernel_array(b_w_bar, (dt.shape[0],), (3,), bias_name)
    if not np.isfinite(b_w_bar).all():
        raise InputError(f"{bias_name}: expected finite values, got {b_w_bar.tolist()}")
    return np.require(acc, float, "C"), np.require(gyro, float, "C"), np.require(dt, float, "C"), b_w_bar


def _unfilled(samples: tuple, b_w_bar: np.ndarray) -> Preintegrated:
    """A :class:`Preintegrated` of the padded ``samples = (acc, gyro, dt)`` (kept as given) around
    ``b_w_bar``, its arrays allocated for the kernels to fill (no covariance)."""
    J = samples[2].shape[0]
    return Preintegrated(np.empty((J, 3, 3)), np.empty((J, 3, 10)), np.empty((J, 3, 10)), np.empty((J, 3, 3)),
                         np.empty((J, 3, 10, 3)), np.empty((J, 3, 10, 3)), b_w_bar, samples)


def _integration(acc, gyro, dt, b_w_bar) -> tuple:
    """``(pre, task)``: a :class:`Preintegrated` of samples from :func:`_ready_samples` whose
    arrays are allocated but not filled (the covariance unset), and ``task(lo, hi)``, which fills
    intervals ``lo .. hi - 1``: it copies their samples into ``pre.samples`` (:class:`Preintegrated`
    keeps them for re-integration, so they must not change with the caller's arrays; copied range
    by range, the copy is shared among the threads) and integrates them (:func:`_integrate_kernel`)."""
    own = np.empty_like(acc), np.empty_like(gyro), np.empty_like(dt)
    pre = _unfilled(own, b_w_bar.copy())

    def task(lo: int, hi: int) -> None:
        for mine, given in zip(own, (acc, gyro, dt)):
            mine[lo:hi] = given[lo:hi]
        _integrate_kernel(*own, pre.b_w_bar, lo, hi, pre.dC, pre.W, pre.Rm, pre.JC, pre.dW, pre.dRm)

    return pre, task


def _run(acc, gyro, dt, b_w_bar, b_f, start, anchors, noise, gravity):
    """Check and lay out the inputs (the samples first); then, in one :func:`in_parallel` pass
    over the intervals, integrate them (:func:`_integration`), chain the reference states
    (:func:`_reference_chain`, in order) and compute the covariances along them
    (:func:`_covariance_kernel`); returns ``(Preintegrated, reference states (J+1))``.
    ``anchors`` None: none."""
    acc, gyro, dt, b_w_bar = _ready_samples(acc, gyro, dt, b_w_bar, "start.b_w")
    J = dt.shape[0]
    anchors = anchors if anchors is not None else Anchors.none(J + 1)
    ready = _kernel_array
    b_f = ready(b_f, (J,), (3,), "b_f")
    g = ready(gravity, (), (3,), "gravity", broadcast=False)
    anchor_r, anchor_C, anchor_v = (ready(a, (J + 1,), tail, "anchors." + name, broadcast=False) for a, tail, name in (
        (anchors.r, (3,), "r"), (anchors.C, (3, 3), "C"), (anchors.world_v, (3,), "world_v")))
    if start.shape != ():
        raise InputError(f"start: expected one state, got states of shape {start.shape}")
    r0, v0, C0 = (ready(a, (), tail, "start." + name, broadcast=False)
                  for a, tail, name in ((start.r, (3,), "r"), (start.v, (3,), "v"), (start.C, (3, 3), "C")))
    for name, a in (("r", r0), ("v", v0), ("C", C0), ("b_f", b_f)):
        if not np.isfinite(a).all():
            raise InputError(f"start.{name} (or the biases given): expected finite values, got {a.tolist()}")
    for name, a in (("r", anchor_r), ("C", anchor_C), ("world_v", anchor_v)):
        finite = np.isfinite(a.reshape(J + 1, -1))
        if finite.all() or not finite.any():  # every keyframe known, or none: no row to check
            continue
        partial = np.flatnonzero(finite.any(axis=1) & ~finite.all(axis=1))
        if partial.size:
            raise InputError(f"anchors.{name}[{partial[0]}]: expected all finite (known) or all NaN (unknown), "
                             f"got {a[partial[0]].tolist()}")
    pre, integrate_task = _integration(acc, gyro, dt, b_w_bar)
    ref_r, ref_v, ref_C = np.empty((J + 1, 3)), np.empty((J + 1, 3)), np.empty((J + 1, 3, 3))
    ref_r[0], ref_v[0], ref_C[0] = r0, v0, C0
    _reference_at(0, ref_r[0], ref_v[0], ref_C[0], anchor_r, anchor_C, anchor_v)
    pre.cov = np.empty((J, imu.STATE_DIM, imu.STATE_DIM))
    q, floor, (acc, gyro, dt), b_w = noise.densities(), COVARIANCE_FLOOR**2, pre.samples, pre.b_w_bar
    in_parallel(integrate_task, J, _MIN_INTERVALS_PER_THREAD,
                scan=lambda lo, hi: _reference_chain(pre.dC, pre.W, pre.Rm, b_f, anchor_r, anchor_C, anchor_v, g, lo,
                                                     hi, ref_r, ref_v, ref_C),
                then=lambda lo, hi: _covariance_kernel(acc, gyro, dt, b_w, b_f, ref_v, ref_C, g, q, floor, lo, hi,
                                                       pre.cov))
    last = lambda a: np.concatenate([a, a[-1:]])  # noqa: E731  (the last keyframe keeps the last biases)
    return pre, imu.ImuState(ref_r, ref_v, ref_C, last(b_f), last(b_w))


def integrate(acc, gyro, dt, b_w_bar) -> Preintegrated:
    """Preintegrate ``J`` intervals of padded samples ``acc, gyro (J, K, 3)``, ``dt (J, K)``
    around gyro biases ``b_w_bar (J, 3)``, with the bias Jacobians, without the covariance (see
    :func:`integrate_with_covariance`). Compiled, on several cores when there are many intervals."""
    pre, task = _integration(*_ready_samples(acc, gyro, dt, b_w_bar, "b_w_bar"))
    in_parallel(task, len(pre), _MIN_INTERVALS_PER_THREAD)
    return pre


def integrate_with_covariance(samples: tuple, start: imu.ImuState, noise: imu.ImuNoise,
                              gravity=imu.DEFAULT_GRAVITY, anchors: Anchors | None = None, biases: tuple | None = None):
    """Preintegrate ``J`` padded intervals ``samples = (acc, gyro, dt)`` around the biases of
    ``start`` (one state), or around ``biases = (b_f, b_w)`` (``(J, 3)`` each, one pair per
    interval), with the bias Jacobians AND the residual covariance of every interval
    (see :func:`noise_covariance`); returns ``(pre, states)``. One compiled pipeline (module
    docstring), on several cores when there are many intervals.

    The covariance of interval ``i`` is evaluated along the reference trajectory from keyframe
    state ``states[i]``: ``states[0]`` is ``start``, ``states[i + 1]`` the prediction from
    ``states[i]`` (:func:`predict`), each (``states[0]`` too) replaced where ``anchors`` (``J + 1``
    keyframes, default none) knows the position, attitude or world velocity -- dead reckoning
    reset by measurements, the smoother's initial trajectory. ``states`` keeps the biases
    integrated around (the last keyframe those of the last interval)."""
    acc, gyro, dt = samples
    b_f, b_w = (start.b_f, start.b_w) if biases is None else biases
    return _run(acc, gyro, dt, b_w, b_f, start, anchors, noise, gravity)


def integrate_interval(acc, gyro, dt, start: imu.ImuState, noise: imu.ImuNoise, gravity) -> tuple:
    """One interval of samples ``acc, gyro (K, 3)``, ``dt (K,)`` preintegrated around the biases
    of ``start`` with its covariance along ``start`` -- what :func:`integrate_with_covariance`
    gives for ``J = 1`` without anchors, as one interval (no leading dimension) -- and the state
    :func:`predict` gives from ``start`` through it: ``(Preintegrated, ImuState)``, the same kernels
    in one compiled call (:func:`_interval_kernel`) without the checks: the per-keyframe path of an
    online smoother, whose samples and states are checked where they enter. Float arrays, finite,
    as documented there; the samples are copied (the interval keeps them to integrate again)."""
    acc, gyro, dt = (np.array(a, dtype=float, order="C")[None] for a in (acc, gyro, dt))
    pre = _unfilled((acc, gyro, dt), np.array(start.b_w, dtype=float, order="C")[None])
    pre.cov = np.empty((1, imu.STATE_DIM, imu.STATE_DIM))
    r, v, C = np.empty((1, 3)), np.empty((1, 3)), np.empty((1, 3, 3))
    own = lambda a: np.array(a, dtype=float, order="C")  # noqa: E731  (the kernels' one layout)
    _interval_kernel(acc, gyro, dt, pre.b_w_bar, own(start.b_f)[None], own(start.r)[None], own(start.v)[None],
                     own(start.C)[None], own(gravity), noise.densities(),
                     COVARIANCE_FLOOR**2, pre.dC, pre.W, pre.Rm, pre.JC, pre.dW, pre.dRm, pre.cov, r, v, C)
    return pre[0], imu.ImuState(r[0], v[0], C[0], np.array(start.b_f, dtype=float), pre.b_w_bar[0].copy())


@recursion
def _interval_kernel(acc, gyro, dt, b_w_bar, b_f, r0, v0, C0, g, q, floor, dC, W, Rm, JC, dW, dRm, cov, r, v, C):
    """:func:`integrate_interval`'s one compiled call over one interval (leading dimension 1):
    :func:`_integrate_kernel`, :func:`_covariance_kernel` along the start ``(r0, v0, C0)`` and
    :func:`_predict_rows` from it (biases ``b_f``, ``b_w_bar``) into ``r, v, C``. The interval range
    is run-time integers, so these are the copies of the kernels that :func:`_run` calls (literal
    ``0, 1`` would compile a second copy of each)."""
    lo, hi = np.int64(0), np.int64(1)
    _integrate_kernel(acc, gyro, dt, b_w_bar, lo, hi, dC, W, Rm, JC, dW, dRm)
    _covariance_kernel(acc, gyro, dt, b_w_bar, b_f, v0, C0, g, q, floor, lo, hi, cov)
    no_jacobian = np.bool_(False)
    _predict_rows(dC, W, Rm, JC, dW, dRm, b_w_bar, r0, v0, C0, b_f, b_w_bar, g, r, v, C, no_jacobian,
                  np.empty((1, imu.STATE_DIM, imu.STATE_DIM)))


def noise_covariance(samples: tuple, reference: imu.ImuState, noise: imu.ImuNoise,
                     gravity=imu.DEFAULT_GRAVITY) -> np.ndarray:
    """Covariance ``(J, 15, 15)`` of the IMU residual of ``J`` padded intervals ``samples = (acc,
    gyro, dt)``: the primer's ``F`` and ``G`` propagated along the trajectory that starts at the
    ``reference`` states (leading dimension ``J``) with zero covariance,
    ``S <- F S F^T + G Q_d G^T`` -- the EKF's own covariance growth over the interval -- in the
    residual's body-``i`` coordinates, ``T S T^T`` with ``T = diag(C_i^T, I, C_i^T, I, I)``.

    A floor of ``COVARIANCE_FLOOR^2`` is added on the diagonal: without the velocity noise
    ``n_v`` the position of a one-sample interval is deterministic (``r_j = r_i + dt C_i v_i``),
    and a zero variance would make the factor's noise model singular. The floor stands for the
    model's own discretisation error and is far below any sensor's noise."""
    acc, gyro, dt = samples
    J = np.shape(dt)[0]
    lead = (J,)
    r, v, C, b_f, b_w = rows_of(lead, (reference.r, reference.v, reference.C, reference.b_f, reference.b_w),
                                _STATE_TAILS)
    for name, a in (("r", r), ("v", v), ("C", C), ("b_f", b_f), ("b_w", b_w)):
        bad = np.flatnonzero(~np.isfinite(a.reshape(J, -1)).all(axis=1))
        if bad.size:  # NaN would read as "unknown" in the anchors below
            raise InputError(f"reference.{name}[{bad[0]}]: expected finite values, got {a[bad[0]].tolist()}")
    unknown = Anchors.none(1)  # keyframe J: not needed
    anchors = Anchors(np.concatenate([r, unknown.r]), np.concatenate([C, unknown.C]),
                      np.concatenate([np.einsum("jab,jb->ja", C, v), unknown.world_v]))
    start = imu.ImuState(r[0], v[0], C[0], b_f[0], b_w[0])  # every interval is anchored: start unused
    pre, _ = _run(acc, gyro, dt, b_w, b_f, start, anchors, noise, gravity)
    return pre.cov


def predict(pre: Preintegrated, state_i: imu.ImuState, gravity=imu.DEFAULT_GRAVITY, jacobians: bool = False):
    """The state at keyframe ``j`` predicted from ``state_i`` (biases held constant): exactly the
    sample-by-sample Euler-forward propagation when ``state_i.b_w == b_w_bar``, first order in
    the gyro-bias offset otherwise (module docstring: ``r_i + C_i Rm z``, ``W z``, ``C_i dC`` of the
    corrected quantities). Vectorised over the intervals and states (broadcast); compiled
    (:func:`_predict_into`). With ``jacobians``: ``(state, J)``, ``J (..., 15, 15)`` the
    prediction's Jacobian with respect to ``state_i``'s error state
    (:func:`prediction_jacobian_into`)."""
    lead = common_shape(pre.b_w_bar.shape[:-1], state_i.shape)
    n = math.prod(lead)
    args = (rows_of(lead, (pre.dC, pre.W, pre.Rm, pre.JC, pre.dW, pre.dRm, pre.b_w_bar), _PRE_TAILS)
            + rows_of(lead, [getattr(state_i, f) for f in ("r", "v", "C", "b_f", "b_w")], _STATE_TAILS))
    r, v, C = np.empty((n, 3)), np.empty((n, 3)), np.empty((n, 3, 3))
    J = np.empty((n if jacobians else 1, imu.STATE_DIM, imu.STATE_DIM))
    _predict_rows(*args, as_trailing(gravity, (3,), "gravity"), r, v, C, np.bool_(jacobians), J)
    b_f, b_w = args[-2:]
    state = imu.ImuState(r.reshape(lead + (3,)), v.reshape(lead + (3,)), C.reshape(lead + (3, 3)),
                         b_f.reshape(lead + (3,)).copy(), b_w.reshape(lead + (3,)).copy())
    return (state, J.reshape(lead + (imu.STATE_DIM, imu.STATE_DIM))) if jacobians else state


#: Trailing shapes of the Preintegrated fields a residual reads, and of an ImuState's fields.
_PRE_TAILS = ((3, 3), (3, 10), (3, 10), (3, 3), (3, 10, 3), (3, 10, 3), (3,))
_STATE_TAILS = ((3,), (3,), (3, 3), (3,), (3,))


@leaf
def _correct(dC, W, Rm, JC, dW, dRm, b_w_bar, b_w, dC_out, W_out, Rm_out, JCd, E) -> None:
    """First-order gyro-bias correction of one interval: ``W + dW . d``, ``Rm + dRm . d``,
    ``exp(JC d) dC`` with ``d = b_w - b_w_bar``; ``JC d`` into ``JCd`` (3), ``E`` a 3x3 work array."""
    d0, d1, d2 = b_w[0] - b_w_bar[0], b_w[1] - b_w_bar[1], b_w[2] - b_w_bar[2]
    for a in range(3):
        for c in range(10):
            W_out[a, c] = W[a, c] + dW[a, c, 0] * d0 + dW[a, c, 1] * d1 + dW[a, c, 2] * d2
            Rm_out[a, c] = Rm[a, c] + dRm[a, c, 0] * d0 + dRm[a, c, 1] * d1 + dRm[a, c, 2] * d2
        JCd[a] = JC[a, 0] * d0 + JC[a, 1] * d1 + JC[a, 2] * d2
    so3.exp_into(JCd[0], JCd[1], JCd[2], E)
    matmul_into(E, dC, dC_out)


@recursion
def _corrected_rows(dC, W, Rm, JC, dW, dRm, b_w_bar, b_w, dC_out, W_out, Rm_out):
    JCd, E = np.empty(3), np.empty((3, 3))
    for n in range(dC.shape[0]):
        _correct(dC[n], W[n], Rm[n], JC[n], dW[n], dRm[n], b_w_bar[n], b_w[n], dC_out[n], W_out[n], Rm_out[n], JCd, E)


@leaf
def _predict_into(dC0, W0, Rm0, JC, dW, dRm, b_w_bar, ri, vi, Ci, bfi, bwi, g, r, v, C, work) -> None:
    """:func:`predict` of one interval into ``r, v, C``; ``work`` from :func:`residual_work`."""
    dC, W, Rm, E, z, JCd, u = work[0], work[1], work[2], work[3], work[7], work[8], work[9]
    _correct(dC0, W0, Rm0, JC, dW, dRm, b_w_bar, bwi, dC, W, Rm, JCd, E)
    for a in range(3):
        z[a], z[3 + a], z[7 + a] = vi[a], Ci[0, a] * g[0] + Ci[1, a] * g[1] + Ci[2, a] * g[2], -bfi[a]
    z[6] = 1.0
    for a in range(3):
        rz, wz = 0.0, 0.0
        for c in range(10):
            rz += Rm[a, c] * z[c]
            wz += W[a, c] * z[c]
        u[a], v[a] = rz, wz
    for a in range(3):
        r[a] = ri[a] + Ci[a, 0] * u[0] + Ci[a, 1] * u[1] + Ci[a, 2] * u[2]
    matmul_into(Ci, dC, C)


@leaf
def prediction_jacobian_into(Ci, W, Rm, JC, dW, dRm, JCd, z, u, E, Y, J) -> None:
    """The Jacobian ``J (15, 15)`` of :func:`predict`'s state ``x_j`` with respect to the error
    state ``(dr, dv, dphi, db_f, db_w)`` of ``x_i`` (LEFT increment ``C_i <- exp(dphi) C_i``), from
    what :func:`_predict_into` leaves: the corrected ``W``, ``Rm``, ``JCd = JC d``, ``z = (v_i,
    gamma, 1, -b_f)`` and ``u = Rm z`` (``E``, ``Y`` 3x3 work arrays). With ``r_j = r_i + C_i u``,
    ``v_j = W z``, ``C_j = C_i exp(JC d) dC`` and the biases held::

        d(C_i u)/dphi = -(C_i u)^x          exp(dphi) C_i u = C_i u + dphi x C_i u   (eqs. 3, 27)
        d gamma/dphi  = gamma^x C_i^T       C_i^T exp(-dphi) g = gamma + C_i^T (g x dphi)
        r_j: dr I, dv C_i Rm_v, dphi -(C_i u)^x + C_i Rm_g gamma^x C_i^T, db_f -C_i Rm_b, db_w C_i (dRm . z)
        v_j: dv W_v, dphi W_g gamma^x C_i^T, db_f -W_b, db_w dW . z
        C_j: dphi I, db_w C_i Gamma(JC d) JC     exp(JC (d + e)) = exp(Gamma(JC d) JC e) exp(JC d)  (eq. 31)
        b_f, b_w: I

    (``Rm_v, Rm_g, Rm_b``: the columns of ``Rm`` acting on ``v_i``, ``gamma`` and ``-b_f``; the
    bias Jacobians ``dW``, ``dRm`` contracted with ``z`` over their columns; the gyro-bias
    offset's derivative of the corrected ``W z``, ``Rm z`` is ``dW . z``, ``dRm . z`` exactly.)"""
    for a in range(15):
        for b in range(15):
            J[a, b] = 0.0
    for a in range(15):
        if a < 3 or a >= 6:
            J[a, a] = 1.0
    g0, g1, g2 = z[3], z[4], z[5]
    for a in range(3):
        # row a of Rm_g gamma^x and W_g gamma^x: (m x gamma) for the row m of Rm_g, W_g
        m0, m1, m2 = Rm[a, 3], Rm[a, 4], Rm[a, 5]
        E[a, 0], E[a, 1], E[a, 2] = m1 * g2 - m2 * g1, m2 * g0 - m0 * g2, m0 * g1 - m1 * g0
        m0, m1, m2 = W[a, 3], W[a, 4], W[a, 5]
        Y[a, 0], Y[a, 1], Y[a, 2] = m1 * g2 - m2 * g1, m2 * g0 - m0 * g2, m0 * g1 - m1 * g0
        for c in range(3):
            J[3 + a, 3 + c] = W[a, c]
            J[3 + a, 9 + c] = -W[a, 7 + c]
            sv = 0.0
            for m in range(10):
                sv += dW[a, m, c] * z[m]
            J[3 + a, 12 + c] = sv
    for a in range(3):
        for c in range(3):
            # v_j's attitude column: W_g gamma^x C_i^T
            J[3 + a, 6 + c] = Y[a, 0] * Ci[c, 0] + Y[a, 1] * Ci[c, 1] + Y[a, 2] * Ci[c, 2]
    for a in range(3):
        for c in range(3):
            crv, crb, crz, cg = 0.0, 0.0, 0.0, 0.0
            for m in range(3):
                crv += Ci[a, m] * Rm[m, c]
                crb += Ci[a, m] * Rm[m, 7 + c]
                cg += Ci[a, m] * E[m, c]
                s = 0.0
                for q in range(10):
                    s += dRm[m, q, c] * z[q]
                crz += Ci[a, m] * s
            J[a, 3 + c] = crv
            J[a, 9 + c] = -crb
            J[a, 12 + c] = crz
            Y[a, c] = cg  # C_i Rm_g gamma^x
    for a in range(3):
        for c in range(3):
            J[a, 6 + c] = Y[a, 0] * Ci[c, 0] + Y[a, 1] * Ci[c, 1] + Y[a, 2] * Ci[c, 2]
    # -(C_i u)^x
    w0 = Ci[0, 0] * u[0] + Ci[0, 1] * u[1] + Ci[0, 2] * u[2]
    w1 = Ci[1, 0] * u[0] + Ci[1, 1] * u[1] + Ci[1, 2] * u[2]
    w2 = Ci[2, 0] * u[0] + Ci[2, 1] * u[1] + Ci[2, 2] * u[2]
    J[0, 7] += w2
    J[0, 8] -= w1
    J[1, 6] -= w2
    J[1, 8] += w0
    J[2, 6] += w1
    J[2, 7] -= w0
    # C_i Gamma(JC d) JC
    so3.gamma_into(JCd[0], JCd[1], JCd[2], E)
    matmul_into(E, JC, Y)
    matmul_into(Ci, Y, E)
    for a in range(3):
        for c in range(3):
            J[6 + a, 12 + c] = E[a, c]


@recursion
def _predict_rows(dC0, W0, Rm0, JC, dW, dRm, b_w_bar, ri, vi, Ci, bfi, bwi, g, r, v, C, jacobians, J):
    work = residual_work()
    for n in range(dC0.shape[0]):
        _predict_into(dC0[n], W0[n], Rm0[n], JC[n], dW[n], dRm[n], b_w_bar[n], ri[n], vi[n], Ci[n], bfi[n], bwi[n],
                      g, r[n], v[n], C[n], work)
        if jacobians:
            prediction_jacobian_into(Ci[n], work[1], work[2], JC[n], dW[n], dRm[n], work[8], work[7], work[9],
                                     work[3], work[4], J[n])


@recursion
def residual_work() -> tuple:
    """Work arrays of :func:`residual_into`; allocate once per batch, reuse for every row."""
    return (np.empty((3, 3)), np.empty((3, 10)), np.empty((3, 10)), np.empty((3, 3)), np.empty((3, 3)),
            np.empty((3, 3)), np.empty((3, 3)), np.empty(10), np.empty(3), np.empty(3), np.empty(3), np.empty(3))


@leaf
def residual_into(dC0, W0, Rm0, JC, dW, dRm, b_w_bar, ri, vi, Ci, bfi, bwi, rj, vj, Cj, bfj, bwj, g,
                   jacobians, e, A, B, work) -> None:
    """:func:`residual` of one interval (see its docstring for every formula): ``e`` (15) and,
    with ``jacobians``, ``A = Ji``, ``B = Jj`` (15x15); ``work`` from :func:`residual_work`."""
    dC, W, Rm, E, X, Y, M, z, JCd, u, gamma, dr = work
    _correct(dC0, W0, Rm0, JC, dW, dRm, b_w_bar, bwi, dC, W, Rm, JCd, E)
    C = Ci
    for a in range(3):
        dr[a] = rj[a] - ri[a]
    for a in range(3):
        gamma[a] = C[0, a] * g[0] + C[1, a] * g[1] + C[2, a] * g[2]
        u[a] = C[0, a] * dr[0] + C[1, a] * dr[1] + C[2, a] * dr[2]
        z[a], z[3 + a], z[7 + a] = vi[a], gamma[a], -bfi[a]
    z[6] = 1.0
    # X = C_i^T C_j dC^T
    for a in range(3):
        for b in range(3):
            Y[a, b] = C[0, a] * Cj[0, b] + C[1, a] * Cj[1, b] + C[2, a] * Cj[2, b]
    for a in range(3):
        for b in range(3):
            X[a, b] = Y[a, 0] * dC[b, 0] + Y[a, 1] * dC[b, 1] + Y[a, 2] * dC[b, 2]
    p0, p1, p2 = so3.log_of(X)
    for a in range(3):
        rz, wz = 0.0, 0.0
        for c in range(10):
            rz += Rm[a, c] * z[c]
            wz += W[a, c] * z[c]
        e[a] = u[a] - rz
        e[3 + a] = vj[a] - wz
        e[9 + a] = bfj[a] - bfi[a]
        e[12 + a] = bwj[a] - bwi[a]
    e[6], e[7], e[8] = p0, p1, p2
    if not jacobians:
        return
    A[:, :] = 0.0
    B[:, :] = 0.0
    so3.gamma_inv_into(p0, p1, p2, M)  # Gamma^-1(e_phi)
    for a in range(3):
        A[9 + a, 9 + a] = A[12 + a, 12 + a] = -1.0
        B[9 + a, 9 + a] = B[12 + a, 12 + a] = B[3 + a, 3 + a] = 1.0
        for b in range(3):
            A[a, b] = -C[b, a]
            B[a, b] = C[b, a]
            A[a, 3 + b] = -Rm[a, b]
            A[a, 9 + b] = Rm[a, 7 + b]
            A[3 + a, 3 + b] = -W[a, b]
            A[3 + a, 9 + b] = W[a, 7 + b]
            # Gamma^-1 C_i^T into the attitude rows
            gc = M[a, 0] * C[b, 0] + M[a, 1] * C[b, 1] + M[a, 2] * C[b, 2]
            B[6 + a, 6 + b] = gc
            A[6 + a, 6 + b] = -gc
            sr, sv = 0.0, 0.0
            for c in range(10):
                sr += dRm[a, c, b] * z[c]
                sv += dW[a, c, b] * z[c]
            A[a, 12 + b] = -sr
            A[3 + a, 12 + b] = -sv
    # attitude columns of the r and v rows: u^x C_i^T - Rm_g gamma^x C_i^T, -W_g gamma^x C_i^T
    for b in range(3):
        c0, c1, c2 = C[b, 0], C[b, 1], C[b, 2]  # column b of C_i^T
        x0, x1, x2 = gamma[1] * c2 - gamma[2] * c1, gamma[2] * c0 - gamma[0] * c2, gamma[0] * c1 - gamma[1] * c0
        y0, y1, y2 = u[1] * c2 - u[2] * c1, u[2] * c0 - u[0] * c2, u[0] * c1 - u[1] * c0
        for a in range(3):
            A[a, 6 + b] = (y0, y1, y2)[a] - (Rm[a, 3] * x0 + Rm[a, 4] * x1 + Rm[a, 5] * x2)
            A[3 + a, 6 + b] = -(W[a, 3] * x0 + W[a, 4] * x1 + W[a, 5] * x2)
    # gyro-bias column of the attitude rows: -Gamma^-1(e) X Gamma(JC d) JC
    so3.gamma_into(JCd[0], JCd[1], JCd[2], E)
    matmul_into(M, X, Y)
    matmul_into(Y, E, M)
    matmul_into(M, JC, Y)
    for a in range(3):
        for b in range(3):
            A[6 + a, 12 + b] = -Y[a, b]




@recursion
def _residual_rows(dC0, W0, Rm0, JC, dW, dRm, b_w_bar, ri, vi, Ci, bfi, bwi, rj, vj, Cj, bfj, bwj, g,
                   jacobians, e, Ji, Jj):
    """:func:`residual_into` for each row."""
    work = residual_work()
    for n in range(dC0.shape[0]):
        A, B = (Ji[n], Jj[n]) if jacobians else (Ji[0], Jj[0])
        residual_into(dC0[n], W0[n], Rm0[n], JC[n], dW[n], dRm[n], b_w_bar[n], ri[n], vi[n], Ci[n], bfi[n], bwi[n],
                       rj[n], vj[n], Cj[n], bfj[n], bwj[n], g, jacobians, e[n], A, B, work)


@recursion
def _residual_one(dC0, W0, Rm0, JC, dW, dRm, b_w_bar, Ci, ri, vi, bi, Cj, rj, vj, bj, g, jacobians, e, Ji, Jj):
    residual_into(dC0, W0, Rm0, JC, dW, dRm, b_w_bar, ri, vi, Ci, bi[:3], bi[3:], rj, vj, Cj, bj[:3], bj[3:], g,
                   jacobians, e, Ji, Jj, residual_work())


def residual(pre: Preintegrated, state_i: imu.ImuState, state_j: imu.ImuState, gravity=imu.DEFAULT_GRAVITY,
             jacobians: bool = False):
    """The 15-dim IMU residual and, optionally, its Jacobians in the primer's convention.

    ``e = (C_i^T (r_j - r_i) - Rm z,  v_j - W z,  log(C_i^T C_j dC^T),  b_fj - b_fi,  b_wj - b_wi)``
    -- position and attitude errors in body frame ``i``, so the covariance does not depend on the
    yaw of keyframe ``i``. To first order ``e`` is the EKF's error state at ``j`` rotated into
    frame ``i``, which is why its covariance is ``pre.cov``.

    Returns ``e`` and, with ``jacobians=True``, ``(Ji, Jj)``: ``(..., 15, 15)`` Jacobians with
    respect to the error states ``(dr, dv, dphi, db_f, db_w)`` of ``i`` and ``j`` (left
    increments of the attitudes). Derivation (eqs. 3, 24, 27-32)::

        d(C_i^T x)/dphi_i = (C_i^T x)^x C_i^T,      d gamma/dphi_i = gamma^x C_i^T
        e_r: dr_i -C_i^T, dr_j C_i^T, dv_i -Rm_v, dphi_i u^x C_i^T - Rm_g gamma^x C_i^T (u = C_i^T(r_j - r_i)),
             db_f Rm_b, db_w -(dRm . z)
        e_v: dv_j I, dv_i -W_v, dphi_i -W_g gamma^x C_i^T, db_f W_b, db_w -(dW . z)
        e_phi = log(X), X = C_i^T C_j dC^T:  dphi_j Gamma^-1(e) C_i^T,  dphi_i -Gamma^-1(e) C_i^T,
             db_w -Gamma^-1(e) X Gamma(JC d) JC
    """
    lead = common_shape(pre.b_w_bar.shape[:-1], state_i.shape, state_j.shape)
    n = math.prod(lead)
    fields = ("r", "v", "C", "b_f", "b_w")
    args = (rows_of(lead, (pre.dC, pre.W, pre.Rm, pre.JC, pre.dW, pre.dRm, pre.b_w_bar), _PRE_TAILS)
            + rows_of(lead, [getattr(state_i, f) for f in fields], _STATE_TAILS)
            + rows_of(lead, [getattr(state_j, f) for f in fields], _STATE_TAILS))
    e = np.empty((n, 15))
    Ji = np.empty((n, 15, 15) if jacobians else (1, 15, 15))
    Jj = np.empty_like(Ji)
    _residual_rows(*args, as_trailing(gravity, (3,), "gravity"), jacobians, e, Ji, Jj)
    e = e.reshape(lead + (15,))
    if not jacobians:
        return e
    return e, (Ji.reshape(lead + (15, 15)), Jj.reshape(lead + (15, 15)))


_ONE_SHAPES = ((3, 3), (3,), (3,), (6,)) * 2


def residual_one(pre: Preintegrated, Ci, ri, vi, bi, Cj, rj, vj, bj, gravity, jacobians: bool = False):
    """:func:`residual` of ONE interval from a factor's variables as GTSAM hands them over
    (attitude matrix, position, body velocity and the bias 6-vector ``(b_f, b_w)`` of keyframes
    ``i`` and ``j``): the same compiled core (:func:`residual_into`) without the batch plumbing,
    for the per-factor callback, where that plumbing cost more than the mathematics."""
    variables = (Ci, ri, vi, bi, Cj, rj, vj, bj)
    if pre.dC.shape != (3, 3) or np.shape(gravity) != (3,):
        raise InputError(f"residual_one: expected one interval and gravity (3,), got {pre.dC.shape[:-2]} "
                         f"intervals and gravity {np.shape(gravity)}")
    for x, shape in zip(variables, _ONE_SHAPES):
        if type(x) is not np.ndarray or x.shape != shape or x.dtype != np.float64:
            raise InputError(f"residual_one: expected float arrays of shapes {_ONE_SHAPES}, "
                             f"got {[np.shape(v) for v in variables]}")
    e = np.empty(15)
    Ji, Jj = np.empty((15, 15)), np.empty((15, 15))
    _residual_one(pre.dC, pre.W, pre.Rm, pre.JC, pre.dW, pre.dRm, pre.b_w_bar, Ci, ri, vi, bi, Cj, rj, vj, bj,
                  gravity, jacobians, e, Ji, Jj)
    return (e, (Ji, Jj)) if jacobians else e
