"""Atomic file output: a file is either its old content or its complete new content, never partial."""
from __future__ import annotations

import contextlib
import os
import secrets
import stat
from pathlib import Path


def _create_beside(path: Path) -> tuple[int, Path]:
    """A new, empty file with a fresh hidden name in ``path``'s folder, opened for writing:
    ``(descriptor, its path)``. Created with mode 0666 less the process's umask, as ``open``
    creates files (``tempfile.mkstemp`` would create it 0600, and the moved file would keep that)."""
    flags = os.O_WRONLY | os.O_CREAT | os.O_EXCL | getattr(os, "O_CLOEXEC", 0)
    while True:
        candidate = path.with_name(f".{path.name}.{secrets.token_hex(4)}.tmp")
        try:
            return os.open(candidate, flags, 0o666), candidate
        except FileExistsError:
            continue


@contextlib.contextmanager
def atomic_write(path, mode: str = "w", **open_kwargs):
    """Open a temporary file beside ``path`` for writing and move it onto ``path`` only when the
    block finishes without an exception (``os.replace`` is atomic on POSIX). On an exception (or
    Ctrl-C) the temporary file is removed and ``path`` keeps what it had.

    The file ends up as ``open(path, "w")`` would leave it: a symbolic link is written through
    (its target gets the new content, the link stays), an existing file keeps its permissions
    and a new one gets the umask's. A system error while writing (an ``OSError`` with an
    ``errno``, a full disk say) that names no file, or the temporary one, is given ``path`` as
    its file name, so that its message says which file could not be written."""
    path = Path(os.path.realpath(path))
    path.parent.mkdir(parents=True, exist_ok=True)
    try:
        fd, tmp = _create_beside(path)
    except OSError as error:  # a full disk or a read-only folder: name the file meant, not the temporary one
        if error.strerror:
            error.filename, error.filename2 = str(path), None
        raise
    try:
        with contextlib.suppress(FileNotFoundError):
            os.fchmod(fd, stat.S_IMODE(os.stat(path).st_mode))
        with os.fdopen(fd, mode, **open_kwargs) as handle:
            yield handle
            handle.flush()
            os.fsync(handle.fileno())
        os.replace(tmp, path)
    except BaseException as error:
        with contextlib.suppress(FileNotFoundError):
            os.unlink(tmp)
        if isinstance(error, OSError) and error.strerror and error.filename in (None, str(tmp)):
            error.filename, error.filename2 = str(path), None
        raise


#: Names of the hidden folders :func:`staging` writes into: ``.staging-<pid>-<random>``.
STAGING_PREFIX = ".staging-"


class Staging:
    """A fresh hidden folder ``path`` inside ``folder``, whose files :meth:`commit` moves into
    ``folder`` together (made by :func:`staging`)."""

    def __init__(self, folder: Path):
        self.folder = Path(os.path.realpath(folder))
        while True:
            path = self.folder / f"{STAGING_PREFIX}{os.getpid()}-{secrets.token_hex(4)}"
            try:
                path.mkdir(mode=0o777)
                break
            except FileExistsError:
                continue
        self.path = path

    def names(self) -> list[str]:
        """The files written into the staging folder so far (temporary ones of
        :func:`atomic_write` excepted), sorted."""
        return sorted(p.name for p in self.path.iterdir() if not p.name.endswith(".tmp"))

    def commit(self, remove=(), last: str | None = None) -> None:
        """Move every staged file onto its namesake in ``folder`` (``os.replace``: each one
        atomically, a file already there keeping its permissions, a symbolic link there written
        through), ``last`` after all others, then delete the files of ``folder`` named in
        ``remove``, then the staging folder. SIGINT and SIGTERM wait until this is done, so that
        no interruption leaves some files moved and others not."""
        names = self.names()
        names.sort(key=lambda name: name == last)
        with _signals_held():
            for name in names:
                target = Path(os.path.realpath(self.folder / name))
                with contextlib.suppress(FileNotFoundError):
                    os.chmod(self.path / name, stat.S_IMODE(os.stat(target).st_mode))
                os.replace(self.path / name, target)
            for name in remove:
                with contextlib.suppress(FileNotFoundError):
                    os.unlink(self.folder / name)
            self.discard()

    def discard(self) -> None:
        """Delete the staging folder and what is in it (this process made it: nothing else is)."""
        if self.path.exists():
            for entry in self.path.iterdir():
                entry.unlink()
            self.path.rmdir()

    def final(self, path) -> Path:
        """Where the staged file ``path`` goes: its namesake in ``folder`` (other paths unchanged)."""
        path = Path(path)
        return self.folder / path.name if Path(os.path.realpath(path)).parent == self.path else path


@contextlib.contextmanager
def staging(folder):
    """A :class:`Staging` folder inside ``folder`` for the block to write into and commit. When
    the block raises (Ctrl-C, a full disk) the staging folder is deleted and ``folder`` keeps
    what it had; an ``OSError`` naming a staged file (as :func:`atomic_write` names it) is made
    to name the file of ``folder`` it was meant for."""
    try:
        stage = Staging(folder)
    except OSError as error:
        if error.strerror:
            error.filename, error.filename2 = str(folder), None
        raise
    try:
        yield stage
    except BaseException as error:
        with contextlib.suppress(OSError):
            stage.discard()
        if isinstance(error, OSError) and error.filename is not None:
            error.filename = str(stage.final(error.filename))
        raise


@contextlib.contextmanager
def _signals_held():
    """SIGINT and SIGTERM, when Python handles them, held until the block ends and then raised
    again (as the handlers in place would have raised them). Only the main thread handles
    signals: elsewhere the block runs as it is."""
    import signal
    import threading

    if threading.current_thread() is not threading.main_thread():
        yield
        return
    pending: list[int] = []
    previous = {}
    for number in (signal.SIGINT, signal.SIGTERM):
        handler = signal.getsignal(number)
        if callable(handler):  # a Python handler (Ctrl-C's default is one); SIG_DFL/SIG_IGN stay
            previous[number] = signal.signal(number, lambda signum, frame: pending.append(signum))
    try:
        yield
    finally:
        for number, handler in previous.items():
            signal.signal(number, handler)
        for number in dict.fromkeys(pending):
            previous[number](number, None)
