"""datasets.atomic.atomic_write: all or nothing, and the file ends up as open(path, "w") would
leave it (permissions from the umask or the old file, symbolic links written through)."""
from __future__ import annotations

import os
import stat

import pytest

from datasets.atomic import atomic_write


@pytest.fixture
def umask():
    """Set the process's umask for one test (and restore it)."""
    before = os.umask(0o022)
    yield lambda mask: os.umask(mask)
    os.umask(before)


def _mode(path) -> int:
    return stat.S_IMODE(os.stat(path).st_mode)


@pytest.mark.parametrize("mask", [0o022, 0o027, 0o077])
def test_a_new_file_gets_the_umask_permissions(tmp_path, umask, mask):
    umask(mask)
    with atomic_write(tmp_path / "new.txt") as handle:
        handle.write("x")
    assert _mode(tmp_path / "new.txt") == 0o666 & ~mask
    assert (tmp_path / "new.txt").read_text() == "x"


def test_an_existing_file_keeps_its_permissions(tmp_path, umask):
    umask(0o077)
    path = tmp_path / "old.txt"
    path.write_text("old")
    os.chmod(path, 0o640)
    with atomic_write(path, "wb") as handle:
        handle.write(b"new")
    assert (path.read_text(), _mode(path)) == ("new", 0o640)


def test_a_symbolic_link_is_written_through(tmp_path):
    target, link = tmp_path / "target.txt", tmp_path / "link.txt"
    target.write_text("old")
    link.symlink_to(target.name)
    with atomic_write(link) as handle:
        handle.write("new")
    assert link.is_symlink() and os.readlink(link) == target.name
    assert target.read_text() == "new"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["link.txt", "target.txt"]


def test_an_error_leaves_the_old_content_and_no_temporary_file(tmp_path):
    path = tmp_path / "keep.txt"
    path.write_text("old")
    with pytest.raises(RuntimeError):
        with atomic_write(path) as handle:
            handle.write("half")
            raise RuntimeError("interrupted")
    assert path.read_text() == "old"
    assert [p.name for p in tmp_path.iterdir()] == ["keep.txt"]


def test_an_os_error_while_writing_names_the_file(tmp_path):
    """A write failing with an OSError that names no file (a full disk) names the file being
    written; the old content stays."""
    import errno

    path = tmp_path / "keep.txt"
    path.write_text("old")
    with pytest.raises(OSError) as caught:
        with atomic_write(path):
            raise OSError(errno.ENOSPC, "No space left on device")
    assert caught.value.filename == str(path) and str(path) in str(caught.value)
    assert path.read_text() == "old"
    assert [p.name for p in tmp_path.iterdir()] == ["keep.txt"]


def test_an_os_error_creating_the_temporary_file_names_the_file(tmp_path, monkeypatch):
    """The temporary file cannot be made (a read-only folder, a full disk): the error names the
    file meant, not the hidden temporary name; nothing is left behind."""
    import errno

    real_open = os.open

    def refusing(name, *args, **kwargs):
        if str(name).endswith(".tmp"):
            raise OSError(errno.EROFS, "Read-only file system", str(name))
        return real_open(name, *args, **kwargs)

    monkeypatch.setattr(os, "open", refusing)
    path = tmp_path / "out.txt"
    with pytest.raises(OSError) as caught:
        with atomic_write(path) as handle:
            handle.write("x")
    assert caught.value.filename == str(path) and ".tmp" not in str(caught.value)
    assert list(tmp_path.iterdir()) == []
