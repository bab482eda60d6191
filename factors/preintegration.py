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
``S_{k+1} = F S F^T + G Q_d G^T``, expressed in the residual's body-``i`` coordinates.

Everything is vectorised over intervals: arrays of shape ``(J, K, ...)`` hold ``J`` intervals of
up to ``K`` samples; padding samples have ``dt = 0``, which is exactly the identity step, so the
Python loop runs over the ``K`` samples of the longest interval, never over intervals.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from factors import imu, so3

#: Standard deviation (in each error-state unit: m, m/s, rad, m/s^2, rad/s) added to every
#: IMU residual's covariance so that it is positive definite even for one-sample intervals.
COVARIANCE_FLOOR = 1e-7

#: Default gyro-bias change (rad/s) beyond which an interval is integrated again.
REINTEGRATION_THRESHOLD = 0.02



def _basis_cross(W: np.ndarray) -> np.ndarray:
    """``out[j, :, :, l] = e_l^x W[j]`` for ``W (J, 3, n)``: the cross products of the basis vectors
    with every column, as signed copies of W's rows."""
    out = np.zeros(W.shape + (3,))
    out[:, 1, :, 0], out[:, 2, :, 0] = -W[:, 2], W[:, 1]
    out[:, 0, :, 1], out[:, 2, :, 1] = W[:, 2], -W[:, 0]
    out[:, 0, :, 2], out[:, 1, :, 2] = -W[:, 1], W[:, 0]
    return out


@dataclass
class Preintegrated:
    """Preintegrated quantities of ``J`` intervals (leading dimension ``J`` on every array).

    ``dC (J,3,3)``, ``W (J,3,10)``, ``Rm (J,3,10)``, their gyro-bias Jacobians
    ``JC (J,3,3)``, ``dW (J,3,10,3)``, ``dRm (J,3,10,3)``, the linearisation point ``b_w_bar
    (J,3)``, the interval lengths ``duration (J,)`` and, if computed, the residual covariance
    ``cov (J,15,15)`` in body-``i`` coordinates. ``samples`` keeps the IMU samples
    ``(acc, gyro, dt)`` padded to ``(J, K, ...)`` so an interval can be integrated again.
    """

    dC: np.ndarray
    W: np.ndarray
    Rm: np.ndarray
    JC: np.ndarray
    dW: np.ndarray
    dRm: np.ndarray
    b_w_bar: np.ndarray
    duration: np.ndarray
    samples: tuple
    cov: np.ndarray | None = None

    def __len__(self) -> int:
        return len(self.duration)

    def __getitem__(self, index) -> "Preintegrated":
        if not isinstance(index, (int, np.integer)):
            index = np.arange(len(self))[index]
        pick = lambda a: None if a is None else a[index]  # noqa: E731
        return Preintegrated(
            self.dC[index], self.W[index], self.Rm[index], self.JC[index], self.dW[index],
            self.dRm[index], self.b_w_bar[index], self.duration[index],
            tuple(s[index] for s in self.samples), pick(self.cov),
        )

    def assign(self, index, other: "Preintegrated") -> None:
        """Overwrite intervals ``index`` with ``other``'s (same count), keeping the covariance."""
        for name in ("dC", "W", "Rm", "JC", "dW", "dRm", "b_w_bar", "duration"):
            getattr(self, name)[index] = getattr(other, name)

    def corrected(self, b_w: np.ndarray):
        """``(dC, W, Rm)`` at gyro bias ``b_w`` (first order around ``b_w_bar``) and the offset
        ``d = b_w - b_w_bar``."""
        d = np.asarray(b_w, dtype=float) - self.b_w_bar
        W = self.W + np.einsum("...acl,...l->...ac", self.dW, d)
        Rm = self.Rm + np.einsum("...acl,...l->...ac", self.dRm, d)
        dC = so3.exp(np.einsum("...al,...l->...a", self.JC, d)) @ self.dC
        return dC, W, Rm, d

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


def _z(v_i, gamma, b_f) -> np.ndarray:
    """``z = (v_i, gamma, 1, -b_f)`` (shape ``(..., 10)``)."""
    one = np.ones(np.shape(v_i)[:-1] + (1,))
    return np.concatenate([v_i, gamma, one, -np.asarray(b_f, dtype=float)], axis=-1)


def integrate(acc, gyro, dt, b_w_bar) -> Preintegrated:
    """Preintegrate ``J`` intervals of padded samples ``acc, gyro (J, K, 3)``, ``dt (J, K)``
    around gyro biases ``b_w_bar (J, 3)`` (no covariance: see :func:`noise_covariance`)."""
    acc, gyro, dt = (np.asarray(a, dtype=float) for a in (acc, gyro, dt))
    b_w_bar = np.asarray(b_w_bar, dtype=float)
    J, K = dt.shape
    eye = np.eye(3)
    dC = np.broadcast_to(eye, (J, 3, 3)).copy()
    W = np.zeros((J, 3, 10))
    W[:, :, 0:3] = eye
    Rm = np.zeros((J, 3, 10))
    JC = np.zeros((J, 3, 3))
    dW = np.zeros((J, 3, 10, 3))
    dRm = np.zeros((J, 3, 10, 3))
    for k in range(K):
        h = dt[:, k]
        hm = h[:, None, None]
        hm4 = hm[..., None]
        w = gyro[:, k] - b_w_bar
        A = eye - hm * so3.skew(w)
        JCd = so3.skew(np.swapaxes(JC, 1, 2))  # (JC e_l)^x for l = 0, 1, 2: shape (J, l, 3, 3)
        dCt = np.swapaxes(dC, 1, 2)
        dC_W = dC @ W
        # Bias Jacobians use the values at step k, so they are updated first. Tensors (J, 3, 10, 3)
        # are contracted as (J, 3, 30) matrices; d^x W for d = e_l is a signed row shuffle.
        dW_new = (A @ dW.reshape(J, 3, 30)).reshape(J, 3, 10, 3) + hm4 * _basis_cross(W)
        dW_new[:, :, 3:6, :] -= hm4 * np.moveaxis(dCt[:, None] @ JCd, 1, -1)
        dRm += hm4 * (np.moveaxis(JCd @ dC_W[:, None], 1, -1) + (dC @ dW.reshape(J, 3, 30)).reshape(J, 3, 10, 3))
        dW = dW_new
        Rm = Rm + hm * dC_W
        B = np.zeros((J, 3, 10))
        B[:, :, 3:6] = dCt
        B[:, :, 6] = acc[:, k]
        B[:, :, 7:10] = eye
        W = A @ W + hm * B
        JC = JC - hm * (dC @ so3.gamma(h[:, None] * w))
        dC = dC @ so3.exp(h[:, None] * w)
    return Preintegrated(dC, W, Rm, JC, dW, dRm, b_w_bar.copy(), dt.sum(axis=1), (acc, gyro, dt))


def noise_covariance(samples: tuple, reference: imu.ImuState, noise: imu.ImuNoise,
                     gravity=imu.DEFAULT_GRAVITY) -> np.ndarray:
    """Covariance ``(J, 15, 15)`` of the IMU residual of ``J`` padded intervals ``samples = (acc,
    gyro, dt)``: the primer's ``F`` and ``G`` propagated along the trajectory that starts at the
    ``reference`` states (leading dimension ``J``) with zero covariance,
    ``S <- F S F^T + G Q_d G^T`` -- the EKF's own covariance growth over the interval -- then
    rotated into the residual's body-``i`` coordinates, ``T S T^T`` with
    ``T = diag(C_i^T, I, C_i^T, I, I)``.

    A floor of ``COVARIANCE_FLOOR^2`` is added on the diagonal: without the velocity noise
    ``n_v`` the position of a one-sample interval is deterministic (``r_j = r_i + dt C_i v_i``),
    and a zero variance would make the factor's noise model singular. The floor stands for the
    model's own discretisation error and is far below any sensor's noise."""
    acc, gyro, dt = samples
    J, K = dt.shape
    state = reference
    S = np.zeros((J, imu.STATE_DIM, imu.STATE_DIM))
    densities = noise.densities()
    for k in range(K):
        state, F, G = imu.propagate(state, acc[:, k], gyro[:, k], dt[:, k], gravity)
        h = dt[:, k]
        q = densities / np.where(h > 0, h, np.inf)[:, None]  # diag of Q_d = R / dt (0 for dt = 0)
        S = F @ S @ np.swapaxes(F, 1, 2) + (G * q[:, None, :]) @ np.swapaxes(G, 1, 2)
    eye = np.eye(3)
    T = np.zeros((J, imu.STATE_DIM, imu.STATE_DIM))
    Ct = np.swapaxes(reference.C, -1, -2)
    T[:, imu.R, imu.R] = Ct
    T[:, imu.V, imu.V] = eye
    T[:, imu.PHI, imu.PHI] = Ct
    T[:, imu.BF, imu.BF] = eye
    T[:, imu.BW, imu.BW] = eye
    cov = T @ S @ np.swapaxes(T, 1, 2)
    cov = 0.5 * (cov + np.swapaxes(cov, 1, 2))
    return cov + COVARIANCE_FLOOR**2 * np.eye(imu.STATE_DIM)


def predict(pre: Preintegrated, state_i: imu.ImuState, gravity=imu.DEFAULT_GRAVITY) -> imu.ImuState:
    """The state at keyframe ``j`` predicted from ``state_i`` (biases held constant): exactly the
    sample-by-sample Euler-forward propagation when ``state_i.b_w == b_w_bar``, first order in
    the gyro-bias offset otherwise."""
    dC, W, Rm, _ = pre.corrected(state_i.b_w)
    gamma = np.einsum("...ba,b->...a", state_i.C, np.asarray(gravity, dtype=float))
    z = _z(state_i.v, gamma, state_i.b_f)
    return imu.ImuState(
        r=state_i.r + np.einsum("...ab,...bc,...c->...a", state_i.C, Rm, z),
        v=np.einsum("...ac,...c->...a", W, z),
        C=state_i.C @ dC,
        b_f=state_i.b_f,
        b_w=state_i.b_w,
    )


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
    g = np.asarray(gravity, dtype=float)
    dC, W, Rm, d = pre.corrected(state_i.b_w)
    Ci, Cj = state_i.C, state_j.C
    Cit = np.swapaxes(Ci, -1, -2)
    gamma = np.einsum("...ab,b->...a", Cit, g)
    z = _z(state_i.v, gamma, state_i.b_f)
    u = np.einsum("...ab,...b->...a", Cit, state_j.r - state_i.r)
    X = Cit @ Cj @ np.swapaxes(dC, -1, -2)
    e_phi = so3.log(X)
    e = np.concatenate(
        [
            u - np.einsum("...ac,...c->...a", Rm, z),
            state_j.v - np.einsum("...ac,...c->...a", W, z),
            e_phi,
            state_j.b_f - state_i.b_f,
            state_j.b_w - state_i.b_w,
        ],
        axis=-1,
    )
    if not jacobians:
        return e
    shape = e.shape[:-1]
    Ji = np.zeros(shape + (15, 15))
    Jj = np.zeros(shape + (15, 15))
    eye = np.eye(3)
    R_, V_, P_, BF_, BW_ = imu.R, imu.V, imu.PHI, imu.BF, imu.BW
    gx_Cit = so3.skew(gamma) @ Cit
    Ginv = so3.gamma_inv(e_phi)
    JCd = np.einsum("...al,...l->...a", pre.JC, d)
    # position rows
    Ji[..., R_, R_] = -Cit
    Jj[..., R_, R_] = Cit
    Ji[..., R_, V_] = -Rm[..., :, 0:3]
    Ji[..., R_, P_] = so3.skew(u) @ Cit - Rm[..., :, 3:6] @ gx_Cit
    Ji[..., R_, BF_] = Rm[..., :, 7:10]
    Ji[..., R_, BW_] = -np.einsum("...acl,...c->...al", pre.dRm, z)
    # velocity rows
    Jj[..., V_, V_] = eye
    Ji[..., V_, V_] = -W[..., :, 0:3]
    Ji[..., V_, P_] = -W[..., :, 3:6] @ gx_Cit
    Ji[..., V_, BF_] = W[..., :, 7:10]
    Ji[..., V_, BW_] = -np.einsum("...acl,...c->...al", pre.dW, z)
    # attitude rows
    Jj[..., P_, P_] = Ginv @ Cit
    Ji[..., P_, P_] = -Ginv @ Cit
    Ji[..., P_, BW_] = -Ginv @ X @ so3.gamma(JCd) @ pre.JC
    # bias rows
    Ji[..., BF_, BF_] = -eye
    Jj[..., BF_, BF_] = eye
    Ji[..., BW_, BW_] = -eye
    Jj[..., BW_, BW_] = eye
    return e, (Ji, Jj)
