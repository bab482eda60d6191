"""The primer's EKF on the project's IMU model (:mod:`~smoother.ekf.filter`) and the same filter
with sensors' calibrations as augmented states (:mod:`~smoother.ekf.calibrated`)."""
