"""The smoother's errors (under :mod:`factors.errors`), a stop by SIGTERM, and recognising
GTSAM's indeterminant-system exception."""
import re
import signal

from factors.errors import InputError, SolverError


class UserError(InputError):
    """A bad command-line option or dataset spec (raised by ``smoother.commands`` and
    ``smoother.commands.dataset_specs``, never by the library): the message names the option and what was expected."""


class Terminated(KeyboardInterrupt):
    """SIGTERM (what ``kill``, ``timeout``, systemd and job schedulers send), raised in the main
    thread as Ctrl-C raises ``KeyboardInterrupt`` (``smoother.cli`` installs the handler): whatever
    keeps finished work on Ctrl-C keeps it on SIGTERM too."""


def interruption(error: KeyboardInterrupt) -> tuple[str, int]:
    """``(what stopped the command, its exit code)``: ``("terminated", 143)`` for SIGTERM,
    ``("interrupted", 130)`` for Ctrl-C -- 128 plus the signal's number, as shells report it."""
    if isinstance(error, Terminated):
        return "terminated", 128 + signal.SIGTERM
    return "interrupted", 128 + signal.SIGINT


class NotConverged(UserWarning):
    """An optimiser stopped at its iteration limit still lowering the cost: the estimate may be off
    the optimum. Its own category, so that a caller solving intermediate estimates (a noise fit's)
    can hold it back and say it only of the estimate it returns."""


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
    "Indeterminant"): match both."""
    text = str(error)
    return "ndeterminate" in text or "ndeterminant" in text



def indeterminant_key(error: BaseException) -> int | None:
    """The key GTSAM names in its indeterminant-system message ("near variable\n<key>", any
    whitespace before the key), or None."""
    match = re.search(r"near variable\s+(\d+)", str(error))
    return int(match.group(1)) if match else None
