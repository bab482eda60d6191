"""The output directory of ``smoother run`` (``--out``): one run at a time, and one run's files.

* **What a run writes**, by name (:func:`run_files`, the one list of them, from the names of
  :mod:`smoother.outputs.layout`): per estimator of :data:`smoother.pipeline.ESTIMATORS` its
  ``.tum``, ``.npz`` and ``.geojson``; ``truth.npz``, ``gps.npz``, ``metrics.json``;
  ``estimates.mcap`` (``--mcap``, :mod:`smoother.outputs.mcap`); ``calibrated.toml``; the figures
  of :mod:`smoother.outputs.plots` (``--plot``, or ``smoother plot DIR``). Nothing else in the
  directory is ever deleted or changed.
* **One run at a time**: a run holds an exclusive ``flock`` on :data:`LOCK` (a hidden file in the
  directory, holding the run's process id) from before its estimators start until it ends; a
  second run into the same directory is refused at once, naming the directory and the other run's
  process id.
* **One run's files**: everything is written into a hidden staging folder inside the directory
  (:func:`datasets.atomic.staging`) and moved in at the end, together; the previous run's files
  that the new run did not write again are then deleted (and named on stderr), so that the
  directory never mixes two runs. A failure while writing (a full disk, Ctrl-C, SIGTERM) leaves the
  directory as it was.
* **Only inside it**: the lock, every file moved in and every file deleted pass
  :func:`smoother.confined.inside` first: a run file that is a symbolic link out of the
  directory is refused (it would overwrite the file it leads to), before anything is moved.
"""
from __future__ import annotations

import contextlib
import errno
import fcntl
import os
import shutil
import sys
from pathlib import Path

from datasets.atomic import STAGING_PREFIX, staging
from factors.errors import InputError, InternalError
from smoother.confined import file_inside, inside
from smoother.errors import UserError
from smoother.outputs.layout import CALIBRATED_RIG, ESTIMATE_SUFFIXES, GPS, MCAP, METRICS, PLOTS, TRUTH

#: The lock file of a run directory.
LOCK = ".smoother.lock"
#: Lock errors of a file system without locks: the run goes on, unguarded, with a warning.
_NO_LOCKS = (errno.ENOLCK, errno.EOPNOTSUPP, errno.ENOSYS, errno.EINVAL)


def run_files() -> frozenset[str]:
    """The names of every file a run (or ``smoother plot`` into it) writes into a run directory."""
    from smoother.estimators import ESTIMATORS

    return frozenset([f"{name}{suffix}" for name in ESTIMATORS for suffix in ESTIMATE_SUFFIXES]
                     + [TRUTH, GPS, METRICS, MCAP, CALIBRATED_RIG] + [f"{plot}.png" for plot in PLOTS])


class RunDirectory:
    """``--out`` of one run, as a context manager: entering creates the directory (or takes an
    existing one), checks that it is writable and takes its lock, or raises a
    :class:`~smoother.errors.UserError` naming ``--out``; leaving releases the lock. Outputs are
    written through :meth:`outputs`; ``removed`` names the previous run's files the last
    :meth:`outputs` deleted."""

    def __init__(self, path):
        self._given = path
        self.path = Path(path)
        self.removed: list[str] = []
        self._lock: int | None = None

    def __enter__(self) -> "RunDirectory":
        from smoother.commands import output_directory

        output_directory(self._given)  # as given: an empty --out is refused, not taken for "."
        for name in run_files():  # before any work: a run file that leads elsewhere would be written there
            if os.path.lexists(self.path / name):
                try:
                    inside(self.path, name)
                except InputError as error:
                    raise UserError(f"--out {self.path}: {error}; remove it or choose another --out") from None
        self._take_lock()
        self._clear_stale_staging()
        return self

    def __exit__(self, *exc) -> None:
        if self._lock is not None:
            os.close(self._lock)  # closing the descriptor releases the flock
            self._lock = None

    def _take_lock(self) -> None:
        try:  # truncated below: never a file elsewhere that a link leads to, nor a pipe or device
            path = file_inside(self.path, LOCK)
        except InputError as error:
            raise UserError(f"--out {self.path}: {error}") from None
        try:
            fd = os.open(path, os.O_RDWR | os.O_CREAT | getattr(os, "O_CLOEXEC", 0) | getattr(os, "O_NONBLOCK", 0),
                         0o666)
        except OSError as error:
            raise UserError(f"--out {self.path}: cannot create its lock file {LOCK} ({error.strerror})") from None
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            holder = os.read(fd, 32).decode("ascii", "replace").strip()
            os.close(fd)
            pid = f" (pid {holder})" if holder.isdigit() else ""
            raise UserError(f"--out {self.path}: another smoother run{pid} is writing into this directory; "
                            "wait for it to end or choose another --out") from None
        except OSError as error:
            os.close(fd)
            if error.errno not in _NO_LOCKS:
                raise UserError(f"--out {self.path}: cannot lock it ({error.strerror})") from None
            print(f"warning: --out {self.path}: its file system has no locks ({error.strerror}); another run "
                  "into it at the same time would not be noticed", file=sys.stderr)
            return
        os.ftruncate(fd, 0)
        os.write(fd, f"{os.getpid()}\n".encode())
        self._lock = fd

    def _clear_stale_staging(self) -> None:
        """Staging folders of a run that was killed (SIGKILL, power loss): with the lock held no
        other run owns one. Their run files are deleted (and the hidden folder a run file was being
        written through, :func:`smoother.outputs.mcap.write_mcap`'s), then the folder if that emptied it."""
        names = run_files()
        for folder in self.path.glob(f"{STAGING_PREFIX}*"):
            if not folder.is_dir() or folder.is_symlink():
                continue
            for entry in folder.iterdir():
                stem = entry.name.rsplit(".", 2)[0].lstrip(".") if entry.name.endswith(".tmp") else entry.name
                if stem not in names or entry.is_symlink():
                    continue
                if entry.is_file():
                    entry.unlink()
                elif entry.is_dir():
                    shutil.rmtree(entry, ignore_errors=True)
            with contextlib.suppress(OSError):
                folder.rmdir()

    @contextlib.contextmanager
    def outputs(self, replace: bool = True):
        """A staging folder to write run files into (the block's value, a ``Path``); when the
        block ends they are moved into the directory, ``metrics.json`` last, each checked to stay
        inside it (:func:`smoother.confined.inside`). With ``replace``
        the run files already in the directory that the block did not write are the previous
        run's: they are deleted and listed in ``removed``. When the block raises, nothing
        changes in the directory; an ``OSError`` names the directory's file, not the staged one.
        A file whose name is not among :func:`run_files` is a programming error
        (:class:`factors.errors.InternalError`): every output is declared there."""
        names = run_files()
        with staging(self.path) as stage:
            yield stage.path
            written = stage.names()
            unknown = [name for name in written if name not in names]
            if unknown:
                raise InternalError(f"run files not declared in smoother.outputs.layout: {', '.join(unknown)}")
            previous = sorted(p.name for p in self.path.iterdir() if p.name in names and p.name not in written
                              and (p.is_file() or p.is_symlink())) if replace else []
            for name in written:
                inside(self.path, name)
            for name in previous:
                inside(self.path, name, follow=False)
            stage.commit(remove=previous, last=METRICS)
            self.removed = previous

    def final(self, path) -> Path:
        """The directory's path of a file written into the staging folder."""
        return self.path / Path(path).name
