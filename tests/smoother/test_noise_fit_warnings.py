"""What a run with a noise fit says of its batch solves (smoother/pipeline.py): the solves on the
way (with noise the fit may yet refuse, from starts left behind) are intermediate, and an optimiser
that stopped short there is not said; the estimate the run returns is, where it stopped short."""
from __future__ import annotations

import warnings
from dataclasses import replace

import pytest

from datasets.simulate import simulate
from smoother.batch import variance_components
from smoother.batch.solve import solve_batch, warn_not_converged
from smoother.errors import NotConverged
from smoother.pipeline import RunOptions, run_estimators


def _stated_wrong():
    """12 s of the gentle profile: 5-Hz fixes whose sigma the rig states 3x too small, so that the
    fit applies a factor and solves the batch again with it."""
    data = simulate("gentle", duration=12.0, seed=3, imu_rate=100.0, pose_rate=None, gnss_rate=None,
                    position_rate=5.0, position_sigma=0.3)
    return replace(data, sensors=tuple(replace(s, data=replace(s.data, cov=s.data.cov / 9.0)) for s in data.sensors))


@pytest.mark.parametrize("stops_short", [False, True])
def test_a_fit_s_own_solve_that_stopped_short_is_said_only_of_the_estimate_returned(monkeypatch, stops_short):
    """The fit's solve with its factors applied is made to say it stopped short (as a solve with a
    factor the run then refuses can, on a real rig), its result unchanged. Where that result is the
    run's estimate and it converged, nothing is said; where it did not, it is said once."""
    def solve(*args, **kwargs):
        result = solve_batch(*args, **kwargs)
        warn_not_converged("lm", 100, 5.1e-6)
        return replace(result, converged=not stops_short, iterations=100, decrease=5.1e-6)

    monkeypatch.setattr(variance_components, "solve_batch", solve)
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        batch = run_estimators(_stated_wrong(), ["batch"], RunOptions(progress=False, estimate_noise=("position",)))
    assert any(g.applied for g in batch["batch"].noise.groups), batch["batch"].noise.record()
    said = [str(w.message) for w in caught if issubclass(w.category, NotConverged)]
    assert len(said) == int(stops_short), said
    assert batch["batch"].details["converged"] is not stops_short
