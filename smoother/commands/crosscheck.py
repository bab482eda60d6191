"""``smoother crosscheck``: batch, fixed-lag (the sliding window and GTSAM's incremental smoother) and EKF
against each other on simulated runs."""
from __future__ import annotations

import json

from smoother.errors import UserError
from smoother.estimators import ESTIMATORS


def register(sub) -> None:
    p = sub.add_parser("crosscheck", help="check that the three estimators agree where theory says they must")
    p.add_argument("--profile", default="gentle", help="simulator profile (default gentle)")
    p.add_argument("--sensors", default="pose", metavar="RIG",
                   help="the simulated rig: pose (a 10 Hz pose sensor, the default) or wheels (that pose sensor, "
                        "100 Hz wheel speeds and 4 Hz GNSS: measurements attached to 10 Hz keyframes)")
    p.add_argument("--seeds", type=int, default=5, help="Monte Carlo runs (default 5)")
    p.add_argument("--first-seed", type=int, default=0)
    p.add_argument("--duration", type=float, default=20.0, help="simulated seconds per run (default 20)")
    p.add_argument("--lag", type=float, default=2.0, help="fixed-lag window [s] (default 2)")
    p.add_argument("--json", action="store_true", help="print the result as JSON")
    p.set_defaults(handler=run)


def run(args) -> int:
    from datasets.simulate import PROFILES
    from smoother.commands import check_option
    from smoother.evaluation.crosscheck import RIGS, TARGETS, CrosscheckOptions, crosscheck
    from smoother.fixed_lag.lag import check_lag
    from smoother.progress import progress_bar

    if args.profile not in PROFILES:
        raise UserError(f"--profile {args.profile}: expected one of {', '.join(PROFILES)}")
    if args.sensors not in RIGS:
        raise UserError(f"--sensors {args.sensors}: expected one of {', '.join(RIGS)}")
    for option in ("--seeds", "--first-seed", "--duration"):
        check_option(option, getattr(args, option[2:].replace("-", "_")))
    check_lag(args.lag, "--lag", UserError)
    options = CrosscheckOptions(args.profile, args.seeds, args.first_seed, args.duration, args.lag,
                                sensors=args.sensors)
    with progress_bar(args.seeds, f"crosscheck {args.profile}", None) as bar:
        result = crosscheck(options, progress=lambda seed: bar.update(1))
    if args.json:
        print(json.dumps(result, indent=2))
    else:
        kf = result["keyframes"]
        print(f"crosscheck on '{args.profile}' with the {args.sensors} rig, {args.seeds} seeds x {args.duration:g} s; "
              f"{kf['count']} keyframes, {kf['attached']} of {kf['measurements']} measurements attached")
        print(f"  prediction_max_abs_error  {result['prediction_max_abs_error']:.3e}  "
              f"(< {TARGETS['prediction_max_abs_error']:g})")
        print(f"  final_state_max_sigma     {result['final_state_max_sigma']:.4f}  "
              f"(< {TARGETS['final_state_max_sigma']:g})")
        lo, hi = result["final_cov_trace_ratio_range"]
        print(f"  final_cov_trace_ratio     {result['final_cov_trace_ratio']:.4f}  "
              f"(range {lo:.4f}..{hi:.4f}, within 10% of 1)")
        for i, (kind, sigma) in enumerate(result["fixed_lag_max_sigma_by_kind"].items()):
            label = "fixed_lag_max_sigma" if i == 0 else ""
            print(f"  {label:<24}  {sigma:.4f}  (< {TARGETS['fixed_lag_max_sigma']:g})  {kind}")
        low, high = result["nees_interval_95"]
        for name in ESTIMATORS:
            label = f"fixed-lag ({result['fixed_lag_kind']})" if name == "fixed-lag" else name
            print(f"  {label:<21} ATE {result['ate_rmse_m'][name]:.4f} m   NEES/6 {result['nees_mean'][name]:.3f}"
                  f"  (95% interval {low:.3f}..{high:.3f})")
        failed = [k for k, v in result["checks"].items() if not v]
        print("  ok" if result["ok"] else f"  FAILED: {', '.join(failed)}")
    return 0 if result["ok"] else 1
