"""Online fixed-lag smoothing, fed as data arrive: :class:`OnlineSmoother` and its parts -- the IMU
buffer, the keyframe schedule, measurements waiting for their keyframe, the hand-over of smoothed
keyframes, the IMU-rate prediction, how late a measurement may arrive (:mod:`~smoother.online.delay`)
-- and the replay of a recorded dataset through it.

``from smoother.online import OnlineSmoother, SensorSetup`` (and the other names below) loads
the defining module on first use."""
from factors.exports import lazy_exports

_EXPORTS = {
    **dict.fromkeys(("OnlineSmoother", "SensorSetup"), "smoother.online.smoother"),
    "OnlineEstimate": "smoother.online.handover",
    **dict.fromkeys(("replay", "ReplayResult", "arrivals", "replaying"), "smoother.online.replay"),
}
__all__ = sorted(_EXPORTS)
__getattr__, __dir__ = lazy_exports(globals(), _EXPORTS)
