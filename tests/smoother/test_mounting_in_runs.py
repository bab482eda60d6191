"""A rig wrong by a half turn in a run (smoother/pipeline.py with smoother/diagnosis/mounting.py
and noise_honesty.py): wheels whose rig ``T_BS`` is turned by 180 degrees about the vertical make
every estimate doubtful naming the wheels' mounting, with or without the noise estimated (the
wheels' fitted noise is never applied as noise); asked to estimate their rotation, the run starts
it from the data's rotation and the calibration ends near the truth."""
from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from datasets.simulate import simulate
from datasets.simulated_sensors import SensorSpec
from factors import so3
from factors.calibration import CalibrationPrior
from smoother.pipeline import RunOptions, estimate_each, heldout_by_estimator, judged, run_doubts, verdicts_by_estimator

#: The rig's wheels: turned by half a turn about the vertical from the truth (the identity).
TURNED = so3.exp(np.array([0.0, 0.0, np.pi]))


def _rig(seed: int = 0, calibrate=None):
    """60 s of the figure-eight (over 30 s the motion determines too little of the wheels' rotation)
    with 1-Hz fixes and 10-Hz wheels mounted at the IMU, the rig stating
    the wheels turned by :data:`TURNED`."""
    data = simulate("gentle", duration=60.0, seed=seed, imu_rate=100.0, pose_rate=None, position_rate=1.0,
                    position_sigma=0.3, sensors=(SensorSpec("wheels", "velocity", 10.0, 0.05),))
    wheels = data.sensor("wheels")
    T = np.eye(4)
    T[:3, :3] = TURNED
    stated = replace(wheels, data=replace(wheels.data, T_BS=T), calibrate=calibrate)
    return replace(data, sensors=tuple(stated if s.name == "wheels" else s for s in data.sensors))


def _run(data, names=("batch", "ekf"), **options):
    record = {}
    estimates = dict(estimate_each(data, names, RunOptions(progress=False, **options), record=record))
    used = record["dataset"]
    judged(estimates, verdicts_by_estimator(used, estimates), heldout_by_estimator(used, estimates),
           run_doubts(record))
    return estimates, record


@pytest.mark.parametrize("noise", [None, ("imu", "position", "wheels")])
def test_wheels_turned_by_half_a_turn_make_every_estimate_doubtful_naming_their_mounting(noise):
    estimates, record = _run(_rig(), estimate_noise=noise)
    (finding,) = record["mounting"].wrong
    assert finding.sensor == "wheels" and "forward axis (x) on the IMU's +x, the rig on -x" in finding.message
    for est in estimates.values():
        assert "the mounting of wheels is not the rig's" in est.details["doubtful"]
    if noise is not None:  # the wheels' misfit is not fitted away as noise
        fit = record["noise"]
        assert not any(g.applied and g.estimable and g.group.sensor == "wheels" and g.factor != 1.0
                       for g in fit.groups)


def test_asked_to_estimate_its_rotation_the_run_starts_from_the_data_and_ends_near_the_truth():
    estimates, record = _run(_rig(calibrate=CalibrationPrior(("rotation",))))
    started = record["dataset"].sensor("wheels").data.T_BS[:3, :3]
    assert np.degrees(np.linalg.norm(so3.boxminus(started, np.eye(3)))) < 10.0  # the data's, not the rig's
    batch = estimates["batch"].details["calibration"]["wheels"]
    R = np.asarray(batch["T_BS"])[:3, :3]
    error = so3.boxminus(R, np.eye(3))
    sigma = np.asarray(batch["rotation_sigma_rad"])
    assert np.all(np.abs(error) <= 3.0 * sigma + 1e-3), (error, sigma)
