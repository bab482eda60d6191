"""The doubt mark (smoother.pipeline.judged): verdicts far above and far below their band, a
held-out verdict standing for the residuals' where it exists, and a run's own doubts."""
from __future__ import annotations

from smoother.diagnosis.verdicts import verdict
from smoother.pipeline import Estimate, judged


def _estimate(name="batch"):
    return Estimate(name, None, 0.0, {})


def _verdict(per_dof, dof=300.0, statistic="residual", **extra):
    return {**verdict(per_dof * dof, dof, int(dof / 3), statistic), **extra}


def test_a_verdict_in_band_leaves_the_estimate_trusted():
    est = _estimate()
    judged({"batch": est}, {"batch": {"gps": _verdict(1.02)}})
    assert "doubtful" not in est.details


def test_a_verdict_far_below_its_band_says_the_sigma_is_overstated():
    est = _estimate()
    judged({"batch": est}, {"batch": {"gps": _verdict(0.2)}})
    assert "far below their band: its sigma is overstated" in est.details["doubtful"]


def test_held_out_predictions_below_the_state_s_own_uncertainty_name_both_causes_and_no_factor():
    est = _estimate()
    held = {"batch": {"gps": _verdict(0.2, statistic="heldout", state_share=0.9, sigma_factor=None)}}
    judged({"batch": est}, {"batch": {"gps": _verdict(1.0)}}, held)
    assert "below even the state's own uncertainty there" in est.details["doubtful"]
    assert "a state the data do not fix" in est.details["doubtful"]
    assert "sigma is overstated" not in est.details["doubtful"]
    assert est.details["sensors"]["gps"]["heldout_per_dof"] == held["batch"]["gps"]["per_dof"]


def test_held_out_predictions_far_below_say_by_how_much_the_sigma_is_overstated():
    """A state's share above half does not excuse the sigma when the errors say a smaller one fits."""
    est = _estimate()
    held = {"batch": {"gps": _verdict(0.2, statistic="heldout", state_share=0.63, sigma_factor=0.19)}}
    judged({"batch": est}, {"batch": {"gps": _verdict(1.0)}}, held)
    assert "its sigma is overstated (by up to 5.3x: they are 1 per dof at 0.19 times it" in est.details["doubtful"]
    assert est.details["sensors"]["gps"]["heldout_sigma_factor"] == 0.19


def test_a_held_out_verdict_stands_for_the_residuals_where_it_exists():
    """Residuals in band by a fitted noise, held-out predictions far above it: doubtful."""
    est = _estimate()
    judged({"batch": est}, {"batch": {"gps": _verdict(1.0)}},
           {"batch": {"gps": _verdict(6.0, statistic="heldout", state_share=0.2)}})
    assert "gps held out" in est.details["doubtful"]


def test_a_run_s_own_doubts_mark_every_estimate():
    estimates = {"batch": _estimate(), "ekf": _estimate("ekf")}
    judged(estimates, {}, {}, ["the mounting of wheels is not the rig's (...)"])
    assert all("the mounting of wheels" in e.details["doubtful"] for e in estimates.values())


def test_errors_far_below_whose_shrunk_noise_was_refused_are_not_blamed_on_the_sigma_alone():
    """An AHRS filtered from the IMU's own gyro fits the estimate far better than its sigma says; the
    noise fit refused to shrink it, so the doubt names both readings and neither covariance direction."""
    est = _estimate()
    judged({"batch": est}, {"batch": {"ahrs": _verdict(0.01)}}, follow_imu={"ahrs": "the noise fit refused to shrink "
                                                                                   "ahrs.tilt"})
    doubt = est.details["doubtful"]
    assert "its sigma is overstated or its errors follow the IMU's (the noise fit refused to shrink ahrs.tilt)" in doubt
    assert "may be too large or too small" in doubt
    assert "so the estimate's covariances are too large" not in doubt


def test_held_out_attitudes_far_below_from_the_imu_s_own_messages_name_that_beside_the_sigma():
    """The Jackal's AHRS: its attitudes come in the IMU's own messages, and held out they are
    predicted 10x better than its sigma says -- not a sigma to shrink by that much alone."""
    est = _estimate()
    held = {"batch": {"ahrs": _verdict(0.11, statistic="heldout", state_share=0.3, sigma_factor=0.075)}}
    judged({"batch": est}, {"batch": {"ahrs": _verdict(1.0)}}, held,
           follow_imu={"ahrs": "it reads the IMU's own messages, bag:run.bag, topic /imu/data"})
    doubt = est.details["doubtful"]
    assert ("ahrs's held-out predictions are 0.11 per dof (expected 0.85-1.2), far below their band: its sigma is "
            "overstated or its errors follow the IMU's (it reads the IMU's own messages, bag:run.bag, topic "
            "/imu/data), so the estimate's covariances may be too large or too small") in doubt, doubt
    assert "by up to" not in doubt


def test_held_out_predictions_below_the_state_s_uncertainty_name_the_imu_s_messages_as_a_cause_too():
    est = _estimate()
    held = {"batch": {"ahrs": _verdict(0.1, statistic="heldout", state_share=0.9, sigma_factor=None)}}
    judged({"batch": est}, {"batch": {"ahrs": _verdict(1.0)}}, held,
           follow_imu={"ahrs": "it reads the IMU's own messages"})
    assert "a state the data do not fix (a heading, a bias), or errors that follow the IMU's (it reads the IMU's " \
           "own messages)" in est.details["doubtful"]
