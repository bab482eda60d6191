"""The IMU integrated once for every sensor of a dataset: the gyro's attitude relative to the
start and the sums through which a gyro bias and the specific force enter the mounting check
(:mod:`smoother.diagnosis.mounting_data`; derivation in ``docs/mounting.md``).

Each sample is held over its step, as the estimators hold it (docs/design.md, section 5); a time
between two samples continues its sample's step. Prefix products and cumulative sums: linear in
the recording, no loop per sample.
"""
from __future__ import annotations

from dataclasses import dataclass
from functools import cached_property

import numpy as np

from datasets.types import Dataset, ImuSamples
from factors import so3
from factors.scan import prefix_products

#: Rows of the blocks :func:`chained` multiplies out first.
_BLOCK = 64


@dataclass(frozen=True, eq=False)
class ImuIntegrals:
    """The IMU samples ``imu`` integrated once for every sensor of a dataset, from the readings
    minus the initial bias estimates ``b_f``, ``b_w``, each sample held over its step (the
    estimators' zero-order hold). At sample ``k`` (``t_0`` the first):

    * ``G_k`` the gyro's attitude relative to the first sample (``G_{k+1} = G_k exp(dt w_k)``);
    * ``Sigma_k``, the integral of ``G`` up to sample ``k``, exact for held readings:
      ``Sigma_{k+1} = Sigma_k + dt G_k Gamma(dt w_k)`` (``int_0^1 exp(s phi^x) ds = Gamma(phi)``, eq.
      33); a gyro bias ``b`` turns ``G_t`` into ``exp(-(Sigma_t - Sigma_s) b) G_t`` relative to any
      time ``s``, to first order in ``b`` (eqs. 31, 24);
    * ``F_k``, the integral of ``G f`` (the specific force in the frame of ``G``), exact likewise;
    * ``K_k = sum_{i<k} dt_i (G_i f_i)^x Sigma_i``, the integral of ``(G f)^x Sigma`` to first order
      in the step (for the velocity family; computed when used).
    """

    imu: ImuSamples
    b_f: np.ndarray
    b_w: np.ndarray

    @cached_property
    def _steps(self):
        t = self.imu.t
        dt = np.diff(t)[:, None]
        w, f = self.imu.gyro - self.b_w, self.imu.acc - self.b_f
        G = np.empty((len(t), 3, 3))
        G[0] = np.eye(3)
        G[1:] = chained(so3.exp(dt * w[:-1]))
        step = dt[:, :, None] * (G[:-1] @ so3.gamma(dt * w[:-1]))
        Sigma = np.zeros_like(G)
        np.cumsum(step, axis=0, out=Sigma[1:])
        F = np.zeros((len(t), 3))
        np.cumsum(np.einsum("kij,kj->ki", step, f[:-1]), axis=0, out=F[1:])
        return w, f, G, Sigma, F

    @cached_property
    def _K(self):
        _, f, G, Sigma, _ = self._steps
        dt = np.diff(self.imu.t)[:, None, None]
        K = np.zeros_like(Sigma)
        np.cumsum(dt * (so3.skew(np.einsum("kij,kj->ki", G[:-1], f[:-1])) @ Sigma[:-1]), axis=0, out=K[1:])
        return K

    def at(self, t, with_K: bool = False):
        """``(G, Sigma, F, K or None)`` at times ``t``: each sample's step continued over the
        part ``h = t - t_k`` of it (``G_k exp(h w_k)``, ``Sigma_k + h G_k Gamma(h w_k)``, ...)."""
        w, f, G, Sigma, F = self._steps
        k = self.imu.held(t)
        h = np.maximum(np.asarray(t, dtype=float) - self.imu.t[k], 0.0)[:, None]
        part = h[:, :, None] * (G[k] @ so3.gamma(h * w[k]))
        G_t = G[k] @ so3.exp(h * w[k])
        Sigma_t = Sigma[k] + part
        F_t = F[k] + np.einsum("kij,kj->ki", part, f[k])
        K_t = None
        if with_K:
            K_t = self._K[k] + h[:, :, None] * (so3.skew(np.einsum("kij,kj->ki", G[k], f[k])) @ Sigma[k])
        return G_t, Sigma_t, F_t, K_t


def chained(M: np.ndarray) -> np.ndarray:
    """Inclusive prefix products ``M_0 M_1 ... M_k`` of ``M`` (K, 3, 3), later factors on the
    right: :func:`factors.scan.prefix_products` within blocks of :data:`_BLOCK` rows, then over
    the blocks' totals, then each block behind the product of those before it (about a third of
    the matrix products of one scan over all K, and as exact)."""
    K = len(M)
    X = np.concatenate([M, np.broadcast_to(np.eye(3), ((-K) % _BLOCK, 3, 3))]).reshape(-1, _BLOCK, 3, 3)
    inner = prefix_products(np.swapaxes(X, 0, 1), later_on_left=False)
    totals = prefix_products(inner[-1], later_on_left=False)
    out = np.empty_like(X)
    out[0] = inner[:, 0]
    out[1:] = totals[:-1, None] @ np.swapaxes(inner[:, 1:], 0, 1)
    return out.reshape(-1, 3, 3)[:K]


def imu_integrals(dataset: Dataset) -> ImuIntegrals:
    """The :class:`ImuIntegrals` of ``dataset``'s IMU, about its initial bias estimates."""
    return ImuIntegrals(dataset.imu, dataset.initial.b_f, dataset.initial.b_w)
