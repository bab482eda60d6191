"""A drifting sensor's correlation time, fitted to half of its held-out measurements and judged by
the other half (a sensor's ``correlation_time = "fit"``, ``smoother run --correlation-time
SENSOR=fit``).

Why held-out measurements. The used measurements alone hardly tell the correlation time: where
they lie further apart than it, consecutive errors share little, and the estimate follows each
one whatever the time (on KITTI, one fix in ten used, the restricted likelihood changes by less
than 1 in ``-2 log L`` from white errors to 20 s). The held-out measurements between them do tell
it: how much of the used measurements' errors a held-out one shares is what the time says
(:mod:`smoother.diagnosis.heldout_correlated`). The density of all the measurements is that of
the used ones times that of the held-out ones given them, so where the first is flat the second
carries the likelihood.

The score. For each candidate time ``tau`` (and white errors) the batch smoother runs as the run
will (its noise fitted where the run fits it, so the sensor's sigma is profiled out), and each
held-out measurement ``z_i`` of the tuning half is predicted given the used measurements (and,
where the errors drift, their errors), ``e_i ~ N(0, S_i)`` in the measurement's units
(:func:`smoother.diagnosis.heldout.heldout_predictions`, :class:`Conditioned`). The score is

    L(tau) = sum_i  log det S_i + e_i^T S_i^-1 e_i

(``-2`` times the log predictive density, without its constant): each term is a proper scoring
rule for the measurement's own prediction, so the sum is least, in expectation, at the time that
predicts them best. It is a composite likelihood: the terms within a gap between two used
measurements are correlated, so differences of ``L`` spread wider than a likelihood ratio's. They
are scaled by ``D / nu`` (``D`` the degrees of freedom of the tuning half, ``nu`` those of its
band, :func:`smoother.diagnosis.heldout.effective_dof`), and the times whose score lies within that
of the least (on the parabola below, where there is one) are the support reported beside the
fitted time: about one standard deviation (for a regular likelihood, a rise of 1 in ``-2 log L``).

The search. Candidates on a grid a factor :data:`COARSE_STEP` apart, from half the sensor's
median spacing (shorter is white at its rate) to the run's span (longer, an offset), and white;
then the best one's neighbours a factor ``sqrt`` of it apart, and the vertex of the parabola in
``log tau`` through the best and its two neighbours; the least of all evaluated is kept.

The halves. The held-out measurements are split by the gap between used measurements they lie in:
odd gaps tune, even ones judge (the errors in one gap share the estimate's error there, so halves
by gap are nearly independent, halves by alternate measurements are not). The tuning half has been
used by the fit and leaves the held-out set (:attr:`datasets.types.Sensor.tuned`: its times stay
keyframes, so the run is the one scored); the run's held-out verdict and held-out RMS are the
judging half's, data no fit has seen. With several sensors to fit, each is fitted in turn, the
ones before it at their fitted times and the ones after it white.
"""
from __future__ import annotations

import math
import time
import warnings
from dataclasses import dataclass
from typing import Callable

import numpy as np

from datasets.kinds import KINDS
from datasets.ranges import RANGES
from datasets.types import Dataset
from factors.errors import BoxplusError, InputError
from smoother.diagnosis.heldout import effective_dof, heldout_predictions
from smoother.progress import progress_bar

#: Neighbouring candidates on the first grid are this factor apart ...
COARSE_STEP = 4.0
#: ... and the fewest gaps with held-out measurements each half needs (fewer: no fit).
MIN_GAPS_PER_HALF = 2
#: The times tried lie within the rig key's range.
TIME_RANGE = RANGES["sensor.correlation_time"]


@dataclass(frozen=True)
class Candidate:
    """One correlation time tried: ``tau`` [s] (None: white errors), its ``score`` (module
    docstring; NaN where the batch failed there, ``failed`` saying why) and whether the batch
    ``converged``."""

    tau: float | None
    score: float
    failed: str | None = None
    converged: bool = True

    def record(self) -> dict:
        out = {"correlation_time_s": self.tau, "score": self.score if math.isfinite(self.score) else None}
        if self.failed is not None:
            out["failed"] = self.failed
        if not self.converged:
            out["converged"] = False
        return out


@dataclass(frozen=True)
class CorrelationFit:
    """The fit of sensor ``sensor``'s correlation time: ``tau`` [s] (None: white errors fit best),
    the ``candidates`` tried in the order tried, ``support`` (the shortest and longest candidate
    within the scaled score's 1 of the least, None for white), the score's ``inflation``
    (``D / nu``), how many held-out measurements ``tuned`` it and how many are left to ``judge``
    the run, ``edge``: ``"longest"`` or ``"shortest"`` where the best candidate is the grid's
    end (the time may lie beyond it), else None, and the ``seconds`` it all took."""

    sensor: str
    tau: float | None
    candidates: tuple
    support: tuple
    inflation: float
    tuned: int
    judge: int
    edge: str | None = None
    seconds: float = 0.0

    def record(self) -> dict:
        """What ``metrics.json`` keeps (``_run.correlation_fit.<sensor>``)."""
        return {"correlation_time_s": self.tau, "support_s": list(self.support), "inflation": self.inflation,
                "tuned_on": self.tuned, "judged_on": self.judge, "edge": self.edge, "seconds": self.seconds,
                "candidates": [c.record() for c in self.candidates]}

    def line(self) -> str:
        """The fit in one line, for the run's report."""
        low, high = self.support
        if self.tau is None:
            value = "white errors fit best" + (f" (up to {high:.3g} s within about one sd)" if high is not None else
                                               ", no time tried within about one sd of them")
        else:
            beyond = {"longest": ", the longest tried: it may be longer",
                      "shortest": ", the shortest tried: it may be shorter"}.get(self.edge, "")
            shortest = "white" if low is None else f"{low:.3g} s"
            value = f"{self.tau:.3g} s ({shortest} to {high:.3g} s within about one sd{beyond})"
        return (f"correlation time of {self.sensor}: {value}; fitted to {self.tuned} held-out measurements (those in "
                f"odd gaps between used ones), the other {self.judge} judge the run")


def fit_correlation_times(dataset: Dataset, solve: Callable, progress: bool | None = None
                          ) -> tuple[list[CorrelationFit], Dataset]:
    """Each sensor of ``dataset`` whose correlation time is to be fitted
    (:attr:`datasets.types.Dataset.correlation_to_fit`), fitted in turn (module docstring):
    ``(fits, dataset)`` with the fitted times and, for those sensors, only the judging half held
    out (the tuning half :attr:`datasets.types.Sensor.tuned`). ``solve(dataset)`` runs the batch
    smoother as the run will and returns its :class:`smoother.pipeline.Estimate` (trajectory,
    calibration, following, held-out predictions of drifting sensors, noise fit); its warnings are
    the candidates' own and are not repeated.
    An InputError, naming the sensor, where either half has held-out measurements in fewer than
    :data:`MIN_GAPS_PER_HALF` gaps, or where every candidate failed."""
    fits = []
    for name in dataset.correlation_to_fit:
        fit, dataset = _fit_one(dataset, name, solve, progress)
        fits.append(fit)
    return fits, dataset


def tuning_half(held_t: np.ndarray, used_t: np.ndarray) -> np.ndarray:
    """Which held-out measurements (times ``held_t``) tune: those in odd gaps between the used
    measurements (times ``used_t``; the gap before the first is 0)."""
    return np.searchsorted(np.sort(used_t), held_t) % 2 == 1


def candidate_grid(times: np.ndarray) -> list[float]:
    """The first grid of correlation times [s] for measurements at ``times`` (module docstring),
    within the rig key's range."""
    times = np.sort(times)
    steps = np.diff(times)
    steps = steps[steps > 0.0]
    first = max(0.5 * float(np.median(steps)) if len(steps) else TIME_RANGE.low, TIME_RANGE.low)
    last = min(max(float(times[-1] - times[0]), first), TIME_RANGE.high)
    count = int(math.floor(math.log(last / first) / math.log(COARSE_STEP) + 1e-9)) + 1
    return [first * COARSE_STEP ** k for k in range(count)]


def _fit_one(dataset: Dataset, name: str, solve: Callable, progress: bool | None) -> tuple[CorrelationFit, Dataset]:
    """:func:`fit_correlation_times` of sensor ``name``."""
    tick = time.perf_counter()
    sensor = dataset.sensor(name)
    tune = tuning_half(sensor.heldout.t, sensor.data.t)
    gaps = np.searchsorted(np.sort(sensor.data.t), sensor.heldout.t)
    for half, mask in (("tuning", tune), ("judging", ~tune)):
        if len(np.unique(gaps[mask])) < MIN_GAPS_PER_HALF:
            raise InputError(f"sensor {name!r}: correlation_time: fitting it needs held-out measurements in at least "
                             f"{2 * MIN_GAPS_PER_HALF} gaps between used ones ({MIN_GAPS_PER_HALF} to fit it, as many "
                             f"to judge it); the {half} half has them in {len(np.unique(gaps[mask]))}")
    grid = candidate_grid(np.concatenate([sensor.data.t, sensor.heldout.t]))
    base = dataset.with_sensor(name, fit_correlation_time=False, correlation_time=None)
    tried: dict = {}  # tau -> (Candidate, the tuning half's normalised errors and gaps)
    with progress_bar(len(grid) + 4, f"fitting {name}'s correlation time", progress) as bar:
        def attempt(taus) -> None:
            for tau in taus:
                if tau not in tried:
                    tried[tau] = _scored(base, name, tau, tune, gaps, solve)
                    bar.update(1)

        attempt([None, *grid])
        best = _least(tried)
        if best is not None:  # between the grid's neighbours, then the parabola's vertex
            attempt(t for t in (best / math.sqrt(COARSE_STEP), best * math.sqrt(COARSE_STEP)) if t in TIME_RANGE)
            attempt(_vertex(tried))
    tau = _least(tried)
    if not math.isfinite(tried[tau][0].score):
        raise InputError(f"sensor {name!r}: correlation_time: the batch smoother failed at every time tried (white: "
                         f"{tried[None][0].failed})")
    best, nis, at = tried[tau]
    d = KINDS[sensor.kind].dim
    inflation = d * len(nis) / effective_dof(nis, d, at)
    support = _support(tried, tau, inflation)
    numbers = sorted(t for t in tried if t is not None)
    edge = None if tau is None else "longest" if tau == numbers[-1] else "shortest" if tau == numbers[0] else None
    fit = CorrelationFit(name, tau, tuple(c for c, _, _ in tried.values()), support, inflation, int(tune.sum()),
                         int((~tune).sum()), edge, time.perf_counter() - tick)
    return fit, base.with_sensor(name, correlation_time=tau, heldout=sensor.heldout.subset(~tune),
                                 tuned=sensor.heldout.subset(tune))


def _least(tried: dict) -> float | None:
    """The correlation time of least finite score among the numbers tried (None: none finite, or
    white's is less)."""
    numbers = [t for t, (c, _, _) in tried.items() if t is not None and math.isfinite(c.score)]
    if not numbers:
        return None
    best = min(numbers, key=lambda t: tried[t][0].score)
    white = tried.get(None)
    return None if white is not None and white[0].score < tried[best][0].score else best


def _parabola(tried: dict) -> tuple | None:
    """``(a, b, c)`` of the parabola ``a x^2 + b x + c`` in ``x = log tau`` through the best time
    tried and its neighbours among those tried; None where it has fewer than two or the parabola
    opens down."""
    best = _least(tried)
    numbers = sorted(t for t, (c, _, _) in tried.items() if t is not None and math.isfinite(c.score))
    if best is None or best in (numbers[0], numbers[-1]):
        return None
    i = numbers.index(best)
    a, b, c = np.polyfit(np.log(numbers[i - 1:i + 2]), [tried[t][0].score for t in numbers[i - 1:i + 2]], 2)
    return (a, b, c) if a > 0.0 else None


def _vertex(tried: dict) -> list[float]:
    """The vertex of :func:`_parabola`, to try (none without one, or where it is a time tried)."""
    parabola = _parabola(tried)
    if parabola is None:
        return []
    vertex = float(np.exp(-parabola[1] / (2.0 * parabola[0])))
    return [vertex] if min(abs(math.log(vertex / t)) for t in tried if t is not None) > 1e-2 else []


def _support(tried: dict, tau: float | None, inflation: float) -> tuple:
    """``(shortest, longest)`` correlation time whose score lies within ``inflation`` of the
    least's (``tau``'s; None: white): on :func:`_parabola` where it has one, else among the times
    tried, and at least those tried within it."""
    least = tried[tau][0].score
    within = [t for t, (c, _, _) in tried.items() if c.score <= least + inflation]
    times = sorted(t for t in within if t is not None)
    low, high = (None if None in within else times[0]), (times[-1] if times else None)
    parabola = _parabola(tried)
    if parabola is not None and tau is not None:
        a, b, _ = parabola
        half = math.sqrt(inflation / a)
        centre = -b / (2.0 * a)
        low = None if low is None else min(low, math.exp(centre - half))  # white within: the support reaches it
        high = max(high, math.exp(centre + half))
    return low, high


def _scored(base: Dataset, name: str, tau: float | None, tune: np.ndarray, gaps: np.ndarray, solve: Callable) -> tuple:
    """``(Candidate, nis, gaps)``: the batch smoother run with sensor ``name``'s correlation time
    ``tau`` and its tuning half's score (module docstring), with the tuning half's normalised
    errors and their gaps. A batch that fails there is a candidate of NaN score."""
    dataset = base.with_sensor(name, correlation_time=tau)
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")  # a candidate's: the run says the chosen one's
            estimate = solve(dataset)
            ran = dataset if estimate.noise is None else estimate.noise.applied(dataset)
            index, nis, log_det = _predicted(ran, name, estimate)
    except (BoxplusError, np.linalg.LinAlgError) as error:  # the factors refuse the time, the solver fails there
        return Candidate(tau, math.nan, " ".join(str(error).split())), np.zeros(0), np.zeros(0, dtype=int)
    part = tune[index] & np.isfinite(nis) & np.isfinite(log_det)
    converged = bool(estimate.details.get("converged", True))
    if not part.any():
        return (Candidate(tau, math.nan, "no held-out measurement of the tuning half predicted", converged),
                np.zeros(0), np.zeros(0, dtype=int))
    # the mean over those predicted, for as many as the half holds: comparable where a few fall outside the span
    score = float(np.mean(nis[part] + log_det[part])) * int(tune.sum())
    return Candidate(tau, score, None, converged), nis[part], gaps[index][part]


def _predicted(dataset: Dataset, name: str, estimate) -> tuple:
    """``(index, nis, log det S)`` of sensor ``name``'s held-out measurements as ``estimate``
    (run on ``dataset``) predicts them: given the used measurements' errors where they drift
    (:class:`smoother.model.predicted.Conditioned`, whitened: ``log det S`` in the measurement's
    units adds ``log det R``), else through the state's covariance plus ``R``."""
    held = dataset.sensor(name).heldout
    own = (estimate.heldout or {}).get(name)
    if own is not None and own.conditioned is not None:
        e, S = own.conditioned.e, own.conditioned.state_part + own.conditioned.noise
        units = np.linalg.slogdet(held.cov[own.index])[1]
    else:
        own = heldout_predictions(dataset, estimate.trajectory, estimate.calibration, estimate.following,
                                  sensors=[name])[name]
        e, S, units = own.e, own.state_part + held.cov[own.index], 0.0
    sign, log_det = np.linalg.slogdet(S)
    nis = np.einsum("ma,ma->m", e, np.linalg.solve(S, e[..., None])[..., 0])
    return own.index, np.where(sign > 0, nis, np.nan), log_det + units
