"""The IMU stream of an online smoother (:class:`smoother.online.smoother.OnlineSmoother`): samples taken
one at a time or in arrays, checked as the offline data types check them, kept in growing arrays.

Samples come in strictly increasing time: one at or before the newest is an InputError (they are
never reordered). An interval longer than :data:`datasets.types.IMU_GAP_FACTOR` typical periods
(the median interval of the samples kept, once there are :data:`TYPICAL_INTERVALS`) is a gap
(:func:`datasets.types.imu_gaps`, the offline rule and message): counted in ``imu_gaps`` with
the longest in ``longest_imu_gap_s``, a warning at the first and at each longer than all before;
a step longer than :data:`datasets.types.MAX_IMU_GAP_S` is a jump of the clock, refused. A
refused sample is not taken.

Memory: the samples before the one held at :attr:`ImuBuffer.keep_from` (the newest keyframe's
time, set by the smoother) are let go when the arrays fill; ``released`` counts them, so that an
index into the stream stays valid as ``index - released``.
"""
from __future__ import annotations

import math
import warnings

import numpy as np

from datasets.types import (
    IMU_GAP_FACTOR,
    MAX_IMU_GAP_S,
    MAX_PLAUSIBLE_SPECIFIC_FORCE,
    check_array,
    check_imu_range,
    check_times,
    gyro_rate_limit,
    imu_gaps,
)
from factors.errors import InputError

#: The IMU's typical period is known (and gaps are judged) once this many intervals have come.
TYPICAL_INTERVALS = 20


def imu_arrays(t, acc, gyro) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``add_imu``'s arguments as arrays ``t (N,)``, ``acc, gyro (N, 3)``: one sample is ``t`` a
    number with 3-vectors, N samples ``t`` of shape (N,) with (N, 3) arrays; any other shape is an
    InputError naming the argument with the shapes expected and got (nothing is reshaped)."""
    arrays = []
    for name, value in (("t", t), ("acc", acc), ("gyro", gyro)):
        try:
            arrays.append(np.asarray(value, dtype=float))
        except (TypeError, ValueError):
            raise InputError(f"add_imu: {name}: expected numbers, got {type(value).__name__}") from None
    t, acc, gyro = arrays
    if t.ndim == 0:
        expected, what = (3,), "one sample (t a number)"
    elif t.ndim == 1:
        expected, what = (t.size, 3), f"{t.size} samples (t of shape ({t.size},))"
    else:
        raise InputError(f"add_imu: t: expected a number (one sample) or shape (N,) (N samples), got shape {t.shape}")
    if t.size == 0:
        raise InputError("add_imu: t: expected at least one sample, got none")
    for name, a in (("acc", acc), ("gyro", gyro)):
        if a.shape != expected:
            raise InputError(f"add_imu: {name}: expected shape {expected} for {what}, got {a.shape}")
    return np.atleast_1d(t), np.atleast_2d(acc), np.atleast_2d(gyro)


class ImuBuffer:
    """The samples ``t[:n]``, ``acc[:n]``, ``gyro[:n]`` kept (module docstring); ``t_last`` the
    newest sample's time (-inf before any). The gyro rate limit is the one in force when the buffer
    is made (:func:`datasets.types.gyro_rate_limit`). Warnings name the frame ``stacklevel``
    frames above :meth:`add` / :meth:`add_one` (1: their caller)."""

    def __init__(self, stacklevel: int = 1):
        self.t = np.empty(1024)
        self.acc = np.empty((1024, 3))
        self.gyro = np.empty((1024, 3))
        self.n = 0
        self.t_last = -math.inf
        #: the time whose held sample (and every later one) is kept; None: keep all
        self.keep_from: float | None = None
        #: samples let go so far (an index into the whole stream is ``index - released`` here)
        self.released = 0
        #: IMU gaps bridged so far (:func:`datasets.types.imu_gaps`), and the longest of them [s]
        self.imu_gaps = 0
        self.longest_imu_gap_s = 0.0
        self._stack = stacklevel
        # the hot path's bounds: an interval up to _gap_limit (IMU_GAP_FACTOR typical periods, once
        # known), squared norms up to the ranges' (below them every axis is in range), and the
        # sample count at which the arrays are full or the typical period is due
        self._typical = None
        self._gap_limit = MAX_IMU_GAP_S
        self._rate_limit = gyro_rate_limit()
        self._acc2, self._rate2 = MAX_PLAUSIBLE_SPECIFIC_FORCE ** 2, self._rate_limit ** 2
        self._room = TYPICAL_INTERVALS + 1

    def add(self, t, acc, gyro) -> int:
        """Samples as ``add_imu`` takes them (:func:`imu_arrays`), checked (:meth:`checked`); none is
        taken when one is refused. Returns how many were taken (the newest ``n`` kept)."""
        t, acc, gyro = self.checked(*imu_arrays(t, acc, gyro), stacklevel=self._stack + 3)
        n = self.n
        if n + t.size > len(self.t):
            self._grow(t.size)
            n = self.n
        self.t[n:n + t.size], self.acc[n:n + t.size], self.gyro[n:n + t.size] = t, acc, gyro
        self.n = n + t.size
        self.t_last = float(t[-1])
        if self._typical is None and self.n > TYPICAL_INTERVALS:
            self._know_typical(stacklevel=self._stack + 3)
        # where add_one acts next: when the arrays are full, or when the typical period is due
        self._room = len(self.t) if self._typical is not None else TYPICAL_INTERVALS + 1
        return t.size

    def add_one(self, t: float, acc, gyro) -> None:
        """One sample (``acc``, ``gyro`` of shape (3,)) with as few operations as it takes: a few
        scalar comparisons (a step forward within the gap limit; the squared norms within the
        squared ranges, NaN failing them all); only when one fails do the checks of
        :meth:`checked` run, to raise their error or warn about a gap."""
        try:
            a0, a1, a2 = acc.tolist() if type(acc) is np.ndarray else acc
            w0, w1, w2 = gyro.tolist() if type(gyro) is np.ndarray else gyro
            quick = (0.0 < t - self.t_last <= self._gap_limit and a0 * a0 + a1 * a1 + a2 * a2 <= self._acc2
                     and w0 * w0 + w1 * w1 + w2 * w2 <= self._rate2)
        except TypeError:  # not numbers: the checks name the argument
            quick = False
        if not quick:
            self.checked(*imu_arrays(t, acc, gyro), stacklevel=self._stack + 3)
        n = self.n
        if n == self._room:
            self._make_room()
            n = self.n
        self.t[n], self.acc[n], self.gyro[n] = t, acc, gyro
        self.n = n + 1
        self.t_last = t

    def held_at(self, t):
        """The index of the sample held at time ``t`` (the last at or before it); for an array of
        times an array of them."""
        i = np.maximum(np.searchsorted(self.t[:self.n], t, side="right") - 1, 0)
        return int(i) if np.ndim(i) == 0 else i

    def checked(self, t: np.ndarray, acc: np.ndarray, gyro: np.ndarray, stacklevel: int):
        """Samples ``t (N,)``, ``acc, gyro (N, 3)`` (:func:`imu_arrays`) checked as the offline
        data types check them -- finite, in range (:func:`datasets.types.check_imu_range`), in
        strictly increasing time after the newest sample, no clock jump -- or an InputError naming
        the field and the sample's time; the gaps among them counted and warned about."""
        check_array("add_imu: t", t, ())
        check_array("add_imu: acc", acc, (3,), t.size, t)
        check_array("add_imu: gyro", gyro, (3,), t.size, t)
        if self.n and t[0] <= self.t_last:
            raise InputError(f"add_imu: t: IMU samples must come in strictly increasing time; got t = {float(t[0])!r} "
                             f"after {self.t_last!r} (a step back of {self.t_last - t[0]:.6g} s; samples are "
                             "never reordered)")
        check_times("add_imu: t", t)
        check_imu_range("add_imu: ", t, acc, gyro, self._rate_limit)
        span = t if not self.n else np.concatenate([[self.t_last], t])
        if self._typical is None:  # judged once the typical period is known (_know_typical)
            imu_gaps(span, math.inf, "online smoother: add_imu", rows=False)  # a clock jump only
        else:
            self._gaps(span, stacklevel)
        return t, acc, gyro

    def _grow(self, extra: int) -> None:
        """Room for ``extra`` more samples: those before the sample held at :attr:`keep_from` are
        let go, and the arrays doubled if that is not enough; the typical period follows the
        stream's rate."""
        base = self.held_at(self.keep_from) if self.keep_from is not None else 0
        if self._typical is not None and self.n > TYPICAL_INTERVALS:
            self._typical = float(np.median(np.diff(self.t[:self.n])))
            self._gap_limit = min(IMU_GAP_FACTOR * self._typical, MAX_IMU_GAP_S)
        if base:
            keep = self.n - base
            for a in (self.t, self.acc, self.gyro):
                a[:keep] = a[base:self.n]
            self.n = keep
            self.released += base
        if self.n + extra > len(self.t):
            size = max(2 * len(self.t), self.n + extra)
            self.t = np.resize(self.t, size)
            self.acc = np.resize(self.acc, (size, 3))
            self.gyro = np.resize(self.gyro, (size, 3))
        self._room = len(self.t)

    def _make_room(self) -> None:
        """At ``_room`` samples: grow the arrays if they are full, learn the typical period when due."""
        if self.n == len(self.t):
            self._grow(1)
        if self._typical is None and self.n > TYPICAL_INTERVALS:
            self._know_typical(stacklevel=self._stack + 4)
        self._room = len(self.t)

    def _know_typical(self, stacklevel: int) -> None:
        """The typical period: the median interval of the samples kept (at least
        :data:`TYPICAL_INTERVALS`); the first time, the intervals so far are judged by it too."""
        t = self.t[:self.n]
        first = self._typical is None
        self._typical = float(np.median(np.diff(t)))
        self._gap_limit = min(IMU_GAP_FACTOR * self._typical, MAX_IMU_GAP_S)
        if first:
            self._gaps(t, stacklevel)

    def _gaps(self, t: np.ndarray, stacklevel: int) -> None:
        """Count the gaps between the times ``t`` (the newest sample kept, then new ones), with a
        warning at the first and at each longer than all before."""
        gaps, text = imu_gaps(t, self._typical if self._typical is not None else math.inf,
                              "online smoother: add_imu", rows=False)
        if gaps.size:
            if gaps.max() > self.longest_imu_gap_s:
                warnings.warn(f"{text} (gaps are counted in .imu_gaps)", stacklevel=stacklevel)
            self.imu_gaps += gaps.size
            self.longest_imu_gap_s = max(self.longest_imu_gap_s, float(gaps.max()))
