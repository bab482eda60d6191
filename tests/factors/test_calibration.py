"""The calibration variables: their chart, their prior, and every kind's calibrated residual's
Jacobians (state, time offset, rotation, lever arm, scale) against central differences."""
from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from datasets.kinds import KINDS, calibrated_rows
from factors import calibration, imu, selfcheck, so3
from factors.errors import InputError
from tests.strategies import rotation_vectors


def _points(kind, rng, n: int):
    """``n`` random points of ``kind`` (:attr:`Kind.random_row`: attitudes tiny, near pi and of
    any size) as stacked states (a pair for a relative kind), rows and IMU readings at them."""
    drawn = [kind.random_row(rng) for _ in range(n)]
    rows = np.stack([row for _, row in drawn])
    if kind.relative:
        states = tuple(imu.ImuState.stack([s[i] for s, _ in drawn]) for i in range(2))
        readings = tuple((rng.normal(size=(n, 3)) * 3, rng.normal(size=(n, 3)) * 3) for _ in range(2))
    else:
        states = imu.ImuState.stack([s for s, _ in drawn])
        readings = (rng.normal(size=(n, 3)) * 3, rng.normal(size=(n, 3)) * 3)
    return states, rows, readings


def _random_calibration(rng, sign: float) -> calibration.Calibration:
    """A mounting rotation of any regime (tiny, near pi, any), a lever arm of ~1 m, a time offset
    of the given sign (1 ms to 0.3 s), a scale near 1."""
    return calibration.Calibration(sign * rng.uniform(1e-3, 0.3), selfcheck.random_rotation(rng),
                                   rng.normal(size=3), float(1 + 0.05 * rng.normal()))


def _numerical(kind, states, rows, c, readings, eps=1e-6):
    """Central differences of the calibrated residual over all rows at once: each row's residual
    reads only its own states, so moving every row's state along one coordinate gives that column
    of every row's Jacobian; the calibration is shared, so moving it gives its column."""
    pair = states if kind.relative else (states,)

    def e_at(moved, cal):
        return calibrated_rows(kind, moved if kind.relative else moved[0], rows, cal, readings)[0]

    columns = []
    for slot in range(len(pair)):
        for i in range(imu.STATE_DIM):
            d = np.zeros(imu.STATE_DIM)
            d[i] = eps
            plus = [imu.boxplus(s, d) if k == slot else s for k, s in enumerate(pair)]
            minus = [imu.boxplus(s, -d) if k == slot else s for k, s in enumerate(pair)]
            columns.append((e_at(tuple(plus), c) - e_at(tuple(minus), c)) / (2 * eps))
    for i in range(calibration.CALIBRATION_DIM):
        d = np.zeros(calibration.CALIBRATION_DIM)
        d[i] = eps
        columns.append((e_at(pair, c.boxplus(d)) - e_at(pair, c.boxplus(-d))) / (2 * eps))
    return np.stack(columns, axis=-1)


@pytest.mark.parametrize("kind", KINDS.values(), ids=lambda k: k.name)
def test_calibrated_jacobians_equal_central_differences_at_1000_points(kind):
    """Every block (the state or states, time offset, rotation, lever arm, scale) at 1000 points:
    50 random calibrations, half with a negative time offset, each at 20 random rows and states,
    to 1e-6 relative to the Jacobian's size (the registered self-check,
    ``smoother check-jacobians``, draws the same way one point at a time)."""
    rng = np.random.default_rng(sum(map(ord, kind.name)))
    worst = 0.0
    for group in range(50):
        states, rows, readings = _points(kind, rng, 20)
        c = _random_calibration(rng, -1.0 if group % 2 else 1.0)
        _, H, H_c = calibrated_rows(kind, states, rows, c, readings)
        analytic = np.concatenate([H, H_c], axis=2)
        numerical = _numerical(kind, states, rows, c, readings)
        size = 1.0 + np.abs(numerical).max(axis=(1, 2))
        worst = max(worst, float(np.max(np.abs(analytic - numerical).max(axis=(1, 2)) / size)))
    assert worst < 1e-6, worst


@pytest.mark.parametrize("kind", KINDS.values(), ids=lambda k: k.name)
def test_the_residual_without_jacobians_is_the_residual_with_them(kind):
    """What a cost evaluates (``jacobians=False``: no step transition, no chain rule) is bit for
    bit the residual of the full evaluation, with and without a time offset of either sign."""
    rng = np.random.default_rng(7 + sum(map(ord, kind.name)))
    for group in range(6):
        states, rows, readings = _points(kind, rng, 20)
        c = _random_calibration(rng, -1.0 if group % 2 else 1.0)
        at = readings if group < 4 else None
        full = calibrated_rows(kind, states, rows, c, at)
        alone = calibrated_rows(kind, states, rows, c, at, jacobians=False)
        assert alone[1] is None and alone[2] is None
        np.testing.assert_array_equal(alone[0], full[0])


@given(rotation_vectors(), st.floats(-0.5, 0.5), st.floats(0.5, 1.5))
@settings(max_examples=200, deadline=None)
def test_boxplus_and_boxminus_are_inverse(phi, dt, scale):
    rng = np.random.default_rng(0)
    c = calibration.Calibration(dt, so3.exp(phi), rng.normal(size=3), scale)
    delta = rng.normal(size=8) * 0.3
    assert np.allclose(c.boxplus(delta).boxminus(c), delta, atol=1e-9)
    assert np.allclose(c.boxplus(c.boxminus(c)).T_BS, c.T_BS)


def test_the_rotation_is_perturbed_on_the_left_in_the_imu_frame():
    R = so3.exp(np.array([0.3, -0.2, 1.0]))
    rho = np.array([0.01, 0.02, -0.03])
    c = calibration.Calibration.of(np.block([[R, np.zeros((3, 1))], [np.zeros((1, 3)), np.ones((1, 1))]]))
    assert np.allclose(c.boxplus(np.r_[0, rho, 0, 0, 0, 0]).R, so3.exp(rho) @ R)


def test_zero_calibration_changes_nothing():
    """With the extrinsic given, no time offset and scale 1 the calibrated residual is the kind's own."""
    rng = np.random.default_rng(3)
    for kind in KINDS.values():
        state, row = kind.random_row(rng)
        states = tuple(s[None] for s in state) if kind.relative else state[None]
        if kind.relative:
            R, p = row[12:21].reshape(3, 3), row[21:24]
        else:
            m = kind.model
            R = row[m.rotation_at:m.rotation_at + 9].reshape(3, 3) if m.rotation_at is not None else np.eye(3)
            p = row[m.lever_at:m.lever_at + 3] if m.lever_at is not None else np.zeros(3)
        e, _, _ = calibrated_rows(kind, states, row[None], calibration.Calibration(0.0, R, p, 1.0))
        from datasets.kinds import evaluate
        assert np.allclose(e[0], evaluate(kind, state, row)[0], atol=1e-12), kind.name


def test_a_time_offset_moves_a_position_by_the_velocity():
    """First order: a GNSS fix taken ``d`` later sees the antenna ``d C v`` further on."""
    kind = KINDS["position"]
    x = imu.ImuState(np.zeros(3), np.array([10.0, 0, 0]), np.eye(3), np.zeros(3), np.zeros(3))
    row = kind.pack(type("M", (), {"position": np.zeros((1, 3)), "T_BS": None})())
    at = (np.array([[0.0, 0, 9.81]]), np.zeros((1, 3)))
    e, _, H_c = calibrated_rows(kind, x[None], row, calibration.Calibration(0.1, np.eye(3), np.zeros(3), 1.0), at)
    assert np.allclose(e[0], [1.0, 0, 0]) and np.allclose(H_c[0, :, 0], [10.0, 0, 0])


def test_prior_residual_jacobian_is_the_chart_derivative():
    rng = np.random.default_rng(5)
    mean = calibration.Calibration(0.02, selfcheck.random_rotation(rng), rng.normal(size=3), 1.01)
    c = mean.boxplus(rng.normal(size=8) * 0.2)
    which = calibration.columns(("rotation", "scale"))
    e, J = calibration.prior_residual(c, mean, which)
    eps = 1e-6
    numerical = []
    for i, col in enumerate(which):
        d = np.zeros(8)
        d[col] = eps
        numerical.append((calibration.prior_residual(c.boxplus(d), mean, which)[0]
                          - calibration.prior_residual(c.boxplus(-d), mean, which)[0]) / (2 * eps))
    assert np.allclose(J, np.stack(numerical, axis=1), atol=1e-7)


def test_columns_refuse_an_unknown_part():
    assert list(calibration.columns(("scale", "time_offset"))) == [0, 7]
    with pytest.raises(InputError, match="expected any of time_offset, rotation, lever_arm, scale"):
        calibration.columns(("mounting",))


def test_which_parts_each_model_can_estimate():
    parts = {k: calibration.applicable(KINDS[k].model) for k in ("gnss", "orientation", "velocity", "odometry")}
    assert parts == {"gnss": ("time_offset", "lever_arm"), "orientation": ("time_offset", "rotation"),
                     "velocity": calibration.PARTS, "odometry": calibration.PARTS}


def test_a_calibration_set_gives_a_sensor_s_value_by_name_and_none_for_another():
    T = np.eye(4)
    T[:3, 3] = [0.1, 0.2, 0.3]
    chosen = calibration.CalibrationSet.given(["gnss", "wheels"], [T, None],
                                              [calibration.CalibrationPrior(("lever_arm",))] * 2)
    np.testing.assert_array_equal(chosen.value_of("gnss").p, [0.1, 0.2, 0.3])
    assert chosen.value_of("wheels") is chosen.values[1] and chosen.value_of("ahrs") is None
