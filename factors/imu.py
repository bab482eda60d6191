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


def propagate(state: ImuState, acc, gyro, dt, gravity=DEFAULT_GRAVITY, jacobians: bool = True):
    """One Euler-forward step of the primer's model (eqs. 54-60) at zero noise.

    Returns ``(next_state, F, G)``; ``F`` (``(..., 15, 15)``) is the Jacobian of the next error
    state with respect to the current one, ``G`` with respect to the discrete noise
    ``(n_v, n_f, n_w, n_bf, n_bw)`` (see the module docstring). With ``jacobians=False`` only
    the next state is computed (``F`` and ``G`` are None). ``dt = 0`` is the identity step.
    """
    acc, gyro = np.asarray(acc, dtype=float), np.asarray(gyro, dtype=float)
    dt = np.asarray(dt, dtype=float)
    g = np.asarray(gravity, dtype=float)
    C, v = state.C, state.v
    f = acc - state.b_f
    w = gyro - state.b_w
    dts = dt[..., None]
    Ct = so3.inverse(C)
    Ct_g = np.einsum("...ij,j->...i", Ct, g)
    w_cross_v = np.cross(w, v)
    rotation = so3.exp(dts * w)
    next_state = ImuState(
        r=state.r + dts * np.einsum("...ij,...j->...i", C, v),
        v=v + dts * (Ct_g + f - w_cross_v),
        C=C @ rotation,
        b_f=state.b_f,
        b_w=state.b_w,
    )
    if not jacobians:
        return next_state, None, None
    dtm = dt[..., None, None]
    shape = np.broadcast_shapes(state.shape, dt.shape, w.shape[:-1])
    eye = np.eye(3)
    F = np.zeros(shape + (STATE_DIM, STATE_DIM))
    G = np.zeros(shape + (STATE_DIM, NOISE_DIM))
    C_gamma = C @ so3.gamma(dts * w)
    v_cross = so3.skew(v)
    F[..., R, R] = eye
    F[..., R, V] = dtm * C
    F[..., R, PHI] = -dtm * so3.skew(np.einsum("...ij,...j->...i", C, v))
    F[..., V, V] = eye - dtm * so3.skew(w)
    F[..., V, PHI] = dtm * (Ct @ so3.skew(g))
    F[..., V, BF] = -dtm * eye
    F[..., V, BW] = -dtm * v_cross
    F[..., PHI, PHI] = eye
    F[..., PHI, BW] = -dtm * C_gamma
    F[..., BF, BF] = eye
    F[..., BW, BW] = eye
    G[..., R, NV] = dtm * C
    G[..., V, NF] = -dtm * eye
    G[..., V, NW] = -dtm * v_cross
    G[..., PHI, NW] = -dtm * C_gamma
    G[..., BF, NBF] = dtm * eye
    G[..., BW, NBW] = dtm * eye
    return next_state, F, G


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
