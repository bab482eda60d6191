"""Sub-commands of the ``smoother`` command line, one module each, and the checks they share:
each raises :class:`smoother.errors.UserError` naming the option, before any work starts.
:mod:`smoother.commands.run_directory` is ``smoother run``'s output directory."""
from __future__ import annotations

import math
import os
from pathlib import Path

from smoother.errors import UserError

#: Longest ``--duration`` [s] accepted: over three years, 2e10 IMU samples at the simulator's
#: 200 Hz, some 20 TB for the simulation alone (about 1 kB per sample). Shorter runs that do not
#: fit in memory end in a one-line out-of-memory error (smoother.cli).
MAX_DURATION_S = 1e8


def positive(option: str, value: float, what: str = "a number") -> None:
    """``value`` must be a finite number > 0 (a rate, a sigma, a time)."""
    if not (math.isfinite(value) and value > 0):
        raise UserError(f"{option}: expected {what} > 0 (finite), got {value!r}")


def duration(value: float) -> None:
    """``--duration``: simulated seconds, at most :data:`MAX_DURATION_S`."""
    positive("--duration", value, "a duration in seconds")
    if value > MAX_DURATION_S:
        raise UserError(f"--duration: expected at most {MAX_DURATION_S:.0f} s (over three years: the simulation "
                        f"alone would need more than 20 TB of memory), got {value!r}")


def at_least(option: str, value: int, low: int) -> None:
    """``value`` must be an integer >= ``low`` (a count, a seed)."""
    if value < low:
        raise UserError(f"{option}: expected an integer >= {low}, got {value}")


def fraction(option: str, value: float) -> None:
    """``value`` must be a fraction in [0, 1]."""
    if not 0.0 <= value <= 1.0:
        raise UserError(f"{option}: expected a fraction in [0, 1], got {value!r}")


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
