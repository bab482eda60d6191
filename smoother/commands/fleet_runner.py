"""Many recordings, each run as ``smoother run --rig`` would run it, on this machine or on a Dask
cluster (``smoother fleet``).

* **One recording, one child process**: :func:`run_recording` runs ``python -m smoother.cli run
  --rig RIG --out DIR/<rig file stem> ...`` as a new process (a fresh interpreter: nothing forked
  from a process with threads), its output in ``DIR/<stem>/run.log``. The run directory is then
  exactly what ``smoother run`` writes (lock, staging, the one-run rule:
  :mod:`smoother.commands.run_directory`). A recording that fails, or whose process dies (a
  crash, the kernel's out-of-memory killer), is a failed result naming why; the others go on.
* **Small results**: what comes back from a recording is a small dict of plain values
  (:func:`result_of`: exit code, the failure in one line, per estimator the held-out and fit
  figures, the per-sensor verdicts, ``doubtful``), never trajectories: a worker writes its own
  folder, so a thousand recordings on a cluster send back a few kB each.
* **Where**: :func:`run_recordings` runs ``workers`` recordings at a time from a thread pool of
  this process (each thread waits for its child), or sends them to a Dask scheduler
  (``distributed.Client(address)``), the same :func:`run_recording` on the workers, which must
  see the rig files and the output folder at the same paths (a shared file system). The window
  of tasks, the failures of workers and the stopping are :func:`smoother.parallel.run_all`'s;
  each child gets its share of the cores (``BOXPLUS_THREADS``, :func:`factors.threads.thread_count`).
* **Stopping**: Ctrl-C or SIGTERM to the fleet stops submitting, forwards that one signal to the
  recordings running here (:func:`forward`: their runs keep their finished estimators, as
  ``smoother run`` does, and their results come back with ``stopped``), and re-raises. The
  children run in their own session, so a terminal's Ctrl-C reaches them only through the fleet,
  once. On Dask the recordings not started are cancelled; those already running finish into their
  folders.
"""
from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import threading
from dataclasses import dataclass
from pathlib import Path

from factors.errors import InputError
from smoother import parallel
from smoother.confined import file_inside, folder_name_problem, inside
from smoother.outputs.layout import METRICS

#: The fleet's own file in its ``--out`` (each recording's files are in its folder).
SUMMARY = "summary.json"

#: What a recording's run printed (stdout and stderr), in its folder.
LOG = "run.log"
#: The per-estimator figures a result keeps from ``metrics.json`` (those the run computed).
FIGURES = ("ate_rmse_m", "rot_rmse_deg", "nees_mean", "gps_heldout_rmse_m", "gps_heldout_horizontal_rmse_m",
           "gps_heldout_vertical_rmse_m", "gps_fit_residual_m", "runtime_s", "failed", "doubtful")
#: The keys of a verdict a result keeps (:func:`smoother.diagnosis.verdicts.verdict`).
VERDICT = ("per_dof", "band", "ok", "statistic", "measurements")


@dataclass(frozen=True)
class Recording:
    """One recording of a fleet: its rig file, its run directory and the options of ``smoother
    run`` besides ``--rig`` and ``--out`` (``run_options``); ``threads`` the cores its run may
    use (None: :func:`run_recording` decides)."""

    rig: str
    out: str
    run_options: tuple = ()
    threads: int | None = None

    @property
    def name(self) -> str:
        return Path(self.rig).stem

    def argv(self) -> list[str]:
        """The command line of its run, after ``smoother``."""
        return ["run", "--rig", self.rig, "--out", self.out, "--no-progress", *self.run_options]


def recordings(rigs, out_dir, run_options=(), threads: int | None = None) -> list[Recording]:
    """The recordings of the rig files ``rigs``, each into ``out_dir/<rig file stem>``; a
    :class:`~factors.errors.InputError` when two rig files share a stem (their folders would be
    one), when a stem cannot name a folder of its own in ``out_dir``
    (:func:`smoother.confined.folder_name_problem`: ``..`` of a rig ``...toml`` is its
    parent) or is the fleet's summary's name, or when its folder would lie outside ``out_dir``
    (:func:`smoother.confined.inside`: a symbolic link there)."""
    seen: dict[str, str] = {}
    for rig in rigs:
        stem = Path(rig).stem
        problem = folder_name_problem(stem) or (f"{stem!r} is the fleet's own {SUMMARY}" if stem == SUMMARY else None)
        if problem is not None:
            raise InputError(f"{rig}: its name without .toml, which names its recording's folder in {out_dir}, "
                             f"cannot: {problem}; rename the rig file")
        if stem in seen:
            raise InputError(f"{seen[stem]} and {rig}: both would be run into {Path(out_dir) / stem}/ (a recording's "
                            "folder is its rig file's name without .toml); rename one of them")
        seen[stem] = str(rig)
    return [Recording(str(Path(rig).resolve()), str(inside(out_dir, Path(rig).stem).resolve()), tuple(run_options),
                      threads) for rig in rigs]


# --- one recording ------------------------------------------------------------------------------

_children: set = set()
_children_lock = threading.Lock()
#: Set by :func:`forward`: no recording starts in this process any more.
_stopping = threading.Event()


def run_recording(recording: Recording) -> dict | None:
    """Run ``recording`` in a child process (module docstring) and return :func:`result_of` it;
    None when the fleet was stopped (:func:`forward`) before it started. Never raises for the
    recording's sake: a folder that cannot be made, a run that fails or a child that dies is a
    result with ``failure``."""
    out = Path(recording.out)
    if _stopping.is_set():
        return None
    try:
        out.mkdir(parents=True, exist_ok=True)
        before = _signature(inside(out, METRICS))
        env = dict(os.environ)
        threads = recording.threads or _dask_share()
        if threads is not None and "BOXPLUS_THREADS" not in os.environ:
            env["BOXPLUS_THREADS"] = str(threads)
        flags = os.O_WRONLY | os.O_CREAT | os.O_TRUNC | getattr(os, "O_NONBLOCK", 0) | getattr(os, "O_CLOEXEC", 0)
        with os.fdopen(os.open(file_inside(out, LOG), flags, 0o666), "w") as log:  # never a pipe's reader awaited
            with _children_lock:  # started and registered at once: forward() misses no child
                if _stopping.is_set():
                    return None
                child = subprocess.Popen([sys.executable, "-m", "smoother.cli", *recording.argv()],
                                         stdin=subprocess.DEVNULL, stdout=log, stderr=subprocess.STDOUT, env=env,
                                         start_new_session=True)
                _children.add(child)
            try:
                code = child.wait()
            finally:
                with _children_lock:
                    _children.discard(child)
    except OSError as error:
        return failed(recording, f"cannot run it: {error.filename or out}: {error.strerror or error}")
    except InputError as error:  # its folder's log or metrics lead out of it
        return failed(recording, f"cannot run it: {error}")
    metrics = out / METRICS
    return result_of(recording, code, metrics if _signature(metrics) != before else None, out / LOG)


def forward(signum: int) -> None:
    """Send ``signum`` to every recording's child process running in this process, and start no
    more."""
    with _children_lock:
        _stopping.set()
        children = list(_children)
    for child in children:
        if child.poll() is None:
            child.send_signal(signum)


def _signature(path: Path):
    """What tells a file written anew from the one there before (``os.replace`` makes a new inode)."""
    try:
        s = path.stat()
    except OSError:
        return None
    return s.st_ino, s.st_mtime_ns, s.st_size


def _dask_share() -> int | None:
    """Inside a Dask worker: the cores per worker thread; elsewhere None."""
    try:
        from distributed import get_worker

        worker = get_worker()
    except (ImportError, ValueError):
        return None
    cores = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count() or 1
    return max(1, cores // max(1, worker.state.nthreads))


def failed(recording: Recording, why: str | None, code: int | None = None) -> dict:
    """The result of a recording without estimates: ``failure`` says why, in one line (the keys
    of :func:`result_of`)."""
    return {"recording": recording.name, "rig": recording.rig, "out": recording.out, "exit_code": code,
            "failure": why, "estimators": {}}


def result_of(recording: Recording, code: int, metrics: Path | None, log: Path | None) -> dict:
    """The small result of a recording's run that ended with exit code ``code``: ``recording``
    (the rig file's stem), ``rig``, ``out``, ``exit_code``, ``failure`` (None, or one line: the
    run's error, the estimators that failed, the signal that killed it), ``stopped`` (when the
    run was interrupted), ``dead_reckoning`` and ``estimators``: per estimator its
    :data:`FIGURES` and verdicts (``fit``, ``sensors``: each :data:`VERDICT`), from the run's
    ``metrics.json`` (``metrics``: None when the run wrote none)."""
    document = {}
    if metrics is not None:
        try:
            document = json.loads(metrics.read_text())
        except (OSError, ValueError) as error:
            return failed(recording, f"its metrics.json cannot be read ({error})", code)
    run = document.pop("_run", {})
    estimators = {}
    for name, m in document.items():
        entry = {k: m[k] for k in FIGURES if k in m}
        if "fit" in m:
            entry["fit"] = {k: m["fit"][k] for k in VERDICT if k in m["fit"]}
        entry["sensors"] = {s: {k: v[k] for k in VERDICT if k in v} for s, v in m.get("sensors", {}).items()}
        estimators[name] = entry
    out = {**failed(recording, None, code), "estimators": estimators}
    if "stopped" in run:
        out["stopped"] = run["stopped"]
    if "dead_reckoning" in run:
        out["dead_reckoning"] = run["dead_reckoning"]
    if code != 0:
        out["failure"] = _why(code, estimators, log)
    return out


def _why(code: int, estimators: dict, log: Path | None) -> str:
    """One line saying why a run ended with exit code ``code``."""
    if code < 0:
        try:
            name = signal.Signals(-code).name
        except ValueError:
            name = f"signal {-code}"
        return f"its process was killed by {name}"
    broken = [f"{name} failed: {e['failed']}" for name, e in estimators.items() if "failed" in e]
    if broken:
        return "; ".join(broken)
    lines = []
    if log is not None:
        try:
            lines = [line.strip() for line in log.read_text(errors="replace").splitlines() if line.strip()]
        except OSError:
            pass
    said = [line for line in lines if line.startswith("smoother: ") and "warning:" not in line]
    text = (said or lines or [f"exit code {code}"])[-1]
    return text.removeprefix("smoother: ").removeprefix("error: ")


# --- many recordings ----------------------------------------------------------------------------

def run_recordings(items: list[Recording], on_result, workers: int = 1, dask_address: str | None = None) -> None:
    """Run ``items`` on this machine, ``workers`` at a time (threads, each waiting for its
    recording's child process), or through the Dask scheduler at ``dask_address``, with
    :func:`smoother.parallel.run_all`'s window; ``on_result(result)`` in this thread as each ends,
    in the order they end (never for one that did not start). A worker that fails (a bug of this
    module, a Dask worker that died: :class:`distributed.KilledWorker`) is its recording's failure.
    Ctrl-C or SIGTERM (:class:`~smoother.errors.Terminated`): nothing more starts, the signal goes
    on to the recordings running in this process (:func:`forward`), their results are passed on,
    and the interruption is raised again; on Dask the recordings not started are cancelled. An
    :class:`~factors.errors.InputError` when the scheduler cannot be reached or ``distributed``
    is not installed."""
    _stopping.clear()
    where = parallel.dask(dask_address) if dask_address is not None else parallel.threads(workers)

    def passed_on(result: dict | None) -> None:
        if result is not None:
            on_result(result)

    with where:
        parallel.run_all(run_recording, items, where, passed_on, on_failure=worker_failed, on_stop=forward)


def worker_failed(item: Recording, error: Exception) -> dict:
    """The failure of ``item`` whose worker raised ``error``."""
    return failed(item, f"its worker failed: {parallel.failure_line(error)}")
