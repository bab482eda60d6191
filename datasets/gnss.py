"""GNSS fixes to the local East-North-Up frame about a datum (``pymap3d``, WGS-84).

The project's world frame for a rig with GNSS is the local ENU frame at the datum: x east, y
north, z up (so gravity is ``(0, 0, -g)``), origin at the datum's latitude [deg], longitude
[deg] and altitude [m above the ellipsoid]. :func:`geodetic_to_enu` and :func:`enu_to_geodetic`
are exact inverses (to well below a millimetre).

A fix's covariance is given in the ENU frame at the fix itself (as ROS's NavSatFix does); it is
used unrotated in the datum's ENU frame. The two frames differ by the angle the earth's surface
turns between them, about 1.6e-4 rad per kilometre, which changes a covariance by that fraction:
negligible for the areas a local frame is meant for.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import NamedTuple

import numpy as np
import pymap3d

from datasets.streams import STATUS_NO_FIX, FixStream
from factors.errors import InputError


@dataclass(frozen=True)
class Datum:
    """The origin of the local ENU frame: ``latitude``, ``longitude`` [deg], ``altitude`` [m]."""

    latitude: float
    longitude: float
    altitude: float

    def __post_init__(self):
        for name, limit in (("latitude", 90.0), ("longitude", 180.0), ("altitude", None)):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, (int, float)) or not np.isfinite(value):
                raise InputError(f"Datum.{name}: expected a finite number, got {value!r}")
            if limit is not None and abs(value) > limit:
                raise InputError(f"Datum.{name}: expected degrees within +-{limit:g}, got {value!r}")
            object.__setattr__(self, name, float(value))


class EnuFixes(NamedTuple):
    """Fixes in the local ENU frame: ``t`` (N,), ``enu`` (N, 3) [m], ``cov`` (N, 3, 3) or None
    (rows of NaN where a fix's covariance is unknown), the ``datum`` used and ``n_dropped``, the
    number of fixes dropped for having no fix (``status < 0``), and ``t_ns``, the integer stamps
    where the source has them (else None)."""

    t: np.ndarray
    enu: np.ndarray
    cov: np.ndarray | None
    datum: Datum
    n_dropped: int
    t_ns: np.ndarray | None = None


def geodetic_to_enu(latitude, longitude, altitude, datum: Datum) -> np.ndarray:
    """Geodetic coordinates (arrays of shape (N,)) as ENU positions (N, 3) about ``datum``."""
    e, n, u = pymap3d.geodetic2enu(np.asarray(latitude, dtype=float), np.asarray(longitude, dtype=float),
                                   np.asarray(altitude, dtype=float), datum.latitude, datum.longitude,
                                   datum.altitude)
    return np.stack([e, n, u], axis=-1)


def enu_to_geodetic(enu, datum: Datum) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """ENU positions (N, 3) about ``datum`` as ``(latitude, longitude, altitude)``."""
    enu = np.asarray(enu, dtype=float)
    lat, lon, alt = pymap3d.enu2geodetic(enu[..., 0], enu[..., 1], enu[..., 2], datum.latitude, datum.longitude,
                                         datum.altitude)
    return np.asarray(lat), np.asarray(lon), np.asarray(alt)


def fixes_to_enu(fixes: FixStream, datum: Datum | None = None) -> EnuFixes:
    """The fixes with a position (``status >= 0``; the others dropped and counted) in the ENU
    frame about ``datum``, by default the first of them. A ``ValueError`` if no fix has a
    position."""
    valid = fixes.status > STATUS_NO_FIX
    if not valid.any():
        raise InputError(f"GNSS fixes: none of the {len(fixes)} has a position (all have status < 0)")
    if datum is None:
        k = int(np.flatnonzero(valid)[0])
        datum = Datum(float(fixes.latitude[k]), float(fixes.longitude[k]), float(fixes.altitude[k]))
    kept = fixes.subset(valid)
    enu = geodetic_to_enu(kept.latitude, kept.longitude, kept.altitude, datum)
    return EnuFixes(kept.t, enu, kept.cov, datum, int((~valid).sum()), kept.t_ns)
