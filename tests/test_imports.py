"""The import structure of the three packages (docs/design.md, "Layout").

The layers -- ``smoother -> datasets -> factors``, the subpackages of ``smoother`` top to bottom,
the estimators independent of each other, the layers of ``factors`` -- are import-linter contracts
in ``pyproject.toml`` (``[tool.importlinter]``), checked here by running ``lint-imports``. What
import-linter does not check is read from the sources with ``ast`` (every import statement, also
those inside functions): no module imports itself through others, the project's modules import from
the defining module rather than from a package's exports, no underscore name crosses a module
(tests included), and the tests of ``factors`` and ``datasets`` do not import ``smoother``."""
from __future__ import annotations

import ast
import subprocess
import sys
from pathlib import Path

from factors.imports import cycles, module_imports, package_modules
from smoother.cli import COMMAND_MODULES

ROOT = Path(__file__).resolve().parents[1]
PACKAGES = ("factors", "datasets", "smoother")


def test_the_import_contracts_hold():
    """``lint-imports`` with the contracts of ``pyproject.toml`` (its report is the failure's text)."""
    result = subprocess.run(
        [sys.executable, "-c", "from importlinter.cli import lint_imports_command; lint_imports_command()",
         "--no-cache"], capture_output=True, text=True, cwd=ROOT)
    assert result.returncode == 0, result.stdout[-6000:] + result.stderr[-2000:]
    assert "0 broken" in result.stdout


def test_the_command_line_imports_only_sub_commands_by_name():
    """``smoother.cli`` imports its sub-commands with ``importlib``, which no import graph sees: the
    contracts place it on top of ``commands``, and that holds while it names nothing else."""
    assert COMMAND_MODULES and all(name.startswith("smoother.commands.") for name in COMMAND_MODULES)
    assert set(COMMAND_MODULES) <= set(package_modules(ROOT, ("smoother",)))


def test_no_module_imports_itself_through_others():
    assert cycles(module_imports(ROOT, PACKAGES)) == []


def test_the_packages_import_from_modules_not_from_the_public_exports():
    """A package's ``__init__`` exports its API lazily, with no import statements; code that took
    a name from there would hide which module it depends on (from the compiled kernels' caches of
    ``factors.kernel_caches`` too)."""
    wrong = [f"{name} imports {other}" for name, imported in sorted(module_imports(ROOT, PACKAGES).items())
             for other in sorted(imported) if other in PACKAGES]
    assert wrong == []


#: What the tests of each package may import of the project: never ``smoother`` (the tests of the
#: sensor models take the kinds to go through from the registry, ``datasets.kinds``).
TESTED_WITH = {"factors": {"factors", "datasets"}, "datasets": {"factors", "datasets"}}


def test_the_tests_of_factors_and_datasets_do_not_import_smoother():
    """A test of ``factors`` or ``datasets`` that needs an estimator or the command line belongs
    with ``smoother``'s tests (``tests/smoother/``, ``tests/cli/``)."""
    wrong = []
    for package, allowed in TESTED_WITH.items():
        for path in sorted((ROOT / "tests" / package).rglob("*.py")):
            for node in ast.walk(ast.parse(path.read_bytes(), filename=str(path))):
                names = ([alias.name for alias in node.names] if isinstance(node, ast.Import)
                         else [node.module or ""] if isinstance(node, ast.ImportFrom) and not node.level else [])
                wrong += [f"{path.relative_to(ROOT)}:{node.lineno}: {name}" for name in names
                          if name.split(".")[0] in PACKAGES and name.split(".")[0] not in allowed]
    assert wrong == []


def _private(name: str) -> bool:
    return name.startswith("_") and not (name.startswith("__") and name.endswith("__"))


def private_uses(path: Path, name: str, project) -> list[tuple[int, str]]:
    """``(line, what)`` wherever the file ``path`` (module ``name``) takes an underscore name from
    another module of ``project`` (a predicate on dotted names): ``from X import _y``, and ``X._y``
    on a name bound to module ``X`` by an import (``import a.b``, ``import a.b as m``,
    ``from a import b``)."""
    tree = ast.parse(path.read_bytes(), filename=str(path))
    bound, out = {}, []
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            for alias in node.names:
                top = alias.name.split(".")[0]
                bound[alias.asname or top] = alias.name if alias.asname else top
        elif isinstance(node, ast.ImportFrom):
            base = node.module or ""
            if node.level:  # relative: from the module's package, up level - 1 packages
                parts = (name if path.name == "__init__.py" else name.rpartition(".")[0]).split(".")
                base = ".".join(parts[: len(parts) - node.level + 1] + ([base] if base else []))
            for alias in node.names:
                if project(base) and _private(alias.name):
                    out.append((node.lineno, f"from {base} import {alias.name}"))
                if project(f"{base}.{alias.name}"):
                    bound[alias.asname or alias.name] = f"{base}.{alias.name}"
    for node in ast.walk(tree):
        if isinstance(node, ast.Attribute) and _private(node.attr):
            chain, value = [], node.value
            while isinstance(value, ast.Attribute):
                chain.append(value.attr)
                value = value.value
            if isinstance(value, ast.Name) and value.id in bound:
                module = ".".join([bound[value.id], *reversed(chain)])
                if project(module) and module != name:
                    out.append((node.lineno, f"{module}.{node.attr}"))
    return out


def test_no_underscore_name_crosses_a_module():
    """What a module offers another is public in it; an underscore name stays in its module. The
    packages' modules and the tests (with their helper modules, imported by their file's name) are
    read alike."""
    modules = package_modules(ROOT, PACKAGES)
    tests = {".".join(path.relative_to(ROOT).with_suffix("").parts): path
             for path in sorted((ROOT / "tests").rglob("*.py"))}
    helpers = {path.stem for path in tests.values() if not path.stem.startswith("test_")}

    def project(dotted: str) -> bool:
        return dotted in modules or dotted in helpers

    wrong = [f"{path.relative_to(ROOT)}:{line}: {what}" for name, path in {**modules, **tests}.items()
             for line, what in private_uses(path, name, project)]
    assert wrong == []


def test_the_underscore_name_scan_sees_both_forms(tmp_path):
    scratch = tmp_path / "scratch.py"
    scratch.write_text("import smoother.batch.variance_components as vc\nfrom datasets import types\n"
                       "from datasets.types import _Hidden, check_times\n"
                       "vc._hidden(types._Hidden, types.__name__, vc.public)\n")
    uses = private_uses(scratch, "scratch", lambda dotted: dotted.split(".")[0] in PACKAGES)
    assert sorted(uses) == [(3, "from datasets.types import _Hidden"), (4, "datasets.types._Hidden"),
                            (4, "smoother.batch.variance_components._hidden")]
