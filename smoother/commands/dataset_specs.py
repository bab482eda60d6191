"""Turning a ``--dataset`` spec into a :class:`datasets.types.Dataset`.

``synthetic[:PROFILE]`` (the simulator, default profile ``gentle``), ``kitti`` (GTSAM's shipped
KITTI IMU + GPS example), ``euroc:PATH`` (an EuRoC/ASL folder). Errors in the spec or the data
become :class:`smoother.errors.UserError` naming what was wrong.
"""
from __future__ import annotations

from dataclasses import dataclass, replace

from datasets.types import Dataset
from smoother.errors import UserError


@dataclass
class SourceOptions:
    """Options that shape a dataset: simulator settings and measurements made from truth."""

    seed: int = 0
    duration: float = 30.0
    outliers: float = 0.0
    gps_every: int = 1
    pose_from_truth: tuple | None = None  # (hz, pos_sigma_m, rot_sigma_rad)
    gps_from_truth: tuple | None = None  # (hz, pos_sigma_m)


def load(spec: str, options: SourceOptions = SourceOptions()) -> Dataset:
    """The dataset named by ``spec`` (see the module docstring)."""
    kind, _, arg = spec.partition(":")
    try:
        if kind == "synthetic":
            from datasets.simulate import PROFILES, simulate

            profile = arg or "gentle"
            if profile not in PROFILES:
                raise UserError(f"--dataset synthetic:{profile}: unknown profile; expected one of "
                                f"{', '.join(PROFILES)}")
            try:
                dataset = simulate(profile=profile, duration=options.duration, seed=options.seed,
                                   outlier_fraction=options.outliers)
            except ValueError as error:  # the other arguments are checked before, with their options' names
                message = str(error)
                raise UserError("--" + message if message.startswith("duration:") else message) from None
        elif kind == "kitti":
            from datasets.kitti import load_kitti

            if arg:
                raise UserError(f"--dataset {spec}: kitti takes no path (it is the KITTI example shipped inside "
                                "the gtsam wheel); for a recording of your own write a rig file: --rig RIG.toml")

            dataset = load_kitti(gps_every=options.gps_every)
        elif kind == "euroc":
            from datasets.euroc import load_euroc

            if not arg:
                raise UserError("--dataset euroc:PATH needs the path of an EuRoC/ASL folder")
            dataset = load_euroc(arg)
        else:
            raise UserError(f"--dataset {spec!r}: expected synthetic[:PROFILE], kitti or euroc:PATH")
    except UserError:
        raise
    except (ValueError, OSError) as error:
        raise UserError(str(error)) from None
    return _with_truth_measurements(dataset, options)


def load_rig_dataset(path, part: tuple | None = None) -> tuple[Dataset, dict]:
    """The recording a rig file describes (:func:`datasets.recording.load_recording`; ``part``:
    ``(start, end)`` of it, ``--start`` and ``--end``) and the robust kernels its sensors ask for,
    by sensor name; errors become one-line UserErrors."""
    from datasets.recording import PartError, load_recording
    from datasets.rig import load_rig

    try:
        rig = load_rig(path)
        dataset = load_recording(rig, part=part)
    except PartError as error:
        raise UserError(f"--start/--end: {error}") from None
    except (ValueError, OSError) as error:
        raise UserError(f"{path}: {error}" if str(path) not in str(error) else str(error)) from None
    return dataset, {s.name: s.robust for s in rig.sensors if s.robust is not None}


def _with_truth_measurements(dataset: Dataset, options: SourceOptions) -> Dataset:
    """Add the sensors ``pose`` / ``gps`` drawn from the ground truth (``--pose-from-truth``,
    ``--gps-from-truth``; :func:`datasets.simulated_sensors.truth_sensors`, independent noise
    streams from ``--seed``), in place of any of the same name."""
    if options.pose_from_truth is None and options.gps_from_truth is None:
        return dataset
    if dataset.truth is None:
        raise UserError(f"--pose-from-truth/--gps-from-truth: dataset {dataset.name!r} has no ground truth")
    from datasets.simulated_sensors import truth_sensors

    try:
        drawn = truth_sensors(dataset.truth, dataset.imu, options.pose_from_truth, options.gps_from_truth,
                              options.seed)
    except ValueError as error:  # "pose_from_truth: ..." -> "--pose-from-truth: ..."
        option, _, reason = str(error).partition(": ")
        raise UserError(f"--{option.replace('_', '-')}: {reason}") from None
    names = {s.name for s in drawn}
    return replace(dataset, sensors=tuple(s for s in dataset.sensors if s.name not in names) + drawn)
