"""The kinds of fixed-lag smoother, by the name ``smoother run --fixed-lag-kind`` and
:class:`smoother.online.smoother.OnlineSmoother` take: the project's compiled sliding window
(:mod:`smoother.fixed_lag.sliding.window`, the default) and GTSAM's ``IncrementalFixedLagSmoother`` and
``BatchFixedLagSmoother`` (:mod:`smoother.fixed_lag.gtsam_window`). A module of its own so that the command line
lists them without importing GTSAM."""

FIXED_LAG_KINDS = ("sliding", "incremental", "batch")
