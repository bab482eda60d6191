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
            noise_groups=(("translation", (0, 1, 2)), ("rotation", (3, 4, 5))))
