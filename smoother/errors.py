"""The smoother's errors (under :mod:`factors.errors`), and recognising GTSAM's
indeterminant-system exception."""
from factors.errors import InputError, SolverError


class UserError(InputError):
    """A bad command-line option or dataset spec (raised by ``smoother.commands`` and
    ``smoother.sources``, never by the library): the message names the option and what was expected."""


class IndeterminantSystem(SolverError):
    """The linearised system is rank-deficient: some variable is not constrained by the factors.
    ``keyframe`` is the keyframe GTSAM was eliminating when it noticed (or None); ``free`` names
    the error-state components left free there, where known (or None)."""

    def __init__(self, message: str, keyframe: int | None = None, free: str | None = None):
        super().__init__(message)
        self.keyframe = keyframe
        self.free = free


def is_indeterminant(error: BaseException) -> bool:
    """Whether ``error`` is GTSAM's indeterminant-system exception. GTSAM 4.3.0 spells it
    "Indeterminate linear system ... near variable\n<key> (Symbol: ...)" (older versions
    "Indeterminant"): match both, and any whitespace before the key (``INDETERMINANT_KEY``)."""
    text = str(error)
    return "ndeterminate" in text or "ndeterminant" in text


#: The key GTSAM names in its indeterminant-system message (group 1).
INDETERMINANT_KEY = r"near variable\s+(\d+)"
