"""``smoother run --out DIR``: a run directory holds one run. A re-run replaces the previous run's
files (and only the tool's), a failure while writing (a full disk) leaves the previous run whole,
a second run into a directory in use is refused at once, SIGTERM keeps the finished estimators as
Ctrl-C does, and neither SIGTERM nor SIGKILL leaves the fixed-lag smoother's second process
running. Those run ``smoother run`` as a child process."""
from __future__ import annotations

import errno
import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from datasets.atomic import STAGING_PREFIX
from smoother.cli import main
from smoother.commands.run_directory import LOCK, RunDirectory, run_files
from smoother.outputs import files

ROOT = Path(__file__).resolve().parents[2]
ESTIMATORS = ("batch", "fixed-lag", "ekf")
#: A run long enough that the fixed-lag smoother is still running when the child is signalled.
CHILD_RUN = ["--duration", "300", "--estimator", "all", "--no-covariance", "--no-progress"]


def _files(folder: Path) -> dict:
    """Every file below ``folder`` (hidden ones and those in subfolders too) and its bytes; the
    lock file is left out."""
    return {str(p.relative_to(folder)): p.read_bytes() for p in sorted(folder.rglob("*"))
            if p.is_file() and p.name != LOCK}


def test_a_rerun_replaces_the_previous_runs_files_and_nothing_else(tmp_path, capsys):
    """All three estimators with plots, then the EKF alone into the same directory: the first
    run's batch and fixed-lag files and its figures go (named on stderr); the user's own files,
    also those named like the tool's in a subfolder, stay."""
    out = tmp_path / "run"
    assert main(["run", "--duration", "2", "--estimator", "all", "--out", str(out), "--no-progress", "--plot"]) == 0
    assert {"batch.tum", "fixed-lag.npz", "trajectory.png"} <= {p.name for p in out.iterdir()}
    (out / "notes.txt").write_text("mine")
    (out / "batch.tum.orig").write_text("mine")
    (out / "old").mkdir()
    (out / "old" / "batch.tum").write_text("mine")
    capsys.readouterr()

    assert main(["run", "--duration", "2", "--estimator", "ekf", "--out", str(out), "--no-progress"]) == 0
    err = capsys.readouterr().err
    names = {p.name for p in out.iterdir()}
    assert names == {"ekf.tum", "ekf.npz", "truth.npz", "metrics.json", "notes.txt", "batch.tum.orig", "old", LOCK}
    assert (out / "old" / "batch.tum").read_text() == "mine"
    removed = next(line for line in err.splitlines() if line.startswith("removed the previous run's"))
    assert "batch.tum" in removed and "fixed-lag.npz" in removed and "trajectory.png" in removed, removed
    assert str(out) in removed and "notes.txt" not in removed
    assert json.loads((out / "metrics.json").read_text())["_run"]["estimators"] == ["ekf"]


def test_a_reference_of_an_earlier_run_is_not_kept(tmp_path):
    """truth.npz belongs to the dataset of the last run: a run without truth into a directory that
    held one removes it (plots would otherwise draw another dataset's truth)."""
    from dataclasses import replace

    from datasets.simulate import simulate
    from smoother.pipeline import Estimate

    data = simulate(profile="tumbling", duration=0.5, seed=0, imu_rate=100.0, pose_rate=None)
    estimates = {"ekf": Estimate("ekf", data.truth, 0.1, {})}
    with RunDirectory(tmp_path / "run") as out:
        with out.outputs() as stage:
            files.write_outputs(stage, data, estimates)
        assert (tmp_path / "run" / "truth.npz").exists()
        with out.outputs() as stage:
            files.write_outputs(stage, replace(data, truth=None), estimates)
    assert not (tmp_path / "run" / "truth.npz").exists() and out.removed == ["truth.npz"]


def test_a_full_disk_midway_leaves_the_previous_run_whole(tmp_path, capsys, monkeypatch):
    """The disk fills while the second estimate's .npz is written (after other files of the run
    were): one line naming that file of the run directory and the reason; the previous run's
    files are all there, unchanged, and nothing of the failed run is left (no staging folder)."""
    out = tmp_path / "run"
    assert main(["run", "--duration", "2", "--estimator", "all", "--out", str(out), "--no-progress",
                 "--no-covariance"]) == 0
    before = _files(out)
    capsys.readouterr()

    real_savez, calls = np.savez, []

    def filling(handle, **arrays):
        calls.append(handle)
        if len(calls) == 2:
            handle.write(b"PK\x03\x04 half an archive")
            raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))
        return real_savez(handle, **arrays)

    monkeypatch.setattr(np, "savez", filling)
    assert main(["run", "--duration", "2", "--estimator", "all", "--out", str(out), "--no-progress",
                 "--no-covariance", "--seed", "5"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert err[-1] == f"smoother: error: {out / 'fixed-lag.npz'}: No space left on device", err
    assert _files(out) == before
    assert not [p for p in out.iterdir() if p.name.startswith(STAGING_PREFIX) or p.name.endswith(".tmp")]


def test_staging_left_by_a_killed_run_is_cleared_of_the_tools_files_only(tmp_path):
    """A run killed with SIGKILL leaves its staging folder: the next run deletes the run files
    in it, and the folder only when that empties it."""
    out = tmp_path / "run"
    stale, kept = out / f"{STAGING_PREFIX}123-abcd", out / f"{STAGING_PREFIX}456-ef01"
    for folder in (stale, kept):
        folder.mkdir(parents=True)
        (folder / "batch.tum").write_text("half")
        (folder / ".metrics.json.0a1b2c3d.tmp").write_text("{")
    (kept / "mine.txt").write_text("mine")
    with RunDirectory(out):
        pass
    assert not stale.exists() and [p.name for p in kept.iterdir()] == ["mine.txt"]


def test_every_output_of_a_run_is_declared():
    """The one list of run files covers what report and plots write (the estimators' files, the
    references, the metrics and the run figures)."""
    from smoother.outputs.plots import FIGSIZE

    names = run_files()
    assert {f"{e}.{ext}" for e in ESTIMATORS for ext in ("tum", "npz", "geojson")} <= names
    assert {"truth.npz", "gps.npz", "metrics.json"} <= names
    assert {f"{stem}.png" for stem in FIGSIZE} <= names


def _child(out: Path, threads: int | None = None, session: bool = False) -> subprocess.Popen:
    """``smoother run`` on the simulator into ``out`` as a child process, stderr piped; with
    ``threads`` (``BOXPLUS_THREADS``) 1 the estimators run one after the other, the fixed-lag
    smoother last, with two or more it runs in a second process beside the others; ``session``:
    in a session of its own (a terminal's Ctrl-C, sent to its process group, then reaches it alone)."""
    env = dict(os.environ, PYTHONPATH=os.pathsep.join([str(ROOT)] + [p for p in [os.environ.get("PYTHONPATH")] if p]))
    if threads is not None:
        env["BOXPLUS_THREADS"] = str(threads)
    return subprocess.Popen([sys.executable, "-m", "smoother.cli", "run", *CHILD_RUN, "--out", str(out)],
                            stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True, env=env,
                            start_new_session=session)


def _wait_for(child: subprocess.Popen, words: str) -> list[str]:
    """The child's stderr lines up to the first that starts with ``words``."""
    lines = []
    for line in child.stderr:
        lines.append(line.rstrip("\n"))
        if line.startswith(words):
            return lines
    child.wait()
    pytest.fail(f"the child ended (exit {child.returncode}) before {words!r}: {lines}")


def test_sigterm_keeps_the_finished_estimators(tmp_path):
    """SIGTERM while the fixed-lag smoother runs (the EKF and the batch smoother finished, one after
    the other): exit 143, one line on stderr, the finished estimators written, metrics.json saying
    stopped: terminated."""
    out = tmp_path / "run"
    child = _child(out, threads=1)
    try:
        _wait_for(child, "running fixed-lag")
        rest = _terminated(child)
    finally:
        child.kill()
        child.wait()
    said = [line for line in rest if not line.startswith("running ")]
    assert len(said) == 1, rest
    assert said[0].startswith("smoother: terminated: wrote the finished estimators (batch, ekf)"), rest
    run = json.loads((out / "metrics.json").read_text())["_run"]
    assert run["stopped"] == "terminated" and run["estimators"] == ["batch", "ekf"]
    for name in ESTIMATORS:
        for suffix in (".tum", ".npz"):
            assert (out / f"{name}{suffix}").exists() == (name in run["estimators"]), (name, suffix)
    files.load_trajectory(out / "batch.npz")


@pytest.mark.skipif(not Path("/proc/self/task").is_dir(), reason="reads a process's children from /proc")
def test_sigterm_stops_the_fixed_lag_smoother_s_second_process_too(tmp_path):
    """SIGTERM to the run while its fixed-lag smoother runs in a second process beside the EKF:
    exit 143, one line on stderr, and that process is gone."""
    out = tmp_path / "run"
    child = _child(out, threads=2)
    try:
        second = _second_process(child)
        rest = _terminated(child)
    finally:
        child.kill()
        child.wait()
    assert second, "no second process"
    said = [line for line in rest if not line.startswith("running ")]
    assert len(said) == 1 and said[0].startswith("smoother: terminated"), rest
    assert not [p for p in second if _running(p)], second


@pytest.mark.skipif(not Path("/proc/self/task").is_dir(), reason="reads a process's children from /proc")
def test_ctrl_c_to_the_run_s_process_group_stops_both_processes_with_one_line(tmp_path):
    """A terminal's Ctrl-C reaches the run and its fixed-lag smoother's second process: exit 130,
    one line on stderr (no traceback of the second process's), and that process is gone."""
    child = _child(tmp_path / "run", threads=2, session=True)
    try:
        second = _second_process(child)
        os.killpg(child.pid, signal.SIGINT)
        rest = child.stderr.read().splitlines()
        assert child.wait() == 128 + signal.SIGINT, rest
    finally:
        child.kill()
        child.wait()
    said = [line for line in rest if not line.startswith("running ")]
    assert len(said) == 1 and said[0].startswith("smoother: interrupted"), rest
    assert second and not [p for p in second if _running(p)], second


@pytest.mark.skipif(not Path("/proc/self/task").is_dir(), reason="reads a process's children from /proc")
def test_the_fixed_lag_smoother_s_second_process_ends_when_the_run_is_killed(tmp_path):
    """SIGKILL to the run (no handler runs): its second process, which nothing would read, ends
    within seconds instead of computing on."""
    child = _child(tmp_path / "run", threads=2)
    try:
        second = _second_process(child)
    finally:
        child.kill()
        child.wait()
    assert second, "no second process"
    deadline = time.monotonic() + 10.0
    while any(_running(p) for p in second) and time.monotonic() < deadline:
        time.sleep(0.1)
    assert not [p for p in second if _running(p)], second


def _terminated(child: subprocess.Popen) -> list[str]:
    """SIGTERM to ``child``: the rest of its stderr, once it has exited with 128 + SIGTERM."""
    child.send_signal(signal.SIGTERM)
    rest = child.stderr.read().splitlines()
    assert child.wait() == 128 + signal.SIGTERM, rest
    return rest


def _second_process(child: subprocess.Popen) -> list[int]:
    """The process ids of ``child``'s children once its fixed-lag smoother runs beside its EKF
    (Linux's /proc)."""
    _wait_for(child, "running fixed-lag (beside the others")
    _wait_for(child, "running ekf")
    return [int(p) for p in Path(f"/proc/{child.pid}/task/{child.pid}/children").read_text().split()]


def _running(pid: int) -> bool:
    """Whether process ``pid`` exists and is not a zombie (Linux's /proc)."""
    try:
        return "zombie" not in Path(f"/proc/{pid}/status").read_text()
    except FileNotFoundError:
        return False


def test_a_second_run_into_a_directory_in_use_is_refused_at_once(tmp_path, capsys, monkeypatch):
    """While a run writes into DIR (a child process), a second run into DIR stops before its
    estimators with one line naming DIR and the other run's process id; the first run goes on."""
    import smoother.pipeline

    out = tmp_path / "run"
    child = _child(out)
    try:
        _wait_for(child, "running batch")
        monkeypatch.setattr(smoother.pipeline, "run_estimators", lambda *a, **k: pytest.fail("estimators ran"))
        assert main(["run", "--duration", "1", "--estimator", "ekf", "--out", str(out), "--no-progress"]) == 2
        err = capsys.readouterr().err.strip().splitlines()
        assert err[-1] == (f"smoother: error: --out {out}: another smoother run (pid {child.pid}) is writing into "
                           "this directory; wait for it to end or choose another --out"), err
        assert child.poll() is None
    finally:
        child.kill()
        child.wait()
