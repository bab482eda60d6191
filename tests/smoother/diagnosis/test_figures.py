"""smoother.diagnosis.figures: a value with its sigma, no sigma printed as zero."""
import math

import pytest

from smoother.diagnosis.figures import plus_minus


@pytest.mark.parametrize("value, sigma, kwargs, text", [
    (0.0214, 3e-5, {"unit": " s", "digits": 4}, "+0.021400 s +- 0.000030 s"),
    (0.0214, 0.0003, {"digits": 4}, "+0.02140 +- 0.00030"),
    (0.98990, 0.00034, {}, "+0.98990 +- 0.00034"),
    (1.0, 0.00034, {"signed": False, "digits": 5}, "1.00000 +- 0.00034"),
    (3.003, 0.014, {"digits": 3}, "+3.003 +- 0.014"),
    (12.3, 2.5, {}, "+12.3 +- 2.5"),
    (1.5, 0.0, {}, "+1.500 +- 0.000"),
    (1.5, math.nan, {"digits": 4}, "+1.5000 +- nan"),
])
def test_a_value_shows_its_sigma_s_first_two_digits_and_at_least_the_decimals_asked(value, sigma, kwargs, text):
    assert plus_minus(value, sigma, **kwargs) == text
