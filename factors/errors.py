"""The exceptions of the three packages, under one base class.

* :class:`BoxplusError`: anything this project raises on purpose; ``except BoxplusError`` catches
  the library's own failures and nothing else.
* :class:`InputError`: bad input or arguments (a malformed file, a wrong shape or option); also a
  ``ValueError``, as Python's convention for a bad value asks.
* :class:`SolverError`: an estimator that could not produce an estimate (a rank-deficient system,
  a diverged filter, a failed smoother update).

The classes that name a particular failure derive from these: ``datasets.errors.DataError``,
``smoother.errors.IndeterminantSystem``, ``smoother.ekf.filter.FilterDiverged``,
``smoother.fixed_lag.contract.FixedLagFailed``. The command line (``smoother.cli``) turns any of them into
a one-line message and an exit code.
"""


class BoxplusError(Exception):
    """Base class of the exceptions this project raises."""


class InputError(BoxplusError, ValueError):
    """Bad input data or arguments: the message names what was wrong and what was expected."""


class SolverError(BoxplusError):
    """An estimator could not produce an estimate from the data it was given."""
