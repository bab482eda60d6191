"""The noise estimated by the batch smoother (smoother/batch/variance_components.py): the
restricted-likelihood score, its iterations, and the noise recovered from simulated rigs whose
rig file states it wrong -- over seeds, against the factors' own standard deviations."""
from __future__ import annotations

import warnings
from dataclasses import replace

import numpy as np
import pytest

from datasets.simulate import simulate
from factors.errors import InputError
from factors.imu import ImuNoise
from smoother.batch import variance_components as vc
from smoother.batch.solve import solve_batch
from smoother.model.problem import build_problem
from smoother.stats import chi2_quantile

#: The rig's IMU noise; the data's is :data:`TRUE_NOISE`.
RIG_NOISE = ImuNoise(acc=5e-3, gyro=5e-4, acc_bias=1e-3, gyro_bias=1e-5, velocity=1e-3)
#: Gyro white noise 4x the rig's, accelerometer bias random walk 10x (no velocity noise: the
#: simulator's discrete truth is the Euler model itself).
TRUE_NOISE = replace(RIG_NOISE, gyro=4 * RIG_NOISE.gyro, acc_bias=10 * RIG_NOISE.acc_bias, velocity=0.0)
#: The data's sigmas: a position sensor's (GNSS-like) and a velocity sensor's (forward, lateral, vertical).
POSITION_SIGMA, VELOCITY_SIGMA = 0.06, (0.02, 0.004, 0.02)
#: What the rig states of them, per axis: the position's a third of the truth, the velocity's
#: lateral five times it.
RIG_SCALE = {"position": np.full(3, 1 / 3), "velocity": np.array([1.0, 5.0, 1.0])}
#: The factors the data should give (on each density or sigma).
TRUE_FACTORS = {"imu.acc": 1.0, "imu.gyro": 4.0, "imu.acc_bias": 10.0, "imu.gyro_bias": 1.0,
                "position.horizontal": 3.0, "position.vertical": 3.0,
                "velocity.forward": 1.0, "velocity.lateral": 0.2, "velocity.vertical": 1.0}


def _rig(seed: int, duration: float = 30.0, noise: ImuNoise = TRUE_NOISE, scale: dict = RIG_SCALE,
         outlier_fraction: float = 0.0, stated: ImuNoise = RIG_NOISE):
    """Data simulated with ``noise`` and the sensors' sigmas, stated as ``stated`` and the
    sensors' sigmas times ``scale``."""
    data = simulate("gentle", duration=duration, seed=seed, imu_rate=100.0, noise=noise, pose_rate=None,
                    gnss_rate=None, position_rate=5.0, position_sigma=POSITION_SIGMA, velocity_rate=10.0,
                    velocity_sigma=VELOCITY_SIGMA, outlier_fraction=outlier_fraction, outlier_scale=(3.0, 0.5))
    sensors = []
    for s in data.sensors:
        f = scale[s.kind]
        sensors.append(replace(s, data=replace(s.data, cov=s.data.cov * f[:, None] * f[None, :])))
    return replace(data, noise=stated, sensors=tuple(sensors))


def _fit(data, robust=None, which=("imu", "position", "velocity")):
    problem = build_problem(data, robust=robust)
    result = solve_batch(problem)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        return (result, *vc.estimate_noise(data, problem, result, which)[:2])


def _within(fit: vc.NoiseFit, truth: dict, k: float = 2.0) -> dict[str, bool]:
    """Per group: its factor within ``k`` of its standard deviations of the truth (a group kept at
    the rig's value counts when the rig's value is the truth)."""
    out = {}
    for g in fit.groups:
        true = truth[g.group.name]
        out[g.group.name] = abs(g.factor - true) <= k * g.factor_sd if g.estimable else true == 1.0
    return out


@pytest.fixture(scope="module")
def seeds():
    """The wrong-noise rig fitted on 20 seeds."""
    return [_fit(_rig(seed)) for seed in range(20)]


def test_the_noise_a_rig_states_wrong_is_recovered_within_two_sd_on_nine_seeds_in_ten(seeds):
    hits = {name: 0 for name in TRUE_FACTORS}
    for _, fit, _ in seeds:
        for name, ok in _within(fit, TRUE_FACTORS).items():
            hits[name] += ok
    assert {name: n for name, n in hits.items() if n < 18} == {}


def test_a_steady_noise_is_called_steady_and_one_that_triples_halfway_is_not(seeds):
    """Each group's factor in the run's two halves (``GroupFit.halves``): on the 20 seeds of a rig
    whose noise is the same throughout, at most one group of one seed is called unsteady (a false
    alarm per group is some 0.3 %); where the position sensor's noise triples halfway through the
    run, its groups are unsteady on every seed and their halves' factors bracket the fit's."""
    false_alarms = [g.group.name for _, fit, _ in seeds for g in fit.groups if not g.steady]
    assert len(false_alarms) <= 1, false_alarms
    for seed in range(3):
        data = _rig(seed)
        position = data.sensor("position")
        m = position.data
        rng = np.random.default_rng(100 + seed)
        late = m.t >= 0.5 * (data.imu.t[0] + data.imu.t[-1])
        noisier = m.position + late[:, None] * rng.normal(scale=np.sqrt(8.0) * POSITION_SIGMA, size=m.position.shape)
        data = replace(data, sensors=tuple(replace(s, data=replace(m, position=noisier)) if s is position else s
                                           for s in data.sensors))
        _, fit, _ = _fit(data)
        for part in ("horizontal", "vertical"):
            g = next(g for g in fit.groups if g.group.name == f"position.{part}")
            first, second = g.halves
            assert not g.steady and 2.0 < second / first < 4.5 and first < g.factor < second, (part, g)


def test_after_the_fit_the_trajectory_is_consistent(seeds):
    """The pose NEES with the fitted noise, averaged over the seeds' keyframes and the seeds,
    inside its chi-square band."""
    from smoother.evaluation.metrics import nees

    values = []
    for seed, (_, _, fitted) in enumerate(seeds):
        data = _rig(seed)
        truth = data.truth.interpolate(fitted.trajectory.t)[0]
        values.append(np.mean(nees(truth, fitted.trajectory.states, fitted.trajectory.cov, "pose")) / 6.0)
    # each seed's keyframes are strongly correlated: the band of the seeds' means, one dof-6 NEES each
    dof = 6 * len(values)
    assert chi2_quantile(0.005, dof) / dof <= np.mean(values) <= chi2_quantile(0.995, dof) / dof


def test_a_rig_whose_noise_is_right_keeps_it_and_its_trajectory():
    right = replace(RIG_NOISE, velocity=0.0)
    data = _rig(3, scale={"position": np.ones(3), "velocity": np.ones(3)}, noise=right, stated=right)
    before, fit, after = _fit(data)
    for g in fit.groups:
        if g.estimable:
            assert abs(g.factor - 1.0) <= 2.0 * g.factor_sd, g
    sigma = np.sqrt(np.diagonal(before.trajectory.cov, axis1=1, axis2=2))[:, :3]
    moved = np.abs(after.trajectory.states.r - before.trajectory.states.r) / sigma
    assert moved.max() <= 0.1


def test_a_fit_every_factor_of_which_stays_the_rig_s_ends_there_with_the_factors_the_iterations_reach(monkeypatch):
    """Once every factor is sure to stay within SIGNIFICANCE sd of the rig's value, the iterations
    end, each factor reported where its Newton step leads: fewer iterations over the seeds than the
    fit that iterates until every step is small (SIGNIFICANCE 0: none is kept), the same groups
    estimable, and each factor within a quarter of its sd of that fit's, with an sd within 20 % of
    it (the factor before the step would be off by up to 0.4 sd)."""
    right = replace(RIG_NOISE, velocity=0.0)
    saved = 0
    for seed in (0, 4, 5, 8):
        data = _rig(seed, scale={"position": np.ones(3), "velocity": np.ones(3)}, noise=right, stated=right)
        _, fit, _ = _fit(data)
        with monkeypatch.context() as m:
            m.setattr(vc, "SIGNIFICANCE", 0.0)
            _, iterated, _ = _fit(data)
        saved += iterated.iterations - fit.iterations
        for g, h in zip(fit.groups, iterated.groups):
            assert g.estimable == h.estimable
            if g.estimable:
                assert not g.applied
                assert abs(g.factor - h.factor) <= 0.25 * g.factor_sd, (g, h)
                assert 0.8 <= g.factor_sd / h.factor_sd <= 1.25, (g, h)
    assert saved >= 3


def test_groups_kept_at_settling_end_the_fit_where_the_rest_is_settled_already(monkeypatch):
    """Where some factors are kept at the rig's value once the steps are small, and the rest's
    Newton step with those back at it is small too, the fit ends there: one evaluation fewer than
    evaluating the rest again (``_held_rest`` answering None), the same groups kept and applied,
    and each factor within a fifth of its sd of that fit's."""
    saved = 0
    for seed in (1, 13, 14):
        data = _rig(seed)
        _, fit, _ = _fit(data)
        with monkeypatch.context() as m:
            m.setattr(vc, "_held_rest", lambda *args: None)
            _, again, _ = _fit(data)
        saved += again.iterations - fit.iterations
        for g, h in zip(fit.groups, again.groups):
            assert (g.estimable, g.applied) == (h.estimable, h.applied)
            if g.estimable:
                assert abs(g.factor - h.factor) <= 0.2 * g.factor_sd, (g, h)
    assert saved == 3


def test_outliers_with_a_robust_kernel_do_not_inflate_the_sensor_s_factor():
    data = _rig(5, outlier_fraction=0.05)
    _, fit, _ = _fit(data, robust={"position": ("huber", None)}, which=("position",))
    for g in fit.groups:
        assert abs(g.factor - TRUE_FACTORS[g.group.name]) <= 2.0 * g.factor_sd, g


def test_components_a_short_run_cannot_separate_are_merged_or_kept_not_returned_as_noise():
    """Over 6 s the bias random walks barely show: each comes back merged with another component
    or kept at the rig's value with its note, never as a free factor of its own."""
    _, fit, _ = _fit(_rig(1, duration=6.0), which=("imu",))
    walks = [g for g in fit.groups if g.group.part in ("acc_bias", "gyro_bias")]
    assert all(g.merged_with or not g.estimable for g in walks), walks
    assert all(g.note.startswith("not estimable") for g in walks if not g.estimable)


def test_a_fit_stopped_before_it_settles_reports_no_factor_its_residuals_cannot_carry(monkeypatch):
    """Cut off after three iterations on a 6-s run, each group whose residuals carry less than
    MIN_REDUNDANCY there (the bias random walks, heading for vanishing variances) is reported not
    estimable at the rig's value, not with the factor the iterations had reached; the rest keep
    theirs."""
    monkeypatch.setattr(vc, "MAX_ITERATIONS", 3)
    _, fit, _ = _fit(_rig(1, duration=6.0), which=("imu",))
    assert not fit.converged
    low = [g for g in fit.groups if g.redundancy < vc.MIN_REDUNDANCY]
    assert {g.group.part for g in low} >= {"acc_bias", "gyro_bias"}, fit.groups
    assert all(not g.estimable and g.factor == 1.0 and g.note.startswith("not estimable") for g in low), low
    assert all(g.estimable and g.factor != 1.0 for g in fit.groups if g.redundancy >= vc.MIN_REDUNDANCY), fit.groups


def test_a_group_alone_takes_foerstners_step():
    """Far from the estimate a single group's step is log(q / r), whatever the local information."""
    for F in (np.array([[3.0]]), np.array([[300.0]])):
        step = vc.far_step(F, np.array([40.0]), np.array([10.0]))
        assert step == pytest.approx([np.log(4.0)])


def test_the_truncated_chi_square_mean_is_that_of_a_sample():
    rng = np.random.default_rng(0)
    for d in (1, 3, 6):
        c = chi2_quantile(vc.TRUNCATION_PROBABILITY, d)
        x = rng.chisquare(d, 2_000_000)
        assert vc.truncated_mean(d, c) == pytest.approx(np.mean(x[x <= c]) / d, rel=2e-3)


def test_the_applied_noise_scales_the_imu_and_each_sensor_s_axes():
    data = _rig(0)
    groups = vc.noise_groups(data, ("imu", "velocity"))
    fits = [vc.GroupFit(g, 2.0 if g.part in ("gyro", "lateral") else 1.0, 0.1, 10.0, None, g.unit) for g in groups]
    applied = vc.NoiseFit(fits, 1, True).applied(data)
    assert applied.noise.gyro == 2.0 * data.noise.gyro and applied.noise.acc == data.noise.acc
    before = next(s for s in data.sensors if s.name == "velocity").data.cov
    after = next(s for s in applied.sensors if s.name == "velocity").data.cov
    np.testing.assert_allclose(after, before * np.array([1.0, 2.0, 1.0])[:, None] * np.array([1.0, 2.0, 1.0]))
    unfitted = [next(s for s in d.sensors if s.name == "position").data.cov for d in (data, applied)]
    np.testing.assert_array_equal(*unfitted)


def test_an_unknown_sensor_is_named():
    with pytest.raises(Exception, match="no sensor 'lidar'"):
        vc.noise_groups(_rig(0, duration=2.0), ("imu", "lidar"))


def test_a_group_to_hold_that_the_fit_does_not_have_is_named_and_so_is_holding_every_group():
    data = _rig(0, duration=2.0)
    problem = build_problem(data)
    result = solve_batch(problem)
    with pytest.raises(InputError, match=r"no group imu\.gyr to hold; expected among imu\.acc, imu\.gyro, "):
        vc.estimate_noise(data, problem, result, ("imu",), fixed={"imu.gyr"})
    every = {g.name for g in vc.noise_groups(data, ("imu",))}
    with pytest.raises(InputError, match="every group of imu is held at the rig's value"):
        vc.estimate_noise(data, problem, result, ("imu",), fixed=every)


def test_the_fit_from_the_batch_s_kept_elimination_equals_the_fit_that_makes_its_own():
    """The batch's covariances' elimination, kept (``square_root``), is what the fit's first
    evaluation would make (the fit's weights at the rig's noise are the problem's): the fits from
    either agree to round-off, and the returned estimate keeps no elimination."""
    data = _rig(3, duration=15.0)
    problem = build_problem(data)
    fits = []
    for square_root in (False, True):
        result = solve_batch(problem, square_root=square_root)
        assert (result.square_root is not None) == square_root
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            fit, fitted, _ = vc.estimate_noise(data, problem, result, ("imu", "position", "velocity"))
        assert fitted.square_root is None
        fits.append(fit)
    for own, kept in zip(*(f.groups for f in fits)):
        assert (own.estimable, own.applied, own.merged_with) == (kept.estimable, kept.applied, kept.merged_with)
        assert kept.factor == pytest.approx(own.factor, rel=1e-7)
        assert kept.redundancy == pytest.approx(own.redundancy, rel=1e-7, abs=1e-6)  # degrees of freedom
    assert fits[0].iterations == fits[1].iterations
