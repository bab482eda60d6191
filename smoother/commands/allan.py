"""``smoother allan SOURCE``: the IMU noise densities of a static recording by Allan deviation
(:mod:`datasets.allan`), printed as an ``[imu]`` block for a rig file, and ``allan.png``."""
from __future__ import annotations

import json
import sys


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


def imu_block(result, source: str, topic: str | None, n: int) -> str:
    """The densities as a rig file's ``[imu]`` block, with the per-axis values as comments."""
    noise = result.noise()
    rows = [
        f"# Allan deviation of {n} samples at {1 / result.dt:.6g} Hz ({n * result.dt:.1f} s)",
        f"# {'per axis':<28}{'x':>12}{'y':>12}{'z':>12}",
    ]
    for label, values in (("accel_noise_density", result.acc_white), ("gyro_noise_density", result.gyro_white),
                          ("accel_random_walk", result.acc_walk), ("gyro_random_walk", result.gyro_walk)):
        rows.append(f"# {label:<28}" + "".join(f"{v:>12.4e}" for v in values))
    rows += ["[imu]", f"source = {json.dumps(source)}"]  # a JSON string is a TOML basic string
    if topic is not None:
        rows.append(f"topic = {json.dumps(topic)}")
    rows += [
        f"accel_noise_density = {noise.acc:.4e}    # m/s^2/sqrt(Hz), largest axis",
        f"gyro_noise_density = {noise.gyro:.4e}     # rad/s/sqrt(Hz)",
        f"accel_random_walk = {noise.acc_bias:.4e}    # m/s^3/sqrt(Hz)",
        f"gyro_random_walk = {noise.gyro_bias:.4e}     # rad/s^2/sqrt(Hz)",
    ]
    return "\n".join(rows)


def run(args) -> int:
    from datasets.allan import allan, motion
    from datasets.sources import read_imu
    from smoother.commands import output_directory
    from smoother.plots import plot_allan

    out = output_directory(args.out)
    imu = read_imu(args.source, args.topic)
    moving = motion(imu)
    if moving is not None:
        print(f"warning: {args.source} does not look static ({moving}): the densities below describe its motion, "
              "not the sensor's noise", file=sys.stderr)
    result = allan(imu)
    print(imu_block(result, args.source, args.topic, len(imu)))
    print(f"wrote {plot_allan(result, out)}", file=sys.stderr)
    return 0
