"""Errors of the dataset loaders, the one bounded reader of their input files, and the small
text-parsing helpers that raise them.

Every malformed input becomes one :class:`DataError` (an ``InputError``, so a ``ValueError``) whose message names the
file, the 1-based line, the field, what was found and what was expected, e.g.::

    /data/imu.txt, line 12, field 'accelY': found 'nan'; expected a finite number

Loaders never let an exception from deep inside NumPy or GTSAM escape for bad input, and never
return silently wrong data: a row they cannot read is an error, not a skipped row.

Every file the datasets package reads as input -- rig files, YAML calibration files, CSV, TUM and
KITTI tables, ROS bags -- passes :func:`read_source` (a whole file's bytes; :func:`read_lines` its
text) or, when a library opens it itself (a bag, which ``rosbags`` reads), :func:`check_source`.
Both refuse

* what is not a regular file: a named pipe (FIFO) would block the reader until another program
  writes to it, a device (``/dev/zero``) never ends, a directory or socket has no content. The
  check is ``os.stat`` before anything opens the file, and :func:`read_source` opens it
  non-blocking and checks the opened file again, so that a file swapped for a pipe in between
  cannot block it either;
* a file larger than the limit of its kind, :data:`LIMITS` (a rig or YAML file is small; a table
  is read whole into memory, some three times its size; a bag is read one topic at a time). A
  file that has more to read than its size says (one growing, a ``/proc`` file) is read no
  further than the limit and refused.

Each refusal is one :class:`DataError` naming the file, what it is (or its size) and the limit;
``docs/rig.md`` ("Limits") lists the limits for users.
"""
from __future__ import annotations

import math
import os
import re
import stat
import warnings
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from datasets.types import MIN_RECORDING_SAMPLES, MIN_RECORDING_SECONDS, MIN_RECORDING_WHY
from factors.errors import InputError

#: Found values longer than this are shortened in messages (fuzzed input can be huge).
_MAX_SHOWN = 60


def _shown(found) -> str:
    """Strings as ``repr`` (so blanks and control characters show), other values as ``str``."""
    text = repr(found) if isinstance(found, str) else str(found)
    if len(text) > _MAX_SHOWN:
        text = text[: _MAX_SHOWN - 3] + "..."
    return text


class DataError(InputError):
    """Malformed input data (an :class:`factors.errors.InputError`, so also a ``ValueError``).
    ``path``, ``line`` (1-based, or None for the file as a whole), ``field`` (or None), ``found``
    and ``expected`` are kept as attributes. ``found`` is shortened to :data:`_MAX_SHOWN` characters
    (it may be a whole fuzzed line) unless ``whole``: a text the loader composed from parsed values,
    which must stay readable to the last digit (kept as an attribute too, for an error re-raised
    with another field)."""

    def __init__(self, path, line: int | None, field: str | None, found, expected: str, whole: bool = False):
        self.path = str(path)
        self.line = line
        self.field = field
        self.found = found
        self.expected = expected
        self.whole = whole
        where = self.path
        if line is not None:
            where += f", line {line}"
        if field is not None:
            where += f", field '{field}'"
        super().__init__(f"{where}: found {found if whole else _shown(found)}; expected {expected}")


#: What ends a line in a text file: LF, CR LF or a lone CR. Not the other characters that
#: ``str.splitlines`` also breaks at (form feed, U+2028, ...): inside a line they would split a
#: comment and turn its tail into a data row.
_LINE_END = re.compile(r"\r\n|\r|\n")


def _split_lines(text: str) -> list[str]:
    """``text`` cut at :data:`_LINE_END` (a final line end ends the last line, adds none)."""
    lines = _LINE_END.split(text)
    if lines[-1] == "":
        lines.pop()
    return lines


#: Bytes in a kibibyte, a mebibyte, a gibibyte.
KIB, MIB, GIB = 1 << 10, 1 << 20, 1 << 30


@dataclass(frozen=True)
class SizeLimit:
    """The largest file of one kind: ``files`` (what they are, plural, for messages), ``bytes``
    and ``why``."""

    files: str
    bytes: int
    why: str


#: The size limit of each kind of file read.
LIMITS: dict[str, SizeLimit] = {
    "rig": SizeLimit("rig files (TOML)", 1 * MIB, "a rig of a hundred sensors is some 10 kB"),
    "yaml": SizeLimit("YAML files (Kalibr imu.yaml and camchains, ASL sensor.yaml, ROS 2 bag metadata.yaml)", 1 * MIB,
                      "a camchain of ten cameras is some 10 kB, the metadata of a bag of a thousand topics some "
                      "500 kB"),
    "table": SizeLimit("text tables (CSV, TUM and KITTI files)", 1 * GIB,
                       "about 8 million lines of an IMU file in EuRoC's layout, a 1 kHz IMU for two hours or a 200 Hz "
                       "one for eleven; read whole, such a file takes some 3 GB of memory"),
    "npz": SizeLimit("a run's NumPy archives (.npz), their arrays unpacked too", 1 * GIB,
                     "the states and 15x15 covariances of some 550 000 keyframes, 15 hours at 10 Hz; every one of a "
                     "run is read whole to plot it"),
    "json": SizeLimit("a run's metrics.json", 64 * MIB, "a run of a thousand sensors writes some 2 MB"),
    "bag": SizeLimit("ROS bag storage files (.bag, .db3, .mcap)", 256 * GIB,
                     "a day of a camera rig writing 3 MB/s; only the topics asked for are read from it"),
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


def _refuse_size(path, kind: str, size: int | None) -> DataError:
    """The error for a file of ``size`` bytes beyond the limit of ``kind``; ``size`` None: one that
    had more than the limit to read than its size said (it grew, or it is a /proc-like file)."""
    limit = LIMITS[kind]
    found = f"{_size(size)} ({size} bytes)" if size is not None else f"more than {limit.bytes} bytes once read"
    return DataError(path, None, None, found, f"at most {_size(limit.bytes)}, the limit of {limit.files}: {limit.why}",
                     whole=True)


def _check_stat(path, kind: str, st: os.stat_result) -> None:
    """A :class:`DataError` unless ``st`` is that of a regular file within the limit of ``kind``."""
    if not stat.S_ISREG(st.st_mode):
        what = next((what for is_type, what in _NOT_REGULAR if is_type(st.st_mode)), "a special file")
        raise DataError(path, None, None, what, "a regular file", whole=True)
    if st.st_size > LIMITS[kind].bytes:
        raise _refuse_size(path, kind, st.st_size)


def _cannot_read(path, error: OSError) -> DataError:
    """The error for a file that is missing or that the system would not read."""
    if isinstance(error, FileNotFoundError):
        return DataError(path, None, None, "no such file", "an existing, readable file")
    return DataError(path, None, None, f"an unreadable file ({error.strerror})", "a readable file")


def check_source(path, kind: str) -> os.stat_result:
    """The ``stat`` of ``path`` (links followed), a regular file within the limit of ``kind`` (a
    key of :data:`LIMITS`), for a reader that opens it itself; a :class:`DataError` otherwise."""
    path = Path(path)
    check_name(path)
    try:
        st = os.stat(path)
    except OSError as error:
        raise _cannot_read(path, error) from None
    _check_stat(path, kind, st)
    return st


def check_name(path) -> None:
    """A :class:`DataError` naming ``path`` (as ``repr`` shows it) when it holds a NUL character,
    which no system call takes: ``os.stat`` raises a ValueError ("embedded null byte") naming no
    file, and ``Path.exists`` says False."""
    if "\0" in str(path):
        raise DataError(repr(str(path)), None, None, "a NUL character in the file name", "the name of a file",
                        whole=True)


#: What :func:`read_source` reads at a time beyond the size a file says it has.
_CHUNK = 1 << 20


def read_source(path, kind: str, head: int | None = None) -> bytes:
    """The bytes of ``path``, a regular file within the limit of ``kind`` (a key of
    :data:`LIMITS`); a :class:`DataError` naming the file otherwise (module docstring). With
    ``head``, only its first ``head`` bytes (fewer if it is shorter): a format's magic number,
    checked before a library that trusts it reads the file."""
    path = Path(path)
    check_source(path, kind)
    flags = os.O_RDONLY | getattr(os, "O_NONBLOCK", 0) | getattr(os, "O_CLOEXEC", 0) | getattr(os, "O_BINARY", 0)
    limit = LIMITS[kind].bytes
    want = limit + 1 if head is None else min(head, limit)
    try:
        with os.fdopen(os.open(path, flags), "rb", buffering=0) as handle:
            st = os.fstat(handle.fileno())
            _check_stat(path, kind, st)  # the file opened is still a regular one
            # as much as its size says, and a byte more (a read of n bytes takes n bytes of memory
            # at once, however few there are: a gibibyte for every small table), then more in
            # chunks while there is more (a file that grows, a /proc file of size 0)
            blocks = [handle.read(min(want, st.st_size + 1))]
            read = len(blocks[0])
            while read < want and (block := handle.read(min(want - read, _CHUNK))):
                blocks.append(block)
                read += len(block)
            data = blocks[0] if len(blocks) == 1 else b"".join(blocks)
    except OSError as error:
        raise _cannot_read(path, error) from None
    if len(data) > limit:
        raise _refuse_size(path, kind, None)
    return data


def read_lines(path, kind: str = "table") -> list[str]:
    """The lines of a UTF-8 text file (without line ends: LF, CR LF or CR; a leading byte-order
    mark dropped), read by :func:`read_source` within the size limit of ``kind`` ("table": CSV,
    TUM, KITTI; "yaml"); a :class:`DataError` naming the file if it is missing, unreadable, not a
    regular file, too large or not text, and the line of the first byte that is not UTF-8 or of
    the first NUL."""
    path = Path(path)
    data = read_source(path, kind)
    try:
        text = data.decode("utf-8")
    except UnicodeDecodeError as error:
        line = len(_LINE_END.split(data[: error.start].decode("utf-8")))  # valid up to the bad byte
        raise DataError(path, line, None, f"byte 0x{data[error.start]:02x}", "UTF-8 text") from None
    del data  # a table's bytes, its text and its lines would be three copies at once
    if text.startswith("\ufeff"):
        text = text[1:]
    if "\x00" in text:
        line = len(_LINE_END.split(text[: text.index("\x00")]))
        raise DataError(path, line, None, "a NUL character", "text") from None
    return _split_lines(text)


def number(token: str, path, line: int, field: str) -> float:
    """``token`` as a finite float, or a :class:`DataError` naming ``path``, ``line``, ``field``."""
    try:
        value = float(token)
    except (ValueError, TypeError):
        raise DataError(path, line, field, token, "a number") from None
    if "_" in token or not math.isfinite(value):
        raise DataError(path, line, field, token, "a finite number")
    return value


def integer(token: str, path, line: int, field: str) -> int:
    """``token`` as a (64-bit) integer, e.g. a nanosecond time stamp."""
    text = token.strip()
    body = text[1:] if text[:1] in "+-" else text
    if not body.isascii() or not body.isdigit():
        raise DataError(path, line, field, token, "an integer")
    value = int(text)
    if not -(2**63) <= value < 2**63:
        raise DataError(path, line, field, token, "an integer that fits in 64 bits")
    return value


def parse_rows(path, rows: list[tuple[int, list[str]]], fields: list[str],
               integer_fields=()) -> tuple[np.ndarray, np.ndarray]:
    """Parse ``rows`` (pairs of 1-based line number and tokens, exactly ``len(fields)`` each)
    into ``(floats, ints)``: a float array of shape ``(len(rows), len(fields))`` and an int64
    array with the columns named in ``integer_fields`` (whose entries in ``floats`` stay 0)."""
    n, m = len(rows), len(fields)
    out = np.zeros((n, m))
    int_cols = [fields.index(f) for f in integer_fields]
    ints = np.zeros((n, len(int_cols)), dtype=np.int64)
    for i, (line, tokens) in enumerate(rows):
        if len(tokens) != m:
            if len(tokens) < m:
                field = fields[len(tokens)]
                raise DataError(path, line, field, f"{len(tokens)} fields", f"{m} fields ({', '.join(fields)})")
            raise DataError(path, line, None, f"{len(tokens)} fields", f"{m} fields ({', '.join(fields)})")
        for j, token in enumerate(tokens):
            if j in int_cols:
                ints[i, int_cols.index(j)] = integer(token, path, line, fields[j])
            else:
                out[i, j] = number(token, path, line, fields[j])
    return out, ints


def check_increasing(path, t: np.ndarray, lines, field: str, duplicates: bool = False, counted: str = "line") -> None:
    """Raise a :class:`DataError` at the first time stamp that does not increase strictly (with
    ``duplicates``: that decreases; a stamp equal to the one before passes). The one time-order
    rule of every reader: stamps are taken in the order the file holds them, never re-sorted.
    ``lines`` says where each stamp is: 1-based lines of a text file (``counted`` "line": the
    error's place), or the 1-based index of a bag topic's message (``counted`` "message": named
    in the error beside the two stamps)."""
    t = np.asarray(t)
    if t.size < 2:
        return
    step = np.diff(t)
    bad = np.flatnonzero(step < 0 if duplicates else step <= 0)
    if bad.size:
        i = int(bad[0]) + 1
        what = "a duplicate of" if step[i - 1] == 0 else "earlier than"
        show = int if np.issubdtype(t.dtype, np.integer) else (lambda x: repr(float(x)))
        expected = "increasing time stamps" if duplicates else "strictly increasing time stamps"
        if counted == "line":
            raise DataError(path, int(lines[i]), field, f"{show(t[i])}, {what} line {int(lines[i - 1])} "
                            f"({show(t[i - 1])})", expected, whole=True)
        raise DataError(path, None, field, f"{counted} {int(lines[i])} stamped {show(t[i])}, {what} {counted} "
                        f"{int(lines[i - 1])} ({show(t[i - 1])})", f"{expected}, {counted} after {counted}",
                        whole=True)


def check_unit_quaternions(path, q: np.ndarray, lines, field: str, tolerance: float) -> np.ndarray:
    """Check ``| |q| - 1 | <= tolerance`` row by row and return the normalised quaternions."""
    norm = np.linalg.norm(q, axis=1)
    bad = np.flatnonzero(np.abs(norm - 1.0) > tolerance)
    if bad.size:
        i = int(bad[0])
        raise DataError(
            path, int(lines[i]), field, f"a quaternion of norm {norm[i]:.9g}",
            f"a unit quaternion (norm 1 within {tolerance:g})",
        )
    return q / norm[:, None]


def read_table(path, lines: list[str], fields: list[str], minimum: int, what: str, delimiter: str | None = None,
               comment: str = "#", skip: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """The data lines of a text table after ``skip`` header lines -- blank lines and lines
    starting with ``comment`` ignored, tokens separated by ``delimiter`` (None: whitespace) --
    as a float array ``(rows, len(fields))`` of finite numbers and the 1-based line number of
    each row; at least ``minimum`` rows (``what`` names them in the error).

    The common case (every data line a row of plain finite numbers) is read by NumPy's C parser
    in one call; anything else -- a bad token, a short row -- goes through the token-by-token
    parser, which names the first offending line and field. The C parser accepts a subset of
    what the token parser does (no underscores, no other Unicode digits), so both give the same
    values for any file they both accept."""
    body, numbers = numbered_lines(lines, comment, skip)
    values = table_fast(body, len(fields), delimiter)
    del body
    if values is not None and len(values) >= minimum:
        return values, numbers
    split = str.split if delimiter is None else (lambda text: text.split(delimiter))
    rows = data_rows(lines, split, comment=comment, skip=skip)
    require_rows(path, rows, len(lines), minimum, what)
    values, _ = parse_rows(path, rows, fields)
    return values, np.array([line for line, _ in rows], dtype=np.int64)


def table_fast(body: list[str], m: int, delimiter: str | None, stamps: bool = False):
    """``body`` as an ``(len(body), m)`` array of finite numbers by NumPy's C parser
    (``np.loadtxt`` of the lines), or None when any line is not such a row (``loadtxt`` skips blank lines, so
    a count mismatch means one). With ``stamps``, returns ``(values, first column as int64)``
    and the first column must be integers >= 0 (nanosecond time stamps, exact beyond 2^53)."""
    if not body:
        return None
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            # the lines themselves, not one text of them in an io.StringIO: that held the text
            # twice more, once as four bytes a character (a table took eight times its size)
            values = np.loadtxt(body, delimiter=delimiter, comments=None, ndmin=2, dtype=float)
            ints = (np.loadtxt(body, delimiter=delimiter, comments=None, ndmin=1, dtype=np.int64, usecols=0)
                    if stamps else None)
    except ValueError:
        return None
    if values.shape != (len(body), m) or not np.all(np.isfinite(values)):
        return None
    if stamps:
        if ints.shape != (len(body),) or np.any(ints < 0):
            return None
        return values, ints
    return values


def numbered_lines(lines: list[str], comment: str = "#", skip: int = 0) -> tuple[list[str], np.ndarray]:
    """:func:`data_lines` as two sequences, ``(texts, 1-based lines (int64))``: no tuple per line
    (a table of millions of lines is read whole, and those cost more than the numbers)."""
    texts, numbers = [], []
    for index in range(skip, len(lines)):
        text = lines[index].strip()
        if text and not (comment and text.startswith(comment)):
            texts.append(text)
            numbers.append(index + 1)
    return texts, np.array(numbers, dtype=np.int64)


def data_lines(lines: list[str], comment: str = "#", skip: int = 0) -> list[tuple[int, str]]:
    """Non-blank, non-comment lines after the first ``skip`` as ``(1-based line, stripped text)``."""
    out = []
    for index in range(skip, len(lines)):
        text = lines[index].strip()
        if text and not (comment and text.startswith(comment)):
            out.append((index + 1, text))
    return out


def data_rows(lines: list[str], split, comment: str = "#", skip: int = 0) -> list[tuple[int, list[str]]]:
    """:func:`data_lines` split into tokens: ``(1-based line, tokens)``."""
    return [(line, split(text)) for line, text in data_lines(lines, comment, skip)]


def require_rows(path, rows, n_lines: int, minimum: int, what: str) -> None:
    """At least ``minimum`` data rows, else a :class:`DataError` pointing after the last line."""
    if len(rows) < minimum:
        found = "an empty file" if n_lines == 0 else f"{len(rows)} data line{'s' if len(rows) != 1 else ''}"
        raise DataError(path, max(n_lines, 1) if len(rows) == 0 else rows[-1][0], None, found,
                        f"at least {minimum} {what}")


def require_imu_recording(path, t, field: str | None = None) -> None:
    """The IMU stamps ``t`` of the file ``path`` (integer nanoseconds, or float seconds) are a
    recording the loaders accept: at least :data:`~datasets.types.MIN_RECORDING_SAMPLES` samples
    over at least :data:`~datasets.types.MIN_RECORDING_SECONDS`; else a :class:`DataError` naming
    the file (and ``field``, a bag's topic) with what it holds."""
    t = np.asarray(t)
    seconds = (int(t[-1]) - int(t[0])) * 1e-9 if np.issubdtype(t.dtype, np.integer) else float(t[-1] - t[0])
    if len(t) >= MIN_RECORDING_SAMPLES and seconds >= MIN_RECORDING_SECONDS:
        return
    raise DataError(path, None, field, f"{len(t)} IMU sample{'s' if len(t) != 1 else ''} over {seconds:.4g} s",
                    f"an IMU recording of at least {MIN_RECORDING_SAMPLES} samples over at least "
                    f"{MIN_RECORDING_SECONDS:g} s ({MIN_RECORDING_WHY})", whole=True)


def duplicate_stamps(path, t: np.ndarray, lines) -> str | None:
    """None when the (non-decreasing) stamps ``t`` are all different, else one sentence naming the
    file, how many stamps repeat the one before and the first of them with its line, stamps whole."""
    t = np.asarray(t)
    repeated = np.flatnonzero(np.diff(t) == 0) + 1 if t.size > 1 else np.zeros(0, dtype=int)
    if repeated.size == 0:
        return None
    i = int(repeated[0])
    show = int(t[i]) if np.issubdtype(t.dtype, np.integer) else repr(float(t[i]))
    return (f"{path}: {repeated.size} time stamp(s) equal to the one before, the first at line {int(lines[i])} "
            f"({show}, as line {int(lines[i - 1])})")
