"""``smoother montecarlo``: the summary and its figure written, bad options and a bad ``--out``
refused in one line before any run. The runs themselves: ``tests/smoother/evaluation/test_montecarlo.py``."""
import json

import pytest

from smoother.cli import main
from smoother.evaluation import montecarlo


def test_cli_writes_summary_and_plot(tmp_path, capsys):
    assert main(["montecarlo", "--runs", "2", "--duration", "2", "--out", str(tmp_path), "--json"]) == 0
    out = json.loads(capsys.readouterr().out)
    assert out["runs"] == 2 and set(out) >= {"batch", "ekf", "nees_interval_95"}
    assert (tmp_path / "summary.json").exists()
    assert (tmp_path / "montecarlo_nees.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


@pytest.mark.parametrize("argv, fragment", [
    (["--runs", "1"], "--runs"),
    (["--workers", "0"], "--workers"),
    (["--profile", "loopy"], "--profile"),
    (["--duration", "-1"], "--duration"),
    (["--duration", "inf"], "--duration"),
    (["--outliers", "2"], "--outliers"),
    (["--first-seed", "-1"], "--first-seed"),
])
def test_cli_rejects_bad_options(tmp_path, capsys, argv, fragment):
    assert main(["montecarlo", "--out", str(tmp_path), *argv]) == 2
    err = capsys.readouterr().err
    assert fragment in err and "Traceback" not in err


def test_cli_rejects_a_bad_out_before_any_run(tmp_path, capsys, monkeypatch):
    """--out under a file: exit 2, one line naming --out and the path, before the first run."""
    monkeypatch.setattr(montecarlo, "run_one", lambda *a: pytest.fail("a run started"))
    blocker = tmp_path / "file"
    blocker.write_text("")
    out = blocker / "mc"
    assert main(["montecarlo", "--runs", "2", "--duration", "1", "--out", str(out)]) == 2
    err = capsys.readouterr().err
    assert err.startswith(f"smoother: error: --out {out}: ") and len(err.splitlines()) == 1
