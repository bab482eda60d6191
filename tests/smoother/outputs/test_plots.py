"""Plots of a run directory: the PNG files, their sizes, runs without truth or with GPS fixes,
errors for missing or malformed inputs (``smoother plot DIR``: ``tests/cli/test_plot_cli.py``).

The run directory is written by :func:`smoother.outputs.files.write_outputs` from a 3 s simulated
dataset and hand-made estimates (the truth perturbed, with matching covariances), so that the
tests exercise the real file format without running the estimators.
"""
from __future__ import annotations

import shutil
import struct
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest

from datasets.atomic import atomic_write
from datasets.simulate import simulate
from datasets.types import SAME_INSTANT_S, Trajectory
from factors import so3
from factors.errors import InputError
from factors.imu import ImuState
from smoother.evaluation import metrics, scoring
from smoother.outputs import canvas, files, plots

PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"
ALL_FIGURES = ["trajectory", "position_error", "orientation_error", "nees", "biases", "comparison"]
# (position [m], attitude [rad], acc bias [m/s^2], gyro bias [rad/s]) error sigmas per estimator
SIGMAS = {"batch": (0.01, 0.002, 0.005, 0.0005), "fixed-lag": (0.02, 0.004, 0.01, 0.001),
          "ekf": (0.02, 0.004, 0.01, 0.001)}


def _estimate(truth: Trajectory, sigmas, rng) -> SimpleNamespace:
    """The truth at 10 Hz, perturbed with the given sigmas, and the matching diagonal covariance."""
    idx = np.arange(0, len(truth), 20)
    s = truth.states[idx]
    n = len(idx)
    sr, sphi, sbf, sbw = sigmas
    # C_est = exp(-e) C_true, so that log(C_true C_est^T) = e ~ N(0, sphi^2 I)
    states = ImuState(
        r=s.r + sr * rng.standard_normal((n, 3)), v=s.v + 0.01 * rng.standard_normal((n, 3)),
        C=so3.boxplus(s.C, -sphi * rng.standard_normal((n, 3))),
        b_f=s.b_f + sbf * rng.standard_normal((n, 3)), b_w=s.b_w + sbw * rng.standard_normal((n, 3)),
    )
    diag = np.repeat([sr, 0.01, sphi, sbf, sbw], 3) ** 2
    cov = np.broadcast_to(np.diag(diag), (n, 15, 15)).copy()
    return SimpleNamespace(trajectory=Trajectory(truth.t[idx], states, cov), runtime_s=0.5, details={}, failed=None,
                           calibration=None, following=None, heldout=None)


@pytest.fixture(scope="module")
def run_dir(tmp_path_factory) -> Path:
    dataset = simulate(duration=3.0, seed=1)
    rng = np.random.default_rng(7)
    estimates = {name: _estimate(dataset.truth, sig, rng) for name, sig in SIGMAS.items()}
    out = tmp_path_factory.mktemp("run")
    files.write_outputs(out, dataset, estimates, {"dataset": "test"})
    return out


def _copy(run_dir: Path, tmp_path: Path, without=()) -> Path:
    target = tmp_path / "copy"
    shutil.copytree(run_dir, target)
    for name in without:
        (target / name).unlink()
    return target


def _png_size(path: Path) -> tuple[int, int]:
    data = path.read_bytes()
    assert data[:8] == PNG_SIGNATURE, f"{path} is not a PNG"
    assert data[12:16] == b"IHDR"
    return struct.unpack(">II", data[16:24])


def _check_pngs(paths, directory: Path, stems) -> None:
    assert [p.stem for p in paths] == list(stems)
    for p in paths:
        assert p.parent == directory and p.suffix == ".png" and p.stat().st_size > 10_000
        w, h = plots.FIGSIZE[p.stem]
        assert _png_size(p) == (round(w * canvas.DPI), round(h * canvas.DPI))
    assert not list(directory.glob(".*.tmp")), "temporary files left behind"


def test_plot_run_writes_every_figure(run_dir, tmp_path):
    from matplotlib._pylab_helpers import Gcf

    directory = _copy(run_dir, tmp_path)  # the shared run directory stays free of PNGs
    paths = plots.plot_run(directory)
    _check_pngs(paths, directory, ALL_FIGURES)
    assert Gcf.get_num_fig_managers() == 0, "plot_run must not leave pyplot figures open"


def test_without_truth_or_gps_draws_what_it_can(run_dir, tmp_path, capsys):
    directory = _copy(run_dir, tmp_path, without=["truth.npz"])
    paths = plots.plot_run(directory, estimators=["ekf"])
    _check_pngs(paths, directory, ["trajectory", "biases"])
    assert "neither truth.npz nor gps.npz" in capsys.readouterr().err


def test_gps_reference(run_dir, tmp_path):
    """KITTI-like: no truth, GPS fixes (every third used, the rest held out) in gps.npz."""
    directory = _copy(run_dir, tmp_path, without=["truth.npz"])
    truth = files.load_trajectory(run_dir / "truth.npz")
    rng = np.random.default_rng(3)
    idx = np.arange(5, len(truth), 10)
    heldout = np.arange(len(idx)) % 3 != 0
    with atomic_write(directory / "gps.npz", "wb") as handle:
        np.savez(handle, t=truth.t[idx], position=truth.position[idx] + 0.05 * rng.standard_normal((len(idx), 3)),
                 cov=np.broadcast_to(0.05 ** 2 * np.eye(3), (len(idx), 3, 3)), heldout=heldout)
    paths = plots.plot_run(directory, estimators=["ekf"])
    _check_pngs(paths, directory, ["trajectory", "position_error", "nees", "biases", "comparison"])

    run = files.load_run(directory, ["ekf"])
    g = run.gps
    e = scoring.errors_against_fixes(g.t, g.position, g.cov, g.heldout, run.estimates["ekf"])
    assert e.dof == 3 and np.array_equal(e.heldout, heldout)
    # comparison.png's bars: the held-out RMSE, and the residual to the used fixes labelled as such
    bars = {key: (label, values) for key, label, values in plots.bar_values(run, "gps", {"ekf": e})}
    assert bars["gps_heldout_rmse_m"][0] == "RMSE to held-out fixes [m]\n(accuracy)"
    assert bars["gps_fit_residual_m"][0] == "residual to used fixes [m]\n(a fit, not accuracy)"
    for key, mask in (("gps_heldout_rmse_m", heldout), ("gps_fit_residual_m", ~heldout)):
        assert bars[key][1]["ekf"] == pytest.approx(np.sqrt(np.mean(np.sum(e.dr[mask] ** 2, axis=1))), rel=1e-12)
    # NEES only where the fix was held out (a used fix is not independent of the estimate)
    assert np.all(np.isfinite(e.nees[heldout])) and np.all(np.isnan(e.nees[~heldout]))


def test_errors_against_truth_match_metrics(run_dir):
    """At common time stamps the plotted errors and NEES are the metrics module's."""
    run = files.load_run(run_dir, ["batch"])
    est = run.estimates["batch"]
    e = scoring.errors_against_truth(run.truth, est)
    i_truth, i_est = metrics.associate(run.truth.t, est.t, SAME_INSTANT_S)
    assert len(i_est) == len(est) == len(e.t)
    T = run.truth.states[i_truth]
    expected = metrics.pose_error(T.r, T.C, est.states.r, est.states.C)
    np.testing.assert_allclose(np.hstack([e.dr, e.dphi]), expected, atol=1e-12)
    np.testing.assert_allclose(e.nees, metrics.nees(T, est.states, est.cov, "pose"), rtol=1e-10)


def test_missing_or_malformed_run_directory(tmp_path, run_dir):
    with pytest.raises(InputError, match="no estimate found"):
        plots.plot_run(tmp_path)
    with pytest.raises(InputError, match="not a directory"):
        plots.plot_run(tmp_path / "nowhere")
    with pytest.raises(InputError, match=r"foo\.npz: not found; this run has batch, fixed-lag, ekf"):
        files.load_run(run_dir, ["foo"])

    bad = tmp_path / "bad"
    bad.mkdir()
    (bad / "ekf.npz").write_text("not an archive\n")
    with pytest.raises(InputError, match=r"ekf\.npz: not an \.npz archive"):
        plots.plot_run(bad)
    np.savez(bad / "ekf.npz", t=np.arange(3.0))
    with pytest.raises(InputError, match=r"ekf\.npz: missing array\(s\) r, v, C, b_f, b_w"):
        plots.plot_run(bad)
    est = files.load_trajectory(run_dir / "ekf.npz")
    files.save_trajectory(bad / "ekf.npz", est)
    np.savez(bad / "gps.npz", t=np.arange(3.0), position=np.zeros((2, 3)))
    with pytest.raises(InputError, match=r"gps\.npz: inconsistent shapes"):
        files.load_run(bad)
    (bad / "gps.npz").unlink()
    (bad / "metrics.json").write_text("{ not json")
    with pytest.raises(InputError, match=r"metrics\.json: cannot read it"):
        files.load_run(bad)


def _gps_run(run_dir: Path, tmp_path: Path) -> Path:
    """A copy of the run directory without truth and metrics, with GPS fixes every 10th truth
    sample (every third used, the rest held out)."""
    directory = _copy(run_dir, tmp_path, without=["truth.npz", "metrics.json"])
    truth = files.load_trajectory(run_dir / "truth.npz")
    rng = np.random.default_rng(3)
    idx = np.arange(5, len(truth), 10)
    with atomic_write(directory / "gps.npz", "wb") as handle:
        np.savez(handle, t=truth.t[idx], position=truth.position[idx] + 0.05 * rng.standard_normal((len(idx), 3)),
                 cov=np.broadcast_to(0.05 ** 2 * np.eye(3), (len(idx), 3, 3)), heldout=np.arange(len(idx)) % 3 != 0)
    return directory


def test_the_figures_draw_what_the_metrics_and_the_report_computed(run_dir, tmp_path):
    """The arrays behind the figures are the report's and the metrics' own, bit for bit: the GPS
    residuals (:func:`smoother.evaluation.scoring.fix_residuals`), the held-out fixes' NEES
    (:func:`smoother.evaluation.metrics.nees_from` of the residual and ``P_est + R_fix``), the pose NEES
    against the truth (:func:`smoother.evaluation.scoring.compare_with_truth`), and, without metrics.json,
    the bars' figures (:func:`smoother.evaluation.scoring.against_truth`,
    :func:`smoother.evaluation.scoring.position_rmse`)."""
    from datasets.types import PositionMeasurements

    gps_run = files.load_run(_gps_run(run_dir, tmp_path), ["ekf"])
    g, est = gps_run.gps, gps_run.estimates["ekf"]
    e = scoring.errors_against_fixes(g.t, g.position, g.cov, g.heldout, est)
    inside, residual = scoring.fix_residuals(g.t, g.position, est)
    np.testing.assert_array_equal(e.dr, -residual)
    h = e.heldout
    P = est.interpolate(g.t[inside])[1][:, :3, :3] + g.cov[inside]
    np.testing.assert_array_equal(e.nees[h], metrics.nees_from(residual[h], P[h]))
    bars = {key: values["ekf"] for key, _, values in plots.bar_values(gps_run, "gps", {"ekf": e})}
    for key, rows in (("gps_heldout_rmse_m", g.heldout), ("gps_fit_residual_m", ~g.heldout)):
        fixes = PositionMeasurements(g.t[rows], g.position[rows], g.cov[rows])
        assert bars[key] == scoring.position_rmse(fixes, est), key

    run = files.load_run(run_dir)
    for name, est in run.estimates.items():
        e = scoring.errors_against_truth(run.truth, est)
        np.testing.assert_array_equal(e.nees, scoring.compare_with_truth(run.truth, est)["nees"])
    bare = files.Run(run.run_dir, run.estimates, run.truth, None, {})  # no metrics.json
    errors = plots.reference_errors(bare)[1]
    for key, _, values in plots.bar_values(bare, "truth", errors):
        if key != "runtime_s":
            assert values == {n: scoring.against_truth(run.truth, est)[key] for n, est in run.estimates.items()}, key


def test_the_nees_figure_draws_the_errors_nees(run_dir, tmp_path, monkeypatch):
    """nees.png's line of each estimator is its NEES at its times (clipped at the axis' bottom only)."""
    drawn = []

    def keep(fig, out_dir, stem):
        drawn.extend((ax.get_lines()[1].get_xydata(), ax.get_ylim()[0]) for ax in fig.axes if ax.get_lines())
        fig.clear()
        return Path(out_dir) / f"{stem}.png"

    monkeypatch.setattr(plots, "save_png", keep)
    run = files.load_run(run_dir)
    kind, errors = plots.reference_errors(run)
    plots.plot_nees(run, tmp_path, kind, errors)
    assert len(drawn) == len(errors) == 3
    for (xy, bottom), e in zip(drawn, errors.values()):
        np.testing.assert_array_equal(xy[:, 0], e.t - run.t0)
        np.testing.assert_array_equal(xy[:, 1], np.clip(e.nees, bottom, None))
