"""The ``smoother`` command line."""
from __future__ import annotations

import argparse
import json
import sys


class UserError(Exception):
    """An error caused by the user's input: shown as one line, exit code 2, no traceback."""


def _check_jacobians(args) -> int:
    from factors import jacobians, selfcheck

    results = selfcheck.run_checks(samples=args.samples, seed=args.seed)
    if args.json:
        print(json.dumps([r.as_dict() for r in results], indent=2))
    else:
        print(jacobians.table(results, title=f"analytic vs numerical Jacobians ({args.samples} random points each, seed {args.seed})"))
    failed = [r.name for r in results if not r.ok]
    if failed and not args.json:
        print(f"FAILED: {', '.join(failed)}", file=sys.stderr)
    return 1 if failed else 0


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="smoother", description=__doc__)
    sub = parser.add_subparsers(dest="command", required=True)

    p = sub.add_parser("check-jacobians", help="every analytic Jacobian against central differences")
    p.add_argument("--json", action="store_true", help="print JSON: one object per check")
    p.add_argument("--samples", type=int, default=200, help="random points per check (default 200)")
    p.add_argument("--seed", type=int, default=0)
    p.set_defaults(handler=_check_jacobians)
    return parser


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    try:
        return args.handler(args)
    except UserError as error:
        print(f"smoother: error: {error}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print("smoother: interrupted", file=sys.stderr)
        return 130


if __name__ == "__main__":
    sys.exit(main())
