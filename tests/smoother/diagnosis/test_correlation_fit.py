"""smoother.diagnosis.correlation_fit: a drifting sensor's correlation time fitted to the held-out
measurements in odd gaps between used ones -- found near the truth on simulated drift, white where
the errors are white, the run then judged by the other half alone -- and the ways it refuses."""
from __future__ import annotations

import math

import numpy as np
import pytest
from drifting_fixes import drifting_run

from factors.errors import InputError, SolverError
from smoother.diagnosis.correlation_fit import (
    COARSE_STEP,
    MIN_BLOCKS,
    Candidate,
    CorrelationFit,
    blocks,
    candidate_grid,
    fit_correlation_times,
    least,
    parabola,
    predictive_terms,
    support,
    tuning_half,
    vertex,
)
from smoother.model.timeline import measurement_knots
from smoother.pipeline import RunOptions, estimate_each, heldout_by_estimator


def _fitted(seed: int, true_tau: float):
    """The batch smoother's run on :func:`drifting_run` (60 s, fixes at 5 Hz, one in five used)
    with the fixes' correlation time to fit: ``(fit, dataset as run, batch estimate)``."""
    data = drifting_run(seed, None, hz=5.0, every=5, true_tau=true_tau).with_sensor("gnss", fit_correlation_time=True)
    record: dict = {}
    estimates = dict(estimate_each(data, ["batch"], RunOptions(progress=False), record=record))
    (fit,) = record["correlation_fit"]
    return fit, record["dataset"], estimates["batch"]


def test_the_tuning_half_is_the_held_out_measurements_in_odd_gaps():
    used = np.array([1.0, 2.0, 3.0])
    held = np.array([0.5, 1.2, 1.8, 2.5, 3.5, 4.0])
    assert tuning_half(held, used).tolist() == [False, True, True, False, True, True]
    assert tuning_half(held, used[::-1]).tolist() == [False, True, True, False, True, True]  # any order


def test_the_grid_runs_from_half_the_spacing_to_the_span_within_the_rig_key_s_range():
    grid = candidate_grid(np.arange(301) * 0.2)  # 5 Hz over 60 s
    assert grid[0] == pytest.approx(0.1) and grid[-1] <= 60.0 < grid[-1] * COARSE_STEP
    assert np.allclose(np.diff(np.log(grid)), math.log(COARSE_STEP))
    dense = candidate_grid(np.arange(11) * 1e-4)  # spacing far below the range's 10 ms
    assert dense == [0.01]


def test_drifting_errors_have_their_correlation_time_found_and_the_other_half_judges_the_run():
    """10 s of true correlation time, fitted within its support, which holds the truth, the run then
    modelling it; the held-out set is the judging half, the tuning half's times still keyframes."""
    fit, ran, batch = _fitted(0, 10.0)
    assert 5.0 < fit.tau < 20.0 and fit.support[0] <= 10.0 <= fit.support[1], fit
    assert fit.support[0] <= fit.tau <= fit.support[1] and fit.edge is None
    scores = {c.tau: c.score for c in fit.candidates}
    assert scores[fit.tau] == min(scores.values()) and scores[None] > scores[fit.tau] + 100.0
    gnss = ran.sensor("gnss")
    assert gnss.correlation_time == fit.tau and not gnss.fit_correlation_time
    held = drifting_run(0, None, hz=5.0, every=5).sensor("gnss").heldout
    assert (len(gnss.heldout), len(gnss.tuned)) == (fit.judge, fit.tuned) and fit.tuned + fit.judge == len(held)
    assert not tuning_half(gnss.heldout.t, gnss.data.t).any() and tuning_half(gnss.tuned.t, gnss.data.t).all()
    assert np.isin(gnss.tuned.t, measurement_knots(ran)).all()
    verdict = heldout_by_estimator(ran, {"batch": batch})["batch"]["gnss"]
    assert verdict["measurements"] == fit.judge and verdict["given_used_errors"]
    assert verdict["band"][0] <= verdict["per_dof"] <= verdict["band"][1], verdict
    assert fit.line().startswith(f"correlation time of gnss: {fit.tau:.3g} s (")


def test_white_errors_are_fitted_white():
    fit, ran, _ = _fitted(0, 0.01)
    assert fit.tau is None and ran.sensor("gnss").correlation_time is None, fit
    assert fit.line().startswith("correlation time of gnss: white errors fit best")


def test_too_few_gaps_to_fit_and_to_judge_are_refused_naming_the_sensor():
    data = drifting_run(0, None, duration=6.0, hz=5.0, every=10).with_sensor("gnss", fit_correlation_time=True)
    with pytest.raises(InputError, match=r"sensor 'gnss': correlation_time: fitting it needs held-out measurements in "
                                         r"at least 4 gaps between used ones .* the judging half has them in 1"):
        fit_correlation_times(data, lambda candidate: None)


def test_a_batch_failing_at_every_time_is_one_error_naming_the_sensor_and_why():
    data = drifting_run(0, None, duration=20.0, hz=5.0, every=5).with_sensor("gnss", fit_correlation_time=True)

    def failing(candidate):
        raise SolverError("indeterminant system")

    with pytest.raises(InputError, match=r"sensor 'gnss': correlation_time: no time tried predicted its held-out "
                                         r"measurements \(white: indeterminant system\)"):
        fit_correlation_times(data, failing, progress=False)


def test_the_record_keeps_every_candidate_and_a_failed_one_says_why():
    tried = (Candidate(None, -5.0), Candidate(4.0, -9.0, converged=False), Candidate(16.0, math.nan, "refused"))
    fit = CorrelationFit("gnss", 4.0, tried, (2.0, 8.0), 10, 12, "longest", 3.5)
    assert fit.record() == {"correlation_time_s": 4.0, "support_s": [2.0, 8.0], "tuned_on": 10,
                            "judged_on": 12, "edge": "longest", "rough": False, "seconds": 3.5, "candidates": [
                                {"correlation_time_s": None, "score": -5.0},
                                {"correlation_time_s": 4.0, "score": -9.0, "converged": False},
                                {"correlation_time_s": 16.0, "score": None, "failed": "refused"}]}
    assert "the range's longest: it may be longer" in fit.line() and "NOT SMOOTH" not in fit.line()


def test_the_least_score_wins_white_on_a_tie_and_failed_times_never():
    assert least({None: -1.0, 2.0: -3.0, 8.0: math.nan}) == 2.0
    assert least({None: -3.0, 2.0: -3.0}) is None and least({None: math.nan, 2.0: math.nan}) is None


def test_the_vertex_lies_between_the_best_s_neighbours_or_is_not_tried():
    scores = {None: 10.0, 1.0: 4.0, 4.0: 0.0, 16.0: 4.0}
    assert vertex(scores) == [] and parabola(scores)[2] == (1.0, 16.0)  # symmetric: the vertex is the best, tried
    scores[16.0] = 2.0
    (at,) = vertex(scores)
    assert 4.0 < at < 16.0
    assert vertex({None: 0.0, 1.0: -1.0, 4.0: -5.0}) == []  # the best at the end: no neighbour beyond it


def test_blocks_are_at_least_twice_the_longest_time_and_between_their_bounds():
    times = np.arange(0.0, 100.5, 0.5)
    assert blocks(times, (None, 10.0)).max() + 1 == 5  # 100 s in blocks of 20 s
    assert blocks(times, (0.1, None)).max() + 1 == 20  # at most MAX_BLOCKS
    assert blocks(times, (80.0, 5.0)).max() + 1 == MIN_BLOCKS
    assert np.all(np.diff(blocks(times, (None, 10.0))) >= 0)


def test_the_support_holds_the_times_not_clearly_worse_and_white_where_it_is():
    """Terms over 40 s (four blocks of 10 s): 16 s behind the best by nothing in sum, its
    differences spread over the blocks, is within; 1 s, behind by 1 at every measurement (200, no
    spread), is not; white, 10 behind with a spread of some 50, is within and makes the short end."""
    t = np.arange(0.0, 40.0, 0.2)
    best = np.sin(t)
    half = np.where(t < 20.0, 0.5, -0.5)
    terms = {4.0: (best, t), 16.0: (best + half, t), 1.0: (best + 1.0, t)}
    scores = {tau: float(v.sum()) for tau, (v, _) in terms.items()}
    low, high, rough = support(scores, terms, 4.0)
    assert 1.0 < low <= 4.0 and high >= 16.0 and not rough, (low, high)
    terms[None] = (best + np.where(t < 20.0, 0.5, -0.4), t)
    scores[None] = float(terms[None][0].sum())
    assert support(scores, terms, 4.0)[0] is None


def test_the_predictive_terms_are_in_the_measurement_s_units_for_white_and_drifting_errors():
    """At a correlation time far below the fixes' spacing the drifting model is the white one: its
    terms (whitened, with ``log det R`` added back) equal the white model's to 1e-6 -- with a sigma
    of 2 m, so that ``log det R`` is not zero."""
    from smoother.diagnosis.heldout_correlated import batch_predictions  # noqa: F401 -- the batch's own

    out = {}
    for tau in (None, 0.01):
        data = drifting_run(0, tau, duration=20.0, hz=1.0, every=2, sigma=2.0, true_tau=0.01)
        record: dict = {}
        estimate = dict(estimate_each(data, ["batch"], RunOptions(progress=False), record=record))["batch"]
        out[tau] = predictive_terms(record["dataset"], "gnss", estimate)
    assert np.array_equal(out[None][0], out[0.01][0]) and len(out[None][0]) > 5
    np.testing.assert_allclose(out[0.01][1], out[None][1], atol=1e-6)


def test_a_nearly_flat_score_gives_a_support_within_the_rig_key_s_range_not_an_overflow():
    """Scores that barely curve (a parabola of curvature 1e-9) with differences that spread: the
    sandwich's reach would be exp(1e8); it stays within the correlation time's range."""
    from smoother.diagnosis.correlation_fit import TIME_RANGE

    t = np.arange(0.0, 40.0, 0.2)
    spread = np.where(t < 20.0, 0.5, -0.5)
    terms = {6.4: (spread, t), 25.6: (np.zeros(len(t)), t), 102.4: (-spread, t)}
    scores = {6.4: 1e-9, 25.6: 0.0, 102.4: 1e-9}
    assert support(scores, terms, 25.6) == (TIME_RANGE.low, TIME_RANGE.high, False)


def test_a_time_beyond_the_grid_is_followed_while_the_score_falls():
    """Errors of 1000 s over a 20-s run: the grid ends at the span, and the fit carries on beyond it
    while the score still falls."""
    data = drifting_run(0, None, duration=20.0, hz=5.0, every=5, true_tau=1000.0)
    grid = candidate_grid(np.concatenate([data.sensor("gnss").data.t, data.sensor("gnss").heldout.t]))
    record: dict = {}
    dict(estimate_each(data.with_sensor("gnss", fit_correlation_time=True), ["batch"], RunOptions(progress=False),
                       record=record))
    (fit,) = record["correlation_fit"]
    assert fit.tau > grid[-1] and max(c.tau or 0.0 for c in fit.candidates) >= grid[-1] * COARSE_STEP, fit


def test_held_out_measurements_all_outside_the_imu_span_are_refused_naming_the_sensor():
    from dataclasses import replace

    data = drifting_run(0, None, duration=20.0, hz=5.0, every=5)
    gnss = data.sensor("gnss")
    with pytest.warns(UserWarning, match="76 of 76 heldout measurements lie outside the IMU span"):
        data = data.with_sensor("gnss", heldout=replace(gnss.heldout, t=gnss.heldout.t - 1000.0),
                                fit_correlation_time=True)
    assert data.sensor("gnss").heldout is None
    with pytest.raises(InputError, match="sensor 'gnss': correlation_time: fitting it needs measurements used and "
                                         "held out within the IMU's span; it has none held out"):
        fit_correlation_times(data, lambda candidate: None)


def test_a_time_inside_the_range_that_scores_clearly_worse_makes_the_fit_rough():
    """A score that jumps between two nearby times (the noise fit refusing a group at one and not at
    the other, as on a rig whose wheels and IMU disagree): 5 s lies behind by 100 without spread,
    between 4 s (the best) and 16 s (within) -- the fit says the score is not smooth."""
    t = np.arange(0.0, 40.0, 0.2)
    best = np.sin(t)
    half = np.where(t < 20.0, 0.5, -0.5)
    terms = {1.0: (best + 4.0 * half + 1.0, t), 4.0: (best, t), 5.0: (best + 0.5, t), 16.0: (best + half, t)}
    scores = {tau: float(v.sum()) for tau, (v, _) in terms.items()}
    low, high, rough = support(scores, terms, 4.0)
    assert low < 4.0 < 5.0 < high and rough, (low, high)
    line = CorrelationFit("gnss", 4.0, (), (low, high), 10, 12, rough=rough).line()
    assert "NOT SMOOTH: a time inside that range scores clearly worse" in line
