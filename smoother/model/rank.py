"""Which components of a keyframe the rows of a linear system leave free: the diagnosis behind
every :class:`smoother.errors.IndeterminantSystem` the estimators raise (a yaw no measurement
fixes, a dead-reckoned stretch), from GTSAM's indeterminant-system errors or from a weak pivot of
the square-root information."""
from __future__ import annotations

import gtsam
import numpy as np

from factors import imu
from smoother.errors import IndeterminantSystem, indeterminant_key, is_indeterminant

DIM = imu.STATE_DIM


def indeterminant_error(error: RuntimeError, graph: gtsam.GaussianFactorGraph, ordering: gtsam.Ordering) -> Exception:
    """GTSAM's indeterminant-system ``error`` under QR as :class:`IndeterminantSystem` naming the
    keyframe and its free components; any other error as it is."""
    if not is_indeterminant(error):
        return error
    key = indeterminant_key(error)
    return IndeterminantSystem(str(error), key, _free_after(graph, ordering, key))


#: The error state's quantities, three components each, in their order.
QUANTITIES = ("position (world) ", "velocity (body) ", "attitude (world) about ", "accelerometer bias ",
              "gyro bias ")


#: Pivots of the square-root information below this fraction of the largest count as zero: the
#: variable is not determined (a condition number of the rows beyond 1e10 leaves no digit of a
#: covariance anyway).
RANK_TOLERANCE = 1e-10


def _free_after(graph: gtsam.GaussianFactorGraph, ordering: gtsam.Ordering, key: int | None) -> str | None:
    """:func:`free_components` of the rows left on ``key`` once the variables before it in
    ``ordering`` are eliminated (None when that cannot be told)."""
    if key is None:
        return None
    position = [int(ordering.at(i)) for i in range(ordering.size())].index(key)
    before = gtsam.Ordering()
    for i in range(position):
        before.push_back(ordering.at(i))
    try:
        _, rest = graph.eliminatePartialSequential(before, gtsam.EliminateQR)
    except RuntimeError:
        return None
    rows = [rest.at(i).jacobian()[0][:, _columns(rest.at(i), key)] for i in range(rest.size())
            if rest.at(i) is not None and key in rest.at(i).keys()]
    A = np.vstack(rows) if rows else np.zeros((0, DIM))
    return free_components(A, 1e-9 * np.abs(A).max() if A.size else 0.0)


def free_components(rows: np.ndarray, tolerance: float) -> str | None:
    """The error-state components that the rows ``(m, 15)`` of one variable leave free, e.g.
    ``"position (world) x, y, attitude (world) about z"`` (a yaw about the origin): those that
    take part in the null space of the rows (singular values at most ``tolerance``; the weakest
    direction if none is), with a weight of at least 1e-8 of the largest -- a rotation about the
    origin moves a position km away 1e3 times more than the attitude, in their units."""
    s, V = np.zeros(DIM), np.eye(DIM)
    if rows.shape[0]:
        _, top, Vt = np.linalg.svd(rows, full_matrices=True)
        s[:len(top)], V = top, Vt.T
    null = V[:, s <= tolerance]
    if null.shape[1] == 0:  # nearly singular only: its weakest direction
        null = V[:, -1:]
    weight = np.sum(null * null, axis=1)
    free = (weight >= 1e-8 * weight.max()).reshape(len(QUANTITIES), 3)
    if free.all():
        return "whole state (position, velocity, attitude, biases)"
    return ", ".join(quantity + ", ".join(np.array(list("xyz"))[axes])
                     for quantity, axes in zip(QUANTITIES, free) if axes.any()) or None


def _columns(factor, key: int) -> slice:
    """The columns of ``key`` in ``factor.jacobian()`` (its keys' 15 columns each, in order)."""
    j = [int(k) for k in factor.keys()].index(key)
    return slice(j * DIM, (j + 1) * DIM)
