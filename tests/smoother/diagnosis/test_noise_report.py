"""The printed lines of a noise fit (smoother/diagnosis/noise_report.py), from ``metrics.json``'s
record: a header with the iterations, then one line per group saying what became of it."""
from __future__ import annotations

from smoother.batch.variance_components import GroupFit, NoiseFit, NoiseGroup
from smoother.diagnosis.noise_report import fitted_sensors, noise_lines
from smoother.diagnosis.verdicts import consistency_warnings


def _record(converged=True, fits=1) -> dict:
    groups = [
        GroupFit(NoiseGroup("imu", "gyro"), 27.3, 2.4, 76.0, 0.00478, "rad/s/sqrt(Hz)"),
        GroupFit(NoiseGroup("imu", "acc"), 3.57, 0.48, 12.4, 0.0357, "m/s^2/sqrt(Hz)", merged_with=("imu.acc_bias",)),
        GroupFit(NoiseGroup("gps", "horizontal", (0, 1)), 1.0, 0.0, 0.58, 0.265, "m", estimable=False,
                 note="not estimable: the data do not determine it (redundancy 0.58)"),
        GroupFit(NoiseGroup("gps", "vertical", (2,)), 1.01, 0.63, 10.3, 0.265, "m", applied=False,
                 note="the rig's value kept: within 3 sd of it"),
        GroupFit(NoiseGroup("wheel", "speed", (0,)), 2.0, 0.1, 40.0, None, "", applied=False),
    ]
    return NoiseFit(groups, iterations=12, converged=converged, fits=fits).record()


def test_one_line_per_group_with_its_value_factor_and_fate():
    header, gyro, acc, horizontal, vertical, wheel = noise_lines(_record())
    assert header == "noise fitted by the batch smoother (12 iterations):"
    assert gyro.split() == ["imu.gyro", "0.00478", "rad/s/sqrt(Hz)", "x27.3", "+-", "2.4", "(redundancy", "76):",
                            "applied"]
    assert acc.endswith("x3.57 +- 0.48 (redundancy 12.4), one factor with imu.acc_bias: applied")
    assert horizontal.split()[:3] == ["gps.horizontal", "0.265", "m"]
    assert horizontal.endswith("kept: not estimable: the data do not determine it (redundancy 0.58)")
    assert "x" not in horizontal.split()[3]  # a group the data do not determine has no factor
    assert vertical.endswith("x1.01 +- 0.63 (redundancy 10.3): the rig's value kept: within 3 sd of it")
    assert wheel.split()[:2] == ["wheel.speed", "x2"] and wheel.endswith(": not applied")
    assert len({line.index(line.split()[1]) for line in (gyro, acc, horizontal, vertical)}) == 1  # one column


def test_a_fit_that_did_not_converge_says_so_in_its_header():
    header = noise_lines(_record(converged=False))[0]
    assert header == "noise fitted by the batch smoother (12 iterations, NOT converged):"


def test_a_fit_made_again_with_its_model_errors_held_says_how_many_fits():
    header = noise_lines(_record(fits=3))[0]
    assert header == ("noise fitted by the batch smoother (12 iterations in 3 fits, each with the model errors found "
                      "before it held):")


def test_a_noise_the_run_s_halves_disagree_on_says_each_half_s_factor():
    groups = [GroupFit(NoiseGroup("imu", "gyro"), 0.39, 0.006, 3800.0, 0.00145, "rad/s/sqrt(Hz)",
                       halves=(0.278, 0.477), steady=False),
              GroupFit(NoiseGroup("imu", "acc"), 0.92, 0.03, 2070.0, 0.018, "m/s^2/sqrt(Hz)", halves=(0.79, 1.16))]
    _, gyro, acc = noise_lines(NoiseFit(groups, iterations=3, converged=True).record())
    assert gyro.endswith("applied; not steady: x0.278 in the run's first half, x0.477 in its second (one value over "
                         "the run is their average, and a run of other data may find it out of band)")
    assert acc.endswith(": applied")


def test_each_sensor_s_fitted_groups_are_said_in_a_phrase():
    assert fitted_sensors(_record()) == {
        "imu": "imu.gyro x27.3, imu.acc x3.57",
        "gps": "gps.horizontal not estimable, gps.vertical kept",
        "wheel": "wheel.speed kept",
    }
    assert fitted_sensors(None) == {}


def test_a_sigma_that_looks_too_large_is_advised_to_be_fitted_only_where_it_was_not():
    """A sensor far below its band whose noise the run fitted is told what the fit did, not to fit
    it; one whose noise was not fitted is told how to."""
    low = {"batch": {"gps": {"per_dof": 0.133, "band": (0.93, 1.07), "ok": False, "measurements": 300}}}
    [fitted] = consistency_warnings(low, fitted=fitted_sensors(_record()))
    assert fitted == ("gps: per dof batch 0.133 (expected 0.93-1.1): its sigma looks 2.7x too large by its errors, "
                      "though its noise was fitted (gps.horizontal not estimable, gps.vertical kept: the noise table "
                      "says why)"), fitted
    [plain] = consistency_warnings(low)
    assert plain.endswith('2.7x too large by its errors; estimate = ["noise"] on it (or smoother run --estimate-noise) '
                          "fits it to the data"), plain


def test_a_sensor_far_above_its_band_whose_noise_was_fitted_says_what_the_fit_did():
    high = {"batch": {"gps": {"per_dof": 2.21, "band": (0.89, 1.1), "ok": False, "measurements": 198}}}
    [line] = consistency_warnings(high, fitted={"gps": "gps.horizontal kept, gps.vertical x6.05"},
                                  sensor_kinds={"gps": "gnss"})
    assert line.endswith("check its sigma (too small), lever arm or time offset; its noise was fitted "
                         "(gps.horizontal kept, gps.vertical x6.05: the noise table says why)"), line
    assert consistency_warnings(high, sensor_kinds={"gps": "gnss"})[0].endswith("lever arm or time offset")


def test_a_sensor_far_above_its_band_is_pointed_at_the_calibration_parts_its_kind_has():
    """A GNSS fix has no rotation, an attitude no lever arm; a velocity sensor has a scale too."""
    high = {"batch": {s: {"per_dof": 9.0, "band": (0.9, 1.1), "ok": False, "measurements": 300}
                      for s in ("gnss", "ahrs", "wheels")}}
    lines = consistency_warnings(high, sensor_kinds={"gnss": "gnss", "ahrs": "orientation", "wheels": "velocity"})
    said = {line.split(":", 1)[0]: line.split("check its sigma (too small), ", 1)[1] for line in lines}
    assert said == {"gnss": "lever arm or time offset", "ahrs": "rotation or time offset",
                    "wheels": "lever arm, rotation, time offset or scale"}, said


def test_a_sensor_whose_residuals_point_at_a_calibration_still_says_what_the_noise_fit_did():
    low = {"batch": {"ahrs": {"per_dof": 0.009, "band": (0.98, 1.02), "ok": False, "measurements": 11863}}}
    causes = {"ahrs": "rotation about z -0.539 deg +- 0.052 deg (explains 24 % of its residuals)"}
    [line] = consistency_warnings(low, causes=causes, fitted={"ahrs": "ahrs.tilt kept"})
    assert line.endswith("then judge its sigma again (it looks too large); its noise was fitted (ahrs.tilt kept: "
                         "the noise table says why)"), line
    assert consistency_warnings(low, causes=causes)[0].endswith("(it looks too large)")
    [line] = consistency_warnings(low, causes=causes, follow_imu={"ahrs": "it reads the IMU's own messages"})
    assert line.endswith("(it looks too large, or they follow the IMU's (it reads the IMU's own messages))"), line


def test_a_sensor_whose_errors_may_follow_the_imu_is_not_told_its_sigma_is_too_large_alone():
    low = {"batch": {"ahrs": {"per_dof": 0.133, "band": (0.93, 1.07), "ok": False, "measurements": 300}}}
    [line] = consistency_warnings(low, follow_imu={"ahrs": "it reads the IMU's own messages, bag:x.bag, topic /imu"})
    assert ("its sigma looks 2.7x too large by its errors, or they follow the IMU's (it reads the IMU's own "
            "messages, bag:x.bag, topic /imu); estimate") in line, line
