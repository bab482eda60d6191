"""Graph building, batch and fixed-lag smoothing, the EKF, cross-checks, evaluation, plots and
the command line. Depends on ``factors`` and ``datasets``."""
