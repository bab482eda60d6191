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
from numba import njit

from factors import scan, so3
from factors.compiled import as_trailing, rows

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
    def stack(states: list["ImuState"]) -> "ImuState":
        return ImuState(*(np.stack([getattr(s, n) for s in states]) for n in ("r", "v", "C", "b_f", "b_w")))

    def world_velocity(self) -> np.ndarray:
        """``I_v = C B_v``."""
        return np.einsum("...ij,...j->...i", self.C, self.v)

    def replace(self, **changes) -> "ImuState":
        return replace(self, **changes)


def boxplus(x: ImuState, dx: np.ndarray) -> ImuState:
    """``x [+] dx``: vectors add, the attitude takes the primer's left boxplus."""
    dx = np.asarray(dx, dtype=float)
    return ImuState(
        x.r + dx[..., R], x.v + dx[..., V], so3.boxplus(x.C, dx[..., PHI]), x.b_f + dx[..., BF], x.b_w + dx[..., BW]
    )


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


@dataclass(frozen=True)
class ImuNoise:
    """Continuous-time noise densities (1-sigma, isotropic), as IMU data sheets give them.

    ``acc``: accelerometer white noise [m/s^2/sqrt(Hz)]; ``gyro``: gyro white noise
    [rad/s/sqrt(Hz)]; ``acc_bias``, ``gyro_bias``: bias random walk [m/s^3/sqrt(Hz)],
    [rad/s^2/sqrt(Hz)]; ``velocity``: the velocity noise ``n_v`` of eq. (47) [m/s/sqrt(Hz)],
    0 by default. The densities squared are the primer's ``R_i``.
    """

    acc: float = 2e-3
    gyro: float = 2e-4
    acc_bias: float = 3e-4
    gyro_bias: float = 2e-5
    velocity: float = 0.0

    def __post_init__(self):
        for name in ("acc", "gyro", "acc_bias", "gyro_bias", "velocity"):
            value = getattr(self, name)
            if not np.isfinite(value) or value < 0:
                raise ValueError(f"ImuNoise.{name}: expected a finite density >= 0, got {value!r}")

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

#: Error-state blocks (index of each 3-block) and the blocks of ``F - I`` and of ``G`` that the
#: step writes; every other block of ``F - I`` and ``G`` is zero. ``_covariance_step`` multiplies
#: only these, so the covariance update costs a few 3x3 products per step instead of dense 15x15
#: ones; tests compare it with the dense ``F S F^T + G Q G^T``.
_RB, _VB, _PB, _FB, _WB = 0, 1, 2, 3, 4
_F_OFF_IDENTITY = ((_RB, _VB), (_RB, _PB), (_VB, _VB), (_VB, _PB), (_VB, _FB), (_VB, _WB), (_PB, _WB))
_G_BLOCKS = ((_RB, _RB), (_VB, _VB), (_VB, _PB), (_PB, _PB), (_FB, _FB), (_WB, _WB))


@njit(cache=True)
def step_into(r, v, C, b_f, b_w, acc, gyro, dt, g, out_r, out_v, out_C, F, G, scratch) -> None:
    """Compiled core of :func:`propagate` for one state and one sample.

    Writes the next state into ``out_r, out_v, out_C`` (which may alias the inputs) and the
    nonzero blocks of ``F`` and ``G`` (15x15, zero elsewhere: the caller zeroes them once).
    ``scratch`` is a (2, 3, 3) work array."""
    E, CG = scratch[0], scratch[1]
    w0, w1, w2 = gyro[0] - b_w[0], gyro[1] - b_w[1], gyro[2] - b_w[2]
    f0, f1, f2 = acc[0] - b_f[0], acc[1] - b_f[1], acc[2] - b_f[2]
    v0, v1, v2 = v[0], v[1], v[2]
    so3.exp_into(dt * w0, dt * w1, dt * w2, E)
    so3.gamma_into(dt * w0, dt * w1, dt * w2, CG)
    Cv = (C[0, 0] * v0 + C[0, 1] * v1 + C[0, 2] * v2, C[1, 0] * v0 + C[1, 1] * v1 + C[1, 2] * v2,
          C[2, 0] * v0 + C[2, 1] * v1 + C[2, 2] * v2)
    Ctg = (C[0, 0] * g[0] + C[1, 0] * g[1] + C[2, 0] * g[2], C[0, 1] * g[0] + C[1, 1] * g[1] + C[2, 1] * g[2],
           C[0, 2] * g[0] + C[1, 2] * g[1] + C[2, 2] * g[2])
    # Jacobians first: they are taken at the current state (and out_* may alias it).
    for a in range(3):
        for b in range(3):
            F[a, 3 + b] = dt * C[a, b]
            G[a, b] = dt * C[a, b]
            F[9 + a, 9 + b] = F[12 + a, 12 + b] = F[a, b] = F[6 + a, 6 + b] = 1.0 if a == b else 0.0
            F[3 + a, 9 + b] = G[3 + a, 3 + b] = -dt if a == b else 0.0
            G[9 + a, 9 + b] = G[12 + a, 12 + b] = dt if a == b else 0.0
            # C^T g^x: column b of g^x is e_b x g
            gx0 = (0.0, -g[2], g[1])[b]
            gx1 = (g[2], 0.0, -g[0])[b]
            gx2 = (-g[1], g[0], 0.0)[b]
            F[3 + a, 6 + b] = dt * (C[0, a] * gx0 + C[1, a] * gx1 + C[2, a] * gx2)
            F[6 + a, 12 + b] = G[6 + a, 6 + b] = -dt * (C[a, 0] * CG[0, b] + C[a, 1] * CG[1, b] + C[a, 2] * CG[2, b])
    _skew_into(-dt * Cv[0], -dt * Cv[1], -dt * Cv[2], F[0:3, 6:9])
    _skew_into(-dt * w0, -dt * w1, -dt * w2, F[3:6, 3:6])
    F[3, 3] = F[4, 4] = F[5, 5] = 1.0
    _skew_into(-dt * v0, -dt * v1, -dt * v2, F[3:6, 12:15])
    G[3:6, 6:9] = F[3:6, 12:15]
    # The step (eqs. 54-60): r' = r + dt C v, v' = v + dt (C^T g + f - w x v), C' = C exp(dt w).
    for a in range(3):
        out_r[a] = r[a] + dt * Cv[a]
    out_v[0] = v0 + dt * (Ctg[0] + f0 - (w1 * v2 - w2 * v1))
    out_v[1] = v1 + dt * (Ctg[1] + f1 - (w2 * v0 - w0 * v2))
    out_v[2] = v2 + dt * (Ctg[2] + f2 - (w0 * v1 - w1 * v0))
    for a in range(3):
        c0, c1, c2 = C[a, 0], C[a, 1], C[a, 2]
        for b in range(3):
            CG[a, b] = c0 * E[0, b] + c1 * E[1, b] + c2 * E[2, b]
    out_C[:, :] = CG


@njit(cache=True)
def _skew_into(x, y, z, out) -> None:
    out[0, 0] = out[1, 1] = out[2, 2] = 0.0
    out[0, 1], out[0, 2], out[1, 2] = -z, y, -x
    out[1, 0], out[2, 0], out[2, 1] = z, -y, x


@njit(cache=True)
def _left_multiply(F, X, out) -> None:
    """``out = F X = X + (F - I) X`` with only the blocks of ``_F_OFF_IDENTITY``: row-block
    updates along contiguous rows of ``X``."""
    n = X.shape[1]
    out[:, :] = X
    for a, c in _F_OFF_IDENTITY:
        d = 1.0 if a == c else 0.0
        m00, m01, m02 = F[3 * a, 3 * c] - d, F[3 * a, 3 * c + 1], F[3 * a, 3 * c + 2]
        m10, m11, m12 = F[3 * a + 1, 3 * c], F[3 * a + 1, 3 * c + 1] - d, F[3 * a + 1, 3 * c + 2]
        m20, m21, m22 = F[3 * a + 2, 3 * c], F[3 * a + 2, 3 * c + 1], F[3 * a + 2, 3 * c + 2] - d
        for col in range(n):
            x0, x1, x2 = X[3 * c, col], X[3 * c + 1, col], X[3 * c + 2, col]
            out[3 * a, col] += m00 * x0 + m01 * x1 + m02 * x2
            out[3 * a + 1, col] += m10 * x0 + m11 * x1 + m12 * x2
            out[3 * a + 2, col] += m20 * x0 + m21 * x1 + m22 * x2


@njit(cache=True)
def _covariance_step(S, F, G, q, T) -> None:
    """``S <- F S F^T + G diag(q) G^T`` in place: ``T = F S``, then ``S = F T^T`` (which is
    ``F S F^T`` for symmetric ``S``), both as block-sparse row updates (:func:`_left_multiply`),
    then the blocks of ``G diag(q) G^T`` that ``_G_BLOCKS`` makes nonzero. ``T`` is a
    (2, 15, 15) work array."""
    _left_multiply(F, S, T[0])
    T[1][:, :] = T[0].T
    _left_multiply(F, T[1], S)
    for a, na in _G_BLOCKS:  # pairs of blocks driven by the same noise
        for b, nb in _G_BLOCKS:
            if na == nb:
                _add_noise_block(S, G, q, a, b, na)


@njit(cache=True)
def _add_noise_block(S, G, q, a, b, noise) -> None:
    """``S[a, b] += G[a, noise] diag(q[noise]) G[b, noise]^T`` on 3-blocks."""
    q0, q1, q2 = q[3 * noise], q[3 * noise + 1], q[3 * noise + 2]
    for i in range(3):
        g0, g1, g2 = G[3 * a + i, 3 * noise] * q0, G[3 * a + i, 3 * noise + 1] * q1, G[3 * a + i, 3 * noise + 2] * q2
        for j in range(3):
            S[3 * a + i, 3 * b + j] += g0 * G[3 * b + j, 3 * noise] + g1 * G[3 * b + j, 3 * noise + 1] \
                + g2 * G[3 * b + j, 3 * noise + 2]


@njit(cache=True)
def _propagate_rows(r, v, C, b_f, b_w, acc, gyro, dt, g, out_r, out_v, out_C, F, G):
    scratch = np.empty((2, 3, 3))
    for i in range(r.shape[0]):
        F[i] = 0.0
        G[i] = 0.0
        step_into(r[i], v[i], C[i], b_f[i], b_w[i], acc[i], gyro[i], dt[i], g, out_r[i], out_v[i], out_C[i],
                  F[i], G[i], scratch)


@njit(cache=True)
def _propagate_steps_kernel(r, v, C, b_f, b_w, S, acc, gyro, dt, q_density, g):
    """For each of the J rows: every sample k with ``dt > 0`` steps the state (in place) and
    its covariance ``S`` (in place)."""
    F = np.zeros((15, 15))
    G = np.zeros((15, 15))
    T = np.empty((2, 15, 15))
    q = np.empty(15)
    scratch = np.empty((2, 3, 3))
    for j in range(r.shape[0]):
        for k in range(dt.shape[1]):
            h = dt[j, k]
            if h <= 0.0:
                continue
            step_into(r[j], v[j], C[j], b_f[j], b_w[j], acc[j, k], gyro[j, k], h, g, r[j], v[j], C[j], F, G, scratch)
            for m in range(15):
                q[m] = q_density[m] / h
            _covariance_step(S[j], F, G, q, T)


def propagate(state: ImuState, acc, gyro, dt, gravity=DEFAULT_GRAVITY, jacobians: bool = True):
    """One Euler-forward step of the primer's model (eqs. 54-60) at zero noise.

    Returns ``(next_state, F, G)``; ``F`` (``(..., 15, 15)``) is the Jacobian of the next error
    state with respect to the current one, ``G`` with respect to the discrete noise
    ``(n_v, n_f, n_w, n_bf, n_bw)`` (see the module docstring). With ``jacobians=False`` ``F``
    and ``G`` are None. ``dt = 0`` is the identity step. Vectorised over (broadcast) leading
    dimensions of the state and the samples; compiled (:func:`step_into`).
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
    F, G = np.empty((n, STATE_DIM, STATE_DIM)), np.empty((n, STATE_DIM, NOISE_DIM))
    _propagate_rows(r, v, C, b_f, b_w, acc, gyro, dt, g, out_r, out_v, out_C, F, G)
    next_state = ImuState(out_r.reshape(shape + vec), out_v.reshape(shape + vec), out_C.reshape(shape + (3, 3)),
                          b_f.reshape(shape + vec), b_w.reshape(shape + vec))
    if not jacobians:
        return next_state, None, None
    return next_state, F.reshape(shape + (STATE_DIM, STATE_DIM)), G.reshape(shape + (STATE_DIM, NOISE_DIM))


def propagate_steps(state: ImuState, cov, acc, gyro, dt, noise: "ImuNoise", gravity=DEFAULT_GRAVITY):
    """The EKF prediction through many samples: :func:`propagate` applied to ``acc[..., k],
    gyro[..., k], dt[..., k]`` in order, and ``S <- F S F^T + G Q_d G^T`` with
    ``Q_d = diag(R_i / dt)`` at each step; samples with ``dt = 0`` are skipped (identity steps).

    ``state`` and ``cov (..., 15, 15)`` have leading dimensions ``J`` (one state, or ``J``
    independent rows, e.g. keyframe intervals); the samples have shape ``(J, K, 3)`` and
    ``(J, K)``. Returns the final ``(state, cov)``. One compiled loop over rows and samples
    (:func:`step_into`, then the block-sparse covariance update), so there is no Python per
    sample."""
    acc, gyro = as_trailing(acc, (3,), "acc"), as_trailing(gyro, (3,), "gyro")
    dt = np.asarray(dt, dtype=float)
    single = dt.ndim == 1
    lead = (1,) if single else dt.shape[:1]
    K = dt.shape[-1]
    vec = (3,)
    # copies: the kernel steps the states and covariances in place
    r, v, C, S = (np.array(a) for a in rows(lead, (state.r, state.v, state.C, cov),
                                             (vec, vec, (3, 3), (STATE_DIM, STATE_DIM))))
    b_f, b_w, acc, gyro, dt = rows(lead, (state.b_f, state.b_w, acc.reshape(lead + (K, 3)),
                                          gyro.reshape(lead + (K, 3)), dt.reshape(lead + (K,))),
                                   (vec, vec, (K, 3), (K, 3), (K,)))
    _propagate_steps_kernel(r, v, C, b_f, b_w, S, acc, gyro, dt, noise.densities(), as_trailing(gravity, vec, "gravity"))
    S = 0.5 * (S + np.swapaxes(S, -1, -2))
    out = ImuState(r, v, C, b_f, b_w)
    return (out[0], S[0]) if single else (out, S)


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
