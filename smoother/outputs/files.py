"""A run's files, written and read back: every estimate as ``<estimator>.tum`` (TUM trajectory,
stamped in the data's own clock: :attr:`datasets.types.Dataset.time_origin_ns`),
``<estimator>.npz`` (the full states and covariances, times from the run's start and the clock's
origin beside them) and, with a GNSS datum, ``<estimator>.geojson``; ``truth.npz`` and ``gps.npz``
(arrays ``t`` (M,), ``position`` (M, 3), ``cov`` (M, 3, 3) and ``heldout`` (M,) bool: fixes kept
out of estimation) where known; ``metrics.json`` (the scores of :mod:`smoother.evaluation.scoring`
and the run's record). The names are :mod:`smoother.outputs.layout`'s. Every file is written
atomically. :func:`write_outputs` writes them into a folder; ``smoother run`` writes them through
:class:`smoother.commands.run_directory.RunDirectory` (one run at a time, the previous run's files
replaced together). :func:`load_run` reads a run directory back (``smoother plot``). The readers
name the file and what was expected when it is not one of these.
"""
from __future__ import annotations

import contextlib
import json
import math
import pickle
import zipfile
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from datasets.atomic import atomic_write
from datasets.errors import LIMITS, DataError, check_source, read_source
from datasets.initialise import world_frame
from datasets.kinds import sensors_of
from datasets.tum import write_tum
from datasets.types import Dataset, Trajectory
from factors import imu
from factors.errors import InputError
from smoother.estimators import ESTIMATORS
from smoother.evaluation.scoring import position_streams, score
from smoother.outputs.layout import GPS, METRICS, TRUTH


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
    block; an :class:`~factors.errors.InputError` naming the file and ``expected`` when it is not
    such an archive, cannot be read or holds arrays the block refuses (a ``ValueError`` there, e.g.
    a data type's validation, ``Trajectory.cov: expected shape ...``, then prefixed with the file)."""
    check_source(path, "npz")  # a regular file (a pipe blocked np.load for ever) within the limit
    try:
        is_zip = zipfile.is_zipfile(path)
    except OSError as error:
        raise InputError(f"{path}: cannot read it ({error.strerror or error}); expected {expected}") from None
    if not is_zip:
        raise InputError(f"{path}: not an .npz archive; expected {expected}")
    try:
        _check_unpacked(path)
        with np.load(path, allow_pickle=False) as data:
            yield data
    except InputError as error:  # the block's own, naming the file, or a data type's, naming its field
        if str(error).startswith(str(path)):
            raise
        raise InputError(f"{path}: {error}") from None
    except _NPZ_ERRORS as error:
        raise InputError(f"{path}: cannot read it ({error}); expected {expected}") from None


def _check_unpacked(path: Path) -> None:
    """The arrays of the ``.npz`` ``path`` fit :data:`datasets.errors.LIMITS` ``["npz"]`` unpacked
    too, each no larger than its member of the archive: ``np.load`` allocates an array as its
    header's shape says before it reads a byte of it, and an archive compresses gigabytes of zeros
    into megabytes. A :class:`~datasets.errors.DataError` naming the file and the array otherwise."""
    limit = LIMITS["npz"]
    readers = {(1, 0): np.lib.format.read_array_header_1_0, (2, 0): np.lib.format.read_array_header_2_0}
    with zipfile.ZipFile(path) as archive:
        members = archive.infolist()
        total = sum(info.file_size for info in members)
        if total > limit.bytes:
            raise DataError(path, None, None, f"arrays of {total} bytes unpacked",
                            f"at most {limit.bytes} bytes, the limit of {limit.files}: {limit.why}", whole=True)
        for info in members:
            if not info.filename.endswith(".npy"):
                continue
            with archive.open(info) as member:
                version = np.lib.format.read_magic(member)
                if version not in readers:  # np.save writes 1.0 (2.0 for headers beyond 64 kB)
                    raise DataError(path, None, info.filename.removesuffix(".npy"), f".npy format {version}",
                                    "an array as np.save writes it (format 1.0 or 2.0)", whole=True)
                shape, _, dtype = readers[version](member)
            size = math.prod(shape) * dtype.itemsize
            if size > info.file_size:
                raise DataError(path, None, info.filename.removesuffix(".npy"),
                                f"an array of shape {shape} ({size} bytes) in {info.file_size} bytes",
                                "an array no larger than its file in the archive", whole=True)


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
    parts = [(p, flag) for _, *pair in position_streams(dataset) for p, flag in zip(pair, (False, True))
             if p is not None]
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
    estimators, ``aiding_sensors``, ``correlation_times_s`` of the drifting ones (their
    ``correlation_time``, where any has one), ``dead_reckoning``: true without any, and ``world_frame``:
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
        report[name] = {**score(dataset, est.trajectory, est.calibration, est.following, est.heldout),
                        "runtime_s": est.runtime_s, **est.details}
    if dataset.truth is not None:
        save_trajectory(out_dir / TRUTH, dataset.truth, dataset.time_origin_ns)
    save_gps(out_dir / GPS, dataset)
    aiding = aiding_sensors(dataset)
    drifting = dataset.correlation_times
    document = {**report, "_run": {**(extra or {}), "estimators": list(estimates), "aiding_sensors": aiding,
                                   **({"correlation_times_s": drifting} if drifting else {}),
                                   "dead_reckoning": not aiding,
                                   "world_frame": world_frame(sensors_of(dataset)).describe()}}
    with atomic_write(out_dir / METRICS) as handle:
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


# --- reading a run directory back ---------------------------------------------------------------

#: Estimators in the order a run directory's estimates are read (others after them, by name).
ESTIMATOR_ORDER = ESTIMATORS


@dataclass(frozen=True)
class Gps:
    """A run's position fixes (``gps.npz``): times, positions, covariances (or None) and which
    were held out of estimation."""

    t: np.ndarray
    position: np.ndarray
    cov: np.ndarray | None
    heldout: np.ndarray


@dataclass(frozen=True)
class Run:
    """What :func:`load_run` read: the estimates by name (in :func:`estimator_names`' order), the
    truth and the fixes (or None), and ``metrics.json`` (empty without one)."""

    run_dir: Path
    estimates: dict
    truth: Trajectory | None
    gps: Gps | None
    metrics: dict

    @property
    def t0(self) -> float:
        """The first estimate's time."""
        return min(float(tr.t[0]) for tr in self.estimates.values())


def load_gps(path: Path) -> Gps:
    """The fixes :func:`save_gps` wrote; an :class:`~factors.errors.InputError` naming the file
    for anything else."""
    expected = "an .npz with arrays t (M,), position (M, 3) and optionally cov (M, 3, 3) and heldout (M,) bool"
    with read_npz(path, expected) as data:
        t = np.asarray(data["t"], dtype=float)
        position = np.asarray(data["position"], dtype=float)
        cov = np.asarray(data["cov"], dtype=float) if "cov" in data else None
        heldout = np.asarray(data["heldout"], dtype=bool) if "heldout" in data else np.zeros(len(t), bool)
    n = len(t)
    if (t.ndim != 1 or position.shape != (n, 3) or heldout.shape != (n,)
            or (cov is not None and cov.shape != (n, 3, 3))):
        covariances = "" if cov is None else f", cov {cov.shape}"
        raise InputError(f"{path}: inconsistent shapes (t {t.shape}, position {position.shape}{covariances}, "
                         f"heldout {heldout.shape}); expected {expected}")
    if n > 1 and np.any(np.diff(t) <= 0):
        raise InputError(f"{path}: the times t must increase strictly")
    return Gps(t, position, cov, heldout)


def estimator_names(run_dir: Path) -> list[str]:
    """Names of the estimates in ``run_dir``, in :data:`ESTIMATOR_ORDER`: those of the last run
    when ``metrics.json`` lists them (so an older run's files left in the directory are not
    read), else every ``<name>.npz`` other than the truth and the fixes."""
    found = {p.stem for p in Path(run_dir).glob("*.npz") if p.name not in (TRUTH, GPS)}
    try:
        listed = json.loads(read_source(Path(run_dir) / METRICS, "json"))["_run"]["estimators"]
        found &= set(listed)
    except (OSError, ValueError, KeyError, TypeError):  # none, or not one (load_run names it)
        pass
    return [n for n in ESTIMATOR_ORDER if n in found] + sorted(found - set(ESTIMATOR_ORDER))


def load_run(run_dir, estimators=None) -> Run:
    """Read a run directory (``estimators``: the names to read, default all of
    :func:`estimator_names`); an :class:`~factors.errors.InputError` naming the file for anything
    missing or malformed."""
    run_dir = Path(run_dir)
    if not run_dir.is_dir():
        raise InputError(f"{run_dir}: not a directory; expected the output directory of smoother run")
    available = estimator_names(run_dir)
    if not available:
        raise InputError(f"{run_dir}: no estimate found; expected <estimator>.npz files "
                         f"(e.g. {', '.join(f'{n}.npz' for n in ESTIMATOR_ORDER)}) written by smoother run")
    names = available if not estimators else list(dict.fromkeys(estimators))
    for name in names:
        if name not in available:
            raise InputError(f"{run_dir / (name + '.npz')}: not found; this run has {', '.join(available)}")
    estimates = {name: load_trajectory(run_dir / f"{name}.npz") for name in names}
    truth = load_trajectory(run_dir / TRUTH) if (run_dir / TRUTH).exists() else None
    gps = load_gps(run_dir / GPS) if (run_dir / GPS).exists() else None
    document: dict = {}
    path = run_dir / METRICS
    if path.exists():
        try:
            document = json.loads(read_source(path, "json"))  # a regular file: a pipe blocked the read
        except DataError:  # not a regular file, too large: it names the file
            raise
        except (OSError, ValueError) as error:
            raise InputError(f"{path}: cannot read it ({error}); expected the JSON object smoother run "
                             "writes") from None
        if not isinstance(document, dict):
            raise InputError(f"{path}: expected a JSON object with one entry per estimator, "
                             f"got {type(document).__name__}")
    return Run(run_dir, estimates, truth, gps, document)
