"""Running the estimators on a dataset: one call per estimator, one result type for all.

``batch`` (the whole graph), ``fixed-lag`` (GTSAM's fixed-lag smoother fed the data in order of
arrival, :func:`smoother.online.replay`; each keyframe's estimate when it leaves the window, i.e.
smoothed over the lag) and ``ekf`` (the primer's filter) see the same dataset; the two smoothers
have the same keyframes and factors (:func:`smoother.graph.build_problem`; the online smoother
makes them as the data arrive), so their differences are the estimators', not the model's.
"""
from __future__ import annotations

import time
from dataclasses import dataclass

import numpy as np

from datasets.types import Dataset, Trajectory
from smoother.batch import solve_batch
from smoother.ekf import run_ekf
from smoother.graph import build_problem
from factors.errors import InputError
from smoother.online import replay

ESTIMATORS = ("batch", "fixed-lag", "ekf")


@dataclass
class Estimate:
    """One estimator's trajectory (with covariances where computed) and wall time [s]; the EKF's
    carries its :class:`smoother.ekf.Innovations`."""

    name: str
    trajectory: Trajectory
    runtime_s: float
    details: dict
    innovations: object = None


@dataclass
class RunOptions:
    """Options shared by the estimators (the command line's flags)."""

    lag_s: float = 2.0
    fixed_lag_kind: str = "sliding"
    optimizer: str = "lm"
    max_iterations: int = 100
    keyframe_rate: float | None = None
    robust: dict | None = None
    ekf_gate: float | None = None  # chi-square gate probability
    covariances: bool = True
    progress: bool | None = None
    max_delay_s: float = 0.0  # how late a measurement may arrive behind the IMU (fixed-lag)
    realtime: bool = False  # fixed-lag: replay at the data's own pace (times ``speed``)
    speed: float = 1.0


def run_estimators(dataset: Dataset, names, options: RunOptions = RunOptions()) -> dict[str, Estimate]:
    """Run each estimator in ``names`` (a subset of :data:`ESTIMATORS`) on ``dataset``."""
    unknown = [n for n in names if n not in ESTIMATORS]
    if unknown:
        raise InputError(f"unknown estimator(s) {unknown}; expected {', '.join(ESTIMATORS)}")
    out: dict[str, Estimate] = {}
    problem, build_s = None, 0.0
    if "batch" in names:
        tick = time.perf_counter()
        problem = build_problem(dataset, options.keyframe_rate, options.robust)
        build_s = time.perf_counter() - tick
    for name in names:
        if name == "batch":
            r = solve_batch(problem, options.optimizer, options.max_iterations, options.covariances)
            out[name] = Estimate(name, r.trajectory, build_s + r.runtime_s,
                                 {"iterations": r.iterations, "converged": r.converged, "final_error": r.error,
                                  "graph_build_s": build_s})
        elif name == "fixed-lag":
            r = replay(dataset, options.lag_s, options.fixed_lag_kind, options.keyframe_rate, options.robust,
                       options.covariances, options.max_delay_s, options.realtime, options.speed, options.progress)
            details = {"lag_s": options.lag_s, "kind": options.fixed_lag_kind, "recovered_keyframes": r.recovered,
                       "dropped_measurements": r.dropped, "skipped_measurements": r.skipped,
                       "longest_measurement_gap_s": r.longest_gap_s}
            if options.realtime and len(r.latency_s):
                ms = 1e3 * r.latency_s
                details["latency_ms"] = {"median": float(np.median(ms)), "p99": float(np.percentile(ms, 99)),
                                         "max": float(ms.max()), "measurements": len(ms)}
            out[name] = Estimate(name, r.smoothed, r.runtime_s, details)
        elif name == "ekf":
            r = run_ekf(dataset, options.ekf_gate, options.progress)
            out[name] = Estimate(name, r.trajectory, r.runtime_s, {"rejected_measurements": r.rejected},
                                 r.innovations)
    return out


def sensor_consistency(dataset: Dataset, estimates: dict[str, Estimate], options: RunOptions = RunOptions()) -> dict:
    """Each sensor's NIS through the EKF (:func:`smoother.diagnostics.sensor_consistency`): from
    the EKF among ``estimates``, else from an EKF run made for it."""
    from smoother.diagnostics import sensor_consistency as consistency

    ekf = estimates.get("ekf")
    innovations = ekf.innovations if ekf is not None else run_ekf(dataset, options.ekf_gate, False).innovations
    return consistency(innovations)
