"""The figures of a run directory (``smoother run --plot``, ``smoother plot DIR``), written as PNG.

They draw what the run directory holds (:func:`smoother.outputs.files.load_run`) and what the
evaluation computes from it (:mod:`smoother.evaluation.scoring`: the errors and NEES over time,
and the metrics of ``metrics.json`` when it lacks them); nothing is computed here but what is
drawn. One function each, the names of :data:`smoother.outputs.layout.PLOTS`:

``trajectory.png``
    top view (x-y) and height over time of every estimate against the truth or the GPS fixes.
``position_error.png``
    per world axis, truth minus estimate [m] over time (or GPS fix minus estimate), one column
    per estimator, with the estimator's +-3 sigma band (plus the fix's own sigma against GPS).
``orientation_error.png``
    the primer's boxminus error ``log(C_true C_est^T)`` (a world-frame rotation vector), its
    three components in degrees with +-3 sigma from the attitude block of the covariance
    (truth only).
``nees.png``
    the pose NEES (6 dof: position and attitude) per time and estimator with the two-sided 95 %
    chi-square band of a single run; against GPS the 3-dof position NEES of the fix residual.
``biases.png``
    accelerometer [m/s^2] and gyro [deg/s] bias estimates per axis with +-3 sigma, and the
    true biases where known.
``comparison.png``
    the position error norm over time of every estimator on one axis set, and bar charts of
    the headline metrics of ``metrics.json`` (ATE, rotation RMSE, NEES/dof, or the GPS RMSEs,
    and the run time).

Figures whose data are missing (no truth and no GPS, no covariances) are skipped, never faked.
The canvas, style, colours and PNG writing are :mod:`smoother.outputs.canvas`'s.
"""
from __future__ import annotations

import math
import sys
from pathlib import Path

import numpy as np

from smoother import stats
from smoother.evaluation import scoring
from smoother.evaluation.scoring import ErrorSeries
from smoother.outputs.canvas import STYLE, estimator_color, estimator_line, new_figure, plain_log_labels, save_png
from smoother.outputs.files import Run, load_run
from smoother.outputs.layout import GPS, TRUTH

#: Figure sizes [inch], one per name of :data:`smoother.outputs.layout.PLOTS`; a PNG is
#: ``round(w * DPI) x round(h * DPI)`` pixels (:data:`smoother.outputs.canvas.DPI`).
FIGSIZE = {
    "trajectory": (12.0, 6.0),
    "position_error": (12.0, 7.5),
    "orientation_error": (12.0, 7.5),
    "nees": (11.0, 7.5),
    "biases": (12.0, 10.5),
    "comparison": (12.0, 8.0),
}
TRUTH_COLOR = "black"
GPS_COLOR = "tab:red"
HELDOUT_COLOR = "tab:purple"
#: Confidence of the NEES band.
NEES_CONFIDENCE = 0.95
AXES = ("x", "y", "z")


def reference_errors(run: Run) -> tuple[str, dict]:
    """``(kind, {name: ErrorSeries})`` of the run's estimates against its truth
    (:func:`smoother.evaluation.scoring.errors_against_truth`), else against its GPS fixes
    (:func:`smoother.evaluation.scoring.errors_against_fixes`); ``kind`` is 'truth', 'gps' or ''
    (no reference). Estimates with nothing to compare are left out."""
    if run.truth is not None:
        out = {n: scoring.errors_against_truth(run.truth, tr) for n, tr in run.estimates.items()}
        kind = "truth"
    elif run.gps is not None:
        g = run.gps
        out = {n: scoring.errors_against_fixes(g.t, g.position, g.cov, g.heldout, tr)
               for n, tr in run.estimates.items()}
        kind = "gps"
    else:
        return "", {}
    return kind, {n: e for n, e in out.items() if e is not None}


def color_of(run: Run, name: str) -> str:
    """Estimator ``name``'s colour in the run's figures."""
    return estimator_color(name, run.estimates)


def line_of(run: Run, name: str, **kwargs) -> dict:
    """Keyword arguments of estimator ``name``'s line in the run's figures."""
    return estimator_line(name, run.estimates, **kwargs)


def _sigma3(P: np.ndarray | None) -> np.ndarray | None:
    """3 sqrt(diag) of (N, 3, 3) covariances (None stays None)."""
    if P is None:
        return None
    return 3.0 * np.sqrt(np.clip(np.diagonal(P, axis1=-2, axis2=-1), 0.0, None))


def _symmetric_limit(values: list, bands: list) -> float:
    """A y half-range showing every error and the band where it is not much wider than the
    errors (a huge initial covariance would otherwise flatten the plot)."""
    err = max((float(np.max(np.abs(v))) for v in values if v is not None and v.size), default=0.0)
    band = max((float(np.percentile(b, 90)) for b in bands if b is not None and b.size), default=0.0)
    limit = max(err, band) * 1.15
    return limit if limit > 0 else 1.0


def _time_label(run: Run) -> str:
    return "time since start [s]" if run.t0 != 0.0 else "time [s]"


# ------------------------------------------------------------------------------------------
# the figures


def plot_trajectory(run: Run, out_dir: Path) -> Path:
    """Top view (x-y) and height over time of the estimates against the truth or the GPS fixes."""
    fig = new_figure(FIGSIZE["trajectory"])
    top, height = fig.subplots(1, 2, width_ratios=[1.0, 1.25])
    t0 = run.t0
    if run.truth is not None:
        r = run.truth.position
        top.plot(r[:, 0], r[:, 1], color=TRUTH_COLOR, lw=2.5, alpha=0.35, label="truth")
        height.plot(run.truth.t - t0, r[:, 2], color=TRUTH_COLOR, lw=2.5, alpha=0.35, label="truth")
    if run.gps is not None:
        g = run.gps
        for mask, color, label in ((~g.heldout, GPS_COLOR, "GPS fix (used)"),
                                   (g.heldout, HELDOUT_COLOR, "GPS fix (held out)")):
            if mask.any():
                top.plot(g.position[mask, 0], g.position[mask, 1], ".", ms=3, color=color, label=label, zorder=1)
                height.plot(g.t[mask] - t0, g.position[mask, 2], ".", ms=3, color=color, label=label, zorder=1)
    for name, tr in run.estimates.items():
        r = tr.position
        top.plot(r[:, 0], r[:, 1], **line_of(run, name, lw=1.1))
        height.plot(tr.t - t0, r[:, 2], **line_of(run, name, lw=1.1))
    first = next(iter(run.estimates.values())).position[0]
    top.plot(first[0], first[1], "o", ms=7, mfc="none", mec="black", mew=1.2, label="start", zorder=4)
    top.set_aspect("equal", adjustable="datalim")
    top.set_xlabel("x [m]")
    top.set_ylabel("y [m]")
    top.set_title("Top view (world x-y)")
    height.set_xlabel(_time_label(run))
    height.set_ylabel("height z [m]")
    height.set_title("Height over time")
    reference = ("vs truth" if run.truth is not None else "vs GPS fixes" if run.gps is not None
                 else "(no truth or GPS in the run directory)")
    handles, labels = top.get_legend_handles_labels()
    fig.legend(handles, labels, loc="outside lower center", ncol=len(labels), markerscale=1.5)
    fig.suptitle(f"Trajectory: estimates {reference}  (run {run.run_dir.name})", fontsize=12)
    return save_png(fig, out_dir, "trajectory")


def _error_grid(run: Run, out_dir: Path, stem: str, errors: dict, title: str, ylabels, unit: str, pick,
                scale: float, points: bool) -> Path:
    """Rows = world axes, columns = estimators; the error with its +-3 sigma band."""
    names = list(errors)
    fig = new_figure(FIGSIZE[stem])
    axes = fig.subplots(3, len(names), sharex=True, sharey="row", squeeze=False)
    t0 = run.t0
    series = {n: pick(errors[n]) for n in names}  # (values (N,3), cov (N,3,3) or None)
    for row in range(3):
        values = [series[n][0][:, row] * scale for n in names]
        bands = [None if series[n][1] is None else _sigma3(series[n][1])[:, row] * scale for n in names]
        limit = _symmetric_limit(values, bands)
        for col, name in enumerate(names):
            ax = axes[row, col]
            t = errors[name].t - t0
            v, b = values[col], bands[col]
            color = color_of(run, name)
            note = f"RMS {np.sqrt(np.mean(v ** 2)):.3g} {unit}"
            if b is not None:
                ax.fill_between(t, -b, b, color=color, alpha=0.18, lw=0, label="±3σ")
                ax.plot(t, b, color=color, lw=0.6, alpha=0.6)
                ax.plot(t, -b, color=color, lw=0.6, alpha=0.6)
                note += f",  {np.mean(np.abs(v) <= b) * 100.0:.0f}% inside ±3σ"
            held = errors[name].heldout
            if points and held is not None and held.any():
                ax.plot(t[~held], v[~held], ".", ms=2.5, color="0.55", label="used fix")
                ax.plot(t[held], v[held], ".", ms=3.0, color=color, label="held-out fix")
            elif points:
                ax.plot(t, v, ".", ms=2.5, color=color, label="fix")
            else:
                ax.plot(t, v, color=color, lw=1.0, label="error")
            ax.axhline(0.0, color="0.3", lw=0.6)
            ax.set_ylim(-limit, limit)
            ax.text(0.99, 0.03, note, transform=ax.transAxes, ha="right", va="bottom", fontsize=8, color="0.2",
                    bbox=dict(boxstyle="round,pad=0.2", fc="white", ec="none", alpha=0.75))
            if row == 0:
                ax.set_title(name if b is not None else f"{name} (no covariance: no band)")
            if col == 0:
                ax.set_ylabel(ylabels[row])
            if row == 2:
                ax.set_xlabel(_time_label(run))
    axes[0, 0].legend(loc="upper right", fontsize=8, markerscale=3)
    fig.suptitle(title, fontsize=12)
    return save_png(fig, out_dir, stem)


def plot_position_error(run: Run, out_dir: Path, kind: str, errors: dict) -> Path:
    """Per-axis position error over time with the estimator's +-3 sigma, one column per estimator."""
    if kind == "truth":
        title = "Position error (truth − estimate) per world axis, with the estimator's ±3σ"
        labels = [f"{a} error [m]" for a in AXES]
    else:
        title = ("Position difference to the GPS fixes (fix − estimate), with ±3σ of estimate and fix combined\n"
                 "(a used fix pulled the estimate towards itself: only held-out fixes test the band)")
        labels = [f"{a} difference [m]" for a in AXES]
    return _error_grid(run, out_dir, "position_error", errors, title, labels, "m", lambda e: (e.dr, e.P_r), 1.0,
                       points=kind == "gps")


def plot_orientation_error(run: Run, out_dir: Path, errors: dict) -> Path:
    """The three components of ``log(C_true C_est^T)`` in degrees with +-3 sigma (rows 6:9 of cov)."""
    title = "Attitude error log(C_true C_estᵀ) (world-frame rotation vector) per component, with the estimator's ±3σ"
    labels = [f"about world {a} [deg]" for a in AXES]
    return _error_grid(run, out_dir, "orientation_error", errors, title, labels, "deg",
                       lambda e: (e.dphi, e.P_phi), math.degrees(1.0), points=False)


def plot_nees(run: Run, out_dir: Path, kind: str, errors: dict) -> Path:
    """NEES per time and estimator with the two-sided chi-square band of one run."""
    names = [n for n in errors if errors[n].nees is not None]
    dof = errors[names[0]].dof
    lo, hi = stats.nees_bounds(dof, 1, NEES_CONFIDENCE)
    fig = new_figure(FIGSIZE["nees"])
    axes = fig.subplots(len(names), 1, sharex=True, sharey=True, squeeze=False)[:, 0]
    t0 = run.t0
    values = np.concatenate([errors[n].nees for n in names])
    values = values[np.isfinite(values)]
    positive = values[values > 0]
    bottom = min(lo, float(positive.min()) if positive.size else lo) / 2.0
    top = max(hi, float(values.max())) * 2.0
    for ax, name in zip(axes, names):
        e = errors[name]
        ok = np.isfinite(e.nees)
        t, nees = e.t[ok] - t0, e.nees[ok]
        inside = float(np.mean((nees >= lo) & (nees <= hi))) * 100.0
        band = ax.axhspan(lo, hi, color="0.5", alpha=0.2, lw=0)
        expected = ax.axhline(dof, color="0.3", lw=0.8, ls="--")
        ax.semilogy(t, np.clip(nees, bottom, None), color=color_of(run, name), lw=1.0,
                    marker="." if len(t) <= 500 else None, ms=3)
        ax.set_ylim(bottom, top)
        plain_log_labels(ax)
        ax.set_ylabel(f"NEES ({dof} dof)")
        ax.set_title(f"{name}: mean NEES/dof = {np.mean(nees) / dof:.2f}, {inside:.0f}% of the "
                     f"{'times' if kind == 'truth' else f'{len(nees)} held-out fixes'} inside the band",
                     loc="left", fontsize=10, color=color_of(run, name))
    axes[-1].set_xlabel(_time_label(run))
    fig.legend([band, expected], [f"{NEES_CONFIDENCE:.0%} band of χ²({dof}) for one run: [{lo:.2f}, {hi:.2f}]",
                                  f"expected value {dof}"], loc="outside lower center", ncol=2)
    what = ("pose (position + attitude) against the truth" if kind == "truth"
            else "position residual to the held-out GPS fixes (covariance: estimate + fix)")
    missing = [n for n in errors if n not in names]
    note = f"\n({', '.join(missing)}: no covariance saved)" if missing else ""
    fig.suptitle(f"NEES of the {what}{note}", fontsize=12)
    return save_png(fig, out_dir, "nees")


def plot_biases(run: Run, out_dir: Path) -> Path:
    """Accelerometer and gyro bias estimates per axis (rows) and estimator (columns) with +-3 sigma,
    and the truth where known."""
    names = list(run.estimates)
    fig = new_figure(FIGSIZE["biases"])
    axes = fig.subplots(6, len(names), sharex=True, sharey="row", squeeze=False)
    t0 = run.t0
    rows = [("b_f", 9 + a, 1.0, f"acc. bias {AXES[a]}\n[m/s²]") for a in range(3)]
    rows += [("b_w", 12 + a, math.degrees(1.0), f"gyro bias {AXES[a]}\n[deg/s]") for a in range(3)]
    truth_drawn = False
    for row, (field, index, scale, label) in enumerate(rows):
        axis = index - (9 if field == "b_f" else 12)
        truth = None
        if run.truth is not None:
            b = getattr(run.truth.states, field)[:, axis] * scale
            truth = b if np.isfinite(b).any() else None
        extent = [] if truth is None else [truth[np.isfinite(truth)]]
        for col, name in enumerate(names):
            ax = axes[row, col]
            tr = run.estimates[name]
            t = tr.t - t0
            b = getattr(tr.states, field)[:, axis] * scale
            color = color_of(run, name)
            if truth is not None:
                ax.plot(run.truth.t - t0, truth, color=TRUTH_COLOR, lw=2.5, alpha=0.35, label="truth")
                truth_drawn = True
            if tr.cov is not None:
                s = 3.0 * np.sqrt(np.clip(tr.cov[:, index, index], 0.0, None)) * scale
                ax.fill_between(t, b - s, b + s, color=color, alpha=0.18, lw=0, label="±3σ")
                # a huge initial uncertainty should not set the y range: clip the band there
                s = np.minimum(s, np.percentile(s, 75))
                extent += [b - s, b + s]
            ax.plot(t, b, color=color, lw=1.1, label="estimate")
            extent.append(b)
            if row == 0:
                ax.set_title(name)
            if col == 0:
                ax.set_ylabel(label)
            if row == len(rows) - 1:
                ax.set_xlabel(_time_label(run))
        v = np.concatenate(extent)
        v = v[np.isfinite(v)]
        if v.size:
            lo, hi = float(v.min()), float(v.max())
            pad = 0.08 * max(hi - lo, 1e-3 * max(abs(lo), abs(hi)), 1e-9)
            axes[row, 0].set_ylim(lo - pad, hi + pad)
    handles, labels = axes[0, 0].get_legend_handles_labels()
    fig.legend(handles, labels, loc="outside lower center", ncol=len(labels))
    bands = any(tr.cov is not None for tr in run.estimates.values())
    fig.suptitle("Bias estimates" + (" with ±3σ" if bands else "") + (" vs truth" if truth_drawn else ""),
                 fontsize=12)
    return save_png(fig, out_dir, "biases")


def bar_values(run: Run, kind: str, errors: dict) -> list[tuple[str, str, dict]]:
    """``(key, label, {name: value})`` for the bars; values from metrics.json (a null there is
    not drawn), else, without metrics.json's entry, computed as :mod:`smoother.evaluation.scoring` computes
    them (:func:`_computed_metrics`)."""
    if kind == "truth":
        specs = [("ate_rmse_m", "ATE RMSE [m]"), ("rot_rmse_deg", "rotation RMSE [deg]"),
                 ("nees_mean", "mean NEES / dof")]
    else:
        specs = [("gps_heldout_rmse_m", "RMSE to held-out fixes [m]\n(accuracy)"),
                 ("gps_fit_residual_m", "residual to used fixes [m]\n(a fit, not accuracy)")]
    specs.append(("runtime_s", "run time [s]"))
    computed: dict = {}
    out = []
    for key, label in specs:
        values = {}
        for name in run.estimates:
            entry = run.metrics.get(name)
            if isinstance(entry, dict) and key in entry:
                v = entry[key]  # null there (a figure not scored, e.g. over too few states) stays out
            elif name in errors:
                if name not in computed:
                    computed[name] = _computed_metrics(run, name, errors[name])
                v = computed[name].get(key)
            else:
                v = None
            if isinstance(v, (int, float)) and math.isfinite(v):
                values[name] = float(v)
        if values:
            out.append((key, label, values))
    return out


def _computed_metrics(run: Run, name: str, e: ErrorSeries) -> dict:
    """The figures ``metrics.json`` would hold for estimator ``name``: against the truth those of
    :func:`smoother.evaluation.scoring.against_truth`; against GPS the RMS distance
    (:func:`smoother.evaluation.scoring.rms_distance`) of the held-out and of the used fixes' residuals."""
    if run.truth is not None:
        return scoring.against_truth(run.truth, run.estimates[name])
    if e.heldout is None:
        return {}
    return {"gps_heldout_rmse_m": scoring.rms_distance(e.dr[e.heldout]),
            "gps_fit_residual_m": scoring.rms_distance(e.dr[~e.heldout])}


def plot_comparison(run: Run, out_dir: Path, kind: str, errors: dict) -> Path:
    """Position error norm over time of all estimators on one axis set, and metric bars."""
    bars = bar_values(run, kind, errors)
    fig = new_figure(FIGSIZE["comparison"])
    grid = fig.add_gridspec(2, max(len(bars), 1), height_ratios=[1.5, 1.0])
    ax = fig.add_subplot(grid[0, :])
    t0 = run.t0
    for name, e in errors.items():
        norm = np.linalg.norm(e.dr, axis=1)
        if kind == "gps":
            ax.plot(e.t - t0, norm, marker=".", ms=2.5, **line_of(run, name, lw=0.7))
        else:
            ax.plot(e.t - t0, norm, **line_of(run, name, lw=1.1))
    ax.set_yscale("log")
    plain_log_labels(ax)
    ax.set_xlabel(_time_label(run))
    ax.set_ylabel("position error norm [m]" if kind == "truth" else "distance to GPS fix [m]")
    ax.set_title("|truth − estimate| over time" if kind == "truth" else "|GPS fix − estimate| at the fix times")
    ax.legend(loc="upper right", ncol=len(errors), markerscale=3)
    for col, (key, label, values) in enumerate(bars):
        bx = fig.add_subplot(grid[1, col])
        names = list(values)
        heights = [values[n] for n in names]
        rects = bx.bar(range(len(names)), heights, color=[color_of(run, n) for n in names], width=0.65)
        bx.bar_label(rects, labels=[f"{h:.3g}" for h in heights], fontsize=8, padding=2)
        bx.set_xticks(range(len(names)), names)
        bx.set_title(label, fontsize=10)
        bx.set_ylim(0, (max(heights + [1.0 if key == "nees_mean" else 0.0]) * 1.25) or 1.0)
        bx.grid(axis="x", visible=False)
        if key == "nees_mean":
            bx.axhline(1.0, color="0.3", lw=0.8, ls="--", label="consistent (1)")
            bx.legend(loc="upper right", fontsize=8)
    fig.suptitle(f"Estimator comparison ({', '.join(run.estimates)})", fontsize=12)
    return save_png(fig, out_dir, "comparison")


# ------------------------------------------------------------------------------------------
# entry point


def plot_run(run_dir, estimators=None, out_dir=None) -> list[Path]:
    """Write every figure the run directory has the data for; return the PNG paths written.
    ``estimators``: names to draw (default all in the directory); ``out_dir``: where to write
    (default ``run_dir``)."""
    import matplotlib

    run = load_run(run_dir, estimators)
    out_dir = Path(run_dir if out_dir is None else out_dir)
    written = []
    with matplotlib.rc_context(STYLE):
        written.append(plot_trajectory(run, out_dir))
        kind, errors = reference_errors(run)
        if errors:
            written.append(plot_position_error(run, out_dir, kind, errors))
            if kind == "truth":
                written.append(plot_orientation_error(run, out_dir, errors))
            if any(e.nees is not None for e in errors.values()):
                written.append(plot_nees(run, out_dir, kind, errors))
            elif kind == "gps" and not run.gps.heldout.any():
                print("plots: no held-out GPS fix (a rig sensor's every = K, or --gps-every K on a built-in "
                      "dataset, holds some out): no NEES figure", file=sys.stderr)
        elif kind:
            print(f"plots: {run.run_dir / (TRUTH if kind == 'truth' else GPS)} has nothing within the estimates' times "
                  "to compare with them: no error figures", file=sys.stderr)
        else:
            print(f"plots: {run.run_dir} has neither {TRUTH} nor {GPS}: no error figures", file=sys.stderr)
        written.append(plot_biases(run, out_dir))
        if errors:
            written.append(plot_comparison(run, out_dir, kind, errors))
    return written
