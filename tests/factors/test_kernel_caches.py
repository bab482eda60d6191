"""factors.kernel_caches: an edit drops the cached kernels of the edited module and of the modules
that import it, and the check runs when called (once per process), never on import."""
from __future__ import annotations

import os
import shutil
import subprocess
import sys
from pathlib import Path

from factors import kernel_caches
from factors.kernel_caches import clear_stale_kernel_caches

ROOT = Path(__file__).resolve().parents[2]


def test_an_edit_drops_the_cached_kernels_of_the_edited_module_and_its_dependants_only(tmp_path):
    """Numba re-validates a cached kernel only against its own file, but a kernel inlines the
    kernels it calls from other modules: an edit drops the caches of the edited module and of
    every module that imports it, directly, through others, inside a function or relatively."""
    sources = {
        "a/__init__.py": "",
        "a/leaf.py": "x = 1\n",
        "a/leafy.py": "x = 1\n",  # its cache files start with 'leaf' too
        "a/mid.py": "def f():\n    from a import leaf\n    return leaf.x\n",
        "b/top.py": "from a.mid import f\n",
        "b/other.py": "x = 1\n",
        "b/rel.py": "from . import other\n",
    }
    for name, text in sources.items():
        (tmp_path / name).parent.joinpath("__pycache__").mkdir(parents=True, exist_ok=True)
        (tmp_path / name).write_text(text)
    stamp = tmp_path / "a" / "__pycache__" / "stamp.json"

    def cache_all():
        for name in sources:
            path = tmp_path / name
            for suffix in ("k-10.py311.nbi", "k-10.py311.1.nbc"):
                path.parent.joinpath("__pycache__", f"{path.stem}.{suffix}").write_text("")

    def cached():
        return sorted({f"{p.parent.parent.name}.{p.name.split('.')[0]}" for p in tmp_path.glob("*/__pycache__/*.nb?")})

    def clear():
        return clear_stale_kernel_caches(tmp_path, ("a", "b"), stamp)

    everything = ["a.__init__", "a.leaf", "a.leafy", "a.mid", "b.other", "b.rel", "b.top"]
    cache_all()
    assert sorted(clear()) == ["a", "a.leaf", "a.leafy", "a.mid", "b.other", "b.rel", "b.top"]  # no stamp yet
    assert cached() == []
    cache_all()
    assert clear() == [] and cached() == everything  # unchanged sources: kept
    (tmp_path / "a/leaf.py").write_text("x = 2\n")
    assert sorted(clear()) == ["a.leaf", "a.mid", "b.top"]
    assert cached() == ["a.__init__", "a.leafy", "b.other", "b.rel"]
    cache_all()
    (tmp_path / "b/other.py").write_text("x = 2\n")
    assert sorted(clear()) == ["b.other", "b.rel"]
    assert cached() == ["a.__init__", "a.leaf", "a.leafy", "a.mid", "b.top"]
    (tmp_path / "b/new.py").write_text("from a import leafy\n")  # a new module: its own caches only
    assert clear() == ["b.new"]
    (tmp_path / "a" / "__pycache__" / "other.pyc").write_text("")
    (tmp_path / "a/leafy.py").write_text("x = 3\n")
    assert sorted(clear()) == ["a.leafy", "b.new"]
    assert (tmp_path / "a" / "__pycache__" / "other.pyc").exists()  # only Numba's files go


def test_the_import_graph_reads_imports_inside_functions_and_relative_ones(tmp_path):
    from factors.imports import cycles, module_imports

    for name, text in {"p/__init__.py": "from .q import x\n", "p/q.py": "import os\nx = 1\n",
                       "p/r.py": "def f():\n    import p.s\n", "p/s.py": "from p import r, q\n"}.items():
        (tmp_path / name).parent.mkdir(exist_ok=True)
        (tmp_path / name).write_text(text)
    graph = module_imports(tmp_path, ("p",))
    assert graph == {"p": {"p.q"}, "p.q": set(), "p.r": {"p.s"}, "p.s": {"p.q", "p.r"}}
    assert cycles(graph) == [["p.r", "p.s"]]


def test_importing_the_packages_checks_no_cache_and_the_check_runs_once_per_process(tmp_path):
    """A fresh process that imports the compiled kernels and runs one writes no fingerprints; the
    first call of ensure_fresh_caches does, the second does nothing. The check runs on a copy of
    the packages' sources with a stamp of its own: without a stamp every module is stale, and on
    the checkout itself that would drop every compiled kernel the other tests (and the next run)
    load."""
    for package in kernel_caches.PACKAGES:
        shutil.copytree(ROOT / package, tmp_path / "copy" / package, ignore=shutil.ignore_patterns("__pycache__"))
    script = (
        "import sys\n"
        "from pathlib import Path\n"
        "from factors import kernel_caches, so3\n"
        "kernel_caches.ROOT, kernel_caches.STAMP = Path(sys.argv[1]), Path(sys.argv[2])\n"
        "so3.exp([[0.1, 0.2, 0.3]])\n"
        "assert not kernel_caches.STAMP.exists(), 'an import or a kernel checked the caches'\n"
        "first = kernel_caches.ensure_fresh_caches()\n"
        "assert kernel_caches.STAMP.exists() and 'factors.so3' in first, first\n"
        "assert kernel_caches.ensure_fresh_caches() == []\n"
    )
    env = {k: v for k, v in os.environ.items() if k != "NUMBA_CACHE_DIR"}
    cached = sorted(ROOT.glob("*/**/__pycache__/*.nb[ic]"))
    done = subprocess.run([sys.executable, "-c", script, str(tmp_path / "copy"), str(tmp_path / "stamp.json")],
                          cwd=ROOT, env=env, capture_output=True, text=True, timeout=300)
    assert done.returncode == 0, done.stderr
    assert all(path.exists() for path in cached), "the checkout's compiled kernels were dropped"


def test_a_cache_folder_of_the_user_s_own_is_left_alone(monkeypatch, tmp_path):
    monkeypatch.setenv("NUMBA_CACHE_DIR", str(tmp_path))
    monkeypatch.setattr(kernel_caches, "_checked", False)
    monkeypatch.setattr(kernel_caches, "STAMP", tmp_path / "stamp.json")
    assert kernel_caches.ensure_fresh_caches() == []
    assert not (tmp_path / "stamp.json").exists()
