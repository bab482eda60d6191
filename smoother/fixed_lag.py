"""Fixed-lag smoothing on GTSAM's ``BatchFixedLagSmoother`` / ``IncrementalFixedLagSmoother``.

The factors of a :class:`smoother.graph.Problem` are fed keyframe by keyframe, in time order,
each with the keyframe's time stamp; variables older than the lag (seconds) are marginalised by
GTSAM. The new keyframe's initial value is the IMU prediction from the smoother's current
estimate of the previous keyframe. After every update the newest state's estimate and, if asked,
its 15x15 covariance (primer convention) are recorded; the smoothed window is returned at the end.

GTSAM pitfalls handled here:

* the Python ``BatchFixedLagSmoother`` has no ``marginalCovariance``: covariances come from
  ``gtsam.Marginals`` on the smoother's current factors (its marginal factors included), which
  works for both smoothers and gives the joint block of the keyframe's four variables;
* a factor that refers to a variable already marginalised out (a relative pose longer than the
  lag) would make GTSAM fail: it is skipped with a warning;
* an indeterminant update (for example a gap with no measurement and yaw unobservable) is caught:
  the keyframe's variables get a weak prior around their prediction and the update is repeated,
  so one bad stretch does not stop or poison the rest of the run.
"""
from __future__ import annotations

import time
import warnings
from dataclasses import dataclass

import gtsam
import numpy as np

from datasets.types import Trajectory
from factors import imu
from factors import measurements as meas
from smoother.batch import is_indeterminant, keyframe_covariances
from smoother.graph import Problem, insert_state, read_state
from smoother.progress import progress_bar

KINDS = ("batch", "incremental")

#: Standard deviations of the weak prior added when an update is indeterminant.
WEAK_PRIOR_SIGMAS = np.array([1e2] * 3 + [1e1] * 3 + [np.pi] * 3 + [1.0] * 3 + [0.1] * 3)


@dataclass
class FixedLagResult:
    """``newest``: the newest state's estimate (and covariance) after each update, at the
    keyframe times; ``window``: the smoothed estimates of the last window; ``update_s``: wall
    time of each update; ``recovered``: keyframes where a weak prior was needed."""

    newest: Trajectory
    window: Trajectory
    update_s: np.ndarray
    recovered: list
    skipped_factors: int
    runtime_s: float


def _make_smoother(kind: str, lag_s: float):
    if kind == "batch":
        return gtsam.BatchFixedLagSmoother(lag_s)
    if kind == "incremental":
        params = gtsam.ISAM2Params()
        params.setRelinearizeThreshold(1e-3)
        return gtsam.IncrementalFixedLagSmoother(lag_s, params)
    raise ValueError(f"fixed-lag smoother kind {kind!r}: expected one of {', '.join(KINDS)}")


def _active_factors(smoother) -> gtsam.NonlinearFactorGraph:
    graph = gtsam.NonlinearFactorGraph()
    factors = smoother.getFactors()
    for i in range(factors.size()):
        f = factors.at(i)
        if f is not None:
            graph.add(f)
    return graph


def run_fixed_lag(problem: Problem, lag_s: float, kind: str = "batch", covariances: bool = True,
                  progress: bool | None = None) -> FixedLagResult:
    """Run a fixed-lag smoother over ``problem`` (see the module docstring)."""
    if not lag_s > 0:
        raise ValueError(f"lag must be positive, got {lag_s}")
    start = time.perf_counter()
    smoother = _make_smoother(kind, lag_s)
    newest_states, newest_covs, update_s, recovered = [], [], [], []
    skipped = 0
    present: set[int] = set()
    with progress_bar(len(problem.times), f"fixed-lag ({kind})", progress) as bar:
        for k, t_k in enumerate(problem.times):
            keys = problem.keys[k]
            new_keys = set(keys.all())
            graph = gtsam.NonlinearFactorGraph()
            for f in problem.factors_at[k]:
                if all(key in present or key in new_keys for key in f.keys()):
                    graph.add(f)
                else:
                    skipped += 1
            values = gtsam.Values()
            if k == 0:
                guess = problem.initial_states[0]
            else:
                previous = read_state(smoother.calculateEstimate(), problem.keys[k - 1])
                guess = problem.imu_factors[k - 1].predict(previous)
            insert_state(values, keys, guess)
            stamps = gtsam.FixedLagSmootherKeyTimestampMap()
            for key in keys.all():
                stamps.insert((key, float(t_k)))
            tick = time.perf_counter()
            try:
                smoother.update(graph, values, stamps)
            except RuntimeError as error:
                if not is_indeterminant(error):
                    raise
                recovered.append(k)
                weak = gtsam.NonlinearFactorGraph()
                weak.add(meas.state_prior_factor(keys, guess, np.diag(WEAK_PRIOR_SIGMAS**2)))
                smoother.update(weak, gtsam.Values(), gtsam.FixedLagSmootherKeyTimestampMap())
            estimate = smoother.calculateEstimate()
            update_s.append(time.perf_counter() - tick)
            present = set(int(key) for key in estimate.keys())
            newest_states.append(read_state(estimate, keys))
            if covariances:
                newest_covs.append(keyframe_covariances(_active_factors(smoother), estimate, [keys])[0])
            bar.update(1)
    if skipped:
        warnings.warn(f"{skipped} factors referred to variables older than the lag ({lag_s} s) and were skipped",
                      stacklevel=2)
    estimate = smoother.calculateEstimate()
    in_window = [k for k, kk in enumerate(problem.keys) if estimate.exists(kk.rot)]
    window_states = imu.ImuState.stack([read_state(estimate, problem.keys[k]) for k in in_window])
    window_cov = None
    if covariances:
        window_cov = keyframe_covariances(_active_factors(smoother), estimate,
                                          [problem.keys[k] for k in in_window])
    newest = Trajectory(problem.times, imu.ImuState.stack(newest_states),
                        np.stack(newest_covs) if covariances else None)
    window = Trajectory(problem.times[in_window], window_states, window_cov)
    return FixedLagResult(newest, window, np.array(update_s), recovered, skipped, time.perf_counter() - start)

