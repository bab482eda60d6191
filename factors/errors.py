"""The exceptions of the three packages, under one base class.

* :class:`BoxplusError`: anything this project raises on purpose; ``except BoxplusError`` catches
  the library's own failures and nothing else.
* :class:`InputError`: bad input or arguments (a malformed file, a wrong shape or option); also a
  ``ValueError``, as Python's convention for a bad value asks. Where that convention asks for
  another built-in class, the error is both: :class:`InputTypeError` (an argument of a kind the
  function cannot take, also a ``TypeError``) and :class:`MissingKeyError` (an entry an argument
  lacks, also a ``KeyError``).
* :class:`SolverError`: an estimator that could not produce an estimate (a rank-deficient system,
  a diverged filter, a failed smoother update).
* :class:`InternalError`: a check of the project's own invariants failed -- a defect in its code
  (or in what it assumes of GTSAM), not in the data or the arguments; also a ``RuntimeError``.

The classes that name a particular failure derive from these: ``datasets.errors.DataError``,
``smoother.errors.IndeterminantSystem``, ``smoother.ekf.filter.FilterDiverged``,
``smoother.fixed_lag.contract.FixedLagFailed``. The command line (``smoother.cli``) turns any of them into
a one-line message and an exit code: 2 for the data, the arguments or an estimator, 3 for an
:class:`InternalError`.
"""


class BoxplusError(Exception):
    """Base class of the exceptions this project raises."""


class InputError(BoxplusError, ValueError):
    """Bad input data or arguments: the message names what was wrong and what was expected."""


class InputTypeError(InputError, TypeError):
    """An argument of a kind the function cannot take; also a ``TypeError``."""


class MissingKeyError(InputError, KeyError):
    """An argument lacks an entry it must have; also a ``KeyError``. Its text is the message as
    given (a plain ``KeyError`` prints the repr of its key)."""

    def __str__(self) -> str:
        return Exception.__str__(self)


class SolverError(BoxplusError):
    """An estimator could not produce an estimate from the data it was given."""


class InternalError(BoxplusError, RuntimeError):
    """A check of the project's own invariants failed: a defect in this code, or in what it
    assumes of a library it calls, not in the data or the arguments. Also a ``RuntimeError``."""
