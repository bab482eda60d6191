"""``smoother check-jacobians``: every analytic Jacobian against central differences."""
from __future__ import annotations

import json
import sys


def register(sub) -> None:
    p = sub.add_parser("check-jacobians", help="every analytic Jacobian against central differences")
    p.add_argument("--json", action="store_true", help="print JSON: one object per check")
    p.add_argument("--samples", type=int, default=200, help="random points per check (default 200)")
    p.add_argument("--seed", type=int, default=0, help="random seed (default 0)")
    p.set_defaults(handler=run)


def run(args) -> int:
    import datasets.kinds  # noqa: F401  (registers every kind's measurement-model check)
    from factors import jacobians, selfcheck
    from smoother.commands import check_option

    check_option("--samples", args.samples)
    check_option("--seed", args.seed)
    results = selfcheck.run_checks(samples=args.samples, seed=args.seed)
    if args.json:
        print(json.dumps([r.as_dict() for r in results], indent=2))
    else:
        title = f"analytic vs numerical Jacobians ({args.samples} random points each, seed {args.seed})"
        print(jacobians.table(results, title=title))
    failed = [r.name for r in results if not r.ok]
    if failed:
        print(f"FAILED: {', '.join(failed)}", file=sys.stderr)
    return 1 if failed else 0
