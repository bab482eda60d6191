"""smoother.parallel: the window of tasks, failures handed over or raised, Ctrl-C stopping the
submission and passing on what was running, pools of processes sharing the threads."""
from __future__ import annotations

import os
import signal
import sys
import threading
import time
from concurrent.futures import Future

import pytest

from factors.errors import InputError
from factors.threads import thread_count, thread_limit
from smoother import parallel


class Counting(parallel.Workers):
    """Tasks run at once in the calling thread, with a window of 3; counts those submitted and
    not yet passed on."""

    def __init__(self):
        self.outstanding, self.most = 0, 0

    def window(self) -> int:
        return 3

    def submit(self, function, item) -> Future:
        self.outstanding += 1
        self.most = max(self.most, self.outstanding)
        future: Future = Future()
        future.set_result(function(item))
        return future


def test_at_most_a_window_of_tasks_is_submitted_and_every_result_passed_on():
    workers, seen = Counting(), []

    def passed_on(result):
        workers.outstanding -= 1
        seen.append(result)

    parallel.run_all(lambda x: x * x, range(10), workers, passed_on)
    assert sorted(seen) == [x * x for x in range(10)] and workers.most == 3


def test_a_failure_is_handed_to_on_failure_or_raised_with_the_rest_cancelled():
    def task(x):
        if x == 1:
            raise ValueError("one is bad")
        return x

    seen = []
    with parallel.threads(2) as workers:
        parallel.run_all(task, range(4), workers, seen.append,
                         on_failure=lambda item, error: f"{item}: {parallel.failure_line(error)}")
    assert sorted(map(str, seen)) == ["0", "1: ValueError: one is bad", "2", "3"]

    ran = []
    with pytest.raises(ValueError, match="one is bad"), parallel.in_this_thread() as workers:
        parallel.run_all(lambda x: ran.append(x) or task(x), range(4), workers, seen.append)
    assert ran == [0, 1]  # nothing started after the failure


def test_ctrl_c_stops_the_submission_and_passes_on_what_was_running():
    """SIGINT while two tasks run on two threads and more are queued: the queued ones never start,
    on_stop gets SIGINT (and here lets the running ones end), their results are passed on, and
    the interruption is raised again."""
    started, release, ran, seen, stops = threading.Semaphore(0), threading.Event(), [], [], []

    def task(x):
        ran.append(x)
        started.release()
        assert release.wait(30)
        return x

    def interrupt():
        for _ in range(2):
            assert started.acquire(timeout=30)
        os.kill(os.getpid(), signal.SIGINT)

    def on_stop(signum):
        stops.append(signum)
        release.set()

    threading.Thread(target=interrupt, daemon=True).start()
    with pytest.raises(KeyboardInterrupt), parallel.threads(2) as workers:
        parallel.run_all(task, range(10), workers, seen.append, on_stop=on_stop)
    assert stops == [signal.SIGINT]
    assert sorted(seen) == sorted(ran) == [0, 1]


def test_an_interruption_inside_a_task_in_this_thread_keeps_the_results_before_it():
    seen = []

    def task(x):
        if x == 2:
            raise KeyboardInterrupt
        return x

    with pytest.raises(KeyboardInterrupt), parallel.in_this_thread() as workers:
        parallel.run_all(task, range(5), workers, seen.append)
    assert seen == [0, 1]


@pytest.mark.parametrize("threads, workers, each", [(4, 2, 2), (1, 3, 1)])
def test_process_workers_share_the_threads_instead_of_each_taking_them_all(threads, workers, each):
    with thread_limit(threads):
        pool = parallel.process_pool(workers)
    try:
        assert pool.submit(thread_count).result(timeout=60) == each
    finally:
        pool.shutdown()


@pytest.mark.parametrize("bad", [0, -1, 1.5, True])
def test_a_pool_of_no_workers_is_refused(bad):
    with pytest.raises(InputError, match="workers: expected a whole number >= 1"):
        parallel.threads(bad)


def test_dask_without_distributed_says_which_extra_to_install(monkeypatch):
    monkeypatch.setitem(sys.modules, "distributed", None)  # import fails as if not installed
    with pytest.raises(InputError, match=r"boxplus-smoother\[dask\]"):
        parallel.dask("tcp://127.0.0.1:1")


def test_failure_line_is_the_type_and_the_first_line():
    assert parallel.failure_line(RuntimeError("first\nsecond")) == "RuntimeError: first"


def test_a_slow_task_does_not_hold_up_the_results_of_others():
    """Results come back in the order the tasks end, not the order given."""
    seen = []

    def task(x):
        time.sleep(0.5 if x == 0 else 0.0)
        return x

    with parallel.threads(2) as workers:
        parallel.run_all(task, range(4), workers, seen.append)
    assert seen[-1] == 0 and sorted(seen) == [0, 1, 2, 3]
