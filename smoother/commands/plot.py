"""``smoother plot DIR``: the figures of a run directory (see :mod:`smoother.outputs.plots`) as PNG files."""
from __future__ import annotations

import sys


def register(sub) -> None:
    p = sub.add_parser(
        "plot",
        help="write the figures (PNG) of a run directory made by smoother run",
        description=(
            "Reads <estimator>.npz, truth.npz (if any), gps.npz (if any) and metrics.json from DIR and writes "
            "trajectory.png, position_error.png, orientation_error.png, nees.png, biases.png and "
            "comparison.png (the ones the data allow: error figures need a truth or GPS fixes)."
        ),
    )
    p.add_argument("dir", metavar="DIR", help="run directory written by smoother run --out DIR")
    p.add_argument("--estimators", nargs="+", metavar="NAME",
                   help="estimators to draw, e.g. batch ekf (default: every <name>.npz in DIR)")
    p.add_argument("--out", default=None, metavar="OUT_DIR", help="where to write the PNGs (default DIR)")
    p.set_defaults(handler=run)


def run(args) -> int:
    from smoother.commands import output_directory
    from smoother.outputs import plots

    if args.out is not None:
        output_directory(args.out)
    for path in plots.plot_run(args.dir, estimators=args.estimators, out_dir=args.out):
        print(f"wrote {path}", file=sys.stderr)
    return 0
