"""Work after the estimators that grew without bound or could not be stopped: the misfit-cause fit
took 3 s for 100 sensors, 99 s and 3.7 GB for 300 and ran out of memory at 10 000, inside one GTSAM
call that SIGTERM waited for. It now fits at most ``MAX_ANALYSED`` sensors (a linear screen
chooses them, and still finds the one at fault among many), eliminates ``ELIMINATION_CHUNK`` keys
per GTSAM call (Python, and so a signal, gets control between them) and gives the same answer as
one call; the EKF's verdicts are grouped in one pass."""
from __future__ import annotations

import warnings
from dataclasses import replace

import gtsam
import numpy as np
import pytest

from datasets.simulate import simulate
from datasets.simulated_sensors import SensorSpec
from smoother.diagnosis import misfit_causes as mc
from smoother.diagnosis.verdicts import sensor_consistency, verdict
from smoother.ekf.filter import Innovations

KINDS = ("position", "velocity", "gnss")
SIGMAS = {"position": 0.3, "velocity": 0.1, "gnss": 0.5}


@pytest.fixture(scope="module")
def many():
    """Twelve sensors (more than ``MAX_ANALYSED``) at 2 Hz over 20 s, one of them -- ``s1``, a
    speed sensor -- reading 20 % low."""
    from smoother.pipeline import run_estimators, verdicts_by_estimator

    n = mc.MAX_ANALYSED + 4
    data = simulate("gentle", duration=20.0, seed=0, pose_rate=0,
                    sensors=[SensorSpec(f"s{i}", KINDS[i % 3], 2.0, SIGMAS[KINDS[i % 3]]) for i in range(n)])
    wheel = data.sensor("s1").data
    data = data.with_sensor("s1", data=replace(wheel, velocity=0.8 * wheel.velocity))
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        estimates = run_estimators(data, ["batch"])
        consistency = verdicts_by_estimator(data, estimates)
    return data, estimates, consistency


def test_of_many_sensors_at_most_max_analysed_are_fitted_together_and_the_one_at_fault_is_among_them(
        many, monkeypatch):
    data, estimates, consistency = many
    fitted = []
    fit = mc.fit_in_problem

    def spy(problem, sensors, *args, **kwargs):
        fitted.append([s.name for s in sensors])
        return fit(problem, sensors, *args, **kwargs)

    monkeypatch.setattr(mc, "fit_in_problem", spy)
    said = mc.hints(data, estimates, consistency)
    assert len(mc.candidates(data)) > mc.MAX_ANALYSED
    assert len(fitted) == 1 and len(fitted[0]) == mc.MAX_ANALYSED and "s1" in fitted[0], fitted
    assert said["s1"].startswith("scale 0.8") and 'add estimate = ["scale"]' in said["s1"], said


def _problem(many):
    data, estimates, _ = many
    from smoother.model.problem import build_problem

    problem = build_problem(data, start=estimates["batch"].trajectory)
    return problem, mc.candidates(data)[:3]


def test_the_fit_is_eliminated_in_chunks_with_the_answer_of_one_call(many, monkeypatch):
    problem, sensors = _problem(many)
    data = many[0]
    whole = mc.fit_in_problem(problem, sensors, data.imu)
    monkeypatch.setattr(mc, "ELIMINATION_CHUNK", 7)
    chunked = mc.fit_in_problem(problem, sensors, data.imu)
    for name in whole:
        for a, b in zip(whole[name], chunked[name]):
            np.testing.assert_allclose(a.value, b.value, rtol=1e-9, atol=1e-12)
            np.testing.assert_allclose(a.sigma, b.sigma, rtol=1e-9)


def test_a_signal_stops_the_fit_between_two_gtsam_calls(many, monkeypatch):
    """Between two chunks Python runs (here: the next chunk's ordering is made), so a Ctrl-C or a
    SIGTERM raised there stops the fit: the elimination is many short calls, not one long one."""
    problem, sensors = _problem(many)
    data = many[0]
    made = []

    def ordering(*args):
        made.append(1)
        if len(made) == 3:
            raise KeyboardInterrupt
        return gtsam.Ordering(*args)

    ordering.ColamdGaussianFactorGraph = gtsam.Ordering.ColamdGaussianFactorGraph

    class Stopping:
        Ordering = staticmethod(ordering)

        def __getattr__(self, name):
            return getattr(gtsam, name)

    monkeypatch.setattr(mc, "ELIMINATION_CHUNK", 7)
    monkeypatch.setattr(mc, "gtsam", Stopping())
    with pytest.raises(KeyboardInterrupt):
        mc.fit_in_problem(problem, sensors, data.imu)
    assert len(made) == 3


def test_the_ekf_s_verdicts_grouped_in_one_pass_are_those_of_each_sensor_alone():
    """``sensor_consistency`` on 3000 updates of 40 sensors, some rejected by the gate, some
    after a divergence (NaN): per sensor the verdict of its accepted finite updates and its count
    of rejected ones, in the order the sensors first updated."""
    rng = np.random.default_rng(0)
    n = 3000
    names = np.array([f"s{k}" for k in rng.integers(0, 40, n)])
    dim = rng.choice([1, 2, 3, 6], n)
    nis = rng.chisquare(dim).astype(float)
    nis[rng.random(n) < 0.01] = np.nan
    accepted = rng.random(n) > 0.1
    got = sensor_consistency(Innovations(names, np.arange(n, dtype=float), dim, nis, accepted))
    assert list(got) == list(dict.fromkeys(names))
    for name, c in got.items():
        mine = (names == name) & np.isfinite(nis)
        used = mine & accepted
        want = verdict(float(nis[used].sum()), float(dim[used].sum()), int(used.sum()), "nis")
        assert c["rejected"] == int((mine & ~accepted).sum())
        for key, value in want.items():
            assert c[key] == (pytest.approx(value, rel=1e-12) if isinstance(value, (float, list)) else value), key
