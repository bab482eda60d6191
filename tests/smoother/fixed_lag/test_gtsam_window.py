"""Fixed-lag smoothing (smoother/fixed_lag.py): the window, long runs with a measurement gap,
factors older than the lag, recovery, options. (Tracking of the EKF is in test_crosscheck.py.)"""
from __future__ import annotations

import functools
import gc
import warnings
import weakref
from dataclasses import replace

import gtsam
import numpy as np
import pytest

from datasets.simulate import simulate
from smoother.fixed_lag import gtsam_window as fixed_lag
from smoother.fixed_lag.gtsam_window import make_smoother
from smoother.fixed_lag.kinds import GTSAM_KINDS as KINDS
from smoother.fixed_lag.offline import run_fixed_lag
from smoother.model.problem import build_problem

import estimator_cases as cases

LAG = 1.0


@pytest.mark.parametrize("kind", KINDS)
def test_window_holds_the_last_lag_seconds_smoothed_like_the_batch(tumbling, kind):
    """At the end the window holds the keyframes of the last ``lag`` seconds (GTSAM keeps a
    variable while ``t_newest - t <= lag``), its last state is the newest estimate, and inside it
    the fixed-lag estimates are those of the full batch smoother within 0.05 batch sigma
    (measured 0.002-0.008: the window has seen every measurement the batch has from its start
    on; older information enters through a marginal linearised at earlier estimates)."""
    problem, result = cases.fixed_lag(tumbling, kind, LAG)
    t_end = problem.times[-1]
    expected = problem.times[problem.times >= t_end - LAG - 1e-9]
    np.testing.assert_array_equal(result.window.t, expected)
    assert len(expected) == 11
    for name in ("r", "v", "C", "b_f", "b_w"):
        np.testing.assert_allclose(getattr(result.window.states, name)[-1], getattr(result.newest.states, name)[-1],
                                   rtol=0, atol=1e-9)
    _, batch = cases.batch(tumbling)
    i = np.searchsorted(batch.trajectory.t, result.window.t)
    diff = cases.sigma_difference(result.window.states, batch.trajectory.states[i], batch.trajectory.cov[i])
    assert diff.max() < 0.05, diff.max()
    # smoothing inside the window: the first window state is more certain than when it was newest
    first = np.searchsorted(problem.times, result.window.t[0])
    assert np.trace(result.window.cov[0]) < np.trace(result.newest.cov[first])
    assert result.skipped_factors == 0 and result.recovered == []
    assert len(result.update_s) == len(problem.times)


@functools.lru_cache(maxsize=None)
def gap_run():
    """10 s gentle run, poses at 10 Hz except in [4, 6) s, lag 0.5 s (incremental smoother): the
    one warning is that of the gap (test_either_kind_warns_...)."""
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



@pytest.mark.parametrize("kind", KINDS)
def test_either_kind_warns_when_measurements_are_further_apart_than_the_lag(kind):
    """A keyframe that leaves the window before the next measurement keeps its dead-reckoned
    estimate (and GTSAM's BatchFixedLagSmoother drifts off besides: it keeps its window's oldest
    state linearised where dead reckoning put it): the 2-s pose gap of gap_run() with a 0.5-s
    lag is named, with the lag that would cover it; a 3-s lag needs no warning."""
    data, problem, _ = gap_run()
    with pytest.warns(UserWarning, match=rf"fixed-lag \({kind}\): absolute measurements \(fixes, poses, attitudes\) up to 2.1 s apart, longer than the "
                                         r"lag \(0.5 s\).*Choose a lag of at least 2.1 s"):
        run_fixed_lag(problem, 0.5, kind, covariances=False, progress=False)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        run_fixed_lag(problem, 3.0, kind, covariances=False, progress=False)


def test_factors_older_than_the_lag_are_skipped_with_a_warning():
    """Odometry between keyframes 1 s apart with a lag of 0.3 s: when such a factor becomes
    available its earlier keyframe has been marginalised; it is skipped (and counted) instead of
    failing GTSAM. With a 2 s lag the same factors are all used."""
    data = simulate(profile="gentle", duration=2.0, seed=1, imu_rate=cases.IMU_RATE, pose_rate=cases.POSE_RATE,
                    odometry_rate=1.0)
    assert len(data.sensor("odometry").data) == 2
    with pytest.warns(UserWarning, match="2 factors referred to variables older than the lag"):
        short = run_fixed_lag(build_problem(data), 0.3, "incremental", covariances=False, progress=False)
    assert short.skipped_factors == 2
    assert np.all(np.isfinite(short.newest.states.r))
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        long = run_fixed_lag(build_problem(data), 2.0, "incremental", covariances=False, progress=False)
    assert long.skipped_factors == 0


@pytest.mark.parametrize("lag", [0.0, -1.0, float("nan")])
def test_lag_must_be_positive(lag, gentle):
    with pytest.raises(ValueError, match="lag"):
        run_fixed_lag(cases.problem(gentle), lag, "incremental")


def test_unknown_kind_is_refused(gentle):
    with pytest.raises(ValueError, match="kind"):
        run_fixed_lag(cases.problem(gentle), 1.0, "window")


@pytest.mark.parametrize("kind", KINDS)
def test_a_keyframe_without_imu_link_is_recovered_with_a_weak_prior(kind):
    """Keyframe 5 of a 1.5 s run keeps its pose measurement but loses its IMU factor (as a gap
    in the IMU data would leave it): its velocity and biases are unconstrained. Nothing ties it
    to the window, so it gets a weak prior in the same update and the run goes on (before that
    change GTSAM raised 'Leftover keys after elimination' / ISAM2 an IndexError, which the
    catch-and-retry could not recover: ISAM2 is inconsistent after a failed update)."""
    data = simulate(profile="gentle", duration=1.5, seed=0, imu_rate=cases.IMU_RATE, pose_rate=cases.POSE_RATE)
    problem = build_problem(data)
    k = 5

    def without_imu_factor(j):
        made = problem.keyframe_factors(j)
        if j == k:  # the factor goes; the interval's prediction (the initial guess) stays
            assert made.factors[0] is made.imu.factor and len(made.factors) == 2
            made = replace(made, factors=made.factors[1:], rows=made.rows[1:], oldest=made.oldest[1:])
        return made

    result = run_fixed_lag(replace(problem, keyframe_factors=without_imu_factor), 0.3, kind, progress=False)
    assert result.recovered == [k]
    assert np.all(np.isfinite(result.newest.states.r))


@pytest.mark.parametrize("kind", KINDS)
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


@pytest.mark.parametrize("kind", KINDS)
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


@pytest.mark.parametrize("kind", KINDS)
def test_each_keyframe_keeps_the_estimate_of_the_last_update_that_held_it(gentle, kind):
    """``lagged``: without covariances only the keyframes that the next update marginalises are
    read; with them the whole window is read at every update. Both give the same estimates, bit
    for bit; the last window's are the window's own, and the older ones are smoothed (they
    differ from the filtered ``newest``)."""
    partial = run_fixed_lag(cases.problem(gentle), 0.5, kind, covariances=False, progress=False)
    whole = run_fixed_lag(cases.problem(gentle), 0.5, kind, covariances=True, progress=False)
    for name in ("r", "v", "C", "b_f", "b_w"):
        np.testing.assert_array_equal(getattr(partial.lagged.states, name), getattr(whole.lagged.states, name))
        np.testing.assert_array_equal(getattr(partial.lagged.states, name)[-len(partial.window.t):],
                                      getattr(partial.window.states, name))
    assert np.abs(partial.lagged.states.r[:-6] - partial.newest.states.r[:-6]).max(axis=1).min() > 0.0


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
    run_fixed_lag(build_problem(data, keyframe_rate=10.0), 0.8, "incremental", covariances=True, progress=False)
    assert len(refused) >= 10, len(refused)
    errors = [np.abs(out - ref).max() / np.abs(ref).max()
              for groups, n, wanted, out in refused for ref in [_svd_marginals(groups, n, wanted)]]
    assert max(errors) <= 1e-6, max(errors)


def test_the_lag_warning_tells_a_gap_from_the_lag_and_suggests_a_lag_that_reaches_it():
    """A gap of 2.0019 s beside a 2-s lag is not printed as "2 s", and the lag suggested is rounded
    up, never below the gap."""
    from smoother.fixed_lag.lag import sparse_measurement_warning

    text = sparse_measurement_warning(2.0019, 2.0, "sliding")
    assert "up to 2.002 s apart" in text and "at least 2.002 s" in text
    suggested = float(sparse_measurement_warning(4.0012, 2.0, "sliding").split("at least ")[1].split(" s")[0])
    assert suggested >= 4.0012
    assert sparse_measurement_warning(2.0, 2.0, "sliding") is None
