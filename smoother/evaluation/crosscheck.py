"""Cross-checks between the three estimators where theory says they must agree (docs/design.md,
section 9).

On simulated runs (discrete-model truth, so no discretisation error pollutes the statistics) of
one of :data:`RIGS` (:attr:`CrosscheckOptions.sensors`):

* ``prediction_max_abs_error``: the IMU factor's prediction of keyframe ``j`` from ``i`` against
  the EKF's sample-by-sample propagation of the same samples (same model: round-off, < 1e-9);
* ``final_state_max_sigma``: batch smoother versus EKF at the LAST state, in EKF standard
  deviations (filtering and smoothing coincide at the end of the data up to linearisation);
  ``final_cov_trace_ratio``: trace of the batch's last-state covariance over the EKF's;
* ``fixed_lag_max_sigma_by_kind``: for each kind of fixed-lag smoother checked
  (:attr:`CrosscheckOptions.fixed_lag_kinds`: the default sliding window and GTSAM's incremental
  smoother), its newest state against the EKF at every keyframe, in EKF standard deviations (both
  are filters up to linearisation); ``fixed_lag_max_sigma`` is that of the first kind, named by
  ``fixed_lag_kind`` (the sliding window unless asked otherwise), which also stands for the
  fixed-lag smoother (``"fixed-lag"``) below; the check holds when every kind is within the target;
* ``ate_rmse_m`` per estimator (the smoothed trajectory at least as accurate as the filtered);
* ``nees_mean`` per estimator over all seeds and times (pose NEES / 6) and the 95% chi-square
  interval of a per-time average over the seeds, ``nees_bounds(6, seeds) / 6``; the average over
  time of correlated per-time averages varies less than one of them, so the interval is
  conservative (a consistent estimator passes it with more than 95% probability);
* ``keyframes``: the smoothers' keyframes (:func:`smoother.model.timeline.keyframe_record`, the
  first seed's: every seed's rig is the same), how many measurements were attached.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from datasets.simulate import simulate
from datasets.simulated_sensors import SensorSpec
from factors import imu
from factors.errors import InputError, InternalError
from smoother import stats
from smoother.batch.solve import solve_batch
from smoother.ekf.filter import Ekf, run_ekf
from smoother.estimators import ESTIMATORS
from smoother.evaluation.scoring import compare_with_truth
from smoother.fixed_lag.kinds import FIXED_LAG_KINDS
from smoother.fixed_lag.offline import run_fixed_lag
from smoother.model.problem import build_problem

TARGETS = {
    "prediction_max_abs_error": 1e-9,
    "final_state_max_sigma": 0.1,
    "final_cov_trace_ratio_tolerance": 0.1,
    "fixed_lag_max_sigma": 0.2,
}


def _mounted(p_BS) -> np.ndarray:
    T = np.eye(4)
    T[:3, 3] = p_BS
    return T


#: The simulated rigs (``datasets.simulate``'s ``sensors``, beside its default 10 Hz pose sensor at
#: the IMU and its 200 Hz IMU): ``pose``, the pose sensor alone (a keyframe at every measurement
#: time); ``wheels``, with a wheel-speed sensor (velocity, 100 Hz, 0.05 m/s, 0.6 m behind and
#: 0.3 m below the IMU) and a GNSS antenna (4 Hz, 0.1 m, 0.8 m above it): the measurements come
#: faster than 10 Hz, so the smoothers' keyframes are the 10 Hz grid, nine speeds in ten and every
#: other fix attached to the keyframe before them (docs/design.md, keyframes). The pose sensor
#: observes the attitude: without it, the EKF's first linearisations on a rig that sees its heading
#: and accelerometer bias only through the motion leave it about 0.2 of its sigma from the
#: nonlinear optimum, keyframes on a grid or not (section 9).
RIGS = {
    "pose": (),
    "wheels": (SensorSpec("wheels", "velocity", 100.0, 0.05, _mounted([-0.6, 0.0, -0.3])),
               SensorSpec("gnss", "gnss", 4.0, 0.1, _mounted([0.0, 0.0, 0.8]))),
}


@dataclass
class CrosscheckOptions:
    """The simulated runs (``profile``, ``seeds`` from ``first_seed``, ``duration`` [s], the rig
    ``sensors``, a name in :data:`RIGS`) and the fixed-lag smoothers checked: the lag ``lag_s``
    [s] and the kinds ``fixed_lag_kinds`` (:data:`smoother.fixed_lag.kinds.FIXED_LAG_KINDS`; the
    first one's figures are the fixed-lag smoother's, module docstring)."""

    profile: str = "gentle"
    seeds: int = 5
    first_seed: int = 0
    duration: float = 20.0
    lag_s: float = 2.0
    fixed_lag_kinds: tuple[str, ...] = ("sliding", "incremental")
    sensors: str = "pose"


def prediction_error(problem, dataset, intervals: int = 5) -> float:
    """Largest |factor prediction - EKF propagation| over r, v, C entries for a few intervals."""
    worst = 0.0
    for k in np.linspace(0, len(problem.imu_factors) - 1, intervals).astype(int):
        factor = problem.imu_factors[k]
        # At the factor's own linearisation point (it may have been integrated again during
        # optimisation) the prediction is exact, not first order in the gyro-bias offset.
        start = problem.initial_states[k].replace(b_w=factor.pre.b_w_bar)
        ekf = Ekf(start, np.zeros((15, 15)), dataset.noise, dataset.gravity)
        acc, gyro, dt = factor.pre.samples
        for a, g, h in zip(acc, gyro, dt):
            ekf.predict(a, g, h)
        predicted = factor.predict(start)
        for name in ("r", "v", "C"):
            worst = max(worst, float(np.max(np.abs(getattr(predicted, name) - getattr(ekf.state, name)))))
    return worst


def sigma_difference(a: imu.ImuState, b: imu.ImuState, cov: np.ndarray) -> np.ndarray:
    """``|a [-] b|`` per error-state component in standard deviations of ``cov``."""
    return np.abs(imu.boxminus(a, b)) / np.sqrt(np.einsum("...ii->...i", cov))


def one_seed(options: CrosscheckOptions, seed: int) -> dict:
    """All the figures for one simulated run."""
    dataset = simulate(profile=options.profile, duration=options.duration, seed=seed, sensors=RIGS[options.sensors])
    problem = build_problem(dataset)
    batch = solve_batch(problem).trajectory
    ekf = run_ekf(dataset, progress=False).trajectory
    newest = {kind: run_fixed_lag(problem, options.lag_s, kind, progress=False).newest
              for kind in options.fixed_lag_kinds}
    i_ekf = np.searchsorted(ekf.t, problem.times)
    if not np.array_equal(ekf.t[i_ekf], problem.times):
        raise InternalError("EKF and smoother keyframe times differ")
    tracking = {kind: float(sigma_difference(fixed.states, ekf.states[i_ekf], ekf.cov[i_ekf]).max())
                for kind, fixed in newest.items()}
    headline = options.fixed_lag_kinds[0]
    out = {
        "prediction_max_abs_error": prediction_error(problem, dataset),
        "final_state_max_sigma": float(sigma_difference(batch.states[-1], ekf.states[-1], ekf.cov[-1]).max()),
        "final_cov_trace_ratio": float(np.trace(batch.cov[-1]) / np.trace(ekf.cov[-1])),
        "fixed_lag_max_sigma": tracking[headline],
        "fixed_lag_max_sigma_by_kind": tracking,
        "keyframes": problem.keyframes,
        "ate_rmse_m": {},
        "nees": {},
    }
    for name, traj in (("batch", batch), ("fixed-lag", newest[headline]), ("ekf", ekf.subset(i_ekf))):
        c = compare_with_truth(dataset.truth, traj)
        out["ate_rmse_m"][name] = c["ate_rmse_m"]
        out["nees"][name] = c["nees"] / 6.0
    return out


def crosscheck(options: CrosscheckOptions, progress=None) -> dict:
    """Run :func:`one_seed` for every seed and aggregate (see the module docstring)."""
    if not options.fixed_lag_kinds or not set(options.fixed_lag_kinds) <= set(FIXED_LAG_KINDS):
        raise InputError(f"fixed_lag_kinds: expected one or more of {', '.join(FIXED_LAG_KINDS)}, got "
                         f"{options.fixed_lag_kinds!r}")
    if options.sensors not in RIGS:
        raise InputError(f"sensors: expected one of {', '.join(RIGS)}, got {options.sensors!r}")
    runs = []
    for seed in range(options.first_seed, options.first_seed + options.seeds):
        runs.append(one_seed(options, seed))
        if progress is not None:
            progress(seed)
    names = ESTIMATORS
    low, high = (b / 6.0 for b in stats.nees_bounds(6, options.seeds))
    nees_mean = {n: float(np.mean([r["nees"][n] for r in runs])) for n in names}
    ate = {n: float(np.mean([r["ate_rmse_m"][n] for r in runs])) for n in names}
    result = {
        "profile": options.profile,
        "sensors": options.sensors,
        "seeds": options.seeds,
        "duration_s": options.duration,
        "prediction_max_abs_error": max(r["prediction_max_abs_error"] for r in runs),
        "final_state_max_sigma": max(r["final_state_max_sigma"] for r in runs),
        "final_cov_trace_ratio": float(np.mean([r["final_cov_trace_ratio"] for r in runs])),
        "final_cov_trace_ratio_range": [min(r["final_cov_trace_ratio"] for r in runs),
                                        max(r["final_cov_trace_ratio"] for r in runs)],
        "fixed_lag_kind": options.fixed_lag_kinds[0],
        "fixed_lag_max_sigma": max(r["fixed_lag_max_sigma"] for r in runs),
        "fixed_lag_max_sigma_by_kind": {kind: max(r["fixed_lag_max_sigma_by_kind"][kind] for r in runs)
                                        for kind in options.fixed_lag_kinds},
        "keyframes": runs[0]["keyframes"],
        "ate_rmse_m": ate,
        "nees_mean": nees_mean,
        "nees_interval_95": [low, high],
    }
    checks = {
        "prediction": result["prediction_max_abs_error"] < TARGETS["prediction_max_abs_error"],
        "final_state": result["final_state_max_sigma"] < TARGETS["final_state_max_sigma"],
        "final_cov": all(abs(x - 1.0) <= TARGETS["final_cov_trace_ratio_tolerance"]
                         for x in result["final_cov_trace_ratio_range"]),
        "fixed_lag": all(x < TARGETS["fixed_lag_max_sigma"] for x in result["fixed_lag_max_sigma_by_kind"].values()),
        "smoothed_at_least_as_accurate": ate["batch"] <= ate["ekf"],
        "nees": all(low <= nees_mean[n] <= high for n in names),
    }
    result["checks"] = checks
    result["ok"] = all(checks.values())
    return result
