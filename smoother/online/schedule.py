"""Which keyframes an online smoother (:class:`smoother.online.smoother.OnlineSmoother`) makes, and when.

A keyframe is asked for at the first IMU sample (:meth:`KeyframeSchedule.start`), at every
measurement time and every time given to ``keyframe_at`` (:meth:`KeyframeSchedule.ask`), and,
with a ``rate``, on the grid ``t0 + m / rate`` -- except grid times within half an IMU interval
of another keyframe. The times come out in increasing order, each once, as the IMU stream
passes them (:meth:`KeyframeSchedule.next_due`); one before the first sample is let go (nothing
anchors it).
"""
from __future__ import annotations

import heapq

import numpy as np


class KeyframeSchedule:
    """The keyframe times asked for and not yet made (a heap, each time once), and the grid of
    ``rate`` [Hz] (None: no grid) from the first sample's time ``t0``."""

    def __init__(self, rate: float | None):
        self.rate = rate
        self.t0: float | None = None
        self._knots: list[float] = []  # heap of the times asked for
        self._knot_set: set[float] = set()
        self._grid_next = 0  # the index m of the next grid time t0 + m / rate
        self._grid_t = np.inf  # that time (inf: no grid)

    def start(self, t0: float) -> None:
        """The first IMU sample's time ``t0``: the first keyframe's and the grid's start."""
        self.t0 = t0
        self._grid_t = t0 if self.rate else np.inf
        self.ask(t0)

    def ask(self, t: float) -> None:
        """Ask for a keyframe at ``t`` (once, however often asked)."""
        if t not in self._knot_set:
            self._knot_set.add(t)
            heapq.heappush(self._knots, t)

    def next_time(self) -> float:
        """The earliest time asked for or on the grid (inf: none): a keyframe is due once the
        stream's horizon reaches it."""
        return min(self._knots[0], self._grid_t) if self._knots else self._grid_t

    def grid_up_to(self, horizon: float, step: float, newest: float | None) -> None:
        """Ask for the grid times up to ``horizon``, except those within ``step`` (half the IMU
        interval) of a time asked for, or less than ``step`` after the ``newest`` keyframe made."""
        while self._grid_t <= horizon:
            g = self._grid_t
            self._grid_next += 1
            self._grid_t = self.t0 + self._grid_next / self.rate
            if not self._near(g, step) and (newest is None or g - newest >= step):
                self.ask(g)

    def _near(self, g: float, step: float) -> bool:
        """Whether a time asked for lies within ``step`` of ``g``: the heap searched from its root,
        leaving each subtree whose root (its smallest time) is ``step`` or more after ``g``. The
        times asked for span a whole recording when ``keyframe_at`` is given them all (a replay):
        a scan of them all at every grid time would make a run's cost grow with its length squared."""
        heap, stack = self._knots, [0] if self._knots else []
        while stack:
            i = stack.pop()
            x = heap[i]
            if x - g >= step:
                continue
            if abs(x - g) < step:
                return True
            stack += [c for c in (2 * i + 1, 2 * i + 2) if c < len(heap)]
        return False

    def next_due(self, horizon: float, end: float) -> float | None:
        """The earliest time asked for at or before both ``horizon`` and ``end`` (the newest IMU
        sample), taken off the schedule; None when there is none. Times before ``t0`` are let go."""
        while self._knots and self._knots[0] <= horizon and self._knots[0] <= end:
            t = heapq.heappop(self._knots)
            self._knot_set.discard(t)
            if t >= self.t0:
                return t
        return None
