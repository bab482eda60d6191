"""``smoother evaluate``: output, JSON, and one-line errors naming file and line."""
from __future__ import annotations

import json

import numpy as np
import pytest

from datasets.tum import read_tum, write_tum
from factors import so3
from smoother.cli import build_parser, main
from smoother.evaluation import metrics


@pytest.fixture
def files(tmp_path):
    rng = np.random.default_rng(0)
    n = 120
    t = 50.0 + 0.1 * np.arange(n)
    r = np.cumsum(rng.normal(scale=0.5, size=(n, 3)), axis=0)
    C = so3.exp(np.cumsum(rng.normal(scale=0.05, size=(n, 3)), axis=0))
    R, offset = so3.exp([0.1, -0.2, 0.9]), np.array([5.0, -2.0, 1.0])
    r_est = (r + rng.normal(scale=0.02, size=r.shape)) @ R.T + offset
    C_est = R @ so3.exp(rng.normal(scale=0.01, size=r.shape)) @ C
    ref, est = tmp_path / "ref.txt", tmp_path / "est.txt"
    write_tum(ref, t, r, C)
    write_tum(est, t + 0.002, r_est, C_est)
    return ref, est


def test_registered():
    parser = build_parser()
    args = parser.parse_args(["evaluate", "--reference", "a", "--estimate", "b"])
    assert args.align == "se3" and args.max_dt == 0.01 and not args.json


@pytest.mark.parametrize("align", ["se3", "posyaw", "none"])
def test_json_equals_the_library(files, capsys, align):
    ref, est = files
    assert main(["evaluate", "--reference", str(ref), "--estimate", str(est), "--align", align, "--json"]) == 0
    out = json.loads(capsys.readouterr().out)
    a, b = read_tum(ref), read_tum(est)
    expected = metrics.evaluate(a.t, a.position, a.C, b.t, b.position, b.C, align=align)
    assert out["pairs"] == 120 and out["align"] == align
    for key in ("rmse", "mean", "median", "std", "min", "max", "sse", "count"):
        assert out["ate"]["translation_m"][key] == expected.ate["translation"][key]
        assert out["ate"]["rotation_deg"][key] == expected.ate["rotation"][key]
        assert out["rpe"]["translation_m"][key] == expected.rpe["translation"][key]
    if align == "se3":
        assert out["ate"]["translation_m"]["rmse"] < 0.05  # the offset is removed
    if align == "none":
        assert out["ate"]["translation_m"]["rmse"] > 1.0


def test_table_and_rpe_options(files, capsys):
    ref, est = files
    assert main(["evaluate", "--reference", str(ref), "--estimate", str(est), "--delta", "10"]) == 0
    text = capsys.readouterr().out
    for label in ("ATE translation [m]", "ATE rotation [deg]", "RPE translation [m]", "RPE rotation [deg]"):
        assert label in text
    assert "associated poses: 120" in text and "10 frames" in text
    assert main(["evaluate", "--reference", str(ref), "--estimate", str(est), "--delta", "2.5",
                 "--delta-unit", "m", "--json"]) == 0
    out = json.loads(capsys.readouterr().out)
    assert out["rpe_delta"] == {"value": 2.5, "unit": "m"} and out["rpe"]["translation_m"]["count"] > 0


def _error(capsys, argv):
    assert main(argv) == 2
    captured = capsys.readouterr()
    err = captured.err.strip()
    assert err.startswith("smoother: error: ") and "\n" not in err and "Traceback" not in err
    return err


def test_bad_files_give_one_line_naming_file_and_line(files, capsys, tmp_path):
    ref, est = files
    lines = est.read_text().splitlines()
    lines[5] = lines[5].replace(lines[5].split()[2], "nan", 1)
    bad = tmp_path / "bad.txt"
    bad.write_text("\n".join(lines) + "\n")
    err = _error(capsys, ["evaluate", "--reference", str(ref), "--estimate", str(bad)])
    assert str(bad) in err and "line 6" in err and "'ty'" in err and "--estimate" in err
    err = _error(capsys, ["evaluate", "--reference", str(tmp_path / "missing.txt"), "--estimate", str(est)])
    assert "missing.txt" in err and "--reference" in err
    empty = tmp_path / "empty.txt"
    empty.write_text("")
    err = _error(capsys, ["evaluate", "--reference", str(empty), "--estimate", str(est)])
    assert str(empty) in err and "line 1" in err


def test_no_association_and_degenerate_alignment(files, capsys, tmp_path):
    ref, est = files
    far = tmp_path / "far.txt"
    write_tum(far, [1.0, 2.0, 3.0], np.zeros((3, 3)), np.tile(np.eye(3), (3, 1, 1)))
    err = _error(capsys, ["evaluate", "--reference", str(ref), "--estimate", str(far)])
    assert "max_dt" in err
    line = tmp_path / "line.txt"
    t = read_tum(ref).t[:3]
    write_tum(line, t, np.outer([0.0, 1.0, 2.0], [1.0, 0.0, 0.0]), np.tile(np.eye(3), (3, 1, 1)))
    # three points on a line fix no rotation about it: posyaw instead, said in a warning and the JSON
    with pytest.warns(UserWarning, match=r"se3 alignment is degenerate: the rotation about the line the positions lie "
                                         r"along is not determined by 3 positions spread 0 m about it.*; posyaw "
                                         r"applied instead$"):
        assert main(["evaluate", "--reference", str(ref), "--estimate", str(line), "--json"]) == 0
    out = json.loads(capsys.readouterr().out)
    assert out["align"] == out["alignment"]["mode"] == "posyaw" and out["alignment"]["requested"] == "se3"
    assert out["alignment"]["conditioning"]["determined"] is False
    assert max(out["alignment"]["conditioning"]["singular_values_m2"][1:]) < 1e-12
    assert main(["evaluate", "--reference", str(ref), "--estimate", str(line), "--align", "posyaw"]) == 0


def test_a_straight_drive_is_aligned_about_gravity_with_a_warning(tmp_path, capsys):
    """--align se3 on a nearly straight drive: a warning with the conditioning, the table names the
    alignment applied, the JSON carries it, and the rotation ATE is the true 7 deg (Umeyama's
    roll about the road made it 75.7 deg)."""
    from straight_drive import straight_drive

    (t, r, C), (r_est, C_est) = straight_drive()
    ref, est = tmp_path / "ref.tum", tmp_path / "est.tum"
    write_tum(ref, t, r, C)
    write_tum(est, t, r_est, C_est)
    argv = ["evaluate", "--reference", str(ref), "--estimate", str(est), "--align", "se3"]
    degenerate = (r"^se3 alignment is degenerate: the rotation about the line the positions lie along is not "
                  r"determined by 301 positions spread 0\.0\d+ m about it, under 5% of their 86\.\d m extent "
                  r"\(singular values .* m\^2\); posyaw applied instead$")
    with pytest.warns(UserWarning, match=degenerate):
        assert main(argv) == 0
    table = capsys.readouterr().out
    assert "alignment: posyaw instead of se3, whose rotation is not determined" in table
    rotation = next(line for line in table.splitlines() if line.startswith("ATE rotation [deg]"))
    assert float(rotation.split()[3]) == pytest.approx(7.0, abs=0.05)
    with pytest.warns(UserWarning, match="degenerate"):
        assert main(argv + ["--json"]) == 0
    out = json.loads(capsys.readouterr().out)
    assert out["align"] == "posyaw" and out["alignment"]["requested"] == "se3"
    assert out["alignment"]["note"].endswith("posyaw applied instead")
    assert out["alignment"]["conditioning"]["determined"] is False
    assert out["ate"]["rotation_deg"]["rmse"] == pytest.approx(7.0, abs=0.05)


@pytest.mark.parametrize("option", [["--max-dt", "-1"], ["--delta", "0"], ["--delta", "1.5"], ["--max-dt", "nan"]])
def test_bad_options(files, capsys, option):
    ref, est = files
    err = _error(capsys, ["evaluate", "--reference", str(ref), "--estimate", str(est)] + option)
    assert option[0] in err


def test_running_out_of_memory_is_one_line(files, capsys, monkeypatch):
    """A MemoryError is one line with exit 2 (no --duration hint: evaluate has no such option)."""
    from smoother.commands import evaluate

    def too_big(path, *args, **kwargs):
        raise MemoryError("Unable to allocate 8.0 GiB for an array with shape (1073741824,) and data type float64")

    monkeypatch.setattr(evaluate, "_read", too_big)
    ref, est = files
    assert main(["evaluate", "--reference", str(ref), "--estimate", str(est)]) == 2
    err = capsys.readouterr().err
    assert err == "smoother: error: out of memory (Unable to allocate 8.0 GiB for an array with shape (1073741824,) " \
                  "and data type float64)\n"


def test_npz_estimates_with_covariances_give_the_nees_of_the_run(tmp_path, capsys):
    """A run directory's .npz against its truth.npz, unaligned: the NEES equals metrics.json's."""
    from smoother.cli import main as cli_main

    out = tmp_path / "run"
    assert cli_main(["run", "--duration", "3", "--estimator", "ekf", "--out", str(out), "--no-progress"]) == 0
    capsys.readouterr()
    expected = json.loads((out / "metrics.json").read_text())["ekf"]["nees_mean"]
    assert cli_main(["evaluate", "--reference", str(out / "truth.npz"), "--estimate", str(out / "ekf.npz"),
                     "--align", "none", "--json"]) == 0
    assert json.loads(capsys.readouterr().out)["nees_mean"] == pytest.approx(expected, rel=1e-12)
    assert cli_main(["evaluate", "--reference", str(out / "truth.npz"), "--estimate", str(out / "ekf.npz"),
                     "--json"]) == 0
    assert json.loads(capsys.readouterr().out)["nees_mean"] is None


def test_a_bad_npz_is_one_line_naming_the_file(files, capsys, tmp_path):
    """Not an archive (NumPy read it as a pickle and asked for allow_pickle), an archive without
    the arrays, and one whose covariances are not covariances: one line naming the file."""
    import numpy as np

    ref, _ = files
    text = tmp_path / "text.npz"
    text.write_text("not an archive\n")
    err = _error(capsys, ["evaluate", "--reference", str(ref), "--estimate", str(text)])
    assert str(text) in err and "not an .npz archive" in err
    empty = tmp_path / "other.npz"
    np.savez(empty, x=np.zeros(3))
    err = _error(capsys, ["evaluate", "--reference", str(ref), "--estimate", str(empty)])
    assert str(empty) in err and "missing array(s) t, r, v, C, b_f, b_w" in err
    n = 4
    bad_cov = tmp_path / "cov.npz"
    np.savez(bad_cov, t=np.arange(n, dtype=float), r=np.zeros((n, 3)), v=np.zeros((n, 3)),
             C=np.tile(np.eye(3), (n, 1, 1)), b_f=np.zeros((n, 3)), b_w=np.zeros((n, 3)), cov=-np.ones((n, 15, 15)))
    err = _error(capsys, ["evaluate", "--reference", str(ref), "--estimate", str(bad_cov)])
    assert str(bad_cov) in err and "Trajectory.cov" in err
