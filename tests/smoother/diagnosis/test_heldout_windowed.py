"""smoother.diagnosis.heldout_windowed: the fixed-lag smoother's prediction of a drifting sensor's
held-out measurements given the used ones' errors, made inside its window -- with a window that
holds the whole run, the batch smoother's prediction (itself checked against the dense inverse);
with a lag of a few seconds, in band where the model is the truth; with a lag shorter than the used
measurements' spacing, still made (given what the window holds); its plain prediction the smoother's
own output's."""
from __future__ import annotations

import numpy as np
import pytest
from drifting_fixes import drifting_run as drifting

from smoother import pipeline
from smoother.diagnosis.heldout import heldout_predictions


def _run(data, lag_s: float, names=("fixed-lag", "batch")):
    return pipeline.run_estimators(data, list(names), pipeline.RunOptions(progress=False, lag_s=lag_s))


def test_a_window_holding_the_whole_run_predicts_as_the_batch_smoother():
    data = drifting(0, 10.0, duration=20.0)
    estimates = _run(data, 100.0)
    window, batch = (estimates[name].heldout["gnss"] for name in ("fixed-lag", "batch"))
    np.testing.assert_array_equal(window.index, batch.index)
    sd = np.sqrt(np.einsum("mii->mi", batch.conditioned.state_part + batch.conditioned.noise))
    assert np.max(np.abs(window.conditioned.e - batch.conditioned.e) / sd) < 0.005
    np.testing.assert_allclose(window.conditioned.state_part, batch.conditioned.state_part, rtol=0,
                               atol=5e-3 * np.abs(batch.conditioned.state_part).max())
    np.testing.assert_allclose(window.conditioned.noise, batch.conditioned.noise, rtol=1e-12)


def test_the_fixed_lag_smoother_s_held_out_verdict_of_drifting_fixes_is_in_band_given_the_used_errors():
    """Four simulated runs (fixes at 5 Hz drifting over 10 s, one in five used) with a lag of 2 s:
    the mean verdict per dof inside one run's band, each given the used errors; its plain prediction
    (no used errors given) far below it."""
    given, plain = [], []
    for seed in range(4):
        data = drifting(seed, 10.0)
        estimates = _run(data, 2.0, ["fixed-lag"])
        v = pipeline.heldout_by_estimator(data, estimates)["fixed-lag"]["gnss"]
        assert v["given_used_errors"]
        given.append(v["per_dof"])
        own = estimates["fixed-lag"].heldout["gnss"]
        S = own.state_part + data.sensor("gnss").heldout.cov[own.index]
        plain.append(np.mean(np.einsum("ma,ma->m", own.e, np.linalg.solve(S, own.e[..., None])[..., 0])) / 3)
        band = v["band"]
    assert band[0] < np.mean(given) < band[1]
    assert max(plain) < 0.6


def test_the_plain_prediction_and_rms_stay_the_smoother_s_own_output_s():
    data = drifting(1, 10.0, duration=20.0)
    estimate = _run(data, 3.0, ["fixed-lag"])["fixed-lag"]
    own = heldout_predictions(data, estimate.trajectory, None, estimate.following)["gnss"]
    np.testing.assert_allclose(estimate.heldout["gnss"].e, own.e, rtol=0, atol=1e-12)
    np.testing.assert_allclose(estimate.heldout["gnss"].state_part, own.state_part, rtol=0, atol=1e-15)


@pytest.mark.filterwarnings("ignore:.*(lag|weighed as independent).*:UserWarning")
def test_a_lag_shorter_than_the_used_fixes_spacing_predicts_in_band_too():
    """Used fixes 1 s apart, a lag of 0.5 s: each held-out fix at a keyframe the window holds when
    the used fix before it leaves is predicted then, given it; the others later, given those the
    window then holds. The mean verdict over four runs inside one run's band."""
    given = []
    for seed in range(4):
        data = drifting(seed, 10.0)
        v = pipeline.heldout_by_estimator(data, _run(data, 0.5, ["fixed-lag"]))["fixed-lag"]["gnss"]
        assert v["given_used_errors"]
        given.append(v["per_dof"])
    assert v["band"][0] < np.mean(given) < v["band"][1]


def test_a_sensor_whose_calibration_the_window_estimates_is_judged_without_the_used_errors_and_says_so():
    from factors.calibration import CalibrationPrior

    data = drifting(3, 10.0, duration=20.0)
    data = data.with_sensor("gnss", calibrate=CalibrationPrior(("lever_arm",)))
    verdict = pipeline.heldout_by_estimator(data, _run(data, 3.0, ["fixed-lag"]))["fixed-lag"]["gnss"]
    assert verdict.get("not_given_used_errors") and not verdict.get("given_used_errors")
