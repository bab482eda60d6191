"""Does the model fit its own data? Per-sensor verdicts from the EKF's innovations
(:mod:`~smoother.diagnosis.verdicts`), from a smoother's residuals
(:mod:`~smoother.diagnosis.residual_consistency`) and from held-out measurements
(:mod:`~smoother.diagnosis.heldout`), the calibrations a misfit points at
(:mod:`~smoother.diagnosis.misfit_causes`), what a run says of the calibrations it estimated
(:mod:`~smoother.diagnosis.calibration_report`), whether a noise fitted to the data hides a model
error (:mod:`~smoother.diagnosis.noise_honesty`) and what the fit says (:mod:`~smoother.diagnosis.noise_report`),
and each sensor's mounting checked in closed form against
what the IMU observes before anything is estimated (:mod:`~smoother.diagnosis.mounting`, from
:mod:`~smoother.diagnosis.mounting_data` over the IMU's integrals,
:mod:`~smoother.diagnosis.imu_integrals`)."""
