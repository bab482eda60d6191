"""Work made of many independent pieces on several threads (:func:`in_parallel`), and how many
threads it may use (:func:`thread_count`).

The preintegration's intervals are such work: the compiled IMU kernels release the GIL
(:data:`factors.compiled.recursion`), the work is cut into contiguous ranges that whichever
thread is free takes next, and each range writes only its own outputs, so the results do not
depend on the thread count. The threads come from one pool per process, started on first use.
:func:`interrupts_held` keeps Ctrl-C and SIGTERM out of the moments when a pool takes work (this
one's, or any other ``concurrent.futures`` pool's), and :func:`wait_interruptibly` lets them in
while the main thread waits for one.
"""
from __future__ import annotations

import os
import signal
import threading
from concurrent.futures import ALL_COMPLETED, FIRST_COMPLETED, ThreadPoolExecutor, wait
from contextlib import ExitStack, contextmanager

from factors.errors import InputError

#: A wait in the main thread wakes this often [s] (:func:`wait_interruptibly`).
SIGNAL_POLL_S = 0.1


def default_threads() -> int:
    """``BOXPLUS_THREADS`` if set (e.g. 1 when several processes share the cores), else the
    number of cores this process may run on."""
    text = os.environ.get("BOXPLUS_THREADS", "").strip()
    if text:
        if not text.isdigit() or int(text) < 1:
            raise InputError(f"BOXPLUS_THREADS: expected a whole number of threads >= 1, got {text!r}")
        return int(text)
    try:
        return len(os.sched_getaffinity(0))
    except AttributeError:  # not Linux
        return os.cpu_count() or 1


_threads = default_threads()
_pool: ThreadPoolExecutor | None = None
_pool_size = 0
#: Held while the pool is checked, replaced or given work: callers on several threads at once
#: must not submit to a pool that another has just shut down to replace it by a larger one.
_pool_lock = threading.Lock()


def forget_the_pool() -> None:
    """In a forked child: only the forking thread exists there, so the parent's pool has no
    workers and anything submitted to it would wait for ever (and the lock may have been held by
    another thread of the parent); the child starts its own."""
    global _pool, _pool_size, _pool_lock
    _pool, _pool_size, _pool_lock = None, 0, threading.Lock()


if hasattr(os, "register_at_fork"):
    os.register_at_fork(after_in_child=forget_the_pool)


def thread_count() -> int:
    """The number of threads :func:`in_parallel` may use now."""
    return _threads


def set_thread_count(n: int) -> None:
    """Let :func:`in_parallel` use at most ``n`` threads from now on in this process (e.g. in
    each worker of a process pool, so that the workers do not oversubscribe the cores; the
    default is :func:`default_threads`). Process-wide: not for changing the limit from several
    threads at once."""
    global _threads
    if isinstance(n, bool) or not isinstance(n, int) or n < 1:
        raise InputError(f"thread count: expected a whole number of threads >= 1, got {n!r}")
    _threads = n


@contextmanager
def thread_limit(n: int):
    """:func:`set_thread_count` inside the ``with`` block only (measurements and tests)."""
    before = _threads
    set_thread_count(n)
    try:
        yield
    finally:
        set_thread_count(before)


#: Pieces per thread that :func:`in_parallel` cuts the work into: threads that finish early take
#: more, so a thread that starts late (a pool worker wakes up tens of microseconds after the
#: hand-over) or runs slower (a core shared with another process) delays the whole by a fraction
#: of a piece, not by its whole share.
PIECES_PER_THREAD = 8


class _Ranges:
    """The ranges of one :func:`in_parallel` call and their hand-out: ``items`` numbers the
    ranges of ``task`` ``0 .. pieces - 1``, then (with ``then``) those of ``then``; one lock
    guards the progress of the scans and the failures.

    Ctrl-C: a KeyboardInterrupt reaches the calling thread between any two bytecodes, also
    between taking a range and running it. Every exception that leaves :meth:`run` is therefore
    recorded as a failure (no new range starts, the threads waiting for a scan wake up and stop),
    and the lock is a plain ``threading.Lock``, whose ``with`` cannot be left held by an
    interrupt (a ``Condition``'s own ``__enter__`` is Python code and can)."""

    def __init__(self, bounds: list, task, scan, then):
        self.bounds, self.task, self.scan, self.then = bounds, task, scan, then
        self.pieces = len(bounds) - 1
        self.items = iter(range(self.pieces * (1 if then is None else 2)))  # next() is atomic under the GIL
        self.failures: list[tuple[int, BaseException]] = []
        self.lock = threading.Lock()
        self.progress = threading.Condition(self.lock)
        self.tasks_done = [False] * self.pieces
        self.scanned = 0  # ranges 0 .. scanned - 1 are scanned
        self.scanning = False  # a thread is scanning: it also takes the ranges finished meanwhile

    def run(self) -> None:
        """Take ranges until none is left or one has failed (the thread whose stage failed
        re-raises; the others stop at their next range)."""
        current = -1  # the item (or scan) being handled, for the order of the failures
        try:
            for item in self.items:
                current = item
                if self.failures:
                    return
                stage, p = divmod(item, self.pieces)
                if stage == 0:
                    self.task(self.bounds[p], self.bounds[p + 1])
                    if self.scan is not None:
                        for current in self._scans_after(p):
                            self.scan(self.bounds[current], self.bounds[current + 1])
                elif self._scanned(p):
                    self.then(self.bounds[p], self.bounds[p + 1])
                else:
                    return
        except BaseException as error:
            self.fail(current, error)
            raise

    def fail(self, index: int, error: BaseException) -> None:
        """Record a failure (of item or scan ``index``; -1: outside the ranges, e.g. the calling
        thread interrupted while it waits) and wake the threads waiting for a scan."""
        with self.lock:
            self.failures.append((index, error))
            self.progress.notify_all()

    def _scans_after(self, p: int):
        """The ranges to scan (in order) now that range ``p``'s task has finished: those from
        the first unscanned one whose tasks have all finished, unless another thread is scanning
        (it takes them then). Each is counted as scanned when the caller asks for the next."""
        with self.lock:
            self.tasks_done[p] = True
            if self.scanning:
                return
            self.scanning = True
        while True:
            with self.lock:
                s = self.scanned
                if s == self.pieces or not self.tasks_done[s] or self.failures:
                    self.scanning = False
                    return
            yield s
            with self.lock:
                self.scanned = s + 1
                self.progress.notify_all()

    def _scanned(self, p: int) -> bool:
        """Wait until range ``p`` is scanned; False if a range failed meanwhile. (Every task range
        is handed out before any ``then`` range, so the ranges waited for are running on other
        threads.) The calling thread waits here too: in steps of :data:`SIGNAL_POLL_S`, so that a
        Ctrl-C the kernel hands to another thread reaches it (:func:`wait_interruptibly`)."""
        with self.lock:
            while self.scanned <= p and not self.failures:
                self.progress.wait(SIGNAL_POLL_S)
            return not self.failures


@contextmanager
def interrupts_held():
    """Ctrl-C and SIGTERM held back inside the block (in the main thread, where Python runs signal
    handlers; elsewhere nothing changes), then raised again, in the order they came, through the
    handlers that were set. Their handlers raise: raised inside
    :meth:`ThreadPoolExecutor.submit`, between its taking a lock and the ``with`` block that
    releases it, the exception left the executors' global shutdown lock held, and the process hung
    at exit waiting for it (a process stopped by SIGTERM during its preintegration). Each handler
    is put back whatever happens meanwhile; one set outside Python (read as None: it could not be
    put back) is left alone."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    held = []
    try:
        with ExitStack() as restore:
            for s in (signal.SIGINT, signal.SIGTERM):
                previous = signal.getsignal(s)
                if previous is not None:
                    signal.signal(s, lambda signum, frame: held.append(signum))
                    restore.callback(signal.signal, s, previous)
            yield
    finally:
        for signum in dict.fromkeys(held):
            signal.raise_signal(signum)


def wait_interruptibly(futures, return_when: str = ALL_COMPLETED) -> tuple[set, set]:
    """:func:`concurrent.futures.wait` (no timeout) in steps of :data:`SIGNAL_POLL_S`. Python runs
    a signal's handler in the main thread, but the kernel may hand a process's signal to any of its
    threads that does not block it; a main thread blocked in one long lock wait is then never
    woken, and Ctrl-C or SIGTERM waits for the futures (seen on a pool of threads: a Ctrl-C that
    waited for its tasks' 30-s timeout). Woken every step, it runs the handler within one."""
    while True:
        done, pending = wait(futures, timeout=SIGNAL_POLL_S, return_when=return_when)
        if not pending or (done and return_when == FIRST_COMPLETED):
            return done, pending


def _wait_for(others: list, ranges: _Ranges) -> None:
    """Wait until the pool's share of ``ranges`` has finished, also through Ctrl-C: an interrupt
    meanwhile is recorded as a failure (so no new range starts) and raised once all have."""
    interrupt = None
    while True:
        try:
            wait_interruptibly(others)
            break
        except BaseException as error:  # noqa: BLE001 -- recorded, raised once every range has finished
            ranges.fail(-1, error)
            interrupt = interrupt or error
    if interrupt is not None:
        raise interrupt


def in_parallel(task, n: int, min_items: int, scan=None, then=None) -> None:
    """``task(lo, hi)`` over contiguous ranges that cover ``range(n)``, each at least
    ``min_items`` long (so small jobs stay on the calling thread, where a thread hand-over would
    cost more than it saves), on up to :func:`thread_count` threads. ``task`` must release the GIL
    for the threads to run at once (a :data:`factors.compiled.recursion` kernel does), must write disjoint outputs
    per range and must not call :func:`in_parallel` itself. Safe to call from several threads at
    once.

    The ranges (up to :data:`PIECES_PER_THREAD` per thread) are handed out in order to whichever
    thread is free: the calling thread and workers of a pool started on first use. Which thread
    runs a range does not change what it computes. After a range fails no new one is started;
    every range that started has finished when this returns or raises (also after a Ctrl-C); an
    exception of the calling thread is raised first, else the earliest failed range's (the
    ranges of ``task`` count before those of ``then``).

    With ``scan`` and ``then`` (work whose second parallel part needs a sequential pass over the
    first part's results, such as the preintegration's reference chain), each range goes through
    three stages in one hand-over: ``task(lo, hi)``; ``scan(lo, hi)``, for one range at a time in
    the order of the ranges, as soon as its task and the previous range's scan have finished (run
    by the thread that finished the later of them); ``then(lo, hi)``, once its range's scan has
    finished. On one thread: ``task(0, n)``, ``scan(0, n)``, ``then(0, n)``. This saves the hand-over
    of a second call and the wait between them (about 0.2 ms of 4 in the preintegration of a
    minute of data) and runs the scan while the other threads work."""
    if (scan is None) != (then is None):
        raise InputError("in_parallel: expected both scan and then, or neither")
    parts = max(1, min(_threads, n // max(1, min_items)))
    if parts == 1:
        for stage in (task, scan, then):
            if stage is not None:
                stage(0, n)
        return
    global _pool, _pool_size
    pieces = min(n // max(1, min_items), parts * PIECES_PER_THREAD)
    ranges = _Ranges([n * p // pieces for p in range(pieces + 1)], task, scan, then)
    others = []
    try:
        with interrupts_held(), _pool_lock:
            if _pool_size < parts - 1:
                if _pool is not None:
                    _pool.shutdown(wait=False)  # what was queued there still runs
                _pool, _pool_size = ThreadPoolExecutor(max_workers=parts - 1, thread_name_prefix="boxplus"), parts - 1
            for _ in range(parts - 1):
                others.append(_pool.submit(ranges.run))
        ranges.run()
    except BaseException as error:
        if not any(error is failed for _, failed in ranges.failures):  # raised outside ranges.run
            ranges.fail(-1, error)
        raise
    finally:
        _wait_for(others, ranges)
    if ranges.failures:
        raise min(ranges.failures, key=lambda failure: failure[0])[1]
