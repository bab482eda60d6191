"""``smoother allan SOURCE``: the IMU noise densities of a static recording by Allan deviation
(:mod:`datasets.allan`), printed as an ``[imu]`` block for a rig file
(:func:`datasets.rig_writer.allan_imu_block`), and ``allan.png``."""
from __future__ import annotations

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


def run(args) -> int:
    from datasets.allan import allan, motion
    from datasets.rig_writer import allan_imu_block
    from datasets.sources import read_imu
    from factors.errors import InputError
    from smoother.commands import output_directory
    from smoother.outputs.allan_plot import plot_allan

    out = output_directory(args.out)
    imu = read_imu(args.source, args.topic)
    moving = motion(imu)
    if moving is not None:
        print(f"warning: {args.source} does not look static ({moving}): the densities below describe its motion, "
              "not the sensor's noise", file=sys.stderr)
    try:
        result = allan(imu)
    except InputError as error:  # the samples, not a file's syntax: say whose
        raise InputError(f"{args.source}: {error}") from None
    print(allan_imu_block(result, args.source, args.topic, len(imu)))
    for note in (result.still_note(), result.walk_note()):
        if note is not None:
            print(f"warning: {note}", file=sys.stderr)
    print(f"wrote {plot_allan(result, out)}", file=sys.stderr)
    return 0
