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
from typing import Callable

import numpy as np

from factors import imu, so3
from factors import sensor_models as sm
from factors.errors import InputError

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
        """``c [+] delta`` for ``delta`` the 8 error coordinates."""
        delta = np.asarray(delta, dtype=float)
        return Calibration(self.time_offset + float(delta[0]), so3.boxplus(self.R, delta[1:4]),
                           self.p + delta[4:7], self.scale + float(delta[7]))

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


#: The residual rows through which ``R_BS`` enters, where not all (a pose's attitude; its
#: position rows read the lever arm alone).
_ATTITUDE_ROWS = {"pose": slice(3, 6)}


def _with_extrinsic(rows: np.ndarray, rotation_at, lever_at, c: Calibration) -> np.ndarray:
    """``rows`` with the calibrated ``R_BS`` and ``p_BS`` in their slots."""
    out = np.array(rows, dtype=float)
    if rotation_at is not None:
        out[:, rotation_at:rotation_at + 9] = c.R.reshape(9)
    if lever_at is not None:
        out[:, lever_at:lever_at + 3] = c.p
    return out


def _one_state_extrinsic_jacobians(model: sm.SensorModel, states: imu.ImuState, rows: np.ndarray, H: np.ndarray):
    """``(de/drho, de/dp)`` (N, d, 3) each, of the unscaled residual (module docstring)."""
    n, d = H.shape[0], H.shape[1]
    J_rho, J_p = np.zeros((n, d, 3)), np.zeros((n, d, 3))
    C = states.C
    if model.name == "velocity":
        omega = rows[:, 3:6] - states.b_w
        p = rows[:, model.lever_at:model.lever_at + 3]
        u = states.v + np.cross(omega, p)
        H_v = H[:, :, 3:6]
        J_rho = H_v @ so3.skew(u)
        J_p = H_v @ so3.skew(omega)
        return J_rho, J_p
    if model.lever_at is not None:  # through r + C p
        J_p = H[:, :, 0:3] @ C
    if model.rotation_at is not None:  # through the attitude C R_BS
        rows_of_attitude = _ATTITUDE_ROWS.get(model.name, slice(None))
        J_rho[:, rows_of_attitude] = H[:, rows_of_attitude, 6:9] @ C
    return J_rho, J_p


def _scaled(e0: np.ndarray, H_parts: list[np.ndarray], z: np.ndarray, k: int, s: float):
    """Apply the scale to the first ``k`` residual rows: ``e = s (e0 + z) - z``, Jacobians times
    ``s``; returns ``(e, parts, de/ds)``."""
    e = e0.copy()
    ds = np.zeros(e0.shape)
    if k:
        h = e0[:, :k] + z
        e[:, :k] = s * h - z
        ds[:, :k] = h
        for J in H_parts:
            J[:, :k] *= s
    return e, H_parts, ds


def _stepped(states: imu.ImuState, imu_at, d: float, gravity):
    """The states one Euler step of ``d`` away, the step's ``F`` and the states' rates (None
    without ``imu_at``)."""
    if imu_at is None:
        return states, None, None
    acc, gyro = imu_at
    moved, F, _ = imu.propagate(states, acc, gyro, np.full(len(states), d), gravity)
    return moved, F, imu.state_derivative(states, acc, gyro, gravity)


def calibrated_residual(model: sm.SensorModel, measure: Callable, states: imu.ImuState, rows: np.ndarray,
                        c: Calibration, imu_at=None, gravity=imu.DEFAULT_GRAVITY):
    """``(e (N, d), H (N, d, 15), H_c (N, d, 8))`` of one-state measurement ``rows`` at
    ``states`` through the calibration ``c`` (module docstring). ``measure(states, rows) -> (e,
    H)`` runs the model's kernel over rows (:func:`datasets.kinds.measure_rows`); ``imu_at =
    (acc, gyro)`` (N, 3) each, the IMU reading held at each measurement's stamp, or None when the
    time offset is not a variable (then ``x' = x`` and its column is 0)."""
    moved, F, rate = _stepped(states, imu_at, c.time_offset, gravity)
    calibrated = _with_extrinsic(rows, model.rotation_at, model.lever_at, c)
    e0, H = measure(moved, calibrated)
    J_rho, J_p = _one_state_extrinsic_jacobians(model, moved, calibrated, H)
    J_t = np.zeros(e0.shape) if rate is None else np.einsum("nab,nb->na", H, rate)
    H_state = H if F is None else H @ F
    e, (H_state, J_t3, J_rho, J_p), J_s = _scaled(e0, [H_state, J_t[..., None], J_rho, J_p],
                                                  calibrated[:, :model.scaled], model.scaled, c.scale)
    return e, H_state, np.concatenate([J_t3, J_rho, J_p, J_s[..., None]], axis=2)


def calibrated_odometry_residual(states_i: imu.ImuState, states_j: imu.ImuState, rows: np.ndarray, c: Calibration,
                                 imu_at=None, gravity=imu.DEFAULT_GRAVITY):
    """``(e (N, 6), H (N, 6, 30), H_c (N, 6, 8))`` of relative pose ``rows``
    (:func:`factors.sensor_models.pack_odometry`) between ``states_i`` and ``states_j`` through
    ``c``; ``imu_at = ((acc_i, gyro_i), (acc_j, gyro_j))`` at the two stamps, or None."""
    at_i, at_j = (None, None) if imu_at is None else imu_at
    moved_i, F_i, rate_i = _stepped(states_i, at_i, c.time_offset, gravity)
    moved_j, F_j, rate_j = _stepped(states_j, at_j, c.time_offset, gravity)
    calibrated = _with_extrinsic(rows, sm.ODOMETRY_ROTATION_AT, sm.ODOMETRY_LEVER_AT, c)
    e0, H = sm.odometry_rows(moved_i, moved_j, calibrated)
    n = len(rows)
    C_i, C_j = moved_i.C, moved_j.C
    D = (moved_j.r + C_j @ c.p) - (moved_i.r + C_i @ c.p)
    J_rho, J_p = np.zeros((n, 6, 3)), np.zeros((n, 6, 3))
    H_rj, H_phij = H[:, 0:3, 15:18], H[:, 3:6, 21:24]
    J_rho[:, 0:3] = H_rj @ so3.skew(D) @ C_i
    J_rho[:, 3:6] = H_phij @ (C_j - C_i)
    J_p[:, 0:3] = H_rj @ (C_j - C_i)
    J_t = np.zeros((n, 6))
    H_state = H.copy()
    if rate_i is not None:
        J_t = np.einsum("nab,nb->na", H[:, :, :15], rate_i) + np.einsum("nab,nb->na", H[:, :, 15:], rate_j)
        H_state[:, :, :15] = H[:, :, :15] @ F_i
        H_state[:, :, 15:] = H[:, :, 15:] @ F_j
    e, (H_state, J_t3, J_rho, J_p), J_s = _scaled(e0, [H_state, J_t[..., None], J_rho, J_p],
                                                  calibrated[:, :sm.ODOMETRY_SCALED], sm.ODOMETRY_SCALED, c.scale)
    return e, H_state, np.concatenate([J_t3, J_rho, J_p, J_s[..., None]], axis=2)


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

    def boxplus(self, delta) -> "CalibrationSet":
        moved = []
        for c, prior, d in zip(self.values, self.priors, delta):
            full = np.zeros(CALIBRATION_DIM)
            full[prior.columns] = d
            moved.append(c.boxplus(full))
        return CalibrationSet(self.names, tuple(moved), self.priors, self.means)
