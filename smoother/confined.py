"""One guard for every path a command writes or deletes: it lies inside the directory the user
named (``--out``, a run directory), after symbolic links and ``..`` are resolved.

A name that leads out of the directory is refused, not followed: a fleet's recording folder named
after a rig file ``...toml`` (stem ``..``) would be the directory's parent, and a run into it would
overwrite the files there and delete others as "the previous run's"; a run file that is a symbolic
link to a file elsewhere would have that file overwritten. Every writer of a command's outputs
resolves its paths through :func:`inside`: the run directory's files, lock and deletions
(:class:`smoother.commands.run_directory.RunDirectory`), every figure
(:func:`smoother.outputs.canvas.save_png`), ``smoother fleet``'s recording folders, logs and summary
and ``smoother montecarlo``'s summary and runs. :func:`folder_name_problem` says why a name cannot
be a folder of its own inside a directory (a fleet's rig stems).
"""
from __future__ import annotations

import os
import stat
from pathlib import Path

from factors.errors import InputError


def inside(directory, name: str, follow: bool = True) -> Path:
    """``directory / name``, when it lies inside ``directory`` (which need not exist yet) once
    both are resolved -- symbolic links followed (with ``follow``; else those of its folder only,
    for a deletion, which removes a link itself), ``..`` taken --; otherwise an InputError naming
    both and where the path leads. An empty ``directory`` is refused too: it would be the current
    one, named by nothing."""
    if not str(directory):
        raise InputError("the output directory is named by an empty string; expected a directory's name")
    root = Path(directory).resolve()
    path = Path(directory) / name
    resolved = path.resolve() if follow else path.parent.resolve() / path.name
    if resolved != root and root not in resolved.parents:
        how = "is a symbolic link to" if os.path.islink(path) else "leads to"
        raise InputError(f"{path} {how} {resolved}, outside {directory}: a command writes and deletes only inside "
                         "the directory it is given")
    return path


def file_inside(directory, name: str) -> Path:
    """:func:`inside`, for a file a command opens and writes in place (a run directory's lock, a
    fleet recording's log): what is there already must be a regular file, or nothing. A named pipe
    there would block the opening until another program read it, a device take what is written;
    an InputError naming it otherwise. (Files written whole are written atomically, replacing
    whatever has their name.)"""
    path = inside(directory, name)
    try:
        mode = os.stat(path).st_mode
    except FileNotFoundError:
        return path
    except OSError as error:
        raise InputError(f"{path}: cannot be written ({error.strerror})") from None
    if not stat.S_ISREG(mode):
        what = ("a named pipe (FIFO)" if stat.S_ISFIFO(mode) else "a directory" if stat.S_ISDIR(mode)
                else "a device" if stat.S_ISCHR(mode) or stat.S_ISBLK(mode) else "a socket" if stat.S_ISSOCK(mode)
                else "a special file")
        raise InputError(f"{path} is {what}, not a regular file: a command writes its files as regular files; "
                         "remove it")
    return path


def folder_name_problem(name: str) -> str | None:
    """None when ``name`` can be a folder of its own inside a directory, else why not: empty,
    ``.`` or ``..`` (the directory itself or its parent), hidden (a leading ``.``: the run
    directory's own hidden files begin so) or holding a path separator or a NUL."""
    if name in ("", ".", ".."):
        return f"{name!r} names {'the directory itself' if name != '..' else 'its parent'}, not a folder in it"
    if name.startswith("."):
        return f"{name!r} begins with '.': it would be a hidden folder, as the tool's own files are"
    if any(c in name for c in (os.sep, os.altsep or os.sep, "\0")):
        return f"{name!r} holds a path separator or a NUL"
    return None
