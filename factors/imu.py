"""The IMU-driven model of the primer's section VI: state, noise, one Euler-forward step and its
Jacobians.

State ``x = (I_r_IB, B_v_B, Phi_IB, B_b_f, B_b_w)`` (eq. 46): world position, BODY-frame
velocity, attitude ``C = C(Phi_IB)`` (body -> world), accelerometer and gyro bias. The error state
is ``(dr, dv, dphi, db_f, db_w)`` (15 dims, this order) with ``x [+] dx`` adding the vectors and
applying the primer's LEFT boxplus ``exp(dphi) C`` to the attitude.

One step of length ``dt`` with IMU sample ``(f~, w~)`` and discrete noise ``n = (n_v, n_f, n_w,
n_bf, n_bw)``, each ``n_i ~ N(0, R_i / dt)`` (eqs. 54-60)::

    f  = f~ - b_f - n_f,      w = w~ - b_w - n_w
    r' = r + dt C (v + n_v)
    v' = v + dt (C^T g + f - w^x v)
    C' = C exp(dt w)                          (= C [+] dt C w, eq. 56)
    b_f' = b_f + dt n_bf,     b_w' = b_w + dt n_bw

Jacobians (derived from eqs. 25-34; each block is checked numerically in
``factors.selfcheck`` and the tests). With ``Gamma = Gamma(dt w)``::

    F = [ I   dt C          -dt (C v)^x     0       0
          0   I - dt w^x    dt C^T g^x    -dt I   -dt v^x
          0   0             I               0     -dt C Gamma
          0   0             0               I       0
          0   0             0               0       I ]

    G = [ dt C   0       0               0      0
          0     -dt I   -dt v^x          0      0
          0      0      -dt C Gamma      0      0
          0      0       0              dt I    0
          0      0       0               0     dt I ]

The attitude rows come from ``C exp(dt(w - e)) = exp(-dt C Gamma(dt w) e) C exp(dt w)``
(eq. 31, then eq. 24 to move the increment to the left). The primer's typeset F and G print
``-dt C^T Gamma`` in that place; with the left boxplus the numerical Jacobian agrees with
``-dt C Gamma`` and not with ``C^T`` (see ``tests/factors/test_imu.py``).
``v' wrt dphi``: ``d C^T g / d Phi = -(C^T g)^x (-C^T) = C^T g^x`` (eqs. 27, 28, 3).

All functions are vectorised over leading dimensions (a batch of states, samples or both).
"""
from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

from factors import scan, so3
from factors.compiled import block_operation, leaf, recursion
from factors.errors import InputError
from factors.rows import as_trailing, rows

STATE_DIM = 15
NOISE_DIM = 15
#: Slices of the error state and of the noise vector.
R, V, PHI, BF, BW = (slice(0, 3), slice(3, 6), slice(6, 9), slice(9, 12), slice(12, 15))
NV, NF, NW, NBF, NBW = R, V, PHI, BF, BW

DEFAULT_GRAVITY = np.array([0.0, 0.0, -9.81])


@dataclass(frozen=True)
class ImuState:
    """``(r, v, C, b_f, b_w)``: arrays of shape ``(..., 3)`` and ``C`` of shape ``(..., 3, 3)``.

    One state or a whole trajectory (leading dimension = time), always arrays, never per-sample
    objects."""

    r: np.ndarray
    v: np.ndarray
    C: np.ndarray
    b_f: np.ndarray
    b_w: np.ndarray

    def __post_init__(self):
        for name in ("r", "v", "b_f", "b_w"):
            object.__setattr__(self, name, np.asarray(getattr(self, name), dtype=float))
        object.__setattr__(self, "C", np.asarray(self.C, dtype=float))

    @property
    def shape(self) -> tuple:
        return self.r.shape[:-1]

    def __len__(self) -> int:
        return self.shape[0]

    def __getitem__(self, index) -> "ImuState":
        return ImuState(self.r[index], self.v[index], self.C[index], self.b_f[index], self.b_w[index])

    @staticmethod
    def identity(shape=()) -> "ImuState":
        shape = (shape,) if isinstance(shape, int) else tuple(shape)
        z = np.zeros(shape + (3,))
        return ImuState(z, z.copy(), np.broadcast_to(np.eye(3), shape + (3, 3)).copy(), z.copy(), z.copy())

    @staticmethod
    def of_flat(x: np.ndarray) -> "ImuState":
        """One state VIEWING the float array ``x (21,)`` laid out ``(r, v, C row by row, b_f,
        b_w)``: no copy and no conversion (the per-sample path of an IMU-rate estimate)."""
        out = object.__new__(ImuState)
        out.__dict__.update(r=x[0:3], v=x[3:6], C=x[6:15].reshape(3, 3), b_f=x[15:18], b_w=x[18:21])  # frozen
        return out

    @staticmethod
    def stack(states: list["ImuState"]) -> "ImuState":
        return ImuState(*(np.stack([getattr(s, n) for s in states]) for n in ("r", "v", "C", "b_f", "b_w")))

    def world_velocity(self) -> np.ndarray:
        """``I_v = C B_v``."""
        return np.einsum("...ij,...j->...i", self.C, self.v)

    def replace(self, **changes) -> "ImuState":
        return replace(self, **changes)


@recursion
def boxplus_into(r, v, C, b_f, b_w, dx) -> None:
    """Compiled core of :func:`boxplus` for one state, in place."""
    E, C0 = np.empty((3, 3)), C.copy()
    so3.exp_into(dx[6], dx[7], dx[8], E)
    for a in range(3):
        r[a] += dx[a]
        v[a] += dx[3 + a]
        b_f[a] += dx[9 + a]
        b_w[a] += dx[12 + a]
        for b in range(3):
            C[a, b] = E[a, 0] * C0[0, b] + E[a, 1] * C0[1, b] + E[a, 2] * C0[2, b]


@recursion
def _boxplus_rows(r, v, C, b_f, b_w, dx):
    for n in range(r.shape[0]):
        boxplus_into(r[n], v[n], C[n], b_f[n], b_w[n], dx[n])


def boxplus(x: ImuState, dx: np.ndarray) -> ImuState:
    """``x [+] dx``: vectors add, the attitude takes the primer's left boxplus ``exp(dphi) C``."""
    dx = as_trailing(dx, (STATE_DIM,), "dx")
    lead = np.broadcast_shapes(x.shape, dx.shape[:-1])
    vec = (3,)
    r, v, C, b_f, b_w = (np.array(a) for a in rows(lead, (x.r, x.v, x.C, x.b_f, x.b_w), (vec, vec, (3, 3), vec, vec)))
    (step,) = rows(lead, (dx,), ((STATE_DIM,),))
    _boxplus_rows(r, v, C, b_f, b_w, step)
    return ImuState(*(a.reshape(lead + a.shape[1:]) for a in (r, v, C, b_f, b_w)))


def boxminus(a: ImuState, b: ImuState) -> np.ndarray:
    """``a [-] b`` (15-vector, error-state order); ``boxminus(boxplus(b, d), b) == d``."""
    return np.concatenate(
        [a.r - b.r, a.v - b.v, so3.boxminus(a.C, b.C), a.b_f - b.b_f, a.b_w - b.b_w], axis=-1
    )


class StateManifold:
    """:class:`factors.jacobians.Manifold` of :class:`ImuState` for numerical Jacobians."""

    dim = STATE_DIM

    @staticmethod
    def plus(x: ImuState, delta: np.ndarray) -> ImuState:
        return boxplus(x, delta)

    @staticmethod
    def minus(a: ImuState, b: ImuState) -> np.ndarray:
        return boxminus(a, b)


#: Default velocity-noise density ``n_v`` [m/s/sqrt(Hz)] (:class:`ImuNoise`): the Euler step's
#: position error, and what keeps keyframes within one IMU sample numerically apart.
POSITION_KINEMATICS_DENSITY = 1e-3


@dataclass(frozen=True)
class ImuNoise:
    """Continuous-time noise densities (1-sigma, isotropic), as IMU data sheets give them.

    ``acc``: accelerometer white noise [m/s^2/sqrt(Hz)]; ``gyro``: gyro white noise
    [rad/s/sqrt(Hz)]; ``acc_bias``, ``gyro_bias``: bias random walk [m/s^3/sqrt(Hz)],
    [rad/s^2/sqrt(Hz)]; ``velocity``: the velocity noise ``n_v`` of eq. (47) [m/s/sqrt(Hz)].
    The densities squared are the primer's ``R_i``.

    ``velocity`` defaults to :data:`POSITION_KINEMATICS_DENSITY`: the Euler step moves the
    position by ``dt C v`` and leaves out ``dt^2 a / 2``, an error of ~1e-3 m/s/sqrt(Hz) for
    1 m/s^2 at 20 Hz, and with ``n_v = 0`` the position of a one-sample interval is exact, so
    two keyframes within one IMU sample of each other are tied with information beyond 1e14
    beside a GNSS fix's 0.04: a sum no longer positive definite in double precision. Over a run
    the default adds 1 mm/sqrt(s) of position random walk.
    """

    acc: float = 2e-3
    gyro: float = 2e-4
    acc_bias: float = 3e-4
    gyro_bias: float = 2e-5
    velocity: float = POSITION_KINEMATICS_DENSITY

    def __post_init__(self):
        for name in ("acc", "gyro", "acc_bias", "gyro_bias", "velocity"):
            value = getattr(self, name)
            if not np.isfinite(value) or value < 0:
                raise InputError(f"ImuNoise.{name}: expected a finite density >= 0, got {value!r}")

    def densities(self) -> np.ndarray:
        """The 15 noise densities squared (``diag R``), in the order ``(n_v, n_f, n_w, n_bf, n_bw)``."""
        sigmas = np.repeat([self.velocity, self.acc, self.gyro, self.acc_bias, self.gyro_bias], 3)
        return sigmas**2

    def discrete_covariance(self, dt) -> np.ndarray:
        """``Q_d = diag(R_i / dt)`` of the discrete noise (shape ``dt.shape + (15, 15)``).
        A step of ``dt = 0`` has no noise (its ``G`` is 0 too)."""
        dt = np.asarray(dt, dtype=float)
        inv = np.divide(1.0, dt, out=np.zeros_like(dt), where=dt > 0)
        return np.einsum("...,i,ij->...ij", inv, self.densities(), np.eye(NOISE_DIM))


# ------------------------------------------------------------------------------------------------
# One step and its Jacobians: the compiled core every estimator runs (see factors.compiled).
#
# A step is described by the 37 numbers ``Q`` of :func:`step_quantities` (the nonzero blocks of
# ``F - I`` and ``G`` are all products of ``dt`` with ``C``, ``C v``, ``w``, ``v``, ``C^T g^x`` and
# ``C Gamma``). ``F`` is never formed on the estimators' path: :func:`_apply_A` applies
# ``A = F - I`` to the columns of a matrix, and the covariance update is
# ``F P F^T = P + B + B^T + A B^T`` with ``B = A P`` (``A B^T = A P A^T`` for symmetric ``P``):
# two such applications, about 1100 multiply-adds instead of 2 x 3375 for dense 15x15 products.
# Matrices on this path are flat arrays of rows ``_W = 16`` wide (15 columns and a zero pad):
# with a compile-time row width every row operation is a fixed-length loop over contiguous
# memory that LLVM turns into SIMD instructions (with a run-time width it does not). The dense
# ``F`` and ``G`` of :func:`propagate` are built from the same ``Q`` (``A`` applied to the
# identity), so the numerical-twin tests of ``F`` and ``G`` check the operator the estimators
# use.

#: Offsets into ``Q``: ``dt C`` (row-major), ``dt C v``, ``dt w``, ``dt v``, ``dt C^T g^x``
#: (row-major), ``dt C Gamma(dt w)`` (row-major), ``dt``.
_Q_C, _Q_CV, _Q_W, _Q_V, _Q_CTGX, _Q_CGAMMA, _Q_DT = 0, 9, 12, 15, 18, 27, 36
Q_SIZE = 37
#: Row width of the flat matrices of the covariance step (see above).
_W = 16


#: A step's numbers in one array (the argument of :func:`step_quantities` and
#: :func:`step_state`): the state ``r``, ``v``, ``C`` (row-major), gravity ``g``, then ``E =
#: exp(dt w)`` (row-major) and ``Q``. One array argument instead of six: each array passed to a
#: compiled function costs a dozen words of call overhead.
_S_R, _S_V, _S_C, _S_G, _S_E, _S_Q = 0, 3, 6, 15, 18, 27
STEP_SIZE = _S_Q + Q_SIZE


@leaf
def step_quantities(s, w0, w1, w2, dt) -> None:
    """For the step of length ``dt`` from the attitude ``C`` and body velocity ``v`` in ``s``
    (``_S_*``) at the bias-free rate ``w = (w0, w1, w2)``: ``E = exp(dt w)`` and ``Q`` (see
    ``_Q_*``) into ``s``."""
    x, y, z = dt * w0, dt * w1, dt * w2
    Em, Gm = so3.exp_and_gamma_entries(x, y, z)  # exp(dt w), Gamma(dt w), row-major
    for t in range(9):
        s[_S_E + t] = Em[t]
    v0, v1, v2 = s[_S_V], s[_S_V + 1], s[_S_V + 2]
    g0, g1, g2 = s[_S_G], s[_S_G + 1], s[_S_G + 2]
    Q = _S_Q
    for i in range(3):
        c0, c1, c2 = s[_S_C + 3 * i], s[_S_C + 3 * i + 1], s[_S_C + 3 * i + 2]
        s[Q + _Q_C + 3 * i], s[Q + _Q_C + 3 * i + 1], s[Q + _Q_C + 3 * i + 2] = dt * c0, dt * c1, dt * c2
        s[Q + _Q_CV + i] = dt * (c0 * v0 + c1 * v1 + c2 * v2)
        for m in range(3):
            s[Q + _Q_CGAMMA + 3 * i + m] = dt * (c0 * Gm[m] + c1 * Gm[3 + m] + c2 * Gm[6 + m])
        # row i of C^T g^x is (c x g)^T with c = column i of C
        k0, k1, k2 = s[_S_C + i], s[_S_C + 3 + i], s[_S_C + 6 + i]
        s[Q + _Q_CTGX + 3 * i] = dt * (k1 * g2 - k2 * g1)
        s[Q + _Q_CTGX + 3 * i + 1] = dt * (k2 * g0 - k0 * g2)
        s[Q + _Q_CTGX + 3 * i + 2] = dt * (k0 * g1 - k1 * g0)
    s[Q + _Q_W], s[Q + _Q_W + 1], s[Q + _Q_W + 2] = x, y, z
    s[Q + _Q_V], s[Q + _Q_V + 1], s[Q + _Q_V + 2] = dt * v0, dt * v1, dt * v2
    s[Q + _Q_DT] = dt


@leaf
def step_state(s, f0, f1, f2, w0, w1, w2) -> None:
    """The step (eqs. 54-60) of the state in ``s`` (``_S_*``) in place: ``r += dt C v``,
    ``v += dt (C^T g + f - w x v)``, ``C <- C exp(dt w)``, with ``f, w`` the bias-free samples
    and ``E, Q`` from :func:`step_quantities` at this state."""
    h = s[_S_Q + _Q_DT]
    v0, v1, v2 = s[_S_V], s[_S_V + 1], s[_S_V + 2]
    g0, g1, g2 = s[_S_G], s[_S_G + 1], s[_S_G + 2]
    C = _S_C
    tg0 = s[C] * g0 + s[C + 3] * g1 + s[C + 6] * g2
    tg1 = s[C + 1] * g0 + s[C + 4] * g1 + s[C + 7] * g2
    tg2 = s[C + 2] * g0 + s[C + 5] * g1 + s[C + 8] * g2
    for i in range(3):
        s[_S_R + i] += s[_S_Q + _Q_CV + i]
    s[_S_V] = v0 + h * (tg0 + f0 - (w1 * v2 - w2 * v1))
    s[_S_V + 1] = v1 + h * (tg1 + f1 - (w2 * v0 - w0 * v2))
    s[_S_V + 2] = v2 + h * (tg2 + f2 - (w0 * v1 - w1 * v0))
    for i in range(3):
        c0, c1, c2 = s[C + 3 * i], s[C + 3 * i + 1], s[C + 3 * i + 2]
        for m in range(3):
            s[C + 3 * i + m] = c0 * s[_S_E + m] + c1 * s[_S_E + 3 + m] + c2 * s[_S_E + 6 + m]


@block_operation
def _state_into(s, r, v, C, g) -> None:
    """``r, v, C, g`` into the step array ``s``."""
    for a in range(3):
        s[_S_R + a], s[_S_V + a], s[_S_G + a] = r[a], v[a], g[a]
        for b in range(3):
            s[_S_C + 3 * a + b] = C[a, b]


@block_operation
def _state_from(s, r, v, C) -> None:
    """``r, v, C`` from the step array ``s``."""
    for a in range(3):
        r[a], v[a] = s[_S_R + a], s[_S_V + a]
        for b in range(3):
            C[a, b] = s[_S_C + 3 * a + b]


@block_operation
def _put(out, t, value, B, X, accumulate) -> None:
    """``out[t] = value``, or with ``accumulate`` (a constant where this is inlined)
    ``out[t] += B[t] + X[t] + value``."""
    if accumulate:
        out[t] += B[t] + X[t] + value
    else:
        out[t] = value


def _applying_A(accumulate: bool):
    """``apply(X, Q, out, B)``: ``A X`` column by column with ``A = F - I`` (the rows in the module
    docstring), ``X`` holding 15 rows and ``out`` 9 rows (the last six rows of ``F - I`` are zero)
    of ``_W`` columns each, flat. Without ``accumulate`` ``out = A X`` (``B`` unused); with it
    ``out += B + X + A X`` over those 9 rows: the covariance step's ``P += B + B^T + A B^T``
    (``X = B^T``) in the same pass, without storing ``A B^T`` and reading it back (3-4% of the
    covariance kernel's time)."""

    @block_operation
    def apply(X, Q, out, B) -> None:
        c00, c01, c02, c10, c11, c12, c20, c21, c22 = (Q[_Q_C], Q[_Q_C + 1], Q[_Q_C + 2], Q[_Q_C + 3], Q[_Q_C + 4],
                                                       Q[_Q_C + 5], Q[_Q_C + 6], Q[_Q_C + 7], Q[_Q_C + 8])
        M = _Q_CTGX
        m00, m01, m02, m10, m11, m12, m20, m21, m22 = (Q[M], Q[M + 1], Q[M + 2], Q[M + 3], Q[M + 4], Q[M + 5],
                                                       Q[M + 6], Q[M + 7], Q[M + 8])
        N = _Q_CGAMMA
        g00, g01, g02, g10, g11, g12, g20, g21, g22 = (Q[N], Q[N + 1], Q[N + 2], Q[N + 3], Q[N + 4], Q[N + 5],
                                                       Q[N + 6], Q[N + 7], Q[N + 8])
        u0, u1, u2 = Q[_Q_CV], Q[_Q_CV + 1], Q[_Q_CV + 2]
        a0, a1, a2 = Q[_Q_W], Q[_Q_W + 1], Q[_Q_W + 2]
        b0, b1, b2 = Q[_Q_V], Q[_Q_V + 1], Q[_Q_V + 2]
        h = Q[_Q_DT]
        for c in range(_W):
            x0, x1, x2 = X[3 * _W + c], X[4 * _W + c], X[5 * _W + c]  # dv
            p0, p1, p2 = X[6 * _W + c], X[7 * _W + c], X[8 * _W + c]  # dphi
            s0, s1, s2 = X[12 * _W + c], X[13 * _W + c], X[14 * _W + c]  # db_w
            # dr row: dt C dv - dt (C v) x dphi
            _put(out, c, c00 * x0 + c01 * x1 + c02 * x2 - (u1 * p2 - u2 * p1), B, X, accumulate)
            _put(out, _W + c, c10 * x0 + c11 * x1 + c12 * x2 - (u2 * p0 - u0 * p2), B, X, accumulate)
            _put(out, 2 * _W + c, c20 * x0 + c21 * x1 + c22 * x2 - (u0 * p1 - u1 * p0), B, X, accumulate)
            # dv row: dt C^T g^x dphi - dt w x dv - dt db_f - dt v x db_w
            _put(out, 3 * _W + c, m00 * p0 + m01 * p1 + m02 * p2 - (a1 * x2 - a2 * x1) - h * X[9 * _W + c]
                 - (b1 * s2 - b2 * s1), B, X, accumulate)
            _put(out, 4 * _W + c, m10 * p0 + m11 * p1 + m12 * p2 - (a2 * x0 - a0 * x2) - h * X[10 * _W + c]
                 - (b2 * s0 - b0 * s2), B, X, accumulate)
            _put(out, 5 * _W + c, m20 * p0 + m21 * p1 + m22 * p2 - (a0 * x1 - a1 * x0) - h * X[11 * _W + c]
                 - (b0 * s1 - b1 * s0), B, X, accumulate)
            # dphi row: -dt C Gamma db_w
            _put(out, 6 * _W + c, -(g00 * s0 + g01 * s1 + g02 * s2), B, X, accumulate)
            _put(out, 7 * _W + c, -(g10 * s0 + g11 * s1 + g12 * s2), B, X, accumulate)
            _put(out, 8 * _W + c, -(g20 * s0 + g21 * s1 + g22 * s2), B, X, accumulate)

    return apply


_A_into = _applying_A(False)
#: ``P += B + X + A X`` on the first 9 rows (see :func:`_applying_A`).
_add_A_plus = _applying_A(True)


@block_operation
def _apply_A(X, Q, out) -> None:
    """``out = (F - I) X`` column by column: ``X`` holds 15 rows and ``out`` 9 rows (the last six
    rows of ``F - I`` are zero) of ``_W`` columns each, flat. The rows of ``F - I`` are those in
    the module docstring."""
    _A_into(X, Q, out, X)


#: Length of the work array of :func:`_jacobians_into`.
JACOBIANS_WORK = (STATE_DIM + 9) * _W


@recursion
def _jacobians_into(Q, F, G, work) -> None:
    """Dense ``F = I + A`` and ``G`` (module docstring) from the step's ``Q``; ``work``:
    :data:`JACOBIANS_WORK` numbers the caller owns (this runs once per sample or measurement)."""
    eye, A = work[:STATE_DIM * _W], work[STATE_DIM * _W:JACOBIANS_WORK]
    eye[:] = 0.0
    for k in range(STATE_DIM):
        eye[k * _W + k] = 1.0
    _apply_A(eye, Q, A)
    for i in range(STATE_DIM):
        for k in range(STATE_DIM):
            F[i, k] = 1.0 if i == k else 0.0
    for i in range(9):
        for k in range(STATE_DIM):
            F[i, k] += A[i * _W + k]
    G[:, :] = 0.0
    h = Q[_Q_DT]
    b0, b1, b2 = Q[_Q_V], Q[_Q_V + 1], Q[_Q_V + 2]
    for i in range(3):
        for m in range(3):
            G[i, m] = Q[_Q_C + 3 * i + m]
            G[6 + i, 6 + m] = -Q[_Q_CGAMMA + 3 * i + m]
        G[3 + i, 3 + i] = -h
        G[9 + i, 9 + i] = G[12 + i, 12 + i] = h
    # -dt v^x in the (dv, n_w) block
    G[3, 7], G[3, 8], G[4, 8] = b2, -b1, b0
    G[4, 6], G[5, 6], G[5, 7] = -b2, b1, -b0


@block_operation
def _covariance_step(P, Q, q, v, B, Bt) -> None:
    """``P <- F P F^T + G diag(q / dt) G^T`` in place, ``P`` flat (15 rows of ``_W``), at the
    step of ``Q`` from body velocity ``v``. ``F P F^T = P + B + B^T + A B^T`` with ``B = A P``
    (rows dr, dv, dphi only; ``Bt`` its transpose, padded with zero columns, so ``A B^T`` is
    one more application of ``A``, added to ``P`` as it is computed). The noise term, written
    out from ``G`` (``C C^T = I``)::

        dr,dr: dt q_v I     dv,dv: dt (q_f I - q_w v^x v^x)     dv,dphi: q_w (dt v)^x (dt C Gamma)^T / dt
        dphi,dphi: q_w (dt C Gamma)(dt C Gamma)^T / dt     db_f: dt q_bf I     db_w: dt q_bw I

    Every entry is updated (not half and a mirror), so ``P`` stays symmetric to round-off;
    :func:`predict_into` symmetrises it once per call."""
    _apply_A(P, Q, B)
    for k in range(STATE_DIM):
        for i in range(9):
            Bt[k * _W + i] = B[i * _W + k]
    _add_A_plus(Bt, Q, P, B)  # rows dr, dv, dphi: P += B + B^T + A B^T
    for t in range(9 * _W, STATE_DIM * _W):  # rows db_f, db_w: P += B^T (a flat SIMD loop)
        P[t] += Bt[t]
    h = Q[_Q_DT]
    qw = q[NW.start]
    vv = v[0] * v[0] + v[1] * v[1] + v[2] * v[2]
    iw = qw / h
    for i in range(3):
        P[i * _W + i] += h * q[NV.start + i]
        P[(9 + i) * _W + 9 + i] += h * q[NBF.start + i]
        P[(12 + i) * _W + 12 + i] += h * q[NBW.start + i]
        P[(3 + i) * _W + 3 + i] += h * (q[NF.start + i] + qw * vv)
        for m in range(3):
            P[(3 + i) * _W + 3 + m] -= h * qw * v[i] * v[m]
            P[(6 + i) * _W + 6 + m] += iw * (Q[_Q_CGAMMA + 3 * i] * Q[_Q_CGAMMA + 3 * m]
                                             + Q[_Q_CGAMMA + 3 * i + 1] * Q[_Q_CGAMMA + 3 * m + 1]
                                             + Q[_Q_CGAMMA + 3 * i + 2] * Q[_Q_CGAMMA + 3 * m + 2])
    b0, b1, b2 = Q[_Q_V], Q[_Q_V + 1], Q[_Q_V + 2]
    for m in range(3):
        y0, y1, y2 = Q[_Q_CGAMMA + 3 * m], Q[_Q_CGAMMA + 3 * m + 1], Q[_Q_CGAMMA + 3 * m + 2]
        n0, n1, n2 = iw * (b1 * y2 - b2 * y1), iw * (b2 * y0 - b0 * y2), iw * (b0 * y1 - b1 * y0)
        P[3 * _W + 6 + m] += n0
        P[4 * _W + 6 + m] += n1
        P[5 * _W + 6 + m] += n2
        P[(6 + m) * _W + 3] += n0
        P[(6 + m) * _W + 4] += n1
        P[(6 + m) * _W + 5] += n2


@recursion
def _propagate_rows(r, v, C, b_f, b_w, acc, gyro, dt, g, out_r, out_v, out_C, F, G, jacobians):
    s, work = np.empty(STEP_SIZE), np.empty(JACOBIANS_WORK)
    for i in range(r.shape[0]):
        w0, w1, w2 = gyro[i, 0] - b_w[i, 0], gyro[i, 1] - b_w[i, 1], gyro[i, 2] - b_w[i, 2]
        _state_into(s, r[i], v[i], C[i], g)
        step_quantities(s, w0, w1, w2, dt[i])
        if jacobians:
            _jacobians_into(s[_S_Q:], F[i], G[i], work)
        step_state(s, acc[i, 0] - b_f[i, 0], acc[i, 1] - b_f[i, 1], acc[i, 2] - b_f[i, 2], w0, w1, w2)
        _state_from(s, out_r[i], out_v[i], out_C[i])


@recursion
def transition_into(r, v, C, b_f, b_w, acc, gyro, dt, g, Phi) -> None:
    """``Phi (15, m) <- F_K ... F_1 Phi``: the error-state transition of the samples ``k`` with
    ``dt[k] > 0`` (the steps :func:`predict_into` takes) applied to ``Phi``, the state ``(r, v,
    C)`` stepped along in place. What carries a covariance between the state and constants
    outside it (calibrations) through the prediction: with ``Phi = P_xc``, ``P_xc <- F_K ... F_1
    P_xc``."""
    s, work = np.empty(STEP_SIZE), np.empty(JACOBIANS_WORK)
    F, G, T = np.empty((STATE_DIM, STATE_DIM)), np.empty((STATE_DIM, NOISE_DIM)), np.empty((STATE_DIM, Phi.shape[1]))
    _state_into(s, r, v, C, g)
    for k in range(dt.shape[0]):
        h = dt[k]
        if h <= 0.0:
            continue
        w0, w1, w2 = gyro[k, 0] - b_w[0], gyro[k, 1] - b_w[1], gyro[k, 2] - b_w[2]
        step_quantities(s, w0, w1, w2, h)
        _jacobians_into(s[_S_Q:], F, G, work)
        for i in range(STATE_DIM):
            for j in range(Phi.shape[1]):
                acc_ij = 0.0
                for m in range(STATE_DIM):
                    acc_ij += F[i, m] * Phi[m, j]
                T[i, j] = acc_ij
        Phi[:, :] = T
        step_state(s, acc[k, 0] - b_f[0], acc[k, 1] - b_f[1], acc[k, 2] - b_f[2], w0, w1, w2)
    _state_from(s, r, v, C)


#: Length of the work array of :func:`predict_flat` (:func:`prediction_work`): the flat
#: covariance (15 rows of ``_W``) first, then the scratch ``B`` (9 rows) and ``Bt`` (15 rows)
#: and the step array (``_S_*``).
PREDICTION_WORK_SIZE = 39 * _W + STEP_SIZE


@block_operation
def prediction_work() -> np.ndarray:
    """A work array for :func:`predict_flat` (zeros; allocate once, reuse): its first
    ``15 * _W`` entries hold the covariance it steps, flat (:func:`flat_from_symmetric`,
    :func:`symmetric_from_flat`)."""
    return np.zeros(PREDICTION_WORK_SIZE)


@block_operation
def predict_flat(r, v, C, b_f, b_w, acc, gyro, dt, q_density, g, work) -> None:
    """Every sample ``k`` with ``dt[k] > 0`` steps the state ``(r, v, C)`` and the covariance
    held flat in ``work`` (:func:`prediction_work`, see :func:`_covariance_step`) in place.

    The scratch arrays are slices of ``work``, which the caller allocates (this is inlined):
    LLVM then sees that they cannot overlap and keeps values in registers across stores into
    the others (4-5% faster than separate arrays). Passed in as an argument to a separately
    compiled function instead, the covariance step runs twice as long: LLVM must then assume
    that ``work`` may overlap the other arguments."""
    flat, B, Bt = work[:15 * _W], work[15 * _W:24 * _W], work[24 * _W:39 * _W]
    s = work[39 * _W:]
    Q, sv = s[_S_Q:], s[_S_V:_S_V + 3]
    _state_into(s, r, v, C, g)
    for k in range(dt.shape[0]):
        h = dt[k]
        if h <= 0.0:
            continue
        w0, w1, w2 = gyro[k, 0] - b_w[0], gyro[k, 1] - b_w[1], gyro[k, 2] - b_w[2]
        step_quantities(s, w0, w1, w2, h)
        _covariance_step(flat, Q, q_density, sv, B, Bt)
        step_state(s, acc[k, 0] - b_f[0], acc[k, 1] - b_f[1], acc[k, 2] - b_f[2], w0, w1, w2)
    _state_from(s, r, v, C)


@block_operation
def clear_flat(work) -> None:
    """The covariance held flat in ``work`` (:func:`prediction_work`) set to zero."""
    for t in range(STATE_DIM * _W):
        work[t] = 0.0


@block_operation
def flat_from_symmetric(P, work) -> None:
    """The covariance held flat in ``work`` (:func:`prediction_work`) set to ``P`` (15x15)."""
    for i in range(STATE_DIM):
        for m in range(_W):
            work[i * _W + m] = P[i, m] if m < STATE_DIM else 0.0


@block_operation
def symmetric_from_flat(work, P, floor) -> None:
    """``P`` (15x15) = the symmetric part of the covariance held flat in ``work``, plus
    ``floor`` on the diagonal. Row by row: contiguous stores (a mirror of the upper triangle
    stores down the columns and took twice as long)."""
    for i in range(STATE_DIM):
        for m in range(STATE_DIM):
            P[i, m] = 0.5 * (work[i * _W + m] + work[m * _W + i])
        P[i, i] += floor


@recursion
def predict_into(r, v, C, b_f, b_w, P, acc, gyro, dt, q_density, g) -> None:
    """Compiled core of :func:`propagate_steps` for one state: every sample ``k`` with
    ``dt[k] > 0`` steps the state ``(r, v, C)`` and its covariance ``P`` (15x15, symmetric on
    return) in place (:func:`predict_flat`)."""
    work = prediction_work()
    flat_from_symmetric(P, work)
    predict_flat(r, v, C, b_f, b_w, acc, gyro, dt, q_density, g, work)
    symmetric_from_flat(work, P, 0.0)


@recursion
def _propagate_steps_kernel(r, v, C, b_f, b_w, S, acc, gyro, dt, q_density, g):
    for j in range(r.shape[0]):
        predict_into(r[j], v[j], C[j], b_f[j], b_w[j], S[j], acc[j], gyro[j], dt[j], q_density, g)


def propagate(state: ImuState, acc, gyro, dt, gravity=DEFAULT_GRAVITY, jacobians: bool = True):
    """One Euler-forward step of the primer's model (eqs. 54-60) at zero noise.

    Returns ``(next_state, F, G)``; ``F`` (``(..., 15, 15)``) is the Jacobian of the next error
    state with respect to the current one, ``G`` with respect to the discrete noise
    ``(n_v, n_f, n_w, n_bf, n_bw)`` (see the module docstring). With ``jacobians=False`` ``F``
    and ``G`` are None. ``dt = 0`` is the identity step. Vectorised over (broadcast) leading
    dimensions of the state and the samples; compiled (:func:`step_quantities`, :func:`step_state`).
    """
    acc, gyro = as_trailing(acc, (3,), "acc"), as_trailing(gyro, (3,), "gyro")
    dt = np.asarray(dt, dtype=float)
    g = as_trailing(gravity, (3,), "gravity")
    shape = np.broadcast_shapes(state.shape, dt.shape, acc.shape[:-1], gyro.shape[:-1])
    n = int(np.prod(shape, dtype=int))
    vec = (3,)
    r, v, C, b_f, b_w, acc, gyro, dt = rows(shape, (state.r, state.v, state.C, state.b_f, state.b_w, acc, gyro, dt),
                                            (vec, vec, (3, 3), vec, vec, vec, vec, ()))
    out_r, out_v, out_C = np.empty((n, 3)), np.empty((n, 3)), np.empty((n, 3, 3))
    m = n if jacobians else 0
    F, G = np.empty((m, STATE_DIM, STATE_DIM)), np.empty((m, STATE_DIM, NOISE_DIM))
    _propagate_rows(r, v, C, b_f, b_w, acc, gyro, dt, g, out_r, out_v, out_C, F, G, jacobians)
    next_state = ImuState(out_r.reshape(shape + vec), out_v.reshape(shape + vec), out_C.reshape(shape + (3, 3)),
                          b_f.reshape(shape + vec), b_w.reshape(shape + vec))
    if not jacobians:
        return next_state, None, None
    return next_state, F.reshape(shape + (STATE_DIM, STATE_DIM)), G.reshape(shape + (STATE_DIM, NOISE_DIM))


@leaf
def state_rate_into(v, C, b_f, b_w, acc, gyro, g, out) -> None:
    """``out (15) <-`` the error-state rate of the continuous model at one state with the IMU
    reading ``acc, gyro`` (:func:`state_derivative`)."""
    w0, w1, w2 = gyro[0] - b_w[0], gyro[1] - b_w[1], gyro[2] - b_w[2]
    for a in range(3):
        out[a] = C[a, 0] * v[0] + C[a, 1] * v[1] + C[a, 2] * v[2]
        out[6 + a] = C[a, 0] * w0 + C[a, 1] * w1 + C[a, 2] * w2
        out[3 + a] = acc[a] - b_f[a] + C[0, a] * g[0] + C[1, a] * g[1] + C[2, a] * g[2]
    out[3] -= w1 * v[2] - w2 * v[1]
    out[4] -= w2 * v[0] - w0 * v[2]
    out[5] -= w0 * v[1] - w1 * v[0]
    for a in range(9, STATE_DIM):
        out[a] = 0.0


@recursion
def _state_rate_rows(v, C, b_f, b_w, acc, gyro, g, out) -> None:
    for i in range(v.shape[0]):
        state_rate_into(v[i], C[i], b_f[i], b_w[i], acc[i], gyro[i], g, out[i])


#: Length of the work array of :func:`stepped_into`.
STEPPED_WORK = STEP_SIZE + STATE_DIM * NOISE_DIM + JACOBIANS_WORK


@recursion
def stepped_into(r, v, C, b_f, b_w, acc, gyro, dt, g, out_r, out_v, out_C, F, rate, work, jacobians) -> None:
    """One Euler step of ``dt`` of one state (:func:`propagate`): the next state into ``out_r,
    out_v, out_C`` (the biases do not move), its transition ``F (15, 15)``, and the state's rate
    ``rate (15)`` before the step (:func:`state_rate_into`): what a time offset ``dt`` of a
    measurement moves its state by, and the derivative of that with respect to ``dt`` (``F``
    only where ``jacobians``). ``work``: :data:`STEPPED_WORK` numbers the caller owns (this runs
    once per measurement)."""
    s = work[:STEP_SIZE]
    w0, w1, w2 = gyro[0] - b_w[0], gyro[1] - b_w[1], gyro[2] - b_w[2]
    state_rate_into(v, C, b_f, b_w, acc, gyro, g, rate)
    _state_into(s, r, v, C, g)
    step_quantities(s, w0, w1, w2, dt)
    if jacobians:
        G = work[STEP_SIZE:STEP_SIZE + STATE_DIM * NOISE_DIM].reshape((STATE_DIM, NOISE_DIM))
        _jacobians_into(s[_S_Q:], F, G, work[STEP_SIZE + STATE_DIM * NOISE_DIM:])
    step_state(s, acc[0] - b_f[0], acc[1] - b_f[1], acc[2] - b_f[2], w0, w1, w2)
    _state_from(s, out_r, out_v, out_C)


# A measurement between keyframes is taken at the state the Euler steps reach from its keyframe:
# the first n - 1 steps of the keyframe's interval, then the n-th cut at the measurement's time.
# The state is stepped as the EKF steps it (:func:`step_state`) and its Jacobian with respect to the
# keyframe's error state is the product of the steps' transitions, J <- F J = J + A J with A = F - I
# applied by the covariance step's own operator (:func:`_apply_A`): F is the exact Jacobian of one
# step, so the product is the exact Jacobian of the prediction. The steps before the cut one are
# kept in the work array, so the measurements of one interval taken in time order each continue
# where the one before stopped (every step once per interval, the same steps in the same order).

#: Offsets into :func:`partial_work`: the steps so far (a step array, ``STEP_SIZE``), their
#: Jacobian (15 flat rows of ``_W``), the cut step's copies of both, ``A J`` (9 rows), and two
#: counters: the steps taken and whether the Jacobian was kept.
_P_S = 0
_P_J = _P_S + STEP_SIZE
_P_S2 = _P_J + STATE_DIM * _W
_P_J2 = _P_S2 + STEP_SIZE
_P_AJ = _P_J2 + STATE_DIM * _W
_P_DONE = _P_AJ + 9 * _W
_P_WITH_J = _P_DONE + 1
PARTIAL_WORK = _P_WITH_J + 1


@recursion
def partial_work() -> np.ndarray:
    """The work array of :func:`partial_prediction_into`: allocate once per loop over measurements."""
    return np.zeros(PARTIAL_WORK)


@block_operation
def _chain_step(s, J, AJ, acc, gyro, h, b_f, b_w, jacobians) -> None:
    """One step of ``h`` with the reading ``acc, gyro`` of the state in ``s`` and, with
    ``jacobians``, of its Jacobian ``J`` (flat) to ``F J``; ``h <= 0`` is the identity step."""
    if h <= 0.0:
        return
    w0, w1, w2 = gyro[0] - b_w[0], gyro[1] - b_w[1], gyro[2] - b_w[2]
    step_quantities(s, w0, w1, w2, h)
    if jacobians:
        _apply_A(J, s[_S_Q:], AJ)
        for t in range(9 * _W):
            J[t] += AJ[t]
    step_state(s, acc[0] - b_f[0], acc[1] - b_f[1], acc[2] - b_f[2], w0, w1, w2)


@recursion
def partial_prediction_into(acc, gyro, dt, n, last_dt, r, v, C, b_f, b_w, g, xr, xv, xC, J, work, jacobians,
                            resume) -> None:
    """The state ``x_m = (xr, xv, xC, b_f, b_w)`` at the end of the first ``n >= 1`` steps of an
    interval's samples ``acc, gyro (K, 3)``, ``dt (K,)``, the last of them cut to ``last_dt``,
    from the state ``x = (r, v, C, b_f, b_w)`` at its start: the Euler steps of
    :func:`step_state`, and with ``jacobians`` the Jacobian ``J (15, 15)`` of ``x_m`` with respect
    to ``x``'s error state, the product of the steps' ``F``. What a measurement between keyframes
    is evaluated at (:func:`datasets.kinds.attached_into`); ``work`` from :func:`partial_work`.

    With ``resume``, the call before on ``work`` was for the same interval's samples from the same
    state, at most ``n`` steps long, and this one continues from the steps it took rather than
    from the interval's start: the same steps in the same order, so the same numbers."""
    s, Jp = work[_P_S:_P_J], work[_P_J:_P_S2]
    s2, J2, AJ = work[_P_S2:_P_J2], work[_P_J2:_P_AJ], work[_P_AJ:_P_DONE]
    done = int(work[_P_DONE])
    if not resume or done > n - 1 or (jacobians and work[_P_WITH_J] == 0.0):
        _state_into(s, r, v, C, g)
        if jacobians:
            for t in range(STATE_DIM * _W):
                Jp[t] = 0.0
            for t in range(STATE_DIM):
                Jp[t * _W + t] = 1.0
        work[_P_WITH_J] = 1.0 if jacobians else 0.0
        done = 0
    keep = work[_P_WITH_J] != 0.0
    for k in range(done, n - 1):
        _chain_step(s, Jp, AJ, acc[k], gyro[k], dt[k], b_f, b_w, keep)
    work[_P_DONE] = n - 1
    for t in range(_S_E):  # the state and gravity; the step recomputes the rest
        s2[t] = s[t]
    if jacobians:
        for t in range(STATE_DIM * _W):
            J2[t] = Jp[t]
    _chain_step(s2, J2, AJ, acc[n - 1], gyro[n - 1], last_dt, b_f, b_w, jacobians)
    _state_from(s2, xr, xv, xC)
    if jacobians:
        for i in range(STATE_DIM):
            for k in range(STATE_DIM):
                J[i, k] = J2[i * _W + k]


#: Length of the work array of :func:`partial_covariance_into`: the state after the steps so far,
#: their covariance (a :func:`prediction_work`), the cut step's covariance, its length, and the
#: count of steps taken.
PARTIAL_COVARIANCE_WORK = 15 + 2 * PREDICTION_WORK_SIZE + 2


@recursion
def partial_covariance_work() -> np.ndarray:
    """The work array of :func:`partial_covariance_into`: allocate once per loop over measurements."""
    return np.zeros(PARTIAL_COVARIANCE_WORK)


@recursion
def partial_covariance_into(acc, gyro, dt, n, last_dt, r, v, C, b_f, b_w, g, q, xr, xv, xC, S, work,
                            resume) -> None:
    """The state ``x_m = (xr, xv, xC, b_f, b_w)`` of :func:`partial_prediction_into` and ``S (15,
    15)``, its covariance given the start state ``x``: the EKF's growth ``F S F^T + G Q_d G^T``
    from zero along the same steps (:func:`predict_flat`, noise densities ``q``). ``work`` from
    :func:`partial_covariance_work`; ``resume`` as :func:`partial_prediction_into`'s."""
    P = PREDICTION_WORK_SIZE
    pr, pv, pC = work[0:3], work[3:6], work[6:15].reshape((3, 3))
    prefix, cut, h = work[15:15 + P], work[15 + P:15 + 2 * P], work[15 + 2 * P:16 + 2 * P]
    done = int(work[16 + 2 * P])
    if not resume or done > n - 1:
        for a in range(3):
            pr[a], pv[a] = r[a], v[a]
            for b in range(3):
                pC[a, b] = C[a, b]
        clear_flat(prefix)
        done = 0
    if n - 1 > done:
        predict_flat(pr, pv, pC, b_f, b_w, acc[done:n - 1], gyro[done:n - 1], dt[done:n - 1], q, g, prefix)
    work[16 + 2 * P] = n - 1
    for a in range(3):
        xr[a], xv[a] = pr[a], pv[a]
        for b in range(3):
            xC[a, b] = pC[a, b]
    for t in range(STATE_DIM * _W):
        cut[t] = prefix[t]
    h[0] = last_dt
    predict_flat(xr, xv, xC, b_f, b_w, acc[n - 1:n], gyro[n - 1:n], h, q, g, cut)
    symmetric_from_flat(cut, S, 0.0)


def state_derivative(state: ImuState, acc, gyro, gravity=DEFAULT_GRAVITY) -> np.ndarray:
    """The error-state rate ``(..., 15)`` of the continuous model at ``state`` with the IMU
    reading ``acc, gyro``: ``(C v, f - b_f + C^T g - w x v, C w, 0, 0)`` with ``w = gyro - b_w``
    (the attitude's rate as a LEFT, world-frame increment: ``d/dt C = (C w)^x C``). The Euler
    step of :func:`propagate` is linear in ``dt`` in these coordinates: ``propagate(state, acc,
    gyro, dt) [-] state = dt * state_derivative(...)``. Compiled (:func:`state_rate_into`)."""
    acc, gyro = as_trailing(acc, (3,), "acc"), as_trailing(gyro, (3,), "gyro")
    g = as_trailing(gravity, (3,), "gravity")
    shape = np.broadcast_shapes(state.shape, acc.shape[:-1], gyro.shape[:-1])
    vec = (3,)
    v, C, b_f, b_w, acc, gyro = rows(shape, (state.v, state.C, state.b_f, state.b_w, acc, gyro),
                                     (vec, (3, 3), vec, vec, vec, vec))
    out = np.empty((len(v), STATE_DIM))
    _state_rate_rows(v, C, b_f, b_w, acc, gyro, g, out)
    return out.reshape(shape + (STATE_DIM,))


def propagate_steps(state: ImuState, cov, acc, gyro, dt, noise: "ImuNoise", gravity=DEFAULT_GRAVITY):
    """The EKF prediction through many samples: :func:`propagate` applied to ``acc[..., k],
    gyro[..., k], dt[..., k]`` in order, and ``S <- F S F^T + G Q_d G^T`` with
    ``Q_d = diag(R_i / dt)`` at each step; samples with ``dt = 0`` are skipped (identity steps).

    ``state`` and ``cov (..., 15, 15)`` have leading dimensions ``J`` (one state, or ``J``
    independent rows, e.g. keyframe intervals); the samples have shape ``(J, K, 3)`` and
    ``(J, K)``. Returns the final ``(state, cov)``. One compiled loop over rows and samples
    (:func:`step_quantities`, :func:`_covariance_step`, :func:`step_state`), so there is no
    Python per sample."""
    single, (r, v, C, b_f, b_w, acc, gyro, dt), S = _step_rows(state, acc, gyro, dt, cov)
    _propagate_steps_kernel(r, v, C, b_f, b_w, S, acc, gyro, dt, noise.densities(),
                            as_trailing(gravity, (3,), "gravity"))
    out = ImuState(r, v, C, b_f, b_w)
    return (out[0], S[0]) if single else (out, S)


def _step_rows(state: ImuState, acc, gyro, dt, matrix) -> tuple:
    """``(single, (r, v, C, b_f, b_w, acc, gyro, dt), matrix)`` of :func:`propagate_steps` and
    :func:`transition_steps`: their arguments as rows ``J`` (one row where ``dt`` is 1-D:
    ``single``), the state's ``r, v, C`` and the ``(J, 15, 15)`` ``matrix`` copied, which the
    kernels step in place."""
    acc, gyro = as_trailing(acc, (3,), "acc"), as_trailing(gyro, (3,), "gyro")
    dt = np.asarray(dt, dtype=float)
    single = dt.ndim == 1
    lead = (1,) if single else dt.shape[:1]
    K = dt.shape[-1]
    vec = (3,)
    r, v, C, M = (np.array(a) for a in rows(lead, (state.r, state.v, state.C, matrix),
                                             (vec, vec, (3, 3), (STATE_DIM, STATE_DIM))))
    b_f, b_w, acc, gyro, dt = rows(lead, (state.b_f, state.b_w, acc.reshape(lead + (K, 3)),
                                          gyro.reshape(lead + (K, 3)), dt.reshape(lead + (K,))),
                                   (vec, vec, (K, 3), (K, 3), (K,)))
    return single, (r, v, C, b_f, b_w, acc, gyro, dt), M


@recursion
def _transition_steps_kernel(r, v, C, b_f, b_w, Phi, acc, gyro, dt, g):
    for j in range(r.shape[0]):
        transition_into(r[j], v[j], C[j], b_f[j], b_w[j], acc[j], gyro[j], dt[j], g, Phi[j])


def transition_steps(state: ImuState, acc, gyro, dt, gravity=DEFAULT_GRAVITY) -> tuple:
    """``(state, Phi)``: :func:`propagate_steps`'s state at the end of the samples and the
    error-state transition of its steps, ``Phi = F_K ... F_1`` (:func:`transition_into`; samples
    with ``dt = 0`` skipped), ``(J, 15, 15)`` for ``J`` rows (``(15, 15)`` for one). With
    :func:`propagate_steps` from a zero covariance, which gives the process noise ``S`` of the same
    steps, the state's error at the end is ``Phi dx + w``, ``w ~ N(0, S)``, to first order."""
    single, (r, v, C, b_f, b_w, acc, gyro, dt), Phi = _step_rows(state, acc, gyro, dt, np.eye(STATE_DIM))
    _transition_steps_kernel(r, v, C, b_f, b_w, Phi, acc, gyro, dt, as_trailing(gravity, (3,), "gravity"))
    out = ImuState(r, v, C, b_f, b_w)
    return (out[0], Phi[0]) if single else (out, Phi)


def propagate_with_noise(state: ImuState, acc, gyro, dt, noise: np.ndarray, gravity=DEFAULT_GRAVITY) -> ImuState:
    """The step of eqs. (54)-(60) with an explicit discrete noise vector ``noise`` (15, order
    ``(n_v, n_f, n_w, n_bf, n_bw)``): the function that ``G`` differentiates."""
    noise = np.asarray(noise, dtype=float)
    dts = np.asarray(dt, dtype=float)[..., None]
    nxt, _, _ = propagate(
        state, np.asarray(acc) - noise[..., NF], np.asarray(gyro) - noise[..., NW], dt, gravity, jacobians=False
    )
    return nxt.replace(
        r=nxt.r + dts * np.einsum("...ij,...j->...i", state.C, noise[..., NV]),
        b_f=state.b_f + dts * noise[..., NBF],
        b_w=state.b_w + dts * noise[..., NBW],
    )


def integrate(state: ImuState, acc, gyro, dt, gravity=DEFAULT_GRAVITY) -> ImuState:
    """Dead reckoning: :func:`propagate` applied to the samples ``acc[k], gyro[k], dt[k]`` in
    order with the biases of ``state`` held constant; returns the states before every sample and
    after the last (``len(dt) + 1`` states).

    Vectorised, without a loop per sample: ``C_k = C_0 exp(dt_0 w_0) ... exp(dt_{k-1} w_{k-1})``
    is a prefix product, ``v_{k+1} = A_k v_k + dt_k (C_k^T g + f_k)`` (``A_k = I - dt_k w_k^x``) is a
    prefix product of affine maps (4x4 homogeneous matrices), and ``r`` a cumulative sum; each
    by recursive doubling (:mod:`factors.scan`), equal to the step-by-step loop up to round-off."""
    acc, gyro = np.asarray(acc, dtype=float), np.asarray(gyro, dtype=float)
    dt = np.asarray(dt, dtype=float)
    g = np.asarray(gravity, dtype=float)
    n = len(dt)
    f = acc[:n] - state.b_f
    w = gyro[:n] - state.b_w
    h = dt[:, None]
    C = np.empty((n + 1, 3, 3))
    C[0] = state.C
    C[1:] = state.C @ scan.prefix_products(so3.exp(h * w), later_on_left=False)
    M = np.zeros((n, 4, 4))
    M[:, :3, :3] = np.eye(3) - h[:, :, None] * so3.skew(w)
    M[:, :3, 3] = h * (np.einsum("kji,j->ki", C[:-1], g) + f)
    M[:, 3, 3] = 1.0
    P = scan.prefix_products(M, later_on_left=True)
    v = np.empty((n + 1, 3))
    v[0] = state.v
    v[1:] = P[:, :3, :3] @ state.v + P[:, :3, 3]
    r = np.empty((n + 1, 3))
    r[0] = state.r
    r[1:] = state.r + np.cumsum(h * np.einsum("kij,kj->ki", C[:-1], v[:-1]), axis=0)
    ones = np.ones((n + 1, 1))
    return ImuState(r, v, C, ones * state.b_f, ones * state.b_w)
