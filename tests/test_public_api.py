"""The public API of each package: every name in ``__all__`` resolves to what its module defines,
``dir`` and ``help`` list them, and importing a package stays cheap (nothing heavy is imported
before a name is used)."""
from __future__ import annotations

import importlib
import subprocess
import sys
import types
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
PACKAGES = ("factors", "datasets", "smoother")


@pytest.mark.parametrize("package", PACKAGES)
def test_every_exported_name_resolves_to_its_modules_object(package):
    module = importlib.import_module(package)
    assert module.__all__ and sorted(module.__all__) == module.__all__
    for name in module.__all__:
        value, source = getattr(module, name), module._EXPORTS[name]
        assert source.split(".")[0] == package
        if isinstance(value, types.ModuleType):
            assert value.__name__ == source and source.rsplit(".", 1)[-1] == name
        else:
            assert value is getattr(importlib.import_module(source), name), name
    assert set(module.__all__) <= set(dir(module))
    # A package attribute named like one of its sub-modules becomes that sub-module as soon as
    # anything imports it: only the sub-module itself may be exported under its name.
    submodules = {path.stem for path in (ROOT / package).glob("*.py")}
    assert not [name for name in module.__all__
                if name in submodules and not isinstance(getattr(module, name), types.ModuleType)]
    with pytest.raises(AttributeError, match=f"module '{package}' has no attribute 'no_such_name'"):
        getattr(module, "no_such_name")


def test_the_readme_names_are_exported():
    import datasets
    import factors
    import smoother

    assert {"simulate", "Dataset", "ImuSamples", "load_kitti", "load_euroc", "read_tum"} <= set(datasets.__all__)
    assert {"ImuState", "ImuNoise", "so3", "quaternion", "check_factor", "numerical_jacobian", "ImuFactor",
            "sensor_factor", "odometry_factor", "state_prior_factor"} <= set(factors.__all__)
    assert {"build_problem", "solve_batch", "run_fixed_lag", "run_ekf", "Ekf", "metrics"} <= set(smoother.__all__)


def test_importing_the_packages_imports_nothing_heavy_and_help_lists_the_exports():
    code = ("import sys, pydoc, factors, datasets, smoother\n"
            "heavy = sorted({'gtsam', 'numba', 'numpy', 'matplotlib'} & set(sys.modules))\n"
            "text = pydoc.render_doc(smoother, renderer=pydoc.plaintext)\n"
            "print(heavy, all(name in text for name in smoother.__all__))\n")
    result = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True, cwd=ROOT,
                            env={"PYTHONPATH": str(ROOT), "PATH": "/usr/bin:/bin"})
    assert result.stdout.split("\n")[0] == "[] True"
