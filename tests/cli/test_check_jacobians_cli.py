"""``smoother check-jacobians [--json] [--samples N] [--seed S]``: every analytic Jacobian of
factors.selfcheck against central differences, as a command.

In-process through ``smoother.cli.main`` with capsys; one subprocess run of the installed console
script. The command's own acceptance threshold is atol = rtol = 1e-6; correct Jacobians show
~1e-9, so the tests also assert that the reported errors are below 1e-7 -- a command that printed
``ok`` without computing anything would fail them.
"""
from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from datasets.kinds import KINDS
from factors import selfcheck
from smoother import cli

KEYS = {"name", "max_abs_error", "max_rel_error", "ok"}
#: Checks of the primer's calculus and IMU model that selfcheck registers itself (others may add more).
FOUNDATION = [
    "exp: Gamma (31)", "log: Gamma^-1 (32)", "coordinate map wrt rotation (27)", "coordinate map wrt vector (26)",
    "quaternion coordinate map (35, 27)", "inverse (28)", "composition wrt left (29)", "composition wrt right (30)",
    "boxplus wrt (Phi, phi)", "boxminus wrt (Phi1, Phi2)", "IMU process F (54-60)", "IMU process G (54-60)",
]


def run(capsys, *argv):
    code = cli.main(["check-jacobians", *argv])
    out, err = capsys.readouterr()
    return code, out, err


def test_json_output_is_valid_and_every_check_passes(capsys):
    code, out, err = run(capsys, "--samples", "5", "--json")
    assert code == 0, err
    assert err == ""
    results = json.loads(out)
    assert isinstance(results, list) and len(results) == len(selfcheck.CHECKS)
    assert [r["name"] for r in results] == list(selfcheck.CHECKS)
    for r in results:
        assert set(r) == KEYS, r
        assert isinstance(r["name"], str) and r["ok"] is True
        assert isinstance(r["max_abs_error"], float) and isinstance(r["max_rel_error"], float)
        assert 0.0 <= r["max_rel_error"] <= r["max_abs_error"] < 1e-7, r
    # the foundation's checks are there, and those that difference numerically see a non-zero
    # error (exact zeros would mean nothing was compared)
    by_name = {r["name"]: r for r in results}
    for name in FOUNDATION:
        assert name in by_name, name
        assert by_name[name]["max_abs_error"] > 0, name


def test_text_output_is_a_table_of_every_check(capsys):
    code, out, _ = run(capsys, "--samples", "3", "--seed", "4")
    assert code == 0
    lines = out.splitlines()
    assert lines[0] == "analytic vs numerical Jacobians (3 random points each, seed 4)"
    assert lines[1].split()[:2] == ["check", "max"]
    assert len(lines) == 2 + len(selfcheck.CHECKS)
    for name, line in zip(selfcheck.CHECKS, lines[2:]):
        assert line.startswith(name) and line.endswith("ok"), line


def test_seed_makes_runs_reproducible(capsys):
    first = run(capsys, "--samples", "4", "--seed", "11", "--json")[1]
    again = run(capsys, "--samples", "4", "--seed", "11", "--json")[1]
    other = run(capsys, "--samples", "4", "--seed", "12", "--json")[1]
    assert first == again
    errors = lambda text: [r["max_abs_error"] for r in json.loads(text)]  # noqa: E731
    assert errors(first) != errors(other)


@pytest.mark.parametrize("samples", ["0", "-3"])
def test_non_positive_samples_is_a_user_error(capsys, samples):
    code, out, err = run(capsys, "--samples", samples)
    assert code == 2
    assert out == ""
    assert err.startswith("smoother: error: --samples") and samples in err


def test_a_negative_seed_is_a_user_error(capsys):
    code, out, err = run(capsys, "--seed", "-1", "--samples", "1")
    assert code == 2
    assert out == ""
    assert err.startswith("smoother: error: --seed") and "-1" in err


def test_a_failing_check_makes_the_command_fail(capsys, monkeypatch):
    # Register a deliberately wrong "Jacobian" (twice the truth): the command must report it,
    # name it on stderr and exit 1, while the genuine checks still pass.
    def wrong(rng):
        x = rng.normal(size=3)
        return 2.0 * np.eye(3), np.eye(3) + 0.0 * x

    monkeypatch.setitem(selfcheck.CHECKS, "deliberately wrong", wrong)
    code, out, err = run(capsys, "--samples", "2", "--json")
    assert code == 1
    verdicts = {r["name"]: r["ok"] for r in json.loads(out)}
    assert verdicts.pop("deliberately wrong") is False
    assert all(verdicts.values())
    assert err.strip() == "FAILED: deliberately wrong"
    row = [r for r in json.loads(out) if r["name"] == "deliberately wrong"][0]
    assert row["max_abs_error"] == 1.0 and row["max_rel_error"] == 1.0


def _console_script() -> str | None:
    """The installed ``smoother`` script: next to this interpreter (a virtual environment's bin/),
    else on PATH."""
    here = Path(sys.executable).with_name("smoother")
    return str(here) if here.exists() else shutil.which("smoother")


@pytest.mark.skipif(_console_script() is None, reason="the smoother console script is not installed")
def test_console_script_json(tmp_path):
    env = dict(os.environ, PYTHONHASHSEED="0")
    done = subprocess.run(
        [_console_script(), "check-jacobians", "--samples", "5", "--json"],
        capture_output=True, text=True, timeout=120, cwd=tmp_path, env=env,
    )
    assert done.returncode == 0, done.stderr
    results = json.loads(done.stdout)
    assert {r["name"] for r in results} == set(selfcheck.CHECKS)
    assert all(set(r) == KEYS and r["ok"] is True and r["max_abs_error"] < 1e-7 for r in results)


def test_the_relative_pose_check_holds_at_many_points_including_residuals_near_pi():
    """The odometry check draws its poses so that the residual rotation, of any size, stays
    PI_MARGIN_FOR_LOG from pi (where log, and so the central differences, jump)."""
    import datasets.kinds  # noqa: F401  (registers the kinds' checks)

    (result,) = selfcheck.run_checks(samples=400, seed=0,
                                     names=["odometry measurement: H of its residual, extrinsic T_BS"])
    assert result.ok, result


def test_check_jacobians_in_a_fresh_process_checks_every_kind():
    done = subprocess.run([sys.executable, "-m", "smoother.cli", "check-jacobians", "--samples", "20", "--json"],
                          capture_output=True, text=True)
    assert done.returncode == 0, done.stderr[-2000:]
    results = {r["name"]: r for r in json.loads(done.stdout)}
    for name, kind in KINDS.items():  # its model, through its calibration; a one-state kind attached too, both ways
        checks = [r for n, r in results.items() if n.startswith(f"{name} measurement")]
        assert len(checks) == (2 if kind.relative else 4) and all(c["ok"] for c in checks), (name, sorted(results))
