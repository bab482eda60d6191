"""Each compiled kernel is compiled for one argument layout: the estimators, the batch solver's
blocks and the Python wrappers all pass C-contiguous, writable float64 arrays, so a first run
compiles (and caches) one copy of each kernel, not one per caller."""
from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

#: Runs the three estimators, and the fixed-lag smoother through GTSAM's factors (whose callbacks
#: run the kernels on GTSAM's arrays), on a short simulation in a fresh process with an empty
#: kernel cache (so every kernel is compiled there, also those called only from other kernels), then prints, for every compiled function of the package that
#: has more than one compiled copy, the copies' argument types with literal values made plain
#: (a literal argument -- a constant row offset, ``True`` -- is a deliberate specialisation).
_SCRIPT = """
import json, sys
from numba.core import types
from numba.core.registry import CPUDispatcher
from datasets.simulate import simulate
from smoother.pipeline import run_estimators, RunOptions

dataset = simulate("gentle", duration=3.0, seed=0)
run_estimators(dataset, ("batch", "fixed-lag", "ekf"), RunOptions(progress=False))
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
print(json.dumps(found))
"""


def test_every_kernel_is_compiled_for_one_layout(tmp_path):
    root = Path(__file__).resolve().parents[2]
    env = {**os.environ, "NUMBA_CACHE_DIR": str(tmp_path)}
    done = subprocess.run([sys.executable, "-c", _SCRIPT], cwd=root, env=env, capture_output=True, text=True,
                          check=True)
    assert json.loads(done.stdout.strip().splitlines()[-1]) == {}
