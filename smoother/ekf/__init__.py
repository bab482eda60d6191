"""The primer's EKF on the project's IMU model (:mod:`~smoother.ekf.filter`), the same filter
with sensors' calibrations as augmented states (:mod:`~smoother.ekf.calibrated`), and what both
do at a measurement time: the order of the updates, the Kalman update with its chi-square gate and
the divergence test (:mod:`~smoother.ekf.update`)."""
