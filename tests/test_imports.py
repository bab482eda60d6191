"""The import structure of the three packages, read from the sources with ``ast`` (every import
statement, also those inside functions): no module imports itself through others, and the
dependencies point one way, ``smoother -> factors, datasets``, ``datasets -> factors``, ``factors``
to neither (docs/design.md, "Layout")."""
from __future__ import annotations

from pathlib import Path

from factors.imports import cycles, module_imports

ROOT = Path(__file__).resolve().parents[1]
PACKAGES = ("factors", "datasets", "smoother")

#: The packages each package may import from (besides itself).
ALLOWED = {"factors": set(), "datasets": {"factors"}, "smoother": {"factors", "datasets"}}


def test_no_module_imports_itself_through_others():
    assert cycles(module_imports(ROOT, PACKAGES)) == []


def test_the_packages_depend_on_each_other_one_way():
    wrong = [f"{name} imports {other}" for name, imported in sorted(module_imports(ROOT, PACKAGES).items())
             for other in sorted(imported)
             if other.split(".")[0] != name.split(".")[0] and other.split(".")[0] not in ALLOWED[name.split(".")[0]]]
    assert wrong == []


def test_the_packages_import_from_modules_not_from_the_public_exports():
    """A package's ``__init__`` exports its API lazily, with no import statements; code that took
    a name from there would hide which module it depends on (from the compiled kernels' caches of
    ``factors.kernel_caches`` too)."""
    wrong = [f"{name} imports {other}" for name, imported in sorted(module_imports(ROOT, PACKAGES).items())
             for other in sorted(imported) if other in PACKAGES]
    assert wrong == []


#: The layers inside ``factors``, lowest first: a module imports from its own layer or below.
FACTOR_LAYERS = (
    ("support", {"compiled", "kernel_caches", "rows", "threads", "scan", "imports", "exports", "errors",
                 "small_linalg"}),
    ("rotation calculus", {"quaternion", "so3", "axis_angle", "euler", "derivatives", "uncertainty", "chart"}),
    ("IMU model", {"imu", "preintegration"}),
    ("GTSAM factors", {"custom", "keys", "priors", "sensor_models", "imu_factor", "jacobians", "selfcheck", "calibration"}),
)


def test_factors_is_layered_rotation_calculus_then_imu_model_then_gtsam_factors():
    layer_of = {f"factors.{module}": rank for rank, (_, modules) in enumerate(FACTOR_LAYERS) for module in modules}
    imports = module_imports(ROOT, ("factors",))
    assert set(imports) - {"factors"} == set(layer_of), "every module of factors/ belongs to one layer"
    upward = [f"{name} ({FACTOR_LAYERS[layer_of[name]][0]}) imports {other} ({FACTOR_LAYERS[layer_of[other]][0]})"
              for name, imported in sorted(imports.items()) if name in layer_of
              for other in sorted(imported) if other in layer_of and layer_of[other] > layer_of[name]]
    assert upward == []
