"""The hand-over of an online smoother (:class:`smoother.online.smoother.OnlineSmoother`): each keyframe's
smoothed estimate, read from the keyframe window just before the update that marginalises it
(or at the end of the data), goes to the caller's ``on_smoothed`` or a queue for
:meth:`HandOver.smoothed`, oldest first.
"""
from __future__ import annotations

from collections import deque
from dataclasses import dataclass

import numpy as np

from factors import imu


@dataclass(slots=True)
class OnlineEstimate:
    """A state at time ``t`` with its 15x15 covariance ``cov`` (None when the smoother computes
    no covariances)."""

    t: float
    state: imu.ImuState
    cov: np.ndarray | None


class HandOver:
    """Estimates out of ``window`` (a :class:`smoother.fixed_lag.contract.FixedLagWindow` of any kind), with
    their marginal covariances when ``covariances``, to ``on_smoothed(OnlineEstimate)`` or, with
    None, the queue."""

    def __init__(self, window, covariances: bool, on_smoothed=None):
        self.window, self.covariances, self.on_smoothed = window, covariances, on_smoothed
        self._queue: deque[OnlineEstimate] = deque()

    def read(self, keyframes) -> list[tuple[int, OnlineEstimate]]:
        """``(number, estimate)`` of the window's ``keyframes`` now (recorded as read, see
        :meth:`smoother.fixed_lag.contract.FixedLagWindow.taken`)."""
        keyframes = list(keyframes)
        if not keyframes:
            return []
        window = self.window
        covs = window.covariances(keyframes) if self.covariances else [None] * len(keyframes)
        window.taken(keyframes)
        return [(j, OnlineEstimate(window.time(j), window.state(j), cov)) for j, cov in zip(keyframes, covs)]

    def give(self, estimates: list[OnlineEstimate]) -> None:
        """Hand ``estimates`` of keyframes that left the window to ``on_smoothed`` or the queue."""
        for out in estimates:
            if self.on_smoothed is not None:
                self.on_smoothed(out)
            else:
                self._queue.append(out)

    def smoothed(self):
        """The queued estimates (oldest first), taken off the queue as they are yielded."""
        while self._queue:
            yield self._queue.popleft()
