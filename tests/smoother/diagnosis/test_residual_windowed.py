"""smoother.diagnosis.residual_windowed: the fixed-lag smoother's in-sample verdict on a drifting
sensor, its innovations judged inside the window -- with a window that holds the whole run, the
batch smoother's verdict; with a lag of a few seconds, in band where the model is the truth and far
above it where the correlation time is wrong (its measurements' own residuals judged as white were
in band there); with a lag shorter than the used measurements' spacing, the ones weighed alone
counted, not judged; a sensor whose calibration the window estimates, not judged so."""
from __future__ import annotations

import numpy as np
import pytest
from drifting_fixes import drifting_run as drifting

from factors.calibration import CalibrationPrior
from smoother import pipeline


def _verdicts(data, lag_s: float, names=("fixed-lag", "batch")) -> dict:
    options = pipeline.RunOptions(progress=False, lag_s=lag_s)
    return pipeline.verdicts_by_estimator(data, pipeline.run_estimators(data, list(names), options), options)


def test_a_window_holding_the_whole_run_judges_as_the_batch_smoother():
    """Each innovation read at the last update, the whole run's solve: the batch's residuals and
    leverages (measured: equal to four digits)."""
    verdicts = _verdicts(drifting(0, 10.0, duration=30.0), 100.0)
    window, batch = verdicts["fixed-lag"]["gnss"], verdicts["batch"]["gnss"]
    assert window["measurements"] == batch["measurements"] and window["weighed_alone"] == 0
    assert window["per_dof"] == pytest.approx(batch["per_dof"], rel=1e-3)
    assert window["dof"] == pytest.approx(batch["dof"], rel=1e-3)


def test_a_few_seconds_lag_judges_drifting_fixes_in_band_and_a_wrong_correlation_time_far_above():
    """Lag 3 s, fixes drifting over 10 s used once a second: three runs' mean verdict in one run's
    band (measured 1.05, 1.04, 1.17); modelled with 2000 s, its innovations weigh differences the
    errors do not have, 198 per dof as the batch's 196 (the measurements' own residuals judged as
    white gave 1.17, ok)."""
    per_dof = []
    for seed in range(3):
        verdict = _verdicts(drifting(seed, 10.0), 3.0, ["fixed-lag"])["fixed-lag"]["gnss"]
        per_dof.append(verdict["per_dof"])
    assert verdict["band"][0] < np.mean(per_dof) < verdict["band"][1], per_dof
    wrong = _verdicts(drifting(0, 2000.0), 3.0, ["fixed-lag"])["fixed-lag"]["gnss"]
    assert wrong["per_dof"] > 50.0


@pytest.mark.filterwarnings("ignore:.*(lag|weighed as independent).*:UserWarning")
def test_fixes_the_window_weighed_alone_are_counted_not_judged():
    """A lag of 0.5 s against used fixes 1 s apart: every pair's earlier keyframe has left when the
    later fix arrives; the first fix alone is judged (its own factor in the model too)."""
    data = drifting(1, 10.0, duration=20.0)
    verdict = _verdicts(data, 0.5, ["fixed-lag"])["fixed-lag"]["gnss"]
    used = len(data.sensor("gnss").data.t)
    assert verdict["measurements"] == 1 and verdict["weighed_alone"] == used - 1


def test_a_drifting_sensor_whose_calibration_the_window_estimates_has_no_white_verdict():
    data = drifting(3, 10.0, duration=20.0).with_sensor("gnss", calibrate=CalibrationPrior(("lever_arm",)))
    assert "gnss" not in _verdicts(data, 3.0, ["fixed-lag"])["fixed-lag"]


@pytest.mark.filterwarnings("ignore:.*(lag|weighed as independent|taken as white).*:UserWarning")
def test_metrics_record_the_drift_model_and_what_the_window_made_of_it(tmp_path):
    """``_run.correlation_times_s``; the sliding window's count of measurements weighed alone, and
    GTSAM's windows naming the sensors whose errors they take as white (not on stderr alone)."""
    import json

    from smoother.outputs import files

    data = drifting(1, 10.0, duration=20.0)
    for kind, lag, expected in (("sliding", 0.5, "weighed_alone"), ("incremental", 3.0, "drift_taken_white")):
        options = pipeline.RunOptions(progress=False, lag_s=lag, fixed_lag_kind=kind)
        estimates = pipeline.run_estimators(data, ["fixed-lag"], options)
        files.write_outputs(tmp_path / kind, data, estimates)
        document = json.loads((tmp_path / kind / "metrics.json").read_text())
        assert document["_run"]["correlation_times_s"] == {"gnss": 10.0}
        assert set(document["fixed-lag"]) & {"weighed_alone", "drift_taken_white"} == {expected}
        assert document["fixed-lag"][expected] == (["gnss"] if kind == "incremental" else
                                                   len(data.sensor("gnss").data.t) - 1)


@pytest.mark.filterwarnings("ignore:.*weighed as independent.*:UserWarning")
def test_fixes_the_batch_s_factors_refuse_leave_the_window_running_unjudged():
    """Two fixes 10 ns apart under a day's correlation time: their errors are one, which the batch's
    factors refuse and the window weighs alone; the window's verdicts, built on the batch's
    factors, are left out with a warning, not the fixed-lag smoother with them."""
    from dataclasses import replace

    from datasets.types import PositionMeasurements, Sensor

    data = drifting(0, 86_400.0, duration=20.0)
    gnss = data.sensor("gnss").data
    t = np.concatenate([gnss.t, gnss.t[5:6] + 1e-8])
    order = np.argsort(t, kind="stable")
    fixes = PositionMeasurements(t[order], np.concatenate([gnss.position, gnss.position[5:6] + 0.1])[order],
                                 np.concatenate([gnss.cov, gnss.cov[5:6]])[order])
    data = replace(data, sensors=(Sensor("gnss", "position", fixes, correlation_time=86_400.0),))
    with pytest.warns(UserWarning, match="its drifting sensors are not judged in its window .*too long"):
        estimates = pipeline.run_estimators(data, ["fixed-lag"], pipeline.RunOptions(progress=False, lag_s=3.0))
    assert estimates["fixed-lag"].details["weighed_alone"] == 1
    assert "gnss" not in pipeline.verdicts_by_estimator(data, estimates, pipeline.RunOptions(lag_s=3.0))["fixed-lag"]
