"""``smoother evaluate``: ATE and RPE of an estimated trajectory against a reference one, and the
NEES where the estimate carries covariances (a run directory's ``.npz``) and is not aligned.

Inputs, each in one of :data:`FORMATS` (``--format``, or recognised: ``.npz`` by its name, a
comma-separated file as EuRoC CSV, 12 numbers a line as a KITTI pose file, 5 as attitudes only,
else TUM): TUM files, EuRoC CSV (``state_groundtruth_estimate0/data.csv``: nanosecond stamps,
read as evo's ``euroc`` mode reads them), KITTI pose files (no stamps: both files must be KITTI,
paired line by line, as in evo's ``kitti`` mode), a run directory's ``.npz``, and a reference with
attitudes only (``t qx qy qz qw`` a line: an IMU's own attitude output), which gives the rotation
figures only. A run's ``.npz`` is read in the data's clock (its ``time_origin_ns`` added), so it
compares with the recording's own reference as its ``.tum`` does. Time stamps equal to the one
before are kept, as evo keeps them, with a warning.
"""
from __future__ import annotations

import json
import warnings
from dataclasses import dataclass

import numpy as np

from smoother.evaluation.modes import ALIGN_MODES, DELTA_UNITS

#: Input formats of ``--format`` (``auto``: recognised per file).
FORMATS = ("auto", "tum", "euroc", "kitti", "npz")


def register(sub) -> None:
    p = sub.add_parser(
        "evaluate",
        help="ATE and RPE of an estimated trajectory against a reference (TUM, EuRoC CSV, KITTI pose files)",
        description=(
            "Associates the two trajectories by time stamp (nearest within --max-dt), aligns the estimate "
            "onto the reference, and reports the absolute trajectory error (ATE) and the relative pose "
            "error (RPE); the definitions are evo's (see smoother/evaluation/metrics.py)."
        ),
    )
    p.add_argument("--reference", required=True, metavar="REF",
                   help="reference trajectory: a TUM file, EuRoC CSV, KITTI pose file, attitudes only "
                        "('t qx qy qz qw' a line: rotation figures only), or a run directory's .npz (e.g. truth.npz)")
    p.add_argument("--estimate", required=True, metavar="EST",
                   help="estimated trajectory: a TUM file, EuRoC CSV, KITTI pose file, or a run directory's .npz "
                        "(with covariances: NEES too)")
    p.add_argument("--format", choices=FORMATS, default="auto",
                   help="format of both files: tum, euroc (CSV, ns stamps), kitti (3x4 matrices, no stamps: "
                        "paired by line), npz; default auto: recognised per file")
    p.add_argument("--align", choices=ALIGN_MODES, default="se3",
                   help="alignment of the estimate: se3 (Umeyama, default), sim3 (Umeyama with scale: monocular "
                        "trajectories), posyaw (translation + yaw), translation, none. A rotation the positions do "
                        "not determine (a nearly straight drive) is not fitted: the next well-posed alignment is "
                        "applied, with a warning")
    p.add_argument("--n-to-align", type=int, default=None, metavar="N",
                   help="fit the alignment to the first N associated poses only (default all)")
    p.add_argument("--t-offset", type=float, default=0.0, metavar="S",
                   help="seconds added to the estimate's time stamps before association (default 0)")
    p.add_argument("--max-dt", type=float, default=0.01, metavar="S",
                   help="largest time difference of associated poses in seconds (default 0.01)")
    p.add_argument("--delta", type=float, default=1, help="RPE pair distance (default 1)")
    p.add_argument("--delta-unit", choices=DELTA_UNITS, default="frames",
                   help="unit of --delta: frames (default), m (path length), s (time)")
    p.add_argument("--json", action="store_true", help="print the results as JSON")
    p.set_defaults(handler=run)


def _table(result, args, n_ref: int, n_est: int) -> str:
    stamps = f", max dt {args.max_dt:g} s" + (f", estimate shifted by {args.t_offset:g} s" if args.t_offset else "")
    rows = [f"associated poses: {len(result.i_ref)} (reference {n_ref}, estimate {n_est}{stamps})"]
    if result.rotation_only:
        rows.append("alignment: none (the reference has attitudes only: rotation figures only)")
    else:
        fitted = ("" if args.n_to_align is None
                  else f", fitted to the first {min(args.n_to_align, len(result.i_ref))} poses")
        scale = f"s = {result.s:.6g}, " if "sim3" in result.align or "scale" in result.align else ""
        instead = "" if result.align == args.align else f" instead of {args.align}, whose rotation is not determined"
        rows.append(f"alignment: {result.align}{instead}" + ("" if result.align == "none" else
                    f" ({scale}t = [{', '.join(f'{x:.4f}' for x in result.t)}] m{fitted})"))
    rows += ["", f"{'':<22}{'rmse':>12}{'mean':>12}{'median':>12}{'std':>12}{'min':>12}{'max':>12}{'n':>7}"]
    unit = {"frames": "frames", "m": "m", "s": "s"}[args.delta_unit]
    delta = f"{args.delta:g} {unit}"
    for label, stats in (
        ("ATE translation [m]", result.ate["translation"]),
        ("ATE rotation [deg]", result.ate["rotation"]),
        ("RPE translation [m]", result.rpe["translation"]),
        ("RPE rotation [deg]", result.rpe["rotation"]),
    ):
        if stats["count"] == 0 and label.endswith("[m]") and result.rotation_only:
            continue
        rows.append(
            f"{label:<22}" + "".join(f"{stats[k]:>12.6f}" for k in ("rmse", "mean", "median", "std", "min", "max"))
            + f"{stats['count']:>7d}"
        )
    rows.append(f"(RPE over pairs {delta} apart)")
    return "\n".join(rows)


def run(args) -> int:
    from datasets.errors import DataError
    from smoother.commands import check_option
    from smoother.errors import UserError
    from smoother.evaluation import metrics
    from smoother.outputs.files import jsonable

    for option in ("--max-dt", "--t-offset", "--delta"):
        check_option(option, getattr(args, option[2:].replace("-", "_")))
    if args.n_to_align is not None:
        check_option("--n-to-align", args.n_to_align)
    if args.delta_unit == "frames" and args.delta != int(args.delta):
        raise UserError(f"--delta: expected a whole number of frames, got {args.delta!r}")
    trajectories = {}
    for option, path in (("--reference", args.reference), ("--estimate", args.estimate)):
        try:
            trajectories[option] = _read(path, args.format, attitudes=option == "--reference")
        except (DataError, ValueError, OSError, KeyError) as error:
            text = str(error)  # the readers' errors name the file themselves, most of them
            named = text if text.startswith(str(path)) else f"{path}: {text}"
            raise UserError(f"{option}: {named}") from None
    ref, est = trajectories["--reference"], trajectories["--estimate"]
    if (ref.t is None) != (est.t is None):
        kitti, other = ("--reference", "--estimate") if ref.t is None else ("--estimate", "--reference")
        raise UserError(f"{kitti} is a KITTI pose file, without time stamps: poses are paired by line, so {other} "
                        f"must be one too (--format kitti)")
    if ref.t is None:
        if len(ref) != len(est):
            raise UserError(f"KITTI pose files are paired by line: the reference has {len(ref)} poses, the estimate "
                            f"{len(est)}")
        if args.delta_unit == "s" or args.t_offset:
            raise UserError("KITTI pose files have no time stamps: --delta-unit s and --t-offset do not apply")
        ref.t = est.t = np.arange(len(ref), dtype=float)
    delta = int(args.delta) if args.delta_unit == "frames" else args.delta
    try:
        result = metrics.evaluate(
            ref.t, ref.position, ref.C, est.t, est.position, est.C, align=args.align, max_dt=args.max_dt,
            delta=delta, delta_unit=args.delta_unit, t_offset=args.t_offset, n_align=args.n_to_align,
        )
    except ValueError as error:
        raise UserError(f"{args.estimate} against {args.reference}: {error}") from None
    nees = _nees(ref, est, result, result.align)
    if result.fit is not None and result.fit.note:
        warnings.warn(result.fit.note, stacklevel=2)
    if args.json:
        out = result.as_dict()
        out["nees_mean"] = nees
        out.update({"reference": str(args.reference), "estimate": str(args.estimate), "align": result.align,
                    "formats": {"reference": ref.format, "estimate": est.format}, "t_offset": args.t_offset,
                    "n_to_align": args.n_to_align, "max_dt": args.max_dt,
                    "rpe_delta": {"value": delta, "unit": args.delta_unit}})
        print(json.dumps(jsonable(out), indent=2, allow_nan=False))
    else:
        print(_table(result, args, len(ref), len(est)))
        if nees is not None:
            print(f"pose NEES / 6 (estimate's covariances): {nees:.4f}  (1 is consistent)")
        elif est.cov is not None:
            print("(NEES only with --align none: an alignment fitted to the reference is not in the covariance)")
    return 0


@dataclass
class _Poses:
    """A trajectory as read: stamps ``t`` (None for a KITTI pose file), positions (NaN: attitudes
    only), attitudes, the format it was read as, and for a run's ``.npz`` its states and
    covariances (else states with the positions and attitudes, NaN elsewhere)."""

    t: np.ndarray | None
    position: np.ndarray
    C: np.ndarray
    format: str
    states: object = None
    cov: np.ndarray | None = None

    def __post_init__(self):
        if self.states is None:
            from factors.imu import ImuState

            nan = np.full((len(self.C), 3), np.nan)
            self.states = ImuState(r=self.position, v=nan, C=self.C, b_f=nan, b_w=nan)

    def __len__(self) -> int:
        return len(self.C)


def _format_of(path) -> str:
    """The format of ``path`` as recognised: ``.npz`` by its name, else by its first data line (a
    comma: EuRoC CSV; 12 fields: KITTI; otherwise TUM, with or without positions)."""
    from datasets.errors import data_lines, read_lines

    if str(path).endswith(".npz"):
        return "npz"
    first = next((text for _, text in data_lines(read_lines(path))), "")
    if "," in first:
        return "euroc"
    return "kitti" if len(first.split()) == 12 else "tum"


def _read(path, fmt: str = "auto", attitudes: bool = False) -> _Poses:
    """The trajectory in ``path`` in format ``fmt`` (see the module docstring); with
    ``attitudes`` a TUM-like file may hold attitudes only. Stamps equal to the one before are
    kept, with a warning (:func:`datasets.errors.duplicate_stamps`)."""
    from datasets.errors import duplicate_stamps
    from datasets.euroc import read_pose_csv
    from datasets.kitti import read_pose_file
    from datasets.tum import read_tum_poses
    from smoother.outputs.files import load_stamped_trajectory

    fmt = _format_of(path) if fmt == "auto" else fmt
    if fmt == "npz":  # stamped in the data's clock, as the run's .tum files are
        trajectory, origin_ns = load_stamped_trajectory(path)
        t = trajectory.t if origin_ns is None else trajectory.t + origin_ns * 1e-9
        return _Poses(t, trajectory.position, trajectory.C, fmt, trajectory.states, trajectory.cov)
    if fmt == "kitti":
        r, C, _ = read_pose_file(path)
        return _Poses(None, r, C, fmt)
    if fmt == "euroc":
        t, r, C, lines = read_pose_csv(path, duplicates=True)
    else:
        t, r, C, lines = read_tum_poses(path, duplicates=True, attitudes=attitudes)
        fmt = "attitudes" if np.isnan(r).all() else "tum"
    repeated = duplicate_stamps(path, t, lines)
    if repeated:
        warnings.warn(f"{repeated}: kept, as evo keeps them (association pairs a stamp with the nearest, among equal "
                      f"ones the last before it or the first after it)", stacklevel=2)
    return _Poses(t, r, C, fmt)


def _nees(ref, est, result, align: str) -> float | None:
    """Mean pose NEES / 6 of the associated poses when the estimate carries covariances and is
    compared in its own frame (``--align none``). An alignment fitted to the reference would
    move the estimate by an amount its covariance knows nothing about (a position-fitted
    rotation of 0.1 deg is several attitude sigmas of a good smoother), so no NEES then; nor
    against a reference with attitudes only."""
    from smoother.evaluation import metrics

    if est.cov is None or align != "none" or result.rotation_only:
        return None
    nees = metrics.nees(ref.states[result.i_ref], est.states[result.i_est], est.cov[result.i_est], "pose")
    return float(np.mean(nees) / 6.0)

