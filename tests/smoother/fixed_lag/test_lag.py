"""The lag of a fixed-lag smoother (:mod:`smoother.fixed_lag.lag`): one check and one message wherever a
lag is given (every window, the offline driver, the online smoother, the command line), and the
rule it must meet -- the warning when absolute measurements are further apart, which names the gap
and a lag that reaches it."""
from __future__ import annotations

from dataclasses import replace

import estimator_cases as cases
import numpy as np
import pytest

from factors.errors import InputError
from smoother.cli import main
from smoother.fixed_lag.kinds import FIXED_LAG_KINDS
from smoother.fixed_lag.lag import check_lag, measured_gap, sparse_measurement_warning
from smoother.fixed_lag.offline import run_fixed_lag
from smoother.fixed_lag.windows import make_window
from smoother.model.problem import build_problem
from smoother.online.smoother import OnlineSmoother

BAD_LAGS = [0.0, -1.0, float("nan"), float("inf")]


@pytest.mark.parametrize("lag", BAD_LAGS)
@pytest.mark.parametrize("kind", FIXED_LAG_KINDS)
def test_every_window_and_driver_refuses_a_lag_that_is_not_a_positive_finite_number(lag, kind, gentle):
    message = rf"lag_s: expected a lag in seconds > 0 \(finite\), got {lag!r}"
    with pytest.raises(InputError, match=message):
        make_window(lag, kind)
    with pytest.raises(InputError, match=message):
        run_fixed_lag(cases.problem(gentle), lag, kind)
    data = cases.dataset(gentle)
    with pytest.raises(InputError, match=message):
        OnlineSmoother(data.initial, data.initial_cov, data.noise, lag_s=lag, kind=kind)


@pytest.mark.parametrize("command", ["run", "crosscheck", "fleet"])
def test_the_command_line_refuses_a_bad_lag_with_the_same_message(command, capsys, tmp_path):
    """``--lag`` is checked by the same function before any work starts: one line, exit code 2."""
    argv = {"run": ["run", "--duration", "1", "--out", str(tmp_path)],
            "crosscheck": ["crosscheck", "--seeds", "2", "--duration", "1"],
            "fleet": ["fleet", str(tmp_path / "rig.toml"), "--out", str(tmp_path)]}[command]
    assert main(argv + ["--lag", "-1"]) == 2
    assert capsys.readouterr().err == "smoother: error: --lag: expected a lag in seconds > 0 (finite), got -1.0\n"


def test_check_lag_returns_the_lag_as_a_float_and_names_what_was_given():
    assert check_lag(np.float32(0.5)) == 0.5 and type(check_lag(2)) is float
    with pytest.raises(InputError, match=r"window: expected a lag in seconds > 0 \(finite\), got 'two'"):
        check_lag("two", "window")


def test_an_unknown_kind_is_refused_naming_every_kind(gentle):
    with pytest.raises(InputError, match=r"kind 'window': expected one of sliding, incremental, batch"):
        run_fixed_lag(cases.problem(gentle), 1.0, "window")


def test_the_lag_warning_tells_a_gap_from_the_lag_and_suggests_a_lag_that_reaches_it():
    """A gap of 2.0019 s beside a 2-s lag is not printed as "2 s", and the lag suggested is rounded
    up, never below the gap."""
    text = sparse_measurement_warning(2.0019, 2.0, "sliding")
    assert "up to 2.002 s apart" in text and "at least 2.002 s" in text
    suggested = float(sparse_measurement_warning(4.0012, 2.0, "sliding").split("at least ")[1].split(" s")[0])
    assert suggested >= 4.0012
    assert sparse_measurement_warning(2.0, 2.0, "sliding") is None


def test_a_problem_without_absolute_measurements_is_one_gap(gentle):
    """Nothing fixes a position or an attitude: the whole run is dead reckoning, one gap from the
    first keyframe to the last, as the online smoother counts it (and the warning names it)."""
    problem = build_problem(replace(cases.dataset(gentle), sensors=()))
    assert measured_gap(problem) == problem.times[-1] - problem.times[0] == 4.0
    assert "up to 4 s apart" in sparse_measurement_warning(measured_gap(problem), 2.0, "sliding")
    assert measured_gap(cases.problem(gentle)) == pytest.approx(0.1)
