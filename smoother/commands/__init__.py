"""Sub-commands of the ``smoother`` command line, one module each, and the checks they share:
each raises :class:`smoother.errors.UserError` naming the option, before any work starts."""
from __future__ import annotations

import os
from pathlib import Path

from smoother.errors import UserError


def output_directory(path) -> Path:
    """``path`` as a directory that exists (created with its parents) and takes new files.
    Called before the computation, so that a bad ``--out`` does not lose its results."""
    path = Path(path)
    try:
        path.mkdir(parents=True, exist_ok=True)
    except OSError as error:
        reason = "a file of that name exists" if isinstance(error, FileExistsError) else error.strerror or error
        raise UserError(f"--out {path}: cannot create the directory ({reason})") from None
    if not os.access(path, os.W_OK | os.X_OK):
        raise UserError(f"--out {path}: the directory is not writable")
    return path
