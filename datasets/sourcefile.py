"""Opening the files a recording is read from: one bounded reader that never blocks.

Every file the datasets package reads as input -- rig files, YAML calibration files, CSV, TUM and
KITTI tables, ROS bags -- passes here first. :func:`read_source` returns a whole file's bytes;
:func:`check_source` checks a file that a library opens itself (a bag, which ``rosbags`` reads).
Both refuse

* what is not a regular file: a named pipe (FIFO) would block the reader until another program
  writes to it, a device (``/dev/zero``) never ends, a directory or socket has no content. The
  check is ``os.stat`` before anything opens the file, and :func:`read_source` opens it
  non-blocking and checks the opened file again, so that a file swapped for a pipe in between
  cannot block it either;
* a file larger than the limit of its kind, :data:`LIMITS` (a rig or YAML file is small; a table
  is read whole into memory, some eight times its size; a bag is read one topic at a time). A
  file that grows past the limit while it is read is refused too.

Each refusal is one :class:`datasets.errors.DataError` naming the file, what it is (or its size)
and the limit. ``docs/rig.md`` ("Limits") lists the limits for users.
"""
from __future__ import annotations

import os
import stat
from dataclasses import dataclass
from pathlib import Path

from datasets.errors import DataError

KIB, MIB, GIB = 1 << 10, 1 << 20, 1 << 30


@dataclass(frozen=True)
class SizeLimit:
    """The largest file of one kind: ``files`` (what they are, for messages), ``bytes`` and
    ``why``."""

    files: str
    bytes: int
    why: str


#: The size limit of each kind of file read.
LIMITS: dict[str, SizeLimit] = {
    "rig": SizeLimit("a rig file (TOML)", 1 * MIB,
                     "a rig of a hundred sensors is some 10 kB"),
    "yaml": SizeLimit("a YAML file (Kalibr imu.yaml or camchain, ASL sensor.yaml, a ROS 2 bag's metadata.yaml)",
                      1 * MIB, "a camchain of ten cameras is some 10 kB, the metadata of a bag of a thousand topics "
                               "some 500 kB"),
    "table": SizeLimit("a text table (CSV, TUM, KITTI)", 1 * GIB,
                       "about 8 million lines of a 7-column IMU file: a 1 kHz IMU for two hours, a 200 Hz one for "
                       "eleven; read whole, it takes some 8 GB of memory"),
    "bag": SizeLimit("a ROS bag's storage file (.bag, .db3, .mcap)", 256 * GIB,
                     "a day of a 3 MB/s camera rig; only the topics asked for are read from it"),
}

#: What a file that is not a regular one is, by its ``stat`` type.
_NOT_REGULAR = (
    (stat.S_ISDIR, "a directory"),
    (stat.S_ISFIFO, "a named pipe (FIFO), which would block until another program writes to it"),
    (stat.S_ISCHR, "a character device"),
    (stat.S_ISBLK, "a block device"),
    (stat.S_ISSOCK, "a socket"),
)


def _size(n: int) -> str:
    """A byte count as people read it: ``1 GiB``, ``6.2 GiB``, ``312 kiB``, ``17 bytes``."""
    for unit, name in ((GIB, "GiB"), (MIB, "MiB"), (KIB, "kiB")):
        if n >= unit:
            return f"{n / unit:.3g} {name}"
    return f"{n} bytes"


def _refuse_size(path, kind: str, size: int, at_least: bool = False) -> DataError:
    limit = LIMITS[kind]
    return DataError(path, None, None, f"{'more than ' if at_least else ''}{_size(size)} ({size} bytes)",
                     f"{limit.files} of at most {_size(limit.bytes)} (the limit for such files: {limit.why})",
                     whole=True)


def _check_stat(path, kind: str, st: os.stat_result) -> None:
    for is_type, what in _NOT_REGULAR:
        if is_type(st.st_mode):
            raise DataError(path, None, None, what, f"a regular file ({LIMITS[kind].files})", whole=True)
    if not stat.S_ISREG(st.st_mode):
        raise DataError(path, None, None, "a special file", f"a regular file ({LIMITS[kind].files})")
    if st.st_size > LIMITS[kind].bytes:
        raise _refuse_size(path, kind, st.st_size)


def _stat(path: Path) -> os.stat_result:
    """``os.stat`` of ``path`` (following links), or a DataError for a file that is not there."""
    try:
        return os.stat(path)
    except FileNotFoundError:
        raise DataError(path, None, None, "no such file", "an existing, readable file") from None
    except OSError as error:
        raise DataError(path, None, None, f"an unreadable file ({error.strerror})", "a readable file") from None


def check_source(path, kind: str) -> os.stat_result:
    """The ``stat`` of ``path``, a regular file within the limit of ``kind`` (a key of
    :data:`LIMITS`), for a reader that opens it itself; a :class:`DataError` otherwise."""
    path = Path(path)
    st = _stat(path)
    _check_stat(path, kind, st)
    return st


def read_source(path, kind: str) -> bytes:
    """The bytes of ``path``, a regular file within the limit of ``kind`` (a key of
    :data:`LIMITS`); a :class:`DataError` naming the file otherwise (module docstring)."""
    path = Path(path)
    check_source(path, kind)
    flags = os.O_RDONLY | getattr(os, "O_NONBLOCK", 0) | getattr(os, "O_CLOEXEC", 0) | getattr(os, "O_BINARY", 0)
    try:
        fd = os.open(path, flags)
    except FileNotFoundError:
        raise DataError(path, None, None, "no such file", "an existing, readable file") from None
    except OSError as error:
        raise DataError(path, None, None, f"an unreadable file ({error.strerror})", "a readable file") from None
    with os.fdopen(fd, "rb") as handle:
        _check_stat(path, kind, os.fstat(fd))  # the file opened is still a regular one
        limit = LIMITS[kind].bytes
        try:
            data = handle.read(limit + 1)
        except OSError as error:
            raise DataError(path, None, None, f"an unreadable file ({error.strerror})", "a readable file") from None
    if len(data) > limit:
        raise _refuse_size(path, kind, len(data), at_least=True)
    return data
