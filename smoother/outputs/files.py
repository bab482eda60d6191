"""A run's files: every estimate as ``<estimator>.tum`` (TUM trajectory, stamped in the data's own
clock: :attr:`datasets.types.Dataset.time_origin_ns`), ``<estimator>.npz`` (the full states and
covariances, times from the run's start and the clock's origin beside them) and, with a GNSS
datum, ``<estimator>.geojson``; ``truth.npz`` and ``gps.npz`` where known; ``metrics.json`` (the
scores of :mod:`smoother.evaluation.scoring` and the run's record). Every file is written
atomically. :func:`write_outputs` writes them into a folder; ``smoother run`` writes them through
:class:`smoother.commands.run_directory.RunDirectory` (one run at a time, the previous run's files
replaced together). The readers name the file and what was expected when it is not one of these.
"""
from __future__ import annotations

import contextlib
import json
import math
import pickle
import zipfile
from pathlib import Path

import numpy as np

from datasets.atomic import atomic_write
from datasets.initialise import world_frame
from datasets.kinds import sensors_of
from datasets.tum import write_tum
from datasets.types import Dataset, Trajectory
from factors import imu
from factors.errors import InputError
from smoother.evaluation.scoring import position_streams, score


def save_trajectory(path: Path, trajectory: Trajectory, time_origin_ns: int | None = None) -> None:
    """A trajectory with its covariances as ``.npz`` (atomic); with ``time_origin_ns`` (the data
    clock's reading at ``t = 0``, :attr:`datasets.types.Dataset.time_origin_ns`) that too, as the
    0-d int64 array ``time_origin_ns``: the stamps in the data's clock are ``t + time_origin_ns
    * 1e-9`` (:func:`load_stamped_trajectory`)."""
    s = trajectory.states
    arrays = {"t": trajectory.t, "r": s.r, "v": s.v, "C": s.C, "b_f": s.b_f, "b_w": s.b_w}
    if trajectory.cov is not None:
        arrays["cov"] = trajectory.cov
    if time_origin_ns is not None:
        arrays["time_origin_ns"] = np.int64(time_origin_ns)
    with atomic_write(path, "wb") as handle:
        np.savez(handle, **arrays)


#: What reading a damaged or foreign ``.npz`` can raise (NumPy, zipfile, pickle refused).
_NPZ_ERRORS = (OSError, ValueError, KeyError, EOFError, zipfile.BadZipFile, pickle.UnpicklingError)


@contextlib.contextmanager
def read_npz(path: Path, expected: str):
    """The arrays of the ``.npz`` archive ``path`` (``np.load`` without pickles) inside the
    block; an :class:`~factors.errors.InputError` naming the file and ``expected`` when it is not such an archive,
    cannot be read or holds arrays the block refuses (a ``ValueError`` there, e.g. a validation)."""
    try:
        is_zip = zipfile.is_zipfile(path)
    except OSError as error:
        raise InputError(f"{path}: cannot read it ({error.strerror or error}); expected {expected}") from None
    if not is_zip:
        raise InputError(f"{path}: not an .npz archive; expected {expected}")
    try:
        with np.load(path, allow_pickle=False) as data:
            yield data
    except InputError:
        raise
    except _NPZ_ERRORS as error:
        raise InputError(f"{path}: cannot read it ({error}); expected {expected}") from None


def load_trajectory(path: Path) -> Trajectory:
    """Inverse of :func:`save_trajectory`, times from the run's start (see
    :func:`load_stamped_trajectory` for the data's clock)."""
    return load_stamped_trajectory(path)[0]


def load_stamped_trajectory(path: Path) -> tuple[Trajectory, int | None]:
    """``(trajectory, time_origin_ns)`` of a file :func:`save_trajectory` wrote (``time_origin_ns``
    None when it has none: its times are the data's own); an :class:`~factors.errors.InputError`
    naming the file for anything else (not an archive, missing arrays, arrays that do not make a
    trajectory, none at all)."""
    expected = ("an .npz written by smoother run with arrays t, r, v, C, b_f, b_w and optionally cov (N, 15, 15) "
                "and time_origin_ns (an integer)")
    with read_npz(path, expected) as data:
        missing = [k for k in ("t", "r", "v", "C", "b_f", "b_w") if k not in data]
        if missing:
            raise InputError(f"{path}: missing array(s) {', '.join(missing)}; expected {expected}")
        states = imu.ImuState(r=data["r"], v=data["v"], C=data["C"], b_f=data["b_f"], b_w=data["b_w"])
        trajectory = Trajectory(data["t"], states, data["cov"] if "cov" in data else None)
        origin = None
        if "time_origin_ns" in data:
            value = data["time_origin_ns"]
            if value.shape != () or value.dtype.kind not in "iu":
                raise InputError(f"{path}: time_origin_ns is {value.dtype} of shape {value.shape}; expected {expected}")
            origin = int(value)
    if len(trajectory) == 0:
        raise InputError(f"{path}: the trajectory is empty; expected at least one state")
    return trajectory, origin


def save_gps(path: Path, dataset: Dataset) -> None:
    """The dataset's position fixes, used and held out (flag ``heldout``), for plots (atomic);
    nothing when it has none. A rig's position and GNSS sensors count too (their antennas'
    positions, as measured)."""
    parts = [(p, flag) for pair in position_streams(dataset) for p, flag in zip(pair, (False, True)) if p is not None]
    if not parts:
        return
    t = np.concatenate([p.t for p, _ in parts])
    order = np.argsort(t, kind="stable")
    with atomic_write(path, "wb") as handle:
        clock = {} if dataset.time_origin_ns is None else {"time_origin_ns": np.int64(dataset.time_origin_ns)}
        np.savez(handle, t=t[order], position=np.concatenate([p.position for p, _ in parts])[order],
                 cov=np.concatenate([p.cov for p, _ in parts])[order],
                 heldout=np.concatenate([np.full(len(p), flag) for p, flag in parts])[order], **clock)


def aiding_sensors(dataset: Dataset) -> list[str]:
    """The names of the dataset's aiding sensors (:func:`datasets.kinds.sensors_of`); none: the
    run is dead reckoning, the IMU alone."""
    return [s.name for s in sensors_of(dataset)]


def write_outputs(out_dir: Path, dataset: Dataset, estimates: dict, extra: dict | None = None) -> dict:
    """Write every estimate (TUM + npz, both in the data's clock; GeoJSON with a datum), the truth
    and the fixes (npz) where known and ``metrics.json`` (its ``_run`` with ``extra``, the
    estimators, ``aiding_sensors``, ``dead_reckoning``: true without any, and ``world_frame``:
    :meth:`datasets.initialise.WorldFrame.describe`) into ``out_dir``;
    return the metrics. An estimator that failed has its reason in ``metrics.json`` (``failed``)
    and no files. Files of these names already there are overwritten, others left (a run
    directory's one-run rule is :class:`smoother.commands.run_directory.RunDirectory`'s)."""
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    report: dict = {}
    for name, est in estimates.items():
        if est.failed is not None:  # no trajectory: why, in metrics.json
            report[name] = {"failed": est.failed, "runtime_s": est.runtime_s, **est.details}
            continue
        write_tum(out_dir / f"{name}.tum", est.trajectory, time_origin_ns=dataset.time_origin_ns)
        save_trajectory(out_dir / f"{name}.npz", est.trajectory, dataset.time_origin_ns)
        datum = getattr(dataset, "datum", None)
        if datum is not None:
            write_geojson(out_dir / f"{name}.geojson", est.trajectory, datum, name, dataset.time_origin_ns)
        report[name] = {**score(dataset, est.trajectory, est.calibration), "runtime_s": est.runtime_s, **est.details}
    if dataset.truth is not None:
        save_trajectory(out_dir / "truth.npz", dataset.truth, dataset.time_origin_ns)
    save_gps(out_dir / "gps.npz", dataset)
    aiding = aiding_sensors(dataset)
    document = {**report, "_run": {**(extra or {}), "estimators": list(estimates), "aiding_sensors": aiding,
                                   "dead_reckoning": not aiding,
                                   "world_frame": world_frame(sensors_of(dataset)).describe()}}
    with atomic_write(out_dir / "metrics.json") as handle:
        json.dump(jsonable(document), handle, indent=2)
        handle.write("\n")
    return report


def write_geojson(path: Path, trajectory: Trajectory, datum, name: str, time_origin_ns: int | None = None) -> None:
    """The trajectory in latitude, longitude and altitude (WGS-84, about the local ENU frame's
    ``datum``) as a GeoJSON ``LineString`` (longitude first, as GeoJSON orders them), atomically:
    it opens in QGIS or any web map. Its ``t_start`` and ``t_end`` are in the data's clock
    (seconds; ``time_origin_ns`` as :attr:`datasets.types.Dataset.time_origin_ns`)."""
    clock = 0.0 if time_origin_ns is None else time_origin_ns * 1e-9
    from datasets.gnss import enu_to_geodetic

    lat, lon, alt = enu_to_geodetic(trajectory.position, datum)
    feature = {"type": "Feature", "properties": {"name": name, "t_start": float(clock + trajectory.t[0]),
                                                 "t_end": float(clock + trajectory.t[-1])},
               "geometry": {"type": "LineString",
                            "coordinates": np.stack([lon, lat, alt], axis=-1).round(9).tolist()}}
    with atomic_write(path) as handle:
        json.dump({"type": "FeatureCollection", "features": [feature]}, handle)
        handle.write("\n")


def jsonable(x):
    """``x`` with NumPy scalars and arrays as plain Python values and every non-finite float as None
    (JSON has no NaN or infinity), through dicts, lists and tuples."""
    if isinstance(x, dict):
        return {k: jsonable(v) for k, v in x.items()}
    if isinstance(x, (list, tuple)):
        return [jsonable(v) for v in x]
    if isinstance(x, (np.floating, float)):
        return None if not math.isfinite(float(x)) else float(x)
    if isinstance(x, np.integer):
        return int(x)
    if isinstance(x, np.ndarray):
        return jsonable(x.tolist())
    return x
