"""The estimators by the names every part of the package uses -- :func:`smoother.pipeline.run_estimators`,
``smoother run --estimator``, the run's files, figures and messages, the diagnosis -- in the order
their results are shown: the batch smoother, the fixed-lag smoother, the EKF. A module of its own at
the bottom of the package, so that every layer (the command line too, before it imports anything
heavy) takes them from this one list."""

ESTIMATORS = ("batch", "fixed-lag", "ekf")
