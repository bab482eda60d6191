"""The batch smoother's optimisers by the names :func:`smoother.batch.solve.solve_batch` and ``smoother
run --optimizer`` take: Levenberg-Marquardt (``lm``, the default), Gauss-Newton (``gn``) and
Powell's dogleg (``dogleg``), all in :mod:`smoother.batch.optimiser`. A module of its own so that
the command line lists them without importing GTSAM."""

OPTIMIZERS = ("lm", "gn", "dogleg")
