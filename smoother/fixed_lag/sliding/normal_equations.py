"""The sliding window's normal equations (:mod:`smoother.fixed_lag.sliding.window`), compiled: the factors
on the window's keyframes, linearised at their linearisation points, whitened and robustly
reweighted, summed into the block-banded ``H = sum J^T J`` and ``g = sum J^T e`` in the layout
of :mod:`smoother.fixed_lag.sliding.banded` (``Hb (n, S + 1, 15, 15)``, block row 0 = the first keyframe
assembled; window keyframe ``k``'s arrays at ring slot ``k % cap``).

The factors: the IMU intervals (:func:`factors.preintegration.residual_into`), the sensor
measurements (:func:`datasets.kinds.measure_into`, :func:`factors.sensor_models.odometry_kernel`
for a relative pose; a drifting sensor's measurement as its innovation on the one before,
:mod:`smoother.model.correlated`) with GTSAM's Huber, Cauchy and Tukey weights, and linear priors
(:class:`LinearPrior`: the marginals of keyframes that left the window, and priors on one
keyframe).
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from numba import njit

from datasets.kinds import attached_into, attached_work, calibrated_into, measure_into
from datasets.robust import ROBUST_KERNEL_NAMES
from factors import imu, so3
from factors.calibration import CALIBRATION_DIM, PACKED_SIZE, calibrated_odometry_into, work_array
from factors.preintegration import residual_into, residual_work
from factors.sensor_models import MAX_RESIDUAL_DIM, odometry_kernel
from factors.small_linalg import cholesky_into, solve_lower
from smoother.model.problem import RELATIVE_MODEL

DIM = imu.STATE_DIM
#: Robust kernels by their code in the compiled loop (0: none), in the order of
#: :data:`datasets.robust.ROBUST_KERNEL_NAMES`, which :func:`robust_scale`'s branches follow.
ROBUST_CODES = {name: code for code, name in enumerate(ROBUST_KERNEL_NAMES, start=1)}
MAX_DIM = MAX_RESIDUAL_DIM  # the widest measurement residual the registry admits
#: Reassociation and contraction only (no assumptions about NaN or infinities): lets LLVM turn the
#: dot products of the linear algebra into SIMD code.
_FAST = {"reassoc", "contract"}
#: The widest whitened Jacobian: a relative pose's two states and a calibration's coordinates.
_WIDE = 2 * DIM + CALIBRATION_DIM
#: ``jacobians`` of the IMU residual as a run-time flag: a literal ``True`` would compile a second
#: copy of :func:`factors.preintegration.residual_into` beside the batch solver's.
_WITH_JACOBIANS = np.bool_(True)
#: The same for the integers the kernels pass their helpers: a literal argument compiles a copy
#: of the helper for its value (five of :func:`_add_diagonal`, three each of :func:`_whiten` and
#: :func:`_add_normal`, on a first run's critical path).
_AT_ZERO, _AT_DIM, _NO_KEYFRAME = np.int64(0), np.int64(DIM), np.int64(-1)
_CALIBRATED = np.int64(CALIBRATION_DIM)  # the rows a drifting pair's calibration shares (_innovation_into)
#: What :func:`datasets.kinds.attached_into` reads of a calibration where a measurement reads none.
_NO_LAYOUT, _NO_CALIBRATION = np.zeros(6, dtype=np.int64), np.zeros(PACKED_SIZE)


@dataclass
class LinearPrior:
    """``e(x, c) = R [x [-] x_lin; dc] + e0`` on the window keyframes ``keyframes`` (ascending;
    their linearisation points ``r, v, C, b_f, b_w`` row by row) and, where ``c_lin`` is given
    (a marginal that informs the calibrations, :mod:`smoother.fixed_lag.sliding.calibration`), on every
    calibration: ``dc`` their error coordinates ``c [-] c_lin`` at the calibrations'
    linearisation points and ``Jdc`` its Jacobian (block diagonal; empty without ``c_lin``)."""

    keyframes: np.ndarray
    r: np.ndarray
    v: np.ndarray
    C: np.ndarray
    b_f: np.ndarray
    b_w: np.ndarray
    R: np.ndarray
    e0: np.ndarray
    c_lin: tuple | None = None
    dc: np.ndarray = field(default_factory=lambda: np.zeros(0))
    Jdc: np.ndarray = field(default_factory=lambda: np.zeros((0, 0)))
    #: a bordered prior's share of the calibrations' ``(D, g_c)`` when last linearised (its
    #: keyframes and the calibrations unchanged since while its keyframes' rows are not stale)
    own: tuple | None = None


@njit(cache=True)
def robust_scale(code, k, norm) -> float:
    """``sqrt(w(|e_w|))`` of GTSAM's mEstimator ``code`` (:data:`ROBUST_CODES`) at threshold ``k``."""
    if code == 1:  # Huber
        return 1.0 if norm <= k else np.sqrt(k / norm)
    if code == 2:  # Cauchy
        return np.sqrt(k * k / (k * k + norm * norm))
    if code == 3:  # Tukey
        if norm > k:
            return 0.0
        u = 1.0 - (norm / k) ** 2
        return u
    return 1.0


@njit(cache=True, fastmath=_FAST)
def _whiten(W, e, J, d, ncol, ew, JT, Jt0) -> None:
    """``ew = W e`` and ``JT = (W J)^T`` for the first ``d`` rows (``W`` lower triangular; ``JT``
    holds the whitened Jacobian transposed, so that the normal equations read contiguous rows;
    ``Jt0`` work space)."""
    for a in range(d):
        s = 0.0
        for b in range(a + 1):
            s += W[a, b] * e[b]
        ew[a] = s
    for c in range(ncol):
        for b in range(d):
            Jt0[c, b] = J[b, c]
    for c in range(ncol):
        for a in range(d):
            s = 0.0
            for b in range(a + 1):
                s += W[a, b] * Jt0[c, b]
            JT[c, a] = s


@njit(cache=True, fastmath=_FAST)
def _add_diagonal(Hb, g, a, ca, JT, ew, d) -> None:
    """Add ``J_a^T J_a`` and ``J_a^T e`` of a factor to keyframe ``a``'s diagonal block (``JT``: its
    whitened Jacobian transposed, ``d`` columns; keyframe ``a`` in rows ``ca:ca+15``)."""
    for p in range(DIM):
        s = 0.0
        for i in range(d):
            s += JT[ca + p, i] * ew[i]
        g[a * DIM + p] += s
        for q in range(p + 1):
            s = 0.0
            for i in range(d):
                s += JT[ca + p, i] * JT[ca + q, i]
            Hb[a, 0, p, q] += s
            if q != p:
                Hb[a, 0, q, p] += s


@njit(cache=True, fastmath=_FAST)
def _add_normal(Hb, g, a, ca, b, cb, JT, ew, d) -> None:
    """Add a factor's ``J^T J`` and ``J^T e`` (``JT``: its whitened Jacobian transposed, ``d``
    columns; keyframe ``a`` in rows ``ca:ca+15``, keyframe ``b > a`` in ``cb:cb+15``; ``b = -1``
    for a one-keyframe factor). Block rows are counted from the first row assembled: a keyframe
    before it (``a < 0``) gets nothing on its own row, only its coupling in row ``b``."""
    if a >= 0:
        _add_diagonal(Hb, g, a, ca, JT, ew, d)
    if b < 0:
        return
    _add_diagonal(Hb, g, b, cb, JT, ew, d)
    for p in range(DIM):
        for q in range(DIM):
            s = 0.0
            for i in range(d):
                s += JT[cb + p, i] * JT[ca + q, i]
            Hb[b, b - a, p, q] += s


@njit(cache=True)
def _add_own(D, gc, cols, Df, gf) -> None:
    """Add a calibrated factor's ``J_c^T J_c`` and ``J_c^T e`` (``Df (8, 8)``, ``gf (8)`` over
    the calibration's error coordinates) to ``D``, ``g_c`` (coordinate ``i`` in border column
    ``cols[i]``, -1: not estimated)."""
    for i in range(CALIBRATION_DIM):
        if cols[i] < 0:
            continue
        gc[cols[i]] += gf[i]
        for j in range(CALIBRATION_DIM):
            if cols[j] >= 0:
                D[cols[i], cols[j]] += Df[i, j]


@njit(cache=True, fastmath=_FAST)
def _add_border(B, Df, gf, a, ca, b, cb, cs, cols, JT, ew, d) -> None:
    """A calibrated factor's share of the border: ``J_k^T J_c`` added to the rows of ``B`` of
    keyframes ``a`` (rows ``ca:ca+15`` of ``JT``) and ``b`` (``cb``; -1: a one-keyframe factor;
    a keyframe outside the rows assembled gets nothing), and its ``J_c^T J_c``, ``J_c^T e`` into
    ``Df``, ``gf`` (:func:`_add_own`); ``JT`` rows ``cs + i`` hold the calibration's error
    coordinate ``i``, which is border column ``cols[i]`` (-1: not estimated)."""
    n = B.shape[0]
    Df[:, :] = 0.0
    gf[:] = 0.0
    for i in range(CALIBRATION_DIM):
        ci = cols[i]
        if ci < 0:
            continue
        s = 0.0
        for t in range(d):
            s += JT[cs + i, t] * ew[t]
        gf[i] = s
        for j in range(CALIBRATION_DIM):
            if cols[j] < 0:
                continue
            s = 0.0
            for t in range(d):
                s += JT[cs + i, t] * JT[cs + j, t]
            Df[i, j] = s
        for k, ck in ((a, ca), (b, cb)):
            if k < 0 or k >= n:
                continue
            for p in range(DIM):
                s = 0.0
                for t in range(d):
                    s += JT[ck + p, t] * JT[cs + i, t]
                B[k, p, ci] += s


@njit(cache=True)
def _reweight(code, k, JT, ew, d) -> None:
    """A whitened factor (``JT``, ``ew``: :func:`_whiten`, ``d`` rows) reweighted in place by
    GTSAM's robust kernel ``code`` at threshold ``k`` (0: none)."""
    if code != 0:
        norm = 0.0
        for a in range(d):
            norm += ew[a] * ew[a]
        scale = robust_scale(code, k, np.sqrt(norm))
        ew[:d] *= scale
        JT[:, :d] *= scale


@njit(cache=True)
def _add_factor(Hb, g, k0, k1, relative, lo, JT, ew, d) -> None:
    """A whitened factor on keyframes ``k0`` (and ``k1`` where ``relative``) added to the rows of
    ``Hb``, ``g`` from keyframe ``lo`` on."""
    if relative:
        _add_normal(Hb, g, k0 - lo, _AT_ZERO, k1 - lo, _AT_DIM, JT, ew, d)
    else:
        _add_normal(Hb, g, k0 - lo, _AT_ZERO, _NO_KEYFRAME, _AT_ZERO, JT, ew, d)


@njit(cache=True)
def _one_state(model, k, step, last, row, W, cap, r, v, C, bf, bw, sacc, sgyro, sdt, acc, gyro, gravity, d, e, Hm,
               Hc, attached, ew, JT, Jt0) -> None:
    """``ew = W e`` and ``JT = (W H)^T`` (:func:`_whiten`) of one measurement of kind ``model`` that
    reads keyframe ``k`` alone and no calibration: at the keyframe's time, or attached to it,
    ``step > 0`` steps (the last ``last`` long) into the interval after it (:func:`linearise`)."""
    i = k % cap
    if step > 0:
        j = (k + 1) % cap
        attached_into(model, _NO_LAYOUT, sacc[j], sgyro[j], sdt[j], step, last, r[i], v[i], C[i], bf[i], bw[i], row,
                      _NO_CALIBRATION, False, False, acc, gyro, gravity, e[:d], Hm[:d], Hc[:d], attached,
                      _WITH_JACOBIANS)
    else:
        measure_into(model, r[i], v[i], C[i], bf[i], bw[i], row, e[:d], Hm[:d])
    _whiten(W, e, Hm, d, _AT_DIM, ew, JT, Jt0)


@njit(cache=True)
def _innovation_into(s, c, pew, PJT, ew, JT, d, shared, relative) -> None:
    """A drifting sensor's whitened innovation ``s u - c u_p`` (:mod:`smoother.model.correlated`) into
    ``ew``, ``JT`` (:func:`_whiten`'s layout), from the later measurement's ``ew``, ``JT`` and the
    earlier one's ``pew``, ``PJT``, each with its keyframe's 15 rows then ``shared`` rows of a
    variable both read (a calibration's). Its rows: where ``relative`` (two keyframes) the earlier
    keyframe's, the later one's, then the shared ones; else the one keyframe's, then the shared."""
    width = 2 * DIM if relative else DIM
    for a in range(d):
        ew[a] = s * ew[a] - c * pew[a]
        for p in range(DIM + shared - 1, -1, -1):  # from the last row: the rows move down
            later = s * JT[p, a]
            if p >= DIM:
                JT[width + p - DIM, a] = later - c * PJT[p, a]
            elif relative:
                JT[DIM + p, a] = later
                JT[p, a] = -c * PJT[p, a]
            else:
                JT[p, a] = later - c * PJT[p, a]


@njit(cache=True)
def _one_calibrated(model, lay, k, step, last, row, W, acc, gyro, cap, r, v, C, bf, bw, cal, with_time, hacc, hgyro,
                    sacc, sgyro, sdt, gravity, d, e, Hm, Hc, Jc, work, attached, ew, JT, Jt0) -> None:
    """:func:`_one_state` of a measurement through its calibration (packed ``cal``, its time offset
    stepped where ``with_time``): ``JT`` rows ``0 .. 15`` the keyframe's, ``15 .. 23`` the
    calibration's error coordinates; ``acc``, ``gyro`` the IMU reading held at an attached
    measurement's stamp (one at its keyframe's time steps with the keyframe's, ``hacc``, ``hgyro``)."""
    i = k % cap
    if step > 0:
        j = (k + 1) % cap
        attached_into(model, lay, sacc[j], sgyro[j], sdt[j], step, last, r[i], v[i], C[i], bf[i], bw[i], row, cal, True,
                      with_time, acc, gyro, gravity, e[:d], Hm[:d], Hc[:d], attached, _WITH_JACOBIANS)
    else:
        calibrated_into(model, lay, r[i], v[i], C[i], bf[i], bw[i], row, cal, with_time, hacc[i], hgyro[i], gravity,
                        e[:d], Hm[:d], Hc[:d], work, True)
    Jc[:d, :DIM] = Hm[:d]
    Jc[:d, DIM:DIM + CALIBRATION_DIM] = Hc[:d]
    _whiten(W, e, Jc, d, DIM + CALIBRATION_DIM, ew, JT, Jt0)


@njit(cache=True)
def linearise(first, lo, cut, cap, r, v, C, bf, bw, has_imu, dC, Wp, Rm, JC, dW, dRm, bwbar, Wimu, gravity,
               m, mk, model, rows, dims, Wm, rcode, rk, mcal, mstep, mlast, macc, mgyro,
               sacc, sgyro, sdt, dc, ds, drow, dWm, dstep, dlast, Hb, g) -> None:
    """Add to ``Hb``, ``g`` (block row 0 = keyframe ``lo``) the rows ``lo ..`` of the normal
    equations of the factors that reach keyframe ``lo`` or later and begin before ``cut``: the
    IMU intervals (stored at the slot of their later keyframe) and the measurements ``0 .. m - 1``
    that read no calibration (``mcal[f] < 0``; the others: :func:`linearise_calibrated`),
    linearised at the state arrays given. Keyframe ``k`` is at slot ``k % cap``. A measurement
    with ``mstep[f] > 0`` is attached to its keyframe ``k``
    (:func:`datasets.kinds.attached_into`): taken after the first ``mstep[f]`` steps of the samples
    ``sacc, sgyro, sdt`` of the interval into keyframe ``k + 1`` (at that keyframe's slot), the last
    cut to ``mlast[f]``; ``macc``, ``mgyro`` (the IMU reading held at its stamp) are read by
    :func:`linearise_calibrated` only. A measurement ``f`` with ``dc[f] != 0`` is the whitened
    innovation of errors correlated in time (:mod:`smoother.model.correlated`), ``ds[f] u_f - dc[f]
    u_p``, of its whitened residual ``u_f`` on keyframe ``mk[f, 1]`` and that of the measurement before
    it, ``u_p``, on keyframe ``mk[f, 0]`` (the same keyframe where both fall on one): the earlier
    one's packed row ``drow[f]``, whitening ``dWm[f]`` and attachment ``dstep[f]``, ``dlast[f]``."""
    work = residual_work()
    e, A, B = np.empty(DIM), np.empty((DIM, DIM)), np.empty((DIM, DIM))
    J, JT, Jt0, ew = np.empty((DIM, 2 * DIM)), np.empty((_WIDE, DIM)), np.empty((_WIDE, DIM)), np.empty(DIM)
    n = Hb.shape[0]
    for k in range(max(lo, first + 1), lo + n):
        if k - 1 >= cut:
            break
        j = k % cap
        if not has_imu[j]:
            continue
        i = (k - 1) % cap
        residual_into(dC[j], Wp[j], Rm[j], JC[j], dW[j], dRm[j], bwbar[j], r[i], v[i], C[i], bf[i], bw[i],
                       r[j], v[j], C[j], bf[j], bw[j], gravity, _WITH_JACOBIANS, e, A, B, work)
        J[:, :DIM] = A
        J[:, DIM:] = B
        _whiten(Wimu[j], e, J, _AT_DIM, 2 * _AT_DIM, ew, JT, Jt0)
        _add_normal(Hb, g, k - 1 - lo, _AT_ZERO, k - lo, _AT_DIM, JT, ew, _AT_DIM)
    # H for a relative pose (both keyframes); Hm, C-contiguous, for the one-state kernels, which the
    # EKF and the batch solver call with C-contiguous arrays too: one compiled copy of each
    H, Hm, Hc = np.empty((MAX_DIM, 2 * DIM)), np.empty((MAX_DIM, DIM)), np.empty((MAX_DIM, CALIBRATION_DIM))
    attached = attached_work()
    pew, PJT = np.empty(DIM), np.empty((_WIDE, DIM))  # the earlier measurement of a drifting pair
    for f in range(m):
        k0, k1 = mk[f, 0], mk[f, 1]
        if k0 >= cut or k1 < lo or mcal[f] >= 0:
            continue
        d = dims[f]
        i = k0 % cap
        relative = model[f] == RELATIVE_MODEL
        if relative:
            odometry_kernel(r[i], C[i], r[k1 % cap], C[k1 % cap], rows[f], e[:d], H[:d])
            _whiten(Wm[f], e, H, d, 2 * _AT_DIM, ew, JT, Jt0)
        elif dc[f] != 0.0:  # the innovation s u_f - c u_p on keyframes k0 <= k1 (one where equal)
            _one_state(model[f], k1, mstep[f], mlast[f], rows[f], Wm[f], cap, r, v, C, bf, bw, sacc, sgyro, sdt,
                       macc[f], mgyro[f], gravity, d, e, Hm, Hc, attached, ew, JT, Jt0)
            _one_state(model[f], k0, dstep[f], dlast[f], drow[f], dWm[f], cap, r, v, C, bf, bw,
                       sacc, sgyro, sdt, macc[f], mgyro[f], gravity, d, e, Hm, Hc, attached, pew, PJT, Jt0)
            relative = k1 != k0
            _innovation_into(ds[f], dc[f], pew, PJT, ew, JT, d, _AT_ZERO, relative)
        else:
            _one_state(model[f], k0, mstep[f], mlast[f], rows[f], Wm[f], cap, r, v, C, bf, bw, sacc, sgyro, sdt,
                       macc[f], mgyro[f], gravity, d, e, Hm, Hc, attached, ew, JT, Jt0)
        _reweight(rcode[f], rk[f], JT, ew, d)
        _add_factor(Hb, g, k0, k1, relative, lo, JT, ew, d)


@njit(cache=True)
def linearise_calibrated(lo, cut, cap, r, v, C, bf, bw, gravity, m, mk, model, rows, dims, Wm, rcode, rk, mcal, mD,
                          mg, kH, kg, kB, kept, cal, cal_time, cal_cols, layouts, hacc, hgyro, mstep, mlast, macc,
                          mgyro, sacc, sgyro, sdt, dc, ds, drow, dWm, dstep, dlast, dacc, dgyro, Hb, g, B, D,
                          gc) -> None:
    """:func:`linearise` of the measurements ``f`` that read calibration ``j = mcal[f] >= 0``
    (packed ``cal[j]``, :func:`factors.calibration.packed`; its time offset stepped with the IMU
    reading held at the keyframe, ``hacc``, ``hgyro``, where ``cal_time[j]``; its error
    coordinates in the border's columns ``cal_cols[j]``, -1 where not estimated; ``layouts``:
    :data:`datasets.kinds.LAYOUTS`): each adds its rows to ``Hb``, ``g``, its border rows to
    ``B`` (block row 0 = keyframe ``lo``) and, whichever keyframes it reads, its share to ``D``,
    ``g_c``, kept in ``mD[f]``, ``mg[f]``. One whose keyframes are all before ``lo`` adds what it
    kept: its keyframes have not been linearised again since it was last linearised (their rows
    of ``L`` would then be stale), nor has its calibration (every row reading one is stale then).
    The one-keyframe ones on a keyframe also keep the sum of what they add to its rows, ``kH``,
    ``kg``, ``kB`` at its slot (its diagonal block, ``g`` and ``B`` rows): where ``kept`` holds
    for its slot (the caller clears it when a keyframe takes the slot, when the keyframe or a
    calibration is linearised again and when a measurement joins it, and moves sums and flags
    with the slots when the ring grows) they add that sum instead of being linearised again;
    the others are linearised, their sums kept and ``kept`` set. A measurement attached to its
    keyframe (``mstep[f] > 0``, :func:`linearise`) is evaluated through the steps to its time,
    its time offset stepped with the reading held at its own stamp (``macc``, ``mgyro``). A drifting
    sensor's innovation (:func:`linearise`; ``dacc``, ``dgyro`` the reading held at the earlier
    measurement's stamp) is a factor on its two keyframes, as a relative one is, or on its one. A
    separate kernel: a window without calibrations never compiles the calibrated residuals."""
    e, ew = np.empty(DIM), np.empty(DIM)
    JT, Jt0 = np.empty((_WIDE, DIM)), np.empty((_WIDE, DIM))
    H, Hm, Hc = np.empty((MAX_DIM, 2 * DIM)), np.empty((MAX_DIM, DIM)), np.empty((MAX_DIM, CALIBRATION_DIM))
    Jc = np.empty((MAX_DIM, _WIDE))  # the factor's states and calibration side by side
    work = work_array()
    attached = attached_work()
    n = Hb.shape[0]
    for k in range(lo, min(cut, lo + n)):  # the sums not kept, made anew below
        s = k % cap
        if not kept[s]:
            kH[s] = 0.0
            kg[s] = 0.0
            kB[s] = 0.0
    pew, PJT = np.empty(DIM), np.empty((_WIDE, DIM))  # the earlier measurement of a drifting pair
    for f in range(m):
        k0, k1 = mk[f, 0], mk[f, 1]
        j = mcal[f]
        if k0 >= cut or j < 0:
            continue
        if k1 < lo or (model[f] != RELATIVE_MODEL and k1 == k0 and kept[k0 % cap]):
            _add_own(D, gc, cal_cols[j], mD[f], mg[f])
            continue
        d = dims[f]
        i, i1 = k0 % cap, k1 % cap
        relative = model[f] == RELATIVE_MODEL or k1 != k0
        width = 2 * DIM if relative else DIM
        if dc[f] != 0.0:  # the innovation s u_f - c u_p, its columns: [k0,] k1's, then the calibration's
            lay = layouts[model[f]]
            _one_calibrated(model[f], lay, k1, mstep[f], mlast[f], rows[f], Wm[f], macc[f], mgyro[f], cap, r, v, C, bf,
                            bw, cal[j], cal_time[j], hacc, hgyro, sacc, sgyro, sdt, gravity, d, e, Hm, Hc, Jc, work,
                            attached, ew, JT, Jt0)
            _one_calibrated(model[f], lay, k0, dstep[f], dlast[f], drow[f], dWm[f], dacc[f], dgyro[f], cap, r, v, C, bf,
                            bw, cal[j], cal_time[j], hacc, hgyro, sacc, sgyro, sdt, gravity, d, e, Hm, Hc, Jc, work,
                            attached, pew, PJT, Jt0)
            _innovation_into(ds[f], dc[f], pew, PJT, ew, JT, d, _CALIBRATED, relative)
            _reweight(rcode[f], rk[f], JT, ew, d)
            if relative:
                _add_border(B, mD[f], mg[f], k0 - lo, 0, k1 - lo, DIM, width, cal_cols[j], JT, ew, d)
                _add_factor(Hb, g, k0, k1, relative, lo, JT, ew, d)
            else:
                _add_border(kB[i], mD[f], mg[f], _AT_ZERO, 0, _NO_KEYFRAME, DIM, width, cal_cols[j], JT, ew, d)
                _add_diagonal(kH[i], kg[i], 0, _AT_ZERO, JT, ew, d)
            _add_own(D, gc, cal_cols[j], mD[f], mg[f])
            continue
        if relative:
            calibrated_odometry_into(r[i], v[i], C[i], bf[i], bw[i], r[i1], v[i1], C[i1], bf[i1], bw[i1], rows[f],
                                     cal[j], cal_time[j], hacc[i], hgyro[i], hacc[i1], hgyro[i1], gravity, e[:d],
                                     H[:d], Hc[:d], work, True)
            Jc[:d, :width] = H[:d]
        elif mstep[f] > 0:
            nxt = (k0 + 1) % cap
            attached_into(model[f], layouts[model[f]], sacc[nxt], sgyro[nxt], sdt[nxt], mstep[f], mlast[f], r[i], v[i],
                          C[i], bf[i], bw[i], rows[f], cal[j], True, cal_time[j], macc[f], mgyro[f], gravity, e[:d],
                          Hm[:d], Hc[:d], attached, _WITH_JACOBIANS)
            Jc[:d, :width] = Hm[:d]
        else:
            calibrated_into(model[f], layouts[model[f]], r[i], v[i], C[i], bf[i], bw[i], rows[f], cal[j], cal_time[j],
                            hacc[i], hgyro[i], gravity, e[:d], Hm[:d], Hc[:d], work, True)
            Jc[:d, :width] = Hm[:d]
        Jc[:d, width:width + CALIBRATION_DIM] = Hc[:d]
        _whiten(Wm[f], e, Jc, d, width + CALIBRATION_DIM, ew, JT, Jt0)
        _reweight(rcode[f], rk[f], JT, ew, d)
        if relative:
            _add_border(B, mD[f], mg[f], k0 - lo, 0, k1 - lo, DIM, width, cal_cols[j], JT, ew, d)
            _add_factor(Hb, g, k0, k1, relative, lo, JT, ew, d)
        else:  # into its keyframe's sums, added below
            _add_border(kB[i], mD[f], mg[f], _AT_ZERO, 0, _NO_KEYFRAME, DIM, width, cal_cols[j], JT, ew, d)
            _add_diagonal(kH[i], kg[i], 0, _AT_ZERO, JT, ew, d)
        _add_own(D, gc, cal_cols[j], mD[f], mg[f])
    for k in range(lo, min(cut, lo + n)):
        s, a = k % cap, k - lo
        kept[s] = True
        for p in range(DIM):
            g[a * DIM + p] += kg[s, p]
            for q in range(DIM):
                Hb[a, 0, p, q] += kH[s, 0, 0, p, q]
            for c in range(B.shape[2]):
                B[a, p, c] += kB[s, 0, p, c]


@njit(cache=True)
def prior_into(blocks, xr, xv, xC, xbf, xbw, R, e0, dc, Jdc, cap, r, v, C, bf, bw, lo, Hb, g, B, D, gc) -> None:
    """Add the linear prior ``e = R [x [-] x_lin; dc] + e0`` on keyframes ``blocks`` (global
    numbers, ascending) and, where ``dc`` is not empty, on the border's calibration coordinates
    (:class:`LinearPrior`), linearised at the state arrays given, to the rows ``lo ..`` of
    ``Hb``, ``g`` (block row 0 = keyframe ``lo``) and to ``B``, ``D``, ``g_c``."""
    P = blocks.shape[0]
    N = DIM * P
    nb = dc.shape[0]
    dx = np.zeros(N)
    Dg = np.zeros((P, 3, 3))  # Gamma^-1 of each attitude difference
    for a in range(P):
        s = blocks[a] % cap
        for c in range(3):
            dx[a * DIM + c] = r[s, c] - xr[a, c]
            dx[a * DIM + 3 + c] = v[s, c] - xv[a, c]
            dx[a * DIM + 9 + c] = bf[s, c] - xbf[a, c]
            dx[a * DIM + 12 + c] = bw[s, c] - xbw[a, c]
        p0, p1, p2 = so3.boxminus_of(C[s], xC[a])
        dx[a * DIM + 6], dx[a * DIM + 7], dx[a * DIM + 8] = p0, p1, p2
        so3.gamma_inv_into(p0, p1, p2, Dg[a])
    e = e0.copy()
    J = R.copy()  # R times the block diagonal (I, I, Gamma^-1, I, I; Jdc)
    for row in range(R.shape[0]):
        for col in range(N):
            e[row] += R[row, col] * dx[col]
        for col in range(nb):
            e[row] += R[row, N + col] * dc[col]
        for a in range(P):
            for c in range(3):
                s = 0.0
                for q in range(3):
                    s += R[row, a * DIM + 6 + q] * Dg[a, q, c]
                J[row, a * DIM + 6 + c] = s
        for c in range(nb):
            s = 0.0
            for q in range(nb):
                s += R[row, N + q] * Jdc[q, c]
            J[row, N + c] = s
    n = B.shape[0]
    for a in range(P):
        ba = blocks[a] - lo
        if ba < 0:
            continue
        for p in range(DIM):
            s = 0.0
            for row in range(R.shape[0]):
                s += J[row, a * DIM + p] * e[row]
            g[ba * DIM + p] += s
            if ba < n:
                for c in range(nb):
                    s = 0.0
                    for row in range(R.shape[0]):
                        s += J[row, a * DIM + p] * J[row, N + c]
                    B[ba, p, c] += s
        for b in range(a + 1):
            bb = blocks[b] - lo
            for p in range(DIM):
                for q in range(DIM):
                    s = 0.0
                    for row in range(R.shape[0]):
                        s += J[row, a * DIM + p] * J[row, b * DIM + q]
                    Hb[ba, ba - bb, p, q] += s
    for c in range(nb):
        s = 0.0
        for row in range(R.shape[0]):
            s += J[row, N + c] * e[row]
        gc[c] += s
        for q in range(nb):
            s = 0.0
            for row in range(R.shape[0]):
                s += J[row, N + c] * J[row, N + q]
            D[c, q] += s


@njit(cache=True)
def whitening_into(cov, W) -> bool:
    """``W = L^-1`` with ``cov = L L^T`` (:func:`smoother.model.blocks.whitening`, compiled for one
    matrix); False if ``cov`` is not positive definite."""
    d = cov.shape[0]
    L = np.empty((d, d))
    if not cholesky_into(cov, L):
        return False
    Wd = np.zeros((d, d))  # C-contiguous, as the banded solves' blocks: one compiled solve_lower
    for c in range(d):
        Wd[c, c] = 1.0
    solve_lower(L, Wd)
    W[:d, :d] = Wd
    return True
