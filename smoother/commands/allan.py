"""``smoother allan SOURCE``: the IMU noise densities of a static recording by Allan deviation
(:mod:`datasets.allan`), printed as an ``[imu]`` block for a rig file, and ``allan.png``."""
from __future__ import annotations

import json
import sys

import numpy as np


def register(sub) -> None:
    p = sub.add_parser(
        "allan",
        help="IMU noise densities of a static recording (Allan deviation), as a rig file's [imu] block",
        description=(
            "Reads the IMU samples of SOURCE (bag:FILE with --topic, or csv:FILE in the EuRoC/ASL layout), "
            "computes the overlapping Allan deviation of each accelerometer and gyro axis, fits the white-noise "
            "(slope -1/2, read at 1 s) and random-walk (slope +1/2, read at 3 s) lines, prints the four "
            "densities (largest axis) as an [imu] block to paste into a rig file, and writes allan.png. "
            "The IMU must be at rest for the whole recording, ideally for hours."
        ),
    )
    p.add_argument("source", metavar="SOURCE", help="bag:FILE (ROS 1 .bag, ROS 2 folder, .db3, .mcap) or csv:FILE")
    p.add_argument("--topic", default=None, metavar="T", help="the sensor_msgs/Imu topic (bag sources)")
    p.add_argument("--out", default=".", metavar="DIR", help="where to write allan.png (default: here)")
    p.set_defaults(handler=run)


#: Per density: the rig file's key, the ImuNoise field, the per-axis values' attribute of an
#: AllanResult and the unit.
_KEYS = (("accel_noise_density", "acc", "acc_white", "m/s^2/sqrt(Hz), largest axis"),
         ("gyro_noise_density", "gyro", "gyro_white", "rad/s/sqrt(Hz)"),
         ("accel_random_walk", "acc_bias", "acc_walk", "m/s^3/sqrt(Hz)"),
         ("gyro_random_walk", "gyro_bias", "gyro_walk", "rad/s^2/sqrt(Hz)"))


def imu_block(result, source: str, topic: str | None, n: int) -> str:
    """The densities as a rig file's ``[imu]`` block, with the per-axis values as comments; a
    random walk the data do not show is left out of the block (commented, to be filled in)."""
    largest = result.largest()
    rows = [
        f"# Allan deviation of {n} samples at {1 / result.dt:.6g} Hz ({n * result.dt:.1f} s)",
        f"# {'per axis':<28}{'x':>12}{'y':>12}{'z':>12}",
    ]
    for key, _, axes, _ in _KEYS:
        rows.append(f"# {key:<28}" + "".join(f"{'-' if np.isnan(v) else f'{v:.4e}':>12}"
                                             for v in getattr(result, axes)))
    rows += ["[imu]", f"source = {json.dumps(source)}"]  # a JSON string is a TOML basic string
    if topic is not None:
        rows.append(f"topic = {json.dumps(topic)}")
    for key, field, _, unit in _KEYS:
        value = largest[field]
        rows.append(f"# {key} = ?    # not estimated: the recording is too short (see the warning)"
                    if np.isnan(value) else f"{key} = {value:.4e}    # {unit}")
    return "\n".join(rows)


def run(args) -> int:
    from datasets.allan import allan, motion
    from datasets.sources import read_imu
    from smoother.commands import output_directory
    from smoother.outputs.allan_plot import plot_allan

    out = output_directory(args.out)
    imu = read_imu(args.source, args.topic)
    moving = motion(imu)
    if moving is not None:
        print(f"warning: {args.source} does not look static ({moving}): the densities below describe its motion, "
              "not the sensor's noise", file=sys.stderr)
    result = allan(imu)
    print(imu_block(result, args.source, args.topic, len(imu)))
    if result.walk_note() is not None:
        print(f"warning: {result.walk_note()}", file=sys.stderr)
    print(f"wrote {plot_allan(result, out)}", file=sys.stderr)
    return 0
