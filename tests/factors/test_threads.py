"""factors.threads: work in contiguous pieces on several threads (failures, interrupts, the
pipeline of task, scan and then), the thread count, and signals held while a pool takes work."""
from __future__ import annotations

import multiprocessing
import os
import signal
import sys
import threading
import time

import numpy as np
import pytest

from factors import threads


def test_in_parallel_covers_the_range_in_contiguous_disjoint_pieces():
    seen = []
    with threads.thread_limit(3):
        threads.in_parallel(lambda lo, hi: seen.append((lo, hi)), 10, 2)
    assert sorted(seen) == [(0, 2), (2, 4), (4, 6), (6, 8), (8, 10)]  # as many as min_items allows
    seen.clear()
    with threads.thread_limit(2):  # at most PIECES_PER_THREAD per thread
        threads.in_parallel(lambda lo, hi: seen.append((lo, hi)), 100, 1)
    pieces = sorted(seen)
    assert len(pieces) == 2 * threads.PIECES_PER_THREAD
    assert pieces[0][0] == 0 and pieces[-1][1] == 100
    assert all(a[1] == b[0] for a, b in zip(pieces[:-1], pieces[1:]))
    seen.clear()
    with threads.thread_limit(4):  # too few items for four pieces of at least 4
        threads.in_parallel(lambda lo, hi: seen.append((lo, hi)), 9, 4)
    assert sorted(seen) == [(0, 4), (4, 9)]
    seen.clear()
    threads.in_parallel(lambda lo, hi: seen.append((lo, hi)), 5, 32)  # small: the calling thread only
    assert seen == [(0, 5)]
    threads.in_parallel(lambda lo, hi: seen.append((lo, hi)), 0, 1)
    assert seen[-1] == (0, 0)


def test_in_parallel_raises_only_after_every_piece_has_finished():
    slow_started, finished = threading.Event(), []

    def task(lo, hi):
        if lo == 0:  # fails while the other piece is still running
            assert slow_started.wait(5)
            raise ValueError("piece 0")
        slow_started.set()
        time.sleep(0.3)
        finished.append(lo)

    with threads.thread_limit(2), pytest.raises(ValueError, match="piece 0"):
        threads.in_parallel(task, 2, 1)
    assert finished == [1]


def test_in_parallel_starts_no_piece_after_one_has_failed():
    other_started, started = threading.Event(), []

    def task(lo, hi):
        started.append(lo)
        if lo == 0:  # handed out first; fails once the other thread has taken its first piece
            assert other_started.wait(5)
            raise ValueError("piece 0")
        other_started.set()
        time.sleep(0.05)

    with threads.thread_limit(2), pytest.raises(ValueError, match="piece 0"):
        threads.in_parallel(task, 10, 1)
    assert sorted(started) == [0, 1]  # eight pieces never started


def test_in_parallel_gives_the_remaining_pieces_to_the_thread_that_is_free():
    """The calling thread is held up on its first piece until the worker has run seven (or 30 s
    pass): where the pieces go to the thread that is free, the worker runs all the others, however
    the two threads are scheduled (the worker's first piece waits for the caller to hold one)."""
    caller = threading.current_thread()
    ran_by = {}
    caller_holds_one, worker_ran_seven = threading.Event(), threading.Event()

    def task(lo, hi):
        if threading.current_thread() is caller:
            caller_holds_one.set()
            worker_ran_seven.wait(30.0)  # the calling thread is held up on its first piece
        else:
            caller_holds_one.wait(30.0)
        ran_by[lo] = threading.current_thread() is caller
        if sum(not by_caller for by_caller in ran_by.values()) == 7:
            worker_ran_seven.set()

    with threads.thread_limit(2):
        threads.in_parallel(task, 8, 1)
    assert sorted(ran_by) == list(range(8))
    assert sum(ran_by.values()) == 1  # the worker ran the other seven


def test_in_parallel_raises_the_calling_threads_own_error_first():
    caller = threading.current_thread()

    def task(lo, hi):
        if threading.current_thread() is caller:
            time.sleep(0.1)  # the worker fails first
            raise ValueError("the calling thread's error")
        time.sleep(0.02)
        raise ValueError("a worker's error")

    with threads.thread_limit(2), pytest.raises(ValueError, match="the calling thread's error"):
        threads.in_parallel(task, 10, 1)


def test_in_parallel_from_several_threads_at_once_while_the_pool_grows():
    """Callers on twelve threads at once, each asking for more pieces than the pool has workers
    (so it is replaced by a larger one while others submit to it), with the interpreter switching
    threads as often as it can: every piece runs exactly once and nothing fails. (Without the
    lock, about one round in five raised "cannot schedule new futures after shutdown".)"""
    callers, rounds = 12, 100
    switch = sys.getswitchinterval()
    sys.setswitchinterval(1e-6)
    try:
        for _ in range(rounds):
            threads.forget_the_pool()
            seen = [[] for _ in range(callers)]
            errors = []
            start = threading.Barrier(callers)

            def caller(i, seen=seen, errors=errors, start=start):
                def piece(lo, hi):
                    for _ in range(200):  # some bytecode, so that the callers overlap
                        pass
                    seen[i].append((lo, hi))

                start.wait()
                try:
                    threads.in_parallel(piece, i + 2, 1)
                except Exception as error:  # noqa: BLE001  (collected, asserted below)
                    errors.append(repr(error))

            with threads.thread_limit(callers + 4):
                spawned = [threading.Thread(target=caller, args=(i,)) for i in range(callers)]
                for thread in spawned:
                    thread.start()
                for thread in spawned:
                    thread.join(timeout=60)
            assert errors == []
            for i, pieces in enumerate(seen):
                assert sorted(pieces) == [(p, p + 1) for p in range(i + 2)]
    finally:
        sys.setswitchinterval(switch)


def _pipeline_log():
    """``(log, stage)``: ``stage(name, delay_for=None)`` is a ``(lo, hi)`` callable that appends
    ``(name, "start"/"end", lo, hi)`` to ``log``, sleeping in between for the ranges ``delay_for``
    picks (``delay_for(lo, calling_thread) -> seconds``)."""
    log, lock, caller = [], threading.Lock(), threading.current_thread()

    def stage(name, delay_for=None):
        def run(lo, hi):
            with lock:
                log.append((name, "start", lo, hi))
            if delay_for is not None:
                time.sleep(delay_for(lo, threading.current_thread() is caller))
            with lock:
                log.append((name, "end", lo, hi))
        return run

    return log, stage


def test_in_parallel_pipeline_scans_in_order_and_runs_each_then_after_its_scan():
    log, stage = _pipeline_log()
    slow_first = lambda lo, on_caller: 0.2 if lo == 0 else 0.002  # noqa: E731  (range 0's task holds up the scan)
    with threads.thread_limit(2):
        _within(20, lambda: threads.in_parallel(stage("task", slow_first), 20, 2, scan=stage("scan"),
                                                 then=stage("then")))
    at = {event[:3]: i for i, event in enumerate(log)}
    ranges = sorted({(lo, hi) for _, _, lo, hi in log})
    assert ranges[0][0] == 0 and ranges[-1][1] == 20 and len(ranges) == 10
    assert all(a[1] == b[0] for a, b in zip(ranges[:-1], ranges[1:]))
    scans = [(lo, hi) for name, when, lo, hi in log if name == "scan" and when == "start"]
    assert scans == ranges  # one at a time, in order, each once
    for (lo, hi), nxt in zip(ranges, ranges[1:] + [None]):
        for name in ("task", "scan", "then"):
            assert (name, "start", lo) in at and (name, "end", lo) in at  # every stage ran
        assert at[("task", "end", lo)] < at[("scan", "start", lo)] < at[("scan", "end", lo)] < at[("then", "start", lo)]
        if nxt is not None:
            assert at[("scan", "end", lo)] < at[("scan", "start", nxt[0])]
    # range 0's task ran 0.2 s: the other thread did the other tasks meanwhile, then waited for
    # scan 0 before its first "then" (no "then" started before the slow task ended)
    assert min(i for (name, when, lo), i in at.items() if name == "then") > at[("task", "end", 0)]


def test_in_parallel_pipeline_on_one_thread_is_the_three_stages_in_turn():
    log, stage = _pipeline_log()
    with threads.thread_limit(1):
        threads.in_parallel(stage("task"), 20, 2, scan=stage("scan"), then=stage("then"))
    assert [(name, when) for name, when, _, _ in log] == [
        ("task", "start"), ("task", "end"), ("scan", "start"), ("scan", "end"), ("then", "start"), ("then", "end")]
    assert {(lo, hi) for *_, lo, hi in log} == {(0, 20)}
    with pytest.raises(ValueError, match="both scan and then"):
        threads.in_parallel(stage("task"), 20, 2, scan=stage("scan"))


def test_in_parallel_pipeline_stops_at_a_failed_scan_and_raises_it():
    log, stage = _pipeline_log()
    record = stage("scan")

    def scan(lo, hi):
        record(lo, hi)
        if lo >= 6:
            raise ValueError(f"scan of {lo}")

    with threads.thread_limit(2), pytest.raises(ValueError, match="scan of 6"):
        _within(20, lambda: threads.in_parallel(stage("task", lambda lo, on_caller: 0.01), 20, 2, scan=scan,
                                                 then=stage("then")))
    scanned = [lo for name, when, lo, _ in log if name == "scan" and when == "start"]
    assert scanned == [0, 2, 4, 6]  # no scan after the failed one
    assert all(lo < 6 for name, _, lo, _ in log if name == "then")  # no "then" whose scan did not finish
    starts = {(name, lo) for name, when, lo, _ in log if when == "start"}
    assert starts == {(name, lo) for name, when, lo, _ in log if when == "end"}  # all that started finished


def _within(seconds, fn):
    """``fn()`` on a thread of its own; fails the test if it has not returned after ``seconds``
    (a hang), else returns its result or re-raises its exception."""
    out = {}

    def target():
        try:
            out["value"] = fn()
        except BaseException as error:  # noqa: BLE001  (re-raised below, on the test's thread)
            out["error"] = error

    thread = threading.Thread(target=target, daemon=True)
    thread.start()
    thread.join(seconds)
    if thread.is_alive():
        threads.forget_the_pool()  # its workers may be stuck too: later tests get a new pool
        pytest.fail(f"did not return within {seconds} s")
    if "error" in out:
        raise out["error"]
    return out.get("value")


def test_in_parallel_pipeline_wakes_the_threads_waiting_for_a_scan_when_a_task_fails():
    def task(lo, hi):
        if lo == 0:  # meanwhile the other thread finishes the other tasks and waits for scan 0
            time.sleep(0.2)
            raise ValueError("task 0")

    def run():
        with threads.thread_limit(2):
            threads.in_parallel(task, 8, 1, scan=lambda lo, hi: None, then=lambda lo, hi: None)

    with pytest.raises(ValueError, match="task 0"):
        _within(10, run)


def test_in_parallel_pipeline_scans_one_at_a_time_while_tasks_finish_and_then_waits_for_the_scan():
    log, stage = _pipeline_log()
    slow_scan = stage("scan", lambda lo, on_caller: 0.03)  # tasks finish on both threads meanwhile
    with threads.thread_limit(2):
        _within(20, lambda: threads.in_parallel(stage("task", lambda lo, on_caller: 0.005), 16, 1, scan=slow_scan,
                                                 then=stage("then")))
    scans = [(when, lo) for name, when, lo, _ in log if name == "scan"]
    assert scans == [(when, lo) for lo in range(16) for when in ("start", "end")]  # never two at once, each once
    at = {event[:3]: i for i, event in enumerate(log)}
    assert all(at[("scan", "end", lo)] < at[("then", "start", lo)] for lo in range(16))


def test_in_parallel_pipeline_starts_no_scan_after_a_task_has_failed():
    log, stage = _pipeline_log()

    def task(lo, hi):
        if lo == 0:  # the caller's first range: it ends after range 2 has failed on the worker
            time.sleep(0.2)
        elif lo == 2:
            raise ValueError("task 2")

    with threads.thread_limit(2), pytest.raises(ValueError, match="task 2"):
        _within(10, lambda: threads.in_parallel(task, 8, 1, scan=stage("scan"), then=stage("then")))
    assert log == []  # range 0 finished after the failure: no scan, so no then


def test_in_parallel_pipeline_raises_a_failed_then_and_starts_no_range_after_it():
    log, stage = _pipeline_log()
    record = stage("then")

    def then(lo, hi):
        record(lo, hi)
        if lo == 3:
            raise ValueError("then 3")
        time.sleep(0.01)

    with threads.thread_limit(2), pytest.raises(ValueError, match="then 3"):
        _within(10, lambda: threads.in_parallel(stage("task"), 12, 1, scan=stage("scan"), then=then))
    thens = [lo for name, when, lo, _ in log if name == "then" and when == "start"]
    assert 3 in thens and max(thens) <= 4  # at most the range the other thread had already taken


def test_in_parallel_raises_the_earliest_failed_range_not_the_first_to_fail():
    caller, workers_ranges = threading.current_thread(), []
    both_started = threading.Barrier(2, timeout=5)

    def task(lo, hi):
        if threading.current_thread() is caller:  # succeeds, after the workers' ranges failed
            time.sleep(0.3)
            return
        workers_ranges.append(lo)
        both_started.wait()  # both worker ranges run before either fails
        if lo == min(workers_ranges):
            time.sleep(0.1)  # the earlier range fails later
        raise ValueError(f"range {lo}")

    with threads.thread_limit(3), pytest.raises(ValueError) as raised:
        threads.in_parallel(task, 3, 1)
    assert str(raised.value) == f"range {min(workers_ranges)}"


def test_in_parallel_pipeline_survives_an_interrupt_between_taking_a_range_and_running_it(monkeypatch):
    """A Ctrl-C reaches the calling thread between any two bytecodes; here, as if one arrived
    right after it took its second range (simulated by the ``divmod`` that follows): the range is
    never run, so the scans cannot pass it and the other thread waits for one. The interrupt
    must be recorded so that it wakes up: KeyboardInterrupt, no hang, everything that started
    has finished."""
    taken = []

    def interrupted_divmod(a, b):
        if threading.current_thread().name == "caller":
            taken.append(a)
            if len(taken) == 2:
                raise KeyboardInterrupt
        return divmod(a, b)

    log, stage = _pipeline_log()
    monkeypatch.setattr(threads, "divmod", interrupted_divmod, raising=False)
    def call():
        threading.current_thread().name = "caller"
        threads.in_parallel(stage("task", lambda lo, on_caller: 0.02), 8, 1, scan=stage("scan"), then=stage("then"))

    with threads.thread_limit(2), pytest.raises(KeyboardInterrupt):
        _within(10, call)
    starts = {(name, lo) for name, when, lo, _ in log if when == "start"}
    assert starts == {(name, lo) for name, when, lo, _ in log if when == "end"}
    assert ("task", taken[1]) not in starts


def test_a_signal_while_the_pool_takes_work_is_handled_after_it_with_the_pool_s_locks_free(monkeypatch):
    """SIGINT sent from inside ``ThreadPoolExecutor.submit`` (where its handler's exception could
    leave the executors' global shutdown lock held, and the process hang at exit): handled once
    the work is handed out -- KeyboardInterrupt from in_parallel, every range that started has
    finished, the lock free, the handler set before in place again."""
    import concurrent.futures.thread as pool_threads
    import os
    import signal

    submit = pool_threads.ThreadPoolExecutor.submit
    inside = []

    def signalled_submit(self, *args, **kwargs):
        os.kill(os.getpid(), signal.SIGINT)
        inside.append(True)  # bytecodes after the signal: its handler did not raise in here
        return submit(self, *args, **kwargs)

    monkeypatch.setattr(pool_threads.ThreadPoolExecutor, "submit", signalled_submit)
    started, ended = [], []

    def task(lo, hi):
        started.append(lo)
        ended.append(lo)

    before = signal.getsignal(signal.SIGINT)
    with threads.thread_limit(2), pytest.raises(KeyboardInterrupt):
        threads.in_parallel(task, 8, 1)
    assert inside and sorted(started) == sorted(ended)
    assert pool_threads._global_shutdown_lock.acquire(blocking=False)
    pool_threads._global_shutdown_lock.release()
    assert signal.getsignal(signal.SIGINT) is before


def test_every_signal_held_is_raised_again_in_order_through_the_handlers_put_back():
    """SIGTERM (its handler records) then SIGINT inside the block: nothing runs inside; after it
    the SIGTERM handler runs, then Ctrl-C's KeyboardInterrupt; both handlers are those set before."""
    import os
    import signal

    seen = []
    before_int = signal.getsignal(signal.SIGINT)
    before_term = signal.signal(signal.SIGTERM, lambda signum, frame: seen.append("term"))
    try:
        with pytest.raises(KeyboardInterrupt):
            with threads.interrupts_held():
                os.kill(os.getpid(), signal.SIGTERM)
                os.kill(os.getpid(), signal.SIGINT)
                seen.append("inside")
        assert seen == ["inside", "term"]
        assert signal.getsignal(signal.SIGINT) is before_int
    finally:
        signal.signal(signal.SIGTERM, before_term)


def test_in_parallel_pipeline_from_several_threads_at_once():
    results, errors = [], []

    def caller(i):
        out = np.zeros(40)

        def task(lo, hi):
            out[lo:hi] = np.arange(lo, hi)

        def scan(lo, hi):  # a running sum, in order
            for k in range(lo, hi):
                out[k] += out[k - 1] if k else 0.0

        try:
            threads.in_parallel(task, 40, 2, scan=scan, then=lambda lo, hi: None)
            results.append(out)
        except Exception as error:  # noqa: BLE001  (collected, asserted below)
            errors.append(repr(error))

    with threads.thread_limit(4):
        spawned = [threading.Thread(target=caller, args=(i,)) for i in range(6)]
        for thread in spawned:
            thread.start()
        for thread in spawned:
            thread.join(timeout=30)
    assert errors == [] and len(results) == 6
    for out in results:
        assert np.array_equal(out, np.cumsum(np.arange(40.0)))


@pytest.mark.parametrize("bad", [0, -1, 1.5, None, True])
def test_a_thread_count_that_is_not_a_whole_number_above_zero_is_refused(bad):
    with pytest.raises(ValueError, match="thread count: expected a whole number"):
        with threads.thread_limit(bad):
            pass
    with pytest.raises(ValueError, match="thread count: expected a whole number"):
        threads.set_thread_count(bad)


def _pieces_in_a_child(queue):
    seen = []
    with threads.thread_limit(2):
        threads.in_parallel(lambda lo, hi: seen.append((lo, hi)), 4, 1)
    queue.put(sorted(seen))


@pytest.mark.skipif(not hasattr(os, "fork"), reason="needs fork")
def test_a_forked_child_runs_in_parallel_work_although_the_parent_had_started_its_pool():
    """A forked child has none of the parent's threads; it must not hand work to the parent's
    pool (it would wait for ever) -- e.g. Monte Carlo workers of a process pool."""
    with threads.thread_limit(2):
        threads.in_parallel(lambda lo, hi: None, 4, 1)  # the parent's pool exists now
    context = multiprocessing.get_context("fork")
    queue = context.Queue()
    child = context.Process(target=_pieces_in_a_child, args=(queue,))
    child.start()
    try:
        assert queue.get(timeout=60) == [(0, 1), (1, 2), (2, 3), (3, 4)]
    finally:
        child.join(timeout=10)
        if child.is_alive():
            child.kill()


def test_the_default_thread_count_comes_from_boxplus_threads_when_set(monkeypatch):
    monkeypatch.setenv("BOXPLUS_THREADS", "3")
    assert threads.default_threads() == 3
    monkeypatch.setenv("BOXPLUS_THREADS", " ")
    assert threads.default_threads() >= 1  # unset: the cores this process may use
    for bad in ("0", "two", "-1", "1.5"):
        monkeypatch.setenv("BOXPLUS_THREADS", bad)
        with pytest.raises(ValueError, match="BOXPLUS_THREADS: expected a whole number"):
            threads.default_threads()


@pytest.mark.skipif(not hasattr(signal, "pthread_sigmask"), reason="needs POSIX thread signal masks")
def test_a_signal_the_kernel_hands_to_another_thread_still_stops_a_wait_in_the_main_thread():
    """Ctrl-C while the main thread waits for a future that never ends, the signal taken by another
    thread (the main thread blocks SIGINT, so the kernel must hand it elsewhere, as it may whenever
    a process has threads): ``wait_interruptibly`` raises the KeyboardInterrupt while the future is
    still running; ``concurrent.futures.wait`` would wait until it ends (here after 5 s, so that the
    test ends either way) and the interruption would come after."""
    from concurrent.futures import Future

    late = Future()
    sender = threading.Timer(0.2, os.kill, (os.getpid(), signal.SIGINT))
    ender = threading.Timer(5.0, late.set_result, (None,))
    blocked = signal.pthread_sigmask(signal.SIG_BLOCK, {signal.SIGINT})
    try:
        sender.start()
        ender.start()
        with pytest.raises(KeyboardInterrupt):
            threads.wait_interruptibly([late])
        ended_first = late.done()
    finally:
        signal.pthread_sigmask(signal.SIG_SETMASK, blocked)
        sender.cancel()
        ender.cancel()
    assert not ended_first


def test_a_signal_the_kernel_hands_to_another_thread_stops_the_calling_thread_waiting_for_a_scan():
    """The calling thread of a pipelined ``in_parallel`` waits for a scan that a slow task on the
    pool holds up; the main thread blocks SIGINT, so the kernel hands the Ctrl-C to another thread.
    Its handler runs in the main thread while the slow task still runs (the wait wakes every
    :data:`factors.threads.SIGNAL_POLL_S`), and the task is then let go; a wait without a timeout
    would run it only once the task had ended (after 5 s, so that the test ends either way) and its
    scan woke the waiter."""
    with threads.thread_limit(2):  # the pool's workers start with SIGINT unblocked
        threads.in_parallel(lambda lo, hi: time.sleep(0.01), 2, 1)
    started, released = threading.Event(), threading.Event()
    seen = []

    def task(lo, hi):
        if threading.current_thread() is threading.main_thread():
            started.wait(5.0)  # the other range is the pool's: the caller's next wait is for its scan
        else:
            started.set()
            released.wait(5.0)
            released.set()

    def handler(signum, frame):
        seen.append(released.is_set())
        released.set()  # the slow task ends now: in_parallel raises once every range has finished
        raise KeyboardInterrupt

    previous = signal.signal(signal.SIGINT, handler)
    blocked = signal.pthread_sigmask(signal.SIG_BLOCK, {signal.SIGINT})
    sender = threading.Timer(0.3, os.kill, (os.getpid(), signal.SIGINT))
    try:
        sender.start()
        with threads.thread_limit(2), pytest.raises(KeyboardInterrupt):
            threads.in_parallel(task, 2, 1, scan=lambda lo, hi: None, then=lambda lo, hi: None)
    finally:
        signal.pthread_sigmask(signal.SIG_SETMASK, blocked)
        signal.signal(signal.SIGINT, previous)
        sender.cancel()
        released.set()
    assert seen == [False]
