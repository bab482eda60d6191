"""Writing rig files in tests: TOML text for a transform and for an ``[imu]`` table."""
from __future__ import annotations

import numpy as np


def toml_matrix(T) -> str:
    """A 4x4 transform as a TOML array of rows, every number exact."""
    return "[" + ", ".join("[" + ", ".join(repr(float(x)) for x in row) + "]" for row in np.asarray(T)) + "]"


def imu_table(source: str, noise, topic: str | None = None) -> str:
    """An ``[imu]`` table reading ``source`` with the four densities of ``noise`` (an ImuNoise)."""
    lines = ["[imu]", f'source = "{source}"'] + ([f'topic = "{topic}"'] if topic else [])
    lines += [f"accel_noise_density = {noise.acc}", f"gyro_noise_density = {noise.gyro}",
              f"accel_random_walk = {noise.acc_bias}", f"gyro_random_walk = {noise.gyro_bias}"]
    return "\n".join(lines) + "\n"


def sensor_table(name: str, kind: str, source: str, extra: str = "") -> str:
    """A ``[[sensor]]`` table: ``name``, ``kind``, ``source`` and the TOML lines ``extra``
    (a topic, ``T_BS``, ...)."""
    return f'\n[[sensor]]\nname = "{name}"\nkind = "{kind}"\nsource = "{source}"\n{extra.strip()}\n'
