"""Kalibr calibration files: IMU noise densities (``imu.yaml``) and camera-IMU extrinsics
(``camchain-imucam.yaml``), and the rigid-transform check every ``T_BS`` passes.

``imu.yaml``: the densities as top-level keys (Kalibr's input format) or inside one ``imuN``
entry (its ``imu.yaml`` output): ``accelerometer_noise_density`` [m/s^2/sqrt(Hz)],
``gyroscope_noise_density`` [rad/s/sqrt(Hz)], ``accelerometer_random_walk`` [m/s^3/sqrt(Hz)],
``gyroscope_random_walk`` [rad/s^2/sqrt(Hz)] -- continuous-time densities, what
:class:`factors.imu.ImuNoise` holds (``acc``, ``gyro``, ``acc_bias``, ``gyro_bias``).

Camchain: per camera (``cam0``, ``cam1``, ...) ``T_cam_imu``, the 4x4 transform taking points from
the IMU frame into the camera frame, ``p_C = T_cam_imu p_I``. That is ``T_SB`` with the camera as
the sensor ``S`` and the IMU as the body ``B``; the project's ``T_BS`` (``p_B = T_BS p_S``) is its
inverse.
"""
from __future__ import annotations

import numpy as np

from datasets.errors import DataError
from datasets.ranges import out_of_range
from datasets.types import rigid_problem
from datasets.yamlfile import read_yaml

#: Kalibr's (and ASL ``sensor.yaml``'s) density keys and the :class:`ImuNoise` fields they set.
NOISE_KEYS = {
    "accelerometer_noise_density": "acc",
    "gyroscope_noise_density": "gyro",
    "accelerometer_random_walk": "acc_bias",
    "gyroscope_random_walk": "gyro_bias",
}

#: The rig key each :class:`ImuNoise` field stands for (its range: :data:`datasets.ranges.RANGES`).
RIG_KEYS = {"acc": "accel_noise_density", "gyro": "gyro_noise_density", "acc_bias": "accel_random_walk",
            "gyro_bias": "gyro_random_walk"}


def density_in_range(doc, keys: tuple, field: str) -> float:
    """The density at ``keys`` of the YAML document ``doc`` (for :class:`ImuNoise` ``field``), a
    number within the range of the rig key it stands for, else a :class:`DataError` naming the
    file, line and key: a density of a calibration file is one of the rig's."""
    value = doc.number(keys, minimum=0.0)
    problem = out_of_range(f"imu.{RIG_KEYS[field]}", value)
    if problem is not None:
        raise doc.error(keys, value, f"as the rig's {RIG_KEYS[field]}: {problem.removeprefix('expected ')}")
    return value


def read_kalibr_imu(path) -> dict[str, float]:
    """The noise densities of a Kalibr ``imu.yaml`` present in it, by :class:`ImuNoise` field
    (at least one must be)."""
    doc = read_yaml(path)
    prefix: tuple = ()
    if isinstance(doc.data, dict) and not any(key in doc.data for key in NOISE_KEYS):
        imus = [key for key, value in doc.data.items() if str(key).startswith("imu") and isinstance(value, dict)]
        if len(imus) == 1:
            prefix = (imus[0],)
    block = doc.get(prefix) if prefix else doc.data
    if not isinstance(block, dict) or not any(key in block for key in NOISE_KEYS):
        raise DataError(doc.path, None, None, "no noise densities",
                        f"{', '.join(NOISE_KEYS)} at the top level or in one imuN entry")
    return {field: doc.number(prefix + (key,), minimum=0.0) for key, field in NOISE_KEYS.items() if key in block}


def read_camchain_T_BS(path, camera: str) -> np.ndarray:
    """``T_BS`` (4, 4) of ``camera`` in a Kalibr camchain: the inverse of its ``T_cam_imu``."""
    doc = read_yaml(path)
    if not isinstance(doc.data, dict) or camera not in doc.data:
        cameras = ", ".join(str(key) for key in doc.data) if isinstance(doc.data, dict) else "none"
        raise DataError(doc.path, None, None, f"no camera {camera!r}", f"one of the cameras in the file: {cameras}")
    keys = (camera, "T_cam_imu")
    value = doc.get(keys)
    try:
        T = np.array(value, dtype=float)
    except (TypeError, ValueError):
        raise doc.error(keys, value, "a 4x4 list of numbers") from None
    problem = rigid_problem(T)
    if problem is not None:
        raise doc.error(keys, problem,
                        "a rigid transform (4x4, rotation part orthonormal with det 1, last row 0 0 0 1)")
    R, p = T[:3, :3], T[:3, 3]
    T_BS = np.eye(4)
    T_BS[:3, :3], T_BS[:3, 3] = R.T, -R.T @ p
    return T_BS
