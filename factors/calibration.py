"""A sensor's calibration as variables, and its measurement residuals through them.

A sensor's calibration is ``c = (d, R_BS, p_BS, s)`` (the conventions of ``docs/design.md``):

* ``d`` [s], the time offset beyond the one already added to its stamps: the measurement stamped
  ``t`` was taken at ``t + d``;
* ``R_BS``, its mounting rotation, perturbed like every rotation here, on the left in the IMU
  frame: ``R_BS [+] rho = exp(rho) R_BS``;
* ``p_BS``, its lever arm (the sensor's origin in the IMU frame), additively;
* ``s``, its scale: what the sensor reads per unit of the truth (a wheel speed reading 1 % low has
  ``s = 0.99``); it multiplies the model's :attr:`~factors.sensor_models.SensorModel.scaled` rows
  (a velocity, odometry's translation).

Its error coordinates are :data:`CALIBRATION_DIM` = 8 numbers ``(dd, rho (3), dp (3), ds)``, in
the order of :data:`PARTS`; a sensor estimates any subset of the parts, whose columns
:func:`columns` gives.

The calibrated residual of a measurement stamped ``t`` is the model's residual at the state one
Euler step of the primer's model (:func:`factors.imu.propagate`) away, by ``d``, with the IMU
reading held at ``t``, and with the calibrated extrinsic in its row:

    e(x, c) = S(s) e_0(x', row(R_BS, p_BS)),   x' = f(x, imu(t), d)

(``S(s)`` the scaling of the scaled rows: ``s (e_0 + z) - z``). Its Jacobians, with ``H_0 =
de_0/dx'`` the model's own (``H_0`` over the scaled rows multiplied by ``s`` below):

* state: ``H_0 F(d)`` with ``F`` the step's own transition Jacobian;
* time offset: ``H_0 xdot(x)``: the step is linear in ``d`` in the chart at ``x'`` (``r + d C v``,
  ``v + d (f - b_f + C^T g - w x v)``, ``exp(d C w) C``), so ``dx'/dd`` is the state's rate
  :func:`factors.imu.state_derivative` -- a position moves through the velocity, an attitude
  through the angular rate, a velocity through the specific force;
* rotation: ``R_BS`` enters the one-state models through the sensor frame's attitude ``C R_BS``
  (and its velocity ``R_BS^T u``). ``C exp(rho) R_BS = exp(C rho) C R_BS`` (primer eq. 6), so
  where only the attitude ``C R_BS`` reads it, ``de/drho = H_phi C`` (pose: its attitude rows);
  a velocity ``R_BS^T u`` moves by ``R_BS^T u^x rho`` (``exp(-rho) u = u + u^x rho`` to first
  order), i.e. ``H_v u^x`` (``H_v = R_BS^T``);
* lever arm: it enters through ``r + C p`` (``de/dp = H_r C``) or through ``v + w x p``
  (``de/dp = H_v w^x``, ``w`` the bias-corrected gyro);
* scale: ``de/ds = e_0 + z`` on the scaled rows.

A relative pose (odometry, :func:`factors.sensor_models.odometry_kernel`) reads the sensor frames
of two states; both stamps shift by ``d`` (``H_0 xdot`` summed over the two states). With ``M =
R^T C_i^T``, ``D = (r_j + C_j p) - (r_i + C_i p)`` and ``A = C_i^T C_j``:
``de_r/drho = R^T (C_i^T D)^x = M D^x C_i`` (``= H_rj D^x C_i``, ``H_rj = M``),
``de_phi/drho = Gamma^-1(e_phi) R^T (A - I)`` (``R^T exp(-rho) A exp(rho) R = exp(R^T (A - I)
rho) R^T A R``, eq. 6 twice; ``= H_phij (C_j - C_i)`` since ``H_phij = Gamma^-1 M``),
``de_r/dp = M (C_j - C_i) = H_rj (C_j - C_i)``.

To first order the IMU reading's noise does not enter (it reaches the residual multiplied by
``d``); a calibrated lever arm's gyro noise on a velocity sensor stays that of the extrinsic given
(:func:`datasets.kinds.velocity.with_gyro_noise`). The numerical twins of every block are in
``tests/factors/test_calibration.py`` and in ``smoother check-jacobians``.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from factors import imu, so3
from factors import sensor_models as sm
from factors.compiled import block_operation, leaf, recursion
from factors.errors import InputError
from factors.imu import STATE_DIM
from factors.rows import rows
from factors.small_linalg import matmul_into

#: The parts of a calibration, in the order of its error coordinates, and their columns there.
PARTS = ("time_offset", "rotation", "lever_arm", "scale")
PART_COLUMNS = {"time_offset": slice(0, 1), "rotation": slice(1, 4), "lever_arm": slice(4, 7), "scale": slice(7, 8)}
CALIBRATION_DIM = 8


def columns(parts) -> np.ndarray:
    """The error coordinates (indices into the 8) of the calibration ``parts``, in :data:`PARTS` order."""
    unknown = [p for p in parts if p not in PART_COLUMNS]
    if unknown:
        raise InputError(f"calibration parts {unknown}: expected any of {', '.join(PARTS)}")
    return np.concatenate([np.arange(8)[PART_COLUMNS[p]] for p in PARTS if p in parts]).astype(int)


@dataclass(frozen=True)
class Calibration:
    """One sensor's calibration values (module docstring): ``time_offset`` [s] beyond its stamps',
    ``R`` = ``R_BS``, ``p`` = ``p_BS`` [m], ``scale``."""

    time_offset: float
    R: np.ndarray
    p: np.ndarray
    scale: float

    @staticmethod
    def of(T_BS=None, time_offset: float = 0.0, scale: float = 1.0) -> "Calibration":
        R, p = sm.extrinsic_parts(T_BS)
        return Calibration(float(time_offset), R, p, float(scale))

    @property
    def T_BS(self) -> np.ndarray:
        T = np.eye(4)
        T[:3, :3], T[:3, 3] = self.R, self.p
        return T

    def boxplus(self, delta) -> "Calibration":
        """``c [+] delta`` for ``delta`` the 8 error coordinates (:func:`boxplus_into`, the kernel
        the EKF runs)."""
        moved = packed(self)
        boxplus_into(moved, np.ascontiguousarray(delta, dtype=float).reshape(CALIBRATION_DIM))
        return unpacked(moved)

    def boxminus(self, other: "Calibration") -> np.ndarray:
        """``c [-] other`` (8), the inverse of :meth:`boxplus`."""
        return np.concatenate([[self.time_offset - other.time_offset], so3.boxminus(self.R, other.R),
                               self.p - other.p, [self.scale - other.scale]])


class CalibrationManifold:
    """:class:`factors.jacobians.Manifold` of :class:`Calibration` for numerical Jacobians."""

    dim = CALIBRATION_DIM

    @staticmethod
    def plus(c: Calibration, delta: np.ndarray) -> Calibration:
        return c.boxplus(delta)

    @staticmethod
    def minus(a: Calibration, b: Calibration) -> np.ndarray:
        return a.boxminus(b)


def prior_residual(c: Calibration, mean: Calibration, which: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``e = (c [-] mean)[which]`` and its Jacobian ``(len(which), len(which))`` with respect to
    the error coordinates ``which``: the identity but for the rotation, ``Gamma^-1(e_rho)``
    (``log(exp(rho) R R_0^T)``, primer eq. 32)."""
    full = c.boxminus(mean)
    J = np.eye(CALIBRATION_DIM)
    J[1:4, 1:4] = so3.gamma_inv(full[1:4])
    return full[which], J[np.ix_(which, which)]


#: A calibration as the compiled kernels read it (:func:`packed`): ``(d, R_BS row-major (9),
#: p_BS (3), s)``.
PACKED_SIZE = 14
_R_AT, _P_AT, _S_AT = 1, 10, 13


def packed(c: Calibration) -> np.ndarray:
    """``c`` as the compiled kernels read it (:data:`PACKED_SIZE` numbers)."""
    return np.concatenate([[c.time_offset], np.asarray(c.R, dtype=float).reshape(9), c.p, [c.scale]])


def unpacked(cal: np.ndarray) -> Calibration:
    """The :class:`Calibration` of a packed one (:func:`packed`'s inverse; copies)."""
    return Calibration(float(cal[0]), np.array(cal[_R_AT:_P_AT], dtype=float).reshape(3, 3),
                       np.array(cal[_P_AT:_S_AT], dtype=float), float(cal[_S_AT]))


@recursion
def boxplus_into(cal, delta) -> None:
    """``cal [+] delta`` in place on a packed calibration (:func:`packed`), ``delta`` its 8 error
    coordinates (module docstring): ``d + dd``, ``exp(rho) R_BS``, ``p_BS + dp``, ``s + ds``."""
    E, R = np.empty((3, 3)), cal[_R_AT:_P_AT].copy().reshape((3, 3))
    so3.exp_into(delta[1], delta[2], delta[3], E)
    matmul_into(E, R, cal[_R_AT:_P_AT].reshape((3, 3)))
    cal[0] += delta[0]
    for a in range(3):
        cal[_P_AT + a] += delta[4 + a]
    cal[_S_AT] += delta[7]


#: The residual rows through whose attitude ``R_BS`` enters, where not all (a pose's; its position
#: rows read the lever arm alone).
_ATTITUDE_ROWS = {"pose": (3, 6)}
#: The models whose extrinsic enters through the sensor frame's velocity ``R_BS^T (v + w x p)``,
#: with the place of the gyro reading ``w`` in their rows.
_THROUGH_VELOCITY = {"velocity": 3}


def layout(model: sm.SensorModel) -> np.ndarray:
    """How a one-state ``model``'s rows and residual read a calibration, for
    :func:`one_state_into`: ``(rotation_at, lever_at, scaled, gyro_at, first, end)`` -- where its
    rows hold ``R_BS`` and ``p_BS`` (-1: they do not), its scaled rows, the place of the gyro
    reading in a row whose velocity reads the extrinsic (-1: it enters through the attitude ``C
    R_BS`` and the position ``r + C p``), and the residual rows ``first:end`` whose attitude reads
    ``R_BS``."""
    first, end = _ATTITUDE_ROWS.get(model.name, (0, model.dim))
    return np.array([-1 if model.rotation_at is None else model.rotation_at,
                     -1 if model.lever_at is None else model.lever_at, model.scaled,
                     _THROUGH_VELOCITY.get(model.name, -1), first, end], dtype=np.int64)


@leaf
def calibrated_row_into(row, rotation_at, lever_at, cal, out) -> None:
    """``out = row`` with the packed calibration ``cal``'s ``R_BS`` and ``p_BS`` in their slots
    (-1: none)."""
    for a in range(row.shape[0]):
        out[a] = row[a]
    if rotation_at >= 0:
        for a in range(9):
            out[rotation_at + a] = cal[_R_AT + a]
    if lever_at >= 0:
        for a in range(3):
            out[lever_at + a] = cal[_P_AT + a]


@leaf
def scaled_error_into(e0, row, scaled, s, e) -> None:
    """The scale on the first ``scaled`` residual rows: ``e = s (e0 + z) - z`` (``z =
    row[:scaled]``), ``e0`` on the others."""
    d = e0.shape[0]
    for a in range(d):
        e[a] = e0[a]
    for a in range(min(scaled, d)):
        e[a] = s * (e0[a] + row[a]) - row[a]


@leaf
def _scale_into(e0, row, scaled, s, e, H, Hc) -> None:
    """:func:`scaled_error_into`, with the scaled rows' state and other calibration columns times
    ``s`` and ``Hc[:, 7] = e0 + z`` there (0 below)."""
    d = e0.shape[0]
    scaled_error_into(e0, row, scaled, s, e)
    for a in range(d):
        Hc[a, 7] = 0.0
    for a in range(min(scaled, d)):
        Hc[a, 7] = e0[a] + row[a]
        for c in range(H.shape[1]):
            H[a, c] *= s
        for c in range(7):
            Hc[a, c] *= s


@leaf
def _through_step(H0, F, rate, at, with_time, H, Hc) -> None:
    """Columns ``at:at+15`` of the state Jacobian ``H = H0 F`` (``H0`` without ``with_time``) and
    the time offset's column ``Hc[:, 0] += H0 rate`` of one state's part of a residual."""
    for a in range(H0.shape[0]):
        if with_time:
            t = 0.0
            for b in range(STATE_DIM):
                t += H0[a, at + b] * rate[b]
            Hc[a, 0] += t
            for c in range(STATE_DIM):
                acc = 0.0
                for b in range(STATE_DIM):
                    acc += H0[a, at + b] * F[b, c]
                H[a, at + c] = acc
        else:
            for c in range(STATE_DIM):
                H[a, at + c] = H0[a, at + c]


@leaf
def one_state_into(lay, v, C, b_w, row, e0, H0, F, rate, with_time, s, e, H, Hc) -> None:
    """A one-state model's calibrated residual (module docstring) from the model's own ``e0 (d)``,
    ``H0 (d, 15)``, evaluated at the stepped state (whose ``v, C, b_w`` are given) with the
    calibrated ``row``; the step's ``F`` and the state's ``rate`` where ``with_time``; ``lay`` the
    model's :func:`layout`, ``s`` the scale. Writes ``e (d)``, ``H (d, 15)``, ``Hc (d, 8)``."""
    d = e0.shape[0]
    lever_at, gyro_at = lay[1], lay[3]
    for a in range(d):
        for c in range(CALIBRATION_DIM):
            Hc[a, c] = 0.0
    _through_step(H0, F, rate, 0, with_time, H, Hc)
    if gyro_at >= 0:  # R_BS^T (v + w x p): rotation H_v u^x, lever arm H_v w^x
        w0, w1, w2 = row[gyro_at] - b_w[0], row[gyro_at + 1] - b_w[1], row[gyro_at + 2] - b_w[2]
        p0, p1, p2 = row[lever_at], row[lever_at + 1], row[lever_at + 2]
        u0, u1, u2 = v[0] + w1 * p2 - w2 * p1, v[1] + w2 * p0 - w0 * p2, v[2] + w0 * p1 - w1 * p0
        for a in range(d):
            h0, h1, h2 = H0[a, 3], H0[a, 4], H0[a, 5]
            Hc[a, 1], Hc[a, 2], Hc[a, 3] = h1 * u2 - h2 * u1, h2 * u0 - h0 * u2, h0 * u1 - h1 * u0
            Hc[a, 4], Hc[a, 5], Hc[a, 6] = h1 * w2 - h2 * w1, h2 * w0 - h0 * w2, h0 * w1 - h1 * w0
    else:
        if lever_at >= 0:  # through r + C p: H_r C
            for a in range(d):
                for c in range(3):
                    Hc[a, 4 + c] = H0[a, 0] * C[0, c] + H0[a, 1] * C[1, c] + H0[a, 2] * C[2, c]
        if lay[0] >= 0:  # through the attitude C R_BS: H_phi C
            for a in range(lay[4], lay[5]):
                for c in range(3):
                    Hc[a, 1 + c] = H0[a, 6] * C[0, c] + H0[a, 7] * C[1, c] + H0[a, 8] * C[2, c]
    _scale_into(e0, row, lay[2], s, e, H, Hc)


_STATE_PART = 3 + 3 + 9 + STATE_DIM * STATE_DIM + STATE_DIM
#: Length of the work array of one calibrated residual (:func:`work_array`): per state its stepped
#: copy ``(r, v, C)``, the step's transition and the state's rate; the calibrated row; the model's
#: residual and Jacobian; the Euler step's own work. Allocated once per loop over measurements,
#: not per measurement.
WORK_SIZE = (2 * _STATE_PART + sm.MAX_ROW_WIDTH + sm.MAX_RESIDUAL_DIM * (1 + 2 * STATE_DIM)
             + imu.STEPPED_WORK)


@recursion
def work_array() -> np.ndarray:
    """A work array for :func:`calibrated_odometry_into` and
    :func:`datasets.kinds.calibrated_into` (:data:`WORK_SIZE`)."""
    return np.empty(WORK_SIZE)


@block_operation
def state_part(work, i):
    """State ``i``'s (0, 1) part of ``work``: views ``(r, v, C, F, rate)``."""
    o = i * _STATE_PART
    return (work[o:o + 3], work[o + 3:o + 6], work[o + 6:o + 15].reshape((3, 3)),
            work[o + 15:o + 240].reshape((STATE_DIM, STATE_DIM)), work[o + 240:o + _STATE_PART])


@block_operation
def model_part(work, width, d, ncol):
    """The rest of ``work``: views ``(calibrated row (width), e0 (d), H0 (d, ncol), step work)``."""
    o = 2 * _STATE_PART
    row = work[o:o + width]
    o += sm.MAX_ROW_WIDTH
    e0 = work[o:o + d]
    o += sm.MAX_RESIDUAL_DIM
    H0 = work[o:o + d * ncol].reshape((d, ncol))
    o += sm.MAX_RESIDUAL_DIM * 2 * STATE_DIM
    return row, e0, H0, work[o:o + imu.STEPPED_WORK]


@recursion
def calibrated_odometry_into(r_i, v_i, C_i, bf_i, bw_i, r_j, v_j, C_j, bf_j, bw_j, row, cal, with_time, acc_i, gyro_i,
                             acc_j, gyro_j, g, e, H, Hc, work, jacobians) -> None:
    """``e (6)``, ``H (6, 30)``, ``H_c (6, 8)`` of one relative pose ``row``
    (:func:`factors.sensor_models.pack_odometry`) between two states through the packed
    calibration ``cal`` (module docstring), with the IMU readings held at the two stamps where
    ``with_time``; ``e`` alone (``H``, ``H_c`` untouched) without ``jacobians``; ``work`` from
    :func:`work_array`."""
    xr_i, xv_i, xC_i, F_i, rate_i = state_part(work, 0)
    xr_j, xv_j, xC_j, F_j, rate_j = state_part(work, 1)
    calibrated, e0, H0, step = model_part(work, row.shape[0], 6, 2 * STATE_DIM)
    if with_time:
        imu.stepped_into(r_i, v_i, C_i, bf_i, bw_i, acc_i, gyro_i, cal[0], g, xr_i, xv_i, xC_i, F_i, rate_i, step,
                         jacobians)
        imu.stepped_into(r_j, v_j, C_j, bf_j, bw_j, acc_j, gyro_j, cal[0], g, xr_j, xv_j, xC_j, F_j, rate_j, step,
                         jacobians)
    else:
        xr_i[:], xC_i[:, :], xr_j[:], xC_j[:, :] = r_i, C_i, r_j, C_j
    calibrated_row_into(row, sm.ODOMETRY_ROTATION_AT, sm.ODOMETRY_LEVER_AT, cal, calibrated)
    sm.odometry_kernel(xr_i, xC_i, xr_j, xC_j, calibrated, e0, H0)
    if not jacobians:
        scaled_error_into(e0, calibrated, sm.ODOMETRY_SCALED, cal[_S_AT], e)
        return
    for a in range(6):
        for c in range(CALIBRATION_DIM):
            Hc[a, c] = 0.0
    _through_step(H0, F_i, rate_i, 0, with_time, H, Hc)
    _through_step(H0, F_j, rate_j, STATE_DIM, with_time, H, Hc)
    D, dC, K = np.empty(3), np.empty((3, 3)), np.empty((3, 3))  # D, C_j - C_i, H_rj D^x
    for a in range(3):
        D[a] = xr_j[a] - xr_i[a]
        for b in range(3):
            D[a] += (xC_j[a, b] - xC_i[a, b]) * cal[_P_AT + b]
            dC[a, b] = xC_j[a, b] - xC_i[a, b]
    for a in range(3):
        h0, h1, h2 = H0[a, 15], H0[a, 16], H0[a, 17]
        K[a, 0], K[a, 1], K[a, 2] = h1 * D[2] - h2 * D[1], h2 * D[0] - h0 * D[2], h0 * D[1] - h1 * D[0]
    for a in range(3):
        for c in range(3):
            Hc[a, 1 + c] = K[a, 0] * xC_i[0, c] + K[a, 1] * xC_i[1, c] + K[a, 2] * xC_i[2, c]
            Hc[3 + a, 1 + c] = H0[3 + a, 21] * dC[0, c] + H0[3 + a, 22] * dC[1, c] + H0[3 + a, 23] * dC[2, c]
            Hc[a, 4 + c] = H0[a, 15] * dC[0, c] + H0[a, 16] * dC[1, c] + H0[a, 17] * dC[2, c]
    _scale_into(e0, calibrated, sm.ODOMETRY_SCALED, cal[_S_AT], e, H, Hc)


@recursion
def _calibrated_odometry_rows(r_i, v_i, C_i, bf_i, bw_i, r_j, v_j, C_j, bf_j, bw_j, rows, cal, with_time, acc_i,
                              gyro_i, acc_j, gyro_j, g, e, H, Hc, jacobians) -> None:
    work = work_array()
    for n in range(rows.shape[0]):
        calibrated_odometry_into(r_i[n], v_i[n], C_i[n], bf_i[n], bw_i[n], r_j[n], v_j[n], C_j[n], bf_j[n], bw_j[n],
                                 rows[n], cal, with_time, acc_i[n], gyro_i[n], acc_j[n], gyro_j[n], g, e[n],
                                 H[n if jacobians else 0], Hc[n if jacobians else 0], work, jacobians)


def state_rows(states: imu.ImuState, n: int) -> list:
    """``(r, v, C, b_f, b_w)`` of ``states`` as the compiled row loops take them (``n`` rows)."""
    return rows((n,), (states.r, states.v, states.C, states.b_f, states.b_w), ((3,), (3,), (3, 3), (3,), (3,)))


def readings(imu_at, n: int) -> tuple[bool, list]:
    """``(with_time, [acc, gyro])`` of the IMU readings held at ``n`` stamps (None: no time
    offset, zeros)."""
    if imu_at is None:
        return False, [np.zeros((n, 3)), np.zeros((n, 3))]
    return True, rows((n,), imu_at, ((3,), (3,)))


def residual_arrays(n: int, d: int, state_width: int, jacobians: bool) -> tuple:
    """``e (n, d)``, ``H``, ``H_c`` for ``n`` calibrated residuals of dimension ``d`` over
    ``state_width`` error-state columns: ``n`` rows of the Jacobians, or one scratch row of each
    without ``jacobians`` (the row loops then write none of them)."""
    m = n if jacobians else 1
    return np.empty((n, d)), np.empty((m, d, state_width)), np.empty((m, d, CALIBRATION_DIM))


def calibrated_odometry_residual(states_i: imu.ImuState, states_j: imu.ImuState, rows_: np.ndarray, c: Calibration,
                                 imu_at=None, gravity=imu.DEFAULT_GRAVITY, jacobians: bool = True):
    """``(e (N, 6), H (N, 6, 30), H_c (N, 6, 8))`` of relative pose ``rows_``
    (:func:`factors.sensor_models.pack_odometry`) between ``states_i`` and ``states_j`` through
    ``c``; ``imu_at = ((acc_i, gyro_i), (acc_j, gyro_j))`` at the two stamps, or None
    (:func:`calibrated_odometry_into`); without ``jacobians`` ``(e, None, None)``."""
    n = len(rows_)
    with_time, at_i = readings(None if imu_at is None else imu_at[0], n)
    _, at_j = readings(None if imu_at is None else imu_at[1], n)
    e, H, Hc = residual_arrays(n, 6, 2 * STATE_DIM, jacobians)
    _calibrated_odometry_rows(*state_rows(states_i, n), *state_rows(states_j, n),
                              np.ascontiguousarray(rows_, dtype=float), packed(c), with_time, *at_i, *at_j,
                              np.asarray(gravity, dtype=float), e, H, Hc, jacobians)
    return (e, H, Hc) if jacobians else (e, None, None)


def applicable(model: sm.SensorModel | None) -> tuple[str, ...]:
    """The calibration parts a model (None: a relative pose) can estimate: a time offset always,
    a rotation where its rows hold ``R_BS``, a lever arm where they hold ``p_BS``, a scale where
    it has scaled rows."""
    if model is None:
        return PARTS
    return tuple(p for p, ok in zip(PARTS, (True, model.rotation_at is not None, model.lever_at is not None,
                                            model.scaled > 0)) if ok)


@dataclass(frozen=True)
class CalibrationPrior:
    """What a sensor's calibration is to estimate: ``parts`` (of :data:`PARTS`), and the prior's
    standard deviations about the values given (the extrinsic ``T_BS`` and the stamps' offset,
    scale 1): ``time_offset`` [s], ``rotation`` [rad, each axis of the left chart],
    ``lever_arm`` [m, each axis], ``scale``."""

    parts: tuple[str, ...]
    time_offset: float = 0.1
    rotation: float = 0.1
    lever_arm: float = 0.2
    scale: float = 0.05
    #: The time offset already added to the sensor's stamps (a rig's ``time_offset``): a
    #: calibrated offset is reported as this plus the one estimated beyond it.
    stamp_offset: float = 0.0

    def __post_init__(self):
        parts = tuple(self.parts)
        if not parts:
            raise InputError("calibration: expected at least one part to estimate, of " + ", ".join(PARTS))
        columns(parts)
        if len(set(parts)) != len(parts):
            raise InputError(f"calibration: a part is named twice in {list(parts)}")
        for name in ("time_offset", "rotation", "lever_arm", "scale"):
            value = getattr(self, name)
            if not (np.isfinite(value) and value > 0):
                raise InputError(f"calibration: {name}_sigma: expected a number > 0, got {value!r}")
        object.__setattr__(self, "parts", tuple(p for p in PARTS if p in parts))

    @property
    def columns(self) -> np.ndarray:
        return columns(self.parts)

    @property
    def sigmas(self) -> np.ndarray:
        """The prior's standard deviations of the estimated coordinates (:attr:`columns`)."""
        full = np.repeat([self.time_offset, self.rotation, self.lever_arm, self.scale], [1, 3, 3, 1])
        return full[self.columns]


def checked_prior(prior, kind: str, model: sm.SensorModel | None, where: str) -> "CalibrationPrior":
    """``prior``, a :class:`CalibrationPrior` whose parts a ``kind`` sensor (its ``model``) can
    estimate (:func:`applicable`), or an InputError naming ``where``."""
    if not isinstance(prior, CalibrationPrior):
        raise InputError(f"{where}: expected a factors.calibration.CalibrationPrior, got {type(prior).__name__}")
    can = applicable(model)
    wrong = [p for p in prior.parts if p not in can]
    if wrong:
        raise InputError(f"{where}: a {kind} sensor cannot estimate {', '.join(wrong)}; it can estimate "
                         f"{', '.join(can)}")
    return prior


@dataclass(frozen=True)
class CalibrationSet:
    """The calibration variables of a problem: each sensor's ``name``, its current ``values``, its
    ``priors`` (:class:`CalibrationPrior`: which coordinates are variables, with their sigmas) and
    the prior's ``means`` (the values given). A step ``delta`` is one array per sensor over its
    estimated coordinates."""

    names: tuple[str, ...]
    values: tuple[Calibration, ...]
    priors: tuple[CalibrationPrior, ...]
    means: tuple[Calibration, ...]

    @staticmethod
    def given(names, extrinsics, priors) -> "CalibrationSet":
        """The variables of sensors ``names`` starting at, and with priors about, the values given:
        each extrinsic ``T_BS`` (None: at the IMU), no further time offset, scale 1."""
        means = tuple(Calibration.of(T) for T in extrinsics)
        return CalibrationSet(tuple(names), means, tuple(priors), means)

    def __len__(self) -> int:
        return len(self.names)

    @property
    def dims(self) -> list[int]:
        return [len(p.columns) for p in self.priors]

    def value_of(self, name: str) -> Calibration | None:
        """The current value of sensor ``name``'s calibration, or None where it has none here."""
        return self.values[self.names.index(name)] if name in self.names else None

    def boxplus(self, delta) -> "CalibrationSet":
        """The values moved by ``delta`` (one array per sensor over its estimated coordinates;
        :func:`set_boxplus_into`, the kernel the EKF runs)."""
        values = np.array([packed(c) for c in self.values]).reshape(len(self), PACKED_SIZE)
        step = np.concatenate([np.zeros(0), *(np.ravel(d) for d in delta)])
        set_boxplus_into(values, *placement(self.priors), step)
        return CalibrationSet(self.names, tuple(unpacked(c) for c in values), self.priors, self.means)


def placement(priors) -> tuple[np.ndarray, np.ndarray]:
    """``(owner, coordinate)``: for each estimated coordinate of calibrations with ``priors``
    (:class:`CalibrationPrior`), in order (a :class:`CalibrationSet`'s step, concatenated), the
    index of its calibration and its place among the 8 error coordinates."""
    owner = [np.full(len(p.columns), j) for j, p in enumerate(priors)]
    return (np.concatenate([np.zeros(0), *owner]).astype(np.int64),
            np.concatenate([np.zeros(0), *(p.columns for p in priors)]).astype(np.int64))


@recursion
def set_boxplus_into(values, owner, coordinate, step) -> None:
    """Packed calibrations ``values (J, PACKED_SIZE)`` moved in place by ``step``, their estimated
    coordinates concatenated as :func:`placement`'s ``owner`` and ``coordinate`` place them, each
    by :func:`boxplus_into` (zero in the coordinates not estimated)."""
    delta = np.empty(CALIBRATION_DIM)
    for j in range(values.shape[0]):
        delta[:] = 0.0
        for k in range(owner.shape[0]):
            if owner[k] == j:
                delta[coordinate[k]] = step[k]
        boxplus_into(values[j], delta)
