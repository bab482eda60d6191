"""Running the estimators on a dataset: one call per estimator, one result type for all.

``batch`` (the whole graph), ``fixed-lag`` (GTSAM's fixed-lag smoother fed the data in order of
arrival, :func:`smoother.online.replay.replay`; each keyframe's estimate when it leaves the window, i.e.
smoothed over the lag) and ``ekf`` (the primer's filter) see the same dataset; the two smoothers
have the same keyframes and factors (:func:`smoother.model.problem.build_problem`; the online smoother
makes them as the data arrive), so their differences are the estimators', not the model's.
"""
from __future__ import annotations

import multiprocessing
import os
import signal
import threading
import time
import warnings
from collections.abc import Callable, Iterator
from dataclasses import dataclass, replace
from typing import TYPE_CHECKING

import numpy as np

from datasets.types import Dataset, Trajectory
from factors.errors import BoxplusError, InputError, SolverError
from factors.threads import interrupts_held
from smoother.batch.solve import solve_batch, warn_not_converged
from smoother.diagnosis.calibration_report import calibration_records
from smoother.diagnosis.heldout import heldout_predictions
from smoother.diagnosis.heldout_correlated import batch_predictions, predicts_correlated
from smoother.diagnosis.residual_consistency import smoother_consistency
from smoother.ekf.calibrated import run_calibrated_ekf
from smoother.ekf.filter import run_ekf
from smoother.errors import NotConverged
from smoother.estimators import ESTIMATORS
from smoother.fixed_lag.kinds import GTSAM_KINDS
from smoother.model.between import Following
from smoother.model.correlated import with_correlated_errors
from smoother.model.covariances import joint_blocks
from smoother.model.problem import build_problem, calibration_set, measurement_blocks
from smoother.model.timeline import keyframe_times
from smoother.online import warm_up as kernel_warm_up

if TYPE_CHECKING:
    from smoother.batch.variance_components import GroupFit


@dataclass
class Estimate:
    """One estimator's trajectory (with covariances where computed) and wall time [s]; the EKF's
    carries its :class:`smoother.ekf.filter.Innovations`. An estimator that failed (``failed``: why, one
    line) has no trajectory."""

    name: str
    trajectory: Trajectory | None
    runtime_s: float
    details: dict
    innovations: object = None
    failed: str | None = None
    #: Per-sensor verdicts computed with the estimate (the batch's, which need its joint covariances).
    consistency: dict | None = None
    #: The calibrations it estimated (:class:`factors.calibration.CalibrationSet`), if any.
    calibration: object = None
    #: The noise it fitted (:class:`smoother.batch.variance_components.NoiseFit`), if any.
    noise: object = None
    #: Each keyframe's next with their joint covariance (:class:`smoother.model.between.Following`),
    #: where the estimator has them (the smoothers'): a state between keyframes is bridged between
    #: both (:func:`smoother.model.between.states_between`).
    following: object = None
    #: The held-out measurements as the estimator predicted them itself, per sensor (the EKF's,
    #: :class:`smoother.model.predicted.HeldoutPrediction`), where it does.
    heldout: object = None


@dataclass
class RunOptions:
    """Options shared by the estimators (the command line's flags)."""

    lag_s: float = 2.0
    fixed_lag_kind: str = "sliding"
    optimizer: str = "lm"
    max_iterations: int = 100
    keyframe_rate: float | str | None = None  # smoother.model.timeline.keyframe_rate
    robust: dict | None = None
    ekf_gate: float | None = None  # chi-square gate probability
    covariances: bool = True
    progress: bool | None = None
    max_delay_s: float = 0.0  # how late a measurement may arrive behind the IMU (fixed-lag)
    realtime: bool = False  # fixed-lag: replay at the data's own pace (times ``speed``)
    speed: float = 1.0
    #: The noise groups the batch smoother estimates ("imu" and sensors' names): None for what the
    #: dataset asks (:attr:`datasets.types.Dataset.noise_to_estimate`), ``()`` for none.
    estimate_noise: tuple | None = None
    #: Sensors whose fitted noise is applied however near the rig's value it settles
    #: (:func:`smoother.batch.variance_components.estimate_noise`'s ``profiled``): those whose
    #: correlation time the run fits, so that the fit's score is continuous in the time.
    profiled_noise: tuple = ()
    #: Run the fixed-lag smoother in a second process beside the others (:func:`estimate_each`):
    #: what ``smoother run`` does where it may use two threads or more; not for runs that are
    #: already one of many processes (Monte Carlo, a fleet).
    fixed_lag_beside: bool = False


def run_estimators(dataset: Dataset, names, options: RunOptions = RunOptions(),
                   keep_going: bool = False) -> dict[str, Estimate]:
    """Run each estimator in ``names`` (a subset of :data:`smoother.estimators.ESTIMATORS`) on ``dataset``, in the
    order of ``names`` (:func:`estimate_each`)."""
    return dict(estimate_each(dataset, names, options, keep_going))


def estimate_each(dataset: Dataset, names, options: RunOptions = RunOptions(), keep_going: bool = False,
                  announce: Callable[[str], None] | None = None,
                  record: dict | None = None) -> Iterator[tuple[str, Estimate]]:
    """Run the estimators ``names`` on ``dataset`` and yield ``(name, Estimate)`` as each finishes,
    so that a caller keeps what finished when a later one is interrupted. ``announce(name)`` is
    called as each starts.

    Before any estimator, each sensor's mounting is checked in closed form against what the IMU
    observes (:func:`smoother.diagnosis.mounting.check_mountings`); a sensor found turned that
    asks for its rotation to be estimated starts from the data's rotation instead of the rig's
    (:func:`mounted_as_found`). The batch smoother starts from the EKF's estimate
    (:func:`smoother.model.problem.build_problem`'s ``start``): the EKF runs first when both are
    asked for, and otherwise for the batch alone (its time counted in the batch's); where the EKF
    fails, from dead reckoning. ``details["start"]`` says which. With noise to estimate
    (:attr:`RunOptions.estimate_noise`) the batch smoother runs first and fits it
    (:mod:`smoother.batch.variance_components`; a batch not asked for runs for it all the same,
    not yielded), and the other estimators run on the data with the fitted noise. Before all of
    them, the correlation times the dataset asks to fit are fitted (:func:`_correlation_fitted`,
    batch runs of their own; those sensors' noise fitted without the pull to the rig's value,
    :attr:`RunOptions.profiled_noise`), and every estimator runs with them. ``record``, if given, receives
    ``mounting`` (the check), ``noise`` (the fit, kept honest by
    :func:`smoother.diagnosis.noise_honesty.honest`), ``correlation_fit`` (the correlation times'
    fits, :class:`smoother.diagnosis.correlation_fit.CorrelationFit`) and ``dataset`` (what the
    estimators ran on).
    ``keep_going``: an estimator that fails yields an :class:`Estimate` with ``failed`` set (its
    error in one line) and the others still run; otherwise its exception propagates. While the
    others run, the sliding window's kernels compile in a second process when they are not on disk
    yet (:mod:`smoother.online.warm_up`). With :attr:`RunOptions.fixed_lag_beside` the fixed-lag
    smoother, which needs nothing of the others, runs in a second process while they run here
    (:class:`_Beside`; not when it needs the batch's fitted noise or paces a replay in
    real time), compiling its kernels there where they are not on disk, and is yielded last; its
    warnings are issued here when it ends, its progress bar is not shown."""
    from smoother.diagnosis.mounting import check_mountings

    unknown = [n for n in names if n not in ESTIMATORS]
    if unknown:
        raise InputError(f"unknown estimator(s) {unknown}; expected {', '.join(ESTIMATORS)}")
    record = {} if record is None else record
    mounting = check_mountings(dataset)
    dataset = record["dataset"] = mounted_as_found(dataset, mounting)
    record["mounting"] = mounting
    noise = dataset.noise_to_estimate if options.estimate_noise is None else tuple(options.estimate_noise)
    both = "ekf" in names and "batch" in names
    if noise:
        order = ["batch", *(n for n in names if n != "batch")]
    else:
        order = ["ekf", *(n for n in names if n != "ekf")] if both else list(names)
    ekf: Estimate | None = None
    warm_up = beside = start = None  # start: the batch's, where the correlation times' fit chose it
    try:
        if dataset.correlation_to_fit:
            # the sensors' sigmas are profiled over the time, in the candidates and in the run they choose
            options = replace(options, profiled_noise=(*options.profiled_noise, *dataset.correlation_to_fit))
            if announce is not None:
                announce(f"batch for the correlation time of {', '.join(dataset.correlation_to_fit)}")
            dataset, start = _correlation_fitted(dataset, options, noise, mounting, record)
            record["dataset"] = dataset
        if options.fixed_lag_beside and "fixed-lag" in order and len(order) > 1 and not noise and not options.realtime:
            order.remove("fixed-lag")  # and its kernels, where they are to compile, compile there
            if announce is not None:
                announce("fixed-lag (beside the others, in a second process)")
            with interrupts_held():  # a stop meanwhile comes once the process is known, to be stopped
                beside = _Beside(dataset, options)
        warm_up = kernel_warm_up.start(order, options.fixed_lag_kind)  # None unless its kernels are to compile
        for name in order:
            if announce is not None:
                announce(name)
            if name == "fixed-lag" and warm_up is not None:
                warm_up.wait()
            tick = time.perf_counter()
            try:
                if name == "batch":
                    estimate = _batch(dataset, options, start or ekf, noise, mounting)
                    if estimate.noise is not None:
                        record["noise"] = estimate.noise
                        dataset = record["dataset"] = estimate.noise.applied(dataset)
                else:
                    estimate = _fixed_lag(dataset, options) if name == "fixed-lag" else _ekf(dataset, options)
                    if "noise" in record:
                        estimate.details["noise_from"] = "batch"
            except Exception as error:
                if not keep_going:
                    raise
                estimate = Estimate(name, None, time.perf_counter() - tick, {}, failed=_one_line(error))
            if name == "ekf":
                ekf = estimate
            if name in names:
                yield name, estimate
        if beside is not None:
            yield "fixed-lag", beside.result(keep_going)
    finally:
        if warm_up is not None:
            warm_up.close()
        if beside is not None:
            beside.close()


class _Beside:
    """:func:`_fixed_lag` running in a second process, without its progress bar: forked where
    the platform can (the dataset is not copied until written), its result and warnings sent back
    through a pipe."""

    def __init__(self, dataset: Dataset, options: RunOptions):
        context = multiprocessing.get_context("fork" if "fork" in multiprocessing.get_all_start_methods() else "spawn")
        self._results, sending = context.Pipe(duplex=False)
        self._started = time.perf_counter()
        quiet = replace(options, progress=False)
        self._process = context.Process(target=_fixed_lag_sent, args=(self._results, sending, dataset, quiet),
                                        daemon=True)
        self._process.start()
        sending.close()

    def result(self, keep_going: bool) -> Estimate:
        """Its :class:`Estimate` once it ends, its warnings issued here; a failure as
        :func:`estimate_each` treats any estimator's (a process that died without a word, too); an
        interruption there raised here."""
        try:
            outcome = self._results.recv()
        except EOFError:
            self._process.join()
            outcome = ("failed", RuntimeError(f"its process ended with exit code {self._process.exitcode}"))
        if outcome[0] == "failed":
            if not keep_going or not isinstance(outcome[1], Exception):  # an interruption is one here too
                raise outcome[1]
            return Estimate("fixed-lag", None, time.perf_counter() - self._started, {}, failed=_one_line(outcome[1]))
        _, estimate, caught = outcome
        for message, category in caught:
            warnings.warn(message, category, stacklevel=2)
        return estimate

    def close(self) -> None:
        """Stop it where it has not ended (an interruption, an estimator's failure here): SIGTERM,
        which ends it at once (:func:`_fixed_lag_sent`), SIGKILL if it has not ended a second later."""
        if self._process.is_alive():
            self._process.terminate()
            self._process.join(1.0)
            if self._process.is_alive():
                self._process.kill()
        self._process.join()
        self._results.close()


def _fixed_lag_sent(receiving, sending, dataset: Dataset, options: RunOptions) -> None:
    """In the second process: :func:`_fixed_lag_with_warnings`, its outcome sent through
    ``sending``: ``("done", estimate, warnings)`` or ``("failed", exception)``. A forked process
    holds copies of its parent's handlers and files. Its parent decides when it stops: Ctrl-C,
    which a terminal sends to both, is ignored here (the parent, interrupted, ends it), and SIGTERM,
    which the parent sends, ends it at once (the parent's handler would make it a Python
    exception, which would then wait to be sent; until this function runs, the handlers are the
    parent's :func:`factors.threads.interrupts_held`'s, which only record). Its copy of the pipe's
    reading end is closed (else a send to a parent that is gone would wait for ever), and a watch
    ends it when the parent is gone (killed: nothing would read what it computes)."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    signal.signal(signal.SIGTERM, signal.SIG_DFL)
    receiving.close()
    parent = os.getppid()
    threading.Thread(target=_end_with, args=(parent,), daemon=True).start()
    try:
        estimate, caught = _fixed_lag_with_warnings(dataset, options)
        outcome = ("done", estimate, caught)
    except BaseException as error:  # noqa: BLE001 -- any end, an interruption too, is told to the waiting process
        outcome = ("failed", error)
    try:
        sending.send(outcome)
    except Exception as error:  # noqa: BLE001 -- an outcome that does not pickle is told as a failure
        sending.send(("failed", RuntimeError(f"its result could not be sent back ({type(error).__name__}: {error})")))
    finally:
        sending.close()


#: How often the second process looks whether its parent is still there [s].
PARENT_WATCH_S = 0.5


def _end_with(parent: int) -> None:
    """End this process once its parent (process ``parent``) is gone."""
    while os.getppid() == parent:
        time.sleep(PARENT_WATCH_S)
    os._exit(1)


def _fixed_lag_with_warnings(dataset: Dataset, options: RunOptions) -> tuple[Estimate, list]:
    """:func:`_fixed_lag` and the warnings it issued, ``(message, category)`` each, to be issued
    again in the process that waits for it."""
    with warnings.catch_warnings(record=True) as caught:
        estimate = _fixed_lag(dataset, options)
    return estimate, [(str(w.message), w.category) for w in caught]


def tune_noise(dataset: Dataset, which=None, options: RunOptions = RunOptions()):
    """The noise of ``dataset`` fitted to its data by the batch smoother
    (:mod:`smoother.batch.variance_components`; ``which``: the groups, by default the IMU and every
    aiding sensor), kept honest (:func:`smoother.diagnosis.noise_honesty.honest`):
    ``(fit, dataset with the fitted noise)``. What ``smoother run --estimate-noise`` runs first."""
    from datasets.kinds import sensors_of

    which = ("imu", *(s.name for s in sensors_of(dataset))) if which is None else tuple(which)
    estimate = _batch(dataset, options, None, which, None)
    return estimate.noise, estimate.noise.applied(dataset)


def mounted_as_found(dataset: Dataset, mounting) -> Dataset:
    """``dataset`` with each sensor whose mounting the check found wrong and that asks for its
    rotation to be estimated turned to the data's rotation (its measurements' ``T_BS``, and so its
    calibration's start and prior mean): a linearised calibration cannot leave a quarter or a half
    turn from the rig's. The lever arm stays the rig's."""
    turned = {f.sensor: f.R_data for f in mounting.wrong}
    if not turned:
        return dataset
    sensors = []
    for s in dataset.sensors:
        if s.name in turned and s.calibrate is not None and "rotation" in s.calibrate.parts:
            T = np.array(s.data.T_BS if s.data.T_BS is not None else np.eye(4), dtype=float)
            T[:3, :3] = turned[s.name]
            s = replace(s, data=replace(s.data, T_BS=T),
                        heldout=None if s.heldout is None else replace(s.heldout, T_BS=T))
        sensors.append(s)
    return replace(dataset, sensors=tuple(sensors))


def _one_line(error: Exception) -> str:
    """An estimator's failure in one line: the project's own errors by their message, anything else
    by its type too."""
    text = " ".join(str(error).split())
    return text if isinstance(error, BoxplusError) else f"{type(error).__name__}: {text}"


def _ekf(dataset: Dataset, options: RunOptions) -> Estimate:
    """The EKF; with calibrations asked for, with them as augmented states (:mod:`smoother.ekf.calibrated`).
    It updates at every measurement time and keeps its state at the smoothers' keyframes
    (:func:`smoother.model.timeline.keyframe_times`: every measurement time where they are no
    denser than the grid, else the grid, the held-out times and the ends)."""
    calibrations = calibration_set(dataset)
    kept_at = keyframe_times(dataset, options.keyframe_rate)
    if calibrations is None:
        r = run_ekf(dataset, options.ekf_gate, options.progress, kept_at)
        return Estimate("ekf", r.trajectory, r.runtime_s, {"rejected_measurements": r.rejected}, r.innovations,
                        heldout=r.heldout)
    r = run_calibrated_ekf(dataset, calibrations, options.ekf_gate, options.progress, kept_at)
    details = {"rejected_measurements": r.rejected}
    details["calibration"], details["calibration_against_prior"] = calibration_records(r.calibration, r.calibration_cov)
    return Estimate("ekf", r.trajectory, r.runtime_s, details, r.innovations, calibration=r.calibration,
                    heldout=r.heldout)


def _start(dataset: Dataset, options: RunOptions) -> Estimate:
    """The EKF the batch smoother starts from, without its progress; a failed one (the batch then
    starts from dead reckoning) where it fails."""
    try:
        return _ekf(dataset, RunOptions(ekf_gate=options.ekf_gate, progress=False, keyframe_rate=options.keyframe_rate))
    except Exception as error:  # noqa: BLE001 -- the batch can still start from dead reckoning
        return Estimate("ekf", None, 0.0, {}, failed=_one_line(error))


def _correlation_fitted(dataset: Dataset, options: RunOptions, noise: tuple, mounting, record: dict) -> tuple:
    """``(dataset, start)``: ``dataset`` with the correlation times it asks to fit fitted
    (:mod:`smoother.diagnosis.correlation_fit`: each candidate a batch run as the run's, its noise
    fitted where the run fits it, from one EKF ``start``, which the run's batch starts from too:
    where the noise fit has more than one minimum, the run is the one scored) and only the judging
    half of those sensors' held-out measurements; ``record["correlation_fit"]`` the fits."""
    from smoother.diagnosis.correlation_fit import fit_correlation_times

    start = _start(dataset, options)
    quiet = replace(options, progress=False, covariances=True)
    fits, dataset = fit_correlation_times(dataset, lambda candidate: _batch(candidate, quiet, start, noise, mounting),
                                          options.progress)
    record["correlation_fit"] = fits
    return dataset, start


def _batch(dataset: Dataset, options: RunOptions, ekf: Estimate | None, noise: tuple = (),
           mounting=None) -> Estimate:
    """The batch smoother started from ``ekf``'s estimate (an EKF run for it when None), its
    calibrations from the EKF's where it estimated them (the priors stay about the values given);
    with the noise groups ``noise``, their variance components fitted and the estimate with the
    fitted noise (``details["noise"]``: the fit, its record and the model errors it would have
    hidden, given the ``mounting`` check)."""
    tick = time.perf_counter()
    details: dict = {}
    if ekf is None:
        ekf = _start(dataset, options)
        details["start_ekf_s"] = time.perf_counter() - tick
    details["start"] = "ekf" if ekf.failed is None else f"dead reckoning (the EKF failed: {ekf.failed})"
    problem = with_correlated_errors(build_problem(dataset, options.keyframe_rate, options.robust,
                                                   start=None if ekf.failed is not None else ekf.trajectory), dataset)
    if problem.calibration is not None and ekf.calibration is not None:  # the filter's calibration too
        problem = replace(problem, calibration=replace(problem.calibration, values=ekf.calibration.values))
    build_s = time.perf_counter() - tick
    # a calibration is never reported without its sigma: its covariance is computed whatever --no-covariance says
    covariances = options.covariances or problem.calibration is not None
    r = solve_batch(problem, options.optimizer, options.max_iterations, covariances or bool(noise),
                    square_root=bool(noise) or (covariances and predicts_correlated(dataset, problem)))
    runtime_s = build_s + r.runtime_s
    fit = None
    if noise:
        fit, r, problem, errors, seconds = _honest_noise(dataset, problem, r, noise, options, mounting)
        runtime_s += seconds
        details["noise"] = fit.record()
        if errors:
            details["noise_model_errors"] = {e.group: e.cause for e in errors}
    details.update({"iterations": r.iterations, "converged": r.converged, "final_error": r.error,
                    "graph_build_s": build_s})
    if r.calibration is not None:
        details["calibration"], details["calibration_against_prior"] = calibration_records(r.calibration,
                                                                                           r.calibration_cov)
    # the verdicts need the joint covariances, which only this call has
    consistency = smoother_consistency(problem.blocks, r.trajectory.states, r.trajectory.cov, r.joint, r.calibration)
    following = None
    if r.joint is not None and len(r.trajectory.t) > 1:
        n = len(r.trajectory.t)
        following = Following.of_batch(r.trajectory, joint_blocks(r.joint, np.arange(n - 1), np.arange(1, n)))
    heldout = batch_predictions(dataset if fit is None else fit.applied(dataset), problem, r, following)
    return Estimate("batch", r.trajectory, runtime_s, details, consistency=consistency, calibration=r.calibration,
                    noise=fit, following=following, heldout=heldout)


#: A noise fit is done again with its model errors at the rig's value at most this many times (:func:`_honest_noise`).
MAX_REFITS = 3


def _honest_noise(dataset: Dataset, problem, r, noise: tuple, options: RunOptions, mounting=None) -> tuple:
    """``(fit, result, problem, errors, seconds)``: the noise groups ``noise`` fitted from the batch
    estimate ``r`` of ``problem`` (:func:`smoother.batch.variance_components.estimate_noise`), every
    group that is a model error kept at the rig's value
    (:func:`smoother.diagnosis.noise_honesty.honest`, with the sensors' misfit causes where it needs
    them and the ``mounting`` check), the estimate with the noise applied and its problem, the model
    errors and the time it all took.

    The groups fitted beside a model error took up part of the misfit it followed (a gyro's noise
    grown to follow an AHRS's delay leaves the AHRS's sigma fitted to the residuals that growth left),
    so once some are held the rest are fitted again with those at the rig's value, from the estimate
    with the rig's noise, and judged again, until no new model error is found -- at most
    :data:`MAX_REFITS` times. Each group is reported from the last fit that estimated it; the
    fit's iterations are those of all the fits, and it converged where each did and the last one
    found no new model error beside groups it applied (a fit again that fails, a SolverError, leaves
    the last one standing, with a warning). ``seconds`` and the fit's ``runtime_s``
    count everything here (the fits, the misfit causes, the solves between them).

    The solves on the way (with noise about to be refused, from a start left behind) are
    intermediate: an optimiser that stopped short there is not said
    (:class:`smoother.errors.NotConverged`); the estimate returned is, where it stopped short. The
    other warnings are said once each."""
    caught: list = []
    try:
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always")
            out = _noise_fitted(dataset, problem, r, noise, options, mounting)
    finally:
        for message, category in dict.fromkeys((str(w.message), w.category) for w in caught
                                               if not issubclass(w.category, NotConverged)):
            warnings.warn(message, category, stacklevel=2)
    final = out[1]
    if not final.converged and final.trajectory is not r.trajectory:  # solved here; the given one was said
        warn_not_converged(options.optimizer, final.iterations, final.decrease, stacklevel=2)
    return out


def _noise_fitted(dataset: Dataset, problem, r, noise: tuple, options: RunOptions, mounting=None) -> tuple:
    """:func:`_honest_noise`'s work, its warnings as they come."""
    from smoother.batch.variance_components import estimate_noise
    from smoother.diagnosis.noise_honesty import honest, to_analyse

    tick = time.perf_counter()
    wrong = [f.sensor for f in mounting.wrong] if mounting is not None else ()
    streams = imu_streams(dataset)
    before = replace(r, joint=None, square_root=None)  # where the fit starts (its memory let go with the fit)
    profiled = frozenset(options.profiled_noise)
    fit, r, problem = estimate_noise(dataset, problem, r, noise, options.optimizer, options.max_iterations,
                                     profiled=profiled)
    order = [g.group.name for g in fit.groups]
    iterations, converged, fits = fit.iterations, fit.converged, 1
    held, errors = {}, []  # the groups kept as model errors, as the fit that found them reported them
    failed = False
    drifting = dataset.correlation_times
    for refit in range(MAX_REFITS + 1):
        causes = None
        if to_analyse(fit):  # a calibration's pattern, or the sensor's own drift or noise?
            from smoother.diagnosis.misfit_causes import causes_at

            causes = causes_at(fit.not_grown().applied(dataset), r.trajectory, options.keyframe_rate,
                               options.robust, calibration=r.calibration)
        fit, found = honest(fit, wrong, causes, streams, correlation_times=drifting)
        errors += found
        held.update({g.group.name: g for g in fit.groups if g.group.name in {e.group for e in found}})
        if not found or refit == MAX_REFITS or len(held) == len(order):
            break
        try:
            start_problem, start = _solved_from(dataset, before, options, square_root=True)
            again = estimate_noise(dataset, start_problem, start, noise, options.optimizer, options.max_iterations,
                                   fixed=frozenset(held), profiled=profiled)
        except SolverError as error:  # the last fit stands, its applied groups fitted beside those held
            warnings.warn(f"noise estimation: fitting again with {', '.join(held)} at the rig's value failed "
                          f"({error}); the other groups keep the values fitted beside them", stacklevel=2)
            failed = True
            break
        fit, r, problem = again
        iterations, converged, fits = iterations + fit.iterations, converged and fit.converged, fits + 1
    latest = {g.group.name: g for g in fit.groups}
    reported = [held_as_reported(held[name], held) if name in held else latest[name] for name in order]
    # the last fit allowed (or the last that could be made) still found model errors: the groups it
    # applied were fitted beside them
    exhausted = bool(found) and (refit == MAX_REFITS or failed) and len(held) < len(order)
    fit = replace(fit, groups=reported, iterations=iterations, converged=converged and not exhausted,
                  runtime_s=time.perf_counter() - tick, fits=fits)
    if found:
        # groups kept at the rig's value by the last fit's judgement: the estimate with the noise applied,
        # from where the fit ended and from the estimate before it (a fit that a misfit drove may end far
        # off, in another minimum), the lower cost kept
        problem, r, _ = solved_from_each(fit.applied(dataset), (r, before), options)
    return fit, r, problem, errors, time.perf_counter() - tick


def held_as_reported(group: GroupFit, held) -> GroupFit:
    """A group kept as a model error (:class:`~smoother.batch.variance_components.GroupFit`), as
    the run reports it: as the fit that found it fitted it, tied only to the groups ``held`` with it
    (names). A factor it shared with groups fitted again since says so in its note: its redundancy
    is its own, its factor and sd the shared one's."""
    refitted = [m for m in group.merged_with if m not in held]
    note = group.note + (f" (its factor was one with {' and '.join(refitted)}, fitted again without it since)"
                         if refitted else "")
    return replace(group, merged_with=tuple(m for m in group.merged_with if m in held), note=note)


def _solved_from(dataset: Dataset, start, options: RunOptions, square_root: bool = False) -> tuple:
    """``(problem, result)``: the batch smoother on ``dataset`` (with covariances; with
    ``square_root``, their elimination kept, :func:`smoother.batch.solve.solve_batch`) from the
    estimate ``start`` (its trajectory and calibration)."""
    problem = with_correlated_errors(build_problem(dataset, options.keyframe_rate, options.robust,
                                                   start=start.trajectory), dataset)
    if problem.calibration is not None and start.calibration is not None:
        problem = replace(problem, calibration=start.calibration)
    return problem, solve_batch(problem, options.optimizer, options.max_iterations, True, square_root=square_root)


def solved_from_each(dataset: Dataset, starts, options: RunOptions) -> tuple:
    """``(problem, result, seconds)``: the batch smoother on ``dataset`` (with covariances) from
    each of the estimates ``starts`` (their trajectories and calibrations; any with a ``trajectory``
    and a ``calibration``), the one of lowest cost, and the time all took: where the problem may have
    more than one minimum, the best of those the starts lead to. The warnings of the solve kept are
    issued once, after all: a start left behind (one that ran out of iterations, say) says nothing of
    the estimate returned."""
    runs = []
    for start in starts:
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always")
            runs.append((*_solved_from(dataset, start, options), [(str(w.message), w.category) for w in caught]))
    problem, result, said = min(runs, key=lambda run: run[1].error)
    for message, category in dict.fromkeys(said):
        warnings.warn(message, category, stacklevel=2)
    return problem, result, sum(run[1].runtime_s for run in runs)


def _given_values_note(dataset: Dataset, kind: str) -> dict:
    """What a fixed-lag smoother of ``kind`` other than the compiled window says of the
    calibrations a dataset asks for: it uses the values given."""
    asking = [s.name for s in dataset.sensors if s.calibrate is not None]
    if not asking or kind == "sliding":
        return {}
    return {"calibration_note": f"used the values given for {', '.join(asking)}; the {kind} fixed-lag smoother "
                                "estimates no calibration (the 'sliding' one, the batch smoother and the EKF do)"}


def _drift_note(dataset: Dataset, kind: str, weighed_alone: int) -> dict:
    """The fixed-lag smoother's details on ``dataset``'s drifting sensors: ``weighed_alone``, how
    many of their measurements the window weighed as independent of the one before (the run warns
    of them too), or, for GTSAM's windows, ``drift_taken_white``: the sensors whose errors they
    take as white; nothing without such sensors."""
    drifting = [s.name for s in dataset.sensors if s.correlation_time is not None and s.data is not None]
    if not drifting:
        return {}
    return {"drift_taken_white": drifting} if kind in GTSAM_KINDS else {"weighed_alone": weighed_alone}


def _fixed_lag(dataset: Dataset, options: RunOptions) -> Estimate:
    from smoother.online.replay import replay

    held_out = any(s.heldout is not None for s in dataset.sensors)  # states between keyframes: bridged there
    windowed, residuals = _in_the_window(dataset, options)
    readers = [reader for reader in (windowed, residuals) if reader is not None]

    def before_leaving(window, leaving) -> None:
        leaving = list(leaving)
        for reader in readers:
            reader(window, leaving)

    r = replay(dataset, options.lag_s, options.fixed_lag_kind, options.keyframe_rate, options.robust,
               options.covariances, options.max_delay_s, options.realtime, options.speed, options.progress,
               joint_with_next=held_out, before_leaving=before_leaving if readers else None)
    details = {"lag_s": options.lag_s, "kind": options.fixed_lag_kind, "recovered_keyframes": r.recovered,
               "dropped_measurements": r.dropped, "skipped_measurements": r.skipped,
               "longest_measurement_gap_s": r.longest_gap_s, **_given_values_note(dataset, options.fixed_lag_kind),
               **_drift_note(dataset, options.fixed_lag_kind, r.weighed_alone)}
    if r.calibration is not None:
        details["calibration"], details["calibration_against_prior"] = calibration_records(*r.calibration)
    if options.realtime and len(r.latency_s):
        ms = 1e3 * r.latency_s
        details["latency_ms"] = {"median": float(np.median(ms)), "p99": float(np.percentile(ms, 99)),
                                 "max": float(ms.max()), "measurements": len(ms)}
    calibration = None if r.calibration is None else r.calibration[0]
    heldout = None
    if windowed is not None and r.following is not None:  # its own predictions, and those given the used errors
        heldout = windowed.attached_to(heldout_predictions(dataset, r.smoothed, calibration, r.following))
    return Estimate("fixed-lag", r.smoothed, r.runtime_s, details, calibration=calibration, following=r.following,
                    heldout=heldout, consistency=None if residuals is None else residuals.verdicts())


def _in_the_window(dataset: Dataset, options: RunOptions) -> tuple:
    """What reads the fixed-lag smoother's window about ``dataset``'s drifting sensors as its
    keyframes leave it, on the batch's factors at the window's keyframes: their held-out
    measurements' predictions given the used errors
    (:class:`smoother.diagnosis.heldout_windowed.WindowedPredictions`) and their own residuals'
    verdicts (:class:`smoother.diagnosis.residual_windowed.WindowedResiduals`), each None where
    there is nothing to read: no such sensor (one whose calibration the window estimates is not read
    so: its estimate changes from update to update), no covariances, or GTSAM's windows (white); or
    data the batch's factors refuse (two measurements whose errors would be one), which the window
    weighs alone, said in a warning."""
    from smoother.diagnosis.heldout_windowed import WindowedPredictions
    from smoother.diagnosis.residual_windowed import WindowedResiduals

    drifting = [s for s in dataset.sensors if s.correlation_time is not None and s.data is not None
                and s.calibrate is None]
    if not drifting or not options.covariances or options.fixed_lag_kind in GTSAM_KINDS:
        return None, None
    try:
        problem = with_correlated_errors(build_problem(dataset, options.keyframe_rate, options.robust), dataset)
    except InputError as error:  # what the batch's factors refuse (two errors one), the window weighs alone
        warnings.warn(f"fixed-lag smoother: its drifting sensors are not judged in its window "
                      f"({_one_line(error)})", stacklevel=2)
        return None, None
    held_out = [s.name for s in drifting if s.heldout is not None]
    return (WindowedPredictions(dataset, problem, held_out) or None,
            WindowedResiduals(problem, [s.name for s in drifting]) or None)


def verdicts_by_estimator(dataset: Dataset, estimates: dict[str, Estimate], options: RunOptions = RunOptions()) -> dict:
    """Each estimator's own verdict on each sensor, ``{estimator: {sensor: verdict}}``
    (:func:`smoother.diagnosis.verdicts.verdict`): the EKF's innovations
    (:func:`smoother.diagnosis.verdicts.sensor_consistency`), the batch smoother's residuals with their
    leverages (computed with its covariances, ``details["sensors"]``), the fixed-lag smoother's
    residuals of the factors on one keyframe at its estimates
    (:func:`smoother.diagnosis.residual_consistency.smoother_consistency` over the measurement factors on
    its keyframes) -- but a drifting sensor's (a ``correlation_time``): its factors are innovations on
    two keyframes, whose residuals' leverage needs the joint covariance of both, which the window's
    output does not keep (and its own residuals judged as white would blame the sigma for the drift
    the estimate follows), so the window judged them as it went (``consistency``:
    :mod:`smoother.diagnosis.residual_windowed`; none where it could not: GTSAM's windows, an
    estimated calibration). An estimator without covariances or that failed has none."""
    from smoother.diagnosis.verdicts import sensor_consistency

    out = {}
    for name, est in estimates.items():
        if est.failed is not None:
            continue
        if name == "ekf":
            out[name] = sensor_consistency(est.innovations)
        elif name == "batch":
            out[name] = est.consistency or {}
        else:  # its keyframes are the batch's: the measurement factors on them, at its estimates
            t = est.trajectory
            times = keyframe_times(dataset, options.keyframe_rate)
            same = len(t.t) == len(times) and np.allclose(t.t, times, rtol=0, atol=1e-9)
            # its calibrations, where it estimated them, in the residuals (the values given otherwise); an
            # attached measurement's process noise along its estimates
            drifting = dataset.correlation_times  # judged in its window (est.consistency)
            blocks = [b for b, _, _ in measurement_blocks(dataset, times, options.robust, est.calibration,
                                                          t.states) if b.name not in drifting] if same else []
            out[name] = {**smoother_consistency(blocks, t.states, t.cov, calibration=est.calibration),
                         **(est.consistency or {})}
    return out


def heldout_by_estimator(dataset: Dataset, estimates: dict[str, Estimate]) -> dict:
    """Each estimator's verdict on each sensor's held-out measurements, ``{estimator: {sensor:
    verdict}}`` (:func:`smoother.diagnosis.heldout.heldout_consistency`): data the fit did not use,
    so a fitted noise cannot put them in band. Estimators without covariances have none."""
    from smoother.diagnosis.heldout import heldout_consistency

    return {name: heldout_consistency(dataset, est.trajectory, est.calibration, est.following, est.heldout)
            for name, est in estimates.items() if est.failed is None}


def unshrunk_groups(record: dict) -> dict[str, list[str]]:
    """Per sensor, its noise groups the fit in ``record`` shrank and the run refused as model errors
    (:mod:`smoother.diagnosis.noise_honesty`: residuals that small are no datasheet's, or errors that
    follow the IMU's); empty without a fit."""
    fit = record.get("noise")
    out: dict[str, list[str]] = {}
    for g in () if fit is None else fit.groups:
        if g.estimable and not g.applied and g.factor < 1.0 and g.note.startswith("not applied: "):
            out.setdefault(g.group.sensor, []).append(g.group.name)
    return out


def imu_streams(dataset: Dataset) -> dict[str, str]:
    """Per sensor of ``dataset`` that reads the IMU's own messages, that stream
    (:attr:`datasets.types.Sensor.imu_stream`)."""
    return {s.name: s.imu_stream for s in dataset.sensors if s.imu_stream is not None}


def imu_followers(dataset: Dataset, record: dict) -> dict[str, str]:
    """Per sensor whose errors may follow the IMU's, why, in a phrase: it reads the IMU's own
    messages (:attr:`datasets.types.Sensor.imu_stream`: a filter's output on the same gyro), the
    noise fit in ``record`` refused to shrink its sigma (:func:`unshrunk_groups`), or both. Such a
    sensor's errors far below their band are not said to be an overstated sigma alone
    (:func:`judged`, :func:`smoother.diagnosis.verdicts.consistency_warnings`)."""
    out = {sensor: [f"it reads the IMU's own messages, {stream}"] for sensor, stream in imu_streams(dataset).items()}
    for sensor, groups in unshrunk_groups(record).items():
        out.setdefault(sensor, []).append(f"the noise fit refused to shrink {' and '.join(groups)}")
    return {sensor: "; ".join(why) for sensor, why in out.items()}


def run_doubts(record: dict) -> list[str]:
    """What makes every estimate of a run doubtful whatever its own verdicts say: a sensor mounted
    otherwise than the rig says (the closed-form check, :mod:`smoother.diagnosis.mounting`), and a
    fitted noise that would have hidden a model error (:mod:`smoother.diagnosis.noise_honesty`), the
    groups refused for one cause named together."""
    out = []
    mounting = record.get("mounting")
    for finding in () if mounting is None else mounting.wrong:
        out.append(f"the mounting of {finding.sensor} is not the rig's ({finding.message})")
    fit = record.get("noise")
    by_cause: dict[str, list[str]] = {}  # groups refused for one cause (the IMU's contradicting pair) said once
    for g in () if fit is None else fit.groups:
        if g.note.startswith("not applied: ") and g.estimable:
            by_cause.setdefault(g.note.removeprefix("not applied: "), []).append(g.group.name)
    for cause, groups in by_cause.items():
        out.append(f"the noise fitted to {' and '.join(groups)} {'is' if len(groups) == 1 else 'are'} a model error, "
                   f"not noise: {cause}")
    return out


def judged(estimates: dict[str, Estimate], consistency: dict, heldout: dict | None = None,
           doubts: list[str] = (), follow_imu: dict[str, str] | None = None) -> None:
    """Record each estimator's verdicts in its details: ``sensors`` (per sensor; with held-out
    measurements also ``heldout_per_dof``, ``heldout_band``, ``heldout_ok``,
    ``heldout_measurements`` and ``heldout_state_share``) and ``fit`` (all together,
    :func:`smoother.diagnosis.verdicts.overall`) and ``doubtful`` with why when

    * the fit or any one verdict is far above its band (:func:`smoother.diagnosis.verdicts.far_above`:
      the estimate does not explain that part of its own data, whatever the optimiser reported) --
      a sensor's held-out verdict (``heldout``: :func:`heldout_by_estimator`) stands for its own
      where it has one: data the fit did not use -- unless they are a drifting sensor's, predicted
      without the used errors (``not_given_used_errors``), which judge no model;
    * a verdict is far below its band (:func:`smoother.diagnosis.verdicts.far_below`): the sensor's
      sigma is overstated, and the estimate's covariances too large (for held-out predictions, by
      the factor that would fit them) -- or, for held-out predictions below even the state's own
      covariance (no sigma of the sensor's fits them with the estimate's covariances held:
      :func:`smoother.diagnosis.heldout.sigma_factor`), a sigma that also inflates those covariances
      or a state the data do not fix -- or, where those near the used measurements lie below those
      far from them (:func:`smoother.diagnosis.heldout.near_and_far`), errors correlated in time --
      but for a sensor in ``follow_imu`` (:func:`imu_followers`, with why), whose low errors may as
      well follow the IMU's, which makes the covariances too small;
    * a run-wide ``doubts`` (:func:`run_doubts`) holds.

    A sensor whose calibration an estimator estimated but could not judge itself (the fixed-lag
    smoother keeps no covariances of its states with the calibrations) counts by the verdict of
    another estimator of the same model on the same data
    (:func:`smoother.diagnosis.calibration_report.verdicts_for`). An EKF whose gate rejected most
    of a sensor's measurements (:func:`smoother.diagnosis.verdicts.rejections`) and an estimator
    whose calibration disagrees with the others' beyond their sigmas
    (:func:`smoother.diagnosis.calibration_report.disagreements`; with run-wide ``doubts``, those
    model errors named as a cause beside a wrong minimum) are doubtful too. Verdicts on
    too few degrees of freedom (:func:`smoother.diagnosis.verdicts.judgeable`) count towards
    nothing."""
    from smoother.diagnosis.calibration_report import disagreements, verdicts_for
    from smoother.diagnosis.verdicts import far_above, far_below, judgeable, overall, rejections, with_heldout

    heldout = heldout or {}
    disagreeing = disagreements({name: est.details for name, est in estimates.items()}, model_errors=bool(doubts))
    for name, est in estimates.items():
        ours = consistency.get(name, {})
        held = heldout.get(name, {})
        est.details["sensors"] = with_heldout(ours, held)
        # a held-out verdict stands for the sensor's own -- but one predicted without the used errors
        # of a drifting sensor (the fixed-lag smoother's, where it cannot give them) judges no model
        held = {k: c for k, c in held.items() if not c.get("not_given_used_errors")}
        judged_by = {**ours, **held}
        why = []
        fit = overall(ours)
        if fit is not None:
            est.details["fit"] = fit
        off = [k for k, c in judged_by.items() if far_above(c)]
        if (fit is not None and far_above(fit)) or off:
            worst = max(judged_by, key=lambda k: judged_by[k]["per_dof"] if judgeable(judged_by[k]) else -np.inf)
            summary = "" if fit is None else (
                f"its normalised {'innovations' if fit['statistic'] == 'nis' else 'residuals'} are "
                f"{fit['per_dof']:.3g} per dof (expected {fit['band'][0]:.2g}-{fit['band'][1]:.2g}), ")
            why.append(f"{summary}those of {', '.join(off) or worst} far above their band (worst: {worst}"
                       f"{' held out' if worst in held else ''}, {judged_by[worst]['per_dof']:.3g})")
        low = [k for k, c in judged_by.items() if far_below(c)]
        for k in low:
            c = judged_by[k]
            figure = (f"{k}'s {'held-out predictions' if k in held else 'errors'} are {c['per_dof']:.3g} per dof "
                      f"(expected {c['band'][0]:.2g}-{c['band'][1]:.2g})")
            if k in held and c.get("correlated"):
                near, far = c["near_far"]
                why.append(f"{figure}, {near:.2g} near the used measurements and {far:.2g} far from them: the "
                           "sensor's errors are correlated in time and the estimate follows them through the used "
                           "ones, " + ("more than its correlation_time says" if c.get("given_used_errors") else
                                       "which no white sigma describes (a correlation_time does)"))
            elif k in held and c.get("sigma_factor") is None:
                following = f", or errors that follow the IMU's ({follow_imu[k]})" if k in (follow_imu or {}) else ""
                why.append(f"{figure}, below even the state's own uncertainty there: the estimate's covariances "
                           "are too large -- a sigma stated too large (a smaller one shrinks them too) or a state "
                           f"the data do not fix (a heading, a bias){following}")
            elif k in (follow_imu or {}):
                why.append(f"{figure}, far below their band: its sigma is overstated or its errors follow the "
                           f"IMU's ({follow_imu[k]}), so the estimate's covariances may be too large or too small")
            else:
                factor = c.get("sigma_factor")
                by = "" if k not in held else (
                    f" (by up to {1.0 / factor:.2g}x: they are 1 per dof at {factor:.2g} times it with the "
                    "estimate's covariances held, which a smaller sigma shrinks too; a value fitted to them)")
                why.append(f"{figure}, far below their band: its sigma is overstated{by}, so the estimate's "
                           "covariances are too large")
        calibrated = () if est.calibration is None else est.calibration.names
        borrowed = {k: v for k, v in verdicts_for(name, consistency).items()
                    if k in calibrated and k not in judged_by and far_above(v)}
        if borrowed:
            why.append("its calibrated " + ", ".join(
                f"{k}, which it does not judge itself, is {v['per_dof']:.3g} per dof by the {v['by']} (expected "
                f"{v['band'][0]:.2g}-{v['band'][1]:.2g})" for k, v in borrowed.items()))
        why += list(doubts)
        if why:
            est.details["doubtful"] = "; ".join(why) + (": the model does not fit the data, so the estimate may be "
                                                        "wrong and its covariances wrong too")
        # a gate that rejected most of a sensor's measurements; a calibration against the other estimators'
        also = [text for text in (rejections(ours), disagreeing.get(name)) if text]
        if also:
            est.details["doubtful"] = "; ".join(filter(None, (est.details.get("doubtful"), *also)))
