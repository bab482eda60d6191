"""Lazy public exports of a package: ``package.name`` imports the module that defines ``name``
on first use, so ``import smoother`` stays cheap (the estimators pull in GTSAM and Numba, ~0.7 s)
while ``from smoother import solve_batch``, ``dir(smoother)`` and ``help(smoother)`` show the
whole public API."""
from __future__ import annotations

import importlib


def lazy_exports(namespace: dict, exports: dict[str, str]):
    """``(__getattr__, __dir__)`` for the package whose module namespace is ``namespace``:
    ``exports`` maps each public name to the module that defines it (a name equal to that
    module's last component is the module itself, e.g. ``"so3": "factors.so3"`` or ``"metrics":
    "smoother.evaluation.metrics"``). A name is looked up once, then kept in the namespace."""
    package = namespace["__name__"]

    def __getattr__(name: str):
        """The public ``name`` of this package, imported from its module on first use."""
        if name not in exports:
            raise AttributeError(f"module {package!r} has no attribute {name!r}")
        module = importlib.import_module(exports[name])
        value = module if exports[name].rsplit(".", 1)[-1] == name else getattr(module, name)
        namespace[name] = value
        return value

    def __dir__():
        """The package's names, the public ones not yet imported included."""
        return sorted(set(namespace) | set(exports))

    return __getattr__, __dir__
