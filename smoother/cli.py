"""The ``smoother`` command line: one sub-command per module, each module exposing
``register(subparsers)`` that adds its parser and sets ``handler``."""
from __future__ import annotations

import argparse
import contextlib
import importlib
import os
import signal
import sys
import threading
import warnings

from factors.errors import BoxplusError, InternalError
from factors.kernel_caches import ensure_fresh_caches
from smoother.errors import Terminated, UserError, interruption

#: Modules that contribute sub-commands, in the order they are listed by ``smoother --help``.
COMMAND_MODULES = [
    "smoother.commands.run",
    "smoother.commands.fleet",
    "smoother.commands.crosscheck",
    "smoother.commands.montecarlo",
    "smoother.commands.check_jacobians",
    "smoother.commands.evaluate",
    "smoother.commands.plot",
    "smoother.commands.allan",
]


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="smoother",
        description="IMU factor-graph smoothing, fixed-lag smoothing and the primer's EKF on GTSAM.",
    )
    sub = parser.add_subparsers(dest="command", required=True)
    for name in COMMAND_MODULES:
        importlib.import_module(name).register(sub)
    return parser


#: The longest error line printed: an error quotes the value it refuses, which can be as long as
#: the file it came from.
MAX_ERROR_CHARS = 1000


def _format_warning(message, category, filename, lineno, line=None) -> str:
    return f"smoother: warning: {message}\n"


def _raise_terminated(signum, frame):
    raise Terminated()


@contextlib.contextmanager
def _sigterm_raises():
    """Inside the block SIGTERM raises :class:`~smoother.errors.Terminated` (in the main thread;
    elsewhere signals cannot be handled and nothing changes); the previous handler afterwards."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    previous = signal.signal(signal.SIGTERM, _raise_terminated)
    try:
        yield
    finally:
        signal.signal(signal.SIGTERM, previous)


def main(argv: list[str] | None = None) -> int:
    """Run the command line ``argv`` (default ``sys.argv[1:]``) and return its exit code. The
    compiled kernels' disk caches are checked first, before any kernel runs
    (:func:`factors.kernel_caches.ensure_fresh_caches`: a cached kernel that inlines an edited
    module's kernels is compiled again)."""
    ensure_fresh_caches()
    previous, warnings.formatwarning = warnings.formatwarning, _format_warning  # one line per warning
    try:
        with _sigterm_raises():
            return _main(argv)
    finally:
        warnings.formatwarning = previous


def _main(argv: list[str] | None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    try:
        return int(args.handler(args) or 0)
    except KeyboardInterrupt as error:  # Ctrl-C, or SIGTERM (Terminated)
        stopped, code = interruption(error)
        print(f"smoother: {stopped}; files already written are complete and kept", file=sys.stderr)
        return code
    except (BoxplusError, ValueError, OSError, MemoryError, RuntimeError, IndexError, ArithmeticError) as error:
        # The library's own errors (factors.errors: bad input naming the file, field, option or
        # time; an estimator that could not finish; a broken invariant of its own, which is an
        # internal failure like those below), other bad values (ValueError), files that
        # cannot be written (OSError; datasets.atomic.atomic_write names the file), data too large
        # for the memory (NumPy names the size) and failures inside GTSAM or NumPy: one line, no
        # traceback (SMOOTHER_DEBUG=1 shows it for all but a bad command-line option).
        if os.environ.get("SMOOTHER_DEBUG") and not isinstance(error, UserError):
            raise
        text = (f"{error.filename}: {error.strerror}" if isinstance(error, OSError) and error.filename
                and error.strerror else str(error)).strip()
        first = text.splitlines()[0] if text else ""
        if len(first) > MAX_ERROR_CHARS:  # a value quoted whole: a 300 000-character topic, a list of a thousand
            first = f"{first[:MAX_ERROR_CHARS]}... ({len(first) - MAX_ERROR_CHARS} more characters)"
        if isinstance(error, MemoryError):
            dataset = str(getattr(args, "dataset", None) or "synthetic")
            simulated = getattr(args, "rig", None) is None and dataset.startswith("synthetic")
            hint = "; try a shorter --duration" if "duration" in args and simulated else ""
            print(f"smoother: error: out of memory ({first or 'no details'}){hint}", file=sys.stderr)
            return 2
        user = isinstance(error, (BoxplusError, ValueError, OSError)) and not isinstance(error, InternalError)
        kind = "error" if user else f"internal failure ({type(error).__name__})"
        print(f"smoother: {kind}: {first}", file=sys.stderr)
        return 2 if user else 3


if __name__ == "__main__":
    sys.exit(main())
