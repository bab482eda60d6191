"""Fixed-lag smoothing: one window contract (:mod:`~smoother.fixed_lag.contract`) kept by every kind of
window (:mod:`~smoother.fixed_lag.kinds`) -- the project's own compiled sliding window
(:mod:`smoother.fixed_lag.sliding`) and GTSAM's fixed-lag smoothers (:mod:`~smoother.fixed_lag.gtsam_window`)
-- made by one call (:mod:`~smoother.fixed_lag.windows`); the lag and the rule it must meet
(:mod:`~smoother.fixed_lag.lag`); and the offline driver over a whole problem
(:mod:`~smoother.fixed_lag.offline`)."""
