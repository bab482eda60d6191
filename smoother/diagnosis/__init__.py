"""Does the model fit its own data? Per-sensor verdicts from the EKF's innovations
(:mod:`~smoother.diagnosis.verdicts`) and from a smoother's residuals
(:mod:`~smoother.diagnosis.residual_consistency`), the calibrations a misfit points at
(:mod:`~smoother.diagnosis.misfit_causes`), what a run says of the calibrations it estimated
(:mod:`~smoother.diagnosis.calibration_report`) and the noise fitted to the data
(:mod:`~smoother.diagnosis.noise_tuning`)."""
