"""Long positional parameter lists belong to the compiled kernels only: Numba takes flat arrays
and numbers, not objects, so a kernel's signature is its data layout (the state's ``r, v, C, b_f,
b_w``, a window's arrays). A plain Python function with :data:`LIMIT` or more positional
parameters takes the dataclass its callers already hold instead (read with ``ast``; a function
counts as compiled when its module's attribute of that name is a Numba dispatcher)."""
from __future__ import annotations

import ast
import importlib
from pathlib import Path

from numba.core.registry import CPUDispatcher

from factors.imports import package_modules

ROOT = Path(__file__).resolve().parents[1]
LIMIT = 15


def long_signatures(name: str, path: Path) -> list[tuple[str, int, bool]]:
    """``(function, positional parameters, compiled)`` of each function of module ``name`` with at
    least :data:`LIMIT` positional parameters."""
    module = importlib.import_module(name)
    out = []
    for node in ast.walk(ast.parse(path.read_bytes())):
        if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef)):
            count = len(node.args.posonlyargs) + len(node.args.args)
            if count >= LIMIT:
                out.append((node.name, count, isinstance(vars(module).get(node.name), CPUDispatcher)))
    return out


def test_only_compiled_kernels_take_many_positional_parameters():
    modules = package_modules(ROOT, ("factors", "datasets", "smoother"))
    plain = [f"{name}.{function} ({count})" for name, path in modules.items()
             for function, count, compiled in long_signatures(name, path) if not compiled]
    assert plain == []
