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
    Candidate,
    CorrelationFit,
    candidate_grid,
    fit_correlation_times,
    tuning_half,
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
    assert fit.support[0] <= fit.tau <= fit.support[1] and fit.edge is None and fit.inflation >= 1.0
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

    with pytest.raises(InputError, match=r"sensor 'gnss': correlation_time: the batch smoother failed at every time "
                                         r"tried \(white: indeterminant system\)"):
        fit_correlation_times(data, failing, progress=False)


def test_the_record_keeps_every_candidate_and_a_failed_one_says_why():
    tried = (Candidate(None, -5.0), Candidate(4.0, -9.0, converged=False), Candidate(16.0, math.nan, "refused"))
    fit = CorrelationFit("gnss", 4.0, tried, (2.0, 8.0), 1.5, 10, 12, "longest", 3.5)
    assert fit.record() == {"correlation_time_s": 4.0, "support_s": [2.0, 8.0], "inflation": 1.5, "tuned_on": 10,
                            "judged_on": 12, "edge": "longest", "seconds": 3.5, "candidates": [
                                {"correlation_time_s": None, "score": -5.0},
                                {"correlation_time_s": 4.0, "score": -9.0, "converged": False},
                                {"correlation_time_s": 16.0, "score": None, "failed": "refused"}]}
    assert "the longest tried: it may be longer" in fit.line()
