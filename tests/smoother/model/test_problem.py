"""Graph building (smoother/model/problem.py): keyframes, factors between the right keyframes, initial
values from dead reckoning and measurements, the prior."""
from __future__ import annotations

import functools

import estimator_cases as cases
import gtsam
import numpy as np
import pytest

from datasets.simulate import simulate
from factors import so3
from smoother.ekf.filter import run_ekf
from smoother.model.problem import build_problem, insert_state
from smoother.model.timeline import EVERY_MEASUREMENT, KEYFRAME_RATE

IMU_STEP = 1.0 / cases.IMU_RATE


@functools.lru_cache(maxsize=None)
def mixed():
    """Pose at 5 Hz, GPS at 4 Hz, attitude at 10 Hz, over 2.03 s (the end is no measurement
    time, so it must be added as a keyframe of its own)."""
    return simulate(profile="gentle", duration=2.03, seed=4, imu_rate=cases.IMU_RATE, pose_rate=5.0,
                    position_rate=4.0, orientation_rate=10.0)


def _symbols(factor) -> list[tuple[str, int]]:
    return [(chr(gtsam.Symbol(k).chr()), gtsam.Symbol(k).index()) for k in factor.keys()]


# ------------------------------------------------------------------------------------------
# keyframes


def test_keyframes_are_the_measurement_times_plus_start_and_end():
    data = mixed()
    problem = build_problem(data, EVERY_MEASUREMENT)
    expected = np.unique(np.concatenate([data.sensor(name).data.t for name in ("pose", "position", "orientation")]
                                        + [[data.t0, data.t1]]))
    np.testing.assert_array_equal(problem.times, expected)
    assert data.t1 not in set(data.measurement_times())  # the end really is an extra keyframe
    # the EKF reports at exactly the same times, so the estimators can be compared state by state
    np.testing.assert_array_equal(run_ekf(data, progress=False).trajectory.t, problem.times)


def test_keyframe_rate_is_the_grid_and_measurements_between_are_attached():
    """A 3 Hz grid (t0 + k/3, which falls between measurement times) and the ends are the
    keyframes; every measurement not on one is attached to the keyframe before it, and becomes
    available with the keyframe after it (a factor on every variable of its keyframe)."""
    data = mixed()
    problem = build_problem(data, keyframe_rate=3.0)
    grid = data.t0 + np.arange(7) / 3.0  # 0, 1/3, ..., 2 (< t1 = 2.03); 0, 1 and 2 are pose times
    np.testing.assert_array_equal(problem.times, np.union1d(grid, [data.t1]))
    one_state = sum(len(s.data.t) for s in data.sensors)
    on_grid = sum(np.isin(s.data.t, problem.times).sum() for s in data.sensors)
    assert problem.keyframes == {"count": 8, "rate_hz": 3.0, "measurements": one_state, "attached": one_state - on_grid,
                                 "max_attached_distance_s": pytest.approx(0.3, abs=1e-12), "relative": 0,
                                 "composed": 0}
    for k, group in enumerate(problem.factors_at):
        for f in group[0 if k == 0 else 1:]:
            (index,) = {i for _, i in _symbols(f)}
            assert index in (k, k - 1)
            if index == k - 1:
                assert list(f.keys()) == problem.keys[k - 1].all()


def test_the_default_keyframe_grid_is_chosen_from_the_measurement_rate():
    """Measurement times denser than 10 per second (here about 13): keyframes on the 10 Hz grid;
    no denser (the 10 Hz poses alone): a keyframe at every measurement time, as before."""
    data = mixed()
    assert len(data.measurement_times()) > KEYFRAME_RATE * (data.t1 - data.t0)
    problem = build_problem(data)
    assert problem.keyframes["rate_hz"] == KEYFRAME_RATE
    np.testing.assert_array_equal(problem.times, np.union1d(data.t0 + np.arange(21) / 10.0, [data.t1]))
    sparse = simulate(profile="gentle", duration=2.03, seed=4, imu_rate=cases.IMU_RATE, pose_rate=10.0)
    sparse_problem = build_problem(sparse)
    assert sparse_problem.keyframes["rate_hz"] == EVERY_MEASUREMENT and sparse_problem.keyframes["attached"] == 0
    np.testing.assert_array_equal(sparse_problem.times, np.union1d(sparse.measurement_times(), [sparse.t1]))


def test_grid_coinciding_with_measurement_times_adds_no_near_duplicate_keyframes():
    """A 10 Hz grid over 10 Hz poses: the grid times are the measurement times, so the keyframes
    are exactly those; no two keyframes closer than half an IMU step (an ulp-off duplicate makes
    a ~1e-16 s IMU interval with a ~0 covariance), and the batch solve works."""
    from smoother.batch.solve import solve_batch

    data = simulate(profile="gentle", duration=2.0, seed=0, imu_rate=cases.IMU_RATE, pose_rate=cases.POSE_RATE)
    for rate in (10.0, 5.0, 25.0):
        times = build_problem(data, keyframe_rate=rate).times
        assert np.diff(times).min() >= 0.5 * IMU_STEP, (rate, np.diff(times).min())
    problem = build_problem(data, keyframe_rate=10.0)
    np.testing.assert_array_equal(problem.times, data.sensor("pose").data.t)
    result = solve_batch(problem, covariances=False)
    assert np.all(np.isfinite(result.trajectory.states.r))


# ------------------------------------------------------------------------------------------
# factors


def test_graph_holds_the_prior_one_imu_factor_per_interval_and_every_measurement():
    data = mixed()
    problem = build_problem(data)
    K = len(problem.times)
    expected = 1 + (K - 1) + sum(len(data.sensor(name).data) for name in ("pose", "position", "orientation"))
    assert problem.graph.size() == expected
    assert sum(len(group) for group in problem.factors_at) == expected
    for k in range(1, K):
        f = problem.imu_factors[k - 1].factor
        assert list(f.keys()) == problem.keys[k - 1].all() + problem.keys[k].all()
        assert any(g is f for g in problem.factors_at[k])
    # each measurement factor is announced at its own keyframe and refers to it only
    for k, group in enumerate(problem.factors_at):
        for f in group:
            if f.size() <= 2:  # pose (P, R), position (P), orientation (R)
                assert {index for _, index in _symbols(f)} == {k}


def test_gtsam_graph_is_built_on_first_use_only():
    """The batch solver works on the vectorised blocks: solving does not build the GTSAM factors
    (about half of the construction time); the first access builds them once, with the initial
    values of the problem's initial states."""
    from smoother.batch.solve import solve_batch

    problem = build_problem(mixed())
    solve_batch(problem, covariances=False)
    assert problem.gtsam_parts is None
    graph = problem.graph
    assert problem.gtsam_parts is not None and problem.graph is graph and problem.factors_at is problem.gtsam.factors_at
    for k in (0, len(problem.times) - 1):
        assert np.allclose(problem.initial.atPoint3(problem.keys[k].pos), problem.initial_states.r[k])


def test_relative_pose_factors_join_the_right_keyframes():
    """Odometry at 5 Hz between consecutive times of its stream: one factor per measurement,
    between the keyframes at t_from and t_to, announced at t_to; evaluated at the TRUE states its
    error is exactly the measurement noise, (C_i^T (r_j - r_i) - dr~, log(C_i^T C_j dC~^T))."""
    data = simulate(profile="tumbling", duration=1.0, seed=6, imu_rate=cases.IMU_RATE, pose_rate=cases.POSE_RATE,
                    odometry_rate=5.0)
    problem = build_problem(data)
    rel = data.sensor("odometry").data
    truth = cases.truth_at(data, problem.times)
    values = gtsam.Values()
    for k, keys in enumerate(problem.keys):
        insert_state(values, keys, truth[k])

    found = {}
    for k, group in enumerate(problem.factors_at):
        for f in group:
            symbols = _symbols(f)
            if [s for s, _ in symbols] == ["R", "P", "R", "P"]:
                i, j = symbols[0][1], symbols[2][1]
                assert (symbols[1][1], symbols[3][1]) == (i, j)
                assert k == j
                found[(i, j)] = f
    expected_pairs = [(int(np.searchsorted(problem.times, a)), int(np.searchsorted(problem.times, b)))
                      for a, b in zip(rel.t_from, rel.t_to)]
    assert sorted(found) == expected_pairs
    assert len(expected_pairs) == len(rel) == 5
    for m, (i, j) in enumerate(expected_pairs):
        assert problem.times[i] == rel.t_from[m] and problem.times[j] == rel.t_to[m]
        Ci, Cj = truth.C[i], truth.C[j]
        expected_error = np.concatenate([
            Ci.T @ (truth.r[j] - truth.r[i]) - rel.dr[m],
            so3.log(Ci.T @ Cj @ rel.dC[m].T),
        ])
        np.testing.assert_allclose(found[(i, j)].unwhitenedError(values), expected_error, rtol=0, atol=1e-12)
        # the noise is visible (sigma 0.02 m / 0.005 rad), so the check is not 0 == 0
        assert np.abs(expected_error).max() > 1e-4


# ------------------------------------------------------------------------------------------
# initial values


def test_initial_values_equal_the_measurements_where_measured():
    """After keyframe 0: positions from pose or GPS, attitudes from pose or attitude
    measurements, exactly; the rest from the IMU prediction off the previous keyframe's initial
    state. Keyframe 0 is the dataset's initial estimate (even though a pose is measured there:
    the prior carries it), where the prior has zero error."""
    data = mixed()
    problem = build_problem(data, EVERY_MEASUREMENT)
    x = problem.initial_states
    index = {t: k for k, t in enumerate(problem.times)}
    assert {data.sensor(name).data.t[0] for name in ("pose", "position", "orientation")} == {data.t0}
    pose_k = [index[t] for t in data.sensor("pose").data.t[1:]]
    gps_k = [index[t] for t in data.sensor("position").data.t[1:]]
    att_k = [index[t] for t in data.sensor("orientation").data.t[1:]]
    np.testing.assert_array_equal(x.r[pose_k], data.sensor("pose").data.position[1:])
    np.testing.assert_array_equal(x.C[pose_k], data.sensor("pose").data.C[1:])
    gps_only = [m for m, k in enumerate(gps_k) if k not in pose_k]
    assert gps_only
    np.testing.assert_array_equal(x.r[[gps_k[m] for m in gps_only]],
                                  data.sensor("position").data.position[1:][gps_only])
    att_only = [m for m, k in enumerate(att_k) if k not in pose_k]
    assert att_only
    np.testing.assert_array_equal(x.C[[att_k[m] for m in att_only]], data.sensor("orientation").data.C[1:][att_only])

    unmeasured_r = [k for k in range(1, len(problem.times)) if k not in pose_k and k not in gps_k]
    unmeasured_C = [k for k in range(1, len(problem.times)) if k not in pose_k and k not in att_k]
    assert unmeasured_r and unmeasured_C  # (the end, at least, and the 10 Hz attitude-only times)
    for k in unmeasured_r:
        predicted = problem.imu_factors[k - 1].predict(x[k - 1])
        np.testing.assert_allclose(x.r[k], predicted.r, rtol=0, atol=1e-12)
    for k in unmeasured_C:
        predicted = problem.imu_factors[k - 1].predict(x[k - 1])
        np.testing.assert_allclose(x.C[k], predicted.C, rtol=0, atol=1e-12)

    for name in ("r", "v", "C", "b_f", "b_w"):
        np.testing.assert_array_equal(getattr(x, name)[0], getattr(data.initial, name))
    prior = problem.factors_at[0][0]
    assert list(prior.keys()) == problem.keys[0].all()
    assert prior.error(problem.initial) == pytest.approx(0.0, abs=1e-20)
    # the GTSAM values hold the same states
    for k in (0, len(problem.times) // 2, len(problem.times) - 1):
        np.testing.assert_allclose(problem.initial.atPoint3(problem.keys[k].pos), x.r[k], rtol=0, atol=0)
        np.testing.assert_allclose(problem.initial.atRot3(problem.keys[k].rot).matrix(), x.C[k], rtol=0, atol=1e-15)
