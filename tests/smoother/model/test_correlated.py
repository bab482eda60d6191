"""smoother.model.correlated: a sensor's errors as a first-order Gauss-Markov process in the batch
smoother -- the factors' values against the AR(1) density written out, their Jacobians against
central differences (calibration variables, attached measurements and several measurements on one
keyframe included), and the white model as its limit."""
from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest
from drifting_fixes import lever_arm_run

from datasets.types import Sensor
from factors.calibration import CalibrationPrior
from factors.errors import InputError
from smoother.model.blocks import Layout, evaluate_block
from smoother.model.correlated import correlated_block, innovation_weights, transitions, with_correlated_errors
from smoother.model.problem import build_problem


def _directional(block, states, calibration, rng, eps=1e-6):
    """The block's linearised change along a random step of every keyframe (and the calibration
    variable) against the central difference of its whitened residuals."""
    layout = Layout.of(states, calibration)
    delta = rng.standard_normal(layout.n * 15 + sum(layout.extra))
    ev = evaluate_block(block, states, True, calibration=calibration)
    kf = block.keyframes
    dx = delta[:layout.n * 15].reshape(layout.n, 15)
    linear = sum(np.einsum("mab,mb->ma", A, dx[kf[:, s]]) for s, A in enumerate(ev.A[:kf.shape[1]]))
    if block.calibration is not None:
        linear = linear + np.einsum("mab,b->ma", ev.A[-1], delta[layout.n * 15:])
    moved = [layout.apply(states, calibration, sign * eps * delta) for sign in (1.0, -1.0)]
    plus, minus = (evaluate_block(block, x, False, calibration=c).e for x, c in moved)
    return linear, (plus - minus) / (2 * eps)


@pytest.mark.parametrize("hz", [1.3, 25.0])  # one measurement per keyframe interval; several on one keyframe
@pytest.mark.parametrize("parts", [None, ("time_offset", "lever_arm")])
def test_the_factors_jacobians_match_central_differences(hz, parts):
    calibrate = None if parts is None else CalibrationPrior(parts)
    data = lever_arm_run(hz, calibrate=calibrate)
    problem = with_correlated_errors(build_problem(data), data)
    block = next(b for b in problem.blocks if b.name == "gnss")
    assert block.keyframes.shape[1] == 2 and np.all(block.keyframes[:, 0] != block.keyframes[:, 1])
    if hz > 10:
        shared = np.flatnonzero(np.diff(build_problem(data).blocks[-1 - (parts is not None)].keyframes[:, 0]) == 0)
        assert len(shared)  # the case: consecutive measurements on one keyframe
    rng = np.random.default_rng(1)
    states = problem.initial_states
    states = states.replace(r=states.r + rng.normal(scale=0.5, size=states.r.shape))  # residuals far from zero
    linear, difference = _directional(block, states, problem.calibration, rng)
    np.testing.assert_allclose(linear, difference, rtol=1e-6, atol=1e-7 * np.abs(difference).max())


def test_the_factors_are_the_ar1_density_s_whitened_innovations():
    data = lever_arm_run(1.3)
    white = build_problem(data)
    problem = with_correlated_errors(white, data)
    plain = next(b for b in white.blocks if b.name == "gnss")
    block = next(b for b in problem.blocks if b.name == "gnss")
    states = white.initial_states
    u = evaluate_block(plain, states, False).e  # W_m e_m
    f = evaluate_block(block, states, False).e
    phi = transitions(data.sensors[0].data.t, 3.0)
    np.testing.assert_allclose(f[0], u[0], rtol=1e-12)
    np.testing.assert_allclose(f[1:], (u[1:] - phi[:, None] * u[:-1]) / np.sqrt(1 - phi[:, None] ** 2), rtol=1e-10)
    # the cost is the AR(1) density's exponent: that of the joint covariance of the whitened errors
    lags = np.abs(np.subtract.outer(data.sensors[0].data.t, data.sensors[0].data.t))
    C = np.exp(-lags / 3.0)
    per_axis = sum(u[:, a] @ np.linalg.solve(C, u[:, a]) for a in range(3))
    np.testing.assert_allclose(np.sum(f**2), per_axis, rtol=1e-9)


def test_a_vanishing_correlation_time_is_the_white_model():
    data = lever_arm_run(1.3, tau=0.01)  # the shortest a dataset takes: 77 of them between fixes
    white = build_problem(data)
    block = next(b for b in with_correlated_errors(white, data).blocks if b.name == "gnss")
    plain = next(b for b in white.blocks if b.name == "gnss")
    np.testing.assert_allclose(evaluate_block(block, white.initial_states, False).e,
                               evaluate_block(plain, white.initial_states, False).e, rtol=1e-12)


def test_a_problem_without_correlation_times_is_left_alone():
    data = lever_arm_run(1.3, tau=None)
    problem = build_problem(data)
    assert with_correlated_errors(problem, data) is problem


def test_measurements_out_of_time_order_are_refused_by_name():
    data = lever_arm_run(1.3)
    problem = build_problem(data)
    block = next(b for b in problem.blocks if b.name == "gnss")
    t = data.sensors[0].data.t.copy()
    t[3] = t[2]
    with pytest.raises(InputError, match=r"sensor 'gnss'.*strictly increasing.*measurement 3"):
        correlated_block(block, t, 3.0)


@pytest.mark.parametrize("tau", [0.0, -1.0, float("nan"), True])
def test_a_bad_correlation_time_is_refused_by_name(tau):
    with pytest.raises(InputError, match=r"sensor 'gnss': correlation_time"):
        lever_arm_run(1.3, tau=tau)


def test_a_correlation_time_far_beyond_the_measurements_spacing_is_refused_by_name():
    """``phi`` rounding to 1 and the innovations' scale to infinity ended in numpy's SVD: 1e20 s is
    beyond what a dataset takes, and the longest it takes, a day, against stamps 10 ns apart
    (increasing, so accepted) is refused where the factors are made."""
    with pytest.raises(InputError, match=r"sensor 'gnss': correlation_time: expected a value within"):
        lever_arm_run(1.3, tau=1e20)
    with pytest.raises(InputError, match=r"sensor 'gnss': correlation_time 86400 s is too long for measurements"):
        innovation_weights("gnss", np.array([0.0, 1.0, 1.0 + 1e-8]), 86_400.0)


def test_a_sensor_without_used_measurements_beside_a_drifting_one_is_no_obstacle():
    """A sensor that only checks the estimate (all held out, ``data`` None) beside one with a
    correlation time: the batch's problem is made and solved."""
    from smoother import pipeline

    data = lever_arm_run(1.3)
    gnss = data.sensors[0]
    checker = Sensor("checker", "position", None, gnss.data.subset(np.arange(len(gnss.data.t)) % 2 == 0))
    data = replace(data, sensors=(gnss, checker))
    estimate = pipeline.run_estimators(data, ["batch"], pipeline.RunOptions(progress=False))["batch"]
    assert estimate.failed is None and np.isfinite(estimate.trajectory.states.r).all()


def test_a_drifting_sensor_with_a_full_covariance_cannot_have_its_axis_groups_fitted_apart():
    from smoother.batch.variance_components import noise_groups

    data = lever_arm_run(1.3)
    gnss = data.sensors[0]
    assert [g.part for g in noise_groups(data, ["gnss"])] == ["horizontal", "vertical"]  # diagonal: fine
    cov = gnss.data.cov.copy()
    cov[:, 0, 1] = cov[:, 1, 0] = 0.01
    full = data.with_sensor("gnss", data=replace(gnss.data, cov=cov))
    with pytest.raises(InputError, match=r"sensor 'gnss' has a correlation_time and covariances that are not "
                                         r"diagonal: its horizontal, vertical cannot be fitted apart"):
        noise_groups(full, ["gnss"])
    assert len(noise_groups(full.with_sensor("gnss", correlation_time=None), ["gnss"])) == 2


def test_a_problem_with_drifting_factors_is_banded_and_one_with_many_long_factors_is_not():
    """``Layout.banded``: factors on keyframes further apart than the next, at most ``BAND`` over any
    interval -- a drifting sensor's between used fixes with held-out ones between them -- have their
    covariances swept in time order; more, COLAMD."""
    from drifting_fixes import drifting_run

    from smoother.model.blocks import BAND, Block

    data = drifting_run(0, 3.0, duration=12.0)
    plain = build_problem(data)
    states = plain.initial_states
    assert Layout.of(states, None, plain.blocks).chain
    layout = Layout.of(states, None, with_correlated_errors(plain, data).blocks)
    assert layout.banded and not layout.chain

    def spans(m):  # m factors each from keyframe 0 to the last
        return Block("long", np.tile([0, len(states) - 1], (m, 1)), None, np.ones((m, 1, 1)))

    assert Layout.of(states, None, [*plain.blocks, spans(BAND)]).banded
    assert not Layout.of(states, None, [*plain.blocks, spans(BAND + 1)]).banded
