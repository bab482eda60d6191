"""datasets.errors.read_table: the NumPy fast path and the token-by-token parser agree, and every
file the fast path cannot take falls back to the parser that names the offending line."""
from __future__ import annotations

import numpy as np
import pytest

from datasets import errors
from datasets.errors import DataError, read_table

FIELDS = ["t", "x", "y"]


def _table(rng, n=50):
    values = np.column_stack([np.arange(n) * 0.01, rng.normal(size=(n, 2)) * 1e3])
    return values, [" ".join(repr(float(v)) for v in row) for row in values]


@pytest.mark.parametrize("delimiter", [None, ","])
def test_fast_path_and_token_parser_give_the_same_values(delimiter, monkeypatch):
    rng = np.random.default_rng(0)
    values, lines = _table(rng)
    if delimiter:
        lines = [line.replace(" ", " , ") for line in lines]  # spaces around the commas too
    with monkeypatch.context() as patch:  # the token parser must not be reached on these two
        patch.setattr(errors, "data_rows", lambda *args, **kwargs: pytest.fail("token parser used"))
        fast, numbers = read_table("f.txt", ["header"] + lines, FIELDS, 1, "rows", delimiter=delimiter, skip=1)
        assert np.array_equal(fast, values) and np.array_equal(numbers, np.arange(2, len(lines) + 2))
        # comment and blank lines (a TUM header) are skipped by the fast path; the numbers shift
        lead, numbers = read_table("f.txt", ["header", "# columns", ""] + lines, FIELDS, 1, "rows",
                                   delimiter=delimiter, skip=1)
        assert np.array_equal(lead, values) and np.array_equal(numbers, np.arange(4, len(lines) + 4))
    # a comment and a blank line further down: same values, the line numbers skip the two extra lines
    slow, numbers = read_table("f.txt", ["header", "# comment"] + lines[:10] + [""] + lines[10:], FIELDS, 1, "rows",
                               delimiter=delimiter, skip=1)
    assert np.array_equal(slow, values)
    assert np.array_equal(numbers, np.r_[3:13, 14:len(lines) + 4])
    # a digit only Python's float reads (ARABIC-INDIC THREE): the token parser takes the file,
    # every other value as the fast path reads it
    sep = delimiter or " "
    odd = lines[:5] + [sep.join(["\u0663"] + lines[5].split(sep)[1:])] + lines[6:]
    slow, numbers = read_table("f.txt", odd, FIELDS, 1, "rows", delimiter=delimiter)
    expected = values.copy()
    expected[5, 0] = 3.0
    assert np.array_equal(slow, expected) and np.array_equal(numbers, np.arange(1, len(lines) + 1))


@pytest.mark.parametrize("bad, field, found", [
    ("0.5 1.0", "y", "2 fields"),
    ("0.5 1.0 2.0 3.0", None, "4 fields"),
    ("0.5 nan 2.0", "x", "nan"),
    ("0.5 1_0 2.0", "x", "1_0"),
    ("0.5 0x10 2.0", "x", "0x10"),
])
def test_a_bad_row_is_named_by_line_and_field(bad, field, found):
    rng = np.random.default_rng(1)
    _, lines = _table(rng, 20)
    lines[7] = bad
    with pytest.raises(DataError) as info:
        read_table("f.txt", lines, FIELDS, 1, "rows")
    message = str(info.value)
    assert "f.txt" in message and "line 8" in message and found in message, message
    if field:
        assert field in message


def test_too_few_rows_is_an_error():
    with pytest.raises(DataError, match="at least 3 rows"):
        read_table("f.txt", ["0 1 2", "1 2 3"], FIELDS, 3, "rows")


@pytest.mark.parametrize("end", ["\n", "\r\n", "\r"])
def test_read_lines_cuts_at_line_ends_only(tmp_path, end):
    """LF, CR LF and CR end lines; characters that str.splitlines would also cut at (form feed,
    U+2028, NEL, ...) stay inside their line, so a comment cannot leak a data row."""
    inside = ["\x0b", "\x0c", "\x1c", "\x1d", "\x1e", "\x85", "\u2028", "\u2029"]
    lines = ["# t x y", "0.0 1 2"] + [f"# dropped:{c}0.05 99 99" for c in inside] + ["0.1 3 4"]
    path = tmp_path / "t.txt"
    path.write_bytes((end.join(lines) + end).encode())
    assert errors.read_lines(path) == lines
    values, numbers = read_table(path, errors.read_lines(path), FIELDS, 1, "rows")
    assert np.array_equal(values, [[0.0, 1, 2], [0.1, 3, 4]]) and list(numbers) == [2, len(lines)]
    path.write_bytes(end.join(lines).encode())  # no line end after the last line
    assert errors.read_lines(path) == lines


def test_read_lines_drops_a_byte_order_mark(tmp_path):
    path = tmp_path / "bom.txt"
    path.write_bytes("\ufeff# t x y\r\n0.0 1 2\r\n".encode())
    assert errors.read_lines(path) == ["# t x y", "0.0 1 2"]
    path.write_bytes("0.0 1 2\n\ufeff0.1 3 4\n".encode())  # only a leading one is a BOM
    with pytest.raises(DataError) as info:
        read_table(path, errors.read_lines(path), FIELDS, 1, "rows")
    assert info.value.line == 2


@pytest.mark.parametrize("end", ["\n", "\r\n", "\r"])
def test_read_lines_names_the_line_of_a_bad_byte_or_nul(tmp_path, end):
    path = tmp_path / "b.txt"
    for bad, found in ((b"\xff", "byte 0xff"), (b"\x00", "a NUL character")):
        path.write_bytes(end.join(["# c", "0.0 1 2", "0.1 3 4"]).encode() + bad + end.encode())
        with pytest.raises(DataError) as info:
            errors.read_lines(path)
        assert (info.value.line, info.value.found) == (3, found)
