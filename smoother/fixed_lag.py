"""Fixed-lag smoothing on GTSAM's ``BatchFixedLagSmoother`` / ``IncrementalFixedLagSmoother``.

The factors of a :class:`smoother.graph.Problem` are fed keyframe by keyframe, in time order,
each with the keyframe's time stamp; variables older than the lag (seconds) are marginalised by
GTSAM. The new keyframe's initial value is the IMU prediction from the smoother's current
estimate of the previous keyframe. After every update the newest state's estimate and, if asked,
its 15x15 covariance (primer convention) are recorded; the smoothed window is returned at the end.

GTSAM pitfalls handled here:

* the Python ``BatchFixedLagSmoother`` has no ``marginalCovariance``: covariances come from the
  smoother's current factors (its marginal factors included) linearised and inverted densely
  (:func:`window_covariances`), which works for both smoothers, gives the joint block of the
  keyframe's four variables, and survives nearly singular windows;
* both smoothers factorise with QR: with Cholesky, sparse GPS (KITTI) is declared
  indeterminant within seconds and ISAM2 cannot continue after a failed update;
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
from factors.chart import state_covariance_to_primer
from smoother.batch import is_indeterminant
from smoother.graph import Problem, insert_state, read_state
from smoother.progress import progress_bar

KINDS = ("batch", "incremental")

#: Standard deviations of the weak prior added when an update is indeterminant.
WEAK_PRIOR_SIGMAS = np.array([1e2] * 3 + [1e1] * 3 + [np.pi] * 3 + [1.0] * 3 + [0.1] * 3)


@dataclass
class FixedLagResult:
    """``newest``: the newest state's estimate (and covariance) after each update, at the
    keyframe times -- a filtered estimate; ``lagged``: each keyframe's estimate (and covariance)
    at the last update that still held it, i.e. smoothed with up to ``lag`` seconds of later
    data -- the fixed-lag smoother's own output; ``window``: the estimates of the last window;
    ``update_s``: wall time of each update; ``recovered``: keyframes where a weak prior was
    needed."""

    newest: Trajectory
    lagged: Trajectory
    window: Trajectory
    update_s: np.ndarray
    recovered: list
    skipped_factors: int
    runtime_s: float


def _make_smoother(kind: str, lag_s: float):
    """GTSAM's smoother of ``kind`` with QR factorisation: Cholesky declares the nearly
    singular systems of sparse GPS (KITTI, a fix every 10 s with 1 s keyframes) indeterminant
    at the velocity variables within seconds, and ISAM2 cannot continue after a failed update;
    QR solves them (the price is about 1.5x per update)."""
    if kind == "batch":
        params = gtsam.LevenbergMarquardtParams()
        params.setLinearSolverType("MULTIFRONTAL_QR")
        return gtsam.BatchFixedLagSmoother(lag_s, params)
    if kind == "incremental":
        params = gtsam.ISAM2Params()
        params.setRelinearizeThreshold(1e-3)
        params.setFactorization("QR")
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


def window_covariances(smoother, estimate: gtsam.Values, keys: list) -> np.ndarray:
    """Primer-convention 15x15 covariances of the keyframes ``keys`` from the smoother's current
    factors (its marginal factors included) linearised at ``estimate``.

    The window is small (lag / keyframe period keyframes), so its information matrix
    ``A^T A`` is formed densely and inverted: unlike ``gtsam.Marginals`` (Cholesky) this does
    not stop at the nearly singular systems that QR-based smoothers accept (sparse GPS); a
    direction the data does not constrain shows as a large variance."""
    linear = _active_factors(smoother).linearize(estimate)
    window = [int(k) for k in estimate.keys()]
    zeros = estimate.zeroVectors()
    dims = {k: zeros.at(k).shape[0] for k in window}
    A, _ = linear.jacobian(gtsam.Ordering(window))
    offsets = dict(zip(window, np.concatenate([[0], np.cumsum([dims[k] for k in window])])[:-1]))
    information = A.T @ A
    try:
        cov = np.linalg.inv(information)
    except np.linalg.LinAlgError:
        cov = np.linalg.pinv(information)
    cov = 0.5 * (cov + cov.T)
    out = []
    for kk in keys:
        idx = np.concatenate([np.arange(offsets[k], offsets[k] + dims[k]) for k in kk.all()])
        out.append(state_covariance_to_primer(cov[np.ix_(idx, idx)], estimate.atRot3(kk.rot)))
    return np.stack(out)


def run_fixed_lag(problem: Problem, lag_s: float, kind: str = "batch", covariances: bool = True,
                  progress: bool | None = None) -> FixedLagResult:
    """Run a fixed-lag smoother over ``problem`` (see the module docstring)."""
    if not lag_s > 0:
        raise ValueError(f"lag must be positive, got {lag_s}")
    start = time.perf_counter()
    smoother = _make_smoother(kind, lag_s)
    newest_states, newest_covs, update_s, recovered = [], [], [], []
    lagged_states: dict[int, imu.ImuState] = {}
    lagged_covs: dict[int, np.ndarray] = {}
    first = 0
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
            while problem.keys[first].rot not in present:  # the window is contiguous: [first, k]
                first += 1
            in_window = range(first, k + 1)
            for j in in_window:
                lagged_states[j] = read_state(estimate, problem.keys[j])
            newest_states.append(lagged_states[k])
            if covariances:
                covs = window_covariances(smoother, estimate, [problem.keys[j] for j in in_window])
                for j, c in zip(in_window, covs):
                    lagged_covs[j] = c
                newest_covs.append(lagged_covs[k])
            bar.update(1)
    if skipped:
        warnings.warn(f"{skipped} factors referred to variables older than the lag ({lag_s} s) and were skipped",
                      stacklevel=2)
    estimate = smoother.calculateEstimate()
    in_window = [k for k, kk in enumerate(problem.keys) if estimate.exists(kk.rot)]
    window_states = imu.ImuState.stack([read_state(estimate, problem.keys[k]) for k in in_window])
    window_cov = None
    if covariances:
        window_cov = window_covariances(smoother, estimate, [problem.keys[k] for k in in_window])
    newest = Trajectory(problem.times, imu.ImuState.stack(newest_states),
                        np.stack(newest_covs) if covariances else None)
    order = range(len(problem.times))
    lagged = Trajectory(problem.times, imu.ImuState.stack([lagged_states[j] for j in order]),
                        np.stack([lagged_covs[j] for j in order]) if covariances else None)
    window = Trajectory(problem.times[in_window], window_states, window_cov)
    return FixedLagResult(newest, lagged, window, np.array(update_s), recovered, skipped,
                          time.perf_counter() - start)

