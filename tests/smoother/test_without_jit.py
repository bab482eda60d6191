"""``NUMBA_DISABLE_JIT=1`` runs every kernel as the plain Python it is written in: no compilation,
so a short case runs in about a second after an edit of a kernel (the compiled caches take tens of
seconds to rebuild). The results must be those of the compiled kernels.

Tolerances: the compiled recursions may fuse ``a * b + c`` (``factors.compiled.recursion``), so the
two differ by round-off: states to 1e-12 relative to each array's size (a few hundred steps);
covariances to 1e-8, since the batch smoother's marginals invert an information matrix whose
condition number (~1e6 with the weakly observed biases) amplifies the round-off (1e-9 measured)."""
from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[2]

CASE = """
import sys
import numpy as np
from datasets.simulate import simulate
from smoother.batch.solve import solve_batch
from smoother.ekf.filter import run_ekf
from smoother.model.problem import build_problem

data = simulate(profile="tumbling", duration=1.0, seed=3)
batch, ekf = solve_batch(build_problem(data)).trajectory, run_ekf(data).trajectory
np.savez(sys.argv[1], **{f"{name}_{part}": getattr(estimate.states, part) if part != "cov" else estimate.cov
                         for name, estimate in (("batch", batch), ("ekf", ekf))
                         for part in ("r", "v", "C", "b_w", "cov")})
"""


def _run(out: Path, **env) -> dict:
    environment = dict(os.environ, PYTHONPATH=str(ROOT), **env)
    subprocess.run([sys.executable, "-c", CASE, str(out)], check=True, env=environment, cwd=ROOT, timeout=600)
    with np.load(out) as arrays:
        return dict(arrays)


def test_the_kernels_run_as_python_with_numba_disable_jit_and_give_the_compiled_results(tmp_path):
    compiled = _run(tmp_path / "compiled.npz", NUMBA_DISABLE_JIT="0")
    python = _run(tmp_path / "python.npz", NUMBA_DISABLE_JIT="1")
    assert compiled.keys() == python.keys()
    for name, value in compiled.items():
        tolerance = 1e-8 if name.endswith("cov") else 1e-12
        assert np.abs(python[name] - value).max() <= tolerance * np.abs(value).max(), name
