"""``smoother montecarlo``: seeded simulations through the estimators, in parallel."""
from __future__ import annotations

import json
import sys

from smoother.errors import UserError
from smoother.estimators import ESTIMATORS

#: The summary of the runs in ``--out``.
SUMMARY = "summary.json"


def register(sub) -> None:
    p = sub.add_parser("montecarlo", help="Monte Carlo runs of the simulator (parallel; optionally on Dask)")
    p.add_argument("--runs", type=int, default=20, help="number of seeded runs (default 20)")
    p.add_argument("--first-seed", type=int, default=0)
    p.add_argument("--workers", type=int, default=1, help="processes on this machine (default 1)")
    p.add_argument("--dask", metavar="ADDRESS", default=None,
                   help="send the runs to an existing Dask scheduler (optional extra 'dask')")
    p.add_argument("--profile", default="gentle")
    p.add_argument("--duration", type=float, default=10.0, help="simulated seconds per run (default 10)")
    p.add_argument("--estimator", action="append", choices=list(ESTIMATORS),
                   help="estimators to run (repeatable; default batch and ekf)")
    p.add_argument("--outliers", type=float, default=0.0, help="fraction of pose measurements made outliers")
    p.add_argument("--robust", action="append", default=[], metavar="[SENSOR=]KERNEL[:T]",
                   help="robust kernel none|huber|cauchy|tukey[:T] for every sensor or the one named (pose)")
    p.add_argument("--out", default="montecarlo", help="output directory (default ./montecarlo)")
    p.add_argument("--json", action="store_true", help="print the summary as JSON")
    p.set_defaults(handler=run)


def run(args) -> int:
    from datasets.simulate import DEFAULT_SENSOR_NAMES, PROFILES
    from smoother.commands import check_option, check_workers, output_directory
    from smoother.commands.run import parse_robust
    from smoother.evaluation import montecarlo
    from smoother.progress import progress_bar

    if args.profile not in PROFILES:
        raise UserError(f"--profile {args.profile}: expected one of {', '.join(PROFILES)}")
    for option in ("--runs", "--first-seed", "--duration", "--outliers"):
        check_option(option, getattr(args, option[2:].replace("-", "_")))
    check_workers(args.workers, args.dask)
    estimators = tuple(args.estimator or ("batch", "ekf"))
    config = montecarlo.MonteCarloConfig(
        profile=args.profile, duration=args.duration, estimators=estimators, outliers=args.outliers,
        robust=tuple(sorted(parse_robust(args.robust, DEFAULT_SENSOR_NAMES).items())),
    )
    out = output_directory(args.out)
    seeds = range(args.first_seed, args.first_seed + args.runs)
    with progress_bar(args.runs, "monte carlo", None) as bar:
        results = montecarlo.run_many(config, seeds, args.workers, dask_address=args.dask, out_dir=out,
                                      on_done=lambda r: bar.update(1))
    summary = montecarlo.aggregate(results, estimators)
    from datasets.atomic import atomic_write
    from smoother.confined import inside

    with atomic_write(inside(out, SUMMARY)) as handle:
        json.dump(summary.as_dict(), handle, indent=2)
    from smoother.outputs.montecarlo_plot import plot_montecarlo

    path = plot_montecarlo(summary, out)
    if args.json:
        brief = {k: {m: v for m, v in e.items() if m not in ("t", "nees_per_keyframe")}
                 for k, e in summary.estimators.items()}
        print(json.dumps({"runs": summary.runs, "nees_interval_95": summary.nees_interval_95, **brief}, indent=2))
    else:
        low, high = summary.nees_interval_95
        print(f"{summary.runs} runs of '{args.profile}' x {args.duration:g} s; per-keyframe NEES/6 "
              f"averaged over runs, 95% interval {low:.3f}..{high:.3f}")
        for name, e in summary.estimators.items():
            print(f"  {name:<10} ATE {e['ate_rmse_m']:.4f} m  rot {e['rot_rmse_deg']:.3f} deg  "
                  f"NEES/6 {e['nees_mean']:.3f}  inside {100 * e['nees_share_inside_95']:.0f}%")
    print(f"wrote {out / SUMMARY}, {path}", file=sys.stderr)
    return 0
