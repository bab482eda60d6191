"""Errors the command line reports in one line, without a traceback."""


class UserError(Exception):
    """Bad input or options: the message names the file, line, field or option and what was expected."""


class IndeterminantSystem(UserError):
    """The linearised system is rank-deficient: some variable is not constrained by the factors.
    ``keyframe`` is the keyframe GTSAM was eliminating when it noticed (or None)."""

    def __init__(self, message: str, keyframe: int | None = None):
        super().__init__(message)
        self.keyframe = keyframe
