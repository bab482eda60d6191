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


#: Modules whose Python code runs as callbacks from native code: llvmlite's, inside numba's
#: compiler and its kernels' disk cache. An exception raised there cannot unwind through the native
#: frames (ctypes prints it and hands LLVM a buffer never filled in): SIGTERM while a kernel was
#: loaded from its cache killed the process with SIGSEGV instead of stopping it.
NATIVE_CALLBACK_MODULES = ("llvmlite.",)
#: An interrupt that comes inside such a callback is sent again after this long [s].
REDELIVERY_S = 0.05


def in_native_callback(frame) -> bool:
    """Whether ``frame`` (a signal handler's: where the main thread was interrupted) or a frame it
    was called from belongs to :data:`NATIVE_CALLBACK_MODULES`."""
    while frame is not None:
        if frame.f_globals.get("__name__", "").startswith(NATIVE_CALLBACK_MODULES):
            return True
        frame = frame.f_back
    return False


def interrupt_handler(error: type[KeyboardInterrupt], pending: list):
    """A signal handler raising ``error`` where the main thread was interrupted, except inside a
    native callback (:func:`in_native_callback`): there it sends the signal to the process again
    :data:`REDELIVERY_S` later, until it comes where it can be raised; each such sending is
    appended to ``pending`` as ``(signum, timer)``."""
    def handler(signum, frame):
        if in_native_callback(frame):
            again = threading.Timer(REDELIVERY_S, os.kill, (os.getpid(), signum))
            again.daemon = True
            pending.append((signum, again))
            again.start()
            return
        raise error()

    return handler


def _send_pending(pending: list) -> None:
    """Each signal of ``pending`` (:func:`interrupt_handler`) whose sending has not happened yet,
    raised now instead, for the handler in place."""
    for signum, timer in pending:
        if timer.is_alive():
            timer.cancel()
            signal.raise_signal(signum)


@contextlib.contextmanager
def _interrupts_raise():
    """Inside the block SIGTERM raises :class:`~smoother.errors.Terminated` and Ctrl-C (where
    Python's own handler is set) ``KeyboardInterrupt``, both through :func:`interrupt_handler`
    (in the main thread; elsewhere signals cannot be handled and nothing changes); the previous
    handlers afterwards, and through them a signal whose sending again was still to come."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    pending: list = []
    with contextlib.ExitStack() as restore:
        restore.callback(_send_pending, pending)  # last: once the handlers are back
        restore.callback(signal.signal, signal.SIGTERM,
                         signal.signal(signal.SIGTERM, interrupt_handler(Terminated, pending)))
        if signal.getsignal(signal.SIGINT) is signal.default_int_handler:
            restore.callback(signal.signal, signal.SIGINT,
                             signal.signal(signal.SIGINT, interrupt_handler(KeyboardInterrupt, pending)))
        yield


def main(argv: list[str] | None = None) -> int:
    """Run the command line ``argv`` (default ``sys.argv[1:]``) and return its exit code. The
    compiled kernels' disk caches are checked first, before any kernel runs
    (:func:`factors.kernel_caches.ensure_fresh_caches`: a cached kernel that inlines an edited
    module's kernels is compiled again)."""
    ensure_fresh_caches()
    previous, warnings.formatwarning = warnings.formatwarning, _format_warning  # one line per warning
    try:
        with _interrupts_raise():
            return _main(argv)
    finally:
        warnings.formatwarning = previous


def _main(argv: list[str] | None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    try:
        return int(args.handler(args) or 0)
    except (KeyboardInterrupt, ImportError) as error:
        # Ctrl-C, or SIGTERM (Terminated); one that came inside an extension module's initialisation
        # (GTSAM's, imported on first use) comes back as that import's failure, caused by it
        interrupt = error if isinstance(error, KeyboardInterrupt) else error.__cause__
        if not isinstance(interrupt, KeyboardInterrupt):
            raise
        stopped, code = interruption(interrupt)
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
