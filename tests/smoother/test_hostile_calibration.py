"""Hostile calibration priors: a prior far wider than the linearisation holds (``rotation_sigma = 3``,
past the chart's pi) on a coordinate the data barely observe (a wheel's roll about its own axis).
The sliding window bounds each update's step on a calibration (``MAX_CALIBRATION_STEP``) so that
its linearisation never swings round to the velocity's second minimum at 180 degrees before the
first keyframes leave and freeze it; and an estimate that disagrees with another estimator's
beyond their sigmas is doubtful, saying which sensor and coordinate, whatever the cause."""
from __future__ import annotations

import functools
import warnings
from types import SimpleNamespace

import numpy as np
import pytest

from datasets.simulate import simulate
from datasets.simulated_sensors import SensorSpec
from factors import so3
from factors.calibration import CalibrationPrior
from smoother.diagnosis.calibration_report import DISAGREEMENT_SIGMAS, disagreements
from smoother.fixed_lag.sliding import calibration as wc


def _wheel_rig(seed: int, rotation_sigma: float):
    """10 s of the gentle profile: a speed sensor mounted as written (the truth is no turn) whose
    rotation is estimated with ``rotation_sigma``, and 5 Hz GNSS fixes."""
    data = simulate("gentle", duration=10.0, seed=seed, pose_rate=0,
                    sensors=(SensorSpec("wheels", "velocity", 10.0, 0.05), SensorSpec("gnss", "gnss", 5.0, 0.5)))
    return data.with_sensor("wheels", calibrate=CalibrationPrior(("rotation",), rotation=rotation_sigma))


@functools.cache
def _estimates(seed: int, rotation_sigma: float, bounded: bool = True) -> dict:
    """``{estimator: (turn [deg], sigma [deg])}`` of the wheels' rotation, batch and fixed-lag."""
    from smoother.pipeline import RunOptions, run_estimators

    with warnings.catch_warnings(), pytest.MonkeyPatch.context() as patch:
        warnings.simplefilter("ignore")
        if not bounded:
            patch.setattr(wc, "MAX_CALIBRATION_STEP", np.full_like(wc.MAX_CALIBRATION_STEP, 1e9))
        found = run_estimators(_wheel_rig(seed, rotation_sigma), ["batch", "fixed-lag"], RunOptions(lag_s=2.0))
    return {name: (np.degrees(e.details["calibration_against_prior"]["wheels"]["rotation_change_rad"]),
                   np.degrees(e.details["calibration"]["wheels"]["rotation_sigma_rad"])) for name, e in found.items()}


@pytest.mark.parametrize("seed, rotation_sigma", [(8, 3.0), (0, 3.0), (11, 3.0), (5, 1.0), (8, 1.0)])
def test_a_wide_rotation_prior_leaves_the_window_with_the_truth_and_the_batch(seed, rotation_sigma):
    """Seed 8 at 3 rad was +50 deg +- 7 about x in the window (the batch +12 +- 9, the truth 0):
    now the window's every coordinate lies within 3 of its sigmas of the truth and within 3
    sigmas of the difference of the batch's; so on other seeds and at the range table's widest
    prior (1 rad)."""
    (batch, batch_sigma), (window, window_sigma) = _estimates(seed, rotation_sigma).values()
    assert np.all(np.abs(window) < 3 * window_sigma), (window, window_sigma)
    assert np.all(np.abs(window - batch) < DISAGREEMENT_SIGMAS * np.hypot(window_sigma, batch_sigma)), (window, batch)


def test_without_the_bound_the_window_settles_far_from_the_truth():
    """The mechanism the bound removes, seen: unbounded, the same window ends over 5 of its
    sigmas from the truth (the test would pass without the bound otherwise)."""
    window, sigma = _estimates(8, 3.0, bounded=False)["fixed-lag"]
    assert np.abs(window / sigma).max() > 5.0, (window, sigma)


def test_a_step_past_the_widest_offset_is_shortened_along_its_direction():
    """``WindowCalibration.bounded``: None within the bound; beyond it, the offset on the segment
    from the last update's to the proposed one where the first coordinate reaches the bound
    (whichever sign); at the bound exactly, nothing is shortened."""
    from factors.calibration import Calibration, CalibrationSet

    prior = CalibrationPrior(("time_offset", "rotation"), rotation=3.0)
    calibrations = CalibrationSet(("wheel",), (Calibration.of(),), (prior,), (Calibration.of(),))
    window = wc.WindowCalibration(calibrations, {"wheel": "velocity"})
    widest = window.widest
    np.testing.assert_allclose(widest, wc.MAX_CALIBRATION_STEP[[0, 1, 2, 3]])
    before = np.zeros(4)
    assert window.bounded(before, 0.5 * widest) is None and window.bounded(before, widest) is None
    proposed = np.array([0.0, -2.0, 0.5, 0.0])  # 40 and 10 bounds away in rotation x, y
    got = window.bounded(before, proposed)
    np.testing.assert_allclose(got, proposed * widest[1] / 2.0)
    assert np.all(np.abs(got) <= widest + 1e-15) and np.isclose(abs(got[1]), widest[1])
    before = np.array([0.0, 0.8, 0.0, 0.0]) * widest
    got = window.bounded(before, np.array([0.0, 3.0, 0.0, 0.0]) * widest)
    np.testing.assert_allclose(got, widest * [0, 1, 0, 0])


def _details(**coordinates) -> dict:
    """An estimator's calibration details for sensor ``wheel``: each keyword ``rotation``,
    ``time_offset``, ``lever_arm`` or ``scale`` as ``(value, sigma)`` (a rotation: the turn about
    the IMU frame's axes [rad] and its sigmas)."""
    record, against = {}, {}
    if "rotation" in coordinates:
        turn, sigma = coordinates["rotation"]
        T = np.eye(4)
        T[:3, :3] = so3.exp(turn)
        record.update(T_BS=T.tolist(), rotation_sigma_rad=list(sigma))
        against["rotation_change_rad"] = list(turn)
    if "time_offset" in coordinates:
        record["time_offset_s"], record["time_offset_sigma_s"] = coordinates["time_offset"]
    if "lever_arm" in coordinates:
        record["lever_arm_m"], record["lever_arm_sigma_m"] = map(list, coordinates["lever_arm"])
    if "scale" in coordinates:
        record["scale"], record["scale_sigma"] = coordinates["scale"]
    return {"calibration": {"wheel": record}, "calibration_against_prior": {"wheel": against}}


def test_every_estimator_party_to_a_disagreement_is_named_with_the_sensor_and_coordinate():
    """The hostile run's numbers: fixed-lag +54.3 +- 6.2 deg about x, batch +13 +- 10, EKF
    +6 +- 5.5. The fixed-lag disagrees with both (3.5 and 6.0 sigmas), each of them with it: all
    three are named, each with whom it disagrees, its sensor, axis and values."""
    def turn(x, s):
        return _details(rotation=(np.radians([x, 0.0, 0.0]), np.radians([s, 1.0, 1.0])))

    said = disagreements({"fixed-lag": turn(54.3, 6.2), "batch": turn(13.0, 10.0), "ekf": turn(6.0, 5.5)})
    assert set(said) == {"fixed-lag", "batch", "ekf"}
    assert said["fixed-lag"].startswith("its wheel rotation about x, +54.3 +- 6.2 deg, disagrees with the "
                                        "batch's +13 +- 10 deg and the ekf's +6 +- 5.5 deg"), said
    assert said["batch"].startswith("its wheel rotation about x, +13 +- 10 deg, disagrees with the fixed-lag's "
                                    "+54.3 +- 6.2 deg (3.5 sigmas"), said


def test_two_estimators_that_agree_with_each_other_are_named_when_they_disagree_with_the_third():
    """A rerun of the issue's wheel (turned 57 deg, rotation_sigma 1): the batch +32.3 +- 1 deg
    about x, within 1.5 deg of the truth; the fixed-lag +20.7 +- 0.89 and the EKF +21.7 +- 0.71,
    agreeing with each other and 11-12 deg from the truth. The majority rule named the batch alone
    and left the EKF's 15-sigma error unmarked: agreement is no vote."""
    def turn(x, s):
        return _details(rotation=(np.radians([x, 0.0, 0.0]), np.radians([s, 1.0, 1.0])))

    said = disagreements({"batch": turn(32.33, 1.0), "fixed-lag": turn(20.68, 0.894), "ekf": turn(21.74, 0.713)})
    assert set(said) == {"batch", "fixed-lag", "ekf"}, said
    assert "disagrees with the batch's +32.3 +- 1 deg (8.6 sigmas" in said["ekf"], said


@pytest.mark.parametrize("coordinate, a, b, name", [
    ("time_offset", (0.10, 0.01), (0.02, 0.01), "time offset"),
    ("scale", (1.05, 0.01), (1.00, 0.005), "scale"),
    ("lever_arm", (np.array([0.0, 0.0, 0.5]), np.full(3, 0.01)), (np.zeros(3), np.full(3, 0.05)), "lever arm z"),
    ("rotation", (np.radians([0, 0, 10.0]), np.radians([1.0] * 3)), (np.zeros(3), np.radians([1.0] * 3)),
     "rotation about z"),
])
def test_two_estimators_that_disagree_are_both_named_and_agreement_is_silent(coordinate, a, b, name):
    """Of two, neither can be told right: both named. Values 3 sigmas of their difference
    apart or less: nothing; an unobserved coordinate at its prior in both: nothing."""
    said = disagreements({"batch": _details(**{coordinate: a}), "ekf": _details(**{coordinate: b})})
    assert set(said) == {"batch", "ekf"} and all(f"wheel {name}," in text for text in said.values()), said
    assert disagreements({"batch": _details(**{coordinate: a}), "ekf": _details(**{coordinate: a})}) == {}
    assert disagreements({"batch": _details(**{coordinate: a})}) == {}  # nothing to compare with


def test_a_disagreement_in_a_run_that_found_its_model_wrong_names_that_cause_too():
    apart = {"batch": _details(scale=(1.05, 0.01)), "ekf": _details(scale=(1.00, 0.005))}
    plain, wrong = disagreements(apart), disagreements(apart, model_errors=True)
    assert all(text.endswith("may have settled in a wrong minimum") for text in plain.values()), plain
    assert all(text.endswith("or the model errors this run found pull the estimators apart")
               for text in wrong.values()), wrong


def test_a_rotation_is_compared_on_the_rotation_not_on_its_printed_turn():
    """Two turns of +179 and -179 deg about x are 2 deg apart, not 358: no disagreement at 1 deg
    sigmas."""
    near = [_details(rotation=(np.radians([s * 179.0, 0, 0]), np.radians([1.0] * 3))) for s in (1, -1)]
    assert disagreements({"batch": near[0], "fixed-lag": near[1]}) == {}


def test_a_disagreement_makes_the_estimators_doubtful_in_judged():
    """``pipeline.judged`` takes the check: each estimator party to a disagreement gets
    ``doubtful`` with its message, one that disagrees with none keeps none; an estimator whose
    verdicts are fine is doubtful by it alone."""
    from smoother.pipeline import judged

    def estimate(x, s):
        return SimpleNamespace(details=_details(rotation=(np.radians([x, 0, 0]), np.radians([s, 1, 1]))),
                               calibration=None)

    estimates = {"batch": estimate(13.0, 10.0), "fixed-lag": estimate(54.3, 6.2), "ekf": estimate(33.0, 10.0)}
    judged(estimates, {})
    assert "doubtful" not in estimates["ekf"].details  # 1.4 and 1.8 sigmas from the others
    assert "its wheel rotation about x, +54.3" in estimates["fixed-lag"].details["doubtful"]
    assert "disagrees with the fixed-lag's +54.3" in estimates["batch"].details["doubtful"]
