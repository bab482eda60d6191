"""Measurements attached to the keyframe before them: the prediction through the IMU's Euler steps,
its Jacobian, every kind's attached residual's Jacobians (state, calibration) against central
differences, and the process noise between keyframe and measurement."""
from __future__ import annotations

import numpy as np
import pytest

from datasets.kinds import KINDS, attached_noise, attached_rows, measure_rows
from factors import calibration, imu, preintegration, selfcheck, so3

ONE_STATE = [k for k in KINDS.values() if not k.relative]


def _intervals(rng, n: int, K: int = 6):
    """``n`` random intervals of ``K`` steps of 2-5 ms at a few rad/s (padded samples ``(acc, gyro,
    dt)``), and where in each a measurement lies: after the first 1..K steps, the last cut anywhere."""
    acc, gyro = rng.normal(size=(n, K, 3)) * 3, rng.normal(size=(n, K, 3)) * 3
    dt = rng.uniform(2e-3, 5e-3, size=(n, 1)) * np.ones((1, K))
    steps = rng.integers(1, K + 1, size=n)
    last = rng.uniform(1e-3, 1.0, size=n) * dt[np.arange(n), steps - 1]
    return (acc, gyro, dt), np.arange(n), steps, last


def _points(kind, rng, n: int):
    drawn = [kind.random_row(rng) for _ in range(n)]
    return imu.ImuState.stack([s for s, _ in drawn]), np.stack([row for _, row in drawn])


def _numerical(e_at, states, c=None, eps=1e-6):
    """Central differences over all rows at once (each row's residual reads only its own state;
    the calibration is shared): one column per error-state coordinate, then per calibration one."""
    columns = []
    for i in range(imu.STATE_DIM):
        d = np.zeros(imu.STATE_DIM)
        d[i] = eps
        columns.append((e_at(imu.boxplus(states, d), c) - e_at(imu.boxplus(states, -d), c)) / (2 * eps))
    if c is not None:
        for i in range(calibration.CALIBRATION_DIM):
            d = np.zeros(calibration.CALIBRATION_DIM)
            d[i] = eps
            columns.append((e_at(states, c.boxplus(d)) - e_at(states, c.boxplus(-d))) / (2 * eps))
    return np.stack(columns, axis=-1)


def _worst(analytic, numerical) -> float:
    size = 1.0 + np.abs(numerical).max(axis=(1, 2))
    return float(np.max(np.abs(analytic - numerical).max(axis=(1, 2)) / size))


def test_prediction_jacobian_equals_central_differences_at_1000_points():
    """``predict``'s Jacobian with respect to the keyframe's error state (every block, the gyro
    bias's through the bias Jacobians, with a bias offset from the linearisation point) over
    intervals of 1-40 samples at several rad/s, attitudes tiny, near pi and of any size."""
    rng = np.random.default_rng(11)
    worst = 0.0
    for group in range(50):
        K = int(rng.integers(1, 41))
        acc, gyro = rng.normal(size=(20, K, 3)) * 3, rng.normal(size=(20, K, 3)) * 3
        dt = rng.uniform(2e-3, 1e-2, size=(20, 1)) * np.ones((1, K))
        states = imu.ImuState.stack([selfcheck.random_state(rng) for _ in range(20)])
        pre = preintegration.integrate(acc, gyro, dt, states.b_w)
        states = states.replace(b_w=states.b_w + (group % 2) * rng.normal(size=(20, 3)) * 0.01)
        _, J = preintegration.predict(pre, states, jacobians=True)
        eps, columns = 1e-6, []
        for i in range(imu.STATE_DIM):
            d = np.zeros(imu.STATE_DIM)
            d[i] = eps
            plus = preintegration.predict(pre, imu.boxplus(states, d))
            minus = preintegration.predict(pre, imu.boxplus(states, -d))
            columns.append(imu.boxminus(plus, minus) / (2 * eps))
        worst = max(worst, _worst(J, np.stack(columns, axis=-1)))
    assert worst < 1e-6, worst


@pytest.mark.parametrize("kind", ONE_STATE, ids=lambda k: k.name)
def test_attached_jacobians_equal_central_differences_at_1000_points(kind):
    """The attached residual's Jacobian with respect to the keyframe's state, and through a
    calibration (time offset of either sign, mounting of any regime, lever arm, scale) with
    respect to the state and every calibration part, at 1000 points each: 50 groups of 20 random
    rows, states and partial intervals, to 1e-6 relative to the Jacobian's size (the registered
    self-checks, ``smoother check-jacobians``, draw the same way one point at a time)."""
    rng = np.random.default_rng(3 + sum(map(ord, kind.name)))
    worst_plain, worst_calibrated = 0.0, 0.0
    for group in range(50):
        states, rows = _points(kind, rng, 20)
        samples, interval, steps, last = _intervals(rng, 20)
        readings = (rng.normal(size=(20, 3)) * 3, rng.normal(size=(20, 3)) * 3)
        c = calibration.Calibration((-1.0 if group % 2 else 1.0) * rng.uniform(1e-3, 0.3),
                                    selfcheck.random_rotation(rng), rng.normal(size=3), float(1 + 0.05 * rng.normal()))

        def e_at(x, cal):
            return attached_rows(kind, x, samples, interval, steps, last, rows, cal, readings if cal else None)[0]

        _, H, H_c = attached_rows(kind, states, samples, interval, steps, last, rows)
        assert H_c is None
        worst_plain = max(worst_plain, _worst(H, _numerical(e_at, states)))
        _, H, H_c = attached_rows(kind, states, samples, interval, steps, last, rows, c, readings)
        worst_calibrated = max(worst_calibrated, _worst(np.concatenate([H, H_c], axis=2),
                                                        _numerical(e_at, states, c)))
    assert worst_plain < 1e-6 and worst_calibrated < 1e-6, (worst_plain, worst_calibrated)


@pytest.mark.parametrize("kind", ONE_STATE, ids=lambda k: k.name)
def test_an_attached_measurement_is_the_model_at_the_euler_propagated_state(kind):
    """The residual of a measurement attached to a keyframe is the model's own at the state the
    primer's Euler steps reach from the keyframe (:func:`factors.imu.propagate`, step by step), to
    round-off; the residual alone (no Jacobians) is bit for bit the full evaluation's."""
    rng = np.random.default_rng(5 + sum(map(ord, kind.name)))
    states, rows = _points(kind, rng, 20)
    samples, interval, steps, last = _intervals(rng, 20)
    acc, gyro, dt = samples
    x = states
    for k in range(acc.shape[1]):
        h = np.where(k < steps - 1, dt[:, k], np.where(k == steps - 1, last, 0.0))
        x = imu.propagate(x, acc[:, k], gyro[:, k], h, jacobians=False)[0]
    e_model, _ = measure_rows(kind, x, rows)
    e, _, _ = attached_rows(kind, states, samples, interval, steps, last, rows)
    np.testing.assert_allclose(e, e_model, rtol=0, atol=1e-9)
    alone = attached_rows(kind, states, samples, interval, steps, last, rows, jacobians=False)
    assert alone[1] is None
    np.testing.assert_array_equal(alone[0], e)


@pytest.mark.parametrize("kind", ONE_STATE, ids=lambda k: k.name)
def test_attached_noise_is_the_measurements_share_of_the_predictions_covariance(kind):
    """``H S H^T``: with ``S`` the EKF's covariance growth from zero over the partial interval
    (:func:`factors.imu.propagate_steps` in the world frame) and ``H`` the model's Jacobian at the
    predicted state, to 1e-9 relative."""
    rng = np.random.default_rng(9 + sum(map(ord, kind.name)))
    noise = imu.ImuNoise(acc=2e-2, gyro=2e-3, acc_bias=1e-3, gyro_bias=1e-4, velocity=1e-3)
    states, rows = _points(kind, rng, 20)
    samples, interval, steps, last = _intervals(rng, 20)
    acc, gyro, dt = samples
    cut = np.where(np.arange(dt.shape[1]) < steps[:, None] - 1, dt,
                   np.where(np.arange(dt.shape[1]) == steps[:, None] - 1, last[:, None], 0.0))
    x, S = imu.propagate_steps(states, np.zeros((20, 15, 15)), acc, gyro, cut, noise)
    _, H = measure_rows(kind, x, rows)
    expected = H @ S @ np.swapaxes(H, 1, 2)
    got = attached_noise(kind, states, samples, interval, steps, last, rows, noise)
    scale = np.abs(expected).max(axis=(1, 2), keepdims=True)
    np.testing.assert_allclose(got / scale, expected / scale, rtol=0, atol=1e-9)


@pytest.mark.parametrize("kind", [KINDS["velocity"], KINDS["gnss"]], ids=lambda k: k.name)
def test_measurements_of_one_interval_in_time_order_equal_each_taken_alone(kind):
    """Several measurements attached to each keyframe, in time order: each continues the steps
    of the one before (the same interval and keyframe state; at most as many steps), and every
    residual, Jacobian and process-noise share equals, to the bit, the measurement's alone; in any other order, or
    from another keyframe state (any part of it), they start again and agree too."""
    rng = np.random.default_rng(5)
    J, K, per = 12, 9, 7
    acc, gyro = rng.normal(size=(J, K, 3)) * 3, rng.normal(size=(J, K, 3)) * 3
    dt = rng.uniform(2e-3, 5e-3, size=(J, 1)) * np.ones((1, K))
    keyframes, rows = _points(kind, rng, J)
    interval = np.repeat(np.arange(J), per)
    steps = np.sort(rng.integers(1, K + 1, size=(J, per)), axis=1).ravel()
    steps[5] = steps[4]  # two at the same step, the later cut later
    last = rng.uniform(1e-3, 1.0, size=J * per) * dt[interval, steps - 1]
    last[5] = max(last[4], last[5])
    states, readings = keyframes[interval], rows[interval]
    states = states.replace(b_w=np.where((np.arange(J * per) == 3 * per + 2)[:, None], states.b_w + 1e-3, states.b_w))
    for m, part in zip((5 * per + 3, 6 * per + 4, 7 * per + 2, 8 * per + 5), ("r", "v", "b_f", "C")):
        value = getattr(states, part).copy()  # a keyframe state other than the one before it: start again
        value[m] = value[m] @ so3.exp(np.array([0.0, 0.0, 1e-3])) if part == "C" else value[m] + 1e-3
        states = states.replace(**{part: value})
    c = calibration.Calibration.of(time_offset=0.004)
    together = attached_rows(kind, states, (acc, gyro, dt), interval, steps, last, readings, c, None)
    alone = [attached_rows(kind, states[m:m + 1], (acc, gyro, dt), interval[m:m + 1], steps[m:m + 1],
                           last[m:m + 1], readings[m:m + 1], c, None) for m in range(J * per)]
    for got, want in zip(together, zip(*alone)):
        assert np.array_equal(got, np.concatenate(want))
    noise = imu.ImuNoise(acc=0.05, gyro=0.01, acc_bias=0.003, gyro_bias=2e-4)
    shared = attached_noise(kind, states, (acc, gyro, dt), interval, steps, last, readings, noise)
    assert np.array_equal(shared, np.concatenate([attached_noise(kind, states[m:m + 1], (acc, gyro, dt),
                                                                 interval[m:m + 1], steps[m:m + 1], last[m:m + 1],
                                                                 readings[m:m + 1], noise) for m in range(J * per)]))
    order = rng.permutation(J * per)
    shuffled = attached_rows(kind, states[order], (acc, gyro, dt), interval[order], steps[order], last[order],
                             readings[order], c, None)
    for got, want in zip(shuffled, together):
        assert np.array_equal(got, want[order])
