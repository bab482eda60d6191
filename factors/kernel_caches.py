"""Numba's disk caches of the compiled kernels kept fresh across edits of the sources.

Numba compiles a kernel on first use and keeps it in its module's ``__pycache__``
(``cache=True``, :mod:`factors.compiled`), re-validated only against the kernel's OWN file. A
compiled kernel contains the kernels it calls from other modules (``so3`` inside ``imu``, ``imu``
inside the EKF), so after an edit of ``so3.py`` alone the cached IMU kernels would keep the old
mathematics. :func:`ensure_fresh_caches` drops the cached kernels of every module whose source,
or the source of a module it imports, has changed since its last check.

It runs when called, never on import, and must run before the first kernel of a process does (a
kernel already loaded keeps what it loaded). The entry points call it: ``smoother``'s command
line (:func:`smoother.cli.main`, also in each child it starts: ``smoother fleet``'s recordings) and
the test suite (``tests/conftest.py``). A library user who imports ``factors``, ``datasets`` or
``smoother`` without the command line gets Numba's own check only: a kernel compiles again when
its own file changes, not when a kernel it inlines from another module does. An installed
release's sources do not change, so nothing goes stale there; whoever edits the sources and runs
them from a script of their own calls :func:`ensure_fresh_caches` first (or sets
``NUMBA_CACHE_DIR`` to a folder they clear themselves).
"""
from __future__ import annotations

import hashlib
import json
import os
from pathlib import Path

from factors.imports import dependencies, imports_of, package_modules

#: The repository's root, whose packages :func:`ensure_fresh_caches` checks.
ROOT = Path(__file__).resolve().parent.parent
#: The packages whose modules hold kernels (or import modules that do).
PACKAGES = ("factors", "datasets", "smoother")
#: The fingerprints of the sources at the last check.
STAMP = ROOT / "factors" / "__pycache__" / "kernel-sources.json"

_checked = False


def ensure_fresh_caches() -> list[str]:
    """Drop the stale cached kernels of :data:`PACKAGES` (:func:`clear_stale_kernel_caches`), once
    per process, and return the modules whose caches were dropped. Nothing is done (and nothing
    returned) when ``NUMBA_CACHE_DIR`` is set -- a cache folder of the user's own is theirs to
    manage -- or when this process has checked already. About 2 ms when nothing changed: the
    import lists of unchanged files are kept with the fingerprints, so only edited files are
    parsed."""
    global _checked
    if _checked or "NUMBA_CACHE_DIR" in os.environ:
        return []
    _checked = True
    return clear_stale_kernel_caches(ROOT, PACKAGES, STAMP)


def clear_stale_kernel_caches(root, packages, stamp: Path) -> list[str]:
    """Remove Numba's cached kernels (``__pycache__/<module>.*.nbi``, ``*.nbc``) of every module
    of ``packages`` (under ``root``) whose source, or the source of any module it imports within
    the packages (directly or through others), has changed since the fingerprints in ``stamp``;
    returns the names of those modules (all of them when there is no stamp yet).

    Each module's fingerprint covers its own source and those of everything it imports
    (:mod:`factors.imports`, which reads every import statement, also inside functions); an edit
    recompiles the kernels of the edited module and of the modules that depend on it, and keeps
    the rest (an edit of the plots drops nothing that is compiled). Numba names a cache file
    after the module's file, ``<module>.<function>-<line>.<python>.nbi``. Unwritable directories
    are left as they are."""
    files = package_modules(root, packages)
    try:
        before = json.loads(stamp.read_text())  # {module: [source digest, fingerprint, imports]}
    except (OSError, ValueError):
        before = {}
    if not isinstance(before, dict):
        before = {}
    digests = {name: hashlib.sha256(path.read_bytes()).hexdigest() for name, path in files.items()}
    same_modules = before.keys() == files.keys()  # else an import may now name another module
    graph = {}
    for name in files:  # the imports of an unchanged source are those recorded (parsing costs ~3 ms a file)
        known = before.get(name)
        graph[name] = set(known[2]) if same_modules and known[0] == digests[name] else imports_of(name, files)
    fingerprints = {}
    for name in graph:
        digest = hashlib.sha256()
        for other in sorted(dependencies(graph, name)):
            digest.update(f"{other}\0{digests[other]}\0".encode())
        fingerprints[name] = digest.hexdigest()
    after = {name: [digests[name], fingerprints[name], sorted(graph[name])] for name in files}
    stale = [name for name in files if name not in before or before[name][1] != fingerprints[name]]
    if after == before:
        return []
    try:
        for name in stale:
            path = files[name]
            for cached in list(path.parent.joinpath("__pycache__").glob(f"{path.stem}.*.nb[ic]")):
                cached.unlink(missing_ok=True)
        stamp.parent.mkdir(parents=True, exist_ok=True)
        stamp.write_text(json.dumps(after, indent=0, sort_keys=True))
    except OSError:
        return []
    return stale
