"""Which modules of the project's packages import which, read from their sources with ``ast``.

Every ``import`` and ``from ... import`` statement counts, also those inside functions (imports
made late to save start-up time are dependencies all the same). An import of ``a.b`` or
``from a import b`` names the module ``a.b`` when that module exists, else the module ``a``; imports
of anything outside the given packages are left out. Parent packages that Python imports on the
way (``a/__init__.py`` for ``a.b``) are not counted: they are not what the importing code uses.

The compiled kernels' caches (:mod:`factors.kernel_caches`) and the test of the layering use it.
"""
from __future__ import annotations

import ast
from pathlib import Path


def package_modules(root, packages) -> dict[str, Path]:
    """The dotted name of every module under ``root/<package>`` (sub-packages included) and its
    file; a package's own name stands for its ``__init__.py``."""
    out = {}
    for package in packages:
        for path in sorted(Path(root, package).rglob("*.py")):
            parts = path.relative_to(root).with_suffix("").parts
            out[".".join(parts[:-1] if parts[-1] == "__init__" else parts)] = path
    return out


def _imported(name: str, node: ast.AST, modules: dict[str, Path]) -> set[str]:
    """The modules of ``modules`` that the import statement ``node`` of module ``name`` names."""
    if isinstance(node, ast.Import):
        return {alias.name for alias in node.names if alias.name in modules}
    base = node.module or ""
    if node.level:  # relative: from the module's package, up level - 1 packages
        package = name if modules[name].name == "__init__.py" else name.rpartition(".")[0]
        parts = package.split(".")
        base = ".".join(parts[: len(parts) - node.level + 1] + ([base] if base else []))
    found = set()
    for alias in node.names:
        if f"{base}.{alias.name}" in modules:
            found.add(f"{base}.{alias.name}")
        elif base in modules:
            found.add(base)
    return found


def imports_of(name: str, modules: dict[str, Path]) -> set[str]:
    """The modules of ``modules`` (:func:`package_modules`) that module ``name`` imports."""
    path = modules[name]
    found = set()
    for node in ast.walk(ast.parse(path.read_bytes(), filename=str(path))):
        if isinstance(node, (ast.Import, ast.ImportFrom)):
            found |= _imported(name, node, modules)
    found.discard(name)
    return found


def module_imports(root, packages) -> dict[str, set[str]]:
    """For every module of ``packages`` (under ``root``), the modules of ``packages`` it imports."""
    modules = package_modules(root, packages)
    return {name: imports_of(name, modules) for name in modules}


def dependencies(graph: dict[str, set[str]], name: str) -> set[str]:
    """``name`` and every module it imports directly or through others."""
    seen, todo = {name}, [name]
    while todo:
        for other in graph[todo.pop()]:
            if other not in seen:
                seen.add(other)
                todo.append(other)
    return seen


def cycles(graph: dict[str, set[str]]) -> list[list[str]]:
    """The import cycles of ``graph``: one list of modules per strongly connected set of more than
    one module, each sorted (Tarjan's algorithm)."""
    index, low, stack, on_stack, out = {}, {}, [], set(), []

    def visit(v):
        index[v] = low[v] = len(index)
        stack.append(v)
        on_stack.add(v)
        for w in sorted(graph[v]):
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in on_stack:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            component = []
            while True:
                w = stack.pop()
                on_stack.discard(w)
                component.append(w)
                if w == v:
                    break
            if len(component) > 1:
                out.append(sorted(component))

    for v in sorted(graph):
        if v not in index:
            visit(v)
    return out
