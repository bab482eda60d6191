"""Performance figures of the project next to their targets (measures; asserts nothing).

Figures (each with its target; ratios are measured side by side in the same run, repetitions
interleaved, medians taken, because the machine is noisy):

1. preintegration of a whole run (``factors.preintegration.integrate_with_covariance``:
   preintegrated quantities, bias Jacobians and the 15x15 covariance, along the true keyframe
   states; on every core, and on one for comparison) per IMU sample, next to GTSAM's
   ``PreintegratedImuMeasurements.integrateMeasurement`` called per sample from Python (which
   always computes its 9x9 covariance and bias Jacobians too), one fresh PIM per keyframe
   interval; for context also ``integrate`` alone (no covariance), GTSAM's
   ``PreintegratedCombinedMeasurements`` (15x15 covariance with the bias walk, like ours), a
   10-minute run, and a call's time split into a fixed cost per call and a marginal cost per
   sample from the two runs;
2. the EKF (``run_ekf``: 15-dim state, prediction and 10 Hz pose updates) per IMU sample, next to
   GTSAM's ``NavStateImuEKF.predict`` called per sample (9-dim NavState, no biases, no updates);
3. KITTI: this project's batch smoother end to end (load, preintegrate, optimise) and GTSAM's
   native ImuFactor graph with LM (``benchmarks/kitti_native.py``, whose time excludes reading
   the files), held-out RMS with every 10th fix; and the whole process of each, started cold
   (Numba's kernels cached on disk, nothing else warm): ``smoother run --dataset kitti --estimator
   batch --gps-every 10`` against ``kitti_native.py --native-only`` (GTSAM and NumPy only), the
   two started in turn;
4. synthetic batch solve (200 Hz IMU, 10 Hz keyframes and poses) of 1, 5, 15 and 60 minutes,
   each in a fresh child process after a warm-up and repeated there to about 15 minutes of data
   (mean): build (preintegration included) + optimise, covariances off; covariance time of the
   short runs; the growth of the cost per keyframe on a power law fitted through the lengths;
5. fixed-lag update times (lag 2 s, covariances off): incremental over one hour (overall and per
   tenth of the run: flat is part of the target; and the objects the run left for Python's
   collector, which a flat run does not accumulate), batch kind over a shorter run (it is ~100x
   slower per update);
6. peak resident memory of the one-hour batch run, measured in a child process (``os.wait4``
   gives that child's own ``ru_maxrss``);
7. online fixed-lag smoothing, keyframe by keyframe side by side with GTSAM's own path (200 Hz IMU,
   10 Hz keyframes and poses, lag 2 s, one hour; covariances off on both sides): GTSAM's
   ``IncrementalFixedLagSmoother`` (default ``ISAM2Params``) on ``CombinedImuFactor`` and
   ``PriorFactorPose3``, preintegrated by ``PreintegratedCombinedMeasurements.integrateMeasurement``
   per sample from Python, against :class:`smoother.online.smoother.OnlineSmoother` fed ``add_imu`` per
   sample and ``add("pose", ...)``. The whole loop per keyframe on each side: the samples of the
   interval in, the update, the newest estimate out (``calculateEstimate`` / ``estimate()``); the
   two smoothers step in turn, one keyframe each, so a slow spell of the machine hits both. Also
   ``estimate()`` called after every IMU sample between keyframes (us per call);
8. self-calibration: the batch smoother on a 60-s rig of wheels, GNSS and an AHRS as given and
   with 12 calibration coordinates; the online smoother on it as given and with the wheels'
   mounting and scale to estimate, the two fed in lockstep, the whole loop per keyframe and the
   window's update alone;
9. a car-like rig (100 Hz IMU, 83 Hz wheel speeds, 10 Hz GNSS, three calibrations; measurements
   attached to 10 Hz keyframes): every estimator as ``smoother run --estimator all`` runs them
   (``pipeline.run_estimators``) over 1, 5, 15 and 60 minutes, each length in a fresh child process:
   the hour's wall time and peak memory, each estimator's cost per second of data and its growth
   with the length; the 60-s rig with a keyframe at every measurement time against the grid; and
   the longest rig fed live to the online smoother (:func:`online_car`: the loop per keyframe and
   per wheel message, the worst single call of each method), beside GTSAM's native fixed-lag loop
   on the same IMU and fixes (GTSAM has no factor for the wheels' body-frame speed).

Run: python benchmarks/run.py [--quick] [--json] [--whole-process | --car]
``--quick`` runs a reduced set (shorter runs, fewer repetitions, no hour runs: ``hour_*`` and
``car_hour_*`` are null).
"""
from __future__ import annotations

import argparse
import gc
import json
import os
import platform
import resource
import statistics
import subprocess
import sys
import tempfile
import time
import warnings
from dataclasses import dataclass, replace
from importlib import metadata
from pathlib import Path

import gtsam
import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
import kitti_native

from datasets import kitti
from datasets.simulate import simulate
from factors import preintegration, threads
from factors.kernel_caches import ensure_fresh_caches
from smoother.batch.solve import solve_batch
from smoother.ekf.filter import run_ekf
from smoother.estimators import ESTIMATORS
from smoother.evaluation import native
from smoother.evaluation.scoring import compare_with_truth
from smoother.fixed_lag.offline import run_fixed_lag
from smoother.model.covariances import covariances_at
from smoother.model.problem import build_problem
from smoother.model.timeline import EVERY_MEASUREMENT, imu_steps, keyframe_record, keyframe_times, measurement_knots
from smoother.online.smoother import OnlineSmoother
from smoother.pipeline import RunOptions, run_estimators

KEYFRAME_RATE = 10.0  # Hz, keyframes and pose measurements of the synthetic runs
LAG_S = 2.0


@dataclass(frozen=True)
class Settings:
    preint_s: float  # duration of the preintegration and EKF runs [s]
    preint_long_s: float  # a longer preintegration run, for the cost per call and per sample
    repeats: int  # repetitions of the cheap figures
    kitti_repeats: int
    process_repeats: int  # whole-process KITTI runs of each side (started in turn)
    scaling_min: tuple  # run lengths of the batch scaling figure [min] (without the hour)
    covariance_min: tuple  # lengths whose covariance time is measured too
    hour: bool
    fixed_lag_min: float  # incremental fixed-lag run [min]
    fixed_lag_batch_s: float  # batch-kind fixed-lag run [s]
    online_min: float  # online against native fixed-lag run [min]
    car_min: tuple  # run lengths of the car rig's every-estimator runs [min] (the hour last where ``hour``)


FULL = Settings(60.0, 600.0, 7, 5, 9, (1, 5, 15), (1, 5), True, 60.0, 60.0, 60.0, (1, 5, 15, 60))
QUICK = Settings(20.0, 60.0, 3, 1, 5, (0.5, 1, 2), (0.5,), False, 1.0, 5.0, 1.0, (0.5, 1, 2))


# ------------------------------------------------------------------------------------------------
# helpers


def _clock(fn):
    """``(seconds, result)`` of one call."""
    tick = time.perf_counter()
    out = fn()
    return time.perf_counter() - tick, out


def _interleaved(fns: dict, repeats: int) -> dict:
    """Wall times of each function over ``repeats`` rounds, called in turn within each round (so
    a slow spell of the machine hits all of them alike). Returns name -> list of seconds."""
    times = {name: [] for name in fns}
    for _ in range(repeats):
        for name, fn in fns.items():
            times[name].append(_clock(fn)[0])
    return times


def _median(xs) -> float:
    return float(statistics.median(xs))


def _synthetic(duration_s: float):
    return simulate("gentle", duration=duration_s, seed=0, imu_rate=200.0, pose_rate=KEYFRAME_RATE)


def _gtsam_params(dataset) -> gtsam.PreintegrationParams:
    """GTSAM preintegration parameters with the dataset's gravity and noise densities."""
    params = gtsam.PreintegrationParams(np.asarray(dataset.gravity, dtype=float))
    params.setAccelerometerCovariance(np.eye(3) * dataset.noise.acc**2)
    params.setGyroscopeCovariance(np.eye(3) * dataset.noise.gyro**2)
    params.setIntegrationCovariance(np.eye(3) * max(dataset.noise.velocity, 1e-4) ** 2)
    return params


def _per_sample(steps):
    """The Euler steps as Python lists of per-sample arrays / floats (prepared untimed, the best
    case for a per-sample Python loop)."""
    return list(steps.acc), list(steps.gyro), steps.dt.tolist()


def warm_up() -> None:
    """Run every timed path once, untimed, on a short run: the first call of a kernel in a new
    environment (or after an edit, which drops the cached kernels) compiles it, seconds that
    would otherwise land in whichever figure happens to call it first."""
    dataset = _synthetic(5.0)
    times = keyframe_times(dataset, KEYFRAME_RATE)
    samples = imu_steps(dataset.imu, times).segments()
    preintegration.integrate_with_covariance(samples, dataset.initial, dataset.noise, dataset.gravity)
    preintegration.integrate(*samples, dataset.initial.b_w)  # the re-integration kernel
    run_ekf(dataset, progress=False)
    solve_batch(build_problem(dataset), covariances=True)
    for kind in ("incremental", "batch"):
        run_fixed_lag(build_problem(dataset, keyframe_rate=KEYFRAME_RATE), LAG_S, kind, covariances=False,
                      progress=False)
    kitti_native.ours(10)
    online_against_native(5.0)


# ------------------------------------------------------------------------------------------------
# 1. preintegration


def _preintegration_inputs(duration_s: float):
    """``(dataset, times, steps, start, anchors)`` of a synthetic run: keyframes at
    :data:`KEYFRAME_RATE` on the true states (the smoother's initial trajectory)."""
    dataset = _synthetic(duration_s)
    times = keyframe_times(dataset, KEYFRAME_RATE)
    steps = imu_steps(dataset.imu, times)
    keyframes = dataset.truth.states[np.searchsorted(dataset.truth.t, times)]
    start = dataset.initial.replace(r=keyframes.r[0], v=keyframes.v[0], C=keyframes.C[0])
    return dataset, times, steps, start, preintegration.Anchors.of_states(keyframes)


def bench_preintegration(s: Settings) -> dict:
    dataset, times, steps, start, anchors = _preintegration_inputs(s.preint_s)
    samples = steps.segments()
    long_dataset, _, long_steps, long_start, long_anchors = _preintegration_inputs(s.preint_long_s)
    long_samples = long_steps.segments()
    b_w = np.broadcast_to(dataset.initial.b_w, (len(times) - 1, 3))
    n, n_long = len(steps.dt), len(long_steps.dt)
    params = _gtsam_params(dataset)
    combined = native.combined_params(dataset.noise, dataset.gravity)
    bias = gtsam.imuBias.ConstantBias(dataset.initial.b_f, dataset.initial.b_w)
    a_rows, g_rows, dt_rows = _per_sample(steps)
    bounds = steps.knot_step.tolist()

    def gtsam_loop(pim_class, pim_params):
        for start_k, stop_k in zip(bounds[:-1], bounds[1:]):
            pim = pim_class(pim_params, bias)
            for k in range(start_k, stop_k):
                pim.integrateMeasurement(a_rows[k], g_rows[k], dt_rows[k])

    def ours():
        return preintegration.integrate_with_covariance(samples, start, dataset.noise, dataset.gravity, anchors)

    def ours_long():
        return preintegration.integrate_with_covariance(long_samples, long_start, long_dataset.noise,
                                                        long_dataset.gravity, long_anchors)

    def one_thread(fn):
        with threads.thread_limit(1):
            return fn()

    # in this order each of our two whole-run calls comes right after one of GTSAM's loops, as a
    # call inside a smoother's work would: neither finds its code and data still in the caches
    t = _interleaved({
        "ours": ours,
        "ours_one_thread": lambda: one_thread(ours),
        "integrate": lambda: preintegration.integrate(*samples, b_w),
        "gtsam": lambda: gtsam_loop(gtsam.PreintegratedImuMeasurements, params),
        "ours_long": ours_long,
        "gtsam_combined": lambda: gtsam_loop(gtsam.PreintegratedCombinedMeasurements, combined),
    }, s.repeats)
    us = lambda seconds: 1e6 * seconds / n  # noqa: E731
    ours, theirs = us(_median(t["ours"])), us(_median(t["gtsam"]))
    # t = fixed + marginal * samples, from the two runs of each round (side by side)
    marginal = [(b - a) / (n_long - n) for a, b in zip(t["ours"], t["ours_long"])]
    fixed = [a - m * n for a, m in zip(t["ours"], marginal)]
    return {
        "preintegration_us_per_sample": ours,
        "preintegration_long_us_per_sample": 1e6 * _median(t["ours_long"]) / n_long,
        "preintegration_marginal_us_per_sample": 1e6 * _median(marginal),
        "preintegration_fixed_ms_per_call": 1e3 * _median(fixed),
        "preintegration_one_thread_us_per_sample": us(_median(t["ours_one_thread"])),
        # what the second thread gains: ~1 in the machine's fast moments, up to ~1.7 in its slow ones
        "preintegration_two_thread_gain": _median(t["ours_one_thread"]) / _median(t["ours"]),
        "preintegration_threads": threads.thread_count(),
        "preintegration_without_covariance_us_per_sample": us(_median(t["integrate"])),
        # the fastest repetition of each: what the code costs when the machine is quiet
        "preintegration_best_us_per_sample": us(min(t["ours"])),
        "gtsam_preintegration_best_us_per_sample": us(min(t["gtsam"])),
        "gtsam_preintegration_us_per_sample": theirs,
        "gtsam_combined_preintegration_us_per_sample": us(_median(t["gtsam_combined"])),
        "preintegration_speedup_vs_gtsam": theirs / ours,
        "preintegration_speedup_vs_gtsam_combined": us(_median(t["gtsam_combined"])) / ours,
        "preintegration_run": f"{s.preint_s:g} s at 200 Hz, {len(times) - 1} intervals (J x K = "
                              f"{samples[2].shape[0]} x {samples[2].shape[1]}), {n} samples, median of {s.repeats}; "
                              f"{threads.thread_count()} threads (one_thread: 1); long run {s.preint_long_s:g} s, "
                              f"{n_long} samples",
    }


# ------------------------------------------------------------------------------------------------
# 2. EKF


def bench_ekf(s: Settings) -> dict:
    dataset = _synthetic(s.preint_s)
    steps = imu_steps(dataset.imu, measurement_knots(dataset))
    n = len(steps.dt)
    a_rows, g_rows, dt_rows = _per_sample(steps)
    x0 = dataset.initial
    nav0 = gtsam.NavState(gtsam.Rot3(x0.C), gtsam.Point3(*x0.r), x0.C @ x0.v)
    params = _gtsam_params(dataset)

    def gtsam_loop():
        ekf = gtsam.NavStateImuEKF(nav0, np.eye(9) * 1e-2, params)
        for k in range(n):
            ekf.predict(g_rows[k], a_rows[k], dt_rows[k])

    t = _interleaved({"ours": lambda: run_ekf(dataset, progress=False), "gtsam": gtsam_loop}, s.repeats)
    ours, theirs = (1e6 * _median(t[k]) / n for k in ("ours", "gtsam"))
    return {
        "ekf_us_per_sample": ours,
        "gtsam_ekf_us_per_sample": theirs,
        "ekf_ratio_vs_gtsam": ours / theirs,
        "ekf_run": (f"{s.preint_s:g} s at 200 Hz, {len(dataset.sensor('pose').data)} pose updates, {n} samples, "
                    f"median of {s.repeats}"),
    }


# ------------------------------------------------------------------------------------------------
# 3. KITTI


def bench_kitti(s: Settings, gps_every: int = 10) -> dict:
    native, ours = [], []
    for _ in range(s.kitti_repeats):
        native.append(kitti_native.native(gps_every, "interval"))
        ours.append(kitti_native.ours(gps_every))
    load_s = _median([_clock(lambda: kitti.load_kitti(gps_every=gps_every))[0] for _ in range(s.kitti_repeats)])
    cumulative = kitti_native.native(gps_every, "cumulative")
    tuned = kitti_native.ours(gps_every, tune_noise=True)
    ours_s = _median([r["compute_s"] for r in ours])
    native_s = _median([r["compute_s"] for r in native])
    paired = kitti_native.paired_difference(ours[-1]["errors"], native[-1]["errors"], gps_every)
    return {
        "kitti_batch_s": ours_s,
        "kitti_native_s": native_s,
        "kitti_time_ratio": ours_s / native_s,
        "kitti_load_s": load_s,
        "kitti_rmse_m": ours[-1]["heldout_rmse_m"],
        "kitti_native_rmse_m": native[-1]["heldout_rmse_m"],
        # ours minus native on the same fixes, and its 95% block-bootstrap interval: whether the
        # difference is one this data can resolve
        "kitti_rmse_minus_native_m": paired["rmse_difference_m"],
        "kitti_rmse_minus_native_ci95_m": paired["ci95_m"],
        "kitti_native_cumulative_rmse_m": cumulative["heldout_rmse_m"],
        "kitti_tuned_rmse_m": tuned["heldout_rmse_m"],
        "kitti_tuned_s": tuned["compute_s"],
        "kitti_run": f"every {gps_every}th fix used, {ours[-1]['states']} keyframes, median of {s.kitti_repeats}",
    }


# ------------------------------------------------------------------------------------------------
# 4. linear scaling of the batch smoother (and 6. memory of the hour run)


#: The whole-process KITTI commands: ours as a user types it, GTSAM's own pipeline alone, and the
#: floor of any process of ours: Python with NumPy, GTSAM and Numba imported and one cached kernel
#: called (the first call of a compiled function sets Numba's compiler up, also to load from its cache).
KITTI_PROCESS = {
    "ours": ["-m", "smoother.cli", "run", "--dataset", "kitti", "--estimator", "batch", "--gps-every", "10"],
    "native": [str(Path(__file__).resolve().parent / "kitti_native.py"), "--native-only", "--gps-every", "10"],
    "floor": ["-c", "import gtsam, numpy; from factors import so3; so3.exp(numpy.zeros(3))"],
}


def bench_kitti_process(s: Settings) -> dict:
    """Wall time of each whole KITTI process (interpreter start to exit, :data:`KITTI_PROCESS`),
    started in turn, ``process_repeats`` times each after one untimed round, in a scratch directory
    (ours writes its outputs there); the ratio of ours to native's medians, the spread of the
    ratios round by round, and the floor's median. Each process is cold but for Numba's on-disk
    cache and Python's bytecode cache, which the untimed round filled (``PYTHONDONTWRITEBYTECODE``
    is dropped: the installed packages of the native side have theirs)."""
    root = str(Path(__file__).resolve().parent.parent)
    env = {**os.environ, "PYTHONPATH": os.pathsep.join(filter(None, [root, os.environ.get("PYTHONPATH")]))}
    env.pop("PYTHONDONTWRITEBYTECODE", None)
    times = {name: [] for name in KITTI_PROCESS}
    with tempfile.TemporaryDirectory() as scratch:
        for round_ in range(s.process_repeats + 1):
            for name, command in KITTI_PROCESS.items():
                tick = time.perf_counter()
                subprocess.run([sys.executable, *command], cwd=scratch, env=env, check=True,
                               stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
                if round_:
                    times[name].append(time.perf_counter() - tick)
    ours, theirs = _median(times["ours"]), _median(times["native"])
    rounds = [a / b for a, b in zip(times["ours"], times["native"])]
    return {
        "kitti_whole_process_s": ours,
        "kitti_native_whole_process_s": theirs,
        "kitti_whole_process_ratio": ours / theirs,
        "kitti_whole_process_floor_s": _median(times["floor"]),
        "kitti_whole_process_floor_ratio": _median(times["floor"]) / theirs,
        "kitti_whole_process_run": {name: [round(x, 3) for x in xs] for name, xs in times.items()}
        | {"ratio_per_round_min_max": [round(min(rounds), 3), round(max(rounds), 3)]},
    }


def _peak_rss_mib() -> float:
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0  # KiB on Linux


#: Length of the reference run that each scaling child times just before and after each
#: repetition of its own length [min]: this machine's speed wanders by up to 2x over tens of
#: seconds, so the cost per keyframe of each length is also given relative to a 1-minute run
#: measured side by side, in the same process and moment.
REFERENCE_MIN = 1.0


def batch_run(minutes: float, covariances: bool = False, memory: bool = False, repeats: int = 1) -> dict:
    """Simulate (untimed), then ``repeats`` times build the problem (preintegration included) and
    optimise with the vectorised engine, covariances off; the mean times, and the cost per
    keyframe relative to the :data:`REFERENCE_MIN` run timed before and after each repetition.
    Optionally time the marginal covariances too. With ``memory`` (a fresh process) the peak RSS
    so far is recorded after each stage."""
    dataset, reference = _synthetic(60.0 * minutes), _synthetic(60.0 * REFERENCE_MIN)
    stages = {"simulate": _peak_rss_mib()} if memory else None

    def reference_ms_per_keyframe() -> float:
        seconds, problem = _clock(lambda: build_problem(reference, keyframe_rate=KEYFRAME_RATE))
        seconds += _clock(lambda: solve_batch(problem, covariances=False))[0]
        return 1e3 * seconds / len(problem.times)

    builds, solves, references = [], [], [reference_ms_per_keyframe()]
    for _ in range(repeats):
        build_s, problem = _clock(lambda: build_problem(dataset, keyframe_rate=KEYFRAME_RATE))
        if memory:
            stages["build"] = _peak_rss_mib()
        solve_s, result = _clock(lambda: solve_batch(problem, covariances=False))
        if memory:
            stages["solve"] = _peak_rss_mib()
        builds.append(build_s)
        solves.append(solve_s)
        references.append(reference_ms_per_keyframe())
    out = {"minutes": minutes, "keyframes": len(problem.times), "iterations": result.iterations,
           "repeats": repeats, "build_s": float(np.mean(builds)), "solve_s": float(np.mean(solves))}
    out["total_s"] = out["build_s"] + out["solve_s"]
    out["ms_per_keyframe"] = 1e3 * out["total_s"] / out["keyframes"]
    out["reference_ms_per_keyframe"] = float(np.mean(references))
    out["relative_ms_per_keyframe"] = out["ms_per_keyframe"] / out["reference_ms_per_keyframe"]
    out["covariance_s"] = None
    if memory:
        out["peak_rss_mib_after"] = stages
    if covariances:
        out["covariance_s"] = _clock(lambda: covariances_at(problem.blocks, result.trajectory.states))[0]
    return out


def _batch_in_child(minutes: float, covariances: bool, repeats: int) -> dict:
    """:func:`batch_run` in a fresh interpreter, after a 10-second warm-up run there, so every
    length is measured in the same conditions (no first-call costs, no memory left by earlier
    runs); the child's own peak RSS."""
    command = [sys.executable, __file__, "--child-batch", str(minutes), "--repeats", str(repeats)]
    return _child(command + (["--covariances"] if covariances else []), f"the {minutes:g}-minute child run")


def _child(command: list, what: str) -> dict:
    """The JSON a child process ``command`` prints, with its own peak RSS (``os.wait4``'s
    ``ru_maxrss``) as ``peak_rss_mib``; ``what`` names it if it fails."""
    with tempfile.TemporaryFile("w+") as out:
        child = subprocess.Popen(command, stdout=out)
        _, status, usage = os.wait4(child.pid, 0)
        code = os.waitstatus_to_exitcode(status)
        if code != 0:
            raise RuntimeError(f"{what} failed (exit code {code})")
        out.seek(0)
        result = json.loads(out.read())
    result["peak_rss_mib"] = usage.ru_maxrss / 1024.0  # KiB on Linux
    return result


#: Each length is repeated until it has run about this many minutes of data (at least once):
#: this machine's speed wanders by +-15% over seconds, and a mean over comparable spans of
#: wall time compares the lengths fairly, where one short run would catch one spell.
SCALING_SPAN_MIN = 15.0


def _fitted_growth(minutes: list, ms_per_keyframe: list) -> float:
    """How much more a keyframe costs at the longest run than at the shortest, on the power law
    ``ms = a minutes^b`` fitted (least squares in logs) through every length: the systematic
    trend, where max/min - 1 of a few noisy figures also measures the noise: four lengths whose
    figures each wander by 10% (standard deviation) with no trend at all show a spread of 22% (the
    median over random draws), and a fitted growth of 9% (90% of draws: 22%)."""
    b = np.polyfit(np.log(minutes), np.log(ms_per_keyframe), 1)[0]
    return float((max(minutes) / min(minutes)) ** b - 1.0)


def bench_scaling(s: Settings) -> dict:
    """Each length in its own fresh child process, repeated there (mean) to a comparable span."""
    lengths = list(s.scaling_min) + ([60.0] if s.hour else [])
    runs = [_batch_in_child(m, m in s.covariance_min, max(1, round(SCALING_SPAN_MIN / m))) for m in lengths]
    hour = runs[-1] if s.hour else None
    per_kf = [r["ms_per_keyframe"] for r in runs]
    relative = [r["relative_ms_per_keyframe"] for r in runs]
    return {
        "scaling": runs,
        # side by side: each length against the 1-minute run timed around it in its own process
        "scaling_ms_per_keyframe_spread": max(relative) / min(relative) - 1.0,
        # across the children, which run at different moments of the machine
        "scaling_ms_per_keyframe_spread_across_runs": max(per_kf) / min(per_kf) - 1.0,
        # the trend through all lengths instead of their two extremes
        "scaling_fitted_growth": _fitted_growth(lengths, per_kf),
        "scaling_fitted_growth_side_by_side": _fitted_growth(lengths, relative),
        "hour_batch_s": hour["total_s"] if hour else None,
        "hour_peak_rss_mib": hour["peak_rss_mib"] if hour else None,
    }


# ------------------------------------------------------------------------------------------------
# 5. fixed-lag


def fixed_lag_run(duration_s: float, kind: str) -> dict:
    """Update times of one fixed-lag run, overall and per tenth of the run (flat over the run is
    part of the target: a smoother whose cost grows with the data it has seen would drift off
    real time in a long mission)."""
    problem = build_problem(_synthetic(duration_s), keyframe_rate=KEYFRAME_RATE)
    gc.collect()
    objects_before = len(gc.get_objects())
    result = run_fixed_lag(problem, LAG_S, kind, covariances=False, progress=False)
    gc.collect()
    objects_added = len(gc.get_objects()) - objects_before  # what the run left behind for the collector
    ms = 1e3 * result.update_s
    minutes = max(int(np.ceil(duration_s / 60.0 - 1e-9)), 1)  # the last keyframe (t = end) joins the last minute
    minute = np.minimum((problem.times - problem.times[0]) // 60.0, minutes - 1).astype(int)
    tenths = np.array_split(ms, 10)
    return {
        "kind": kind, "seconds": duration_s, "updates": len(ms),
        "median_ms": float(np.median(ms)), "p99_ms": float(np.percentile(ms, 99)), "max_ms": float(ms.max()),
        "over_10ms": int(np.sum(ms > 10.0)),
        "first_minute_median_ms": float(np.median(ms[minute == minute.min()])),
        "last_minute_median_ms": float(np.median(ms[minute == minute.max()])),
        "per_minute_median_ms": [float(np.median(ms[minute == m])) for m in np.unique(minute)],
        "per_tenth_median_ms": [float(np.median(t)) for t in tenths],
        "per_tenth_p99_ms": [float(np.percentile(t, 99)) for t in tenths],
        "total_s": result.runtime_s,
        "python_objects_added": objects_added,
    }


def bench_fixed_lag(s: Settings) -> dict:
    inc = fixed_lag_run(60.0 * s.fixed_lag_min, "incremental")
    bat = fixed_lag_run(s.fixed_lag_batch_s, "batch")
    return {
        "fixed_lag_update_ms_median": inc["median_ms"],
        "fixed_lag_update_ms_p99": inc["p99_ms"],
        # the worst tenth of the run: under 10 ms "flat over the run"
        "fixed_lag_update_ms_p99_worst_tenth": max(inc["per_tenth_p99_ms"]),
        "fixed_lag_incremental": inc,
        "fixed_lag_batch_update_ms_median": bat["median_ms"],
        "fixed_lag_batch_update_ms_p99": bat["p99_ms"],
        "fixed_lag_batch": bat,
    }


# ------------------------------------------------------------------------------------------------
# 7. online fixed-lag against GTSAM's native fixed-lag path


class _NativeFixedLag:
    """GTSAM's own fixed-lag path, as its examples write it: ``Pose3`` + world velocity +
    ``ConstantBias`` per keyframe, ``CombinedImuFactor`` between keyframes preintegrated per
    sample from Python, poses as ``PriorFactorPose3``, ``IncrementalFixedLagSmoother`` with
    default ``ISAM2Params``."""

    def __init__(self, dataset):
        from gtsam.symbol_shorthand import B, V, X

        self.X, self.V, self.B = X, V, B
        self.params = native.combined_params(dataset.noise, dataset.gravity)
        self.smoother = gtsam.IncrementalFixedLagSmoother(LAG_S, gtsam.ISAM2Params())
        x0, P0 = dataset.initial, dataset.initial_cov
        pose0 = gtsam.Pose3(gtsam.Rot3(x0.C), x0.r)
        self.nav = gtsam.NavState(pose0, x0.C @ x0.v)
        self.bias = gtsam.imuBias.ConstantBias(x0.b_f, x0.b_w)
        graph, values = gtsam.NonlinearFactorGraph(), gtsam.Values()
        graph.add(gtsam.PriorFactorPose3(X(0), pose0, gtsam.noiseModel.Isotropic.Sigma(6, 0.01)))
        graph.add(gtsam.PriorFactorVector(V(0), self.nav.velocity(), gtsam.noiseModel.Isotropic.Sigma(3, 0.1)))
        graph.add(gtsam.PriorFactorConstantBias(B(0), self.bias, gtsam.noiseModel.Gaussian.Covariance(P0[9:15, 9:15])))
        values.insert(X(0), pose0)
        values.insert(V(0), self.nav.velocity())
        values.insert(B(0), self.bias)
        self._update(graph, values, 0, float(dataset.imu.t[0]))
        self.pose_noise = None if "pose" not in dataset.sensor_names else gtsam.noiseModel.Isotropic.Sigmas(
            np.sqrt(np.diag(dataset.sensor("pose").data.cov[0]))[[3, 4, 5, 0, 1, 2]])
        self.k = 0

    def _update(self, graph, values, k, t) -> None:
        stamps = gtsam.FixedLagSmootherKeyTimestampMap()
        for key in (self.X(k), self.V(k), self.B(k)):
            stamps.insert((key, t))
        self.smoother.update(graph, values, stamps)
        estimate = self.smoother.calculateEstimate()
        self.nav = gtsam.NavState(estimate.atPose3(self.X(k)), estimate.atVector(self.V(k)))
        self.bias = estimate.atConstantBias(self.B(k))

    def keyframe(self, acc, gyro, dt, t, position, C) -> None:
        """The samples of one interval (lists), the pose at its end, one update, the estimate."""
        self.step(acc, gyro, dt, t, [gtsam.PriorFactorPose3(self.X(self.k + 1), gtsam.Pose3(gtsam.Rot3(C), position),
                                                            self.pose_noise)])

    def step(self, acc, gyro, dt, t, factors: list) -> None:
        """The samples of one interval (lists), the ``factors`` measuring the keyframe at its end
        (key ``X(self.k + 1)``), one update, the estimate."""
        X, V, B, k = self.X, self.V, self.B, self.k + 1
        pim = gtsam.PreintegratedCombinedMeasurements(self.params, self.bias)
        for a, w, h in zip(acc, gyro, dt):
            pim.integrateMeasurement(a, w, h)
        graph, values = gtsam.NonlinearFactorGraph(), gtsam.Values()
        graph.add(gtsam.CombinedImuFactor(X(k - 1), V(k - 1), X(k), V(k), B(k - 1), B(k), pim))
        for factor in factors:
            graph.add(factor)
        predicted = pim.predict(self.nav, self.bias)
        values.insert(X(k), predicted.pose())
        values.insert(V(k), predicted.velocity())
        values.insert(B(k), self.bias)
        self._update(graph, values, k, t)
        self.k = k


def _percentiles(ms: np.ndarray) -> dict:
    tenths = np.array_split(ms, 10)
    return {"median_ms": float(np.median(ms)), "p99_ms": float(np.percentile(ms, 99)), "max_ms": float(ms.max()),
            "per_tenth_median_ms": [float(np.median(x)) for x in tenths],
            "per_tenth_p99_ms": [float(np.percentile(x, 99)) for x in tenths]}


def online_against_native(duration_s: float) -> dict:
    """Whole loop per keyframe of both smoothers, stepping in turn (section 7 of the module
    docstring); the first 2 s (the window filling) are left out of the statistics."""
    dataset = _synthetic(duration_s)
    m = dataset.sensor("pose").data
    t, acc, gyro = dataset.imu.t, list(dataset.imu.acc), list(dataset.imu.gyro)
    times = t.tolist()
    ends = np.searchsorted(t, m.t)  # the sample at each pose time (poses fall on samples)
    assert np.array_equal(t[ends], m.t)
    native_side = _NativeFixedLag(dataset)
    published = [None]  # the smoothed keyframes go on as a robot's would: here, the newest is kept

    def publish(estimate) -> None:
        published[0] = estimate

    online = OnlineSmoother.for_dataset(dataset, lag_s=LAG_S, on_smoothed=publish)
    online.add_imu(times[0], acc[0], gyro[0])
    dts = np.diff(t).tolist()
    native_ms, online_ms = [], []
    first = 1 if ends[0] == 0 else 0
    previous = 0
    for i in range(first, len(ends)):
        end = int(ends[i])
        tick = time.perf_counter()
        native_side.keyframe(acc[previous:end], gyro[previous:end], dts[previous:end], times[end], m.position[i],
                             m.C[i])
        native_ms.append(time.perf_counter() - tick)
        tick = time.perf_counter()
        for j in range(previous + 1, end):
            online.add_imu(times[j], acc[j], gyro[j])
        online.add("pose", times[end], m.position[i], m.C[i], cov=m.cov[i])
        online.add_imu(times[end], acc[end], gyro[end])
        online.estimate()
        online_ms.append(time.perf_counter() - tick)
        previous = end
    skip = int(LAG_S * KEYFRAME_RATE)
    native_ms, online_ms = 1e3 * np.array(native_ms[skip:]), 1e3 * np.array(online_ms[skip:])
    # estimate() at IMU rate: after every sample between keyframes, a short second pass
    short = _synthetic(min(duration_s, 60.0))
    online = OnlineSmoother.for_dataset(short, lag_s=LAG_S)
    keyframe_times = set(short.sensor("pose").data.t.tolist())
    estimate_s = []
    pose_row = {tt: i for i, tt in enumerate(short.sensor("pose").data.t.tolist())}
    for j, tt in enumerate(short.imu.t.tolist()):
        if tt in pose_row:
            i = pose_row[tt]
            online.add("pose", tt, short.sensor("pose").data.position[i], short.sensor("pose").data.C[i],
                       cov=short.sensor("pose").data.cov[i])
        online.add_imu(tt, short.imu.acc[j], short.imu.gyro[j])
        tick = time.perf_counter()
        online.estimate()
        if tt not in keyframe_times:
            estimate_s.append(time.perf_counter() - tick)
    return {"seconds": duration_s, "keyframes": len(online_ms), "native": _percentiles(native_ms),
            "online": _percentiles(online_ms), "online_estimate_us": 1e6 * float(np.median(estimate_s)),
            "online_estimate_us_p99": 1e6 * float(np.percentile(estimate_s, 99))}


def bench_online(s: Settings) -> dict:
    r = online_against_native(60.0 * s.online_min)
    return {
        "online_loop_ms_median": r["online"]["median_ms"],
        "online_loop_ms_p99": r["online"]["p99_ms"],
        "native_fixed_lag_loop_ms_median": r["native"]["median_ms"],
        "native_fixed_lag_loop_ms_p99": r["native"]["p99_ms"],
        "online_estimate_us": r["online_estimate_us"],
        "online_run": r,
    }


# ------------------------------------------------------------------------------------------------
# report


def _calibration_rigs(duration_s: float):
    """60 s of a 100 Hz IMU with wheels (10 Hz), GNSS (5 Hz) and an AHRS (10 Hz), as given and
    with the wheels' rotation, scale and time offset, the fixes' time offset and lever arm and the
    AHRS's rotation to estimate (12 calibration coordinates)."""
    from datasets.simulated_sensors import SensorSpec
    from factors.calibration import CalibrationPrior

    data = simulate("gentle", duration=duration_s, seed=1, imu_rate=100.0, pose_rate=0, sensors=(
        SensorSpec("wheels", "velocity", 10.0, 0.05), SensorSpec("gnss", "gnss", 5.0, 0.2),
        SensorSpec("ahrs", "orientation", 10.0, 0.02)))
    calibrating = data.with_sensor("wheels", calibrate=CalibrationPrior(("rotation", "scale", "time_offset")))
    calibrating = calibrating.with_sensor("gnss", calibrate=CalibrationPrior(("time_offset", "lever_arm")))
    return data, calibrating.with_sensor("ahrs", calibrate=CalibrationPrior(("rotation",)))


def bench_calibration(s: Settings) -> dict:
    """The batch smoother (build + optimise + covariances) on :func:`_calibration_rigs`, without and
    with the calibrations, interleaved; the median of their ratio is ``batch_calibration_ratio``."""
    plain, calibrating = _calibration_rigs(60.0)
    run = {name: (lambda d=d: solve_batch(build_problem(d))) for name, d in (("plain", plain),
                                                                               ("calibrating", calibrating))}
    for fn in run.values():
        fn()  # first calls
    times = _interleaved(run, s.repeats)
    ratios = [c / p for p, c in zip(times["plain"], times["calibrating"])]
    out = {"batch_calibration_ratio": _median(ratios), "batch_uncalibrated_s": _median(times["plain"]),
           "batch_calibrated_s": _median(times["calibrating"])}
    return {**out, **_noise_estimation(s.repeats), **_online_calibration(plain, s.repeats)}


def _noise_estimation(repeats: int) -> dict:
    """The batch smoother on the calibrating rig of :func:`_calibration_rigs` (60 s and 120 s) with
    and without its noise estimated (every group: the IMU's four densities, each sensor's axis
    groups; :func:`smoother.batch.variance_components.estimate_noise` after the solve),
    interleaved: the median ratio ``batch_noise_ratio`` and, per second of data, the fit's time at
    both lengths (``batch_noise_s_per_data_s_60``, ``_120``: linear in the run's length when they
    agree). That rig states its noise right; ``batch_noise_ratio_stated_wrong`` is the ratio on the
    60-s rig stating its gyro's white noise 4x too small and its GNSS sigma 3x, whose fit iterates
    and applies its factors (the batch solved again with them), and
    ``batch_noise_stated_wrong_iterations`` its iterations."""
    from smoother.batch.variance_components import estimate_noise

    out = {}
    _, sixty = _calibration_rigs(60.0)
    sensors = tuple(replace(s, data=replace(s.data, cov=s.data.cov / 9.0)) if s.name == "gnss" else s
                    for s in sixty.sensors)
    wrong = replace(sixty, noise=replace(sixty.noise, gyro=sixty.noise.gyro / 4.0), sensors=sensors)
    for seconds, data in ((60.0, sixty), (120.0, _calibration_rigs(120.0)[1]), (60.0, wrong)):
        which = ("imu", *data.sensor_names)
        fits = []

        def with_noise(d=data):
            problem = build_problem(d)
            fits.append(estimate_noise(d, problem, solve_batch(problem, square_root=True), which)[0])

        run = {"plain": lambda d=data: solve_batch(build_problem(d)), "noise": with_noise}
        for fn in run.values():
            fn()
        times = _interleaved(run, repeats)
        ratio = _median([n / p for p, n in zip(times["plain"], times["noise"])])
        if data is wrong:
            out["batch_noise_ratio_stated_wrong"] = ratio
            out["batch_noise_stated_wrong_iterations"] = fits[-1].iterations
            continue
        if seconds == 60.0:
            out["batch_noise_ratio"] = ratio
            out["batch_noise_s"], out["batch_plain_s"] = _median(times["noise"]), _median(times["plain"])
        fit = [n - p for p, n in zip(times["plain"], times["noise"])]
        out[f"batch_noise_s_per_data_s_{int(seconds)}"] = _median(fit) / seconds
    return out


def _online_calibration(plain, repeats: int) -> dict:
    """The online smoother on ``plain`` as given and with one calibrated sensor (the wheels'
    rotation and scale), lag 2 s, no covariances, both fed the same recording in lockstep
    (:func:`_lockstep`: what the guest's speed does at any moment it does to both): the whole loop
    per keyframe (``online_loop_*``, as ``online_loop_ms_median``: the samples one by one, the
    measurements, the update, ``estimate()`` out) and the window's update alone
    (``online_update_*``); each figure the median over a run, then over the repetitions after a
    first round (which loads the kernels), each ratio the median of the rounds' ratios."""
    from factors.calibration import CalibrationPrior

    one = plain.with_sensor("wheels", calibrate=CalibrationPrior(("rotation", "scale")))
    rounds = [_lockstep((plain, one)) for _ in range(max(repeats, 1) + 1)][1:]
    out = {}
    for figure, i in (("loop", 0), ("update", 1)):
        plain_ms, one_ms = (_median([1e3 * float(np.median(r[k][i])) for r in rounds]) for k in (0, 1))
        ratio = _median([float(np.median(r[1][i]) / np.median(r[0][i])) for r in rounds])
        out.update({f"online_{figure}_uncalibrated_ms_median": plain_ms,
                    f"online_{figure}_calibrated_ms_median": one_ms,
                    f"online_{figure}_calibration_ratio": ratio})
    return out


def _lockstep(datasets) -> list:
    """Replay ``datasets`` -- one recording, each with its own sensor setup -- through one online
    smoother each (lag 2 s, no covariances) as a robot would feed it: each arrival
    (:func:`smoother.online.replay.arrivals`) -- the IMU samples before it one by one, its measurements,
    then ``estimate()`` -- handed to every smoother before the next, in turn first (what the
    caches keep from one smoother's step is the other's loss). Each smoother's ``(loop, update)``
    times [s]: of each arrival (about one keyframe each) after the first 2 s, as
    :func:`online_against_native` leaves out the window filling, and of each window update."""
    from smoother.online.replay import arrivals, replaying

    smoothers = [replaying(d, lag_s=2.0, covariances=False) for d in datasets]
    loops = [[] for _ in smoothers]
    imu_data, fed = datasets[0].imu, 0
    t, acc, gyro = imu_data.t.tolist(), list(imu_data.acc), list(imu_data.gyro)
    for i, (at, upto, arrived) in enumerate(arrivals(datasets[0])):
        for j in (range(len(smoothers)) if i % 2 == 0 else reversed(range(len(smoothers)))):
            online = smoothers[j]
            tick = time.perf_counter()
            for m in range(fed, upto):
                online.add_imu(t[m], acc[m], gyro[m])
            for name, data in arrived:
                online.add_measurements(name, data)
            if upto:
                online.estimate()
            if at >= t[0] + LAG_S:
                loops[j].append(time.perf_counter() - tick)
        fed = upto
    for online in smoothers:
        for m in range(fed, len(t)):
            online.add_imu(t[m], acc[m], gyro[m])
        online.finish()
    return [(np.array(loop), np.array(online.update_s)) for online, loop in zip(smoothers, loops)]


# ------------------------------------------------------------------------------------------------
# 9. a car-like rig: every estimator, cost per second of data, keyframes on the grid


#: Each length of the car's scaling is repeated until it has run about this many minutes of data.
CAR_SPAN_MIN = 5.0


def car_rig(duration_s: float, seed: int = 0):
    """A car-like rig: the gentle figure-eight (heading along the velocity) with a 100 Hz IMU, wheel
    speeds (a ``velocity`` sensor, 83 Hz: on the IMU's samples, so 10 or 20 ms apart; 0.05 m/s; 1.2 m
    behind and 0.3 m below the IMU, pitched 2 deg and reading 1 % low) and GNSS (10 Hz, 0.2 m; an
    antenna 1.2 m above, its fixes stamped 0.05 s late), the wheels' rotation and scale and the
    fixes' time offset to estimate. The measurements come faster than 10 Hz, so the default
    keyframes are the 10 Hz grid, the speeds between them and every fix attached."""

    from datasets.simulated_sensors import SensorSpec, scaled_speeds, stamped_late
    from factors import so3
    from factors.calibration import CalibrationPrior

    wheels, antenna = np.eye(4), np.eye(4)
    wheels[:3, :3], wheels[:3, 3] = so3.exp(np.radians([0.0, 2.0, 0.0])), [-1.2, 0.0, -0.3]
    antenna[:3, 3] = [0.0, 0.0, 1.2]
    data = simulate("gentle", duration=duration_s, seed=seed, imu_rate=100.0, pose_rate=0, sensors=(
        SensorSpec("wheels", "velocity", 83.0, 0.05, wheels), SensorSpec("gnss", "gnss", 10.0, 0.2, antenna)))
    data = stamped_late(scaled_speeds(data, "wheels", 0.99), "gnss", 0.05)
    data = data.with_sensor("wheels", calibrate=CalibrationPrior(("rotation", "scale")))
    return data.with_sensor("gnss", calibrate=CalibrationPrior(("time_offset",)))


def car_all(dataset, names=ESTIMATORS, keyframe_rate=None, beside: bool = True) -> dict:
    """``pipeline.run_estimators`` of ``names`` on ``dataset`` (what ``smoother run --estimator all``
    runs, without the verdicts and files after it: with ``beside``, the fixed-lag smoother in a
    second process where two threads are allowed, as the command does): the wall time of the call,
    each estimator's own time and its ATE against the truth (at its own states)."""
    options = RunOptions(keyframe_rate=keyframe_rate, progress=False,
                         fixed_lag_beside=beside and threads.thread_count() >= 2)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # the rig's deliberate mounting and offsets are said in warnings
        seconds, estimates = _clock(lambda: run_estimators(dataset, names, options))
    return {"seconds": dataset.t1 - dataset.t0, "all_s": seconds,
            "runtime_s": {n: e.runtime_s for n, e in estimates.items()},
            "ate_m": {n: compare_with_truth(dataset.truth, e.trajectory)["ate_rmse_m"] for n, e in estimates.items()}}


def car_run(minutes: float, repeats: int = 1) -> dict:
    """:func:`car_all` on :func:`car_rig` of ``minutes`` (simulated untimed), ``repeats`` times, each
    repetition between two runs of the :data:`REFERENCE_MIN` rig timed in the same process (the
    machine's speed wanders by up to 2x): the mean times, each estimator's (and all together's) cost
    per second of data and that cost relative to the reference runs' (``relative``), with the peak
    RSS so far after simulating and after the estimators (a fresh process: :func:`_car_in_child`)."""
    dataset, reference = car_rig(60.0 * minutes), car_rig(60.0 * REFERENCE_MIN)
    stages = {"simulate": _peak_rss_mib()}
    runs, references = [], [car_all(reference)]
    for _ in range(repeats):
        runs.append(car_all(dataset))
        references.append(car_all(reference))
    stages["estimators"] = _peak_rss_mib()

    def ms_per_data_s(of: list) -> dict:
        return {n: 1e3 * float(np.mean([(r["all_s"] if n == "all" else r["runtime_s"][n]) / r["seconds"] for r in of]))
                for n in (*ESTIMATORS, "all")}

    ms, ref = ms_per_data_s(runs), ms_per_data_s(references)
    return {"minutes": minutes, "repeats": repeats, "all_s": float(np.mean([r["all_s"] for r in runs])),
            "runtime_s": {n: float(np.mean([r["runtime_s"][n] for r in runs])) for n in ESTIMATORS},
            "ms_per_data_s": ms, "reference_ms_per_data_s": ref, "relative": {n: ms[n] / ref[n] for n in ms},
            "ate_m": runs[-1]["ate_m"], "peak_rss_mib_after": stages}


def _car_in_child(minutes: float, repeats: int) -> dict:
    """:func:`car_run` in a fresh interpreter after a 10-second warm-up run there; its own peak RSS."""
    return _child([sys.executable, __file__, "--child-car", str(minutes), "--repeats", str(repeats)],
                  f"the {minutes:g}-minute car run")


def bench_car(s: Settings) -> dict:
    """The car rig: every estimator over each length of ``s.car_min`` in its own child process
    (:func:`car_run`; the longest, an hour in the full set, gives ``car_hour_all_s`` and its peak
    memory), each estimator's time per second of data and its fitted growth from the shortest to
    the longest, across the children and side by side with the 1-minute runs timed in each; and the
    60-s rig with a keyframe at every measurement time against the default grid."""
    lengths = list(s.car_min)
    runs = [_car_in_child(m, max(1, round(CAR_SPAN_MIN / m))) for m in lengths]
    hour = runs[-1] if s.hour else None
    names = list(runs[0]["ms_per_data_s"])
    return {
        "car_hour_all_s": hour["all_s"] if hour else None,
        "car_hour_peak_rss_mib": hour["peak_rss_mib"] if hour else None,
        "car_scaling": {
            "minutes": lengths,
            "ms_per_data_s": {n: [r["ms_per_data_s"][n] for r in runs] for n in names},
            # across the children, which run at different moments of the machine
            "fitted_growth": {n: _fitted_growth(lengths, [r["ms_per_data_s"][n] for r in runs]) for n in names},
            # side by side: each length against the 1-minute runs timed around it in its own process
            "fitted_growth_side_by_side": {n: _fitted_growth(lengths, [r["relative"][n] for r in runs])
                                           for n in names},
            "runs": runs},
        "car_keyframe_speedup": keyframe_speedup(s.repeats),
        "car_online": online_car(lengths[-1]),
    }


def online_car(minutes: float) -> dict:
    """The car rig of ``minutes`` fed live, as a robot's callbacks would, to the online smoother
    (lag 2 s, covariances off, the rig's three calibrations estimated, keyframes on the 10 Hz
    grid): each IMU sample by ``add_imu``, each wheel speed and fix by ``add`` when it arrives (at
    its stamp, before the sample of that time), ``estimate()`` after each sample that made a
    keyframe, the smoothed keyframes handed on (``on_smoothed``) as they leave the window. Each call
    timed (in a process whose kernels are loaded): the loop per keyframe (the
    sample that made it and the estimate out)
    and per wheel message, median and p99 after the first 2 s, and the worst single call of each
    method over the whole run. Beside it, GTSAM's native fixed-lag loop on the same IMU and fixes
    (:class:`_NativeFixedLag`, stepped keyframe by keyframe in turn with ours: ``GPSFactorArm`` at
    the antenna's lever arm, each fix at the keyframe of its true time -- GTSAM estimates no time
    offset -- and no wheels: GTSAM has no factor for a body-frame speed): its loop per keyframe and
    its worst."""
    from smoother.online.replay import replaying

    dataset = car_rig(60.0 * minutes)
    t, acc, gyro = dataset.imu.t, dataset.imu.acc, dataset.imu.gyro
    times, acc_rows, gyro_rows = t.tolist(), list(acc), list(gyro)
    speeds, fixes = dataset.sensor("wheels").data, dataset.sensor("gnss").data
    grid = keyframe_times(dataset)
    # the sample at or after each keyframe time makes it; each message arrives before the sample of its stamp
    makes = np.zeros(len(t), dtype=bool)
    makes[np.searchsorted(t, grid[1:], side="left")] = True
    wheel_before = np.searchsorted(t, speeds.t, side="left")
    fix_before = np.searchsorted(t, fixes.t, side="left")
    published = [None]  # the smoothed keyframes go on as a robot's would: here, the newest is kept

    def publish(estimate) -> None:
        published[0] = estimate

    online = replaying(dataset, lag_s=LAG_S, covariances=False, on_smoothed=publish)
    native_side = _NativeFixedLag(dataset)
    antenna = fixes.T_BS[:3, 3]
    fix_noise = gtsam.noiseModel.Isotropic.Sigma(3, float(np.sqrt(fixes.cov[0, 0, 0])))
    fix_at = {round(x - 0.05, 9): i for i, x in enumerate(fixes.t.tolist())}  # the rig's fixes are 0.05 s late
    worst = {"add_imu": 0.0, "add wheels": 0.0, "add gnss": 0.0, "estimate": 0.0}
    keyframe_ms, wheel_ms, native_ms = [], [], []
    w = f = 0
    previous = 0
    dts = np.diff(t).tolist()
    settled = times[0] + LAG_S
    for j in range(len(t)):
        while w < len(speeds.t) and wheel_before[w] <= j:
            tick = time.perf_counter()
            online.add("wheels", speeds.t[w], speeds.velocity[w], speeds.gyro[w], cov=speeds.cov[w])
            took = time.perf_counter() - tick
            worst["add wheels"] = max(worst["add wheels"], took)
            if times[j] >= settled:
                wheel_ms.append(1e3 * took)
            w += 1
        while f < len(fixes.t) and fix_before[f] <= j:
            tick = time.perf_counter()
            online.add("gnss", fixes.t[f], fixes.position[f], cov=fixes.cov[f])
            worst["add gnss"] = max(worst["add gnss"], time.perf_counter() - tick)
            f += 1
        tick = time.perf_counter()
        online.add_imu(times[j], acc_rows[j], gyro_rows[j])
        took = time.perf_counter() - tick
        worst["add_imu"] = max(worst["add_imu"], took)
        if not makes[j]:
            continue
        tick = time.perf_counter()
        online.estimate()
        took_estimate = time.perf_counter() - tick
        worst["estimate"] = max(worst["estimate"], took_estimate)
        i = fix_at.get(round(times[j], 9))
        factors = [] if i is None else [gtsam.GPSFactorArm(native_side.X(native_side.k + 1), fixes.position[i],
                                                           antenna, fix_noise)]
        tick = time.perf_counter()
        native_side.step(acc_rows[previous:j], gyro_rows[previous:j], dts[previous:j], times[j], factors)
        native_took = time.perf_counter() - tick
        previous = j
        if times[j] >= settled:
            keyframe_ms.append(1e3 * (took + took_estimate))
            native_ms.append(1e3 * native_took)
    online.finish()
    keyframe_ms, wheel_ms, native_ms = (np.array(x) for x in (keyframe_ms, wheel_ms, native_ms))
    return {"minutes": minutes, "keyframes": len(keyframe_ms), "wheel_messages": len(wheel_ms),
            "online_keyframe_ms": _percentiles(keyframe_ms), "online_wheel_message_ms": _percentiles(wheel_ms),
            "online_worst_call_ms": {k: 1e3 * v for k, v in worst.items()},
            "native_keyframe_ms": _percentiles(native_ms)}


def keyframe_speedup(repeats: int) -> dict:
    """The 60-s car rig with a keyframe at every measurement time (``keyframe_rate="measurements"``)
    and on the default grid, every estimator each, one after the other (so the batch starts from
    the EKF run before it, its time the build and solve alone, and no estimator shares the cores
    with another), interleaved after a first round: the median batch and
    fixed-lag times of each, their ratios (every measurement over the grid) and each one's ATE
    against the truth."""
    dataset = car_rig(60.0)
    sides = {"measurements": EVERY_MEASUREMENT, "grid": None}
    rounds = [{side: car_all(dataset, keyframe_rate=rate, beside=False) for side, rate in sides.items()}
              for _ in range(max(repeats, 1) + 1)][1:]
    out = {}
    for name in ("batch", "fixed-lag"):
        times = {side: _median([r[side]["runtime_s"][name] for r in rounds]) for side in sides}
        ate = {side: rounds[-1][side]["ate_m"][name] for side in sides}
        out[name] = {"every_measurement_s": times["measurements"], "grid_s": times["grid"],
                     "speedup": _median([r["measurements"]["runtime_s"][name] / r["grid"]["runtime_s"][name]
                                         for r in rounds]),
                     "every_measurement_ate_m": ate["measurements"], "grid_ate_m": ate["grid"],
                     "ate_change": ate["grid"] / ate["measurements"] - 1.0}
    out["keyframes"] = {side: keyframe_record(dataset, rate)["count"] for side, rate in sides.items()}
    return out


def machine() -> dict:
    model = "unknown"
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                model = line.split(":", 1)[1].strip()
                break
    except OSError:
        pass
    return {
        "nproc": len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count(),
        "cpu": model,
        "python": platform.python_version(),
        "numpy": np.__version__,
        "gtsam": metadata.version("gtsam"),
        "loadavg": [round(x, 2) for x in os.getloadavg()],
    }


def _table_rows(r: dict) -> list:
    """(figure, value, unit, target text, met) rows; met None where the target is a comparison
    without a threshold or the figure was not measured."""
    def row(key, unit, target=None, test=None, value=None):
        v = r.get(key) if value is None else value
        met = None if (v is None or test is None) else bool(test(v))
        return (key, v, unit, target or "", met)

    gt_ekf = r["gtsam_ekf_us_per_sample"]
    rows = [
        row("preintegration_us_per_sample", "us", "<= 0.3", lambda v: v <= 0.3),
        row("preintegration_long_us_per_sample", "us"),
        row("preintegration_marginal_us_per_sample", "us"),
        row("preintegration_fixed_ms_per_call", "ms"),
        row("preintegration_one_thread_us_per_sample", "us"),
        row("preintegration_two_thread_gain", "x"),
        row("preintegration_without_covariance_us_per_sample", "us"),
        row("gtsam_preintegration_us_per_sample", "us"),
        row("gtsam_combined_preintegration_us_per_sample", "us"),
        row("preintegration_best_us_per_sample", "us"),
        row("gtsam_preintegration_best_us_per_sample", "us"),
        row("preintegration_speedup_vs_gtsam", "x", ">= 5", lambda v: v >= 5.0),
        row("preintegration_speedup_vs_gtsam_combined", "x"),
        row("ekf_us_per_sample", "us", f"<= gtsam ({gt_ekf:.2f})", lambda v: v <= gt_ekf),
        row("gtsam_ekf_us_per_sample", "us"),
        row("kitti_batch_s", "s", f"<= 1.5x native ({1.5 * r['kitti_native_s']:.2f})",
            lambda v: v <= 1.5 * r["kitti_native_s"]),
        row("kitti_native_s", "s"),
        row("kitti_rmse_m", "m", f"<= native ({r['kitti_native_rmse_m']:.2f})",
            lambda v: v <= r["kitti_native_rmse_m"]),
        row("kitti_native_rmse_m", "m"),
        row("kitti_whole_process_ratio", "x", "<= 1 (ours / native, whole process)", lambda v: v <= 1.0),
        row("batch_calibration_ratio", "x", "<= 1.5 (calibrating / not, 60 s, 3 sensors)", lambda v: v <= 1.5),
        row("batch_noise_ratio", "x", "<= 3 (the batch with its noise estimated / without, the calibrating 60-s rig)",
            lambda v: v <= 3.0),
        row("batch_noise_ratio_stated_wrong", "x", "none (the same rig stating its noise wrong: the fit iterates)"),
        row("batch_noise_stated_wrong_iterations", "", "its iterations"),
        row("batch_noise_s_per_data_s_60", "s/s", "the fit's time per second of data, 60 s"),
        row("batch_noise_s_per_data_s_120", "s/s", "the same at 120 s (linear: equal)"),
        row("batch_uncalibrated_s", "s"),
        row("batch_calibrated_s", "s"),
        row("online_loop_calibration_ratio", "x", "<= 1.2 (whole loop per keyframe, one calibrated sensor / none)",
            lambda v: v <= 1.2),
        row("online_loop_calibrated_ms_median", "ms"),
        row("online_loop_uncalibrated_ms_median", "ms"),
        row("online_update_calibration_ratio", "x", "<= 1.2 (the window's update alone)", lambda v: v <= 1.2),
        row("online_update_calibrated_ms_median", "ms"),
        row("online_update_uncalibrated_ms_median", "ms"),
        row("kitti_whole_process_s", "s"),
        row("kitti_native_whole_process_s", "s"),
        row("kitti_whole_process_floor_s", "s"),
        row("kitti_whole_process_floor_ratio", "x"),
    ]
    for run in r["scaling"]:
        rows.append((f"batch {run['minutes']:g} min: total s ({run['keyframes']} kf)", run["total_s"], "s", "", None))
        rows.append((f"batch {run['minutes']:g} min: ms / keyframe", run["ms_per_keyframe"], "ms", "", None))
        rows.append((f"batch {run['minutes']:g} min: ms / keyframe over {REFERENCE_MIN:g}-min run's",
                     run["relative_ms_per_keyframe"], "", "", None))
        if run.get("covariance_s") is not None:
            rows.append((f"batch {run['minutes']:g} min: covariances", run["covariance_s"], "s", "", None))
    rows += [
        row("scaling_ms_per_keyframe_spread", "", "<= 0.20 (max/min - 1)", lambda v: v <= 0.2),
        row("scaling_ms_per_keyframe_spread_across_runs", ""),
        row("scaling_fitted_growth", "", "<= 0.20 (trend, shortest to longest)", lambda v: abs(v) <= 0.2),
        row("scaling_fitted_growth_side_by_side", ""),
        row("hour_batch_s", "s", "< 60", lambda v: v < 60.0),
        row("fixed_lag_update_ms_median", "ms", "<= 2", lambda v: v <= 2.0),
        row("fixed_lag_update_ms_p99", "ms", "<= 10", lambda v: v <= 10.0),
        row("fixed_lag_update_ms_p99_worst_tenth", "ms", "<= 10", lambda v: v <= 10.0),
        row("fixed_lag_batch_update_ms_median", "ms"),
        row("fixed_lag_batch_update_ms_p99", "ms"),
        row("hour_peak_rss_mib", "MiB", "< 2048", lambda v: v < 2048.0),
        row("online_loop_ms_median", "ms", f"<= native ({r['native_fixed_lag_loop_ms_median']:.3f})",
            lambda v: v <= r["native_fixed_lag_loop_ms_median"]),
        row("online_loop_ms_p99", "ms", f"<= native ({r['native_fixed_lag_loop_ms_p99']:.3f})",
            lambda v: v <= r["native_fixed_lag_loop_ms_p99"]),
        row("native_fixed_lag_loop_ms_median", "ms"),
        row("native_fixed_lag_loop_ms_p99", "ms"),
        row("online_estimate_us", "us", "< 5", lambda v: v < 5.0),
        row("car_hour_all_s", "s", "<= 60 (every estimator, one hour of the car rig)", lambda v: v <= 60.0),
        row("car_hour_peak_rss_mib", "MiB", "<= 2048", lambda v: v <= 2048.0),
    ]
    scaling = r["car_scaling"]
    for name, growth in scaling["fitted_growth_side_by_side"].items():
        rows.append((f"car_scaling {name}: ms per s of data at {', '.join(f'{m:g}' for m in scaling['minutes'])} min",
                     " / ".join(f"{x:.3g}" for x in scaling["ms_per_data_s"][name]), "ms", "", None))
        rows.append(row(f"car_scaling {name}: fitted growth", "", "", value=scaling["fitted_growth"][name]))
        rows.append(row(f"car_scaling {name}: fitted growth side by side", "",
                        "<= 0.20 (shortest to longest, against 1-min runs)", lambda v: abs(v) <= 0.2, growth))
    live = r["car_online"]
    for figure, unit in (("online_keyframe_ms", "per keyframe"), ("online_wheel_message_ms", "per wheel message")):
        for stat in ("median_ms", "p99_ms"):
            rows.append(row(f"car_online {live['minutes']:g} min: loop {unit}, {stat[:-3]}", "ms",
                            value=live[figure][stat]))
    for stat in ("median_ms", "p99_ms"):
        rows.append(row(f"car_online: native loop per keyframe, {stat[:-3]}", "ms",
                        value=live["native_keyframe_ms"][stat]))
    method, ms = max(live["online_worst_call_ms"].items(), key=lambda item: item[1])
    rows.append(row(f"car_online: worst single call ({method})", "ms",
                    f"beside native's worst keyframe ({live['native_keyframe_ms']['max_ms']:.3g})", value=ms))
    speedup = r["car_keyframe_speedup"]
    for name in ("batch", "fixed-lag"):
        k = speedup[name]
        rows.append(row(f"car_keyframe_speedup {name}", "x", ">= 5 (every measurement / 10 Hz grid, 60 s)",
                        lambda v: v >= 5.0, k["speedup"]))
        rows.append(row(f"car_keyframe_speedup {name}: ATE change", "", "within 2 % (grid / every measurement - 1)",
                        lambda v: abs(v) <= 0.02, k["ate_change"]))
    return rows


def _fmt(v) -> str:
    if v is None:
        return "null"
    if isinstance(v, float):
        return f"{v:.4g}" if abs(v) < 1e5 else f"{v:.0f}"
    return str(v)


def print_table(r: dict) -> None:
    m = r["machine"]
    print(f"machine: {m['nproc']} CPUs, {m['cpu']}; python {m['python']}, numpy {m['numpy']}, "
          f"gtsam {m['gtsam']}; load average {m['loadavg']}")
    rows = _table_rows(r)
    width = max(len(name) for name, *_ in rows)
    print(f"{'figure':<{width}}  {'value':>10} {'unit':<4}  {'target':<28} met?")
    for name, value, unit, target, met in rows:
        ok = "" if met is None else ("yes" if met else "NO")
        print(f"{name:<{width}}  {_fmt(value):>10} {unit:<4}  {target:<28} {ok}")
    print()
    for key in ("preintegration_run", "ekf_run", "kitti_run", "kitti_whole_process_run"):
        print(f"{key}: {r[key]}")
    print(f"preintegration: GTSAM / ours = {r['preintegration_speedup_vs_gtsam']:.3g}; "
          f"EKF: ours / GTSAM = {r['ekf_ratio_vs_gtsam']:.3g} (GTSAM's NavStateImuEKF: 9-dim, predict only; "
          f"ours: 15-dim, predict + updates)")
    print(f"KITTI: ours / native time = {r['kitti_time_ratio']:.3g} (ours includes loading, "
          f"{r['kitti_load_s']:.2f} s; native excludes reading the files); native with the cumulative "
          f"bias count (GTSAM's Python example): {r['kitti_native_cumulative_rmse_m']:.3f} m; ours with the IMU "
          f"noise tuned to the used fixes' likelihood: {r['kitti_tuned_rmse_m']:.3f} m in {r['kitti_tuned_s']:.2f} s")
    print("batch scaling (each length in a fresh child process after a warm-up, repeated to ~15 min of data, "
          f"mean, with a {REFERENCE_MIN:g}-min run timed before and after each repetition; covariances=False, "
          "covariance time measured separately on the short runs):")
    for run in r["scaling"]:
        extra = ""
        if "peak_rss_mib" in run:
            after = ", ".join(f"{k} {v:.0f}" for k, v in run["peak_rss_mib_after"].items())
            extra = f", peak RSS {run['peak_rss_mib']:.0f} MiB (peak after {after} MiB)"
        print(f"  {run['minutes']:>5g} min (x{run['repeats']}): {run['keyframes']:>6} kf, build {run['build_s']:.2f} s "
              f"+ solve {run['solve_s']:.2f} s ({run['iterations']} it) = {run['total_s']:.2f} s, "
              f"{run['ms_per_keyframe']:.3f} ms/kf ({run['relative_ms_per_keyframe']:.2f}x the "
              f"{REFERENCE_MIN:g}-min run's {run['reference_ms_per_keyframe']:.3f}){extra}")
    for key in ("fixed_lag_incremental", "fixed_lag_batch"):
        f = r[key]
        print(f"fixed-lag {f['kind']} ({f['seconds']:g} s, lag {LAG_S:g} s, covariances=False): median "
              f"{f['median_ms']:.2f} ms, p99 {f['p99_ms']:.2f} ms, max {f['max_ms']:.1f} ms, {f['over_10ms']} of "
              f"{f['updates']} > 10 ms; per tenth of the run: median "
              f"{' '.join(f'{x:.2f}' for x in f['per_tenth_median_ms'])} ms, p99 "
              f"{' '.join(f'{x:.1f}' for x in f['per_tenth_p99_ms'])} ms")
    o = r["online_run"]
    for side in ("online", "native"):
        f = o[side]
        print(f"{side} fixed-lag whole loop per keyframe ({o['seconds']:g} s, {o['keyframes']} keyframes): median "
              f"{f['median_ms']:.3f} ms, p99 {f['p99_ms']:.3f} ms, max {f['max_ms']:.1f} ms; per tenth of the run: "
              f"median {' '.join(f'{x:.3f}' for x in f['per_tenth_median_ms'])} ms, p99 "
              f"{' '.join(f'{x:.2f}' for x in f['per_tenth_p99_ms'])} ms")
    print(f"online estimate() after every IMU sample between keyframes: median {o['online_estimate_us']:.2f} us, "
          f"p99 {o['online_estimate_us_p99']:.2f} us")
    print("car rig (100 Hz IMU, 83 Hz wheel speeds, 10 Hz GNSS, three calibrations; every estimator, each length in "
          "a fresh child process after a warm-up):")
    for run in r["car_scaling"]["runs"]:
        each = ", ".join(f"{n} {v:.2f} s" for n, v in run["runtime_s"].items())
        after = ", ".join(f"{k} {v:.0f}" for k, v in run["peak_rss_mib_after"].items())
        relative = ", ".join(f"{n} {v:.2f}x" for n, v in run["relative"].items())
        print(f"  {run['minutes']:>5g} min (x{run['repeats']}): all {run['all_s']:.2f} s ({each}; per second of data "
              f"against the 1-min runs beside it: {relative}), peak RSS {run['peak_rss_mib']:.0f} MiB (peak after "
              f"{after} MiB); ATE " + ", ".join(f"{n} {v:.3f} m" for n, v in run["ate_m"].items()))
    k = r["car_keyframe_speedup"]
    print(f"car rig, 60 s: {k['keyframes']['measurements']} keyframes at every measurement time against "
          f"{k['keyframes']['grid']} on the grid:")
    for name in ("batch", "fixed-lag"):
        f = k[name]
        print(f"  {name}: {f['every_measurement_s']:.3f} s against {f['grid_s']:.3f} s ({f['speedup']:.2f}x); ATE "
              f"{f['every_measurement_ate_m']:.4f} m against {f['grid_ate_m']:.4f} m ({100 * f['ate_change']:+.2f} %)")
    print(f"wall time of the benchmark: {r['benchmark_s']:.1f} s")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--quick", action="store_true", help="reduced set, a few minutes, no hour runs")
    parser.add_argument("--json", action="store_true", help="print JSON instead of the table")
    parser.add_argument("--whole-process", action="store_true",
                        help="only the whole-process KITTI figure (kitti_whole_process_ratio)")
    parser.add_argument("--car", action="store_true", help="only the car rig's figures (car_*), as JSON")
    parser.add_argument("--child-batch", type=float, metavar="MIN", help=argparse.SUPPRESS)
    parser.add_argument("--child-car", type=float, metavar="MIN", help=argparse.SUPPRESS)
    parser.add_argument("--covariances", action="store_true", help=argparse.SUPPRESS)
    parser.add_argument("--repeats", type=int, default=1, help=argparse.SUPPRESS)
    args = parser.parse_args()
    ensure_fresh_caches()  # before any kernel runs: an edited source's dependants compile again
    if args.child_batch is not None:  # internal: one batch run in a clean process (peak RSS)
        batch_run(10.0 / 60.0)  # warm-up: first calls, lazy imports, allocator
        print(json.dumps(batch_run(args.child_batch, args.covariances, memory=True, repeats=args.repeats)))
        return
    if args.child_car is not None:  # internal: the car rig's estimators in a clean process (peak RSS)
        car_all(car_rig(10.0))  # warm-up: first calls, lazy imports, allocator
        print(json.dumps(car_run(args.child_car, args.repeats)))
        return
    s = QUICK if args.quick else FULL
    if args.whole_process or args.car:
        result = {"machine": machine(), **(bench_kitti_process(s) if args.whole_process else bench_car(s))}
        print(json.dumps(result, indent=2))
        return
    tick = time.perf_counter()
    result = {"quick": args.quick, "machine": machine()}
    warm_up()
    if not args.json:
        print(f"[{time.perf_counter() - tick:6.1f} s] warm-up done (kernels compiled or loaded)", file=sys.stderr)
    for bench in (bench_preintegration, bench_ekf, bench_kitti, bench_kitti_process, bench_scaling, bench_fixed_lag,
                  bench_online, bench_calibration, bench_car):
        result.update(bench(s))
        if not args.json:
            print(f"[{time.perf_counter() - tick:6.1f} s] {bench.__name__} done", file=sys.stderr)
    result["benchmark_s"] = time.perf_counter() - tick
    if args.json:
        print(json.dumps(result, indent=2))
    else:
        print_table(result)


if __name__ == "__main__":
    main()
