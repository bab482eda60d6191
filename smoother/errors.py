"""Errors the command line reports in one line, without a traceback."""


class UserError(Exception):
    """Bad input or options: the message names the file, line, field or option and what was expected."""
