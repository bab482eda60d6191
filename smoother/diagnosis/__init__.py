"""Diagnoses of a dataset or a run: what the data say about a rig before and after estimating.

``mounting`` checks each sensor's mounting rotation against what the sensor and the IMU both
observe (``check_mountings``); ``mounting_data`` finds that rotation in closed form, on the IMU
integrated once by ``imu_integrals``.
"""
