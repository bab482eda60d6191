"""GTSAM's fixed-lag smoothers as a window (:mod:`smoother.fixed_lag.gtsam_window`): a long run with a
measurement gap, the factors a run holds and GTSAM's graph kept to the window, a keyframe GTSAM
marginalises before it was read, the window's covariances, and the batch smoother's isolated misses
at a short lag. What every kind of window does is in ``test_window_contract.py``."""
from __future__ import annotations

import functools
import gc
import warnings
import weakref
from dataclasses import replace

import estimator_cases as cases
import gtsam
import numpy as np
import pytest

from datasets.simulate import simulate
from smoother.evaluation.crosscheck import TARGETS
from smoother.fixed_lag import gtsam_window as fixed_lag
from smoother.fixed_lag.gtsam_window import make_smoother
from smoother.fixed_lag.kinds import GTSAM_KINDS
from smoother.fixed_lag.offline import run_fixed_lag
from smoother.model.problem import build_problem


@functools.lru_cache(maxsize=None)
def gap_run():
    """10 s gentle run, poses at 10 Hz except in [4, 6) s, lag 0.5 s (incremental smoother): the
    one warning is that of the gap (as test_window_contract.test_every_kind_warns_... has it)."""
    data = simulate(profile="gentle", duration=10.0, seed=0, imu_rate=cases.IMU_RATE, pose_rate=cases.POSE_RATE)
    keep = (data.sensor("pose").data.t < 4.0) | (data.sensor("pose").data.t >= 6.0)
    gapped = data.with_sensor("pose", data=data.sensor("pose").data.subset(keep))
    assert len(gapped.sensor("pose").data) == len(data.sensor("pose").data) - 20
    problem = build_problem(gapped)
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        result = run_fixed_lag(problem, 0.5, "incremental", progress=False)
    assert [str(w.message).split(":")[0] for w in caught] == ["fixed-lag (incremental)"]
    return gapped, problem, result


def test_a_long_run_with_a_measurement_gap_keeps_working():
    """Lag 0.5 s over 10 s (20 lags), no pose for 2 s: no exception, every estimate and
    covariance finite, no update needed a recovery; at the first keyframe after the gap the
    position sigma is larger than anywhere before it (the gap is real: 2 s of dead reckoning),
    and one second after the gap the error is back to normal: RMS over [7, 10] s at most 1.5
    times the RMS over [0, 4) s (0.028 against 0.050 m here; over seeds 0-5, 0.6-0.9 times)."""
    data, problem, result = gap_run()
    newest = result.newest
    assert np.all(np.isfinite(newest.states.r)) and np.all(np.isfinite(newest.states.v))
    assert np.all(np.isfinite(newest.cov))
    assert np.linalg.eigvalsh(newest.cov).min() > 0
    assert result.recovered == [] and result.skipped_factors == 0
    t = problem.times
    assert not np.any((t > 3.95) & (t < 6.0))  # no keyframe inside the gap
    error = np.linalg.norm(newest.states.r - cases.truth_at(data, t).r, axis=1)
    before, after = error[t < 4.0], error[t >= 7.0]
    sigma = np.sqrt(np.trace(newest.cov[:, 0:3, 0:3], axis1=1, axis2=2))
    at_gap_end = sigma[np.searchsorted(t, 6.0)]
    assert at_gap_end > sigma[t < 4.0].max(), (at_gap_end, sigma[t < 4.0].max())
    rms_before, rms_after = np.sqrt(np.mean(before**2)), np.sqrt(np.mean(after**2))
    assert rms_after <= 1.5 * rms_before, (rms_after, rms_before)
    # the window at the end is the last 0.5 s only: the smoother did marginalise all along
    assert result.window.t[0] >= t[-1] - 0.5 - 1e-9
    # and what it kept of the past is right: its newest state equals the full batch smoother's
    # last state within 0.2 batch sigma (measured 0.08; the EKF, which linearised the first
    # update after the gap about a 2 s dead-reckoning prediction and never again, is 0.96 sigma
    # off in the accelerometer bias there)
    from smoother.batch.solve import solve_batch

    final = solve_batch(build_problem(data)).trajectory
    assert cases.sigma_difference(newest.states[-1], final.states[-1], final.cov[-1]).max() < 0.2



@pytest.mark.parametrize("kind", GTSAM_KINDS)
def test_a_run_holds_the_factors_of_its_window_only(kind, gentle):
    """The loop makes each keyframe's factors when it reaches it and lets go of them when GTSAM
    marginalises their keyframes, so what a run holds does not grow with its length. Watched
    through weak references to everything made (41 keyframes at 10 Hz, lag 0.5 s: a window of 6
    keyframes, an IMU and a pose factor each): when keyframe k's factors are made, at most 14 of
    the GTSAM factors made before are alive (measured 12; with the whole problem's factors held,
    81) and at most one ImuFactor, the previous keyframe's (GTSAM's factor keeps only what its
    callback needs; with a callback that referred back to the ImuFactor, a reference cycle through
    GTSAM's C++ objects would keep all 40 alive). After the run nothing is."""
    problem = cases.problem(gentle)
    imu_factors, factors, alive_at = [], [], []  # weak references; (IMU, all) alive at each keyframe

    def watched(k):
        alive_at.append(tuple(sum(r() is not None for r in refs) for refs in (imu_factors, factors)))
        made = problem.keyframe_factors(k)
        imu_factors.extend(weakref.ref(made.imu) for _ in range(made.imu is not None))
        factors.extend(weakref.ref(f) for f in made.factors)
        return made

    run_fixed_lag(replace(problem, keyframe_factors=watched), 0.5, kind, covariances=True, progress=False)
    gc.collect()
    assert len(alive_at) == len(problem.times) == 41
    assert max(a for a, _ in alive_at) <= 1 and max(b for _, b in alive_at) <= 14, alive_at
    assert not any(r() is not None for r in imu_factors + factors)


@pytest.mark.parametrize("kind", GTSAM_KINDS)
def test_the_smoother_keeps_its_factor_graph_to_the_window_over_a_long_run(kind):
    """Marginalisation removes factors; their slots must be reused, or GTSAM's factor graph
    grows with the run and every relinearisation with it (ISAM2's default). A chain of 3-vector
    variables at 10 Hz, lag 0.5 s: after 300 updates the graph holds about the window's six
    factors plus a marginal, as after 100 (without slot reuse: 300 slots)."""
    smoother = make_smoother(kind, 0.5)
    noise = gtsam.noiseModel.Isotropic.Sigma(3, 0.1)
    sizes = []
    for k in range(300):
        graph, values, stamps = gtsam.NonlinearFactorGraph(), gtsam.Values(), gtsam.FixedLagSmootherKeyTimestampMap()
        if k == 0:
            graph.add(gtsam.PriorFactorVector(k, np.zeros(3), noise))
        else:
            graph.add(gtsam.BetweenFactorVector(k - 1, k, np.ones(3), noise))
        values.insert(k, np.full(3, float(k)))
        stamps.insert((k, 0.1 * k))
        smoother.update(graph, values, stamps)
        sizes.append(smoother.getFactors().size())
    assert max(sizes[100:]) <= 12, max(sizes[100:])
    assert sizes[-1] <= sizes[99] + 2, (sizes[99], sizes[-1])


@pytest.mark.parametrize("covariances", [False, True])
def test_a_keyframe_marginalised_before_it_was_read_is_an_error(gentle, monkeypatch, covariances):
    """The smoother takes a keyframe's estimate (and covariance) just before the update that
    marginalises it; were GTSAM to marginalise earlier than that rule says (simulated by a margin
    that takes them more than a keyframe period too late), the run stops with a clear error
    instead of returning an older estimate."""
    monkeypatch.setattr(fixed_lag, "LAG_MARGIN_S", -0.15)
    with pytest.raises(RuntimeError, match="left the window before its estimate was taken"):
        run_fixed_lag(cases.problem(gentle), 0.5, "incremental", covariances=covariances, progress=False)


def test_the_lagged_covariances_are_those_of_the_whole_window(gentle, monkeypatch):
    """Each update takes the marginal covariances of the newest keyframe and of those that leave
    with the next update only. Reference: the whole window's covariances at every update (taken
    here beside the run), each keyframe's from the last update that held it, the newest's from its
    own update -- equal bit for bit."""
    every = fixed_lag.window_covariances
    calls = []  # (first keyframe of the window, its covariances) per call

    def whole_window_too(blocks, smoother, estimate, first, states, rows_of, wanted=None):
        covs = every(blocks, smoother, estimate, first, states, rows_of)
        calls.append((first, covs))
        return covs if wanted is None else covs[list(wanted)]

    monkeypatch.setattr(fixed_lag, "window_covariances", whole_window_too)
    result = run_fixed_lag(cases.problem(gentle), 0.5, "incremental", covariances=True, progress=False)
    lagged, newest = {}, []
    for first, covs in calls[:-1]:  # one call per update, then one for the last window
        lagged.update((first + i, c) for i, c in enumerate(covs))
        newest.append(covs[-1])
    assert len(newest) == len(result.newest.t)
    np.testing.assert_array_equal(result.newest.cov, np.stack(newest))
    np.testing.assert_array_equal(result.lagged.cov, np.stack([lagged[j] for j in range(len(result.lagged.t))]))
    np.testing.assert_array_equal(result.window.cov, calls[-1][1])


def _cholesky_refuses(groups, n: int) -> bool:
    """Whether GTSAM's Cholesky-based ``Marginals`` calls this window's linear system indeterminant."""
    try:
        fixed_lag.cholesky_marginals(fixed_lag.linear_graph(groups), n, [0])
    except RuntimeError:
        return True
    return False


def _svd_marginals(groups, n: int, wanted) -> np.ndarray:
    """Reference marginal covariances from an SVD of the window's stacked rows (no squaring)."""
    _, s, vt = np.linalg.svd(fixed_lag.stacked_rows(groups, n), full_matrices=False)
    return np.stack([(vt[:, 15 * j:15 * (j + 1)].T / s**2) @ vt[:, 15 * j:15 * (j + 1)] for j in wanted])


def test_windows_that_cholesky_refuses_are_solved_to_the_accuracy_of_an_svd(monkeypatch):
    """Keyframes 25 ms apart and four kinds of measurement: GTSAM's Cholesky calls about a third of
    the windows nearly indeterminant although they have full rank. Their marginal covariances, now
    by QR, are within 1e-6 of the largest entry of those from an SVD of the window's rows (measured
    7e-8; the dense pseudo-inverse of A^T A that took these windows before was up to 4e-5 off)."""
    data = simulate(profile="gentle", duration=6.0, seed=5, imu_rate=200.0, pose_rate=5.0,
                    position_rate=8.0, orientation_rate=4.0, odometry_rate=2.0)
    refused = []
    solve = fixed_lag.window_marginals

    def recording(groups, n, wanted):
        out = solve(groups, n, wanted)
        if _cholesky_refuses(groups, n):
            refused.append((groups, n, list(wanted), out))
        return out

    monkeypatch.setattr(fixed_lag, "window_marginals", recording)
    run_fixed_lag(build_problem(data, keyframe_rate=40.0), 0.8, "incremental", covariances=True,
                  progress=False)
    assert len(refused) >= 10, len(refused)
    errors = [np.abs(out - ref).max() / np.abs(ref).max()
              for groups, n, wanted, out in refused for ref in [_svd_marginals(groups, n, wanted)]]
    assert max(errors) <= 1e-6, max(errors)


@pytest.mark.xfail(strict=True, reason=(
    "GTSAM's BatchFixedLagSmoother keeps the state its marginal factor lands on linearised at a "
    "fixed point (enforceConsistency: on by default, not settable from Python). With a short lag "
    "(0.5 s here; 0.3-0.45 s on other seeds) its Levenberg-Marquardt then finds no descent after "
    "1-2 iterations at isolated updates: the newest state is off by up to 0.39 EKF sigma (1.3 sigma "
    "at lag 0.3 s) while its covariance is right (trace ratio 1.00); the next update is back within "
    "0.01 sigma. A Python copy of its algorithm with enforceConsistency off passes; the incremental "
    "smoother is not affected, lags >= 1 s rarely (one keyframe at 0.31 sigma, on one tumbling seed in six)"))
def test_batch_fixed_lag_with_a_short_lag_tracks_the_ekf():
    spec = cases.CaseSpec("gentle", 3.0, 2)
    ekf = cases.ekf(spec).trajectory
    _, result = cases.fixed_lag(spec, "batch", 0.5)
    assert cases.sigma_difference(result.newest.states, ekf.states, ekf.cov).max() < TARGETS["fixed_lag_max_sigma"]
