"""``smoother plot DIR``: the figures of a run directory that ``smoother run`` wrote, into ``--out``
when given; a missing directory and a bad ``--out`` are one line each. What each figure draws:
``tests/smoother/outputs/test_plots.py``."""
from __future__ import annotations

import shutil
from pathlib import Path

import pytest

from smoother.cli import main


@pytest.fixture(scope="module")
def run_dir(tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("run") / "run"
    assert main(["run", "--duration", "2", "--estimator", "ekf", "--out", str(out), "--no-progress"]) == 0
    return out


def test_plot_writes_the_figures_it_can_into_out(run_dir, tmp_path, capsys):
    # without truth.npz only two figures are possible, which keeps this test quick
    directory = tmp_path / "copy"
    shutil.copytree(run_dir, directory)
    (directory / "truth.npz").unlink()
    out = tmp_path / "figures"
    assert main(["plot", str(directory), "--estimators", "ekf", "--out", str(out)]) == 0
    assert sorted(p.name for p in out.glob("*.png")) == ["biases.png", "trajectory.png"]
    assert not list(directory.glob("*.png"))
    assert f"wrote {out / 'biases.png'}" in capsys.readouterr().err

    assert main(["plot", str(tmp_path / "empty-or-missing")]) == 2
    err = capsys.readouterr().err
    assert err.startswith("smoother: error: ") and "empty-or-missing" in err and len(err.splitlines()) == 1


def test_plot_with_a_bad_out_is_one_line(run_dir, tmp_path, capsys):
    """--out under a file: exit 2, one line naming --out and the path, no figure drawn."""
    blocker = tmp_path / "file"
    blocker.write_text("")
    out = blocker / "figures"
    assert main(["plot", str(run_dir), "--out", str(out)]) == 2
    err = capsys.readouterr().err
    assert err.startswith(f"smoother: error: --out {out}: ") and len(err.splitlines()) == 1
    assert not list(run_dir.glob("*.png"))
