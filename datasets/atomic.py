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
