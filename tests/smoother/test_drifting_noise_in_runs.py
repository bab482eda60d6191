"""Residuals alike in time in a run that estimates its noise (smoother/pipeline.py with
smoother/diagnosis/noise_honesty.py and misfit_causes.py): fixes whose error drifts -- a GNSS
receiver's, over seconds -- have their sigma fitted and applied, with the note that the estimate
takes them as independent, and no estimate is doubtful for it; fixes whose rig leaves out the
antenna's lever arm have residuals as alike in time, which the lever arm explains: their fitted
sigma is not applied, and the run names the lever arm. Both hold for fixes that estimate part of
their calibration (a GNSS delay): the parts they do not estimate are the candidates."""
from __future__ import annotations

import warnings
from dataclasses import replace

import numpy as np
import pytest

from datasets.simulate import simulate
from datasets.simulated_sensors import SensorSpec
from factors.calibration import CalibrationPrior
from smoother.pipeline import RunOptions, estimate_each, heldout_by_estimator, judged, run_doubts, verdicts_by_estimator

NOISE = ("imu", "gnss", "wheels")


def _rig(lever_arm=None, drift: float = 0.0, seed: int = 0):
    """60 s of the figure-eight with 5-Hz fixes (the rig states 0.3 m) and 10-Hz wheels; ``drift``
    [m]: an AR(1) error of that size added to the fixes, 0.97 from one fix to the next;
    ``lever_arm``: the antenna's true place, which the rig leaves out (the IMU's origin)."""
    T = np.eye(4)
    if lever_arm is not None:
        T[:3, 3] = lever_arm
    data = simulate("gentle", duration=60.0, seed=seed, imu_rate=100.0, pose_rate=None,
                    sensors=(SensorSpec("gnss", "position", 5.0, 0.3, T), SensorSpec("wheels", "velocity", 10.0, 0.05)))
    gnss = data.sensor("gnss")
    rng = np.random.default_rng(seed + 100)
    e = np.zeros((len(gnss.data.t), 3))
    for k in range(1, len(e)):
        e[k] = 0.97 * e[k - 1] + np.sqrt(1.0 - 0.97**2) * drift * rng.normal(size=3)
    stated = replace(gnss, data=replace(gnss.data, position=gnss.data.position + e, T_BS=np.eye(4)))
    return replace(data, sensors=tuple(stated if s.name == "gnss" else s for s in data.sensors))


def _run(data):
    record = {}
    estimates = dict(estimate_each(data, ("batch",), RunOptions(progress=False, estimate_noise=NOISE), record=record))
    used = record["dataset"]
    judged(estimates, verdicts_by_estimator(used, estimates), heldout_by_estimator(used, estimates),
           run_doubts(record))
    return estimates["batch"], {g.group.name: g for g in record["noise"].groups}


def _estimating(data, parts):
    """``data`` with the fixes estimating the calibration ``parts`` (none: as given)."""
    return data.with_sensor("gnss", calibrate=CalibrationPrior(parts)) if parts else data


@pytest.mark.parametrize("seed, parts", [(0, ()), (1, ()), (0, ("time_offset",)), (1, ("lever_arm",))])
def test_fixes_whose_error_drifts_have_their_sigma_fitted_and_applied(seed, parts):
    batch, groups = _run(_estimating(_rig(drift=1.0, seed=seed), parts))
    for part in ("gnss.horizontal", "gnss.vertical"):
        g = groups[part]
        assert g.correlation > 0.5 and g.applied and g.factor > 2.0, (part, g)
        assert "no calibration explains them" in g.note
    assert "doubtful" not in batch.details or "gnss" not in batch.details["doubtful"], batch.details.get("doubtful")


@pytest.mark.parametrize("parts", [(), ("time_offset",)])
def test_fixes_whose_lever_arm_the_rig_leaves_out_are_named_not_fitted(parts):
    batch, groups = _run(_estimating(_rig(lever_arm=[0.0, 1.5, 0.5]), parts))
    horizontal = groups["gnss.horizontal"]
    assert horizontal.correlation > 0.5 and not horizontal.applied, horizontal
    assert horizontal.note.startswith("not applied: ") and "point at lever arm" in horizontal.note, horizontal.note
    assert "lever arm" in batch.details["doubtful"]


def test_the_estimate_after_a_refused_fit_is_the_lower_cost_of_both_starts():
    """Where a fitted group is refused, the estimate with the noise applied is solved from where the
    fit ended and from the estimate before it, and the one of lower cost is kept: a start the
    optimiser cannot bring back in one iteration (the fit's end, 30 m off) loses, in either order."""
    from smoother.batch.solve import solve_batch
    from smoother.model.problem import build_problem
    from smoother.pipeline import solved_from_each

    data = _rig(drift=0.0)
    good = solve_batch(build_problem(data))
    off = replace(good, trajectory=replace(good.trajectory, states=good.trajectory.states.replace(
        r=good.trajectory.states.r + np.array([30.0, -20.0, 5.0]))))
    options = RunOptions(progress=False, max_iterations=1)
    for starts in ((off, good), (good, off)):
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always")
            _, result, _ = solved_from_each(data, starts, options)
        assert result.error <= solve_batch(build_problem(data, start=good.trajectory), max_iterations=1).error + 1e-9
        np.testing.assert_allclose(result.trajectory.states.r, good.trajectory.states.r, atol=1e-3)
        # both starts ran out of their iteration; only the word of the one kept is passed on
        said = [str(w.message) for w in caught if "without converging" in str(w.message)]
        assert len(said) == (0 if result.converged else 1), said
