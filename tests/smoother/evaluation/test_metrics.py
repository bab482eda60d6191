"""Evaluation metrics (smoother/evaluation/metrics.py): association, alignment, ATE, RPE, NEES,
chi-square; and agreement with evo."""
from __future__ import annotations

import numpy as np
import pytest
from straight_drive import straight_drive, transformed

from datasets.tum import write_tum
from factors import imu, so3
from factors.imu import ImuState
from smoother.evaluation import metrics
from smoother.evaluation.metrics import (
    align_posyaw,
    associate,
    ate,
    evaluate,
    nees,
    rpe,
    rpe_pairs,
    umeyama,
)
from smoother.stats import chi2_quantile, nees_bounds


def _walk(n=300, seed=0, dt=0.05, t0=1000.0):
    rng = np.random.default_rng(seed)
    t = t0 + dt * np.arange(n)
    r = np.cumsum(rng.normal(scale=0.3, size=(n, 3)), axis=0)
    C = so3.exp(np.cumsum(rng.normal(scale=0.05, size=(n, 3)), axis=0) + [0.2, -0.4, 1.0])
    return t, r, C


# ------------------------------------------------------------------------------------------
# association


def test_associate_nearest_within_max_dt():
    t_ref = np.array([0.0, 1.0, 2.0, 3.0])
    t_est = np.array([0.004, 1.5, 2.996])  # the shorter one is walked
    i_ref, i_est = associate(t_ref, t_est, 0.01)
    assert i_ref.tolist() == [0, 3] and i_est.tolist() == [0, 2]
    # the reference walked when it is shorter; the nearest wins
    i_ref, i_est = associate([1.0], [0.0, 0.995, 1.004, 2.0], 0.01)
    assert i_ref.tolist() == [0] and i_est.tolist() == [2]
    # tie: the earlier stamp; a difference of exactly max_dt is accepted
    assert associate([0.0, 0.5], [0.25], 0.25)[0].tolist() == [0]
    assert associate([0.0, 1.0], [0.5], 0.4)[0].size == 0
    # equal lengths: the estimate is walked; a stamp of the longer may serve twice (as in evo)
    i_ref, i_est = associate([1.0, 2.0], [1.001, 1.003], 0.01)
    assert i_ref.tolist() == [0, 0] and i_est.tolist() == [0, 1]
    i_ref, i_est = associate([1.0, 5.0, 6.0], [0.996, 1.004], 0.01)
    assert i_ref.tolist() == [0, 0] and i_est.tolist() == [0, 1]
    assert associate([], [1.0], 0.1)[0].size == 0
    with pytest.raises(ValueError, match="sorted"):
        associate([1.0, 0.0], [0.0], 0.1)
    with pytest.raises(ValueError, match="max_dt"):
        associate([0.0], [0.0], -1.0)


# ------------------------------------------------------------------------------------------
# alignment


def test_umeyama_recovers_a_known_transform_and_scale():
    rng = np.random.default_rng(1)
    src = rng.normal(size=(50, 3))
    R, t = so3.exp([0.5, -2.0, 1.0]), np.array([3.0, -1.0, 7.0])
    R_hat, t_hat, s_hat = umeyama(src, src @ R.T + t)
    assert np.abs(R_hat - R).max() < 1e-12 and np.abs(t_hat - t).max() < 1e-12 and s_hat == 1.0
    R_hat, t_hat, s_hat = umeyama(src, 2.5 * src @ R.T + t, with_scale=True)
    assert np.abs(R_hat - R).max() < 1e-12 and np.abs(t_hat - t).max() < 1e-11 and abs(s_hat - 2.5) < 1e-12
    # a mirror image still gives a rotation
    R_hat, _, _ = umeyama(src, src * [1, 1, -1])
    assert abs(np.linalg.det(R_hat) - 1.0) < 1e-12


@pytest.mark.parametrize("points", [np.zeros((2, 3)), np.outer(np.arange(10.0), [1.0, 2.0, 3.0]), np.ones((5, 3))])
def test_umeyama_refuses_degenerate_points(points):
    with pytest.raises(ValueError, match="degenerate"):
        umeyama(points, points + 1.0)


def test_posyaw_recovers_yaw_and_translation_only():
    rng = np.random.default_rng(2)
    src = rng.normal(size=(40, 3))
    Rz = so3.exp([0.0, 0.0, 2.5])
    R, t = align_posyaw(src, src @ Rz.T + [1.0, 2.0, 3.0])
    assert np.abs(R - Rz).max() < 1e-12 and np.abs(t - [1.0, 2.0, 3.0]).max() < 1e-12
    # with a roll in the true offset, the result is still a rotation about z
    R, _ = align_posyaw(src, src @ so3.exp([0.3, 0.0, 2.5]).T)
    assert R[2, 2] == 1.0 and R[0, 2] == R[2, 0] == 0.0


def test_a_straight_drive_is_not_rolled_about_the_road():
    """Positions near a line fix no rotation about it: Umeyama's se3 fits that roll to the drift
    (a rotation ATE of 75.7 deg here for a true 7 deg). The fit reports its conditioning and, the
    rotation not being determined, aligns position and yaw only: the rotation ATE stays 7 deg."""
    (t, r, C), (r_est, C_est) = straight_drive()
    result = evaluate(t, r, C, t, r_est, C_est, align="se3")
    assert result.ate["rotation"]["rmse"] == pytest.approx(7.0, abs=0.05)
    assert result.align == result.fit.mode == "posyaw" and result.fit.requested == "se3"
    conditioning = result.fit.conditioning
    assert not conditioning["determined"] and conditioning["spread_m"] < 0.05 * conditioning["extent_m"]
    values = conditioning["singular_values_m2"]
    assert values[1] < 1e-5 * values[0] and values[2] < 1e-5 * values[0]
    assert result.fit.note.startswith("se3 alignment is degenerate: the rotation about the line the positions lie "
                                      "along is not determined by 301 positions spread ")
    assert result.fit.note.endswith("; posyaw applied instead")
    # sim3 keeps its scale, about gravity
    scaled = evaluate(t, r, C, t, 0.5 * r_est, C_est, align="sim3")
    assert scaled.align == "posyaw+scale" and scaled.s == pytest.approx(2.0, rel=0.02)
    assert scaled.ate["rotation"]["rmse"] == pytest.approx(7.0, abs=0.05)


def test_alignments_that_fix_no_rotation_fall_back_to_a_translation():
    """An elevator (a vertical line) fixes neither the rotation about it nor a yaw; standing still
    fixes no rotation at all: the translation is aligned, and the note says so."""
    t = np.arange(40.0)
    rise = np.outer(t, [0.0, 0.0, 0.5]) + np.random.default_rng(0).normal(scale=1e-3, size=(40, 3))
    C = np.tile(np.eye(3), (40, 1, 1))
    for mode in ("se3", "posyaw"):
        fit = metrics.fit_alignment(rise + [1.0, 2.0, 3.0], rise, mode)
        assert fit.mode == "translation" and np.array_equal(fit.R, np.eye(3))
        assert np.allclose(fit.t, [1.0, 2.0, 3.0]) and f"{mode} alignment is degenerate" in fit.note
    still = np.zeros((5, 3))
    assert evaluate(t[:5], still, C[:5], t[:5], still + 1.0, C[:5]).align == "translation"


def test_a_well_spread_trajectory_keeps_its_alignment_and_a_loose_fit_is_said():
    t, r, C = _walk()
    fit = metrics.fit_alignment(r, r @ so3.exp([0.1, 0.2, 0.3]).T, "se3")
    assert fit.mode == "se3" and fit.note is None and fit.conditioning["determined"]
    assert fit.conditioning["uncertainty_deg"] < 1e-6
    # errors as large as the trajectory's spread: applied, with how uncertain its rotation is
    noisy = r + np.random.default_rng(3).normal(scale=0.5 * r.std(), size=r.shape)
    loose = metrics.fit_alignment(r, noisy, "se3")
    assert loose.mode == "se3" and loose.note.startswith("se3 alignment is poorly determined: its residual across")


@pytest.mark.parametrize("mode", ["se3", "posyaw"])
def test_alignment_recovers_a_known_offset_and_ate_is_zero(mode):
    t, r, C = _walk()
    phi = [0.0, 0.0, -1.2] if mode == "posyaw" else [0.4, -0.3, -1.2]
    R, offset = so3.exp(phi), np.array([10.0, -5.0, 2.0])
    r_est, C_est = transformed(R, offset, r, C)
    result = evaluate(t, r, C, t, r_est, C_est, align=mode)
    assert np.abs(result.R - R.T).max() < 1e-12
    assert np.abs(result.t + R.T @ offset).max() < 1e-10
    assert result.ate["translation"]["max"] < 1e-10 and result.ate["rotation"]["max"] < 1e-6
    unaligned = evaluate(t, r, C, t, r_est, C_est, align="none")
    assert unaligned.ate["translation"]["min"] > 1.0


def test_ate_known_errors():
    t, r, C = _walk(n=20)
    e = ate(r, C, r + [0.0, 3.0, 4.0], so3.exp([0.0, 0.0, np.radians(2.0)]) @ C)
    assert np.allclose(e["translation_errors"], 5.0) and e["translation"]["rmse"] == pytest.approx(5.0)
    assert np.allclose(e["rotation_errors"], 2.0) and e["rotation"]["median"] == pytest.approx(2.0)
    stats = metrics.statistics([3.0, 4.0])
    assert stats == {"rmse": np.sqrt(12.5), "mean": 3.5, "median": 3.5, "std": 0.5, "min": 3.0, "max": 4.0,
                     "sse": 25.0, "count": 2}


# ------------------------------------------------------------------------------------------
# RPE


def test_rpe_pairs_semantics():
    r = np.zeros((9, 3))
    r[:, 0] = 0.5 * np.arange(9)
    assert rpe_pairs(r, None, 1) == [(i, i + 1) for i in range(8)]
    assert rpe_pairs(r, None, 3) == [(0, 3), (3, 6)]
    assert rpe_pairs(r, None, 3, all_pairs=True) == [(i, i + 3) for i in range(6)]
    assert rpe_pairs(r, None, 1.0, unit="m") == [(0, 2), (2, 4), (4, 6), (6, 8)]
    assert rpe_pairs(r, None, 1.0, unit="m", all_pairs=True) == [(i, i + 2) for i in range(7)]
    t = np.array([0.0, 0.1, 0.3, 0.35, 0.6, 0.9])
    assert rpe_pairs(r[:6], t, 0.3, unit="s") == [(0, 2), (2, 4), (4, 5)]
    for bad in (0, 1.5, -2):
        with pytest.raises(ValueError, match="delta"):
            rpe_pairs(r, None, bad)
    with pytest.raises(ValueError, match="unit"):
        rpe_pairs(r, None, 1.0, unit="deg")


def test_rpe_is_invariant_to_a_global_transform_and_local():
    t, r, C = _walk(n=60, seed=4)
    rng = np.random.default_rng(5)
    r_est = r + rng.normal(scale=0.01, size=r.shape)
    C_est = so3.exp(rng.normal(scale=0.01, size=r.shape)) @ C
    a = rpe(r, C, r_est, C_est)
    moved = transformed(so3.exp([1.0, 2.0, -0.5]), [4.0, 5.0, 6.0], r_est, C_est)
    b = rpe(r, C, *moved)
    assert np.allclose(a["translation_errors"], b["translation_errors"], atol=1e-12)
    assert np.allclose(a["rotation_errors"], b["rotation_errors"], atol=1e-9)
    # a jump at one pose only changes the two pairs touching it
    r_jump = r.copy()
    r_jump[30] += [0.0, 0.0, 1.0]
    e = rpe(r, C, r_jump, C)["translation_errors"]
    assert np.allclose(np.flatnonzero(e > 1e-12), [29, 30]) and np.allclose(e[[29, 30]], 1.0)


# ------------------------------------------------------------------------------------------
# NEES


def _random_cov(rng, anisotropic=True):
    A = rng.normal(size=(15, 15))
    cov = A @ A.T * 1e-3 + np.eye(15) * 1e-4
    if anisotropic:
        cov[8, 8] += 0.05  # large yaw (about WORLD z) uncertainty
    return cov


def test_nees_definition_exact():
    rng = np.random.default_rng(6)
    est = ImuState(rng.normal(size=3), rng.normal(size=3), so3.exp(rng.normal(size=3)), rng.normal(size=3),
                   rng.normal(size=3))
    cov = _random_cov(rng)
    e = rng.multivariate_normal(np.zeros(15), cov)
    truth = imu.boxplus(est, e)  # truth = est [+] e, i.e. e = truth [-] est
    idx = np.r_[0:3, 6:9]
    expected = e[idx] @ np.linalg.solve(cov[np.ix_(idx, idx)], e[idx])
    assert nees(truth, est, cov) == pytest.approx(expected, rel=1e-9)
    assert nees(truth, est, cov, part="full") == pytest.approx(e @ np.linalg.solve(cov, e), rel=1e-9)
    pos = e[:3] @ np.linalg.solve(cov[:3, :3], e[:3])
    assert nees(truth, est, cov, part="position") == pytest.approx(pos, rel=1e-9)
    with pytest.raises(ValueError, match="part"):
        nees(truth, est, cov, part="bias")
    unknown = truth.replace(v=np.full(3, np.nan))
    assert np.isfinite(nees(unknown, est, cov))  # the pose part does not need velocities
    with pytest.raises(ValueError, match="not finite"):
        nees(unknown, est, cov, part="full")


def test_nees_monte_carlo_consistent_only_in_the_left_world_convention():
    rng = np.random.default_rng(7)
    runs = 3000
    C_est = so3.exp([1.2, 0.3, -0.8])
    est = ImuState(np.zeros((runs, 3)), np.zeros((runs, 3)), np.broadcast_to(C_est, (runs, 3, 3)),
                   np.zeros((runs, 3)), np.zeros((runs, 3)))
    cov = np.diag([0.01] * 3 + [0.01] * 3 + [1e-4, 1e-4, 0.05] + [1e-3] * 6)
    e = rng.multivariate_normal(np.zeros(15), cov, size=runs)
    left = imu.boxplus(est, e)
    value = nees(left, est, np.broadcast_to(cov, (runs, 15, 15))).mean()
    lo, hi = nees_bounds(6, runs, 0.999)
    assert lo < value < hi
    # the same numbers as a body-frame (right) perturbation C exp(n) are not consistent
    right = left.replace(C=C_est @ so3.exp(e[:, 6:9]))
    assert nees(right, est, np.broadcast_to(cov, (runs, 15, 15))).mean() > 2 * hi


# ------------------------------------------------------------------------------------------
# chi-square (SciPy's) and the NEES band


def test_the_nees_band_and_its_arguments():
    """The band of one run's 1-dof NEES is [z_0.025^2, z_0.975^2] = [0.000982, 5.02]; averaged
    over M runs it narrows around 1 per dof; p outside [0, 1], dof or runs below 1 are refused."""
    lo, hi = nees_bounds(1, 1, 0.95)
    assert lo == pytest.approx(0.0009820691171752583, rel=1e-9) and hi == pytest.approx(5.023886187314888, rel=1e-9)
    lo, hi = nees_bounds(6, 1000, 0.95)
    assert 5.6 < lo < 6.0 < hi < 6.4
    assert chi2_quantile(0.95, 1) == pytest.approx(1.959963984540054**2, rel=1e-12)
    from scipy.stats import chi2

    for p, dof in ((1e-9, 1), (0.025, 6), (0.5, 15), (0.975, 6000), (1 - 1e-6, 45000)):
        assert chi2_quantile(p, dof) == chi2.ppf(p, dof), (p, dof)  # SciPy's own chi-square, bit for bit
    assert chi2_quantile(0.0, 3) == 0.0 and chi2_quantile(1.0, 3) == np.inf
    for bad in ((1.5, 3), (np.nan, 3), (0.5, 0), (0.5, -1), (0.5, np.inf)):
        with pytest.raises(ValueError):
            chi2_quantile(*bad)
    with pytest.raises(ValueError):
        nees_bounds(0, 10)


def test_the_quantiles_import_scipy_special_at_the_first_call_and_never_scipy_stats():
    """Importing the metrics and the modules that take chi-square quantiles (EKF gate, robust
    kernels' thresholds, the sensors' verdicts) imports no ``scipy.special``; the first quantile
    does, and ``scipy.stats`` (five times slower to import) is never imported."""
    import subprocess
    import sys

    script = (
        "import sys\n"
        "import smoother.stats, smoother.evaluation.metrics, smoother.ekf.filter, smoother.model.problem\n"
        "import smoother.diagnosis.verdicts\n"
        "assert 'scipy.special' not in sys.modules, 'imported with the modules'\n"
        "smoother.stats.nees_bounds(6, 10)\n"
        "assert 'scipy.special' in sys.modules and 'scipy.stats' not in sys.modules\n"
    )
    done = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True)
    assert done.returncode == 0, done.stderr[-2000:]


# ------------------------------------------------------------------------------------------
# evo


def _evo_case(tmp_path, seed):
    """Reference and estimate TUM files: noisy, transformed, jittered in time, of different
    lengths, with gaps, so that association and alignment both matter."""
    rng = np.random.default_rng(seed)
    t, r, C = _walk(n=300, seed=seed)
    keep = np.sort(rng.choice(300, size=250, replace=False))
    R, offset = so3.exp(rng.normal(size=3)), rng.normal(scale=20.0, size=3)
    r_est = r + rng.normal(scale=0.05, size=r.shape)
    C_est = so3.exp(rng.normal(scale=0.02, size=r.shape)) @ C
    r_est, C_est = transformed(R, offset, r_est, C_est)
    t_est = t + rng.uniform(-0.004, 0.004, size=t.size)
    t_est[keep[::7]] += 0.03  # some too far off to associate
    order = np.argsort(t_est[keep])
    ref_path, est_path = tmp_path / f"ref{seed}.txt", tmp_path / f"est{seed}.txt"
    write_tum(ref_path, t, r, C)
    write_tum(est_path, t_est[keep][order], r_est[keep][order], C_est[keep][order])
    return ref_path, est_path


def _close(a, b):
    return abs(a - b) <= 1e-9 * max(1.0, abs(b))


@pytest.mark.parametrize("align", ["se3", "none"])
@pytest.mark.parametrize("seed, delta, unit, all_pairs", [(11, 1, "frames", False), (12, 5, "frames", False),
                                                          (13, 4, "frames", True), (14, 2.0, "m", False),
                                                          (15, 3.0, "m", True)])
def test_agrees_with_evo(tmp_path, seed, align, delta, unit, all_pairs):
    pytest.importorskip("evo", reason="evo (test-only dependency) is not installed: pip install evo")
    from evo.core import metrics as evo_metrics
    from evo.core import sync
    from evo.tools import file_interface

    from datasets.tum import read_tum

    ref_path, est_path = _evo_case(tmp_path, seed)
    ref, est = read_tum(ref_path), read_tum(est_path)
    ours = evaluate(ref.t, ref.position, ref.C, est.t, est.position, est.C, align=align, max_dt=0.01,
                    delta=delta, delta_unit=unit, all_pairs=all_pairs)

    evo_ref = file_interface.read_tum_trajectory_file(str(ref_path))
    evo_est = file_interface.read_tum_trajectory_file(str(est_path))
    evo_ref, evo_est = sync.associate_trajectories(evo_ref, evo_est, max_diff=0.01)
    assert np.array_equal(evo_ref.timestamps, ref.t[ours.i_ref])
    assert np.array_equal(evo_est.timestamps, est.t[ours.i_est])
    if align == "se3":
        R, t, s = evo_est.align(evo_ref, correct_scale=False)
        assert np.abs(R - ours.R).max() < 1e-9 and np.abs(t - ours.t).max() < 1e-9
    relations = {"translation": evo_metrics.PoseRelation.translation_part,
                 "rotation": evo_metrics.PoseRelation.rotation_angle_deg}
    evo_unit = evo_metrics.Unit.frames if unit == "frames" else evo_metrics.Unit.meters
    compared = 0
    for name, relation in relations.items():
        ape = evo_metrics.APE(relation)
        ape.process_data((evo_ref, evo_est))
        rpe_metric = evo_metrics.RPE(relation, delta=delta, delta_unit=evo_unit, all_pairs=all_pairs)
        rpe_metric.process_data((evo_ref, evo_est))
        pairs = ((ours.ate[name], ape.get_all_statistics()), (ours.rpe[name], rpe_metric.get_all_statistics()))
        for mine, theirs in pairs:
            for key in ("rmse", "mean", "median", "std", "min", "max", "sse"):
                assert _close(mine[key], theirs[key]), (name, key, mine[key], theirs[key])
                compared += 1
        assert mine["count"] == len(rpe_metric.error)
    assert compared == 28


# ------------------------------------------------------------------------------------------
# two estimators at the same points


def test_rmse_difference_of_equal_errors_is_exactly_zero():
    e = np.random.default_rng(0).rayleigh(1.0, 60)
    out = metrics.rmse_difference(e, e.copy(), np.repeat(np.arange(12), 5))
    assert out["difference"] == 0.0 and out["interval"] == (0.0, 0.0)
    assert out["blocks"] == 12 and out["blocks_a_lower"] == 0


def test_rmse_difference_resolves_a_uniformly_worse_estimator():
    """a = 1.5 b at every point: the difference is 0.5 RMS(b), and every resample keeps a worse."""
    b = np.random.default_rng(1).rayleigh(1.0, 200)
    out = metrics.rmse_difference(1.5 * b, b, np.arange(200) // 10)
    assert out["difference"] == pytest.approx(0.5 * np.sqrt(np.mean(b**2)), rel=1e-12)
    low, high = out["interval"]
    assert 0.0 < low < out["difference"] < high
    assert out["blocks"] == 20 and out["blocks_a_lower"] == 0


def test_rmse_difference_interval_reflects_correlation_within_blocks():
    """Within each block a is offset from b by one shared random amount (correlated errors, no
    difference on average): the interval over the 10 true blocks contains 0 and is much wider than
    the one that (wrongly) treats the 400 points as independent."""
    rng = np.random.default_rng(2)
    block = np.arange(400) // 40
    b = 2.0 + rng.normal(0.0, 0.05, 400)
    a = b + rng.normal(0.0, 0.3, 10)[block]
    by_block = metrics.rmse_difference(a, b, block)["interval"]
    by_point = metrics.rmse_difference(a, b, np.arange(400))["interval"]
    assert by_block[0] < 0.0 < by_block[1]
    assert by_block[1] - by_block[0] > 3.0 * (by_point[1] - by_point[0])


def test_rmse_difference_rejects_mismatched_or_bad_input():
    e = np.ones(5)
    with pytest.raises(ValueError, match="equal length"):
        metrics.rmse_difference(e, np.ones(4), np.zeros(5))
    with pytest.raises(ValueError, match="equal length"):
        metrics.rmse_difference(e, e, np.zeros(4))
    with pytest.raises(ValueError, match="finite"):
        metrics.rmse_difference(np.r_[1.0, np.nan, 1, 1, 1], e, np.zeros(5))
    with pytest.raises(ValueError, match="confidence"):
        metrics.rmse_difference(e, e, np.zeros(5), confidence=1.0)
    with pytest.raises(ValueError, match="resamples"):
        metrics.rmse_difference(e, e, np.zeros(5), resamples=0)
    with pytest.raises(ValueError, match="equal length"):
        metrics.rmse_difference(np.ones((5, 3)), np.ones((5, 3)), np.zeros(5))
