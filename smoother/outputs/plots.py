"""Figures of a run directory (``smoother run --plot``, ``smoother plot DIR``), written as PNG.

A run directory (:mod:`smoother.evaluation.scoring`) holds ``<estimator>.npz`` per estimator, ``truth.npz``
where the truth is known, ``metrics.json`` and, for GPS-referenced datasets, optionally
``gps.npz`` (arrays ``t`` (M,), ``position`` (M, 3), optional ``cov`` (M, 3, 3) and optional
``heldout`` (M,) bool: fixes kept out of estimation). The figures, one function each:

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
Every PNG is written atomically; the module uses Matplotlib's object API with the Agg canvas,
so it works without a display and leaves no global pyplot state behind.
"""
from __future__ import annotations

import json
import math
import sys
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.figure import Figure
from matplotlib.ticker import FuncFormatter

from datasets.allan import WALK_TAU, WHITE_TAU
from datasets.atomic import atomic_write
from datasets.types import Trajectory
from factors.errors import InputError
from smoother import stats
from smoother.estimators import ESTIMATORS
from smoother.evaluation import metrics
from smoother.evaluation import scoring as report
from smoother.evaluation.scoring import fix_residuals, truth_at
from smoother.outputs.files import load_trajectory, read_npz

#: Resolution of every PNG [dots per inch].
DPI = 120
#: Figure sizes [inch] by file stem; a PNG is ``round(w * DPI) x round(h * DPI)`` pixels.
FIGSIZE = {
    "trajectory": (12.0, 6.0),
    "position_error": (12.0, 7.5),
    "orientation_error": (12.0, 7.5),
    "nees": (11.0, 7.5),
    "biases": (12.0, 10.5),
    "comparison": (12.0, 8.0),
    "montecarlo_nees": (11.0, 5.0),
    "allan": (12.0, 5.0),
}
#: Estimators in the order they are drawn, with their colours (others get the next free colour).
ESTIMATOR_ORDER = ESTIMATORS
COLORS = {"batch": "tab:blue", "fixed-lag": "tab:orange", "ekf": "tab:green"}
#: Fixed-lag's newest state is close to the EKF's: it is drawn dashed and on top, so both show.
LINESTYLES = {"fixed-lag": (0, (4, 2))}
ZORDER = {"fixed-lag": 3.0}
_SPARE_COLORS = ("tab:red", "tab:purple", "tab:brown", "tab:pink", "tab:olive", "tab:cyan")
TRUTH_COLOR = "black"
GPS_COLOR = "tab:red"
HELDOUT_COLOR = "tab:purple"
#: Files of a run directory that are not estimates.
RESERVED = ("truth", "gps")
#: Confidence of the NEES band.
NEES_CONFIDENCE = 0.95
AXES = ("x", "y", "z")
STYLE = {
    "font.size": 10,
    "axes.titlesize": 11,
    "axes.labelsize": 10,
    "legend.fontsize": 9,
    "xtick.labelsize": 9,
    "ytick.labelsize": 9,
    "axes.grid": True,
    "grid.alpha": 0.3,
    "lines.linewidth": 1.3,
}


# ------------------------------------------------------------------------------------------
# the run directory


@dataclass(frozen=True)
class Gps:
    """GPS fixes: times, positions, covariances (or None) and which were held out of estimation."""

    t: np.ndarray
    position: np.ndarray
    cov: np.ndarray | None
    heldout: np.ndarray


@dataclass(frozen=True)
class Run:
    """What :func:`load_run` read: estimates by name (drawing order), truth, GPS, metrics."""

    run_dir: Path
    estimates: dict
    truth: Trajectory | None
    gps: Gps | None
    metrics: dict

    @property
    def t0(self) -> float:
        """Start of the time axis: the first estimate's time."""
        return min(float(tr.t[0]) for tr in self.estimates.values())

    def color(self, name: str) -> str:
        if name in COLORS:
            return COLORS[name]
        others = [n for n in self.estimates if n not in COLORS]
        return _SPARE_COLORS[others.index(name) % len(_SPARE_COLORS)]

    def line(self, name: str, **kwargs) -> dict:
        """Keyword arguments of an estimator's line: colour, line style, drawing order."""
        return {"color": self.color(name), "ls": LINESTYLES.get(name, "-"), "zorder": ZORDER.get(name, 2.0),
                "label": name, **kwargs}


def _load_gps(path: Path) -> Gps:
    expected = "an .npz with arrays t (M,), position (M, 3) and optionally cov (M, 3, 3) and heldout (M,) bool"
    with read_npz(path, expected) as data:
        t = np.asarray(data["t"], dtype=float)
        position = np.asarray(data["position"], dtype=float)
        cov = np.asarray(data["cov"], dtype=float) if "cov" in data else None
        heldout = np.asarray(data["heldout"], dtype=bool) if "heldout" in data else np.zeros(len(t), bool)
    n = len(t)
    if (t.ndim != 1 or position.shape != (n, 3) or heldout.shape != (n,)
            or (cov is not None and cov.shape != (n, 3, 3))):
        raise InputError(f"{path}: inconsistent shapes (t {t.shape}, position {position.shape}"
                        f"{'' if cov is None else f', cov {cov.shape}'}, heldout {heldout.shape}); expected {expected}")
    if n > 1 and np.any(np.diff(t) <= 0):
        raise InputError(f"{path}: the times t must increase strictly")
    return Gps(t, position, cov, heldout)


def estimator_names(run_dir: Path) -> list[str]:
    """Names of the estimates in ``run_dir``, drawing order: those of the last run when
    ``metrics.json`` lists them (so an older run's files left in the directory are not drawn),
    else every ``<name>.npz`` other than truth/gps."""
    found = {p.stem for p in Path(run_dir).glob("*.npz") if p.stem not in RESERVED}
    try:
        listed = json.loads((Path(run_dir) / "metrics.json").read_text())["_run"]["estimators"]
        found &= set(listed)
    except (OSError, ValueError, KeyError, TypeError):
        pass
    return [n for n in ESTIMATOR_ORDER if n in found] + sorted(found - set(ESTIMATOR_ORDER))


def load_run(run_dir, estimators=None) -> Run:
    """Read a run directory; :class:`~factors.errors.InputError` naming the file for anything missing or malformed."""
    run_dir = Path(run_dir)
    if not run_dir.is_dir():
        raise InputError(f"{run_dir}: not a directory; expected the output directory of smoother run")
    available = estimator_names(run_dir)
    if not available:
        raise InputError(f"{run_dir}: no estimate found; expected <estimator>.npz files "
                        f"(e.g. {', '.join(f'{n}.npz' for n in ESTIMATOR_ORDER)}) written by smoother run")
    names = available if not estimators else list(dict.fromkeys(estimators))
    for name in names:
        if name not in available:
            raise InputError(f"{run_dir / (name + '.npz')}: not found; this run has {', '.join(available)}")
    estimates = {name: load_trajectory(run_dir / f"{name}.npz") for name in names}
    truth = load_trajectory(run_dir / "truth.npz") if (run_dir / "truth.npz").exists() else None
    gps = _load_gps(run_dir / "gps.npz") if (run_dir / "gps.npz").exists() else None
    document: dict = {}
    path = run_dir / "metrics.json"
    if path.exists():
        try:
            document = json.loads(path.read_text())
        except (OSError, ValueError) as error:
            raise InputError(f"{path}: cannot read it ({error}); expected the JSON object smoother run writes") from None
        if not isinstance(document, dict):
            raise InputError(f"{path}: expected a JSON object with one entry per estimator, "
                            f"got {type(document).__name__}")
    return Run(run_dir, estimates, truth, gps, document)


# ------------------------------------------------------------------------------------------
# errors against the truth or the GPS fixes


@dataclass(frozen=True)
class Errors:
    """One estimator's errors against a reference at times ``t`` (absolute, not shifted):
    position ``dr`` = reference minus estimate [m] with covariance ``P_r`` (estimate's, plus the
    fix's against GPS), attitude ``dphi = log(C_ref C_est^T)`` [rad] with ``P_phi`` (truth only),
    ``nees`` and its degrees of freedom."""

    t: np.ndarray
    dr: np.ndarray
    P_r: np.ndarray | None
    dphi: np.ndarray | None = None
    P_phi: np.ndarray | None = None
    nees: np.ndarray | None = None
    dof: int = 6
    heldout: np.ndarray | None = None


def _nees_or_none(compute) -> np.ndarray | None:
    """``compute()`` (a NEES of :mod:`smoother.evaluation.metrics`), None where a covariance is singular."""
    try:
        return compute()
    except np.linalg.LinAlgError:
        return None


def errors_against_truth(truth: Trajectory, estimate: Trajectory) -> Errors | None:
    """Errors at the estimate's times inside the truth's span and outside its gaps (as the
    metrics: :func:`smoother.evaluation.scoring.truth_at`; None if there are none); the pose NEES of
    :func:`smoother.evaluation.metrics.nees`, the one ``metrics.json``'s ``nees_mean`` averages."""
    T, inside = truth_at(truth, estimate.t)
    if not inside.any():
        return None
    E = estimate.states[inside]
    cov = None if estimate.cov is None else estimate.cov[inside]
    e = metrics.pose_error(T.r, T.C, E.r, E.C)
    nees = None if cov is None else _nees_or_none(lambda: metrics.nees(T, E, cov, "pose"))
    return Errors(
        t=estimate.t[inside], dr=e[:, :3], P_r=None if cov is None else cov[:, 0:3, 0:3],
        dphi=e[:, 3:], P_phi=None if cov is None else cov[:, 6:9, 6:9], nees=nees, dof=6,
    )


def errors_against_gps(gps: Gps, estimate: Trajectory) -> Errors | None:
    """Fix minus estimate at the fixes inside the estimate's span: the residuals of
    ``metrics.json``'s GPS RMSEs (:func:`smoother.evaluation.scoring.fix_residuals`, negated), with covariance
    ``P_est + R_fix`` (``P_est`` interpolated to the fix times); None if no fix lies inside.

    ``P_est + R_fix`` is the residual's covariance only for a HELD-OUT fix (independent of the
    estimate); a fix the estimator used pulled the estimate towards itself, so its residual is
    smaller than that. The NEES is therefore computed over the held-out fixes only (NaN at the
    others, None if there are none)."""
    inside, residual = fix_residuals(gps.t, gps.position, estimate)
    if not inside.any():
        return None
    dr = -residual
    heldout = gps.heldout[inside]
    P = None
    if estimate.cov is not None:
        cov = estimate.interpolate(gps.t[inside])[1]
        P = cov[:, 0:3, 0:3] + (0.0 if gps.cov is None else gps.cov[inside])
    nees = None
    if P is not None and heldout.any():
        values = _nees_or_none(lambda: metrics.nees_from(dr[heldout], P[heldout]))
        if values is not None:
            nees = np.full(len(dr), np.nan)
            nees[heldout] = values
    return Errors(t=gps.t[inside], dr=dr, P_r=P, nees=nees, dof=3, heldout=heldout)


def reference_errors(run: Run) -> tuple[str, dict]:
    """``(kind, {name: Errors})`` with ``kind`` 'truth', 'gps' or '' (no reference)."""
    if run.truth is not None:
        out = {n: errors_against_truth(run.truth, tr) for n, tr in run.estimates.items()}
        return "truth", {n: e for n, e in out.items() if e is not None}
    if run.gps is not None:
        out = {}
        for n, tr in run.estimates.items():
            result = errors_against_gps(run.gps, tr)
            if result is not None:
                out[n] = result
        return "gps", out
    return "", {}


# ------------------------------------------------------------------------------------------
# figure plumbing


def _figure(stem: str) -> Figure:
    """A new figure of the configured size with an Agg canvas (no pyplot)."""
    fig = Figure(figsize=FIGSIZE[stem], dpi=DPI, layout="constrained")
    FigureCanvasAgg(fig)
    return fig


def _save(fig: Figure, out_dir: Path, stem: str) -> Path:
    path = Path(out_dir) / f"{stem}.png"
    with atomic_write(path, "wb") as handle:
        fig.savefig(handle, format="png", dpi=DPI)
    fig.clear()
    return path


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


def _plain_log_labels(ax) -> None:
    """Tick labels like 0.02 instead of 2 x 10^-2 on a log y axis (call after setting the limits);
    minor ticks 2 and 5 are labelled only when the axis spans at most two decades."""
    ax.yaxis.set_major_formatter(FuncFormatter(lambda v, _: f"{v:g}"))
    lo, hi = ax.get_ylim()
    few = lo > 0 and math.log10(hi / lo) <= 2.0
    ax.yaxis.set_minor_formatter(FuncFormatter(
        lambda v, _: f"{v:g}" if few and _leading_digit(v) in (2, 5) else ""))


def _leading_digit(v: float) -> int:
    return int(round(v / 10.0 ** math.floor(math.log10(v)))) if v > 0 else 0


def _time_label(run: Run) -> str:
    return "time since start [s]" if run.t0 != 0.0 else "time [s]"


# ------------------------------------------------------------------------------------------
# the figures


def plot_trajectory(run: Run, out_dir: Path) -> Path:
    """Top view (x-y) and height over time of the estimates against the truth or the GPS fixes."""
    fig = _figure("trajectory")
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
        top.plot(r[:, 0], r[:, 1], **run.line(name, lw=1.1))
        height.plot(tr.t - t0, r[:, 2], **run.line(name, lw=1.1))
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
    return _save(fig, out_dir, "trajectory")


def _error_grid(run: Run, out_dir: Path, stem: str, errors: dict, title: str, ylabels, unit: str, pick,
                scale: float, points: bool) -> Path:
    """Rows = world axes, columns = estimators; the error with its +-3 sigma band."""
    names = list(errors)
    fig = _figure(stem)
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
            color = run.color(name)
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
    return _save(fig, out_dir, stem)


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
    fig = _figure("nees")
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
        ax.semilogy(t, np.clip(nees, bottom, None), color=run.color(name), lw=1.0,
                    marker="." if len(t) <= 500 else None, ms=3)
        ax.set_ylim(bottom, top)
        _plain_log_labels(ax)
        ax.set_ylabel(f"NEES ({dof} dof)")
        ax.set_title(f"{name}: mean NEES/dof = {np.mean(nees) / dof:.2f}, {inside:.0f}% of the "
                     f"{'times' if kind == 'truth' else f'{len(nees)} held-out fixes'} inside the band",
                     loc="left", fontsize=10, color=run.color(name))
    axes[-1].set_xlabel(_time_label(run))
    fig.legend([band, expected], [f"{NEES_CONFIDENCE:.0%} band of χ²({dof}) for one run: [{lo:.2f}, {hi:.2f}]",
                                  f"expected value {dof}"], loc="outside lower center", ncol=2)
    what = ("pose (position + attitude) against the truth" if kind == "truth"
            else "position residual to the held-out GPS fixes (covariance: estimate + fix)")
    missing = [n for n in errors if n not in names]
    note = f"\n({', '.join(missing)}: no covariance saved)" if missing else ""
    fig.suptitle(f"NEES of the {what}{note}", fontsize=12)
    return _save(fig, out_dir, "nees")


def plot_biases(run: Run, out_dir: Path) -> Path:
    """Accelerometer and gyro bias estimates per axis (rows) and estimator (columns) with +-3 sigma,
    and the truth where known."""
    names = list(run.estimates)
    fig = _figure("biases")
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
            color = run.color(name)
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
    return _save(fig, out_dir, "biases")


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


def _computed_metrics(run: Run, name: str, e: Errors) -> dict:
    """The figures ``metrics.json`` would hold for estimator ``name``: against the truth those of
    :func:`smoother.evaluation.scoring.against_truth`; against GPS the RMS distance
    (:func:`smoother.evaluation.scoring.rms_distance`) of the held-out and of the used fixes' residuals."""
    if run.truth is not None:
        return report.against_truth(run.truth, run.estimates[name])
    if e.heldout is None:
        return {}
    return {"gps_heldout_rmse_m": report.rms_distance(e.dr[e.heldout]),
            "gps_fit_residual_m": report.rms_distance(e.dr[~e.heldout])}


def plot_comparison(run: Run, out_dir: Path, kind: str, errors: dict) -> Path:
    """Position error norm over time of all estimators on one axis set, and metric bars."""
    bars = bar_values(run, kind, errors)
    fig = _figure("comparison")
    grid = fig.add_gridspec(2, max(len(bars), 1), height_ratios=[1.5, 1.0])
    ax = fig.add_subplot(grid[0, :])
    t0 = run.t0
    for name, e in errors.items():
        norm = np.linalg.norm(e.dr, axis=1)
        if kind == "gps":
            ax.plot(e.t - t0, norm, marker=".", ms=2.5, **run.line(name, lw=0.7))
        else:
            ax.plot(e.t - t0, norm, **run.line(name, lw=1.1))
    ax.set_yscale("log")
    _plain_log_labels(ax)
    ax.set_xlabel(_time_label(run))
    ax.set_ylabel("position error norm [m]" if kind == "truth" else "distance to GPS fix [m]")
    ax.set_title("|truth − estimate| over time" if kind == "truth" else "|GPS fix − estimate| at the fix times")
    ax.legend(loc="upper right", ncol=len(errors), markerscale=3)
    for col, (key, label, values) in enumerate(bars):
        bx = fig.add_subplot(grid[1, col])
        names = list(values)
        heights = [values[n] for n in names]
        rects = bx.bar(range(len(names)), heights, color=[run.color(n) for n in names], width=0.65)
        bx.bar_label(rects, labels=[f"{h:.3g}" for h in heights], fontsize=8, padding=2)
        bx.set_xticks(range(len(names)), names)
        bx.set_title(label, fontsize=10)
        bx.set_ylim(0, (max(heights + [1.0 if key == "nees_mean" else 0.0]) * 1.25) or 1.0)
        bx.grid(axis="x", visible=False)
        if key == "nees_mean":
            bx.axhline(1.0, color="0.3", lw=0.8, ls="--", label="consistent (1)")
            bx.legend(loc="upper right", fontsize=8)
    fig.suptitle(f"Estimator comparison ({', '.join(run.estimates)})", fontsize=12)
    return _save(fig, out_dir, "comparison")

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
                print("plots: no held-out GPS fix (see --gps-every): no NEES figure", file=sys.stderr)
        else:
            print(f"plots: {run.run_dir} has neither truth.npz nor gps.npz: no error figures", file=sys.stderr)
        written.append(plot_biases(run, out_dir))
        if errors:
            written.append(plot_comparison(run, out_dir, kind, errors))
    return written


def plot_montecarlo(summary, out_dir) -> Path:
    """``montecarlo_nees.png``: the pose NEES per dimension at each keyframe, averaged over the
    Monte Carlo runs, per estimator, with the 95% chi-square interval of that average."""
    import matplotlib

    low, high = summary.nees_interval_95
    with matplotlib.rc_context(STYLE):
        fig = _figure("montecarlo_nees")
        ax = fig.add_subplot()
        ax.axhspan(low, high, color="0.85", label=f"95% interval ({summary.runs} runs)")
        ax.axhline(1.0, color="0.3", lw=0.8, ls="--")
        for k, (name, e) in enumerate(summary.estimators.items()):
            color = COLORS.get(name, _SPARE_COLORS[k % len(_SPARE_COLORS)])
            ax.plot(e["t"], e["nees_per_keyframe"], color=color, lw=1.2, ls=LINESTYLES.get(name, "-"),
                    label=f"{name} (mean {e['nees_mean']:.2f}, {100 * e['nees_share_inside_95']:.0f}% inside)")
        ax.set_xlabel("time [s]")
        ax.set_ylabel("pose NEES / 6, mean over runs")
        ax.set_title(f"Monte Carlo consistency: {summary.runs} runs")
        ax.legend(loc="upper right", fontsize=9)
        return _save(fig, out_dir, "montecarlo_nees")


def plot_allan(result, out_dir) -> Path:
    """``allan.png``: the Allan deviation of each accelerometer and gyro axis (a
    :class:`datasets.allan.AllanResult`), log-log, with the fitted white-noise (slope -1/2) and
    random-walk (slope +1/2) lines of each axis and the points where they are read (1 s, 3 s)."""
    import matplotlib

    with matplotlib.rc_context(STYLE):
        fig = _figure("allan")
        panels = (("accelerometer", result.acc_adev, result.acc_white, result.acc_walk, "m/s$^2$"),
                  ("gyro", result.gyro_adev, result.gyro_white, result.gyro_walk, "rad/s"))
        tau = result.tau
        for j, (name, adev, white, walk, unit) in enumerate(panels):
            ax = fig.add_subplot(1, 2, j + 1)
            for k, axis in enumerate("xyz"):
                color = ("tab:blue", "tab:orange", "tab:green")[k]
                known = f"{walk[k]:.3g}" if np.isfinite(walk[k]) else "not estimated"
                ax.loglog(tau, adev[:, k], color=color, label=f"{axis}: N {white[k]:.3g}, K {known}")
                ax.loglog(tau, white[k] / np.sqrt(tau / WHITE_TAU), color=color, lw=0.8, ls="--")
                ax.loglog(tau, walk[k] * np.sqrt(tau / WALK_TAU), color=color, lw=0.8, ls=":")
                ax.plot([WHITE_TAU, WALK_TAU], [white[k], walk[k]], "o", color=color, ms=4)
            low = min(adev.min(), white.min(), np.nanmin(walk, initial=np.inf))  # NaN: a walk not estimated
            high = max(adev.max(), white.max(), np.nanmax(walk, initial=0.0))
            ax.set_ylim(low / 3, high * 3)  # the fitted lines run far beyond the data: keep them in view
            ax.set_xlabel("cluster time $\\tau$ [s]")
            ax.set_ylabel(f"Allan deviation [{unit}]")
            ax.set_title(f"{name}: white noise N (--, read at 1 s), random walk K (:, read at 3 s)")
            ax.legend(loc="upper center")
        return _save(fig, out_dir, "allan")
