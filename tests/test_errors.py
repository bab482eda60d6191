"""One exception hierarchy (factors/errors.py): everything the project raises on purpose is a
``BoxplusError``; bad input an ``InputError`` (and a ``ValueError``), an estimator that could not
finish a ``SolverError``; the library never raises the command line's ``UserError``, and the
command line turns any of them into one line and exit code 2."""
from __future__ import annotations

import ast
from pathlib import Path

import pytest

from datasets.errors import DataError
from factors.errors import BoxplusError, InputError, SolverError
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
])
def test_every_error_of_the_project_is_a_boxplus_error(error, bases):
    assert issubclass(error, BoxplusError) and all(issubclass(error, base) for base in bases)


def test_every_exception_class_the_packages_define_derives_from_the_base():
    """Not a list to keep up: every exception class defined in any module of the three packages
    (``KeyboardInterrupt``'s kin for signals aside) is a ``BoxplusError``."""
    import importlib
    import inspect

    outside = []
    for name in package_modules(ROOT, ("factors", "datasets", "smoother")):
        module = importlib.import_module(name)
        for cls in vars(module).values():
            if (inspect.isclass(cls) and issubclass(cls, BaseException) and cls.__module__ == name
                    and not issubclass(cls, (BoxplusError, KeyboardInterrupt))):
                outside.append(f"{name}.{cls.__name__}")
    assert outside == []


def test_only_the_command_line_raises_its_user_error():
    """``UserError`` names a command-line option; the library raises ``InputError`` (e.g.
    ``solve_batch`` with an unknown optimizer) and the command line words it."""
    command_line = ("smoother.cli", "smoother.errors", "smoother.commands.dataset_specs")
    users = [name for name, path in package_modules(ROOT, ("factors", "datasets", "smoother")).items()
             if not name.startswith("smoother.commands") and name not in command_line
             and any(isinstance(node, ast.Name) and node.id == "UserError" or
                     isinstance(node, ast.alias) and node.name == "UserError" for node in ast.walk(ast.parse(path.read_bytes())))]
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


def test_nothing_raises_a_bare_value_error():
    """Bad input is an ``InputError`` (still a ``ValueError`` for callers that catch that), so a
    caller can tell the project's errors from NumPy's or GTSAM's by one base class."""
    bare = []
    for package in ("factors", "datasets", "smoother"):
        for path in sorted((ROOT / package).rglob("*.py")):
            for node in ast.walk(ast.parse(path.read_text())):
                if isinstance(node, ast.Raise) and node.exc is not None:
                    call = node.exc.func if isinstance(node.exc, ast.Call) else node.exc
                    if isinstance(call, ast.Name) and call.id == "ValueError":
                        bare.append(f"{path.relative_to(ROOT)}:{node.lineno}")
    assert bare == []
