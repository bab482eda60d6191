"""Robust kernels on the factors (smoother/model/robust.py): a spec's threshold given or its
dimension's default, GTSAM's mEstimator of each kernel, the noise models wrapped in one. The
default thresholds and the kernels at work in a solve: ``tests/smoother/batch/test_solve.py``."""
from __future__ import annotations

import gtsam
import numpy as np
import pytest

from datasets.robust import ROBUST_KERNEL_NAMES
from smoother.model.robust import ROBUST_KERNELS, default_threshold, noise_model, robust_estimator, robust_threshold


def test_every_kernel_name_has_its_estimator_and_a_default_threshold_for_every_dimension():
    assert set(ROBUST_KERNELS) == set(ROBUST_KERNEL_NAMES)
    for name in ROBUST_KERNEL_NAMES:
        thresholds = [default_threshold(name, dim) for dim in (1, 3, 6, 15)]
        assert thresholds == sorted(thresholds) and thresholds[0] > 1.0, name


@pytest.mark.parametrize("name", ROBUST_KERNEL_NAMES)
def test_a_threshold_given_is_the_one_used_and_none_takes_the_dimension_s_default(name):
    assert robust_threshold((name, 0.7), 6) == 0.7
    assert robust_threshold((name, None), 6) == default_threshold(name, 6)
    assert robust_estimator(None, 6) is None


def test_the_huber_estimator_keeps_full_weight_inside_its_threshold_and_k_over_the_error_beyond():
    k = default_threshold("huber", 6)
    huber = robust_estimator(("huber", None), 6)
    assert huber.weight(0.9 * k) == 1.0 and huber.weight(10.0) == pytest.approx(k / 10.0, rel=1e-12)
    assert robust_estimator(("cauchy", 2.0), 6).weight(2.0) == pytest.approx(0.5, rel=1e-12)  # 1 / (1 + (e/k)^2)
    assert robust_estimator(("tukey", 2.0), 6).weight(2.5) == 0.0  # rejected beyond its threshold


def test_the_noise_model_is_the_covariance_s_wrapped_in_the_kernel_when_one_is_given():
    cov = np.diag([4.0, 1.0, 0.25])
    plain = noise_model(cov)
    assert not isinstance(plain, gtsam.noiseModel.Robust)
    np.testing.assert_allclose(plain.whiten(np.array([2.0, 1.0, 0.5])), np.ones(3), rtol=1e-12)
    robust = noise_model(cov, ("huber", 1.5))
    assert isinstance(robust, gtsam.noiseModel.Robust)
    np.testing.assert_allclose(robust.noise().whiten(np.array([2.0, 1.0, 0.5])), np.ones(3), rtol=1e-12)
    assert robust.robust().weight(3.0) == pytest.approx(0.5, rel=1e-12)
