"""The measurement kinds: each declared once, everything else iterates over :data:`KINDS`.

A :class:`~datasets.kinds.base.Kind` names its data type (a dataclass of :mod:`datasets.types`),
its measurement model (:class:`factors.sensor_models.SensorModel`: residual, Jacobians, GTSAM
factor, EKF update all run the model's one compiled kernel), how its measurements become the
kernel's rows, how the simulator draws them, what they say about the initial trajectory and how a
rig's sensor of that kind is read. Each kind lives in a module of this package (``pose``,
``position`` with ``gnss``, ``orientation``, ``roll_pitch``, ``velocity``, ``odometry``,
``altitude``, ``magnetometer``). A relative kind
(``odometry``) connects two keyframes and has no one-state model: the smoothers use it through
:func:`factors.sensor_models.odometry_residual`, the EKF does not.

Adding a kind: a module with its :class:`~datasets.kinds.base.Kind` (and its model, if new, with
a kernel of the common signature), its tests, and one line in :data:`KINDS`. The registry checks
what the kind declares (:func:`registered`) and registers its model's Jacobian check with
:mod:`factors.selfcheck` (``smoother check-jacobians`` runs it); the every-kind tests
(``tests/datasets/test_every_kind.py``) run over the registry.

The compiled :func:`measure_into` dispatches to a model's kernel by its index in :data:`MODELS`;
the EKF's loop and the batch solver's blocks call it, so neither knows any kind by name.
"""
from __future__ import annotations

import warnings
from contextlib import contextmanager
from dataclasses import fields as dataclass_fields

import numpy as np
from numba import literal_unroll, njit
from numba.core.errors import NumbaExperimentalFeatureWarning

from datasets.kinds import altitude, magnetometer, odometry, orientation, pose, position, roll_pitch, velocity
from datasets.kinds.base import Clock, Kind, kind_sigmas, with_sigma_factor
from datasets.ranges import SIGMA_RANGES
from datasets.types import Dataset, Sensor
from factors import calibration, imu, jacobians, selfcheck
from factors import sensor_models as sm
from factors.errors import InputError
from factors.selfcheck import random_rotation
from factors.small_linalg import matmul_into

__all__ = ["KINDS", "KIND_NAMES", "LAYOUTS", "MODELS", "Clock", "Kind", "attached_into", "attached_noise",
           "attached_noise_into", "attached_noise_work", "attached_rows", "attached_work",
           "calibrated_into", "calibrated_rows", "evaluate", "kind_sigmas", "measure_into", "measure_rows",
           "model_index", "quiet_dispatch", "registered", "sensors_of", "with_sigma_factor"]


def registered(*kinds: Kind) -> dict[str, Kind]:
    """The kinds by name, each checked against the rules the estimators rely on: a unique name;
    a residual of at most :data:`factors.sensor_models.MAX_RESIDUAL_DIM` and kernel rows of at
    most :data:`factors.sensor_models.MAX_ROW_WIDTH` numbers (the room the EKF and the sliding
    window hold); a model of the kind's dimension; a data type whose fields are the kind's
    ``times``, ``fields``, ``cov``, ``T_BS`` in that order; a ``scaled_field`` exactly where the
    model has scaled rows; a ``default_sigma`` that
    :func:`kind_sigmas` reads; a unit of :data:`datasets.ranges.SIGMA_RANGES` for each residual
    axis (``sigma_units``); a ``random_row`` of the declared width; ``noise_groups`` with distinct
    names whose axes partition the residual's, one unit each. An error naming the
    kind and the rule else (an InputError)."""
    out: dict[str, Kind] = {}
    for k in kinds:
        def refuse(rule: str):
            raise InputError(f"measurement kind {k.name!r}: {rule}")

        if k.name in out:
            refuse("the name is registered twice")
        if not 1 <= k.dim <= sm.MAX_RESIDUAL_DIM:
            refuse(f"residual dimension {k.dim}; expected 1 .. {sm.MAX_RESIDUAL_DIM}")
        if k.model is not None and k.model.dim != k.dim:
            refuse(f"its model {k.model.name!r} has dimension {k.model.dim}, the kind {k.dim}")
        if not 1 <= k.width <= sm.MAX_ROW_WIDTH:
            refuse(f"row width {k.width}; expected 1 .. {sm.MAX_ROW_WIDTH}")
        expected = (*k.times, *k.fields, "cov", "T_BS")
        found = tuple(f.name for f in dataclass_fields(k.data_type))
        if found != expected:
            refuse(f"{k.data_type.__name__} has the fields {found}; the kind declares {expected}")
        kind_sigmas(f"measurement kind {k.name!r}: default_sigma", k.default_sigma, k.dim)
        if len(k.sigma_units) != k.dim or not set(k.sigma_units) <= set(SIGMA_RANGES):
            refuse(f"sigma_units {k.sigma_units!r}; expected one of {', '.join(SIGMA_RANGES)} per residual axis")
        if k.relative != (k.compose is not None):
            refuse("a relative kind composes its consecutive measurements (compose), a one-state kind does not")
        scaled_rows = sm.ODOMETRY_SCALED if k.relative else k.model.scaled
        if (k.scaled_field is None) != (scaled_rows == 0):
            refuse(f"scaled_field {k.scaled_field!r}, and its model has {scaled_rows} scaled rows")
        axes = sorted(a for _, group, _ in k.axis_groups for a in group)
        names = [name for name, _, _ in k.axis_groups]
        if (axes != list(range(k.dim)) or len(set(names)) != len(names)
                or (k.noise_groups and not all(unit for _, _, unit in k.axis_groups))):
            refuse(f"noise_groups {k.noise_groups}: expected distinct names whose axes partition 0 .. {k.dim - 1}, "
                   "each group's axes in one unit")
        _, row = k.random_row(np.random.default_rng(0))
        if np.shape(row) != (k.width,):
            refuse(f"random_row gives a row of shape {np.shape(row)}; expected ({k.width},)")
        out[k.name] = k
    return out


#: The registry: every kind, by name. Adding a kind is a module of its own and a line here.
KINDS: dict[str, Kind] = registered(
    pose.KIND, position.POSITION, position.GNSS, orientation.KIND, roll_pitch.KIND, velocity.KIND, odometry.KIND,
    altitude.KIND, magnetometer.KIND,
)

#: The kinds of aiding sensor, by the name a rig file's ``kind`` and the command line use.
KIND_NAMES = tuple(KINDS)

#: The distinct one-state models, in the order :func:`measure_into` indexes them.
MODELS: tuple[sm.SensorModel, ...] = tuple(dict.fromkeys(k.model for k in KINDS.values() if k.model is not None))
_KERNELS = tuple(m.kernel for m in MODELS)


def drift_problem(kind: str) -> str | None:
    """Why a sensor of ``kind`` (a name of :data:`KINDS`) cannot have errors correlated in time
    (a ``correlation_time``, :mod:`smoother.model.correlated`), or None where it can: the model
    chains one-state measurements' residuals."""
    if KINDS[kind].relative:
        return (f"{kind} measurements are relative (two states each); errors correlated in time are modelled for "
                "kinds of one state per measurement")
    return None


def model_index(kind: Kind) -> int:
    """The index of ``kind``'s model in :data:`MODELS` (the first argument of :func:`measure_into`)."""
    return MODELS.index(kind.model)


@njit(cache=True)
def measure_into(model, r, v, C, b_f, b_w, row, e, H) -> None:
    """Run the kernel of ``MODELS[model]`` (signature of :mod:`factors.sensor_models`)."""
    i = 0
    for kernel in literal_unroll(_KERNELS):
        if i == model:
            kernel(r, v, C, b_f, b_w, row, e, H)
        i += 1


@njit(cache=True)
def _measure_rows(model, r, v, C, b_f, b_w, rows, e, H) -> None:
    for n in range(rows.shape[0]):
        measure_into(model, r[n], v[n], C[n], b_f[n], b_w[n], rows[n], e[n], H[n])


@contextmanager
def quiet_dispatch():
    """Silences Numba's note, shown when :func:`measure_into` compiles, that dispatching over a
    tuple of kernels is an experimental feature."""
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", NumbaExperimentalFeatureWarning)
        yield


def measure_rows(kind: Kind, states, rows: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``(e (N, d), H (N, d, 15))`` of ``kind``'s measurement ``rows`` at ``states`` (an
    :class:`factors.imu.ImuState` with leading dimension N)."""
    n = len(rows)
    e, H = np.empty((n, kind.dim)), np.empty((n, kind.dim, 15))
    parts = [np.ascontiguousarray(a, dtype=float) for a in (states.r, states.v, states.C, states.b_f, states.b_w)]
    with quiet_dispatch():
        _measure_rows(model_index(kind), *parts, np.ascontiguousarray(rows, dtype=float), e, H)
    return e, H


def evaluate(kind: Kind, state, row: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``(e, H)`` of one measurement ``row`` of ``kind`` at ``state`` (for a relative kind the
    pair ``(x_i, x_j)``, ``H`` over both error states side by side)."""
    if kind.relative:
        return sm.evaluate_pair(*state, row)
    return sm.evaluate_one(kind.model, state, row)


#: Each one-state model's calibration layout (:func:`factors.calibration.layout`), by its index
#: in :data:`MODELS`.
LAYOUTS = np.stack([calibration.layout(m) for m in MODELS])


@njit(cache=True)
def calibrated_into(model, lay, r, v, C, b_f, b_w, row, cal, with_time, acc, gyro, g, e, H, Hc, work,
                    jacobians) -> None:
    """``e (d)``, ``H (d, 15)``, ``H_c (d, 8)`` of one measurement ``row`` of ``MODELS[model]``
    (its layout ``lay``, :data:`LAYOUTS`) at one state through the packed calibration ``cal``
    (:func:`factors.calibration.packed`): the model's kernel at the state one Euler step of the
    time offset away (with the IMU reading ``acc, gyro`` held at the stamp, where
    ``with_time``), with the calibrated extrinsic in its row
    (:func:`factors.calibration.one_state_into`); ``e`` alone (``H``, ``H_c`` untouched)
    without ``jacobians``; ``work`` from :func:`factors.calibration.work_array`."""
    d = e.shape[0]
    xr, xv, xC, F, rate = calibration.state_part(work, 0)
    calibrated, e0, H0, step = calibration.model_part(work, row.shape[0], d, imu.STATE_DIM)
    if with_time:
        imu.stepped_into(r, v, C, b_f, b_w, acc, gyro, cal[0], g, xr, xv, xC, F, rate, step, jacobians)
    else:
        xr[:], xv[:], xC[:, :] = r, v, C
    calibration.calibrated_row_into(row, lay[0], lay[1], cal, calibrated)
    measure_into(model, xr, xv, xC, b_f, b_w, calibrated, e0, H0)
    if jacobians:
        calibration.one_state_into(lay, xv, xC, b_w, calibrated, e0, H0, F, rate, with_time, cal[13], e, H, Hc)
    else:
        calibration.scaled_error_into(e0, calibrated, lay[2], cal[13], e)


@njit(cache=True)
def _calibrated_rows(model, lay, r, v, C, b_f, b_w, rows, cal, with_time, acc, gyro, g, e, H, Hc, jacobians) -> None:
    work = calibration.work_array()
    for n in range(rows.shape[0]):
        j = n if jacobians else 0
        calibrated_into(model, lay, r[n], v[n], C[n], b_f[n], b_w[n], rows[n], cal, with_time, acc[n], gyro[n], g,
                        e[n], H[j], Hc[j], work, jacobians)


def calibrated_rows(kind: Kind, states, rows: np.ndarray, c, imu_at=None, gravity=imu.DEFAULT_GRAVITY,
                    jacobians: bool = True):
    """``(e, H, H_c)`` of ``kind``'s measurement ``rows`` through the calibration ``c``
    (:class:`factors.calibration.Calibration`; :func:`calibrated_into`,
    :func:`factors.calibration.calibrated_odometry_into`): ``states`` one
    :class:`factors.imu.ImuState` with leading dimension N, for a relative kind the pair
    ``(states_i, states_j)`` (``H`` over both error states side by side, ``imu_at`` a pair of
    ``(acc, gyro)``); ``imu_at`` None when the time offset is not estimated. Without
    ``jacobians``: ``(e, None, None)`` (what a cost needs, at a fraction of the work)."""
    rows = np.ascontiguousarray(rows, dtype=float)
    if kind.relative:
        return calibration.calibrated_odometry_residual(*states, rows, c, imu_at, gravity, jacobians)
    n, i = len(rows), model_index(kind)
    with_time, at = calibration.readings(imu_at, n)
    e, H, Hc = calibration.residual_arrays(n, kind.dim, imu.STATE_DIM, jacobians)
    with quiet_dispatch():
        _calibrated_rows(i, LAYOUTS[i], *calibration.state_rows(states, n), rows, calibration.packed(c), with_time,
                         *at, np.asarray(gravity, dtype=float), e, H, Hc, jacobians)
    return (e, H, Hc) if jacobians else (e, None, None)


#: Length of the flat part of :func:`attached_work` and :func:`attached_noise_work`: the predicted
#: state ``(r, v, C)``, its Jacobian (or, for :func:`attached_noise_into`, its covariance), the
#: model's Jacobian and residual at it.
_ATTACHED_FLAT = 3 + 3 + 9 + imu.STATE_DIM * imu.STATE_DIM + sm.MAX_RESIDUAL_DIM * imu.STATE_DIM + sm.MAX_RESIDUAL_DIM


@njit(cache=True)
def attached_work() -> tuple:
    """Work arrays of :func:`attached_into`; allocate once per loop over measurements."""
    return imu.partial_work(), calibration.work_array(), np.empty(_ATTACHED_FLAT)


@njit(cache=True)
def attached_into(model, lay, acc, gyro, dt, n, last_dt, r, v, C, b_f, b_w, row, cal, calibrated, with_time, hacc,
                  hgyro, g, e, H, Hc, work, jacobians, resume=False) -> None:
    """``e (d)``, ``H (d, 15)`` (and ``H_c (d, 8)`` where ``calibrated``) of one measurement
    ``row`` of ``MODELS[model]`` ATTACHED to the keyframe state ``x = (r, v, C, b_f, b_w)``: taken
    after the keyframe, at the end of the first ``n`` steps of the keyframe's interval
    ``acc, gyro (K, 3)``, ``dt (K,)``, the last of them cut to ``last_dt``. Its state is the
    primer's Euler steps from ``x``, ``x_m = f(x)``, and its Jacobian ``F_m = dx_m/dx`` the
    product of the steps' transitions
    (:func:`factors.imu.partial_prediction_into`); the measurement is the model's
    (:func:`measure_into`), or through its calibration ``cal`` (:func:`calibrated_into`: the
    time offset one more Euler step from ``x_m`` with the IMU reading ``hacc, hgyro`` held at its
    stamp), at ``x_m``, so that by the chain rule

        e(x, c) = e_m(f(x), c),    H = H_m F_m,    H_c = H_c,m

    ``e`` alone (``H``, ``H_c`` untouched) without ``jacobians``; ``work`` from
    :func:`attached_work`, ``resume`` as :func:`factors.imu.partial_prediction_into`'s (the
    call before on ``work`` a measurement of the same interval and keyframe, at most as late). The
    measurement's noise is that of the model at ``x_m``; the process noise between the keyframe
    and the measurement is the caller's (the measurement's covariance,
    :func:`smoother.model.problem.attached_covariance`)."""
    pw, cwork, flat = work
    d = e.shape[0]
    xr, xv, xC = flat[0:3], flat[3:6], flat[6:15].reshape((3, 3))
    J = flat[15:15 + imu.STATE_DIM * imu.STATE_DIM].reshape((imu.STATE_DIM, imu.STATE_DIM))
    o = 15 + imu.STATE_DIM * imu.STATE_DIM
    Hm = flat[o:o + d * imu.STATE_DIM].reshape((d, imu.STATE_DIM))
    imu.partial_prediction_into(acc, gyro, dt, n, last_dt, r, v, C, b_f, b_w, g, xr, xv, xC, J, pw, jacobians,
                                resume)
    if calibrated:
        calibrated_into(model, lay, xr, xv, xC, b_f, b_w, row, cal, with_time, hacc, hgyro, g, e, Hm, Hc, cwork,
                        jacobians)
    else:
        measure_into(model, xr, xv, xC, b_f, b_w, row, e, Hm)
    if jacobians:
        matmul_into(Hm, J, H)


@njit(cache=True)
def _continues(interval, n, r, v, C, b_f, b_w, m) -> bool:
    """Whether measurement ``m`` can continue the steps taken for measurement ``m - 1``: the same
    interval from the same keyframe state, and at least as many steps."""
    if m == 0 or interval[m] != interval[m - 1] or n[m] < n[m - 1]:
        return False
    for a in range(3):
        if r[m, a] != r[m - 1, a] or v[m, a] != v[m - 1, a] or b_f[m, a] != b_f[m - 1, a] or b_w[m, a] != b_w[m - 1, a]:
            return False
        for b in range(3):
            if C[m, a, b] != C[m - 1, a, b]:
                return False
    return True


@njit(cache=True)
def _attached_rows(model, lay, r, v, C, b_f, b_w, acc, gyro, dt, interval, n, last_dt, rows, cal, calibrated,
                   with_time, hacc, hgyro, g, e, H, Hc, jacobians) -> None:
    work = attached_work()
    for m in range(rows.shape[0]):
        j = m if jacobians else 0
        k = interval[m]
        resume = _continues(interval, n, r, v, C, b_f, b_w, m)
        attached_into(model, lay, acc[k], gyro[k], dt[k], n[m], last_dt[m], r[m], v[m], C[m], b_f[m], b_w[m], rows[m],
                      cal, calibrated, with_time, hacc[m], hgyro[m], g, e[m], H[j], Hc[j], work, jacobians, resume)


def attached_rows(kind: Kind, states, samples: tuple, interval, steps, last_dt, rows: np.ndarray, c=None,
                  imu_at=None, gravity=imu.DEFAULT_GRAVITY, jacobians: bool = True):
    """``(e, H, H_c)`` of ``kind``'s (one-state) measurement ``rows`` attached to the keyframe
    states ``states`` (leading dimension N; :func:`attached_into`): measurement ``m`` at the end of
    the first ``steps[m]`` steps of interval ``interval[m]`` of the padded ``samples = (acc, gyro
    (J, K, 3), dt (J, K))`` (an IMU factor's :attr:`factors.preintegration.Preintegrated.samples`),
    the last cut to ``last_dt[m]``; through the calibration ``c``
    (:class:`factors.calibration.Calibration`; None: the model's own, ``H_c`` None), ``imu_at``
    the IMU readings ``(acc, gyro)`` held at the stamps where the time offset is estimated. Without
    ``jacobians``: ``(e, None, None)``."""
    if kind.relative:
        raise InputError(f"kind {kind.name!r}: a relative measurement is not attached; its times are keyframes")
    rows = np.ascontiguousarray(rows, dtype=float)
    n, i = len(rows), model_index(kind)
    with_time, at = calibration.readings(imu_at, n)
    e, H, Hc = calibration.residual_arrays(n, kind.dim, imu.STATE_DIM, jacobians)
    cal = calibration.packed(calibration.Calibration.of() if c is None else c)
    acc, gyro, dt = (np.ascontiguousarray(a, dtype=float) for a in samples)
    with quiet_dispatch():
        _attached_rows(i, LAYOUTS[i], *calibration.state_rows(states, n), acc, gyro, dt,
                       np.ascontiguousarray(interval, dtype=np.int64), np.ascontiguousarray(steps, dtype=np.int64),
                       np.ascontiguousarray(last_dt, dtype=float), rows, cal, c is not None, with_time, *at,
                       np.asarray(gravity, dtype=float), e, H, Hc, jacobians)
    if not jacobians:
        return e, None, None
    return e, H, (Hc if c is not None else None)


def _calibration_check(kind: Kind):
    """The self-check of ``kind``'s calibrated residual: its Jacobians with respect to the state(s)
    and to every calibration part, at a random row, a random calibration (rotation of any regime,
    lever arm ~1 m, time offset of either sign, scale ~1) and a random IMU reading, against
    central differences."""
    def draw(rng):
        state, row = kind.random_row(rng)
        states = state if kind.relative else (state,)
        c = calibration.Calibration(float(rng.choice([-1, 1]) * rng.uniform(1e-3, 0.3)), random_rotation(rng),
                                    rng.normal(size=3), float(1 + 0.05 * rng.normal()))
        readings = [(rng.normal(size=(1, 3)) * 3, rng.normal(size=(1, 3)) * 3) for _ in states]
        at = tuple(readings) if kind.relative else readings[0]

        def e_of(*args):
            lead = tuple(s[None] for s in args[:-1])
            return calibrated_rows(kind, lead if kind.relative else lead[0], row[None], args[-1], at)[0][0]

        _, H, H_c = calibrated_rows(kind, tuple(s[None] for s in states) if kind.relative else state[None],
                                    row[None], c, at)
        numerical = jacobians.numerical_jacobian(
            e_of, *states, c, arg_kinds=[imu.StateManifold] * len(states) + [calibration.CalibrationManifold],
            value_kind="vector")
        return np.hstack([H[0], H_c[0]]), np.hstack(numerical)

    return draw


@njit(cache=True)
def attached_noise_work() -> tuple:
    """Work arrays of :func:`attached_noise_into`; allocate once per loop over measurements."""
    return imu.partial_covariance_work(), np.empty(_ATTACHED_FLAT)


@njit(cache=True)
def attached_noise_into(model, acc, gyro, dt, n, last_dt, r, v, C, b_f, b_w, row, g, q, out, work,
                        resume=False) -> None:
    """``out (d, d) = H S_w H^T``: the share of the process noise between a keyframe ``x = (r, v,
    C, b_f, b_w)`` and a measurement ``row`` of ``MODELS[model]`` attached to it (at the end of
    the first ``n`` steps of the keyframe's interval ``acc, gyro, dt``, the last cut to
    ``last_dt``; :func:`attached_into`) in the measurement's error given the keyframe: ``S_w``
    the covariance of the predicted state ``x_m`` given ``x``, the EKF's growth ``F S F^T + G Q_d
    G^T`` from zero along the same steps (:func:`factors.imu.partial_covariance_into`, noise
    densities ``q``), and ``H`` the model's Jacobian at ``x_m``. ``work`` from
    :func:`attached_noise_work`, ``resume`` as :func:`attached_into`'s."""
    cw, flat = work
    d = out.shape[0]
    D2 = imu.STATE_DIM * imu.STATE_DIM
    xr, xv, xC = flat[0:3], flat[3:6], flat[6:15].reshape((3, 3))
    S = flat[15:15 + D2].reshape((imu.STATE_DIM, imu.STATE_DIM))
    o = 15 + D2
    Hm = flat[o:o + d * imu.STATE_DIM].reshape((d, imu.STATE_DIM))
    e = flat[o + sm.MAX_RESIDUAL_DIM * imu.STATE_DIM:o + sm.MAX_RESIDUAL_DIM * imu.STATE_DIM + d]
    imu.partial_covariance_into(acc, gyro, dt, n, last_dt, r, v, C, b_f, b_w, g, q, xr, xv, xC, S, cw, resume)
    measure_into(model, xr, xv, xC, b_f, b_w, row, e, Hm)
    for a in range(d):
        for b in range(d):
            total = 0.0
            for p in range(imu.STATE_DIM):
                hs = 0.0
                for q_ in range(imu.STATE_DIM):
                    hs += S[p, q_] * Hm[b, q_]
                total += Hm[a, p] * hs
            out[a, b] = total


@njit(cache=True)
def _attached_noise_rows(model, r, v, C, b_f, b_w, acc, gyro, dt, interval, n, last_dt, rows, g, q, out) -> None:
    work = attached_noise_work()
    for m in range(rows.shape[0]):
        k = interval[m]
        attached_noise_into(model, acc[k], gyro[k], dt[k], n[m], last_dt[m], r[m], v[m], C[m], b_f[m], b_w[m], rows[m],
                            g, q, out[m], work, _continues(interval, n, r, v, C, b_f, b_w, m))


def attached_noise(kind: Kind, states, samples: tuple, interval, steps, last_dt, rows: np.ndarray,
                   noise: imu.ImuNoise, gravity=imu.DEFAULT_GRAVITY) -> np.ndarray:
    """``(N, d, d)``: :func:`attached_noise_into` of ``kind``'s measurement ``rows`` attached to
    the keyframe states ``states`` (leading dimension N), placed as in :func:`attached_rows`."""
    rows = np.ascontiguousarray(rows, dtype=float)
    n = len(rows)
    out = np.empty((n, kind.dim, kind.dim))
    acc, gyro, dt = (np.ascontiguousarray(a, dtype=float) for a in samples)
    with quiet_dispatch():
        _attached_noise_rows(model_index(kind), *calibration.state_rows(states, n), acc, gyro, dt,
                             np.ascontiguousarray(interval, dtype=np.int64),
                             np.ascontiguousarray(steps, dtype=np.int64),
                             np.ascontiguousarray(last_dt, dtype=float), rows, np.asarray(gravity, dtype=float),
                             noise.densities(), out)
    return out


def _attached_check(kind: Kind, calibrated: bool):
    """The self-check of ``kind``'s measurement attached to the keyframe before it
    (:func:`attached_rows`): its Jacobian with respect to the keyframe's state (and, where
    ``calibrated``, to every calibration part, as :func:`_calibration_check` draws them) at a
    random row, after 1-5 steps of 2-5 ms of a random interval (rates of a few rad/s, the last step
    cut anywhere), against central differences."""
    def draw(rng):
        state, row = kind.random_row(rng)
        K = int(rng.integers(1, 6))
        n = int(rng.integers(1, K + 1))
        samples = (rng.normal(size=(1, K, 3)) * 3, rng.normal(size=(1, K, 3)) * 3,
                   np.full((1, K), rng.uniform(2e-3, 5e-3)))
        where = ([0], [n], [rng.uniform(1e-3, 1.0) * samples[2][0, n - 1]])
        c, at = None, None
        if calibrated:
            c = calibration.Calibration(float(rng.choice([-1, 1]) * rng.uniform(1e-3, 0.3)), random_rotation(rng),
                                        rng.normal(size=3), float(1 + 0.05 * rng.normal()))
            at = (rng.normal(size=(1, 3)) * 3, rng.normal(size=(1, 3)) * 3)

        def e_of(x, *cal):
            return attached_rows(kind, x[None], samples, *where, row[None], cal[0] if cal else None, at)[0][0]

        _, H, H_c = attached_rows(kind, state[None], samples, *where, row[None], c, at)
        numerical = jacobians.numerical_jacobian(
            e_of, state, *([c] if calibrated else []),
            arg_kinds=[imu.StateManifold] + ([calibration.CalibrationManifold] if calibrated else []),
            value_kind="vector")
        return (np.hstack([H[0], H_c[0]]) if calibrated else H[0]), np.hstack(numerical)

    return draw


def _model_check(kind: Kind):
    """The self-check of ``kind``'s model: its analytic error-state Jacobian at a random row
    (:attr:`Kind.random_row`) against central differences of its residual (boxplus on the state)."""
    def draw(rng):
        state, row = kind.random_row(rng)
        states = state if kind.relative else (state,)
        _, H = evaluate(kind, state, row)
        numerical = jacobians.numerical_jacobian(
            lambda *s: evaluate(kind, s if kind.relative else s[0], row)[0], *states,
            arg_kinds=[imu.StateManifold] * len(states), value_kind="vector")
        return H, np.hstack(numerical)

    return draw


for _kind in KINDS.values():
    selfcheck.register(f"{_kind.name} measurement: H of its residual, extrinsic T_BS", _model_check(_kind))
    selfcheck.register(f"{_kind.name} measurement through its calibration: H and H_c (time offset, rotation, "
                       "lever arm, scale)", _calibration_check(_kind))
    if not _kind.relative:
        selfcheck.register(f"{_kind.name} measurement attached to the keyframe before it: H through the Euler "
                           "steps to its time", _attached_check(_kind, False))
        selfcheck.register(f"{_kind.name} measurement attached, through its calibration: H and H_c",
                           _attached_check(_kind, True))


def sensors_of(dataset: Dataset) -> list[Sensor]:
    """The aiding sensors of ``dataset`` (those with measurements to use; a sensor whose every
    measurement is held out only scores), each one's kind checked against :data:`KINDS`, its
    measurements against the kind's data type and a ``correlation_time`` against the kind
    (:func:`drift_problem`)."""
    for s in dataset.sensors:
        if s.kind not in KINDS:
            raise InputError(f"sensor {s.name!r}: unknown kind {s.kind!r}; expected one of {', '.join(KINDS)}")
        problem = drift_problem(s.kind) if s.correlation_time is not None or s.fit_correlation_time else None
        if problem is not None:
            raise InputError(f"sensor {s.name!r}: correlation_time: {problem}")
        expected = KINDS[s.kind].data_type
        for part in (s.data, s.heldout):
            if part is not None and not isinstance(part, expected):
                raise InputError(f"sensor {s.name!r} of kind {s.kind!r}: expected {expected.__name__}, "
                                 f"got {type(part).__name__}")
    return [s for s in dataset.sensors if s.data is not None]
