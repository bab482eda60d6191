"""The ``odometry`` kind: the relative pose of a sensor frame between consecutive poses of a
drifting source (:func:`factors.sensor_models.odometry_residual`), in the earlier pose's frame;
it connects two keyframes, so the smoothers use it and the EKF does not."""
from __future__ import annotations

import numpy as np

from datasets.kinds.base import Kind, noise, noisy, poses
from datasets.types import RelativePoseMeasurements
from factors import sensor_models as sm
from factors import so3
from factors.errors import InputError
from factors.selfcheck import PI_MARGIN_FOR_LOG, random_extrinsic, random_rotation, random_state


def _relative(t, r, C, cov, T_BS):
    Ct = np.swapaxes(C[:-1], 1, 2)
    dr = np.einsum("nab,nb->na", Ct, r[1:] - r[:-1])
    return RelativePoseMeasurements(t[:-1], t[1:], dr, Ct @ C[1:], cov, T_BS)


def _composed(data: RelativePoseMeasurements, spans: np.ndarray) -> RelativePoseMeasurements:
    """The measurements of each span ``(lo, hi)`` of ``spans (S, 2)`` composed in order into one
    from ``t_from[lo]`` to ``t_to[hi - 1]`` (:attr:`datasets.kinds.base.Kind.compose`):
    ``dr = dr_1 + dC_1 dr_2``, ``dC = dC_1 dC_2``. In the noise convention of
    :class:`~datasets.types.RelativePoseMeasurements` (``dr_meas = dr + n_r``, ``dC_meas = exp(n_Phi)
    dC``), ``exp(n_1) dC_1 exp(n_2) = exp(n_1 + dC_1 n_2) dC_1`` (the primer's eq. 24) and
    ``exp(n_1) dC_1 (dr_2 + n_r2) = dC_1 dr_2 + n_1 x dC_1 dr_2 + dC_1 n_r2`` to first order, so

        n_r = n_r1 + dC_1 n_r2 - (dC_1 dr_2)^x n_Phi1,      n_Phi = n_Phi1 + dC_1 n_Phi2

    and the covariance is ``J_1 S_1 J_1^T + J_2 S_2 J_2^T`` with ``J_1 = [[I, -(dC_1 dr_2)^x], [0,
    I]]``, ``J_2 = diag(dC_1, dC_1)``: the steps' noises independent, as the factors assume. In the
    sensor's frame, so a lever arm, a mounting and a scale (which multiplies every ``dr``, and so
    the composed one) apply to the composed measurement as to each."""
    spans = np.asarray(spans, dtype=int).reshape(-1, 2)
    lo, hi = spans[:, 0], spans[:, 1]
    dr, dC, cov = data.dr[lo].copy(), data.dC[lo].copy(), data.cov[lo].copy()
    for k in range(1, int((hi - lo).max(initial=1))):
        m = np.flatnonzero(lo + k < hi)  # the spans with a (k+1)-th measurement
        i = lo[m] + k
        step = np.einsum("nab,nb->na", dC[m], data.dr[i])  # dC_1 dr_2
        J1 = np.broadcast_to(np.eye(6), (len(m), 6, 6)).copy()
        J1[:, :3, 3:] = -so3.skew(step)
        J2 = np.zeros((len(m), 6, 6))
        J2[:, :3, :3] = J2[:, 3:, 3:] = dC[m]
        cov[m] = J1 @ cov[m] @ np.swapaxes(J1, 1, 2) + J2 @ data.cov[i] @ np.swapaxes(J2, 1, 2)
        dr[m] += step
        dC[m] = dC[m] @ data.dC[i]
    return RelativePoseMeasurements(data.t_from[lo], data.t_to[hi - 1], dr, dC, cov, data.T_BS)


def _simulate(truth, k, imu, T_BS, sigma, rng):
    R, p = sm.extrinsic_parts(T_BS)
    exact = _relative(truth.t[k], truth.position[k] + truth.C[k] @ p, truth.C[k] @ R, np.diag(sigma**2), T_BS)
    n = len(exact)
    return RelativePoseMeasurements(exact.t_from, exact.t_to, noisy(exact.dr, sigma[:3], rng),
                                    so3.boxplus(exact.dC, sigma[3:] * rng.standard_normal((n, 3))), exact.cov, T_BS)


def _read(sensor, clock):
    """Needs the rig's ``sigma``: a drifting source's pose covariances grow with the path and say
    nothing of one step."""
    if sensor.sigma is None:
        raise InputError("give sigma in the rig file, the noise of one step between consecutive poses "
                         "(translation [m], rotation [rad])")
    stream, t = poses(sensor, clock)
    return _relative(t, stream.position, stream.C, noise(sensor, 6, None, len(t) - 1), sensor.T_BS), clock.datum


def _random_row(rng):
    """Two states whose sensor frames' relative rotation differs from the measured one by a random
    rotation of any size short of pi (the residual's log is defined), random lever arms."""
    T = random_extrinsic(rng)
    R = T[:3, :3]
    xi, xj, dC = random_state(rng), random_state(rng), random_rotation(rng)
    xj = xj.replace(C=xi.C @ R @ random_rotation(rng, pi_margin=PI_MARGIN_FOR_LOG) @ dC @ R.T)
    return (xi, xj), sm.pack_odometry(rng.normal(size=(1, 3)), dC[None], T)[0]


KIND = Kind("odometry", RelativePoseMeasurements, 6, None, None, _simulate, None, _read, fields=("dr", "dC"),
            random_row=_random_row, default_sigma=(0.02, 0.005), times=("t_from", "t_to"),
            scaled_field="dr", sigma_units=("m",) * 3 + ("rad",) * 3,
            noise_groups=(("translation", (0, 1, 2)), ("rotation", (3, 4, 5))), compose=_composed)
