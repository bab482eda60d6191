"""Measurement models of sensors mounted anywhere on the body, in the primer's convention.

A sensor's frame ``S`` is fixed to the body (IMU) frame ``B`` by its extrinsic ``T_BS``:
``p_B = R_BS p_S + p_BS`` (``p_BS``, the sensor's origin in the IMU frame). With the state
``x = (r, v, C, b_f, b_w)`` (world position, BODY velocity, ``C = C(Phi_IB)``, biases) the sensor
frame's pose in the world is ``(r + C p_BS, C R_BS)``. The models (``docs/design.md``, sensors):

=============  ===========================================  ====================================
model          prediction ``h(x)``                          residual ``e``
=============  ===========================================  ====================================
position       ``r + C p_BS`` (a GNSS antenna)              ``h - z``
orientation    ``C R_BS``                                   ``log(C R_BS Z^T)``
pose           both of the above                            ``(r + C p_BS - z, log(C R_BS Z^T))``
velocity       ``R_BS^T (v + (w - b_w) x p_BS)``            ``h - z``
roll_pitch     ``u = R_BS^T C^T e_z`` (up, in ``S``)        ``((Z u)_y, -(Z u)_x)``
altitude       ``e_z^T (r + C p_BS)`` (a barometer)         ``h - z``
magnetometer   ``u = R_BS^T C^T m`` (the field's direction  ``B_z^T u`` (``B_z``: a basis of the
               ``m`` in ``S``)                              plane normal to the measured ``z``)
=============  ===========================================  ====================================

``w`` is the gyro sample at the measurement time: the sensor frame moves with the body, so its
velocity in its own frame is the body velocity plus the lever arm's ``omega x p_BS``, rotated into
``S``. Noise: ``z = h + n`` for vectors; ``Z = exp(n) C_IS`` (world-frame attitude noise, as the
pose sensor of primer eqs. 61-63) for attitudes, so ``e_phi`` has the covariance of ``n``.

Jacobians with respect to the error state ``(dr, dv, dphi, db_f, db_w)`` (LEFT boxplus
``C <- exp(dphi) C``), derived from the primer's identities:

* ``d(C p)/dphi = -(C p)^x``: ``exp(dphi) C p ~ C p + dphi x C p`` (eqs. 3, 27);
* ``d log(C R Z^T)/dphi = Gamma^-1(e)``: ``exp(dphi) X`` moves ``log X`` by ``Gamma^-1(log X) dphi``
  (eqs. 24, 32);
* ``d/db_w (w - b_w) x p = p^x`` (the cross product is linear; ``a x p = -p^x a``).

Each model is ONE compiled kernel with the signature ``kernel(r, v, C, b_f, b_w, row, e, H)``:
``row`` holds the measurement and the extrinsic (the layout is the model's ``pack``), ``e (d,)``
receives the residual and ``H (d, 15)`` its error-state Jacobian (every entry written). The EKF
(``smoother.ekf.filter``), the batch solver's blocks and the GTSAM factors (:func:`sensor_factor`) all
run these kernels; there is no second copy of any formula.

Relative poses of a sensor (odometry of a drifting source) connect two states; their model is
:func:`odometry_residual` (sensor frame ``S_i``; ``dr = R_BS^T C_i^T (r_j + C_j p - r_i - C_i p)``,
``dC = R_BS^T C_i^T C_j R_BS``).
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Callable

import gtsam
import numpy as np
from numba import njit

from factors import so3
from factors.custom import BIAS, ROT, VEC, custom_factor
from factors.errors import InputError
from factors.imu import STATE_DIM, ImuState

#: The widest kernel row and the largest residual dimension the estimators hold room for (the EKF's
#: batched updates, the sliding window's measurement store); the kinds registry refuses a kind
#: beyond them.
MAX_ROW_WIDTH = 24
MAX_RESIDUAL_DIM = 6


def extrinsic_parts(T_BS) -> tuple[np.ndarray, np.ndarray]:
    """``(R_BS, p_BS)`` of a 4x4 extrinsic (identity when ``T_BS`` is None)."""
    if T_BS is None:
        return np.eye(3), np.zeros(3)
    T = np.asarray(T_BS, dtype=float)
    return T[:3, :3].copy(), T[:3, 3].copy()


@njit(cache=True)
def _rotated_lever_into(C, p, Cp, H_rows, first_row) -> None:
    """``Cp = C p`` and ``H[first_row:first_row + 3, 6:9] = -(C p)^x``."""
    for a in range(3):
        Cp[a] = C[a, 0] * p[0] + C[a, 1] * p[1] + C[a, 2] * p[2]
    x, y, z = Cp[0], Cp[1], Cp[2]
    i = first_row
    H_rows[i, 6], H_rows[i, 7], H_rows[i, 8] = 0.0, z, -y
    H_rows[i + 1, 6], H_rows[i + 1, 7], H_rows[i + 1, 8] = -z, 0.0, x
    H_rows[i + 2, 6], H_rows[i + 2, 7], H_rows[i + 2, 8] = y, -x, 0.0


@njit(cache=True)
def orientation_error_into(C, measured, e, J) -> None:
    """``e (3) = log(C C_meas^T)`` and ``J (3x3) = Gamma^-1(e)`` for one attitude (eqs. 62, 63;
    the derivative of log, eq. 32): the one attitude residual of the project
    (every sensor model's attitude part runs it)."""
    e[0], e[1], e[2] = so3.boxminus_of(C, measured)
    so3.gamma_inv_into(e[0], e[1], e[2], J)


#: The residual rows where an orientation's and a pose's attitude errors begin, as run-time values:
#: literal arguments would compile a copy of :func:`_attitude_error_into` for each.
_ORIENTATION_ROWS, _POSE_ATTITUDE_ROWS = np.int64(0), np.int64(3)


@njit(cache=True)
def _attitude_error_into(C, R, Z, e, H, first_row) -> None:
    """``e[first_row:+3] = log(C R Z^T)`` and ``H[first_row:+3, 6:9] = Gamma^-1(e)``."""
    CR = np.empty((3, 3))
    for a in range(3):
        for b in range(3):
            CR[a, b] = C[a, 0] * R[0, b] + C[a, 1] * R[1, b] + C[a, 2] * R[2, b]
    G = np.empty((3, 3))
    orientation_error_into(CR, Z, e[first_row:first_row + 3], G)
    H[first_row:first_row + 3, 6:9] = G


# Row layouts (flat float64): position (z 3, p 3); orientation (Z 9, R 9); pose (z 3, Z 9, R 9, p 3);
# velocity (z 3, w 3, R 9, p 3); roll_pitch (Z 9, R 9); altitude (z 1, p 3); magnetometer (z 3, B 6, m 3, R 9).


@njit(cache=True)
def _origin_error_into(r, C, z, p, e, H) -> None:
    """``e[0:3] = r + C p - z``, ``H[0:3, 0:3] = I``, ``H[0:3, 6:9] = -(C p)^x``."""
    Cp = np.empty(3)
    _rotated_lever_into(C, p, Cp, H, 0)
    for a in range(3):
        e[a] = r[a] + Cp[a] - z[a]
        H[a, a] = 1.0


@njit(cache=True)
def position_kernel(r, v, C, b_f, b_w, row, e, H) -> None:
    """Antenna position ``r + C p_BS`` minus the measured one; ``row = (z, p_BS)``."""
    H[:, :] = 0.0
    _origin_error_into(r, C, row[0:3], row[3:6], e, H)


@njit(cache=True)
def orientation_kernel(r, v, C, b_f, b_w, row, e, H) -> None:
    """``log(C R_BS Z^T)``; ``row = (Z, R_BS)`` (row-major 3x3 each)."""
    H[:, :] = 0.0
    _attitude_error_into(C, row[9:18].reshape((3, 3)), row[0:9].reshape((3, 3)), e, H, _ORIENTATION_ROWS)


@njit(cache=True)
def pose_kernel(r, v, C, b_f, b_w, row, e, H) -> None:
    """``(r + C p_BS - z, log(C R_BS Z^T))``; ``row = (z, Z, R_BS, p_BS)``."""
    H[:, :] = 0.0
    _origin_error_into(r, C, row[0:3], row[21:24], e, H)
    _attitude_error_into(C, row[12:21].reshape((3, 3)), row[3:12].reshape((3, 3)), e, H, _POSE_ATTITUDE_ROWS)


@njit(cache=True)
def velocity_kernel(r, v, C, b_f, b_w, row, e, H) -> None:
    """``R_BS^T (v + (w - b_w) x p_BS) - z``; ``row = (z, w, R_BS, p_BS)``."""
    H[:, :] = 0.0
    R = row[6:15].reshape((3, 3))
    p = row[15:18]
    wx, wy, wz = row[3] - b_w[0], row[4] - b_w[1], row[5] - b_w[2]
    u = np.empty(3)  # v + omega x p, in the body frame
    u[0] = v[0] + wy * p[2] - wz * p[1]
    u[1] = v[1] + wz * p[0] - wx * p[2]
    u[2] = v[2] + wx * p[1] - wy * p[0]
    P = np.empty((3, 3))  # p^x = d(omega x p)/d b_w
    P[0, 0], P[0, 1], P[0, 2] = 0.0, -p[2], p[1]
    P[1, 0], P[1, 1], P[1, 2] = p[2], 0.0, -p[0]
    P[2, 0], P[2, 1], P[2, 2] = -p[1], p[0], 0.0
    for a in range(3):
        e[a] = R[0, a] * u[0] + R[1, a] * u[1] + R[2, a] * u[2] - row[a]
        for b in range(3):
            H[a, 3 + b] = R[b, a]
            H[a, 12 + b] = R[0, a] * P[0, b] + R[1, a] * P[1, b] + R[2, a] * P[2, b]


@njit(cache=True)
def roll_pitch_kernel(r, v, C, b_f, b_w, row, e, H) -> None:
    """The attitude error without its heading: the tilt between the measured and the predicted
    vertical. ``row = (Z, R_BS)`` as :func:`orientation_kernel`'s; ``e (2)``, ``H (2, 15)``.

    With ``M = Z R_BS^T C^T`` (``= E^T`` for the attitude error ``E = C R_BS Z^T``), ``M e_z = Z u``
    is the predicted up direction of the sensor frame, ``u = R_BS^T C^T e_z``, carried into the
    world by the MEASURED attitude; it is ``e_z`` when the two agree in roll and pitch, whatever
    their headings. The residual is its horizontal part turned by 90 degrees,
    ``e = ((M e_z)_y, -(M e_z)_x)``:

    * heading-free: a turn of the state about the world vertical, ``C <- Rz C``, leaves ``u``
      (``Rz^T e_z = e_z``) and so ``e`` exactly unchanged; ``H``'s column of ``dphi_z`` is 0;
    * small errors: ``E = exp(eps)`` gives ``M e_z = e_z - eps x e_z``, i.e. ``e = (eps_x, eps_y)``
      to first order, the tilt components of ``log(C R_BS Z^T)``; with the measurement noise
      ``Z = exp(n) C R_BS`` (world axes) ``e = -(n_x, n_y)``: its covariance is the upper-left
      2x2 block of the attitude covariance, and the noise about the vertical does not enter;
    * defined at every attitude, upside-down and any heading included: ``e`` is a smooth function
      of ``C`` (no angle is extracted); ``|e| = sin`` of the angle between the two verticals, 0
      only when they agree or are opposite (a tilt error of 180 degrees, no AHRS's output);
    * Jacobian: ``d(C^T a)/dphi = C^T a^x`` (the coordinate map of the inverse, primer eqs. 27,
      28: ``(exp(dphi) C)^T a ~ C^T (a - dphi x a) = C^T a + C^T a^x dphi``), so
      ``d(M e_z)/dphi = M e_z^x``, whose columns are ``(M[:, 1], -M[:, 0], 0)``.
    """
    H[:, :] = 0.0
    Z = row[0:9].reshape((3, 3))
    R = row[9:18].reshape((3, 3))
    CR = np.empty((3, 3))
    for a in range(3):
        for b in range(3):
            CR[a, b] = C[a, 0] * R[0, b] + C[a, 1] * R[1, b] + C[a, 2] * R[2, b]
    M = np.empty((3, 3))  # Z (C R)^T
    for a in range(3):
        for b in range(3):
            M[a, b] = Z[a, 0] * CR[b, 0] + Z[a, 1] * CR[b, 1] + Z[a, 2] * CR[b, 2]
    e[0] = M[1, 2]
    e[1] = -M[0, 2]
    H[0, 6], H[0, 7] = M[1, 1], -M[1, 0]
    H[1, 6], H[1, 7] = -M[0, 1], M[0, 0]


@njit(cache=True)
def altitude_kernel(r, v, C, b_f, b_w, row, e, H) -> None:
    """The height of the sensor's origin, ``e_z^T (r + C p_BS)``, minus the measured one;
    ``row = (z, p_BS)``. ``H = [e_z^T, 0, -e_z^T (C p)^x, 0, 0]`` (``d(C p)/dphi = -(C p)^x``)."""
    H[:, :] = 0.0
    p = row[1:4]
    x = C[0, 0] * p[0] + C[0, 1] * p[1] + C[0, 2] * p[2]
    y = C[1, 0] * p[0] + C[1, 1] * p[1] + C[1, 2] * p[2]
    z = C[2, 0] * p[0] + C[2, 1] * p[1] + C[2, 2] * p[2]
    e[0] = r[2] + z - row[0]
    H[0, 2] = 1.0
    H[0, 6], H[0, 7] = y, -x


@njit(cache=True)
def magnetometer_kernel(r, v, C, b_f, b_w, row, e, H) -> None:
    """The direction of the world's magnetic field in the sensor frame against the measured one:
    ``row = (z, b_1, b_2, m, R_BS)`` with ``z`` the measured unit direction, ``b_1, b_2`` an
    orthonormal basis of the plane normal to it (:func:`pack_magnetometer`), ``m`` the world
    field's unit direction. ``e (2) = (b_i^T u)`` with ``u = R_BS^T C^T m``: the components of
    the predicted direction across the measured one, 0 when they agree (``|e|`` the sine of the
    angle between them). With ``g_i = C R_BS b_i`` (world) ``e_i = g_i^T m`` and, by
    ``d(C^T m)/dphi = C^T m^x`` (primer eqs. 27, 28), ``d e_i/dphi = b_i^T R^T C^T m^x =
    (g_i x m)^T``. Measurement noise ``n`` on the field vector ``f`` (sensor frame) moves ``z`` by
    ``(I - z z^T) n / |f|``, so ``cov(e) = B^T cov(n) B / |f|^2``."""
    H[:, :] = 0.0
    R = row[12:21].reshape((3, 3))
    m = row[9:12]
    for i in range(2):
        b = row[3 + 3 * i: 6 + 3 * i]
        g = np.empty(3)  # C R b
        for a in range(3):
            s = 0.0
            for k in range(3):
                s += (C[a, 0] * R[0, k] + C[a, 1] * R[1, k] + C[a, 2] * R[2, k]) * b[k]
            g[a] = s
        e[i] = g[0] * m[0] + g[1] * m[1] + g[2] * m[2]
        H[i, 6] = g[1] * m[2] - g[2] * m[1]
        H[i, 7] = g[2] * m[0] - g[0] * m[2]
        H[i, 8] = g[0] * m[1] - g[1] * m[0]


def _flat(*arrays) -> np.ndarray:
    """Rows of the measurements ``arrays`` (each with a leading dimension N: one row a
    measurement; a single measurement is refused rather than read as N rows)."""
    first = np.asarray(arrays[0], dtype=float)
    if first.ndim < 2:
        raise InputError(f"pack: expected measurements with a leading dimension (N, ...), got shape {first.shape}")
    n = len(first)
    return np.concatenate([np.reshape(np.asarray(a, dtype=float), (n, -1)) for a in arrays], axis=1)


def _checked_row(model: "SensorModel", row) -> np.ndarray:
    row = np.ascontiguousarray(row, dtype=float)
    if row.shape != (model.width,):
        raise InputError(f"{model.name} measurement row: expected {model.width} numbers (its pack_* layout), "
                         f"got shape {row.shape}")
    return row


def _repeat(a: np.ndarray, n: int) -> np.ndarray:
    """``a`` as ``n`` rows (a view; ``np.broadcast_to`` costs 2 us, a measurement's whole check)."""
    return a[None] if n == 1 else np.broadcast_to(a, (n,) + a.shape)


def pack_position(z, T_BS=None) -> np.ndarray:
    z = np.asarray(z, dtype=float)
    _, p = extrinsic_parts(T_BS)
    return _flat(z, _repeat(p, len(z)))


def pack_orientation(Z, T_BS=None) -> np.ndarray:
    Z = np.asarray(Z, dtype=float)
    R, _ = extrinsic_parts(T_BS)
    return _flat(Z, _repeat(R, len(Z)))


def pack_pose(z, Z, T_BS=None) -> np.ndarray:
    z = np.asarray(z, dtype=float)
    R, p = extrinsic_parts(T_BS)
    return _flat(z, Z, _repeat(R, len(z)), _repeat(p, len(z)))


def pack_velocity(z, w, T_BS=None) -> np.ndarray:
    z = np.asarray(z, dtype=float)
    R, p = extrinsic_parts(T_BS)
    return _flat(z, w, _repeat(R, len(z)), _repeat(p, len(z)))


def pack_altitude(z, T_BS=None) -> np.ndarray:
    z = np.asarray(z, dtype=float)
    _, p = extrinsic_parts(T_BS)
    return _flat(np.reshape(z, (-1, 1)), _repeat(p, len(z)))


def normal_basis(z) -> np.ndarray:
    """``(N, 2, 3)``: for each unit vector ``z`` (N, 3) two unit vectors normal to it and to each
    other, ``(b_1, b_2, z)`` right-handed (``b_1`` from the axis least aligned with ``z``)."""
    z = np.asarray(z, dtype=float)
    axis = np.where((np.abs(z[:, 0]) < 0.9)[:, None], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0])
    b1 = axis - np.sum(axis * z, axis=1, keepdims=True) * z
    b1 /= np.linalg.norm(b1, axis=1, keepdims=True)
    return np.stack([b1, np.cross(z, b1)], axis=1)


def pack_magnetometer(z, m, T_BS=None) -> np.ndarray:
    """Rows of measured field directions ``z`` (N, 3; made unit) against the world field's
    direction ``m`` ((3,) or (N, 3); made unit)."""
    z = np.asarray(z, dtype=float)
    z = z / np.linalg.norm(z, axis=-1, keepdims=True)
    m = np.broadcast_to(np.asarray(m, dtype=float), z.shape)
    m = m / np.linalg.norm(m, axis=-1, keepdims=True)
    R, _ = extrinsic_parts(T_BS)
    return _flat(z, normal_basis(z), m, _repeat(R, len(z)))


#: Which GTSAM variables (keyframe keys) a model reads, by the error-state columns it may touch.
_VARIABLE_COLUMNS = {"pos": slice(0, 3), "vel": slice(3, 6), "rot": slice(6, 9), "bias": slice(9, 15)}
_VARIABLE_KINDS = {"pos": VEC, "vel": VEC, "rot": ROT, "bias": BIAS}


@dataclass(frozen=True)
class SensorModel:
    """One measurement model: its residual dimension ``dim``, the row width of its data, its
    compiled ``kernel`` (module docstring) and the keyframe variables it depends on
    (``variables``, a subset of ``pos, vel, rot, bias``: the GTSAM keys of its factor).

    Where its rows hold the extrinsic (what a calibration replaces, :mod:`factors.calibration`):
    ``rotation_at``, the first of the nine numbers of ``R_BS`` (row-major), ``lever_at``, the first
    of the three of ``p_BS`` (None: the model does not read it); ``scaled``, how many leading
    residual rows are ``h - z`` with ``z = row[:scaled]`` a reading that a sensor's scale
    multiplies (a velocity; 0: none)."""

    name: str
    dim: int
    width: int
    kernel: Callable
    variables: tuple[str, ...]
    rotation_at: int | None = None
    lever_at: int | None = None
    scaled: int = 0


POSITION = SensorModel("position", 3, 6, position_kernel, ("pos", "rot"), lever_at=3)
ORIENTATION = SensorModel("orientation", 3, 18, orientation_kernel, ("rot",), rotation_at=9)
POSE = SensorModel("pose", 6, 24, pose_kernel, ("pos", "rot"), rotation_at=12, lever_at=21)
VELOCITY = SensorModel("velocity", 3, 18, velocity_kernel, ("vel", "bias"), rotation_at=6, lever_at=15, scaled=3)
ROLL_PITCH = SensorModel("roll_pitch", 2, 18, roll_pitch_kernel, ("rot",), rotation_at=9)
ALTITUDE = SensorModel("altitude", 1, 4, altitude_kernel, ("pos", "rot"), lever_at=1)
MAGNETOMETER = SensorModel("magnetometer", 2, 21, magnetometer_kernel, ("rot",), rotation_at=12)


def evaluate_one(model: SensorModel, state: ImuState, row: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``(e (d,), H (d, 15))`` of one measurement ``row`` at one state."""
    e, H = np.empty(model.dim), np.empty((model.dim, STATE_DIM))
    model.kernel(*(np.ascontiguousarray(a, dtype=float) for a in (state.r, state.v, state.C, state.b_f, state.b_w)),
                 _checked_row(model, row), e, H)
    return e, H


def sensor_factor(model: SensorModel, keys, row, noise_model) -> gtsam.CustomFactor:
    """A GTSAM factor of one measurement ``row`` on a keyframe's ``keys``
    (:class:`factors.keys.KeyframeKeys`); only the variables the model reads become its keys, and
    the rotation block passes through the chart adapter (:func:`factors.custom.custom_factor`)."""
    row = _checked_row(model, row)
    names = model.variables
    zero3 = np.zeros(3)

    def residual(*args, jacobians):
        given = dict(zip(names, args))
        b = given.get("bias")
        e, H = np.empty(model.dim), np.empty((model.dim, STATE_DIM))
        model.kernel(given.get("pos", zero3), given.get("vel", zero3), given.get("rot", np.eye(3)),
                     zero3 if b is None else b[:3].copy(), zero3 if b is None else b[3:].copy(), row, e, H)
        return (e, [H[:, _VARIABLE_COLUMNS[n]] for n in names]) if jacobians else e

    return custom_factor(noise_model, [getattr(keys, n) for n in names], [_VARIABLE_KINDS[n] for n in names],
                         residual)


#: Row layout of a relative pose (odometry) measurement: ``(dr 3, dC 9, R_BS 9, p_BS 3)``.
ODOMETRY_WIDTH = 24
#: Where an odometry row holds its extrinsic, and the residual rows a scale multiplies (``dr``),
#: as :class:`SensorModel` declares them for the one-state models.
ODOMETRY_ROTATION_AT, ODOMETRY_LEVER_AT, ODOMETRY_SCALED = 12, 21, 3


def pack_odometry(dr, dC, T_BS=None) -> np.ndarray:
    dr = np.asarray(dr, dtype=float)
    R, p = extrinsic_parts(T_BS)
    return _flat(dr, dC, _repeat(R, len(dr)), _repeat(p, len(dr)))


@njit(cache=True)
def odometry_kernel(r_i, C_i, r_j, C_j, row, e, H) -> None:
    """Relative pose of the sensor frame between two states, in ``S_i``:
    ``e = (R^T C_i^T (r_j + C_j p - r_i - C_i p) - dr_meas, log(R^T C_i^T C_j R dC_meas^T))`` with
    ``row = (dr_meas, dC_meas, R, p)`` (:data:`ODOMETRY_WIDTH`); ``H (6, 30)``: the error-state
    Jacobians of state ``i`` (columns 0-14) and ``j`` (15-29), every entry written.

    With ``w = r_j - r_i + C_j p`` and ``M = R^T C_i^T``: ``d e_r/dphi_i = M w^x`` (the ``-C_i p``
    term's motion joins ``w``), ``d e_r/dphi_j = -M (C_j p)^x``, ``d e_r/dr_i = -M``,
    ``d e_r/dr_j = M``; the rotation part moves by ``-+Gamma^-1(e) M`` for ``phi_i`` / ``phi_j``
    (eq. 24 with ``exp(a) X = X exp(X^T a)``)."""
    H[:, :] = 0.0
    R = row[12:21].reshape((3, 3))
    p = row[21:24]
    M = np.empty((3, 3))  # R^T C_i^T
    for a in range(3):
        for b in range(3):
            M[a, b] = R[0, a] * C_i[b, 0] + R[1, a] * C_i[b, 1] + R[2, a] * C_i[b, 2]
    Cjp, Cip, w, d = np.empty(3), np.empty(3), np.empty(3), np.empty(3)
    for a in range(3):
        Cjp[a] = C_j[a, 0] * p[0] + C_j[a, 1] * p[1] + C_j[a, 2] * p[2]
        Cip[a] = C_i[a, 0] * p[0] + C_i[a, 1] * p[1] + C_i[a, 2] * p[2]
    for a in range(3):
        w[a] = r_j[a] - r_i[a] + Cjp[a]
        d[a] = w[a] - Cip[a]
    for a in range(3):
        e[a] = M[a, 0] * d[0] + M[a, 1] * d[1] + M[a, 2] * d[2] - row[a]
    X = np.empty((3, 3))  # M C_j R dC_meas^T
    Y = np.empty((3, 3))
    for a in range(3):
        for b in range(3):
            Y[a, b] = M[a, 0] * C_j[0, b] + M[a, 1] * C_j[1, b] + M[a, 2] * C_j[2, b]
    for a in range(3):
        for b in range(3):
            X[a, b] = Y[a, 0] * R[0, b] + Y[a, 1] * R[1, b] + Y[a, 2] * R[2, b]
    Z = row[3:12].reshape((3, 3))
    for a in range(3):
        for b in range(3):
            Y[a, b] = X[a, 0] * Z[b, 0] + X[a, 1] * Z[b, 1] + X[a, 2] * Z[b, 2]
    e[3], e[4], e[5] = so3.log_of(Y)
    G = np.empty((3, 3))
    so3.gamma_inv_into(e[3], e[4], e[5], G)
    for a in range(3):
        for b in range(3):
            g = G[a, 0] * M[0, b] + G[a, 1] * M[1, b] + G[a, 2] * M[2, b]
            H[3 + a, 6 + b] = -g
            H[3 + a, 21 + b] = g
            H[a, b] = -M[a, b]
            H[a, 15 + b] = M[a, b]
    for b in range(3):  # columns of M w^x and -M (C_j p)^x: M (w x unit_b) etc.
        ux0, ux1, ux2 = (0.0, w[2], -w[1]) if b == 0 else ((-w[2], 0.0, w[0]) if b == 1 else (w[1], -w[0], 0.0))
        uy0, uy1, uy2 = ((0.0, Cjp[2], -Cjp[1]) if b == 0 else
                         ((-Cjp[2], 0.0, Cjp[0]) if b == 1 else (Cjp[1], -Cjp[0], 0.0)))
        for a in range(3):
            H[a, 6 + b] = M[a, 0] * ux0 + M[a, 1] * ux1 + M[a, 2] * ux2
            H[a, 21 + b] = -(M[a, 0] * uy0 + M[a, 1] * uy1 + M[a, 2] * uy2)


@njit(cache=True)
def _odometry_rows(r_i, C_i, r_j, C_j, rows, e, H) -> None:
    for n in range(rows.shape[0]):
        odometry_kernel(r_i[n], C_i[n], r_j[n], C_j[n], rows[n], e[n], H[n])


def odometry_residual(C_i, r_i, C_j, r_j, measured_dr, measured_dC, T_BS=None, jacobians: bool = False):
    """:func:`odometry_kernel` vectorised over broadcast leading dimensions: ``e (..., 6)`` and,
    with ``jacobians``, ``[J_Ci, J_ri, J_Cj, J_rj]`` (each ``(..., 6, 3)``)."""
    C_i, r_i, C_j, r_j = (np.asarray(a, dtype=float) for a in (C_i, r_i, C_j, r_j))
    measured_dr, measured_dC = np.asarray(measured_dr, dtype=float), np.asarray(measured_dC, dtype=float)
    lead = np.broadcast_shapes(C_i.shape[:-2], r_i.shape[:-1], C_j.shape[:-2], r_j.shape[:-1],
                               measured_dr.shape[:-1], measured_dC.shape[:-2])
    n = int(np.prod(lead, dtype=int))
    flat = lambda a, tail: np.ascontiguousarray(np.broadcast_to(a, lead + tail).reshape((n,) + tail))  # noqa: E731
    rows = pack_odometry(flat(measured_dr, (3,)), flat(measured_dC, (3, 3)), T_BS)
    e, H = np.empty((n, 6)), np.empty((n, 6, 30))
    _odometry_rows(flat(r_i, (3,)), flat(C_i, (3, 3)), flat(r_j, (3,)), flat(C_j, (3, 3)), rows, e, H)
    e = e.reshape(lead + (6,))
    if not jacobians:
        return e
    H = H.reshape(lead + (6, 30))
    return e, [H[..., 6:9], H[..., 0:3], H[..., 21:24], H[..., 15:18]]


def evaluate_pair(state_i: ImuState, state_j: ImuState, row: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``(e (6,), H (6, 30))`` of one relative pose ``row`` (:func:`pack_odometry`) between two
    states, ``H`` over both error states side by side."""
    row = np.ascontiguousarray(row, dtype=float)
    if row.shape != (ODOMETRY_WIDTH,):
        raise InputError(f"odometry measurement row: expected {ODOMETRY_WIDTH} numbers (the pack_odometry layout), "
                         f"got shape {row.shape}")
    e, H = np.empty(6), np.empty((6, 2 * STATE_DIM))
    parts = [np.ascontiguousarray(a, dtype=float) for a in (state_i.r, state_i.C, state_j.r, state_j.C)]
    odometry_kernel(*parts, row, e, H)
    return e, H


def odometry_factor(keys_i, keys_j, measured_dr, measured_dC, T_BS, noise_model) -> gtsam.CustomFactor:
    """Relative pose of a sensor between two keyframes (noise in ``S_i``, position first)."""
    mr, mC = np.array(measured_dr, dtype=float), np.array(measured_dC, dtype=float)
    T = None if T_BS is None else np.array(T_BS, dtype=float)
    return custom_factor(
        noise_model, [keys_i.rot, keys_i.pos, keys_j.rot, keys_j.pos], [ROT, VEC, ROT, VEC],
        lambda Ci, ri, Cj, rj, jacobians: odometry_residual(Ci, ri, Cj, rj, mr, mC, T, jacobians),
    )
