"""Fixed-lag smoothing of a whole :class:`smoother.model.problem.Problem`: :func:`run_fixed_lag` feeds its
keyframes, in time order, to a window of any kind (:data:`smoother.fixed_lag.kinds.FIXED_LAG_KINDS`, the
compiled ``"sliding"`` window by default) through the fixed-lag contract
(:class:`smoother.fixed_lag.contract.FixedLagWindow`) and records what comes out of it: after every update the
newest keyframe's estimate and, if asked, its 15x15 covariance (primer convention); each keyframe's
estimate as it leaves the window; and the window at the end.

Keyframe ``k``'s factors are the problem's own (``Problem.keyframe_factors``, made when the loop
reaches it and let go once the window has marginalised it); its initial value is the IMU
prediction from the window's estimate of the previous keyframe. The calibrations a problem
estimates (``Problem.calibration``) keep the values given here, as in the problem's factors.
"""
from __future__ import annotations

import time
import warnings
from dataclasses import dataclass

import numpy as np

from datasets.types import Trajectory
from factors import imu
from smoother.fixed_lag.lag import measured_gap, warn_of_sparse_measurements
from smoother.fixed_lag.windows import make_window
from smoother.model.correlated import weighed_alone_warning
from smoother.model.problem import Problem
from smoother.progress import progress_bar


@dataclass
class FixedLagResult:
    """``newest``: the newest state's estimate (and covariance) after each update, at the
    keyframe times -- a filtered estimate; ``lagged``: each keyframe's estimate (and covariance)
    at the last update that still held it, i.e. smoothed with up to ``lag`` seconds of later
    data -- the fixed-lag smoother's own output; ``window``: the estimates of the last window;
    ``update_s``: wall time of each update; ``recovered``: keyframes where a weak prior was
    needed; ``skipped_factors``: factors left out because they read a keyframe already
    marginalised; ``runtime_s``: the whole run."""

    newest: Trajectory
    lagged: Trajectory
    window: Trajectory
    update_s: np.ndarray
    recovered: list
    skipped_factors: int
    runtime_s: float


def run_fixed_lag(problem: Problem, lag_s: float, kind: str = "sliding", covariances: bool = True,
                  progress: bool | None = None) -> FixedLagResult:
    """Run the fixed-lag smoother ``kind`` with the lag ``lag_s`` [s] over ``problem`` (module
    docstring): its keyframes through one window (:func:`smoother.fixed_lag.windows.make_window`), with a
    warning when its absolute measurements are further apart than the lag
    (:func:`smoother.fixed_lag.lag.sparse_measurement_warning`) and one when factors were skipped.
    ``covariances``: the newest and lagged keyframes' covariances and the last window's."""
    window = make_window(lag_s, kind, problem.gravity)
    warn_of_sparse_measurements(measured_gap(problem), window.lag_s, kind)
    start = time.perf_counter()
    n = len(problem.times)
    newest, lagged = [], {}  # the newest estimate after each update; each keyframe's as last taken
    newest_cov, lagged_cov = [], {}
    with progress_bar(n, f"fixed-lag ({kind})", progress) as bar:
        for k, t_k in enumerate(problem.times):
            made = problem.keyframe_factors(k)
            # the initial value: from the window's estimate of the previous keyframe after the last update
            guess = problem.initial_states[0] if k == 0 else made.imu.predict(window.newest_state)
            newest.append(window.add_problem_keyframe(t_k, guess, made, problem.blocks))
            # A keyframe's lagged estimate and covariance are those of the last update that holds
            # it: taken for the keyframes that the next update marginalises and the newest, not
            # for the whole window at every update.
            taken = sorted(set(window.leaving(problem.times[k + 1]) if k + 1 < n else []) | {k})
            covs = window.covariances(taken) if covariances else [None] * len(taken)
            window.taken(taken)
            for j, cov in zip(taken, covs):
                lagged[j], lagged_cov[j] = window.state(j), cov
            newest_cov.append(lagged_cov[k])
            bar.update(1)
    alone = weighed_alone_warning(f"fixed-lag ({kind})", window.weighed_alone, lag_s)
    if alone is not None:
        warnings.warn(alone, stacklevel=2)
    if window.skipped:
        warnings.warn(f"{window.skipped} factors referred to variables older than the lag ({lag_s} s) and were "
                      "skipped", stacklevel=2)
    in_window = list(range(window.first, window.newest + 1))
    window_cov = window.covariances(in_window) if covariances else None
    for j, cov in zip(in_window, window_cov if covariances else [None] * len(in_window)):
        lagged[j], lagged_cov[j] = window.state(j), cov

    def trajectory(keyframes, states, covs) -> Trajectory:
        return Trajectory(problem.times[keyframes], imu.ImuState.stack(states),
                          np.stack(covs) if covariances else None)

    every = range(n)
    return FixedLagResult(trajectory(every, newest, newest_cov),
                          trajectory(every, [lagged[j] for j in every], [lagged_cov[j] for j in every]),
                          trajectory(in_window, [lagged[j] for j in in_window], [lagged_cov[j] for j in in_window]),
                          np.array(window.update_s), window.recovered, window.skipped, time.perf_counter() - start)
