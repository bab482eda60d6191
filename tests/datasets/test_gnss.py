"""GNSS fixes to local ENU: a round trip within a millimetre, the datum, dropped fixes."""
from __future__ import annotations

import numpy as np
import pytest

from datasets.gnss import Datum, enu_to_geodetic, fixes_to_enu, geodetic_to_enu
from datasets.streams import FixStream


def test_round_trip_within_a_millimetre():
    rng = np.random.default_rng(0)
    datum = Datum(47.3769, 8.5417, 408.0)
    enu = rng.uniform(-20_000, 20_000, size=(500, 3)) * [1, 1, 0.05]
    lat, lon, alt = enu_to_geodetic(enu, datum)
    assert np.abs(geodetic_to_enu(lat, lon, alt, datum) - enu).max() < 1e-3
    assert np.abs(geodetic_to_enu([datum.latitude], [datum.longitude], [datum.altitude], datum)).max() < 1e-9


def test_fixes_without_a_fix_are_dropped_and_the_datum_is_the_first_valid_fix():
    datum = Datum(-33.9, 151.2, 50.0)
    enu = np.array([[0.0, 0, 0], [10, 20, 1], [100, -50, 2], [-3, 4, 5]])
    lat, lon, alt = enu_to_geodetic(enu, datum)
    lat[0] = lon[0] = alt[0] = np.nan
    cov = np.array([np.full((3, 3), np.nan), np.eye(3), np.full((3, 3), np.nan), 4 * np.eye(3)])
    fixes = FixStream(np.arange(4.0), lat, lon, alt, np.array([-1, 0, 2, 1]), cov)
    out = fixes_to_enu(fixes)
    assert out.n_dropped == 1 and np.array_equal(out.t, [1, 2, 3])
    assert out.datum == Datum(float(lat[1]), float(lon[1]), float(alt[1]))
    assert np.abs(out.enu - geodetic_to_enu(lat[1:], lon[1:], alt[1:], out.datum)).max() == 0
    assert np.abs(out.enu[0]).max() < 1e-9 and np.isnan(out.cov[1]).all() and np.array_equal(out.cov[2], 4 * np.eye(3))
    given = fixes_to_enu(fixes, datum)
    assert given.datum is datum and np.abs(given.enu - enu[1:]).max() < 1e-3
    with pytest.raises(ValueError, match="none of the 1 has a position"):
        fixes_to_enu(FixStream([0.0], [np.nan], [np.nan], [np.nan], np.array([-1])))


def test_a_datum_is_checked():
    with pytest.raises(ValueError, match="Datum.latitude: expected degrees within"):
        Datum(91.0, 0.0, 0.0)
    with pytest.raises(ValueError, match="Datum.altitude: expected a finite number"):
        Datum(1.0, 0.0, "high")
