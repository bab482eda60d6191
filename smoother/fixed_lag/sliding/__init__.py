"""The project's own fixed-lag smoother, compiled: the window (:mod:`~smoother.fixed_lag.sliding.window`),
its block-banded linear algebra (:mod:`~smoother.fixed_lag.sliding.banded`), its normal equations
(:mod:`~smoother.fixed_lag.sliding.normal_equations`) and the calibrations' dense border
(:mod:`~smoother.fixed_lag.sliding.calibration`)."""
