"""``smoother evaluate``: ATE and RPE of an estimated trajectory against a reference one, and the
NEES where the estimate carries covariances (a run directory's ``.npz``) and is not aligned."""
from __future__ import annotations

import json


def register(sub) -> None:
    p = sub.add_parser(
        "evaluate",
        help="ATE and RPE of an estimated trajectory against a reference (TUM files)",
        description=(
            "Associates the two trajectories by time stamp (nearest within --max-dt), aligns the estimate "
            "onto the reference, and reports the absolute trajectory error (ATE) and the relative pose "
            "error (RPE); the definitions are evo's (see smoother/metrics.py)."
        ),
    )
    p.add_argument("--reference", required=True, metavar="REF",
                   help="reference trajectory: a TUM file, or a run directory's .npz (e.g. truth.npz)")
    p.add_argument("--estimate", required=True, metavar="EST",
                   help="estimated trajectory: a TUM file, or a run directory's .npz (with covariances: NEES too)")
    p.add_argument("--align", choices=["se3", "posyaw", "none"], default="se3",
                   help="alignment of the estimate: se3 (Umeyama, default), posyaw (translation + yaw), none")
    p.add_argument("--max-dt", type=float, default=0.01, metavar="S",
                   help="largest time difference of associated poses in seconds (default 0.01)")
    p.add_argument("--delta", type=float, default=1, help="RPE pair distance (default 1)")
    p.add_argument("--delta-unit", choices=["frames", "m", "s"], default="frames",
                   help="unit of --delta: frames (default), m (path length), s (time)")
    p.add_argument("--json", action="store_true", help="print the results as JSON")
    p.set_defaults(handler=run)


def _table(result, args, n_ref: int, n_est: int) -> str:
    rows = [
        f"associated poses: {len(result.i_ref)} (reference {n_ref}, estimate {n_est}, max dt {args.max_dt:g} s)",
        f"alignment: {args.align}" + ("" if args.align == "none" else
                                      f" (t = [{', '.join(f'{x:.4f}' for x in result.t)}] m)"),
        "",
        f"{'':<22}{'rmse':>12}{'mean':>12}{'median':>12}{'std':>12}{'min':>12}{'max':>12}{'n':>7}",
    ]
    unit = {"frames": "frames", "m": "m", "s": "s"}[args.delta_unit]
    delta = f"{args.delta:g} {unit}"
    for label, stats in (
        ("ATE translation [m]", result.ate["translation"]),
        ("ATE rotation [deg]", result.ate["rotation"]),
        ("RPE translation [m]", result.rpe["translation"]),
        ("RPE rotation [deg]", result.rpe["rotation"]),
    ):
        rows.append(
            f"{label:<22}" + "".join(f"{stats[k]:>12.6f}" for k in ("rmse", "mean", "median", "std", "min", "max"))
            + f"{stats['count']:>7d}"
        )
    rows.append(f"(RPE over pairs {delta} apart)")
    return "\n".join(rows)


def run(args) -> int:
    import math

    from datasets.errors import DataError
    from smoother import metrics
    from smoother.commands import positive
    from smoother.errors import UserError

    if not (math.isfinite(args.max_dt) and args.max_dt >= 0):
        raise UserError(f"--max-dt: expected a time in seconds >= 0, got {args.max_dt!r}")
    positive("--delta", args.delta)
    if args.delta_unit == "frames" and args.delta != int(args.delta):
        raise UserError(f"--delta: expected a whole number of frames, got {args.delta!r}")
    trajectories = {}
    for option, path in (("--reference", args.reference), ("--estimate", args.estimate)):
        try:
            trajectories[option] = _read(path)
        except (DataError, ValueError, OSError, KeyError) as error:
            raise UserError(f"{option}: {path}: {error}") from None
    ref, est = trajectories["--reference"], trajectories["--estimate"]
    delta = int(args.delta) if args.delta_unit == "frames" else args.delta
    try:
        result = metrics.evaluate(
            ref.t, ref.position, ref.C, est.t, est.position, est.C,
            align=args.align, max_dt=args.max_dt, delta=delta, delta_unit=args.delta_unit,
        )
    except ValueError as error:
        raise UserError(f"{args.estimate} against {args.reference}: {error}") from None
    nees = _nees(ref, est, result, args.align)
    if args.json:
        out = result.as_dict()
        out["nees_mean"] = nees
        out.update({"reference": str(args.reference), "estimate": str(args.estimate), "align": args.align,
                    "max_dt": args.max_dt, "rpe_delta": {"value": delta, "unit": args.delta_unit}})
        print(json.dumps(_clean(out), indent=2, allow_nan=False))
    else:
        print(_table(result, args, len(ref), len(est)))
        if nees is not None:
            print(f"pose NEES / 6 (estimate's covariances): {nees:.4f}  (1 is consistent)")
        elif est.cov is not None:
            print("(NEES only with --align none: an alignment fitted to the reference is not in the covariance)")
    return 0


def _read(path):
    """A TUM file, or a run directory's ``.npz`` (states and, if present, covariances)."""
    from datasets.tum import read_tum
    from smoother.report import load_trajectory

    return load_trajectory(path) if str(path).endswith(".npz") else read_tum(path)


def _nees(ref, est, result, align: str) -> float | None:
    """Mean pose NEES / 6 of the associated poses when the estimate carries covariances and is
    compared in its own frame (``--align none``). An alignment fitted to the reference would
    move the estimate by an amount its covariance knows nothing about (a position-fitted
    rotation of 0.1 deg is several attitude sigmas of a good smoother), so no NEES then."""
    import numpy as np

    from smoother import metrics

    if est.cov is None or align != "none":
        return None
    nees = metrics.nees(ref.states[result.i_ref], est.states[result.i_est], est.cov[result.i_est], "pose")
    return float(np.mean(nees) / 6.0)


def _finite(obj) -> bool:
    if isinstance(obj, float):
        return obj == obj and obj not in (float("inf"), float("-inf"))
    if isinstance(obj, dict):
        return all(_finite(v) for v in obj.values())
    if isinstance(obj, (list, tuple)):
        return all(_finite(v) for v in obj)
    return True


def _clean(obj):
    """NaN/inf -> None so that the output is valid JSON (e.g. RPE with no pairs)."""
    if isinstance(obj, float):
        return obj if _finite(obj) else None
    if isinstance(obj, dict):
        return {k: _clean(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [_clean(v) for v in obj]
    return obj

