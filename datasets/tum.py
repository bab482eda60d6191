"""TUM trajectory files: one pose per line, ``t x y z qx qy qz qw``.

Format (as the TUM RGB-D benchmark and evo use it): fields separated by spaces or tabs, lines
starting with ``#`` and blank lines ignored; ``t`` in seconds, ``(x, y, z)`` the position of the
body in the world frame, ``(qx, qy, qz, qw)`` the Hamilton quaternion of the body-to-world
rotation with the scalar LAST. In memory the project keeps quaternions scalar first and attitudes
as matrices ``C(Phi_IB)`` (see ``factors.quaternion``).

Reading checks every line (8 finite numbers, strictly increasing times, quaternion norm 1 within
:data:`QUATERNION_TOLERANCE`, then normalised: files written with 6 decimals are off by ~1e-6)
and raises :class:`datasets.errors.DataError` naming the file, line and field otherwise.

Writing is atomic (``datasets.atomic.atomic_write``) and exact: every number is written with
Python's ``repr`` of the float, the shortest decimal that reads back to the identical float64,
so ``read_tum(write_tum(...))`` reproduces times and positions bit for bit (attitudes to
round-off of the matrix-quaternion conversion). The quaternion is written with ``qw >= 0``.
"""
from __future__ import annotations

from pathlib import Path

import numpy as np

from datasets.atomic import atomic_write
from datasets.errors import check_increasing, check_unit_quaternions, data_lines, read_lines, read_table
from datasets.types import Trajectory
from factors import quaternion
from factors.errors import InputError
from factors.imu import ImuState

FIELDS = ["timestamp", "tx", "ty", "tz", "qx", "qy", "qz", "qw"]
#: An attitude-only file's fields (:func:`read_tum_poses`).
ATTITUDE_FIELDS = ["timestamp", "qx", "qy", "qz", "qw"]

#: Accepted deviation of a quaternion's norm from 1 before it is normalised.
QUATERNION_TOLERANCE = 1e-3

HEADER = "# timestamp tx ty tz qx qy qz qw (TUM; Hamilton quaternion of body-to-world, scalar last)"


def read_tum(path) -> Trajectory:
    """Read a TUM trajectory file into a :class:`Trajectory` (velocities and biases NaN)."""
    t, r, C, _ = read_tum_poses(path)
    n = len(t)
    nan = np.full((n, 3), np.nan)
    states = ImuState(r=r, v=nan, C=C, b_f=nan.copy(), b_w=nan.copy())
    return Trajectory(t, states)


def read_tum_poses(path, duplicates: bool = False, attitudes: bool = False):
    """The poses of a TUM file as arrays ``(t, r, C, lines)`` (``lines``: the 1-based line of each
    pose), checked as :func:`read_tum` checks them. With ``duplicates`` a stamp may equal the one
    before (:func:`datasets.errors.duplicate_stamps` tells). With ``attitudes`` the file may hold
    attitudes only, ``t qx qy qz qw`` per line (:data:`ATTITUDE_FIELDS`, an IMU's own attitude
    output): then ``r`` is NaN. Which of the two layouts a file has, its first data line says."""
    path = Path(path)
    lines = read_lines(path)
    fields = FIELDS
    if attitudes:
        first = next((text for _, text in data_lines(lines)), "")
        fields = ATTITUDE_FIELDS if len(first.split()) == len(ATTITUDE_FIELDS) else FIELDS
    what = "pose line ('t x y z qx qy qz qw')" if fields is FIELDS else "attitude line ('t qx qy qz qw')"
    values, line_numbers = read_table(path, lines, fields, 1, what)
    t = values[:, 0]
    check_increasing(path, t, line_numbers, "timestamp", duplicates)
    q_xyzw = check_unit_quaternions(path, values[:, -4:], line_numbers, "qx qy qz qw", QUATERNION_TOLERANCE)
    C = quaternion.to_matrix(quaternion.from_xyzw(q_xyzw))
    r = values[:, 1:4].copy() if fields is FIELDS else np.full((len(t), 3), np.nan)
    return t, r, C, line_numbers


def write_tum(path, trajectory_or_t, r=None, C=None, header: bool = True, time_origin_ns: int | None = None) -> None:
    """Write a TUM file atomically from a :class:`Trajectory` or from arrays ``(t, r, C)``
    (``C`` body-to-world matrices of shape ``(N, 3, 3)``). With ``header`` a ``#`` comment line
    naming the columns comes first. With ``time_origin_ns`` (the data's own clock at ``t = 0``,
    :attr:`datasets.types.Dataset.time_origin_ns`) the stamps are written in that clock, in
    seconds with nine decimals computed from integer nanoseconds (EuRoC's stamps exactly)."""
    if isinstance(trajectory_or_t, Trajectory):
        if r is not None or C is not None:
            raise InputError("write_tum: give either a Trajectory or (t, r, C), not both")
        traj = trajectory_or_t
    else:
        if r is None or C is None:
            raise InputError("write_tum: (t, r, C) needs all three arrays")
        n = len(np.atleast_1d(trajectory_or_t))
        z = np.zeros((n, 3))
        traj = Trajectory(trajectory_or_t, ImuState(r=r, v=z, C=C, b_f=z, b_w=z))
    q = quaternion.to_xyzw(quaternion.from_matrix(traj.C))
    with atomic_write(path) as handle:
        if header:
            handle.write(HEADER + "\n")
        stamps = ([repr(float(t)) for t in traj.t] if time_origin_ns is None
                  else [format_ns(int(time_origin_ns) + int(ns)) for ns in np.round(traj.t * 1e9).astype(np.int64)])
        for k in range(len(traj)):
            numbers = (*traj.position[k], *q[k])
            handle.write(stamps[k] + " " + " ".join(repr(float(x)) for x in numbers) + "\n")


def format_ns(ns: int) -> str:
    """Integer nanoseconds as seconds with nine decimals, exactly (``1403715273262142976`` ->
    ``"1403715273.262142976"``)."""
    sign, ns = ("-", -ns) if ns < 0 else ("", ns)
    return f"{sign}{ns // 1_000_000_000}.{ns % 1_000_000_000:09d}"
