"""Errors of the dataset loaders, and the small text-parsing helpers that raise them.

Every malformed input becomes one :class:`DataError` (an ``InputError``, so a ``ValueError``) whose message names the
file, the 1-based line, the field, what was found and what was expected, e.g.::

    /data/imu.txt, line 12, field 'accelY': found 'nan'; expected a finite number

Loaders never let an exception from deep inside NumPy or GTSAM escape for bad input, and never
return silently wrong data: a row they cannot read is an error, not a skipped row.
"""
from __future__ import annotations

import io
import math
import re
import warnings
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
    """Malformed input data (an :class:`factors.errors.InputError`, so also a ``ValueError``). ``path``, ``line`` (1-based, or None for the file as a whole),
    ``field`` (or None), ``found`` and ``expected`` are kept as attributes. ``found`` is shortened
    to :data:`_MAX_SHOWN` characters (it may be a whole fuzzed line) unless ``whole``: a text the
    loader composed from parsed values, which must stay readable to the last digit (kept as an
    attribute too, for an error re-raised with another field)."""

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


def read_lines(path, kind: str = "table") -> list[str]:
    """The lines of a UTF-8 text file (without line ends: LF, CR LF or CR; a leading byte-order
    mark dropped), read by :func:`datasets.sourcefile.read_source` within the size limit of
    ``kind`` ("table": CSV, TUM, KITTI; "yaml"); a :class:`DataError` naming the file if it is
    missing, unreadable, not a regular file, too large or not text, and the line of the first
    byte that is not UTF-8 or of the first NUL."""
    from datasets.sourcefile import read_source  # it raises this module's DataError

    path = Path(path)
    data = read_source(path, kind)
    try:
        text = data.decode("utf-8")
    except UnicodeDecodeError as error:
        line = len(_LINE_END.split(data[: error.start].decode("utf-8")))  # valid up to the bad byte
        raise DataError(path, line, None, f"byte 0x{data[error.start]:02x}", "UTF-8 text") from None
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
        show = int if np.issubdtype(t.dtype, np.integer) else (lambda x: repr(float(x)))  # noqa: E731
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
    numbered = data_lines(lines, comment, skip)
    values = table_fast([text for _, text in numbered], len(fields), delimiter)
    if values is not None and len(values) >= minimum:
        return values, np.array([line for line, _ in numbered], dtype=np.int64)
    split = str.split if delimiter is None else (lambda text: text.split(delimiter))
    rows = data_rows(lines, split, comment=comment, skip=skip)
    require_rows(path, rows, len(lines), minimum, what)
    values, _ = parse_rows(path, rows, fields)
    return values, np.array([line for line, _ in rows], dtype=np.int64)


def table_fast(body: list[str], m: int, delimiter: str | None, stamps: bool = False):
    """``body`` as an ``(len(body), m)`` array of finite numbers by NumPy's C parser
    (``np.loadtxt``), or None when any line is not such a row (``loadtxt`` skips blank lines, so
    a count mismatch means one). With ``stamps``, returns ``(values, first column as int64)``
    and the first column must be integers >= 0 (nanosecond time stamps, exact beyond 2^53)."""
    if not body:
        return None
    text = "\n".join(body)
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            values = np.loadtxt(io.StringIO(text), delimiter=delimiter, comments=None, ndmin=2, dtype=float)
            ints = (np.loadtxt(io.StringIO(text), delimiter=delimiter, comments=None, ndmin=1, dtype=np.int64,
                               usecols=0) if stamps else None)
    except ValueError:
        return None
    if values.shape != (len(body), m) or not np.all(np.isfinite(values)):
        return None
    if stamps:
        if ints.shape != (len(body),) or np.any(ints < 0):
            return None
        return values, ints
    return values


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
    raise DataError(path, None, field, f"{len(t)} IMU sample{'s' if len(t) != 1 else ''} over {seconds:.6g} s",
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
