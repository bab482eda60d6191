"""The estimators started from a self-initialised dataset (:func:`datasets.initialise.self_initialised`:
no ground truth) reach the accuracy of a start from the truth (how the start is found:
``tests/datasets/test_initialise.py``)."""
import numpy as np
import pytest
from initialisation_rig import CAMERA, GNSS, WHEEL

from datasets.initialise import self_initialised
from datasets.simulate import simulate
from factors import so3
from smoother.pipeline import run_estimators


def _final_error(data, truth) -> dict:
    """RMS position error over the last 5 s of each estimator's trajectory."""
    out = {}
    for name, est in run_estimators(data, ["batch", "ekf"]).items():
        tr = est.trajectory
        last = tr.t > tr.t[-1] - 5
        ref = np.stack([np.interp(tr.t[last], truth.t, truth.position[:, a]) for a in range(3)], axis=-1)
        out[name] = float(np.sqrt(np.mean(np.sum((tr.position[last] - ref) ** 2, axis=1))))
    return out


@pytest.mark.parametrize("profile, specs", [("static", [CAMERA]), ("gentle", [GNSS, WHEEL])],
                         ids=["from rest, heading from a rotated camera", "moving, heading from the GNSS course"])
def test_self_initialisation_reaches_the_accuracy_of_a_start_from_truth(profile, specs):
    """Batch / EKF error over the last 5 s is that of a start from truth (initial attitude from
    the course 5.9 deg off, inside its 10 deg sigma)."""
    data = simulate(profile, duration=20, seed=2, pose_rate=None, sensors=specs)
    started = self_initialised(data)
    k = np.searchsorted(data.truth.t, started.t0)
    error = np.linalg.norm(so3.boxminus(started.initial.C, data.truth.C[k]))
    assert error < 3 * np.sqrt(started.initial_cov[6:9, 6:9].diagonal().max())  # within its own 3 sigma
    from_truth, own = _final_error(data, data.truth), _final_error(started, data.truth)
    for name in from_truth:
        assert own[name] <= 1.2 * from_truth[name] + 0.005, (name, own[name], from_truth[name])
