"""The measurements of sensors whose errors drift (:mod:`smoother.model.correlated`) as they reach an
online smoother's window: each one after the first as its innovation on the one before it, the
factor the batch smoother makes of it (:class:`smoother.model.correlated.Innovation`).

A sensor's measurements reach the window in time order (:mod:`smoother.online.pending` sorts them
into their keyframes), so the one before is the last one that reached it. Where the two share a
stamp, or lie so close that their errors are one (:func:`smoother.model.correlated.pair_weights`),
the later one is weighed as independent of it, and counted (``restarted``).
"""
from __future__ import annotations

import numpy as np

from smoother.model.correlated import Innovation, pair_weights


class DriftChains:
    """The last measurement of each drifting sensor that reached the window, and the innovation of
    the next one on it. ``taus``: the sensors' correlation times [s] by name."""

    def __init__(self, taus: dict[str, float]):
        self._taus = dict(taus)
        self._last: dict[str, tuple] = {}
        #: measurements weighed as independent of the one before: stamped at once, or as good as
        self.restarted = 0

    def __bool__(self) -> bool:
        return bool(self._taus)

    def saved(self) -> tuple:
        """What :meth:`restore` takes back to: the chains now (before a window's update that may be refused)."""
        return dict(self._last), self.restarted

    def restore(self, saved: tuple) -> None:
        """The chains as :meth:`saved` found them."""
        self._last, self.restarted = dict(saved[0]), saved[1]

    def chained(self, sensor: str, t: float, entry: tuple) -> tuple:
        """The window's ``entry`` ``(spec, row, keyframes, robust, attached)`` of ``sensor``'s
        measurement at ``t`` [s], with its :class:`~smoother.model.correlated.Innovation` on the one
        before appended where the sensor drifts and one came before; it is the one before the next."""
        tau = self._taus.get(sensor)
        if tau is None:
            return entry
        last = self._last.get(sensor)
        self._last[sensor] = (t, entry)
        if last is None:
            return entry
        t_before, (spec, row, keyframes, _, attached) = last
        phi, s = pair_weights(t - t_before, tau)
        if not (t > t_before and np.isfinite(s)):
            self.restarted += 1
            return entry
        return (*entry, Innovation(spec, row, keyframes[0], attached, float(s * phi), float(s)))
