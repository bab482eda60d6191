"""The window of each kind of fixed-lag smoother (:data:`smoother.fixed_lag.kinds.FIXED_LAG_KINDS`), made
by one call (:func:`make_window`) for :class:`smoother.online.smoother.OnlineSmoother` and
:func:`smoother.fixed_lag.offline.run_fixed_lag`: each keeps the contract of
:class:`smoother.fixed_lag.contract.FixedLagWindow`."""
from __future__ import annotations

from factors import imu, preintegration
from factors.errors import InputError
from smoother.fixed_lag.contract import FixedLagWindow
from smoother.fixed_lag.gtsam_window import KeyframeWindow
from smoother.fixed_lag.kinds import FIXED_LAG_KINDS, GTSAM_KINDS
from smoother.fixed_lag.sliding.window import SlidingWindow


def make_window(lag_s: float, kind: str = "sliding", gravity=imu.DEFAULT_GRAVITY,
                reintegration_threshold: float = preintegration.REINTEGRATION_THRESHOLD,
                calibrations=None) -> FixedLagWindow:
    """The keyframe window of fixed-lag smoother ``kind`` with the lag ``lag_s`` [s], ``gravity``
    (world, m/s^2) and ``reintegration_threshold`` (rad/s) of the IMU factors it makes, and the
    calibration variables ``calibrations`` (a :class:`smoother.fixed_lag.sliding.calibration.WindowCalibration`;
    the compiled window only) or None."""
    if kind == "sliding":
        return SlidingWindow(lag_s, gravity, reintegration_threshold, calibration=calibrations)
    if kind not in GTSAM_KINDS:
        raise InputError(f"fixed-lag smoother kind {kind!r}: expected one of {', '.join(FIXED_LAG_KINDS)}")
    if calibrations is not None:
        raise InputError(f"fixed-lag smoother kind {kind!r} cannot estimate calibrations (sensors "
                         f"{', '.join(calibrations.set.names)} ask for them): use kind 'sliding'")
    return KeyframeWindow(lag_s, kind, gravity, reintegration_threshold)
