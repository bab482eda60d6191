"""Hostile command lines: every numeric option has its range in one table
(``smoother.commands.OPTION_RANGES``) and every command checks it where it reads the option, with
the option named -- each tried just beyond each bound, and each bound itself accepted by the
table --; ``--keyframe-rate`` is capped by the IMU's own rate (1 kHz on a 200 Hz IMU made 9 601
keyframes, 1e9 asked for 74.5 GiB); messages point the right way: a rig run without held-out
fixes is told to set ``every``, not ``--gps-every`` which ``--rig`` refuses; an IMU in deg/s beside
a wheel is named as the IMU, not as the wheel's "gyro"."""
from __future__ import annotations

import argparse
import math
import sys

import numpy as np
import pytest
from rigfiles import imu_table

from datasets.simulate import simulate
from datasets.simulated_sensors import SensorSpec
from smoother.cli import build_parser, main
from smoother.commands import OPTION_RANGES, check_option
from smoother.errors import UserError

if sys.version_info >= (3, 11):
    import tomllib
else:
    import tomli as tomllib

#: Where each option of the table is read, with what else the command needs to get that far.
WHERE = {
    "--seed": [["run"], ["check-jacobians"]],
    "--first-seed": [["montecarlo"], ["crosscheck"]],
    "--duration": [["run"], ["montecarlo"], ["crosscheck"]],
    "--outliers": [["run"], ["montecarlo"]],
    "--gps-every": [["run"]], "--max-iterations": [["run"]], "--max-delay": [["run"]], "--speed": [["run"]],
    "--keyframe-rate": [["run"]], "--ekf-gate": [["run"]], "--max-gyro-rate": [["run"]], "--start": [["run"]],
    "--end": [["run"]],
    "--runs": [["montecarlo"]], "--seeds": [["crosscheck"]], "--workers": [["montecarlo"], ["fleet", "x.toml"]],
    "--samples": [["check-jacobians"]],
    "--max-dt": [["evaluate", "--reference", "r", "--estimate", "e"]],
    "--t-offset": [["evaluate", "--reference", "r", "--estimate", "e"]],
    "--n-to-align": [["evaluate", "--reference", "r", "--estimate", "e"]],
    "--delta": [["evaluate", "--reference", "r", "--estimate", "e", "--delta-unit", "m"]],
}
#: The options that take several numbers: the others' values when one is tried.
SEVERAL = {"--pose-from-truth": ("HZ", "POS_M", "ROT_RAD"), "--gps-from-truth": ("HZ", "POS_M")}


def _is_int(command: str, option: str) -> bool:
    """Whether the command line reads ``option`` of ``command`` as an integer."""
    sub = next(a for a in build_parser()._actions if isinstance(a, argparse._SubParsersAction)).choices[command]
    return next(a for a in sub._actions if option in a.option_strings).type is int


def _beyond(value, integer: bool, up: bool):
    if integer:
        return int(value) + (1 if up else -1)
    return float(np.nextafter(value, math.inf if up else -math.inf))


def _middle(option: str) -> float:
    r = OPTION_RANGES[option]
    return r.low if r.low > 0 else r.high / 2  # a value inside, for the other numbers of an option


def test_every_option_of_the_table_is_read_somewhere_and_every_numeric_option_is_in_the_table():
    numeric = set()
    for sub in next(a for a in build_parser()._actions if isinstance(a, argparse._SubParsersAction)).choices.values():
        for action in sub._actions:
            if action.type in (int, float) and action.option_strings:
                numeric.add(action.option_strings[0])
    tabled = {option.split()[0] for option in OPTION_RANGES}
    assert numeric - {"--lag"} == tabled  # --lag: the lag module's one check (smoother.fixed_lag.lag)
    assert set(WHERE) | set(SEVERAL) == tabled


@pytest.mark.parametrize("option", sorted(OPTION_RANGES))
def test_each_bound_is_accepted_and_just_beyond_it_is_refused_naming_the_option(option):
    r = OPTION_RANGES[option]
    for bound in (r.low, r.high):
        check_option(option, bound)
    for value in (_beyond(r.low, isinstance(r.low, int), up=False), _beyond(r.high, isinstance(r.high, int), up=True),
                  math.inf, math.nan):
        with pytest.raises(UserError, match=f"^{option}: expected a value within"):
            check_option(option, value)


@pytest.mark.parametrize("option, argv", [(o, a) for o, places in WHERE.items() for a in places])
def test_each_command_checks_its_options_where_it_reads_them(capsys, tmp_path, option, argv):
    r = OPTION_RANGES[option]
    integer = _is_int(argv[0], option)
    for value in (_beyond(r.low, integer, up=False), _beyond(r.high, integer, up=True)):
        given = f"{option}={value!r}"  # one word: argparse takes -5e-324 for an option otherwise
        assert main([*argv, given, "--out", str(tmp_path / "out")] if argv[0] in ("run", "montecarlo", "fleet")
                    else [*argv, given]) == 2
        err = capsys.readouterr().err.strip().splitlines()
        assert len(err) == 1 and err[0].startswith(f"smoother: error: {option}: expected a value within"), err


@pytest.mark.parametrize("option", sorted(SEVERAL))
def test_each_number_of_a_truth_sensor_option_is_checked_by_its_own_range(capsys, tmp_path, option):
    names = SEVERAL[option]
    for i, name in enumerate(names):
        values = [_middle(f"{option} {n}") for n in names]
        values[i] = _beyond(OPTION_RANGES[f"{option} {name}"].high, False, up=True)
        assert main(["run", option, *map(repr, values), "--out", str(tmp_path / "out")]) == 2
        assert f"{option} {name}: expected a value within" in capsys.readouterr().err


def test_hostile_values_of_the_issue_are_refused_up_front(capsys, tmp_path):
    for argv, said in ((["--ekf-gate", "1e-300"], "--ekf-gate: expected a value within [0.5, 1]"),
                       (["--keyframe-rate", "1e9"], "--keyframe-rate: expected a value within"),
                       (["--speed", "1e-300", "--realtime"], "--speed: expected a value within"),
                       (["--robust", "huber:1e300"], "--robust huber:1e300: robust kernel threshold '1e300': expected "
                                                     "a value within [0.1, 100] sigma")):
        assert main(["run", "--duration", "2", "--estimator", "ekf", "--out", str(tmp_path / "o"), *argv]) == 2
        assert said in capsys.readouterr().err


@pytest.mark.parametrize("rate, refused", [(1000.0, True), (200.001, True), (200.0, False), (50.0, False)])
def test_the_keyframe_rate_is_capped_by_the_imu_s_rate(capsys, tmp_path, rate, refused):
    """1 kHz on the simulator's 200 Hz IMU is refused naming the option and the IMU's rate; at the
    IMU's rate and below it runs."""
    code = main(["run", "--duration", "2", "--estimator", "ekf", "--keyframe-rate", repr(rate), "--no-progress",
                 "--out", str(tmp_path / "o")])
    err = capsys.readouterr().err
    assert (code == 2) == refused, err
    assert ("--keyframe-rate: expected at most the IMU's rate, 200 Hz" in err) == refused, err


def _csv_rig(folder, gyro_scale: float = 1.0, every: int = 1):
    """A rig of CSV files: an IMU (its gyro times ``gyro_scale``), a wheel (velocity) and a
    position sensor used every ``every``-th fix, 20 s of the gentle profile."""
    data = simulate("gentle", duration=20.0, seed=1, pose_rate=0, sensors=[
        SensorSpec("wheel", "velocity", 10, 0.05), SensorSpec("fix", "position", 2, 0.3)])
    folder.mkdir(parents=True, exist_ok=True)
    rows = [f"{int(round(t * 1e9)) + 10**18},{','.join(repr(float(x)) for x in (*w * gyro_scale, *a))}"
            for t, a, w in zip(data.imu.t, data.imu.acc, data.imu.gyro)]
    (folder / "imu.csv").write_text("#timestamp [ns],w_RS_S_x,w_RS_S_y,w_RS_S_z,a_RS_S_x,a_RS_S_y,a_RS_S_z\n"
                                    + "\n".join(rows) + "\n")
    for name, header, field in (("wheel", "t,vx,vy,vz", "velocity"), ("fix", "t,x,y,z", "position")):
        m = data.sensor(name).data
        lines = [f"{float(t) + 1e9!r},{','.join(repr(float(x)) for x in v)}" for t, v in zip(m.t, getattr(m, field))]
        (folder / f"{name}.csv").write_text(header + "\n" + "\n".join(lines) + "\n")
    rig = folder / "rig.toml"
    rig.write_text(imu_table("csv:imu.csv", data.noise)
                   + '\n[[sensor]]\nname = "wheel"\nkind = "velocity"\nsource = "csv:wheel.csv"\nsigma = 0.05\n'
                   + f'\n[[sensor]]\nname = "fix"\nkind = "position"\nsource = "csv:fix.csv"\nsigma = 0.3\n'
                   f'every = {every}\n')
    return rig


def test_a_rig_run_without_held_out_fixes_is_told_to_set_every_not_gps_every(capsys, tmp_path):
    rig = _csv_rig(tmp_path / "rig")
    assert main(["run", "--rig", str(rig), "--estimator", "ekf", "--no-progress", "--out", str(tmp_path / "o")]) == 0
    printed = capsys.readouterr().out
    assert "no held-out fixes: no ranking (hold fixes out with a sensor's every = K > 1 in the rig file)" in printed
    assert "--gps-every" not in printed


def test_an_imu_in_degrees_beside_a_wheel_is_named_as_the_imu(capsys, tmp_path):
    """The wheel's rows carry the IMU's gyro for its lever arm; the error names the IMU's source
    and its units, not the wheel."""
    rig = _csv_rig(tmp_path / "rig", gyro_scale=np.degrees(1.0) * 3)
    assert main(["run", "--rig", str(rig), "--estimator", "ekf", "--no-progress", "--out", str(tmp_path / "o")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "imu (csv:" in err[0] and "deg/s" in err[0] and "wheel" not in err[0], err


@pytest.mark.parametrize("argv", [["montecarlo", "--runs", "2000"], ["fleet", "x.toml"]])
def test_workers_beyond_twice_the_machines_cores_are_refused_before_any_starts(capsys, tmp_path, monkeypatch, argv):
    """--workers 1024 (the range's bound) forked a process of some 300 MB for each of 1024 tasks
    on a 2-core machine; a Dask cluster takes any number in the range."""
    import smoother.commands as commands

    monkeypatch.setattr(commands, "usable_cores", lambda: 2)
    commands.check_workers(4)
    commands.check_workers(1024, "tcp://scheduler:8786")
    assert main([*argv, "--workers", "5", "--out", str(tmp_path / "out")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert err == ["smoother: error: --workers: expected at most 4 on this machine (twice its 2 cores: each worker is "
                   "a process of its own memory, some 300 MB, and more only wait for the cores), got 5; a Dask "
                   "cluster (--dask) takes more"], err
    assert not (tmp_path / "out").exists()


def test_two_kernels_for_one_sensor_are_refused_and_a_sensors_own_holds_in_any_order(capsys, tmp_path):
    """``--robust gnss=huber --robust gnss=cauchy`` ran with cauchy, saying nothing of huber, and
    ``--robust gnss=cauchy --robust huber`` gave gnss huber: the order decided, silently."""
    from smoother.commands.run import parse_robust

    types = ("gnss", "wheel")
    for specs in (["gnss=cauchy", "huber"], ["huber", "gnss=cauchy"]):
        assert parse_robust(specs, types) == {"gnss": ("cauchy", None), "wheel": ("huber", None)}
    for specs, said in ((["pose=huber", "pose=cauchy"], "sensor 'pose' has a kernel already (--robust pose=huber)"),
                        (["huber", "tukey:3"], "every sensor has a kernel already (--robust huber)")):
        assert main(["run", "--duration", "2", "--estimator", "ekf", "--out", str(tmp_path / "o"),
                     *[a for s in specs for a in ("--robust", s)]]) == 2
        err = capsys.readouterr().err.strip().splitlines()
        assert len(err) == 1 and err[0].startswith(f"smoother: error: --robust {specs[1]}: {said}"), err


def _allan_csv(path, x, stamps_ns):
    path.write_text("#timestamp [ns],w_RS_S_x,w_RS_S_y,w_RS_S_z,a_RS_S_x,a_RS_S_y,a_RS_S_z\n" + "".join(
        f"{s},{','.join(repr(float(v)) for v in (*row[3:], *row[:3]))}\n" for s, row in zip(stamps_ns, x)))
    return path


@pytest.mark.parametrize("case", ["one value", "uneven stamps", "beyond the range"])
def test_allan_prints_no_density_a_rig_would_refuse_or_the_data_cannot_give(capsys, tmp_path, case):
    """A recording whose axes read one value throughout printed densities of 0 and 2e-13 to paste
    (and "divide by zero" warnings); stamps 0.1-0.9 s apart were taken as evenly spaced at their
    median and gave densities as sure as any; a density beyond the rig's range was printed as
    a value to paste, which the rig then refuses."""
    rng = np.random.default_rng(0)
    n, stamps = 20_000, 10**18 + 10_000_000 * np.arange(20_000)
    x = np.column_stack([rng.normal(size=(n, 3)) * 0.02, rng.normal(size=(n, 3)) * 2e-3])
    x[:, 2] += 9.81
    if case == "one value":
        x[:] = (0.0, 0.0, 9.81, 0.0, 0.0, 0.0)
    elif case == "uneven stamps":
        stamps = 10**18 + np.cumsum(rng.integers(10**8, 9 * 10**8, size=n))
    else:
        x[:, :3] *= 1000.0  # an accelerometer noise of 2 m/s^2/sqrt(Hz): in mm/s^2, say
    path = _allan_csv(tmp_path / "imu.csv", x, stamps)
    code = main(["allan", f"csv:{path}", "--out", str(tmp_path / "out")])
    out, err = capsys.readouterr()
    if case == "uneven stamps":
        assert code == 2 and err.startswith(f"smoother: error: csv:{path}: Allan deviation: expected evenly spaced "
                                            "samples; the steps between samples range from "), err
        return
    assert code == 0 and "divide by zero" not in err, err
    block = tomllib.loads(out)["imu"]
    assert "accel_noise_density" not in block, out
    if case == "one value":
        assert "# accel_noise_density = ?    # not estimated: an axis reads one value throughout" in out
        assert "gyro z read the same value in every sample: a stuck axis" in err
    else:
        assert "# accel_noise_density = 2.0" in out and "# not usable: expected a value within [1e-06, 1]" in out, out
        assert block["gyro_noise_density"] > 0


def test_a_lag_no_longer_than_the_keyframe_interval_is_refused_before_any_estimator_runs(capsys, tmp_path):
    """``--keyframe-rate 0.001 --lag 0.5`` ran the EKF and the batch smoother, then failed the
    fixed-lag smoother with an error naming ``lag_s``, the library's argument."""
    out = tmp_path / "o"
    assert main(["run", "--duration", "2", "--keyframe-rate", "0.001", "--lag", "0.5", "--out", str(out)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("smoother: error: --lag: 0.5 s is no longer than the keyframe "
                                               "interval (1 / 0.001 Hz)"), err
    assert not (out / "ekf.tum").exists()
    assert main(["run", "--duration", "2", "--keyframe-rate", "0.001", "--lag", "0.5", "--estimator", "ekf",
                 "--no-progress", "--out", str(out)]) == 0  # the lag is the fixed-lag smoother's alone


def test_an_error_quoting_a_huge_value_is_one_line_of_bounded_length(capsys, tmp_path):
    """A rig's topic of 300 000 characters was quoted whole in a 300 kB error line."""
    rig = tmp_path / "rig.toml"
    rig.write_text('[imu]\nsource = "bag:run.bag"\ntopic = "' + "t" * 300_000 + '"\naccel_noise_density = 2e-3\n'
                   'gyro_noise_density = 2e-4\naccel_random_walk = 3e-4\ngyro_random_walk = 2e-5\n')
    assert main(["run", "--rig", str(rig), "--out", str(tmp_path / "o")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and str(tmp_path / "run.bag") in err[0] and len(err[0]) < 1100, len(err[0])
    assert err[0].endswith(" more characters)"), err[0][-80:]


@pytest.mark.parametrize("spec, said", [
    ("pose", "--correlation-time pose: expected SENSOR=SECONDS"),
    ("gnss=5", "--correlation-time gnss=5: unknown sensor 'gnss'; expected one of pose"),
    ("pose=soon", "--correlation-time pose=soon: expected a number of seconds or 'fit', got 'soon'"),
    ("pose=fit", "--correlation-time pose=fit: fitting it needs measurements of 'pose' used and held out (a rig's "
                 "every = K > 1, --gps-every K > 1)"),
    ("pose=0", "--correlation-time pose=0: expected a value within [0.01, 86400] s"),
    ("pose=nan", "--correlation-time pose=nan: expected a value within [0.01, 86400] s"),
])
def test_a_bad_correlation_time_is_one_line_naming_the_option(capsys, tmp_path, spec, said):
    assert main(["run", "--duration", "2", "--estimator", "ekf", "--out", str(tmp_path / "o"),
                 "--correlation-time", spec]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith(f"smoother: error: {said}"), err


def test_a_correlation_time_given_twice_or_on_a_relative_sensor_is_refused():
    from smoother.commands.run import with_correlation_times

    data = simulate(profile="gentle", duration=3.0, seed=0)
    assert with_correlation_times(["pose=4"], data).sensor("pose").correlation_time == 4.0
    with pytest.raises(UserError, match=r"--correlation-time pose=5: sensor 'pose' has one already "
                                        r"\(--correlation-time pose=4\)"):
        with_correlation_times(["pose=4", "pose=5"], data)
    odometry = data.with_sensor("pose", kind="odometry")
    with pytest.raises(UserError, match="odometry measurements are relative"):
        with_correlation_times(["pose=4"], odometry)
    with pytest.raises(UserError, match="odometry measurements are relative"):
        with_correlation_times(["pose=fit"], odometry)
    pose = data.sensor("pose").data
    held = data.with_sensor("pose", data=pose.subset(slice(0, None, 2)), heldout=pose.subset(slice(1, None, 2)),
                            correlation_time=4.0)
    fitted = with_correlation_times(["pose=fit"], held).sensor("pose")
    assert fitted.fit_correlation_time and fitted.correlation_time is None
    given = with_correlation_times(["pose=3"], held.with_sensor("pose", correlation_time=None,
                                                               fit_correlation_time=True)).sensor("pose")
    assert given.correlation_time == 3.0 and not given.fit_correlation_time  # the option overrides the rig's "fit"
