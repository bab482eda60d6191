"""The kinds of fixed-lag smoother, by the name ``smoother run --fixed-lag-kind``,
:class:`smoother.online.smoother.OnlineSmoother` and :func:`smoother.fixed_lag.offline.run_fixed_lag` take: the
project's compiled sliding window (:mod:`smoother.fixed_lag.sliding.window`, the default) and GTSAM's
``IncrementalFixedLagSmoother`` and ``BatchFixedLagSmoother`` (:mod:`smoother.fixed_lag.gtsam_window`). Every kind
is a window of one contract (:class:`smoother.fixed_lag.contract.FixedLagWindow`), made by
:func:`smoother.fixed_lag.windows.make_window`. A module of its own so that the command line lists them without
importing GTSAM."""

#: Every kind of fixed-lag smoother, the default first.
FIXED_LAG_KINDS = ("sliding", "incremental", "batch")
#: The kinds that are GTSAM's fixed-lag smoothers (all but the compiled sliding window).
GTSAM_KINDS = tuple(kind for kind in FIXED_LAG_KINDS if kind != "sliding")
