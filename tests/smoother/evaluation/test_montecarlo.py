"""Monte Carlo runs (:mod:`smoother.evaluation.montecarlo`): results independent of where the runs run
and kept on interruption (``smoother montecarlo``: ``tests/cli/test_montecarlo_cli.py``)."""
import json

import numpy as np
import pytest

from smoother.evaluation import montecarlo

CONFIG = montecarlo.MonteCarloConfig(profile="gentle", duration=2.0, estimators=("batch", "ekf"))


@pytest.fixture(scope="module")
def serial():
    return montecarlo.run_many(CONFIG, [3, 1, 2])


def test_one_worker_and_several_give_identical_results(serial):
    on_processes = montecarlo.run_many(CONFIG, [2, 3, 1], workers=2)
    assert [r["seed"] for r in serial] == [1, 2, 3]
    assert json.dumps(serial, sort_keys=True) == json.dumps(on_processes, sort_keys=True)


def test_runs_are_seeded_and_differ_between_seeds(serial):
    again = montecarlo.run_many(CONFIG, [1])
    assert again[0] == serial[0]
    assert serial[0]["ekf"]["ate_rmse_m"] != serial[1]["ekf"]["ate_rmse_m"]


def test_aggregate_averages_nees_over_runs(serial):
    summary = montecarlo.aggregate(serial, ("batch", "ekf"))
    assert summary.runs == 3
    for name in ("batch", "ekf"):
        per_run = np.array([r[name]["nees"] for r in serial])
        np.testing.assert_allclose(summary.estimators[name]["nees_per_keyframe"], per_run.mean(axis=0) / 6.0)
        assert 0.0 <= summary.estimators[name]["nees_share_inside_95"] <= 1.0
    low, high = summary.nees_interval_95
    assert low < 1.0 < high


def test_finished_runs_are_written_as_they_complete(tmp_path):
    seen = []
    montecarlo.run_many(CONFIG, [5, 6], out_dir=tmp_path, on_done=seen.append)
    files = sorted(p.name for p in (tmp_path / "runs").iterdir())
    assert files == ["seed_5.json", "seed_6.json"]
    assert json.loads((tmp_path / "runs" / "seed_5.json").read_text()) == {r["seed"]: r for r in seen}[5]
    # a second call into the same folder: its runs only, not those of the first (another config)
    montecarlo.run_many(CONFIG, [6, 7], out_dir=tmp_path)
    assert sorted(p.name for p in (tmp_path / "runs").iterdir()) == ["seed_6.json", "seed_7.json"]


def test_an_interrupted_run_keeps_what_finished(tmp_path, monkeypatch):
    calls = []
    real = montecarlo.run_one

    def interrupt_second(config, seed):
        calls.append(seed)
        if len(calls) == 2:
            raise KeyboardInterrupt
        return real(config, seed)

    monkeypatch.setattr(montecarlo, "run_one", interrupt_second)
    with pytest.raises(KeyboardInterrupt):
        montecarlo.run_many(CONFIG, [7, 8, 9], out_dir=tmp_path)
    assert [p.name for p in (tmp_path / "runs").iterdir()] == ["seed_7.json"]


def test_dask_cluster_gives_the_same_results(serial):
    """The optional Dask path on a local in-process cluster (skipped without the 'dask' extra)."""
    distributed = pytest.importorskip("distributed")
    with distributed.LocalCluster(n_workers=1, threads_per_worker=1, processes=False,
                                  dashboard_address=None) as cluster:
        on_dask = montecarlo.run_many(CONFIG, [1, 2, 3], dask_address=cluster.scheduler_address)
    assert json.dumps(serial, sort_keys=True) == json.dumps(on_dask, sort_keys=True)
