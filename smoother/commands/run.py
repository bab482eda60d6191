"""``smoother run``: run the estimators on a dataset, write trajectories, metrics and plots."""
from __future__ import annotations

import math
import sys
import time

from factors.threads import thread_count
from smoother.batch.methods import OPTIMIZERS
from smoother.errors import UserError, interruption
from smoother.estimators import ESTIMATORS
from smoother.fixed_lag.kinds import FIXED_LAG_KINDS


def register(sub) -> None:
    p = sub.add_parser("run", help="run batch, fixed-lag and/or EKF estimation on a dataset")
    p.add_argument("--dataset", default=None,
                   help="synthetic[:PROFILE] (gentle, tumbling, static), kitti, or euroc:PATH "
                        "(default synthetic:gentle)")
    p.add_argument("--rig", default=None, metavar="RIG.toml",
                   help="a recording of your own, described by a rig file (IMU, sensors, extrinsics; see the README)")
    p.add_argument("--estimator", default="all", choices=[*ESTIMATORS, "all"],
                   help="which estimator(s) to run (default all)")
    p.add_argument("--out", default="out", help="output directory (default ./out)")
    p.add_argument("--seed", type=int, default=0, help="random seed of the simulator and of synthetic measurements")
    p.add_argument("--duration", type=float, default=30.0, help="simulated duration [s] (default 30)")
    p.add_argument("--start", type=float, default=None, metavar="S",
                   help="with --rig: estimate from this many seconds after the recording's first IMU sample on "
                        "(self-initialised there)")
    p.add_argument("--end", type=float, default=None, metavar="S",
                   help="with --rig: estimate up to this many seconds after the recording's first IMU sample (fit a "
                        "rig's calibration and noise on one part, check its calibrated.toml on another)")
    p.add_argument("--lag", type=float, default=2.0, help="fixed-lag window [s] (default 2)")
    p.add_argument("--fixed-lag-kind", default="sliding", choices=list(FIXED_LAG_KINDS),
                   help="the compiled sliding window (default), GTSAM's IncrementalFixedLagSmoother (iSAM2) or "
                        "BatchFixedLagSmoother")
    p.add_argument("--max-delay", type=float, default=0.0, metavar="S",
                   help="fixed-lag: how late [s] a measurement may arrive behind the IMU stream and still be used "
                        "(a keyframe waits that long; one at or before the newest keyframe made is dropped and "
                        "counted; default 0)")
    p.add_argument("--realtime", action="store_true",
                   help="fixed-lag: replay the data at its own pace through the online smoother and report the "
                        "latency from each measurement's arrival to the updated estimate (median, p99, max)")
    p.add_argument("--speed", type=float, default=1.0,
                   help="with --realtime: replay this many times faster than recorded (default 1)")
    p.add_argument("--optimizer", default="lm", choices=list(OPTIMIZERS), help="batch optimiser (default lm)")
    p.add_argument("--max-iterations", type=int, default=100, metavar="N",
                   help="iterations of the batch optimiser at most (default 100); metrics.json's batch 'converged' "
                        "says whether it converged before them")
    p.add_argument("--keyframe-rate", type=float, default=None, metavar="HZ",
                   help="the smoothers' keyframes on a grid of this rate [Hz], the measurements between them attached "
                        "to the keyframe before them (default: 10 Hz where the measurements come faster, else a "
                        "keyframe at every measurement time)")
    p.add_argument("--robust", action="append", default=[], metavar="[SENSOR=]KERNEL[:T]",
                   help="robust kernel none|huber|cauchy|tukey, optionally with threshold, for every sensor or "
                        "the one named (a rig's names; the built-in datasets' pose, gps, ...); repeatable")
    p.add_argument("--correlation-time", action="append", default=[], metavar="SENSOR=SECONDS|fit",
                   help="the sensor's errors drift as a first-order Gauss-Markov process with this time constant, "
                        "its sigma their spread (every estimator models it but GTSAM's fixed-lag kinds; a rig's "
                        "correlation_time, which this overrides); 'fit': the time that best predicts half of its "
                        "held-out measurements, which the other half then judge; repeatable")
    p.add_argument("--ekf-gate", type=float, default=None, metavar="PROB",
                   help="EKF chi-square gate: reject innovations beyond this probability (e.g. 0.999)")
    p.add_argument("--outliers", type=float, default=0.0,
                   help="fraction of simulated pose measurements made gross outliers")
    p.add_argument("--gps-every", type=int, default=1,
                   help="use the GPS fixes whose number in the file is a multiple of K (as GTSAM's example), "
                        "hold out the rest (kitti)")
    p.add_argument("--pose-from-truth", type=float, nargs=3, metavar=("HZ", "POS_M", "ROT_RAD"),
                   help="pose measurements drawn from the ground truth")
    p.add_argument("--gps-from-truth", type=float, nargs=2, metavar=("HZ", "POS_M"),
                   help="position measurements drawn from the ground truth")
    p.add_argument("--estimate-noise", "--tune-noise", dest="estimate_noise", action="store_true",
                   help="estimate the IMU's four noise densities and every sensor's sigmas (per axis group) from the "
                        "data with the batch smoother (variance components), and run the other estimators with them "
                        "(a rig asks for some with estimate = [\"noise\"])")
    p.add_argument("--max-gyro-rate", type=float, default=None, metavar="RAD_S",
                   help="accept gyro data up to this rate [rad/s], as a 99th percentile and on each sample's axes "
                        "(default 35, 2000 deg/s: beyond it the data are refused as probably in deg/s)")
    p.add_argument("--no-covariance", action="store_true", help="skip marginal covariances (faster; no NEES)")
    p.add_argument("--plot", action="store_true", help="also write the plots (PNG) into the output directory")
    p.add_argument("--mcap", action="store_true",
                   help="also write estimates.mcap: the estimates as ROS 2 messages (Odometry, /tf, NavSatFix) for "
                        "Foxglove, ros2 bag and rosbags")
    p.add_argument("--progress", dest="progress", action="store_true", default=None, help="always show progress bars")
    p.add_argument("--no-progress", dest="progress", action="store_false", help="never show progress bars")
    p.set_defaults(handler=run)


def parse_robust(specs: list[str], types, defaults: dict | None = None) -> dict:
    """``["huber"]`` -> the same kernel for every sensor named in ``types``; ``["pose=cauchy:2"]``
    -> per sensor; over ``defaults`` (a rig file's per-sensor kernels). A sensor's own kernel
    holds, before or after one for every sensor (which the others take); two for one sensor (or
    two for every sensor) are a UserError: one of them would be dropped without a word."""
    from datasets.robust import robust_spec

    given: dict = {}  # per target (None: every sensor): (the spec, its kernel)
    for spec in specs:
        target, sep, kernel = spec.partition("=")
        if not sep:
            target, kernel = None, spec
        elif target not in types:
            raise UserError(f"--robust {spec}: unknown sensor {target!r}; expected one of {', '.join(types)}")
        if target in given:  # two kernels for one sensor: which was meant?
            whose = "every sensor" if target is None else f"sensor {target!r}"
            raise UserError(f"--robust {spec}: {whose} has a kernel already (--robust {given[target][0]}); give one "
                            "--robust per sensor (and at most one without a sensor, for the others)")
        try:
            given[target] = spec, robust_spec(kernel)
        except ValueError as error:
            raise UserError(f"--robust {spec}: {error}") from None  # a threshold's range is the rig key robust's
    out: dict = dict(defaults or {})
    if None in given:
        out.update((t, given[None][1]) for t in types)
    out.update((t, parsed) for t, (_, parsed) in given.items() if t is not None)
    return {k: v for k, v in out.items() if v is not None}


def with_correlation_times(specs: list[str], dataset):
    """``dataset`` with each ``SENSOR=SECONDS`` of ``specs`` (``--correlation-time``) as that sensor's
    :attr:`datasets.types.Sensor.correlation_time` (``SENSOR=fit``: to be fitted,
    :attr:`datasets.types.Sensor.fit_correlation_time`); a UserError naming the option for an
    unknown sensor, one of a relative kind, a value that is no number or outside the rig key's
    range, a fit without held-out measurements, or a sensor given twice."""
    from datasets.kinds import drift_problem
    from datasets.ranges import RANGES
    from datasets.rig import FIT

    seen: dict = {}
    for spec in specs:
        name, sep, value = spec.partition("=")
        if not sep:
            raise UserError(f"--correlation-time {spec}: expected SENSOR=SECONDS")
        if name not in dataset.sensor_names:
            raise UserError(f"--correlation-time {spec}: unknown sensor {name!r}; expected one of "
                            f"{', '.join(dataset.sensor_names)}")
        if name in seen:
            raise UserError(f"--correlation-time {spec}: sensor {name!r} has one already (--correlation-time "
                            f"{seen[name]}); give one per sensor")
        if (why := drift_problem(dataset.sensor(name).kind)) is not None:
            raise UserError(f"--correlation-time {spec}: {why}")
        seen[name] = spec
        if value == FIT:
            sensor = dataset.sensor(name)
            if sensor.heldout is None or sensor.data is None:
                raise UserError(f"--correlation-time {spec}: fitting it needs measurements of {name!r} used and held "
                                "out (a rig's every = K > 1, --gps-every K > 1): the used ones alone hardly tell it")
            dataset = dataset.with_sensor(name, correlation_time=None, fit_correlation_time=True)
            continue
        try:
            seconds = float(value)
        except ValueError:
            raise UserError(f"--correlation-time {spec}: expected a number of seconds or {FIT!r}, got {value!r}") \
                from None
        problem = RANGES["sensor.correlation_time"].problem(seconds)
        if problem is not None:
            raise UserError(f"--correlation-time {spec}: {problem}")
        dataset = dataset.with_sensor(name, correlation_time=seconds, fit_correlation_time=False)
    return dataset


def check_keyframe_rate(rate: float | None, dataset) -> None:
    """``--keyframe-rate`` at most the rate of the dataset's IMU (its median sample interval's
    inverse): a keyframe between two IMU samples has no IMU step of its own, and a grid finer than
    the samples multiplies the states (1 kHz on a 200 Hz IMU: five times the keyframes, for nothing)."""
    import numpy as np

    if rate is None or len(dataset.imu.t) < 2:
        return
    imu_rate = 1.0 / float(np.median(np.diff(dataset.imu.t)))
    if rate > imu_rate * (1.0 + 1e-9):
        raise UserError(f"--keyframe-rate: expected at most the IMU's rate, {imu_rate:.6g} Hz (a keyframe between "
                        f"two IMU samples has no IMU step of its own), got {rate!r}")


def keyframe_line(record: dict, given: bool) -> str:
    """The smoothers' keyframes in one line (:func:`smoother.model.timeline.keyframe_record`'s
    ``record``; ``given``: whether ``--keyframe-rate`` chose them)."""
    from smoother.model.timeline import EVERY_MEASUREMENT, KEYFRAME_RATE

    if record["rate_hz"] == EVERY_MEASUREMENT:
        line = f"keyframes: {record['count']}, one at every measurement time"
    else:
        line = f"keyframes: {record['count']} on a {record['rate_hz']:g} Hz grid"
    if not given:
        line += (f" (the default: a {KEYFRAME_RATE:g} Hz grid where measurements come faster; --keyframe-rate HZ "
                 "sets it)")
    if record["attached"]:
        line += (f"; {record['attached']} of {record['measurements']} measurements attached to the keyframe before "
                 f"them, at most {record['max_attached_distance_s']:.3g} s after it")
    if record["composed"] < record["relative"]:
        line += f"; {record['relative']} relative measurements composed into {record['composed']} between keyframes"
    return line


def run(args) -> int:
    from datasets.types import MAX_PLAUSIBLE_RATE, max_gyro_rate
    from smoother.commands import check_option

    if args.max_gyro_rate is not None:
        check_option("--max-gyro-rate", args.max_gyro_rate)
    # the whole run: datasets are re-made (measurements from truth, tuned noise) after loading
    with max_gyro_rate(MAX_PLAUSIBLE_RATE if args.max_gyro_rate is None else args.max_gyro_rate):
        return _run(args)


def _run(args) -> int:
    from smoother.commands import check_option, dataset_specs
    from smoother.commands.run_directory import RunDirectory
    from smoother.fixed_lag.lag import check_lag, check_lag_spans_keyframes
    from smoother.pipeline import ESTIMATORS, RunOptions

    for option in ("--seed", "--duration", "--outliers", "--gps-every", "--max-iterations", "--max-delay", "--speed"):
        check_option(option, getattr(args, option[2:].replace("-", "_")))
    for option, values, names in (("--pose-from-truth", args.pose_from_truth, ("HZ", "POS_M", "ROT_RAD")),
                                  ("--gps-from-truth", args.gps_from_truth, ("HZ", "POS_M"))):
        for value, name in zip(values or (), names):
            check_option(f"{option} {name}", value)
    check_lag(args.lag, "--lag", UserError)
    if args.realtime and args.estimator not in ("fixed-lag", "all"):
        raise UserError(f"--realtime replays through the fixed-lag smoother; it does not apply to --estimator "
                        f"{args.estimator}")
    if args.max_delay and args.estimator not in ("fixed-lag", "all"):
        raise UserError(f"--max-delay applies to the fixed-lag smoother, not to --estimator {args.estimator}")
    if args.speed != 1.0 and not args.realtime:
        raise UserError("--speed sets the pace of --realtime; give --realtime too")
    for option, value in (("--keyframe-rate", args.keyframe_rate), ("--ekf-gate", args.ekf_gate),
                          ("--start", args.start), ("--end", args.end)):
        if value is not None:  # left out: none
            check_option(option, value)
    if args.estimator in ("fixed-lag", "all"):  # before any estimator runs, naming the option
        check_lag_spans_keyframes(args.lag, args.keyframe_rate, "--lag", UserError)
    options = dataset_specs.SourceOptions(
        seed=args.seed, duration=args.duration, outliers=args.outliers, gps_every=args.gps_every,
        pose_from_truth=tuple(args.pose_from_truth) if args.pose_from_truth else None,
        gps_from_truth=tuple(args.gps_from_truth) if args.gps_from_truth else None,
    )
    names = list(ESTIMATORS) if args.estimator == "all" else [args.estimator]
    if args.rig is not None and args.dataset is not None:
        raise UserError("--rig and --dataset: give one of them")
    if args.rig is not None:  # options that shape a built-in dataset would be ignored silently
        for option, value, default in (("--duration", args.duration, 30.0), ("--outliers", args.outliers, 0.0),
                                       ("--gps-every", args.gps_every, 1),
                                       ("--pose-from-truth", args.pose_from_truth, None),
                                       ("--gps-from-truth", args.gps_from_truth, None)):
            if value != default:
                raise UserError(f"{option} shapes a built-in dataset, not a recording; with --rig, hold fixes out with "
                                "a sensor's `every` in the rig file" if option == "--gps-every" else
                                f"{option} shapes a built-in dataset, not a recording given by --rig")
    part = None if args.start is None and args.end is None else (args.start, args.end)
    if part is not None and args.rig is None:
        raise UserError("--start/--end take a part of a recording given by --rig, not of --dataset" if args.dataset
                        and not args.dataset.startswith("synthetic") else "--start/--end take a part of a recording "
                        "given by --rig; the simulator's length is --duration")
    if None not in (args.start, args.end) and args.end <= args.start:
        raise UserError(f"--start {args.start:g} --end {args.end:g}: expected the end after the start")
    if args.rig is not None:
        dataset, rig_robust = dataset_specs.load_rig_dataset(args.rig, part)
    else:
        dataset, rig_robust = dataset_specs.load(args.dataset or "synthetic:gentle", options), None
    check_keyframe_rate(args.keyframe_rate, dataset)
    dataset = with_correlation_times(args.correlation_time, dataset)
    robust = parse_robust(args.robust, dataset.sensor_names, rig_robust)
    run_options = RunOptions(
        lag_s=args.lag, fixed_lag_kind=args.fixed_lag_kind, optimizer=args.optimizer,
        max_iterations=args.max_iterations,
        keyframe_rate=args.keyframe_rate, robust=robust,
        ekf_gate=args.ekf_gate, covariances=not args.no_covariance, progress=args.progress,
        max_delay_s=args.max_delay, realtime=args.realtime, speed=args.speed,
        estimate_noise=("imu", *dataset.sensor_names) if args.estimate_noise else None,
        fixed_lag_beside=thread_count() >= 2,
    )
    with RunDirectory(args.out) as out:  # locked for the run, before any estimator starts
        return _estimate(args, dataset, names, run_options, out)


def _estimate(args, dataset, names: list[str], run_options, out) -> int:
    """Run the estimators ``names`` on ``dataset`` and write the run into ``out`` (a locked
    :class:`~smoother.commands.run_directory.RunDirectory`). An estimator that fails is reported
    (table, stderr, ``metrics.json``) and the others run; the exit code is then 2. Stopped early
    (Ctrl-C, SIGTERM) the finished estimators are written with ``stopped`` in ``metrics.json``,
    one line on stderr and the exit code 130 or 143."""
    from datasets.imu_health import findings_record
    from datasets.initialise import world_frame
    from datasets.kinds import sensors_of
    from smoother.diagnosis.calibration_report import calibration_lines, verdicts_for
    from smoother.diagnosis.misfit_causes import hints
    from smoother.diagnosis.noise_report import fitted_sensors, noise_lines
    from smoother.diagnosis.verdicts import consistency_lines, consistency_warnings
    from smoother.evaluation import scoring as report
    from smoother.model.timeline import keyframe_record
    from smoother.outputs import files
    from smoother.pipeline import (
        estimate_each,
        heldout_by_estimator,
        imu_followers,
        judged,
        run_doubts,
        verdicts_by_estimator,
    )

    part = args.start is not None or args.end is not None
    print(f"dataset {dataset.name}: {len(dataset.imu)} IMU samples over {dataset.t1 - dataset.t0:.1f} s"
          + (f" ({dataset.t0:.3f}-{dataset.t1:.3f} s after the recording's first IMU sample)" if part else ""),
          file=sys.stderr)
    started = time.perf_counter()
    imu_findings = imu_health(dataset)
    run_info = {"dataset": dataset.name, "seed": args.seed, "argv": sys.argv[1:], "imu": findings_record(imu_findings)}
    if part:  # the part of the recording estimated, as asked and as found
        run_info["part"] = {"start_s": args.start, "end_s": args.end, "t0": dataset.t0, "t1": dataset.t1}
    if {"batch", "fixed-lag"} & set(names):
        run_info["keyframes"] = keyframe_record(dataset, run_options.keyframe_rate)
        print(keyframe_line(run_info["keyframes"], given=run_options.keyframe_rate is not None), file=sys.stderr)
    estimates, record = {}, {}
    announce = lambda name: print(f"running {name} ...", file=sys.stderr)  # noqa: E731
    try:
        for name, estimate in estimate_each(dataset, names, run_options, keep_going=True, announce=announce,
                                            record=record):
            estimates[name] = estimate
            if estimate.failed is not None:
                print(f"{name} failed: {estimate.failed}", file=sys.stderr)
    except BaseException as error:  # keep what finished: an interruption
        if not estimates or not isinstance(error, KeyboardInterrupt):
            raise
        # as the finished estimators ran: the fitted correlation times, their held-out measurements the judging half
        return _stopped(args, out, record.get("dataset", dataset), _in_order(estimates, names),
                        {**run_info, **_fits_of(record)}, error)
    estimates = _in_order(estimates, names)
    dataset = record.get("dataset", dataset)  # as the estimators ran on it: the fitted noise, mountings as found
    run_info["mounting"] = record["mounting"].record() if "mounting" in record else {}
    if "noise" in record and "batch" not in estimates:  # the batch ran for the fit alone: the fit is the run's
        run_info["noise"] = record["noise"].record()
    fitted_times = record.get("correlation_fit", [])
    run_info.update(_fits_of(record))
    for finding in record["mounting"].wrong if "mounting" in record else ():
        print(f"warning: mounting: {finding.message}", file=sys.stderr)
    # what follows the estimators never costs their outputs: stopped, the finished estimates are written
    # without it; failed (out of memory, say), they are written, the failure said, and the run ends with 2
    try:
        consistency = verdicts_by_estimator(dataset, estimates, run_options)
        followers = imu_followers(dataset, record)
        judged(estimates, consistency, heldout_by_estimator(dataset, estimates), run_doubts(record), followers)
        baseline = report.interpolation_baseline(dataset)
        correlations = _calibration_correlations(dataset, estimates)
    except KeyboardInterrupt as error:
        return _stopped(args, out, dataset, estimates, run_info, error)
    except Exception as error:  # noqa: BLE001 -- any failure of the analysis; the estimates stand without it
        run_info["analysis_failed"] = " ".join(f"{type(error).__name__}: {error}".split())
        print(f"warning: the analysis after the estimators failed ({run_info['analysis_failed']}): the estimates are "
              "written without their verdicts", file=sys.stderr)
        consistency, baseline, correlations, followers = {}, None, {}, {}
    if baseline is not None:
        run_info["interpolated_fixes"] = baseline
    with out.outputs() as stage:
        run_info["total_s"] = time.perf_counter() - started
        metrics = _write_outputs(args, stage, dataset, estimates, run_info, correlations, followers)
    _say_removed(out)
    if args.plot:
        from smoother.outputs import plots

        with out.outputs(replace=False) as stage:
            figures = plots.plot_run(out.path, out_dir=stage)
        for path in figures:
            print(f"wrote {out.final(path)}", file=sys.stderr)
    print(format_table(metrics, dead_reckoning=not files.aiding_sensors(dataset),
                       frame_note=world_frame(sensors_of(dataset)).note(), rig=args.rig is not None))
    for name, m in metrics.items():
        if m.get("ate_note"):
            print(f"warning: {name}: {m['ate_note']}", file=sys.stderr)
    if baseline is not None:
        print(f"the used fixes interpolated, no IMU ({baseline['heldout_fixes']} held-out fixes between them): "
              f"held-out {baseline['gps_heldout_rmse_m']:.4f} m, horizontal "
              f"{baseline['gps_heldout_horizontal_rmse_m']:.4f} m, "
              f"vertical {baseline['gps_heldout_vertical_rmse_m']:.4f} m")
        note = interpolation_note(baseline, metrics, estimates, dataset)
        if note:
            print(f"note: {note}", file=sys.stderr)
    verdicts = {name: m.get("sensors", {}) for name, m in metrics.items()}
    for name, m in metrics.items():
        if m.get("calibration"):
            print(f"{name}:")
            for line in calibration_lines(m["calibration"], m.get("calibration_against_prior", {}),
                                          verdicts_for(name, verdicts), correlations.get(name), followers):
                print(f"  {line}")
    for fit in fitted_times:
        print(fit.line())
    if _noise(metrics, run_info):
        for line in noise_lines(_noise(metrics, run_info)):
            print(line)
    if args.rig is not None and (metrics.get("batch", {}).get("calibration") or _noise(metrics, run_info)
                                 or fitted_times):
        print(f"the rig with the batch's calibration and noise: {args.out}/calibrated.toml", file=sys.stderr)
    latency = estimates["fixed-lag"].details.get("latency_ms") if "fixed-lag" in estimates else None
    if latency is not None:
        print(f"fixed-lag latency, measurement arrival to updated estimate ({latency['measurements']} measurements): "
              f"median {latency['median']:.3g} ms, p99 {latency['p99']:.3g} ms, max {latency['max']:.3g} ms")
    # each estimator's verdicts as judged: its own and, beside them, its held-out predictions'
    for line in consistency_lines({name: est.details["sensors"] for name, est in estimates.items()
                                   if "sensors" in est.details}):
        print(line, file=sys.stderr)
    try:  # the outputs are written: Ctrl-C or SIGTERM here ends the run with them kept
        causes = hints(dataset, estimates, consistency, run_options.keyframe_rate, run_options.robust)
    except Exception as error:  # noqa: BLE001 -- advice only: the run stands without it
        print(f"warning: the fit of the sensors' likely calibrations failed ({type(error).__name__}: "
              f"{' '.join(str(error).split())}); no advice below", file=sys.stderr)
        causes = {}
    kinds = {s.name: s.kind for s in dataset.sensors}
    for line in consistency_warnings(consistency, imu_findings, causes, fitted_sensors(_noise(metrics, run_info)),
                                     kinds, followers, correlation_times=dataset.correlation_times):
        print(f"warning: {line}", file=sys.stderr)
    for name, est in estimates.items():
        if "doubtful" in est.details:
            print(f"warning: {name} is doubtful: {est.details['doubtful']}", file=sys.stderr)
    failed = [name for name, est in estimates.items() if est.failed is not None]
    print(f"outputs in {args.out}/", file=sys.stderr)
    if failed:
        print(f"{', '.join(failed)} failed (why: above and in metrics.json)", file=sys.stderr)
    return 2 if failed or "analysis_failed" in run_info else 0


def _stopped(args, out, dataset, estimates: dict, run_info: dict, error: KeyboardInterrupt) -> int:
    """Ctrl-C or SIGTERM (``error``) after ``estimates`` finished: write them (without what was
    still to be computed of them) with ``stopped`` in ``metrics.json``, say so, and return the exit
    code."""
    stopped, code = interruption(error)
    with out.outputs() as stage:
        _write_outputs(args, stage, dataset, estimates, {**run_info, "stopped": stopped})
    _say_removed(out)
    print(f"smoother: {stopped}: wrote the finished estimators ({', '.join(estimates)}) to {args.out}; "
          f"metrics.json says stopped: {stopped}", file=sys.stderr)
    return code


def _calibration_correlations(dataset, estimates: dict) -> dict:
    """``{estimator: {sensor: rho}}``: the lag-one correlation of each calibrated position
    sensor's residuals at the estimator's calibration (:func:`smoother.evaluation.scoring.residual_correlation`;
    None for other kinds)."""
    from smoother.evaluation import scoring as report

    return {name: {s: report.residual_correlation(dataset, est.trajectory, est.calibration, s, est.following)
                   for s in est.details.get("calibration", {})}
            for name, est in estimates.items() if est.details.get("calibration")}


def _write_outputs(args, stage, dataset, estimates: dict, run_info: dict, correlations: dict | None = None,
                   followers: dict | None = None) -> dict:
    """The run's files (:func:`smoother.outputs.files.write_outputs`) and, with ``--mcap``, its MCAP
    (:func:`smoother.outputs.mcap.write_mcap`), into the staging folder ``stage``; the metrics.
    ``calibrated.toml`` carries, as a caution beside a sensor's values, what the batch's verdict
    on it, its ``correlations`` (:func:`_calibration_correlations`) and its errors' following the
    IMU's (``followers``, :func:`smoother.pipeline.imu_followers`) say of them
    (:func:`smoother.diagnosis.calibration_report.fit_note`)."""
    from smoother.outputs import files
    from smoother.outputs.layout import CALIBRATED_RIG, MCAP

    metrics = files.write_outputs(stage, dataset, estimates, run_info)
    if args.mcap:
        from smoother.outputs.mcap import write_mcap

        write_mcap(stage / MCAP, dataset, estimates)
    records = metrics.get("batch", {}).get("calibration") or {}
    noise = _noise(metrics, run_info)
    fitted = tuple(run_info.get("correlation_fit", ()))
    if args.rig is not None and (records or noise or fitted):
        from datasets.atomic import atomic_write
        from datasets.rig import load_rig
        from datasets.rig_writer import calibrated_rig_text
        from smoother.diagnosis.calibration_report import fit_note

        verdicts, rhos = metrics["batch"].get("sensors", {}), (correlations or {}).get("batch", {})
        cautions = {s: fit_note(verdicts.get(s), rhos.get(s), (followers or {}).get(s)) for s in records}
        with atomic_write(stage / CALIBRATED_RIG, "w") as handle:
            handle.write(calibrated_rig_text(load_rig(args.rig), records, cautions, noise,
                                             dataset.correlation_times, fitted))
    return metrics


def _noise(metrics: dict, run_info: dict) -> dict | None:
    """The run's noise fit as ``metrics.json`` records it: the batch smoother's (``batch.noise``),
    or, where the batch ran only to fit it for the estimators asked for, the run's (``run_info``,
    written as ``_run.noise``); None without a fit."""
    return metrics.get("batch", {}).get("noise") or run_info.get("noise")


def _fits_of(record: dict) -> dict:
    """``{"correlation_fit": {sensor: record}}`` of the correlation times the run fitted
    (:class:`smoother.diagnosis.correlation_fit.CorrelationFit`), for ``metrics.json``'s ``_run``;
    ``{}`` without one."""
    fits = record.get("correlation_fit", [])
    return {"correlation_fit": {fit.sensor: fit.record() for fit in fits}} if fits else {}


def _in_order(estimates: dict, names: list[str]) -> dict:
    """``estimates`` in the order the estimators were asked for (the EKF runs before the batch)."""
    return {name: estimates[name] for name in names if name in estimates}


def imu_health(dataset) -> list:
    """The findings about the dataset's IMU itself (:func:`datasets.imu_health.inspect_imu`), each
    printed as a ``warning: imu:`` line."""
    import numpy as np

    from datasets.imu_health import inspect_imu

    findings = inspect_imu(dataset.imu.t, dataset.imu.acc, dataset.imu.gyro, float(np.linalg.norm(dataset.gravity)))
    for finding in findings:
        print(f"warning: imu: {finding.message}", file=sys.stderr)
    return findings


def _say_removed(out) -> None:
    """Name on stderr the previous run's files the last write into ``out`` deleted."""
    if out.removed:
        print(f"removed the previous run's {', '.join(out.removed)} from {out.path} (a run directory holds one run)",
              file=sys.stderr)


def interpolation_note(baseline: dict, metrics: dict, estimates: dict, dataset) -> str | None:
    """When interpolating the used fixes beats every smoother's held-out RMSE: why that need not
    mean the smoothers are less accurate (the best smoother's residuals at consecutive used fixes,
    :func:`smoother.evaluation.scoring.residual_correlation`)."""
    from smoother.evaluation import scoring as report

    smoothers = {name: metrics[name].get("gps_heldout_rmse_m") for name in ("batch", "fixed-lag") if name in metrics}
    smoothers = {name: v for name, v in smoothers.items() if v is not None and math.isfinite(v)}
    if not smoothers or min(smoothers.values()) <= baseline["gps_heldout_rmse_m"]:
        return None
    best = min(smoothers, key=smoothers.get)
    rho = report.residual_correlation(dataset, estimates[best].trajectory, estimates[best].calibration,
                                      following=estimates[best].following)
    if rho is None:
        return None
    return (f"interpolating the used fixes scores better on the held-out fixes than the smoothers; {best}'s "
            f"residuals at consecutive used fixes correlate {rho:.2f} (0 for white GNSS noise): "
            + ("the receiver's error drifts slowly over the fix spacing, and interpolation follows it. The held-out "
               "RMSE then measures agreement with that drift, not accuracy: compare with an independent reference "
               "(smoother evaluate), hold out fixes further apart, or model the drift (correlation_time)"
               if rho > 0.2 else
               "the fixes look independent: check the IMU noise, the sensors' sigmas, extrinsics and time offsets"))


#: The table's cell for a figure against the truth that is not scored (metrics.json: ``ate_note``).
UNSCORED = "unscored"
#: The figures that :func:`smoother.evaluation.scoring.against_truth` leaves unscored together.
TRUTH_FIGURES = ("ate_rmse_m", "rot_rmse_deg", "nees_mean")


def format_table(metrics: dict, dead_reckoning: bool = False, frame_note: str | None = None,
                 rig: bool = False) -> str:
    """One line per estimator with the headline metrics that exist; a figure against the truth
    that is not scored (too few states compared, metrics.json's ``ate_note``) shows
    :data:`UNSCORED`, and a closing line says so. Against GPS, two closing lines: the estimators
    ranked by their held-out RMSE (an accuracy), and what the fit residual is -- the distance to
    fixes an estimator used, which no ranking may rest on. With ``dead_reckoning`` (no aiding
    sensor) a closing line says that the estimates are the IMU's alone; ``frame_note``
    (:meth:`datasets.initialise.WorldFrame.note`) closes an odometry-frame run's table. Without
    held-out fixes the table says how to hold some out: ``every`` in a ``rig`` file, else
    ``--gps-every`` (which a rig run refuses)."""
    columns = [("ate_rmse_m", "ATE [m]"), ("rot_rmse_deg", "rot [deg]"), ("nees_mean", "NEES/dim"),
               ("gps_heldout_rmse_m", "held-out [m]"), ("gps_fit_residual_m", "fit resid [m]"),
               ("runtime_s", "time [s]")]
    present = [(k, h) for k, h in columns if any(k in m for m in metrics.values())]
    def finite(v) -> bool:
        return v is not None and math.isfinite(v)

    lines = [f"{'estimator':<14}" + "".join(f"{h:>14}" for _, h in present)]
    unscored = [name for name, m in metrics.items() if m.get("ate_note") and not finite(m.get("ate_rmse_m"))]
    for name, m in metrics.items():
        if "failed" in m:
            lines.append(f"{name:<14}  failed: {m['failed']}")
            continue
        shown, name = name, name + " (?)" if "doubtful" in m else name
        cells = []
        for k, _ in present:
            v = m.get(k, math.nan)
            cell = f"{v:.4f}" if finite(v) else UNSCORED if shown in unscored and k in TRUTH_FIGURES else "-"
            cells.append(f"{cell:>14}")
        lines.append(f"{name:<14}" + "".join(cells))
    if unscored:
        lines.append(f"{UNSCORED}: {', '.join(unscored)} compared with the truth at too few states or over too little "
                     "of the run (the warning below; metrics.json: ate_note)")
    if any(k == "gps_fit_residual_m" for k, _ in present):
        heldout = {name: m.get("gps_heldout_rmse_m") for name, m in metrics.items()}
        heldout = {name: v for name, v in heldout.items() if v is not None and math.isfinite(v)}
        if heldout:
            lines.append("ranked by held-out RMSE: " + " < ".join(sorted(heldout, key=heldout.get)))
        else:
            how = "a sensor's every = K > 1 in the rig file" if rig else "--gps-every K > 1"
            lines.append(f"no held-out fixes: no ranking (hold fixes out with {how})")
        lines.append("fit resid: RMS distance to the fixes the estimators used -- a residual, not an accuracy")
    if any("doubtful" in m for m in metrics.values()):
        lines.append("(?): doubtful -- the estimate does not fit its own data (the warning below says how far)")
    if dead_reckoning:
        lines.append("dead reckoning: no aiding sensor, the IMU alone; the errors grow without bound "
                     "(metrics.json: _run.dead_reckoning)")
    if frame_note:
        lines.append(frame_note)
    return "\n".join(lines)
