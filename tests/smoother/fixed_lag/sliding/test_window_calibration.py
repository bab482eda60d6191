"""Calibration variables in the sliding window: the dense border of its banded system
(:mod:`smoother.fixed_lag.sliding.calibration`), kept across updates and marginalisations, against a
solve of the whole bordered system made from scratch; the online smoother's ``calibrate``."""
from __future__ import annotations

import warnings

import numpy as np
import pytest
from banded_cases import dense
from miscalibrated_rig import miscalibrated_rig

from factors import so3
from factors.calibration import CalibrationPrior
from factors.errors import InputError
from smoother.fixed_lag.sliding import kernels
from smoother.fixed_lag.sliding import window as sw
from smoother.fixed_lag.windows import make_window
from smoother.online.replay import replay
from smoother.online.smoother import OnlineSmoother, SensorSetup

DIM = sw.DIM


def _calibrating_rig(duration: float):
    data = miscalibrated_rig(1, duration=duration)
    data = data.with_sensor("wheels", calibrate=CalibrationPrior(("rotation", "scale")))
    return data.with_sensor("gnss", calibrate=CalibrationPrior(("time_offset", "lever_arm")))


def _bordered(Hb, g, border):
    """The dense symmetric bordered matrix ``[A B; B^T D]`` and right-hand side of a window."""
    B, D, gc = border
    A = dense(Hb)
    N = A.shape[0]
    H = np.block([[A, B.reshape(N, -1)], [B.reshape(N, -1).T, D]])
    return H, np.concatenate([g, gc])


def test_the_bordered_window_is_the_whole_bordered_system_solved_from_scratch(monkeypatch):
    """After each update whose rows are all up to date -- the border's rows of the factor kept
    from the oldest change on, keyframes marginalised into bordered priors without a new
    factorisation -- the keyframes' and the calibrations' offsets solve the whole window's
    bordered normal equations at the linearisation points, made from scratch, to a backward
    error below 1e-14 (a calibration 1 % off gives 1e-13 and more: the system's condition number
    is ~1e13, so comparing against a dense solve would measure the dense solve's rounding), and
    the newest keyframe's, one inside the window's and the calibrations' marginal covariances are
    the blocks of its inverse (to 2e-3; the calibrations' share of the keyframe's, which a window without the
    border would leave out, is tens of times that). Halfway, before an update that keeps the rows
    before its change, the window moves to a ring of twice the slots (as when it outgrows its
    ring): the factor's rows, the border's and their products go with it. After each
    factorisation the border's products ``Z_k^T [Z_k, y_k]`` kept by slot are those of its rows
    over the whole window."""
    data = _calibrating_rig(15.0)
    checked, grown, kept_rows = [], [], []
    solve, factorise = sw.SlidingWindow._solve, kernels.factorise_forward_border

    def factorise_and_check_products(Hr, g, L, y, first, start, newest, cap, S, Z, ZZ, *rest):
        out = factorise(Hr, g, L, y, first, start, newest, cap, S, Z, ZZ, *rest)
        if out[0] < 0:
            slots = np.arange(first, newest + 1) % cap
            nc = Z.shape[2]
            want = np.einsum("kpa,kpb->kab", Z[slots], np.concatenate([Z[slots], y[slots]], axis=2))
            lower = np.tril(np.ones((nc, nc + 1), dtype=bool))
            got = ZZ[slots][:, lower]
            assert np.allclose(got, want[:, lower], rtol=1e-12, atol=1e-12 * np.abs(want).max())
            kept_rows.append(start > first)
        return out

    monkeypatch.setattr(sw, "factorise_forward_border", factorise_and_check_products)

    def solve_and_check(window, t):
        shortened = window.shortened
        keeps_rows = min(window._stale, window.newest - window._bandwidth()) > window.first
        if window._cal is not None and not grown and t > 7.5 and keeps_rows:
            window._allocate_keyframes(2 * window._cap)
            grown.append(len(checked))
        solve(window, t)
        valid = min(window._stale, window.newest + 1) - window.first
        n = window.newest - window.first + 1
        if window._cal is None or valid != n or window.shortened != shortened:
            return  # (the kernels' warm-up window has no calibration)
        kept = [a.copy() for a in (window._kept, window._kH, window._kg, window._kB, window._mD, window._mg)]
        window._kept[:] = False  # every measurement linearised anew, what the window keeps left as it was
        Hb, g, border = window._normal_equations(window.first, window.newest + 1, n, window._S)
        for a, b in zip((window._kept, window._kH, window._kg, window._kB, window._mD, window._mg), kept):
            a[...] = b
        H, rhs = _bordered(Hb, g, border)
        slots = np.arange(window.first, window.newest + 1) % window._cap
        got = np.concatenate([window._dx[slots, :, 0].ravel(), window._cal.delta])
        scale = np.abs(H).sum(axis=1).max() * np.abs(got).max() + np.abs(rhs).max()
        assert np.abs(H @ got + rhs).max() < 1e-14 * scale
        cov = np.linalg.inv(H)
        newest = slice((n - 1) * DIM, n * DIM)
        window_cov = window.covariances([window.newest])[0]
        size = np.abs(cov[newest, newest]).max()
        assert np.abs(window_cov - cov[newest, newest]).max() < 2e-3 * size
        middle = n // 2  # the solves from a keyframe inside the window on
        got_middle = window.covariances([window.first + middle, window.newest])[0]
        reference = cov[middle * DIM:(middle + 1) * DIM, middle * DIM:(middle + 1) * DIM]
        assert np.abs(got_middle - reference).max() < 2e-3 * np.abs(reference).max()
        share = window_cov - np.linalg.inv(H[:n * DIM, :n * DIM])[newest, newest]
        cal = window._cal
        for (a, b), block in zip(zip(cal.offsets[:-1], cal.offsets[1:]), cal.covariance()):
            reference = cov[n * DIM + a:n * DIM + b, n * DIM + a:n * DIM + b]
            assert np.abs(block - reference).max() < 2e-3 * np.abs(reference).max()
        bordered = sum(p.c_lin is not None for p in window._priors)
        checked.append((bordered, cal.relinearised, np.abs(share).max() / size))

    sw.SlidingWindow._solve = solve_and_check
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            replay(data, 1.0, "sliding", covariances=False, progress=False)
    finally:
        sw.SlidingWindow._solve = solve
    assert len(checked) > 20, len(checked)
    assert max(p for p, _, _ in checked) > 0  # bordered marginal priors in the window
    assert checked[-1][1] > 0  # the calibrations were linearised again on the way
    assert max(s for _, _, s in checked) > 0.05
    assert grown and len(checked) > grown[0] + 20, (grown, len(checked))
    assert sum(kept_rows) > 20  # products kept from earlier factorisations were checked


def test_a_gtsam_fixed_lag_smoother_refuses_calibrations_naming_the_sensors():
    data = _calibrating_rig(2.0)
    online = OnlineSmoother.for_dataset(data, kind="sliding")
    asked = online._window._cal
    with pytest.raises(InputError, match="kind 'incremental' cannot estimate calibrations .*wheels, gnss"):
        make_window(1.0, "incremental", data.gravity, 1e-3, asked)
    # a dataset replayed through GTSAM's smoother: the values given, no variables
    assert OnlineSmoother.for_dataset(data, kind="incremental").calibration is None


def test_sensor_setup_checks_what_it_is_to_calibrate():
    with pytest.raises(InputError, match="SensorSetup.calibrate: a gnss sensor cannot estimate rotation"):
        SensorSetup("gnss", calibrate=CalibrationPrior(("rotation",)))
    with pytest.raises(InputError, match="SensorSetup.calibrate: expected a factors.calibration.CalibrationPrior"):
        SensorSetup("gnss", calibrate=("time_offset",))
    with pytest.raises(InputError, match="stamp_offset 0.2 differs from time_offset 0.1"):
        SensorSetup("gnss", time_offset=0.1, calibrate=CalibrationPrior(("time_offset",), stamp_offset=0.2))
    # the offset its stamps get is the one the estimate is reported beyond
    setup = SensorSetup("gnss", time_offset=0.1, calibrate=CalibrationPrior(("time_offset",)))
    assert setup.calibrate.stamp_offset == 0.1


def test_a_calibration_information_that_fails_stops_the_update_naming_the_calibrations(monkeypatch):
    """The calibrations' Schur complement refused at the tenth update (as a numerically singular
    one would be): the update stops with one line naming the calibrations, the window's offsets
    as the ninth left them (not its forward solution)."""
    from smoother.fixed_lag.contract import FixedLagFailed

    data = _calibrating_rig(3.0)
    factorise_forward_border, after = kernels.factorise_forward_border, []
    solve_once = sw.SlidingWindow._solve_once

    def refusing_the_tenth(Hr, g, L, y, first, start, newest, *rest):
        return (-1, -1) if newest == 9 else factorise_forward_border(Hr, g, L, y, first, start, newest, *rest)

    def recording(window):
        out = solve_once(window)
        after.append(window._dx.copy())
        return out

    monkeypatch.setattr(sw, "factorise_forward_border", refusing_the_tenth)
    monkeypatch.setattr(sw.SlidingWindow, "_solve_once", recording)
    online = OnlineSmoother.for_dataset(data, lag_s=1.0)
    online.keyframe_at(data.imu.t[0] + 0.05 * np.arange(20))
    with pytest.raises(FixedLagFailed, match="the calibrations of wheels, gnss have an information that is not"):
        online.add_imu(data.imu.t, data.imu.acc, data.imu.gyro)
    assert online._window.newest == 9 and np.abs(after[-1]).max() > 0
    np.testing.assert_array_equal(online._window._dx, after[-1])


def test_a_calibrated_time_offset_without_the_imu_reading_is_refused():
    data = _calibrating_rig(2.0)
    online = OnlineSmoother.for_dataset(data, lag_s=1.0)
    window = online._window
    with pytest.raises(InputError, match="a calibrated time offset needs the IMU reading held"):
        window.add_keyframe(0.0, data.initial, prior=(data.initial, data.initial_cov))


def _tied_through_the_calibration(lag_s: float, duration: float, late: bool = False, bare_every: int = 0,
                                  after_update=None):
    """A window fed keyframes at the wheels' 10 Hz with no IMU between them, each with a prior
    about its true state and one wheel-speed reading through the calibrated rotation and scale
    (``late``: every third update also the previous reading, on the keyframe before;
    ``bare_every``: every so many keyframes without its reading; ``after_update(window)`` called
    after each update)."""
    from factors.calibration import CalibrationSet
    from smoother.fixed_lag.sliding.calibration import WindowCalibration
    from smoother.model.problem import measurement_spec

    data = miscalibrated_rig(2, duration=duration)
    prior = CalibrationPrior(("rotation", "scale"))
    calibrations = WindowCalibration(CalibrationSet.given(["wheels"], [np.eye(4)], [prior]), {"wheels": "velocity"})
    window = sw.SlidingWindow(lag_s, calibration=calibrations)
    wheels = data.sensor("wheels").data
    spec = measurement_spec(data.sensor("wheels"))
    truth, _, inside = data.truth.interpolate(wheels.t)
    assert inside.all()
    cov = np.diag(np.r_[[0.1] * 3, [0.05] * 3, [0.01] * 3, [0.05] * 3, [0.01] * 3] ** 2)
    calibration_only = 0
    for m, t in enumerate(wheels.t):
        window.taken(window.leaving(float(t)))
        readings = [] if bare_every and m % bare_every == 1 else [(spec, m, [window.newest + 1], None)]
        if late and m % 3 == 2:
            readings.append((spec, m - 1, [window.newest], None))
        window.add_keyframe(float(t), truth[m], None, readings, prior=(truth[m], cov))
        calibration_only += any(p.keyframes.size == 0 for p in window._priors)
        if after_update is not None:
            after_update(window)
    return window, calibration_only


def test_keyframes_tied_only_through_a_calibration_leave_a_prior_on_it_alone():
    """Each leaving keyframe informs no keyframe left, only the calibration: its marginal is a
    prior on the calibration alone (spanning no keyframes), kept until it joins the next marginal.
    The calibration after 6 s with a 0.5 s lag is that of a window that keeps every keyframe, to
    0.1 of its sigma (the marginals keep their linearisation points; a window that keeps every
    keyframe moves them), and so is its covariance, to 0.05 of the products of the sigmas."""
    short, calibration_only = _tied_through_the_calibration(0.5, 6.0)
    whole, _ = _tied_through_the_calibration(100.0, 6.0)
    assert short.first > 50 and whole.first == 0
    assert calibration_only > 50
    (got,), (cov,) = short.calibration[0].values, short.calibration[1]
    (want,), (cov_whole,) = whole.calibration[0].values, whole.calibration[1]
    sigma = np.sqrt(np.diag(cov_whole))
    difference = np.r_[so3.log(got.R @ want.R.T), got.scale - want.scale]
    assert np.all(np.abs(difference) < 0.1 * sigma), difference / sigma
    assert (np.abs(cov - cov_whole) / np.outer(sigma, sigma)).max() < 0.05


def test_relinearising_the_calibrations_less_often_stays_close_to_relinearising_everything(monkeypatch):
    """The default thresholds -- a calibration linearised again once its offset exceeds its
    threshold and half its marginal sigma -- against relinearising every keyframe and every
    calibration at every update: the keyframes and the calibrations within 0.2 of their sigmas
    (measured 0.14 and 0.15; half a sigma's worth of offset is what keeps it there: at 5 sigmas
    0.37 and 0.46), with fewer than 0.6 of the relinearisations of the thresholds alone (measured
    27 against 59 on these 15 s, which begin with every calibration at its prior). After an
    update each coordinate's limit is the larger of its threshold and half its marginal sigma."""
    import estimator_cases as cases

    from factors.calibration import prior_residual
    from smoother.fixed_lag.sliding import calibration as wc

    data = _calibrating_rig(15.0)
    made = []
    init = wc.WindowCalibration.__init__

    def recorded(calibrations, *args):
        init(calibrations, *args)
        made.append(calibrations)

    def run(fraction, thresholds=(sw.RELINEARISATION_THRESHOLD, wc.CALIBRATION_RELINEARISATION_THRESHOLD)):
        monkeypatch.setattr(sw, "RELINEARISATION_SIGMA_FRACTION", fraction)
        monkeypatch.setattr(sw, "RELINEARISATION_THRESHOLD", thresholds[0])
        monkeypatch.setattr(wc, "CALIBRATION_RELINEARISATION_THRESHOLD", thresholds[1])
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            return replay(data, 1.0, "sliding", covariances=True, progress=False), made[-1]

    monkeypatch.setattr(wc.WindowCalibration, "__init__", recorded)
    every, _ = run(0.0, (np.zeros(DIM), np.zeros_like(wc.CALIBRATION_RELINEARISATION_THRESHOLD)))
    default, calibrations = run(wc.RELINEARISATION_SIGMA_FRACTION)
    _, thresholds_alone = run(0.0)
    diff = cases.sigma_difference(default.smoothed.states, every.smoothed.states, every.smoothed.cov)
    assert diff.max() < 0.2, diff.max()
    (values, _), (want, _) = default.calibration, every.calibration
    for got, reference, cov, prior in zip(values.values, want.values, every.calibration[1], want.priors):
        error = prior_residual(got, reference, prior.columns)[0] / np.sqrt(np.diag(cov))
        assert np.abs(error).max() < 0.2, error
    assert 0 < calibrations.relinearised < 0.6 * thresholds_alone.relinearised, (calibrations.relinearised,
                                                                              thresholds_alone.relinearised)
    sigma = np.sqrt(np.diag(calibrations.joint_covariance()))
    limits = np.maximum(calibrations.thresholds, np.minimum(wc.RELINEARISATION_SIGMA_FRACTION * sigma,
                                                            wc.RELINEARISATION_WIDEST * calibrations.thresholds))
    np.testing.assert_allclose(calibrations.limits, limits, rtol=1e-9)
    assert (limits > calibrations.thresholds).any() and (limits == calibrations.thresholds).any()


@pytest.mark.parametrize("lag_s, duration, moves", [(0.5, 8.0, True), (0.5, 8.0, False), (8.0, 9.0, True)])
def test_what_a_window_keeps_of_its_calibrated_measurements_is_what_they_give_made_anew(lag_s, duration, moves,
                                                                                    monkeypatch):
    """The sums a keyframe's calibrated one-keyframe measurements keep for its rows (``_kH``,
    ``_kg``, ``_kB``) against every measurement linearised anew, after every update: the same
    normal equations to rounding -- also when a reading joins a keyframe after its sums were kept
    (every third update, on the keyframe before), as the calibration is linearised again, when a
    keyframe without a reading takes a slot whose sums were kept (a 0.5-s lag: the ring's 64
    slots go round; with the calibration never linearised again, which would clear every sum) and
    when the ring grows (an 8-s lag: 80 keyframes in the window)."""
    from smoother.fixed_lag.sliding import calibration as wc

    if not moves:
        never = np.full_like(wc.CALIBRATION_RELINEARISATION_THRESHOLD, 1e9)
        monkeypatch.setattr(wc, "CALIBRATION_RELINEARISATION_THRESHOLD", never)
        monkeypatch.setattr(wc, "MAX_CALIBRATION_STEP", never)  # nor a long step linearised again
    compared = []

    def compare(window):
        n = window.newest - window.first + 1
        lo, cut = window.first, window.newest + 1
        kept = window._normal_equations(lo, cut, n, window._S)
        saved = [a.copy() for a in (window._kept, window._kH, window._kg, window._kB)]
        window._kept[:] = False
        fresh = window._normal_equations(lo, cut, n, window._S)
        for a, b in zip((window._kept, window._kH, window._kg, window._kB), saved):
            a[...] = b
        for got, want in zip((kept[0], kept[1], *kept[2]), (fresh[0], fresh[1], *fresh[2])):
            np.testing.assert_allclose(got, want, rtol=1e-12, atol=1e-12 * np.abs(want).max())
        compared.append(window._cal.relinearised)

    window, _ = _tied_through_the_calibration(lag_s, duration, late=True, bare_every=5, after_update=compare)
    assert len(compared) > 75 and (compared[-1] > 0) == moves, compared
    assert window.newest >= 64 and (window._cap > 64) == (lag_s > 6.4), (window.newest, window._cap)
