"""Graph building, batch and fixed-lag smoothing, the EKF, cross-checks, evaluation, plots and
the ``smoother`` command line.

A run: ``problem = build_problem(dataset)`` (keyframes, preintegrated IMU factors, measurement
factors, the initial trajectory), then ``solve_batch(problem)``, ``run_fixed_lag(problem, lag_s)``
or ``run_ekf(dataset)``; each result's ``trajectory`` holds the times, the states and (where
computed) their 15x15 covariances; ``run_estimators`` runs any of them on a dataset, an
estimator that failed with no trajectory and its reason. ``OnlineSmoother`` is the fixed-lag
smoother fed sample by sample as data arrive (``replay`` feeds it a whole dataset). ``metrics``
compares trajectories (ATE, RPE, NEES, as evo computes them), the module ``crosscheck`` runs the
three estimators against each other, ``plot_run`` draws a run directory, ``causes_at`` fits the
calibrations a sensor's misfit points at (the warnings' hints).

The names below are importable from the package itself (``from smoother import solve_batch``);
each is loaded on first use. This package depends on ``factors`` and ``datasets``.
"""
from factors.exports import lazy_exports

_EXPORTS = {
    **dict.fromkeys(("build_problem", "Problem"), "smoother.model.problem"),
    **dict.fromkeys(("solve_batch", "SmootherResult"), "smoother.batch.solve"),
    **dict.fromkeys(("run_fixed_lag", "FixedLagResult"), "smoother.fixed_lag.offline"),
    "FixedLagFailed": "smoother.fixed_lag.contract",
    **dict.fromkeys(("OnlineSmoother", "SensorSetup"), "smoother.online.smoother"),
    "OnlineEstimate": "smoother.online.handover",
    **dict.fromkeys(("replay", "ReplayResult"), "smoother.online.replay"),
    **dict.fromkeys(("run_ekf", "Ekf", "FilterResult", "FilterDiverged"), "smoother.ekf.filter"),
    "IndeterminantSystem": "smoother.errors",
    **dict.fromkeys(("RunOptions", "run_estimators"), "smoother.pipeline"),
    **dict.fromkeys(("evaluate", "ate", "rpe", "nees", "rmse_difference"), "smoother.evaluation.metrics"),
    **dict.fromkeys(("compare_with_truth", "position_errors"), "smoother.evaluation.scoring"),
    **dict.fromkeys(("save_trajectory", "load_trajectory", "load_stamped_trajectory"), "smoother.outputs.files"),
    **{name: f"smoother.evaluation.{name}" for name in ("metrics", "crosscheck")},
    "CrosscheckOptions": "smoother.evaluation.crosscheck",
    "tune_noise": "smoother.pipeline",
    **dict.fromkeys(("sensor_consistency", "consistency_warnings"), "smoother.diagnosis.verdicts"),
    **dict.fromkeys(("causes_at", "Cause"), "smoother.diagnosis.misfit_causes"),
    "plot_run": "smoother.outputs.plots",
}
__all__ = sorted(_EXPORTS)
__getattr__, __dir__ = lazy_exports(globals(), _EXPORTS)
