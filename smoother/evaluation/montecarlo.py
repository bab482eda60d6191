"""Monte Carlo runs of the simulator through the estimators, in this process, on a pool of
processes or on a Dask cluster (:mod:`smoother.parallel`), with results that do not depend on which.

Each run is a pure function of its configuration and its seed (:func:`run_one`): it simulates,
runs the estimators and returns plain numbers (metrics and the per-keyframe pose NEES). Runs are
collected by seed, so 1 worker, several processes or a Dask cluster give identical results.
:func:`aggregate` averages the NEES over runs per keyframe and compares it with the two-sided
95% chi-square interval of an average of ``runs`` independent 6-dim NEES.
"""
from __future__ import annotations

import json
from dataclasses import asdict, dataclass, field
from functools import partial
from pathlib import Path

import numpy as np

from datasets.atomic import atomic_write
from smoother import parallel
from smoother.confined import inside

#: The folder of ``out_dir`` that holds each run's result (:func:`run_many`).
RUNS = "runs"


@dataclass(frozen=True)
class MonteCarloConfig:
    profile: str = "gentle"
    duration: float = 10.0
    estimators: tuple = ("batch", "ekf")
    lag_s: float = 2.0
    outliers: float = 0.0
    robust: tuple = ()  # ((sensor name, (kernel, threshold)), ...) as hashable pairs


def run_one(config: MonteCarloConfig, seed: int) -> dict:
    """One seeded run: ``{"seed", <estimator>: {"ate_rmse_m", "rot_rmse_deg", "nees_mean",
    "nees": [...] per keyframe, "t": [...]}}``. Plain lists and floats only (picklable, JSON)."""
    from datasets.simulate import simulate
    from smoother.evaluation.scoring import compare_with_truth
    from smoother.pipeline import RunOptions, run_estimators

    dataset = simulate(profile=config.profile, duration=config.duration, seed=seed,
                       outlier_fraction=config.outliers)
    options = RunOptions(lag_s=config.lag_s, robust=dict(config.robust) or None, progress=False)
    estimates = run_estimators(dataset, list(config.estimators), options)
    out: dict = {"seed": int(seed)}
    for name, est in estimates.items():
        c = compare_with_truth(dataset.truth, est.trajectory)
        out[name] = {
            "ate_rmse_m": c["ate_rmse_m"],
            "rot_rmse_deg": c["rot_rmse_deg"],
            "nees_mean": float(np.mean(c["nees"]) / 6.0),
            "t": c["t"].tolist(),
            "nees": c["nees"].tolist(),
        }
    return out


def run_many(config: MonteCarloConfig, seeds, workers: int = 1, dask_address: str | None = None,
             out_dir: Path | None = None, on_done=None) -> list[dict]:
    """Every seed through :func:`run_one` -- in this process, one after the other, for one worker;
    on a pool of ``workers`` processes (:func:`smoother.parallel.processes`) or on the Dask
    scheduler at ``dask_address`` otherwise -- with :func:`smoother.parallel.run_all`'s window,
    failures and stopping; results sorted by seed. With ``out_dir`` each finished run is written
    at once (``runs/seed_<n>.json``, atomically, only inside ``out_dir``:
    :func:`smoother.confined.inside`), so an interruption keeps them (and those of the
    runs under way in worker processes that end after it: a SIGTERM to this process alone lets
    them finish, a terminal's Ctrl-C stops them too); the seed files of an earlier call into the
    same folder are removed first, so that ``runs/`` never mixes two configurations."""
    seeds = [int(s) for s in seeds]
    results = []
    runs = None if out_dir is None else inside(out_dir, RUNS)
    if runs is not None:
        for stale in runs.glob("seed_*.json"):
            inside(runs, stale.name, follow=False).unlink(missing_ok=True)

    def keep(result):
        results.append(result)
        if runs is not None:
            with atomic_write(inside(runs, f"seed_{result['seed']}.json")) as handle:
                json.dump(result, handle)
        if on_done is not None:
            on_done(result)

    if dask_address is not None:
        where = parallel.dask(dask_address)
    else:
        where = parallel.in_this_thread() if workers == 1 else parallel.processes(workers)
    with where:
        parallel.run_all(partial(run_one, config), seeds, where, keep)
    return sorted(results, key=lambda r: r["seed"])


@dataclass
class Summary:
    runs: int
    estimators: dict = field(default_factory=dict)
    nees_interval_95: tuple = (0.0, 0.0)

    def as_dict(self) -> dict:
        return asdict(self)


def aggregate(results: list[dict], estimators) -> Summary:
    """Mean metrics over runs, and the per-keyframe NEES averaged over runs with the share of
    keyframes inside the 95% interval of ``chi2(6 runs) / runs``."""
    from smoother import stats

    runs = len(results)
    low, high = stats.nees_bounds(6, runs)
    summary = Summary(runs=runs, nees_interval_95=(low / 6.0, high / 6.0))
    for name in estimators:
        per_run = [r[name] for r in results]
        n = min(len(p["nees"]) for p in per_run)
        nees = np.mean([p["nees"][:n] for p in per_run], axis=0)
        summary.estimators[name] = {
            "ate_rmse_m": float(np.mean([p["ate_rmse_m"] for p in per_run])),
            "rot_rmse_deg": float(np.mean([p["rot_rmse_deg"] for p in per_run])),
            "nees_mean": float(np.mean(nees) / 6.0),
            "nees_share_inside_95": float(np.mean((nees >= low) & (nees <= high))),
            "t": per_run[0]["t"][:n],
            "nees_per_keyframe": (nees / 6.0).tolist(),
        }
    return summary
