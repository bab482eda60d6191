"""Fixtures of the tests of ``smoother`` (ekf/, model/, batch/, fixed_lag/, online/, evaluation/,
outputs/): session-wide small simulated cases from ``estimator_cases.py`` (computed once, on first
use; shared, so never changed in place)."""
from __future__ import annotations

import os
import sys

import pytest

# ``estimator_cases.py`` sits next to this file; keep it importable under --import-mode=importlib.
_HERE = os.path.dirname(os.path.abspath(__file__))
if _HERE not in sys.path:
    sys.path.insert(0, _HERE)

import estimator_cases as cases  # noqa: E402


@pytest.fixture(scope="session")
def gentle():
    """The gentle case's spec (``estimator_cases.GENTLE``): 4 s, 100 Hz IMU, 10 Hz poses."""
    return cases.GENTLE


@pytest.fixture(scope="session")
def tumbling():
    """The tumbling case's spec (``estimator_cases.TUMBLING``): 3 s, 100 Hz IMU, 10 Hz poses."""
    return cases.TUMBLING


@pytest.fixture(scope="session", params=["gentle", "tumbling"])
def case(request):
    """Both small cases, one after the other."""
    return {"gentle": cases.GENTLE, "tumbling": cases.TUMBLING}[request.param]
