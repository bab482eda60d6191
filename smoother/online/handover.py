"""The hand-over of an online smoother (:class:`smoother.online.smoother.OnlineSmoother`): each keyframe's
smoothed estimate, read from the keyframe window just before the update that marginalises it
(or at the end of the data), goes to the caller's ``on_smoothed`` or a queue for
:meth:`HandOver.smoothed`, oldest first; when asked, with the window's estimate of the keyframe
after it then and the two's joint covariance, where the window computes it (what a state between
the two is bridged with: :mod:`smoother.model.between`).
"""
from __future__ import annotations

from collections import deque
from dataclasses import dataclass

import numpy as np

from factors import imu


@dataclass(slots=True)
class NextKeyframe:
    """The keyframe after a smoothed one as the window had it when that one was read: its time
    ``t``, estimate ``state`` and covariance ``cov``, and ``cross`` (15x15), the two's cross
    covariance ``Sigma_(k, k+1)``."""

    t: float
    state: imu.ImuState
    cov: np.ndarray
    cross: np.ndarray


@dataclass(slots=True)
class OnlineEstimate:
    """A state at time ``t`` with its 15x15 covariance ``cov`` (None when the smoother computes
    no covariances); ``following``: the keyframe after it as the window had it then
    (:class:`NextKeyframe`), where the window computes joint covariances
    (:meth:`smoother.fixed_lag.contract.FixedLagWindow.joint_with_next`) and there is one."""

    t: float
    state: imu.ImuState
    cov: np.ndarray | None
    following: NextKeyframe | None = None


class HandOver:
    """Estimates out of ``window`` (a :class:`smoother.fixed_lag.contract.FixedLagWindow` of any kind), with
    their marginal covariances when ``covariances`` (and, with ``with_next``, the next keyframe's
    with the two's joint covariance, where the window computes it), to ``on_smoothed(OnlineEstimate)``
    or, with None, the queue."""

    def __init__(self, window, covariances: bool, on_smoothed=None, with_next: bool = False):
        self.window, self.covariances, self.on_smoothed = window, covariances, on_smoothed
        self.with_next = with_next
        self._queue: deque[OnlineEstimate] = deque()

    def read(self, keyframes) -> list[tuple[int, OnlineEstimate]]:
        """``(number, estimate)`` of the window's ``keyframes`` now (recorded as read, see
        :meth:`smoother.fixed_lag.contract.FixedLagWindow.taken`)."""
        keyframes = list(keyframes)
        if not keyframes:
            return []
        window = self.window
        covs, following = [None] * len(keyframes), [None] * len(keyframes)
        if self.covariances:
            before = [i for i, j in enumerate(keyframes) if j < window.newest] if self.with_next else []
            joint = window.joint_with_next([keyframes[i] for i in before]) if before else None
            if joint is not None:
                for i, J in zip(before, joint):  # copies: a view would keep the whole 30x30 block
                    j = keyframes[i]
                    covs[i] = J[:15, :15].copy()
                    following[i] = NextKeyframe(window.time(j + 1), window.state(j + 1), J[15:, 15:].copy(),
                                                J[:15, 15:].copy())
            rest = [i for i, cov in enumerate(covs) if cov is None]
            for i, cov in zip(rest, window.covariances([keyframes[i] for i in rest]) if rest else ()):
                covs[i] = cov
        window.taken(keyframes)
        return [(j, OnlineEstimate(window.time(j), window.state(j), cov, nxt))
                for j, cov, nxt in zip(keyframes, covs, following)]

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
