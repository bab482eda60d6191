"""SIGTERM and Ctrl-C through the command line's handler (smoother/cli.py): raised where the main
thread was interrupted, except inside a callback from native code (llvmlite's, in numba's compiler
and kernel cache), where an exception cannot unwind and the process crashed with SIGSEGV; there
the signal is sent again a moment later."""
from __future__ import annotations

import signal
import sys
import time
from types import SimpleNamespace

import pytest

from smoother.cli import in_native_callback, interrupt_handler, main
from smoother.commands import run as run_command
from smoother.errors import Terminated


def _frame_in(module: str):
    """A frame of a function of the module named ``module``, called from this one."""
    namespace = {"__name__": module, "sys": sys}
    exec("def here():\n    return sys._getframe()\n", namespace)
    return namespace["here"]()


def test_a_frame_is_in_a_native_callback_when_llvmlite_s_code_runs_it_or_called_it():
    assert in_native_callback(_frame_in("llvmlite.binding.executionengine"))
    assert not in_native_callback(_frame_in("numba.core.dispatcher"))
    assert not in_native_callback(sys._getframe())
    called_from_llvmlite = SimpleNamespace(f_globals={"__name__": "smoother.pipeline"},
                                           f_back=_frame_in("llvmlite.binding.ffi"))
    assert in_native_callback(called_from_llvmlite)


def test_the_handler_raises_outside_a_native_callback_and_sends_the_signal_again_inside_one():
    pending = []
    handler = interrupt_handler(Terminated, pending)
    with pytest.raises(Terminated):
        handler(signal.SIGTERM, sys._getframe())
    assert pending == []
    came = []
    previous = signal.signal(signal.SIGUSR1, lambda signum, frame: came.append(signum))
    try:
        assert handler(signal.SIGUSR1, _frame_in("llvmlite.binding.executionengine")) is None
        assert [signum for signum, _ in pending] == [signal.SIGUSR1]
        deadline = time.monotonic() + 5.0
        while not came and time.monotonic() < deadline:
            time.sleep(0.01)
    finally:
        signal.signal(signal.SIGUSR1, previous)
    assert came == [signal.SIGUSR1]
    with pytest.raises(KeyboardInterrupt):
        interrupt_handler(KeyboardInterrupt, [])(signal.SIGINT, sys._getframe())


def test_an_interrupt_inside_an_extension_s_initialisation_stops_the_command_as_one(monkeypatch, capsys):
    """SIGTERM while GTSAM's extension initialised (imported on a command's first use of it) came
    back as ``ImportError: initialization failed`` with a traceback; it is the termination it is."""
    def run(args):
        try:
            raise Terminated()
        except Terminated as error:
            raise ImportError("initialization failed") from error

    monkeypatch.setattr(run_command, "run", run)
    assert main(["run", "--no-progress"]) == 143
    assert capsys.readouterr().err.strip() == "smoother: terminated; files already written are complete and kept"
    monkeypatch.setattr(run_command, "run", lambda args: __import__("no_such_module_anywhere"))
    with pytest.raises(ImportError):
        main(["run", "--no-progress"])
