"""Measurements waiting for their keyframe in an online smoother
(:class:`smoother.online.smoother.OnlineSmoother`), sorted into time whatever the order they arrive in.

A measurement waits until the keyframe at its latest time is made, or, one of one time between
keyframes, the keyframe after it (it is attached to the one before); those of a keyframe come out
sorted by latest time, sensor and row (:class:`Pending`), so a keyframe's factors do not depend
on the order of arrival. What is too old to reach the window is refused, counted per sensor with
a warning at the sensor's first:

- ``dropped``: its latest time is at or before the newest keyframe made (it arrived later than
  ``max_delay_s`` behind the IMU), it lies before the first keyframe or after the last IMU sample;
- ``skipped``: a relative measurement whose earlier time is no keyframe in the window (it has
  left: older than the lag), when it arrives or when its later keyframe is made.
"""
from __future__ import annotations

import heapq
import warnings
from dataclasses import dataclass


@dataclass(order=True)
class Pending:
    """A measurement waiting for its keyframe: sorted by its latest time, then sensor and times,
    then order of arrival; ``spec`` and ``row`` the measurement (:func:`smoother.model.problem.measurement_spec`),
    ``arrived`` its wall time of arrival."""

    latest: float
    sensor: str
    times: tuple
    seq: int
    spec: object = None
    row: int = 0
    arrived: float = 0.0


class PendingMeasurements:
    """The heap of :class:`Pending` measurements and the counts of those refused (module
    docstring); ``max_delay_s`` and ``lag_s`` are the smoother's, named in the warnings."""

    def __init__(self, max_delay_s: float, lag_s: float):
        self.max_delay_s, self.lag_s = max_delay_s, lag_s
        #: measurements dropped for arriving too late (or lying outside the IMU's span), per sensor
        self.dropped: dict[str, int] = {}
        #: relative measurements skipped because their earlier time has left the window, per sensor
        self.skipped: dict[str, int] = {}
        self._heap: list[Pending] = []
        self._seq = 0

    def __len__(self) -> int:
        return len(self._heap)

    def offer(self, sensor: str, times: tuple, spec, row: int, arrived: float, newest: float | None,
              keyframes) -> bool:
        """Take the measurement ``row`` of ``spec`` at ``times`` unless it is older than the window:
        its latest time at or before the ``newest`` keyframe made (dropped), or one of its times
        at or before it and no keyframe in the window (``keyframes``: the window's keyframe times;
        skipped). Whether it was taken."""
        latest = max(times)
        if newest is not None and latest <= newest:
            self.drop(sensor)
            return False
        if newest is not None and any(x <= newest and x not in keyframes for x in times):
            self.skip(sensor)
            return False
        self._seq += 1
        heapq.heappush(self._heap, Pending(latest, sensor, times, self._seq, spec, row, arrived))
        return True

    def due(self, t: float, first: bool, keyframes) -> tuple[list[Pending], list[Pending]]:
        """The measurements that reach the window with the keyframe at ``t``, sorted
        (:class:`Pending`) and taken off the heap: those at ``t`` (latest time ``t``), and, unless
        it is the ``first`` keyframe, those of one time between the newest keyframe made and ``t``
        (attached to that keyframe). Taken off too: every one before the ``first`` keyframe
        (dropped) and every relative one whose earlier time is neither ``t`` nor a keyframe in the
        window (``keyframes``; skipped)."""
        used, attached = [], []
        while self._heap and self._heap[0].latest <= t:
            item = heapq.heappop(self._heap)
            if item.latest < t and first:  # before the first keyframe
                self.drop(item.sensor, "lies before the IMU's first sample and was dropped")
                continue
            # its earlier keyframe left
            if any(x not in keyframes and x != t for x in item.times) and len(item.times) > 1:
                self.skip(item.sensor)
                continue
            (used if item.latest == t else attached).append(item)
        return used, attached

    def drop_all(self, why: str) -> None:
        """Drop every measurement still waiting, saying ``why``."""
        while self._heap:
            self.drop(heapq.heappop(self._heap).sensor, why)

    def drop(self, sensor: str, why: str | None = None) -> None:
        """Count a measurement of ``sensor`` dropped (``why``; default: it arrived too late)."""
        self._count(self.dropped, sensor, why or (f"arrived after its keyframe time had been processed (more than "
                                                  f"max_delay_s = {self.max_delay_s:g} s behind the IMU) and was "
                                                  "dropped"), "dropped")

    def skip(self, sensor: str) -> None:
        """Count a relative measurement of ``sensor`` skipped: it reaches beyond the window."""
        self._count(self.skipped, sensor, f"refers to a time that has left the window (older than the lag, "
                                          f"{self.lag_s:g} s, or no keyframe) and was skipped", "skipped")

    @staticmethod
    def _count(counts: dict, sensor: str, what: str, attribute: str) -> None:
        """Count one measurement of ``sensor`` in ``counts``, with a warning at its first."""
        counts[sensor] = counts.get(sensor, 0) + 1
        if counts[sensor] == 1:
            warnings.warn(f"online smoother: a measurement of {sensor!r} {what}; the smoother counts such "
                          f"measurements in .{attribute}", stacklevel=6)
