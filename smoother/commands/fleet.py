"""``smoother fleet``: many recordings, each as ``smoother run --rig`` runs it, in one command;
``DIR/summary.json`` and a table per recording and estimator (:mod:`smoother.commands.fleet_runner`)."""
from __future__ import annotations

import json
import math
import sys

from factors.errors import InputError
from smoother.errors import UserError, interruption
from smoother.estimators import ESTIMATORS


def register(sub) -> None:
    p = sub.add_parser("fleet", help="run many recordings (rig files) at once, on this machine or a Dask cluster")
    p.add_argument("rigs", nargs="+", metavar="RIG.toml", help="the recordings' rig files (as smoother run --rig)")
    p.add_argument("--out", required=True, metavar="DIR",
                   help="output directory: DIR/<rig file stem>/ per recording, as smoother run --out writes it, "
                        "its output in run.log there; DIR/summary.json")
    p.add_argument("--estimator", default="all", choices=[*ESTIMATORS, "all"],
                   help="which estimator(s) to run (default all)")
    p.add_argument("--lag", type=float, default=2.0, help="fixed-lag window [s] (default 2)")
    p.add_argument("--mcap", action="store_true", help="also write each recording's estimates.mcap")
    p.add_argument("--plot", action="store_true", help="also write each recording's plots")
    where = p.add_mutually_exclusive_group()
    where.add_argument("--workers", type=int, default=1, help="recordings at a time on this machine (default 1)")
    where.add_argument("--dask", metavar="ADDRESS", default=None,
                       help="send the recordings to this Dask scheduler (optional extra 'dask'; the workers must see "
                            "the rig files and DIR at the same paths)")
    p.add_argument("--progress", dest="progress", action="store_true", default=None,
                   help="always show the progress bar")
    p.add_argument("--no-progress", dest="progress", action="store_false", help="never show the progress bar")
    p.set_defaults(handler=run)


def run(args) -> int:
    from datasets.atomic import atomic_write
    from factors.threads import thread_count
    from smoother.commands import check_workers, named_directory, output_directory
    from smoother.commands import fleet_runner as fleet
    from smoother.confined import inside
    from smoother.fixed_lag.lag import check_lag
    from smoother.progress import progress_bar

    check_workers(args.workers, args.dask)
    check_lag(args.lag, "--lag", UserError)
    options = ["--estimator", args.estimator, "--lag", repr(args.lag)] + ["--mcap"] * args.mcap + ["--plot"] * args.plot
    share = None if args.dask else max(1, thread_count() // args.workers)
    items = fleet.recordings(args.rigs, named_directory(args.out), options, share)  # refused before --out is made
    out = output_directory(args.out)
    try:  # before any recording runs: a summary that leads out of --out would be refused after all of them
        inside(out, fleet.SUMMARY)
    except InputError as error:
        raise UserError(f"--out {out}: {error}; remove it or choose another --out") from None
    results: dict = {}
    stopped = None
    with progress_bar(len(items), "recordings", args.progress) as bar:
        def done(result):
            results[result["recording"]] = result
            bar.update(1)
            if result["failure"]:
                bar.write(f"{result['recording']}: {result['failure']}", file=sys.stderr)

        try:
            fleet.run_recordings(items, done, args.workers, args.dask)
        except KeyboardInterrupt as error:
            stopped, code = interruption(error)
    ordered = [results[item.name] for item in items if item.name in results]
    not_run = [item.name for item in items if item.name not in results]
    failures = [r["recording"] for r in ordered if r["failure"]]
    summary = {"recordings": ordered, "failed": failures, "not_run": not_run, "argv": sys.argv[1:]}
    if stopped:
        summary["stopped"] = stopped
    with atomic_write(inside(out, fleet.SUMMARY)) as handle:
        json.dump(summary, handle, indent=2)
        handle.write("\n")
    print(format_table(ordered))
    print(f"{len(ordered) - len(failures)} of {len(items)} recordings ran, {len(failures)} failed"
          + (f", {len(not_run)} not run ({stopped})" if not_run else "") + f"; summary in {out / fleet.SUMMARY}",
          file=sys.stderr)
    if stopped:
        return code
    return 2 if failures else 0


#: The table's figures per estimator: (key of a result's estimator, header).
COLUMNS = (("ate_rmse_m", "ATE [m]"), ("gps_heldout_rmse_m", "held-out [m]"), ("gps_fit_residual_m", "fit resid [m]"))


def format_table(results: list[dict]) -> str:
    """One line per recording and estimator: the figures of :data:`COLUMNS` that any has, the fit
    of all its sensors together (per dof, ``ok`` inside its band, ``OUT`` outside, ``few-dof`` on
    too few degrees of freedom to judge) and each sensor's; ``(?)`` after a doubtful estimator; a
    recording or estimator that failed says why on its line."""
    present = [(k, h) for k, h in COLUMNS if any(k in e for r in results for e in r["estimators"].values())]
    width = max([len("recording")] + [len(r["recording"]) for r in results]) + 2
    lines = [f"{'recording':<{width}}{'estimator':<16}" + "".join(f"{h:>14}" for _, h in present)
             + f"  {'fit/dof':<12}sensors (per dof)"]
    for r in results:
        if not r["estimators"]:
            lines.append(f"{r['recording']:<{width}}failed: {r['failure']}")
            continue
        for name, e in r["estimators"].items():
            label = f"{name} (?)" if e.get("doubtful") else name
            head = f"{r['recording']:<{width}}{label:<16}"
            if "failed" in e:
                lines.append(f"{head}failed: {e['failed']}")
                continue
            cells = "".join(f"{_number(e.get(k)):>14}" for k, _ in present)
            fit = _verdict(e["fit"]) if "fit" in e else "-"
            sensors = ", ".join(f"{s} {_verdict(v)}" for s, v in e["sensors"].items()) or "-"
            lines.append(f"{head}{cells}  {fit:<12}{sensors}")
        if r["failure"] and not any("failed" in e for e in r["estimators"].values()):
            lines.append(f"{r['recording']:<{width}}failed: {r['failure']}")
    if any(e.get("doubtful") for r in results for e in r["estimators"].values()):
        lines.append("(?): doubtful -- the estimate does not fit its own data (the recording's run.log says how far)")
    from smoother.diagnosis.verdicts import MIN_DOF, TOO_FEW_DOF, judgeable

    if any(not judgeable(v) for r in results for e in r["estimators"].values()
           for v in [*e.get("sensors", {}).values(), *([e["fit"]] if "fit" in e else [])]):
        lines.append(f"{_FEW}: {TOO_FEW_DOF} (fewer than {MIN_DOF:g}); no band, not counted as a misfit")
    return "\n".join(lines)


def _number(value) -> str:
    return f"{value:.4f}" if isinstance(value, (int, float)) and math.isfinite(value) else "-"


#: The table's mark of a verdict not formed (:func:`smoother.diagnosis.verdicts.judgeable`).
_FEW = "few-dof"


def _verdict(v: dict) -> str:
    from smoother.diagnosis.verdicts import judgeable

    if v["per_dof"] is None:  # no update used (an EKF's gate rejected them all)
        return "none"
    if not judgeable(v):
        return f"{v['per_dof']:.3g} {_FEW}"
    return f"{v['per_dof']:.3g} {'ok' if v['ok'] else 'OUT'}"
