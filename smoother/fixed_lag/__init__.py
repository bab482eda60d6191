"""Fixed-lag smoothing: the kinds of window (:mod:`~smoother.fixed_lag.kinds`), GTSAM's fixed-lag
smoothers behind one keyframe loop (:mod:`~smoother.fixed_lag.gtsam_window`), and the project's own
compiled sliding window (:mod:`smoother.fixed_lag.sliding`)."""
