"""The ``position`` and ``gnss`` kinds: a sensor's origin in the world, ``r + C p_BS`` (a GNSS
antenna on its lever arm). ``position`` reads positions (of poses, or a file of positions alone);
``gnss`` reads fixes in latitude, longitude and altitude and converts them to the local ENU frame
about the datum."""
from __future__ import annotations

import warnings

import numpy as np

from datasets.kinds.base import Kind, displaced, near_prediction, noise, noisy
from datasets.types import PositionMeasurements
from factors import sensor_models as sm
from factors.selfcheck import random_state


def _simulate(truth, k, imu, T_BS, sigma, rng):
    _, p = sm.extrinsic_parts(T_BS)
    z = truth.position[k] + truth.C[k] @ p
    return PositionMeasurements(truth.t[k], noisy(z, sigma, rng), np.diag(sigma**2), T_BS)


def _anchor(m):
    return m.t, m.position, None  # the lever arm is left in: initial values only


def _read_positions(sensor, clock):
    from datasets.sources import read_positions

    stream = read_positions(sensor.source, sensor.topic)
    t = clock.stamps(stream.t, stream.t_ns, sensor.time_offset)
    return PositionMeasurements(t, stream.position, noise(sensor, 3, stream.cov, len(t)), sensor.T_BS), clock.datum


def _read_fixes(sensor, clock):
    """Fixes without a position (status "no fix") are dropped and counted in a warning; the
    first valid fix sets the datum when the rig gives none."""
    from datasets.gnss import fixes_to_enu
    from datasets.sources import read_fixes

    fixes = fixes_to_enu(read_fixes(sensor.source, sensor.topic), clock.datum)
    if fixes.n_dropped:
        warnings.warn(f"sensor {sensor.name!r}: {fixes.n_dropped} of {fixes.n_dropped + len(fixes.t)} fixes have no "
                      "position (status 'no fix') and are dropped", stacklevel=4)
    t = clock.stamps(fixes.t, fixes.t_ns, sensor.time_offset)
    return PositionMeasurements(t, fixes.enu, noise(sensor, 3, fixes.cov, len(t)), sensor.T_BS), fixes.datum


def _pack(m):
    return sm.pack_position(m.position, m.T_BS)


def _random_row(rng):
    x = random_state(rng)
    T, z, _ = near_prediction(x, rng)
    return x, sm.pack_position(z[None], T)[0]



_DECLARED = dict(fields=("position",), random_row=_random_row, default_sigma=(0.5,), corrupt=displaced,
                 sigma_units=("m",) * 3, noise_groups=(("horizontal", (0, 1)), ("vertical", (2,))))
POSITION = Kind("position", PositionMeasurements, 3, sm.POSITION, _pack, _simulate, _anchor, _read_positions,
                **_DECLARED)
GNSS = Kind("gnss", PositionMeasurements, 3, sm.POSITION, _pack, _simulate, _anchor, _read_fixes, **_DECLARED)
