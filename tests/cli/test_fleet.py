"""``smoother fleet``: three small recordings (bags and rig files written by the test), one rig
broken. Both good recordings are run into their folders exactly as ``smoother run --rig`` writes
them, the broken one is named in ``summary.json`` and the table, and the exit status says that one
failed -- on local worker processes and on a ``distributed.LocalCluster``. A recording whose
process dies does not stop the others; SIGTERM stops the fleet cleanly."""
from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
from small_recording import write_recording

from smoother.cli import main
from smoother.commands import fleet_runner as fleet

ROOT = Path(__file__).resolve().parents[2]
#: A rig file that names a bag but no topic: refused with one line by ``smoother run --rig``.
BROKEN = "[imu]\nsource = \"bag:missing.mcap\"\n"
RUN = ["--estimator", "ekf"]


@pytest.fixture(scope="module")
def rigs(tmp_path_factory):
    folder = tmp_path_factory.mktemp("fleet")
    a, _ = write_recording(folder / "site1", "husky", seed=1)
    b, _ = write_recording(folder / "site2", "jackal", seed=2)
    broken = folder / "site2" / "broken.toml"
    broken.write_text(BROKEN)
    return [a, broken, b]


def _check(out: Path, printed: str, rigs, tmp_path) -> None:
    """Two results and the broken rig's failure, in summary.json and in the table; each good
    recording's folder holds what ``smoother run --rig`` writes, the same bytes."""
    summary = json.loads((out / "summary.json").read_text())
    by_name = {r["recording"]: r for r in summary["recordings"]}
    assert list(by_name) == ["husky", "broken", "jackal"]  # the order given
    assert summary["failed"] == ["broken"] and summary["not_run"] == []
    assert "imu.topic: missing" in by_name["broken"]["failure"] and by_name["broken"]["exit_code"] == 2
    for name in ("husky", "jackal"):
        r = by_name[name]
        assert r["failure"] is None and r["exit_code"] == 0
        ekf = r["estimators"]["ekf"]
        assert ekf["gps_heldout_rmse_m"] > 0 and ekf["gps_fit_residual_m"] > 0
        assert set(ekf["sensors"]) == {"gnss", "wheel"} and "ok" in ekf["fit"]
        assert (out / name / "run.log").read_text().count("running ekf") == 1
    lines = printed.splitlines()
    assert any(line.startswith("broken") and "failed: " in line and "imu.topic: missing" in line for line in lines)
    assert sum(line.startswith(("husky", "jackal")) and " ekf " in line for line in lines) == 2
    direct = tmp_path / "direct"
    assert main(["run", "--rig", str(rigs[0]), "--out", str(direct), "--no-progress", *RUN]) == 0
    assert (out / "husky" / "ekf.npz").read_bytes() == (direct / "ekf.npz").read_bytes()
    names = lambda d: {p.name for p in d.iterdir()} - {"run.log"}  # noqa: E731
    assert names(out / "husky") == names(direct)


def test_fleet_on_local_workers(rigs, tmp_path, capsys):
    out = tmp_path / "fleet"
    code = main(["fleet", *map(str, rigs), "--out", str(out), "--workers", "2", "--no-progress", *RUN])
    printed = capsys.readouterr().out
    assert code == 2
    _check(out, printed, rigs, tmp_path)


def test_fleet_on_a_dask_cluster(rigs, tmp_path, capsys):
    distributed = pytest.importorskip("distributed")
    out = tmp_path / "fleet"
    with distributed.LocalCluster(n_workers=1, threads_per_worker=2, processes=False,
                                  dashboard_address=None) as cluster:
        code = main(["fleet", *map(str, rigs), "--out", str(out), "--dask", cluster.scheduler_address, "--no-progress",
                     *RUN])
    printed = capsys.readouterr().out
    assert code == 2
    _check(out, printed, rigs, tmp_path)


def test_two_rig_files_of_one_name_are_refused_up_front(rigs, tmp_path, capsys):
    twin = tmp_path / "other" / "husky.toml"
    twin.parent.mkdir()
    twin.write_text(rigs[0].read_text())
    assert main(["fleet", str(rigs[0]), str(twin), "--out", str(tmp_path / "fleet")]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "husky" in err and "rename one" in err
    assert not (tmp_path / "fleet").exists()


def test_dask_without_distributed_is_one_line(rigs, tmp_path, capsys, monkeypatch):
    monkeypatch.setitem(sys.modules, "distributed", None)  # import fails as if not installed
    assert main(["fleet", str(rigs[0]), "--out", str(tmp_path / "fleet"), "--dask", "tcp://127.0.0.1:1"]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "boxplus-smoother[dask]" in err


def test_a_recording_whose_process_dies_does_not_stop_the_others(rigs, tmp_path, monkeypatch):
    """The recording's process killed by a signal (a crash): its result names the signal, the
    other recordings' results are whole."""
    python = tmp_path / "python"
    python.write_text(f"#!/bin/sh\ncase \"$*\" in *jackal*) kill -SEGV $$;; esac\nexec {sys.executable} \"$@\"\n")
    python.chmod(0o755)
    monkeypatch.setattr(sys, "executable", str(python))
    results = []
    fleet.run_recordings(fleet.recordings([rigs[0], rigs[2]], tmp_path / "fleet", RUN), results.append, workers=2)
    by_name = {r["recording"]: r for r in results}
    assert by_name["jackal"]["failure"] == "its process was killed by SIGSEGV"
    assert by_name["husky"]["failure"] is None and "ekf" in by_name["husky"]["estimators"]


def test_sigterm_stops_the_fleet_and_its_recordings(tmp_path):
    """SIGTERM to the fleet while its first recording runs (one worker, three recordings): the
    running one is stopped through its own run (exit 143), the others never start, summary.json
    says so, and the fleet exits 143 leaving no process behind."""
    rigs = [write_recording(tmp_path / "rigs", name, duration=120.0, seed=k)[0] for k, name in enumerate("abc")]
    out = tmp_path / "fleet"
    env = {**os.environ, "PYTHONPATH": str(ROOT) + os.pathsep + os.environ.get("PYTHONPATH", "")}
    child = subprocess.Popen([sys.executable, "-m", "smoother.cli", "fleet", *map(str, rigs), "--out", str(out),
                              "--workers", "1", "--estimator", "all", "--no-progress"], env=env, cwd=tmp_path,
                             stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    log = out / "a" / "run.log"
    deadline = time.monotonic() + 300
    while not (log.exists() and "running" in log.read_text()):
        assert child.poll() is None and time.monotonic() < deadline, child.communicate()
        time.sleep(0.2)
    child.send_signal(signal.SIGTERM)
    stdout, stderr = child.communicate(timeout=300)
    assert child.returncode == 143, stderr
    summary = json.loads((out / "summary.json").read_text())
    assert summary["stopped"] == "terminated" and summary["not_run"] == ["b", "c"]
    (a,) = summary["recordings"]
    assert a["exit_code"] == 143 and "terminated" in a["failure"]
    assert not (out / "b").exists() and "a" in stdout
