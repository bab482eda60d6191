"""Chi-square quantiles and the bands built from them, in one place: the sensors' verdicts, the
EKF's innovation gate, the robust kernels' default thresholds and the NEES intervals of the
evaluation all take theirs from here; and the lag-one correlation of residuals in time order."""
from __future__ import annotations

import math

import numpy as np

from factors.errors import InputError


def chi2_quantile(p: float, dof: float) -> float:
    """The ``x`` with ``P(X <= x) = p`` for ``X`` chi-square with ``dof`` degrees of freedom (0 at
    ``p = 0``, inf at ``p = 1``); an InputError for ``p`` outside [0, 1] or ``dof`` not a positive
    finite number. SciPy's: ``2 gammaincinv(dof / 2, p)``, the inverse regularised incomplete gamma
    function that ``scipy.stats.chi2.ppf`` evaluates, bit for bit. It is imported from
    ``scipy.special`` at the first call: every run with aiding sensors needs quantiles (the
    sensors' verdicts), and ``scipy.stats`` takes about five times as long to import."""
    dof = float(dof)
    if not (math.isfinite(dof) and dof > 0):
        raise InputError(f"dof: expected degrees of freedom > 0, got {dof!r}")
    p = float(p)
    if not 0.0 <= p <= 1.0:
        raise InputError(f"p: expected a probability in [0, 1], got {p!r}")
    from scipy.special import gammaincinv

    return float(2.0 * gammaincinv(0.5 * dof, p))


def nees_bounds(dim: int, runs: int = 1, confidence: float = 0.95) -> tuple[float, float]:
    """Two-sided ``confidence`` interval for the NEES of dimension ``dim`` averaged over ``runs``
    independent runs (at one time step): ``[q((1-c)/2), q((1+c)/2)] / runs`` with ``q`` the
    quantile of chi-square with ``runs * dim`` degrees of freedom."""
    if int(dim) != dim or dim < 1 or int(runs) != runs or runs < 1:
        raise InputError(f"nees_bounds: expected dim >= 1 and runs >= 1 (integers), got {dim!r}, {runs!r}")
    if not 0.0 < confidence < 1.0:
        raise InputError(f"confidence: expected a probability in (0, 1), got {confidence!r}")
    dof = dim * runs
    alpha = 1.0 - confidence
    return chi2_quantile(0.5 * alpha, dof) / runs, chi2_quantile(1.0 - 0.5 * alpha, dof) / runs


def per_dof_band(dof: float, probability: float) -> tuple[float, float]:
    """The two-sided ``probability`` interval of a chi-square variable with ``dof`` degrees of
    freedom divided by ``dof`` (the band of a mean squared normalised error per degree of
    freedom for a model that fits)."""
    lo = chi2_quantile(0.5 * (1 - probability), dof) / dof
    hi = chi2_quantile(0.5 * (1 + probability), dof) / dof
    return lo, hi


def dof_means_apart(first: float, first_dof: float, second: float, second_dof: float, ratio: float,
                    sigmas: float) -> float:
    """``log(second / first)`` of two means per degree of freedom of chi-square variables (with
    ``first_dof`` and ``second_dof`` degrees of freedom) where it exceeds both ``log(ratio)`` and
    ``sigmas`` of its standard deviation, ``sqrt(2 / first_dof + 2 / second_dof)`` (each mean's
    relative variance is ``2 / dof``), in either direction; 0 where it does not."""
    apart = math.log(second / first)
    bound = max(math.log(ratio), sigmas * math.sqrt(2.0 / first_dof + 2.0 / second_dof))
    return apart if abs(apart) > bound else 0.0


def lag_one_correlation(u: np.ndarray) -> float:
    """The lag-one correlation of whitened residuals ``u (N, d)`` in time order, over their axes
    together (0 with fewer than three)."""
    u = np.asarray(u, dtype=float)
    if len(u) < 3:
        return 0.0
    u = u - u.mean(axis=0)
    denominator = float(np.sum(u * u))
    return float(np.sum(u[1:] * u[:-1]) / denominator) if denominator > 0.0 and math.isfinite(denominator) else 0.0
