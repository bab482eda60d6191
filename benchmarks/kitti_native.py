"""GTSAM's own KITTI IMU + GPS pipeline (native ImuFactor + GPSFactor) on the shipped example data,
solved in batch with Levenberg-Marquardt, next to this project's batch smoother on the same data.

The native graph follows GTSAM's IMUKittiExampleGPS: a keyframe at every GPS fix from the second
one on, PreintegratedImuMeasurements between consecutive fixes (each IMU sample integrated over the
dt ending at its own time stamp, as the example does), a BetweenFactorConstantBias per interval,
a GPS factor at every K-th fix (sigma sqrt(0.07) m) and the example's priors. The bias between
factor's sigma is sqrt(n) * metadata sigma with n either the samples of the interval ("interval",
as in the C++ original) or the running count since the start ("cumulative", as the Python example
counts it). A third native row replaces each ImuFactor and bias between factor by one
CombinedImuFactor with the same noise (the bias walk inside the IMU factor, correlated with the
navigation states: GTSAM's own version of this project's model, for comparison). Cholesky fails on
this graph (indeterminant system: the example's pose prior leaves the position free), so the linear
solver is QR.

Prints JSON and a table: held-out RMS position error against the GPS fixes not used, and wall
times (compute only: data loading excluded for native; our figure is load + build + solve). A
last row runs ours with the IMU noise first tuned to the maximum likelihood of the used fixes
(``smoother run --tune-noise``; the tuning's time included): the metadata's noise is far from
what this data shows.

``--native-only`` runs GTSAM's pipeline alone (``ImuFactor``, "interval"), importing nothing but
GTSAM and NumPy and reading the files as GTSAM's example does: the whole process of GTSAM's own
pipeline, which ``benchmarks/run.py`` times beside ``smoother run --dataset kitti --estimator batch``
(``kitti_whole_process_ratio``).

Run: python benchmarks/kitti_native.py [--gps-every 10] [--json] [--native-only]
"""
from __future__ import annotations

import argparse
import json
import time

import gtsam
import numpy as np
from gtsam.symbol_shorthand import B, V, X

# GTSAM's example data and constants (IMUKittiExampleGPS); datasets.kitti reads the same files with
# its checks, which this script imports only beside our own pipeline.
IMU_FILE, GPS_FILE, METADATA_FILE = ("KittiEquivBiasedImu.txt", "KittiGps_converted.txt",
                                     "KittiEquivBiasedImu_metadata.txt")
GPS_VARIANCE = 0.07


def native(gps_every: int, bias_count: str, factor: str = "imu") -> dict:
    """GTSAM's pipeline; ``factor`` "imu" (ImuFactor + bias between factor, ``bias_count`` as
    above) or "combined" (CombinedImuFactor, the walk's densities those of our model)."""
    meta = _raw_metadata()
    t_imu, dt_imu, acc, gyro = _raw_imu()
    t_gps, p_gps = _raw_gps()
    first = 1
    tick = time.perf_counter()
    if factor == "combined":
        from datasets import kitti
        from smoother.evaluation.native import combined_params

        params = combined_params(kitti.read_metadata().noise(), kitti.GRAVITY)
        pim_class = gtsam.PreintegratedCombinedMeasurements
    else:
        params = gtsam.PreintegrationParams.MakeSharedU(9.8)
        params.setAccelerometerCovariance(np.eye(3) * meta["AccelerometerSigma"]**2)
        params.setGyroscopeCovariance(np.eye(3) * meta["GyroscopeSigma"]**2)
        params.setIntegrationCovariance(np.eye(3) * meta["IntegrationSigma"]**2)
        pim_class = gtsam.PreintegratedImuMeasurements
    graph, values = gtsam.NonlinearFactorGraph(), gtsam.Values()
    pose0 = gtsam.Pose3(gtsam.Rot3(), p_gps[first])
    graph.add(gtsam.PriorFactorPose3(X(first), pose0, gtsam.noiseModel.Diagonal.Precisions([0, 0, 0, 1, 1, 1])))
    graph.add(gtsam.PriorFactorVector(V(first), np.zeros(3), gtsam.noiseModel.Isotropic.Sigma(3, 1000.0)))
    bias0 = gtsam.imuBias.ConstantBias()
    graph.add(gtsam.PriorFactorConstantBias(B(first), bias0, gtsam.noiseModel.Diagonal.Sigmas([0.1] * 3 + [5e-5] * 3)))
    gps_model = gtsam.noiseModel.Isotropic.Sigma(3, np.sqrt(GPS_VARIANCE))
    # Initial values: integrate forward from the previous keyframe's initial value (the example
    # seeds each keyframe with the previous estimate; a batch solve needs a whole trajectory).
    nav = gtsam.NavState(pose0, np.zeros(3))
    values.insert(X(first), pose0)
    values.insert(V(first), np.zeros(3))
    values.insert(B(first), bias0)
    used, heldout = [], []
    running = 0
    j = np.searchsorted(t_imu, t_gps[first], side="left")
    for i in range(first + 1, len(t_gps)):
        pim = pim_class(params, bias0)
        n = 0
        while j < len(t_imu) and t_imu[j] <= t_gps[i]:
            if t_imu[j] >= t_gps[i - 1]:
                pim.integrateMeasurement(acc[j], gyro[j], dt_imu[j])
                n += 1
            j += 1
        running += n
        count = n if bias_count == "interval" else running
        if factor == "combined":
            graph.add(gtsam.CombinedImuFactor(X(i - 1), V(i - 1), X(i), V(i), B(i - 1), B(i), pim))
        else:
            graph.add(gtsam.ImuFactor(X(i - 1), V(i - 1), X(i), V(i), B(i - 1), pim))
            sig = np.sqrt(max(count, 1)) * np.array([meta["AccelerometerBiasSigma"]] * 3
                                                       + [meta["GyroscopeBiasSigma"]] * 3)
            graph.add(gtsam.BetweenFactorConstantBias(B(i - 1), B(i), gtsam.imuBias.ConstantBias(),
                                                      gtsam.noiseModel.Diagonal.Sigmas(sig)))
        nav = pim.predict(nav, bias0)
        pose = nav.pose()
        if (i % gps_every) == 0:
            graph.add(gtsam.GPSFactor(X(i), p_gps[i], gps_model))
            pose = gtsam.Pose3(pose.rotation(), p_gps[i])
            nav = gtsam.NavState(pose, nav.velocity())
            used.append(i)
        else:
            heldout.append(i)
        values.insert(X(i), pose)
        values.insert(V(i), nav.velocity())
        values.insert(B(i), bias0)
    lm = gtsam.LevenbergMarquardtParams()
    lm.setLinearSolverType("MULTIFRONTAL_QR")
    lm.setMaxIterations(100)
    result = gtsam.LevenbergMarquardtOptimizer(graph, values, lm).optimize()
    elapsed = time.perf_counter() - tick
    est = np.array([result.atPose3(X(i)).translation() for i in heldout])
    distance = np.linalg.norm(est - p_gps[heldout], axis=1)
    return {"heldout_rmse_m": float(np.sqrt(np.mean(distance**2))), "compute_s": elapsed,
            "states": len(t_gps) - first, "errors": (t_gps[heldout], distance)}


def _raw_imu():
    """The IMU file as GTSAM's example reads it (time, dt, acc, gyro; first line's dt ignored)."""
    data = np.loadtxt(gtsam.findExampleDataFile(IMU_FILE), skiprows=1)
    return data[:, 0], data[:, 1], data[:, 2:5], data[:, 5:8]


def _raw_gps():
    """The GPS file as GTSAM's example reads it: times and positions (N, 3)."""
    data = np.loadtxt(gtsam.findExampleDataFile(GPS_FILE), delimiter=",", skiprows=1)
    return data[:, 0], data[:, 1:4]


def _raw_metadata() -> dict:
    """The metadata file as GTSAM's example reads it: its one line of values by the header's names."""
    path = gtsam.findExampleDataFile(METADATA_FILE)
    with open(path) as f:
        names = f.readline().split()
    return dict(zip(names, np.loadtxt(path, skiprows=1, ndmin=1).tolist()))


def ours(gps_every: int, tune_noise: bool = False) -> dict:
    """Our batch smoother, load + build + solve; with ``tune_noise`` the noise is first fitted to
    the data by the batch smoother (:func:`smoother.pipeline.tune_noise`; its time included)."""

    from datasets import kitti
    from smoother.batch.solve import solve_batch
    from smoother.evaluation import scoring as report
    from smoother.model.problem import build_problem
    from smoother.pipeline import tune_noise as tune

    tick = time.perf_counter()
    dataset = kitti.load_kitti(gps_every=gps_every)
    if tune_noise:
        dataset = tune(dataset)[1]
    problem = build_problem(dataset)
    result = solve_batch(problem, covariances=False)
    elapsed = time.perf_counter() - tick
    t, distance = report.position_errors(dataset.sensor("gps").heldout, result.trajectory)
    return {"heldout_rmse_m": float(np.sqrt(np.mean(distance**2))), "compute_s": elapsed,
            "states": len(problem.times), "errors": (t, distance)}


def paired_difference(ours_errors: tuple, native_errors: tuple, gps_every: int) -> dict:
    """Held-out RMS of ours minus native's on the same fixes, with a 95% block-bootstrap interval
    (:func:`smoother.evaluation.metrics.rmse_difference`): the held-out fixes between two used fixes form one
    block (their errors are correlated along the gap). Also counted: the gaps where ours is closer
    (mean squared distance)."""
    from datasets import kitti
    from smoother.evaluation import metrics

    (t_a, d_a), (t_b, d_b) = ours_errors, native_errors
    if t_a.shape != t_b.shape or not np.allclose(t_a, t_b, rtol=0, atol=1e-6):
        raise ValueError("the two pipelines were evaluated on different held-out fixes")
    t_gps = kitti.read_gps()[0]
    gap = np.searchsorted(t_gps, t_b - 1e-6) // gps_every  # fix index // K: the gap it lies in
    result = metrics.rmse_difference(d_a, d_b, gap)
    return {"rmse_difference_m": result["difference"], "ci95_m": list(result["interval"]),
            "blocks": result["blocks"], "fixes": int(len(d_a)), "gaps_where_ours_is_closer": result["blocks_a_lower"]}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--gps-every", type=int, default=10)
    parser.add_argument("--json", action="store_true")
    parser.add_argument("--native-only", action="store_true",
                        help="GTSAM's ImuFactor pipeline alone: prints its held-out RMS [m] and compute time [s]")
    args = parser.parse_args()
    if args.native_only:
        result = native(args.gps_every, "interval")
        print(f"{result['heldout_rmse_m']:.4f} {result['compute_s']:.3f}")
        return
    rows = {
        "native_interval": native(args.gps_every, "interval"),
        "native_cumulative": native(args.gps_every, "cumulative"),
        "native_combined": native(args.gps_every, "interval", factor="combined"),
        "ours_batch": ours(args.gps_every),
        "ours_batch_tuned_noise": ours(args.gps_every, tune_noise=True),
    }
    paired = {name: paired_difference(rows["ours_batch"]["errors"], rows[name]["errors"], args.gps_every)
              for name in ("native_interval", "native_combined")}
    for r in rows.values():
        del r["errors"]
    if args.json:
        print(json.dumps({**rows, "ours_batch_minus": paired}, indent=2))
        return
    print(f"KITTI, every {args.gps_every}th GPS fix used, held-out fixes evaluated")
    print(f"{'pipeline':<24}{'held-out RMS [m]':>18}{'time [s]':>10}{'states':>8}")
    for name, r in rows.items():
        print(f"{name:<24}{r['heldout_rmse_m']:>18.4f}{r['compute_s']:>10.2f}{r['states']:>8}")
    for name, p in paired.items():
        low, high = p["ci95_m"]
        print(f"ours_batch - {name}: {p['rmse_difference_m']:+.4f} m, 95% interval [{low:+.4f}, {high:+.4f}] "
              f"(block bootstrap over {p['blocks']} gaps between used fixes, {p['fixes']} fixes; ours closer "
              f"in {p['gaps_where_ours_is_closer']} of the gaps)")


if __name__ == "__main__":
    main()
