"""The fixed-lag smoother in a second process beside the other estimators
(smoother/pipeline.py, ``RunOptions.fixed_lag_beside``): the same estimate, its warnings and
failures told in the caller, nothing left running after an interruption."""
from __future__ import annotations

import multiprocessing
import os
import warnings

import numpy as np
import pytest

from datasets.simulate import simulate
from smoother import pipeline
from smoother.pipeline import Estimate, RunOptions, estimate_each, run_estimators

NAMES = ["ekf", "batch", "fixed-lag"]


@pytest.fixture(scope="module")
def data():
    return simulate("gentle", duration=6.0, seed=3)


def test_the_fixed_lag_smoother_beside_the_others_gives_the_same_estimate_and_comes_last(data):
    here = run_estimators(data, NAMES, RunOptions(progress=False))
    order = [name for name, _ in estimate_each(data, NAMES, RunOptions(progress=False, fixed_lag_beside=True))]
    beside = run_estimators(data, NAMES, RunOptions(progress=False, fixed_lag_beside=True))
    assert order == ["ekf", "batch", "fixed-lag"]
    for name in NAMES:
        a, b = here[name].trajectory, beside[name].trajectory
        assert np.array_equal(a.t, b.t) and np.array_equal(a.states.r, b.states.r) and np.array_equal(a.cov, b.cov)


def _warns(dataset, options):
    warnings.warn("the lag is shorter than a gap", UserWarning, stacklevel=1)
    return Estimate("fixed-lag", None, 0.0, {"kind": "stand-in"})


def _raises(dataset, options):
    raise ValueError("the window has no keyframe")


def _dies(dataset, options):
    os._exit(3)


def test_its_warnings_are_issued_in_the_caller(data, monkeypatch):
    monkeypatch.setattr(pipeline, "_fixed_lag", _warns)
    with pytest.warns(UserWarning, match="the lag is shorter than a gap"):
        out = run_estimators(data, ["ekf", "fixed-lag"], RunOptions(progress=False, fixed_lag_beside=True))
    assert out["fixed-lag"].details == {"kind": "stand-in"}


@pytest.mark.parametrize("stand_in, said", [(_raises, "ValueError: the window has no keyframe"),
                                            (_dies, "RuntimeError: its process ended with exit code 3")])
def test_its_failure_is_an_estimate_that_failed_or_raised_as_in_this_process(data, monkeypatch, stand_in, said):
    monkeypatch.setattr(pipeline, "_fixed_lag", stand_in)
    options = RunOptions(progress=False, fixed_lag_beside=True)
    out = dict(estimate_each(data, ["ekf", "fixed-lag"], options, keep_going=True))
    assert out["fixed-lag"].failed == said and out["ekf"].failed is None
    with pytest.raises((ValueError, RuntimeError)):
        run_estimators(data, ["ekf", "fixed-lag"], options)


def test_an_interruption_here_stops_the_second_process(data, monkeypatch):
    def interrupted(dataset, options):
        raise KeyboardInterrupt

    monkeypatch.setattr(pipeline, "_ekf", interrupted)
    with pytest.raises(KeyboardInterrupt):
        run_estimators(data, ["ekf", "fixed-lag"], RunOptions(progress=False, fixed_lag_beside=True))
    assert multiprocessing.active_children() == []


def test_an_interruption_in_the_second_process_is_one_here(data, monkeypatch):
    """An interruption raised in the second process is raised here, as it would be in this
    process, not made a failed estimate."""
    def interrupted(dataset, options):
        raise KeyboardInterrupt

    monkeypatch.setattr(pipeline, "_fixed_lag", interrupted)
    with pytest.raises(KeyboardInterrupt):
        dict(estimate_each(data, ["ekf", "fixed-lag"], RunOptions(progress=False, fixed_lag_beside=True),
                           keep_going=True))
