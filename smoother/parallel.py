"""Many independent tasks at once, on this machine or on a Dask cluster: the one loop of
``smoother montecarlo`` (:mod:`smoother.evaluation.montecarlo`) and ``smoother fleet``
(:mod:`smoother.commands.fleet_runner`).

* **Where** the tasks run, a :class:`Workers`: :func:`in_this_thread`, one after the other;
  :func:`processes`, a pool of processes whose compiled work shares this process's threads;
  :func:`threads`, a pool of threads (for tasks that wait for a child process); :func:`dask`, the
  workers of a Dask scheduler (the optional dependency ``distributed``).
* **A bounded window** (:func:`run_all`): at most :data:`AHEAD` tasks per worker are submitted and
  unfinished at a time, refilled as results come back (a Dask cluster that grows gets more at
  once), so that a stop has few tasks to cancel and a cluster holds few results; each result is
  passed on in the calling thread as its task ends, in the order they end.
* **Failures**: a task that raises an exception is handed to ``on_failure(item, error)``, whose
  return is its result (a fleet's failed recording, :func:`failure_line` its one line); without
  ``on_failure`` the first one is raised, after the tasks not started have been cancelled.
* **Stopping**: Ctrl-C or SIGTERM (``KeyboardInterrupt``; :class:`smoother.errors.Terminated`)
  while tasks run: nothing more is submitted, the tasks not started are cancelled,
  ``on_stop(signum)`` is called (a fleet passes the signal on to its recordings), the results of
  the tasks already running on this machine are passed on as they end (a task that the signal
  stopped with an exception of its own has none), and the interruption is raised again. Tasks
  running on a Dask worker are left to finish there.
"""
from __future__ import annotations

import itertools
import signal
from abc import ABC, abstractmethod
from concurrent.futures import FIRST_COMPLETED, Future, ProcessPoolExecutor, ThreadPoolExecutor

from factors.errors import InputError
from factors.threads import interrupts_held, set_thread_count, thread_count, wait_interruptibly
from smoother.errors import Terminated

#: Tasks submitted ahead per worker (the window of :func:`run_all`).
AHEAD = 2
#: The fewest workers a Dask window is made for (a cluster whose workers have not joined yet).
MIN_DASK_THREADS = 4


class Workers(ABC):
    """Where :func:`run_all` runs tasks; a context manager that releases them (a pool shut down,
    a Dask client closed) on leaving."""

    #: Whether the tasks running when a stop comes are waited for and their results passed on.
    finish_running = True

    @abstractmethod
    def window(self) -> int:
        """How many tasks may be submitted and unfinished at once now."""

    @abstractmethod
    def submit(self, function, item):
        """A future of ``function(item)``."""

    def first_done(self, futures) -> set:
        """Wait until one of ``futures`` is done (a Ctrl-C or SIGTERM seen meanwhile,
        :func:`factors.threads.wait_interruptibly`); those done."""
        return wait_interruptibly(futures, FIRST_COMPLETED)[0]

    def cancel(self, futures) -> None:
        """Cancel the ``futures`` whose tasks have not started."""
        for future in futures:
            future.cancel()

    def close(self) -> None:
        """Release the workers; tasks not started are cancelled, running ones are not waited for."""

    def __enter__(self) -> Workers:
        return self

    def __exit__(self, *exc) -> None:
        self.close()


class _InThisThread(Workers):
    def window(self) -> int:
        return 1

    def submit(self, function, item) -> Future:
        """Run the task now; its result or exception in a finished future. A ``KeyboardInterrupt``
        inside it is a stop, raised at once."""
        future: Future = Future()
        try:
            future.set_result(function(item))
        except Exception as error:  # noqa: BLE001 -- the task's failure, handled as a pool's would be
            future.set_exception(error)
        return future


class _Pool(Workers):
    def __init__(self, executor, size: int):
        self.executor, self.size = executor, size

    def window(self) -> int:
        return AHEAD * self.size

    def submit(self, function, item) -> Future:
        return self.executor.submit(function, item)

    def close(self) -> None:
        self.executor.shutdown(wait=False, cancel_futures=True)


class _Dask(Workers):
    finish_running = False

    def __init__(self, client, wait_for):
        self.client, self._wait = client, wait_for

    def window(self) -> int:
        return AHEAD * max(sum(self.client.nthreads().values()), MIN_DASK_THREADS)

    def submit(self, function, item):
        return self.client.submit(function, item, pure=False)

    def first_done(self, futures) -> set:
        return self._wait(list(futures), return_when="FIRST_COMPLETED").done

    def cancel(self, futures) -> None:
        if futures:
            self.client.cancel(list(futures))

    def close(self) -> None:
        self.client.close()


def in_this_thread() -> Workers:
    """The tasks one after the other in the calling thread, in the order given."""
    return _InThisThread()


def process_pool(workers: int) -> ProcessPoolExecutor:
    """A pool of ``workers`` processes whose compiled work shares this process's threads among
    them (:func:`factors.threads.in_parallel` in each would otherwise use every core, ``workers``
    times over)."""
    share = max(1, thread_count() // workers)
    return ProcessPoolExecutor(max_workers=workers, initializer=set_thread_count, initargs=(share,))


def processes(workers: int) -> Workers:
    """``workers`` processes of :func:`process_pool` (tasks and their items must pickle)."""
    _check_count(workers)
    return _Pool(process_pool(workers), workers)


def threads(workers: int) -> Workers:
    """A pool of ``workers`` threads of this process, for tasks that mostly wait (for a child
    process); the calling thread stays free to handle signals."""
    _check_count(workers)
    return _Pool(ThreadPoolExecutor(max_workers=workers, thread_name_prefix="task"), workers)


def dask(address: str) -> Workers:
    """The workers of the Dask scheduler at ``address`` (``distributed.Client(address)``); an
    :class:`~factors.errors.InputError` without the optional dependency ``distributed`` or when
    the scheduler cannot be reached."""
    try:
        from distributed import Client
        from distributed import wait as wait_for
    except ImportError:
        raise InputError("a Dask scheduler needs Dask's distributed package, an optional dependency: "
                         "pip install 'boxplus-smoother[dask]'") from None
    try:
        client = Client(address)
    except (OSError, ValueError, TypeError) as error:  # a timeout is an OSError
        raise InputError(f"the Dask scheduler {address} cannot be reached ({type(error).__name__}: {error})") from None
    return _Dask(client, wait_for)


def _check_count(workers: int) -> None:
    if isinstance(workers, bool) or not isinstance(workers, int) or workers < 1:
        raise InputError(f"workers: expected a whole number >= 1, got {workers!r}")


def failure_line(error: BaseException) -> str:
    """What a task's exception says, in one line: its type and the first line of its message."""
    return f"{type(error).__name__}: {error}".splitlines()[0]


def run_all(function, items, workers: Workers, on_result, on_failure=None, on_stop=None) -> None:
    """``function(item)`` for every item of ``items`` on ``workers``, a window of tasks at a time;
    ``on_result(result)`` in the calling thread as each ends, in the order they end. Failures and
    stopping as the module docstring says: ``on_failure(item, error)`` makes a failed task's
    result (else the failure is raised), ``on_stop(signum)`` is called on Ctrl-C (SIGINT) or
    SIGTERM before the running tasks' results are passed on and the interruption raised again."""
    pending = iter(items)
    running: dict = {}  # future -> item

    def refill() -> None:
        # signals held until every future submitted is recorded: one raised between a submission
        # and its record would lose that task's result (and inside ThreadPoolExecutor.submit it
        # could leave the executors' lock held)
        with interrupts_held():
            for item in itertools.islice(pending, max(0, workers.window() - len(running))):
                running[workers.submit(function, item)] = item

    def outcome(future, item):
        try:
            return future.result()
        except Exception as error:
            if on_failure is None:
                raise
            return on_failure(item, error)

    try:
        refill()
        while running:
            for future in workers.first_done(running):
                on_result(outcome(future, running.pop(future)))
            refill()
    except KeyboardInterrupt as error:
        workers.cancel(running)
        if on_stop is not None:
            on_stop(signal.SIGTERM if isinstance(error, Terminated) else signal.SIGINT)
        if workers.finish_running:
            for future, item in running.items():
                if future.cancelled():
                    continue
                wait_interruptibly([future])  # a second Ctrl-C here ends the waiting
                try:
                    result = outcome(future, item)
                except BaseException:  # noqa: BLE001 -- the task stopped by the signal too: no result
                    continue
                on_result(result)
        raise
    except BaseException:
        workers.cancel(running)
        raise
