"""``smoother allan SOURCE``: the printed block is TOML (tomllib reads it) and a valid [imu] table
of a rig file holding the densities, allan.png is written, and a bad source is one error line."""
from __future__ import annotations

import sys

import numpy as np
from bagfiles import Messages, write_bag

from datasets.allan import allan
from datasets.rig import load_rig
from datasets.sources import read_imu
from smoother.cli import main

if sys.version_info >= (3, 11):
    import tomllib
else:
    import tomli as tomllib

DT_NS = 10_000_000


def _static_imu(n=30_000, seed=3):
    rng = np.random.default_rng(seed)
    white, walk = np.array([2e-3] * 3 + [2e-4] * 3), np.array([2e-2] * 3 + [2e-3] * 3)
    x = white / np.sqrt(0.01) * rng.normal(size=(n, 6)) + np.cumsum(walk * 0.1 * rng.normal(size=(n, 6)), axis=0)
    x[:, 2] += 9.81
    return x


def _write_csv(path, x):
    """Samples ``x`` (acc, gyro per row) as an EuRoC/ASL IMU CSV, 100 Hz."""
    stamps = 1_600_000_000_000_000_000 + DT_NS * np.arange(len(x))
    path.write_text("#timestamp [ns],w_RS_S_x,w_RS_S_y,w_RS_S_z,a_RS_S_x,a_RS_S_y,a_RS_S_z\n" + "".join(
        f"{s},{','.join(repr(float(v)) for v in (*row[3:], *row[:3]))}\n" for s, row in zip(stamps, x)))


def test_block_pastes_into_a_rig_and_the_figure_is_written(tmp_path, capsys):
    x = _static_imu()
    path = tmp_path / "imu.csv"
    _write_csv(path, x)
    assert main(["allan", f"csv:{path}", "--out", str(tmp_path / "out")]) == 0
    out = capsys.readouterr()
    assert tomllib.loads(out.out)["imu"]["source"] == f"csv:{path}"
    (tmp_path / "rig.toml").write_text(out.out)
    rig = load_rig(tmp_path / "rig.toml")
    expected = allan(read_imu(f"csv:{path}")).noise()
    assert rig.imu.source == f"csv:{path}" and rig.imu.topic is None
    for name in ("acc", "gyro", "acc_bias", "gyro_bias"):  # printed with 5 significant digits
        assert abs(getattr(rig.imu.noise, name) / getattr(expected, name) - 1) < 1e-4
    assert (tmp_path / "out" / "allan.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    assert "allan.png" in out.err and "does not look static" not in out.err


def test_bag_source_and_errors(tmp_path, capsys):
    x = _static_imu(n=2000)
    m = Messages("ros1")
    write_bag(tmp_path / "run.bag", "ros1", {"/imu": ("sensor_msgs/msg/Imu", [
        m.imu(10**18 + k * DT_NS, row[:3], row[3:]) for k, row in enumerate(x)])})
    assert main(["allan", f"bag:{tmp_path / 'run.bag'}", "--topic", "/imu", "--out", str(tmp_path)]) == 0
    assert 'topic = "/imu"' in capsys.readouterr().out
    assert main(["allan", f"bag:{tmp_path / 'run.bag'}", "--out", str(tmp_path)]) == 2
    assert "a bag needs a topic" in capsys.readouterr().err
    assert main(["allan", "tum:traj.txt", "--out", str(tmp_path)]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "a tum: source has no IMU samples" in err


def test_a_recording_that_moves_is_warned_of(tmp_path, capsys):
    """The Allan deviation of a moving IMU describes its motion: a warning says so (the static
    recording above gets none)."""
    x = _static_imu(n=3000)
    t = np.arange(len(x)) * 0.01
    x[:, 5] += 0.5 * (t > 10)  # a turn at 0.5 rad/s after 10 s
    path = tmp_path / "imu.csv"
    _write_csv(path, x)
    assert main(["allan", f"csv:{path}", "--out", str(tmp_path / "out")]) == 0
    assert "does not look static (a 1-s mean angular rate of 0.5" in capsys.readouterr().err


def test_a_recording_too_short_for_the_random_walk_says_so(tmp_path, capsys):
    """Two seconds at rest: the block gives the white-noise densities and leaves the random walks
    out (commented, to be filled in); a warning says how long a recording they need."""
    x = 2e-2 * np.random.default_rng(5).normal(size=(200, 6))  # white noise only
    x[:, 2] += 9.81
    path = tmp_path / "imu.csv"
    _write_csv(path, x)
    assert main(["allan", f"csv:{path}", "--out", str(tmp_path / "out")]) == 0
    out = capsys.readouterr()
    block = out.out.splitlines()
    assert any(line.startswith("accel_noise_density = ") for line in block)
    assert set(tomllib.loads(out.out)["imu"]) == {"source", "accel_noise_density", "gyro_noise_density"}
    for key in ("accel_random_walk", "gyro_random_walk"):
        assert not any(line.startswith(key) for line in block) and f"# {key} = ?" in out.out
    assert "warning: random walk not estimated" in out.err and "record at least" in out.err
    assert (tmp_path / "out" / "allan.png").exists()
