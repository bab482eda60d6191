"""Every analytic Jacobian of the project against its numerical twin, at random points.

Each entry of :data:`CHECKS` draws one random point from a generator and returns the analytic
Jacobian and the central-difference one (:func:`factors.jacobians.numerical_jacobian`).
:func:`run_checks` evaluates each entry at many points -- rotations of ordinary size, tiny ones
(1e-9 to 1e-6 rad) and ones within 1e-3 rad of pi -- and keeps the worst error.
``smoother check-jacobians`` prints the result.
"""
from __future__ import annotations

from typing import Callable

import numpy as np

from factors import derivatives as d
from factors import jacobians, quaternion, so3
from factors.errors import InputError

#: Angles closer to pi than this are not used where a numerical step could cross pi (log jumps there).
PI_MARGIN_FOR_LOG = 1e-4


def random_rotation_vector(rng: np.random.Generator, regime: str | None = None, pi_margin: float = 1e-9) -> np.ndarray:
    """A rotation vector with a random axis and an angle from one of three regimes:
    ``"tiny"`` (1e-9 to 1e-6 rad, log-uniform), ``"near_pi"`` (pi - 1e-3 to pi - ``pi_margin``,
    log-uniform in the distance to pi) or ``"any"`` (uniform in [0, pi)). ``None`` picks one."""
    regime = regime or rng.choice(["tiny", "near_pi", "any", "any"])
    axis = rng.normal(size=3)
    axis /= np.linalg.norm(axis)
    if regime == "tiny":
        angle = 10 ** rng.uniform(-9, -6)
    elif regime == "near_pi":
        angle = np.pi - 10 ** rng.uniform(np.log10(pi_margin), -3)
    elif regime == "any":
        angle = rng.uniform(0, np.pi)
    else:
        raise InputError(f"unknown regime {regime!r}")
    return angle * axis


def random_rotation(rng: np.random.Generator, regime: str | None = None, pi_margin: float = 1e-9) -> np.ndarray:
    """``exp`` of :func:`random_rotation_vector`."""
    return so3.exp(random_rotation_vector(rng, regime, pi_margin))


def _num(f, *args, **kw):
    return jacobians.numerical_jacobian(f, *args, **kw)


def _rotate_wrt_rotation(rng):
    C, r = random_rotation(rng), rng.normal(size=3) * 3
    return d.rotate_wrt_rotation(C, r), _num(lambda X: X @ r, C)[0]


def _rotate_wrt_vector(rng):
    C, r = random_rotation(rng), rng.normal(size=3)
    return d.rotate_wrt_vector(C), _num(lambda x: C @ x, r)[0]


def _inverse(rng):
    C = random_rotation(rng)
    return d.inverse_wrt_rotation(C), _num(so3.inverse, C)[0]


def _compose_left(rng):
    C1, C2 = random_rotation(rng), random_rotation(rng)
    return d.compose_wrt_left(C1), _num(so3.compose, C1, C2)[0]


def _compose_right(rng):
    C1, C2 = random_rotation(rng), random_rotation(rng)
    return d.compose_wrt_right(C1), _num(so3.compose, C1, C2)[1]


def _exp(rng):
    phi = random_rotation_vector(rng, pi_margin=1e-9)
    return d.exp_wrt_vector(phi), _num(so3.exp, phi, arg_kinds=["vector"])[0]


def _log(rng):
    C = random_rotation(rng, pi_margin=PI_MARGIN_FOR_LOG)
    return d.log_wrt_rotation(C), _num(so3.log, C, arg_kinds=["rotation"])[0]


def _boxplus(rng):
    C, phi = random_rotation(rng), random_rotation_vector(rng)
    ana = np.hstack([d.boxplus_wrt_rotation(C, phi), d.boxplus_wrt_vector(C, phi)])
    num = np.hstack(_num(so3.boxplus, C, phi, arg_kinds=["rotation", "vector"], value_kind="rotation"))
    return ana, num


def _boxminus(rng):
    C2 = random_rotation(rng)
    C1 = so3.boxplus(C2, random_rotation_vector(rng, pi_margin=PI_MARGIN_FOR_LOG))
    ana = np.hstack([d.boxminus_wrt_left(C1, C2), d.boxminus_wrt_right(C1, C2)])
    num = np.hstack(_num(so3.boxminus, C1, C2, arg_kinds=["rotation", "rotation"], value_kind="vector"))
    return ana, num


def _gamma_inverse(rng):
    """Gamma_inv is the inverse of Gamma (the check that the two closed forms agree)."""
    phi = random_rotation_vector(rng, pi_margin=PI_MARGIN_FOR_LOG)
    return so3.gamma_inv(phi) @ so3.gamma(phi), np.eye(3)


def _quaternion_rotate(rng):
    """Eq. (35) through quaternions: d q(r) / d q = -(q(r))^x."""
    q, r = quaternion.exp(random_rotation_vector(rng)), rng.normal(size=3)
    C = quaternion.to_matrix(q)
    num = _num(lambda X: quaternion.rotate(quaternion.from_matrix(X), r), C)[0]
    return d.rotate_wrt_rotation(C, r), num


#: name -> draw(rng) returning (analytic, numerical).
CHECKS: dict[str, Callable] = {
    "exp: Gamma (31)": _exp,
    "log: Gamma^-1 (32)": _log,
    "Gamma^-1 Gamma = I": _gamma_inverse,
    "coordinate map wrt rotation (27)": _rotate_wrt_rotation,
    "coordinate map wrt vector (26)": _rotate_wrt_vector,
    "quaternion coordinate map (35, 27)": _quaternion_rotate,
    "inverse (28)": _inverse,
    "composition wrt left (29)": _compose_left,
    "composition wrt right (30)": _compose_right,
    "boxplus wrt (Phi, phi)": _boxplus,
    "boxminus wrt (Phi1, Phi2)": _boxminus,
}


def register(name: str, draw: Callable) -> None:
    """Add a check (used by modules with further analytic Jacobians, e.g. the IMU model)."""
    CHECKS[name] = draw


def run_checks(samples: int = 200, seed: int = 0, atol: float = 1e-6, rtol: float = 1e-6,
               names: list[str] | None = None) -> list[jacobians.Comparison]:
    """Evaluate each registered check at ``samples`` random points; the worst error per check."""
    rng = np.random.default_rng(seed)
    results = []
    for name, draw in CHECKS.items():
        if names is not None and name not in names:
            continue
        worst_abs, worst_rel, ok = 0.0, 0.0, True
        for _ in range(samples):
            analytic, numerical = draw(rng)
            c = jacobians.compare(name, analytic, numerical, atol, rtol)
            worst_abs, worst_rel, ok = max(worst_abs, c.max_abs_error), max(worst_rel, c.max_rel_error), ok and c.ok
        results.append(jacobians.Comparison(name, worst_abs, worst_rel, ok))
    return results


def _random_imu_point(rng):
    from factors import imu

    state = imu.ImuState(
        r=rng.normal(size=3) * 10,
        v=rng.normal(size=3) * 5,
        C=random_rotation(rng),
        b_f=rng.normal(size=3) * 0.5,
        b_w=rng.normal(size=3) * 0.2,
    )
    acc, gyro = rng.normal(size=3) * 5, rng.normal(size=3) * 4  # several rad/s
    dt = rng.uniform(1e-3, 0.05)
    return state, acc, gyro, dt


def _process_F(rng):
    from factors import imu

    state, acc, gyro, dt = _random_imu_point(rng)
    _, F, _ = imu.propagate(state, acc, gyro, dt)
    num = _num(lambda x: imu.propagate(x, acc, gyro, dt, jacobians=False)[0], state,
               arg_kinds=[imu.StateManifold], value_kind=imu.StateManifold)[0]
    return F, num


def _process_G(rng):
    from factors import imu

    state, acc, gyro, dt = _random_imu_point(rng)
    _, _, G = imu.propagate(state, acc, gyro, dt)
    num = _num(lambda n: imu.propagate_with_noise(state, acc, gyro, dt, n), np.zeros(imu.NOISE_DIM),
               arg_kinds=["vector"], value_kind=imu.StateManifold)[0]
    return G, num


register("IMU process F (54-60)", _process_F)
register("IMU process G (54-60)", _process_G)


def _random_state(rng):
    from factors import imu

    return imu.ImuState(r=rng.normal(size=3) * 10, v=rng.normal(size=3) * 5, C=random_rotation(rng),
                        b_f=rng.normal(size=3) * 0.5, b_w=rng.normal(size=3) * 0.2)


def _pose_measurement_H(rng):
    """The pose sensor's H (primer VI.D) as the Jacobian of the residual e(x) = (r - r~, C [-] C~)
    with respect to the error state."""
    from factors import imu, measurements

    x = _random_state(rng)
    r_m, C_m = x.r + rng.normal(size=3) * 0.1, so3.boxplus(x.C, rng.normal(size=3) * 0.1)
    _, (J_r, J_C) = measurements.pose_residual(x.r, x.C, r_m, C_m, jacobians=True)
    H = np.zeros((6, imu.STATE_DIM))
    H[:, imu.R], H[:, imu.PHI] = J_r, J_C
    num = _num(lambda s: measurements.pose_residual(s.r, s.C, r_m, C_m), x,
               arg_kinds=[imu.StateManifold], value_kind="vector")[0]
    return H, num


def _relative_pose_jacobians(rng):
    """The odometry residual at random poses whose residual rotation ``C_i^T C_j dC^T`` keeps
    ``PI_MARGIN_FOR_LOG`` from pi, where ``log`` (and so the central differences) jumps."""
    from factors import measurements

    Ci, dC = random_rotation(rng), random_rotation(rng)
    Cj = Ci @ random_rotation(rng, pi_margin=PI_MARGIN_FOR_LOG) @ dC
    ri, rj = rng.normal(size=3) * 5, rng.normal(size=3) * 5
    dr = rng.normal(size=3)
    _, J = measurements.relative_pose_residual(Ci, ri, Cj, rj, dr, dC, jacobians=True)
    num = _num(lambda a, b, c, d: measurements.relative_pose_residual(a, b, c, d, dr, dC), Ci, ri, Cj, rj,
               arg_kinds=["rotation", "vector", "rotation", "vector"], value_kind="vector")
    return np.hstack(J), np.hstack(num)


def _imu_residual_jacobians(rng):
    """The IMU factor's residual (preintegration) with respect to both keyframes' error states,
    over an interval of 10-60 samples at rates of several rad/s, with a gyro-bias offset."""
    from factors import imu, preintegration

    n = rng.integers(10, 60)
    acc, gyro = rng.normal(size=(1, n, 3)) * 3, rng.normal(size=(1, n, 3)) * 3
    dt = np.full((1, n), rng.uniform(2e-3, 1e-2))
    xi = _random_state(rng)
    pre = preintegration.integrate(acc, gyro, dt, xi.b_w[None])[0]
    xi = xi.replace(b_w=xi.b_w + rng.normal(size=3) * 0.01)
    xj = imu.boxplus(preintegration.predict(pre, xi), rng.normal(size=15) * 0.05)
    _, (Ji, Jj) = preintegration.residual(pre, xi, xj, jacobians=True)
    num = _num(lambda a, b: preintegration.residual(pre, a, b), xi, xj,
               arg_kinds=[imu.StateManifold] * 2, value_kind="vector")
    return np.hstack([Ji, Jj]), np.hstack(num)


def random_extrinsic(rng) -> np.ndarray:
    """A 4x4 ``T_BS`` with a random rotation and a lever arm of up to ~2 m."""
    T = np.eye(4)
    T[:3, :3], T[:3, 3] = random_rotation(rng), rng.normal(size=3)
    return T


def random_sensor_row(model, state, rng) -> np.ndarray:
    """A measurement row of ``model`` (:mod:`factors.sensor_models`) near the prediction at
    ``state`` (so the attitude residual stays small even where the attitude is near pi), with a
    random extrinsic."""
    from factors import sensor_models as sm

    T = random_extrinsic(rng)
    R = T[:3, :3]
    z = state.r + state.C @ T[:3, 3] + rng.normal(size=3) * 0.1
    Z = so3.boxplus(state.C @ R, rng.normal(size=3) * 0.1)
    if model is sm.POSITION:
        return sm.pack_position(z[None], T)[0]
    if model is sm.ORIENTATION:
        return sm.pack_orientation(Z[None], T)[0]
    if model is sm.POSE:
        return sm.pack_pose(z[None], Z[None], T)[0]
    if model is sm.ALTITUDE:
        return sm.pack_altitude(z[None, 2], T)[0]
    if model is sm.MAGNETOMETER:  # a measured direction ~0.1 rad from the predicted one
        m = rng.normal(size=3)
        return sm.pack_magnetometer((so3.exp(rng.normal(size=3) * 0.1) @ R.T @ state.C.T @ m)[None], m, T)[0]
    if model is sm.ROLL_PITCH:  # the measured heading anything: the model must not care
        return sm.pack_orientation((so3.exp(np.array([0.0, 0.0, rng.uniform(-np.pi, np.pi)])) @ Z)[None], T)[0]
    return sm.pack_velocity(rng.normal(size=(1, 3)), rng.normal(size=(1, 3)) * 3, T)[0]


def _sensor_model_H(name: str):
    """The error-state Jacobian of a sensor model's kernel against central differences of its
    residual over the state (boxplus perturbation), with a random extrinsic."""
    def draw(rng):
        from factors import imu, sensor_models as sm

        model = getattr(sm, name)
        x = _random_state(rng)
        row = random_sensor_row(model, x, rng)
        _, H = sm.evaluate_one(model, x, row)
        num = _num(lambda s: sm.evaluate_one(model, s, row)[0], x, arg_kinds=[imu.StateManifold],
                   value_kind="vector")[0]
        return H, num

    return draw


def _odometry_jacobians(rng):
    """The relative pose of a sensor with a random extrinsic (as :func:`_relative_pose_jacobians`)."""
    from factors import sensor_models as sm

    T = random_extrinsic(rng)
    R = T[:3, :3]
    Ci, dC = random_rotation(rng), random_rotation(rng)
    Cj = Ci @ R @ random_rotation(rng, pi_margin=PI_MARGIN_FOR_LOG) @ dC @ R.T
    ri, rj, dr = rng.normal(size=3) * 5, rng.normal(size=3) * 5, rng.normal(size=3)
    _, J = sm.odometry_residual(Ci, ri, Cj, rj, dr, dC, T, jacobians=True)
    num = _num(lambda a, b, c, d: sm.odometry_residual(a, b, c, d, dr, dC, T), Ci, ri, Cj, rj,
               arg_kinds=["rotation", "vector", "rotation", "vector"], value_kind="vector")
    return np.hstack(J), np.hstack(num)


register("pose measurement H (61-63)", _pose_measurement_H)
for _model in ("POSITION", "ORIENTATION", "POSE", "VELOCITY", "ROLL_PITCH", "ALTITUDE", "MAGNETOMETER"):
    register(f"{_model.lower()} sensor with extrinsic T_BS, H", _sensor_model_H(_model))
register("odometry of a sensor with extrinsic T_BS", _odometry_jacobians)
register("relative pose residual", _relative_pose_jacobians)
register("IMU factor residual (preintegrated)", _imu_residual_jacobians)
