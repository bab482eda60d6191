"""Held-out verdicts (smoother/diagnosis/heldout.py): measurements the fit did not use, predicted
by an estimate through its covariance and the sensor's."""
from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from datasets.simulate import simulate
from smoother.batch.solve import solve_batch
from smoother.diagnosis.heldout import MIN_GAPS, effective_dof, heldout_consistency
from smoother.diagnosis.verdicts import verdict
from smoother.ekf.filter import run_ekf
from smoother.model.between import Following
from smoother.model.covariances import joint_blocks
from smoother.model.problem import build_problem
from smoother.stats import per_dof_band


def _held_out(seed: int, every: int = 3, sigma_scale: float = 1.0):
    """20 s of the figure-eight with 5-Hz positions, every ``every``-th used, the rest held out;
    the sigma the data state ``sigma_scale`` times the truth's."""
    data = simulate("gentle", duration=20.0, seed=seed, imu_rate=100.0, pose_rate=None, position_rate=5.0,
                    position_sigma=0.2)
    s = data.sensor("position")
    used = np.arange(len(s.data.t)) % every == 0
    stated = s.data.cov * sigma_scale**2
    take = lambda m: replace(s.data, t=s.data.t[m], position=s.data.position[m], cov=stated[m])  # noqa: E731
    return replace(data, sensors=(replace(s, data=take(used), heldout=take(~used)),))


@pytest.fixture(scope="module")
def seeds():
    out = []
    for seed in range(20):
        data = _held_out(seed)
        batch = solve_batch(build_problem(data)).trajectory
        out.append((heldout_consistency(data, batch)["position"], heldout_consistency(data, run_ekf(data).trajectory)
                    ["position"]))
    return out


def _held_out_between_keyframes(seed: int):
    """20 s of the figure-eight with 50-Hz positions, every other one used: the used ones come
    faster than the 10-Hz keyframe grid, the held-out ones lie between its keyframes."""
    data = simulate("gentle", duration=20.0, seed=seed, imu_rate=100.0, pose_rate=None, position_rate=50.0,
                    position_sigma=0.05)
    s = data.sensor("position")
    used = np.arange(len(s.data.t)) % 2 == 0
    return replace(data, sensors=(replace(s, data=s.data.subset(used), heldout=s.data.subset(~used)),))


def test_held_out_measurements_between_keyframes_are_predicted_there_and_lie_in_their_band_over_10_seeds():
    """Held-out times are no keyframes: the 25 held-out positions a second sit between the 10-Hz
    keyframes, the batch's state there bridged between the keyframes on either side, the EKF's
    carried from the one before (``smoother.model.between``, as a window without joint
    covariances has it) or its own prediction in its loop, and over 10 seeds the errors of each
    are chi-square: their mean per dof in its band, as where every held-out time is a state. Read
    at the keyframe before, without the IMU's steps, they would not be."""
    from smoother.model.timeline import keyframe_times

    batch, ekf, own, stale = [], [], [], []
    for seed in range(10):
        data = _held_out_between_keyframes(seed)
        times = keyframe_times(data)
        assert len(times) == len(keyframe_times(replace(data, sensors=(replace(data.sensors[0], heldout=None),))))
        assert not np.isin(data.sensor("position").heldout.t, times).all()
        result = solve_batch(build_problem(data))
        trajectory, n = result.trajectory, len(result.trajectory.t)
        following = Following.of_batch(trajectory, joint_blocks(result.joint, np.arange(n - 1), np.arange(1, n)))
        batch.append(heldout_consistency(data, trajectory, following=following)["position"])
        filtered = run_ekf(data, kept_at=times)
        ekf.append(heldout_consistency(data, filtered.trajectory)["position"])
        own.append(heldout_consistency(data, filtered.trajectory, predictions=filtered.heldout)["position"])
        assert own[-1]["per_dof"] != ekf[-1]["per_dof"]
        held = data.sensor("position").heldout
        before = np.searchsorted(trajectory.t, held.t, side="right") - 1
        last = np.sort(len(before) - 1 - np.unique(before[::-1], return_index=True)[1])  # the last in each interval
        moved = replace(held.subset(last), t=trajectory.t[before[last]])  # the keyframe's own state, not carried
        stale.append(heldout_consistency(replace(data, sensors=(replace(data.sensors[0], heldout=moved),)),
                                         trajectory)["position"])
    for records in (batch, ekf, own):
        dof = sum(r["dof"] for r in records)
        lo, hi = per_dof_band(dof, 0.99)
        assert lo <= sum(r["per_dof"] * r["dof"] for r in records) / dof <= hi, [r["per_dof"] for r in records]
    assert sum(r["per_dof"] for r in stale) / len(stale) > 1.5


@pytest.mark.parametrize("estimator", [0, 1], ids=["batch", "ekf"])
def test_the_held_out_errors_per_dof_lie_in_their_band_over_20_seeds(seeds, estimator):
    records = [pair[estimator] for pair in seeds]
    dof = sum(r["dof"] for r in records)
    mean = sum(r["per_dof"] * r["dof"] for r in records) / dof
    lo, hi = per_dof_band(dof, 0.99)
    assert lo <= mean <= hi, (mean, lo, hi)
    assert all(r["statistic"] == "heldout" and r["measurements"] > 0 for r in records)


def test_white_errors_are_not_called_correlated_over_20_seeds(seeds):
    """The held-out errors near the used measurements and far from them agree (``near_far``) where
    the sensor's noise is white: no seed's batch or EKF verdict calls them correlated."""
    flagged = [(seed, k) for seed, pair in enumerate(seeds) for k, r in enumerate(pair) if r.get("correlated")]
    assert not flagged, flagged
    assert all(len(r["near_far"]) == 2 for pair in seeds for r in pair)


def test_errors_that_drift_are_called_correlated_and_printed_so():
    """Fixes at 10 Hz with an AR(1) error 0.8 from one fix to the next (a drift over half a
    second), one in 20 used, and an IMU loose enough that the estimate follows the used fixes (its
    white noise 300 times the simulated one's): the held-out fixes next to a used one share its
    error and lie far below those further off; the verdict says the errors are correlated in time
    instead of naming a sigma."""
    from drifting_fixes import fixes_with_noise

    from smoother.diagnosis.verdicts import shown

    data, _ = fixes_with_noise(0.8, n=600, every=20)
    data = replace(data, noise=replace(data.noise, acc=300.0 * data.noise.acc, gyro=300.0 * data.noise.gyro))
    record = heldout_consistency(data, solve_batch(build_problem(data)).trajectory)["gps"]
    near, far = record["near_far"]
    assert record["correlated"] and near < far / 1.5, record
    assert shown(record).endswith(f"{near:.2g} near the used measurements, {far:.2g} far from them -- the sensor's "
                                  "errors are correlated in time, which no white sigma fits (a correlation_time "
                                  "models them)")


def test_a_sigma_stated_too_large_puts_the_held_out_errors_below_their_band_with_the_sensor_s_share():
    data = _held_out(0, sigma_scale=3.0)
    record = heldout_consistency(data, solve_batch(build_problem(data)).trajectory)["position"]
    assert record["per_dof"] < record["band"][0]
    assert record["state_share"] < 0.5  # the sensor's own covariance dominates: its sigma is the cause
    # the held-out errors say by how much: with the estimate's covariance held, which the smaller
    # sigma would shrink too, at or beyond the truth's 1/3 (here 0.22)
    assert 0.1 < record["sigma_factor"] < 1.1 / 3.0


@pytest.mark.parametrize("k", [0.1, 1.0, 4.0])
def test_the_sigma_factor_recovers_the_factor_the_errors_were_drawn_with(k):
    from smoother.diagnosis.heldout import sigma_factor

    rng = np.random.default_rng(int(10 * k))
    A = rng.normal(size=(4000, 3, 3))
    state_part = 0.01 * A @ np.swapaxes(A, 1, 2)
    R = np.broadcast_to(np.diag([0.04, 0.04, 0.09]), (4000, 3, 3))
    L = np.linalg.cholesky(state_part + k**2 * R)
    e = (L @ rng.normal(size=(4000, 3, 1)))[..., 0]
    assert abs(sigma_factor(e, state_part, R) / k - 1.0) < 0.1


def test_errors_below_the_state_s_own_covariance_have_no_sigma_factor():
    """A state the data do not fix: the errors smaller than its covariance alone says, which no
    sigma, however small, explains."""
    from smoother.diagnosis.heldout import sigma_factor

    rng = np.random.default_rng(1)
    state_part = np.broadcast_to(np.eye(3), (500, 3, 3))
    e = 0.3 * rng.normal(size=(500, 3))
    assert sigma_factor(e, state_part, 0.01 * state_part) is None


def test_without_covariances_or_held_out_measurements_there_is_no_verdict():
    data = _held_out(0)
    trajectory = solve_batch(build_problem(data), covariances=False).trajectory
    assert heldout_consistency(data, trajectory) == {}
    s = data.sensor("position")
    nothing_held = replace(data, sensors=(replace(s, heldout=None),))
    assert heldout_consistency(nothing_held, solve_batch(build_problem(nothing_held)).trajectory) == {}


def test_the_printed_line_shows_the_held_out_predictions_beside_the_sensor_s_own_verdict():
    from smoother.diagnosis.verdicts import consistency_lines, verdict, with_heldout

    own = {"gps": verdict(13.2, 12.3, 46, "residual")}
    held = {"gps": {**verdict(775.0, 1266.0, 422, "heldout"), "state_share": 0.63}}
    [line] = consistency_lines({"batch": with_heldout(own, held)})
    assert line.startswith("sensor gps (46 measurements), per dof: batch residuals 1.07 (")
    assert line.endswith("ok, held-out predictions (422) 0.612 (0.92-1.1) OUT OF BAND")
    [alone] = consistency_lines({"batch": with_heldout({}, held)})  # judged on held-out measurements alone
    assert "batch held-out predictions 0.612" in alone and alone.count("held-out") == 1


def test_a_delayed_sensor_s_held_out_fixes_are_predicted_at_its_stamp_plus_the_estimated_offset():
    """Positions stamped 0.2 s late, the estimate's calibration has the offset: each held-out fix is
    predicted at its stamp plus the offset, exactly on the truth's antenna there (to round-off:
    no first-order extrapolation through the IMU reading, which leaves a centimetre at this delay
    and speed), and the metrics' held-out RMS reads the same predictions."""
    from factors.calibration import CalibrationPrior, CalibrationSet
    from smoother.diagnosis.heldout import heldout_predictions
    from smoother.evaluation.scoring import rms_distance, score

    data = _held_out(0)
    s = data.sensor("position")

    def late(m):  # the true positions, stamped 0.2 s after their time
        return replace(m, t=m.t + 0.2, position=data.truth.position[np.searchsorted(data.truth.t, m.t)])

    with pytest.warns(UserWarning, match="outside the IMU span"):  # the last, stamped after the data end
        data = replace(data, sensors=(replace(s, data=late(s.data), heldout=late(s.heldout)),))
    truth = replace(data.truth, cov=None)
    found = CalibrationSet.given(["position"], [None], [CalibrationPrior(("time_offset",))])
    found = replace(found, values=(replace(found.values[0], time_offset=-0.2),))
    predicted = heldout_predictions(data, truth, found, covariances=False)["position"]
    assert predicted.state_part is None and len(predicted.index) == len(data.sensor("position").heldout.t)
    np.testing.assert_allclose(predicted.e, 0.0, atol=1e-9)
    assert score(data, truth, found)["gps_heldout_rmse_m"] == rms_distance(predicted.e)
    at_stamps = heldout_predictions(data, truth, None, covariances=False)["position"]
    assert rms_distance(at_stamps.e) > 0.1  # the offset matters: 0.2 m at these speeds


def test_a_sensor_that_holds_every_measurement_out_is_judged_and_scored_by_its_predictions():
    """A second position sensor, none of its fixes used (it only checks the estimate): its held-out
    fixes have a verdict, in band on the truth-consistent data, without the near/far split (no used
    measurement to be near), and the metrics' held-out RMS counts them."""
    from smoother.evaluation.scoring import rms_distance, score

    data = _held_out(0)
    s = data.sensor("position")
    checking = replace(s, name="check", data=None, heldout=s.heldout)
    data = replace(data, sensors=(replace(s, heldout=None), checking))
    batch = solve_batch(build_problem(data))
    following = Following.of_batch(batch.trajectory, joint_blocks(batch.joint, np.arange(len(batch.trajectory.t) - 1),
                                                                  np.arange(1, len(batch.trajectory.t))))
    verdicts = heldout_consistency(data, batch.trajectory, following=following)
    assert set(verdicts) == {"check"} and "near_far" not in verdicts["check"]
    low, high = verdicts["check"]["band"]
    assert low <= verdicts["check"]["per_dof"] <= high, verdicts["check"]
    from smoother.diagnosis.heldout import heldout_predictions

    e = heldout_predictions(data, batch.trajectory, following=following, covariances=False)["check"].e
    assert len(e) == len(s.heldout.t) and score(data, batch.trajectory, following=following)[
        "gps_heldout_rmse_m"] == rms_distance(e)


def test_the_band_s_degrees_of_freedom_follow_how_alike_the_errors_are_within_the_gaps():
    """Held-out errors independent of each other keep nearly all their degrees of freedom; errors
    alike within each gap between used measurements (one dead reckoning each) count as
    ``d (sum n)^2 / sum n^2`` -- once per gap and dimension where the gaps are equal, fewer where one
    gap (an outage) holds most of them; with fewer gaps than :data:`MIN_GAPS`, that conservative
    count itself. Over 2000 draws each, a band on it holds the verdict with about its probability
    (measured 0.96, 0.93, 0.86 with the outage, 0.95 with few gaps; 0.20 with the outage with each
    gap's deviation taken from the mean of all, which that gap dominates)."""
    rng = np.random.default_rng(3)
    d = 3

    def coverage(sizes, alike):
        gap = np.repeat(np.arange(len(sizes)), sizes)
        held = []
        for _ in range(2000):
            nis = rng.chisquare(d, len(sizes))[gap] if alike else rng.chisquare(d, len(gap))
            held.append(verdict(float(nis.sum()), float(d * len(nis)), len(nis), "heldout",
                                band_dof=effective_dof(nis, d, gap))["ok"])
        return np.mean(held)

    assert coverage([9] * 46, False) > 0.92 and coverage([9] * 46, True) > 0.9
    assert coverage([300] + [5] * 20, True) > 0.8
    assert coverage([60] * (MIN_GAPS - 1), True) > 0.92
    gap = np.repeat(np.arange(MIN_GAPS - 1), 60)
    assert effective_dof(rng.chisquare(d, len(gap)), d, gap) == pytest.approx(d * (MIN_GAPS - 1))
