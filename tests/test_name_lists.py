"""Each list of names that several modules need is written once, in a module of its own that the
command line can import cheaply, and everything else takes it from there: no other literal tuple,
list or set in the three packages holds all of its names (read with ``ast``)."""
from __future__ import annotations

import ast
from pathlib import Path

import pytest

from smoother.batch.methods import OPTIMIZERS
from smoother.estimators import ESTIMATORS
from smoother.evaluation.modes import ALIGN_MODES, DELTA_UNITS
from smoother.fixed_lag.kinds import FIXED_LAG_KINDS

ROOT = Path(__file__).resolve().parents[1]

#: Each list with the module that defines it.
LISTS = [
    ("smoother/estimators.py", ESTIMATORS),
    ("smoother/batch/methods.py", OPTIMIZERS),
    ("smoother/evaluation/modes.py", ALIGN_MODES),
    ("smoother/evaluation/modes.py", DELTA_UNITS),
    ("smoother/fixed_lag/kinds.py", FIXED_LAG_KINDS),
]


def _literal_lists(tree: ast.AST):
    """``(line, names)`` of every tuple, list or set literal of string constants in ``tree``."""
    for node in ast.walk(tree):
        if isinstance(node, (ast.Tuple, ast.List, ast.Set)) and node.elts and all(
                isinstance(e, ast.Constant) and isinstance(e.value, str) for e in node.elts):
            yield node.lineno, {e.value for e in node.elts}


def written_again(root: Path, home: str, names) -> list[str]:
    """Where under ``root`` a literal holds all of ``names``, outside ``home``."""
    again = []
    for package in ("factors", "datasets", "smoother"):
        for path in sorted((root / package).rglob("*.py")):
            where = path.relative_to(root).as_posix()
            if where != home:
                again += [f"{where}:{line}" for line, found in _literal_lists(ast.parse(path.read_text()))
                          if set(names) <= found]
    return again


@pytest.mark.parametrize("home, names", LISTS)
def test_a_list_of_names_is_written_once(home, names):
    assert written_again(ROOT, home, names) == [], f"{names} written again (take it from {home})"
