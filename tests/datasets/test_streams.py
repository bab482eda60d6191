"""Raw-stream types: unknown covariances as NaN rows, fixes without a position, exact stamps."""
from __future__ import annotations

from fractions import Fraction

import numpy as np
import pytest

from datasets.streams import FixStream, PoseStream, TwistStream, known_covariances, seconds


def test_known_covariances_marks_zero_and_indefinite_matrices_unknown():
    good = np.diag([1.0, 2.0, 3.0])
    indefinite = np.diag([1.0, -1.0, 1.0])
    asymmetric = good + np.triu(np.ones((3, 3)), 1)
    cov = known_covariances(np.array([good, np.zeros((3, 3)), indefinite, asymmetric, np.full((3, 3), np.nan)]))
    assert np.array_equal(cov[0], good) and np.isnan(cov[1:]).all()
    assert known_covariances(np.zeros((4, 6, 6))) is None


def test_seconds_of_nanosecond_stamps():
    t_ns = np.array([1_700_000_000_123_456_789, 1_700_000_000_123_457_789])
    exact = [float(Fraction(int(s), 10**9)) for s in t_ns]  # correctly rounded
    assert np.abs(seconds(t_ns) - exact).max() <= np.spacing(1.7e9)


def test_fixes_may_hold_nan_only_without_a_fix():
    FixStream([0.0, 1.0], [np.nan, 47.0], [np.nan, 8.0], [np.nan, 400.0], np.array([-1, 0]))
    with pytest.raises(ValueError, match="FixStream.latitude: non-finite value at row 1, a fix of status 0"):
        FixStream([0.0, 1.0], [47.0, np.nan], [8.0, 8.0], [400.0, 400.0], np.array([0, 0]))
    with pytest.raises(ValueError, match="FixStream.status: expected 2 integers"):
        FixStream([0.0, 1.0], [47.0, 47.0], [8.0, 8.0], [400.0, 400.0], np.array([0.0, 0.0]))


def test_covariance_rows_are_valid_or_all_nan():
    C = np.broadcast_to(np.eye(3), (2, 3, 3))
    cov = np.array([np.eye(6), np.full((6, 6), np.nan)])
    pose = PoseStream([0.0, 1.0], np.zeros((2, 3)), C, cov, np.array([0, 10**9]))
    assert len(pose) == 2 and pose.subset(np.array([False, True])).cov is None  # no row known: None
    assert PoseStream([0.0, 1.0], np.zeros((2, 3)), C, np.full((2, 6, 6), np.nan)).cov is None
    with pytest.raises(ValueError, match="PoseStream.cov: covariance at row 0 is not positive definite"):
        PoseStream([0.0, 1.0], np.zeros((2, 3)), C, np.array([-np.eye(6), np.eye(6)]))
    assert TwistStream([0.0], np.zeros((1, 3)), None, np.eye(3)[None]).cov.shape == (1, 3, 3)
    with pytest.raises(ValueError, match=r"TwistStream.cov: expected shape \(1, 6, 6\)"):
        TwistStream([0.0], np.zeros((1, 3)), np.zeros((1, 3)), np.eye(3)[None])
