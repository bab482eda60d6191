"""The chi-square bands, two means per dof apart, and the residuals' lag-one correlation
(smoother/stats.py); the quantiles themselves against SciPy's and the NEES intervals:
``tests/smoother/evaluation/test_metrics.py``."""
from __future__ import annotations

import numpy as np
import pytest
from scipy.stats import chi2

from factors.errors import InputError
from smoother.stats import dof_means_apart, lag_one_correlation, nees_bounds, per_dof_band


@pytest.mark.parametrize("dof", [1, 3, 12.5, 400])
@pytest.mark.parametrize("probability", [0.95, 0.99])
def test_the_per_dof_band_is_the_chi_square_interval_divided_by_the_dof(dof, probability):
    lo, hi = per_dof_band(dof, probability)
    expected = np.array(chi2.interval(probability, dof)) / dof
    np.testing.assert_allclose([lo, hi], expected, rtol=1e-12)


def test_the_band_narrows_about_one_as_the_dof_grow_and_widens_with_the_probability():
    widths = [np.subtract(*per_dof_band(dof, 0.95)[::-1]) for dof in (3, 30, 300, 3000)]
    assert widths == sorted(widths, reverse=True) and widths[-1] < 0.11
    assert all(lo < 1.0 < hi for lo, hi in (per_dof_band(dof, 0.95) for dof in (30, 300, 3000)))
    assert np.subtract(*per_dof_band(30, 0.99)[::-1]) > np.subtract(*per_dof_band(30, 0.95)[::-1])


def test_the_band_of_one_run_is_the_nees_interval_of_one_run_per_dimension():
    lo, hi = nees_bounds(6, 1)
    assert per_dof_band(6, 0.95) == pytest.approx((lo / 6, hi / 6), rel=1e-12)
    with pytest.raises(InputError, match="dof: expected degrees of freedom > 0"):
        per_dof_band(0, 0.95)


def test_the_lag_one_correlation_of_an_ar1_sequence_is_its_coefficient_over_every_axis():
    rng = np.random.default_rng(3)
    for rho in (0.0, 0.5, 0.9, -0.4):
        u = np.zeros((20000, 3))
        u[0] = rng.standard_normal(3)
        for k in range(1, len(u)):
            u[k] = rho * u[k - 1] + np.sqrt(1 - rho**2) * rng.standard_normal(3)
        assert lag_one_correlation(u + 5.0) == pytest.approx(rho, abs=0.02), rho  # the mean taken out


def test_the_lag_one_correlation_of_too_few_or_constant_residuals_is_zero_and_of_four_is_the_sample_s():
    assert lag_one_correlation(np.ones((2, 3))) == 0.0
    assert lag_one_correlation(np.full((10, 2), 4.0)) == 0.0
    # alternating signs: three lagged products of -1 over four squares
    assert lag_one_correlation(np.array([[1.0], [-1.0], [1.0], [-1.0]])) == pytest.approx(-0.75, rel=1e-12)


def test_two_means_per_dof_are_apart_beyond_both_the_ratio_and_the_sigmas():
    # 1 against 3 on 100 dof each: log 3 = 1.10 beyond log 1.5 and 3 sd (0.6): apart, either way
    assert dof_means_apart(1.0, 100, 3.0, 100, 1.5, 3.0) == pytest.approx(np.log(3.0))
    assert dof_means_apart(3.0, 100, 1.0, 100, 1.5, 3.0) == pytest.approx(-np.log(3.0))
    assert dof_means_apart(1.0, 10, 3.0, 10, 1.5, 3.0) == 0.0  # within 3 sd (1.9) on 10 dof each
    assert dof_means_apart(1.0, 1e6, 1.4, 1e6, 1.5, 3.0) == 0.0  # significant, but within the ratio
