"""The lag of a fixed-lag smoother, in seconds: the one check of its value (:func:`check_lag`, the
library's and the command line's), and the rule it must meet to be useful -- absolute measurements
no further apart than the lag (:func:`measured_gap`, :func:`sparse_measurement_warning`), or
keyframes leave the window before the next measurement reaches them and keep their dead-reckoned
estimates. No GTSAM here: the command line checks ``--lag`` with it before any work starts."""
from __future__ import annotations

import math
import warnings
from typing import TYPE_CHECKING

import numpy as np

from factors.errors import InputError

if TYPE_CHECKING:
    from smoother.model.problem import Problem


def check_lag(lag_s, name: str = "lag_s", error: type[Exception] = InputError) -> float:
    """``lag_s`` as a float: a lag in seconds, finite and > 0; otherwise ``error`` (an
    :class:`factors.errors.InputError`; the command line's ``UserError``) naming ``name`` -- the
    argument, or the option (``--lag``)."""
    try:
        value = float(lag_s)
    except (TypeError, ValueError):
        value = math.nan
    if not (math.isfinite(value) and value > 0):
        raise error(f"{name}: expected a lag in seconds > 0 (finite), got {lag_s!r}")
    return value


def check_lag_spans_keyframes(lag_s: float, keyframe_rate: float | None, name: str = "lag_s",
                              error: type[Exception] = InputError) -> None:
    """A measurement between keyframes is attached to the keyframe before it and reaches the
    window with the keyframe after it; a lag no longer than the keyframe interval (``1 /
    keyframe_rate``; None: a keyframe at every measurement time) would let that keyframe leave
    first and the measurement be skipped: ``error`` naming ``name``."""
    if keyframe_rate is not None and not lag_s > 1.0 / keyframe_rate:
        raise error(f"{name}: {lag_s:g} s is no longer than the keyframe interval (1 / {keyframe_rate:g} Hz): a "
                    "measurement between keyframes reaches the window with the keyframe after its own, which would "
                    "have left; choose a longer lag or a higher keyframe rate")


def measured_gap(problem: Problem) -> float:
    """The longest time between consecutive keyframes with an absolute measurement (one that fixes a
    position or an attitude: :attr:`Problem.absolute`; velocities and relative poses do not end
    dead reckoning), the first and last keyframes included: the whole run when there is none (as
    :class:`smoother.online.smoother.OnlineSmoother` counts it)."""
    measured = [np.asarray(b.keyframes).ravel() for b in problem.blocks if b.name in problem.absolute]
    times = problem.times[np.unique(np.concatenate(measured))] if measured else problem.times[:0]
    return float(np.max(np.diff(np.concatenate([problem.times[:1], times, problem.times[-1:]]))))


def sparse_measurement_warning(longest_s: float, lag_s: float, kind: str) -> str | None:
    """The warning when measurements are ``longest_s`` apart, longer than the lag; None if not.

    Every kind: a keyframe's fixed-lag estimate is the one it has when it leaves the window, so a
    keyframe that leaves before the next measurement arrives keeps the dead-reckoned estimate
    from the last one: on KITTI with every 20th GPS fix (20 s apart) the incremental smoother
    ends ~50 m off the held-out fixes at a 2-s lag and ~35 m at 0.5 s. The batch kind is worse:
    GTSAM's ``BatchFixedLagSmoother`` keeps the linearisation point of the state its marginal
    factor lands on fixed (its ``enforceConsistency``, on by default and not settable from
    Python), so after dead reckoning through a whole window a measurement's correction cannot
    reach that state's IMU factor, Levenberg-Marquardt finds no descent and stops, and the
    estimate drifts: a 120-s simulation with a position fix every 10 s and a 2-s lag ended 1.3 km
    off (the incremental smoother: 8 m, the EKF: 0.7 m)."""
    if not longest_s > lag_s:
        return None
    digits = 3  # enough to tell the gap from the lag (2.0019 s beside a 2-s lag is not "2 s")
    while digits < 12 and float(f"{longest_s:.{digits}g}") <= lag_s:
        digits += 1
    step = 10.0 ** (math.floor(math.log10(longest_s)) - digits + 1)
    enough = math.ceil(longest_s / step) * step  # rounded up: a lag that does reach the gap
    text = (f"fixed-lag ({kind}): absolute measurements (fixes, poses, attitudes) up to {longest_s:.{digits}g} s "
            f"apart, longer than the lag ({lag_s:g} s): "
            "keyframes leave the window before the next measurement reaches them and keep their dead-reckoned "
            "estimates")
    if kind == "batch":
        text += (" (GTSAM's BatchFixedLagSmoother can drift far off: it keeps the states at its window's edge "
                 "linearised where dead reckoning put them; use the incremental smoother)")
    return text + f". Choose a lag of at least {enough:.{digits}g} s (the longest gap between absolute measurements)"


def warn_of_sparse_measurements(longest_s: float, lag_s: float, kind: str) -> None:
    """Warn (:func:`sparse_measurement_warning`) when measurements are further apart than the lag."""
    text = sparse_measurement_warning(longest_s, lag_s, kind)
    if text is not None:
        warnings.warn(text, stacklevel=3)
