"""``smoother evaluate`` against evo (a test-only dependency) on the inputs evo accepts: duplicate
stamps, Sim(3) alignment, alignment to the first N poses, EuRoC CSV and KITTI pose files, a time
offset; and what evo does not take: a reference with attitudes only, stamps that never meet."""
from __future__ import annotations

import json
import warnings

import numpy as np
import pytest

from datasets.tum import write_tum
from factors import quaternion, so3
from smoother.cli import main

evo_metrics = pytest.importorskip("evo.core.metrics", reason="evo (test-only dependency): pip install evo")
from evo.core import sync  # noqa: E402
from evo.tools import file_interface  # noqa: E402

STATS = ("rmse", "mean", "median", "std", "min", "max", "sse")


def _walk(n: int, seed: int):
    """A random trajectory at 20 Hz from t = 1000 s: positions and attitudes."""
    rng = np.random.default_rng(seed)
    t = 1000.0 + 0.05 * np.arange(n)
    r = np.cumsum(rng.normal(scale=0.3, size=(n, 3)), axis=0)
    C = so3.exp(np.cumsum(rng.normal(scale=0.05, size=(n, 3)), axis=0))
    return t, r, C


def _estimate_of(r, C, seed: int, scale: float = 1.0):
    """``r, C`` with noise, scaled by ``scale`` and moved by a random rigid transform."""
    rng = np.random.default_rng(seed)
    R, offset = so3.exp(rng.normal(size=3)), rng.normal(scale=10.0, size=3)
    r_est = scale * (r + rng.normal(scale=0.05, size=r.shape)) @ R.T + offset
    C_est = R @ so3.exp(rng.normal(scale=0.01, size=r.shape)) @ C
    return r_est, C_est


def _ours(capsys, ref, est, *options) -> dict:
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        code = main(["evaluate", "--reference", str(ref), "--estimate", str(est), "--json", *options])
    captured = capsys.readouterr()
    assert code == 0, captured.err
    out = json.loads(captured.out)
    out["_warnings"] = [str(w.message) for w in caught]
    return out


def _evo(traj_ref, traj_est, delta=1) -> dict:
    """evo's APE and RPE (frames) statistics of already associated and aligned trajectories."""
    out = {}
    for key, relation in (("translation_m", evo_metrics.PoseRelation.translation_part),
                          ("rotation_deg", evo_metrics.PoseRelation.rotation_angle_deg)):
        ape = evo_metrics.APE(relation)
        ape.process_data((traj_ref, traj_est))
        rpe = evo_metrics.RPE(relation, delta=delta, delta_unit=evo_metrics.Unit.frames, all_pairs=False)
        rpe.process_data((traj_ref, traj_est))
        out[("ate", key)] = ape.get_all_statistics()
        out[("rpe", key)] = rpe.get_all_statistics()
    return out


def _assert_equal(ours: dict, theirs: dict, keys=("translation_m", "rotation_deg")) -> int:
    compared = 0
    for (kind, key), stats in theirs.items():
        if key not in keys:
            continue
        for stat in STATS:
            mine = ours[kind][key][stat]
            assert abs(mine - stats[stat]) <= 1e-9 * max(1.0, abs(stats[stat])), (kind, key, stat, mine, stats[stat])
            compared += 1
    return compared


def _evo_tum(ref_path, est_path, max_diff=0.01, offset=0.0):
    traj_ref = file_interface.read_tum_trajectory_file(str(ref_path))
    traj_est = file_interface.read_tum_trajectory_file(str(est_path))
    return sync.associate_trajectories(traj_ref, traj_est, max_diff=max_diff, offset_2=offset)


@pytest.mark.parametrize("estimate_longer", [False, True])
def test_duplicate_stamps_are_kept_as_evo_keeps_them(tmp_path, capsys, estimate_longer):
    """A reference with two stamps repeated (as evo's fr2_desk_groundtruth.txt has one): a warning
    naming the first, and every figure equal to evo's, whichever trajectory association walks."""
    t, r, C = _walk(200, seed=1)
    r_est, C_est = _estimate_of(r, C, seed=2)
    dup = [40, 41, 120]
    t_ref = t.copy()
    t_ref[dup[1]] = t_ref[dup[0]]  # line 42 repeats line 41's stamp
    t_ref[dup[2]] = t_ref[dup[2] - 1]
    keep = np.arange(0, 200, 1 if estimate_longer else 3)
    jitter = np.random.default_rng(3).uniform(-0.004, 0.004, size=keep.size)
    ref, est = tmp_path / "ref.txt", tmp_path / "est.txt"
    # write_tum makes a Trajectory (strictly increasing stamps): the reference is written by hand
    q = quaternion.to_xyzw(quaternion.from_matrix(C))
    ref.write_text("".join(" ".join(repr(float(x)) for x in (t_ref[k], *r[k], *q[k])) + "\n" for k in range(200)))
    write_tum(est, t[keep] + jitter, r_est[keep], C_est[keep], header=False)
    ours = _ours(capsys, ref, est)
    repeated = (f"{ref}: 2 time stamp(s) equal to the one before, the first at line 42 ({float(t_ref[40])!r}, "
                "as line 41)")
    assert any(repeated in w for w in ours["_warnings"]), ours["_warnings"]
    traj_ref, traj_est = _evo_tum(ref, est)
    traj_est.align(traj_ref)
    assert ours["pairs"] == traj_ref.num_poses
    assert _assert_equal(ours, _evo(traj_ref, traj_est)) == 28


@pytest.mark.parametrize("n_to_align", [None, 25])
def test_sim3_alignment_and_alignment_to_the_first_poses_equal_evo(tmp_path, capsys, n_to_align):
    """A monocular-like estimate at 0.4 times the scale: --align sim3 (evo -as), optionally fitted
    to the first 25 poses (evo --n_to_align 25); scale, ATE and RPE equal evo's."""
    t, r, C = _walk(150, seed=4)
    r_est, C_est = _estimate_of(r, C, seed=5, scale=0.4)
    ref, est = tmp_path / "ref.txt", tmp_path / "est.txt"
    write_tum(ref, t, r, C)
    write_tum(est, t + 0.001, r_est, C_est)
    options = ["--align", "sim3"] + ([] if n_to_align is None else ["--n-to-align", str(n_to_align)])
    ours = _ours(capsys, ref, est, *options)
    traj_ref, traj_est = _evo_tum(ref, est)
    _, _, s = traj_est.align(traj_ref, correct_scale=True, n=-1 if n_to_align is None else n_to_align)
    assert abs(ours["alignment"]["s"] - s) < 1e-12 and abs(s - 2.5) < 0.1
    assert _assert_equal(ours, _evo(traj_ref, traj_est)) == 28
    if n_to_align is not None:  # the first poses only: another fit than over all of them
        assert abs(_ours(capsys, ref, est, "--align", "sim3")["alignment"]["s"] - s) > 1e-6
    se3_first = _ours(capsys, ref, est, "--n-to-align", "25")
    traj_ref, traj_est = _evo_tum(ref, est)
    traj_est.align(traj_ref, n=25)
    assert _assert_equal(se3_first, _evo(traj_ref, traj_est)) == 28


def test_a_euroc_csv_reference_equals_evo_euroc_mode(tmp_path, capsys):
    """state_groundtruth_estimate0/data.csv (17 columns, nanosecond stamps) against a TUM estimate
    in seconds, recognised without --format; and with --format euroc."""
    t, r, C = _walk(180, seed=6)
    stamps = (np.round(t * 1e9).astype(np.int64) + 1_403_636_579_000_000_000)
    r_est, C_est = _estimate_of(r, C, seed=7)
    q = quaternion.from_matrix(C)  # w, x, y, z
    csv = tmp_path / "data.csv"
    header = ("#timestamp, p_RS_R_x [m], p_RS_R_y [m], p_RS_R_z [m], q_RS_w [], q_RS_x [], q_RS_y [], q_RS_z [], "
              "v_RS_R_x [m s^-1], v_RS_R_y [m s^-1], v_RS_R_z [m s^-1], b_w_RS_S_x [rad s^-1], "
              "b_w_RS_S_y [rad s^-1], b_w_RS_S_z [rad s^-1], b_a_RS_S_x [m s^-2], b_a_RS_S_y [m s^-2], "
              "b_a_RS_S_z [m s^-2]")
    rows = [",".join([str(int(stamps[k]))] + [repr(float(x)) for x in (*r[k], *q[k])] + ["0.0"] * 9)
            for k in range(len(t))]
    csv.write_text(header + "\n" + "\n".join(rows) + "\n")
    est = tmp_path / "est.txt"
    write_tum(est, stamps[::2] / 1e9 + 0.002, r_est[::2], C_est[::2])
    traj_ref = file_interface.read_euroc_csv_trajectory(str(csv))
    traj_est = file_interface.read_tum_trajectory_file(str(est))
    traj_ref, traj_est = sync.associate_trajectories(traj_ref, traj_est, max_diff=0.01)
    traj_est.align(traj_ref)
    theirs = _evo(traj_ref, traj_est)
    for options in ([], ["--format", "euroc"]):
        if options:  # --format names both files' format: the estimate must then be EuRoC CSV too
            est_csv = tmp_path / "est.csv"
            q_est = quaternion.from_matrix(C_est[::2])
            est_csv.write_text("\n".join(",".join([str(int(s + 2_000_000))] + [repr(float(x)) for x in (*p, *qq)])
                                         for s, p, qq in zip(stamps[::2], r_est[::2], q_est)) + "\n")
            ours = _ours(capsys, csv, est_csv, *options)
        else:
            ours = _ours(capsys, csv, est, *options)
        assert ours["formats"]["reference"] == "euroc" and ours["pairs"] == traj_ref.num_poses
        assert _assert_equal(ours, theirs) == 28


def test_kitti_pose_files_equal_evo_kitti_mode(tmp_path, capsys):
    """Two KITTI pose files (3x4 matrices, no stamps), paired by line: as evo's kitti mode; a
    KITTI file against a stamped one, or files of different lengths, are one-line errors."""
    _, r, C = _walk(120, seed=8)
    r_est, C_est = _estimate_of(r, C, seed=9)
    ref, est = tmp_path / "ref.kitti", tmp_path / "est.kitti"
    for path, (rr, CC) in ((ref, (r, C)), (est, (r_est, C_est))):
        M = np.concatenate([CC, rr[:, :, None]], axis=2).reshape(-1, 12)
        path.write_text("\n".join(" ".join(repr(float(x)) for x in row) for row in M) + "\n")
    ours = _ours(capsys, ref, est, "--delta", "5")
    traj_ref = file_interface.read_kitti_poses_file(str(ref))
    traj_est = file_interface.read_kitti_poses_file(str(est))
    traj_est.align(traj_ref)
    assert ours["formats"] == {"reference": "kitti", "estimate": "kitti"} and ours["pairs"] == 120
    assert _assert_equal(ours, _evo(traj_ref, traj_est, delta=5)) == 28
    tum = tmp_path / "est.txt"
    write_tum(tum, np.arange(120.0), r_est, C_est)
    for argv, fragment in (([str(ref), str(tum)], "--reference is a KITTI pose file, without time stamps"),
                           ([str(ref), str(tmp_path / "short.kitti")], "the reference has 120 poses, the estimate 60")):
        if "short" in argv[1]:
            (tmp_path / "short.kitti").write_text("\n".join(est.read_text().splitlines()[:60]) + "\n")
        assert main(["evaluate", "--reference", argv[0], "--estimate", argv[1]]) == 2
        err = capsys.readouterr().err
        assert err.startswith("smoother: error: ") and fragment in err and err.count("\n") == 1, err


def test_a_time_offset_equals_evo_t_offset(tmp_path, capsys):
    """Estimate stamps 100 s late: nothing associates without --t-offset, and the error names both
    time ranges; with --t-offset -100 every figure equals evo's with --t_offset -100."""
    t, r, C = _walk(160, seed=10)
    r_est, C_est = _estimate_of(r, C, seed=11)
    ref, est = tmp_path / "ref.txt", tmp_path / "est.txt"
    write_tum(ref, t, r, C)
    write_tum(est, t[::2] + 100.003, r_est[::2], C_est[::2])
    assert main(["evaluate", "--reference", str(ref), "--estimate", str(est)]) == 2
    err = capsys.readouterr().err
    spans = f"the reference spans [{float(t[0])!r}, {float(t[-1])!r}] s, the estimate [{float(t[0]) + 100.003!r}, "
    assert spans in err
    assert "--t-offset" in err
    ours = _ours(capsys, ref, est, "--t-offset", "-100")
    traj_ref, traj_est = _evo_tum(ref, est, offset=-100.0)
    traj_est.align(traj_ref)
    assert ours["pairs"] == traj_ref.num_poses == 80
    assert _assert_equal(ours, _evo(traj_ref, traj_est)) == 28


def test_nanoseconds_against_seconds_are_named(tmp_path, capsys):
    t, r, C = _walk(50, seed=12)
    ref, est = tmp_path / "ref.txt", tmp_path / "est.txt"
    write_tum(ref, t * 1e9, r, C)
    write_tum(est, t, r, C)
    assert main(["evaluate", "--reference", str(ref), "--estimate", str(est)]) == 2
    err = capsys.readouterr().err
    assert "the reference spans [1000000000000.0, " in err and "the estimate [1000.0, " in err
    assert "one is probably in nanoseconds, the other in seconds" in err


def test_a_reference_with_attitudes_only_gives_the_rotation_figures(tmp_path, capsys):
    """An IMU's own attitude output ('t qx qy qz qw'): no refusal, no alignment, rotation ATE and
    RPE equal to evo's on the same attitudes (unaligned; positions do not enter them), no
    translation figures."""
    t, r, C = _walk(140, seed=13)
    _, C_est = _estimate_of(r, C, seed=14)
    C_est = so3.exp([0.0, 0.0, 0.3]) @ C  # an attitude estimate 0.3 rad off in yaw
    C_est = so3.exp(np.random.default_rng(15).normal(scale=0.01, size=(140, 3))) @ C_est
    ref, est = tmp_path / "attitudes.txt", tmp_path / "est.txt"
    q = quaternion.to_xyzw(quaternion.from_matrix(C))
    ref.write_text("# t qx qy qz qw\n" + "".join(" ".join(repr(float(x)) for x in (t[k], *q[k])) + "\n"
                                                for k in range(140)))
    write_tum(est, t, r, C_est)
    ours = _ours(capsys, ref, est)
    assert ours["rotation_only"] is True and ours["align"] == "none" and ours["formats"]["reference"] == "attitudes"
    assert ours["ate"]["translation_m"]["rmse"] is None and ours["ate"]["translation_m"]["count"] == 0
    zero_positions = tmp_path / "ref.txt"
    write_tum(zero_positions, t, np.zeros((140, 3)), C)
    traj_ref, traj_est = _evo_tum(zero_positions, est)
    assert _assert_equal(ours, _evo(traj_ref, traj_est), keys=("rotation_deg",)) == 14
    assert 16.0 < ours["ate"]["rotation_deg"]["rmse"] < 18.0  # 0.3 rad
    assert main(["evaluate", "--reference", str(ref), "--estimate", str(est)]) == 0
    text = capsys.readouterr().out
    assert "alignment: none (the reference has attitudes only: rotation figures only)" in text
    assert "ATE rotation [deg]" in text and "ATE translation" not in text
