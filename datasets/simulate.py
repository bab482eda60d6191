"""Synthetic datasets: an analytic motion, the IMU it would measure, and noisy measurements.

``simulate(profile=..., duration=..., seed=...)`` returns a :class:`SimulatedDataset` (a
:class:`datasets.types.Dataset` with a few extra fields). The construction, step by step:

Time. IMU samples at ``t_k = t0 + k / imu_rate``, ``k = 0 .. N-1``, ``N = floor(duration *
imu_rate) + 1`` (so ``duration * imu_rate`` steps; the last sample would drive the step after the
data and is only there to end the record). Sample ``k`` drives the Euler step over ``[t_k,
t_{k+1}]``. A measurement stream at ``rate`` takes every ``imu_rate / rate``-th sample starting
with ``k = 0``; ``imu_rate`` must be an integer multiple of ``rate``, so measurement times are IMU
times exactly (the same floats).

Clean IMU. ``clean_imu="analytic"``: the profile (:mod:`datasets.trajectories`) is
evaluated at the sample times, ``f_k = C(t_k)^T (a(t_k) - g)`` (eq. 42) and ``w_k = omega_B(t_k)``.
``clean_imu="matched"`` (default, so the discrete truth follows the profile instead of drifting
metres away from it over a minute): the samples that make the Euler-forward model pass exactly
through the profile's positions and attitudes at every sample time (``w_k = log(C_k^T C_{k+1}) / dt``,
``v_k = C_k^T (r_{k+1} - r_k) / dt``, ``f_k`` from eq. 55); they differ from the analytic ones by
O(dt).

Biases. ``b_0 ~ N(0, initial_bias_sigma^2)`` per axis (accelerometer, gyro), then the
discretisation of VI.B: ``b_{k+1} = b_k + dt n_b`` with ``n_b ~ N(0, R_b / dt)``, i.e. independent
increments of variance ``R_b dt`` (``R_b = noise.acc_bias^2`` or ``noise.gyro_bias^2``,
``dt = 1 / imu_rate``).

Measured IMU. ``f~_k = f_k + b_f,k + n_f,k`` and ``w~_k = w_k + b_w,k + n_w,k`` with
``n ~ N(0, R / dt)`` per sample and axis (``R = noise.acc^2``, ``noise.gyro^2``).

Truth. ``truth="continuous"``: the profile at ``t_k`` (``r``, ``v_B = C^T dr/dt``, ``C``) with the
bias sequence ``b_k``. ``truth="discrete"`` (default): the primer's Euler-forward model
(:func:`factors.imu.propagate`, eqs. 54-60) run on the CLEAN signals ``f_k, w_k`` with zero biases
from the profile's state at ``t0``, with ``dt_k = t_{k+1} - t_k``; then the bias sequence is
attached (with ``clean_imu="matched"`` the start velocity is the matched ``v_0``). If
``noise.velocity > 0`` the position also takes the model's velocity noise,
``r_{k+1} = r_k + dt C_k (v_k + n_v,k)``, ``n_v ~ N(0, R_v / dt)`` (the continuous truth has no such
term: there ``noise.velocity`` is only a tuning term of the estimator). Since ``f~ - b - n = f``,
an EKF that runs :func:`factors.imu.propagate` on the measured IMU is then exactly consistent with
this truth: no discretisation error enters the comparison. With the analytic clean IMU the Euler
model drifts from the analytic motion by O(dt) per unit time, and the drift adds up: over 60 s at
200 Hz the discrete truth ends 5.8 m (gentle) and 300 m (tumbling: a 0.02 rad attitude error lets
gravity leak in) away from the profile. ``clean_imu="matched"`` removes that drift (positions and
attitudes on the profile to round-off, body velocity within O(dt)) while keeping the exact
consistency. The continuous truth is the one to use for questions about the discretisation itself.

The discrete truth is computed without a per-sample Python loop: the attitude is a cumulative
product of ``exp(dt_k w_k)`` and the body velocity an affine recursion ``v_{k+1} = (I - dt_k
w_k^x) v_k + dt_k (C_k^T g + f_k)``; both are prefix products of small matrices (3x3, and 4x4 in
homogeneous form), evaluated by recursive doubling in ``log2 N`` batched matrix products. It
equals :func:`factors.imu.integrate` to round-off (tested); it is about 100x faster.

Measurements, all from the truth (whichever was chosen): named sensors of any kind of the
registry (:data:`datasets.kinds.KINDS`), each drawn by its kind's own simulator
(:attr:`datasets.kinds.base.Kind.simulate`, through :func:`datasets.simulated_sensors.sensors_from_truth`)
at truth samples, with a noise stream of its own derived from its name. ``<kind>_rate=`` [Hz] (and
``<kind>_sigma=``, else the kind's ``default_sigma``) adds a sensor of that kind at the IMU, named
after its kind; ``sensors=`` adds sensors mounted anywhere (:class:`~datasets.simulated_sensors.SensorSpec`).
By default a ``pose`` sensor at 10 Hz. The kinds' simulators, in the primer's convention: a position
``r~ = r + C p_BS + n``; an attitude ``C~ = exp(n) C R_BS`` (world-frame noise, eqs. 61-63); a
relative pose between consecutive times ``i -> j`` of its stream in frame ``i``; their covariances
those of the noise drawn.

Outliers: ``round(outlier_fraction * N)`` of the ``N`` measurements of each sensor whose kind can be
corrupted (:attr:`~datasets.kinds.base.Kind.corrupt`: positions moved by ``outlier_scale[0]``
metres, attitudes turned by ``outlier_scale[1]`` radians, in uniformly random directions), chosen
uniformly without replacement; their indices are ``SimulatedDataset.outliers[name]``. Their
``cov`` still states the nominal noise: that is what makes them outliers.

Initial estimate. ``Dataset.initial_cov = diag(s_r^2 I, s_v^2 I, s_phi^2 I, s_bf^2 I, s_bw^2 I)``
(error-state order of :mod:`factors.imu`) with ``(s_r, s_v, s_phi) = initial_sigma`` and
``(s_bf, s_bw) = initial_bias_sigma``. ``Dataset.initial`` is the true state at ``t0`` with
``r + d_r``, ``v + d_v``, ``exp(d_phi) C`` and biases 0, where ``d ~ N(0, diag(s_r^2, s_v^2,
s_phi^2))``. Because the true ``b_0`` was drawn from ``N(0, s_b^2)`` and the estimate is 0, the
error ``initial [-] truth_0 = (d_r, d_v, d_phi, -b_f0, -b_w0)`` is exactly one draw from
``N(0, initial_cov)``, so NEES tests on it are meaningful. A sigma of 0 means "known exactly": the
state is not perturbed and its variance is floored at ``MIN_SIGMA^2`` so that the covariance stays
positive definite, as :class:`~datasets.types.Dataset` requires.

Randomness. ``np.random.SeedSequence(seed).spawn`` gives one independent generator per role
(:data:`STREAMS`), always all of them and in a fixed order, and each sensor's noise stream is
derived from its name, so switching a sensor on or off, or changing its rate, changes nothing
else; the same seed gives the same dataset.
"""
from __future__ import annotations

from dataclasses import dataclass, field, replace

import numpy as np

from datasets.kinds import KINDS, kind_sigmas
from datasets.simulated_sensors import SensorSpec, sensors_from_truth
from datasets.trajectories import PROFILES, Profile
from datasets.types import Dataset, ImuSamples, Sensor, Trajectory
from factors import so3
from factors.errors import InputError
from factors.imu import DEFAULT_GRAVITY, ImuNoise, ImuState, integrate

__all__ = ["PROFILES", "Profile", "SimulatedDataset", "simulate", "euler_truth", "STREAMS", "TRUTH_MODELS",
           "CLEAN_IMU_MODELS"]

#: The independent random streams, in spawn order (never reorder: it would change every dataset).
STREAMS = ("imu", "bias", "initial", "velocity", "outliers", "sensors")

#: The sensors simulated unless ``<kind>_rate=`` options say otherwise (a pose sensor at 10 Hz).
DEFAULT_RATES = {"pose_rate": 10.0}
#: The names of those sensors (each named after its kind).
DEFAULT_SENSOR_NAMES = tuple(option.removesuffix("_rate") for option in DEFAULT_RATES)

TRUTH_MODELS = ("discrete", "continuous")

CLEAN_IMU_MODELS = ("analytic", "matched")

#: Floor of the initial-covariance sigmas (a state given a sigma of 0 is known exactly).
MIN_SIGMA = 1e-6

#: Tolerance on "integer multiple" and "whole number of steps" (relative).
_RATE_TOLERANCE = 1e-9


@dataclass(frozen=True)
class SimulatedDataset(Dataset):
    """A :class:`~datasets.types.Dataset` with what only a simulator knows.

    ``clean_imu``: the noise- and bias-free IMU signals at the same times; ``outliers``: per
    sensor name, the indices (into its measurements) of those given a gross error; ``profile``,
    ``truth_model``, ``seed``: how it was made."""

    clean_imu: ImuSamples | None = None
    outliers: dict = field(default_factory=dict)
    profile: str = ""
    truth_model: str = ""
    seed: int | None = None


# --------------------------------------------------------------------------------------------
# option checking


def _sigmas(name: str, value, count: int) -> np.ndarray:
    """``value`` as ``count`` finite sigmas >= 0 (a scalar is accepted when ``count == 1``)."""
    a = np.atleast_1d(np.asarray(value, dtype=float))
    if a.shape != (count,) or not np.all(np.isfinite(a)) or np.any(a < 0):
        what = "a sigma" if count == 1 else f"{count} sigmas"
        raise InputError(f"{name}: expected {what}, finite and >= 0, got {value!r}")
    return a


def _stride(name: str, rate, imu_rate: float) -> int | None:
    """Every how many IMU samples a stream at ``rate`` is measured; None if it is off."""
    if rate is None or rate == 0:
        return None
    rate = float(rate)
    if not np.isfinite(rate) or rate < 0:
        raise InputError(f"{name}: expected a rate in Hz > 0 (or None/0 for none), got {rate!r}")
    ratio = imu_rate / rate
    stride = int(round(ratio))
    if stride < 1 or abs(ratio - stride) > _RATE_TOLERANCE * ratio:
        raise InputError(
            f"{name}: imu_rate ({imu_rate:g} Hz) must be an integer multiple of {name} ({rate:g} Hz) "
            "so that measurement times are IMU sample times"
        )
    return stride


def _profile(profile) -> Profile:
    if isinstance(profile, Profile):
        return profile
    if profile not in PROFILES:
        raise InputError(f"profile: unknown {profile!r}; choose one of {sorted(PROFILES)} or pass a Profile")
    return PROFILES[profile]


# --------------------------------------------------------------------------------------------
# the discrete truth


def euler_truth(initial: ImuState, acc, gyro, t, gravity=DEFAULT_GRAVITY, velocity_noise=None) -> ImuState:
    """The states of :func:`factors.imu.integrate` (``initial``'s biases are ignored: zero biases)
    on samples ``acc[k], gyro[k]`` over steps ``dt_k = t[k+1] - t[k]``. ``velocity_noise``
    (``len(t) - 1``, 3), if given, is the model's ``n_v`` of each step, which moves only the
    position: ``r_{k+1} = r_k + dt_k C_k (v_k + n_v)``. Returns ``len(t)`` states with zero biases."""
    t = np.asarray(t, dtype=float)
    dt = np.diff(t)
    zero = np.zeros(3)
    states = integrate(initial.replace(b_f=zero, b_w=zero), acc, gyro, dt, gravity)
    if velocity_noise is None:
        return states
    extra = np.cumsum(dt[:, None] * np.einsum("kij,kj->ki", states.C[:-1], velocity_noise), axis=0)
    r = states.r.copy()
    r[1:] += extra
    return states.replace(r=r)


def _matched_signals(profile: Profile, t: np.ndarray, gravity: np.ndarray):
    """The IMU samples whose Euler-forward propagation passes through the profile's positions and
    attitudes at every sample time (``clean_imu="matched"``). ``t`` has two times more than the
    samples wanted. Returns ``(kinematics at the samples, f, w, v_0)``.

    With ``v_k = C_k^T (r_{k+1} - r_k) / dt_k`` (then eq. 54 gives ``r_{k+1}`` exactly),
    ``w_k = log(C_k^T C_{k+1}) / dt_k`` (eq. 56 gives ``C_{k+1}``) and
    ``f_k = (v_{k+1} - v_k) / dt_k - C_k^T g + w_k x v_k`` (eq. 55 gives ``v_{k+1}``)."""
    kin = profile.evaluate(t)
    dt = np.diff(t)[:, None]
    C, C_T = kin.C, so3.inverse(kin.C)
    v = np.einsum("kij,kj->ki", C_T[:-1], np.diff(kin.r, axis=0)) / dt
    w = so3.log(C_T[:-1] @ C[1:]) / dt
    f = np.diff(v, axis=0) / dt[:-1] - np.einsum("kji,j->ki", C[:-2], gravity) + np.cross(w[:-1], v[:-1])
    n = len(t) - 2
    return kin[:n], f, w[:n], v[0]


# --------------------------------------------------------------------------------------------
# the simulator


def _sensors_at_imu(rates: dict, imu_rate: float) -> list[SensorSpec]:
    """The sensors the ``<kind>_rate`` / ``<kind>_sigma`` options ask for (module docstring)."""
    known = {f"{k}_{what}" for k in KINDS for what in ("rate", "sigma")}
    for option in rates:
        if option not in known:
            raise InputError(f"simulate: unknown option {option!r}; sensors at the IMU are asked for with "
                             f"<kind>_rate and <kind>_sigma, kind one of {', '.join(KINDS)}")
    specs = []
    for name, kind in KINDS.items():
        rate = rates.get(f"{name}_rate")
        if _stride(f"{name}_rate", rate, imu_rate) is None:
            continue
        sigma = kind_sigmas(f"{name}_sigma", rates.get(f"{name}_sigma", kind.default_sigma), kind.dim)
        specs.append(SensorSpec(name, name, float(rate), sigma))
    return specs


def _with_outliers(sensors, fraction: float, scale: np.ndarray, rng) -> tuple[tuple[Sensor, ...], dict]:
    """``sensors`` with ``round(fraction * N)`` of each corruptible one's ``N`` measurements made
    outliers (module docstring), and their indices per sensor name."""
    out, index = [], {}
    for s in sensors:
        corrupt = KINDS[s.kind].corrupt
        n_out = int(round(fraction * len(s.data))) if corrupt is not None else 0
        if n_out:
            index[s.name] = np.sort(rng.choice(len(s.data), size=n_out, replace=False))
            s = replace(s, data=corrupt(s.data, index[s.name], scale, rng))
        out.append(s)
    return tuple(out), index


def _covariance(*sigma_blocks) -> np.ndarray:
    return np.diag(np.repeat(np.asarray(sigma_blocks, dtype=float) ** 2, 3))


def simulate(
    profile="gentle",
    duration: float = 60.0,
    seed: int = 0,
    imu_rate: float = 200.0,
    noise: ImuNoise = ImuNoise(velocity=0.0),
    truth: str = "discrete",
    initial_bias_sigma=(0.1, 0.01),
    initial_sigma=(0.1, 0.1, 0.02),
    outlier_fraction: float = 0.0,
    outlier_scale=(5.0, 1.0),
    gravity=DEFAULT_GRAVITY,
    t0: float = 0.0,
    clean_imu: str = "matched",
    sensors=(),
    **rates,
) -> SimulatedDataset:
    """Simulate an IMU dataset with measurements and ground truth (construction: module docstring).

    ``profile``: a name in :data:`PROFILES` (``gentle``, ``tumbling``, ``static``,
    ``static_level``) or a :class:`~datasets.trajectories.Profile`. ``duration`` [s] and
    ``imu_rate`` [Hz]: ``floor(duration * imu_rate) + 1`` samples from ``t0``. ``seed``: every
    random draw. ``noise``: the IMU noise densities (also stored as ``Dataset.noise``); by
    default without the velocity noise ``n_v`` (the discrete truth is the Euler model itself, so
    the estimators' model is then exactly the truth's).
    ``truth``: ``"discrete"`` (the Euler model's propagation of the clean IMU) or
    ``"continuous"`` (the analytic motion). ``clean_imu``: ``"analytic"`` (eq. 42 at the sample
    times) or ``"matched"`` (the samples whose Euler propagation follows the profile exactly).

    Sensors at the IMU, by kind (``rates``): ``<kind>_rate`` [Hz] (None or 0: none; ``imu_rate``
    must be an integer multiple; the first measurement is at ``t0``) for any kind of
    :data:`datasets.kinds.KINDS`, with ``<kind>_sigma`` (one number, one per residual dimension,
    or for 6-dim kinds ``(translation [m], rotation [rad])``; default the kind's
    ``default_sigma``); the sensor is named after its kind. Unless given, :data:`DEFAULT_RATES`.
    ``sensors``: further sensors of any kind, mounted anywhere
    (:class:`datasets.simulated_sensors.SensorSpec`).

    ``initial_bias_sigma = (acc [m/s^2], gyro [rad/s])``: spread of the true initial biases (and
    the bias block of ``initial_cov``; the initial bias estimate is 0). ``initial_sigma =
    (position [m], velocity [m/s], attitude [rad])``: spread of the initial estimate's error.
    ``outlier_fraction`` in [0, 1] of the measurements of each sensor whose kind can be corrupted
    get an error of ``outlier_scale = (metres, radians)``. ``gravity``: ``I_g`` [m/s^2].

    Raises an InputError naming the option for any bad option.
    """
    prof = _profile(profile)
    duration, imu_rate, t0 = float(duration), float(imu_rate), float(t0)
    if not np.isfinite(imu_rate) or imu_rate <= 0:
        raise InputError(f"imu_rate: expected a rate in Hz > 0, got {imu_rate!r}")
    if not np.isfinite(duration) or duration <= 0:
        raise InputError(f"duration: expected a duration in seconds > 0, got {duration!r}")
    if not np.isfinite(t0):
        raise InputError(f"t0: expected a finite start time, got {t0!r}")
    steps = int(np.floor(duration * imu_rate * (1 + _RATE_TOLERANCE)))
    if steps < 1:
        raise InputError(f"duration: {duration!r} s is shorter than one IMU step (1/imu_rate = {1 / imu_rate:g} s)")
    if clean_imu not in CLEAN_IMU_MODELS:
        raise InputError(f"clean_imu: expected one of {CLEAN_IMU_MODELS}, got {clean_imu!r}")
    if truth not in TRUTH_MODELS:
        raise InputError(f"truth: expected one of {TRUTH_MODELS}, got {truth!r}")
    if not isinstance(noise, ImuNoise):
        raise InputError(f"noise: expected an ImuNoise, got {type(noise).__name__}")
    g = np.asarray(gravity, dtype=float)
    if g.shape != (3,) or not np.all(np.isfinite(g)):
        raise InputError(f"gravity: expected a finite 3-vector, got {gravity!r}")
    shorthand = _sensors_at_imu({**DEFAULT_RATES, **rates}, imu_rate)
    sigma_bias = _sigmas("initial_bias_sigma", initial_bias_sigma, 2)
    sigma_initial = _sigmas("initial_sigma", initial_sigma, 3)
    outlier_fraction = float(outlier_fraction)
    if not 0.0 <= outlier_fraction <= 1.0:
        raise InputError(f"outlier_fraction: expected a fraction in [0, 1], got {outlier_fraction!r}")
    outlier_scale = _sigmas("outlier_scale", outlier_scale, 2)
    seeds = dict(zip(STREAMS, np.random.SeedSequence(seed).spawn(len(STREAMS))))
    rngs = {name: np.random.default_rng(s) for name, s in seeds.items()}

    # --- time, clean IMU
    n = steps + 1
    dt = 1.0 / imu_rate
    t = t0 + np.arange(n) / imu_rate
    if clean_imu == "analytic":
        kin = prof.evaluate(t)
        f_clean, w_clean = kin.specific_force(g), kin.omega
        v0 = kin.body_velocity()[0]
    else:
        kin, f_clean, w_clean, v0 = _matched_signals(prof, t0 + np.arange(n + 2) / imu_rate, g)

    # --- biases and measured IMU (draw order within each stream is fixed)
    initial_rng = rngs["initial"]
    b0 = initial_rng.standard_normal((2, 3)) * sigma_bias[:, None]
    initial_error = initial_rng.standard_normal((3, 3)) * sigma_initial[:, None]
    bias_steps = rngs["bias"].standard_normal((2, n - 1, 3)) * (
        np.array([noise.acc_bias, noise.gyro_bias])[:, None, None] * np.sqrt(dt)
    )
    b_f = b0[0] + np.concatenate([np.zeros((1, 3)), np.cumsum(bias_steps[0], axis=0)])
    b_w = b0[1] + np.concatenate([np.zeros((1, 3)), np.cumsum(bias_steps[1], axis=0)])
    white = rngs["imu"].standard_normal((2, n, 3))
    acc = f_clean + b_f + white[0] * (noise.acc / np.sqrt(dt))
    gyro = w_clean + b_w + white[1] * (noise.gyro / np.sqrt(dt))

    # --- truth
    if truth == "discrete":
        start = ImuState(kin.r[0], v0, kin.C[0], np.zeros(3), np.zeros(3))
        n_v = None
        if noise.velocity > 0:
            n_v = rngs["velocity"].standard_normal((n - 1, 3)) * (noise.velocity / np.sqrt(dt))
        states = euler_truth(start, f_clean, w_clean, t, g, velocity_noise=n_v).replace(b_f=b_f, b_w=b_w)
    else:
        states = ImuState(kin.r, kin.body_velocity(), kin.C, b_f, b_w)

    # --- initial estimate: the truth at t0 (whichever truth) perturbed
    first = states[0]
    initial = ImuState(
        first.r + initial_error[0], first.v + initial_error[1], so3.boxplus(first.C, initial_error[2]),
        np.zeros(3), np.zeros(3),
    )
    initial_cov = _covariance(*np.maximum(np.concatenate([sigma_initial, sigma_bias]), MIN_SIGMA))

    # --- measurements: every sensor by its kind's simulator, then the outliers
    truth_trajectory = Trajectory(t, states)
    imu_samples = ImuSamples(t, acc, gyro)
    drawn = sensors_from_truth(truth_trajectory, imu_samples, [*shorthand, *sensors], seeds["sensors"], w_clean,
                               noise.gyro)
    drawn, outliers = _with_outliers(drawn, outlier_fraction, outlier_scale, rngs["outliers"])
    return SimulatedDataset(
        name=f"synthetic:{prof.name}",
        imu=imu_samples,
        noise=noise,
        initial=initial,
        initial_cov=initial_cov,
        gravity=g.copy(),
        truth=truth_trajectory,
        sensors=drawn,
        clean_imu=ImuSamples(t, f_clean, w_clean),
        outliers=outliers,
        profile=prof.name,
        truth_model=truth,
        seed=seed,
    )
