"""Running a call on hostile input where a regression can neither hang the test run nor exhaust its
memory (:func:`isolated`): the ``isolated`` fixtures of the datasets and command-line tests.

Import as ``import isolation`` (``tests/conftest.py`` puts this directory on ``sys.path``)."""
from __future__ import annotations

import os
import pickle
import resource
import select
import signal
from typing import NamedTuple

import pytest


class Outcome(NamedTuple):
    """How a call ended: ``raised`` the names of the exception's classes (its MRO; empty when it
    returned) and ``message`` its text."""

    raised: tuple[str, ...]
    message: str


def _address_space() -> int | None:
    """This process's virtual memory in bytes (Linux), or None."""
    try:
        with open("/proc/self/statm") as handle:
            return int(handle.read().split()[0]) * os.sysconf("SC_PAGE_SIZE")
    except (OSError, ValueError):
        return None


def _child(call, memory: int, write_fd: int) -> None:
    """Run ``call`` with at most ``memory`` bytes more address space, and write how it ended (a
    plain tuple: this module's own classes need not pickle by the name pytest gave it)."""
    try:
        size = _address_space()
        if size is not None:
            _, hard = resource.getrlimit(resource.RLIMIT_AS)
            limit = size + memory if hard == resource.RLIM_INFINITY else min(size + memory, hard)
            resource.setrlimit(resource.RLIMIT_AS, (limit, hard))
        call()
        ended = ((), "")
    except BaseException as error:  # noqa: BLE001 - every ending is reported to the parent
        ended = (tuple(c.__name__ for c in type(error).__mro__), str(error))
    with os.fdopen(write_fd, "wb") as pipe:
        pipe.write(pickle.dumps(ended))


def isolated(call, seconds: float = 10.0, memory: int = 2 << 30) -> Outcome:
    """The :class:`Outcome` of ``call()`` run in a forked copy of this process, which is killed
    after ``seconds`` (a reader blocked on a pipe) and given ``memory`` bytes more address space
    than this process has (a reader of ``/dev/zero`` or of a "billion laughs" gets a MemoryError,
    not the machine's memory); the test fails when the call runs out of either."""
    if not hasattr(os, "fork"):
        pytest.skip("needs fork")
    read_fd, write_fd = os.pipe()
    pid = os.fork()
    if pid == 0:  # the child: never returns into pytest
        try:
            os.close(read_fd)
            _child(call, memory, write_fd)
        finally:
            os._exit(0)
    os.close(write_fd)
    with os.fdopen(read_fd, "rb") as pipe:
        if not select.select([pipe], [], [], seconds)[0]:
            os.kill(pid, signal.SIGKILL)
            os.waitpid(pid, 0)
            pytest.fail(f"still running after {seconds} s (killed)")
        data = pipe.read()
    _, status = os.waitpid(pid, 0)
    if not data:
        pytest.fail(f"the call's process died without a result (wait status {status:#x})")
    outcome = Outcome(*pickle.loads(data))
    if "MemoryError" in outcome.raised:
        pytest.fail(f"ran out of its {memory} bytes of memory: {outcome.message}")
    return outcome

