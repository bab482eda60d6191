"""The sliding window's own compiled steps over its ring of keyframes
(:class:`smoother.fixed_lag.sliding.window.SlidingWindow`): the estimates' boxplus, the factorisation
and forward solve from a row on (plain and bordered by the calibrations), the step with its turn
limit and relinearisation marks, dropping the measurements of keyframes that left, and moving the
linearisation points of the keyframes past their thresholds."""
from __future__ import annotations

import math

from numba import njit

from factors import imu
from smoother.fixed_lag.sliding.banded import (
    backward_solve,
    border_solve,
    factorise,
    forward_solve,
)

DIM = imu.STATE_DIM



@njit(cache=True)
def window_boxplus(first, newest, cap, delta, r, v, C, bf, bw, xr, xv, xC, xbf, xbw) -> None:
    """``x = theta [+] delta`` for the window's keyframes (:func:`factors.imu.boxplus_into`: the
    left attitude increment)."""
    for k in range(first, newest + 1):
        s = k % cap
        xr[s], xv[s], xC[s], xbf[s], xbw[s] = r[s], v[s], C[s], bf[s], bw[s]
        imu.boxplus_into(xr[s], xv[s], xC[s], xbf[s], xbw[s], delta[s].reshape(delta.shape[1]))  # C, as the EKF's


@njit(cache=True)
def factorise_forward(Hr, g, L, y, first, start, newest, cap, S) -> int:
    """The rows ``start ..`` of ``L`` from ``Hr`` (:func:`factorise`) and the forward solution
    ``y = L^-1 (-g)`` from row ``start`` on (``g``'s rows from ``start``; the rows before kept).
    Returns -1, or the keyframe whose pivot failed (nothing else done)."""
    failed = factorise(Hr, L, first, start, newest, cap, S)
    if failed >= 0:
        return failed
    for k in range(start, newest + 1):
        s = k % cap
        for p in range(DIM):
            y[s, p, 0] = -g[(k - start) * DIM + p]
    forward_solve(L, y, first, start, first, newest, cap, S)
    return -1


@njit(cache=True)
def factorise_forward_border(Hr, g, L, y, first, start, newest, cap, S, Z, ZZ, B, D, gc, dx, L_D, delta_c,
                              threshold, fraction, widest, limits):
    """A bordered window's :func:`factorise_forward`, then ``dx = y`` over the window and the
    border's part (:func:`smoother.fixed_lag.sliding.banded.border_solve`: ``Z``, ``ZZ``, ``L_D``, ``delta_c``,
    ``limits``, ``dx -= Z delta_c``) in the same call. Returns ``(failed, code)``: ``failed`` as
    :func:`factorise_forward`'s (``code`` 0, nothing else done), else -1 and the border's code
    (1: some ``|delta_c|`` exceeds its limit, 0: none, -1: the calibrations' Schur complement is
    not positive definite, ``dx = y``)."""
    failed = factorise_forward(Hr, g, L, y, first, start, newest, cap, S)
    if failed >= 0:
        return failed, 0
    for k in range(first, newest + 1):
        s = k % cap
        dx[s] = y[s]
    return -1, border_solve(L, Z, ZZ, B, D, gc, y, dx, first, start, newest, cap, S, L_D, delta_c, threshold,
                             fraction, widest, limits)


@njit(cache=True)
def step_window(L, delta, before, first, newest, cap, S, threshold, max_turn, moved, r, v, C, bf, bw, xr, xv, xC, xbf,
          xbw):
    """The rest of an update, ``delta`` holding the forward solution (less the calibrations'
    share, :mod:`smoother.fixed_lag.sliding.calibration`) and ``before`` the offsets of the last update:
    ``delta = L^-T delta``, the whole step from ``before`` shortened so that no attitude turns by
    more than ``max_turn`` [rad], the estimates ``theta [+] delta`` (:func:`_boxplus`), then the
    keyframes whose offset exceeds ``threshold`` linearised again (:func:`_relinearise`). Returns
    ``(oldest, a)``: -1 or the oldest keyframe linearised again, and the factor the step was
    shortened by (1: not shortened)."""
    backward_solve(L, delta, first, newest, cap, S)
    turn = 0.0
    for k in range(first, newest + 1):
        s = k % cap
        d0, d1, d2 = (delta[s, 6, 0] - before[s, 6, 0], delta[s, 7, 0] - before[s, 7, 0],
                      delta[s, 8, 0] - before[s, 8, 0])
        turn = max(turn, math.sqrt(d0 * d0 + d1 * d1 + d2 * d2))
    a = 1.0
    if turn > max_turn:  # along the Gauss-Newton step, no further than max_turn in attitude
        a = max_turn / turn
        for k in range(first, newest + 1):
            s = k % cap
            for p in range(DIM):
                delta[s, p, 0] = before[s, p, 0] + a * (delta[s, p, 0] - before[s, p, 0])
    window_boxplus(first, newest, cap, delta, r, v, C, bf, bw, xr, xv, xC, xbf, xbw)
    return relinearise_offsets(first, newest, cap, delta, threshold, r, v, C, bf, bw, xr, xv, xC, xbf, xbw, moved), a


@njit(cache=True)
def drop_measurements(cut, m, mk, model, rows, dims, Wm, rcode, rk, mcal, mD, mg, mstep, mlast, macc, mgyro):
    """Remove the measurements whose earliest keyframe is before ``cut``, keeping the order of the
    rest; returns their number and the longest span (later minus earlier keyframe) among them."""
    n, span = 0, 0
    for f in range(m):
        if mk[f, 0] >= cut:
            if n != f:
                mk[n], model[n], rows[n], dims[n] = mk[f], model[f], rows[f], dims[f]
                Wm[n], rcode[n], rk[n], mcal[n], mD[n], mg[n] = Wm[f], rcode[f], rk[f], mcal[f], mD[f], mg[f]
                mstep[n], mlast[n], macc[n], mgyro[n] = mstep[f], mlast[f], macc[f], mgyro[f]
            span = max(span, mk[n, 1] - mk[n, 0])
            n += 1
    return n, span


@njit(cache=True)
def relinearise_offsets(first, newest, cap, delta, threshold, r, v, C, bf, bw, xr, xv, xC, xbf, xbw, moved) -> int:
    """Move the linearisation point ``theta`` of each window keyframe whose offset ``delta`` exceeds
    ``threshold`` in any component to its estimate (``theta <- theta [+] delta = x``,
    ``delta <- 0``), flagging it in ``moved``; returns the oldest moved keyframe, or -1."""
    oldest = -1
    for k in range(first, newest + 1):
        s = k % cap
        moved[s] = False
        for i in range(DIM):
            if abs(delta[s, i, 0]) > threshold[i]:
                moved[s] = True
                break
        if moved[s]:
            if oldest < 0:
                oldest = k
            r[s, :], v[s, :], bf[s, :], bw[s, :] = xr[s], xv[s], xbf[s], xbw[s]
            C[s, :, :] = xC[s]
            delta[s] = 0.0
    return oldest
