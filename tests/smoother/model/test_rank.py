"""What the rows of one keyframe leave free (smoother/model/rank.py), named by the error state's
components; how the estimators word it when GTSAM finds the system indeterminant:
``tests/smoother/batch/test_solve.py``."""
from __future__ import annotations

import numpy as np

from smoother.errors import IndeterminantSystem
from smoother.model.rank import free_components, indeterminant_error


def _rows_fixing_all_but(*free: int) -> np.ndarray:
    """Unit rows on every error-state coordinate but ``free`` (0-14: r, v, phi, b_f, b_w)."""
    return np.eye(15)[[i for i in range(15) if i not in free]]


def test_the_free_coordinates_are_named_by_quantity_and_axis():
    assert free_components(_rows_fixing_all_but(0, 1, 8), 1e-9) == "position (world) x, y, attitude (world) about z"
    assert free_components(_rows_fixing_all_but(5, 12, 13, 14), 1e-9) == "velocity (body) z, gyro bias x, y, z"


def test_a_yaw_about_the_origin_far_away_names_the_position_it_moves_too():
    """A keyframe 1 km out: the unfixed yaw about the world's origin moves the position across the
    line to it (y here): the position and the yaw are free together, however unequal their units."""
    p = np.array([1000.0, 0.0, 0.0])
    direction = np.zeros(15)
    direction[0:3] = np.cross([0.0, 0.0, 1.0], p)  # d r = dpsi e_z x r
    direction[8] = 1.0
    Q = np.linalg.qr(np.column_stack([direction / np.linalg.norm(direction), np.eye(15)]))[0]
    rows = Q[:, 1:].T  # every direction but that one
    named = free_components(rows, 1e-9)
    assert named == "position (world) y, attitude (world) about z", named


def test_no_rows_leave_the_whole_state_free_and_nearly_singular_rows_their_weakest_direction():
    assert free_components(np.zeros((0, 15)), 0.0) == "whole state (position, velocity, attitude, biases)"
    rows = np.diag([1.0] * 14 + [1e-6])
    assert free_components(rows, 1e-9) == "gyro bias z"


def test_an_error_that_is_not_gtsam_s_indeterminant_system_is_passed_on_as_it_is():
    error = RuntimeError("out of memory in the elimination")
    assert indeterminant_error(error, None, None) is error
    assert not isinstance(error, IndeterminantSystem)
