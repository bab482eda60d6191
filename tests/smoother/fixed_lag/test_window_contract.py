"""The fixed-lag window contract (:mod:`smoother.fixed_lag.contract`), the same checks on every kind of
window (:data:`smoother.fixed_lag.kinds.FIXED_LAG_KINDS`: the compiled sliding window, GTSAM's
incremental and batch smoothers), driven by hand or by the offline driver
(:func:`smoother.fixed_lag.offline.run_fixed_lag`): the newest state tracks the EKF, a window spanning the
run is the batch optimum, ``leaving`` and ``taken`` keep their bookkeeping, covariances are
symmetric positive definite, an IMU gap longer than the lag keeps its IMU factor, what cannot be
used is skipped or recovered, and sparse measurements are warned of. Each kind's own machinery is
tested beside this file (``test_gtsam_window.py``, ``sliding/``)."""
from __future__ import annotations

import warnings
from dataclasses import replace

import estimator_cases as cases
import numpy as np
import pytest

from datasets.simulate import simulate
from smoother.evaluation.crosscheck import TARGETS
from smoother.fixed_lag import offline
from smoother.fixed_lag.contract import FixedLagWindow
from smoother.fixed_lag.kinds import FIXED_LAG_KINDS
from smoother.fixed_lag.offline import run_fixed_lag
from smoother.fixed_lag.windows import make_window
from smoother.model.problem import build_problem

kinds = pytest.mark.parametrize("kind", FIXED_LAG_KINDS)


def _feed(problem, window, take: bool = True, after=None, change=None) -> None:
    """``problem``'s keyframes through ``window`` as the offline driver feeds them (the initial value
    predicted from the newest estimate), taking what ``leaving`` names after each update when
    ``take``; ``after(window, k, named)`` is called after update ``k`` with what ``leaving`` named
    before it (None at the first); ``change(k, made)`` may replace a keyframe's factors."""
    named = None
    for k, t in enumerate(problem.times):
        made = problem.keyframe_factors(k)
        guess = problem.initial_states[0] if k == 0 else made.imu.predict(window.newest_state)
        window.add_problem_keyframe(t, guess, made if change is None else change(k, made), problem.blocks)
        if after is not None:
            after(window, k, named)
        if k + 1 < len(problem.times):
            named = window.leaving(problem.times[k + 1])
            if take:
                window.taken(named)


@kinds
def test_every_kind_is_a_window_of_the_contract(kind):
    window = make_window(0.5, kind)
    assert isinstance(window, FixedLagWindow)
    assert (window.kind, window.lag_s, window.first, window.newest) == (kind, 0.5, 0, -1)
    assert window.recovered == [] and window.skipped == 0 and len(window.update_s) == 0
    assert window.calibration is None


@kinds
def test_the_newest_state_tracks_the_ekf(case, kind):
    """Lag 1 s: the newest fixed-lag state is within the cross-check's tolerance (0.2 EKF sigma,
    all 15 components) of the EKF at every keyframe -- both are filters of the same model up to
    linearisation; measured at most 0.04 for the sliding window and GTSAM's incremental smoother
    -- and for GTSAM's batch smoother at all but isolated keyframes (at most one in 20, and within
    0.5 sigma there: measured 0.31 at one tumbling keyframe; see
    test_gtsam_window.test_batch_fixed_lag_with_a_short_lag_tracks_the_ekf); its covariance trace
    within 10% of the EKF's everywhere (measured 0.3%)."""
    ekf = cases.ekf(case).trajectory
    problem, result = cases.fixed_lag(case, kind, 1.0)
    np.testing.assert_array_equal(result.newest.t, ekf.t)
    worst = cases.sigma_difference(result.newest.states, ekf.states, ekf.cov).max(axis=1)
    off = worst >= TARGETS["fixed_lag_max_sigma"]
    if kind == "batch":
        assert off.sum() <= len(worst) / 20 and worst.max() < 0.5, (worst.max(), problem.times[off].tolist())
    else:
        assert not off.any(), (worst.max(), problem.times[off].tolist())
    ratio = np.trace(result.newest.cov, axis1=1, axis2=2) / np.trace(ekf.cov, axis1=1, axis2=2)
    assert np.all(np.abs(ratio - 1.0) <= 0.1), ratio


@kinds
def test_the_window_at_the_end_holds_the_last_lag_seconds_smoothed_like_the_batch(tumbling, kind):
    """At the end the window holds the keyframes of the last ``lag`` seconds (a keyframe stays
    while ``t_newest - t <= lag``), its last state is the newest estimate, and inside it the
    fixed-lag estimates are those of the full batch smoother within 0.05 batch sigma (measured
    0.003-0.014: the window has seen every measurement the batch has from its start on; older
    information enters through a marginal linearised at earlier estimates)."""
    problem, result = cases.fixed_lag(tumbling, kind, 1.0)
    expected = problem.times[problem.times >= problem.times[-1] - 1.0 - 1e-9]
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


@kinds
def test_a_window_spanning_the_whole_run_is_the_batch_optimum(gentle, kind):
    """A lag longer than the run marginalises nothing: at the end the window is the batch
    smoother's estimate within 0.05 sigma (measured: sliding 0.006, GTSAM's batch 1e-9, the
    incremental smoother 0.042, which relinearises only what moved more than its threshold) with
    its covariances within 0.02 in correlation units (measured at most 0.006)."""
    data = cases.dataset(gentle)
    window = run_fixed_lag(build_problem(data), 100.0, kind, progress=False).window
    batch = cases.batch(gentle)[1].trajectory
    np.testing.assert_array_equal(window.t, batch.t)
    diff = cases.sigma_difference(window.states, batch.states, batch.cov)
    assert diff.max() < 0.05, diff.max()
    scale = np.sqrt(np.einsum("nii->ni", batch.cov))
    correlation_diff = np.abs(window.cov - batch.cov) / (scale[:, :, None] * scale[:, None, :])
    assert correlation_diff.max() < 0.02, correlation_diff.max()


@kinds
def test_leaving_names_what_the_next_update_marginalises_and_covariances_are_positive_definite(gentle, kind):
    """Keyframes 0.1 s apart, lag 0.5 s, each update's ``leaving`` taken: every keyframe an update
    marginalises was named by ``leaving`` before it, the newest never (the sliding window) or only
    after a gap longer than the lag (none here), and what was named and stays is a keyframe at the
    boundary, within :data:`smoother.fixed_lag.gtsam_window.LAG_MARGIN_S` of it (GTSAM's windows
    name those too; the sliding window names exactly what leaves). After every update the window
    is the keyframes of the last lag seconds, and their covariances are symmetric and positive
    definite."""
    problem = cases.problem(gentle)
    window = make_window(0.5, kind, problem.gravity)
    seen = {"first": 0, "stayed": []}

    def check(window, k, named):
        t = problem.times[k]
        gone = list(range(seen["first"], window.first))
        if named is not None:
            assert set(gone) <= set(named) and k - 1 not in named, (k, gone, named)
            stayed = [j for j in named if j not in gone]
            assert all(abs(problem.times[j] - (t - 0.5)) <= 1e-6 for j in stayed), (k, stayed)
            seen["stayed"] += stayed
        seen["first"] = window.first
        assert window.newest == k and problem.times[window.first] >= t - 0.5 - 1e-6
        assert window.first == 0 or problem.times[window.first - 1] < t - 0.5 + 1e-6
        covs = window.covariances(range(window.first, window.newest + 1))
        np.testing.assert_allclose(covs, covs.transpose(0, 2, 1), rtol=0, atol=1e-12 * np.abs(covs).max())
        assert min(np.linalg.eigvalsh(c).min() for c in covs) > 0

    _feed(problem, window, after=check)
    assert window.newest == len(problem.times) - 1 and window.first > 30
    if kind == "sliding":
        assert seen["stayed"] == []


@kinds
def test_a_keyframe_not_taken_before_it_leaves_is_an_error(gentle, kind):
    """A caller that never takes what ``leaving`` names: the update that marginalises the first
    keyframe (at 0.6 s with a 0.5-s lag) raises, naming it, instead of letting an estimate go
    unread."""
    problem = cases.problem(gentle)
    with pytest.raises(RuntimeError, match=r"keyframe 0 \(t = 0.000000 s\) left the window before its estimate was "
                                           "taken"):
        _feed(problem, make_window(0.5, kind, problem.gravity), take=False)


@kinds
def test_each_keyframe_keeps_the_estimate_of_the_last_update_that_held_it(gentle, kind, monkeypatch):
    """The offline driver reads a keyframe's estimate and covariance only when ``leaving`` names it
    (and the newest, and the last window): its ``lagged`` output is, bit for bit, the estimate and
    covariance each keyframe had after the last update that held it (recorded here after every
    update), the same with and without covariances; the older ones are smoothed (they differ from
    the filtered ``newest``)."""
    held = {}  # keyframe -> (estimate, covariance) after the last update that held it
    make = offline.make_window

    def recording(*args, **kwargs):
        window = make(*args, **kwargs)
        add = window.add_problem_keyframe

        def add_and_record(*a, **k):
            out = add(*a, **k)
            keyframes = range(window.first, window.newest + 1)
            held.update(zip(keyframes, zip((window.state(j) for j in keyframes), window.covariances(keyframes))))
            return out

        window.add_problem_keyframe = add_and_record
        return window

    monkeypatch.setattr(offline, "make_window", recording)
    whole = run_fixed_lag(cases.problem(gentle), 0.5, kind, covariances=True, progress=False)
    partial = run_fixed_lag(cases.problem(gentle), 0.5, kind, covariances=False, progress=False)
    assert sorted(held) == list(range(len(whole.lagged.t)))
    for name in ("r", "v", "C", "b_f", "b_w"):
        expected = np.stack([getattr(held[j][0], name) for j in sorted(held)])
        np.testing.assert_array_equal(getattr(whole.lagged.states, name), expected)
        np.testing.assert_array_equal(getattr(partial.lagged.states, name), expected)
    np.testing.assert_array_equal(whole.lagged.cov, np.stack([held[j][1] for j in sorted(held)]))
    assert partial.lagged.cov is None and partial.newest.cov is None
    assert np.abs(whole.lagged.states.r[:-6] - whole.newest.states.r[:-6]).max(axis=1).min() > 0.0


@kinds
def test_an_imu_gap_longer_than_the_lag_keeps_its_imu_factor(gentle, kind):
    """Keyframes 1 s apart with a 0.3-s lag and nothing measured: each keyframe is tied to the
    next by its IMU factor (nothing skipped, no weak prior; the sliding window keeps the newest
    keyframe until the next is added, GTSAM's smoothers marginalise it in the update that adds
    the factor), so the estimates are the dead reckoning from the initial state (the problem's
    initial trajectory, within 1e-6 m; measured 1e-14). The whole run counts as one gap between
    absolute measurements."""
    problem = build_problem(replace(cases.dataset(gentle), sensors=()), keyframe_rate=1.0)
    assert np.diff(problem.times).min() > 0.9
    with pytest.warns(UserWarning, match=rf"fixed-lag \({kind}\): absolute measurements .* up to 4 s apart"):
        result = run_fixed_lag(problem, 0.3, kind, progress=False)
    assert result.recovered == [] and result.skipped_factors == 0
    np.testing.assert_allclose(result.lagged.states.r, problem.initial_states.r, rtol=0, atol=1e-6)
    np.testing.assert_allclose(result.newest.states.r, problem.initial_states.r, rtol=0, atol=1e-6)


@kinds
def test_a_keyframe_nothing_ties_to_the_window_gets_a_weak_prior(kind):
    """Keyframe 5 of a 1.5 s run keeps its pose measurement but loses its IMU factor (as a gap in
    the IMU data would leave it): its velocity and biases are unconstrained. Nothing ties it to the
    window, so it gets a weak prior around its initial value in the same update, is listed in
    ``recovered``, and the run goes on (without it GTSAM raised 'Leftover keys after elimination',
    ISAM2 an IndexError it cannot recover from)."""
    data = simulate(profile="gentle", duration=1.5, seed=0, imu_rate=cases.IMU_RATE, pose_rate=cases.POSE_RATE)
    problem = build_problem(data)

    def without_imu_factor(k, made):
        if k != 5:
            return made
        assert made.factors[0] is made.imu.factor and len(made.factors) == 2 and len(made.measurements) == 1
        return replace(made, imu=None, factors=made.factors[1:], rows=made.rows[1:], oldest=made.oldest[1:])

    window = make_window(0.3, kind, problem.gravity)
    _feed(problem, window, change=without_imu_factor)
    assert window.recovered == [5]
    assert np.all(np.isfinite(window.newest_state.r)) and np.all(np.isfinite(window.covariances([window.newest])))


@kinds
def test_factors_older_than_the_lag_are_skipped_with_a_warning(kind):
    """Odometry between keyframes 1 s apart with a lag of 0.3 s: when such a factor becomes
    available its earlier keyframe has been marginalised; it is skipped and counted (with a
    warning) instead of failing. With a 2-s lag the same factors are all used."""
    data = simulate(profile="gentle", duration=2.0, seed=1, imu_rate=cases.IMU_RATE, pose_rate=cases.POSE_RATE,
                    odometry_rate=1.0)
    assert len(data.sensor("odometry").data) == 2
    with pytest.warns(UserWarning, match="2 factors referred to variables older than the lag"):
        short = run_fixed_lag(build_problem(data), 0.3, kind, covariances=False, progress=False)
    assert short.skipped_factors == 2
    assert np.all(np.isfinite(short.newest.states.r))
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        long = run_fixed_lag(build_problem(data), 2.0, kind, covariances=False, progress=False)
    assert long.skipped_factors == 0


@kinds
def test_every_kind_warns_when_measurements_are_further_apart_than_the_lag(gentle, kind):
    """A keyframe that leaves the window before the next measurement keeps its dead-reckoned
    estimate (and GTSAM's batch smoother drifts off besides): poses missing for 2 s with a 0.5-s
    lag are warned of, with the lag that would cover them; a 3-s lag needs no warning."""
    data = cases.dataset(gentle)
    poses = data.sensor("pose").data
    gapped = data.with_sensor("pose", data=poses.subset((poses.t < 1.5) | (poses.t >= 3.5)))
    with pytest.warns(UserWarning, match=rf"fixed-lag \({kind}\): absolute measurements \(fixes, poses, attitudes\) "
                                         r"up to 2.1 s apart, longer than the lag \(0.5 s\).*Choose a lag of at least "
                                         r"2.1 s"):
        run_fixed_lag(build_problem(gapped), 0.5, kind, covariances=False, progress=False)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        run_fixed_lag(build_problem(gapped), 3.0, kind, covariances=False, progress=False)
