"""Shared test configuration: the compiled kernels' caches checked before any test runs a kernel
(:func:`factors.kernel_caches.ensure_fresh_caches`, as the command line does), Hypothesis profiles
and the import path of the shared helper modules (``tests/strategies.py`` and the others
next to it).

Profiles (choose with ``HYPOTHESIS_PROFILE=<name>``; ``ci`` when the environment variable ``CI``
is set, as it is in the project's CI; ``default`` otherwise):

* ``default``: 100 examples per property, no deadline (the first call of a GTSAM wrapper or of
  numpy's linear algebra can be slow, and timing is not what these tests assert).
* ``ci``: as ``default`` but derandomised, so that a CI run is reproducible from the commit alone.
* ``dev``: 30 examples, for a quick edit-and-run loop.
* ``thorough``: 2000 examples, for an occasional deep run.
"""
from __future__ import annotations

import os
import signal
import sys

from hypothesis import HealthCheck, settings

from factors.kernel_caches import ensure_fresh_caches

ensure_fresh_caches()  # before the test modules import (and run) any kernel

# Python turns SIGINT into KeyboardInterrupt only when the process starts with SIGINT's default
# disposition; a run started where it is ignored (a background job of a non-interactive shell, under
# GNU time) would leave the tests of Ctrl-C handling without it
if signal.getsignal(signal.SIGINT) is signal.SIG_IGN:
    signal.signal(signal.SIGINT, signal.default_int_handler)

# The helper modules the tests share sit next to this file (strategies.py, rigfiles.py, bagfiles.py,
# eurocfiles.py, small_recording.py, mounted_kinds.py, gtsam_values.py, drifting_fixes.py, isolation.py):
# this directory on sys.path makes ``import strategies`` work from every folder of tests/, under
# pytest's default (prepend) import mode, which puts only each test file's own folder there, and
# under ``--import-mode=importlib``.
_HERE = os.path.dirname(os.path.abspath(__file__))
if _HERE not in sys.path:
    sys.path.insert(0, _HERE)

_COMMON = dict(deadline=None, suppress_health_check=[HealthCheck.too_slow])
settings.register_profile("default", max_examples=100, **_COMMON)
settings.register_profile("ci", max_examples=100, derandomize=True, **_COMMON)
settings.register_profile("dev", max_examples=30, **_COMMON)
settings.register_profile("thorough", max_examples=2000, **_COMMON)
settings.load_profile(os.environ.get("HYPOTHESIS_PROFILE", "ci" if os.environ.get("CI") else "default"))
