"""Hostile output paths and interrupted post-run work: every path a command writes or deletes lies
inside the directory the user named (``smoother.confined.inside``) -- a fleet's rig named
``...toml`` (stem ``..``) once wrote into the parent of ``--out``, overwrote the user's
``metrics.json`` there and deleted their ``batch.tum`` --, an empty ``--out`` is refused, and what
follows the estimators (verdicts, the advice fit) can be stopped or fail without costing the
finished estimates. ``smoother plot`` names the ``.npz`` it cannot use."""
from __future__ import annotations

import contextlib
import io
import json
import os
import zipfile
from pathlib import Path

import numpy as np
import pytest
from isolation import isolated

from datasets.errors import LIMITS, SizeLimit
from factors.errors import InputError
from smoother.cli import main
from smoother.confined import folder_name_problem, inside
from smoother.errors import Terminated

#: The user's own files beside (or above) an output directory, which no command may touch.
THEIRS = {"metrics.json": b'{"mine": true}\n', "batch.tum": b"0 0 0 0 0 0 0 1\n", "trajectory.png": b"mine"}
RUN = ["--duration", "2", "--estimator", "ekf", "--no-progress"]


def _theirs(folder: Path) -> Path:
    folder.mkdir(parents=True, exist_ok=True)
    for name, content in THEIRS.items():
        (folder / name).write_bytes(content)
    return folder


def _untouched(folder: Path) -> None:
    for name, content in THEIRS.items():
        assert (folder / name).read_bytes() == content, name


def _one_line(capsys) -> str:
    err = [line for line in capsys.readouterr().err.splitlines() if line.startswith("smoother:")]
    assert len(err) == 1, err
    return err[0]


def test_inside_takes_names_in_the_directory_and_refuses_those_that_lead_out(tmp_path):
    root = tmp_path / "out"
    assert inside(root, "metrics.json") == root / "metrics.json"  # the directory need not exist yet
    root.mkdir()
    (root / "sub").mkdir()
    (root / "in.json").symlink_to(root / "sub" / "x.json")
    assert inside(root, "in.json") == root / "in.json"  # a link that stays inside
    (root / "out.json").symlink_to(tmp_path / "metrics.json")
    for name in ("..", "../metrics.json", "sub/../../metrics.json", "out.json", str(tmp_path / "x")):
        with pytest.raises(InputError, match="outside"):
            inside(root, name)
    assert inside(root, "out.json", follow=False) == root / "out.json"  # deleting a link removes the link
    with pytest.raises(InputError, match="empty"):
        inside("", "metrics.json")


@pytest.mark.parametrize("name", ["", ".", "..", ".hidden", "a/b", "a\0b"])
def test_a_name_that_cannot_be_a_folder_of_its_own_is_said_to_be(name):
    assert folder_name_problem(name) is not None
    assert folder_name_problem("husky") is None and folder_name_problem("site.2") is None


@pytest.mark.parametrize("rig, why", [("...toml", "its parent"), ("..toml", "the directory itself"),
                                      (".toml", "hidden"), ("summary.json.toml", "summary.json")])
def test_a_fleet_rig_whose_stem_is_no_folder_is_refused_before_anything_is_written(tmp_path, capsys, monkeypatch,
                                                                                    rig, why):
    """The fleet refuses the rig file by name (its stem would be ``..``, ``.``, hidden, or the
    fleet's own summary) before the output directory is made or anything read: the user's files
    in the parent are as they were."""
    parent = _theirs(tmp_path / "parent")
    (parent / "rigs").mkdir()
    (parent / "rigs" / rig).write_text("[imu]\n")
    monkeypatch.chdir(parent / "rigs")
    assert main(["fleet", rig, "--out", str(parent / "fleet"), "--no-progress"]) == 2
    line = _one_line(capsys)
    assert rig in line and why in line and "rename the rig file" in line, line
    assert not (parent / "fleet").exists()
    _untouched(parent)


def test_a_fleet_recording_folder_that_is_a_link_out_of_out_is_refused(tmp_path, capsys):
    elsewhere = _theirs(tmp_path / "elsewhere")
    out = tmp_path / "fleet"
    out.mkdir()
    (out / "husky").symlink_to(elsewhere, target_is_directory=True)
    rig = tmp_path / "husky.toml"
    rig.write_text("[imu]\n")
    assert main(["fleet", str(rig), "--out", str(out), "--no-progress"]) == 2
    assert "is a symbolic link to" in _one_line(capsys)
    _untouched(elsewhere)


@pytest.mark.parametrize("argv", [["run", *RUN], ["fleet", "x.toml"], ["plot", "somewhere"],
                                  ["montecarlo", "--runs", "2"], ["allan", "csv:imu.csv"]])
def test_an_empty_out_is_refused_not_taken_for_the_current_directory(tmp_path, capsys, monkeypatch, argv):
    monkeypatch.chdir(tmp_path)
    (tmp_path / "x.toml").write_text("[imu]\n")
    before = sorted(p.name for p in tmp_path.iterdir())
    assert main([*argv, "--out", ""]) == 2
    assert "--out: expected a directory, got an empty name" in _one_line(capsys)
    assert sorted(p.name for p in tmp_path.iterdir()) == before


@pytest.mark.parametrize("name", ["metrics.json", "ekf.tum", ".smoother.lock"])
def test_a_run_file_that_is_a_link_out_of_out_is_refused_before_any_work(tmp_path, capsys, name):
    """A run file (or the lock, which a run truncates) linked to the user's file elsewhere: the
    run is refused naming it, before any estimator runs, and the file keeps its content."""
    elsewhere = _theirs(tmp_path / "elsewhere")
    out = tmp_path / "out"
    out.mkdir()
    (out / name).symlink_to(elsewhere / "metrics.json")
    assert main(["run", *RUN, "--out", str(out)]) == 2
    line = _one_line(capsys)
    assert name in line and "outside" in line, line
    assert "running ekf" not in capsys.readouterr().err
    _untouched(elsewhere)


def test_a_figure_that_is_a_link_out_of_out_is_refused(tmp_path, capsys):
    run = tmp_path / "run"
    assert main(["run", *RUN, "--out", str(run)]) == 0
    elsewhere = _theirs(tmp_path / "elsewhere")
    out = tmp_path / "figures"
    out.mkdir()
    (out / "trajectory.png").symlink_to(elsewhere / "trajectory.png")
    capsys.readouterr()
    assert main(["plot", str(run), "--out", str(out)]) == 2
    assert "trajectory.png is a symbolic link to" in _one_line(capsys)
    _untouched(elsewhere)


def test_montecarlo_runs_folder_that_is_a_link_out_is_neither_emptied_nor_written(tmp_path):
    from smoother.evaluation import montecarlo

    elsewhere = tmp_path / "elsewhere"
    elsewhere.mkdir()
    (elsewhere / "seed_1.json").write_text("mine")
    out = tmp_path / "mc"
    out.mkdir()
    (out / montecarlo.RUNS).symlink_to(elsewhere, target_is_directory=True)
    config = montecarlo.MonteCarloConfig(profile="gentle", duration=1.0, estimators=("ekf",))
    with pytest.raises(InputError, match="outside"):
        montecarlo.run_many(config, [1], out_dir=out)
    assert (elsewhere / "seed_1.json").read_text() == "mine"


@pytest.mark.parametrize("stage, error, code", [
    ("smoother.pipeline.verdicts_by_estimator", Terminated(), 143),
    ("smoother.pipeline.verdicts_by_estimator", KeyboardInterrupt(), 130),
    ("smoother.pipeline.judged", MemoryError("no room for the verdicts"), 2),
    ("smoother.diagnosis.misfit_causes.hints", Terminated(), 143),
    ("smoother.diagnosis.misfit_causes.hints", RuntimeError("GTSAM failed"), 0),
])
def test_the_work_after_the_estimators_never_costs_their_outputs(tmp_path, capsys, monkeypatch, stage, error, code):
    """SIGTERM, Ctrl-C or a failure (out of memory, GTSAM) in the verdicts or in the advice fit:
    the finished EKF is written -- stopped, ``metrics.json`` says so; failed, it says why and the
    exit code is 2; the advice fit runs after the outputs are written, and its failure is a
    warning."""
    module, _, name = stage.rpartition(".")

    def fails(*args, **kwargs):
        raise error

    monkeypatch.setattr(f"{module}.{name}", fails)
    out = tmp_path / "run"
    assert main(["run", *RUN, "--out", str(out)]) == code
    err = capsys.readouterr().err
    run = json.loads((out / "metrics.json").read_text())["_run"]
    assert (out / "ekf.tum").exists() and (out / "ekf.npz").exists()
    if isinstance(error, KeyboardInterrupt) and name != "hints":
        assert run["stopped"] == ("terminated" if code == 143 else "interrupted")
    if isinstance(error, MemoryError):
        assert "no room for the verdicts" in run["analysis_failed"] and "written without their verdicts" in err
    if name == "hints" and not isinstance(error, KeyboardInterrupt):
        assert "GTSAM failed" in err and "no advice" in err


def test_plot_names_the_npz_whose_arrays_do_not_make_a_trajectory(tmp_path, capsys):
    run = tmp_path / "run"
    run.mkdir()
    n = 10
    arrays = dict(t=np.arange(n, dtype=float), r=np.zeros((n, 3)), v=np.zeros((n, 3)), C=np.tile(np.eye(3), (n, 1, 1)),
                  b_f=np.zeros((n, 3)), b_w=np.zeros((n, 3)))
    np.savez(run / "ekf.npz", **arrays, cov=np.zeros((n - 1, 15, 15)))
    assert main(["plot", str(run)]) == 2
    line = _one_line(capsys)
    assert f"{run / 'ekf.npz'}: Trajectory.cov" in line, line
    np.savez(run / "ekf.npz", **{**arrays, "r": np.zeros((n - 2, 3))})
    assert main(["plot", str(run)]) == 2
    assert f"{run / 'ekf.npz'}: Trajectory.states.r" in _one_line(capsys)


def _run_files(folder: Path) -> dict:
    """A run directory's ekf.npz and metrics.json, as smoother run writes them."""
    folder.mkdir()
    n = 10
    arrays = dict(t=np.arange(n, dtype=float), r=np.zeros((n, 3)), v=np.zeros((n, 3)), C=np.tile(np.eye(3), (n, 1, 1)),
                  b_f=np.zeros((n, 3)), b_w=np.zeros((n, 3)), cov=np.tile(np.eye(15), (n, 1, 1)))
    np.savez(folder / "ekf.npz", **arrays)
    (folder / "metrics.json").write_text(json.dumps({"ekf": {}, "_run": {"estimators": ["ekf"]}}))
    return arrays


def _unpacking_to(path: Path, arrays: dict, shape: tuple, written: int) -> None:
    """``arrays`` as an .npz whose ``cov`` says ``shape`` and holds ``written`` bytes of zeros:
    compressed, gigabytes of them take megabytes."""
    with zipfile.ZipFile(path, "w", compression=zipfile.ZIP_DEFLATED) as archive:
        for name, value in arrays.items():
            with archive.open(f"{name}.npy", "w", force_zip64=True) as member:
                if name != "cov":
                    np.lib.format.write_array(member, value)
                    continue
                np.lib.format.write_array_header_1_0(member, {"descr": "<f8", "fortran_order": False, "shape": shape})
                block = bytes(1 << 24)
                for _ in range(written // len(block)):
                    member.write(block)


@pytest.mark.parametrize("command", ["plot", "evaluate"])
@pytest.mark.parametrize("which, make, fragment", [
    ("ekf.npz", "pipe", "found a named pipe (FIFO)"),
    ("metrics.json", "pipe", "found a named pipe (FIFO)"),
    ("metrics.json", "device", "found a character device"),
    ("ekf.npz", "bomb", "bytes unpacked; expected at most 1048576 bytes"),
    ("ekf.npz", "header", "field 'cov': found an array of shape (100000000, 15, 15)"),
])
def test_a_run_directorys_file_that_is_no_file_or_unpacks_past_its_limit_is_refused_naming_it(
        tmp_path, monkeypatch, command, which, make, fragment):
    """A pipe blocked ``smoother plot`` and ``evaluate`` for ever (np.load and read_text opened it);
    /dev/zero ran them out of memory, unnamed; an archive of a few megabytes unpacked to
    gigabytes (here past a limit of 1 MiB), and an array header of a shape its data do not have
    allocated that shape first."""
    if command == "evaluate" and which == "metrics.json":
        pytest.skip("smoother evaluate reads no metrics.json")
    run = tmp_path / "run"
    arrays = _run_files(run)
    path = run / which
    path.unlink()
    if make == "pipe":
        os.mkfifo(path)
    elif make == "device":
        path.symlink_to("/dev/zero")
    elif make == "bomb":
        monkeypatch.setitem(LIMITS, "npz", SizeLimit(LIMITS["npz"].files, 1 << 20, LIMITS["npz"].why))
        _unpacking_to(path, arrays, (4660, 15, 15), 1 << 24)
    else:
        _unpacking_to(path, arrays, (100_000_000, 15, 15), 0)
    argv = ["plot", str(run)] if command == "plot" else ["evaluate", "--reference", str(run / "ekf.npz"),
                                                         "--estimate", str(run / "ekf.npz"), "--align", "none"]

    def call():
        err = io.StringIO()
        with contextlib.redirect_stderr(err):
            code = main(argv)
        raise SystemExit(f"{code}\n{err.getvalue()}")

    outcome = isolated(call, seconds=30)
    code, text = outcome.message.split("\n", 1)
    lines = [line for line in text.splitlines() if line.startswith("smoother:")]
    named = f"smoother: error: {'--reference: ' if command == 'evaluate' else ''}{path}"
    assert code == "2" and len(lines) == 1 and lines[0].startswith(named) and fragment in lines[0], outcome


def _main_isolated(argv: list[str]) -> tuple[str, list[str]]:
    """``main(argv)`` in a bounded child process: its exit code and the lines it wrote that say
    ``smoother:`` or ``failed:`` (the child is killed, and the test fails, when it blocks)."""

    def call():
        said = io.StringIO()
        with contextlib.redirect_stderr(said), contextlib.redirect_stdout(said):
            code = main(argv)
        raise SystemExit(f"{code}\n{said.getvalue()}")

    outcome = isolated(call, seconds=30)
    assert "SystemExit" in outcome.raised, outcome
    code, text = outcome.message.split("\n", 1)
    return code, [line.strip() for line in text.splitlines() if "smoother:" in line or "failed:" in line]


@pytest.mark.parametrize("command", ["run", "fleet"])
def test_a_pipe_where_a_command_opens_a_file_to_write_is_refused_naming_it(tmp_path, command):
    """A named pipe at a fleet recording's run.log blocked ``smoother fleet`` for ever (opened for
    writing, it waits for a reader); one at a run directory's lock file failed with "[Errno 22]
    Invalid argument", naming nothing."""
    out = tmp_path / "out"
    if command == "run":
        out.mkdir()
        pipe = out / ".smoother.lock"
        argv = ["run", *RUN, "--out", str(out)]
    else:
        (tmp_path / "husky.toml").write_text("[imu]\n")
        (out / "husky").mkdir(parents=True)
        pipe = out / "husky" / "run.log"
        argv = ["fleet", str(tmp_path / "husky.toml"), "--out", str(out), "--no-progress"]
    os.mkfifo(pipe)
    code, lines = _main_isolated(argv)
    assert code == "2" and any(f"{pipe} is a named pipe (FIFO), not a regular file" in line for line in lines), lines


def test_a_fleet_summary_that_is_a_link_out_of_out_is_refused_before_any_recording_runs(tmp_path, capsys):
    """It was refused after every recording had run (their work written, the summary not)."""
    elsewhere = _theirs(tmp_path / "elsewhere")
    out = tmp_path / "fleet"
    out.mkdir()
    (out / "summary.json").symlink_to(elsewhere / "metrics.json")
    rig = tmp_path / "husky.toml"
    rig.write_text("[imu]\n")
    assert main(["fleet", str(rig), "--out", str(out), "--no-progress"]) == 2
    assert "summary.json is a symbolic link to" in _one_line(capsys)
    assert not (out / "husky").exists()
    _untouched(elsewhere)
