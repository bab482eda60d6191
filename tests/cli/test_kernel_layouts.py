"""Each compiled kernel is compiled for one argument layout: the estimators, the batch solver's
blocks and the Python wrappers all pass C-contiguous, writable float64 arrays, so a first run
compiles (and caches) one copy of each kernel, not one per caller. The same first run compiles the
sliding window's kernels in a second process (smoother/online/warm_up.py), from whose cache the
run then loads them."""
from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

from factors.threads import thread_count

#: Runs the three estimators, and the fixed-lag smoother through GTSAM's factors (whose callbacks
#: run the kernels on GTSAM's arrays), on a short simulation in a fresh process with an empty
#: kernel cache (so every kernel is compiled there, also those called only from other kernels),
#: then prints, for every compiled function of the package that has more than one compiled copy,
#: the copies' argument types with literal values made plain (a literal argument -- a constant row
#: offset, ``True`` -- is a deliberate specialisation);
#: and the warm-up child's exit status and the window kernel's cache hits and misses.
_SCRIPT = """
import json, sys
from numba.core import types
from numba.core.registry import CPUDispatcher
from datasets.simulate import simulate
from smoother.online import warm_up as kernel_warm_up
from smoother.fixed_lag.sliding.normal_equations import linearise
from smoother.pipeline import run_estimators, RunOptions

children = []
start = kernel_warm_up.start
kernel_warm_up.start = lambda *args: children.append(start(*args)) or children[-1]
dataset = simulate("gentle", duration=3.0, seed=0)
run_estimators(dataset, ("batch", "fixed-lag", "ekf"), RunOptions(progress=False))
warm_up = {"exit": [c._process.returncode for c in children if c is not None],
           "hits": sum(linearise.stats.cache_hits.values()), "misses": sum(linearise.stats.cache_misses.values())}
run_estimators(dataset, ("fixed-lag",), RunOptions(fixed_lag_kind="incremental", progress=False))
found = {}
for name, module in list(sys.modules.items()):
    if module is None or not name.startswith(("factors", "datasets", "smoother")):
        continue
    for attr, value in vars(module).items():
        if isinstance(value, CPUDispatcher) and value.__module__ == name:
            plain = {tuple(str(types.unliteral(t)) for t in sig) for sig in value.signatures}
            if len(plain) > 1:
                found[f"{name}.{attr}"] = sorted(map(list, plain))
print(json.dumps({"layouts": found, "warm_up": warm_up}))
"""


@pytest.fixture(scope="module")
def first_run(tmp_path_factory) -> dict:
    root = Path(__file__).resolve().parents[2]
    env = {**os.environ, "NUMBA_CACHE_DIR": str(tmp_path_factory.mktemp("cache"))}
    done = subprocess.run([sys.executable, "-c", _SCRIPT], cwd=root, env=env, capture_output=True, text=True,
                          check=True)
    return json.loads(done.stdout.strip().splitlines()[-1])


def test_every_kernel_is_compiled_for_one_layout(first_run):
    assert first_run["layouts"] == {}


@pytest.mark.skipif(thread_count() < 2, reason="the warm-up runs only with a second thread")
def test_the_first_run_loads_the_window_kernels_the_warm_up_child_compiled(first_run):
    assert first_run["warm_up"] == {"exit": [0], "hits": 1, "misses": 0}
