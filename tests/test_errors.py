"""One exception hierarchy (factors/errors.py): everything the project raises on purpose is a
``BoxplusError``; bad input an ``InputError`` (and a ``ValueError``), an estimator that could not
finish a ``SolverError``, a broken invariant of the project's own an ``InternalError``; the library
never raises the command line's ``UserError``, and the command line turns any of them into one
line and exit code 2 (3 for an ``InternalError``). No ``raise`` in the packages names a class
outside the hierarchy."""
from __future__ import annotations

import ast
import builtins
import importlib
import inspect
from pathlib import Path

import pytest

from datasets.errors import DataError
from factors.errors import BoxplusError, InputError, InputTypeError, InternalError, MissingKeyError, SolverError
from factors.imports import package_modules
from smoother.ekf.filter import FilterDiverged
from smoother.errors import IndeterminantSystem, UserError
from smoother.fixed_lag.contract import FixedLagFailed

ROOT = Path(__file__).resolve().parents[1]


@pytest.mark.parametrize("error, bases", [
    (DataError, (InputError, ValueError)),
    (UserError, (InputError, ValueError)),
    (IndeterminantSystem, (SolverError,)),
    (FilterDiverged, (SolverError, ValueError)),
    (FixedLagFailed, (SolverError, ValueError)),
    (InputTypeError, (InputError, TypeError)),
    (MissingKeyError, (InputError, KeyError)),
    (InternalError, (RuntimeError,)),
])
def test_every_error_of_the_project_is_a_boxplus_error(error, bases):
    assert issubclass(error, BoxplusError) and all(issubclass(error, base) for base in bases)


def test_every_exception_class_the_packages_define_derives_from_the_base():
    """Not a list to keep up: every exception class defined in any module of the three packages
    (``KeyboardInterrupt``'s kin for signals and warning categories, which are issued, never
    raised, aside) is a ``BoxplusError``."""
    outside = []
    for name in package_modules(ROOT, ("factors", "datasets", "smoother")):
        module = importlib.import_module(name)
        for cls in vars(module).values():
            if (inspect.isclass(cls) and issubclass(cls, BaseException) and cls.__module__ == name
                    and not issubclass(cls, (BoxplusError, KeyboardInterrupt, Warning))):
                outside.append(f"{name}.{cls.__name__}")
    assert outside == []


def test_only_the_command_line_raises_its_user_error():
    """``UserError`` names a command-line option; the library raises ``InputError`` (e.g.
    ``solve_batch`` with an unknown optimizer) and the command line words it."""
    command_line = ("smoother.cli", "smoother.errors", "smoother.commands.dataset_specs")
    users = [name for name, path in package_modules(ROOT, ("factors", "datasets", "smoother")).items()
             if not name.startswith("smoother.commands") and name not in command_line
             and any(isinstance(node, ast.Name) and node.id == "UserError" or
                     isinstance(node, ast.alias) and node.name == "UserError"
                     for node in ast.walk(ast.parse(path.read_bytes())))]
    assert users == []


def test_a_bad_optimizer_name_is_an_input_error():
    from datasets.simulate import simulate
    from smoother.batch.solve import solve_batch
    from smoother.model.problem import build_problem

    with pytest.raises(InputError, match="optimizer 'newton': expected one of lm, gn, dogleg") as info:
        solve_batch(build_problem(simulate(duration=0.5, seed=0)), optimizer="newton")
    assert not isinstance(info.value, UserError)


@pytest.mark.parametrize("error", [
    IndeterminantSystem("indeterminant system near keyframe 3\nGTSAM's own text"),
    FilterDiverged("the EKF diverged at t = 1.000000 s"),
    InputError("engine 'x': expected one of vectorized, gtsam"),
])
def test_the_command_line_reports_a_library_error_in_one_line_with_exit_code_2(error, monkeypatch, capsys, tmp_path):
    import smoother.pipeline
    from smoother.cli import main

    def fail(*args, **kwargs):
        raise error

    monkeypatch.setattr(smoother.pipeline, "estimate_each", fail)
    assert main(["run", "--duration", "1", "--no-progress", "--out", str(tmp_path)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert err[-1] == f"smoother: error: {str(error).splitlines()[0]}"
    assert not any("Traceback" in line or "GTSAM's own text" in line for line in err)


def _raises(tree: ast.AST, function: str = ""):
    """``(raise node, name of the function it is in)`` of every ``raise`` under ``tree``."""
    for node in ast.iter_child_nodes(tree):
        if isinstance(node, ast.Raise):
            yield node, function
        inner = node.name if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef)) else function
        yield from _raises(node, inner)


def _raised_classes(name: str, path: Path):
    """``(line, class, function)`` of every ``raise X(...)`` / ``raise X`` in module ``name`` whose
    ``X`` is a name or dotted name that resolves, in the module's namespace or the built-ins, to an
    exception class (a re-raise of a caught object, or a function that builds the exception, is
    not a class), with the name of the function it is in."""
    module = importlib.import_module(name)
    for node, function in _raises(ast.parse(path.read_bytes())):
        if node.exc is None:
            continue
        target = node.exc.func if isinstance(node.exc, ast.Call) else node.exc
        dotted = []
        while isinstance(target, ast.Attribute):
            dotted.insert(0, target.attr)
            target = target.value
        if not isinstance(target, ast.Name):
            continue
        value = vars(module).get(target.id, getattr(builtins, target.id, None))
        for attr in dotted:
            value = getattr(value, attr, None)
        if inspect.isclass(value) and issubclass(value, BaseException):
            yield node.lineno, value, function


#: Built-in classes that Python's own protocols ask for, by the function that raises them: an
#: interface's method that implementations replace (factors.jacobians.Manifold), and a lazily
#: exporting package's ``__getattr__`` (factors.exports), which ``getattr`` and ``hasattr`` need.
PROTOCOL = {("plus", NotImplementedError), ("minus", NotImplementedError), ("__getattr__", AttributeError)}


def test_every_raise_names_a_class_of_the_hierarchy():
    """Bad input is an ``InputError`` (still a ``ValueError``, ``TypeError`` or ``KeyError`` for
    callers that catch those), a broken invariant an ``InternalError`` (still a ``RuntimeError``),
    so a caller tells the project's errors from NumPy's or GTSAM's by one base class: no ``raise``
    names a built-in or foreign exception class (signals' ``KeyboardInterrupt`` kin and
    :data:`PROTOCOL` aside)."""
    outside = [f"{path.relative_to(ROOT)}:{line} raises {cls.__name__}"
               for name, path in package_modules(ROOT, ("factors", "datasets", "smoother")).items()
               for line, cls, function in _raised_classes(name, path)
               if not issubclass(cls, (BoxplusError, KeyboardInterrupt)) and (function, cls) not in PROTOCOL]
    assert outside == []


def test_a_plain_raise_would_be_caught(tmp_path, monkeypatch):
    """The scan above finds a built-in class raised by name, bare or called, and a class
    reached through a module."""
    package = tmp_path / "scanned"
    package.mkdir()
    (package / "__init__.py").write_text("")
    (package / "bad.py").write_text("import json\n\ndef f(x):\n    if x:\n        raise RuntimeError('no')\n"
                                    "    if x is None:\n        raise TypeError\n"
                                    "    raise json.JSONDecodeError('x', '', 0)\n")
    monkeypatch.syspath_prepend(str(tmp_path))
    found = sorted((line, cls.__name__, function) for line, cls, function in _raised_classes("scanned.bad",
                                                                                              package / "bad.py"))
    assert found == [(5, "RuntimeError", "f"), (7, "TypeError", "f"), (8, "JSONDecodeError", "f")]


def test_the_command_line_reports_a_broken_invariant_as_an_internal_failure(monkeypatch, capsys, tmp_path):
    """An ``InternalError`` is a defect, not bad input: one line naming it an internal failure,
    exit code 3 (as for any other failure inside the code)."""
    import smoother.pipeline
    from smoother.cli import main

    def fail(*args, **kwargs):
        raise InternalError("EKF and smoother keyframe times differ")

    monkeypatch.setattr(smoother.pipeline, "estimate_each", fail)
    assert main(["run", "--duration", "1", "--no-progress", "--out", str(tmp_path)]) == 3
    err = capsys.readouterr().err.strip().splitlines()
    assert err[-1] == "smoother: internal failure (InternalError): EKF and smoother keyframe times differ"
