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
predicts them best. Where the run fits the sensor's noise, its sigma is fitted at each time and
applied however near the rig's value it settles (:attr:`smoother.pipeline.RunOptions.profiled_noise`):
a sigma that snapped back to the rig's at some times and not at others would make ``L`` jump.

The support. ``L`` is a composite likelihood: its terms are correlated within a gap between used
measurements and, through the drift and the estimate's own errors, across gaps, so its
differences spread wider than a likelihood ratio's. How far a time ``tau`` lies behind the best
``tau*`` is read from the difference of their terms, measurement by measurement, ``d_i``, whose
sum's variance is estimated from the sums over :func:`blocks` of the run (each longer than twice
either time, so that the blocks are nearly independent; at least :data:`MIN_BLOCKS`): a time is
within about one standard deviation of the best where ``sum d_i <= sd / 2``. (Near the best,
``L`` rises as ``a delta^2`` and its noise as ``g delta``; the fitted time's sandwich standard
deviation is ``sd(g) / 2a``, the ``delta`` at which the rise is half the noise.) The support is
the range of times tried so within, white included where it is.

The search. White errors and a grid a factor :data:`COARSE_STEP` apart, from half the sensor's
median spacing (shorter is white at its rate) to the run's span, carried on beyond either end
while the score keeps falling there (within the rig key's range, :data:`TIME_RANGE`: a time at
its end is said to be one); then the best one's neighbours a factor ``sqrt`` of it apart, and the
vertex of the parabola in ``log tau`` through the best and its two neighbours, where it lies
between them; the least of all evaluated is kept.

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
from typing import Callable, NamedTuple

import numpy as np

from datasets.ranges import RANGES
from datasets.types import Dataset
from factors.errors import BoxplusError, InputError, InternalError
from smoother.diagnosis.heldout import heldout_predictions, judged_errors
from smoother.progress import progress_bar

#: Neighbouring candidates on the first grid are this factor apart ...
COARSE_STEP = 4.0
#: ... and the fewest gaps with held-out measurements each half needs (fewer: no fit).
MIN_GAPS_PER_HALF = 2
#: The support's blocks (:func:`blocks`): at least this many, ...
MIN_BLOCKS = 4
#: ... at most this many.
MAX_BLOCKS = 20
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
    the ``candidates`` tried in the order tried, ``support`` (the shortest and longest time tried
    within about one standard deviation of it, :func:`support`; None for white), how many held-out
    measurements ``tuned`` it and how many are left to ``judge`` the run, ``edge``: ``"longest"``
    or ``"shortest"`` where it is the end of the rig key's range (the time may lie beyond it),
    else None, the ``seconds`` it all took, and whether the score is ``rough`` in the time
    (:func:`support`)."""

    sensor: str
    tau: float | None
    candidates: tuple
    support: tuple
    tuned: int
    judge: int
    edge: str | None = None
    seconds: float = 0.0
    rough: bool = False

    def record(self) -> dict:
        """What ``metrics.json`` keeps (``_run.correlation_fit.<sensor>``)."""
        return {"correlation_time_s": self.tau, "support_s": list(self.support), "tuned_on": self.tuned,
                "judged_on": self.judge, "edge": self.edge, "rough": self.rough, "seconds": self.seconds,
                "candidates": [c.record() for c in self.candidates]}

    def line(self) -> str:
        """The fit in one line, for the run's report."""
        low, high = self.support
        if self.tau is None:
            value = "white errors fit best" + (f" (up to {high:.3g} s within about one sd)" if high is not None else
                                               ", no time tried within about one sd of them")
        else:
            beyond = {"longest": ", the range's longest: it may be longer",
                      "shortest": ", the range's shortest: it may be shorter"}.get(self.edge, "")
            shortest = "white" if low is None else f"{low:.3g} s"
            value = f"{self.tau:.3g} s ({shortest} to {high:.3g} s within about one sd{beyond})"
        rough = ("; NOT SMOOTH: a time inside that range scores clearly worse (the noise fit or the model errors "
                 "it finds change from one time to the next), so the time is known less well than the range says"
                 if self.rough else "")
        return (f"correlation time of {self.sensor}: {value}; fitted to {self.tuned} held-out measurements (those in "
                f"odd gaps between used ones), the other {self.judge} judge the run{rough}")


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
    if sensor.heldout is None or sensor.data is None:  # all of them outside the IMU's span, say
        raise InputError(f"sensor {name!r}: correlation_time: fitting it needs measurements used and held out within "
                         "the IMU's span; it has " + ("none held out" if sensor.heldout is None else "none used"))
    tune = tuning_half(sensor.heldout.t, sensor.data.t)
    gaps = np.searchsorted(np.sort(sensor.data.t), sensor.heldout.t)
    for half, mask in (("tuning", tune), ("judging", ~tune)):
        if len(np.unique(gaps[mask])) < MIN_GAPS_PER_HALF:
            raise InputError(f"sensor {name!r}: correlation_time: fitting it needs held-out measurements in at least "
                             f"{2 * MIN_GAPS_PER_HALF} gaps between used ones ({MIN_GAPS_PER_HALF} to fit it, as many "
                             f"to judge it); the {half} half has them in {len(np.unique(gaps[mask]))}")
    grid = candidate_grid(np.concatenate([sensor.data.t, sensor.heldout.t]))
    base = dataset.with_sensor(name, fit_correlation_time=False, correlation_time=None)
    tried: dict = {}  # tau -> Scored
    with progress_bar(len(grid) + 4, f"fitting {name}'s correlation time", progress) as bar:
        def attempt(taus) -> None:
            for tau in taus:
                if tau not in tried:
                    tried[tau] = _scored(base, name, tau, tune, solve)
                    bar.update(1)

        attempt([None, *grid])
        for step in (COARSE_STEP, 1.0 / COARSE_STEP):  # on beyond an end while the score falls there
            while (best := least(_scores(tried))) is not None and best == _ends(tried)[step > 1.0] \
                    and best * step in TIME_RANGE:
                attempt([best * step])
        best = least(_scores(tried))
        if best is not None:  # between the neighbours, then the parabola's vertex
            attempt(t for t in (best / math.sqrt(COARSE_STEP), best * math.sqrt(COARSE_STEP)) if t in TIME_RANGE)
            attempt(vertex(_scores(tried)))
    scores = _scores(tried)
    tau = least(scores)
    if not math.isfinite(scores[tau]):
        raise InputError(f"sensor {name!r}: correlation_time: no time tried predicted its held-out measurements "
                         f"(white: {tried[None].candidate.failed})")
    edge = None
    if tau is not None and tau == _ends(tried)[1] and tau * COARSE_STEP not in TIME_RANGE:
        edge = "longest"
    elif tau is not None and tau == _ends(tried)[0] and tau / COARSE_STEP not in TIME_RANGE:
        edge = "shortest"
    terms = {t: (c.terms, c.times) for t, c in tried.items() if math.isfinite(c.candidate.score)}
    *reach, rough = support(scores, terms, tau)
    fit = CorrelationFit(name, tau, tuple(c.candidate for c in tried.values()), tuple(reach), int(tune.sum()),
                         int((~tune).sum()), edge, time.perf_counter() - tick, rough)
    return fit, base.with_sensor(name, correlation_time=tau, heldout=sensor.heldout.subset(~tune),
                                 tuned=sensor.heldout.subset(tune))


class Scored(NamedTuple):
    """A candidate as scored: the :class:`Candidate` and its tuning half's terms ``log det S_i +
    e_i^T S_i^-1 e_i`` (``terms``) at the measurements' ``times`` (empty where it failed)."""

    candidate: Candidate
    terms: np.ndarray
    times: np.ndarray


def _scores(tried: dict) -> dict:
    """``{tau: score}`` of the candidates tried."""
    return {tau: c.candidate.score for tau, c in tried.items()}


def _ends(tried: dict) -> tuple:
    """The shortest and longest times tried whose score is finite (None, None: none)."""
    numbers = sorted(t for t, c in tried.items() if t is not None and math.isfinite(c.candidate.score))
    return (numbers[0], numbers[-1]) if numbers else (None, None)


def least(scores: dict) -> float | None:
    """The time of least finite score among ``scores`` (``{tau: score}``, None for white errors);
    None where that is white's, or where none is finite."""
    finite = {t: v for t, v in scores.items() if math.isfinite(v)}
    return min(finite, key=lambda t: (finite[t], t is not None)) if finite else None


def parabola(scores: dict) -> tuple | None:
    """``(a, b, neighbours)``: the parabola ``a x^2 + b x + c`` in ``x = log tau`` through the best
    time of ``scores`` (``{tau: score}``) and its two neighbours among the finite ones; None where
    the best has no neighbour on a side or the parabola opens down."""
    best = least(scores)
    numbers = sorted(t for t, v in scores.items() if t is not None and math.isfinite(v))
    if best is None or best in (numbers[0], numbers[-1]):
        return None
    i = numbers.index(best)
    a, b, _ = np.polyfit(np.log(numbers[i - 1:i + 2]), [scores[t] for t in numbers[i - 1:i + 2]], 2)
    return (float(a), float(b), (numbers[i - 1], numbers[i + 1])) if a > 0.0 else None


def vertex(scores: dict) -> list[float]:
    """The vertex of :func:`parabola`, to try: none without one, where it lies outside the best's
    neighbours or at a time tried."""
    fitted = parabola(scores)
    if fitted is None:
        return []
    a, b, (low, high) = fitted
    if not math.log(low) < -b / (2.0 * a) < math.log(high):
        return []
    at = math.exp(-b / (2.0 * a))
    return [at] if min(abs(math.log(at / t)) for t in scores if t is not None) > 1e-2 else []


def blocks(times: np.ndarray, taus) -> np.ndarray:
    """Which block of the run each time of ``times`` falls in for :func:`support`'s comparison of
    the correlation times ``taus`` (None: white): equal spans, each at least twice the longest time
    and the held-out measurements' median spacing, :data:`MIN_BLOCKS` to :data:`MAX_BLOCKS` of them."""
    span = float(times.max() - times.min()) if len(times) else 0.0
    steps = np.diff(np.sort(times))
    longest = max([2.0 * t for t in taus if t is not None] + [2.0 * float(np.median(steps)) if len(steps) else 0.0])
    count = int(np.clip(span // longest if longest > 0.0 else MAX_BLOCKS, MIN_BLOCKS, MAX_BLOCKS))
    return np.minimum(((times - times.min()) / (span / count) if span > 0.0 else 0 * times).astype(int), count - 1)


def support(scores: dict, terms: dict, best: float | None) -> tuple:
    """``(shortest, longest, rough)``: the shortest and longest time within about one standard
    deviation of ``best`` among ``scores`` (``{tau: score}``, None: white), from each finite
    candidate's ``terms`` (``{tau: (terms, times)}``, :class:`Scored`; module docstring): the times
    tried whose score lies
    behind the best's by at most half the standard deviation of the difference, and, where the
    best has a :func:`parabola`, the sandwich's ``log tau* +- sd(g) / 2a`` (``sd(g)``: the
    difference's standard deviation per unit of ``log tau`` at the neighbours), within the rig
    key's range. White as the shortest where it is within (None); None as the longest where no
    time is. ``rough``: a time tried inside that range lies clearly behind (the score is not
    smooth in the time: the noise fit or the model errors it finds change from one time to the
    next, and the range understates how little the time is known)."""
    within, behind, slopes = [best], [], []
    own, at = terms[best]
    for tau, (values, times) in terms.items():
        if tau == best:
            continue
        shared, i, j = np.intersect1d(at, times, return_indices=True)
        if len(shared) < 2:
            continue
        d = values[j] - own[i]
        sums = np.bincount(blocks(shared, (tau, best)), weights=d)
        sd = math.sqrt(len(sums) * float(np.var(sums, ddof=1)))
        (within if float(d.sum()) <= 0.5 * sd else behind).append(tau)
        fitted = parabola(scores)
        if fitted is not None and tau in fitted[2]:
            slopes.append(sd / abs(math.log(tau / best)))
    numbers = sorted(t for t in within if t is not None)
    low, high = (None if None in within else numbers[0]), (numbers[-1] if numbers else None)
    if slopes and best is not None:
        half = float(np.mean(slopes)) / (2.0 * parabola(scores)[0])
        reach = (max(TIME_RANGE.low, best * math.exp(-min(half, 50.0))), min(TIME_RANGE.high,
                                                                             best * math.exp(min(half, 50.0))))
        low = None if low is None else min(low, reach[0])
        high = max(high, reach[1])
    rough = high is not None and any(t is not None and (low or 0.0) < t < high for t in behind)
    return low, high, rough


def _scored(base: Dataset, name: str, tau: float | None, tune: np.ndarray, solve: Callable) -> Scored:
    """The batch smoother run with sensor ``name``'s correlation time ``tau`` and its tuning half's
    score (module docstring). A batch that fails there, or a held-out measurement of the tuning
    half without a finite term (a prediction's covariance not positive definite), makes a
    candidate of NaN score saying why."""
    dataset = base.with_sensor(name, correlation_time=tau)
    empty = (np.zeros(0), np.zeros(0))
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")  # a candidate's: the run says the chosen one's
            estimate = solve(dataset)
            ran = dataset if estimate.noise is None else estimate.noise.applied(dataset)
            index, terms = predictive_terms(ran, name, estimate)
    except InternalError:
        raise
    except (BoxplusError, np.linalg.LinAlgError) as error:  # the factors refuse the time, the solver fails there
        return Scored(Candidate(tau, math.nan, " ".join(str(error).split())), *empty)
    converged = bool(estimate.details.get("converged", True))
    part = tune[index]
    if not np.isfinite(terms[part]).all():
        return Scored(Candidate(tau, math.nan, "a held-out prediction's covariance is not positive definite",
                                converged), *empty)
    if not part.any():
        return Scored(Candidate(tau, math.nan, "no held-out measurement of the tuning half predicted", converged),
                      *empty)
    # the mean over those predicted, for as many as the half holds: comparable where a few fall outside the span
    score = float(np.mean(terms[part])) * int(tune.sum())
    held_t = ran.sensor(name).heldout.t
    return Scored(Candidate(tau, score, None, converged), terms[part], held_t[index][part])


def predictive_terms(dataset: Dataset, name: str, estimate) -> tuple:
    """``(index, log det S_i + e_i^T S_i^-1 e_i)`` of sensor ``name``'s held-out measurements as
    ``estimate`` (run on ``dataset``) predicts them, in the measurement's units (NaN where ``S``
    is not positive definite): given the used measurements' errors where they drift (whitened by
    ``L^-1``, ``R = L L^T``: ``log det S`` adds ``log det R``), else through the state's
    covariance plus ``R`` (:func:`smoother.diagnosis.heldout.judged_errors`)."""
    held = dataset.sensor(name).heldout
    own = (estimate.heldout or {}).get(name)
    if own is None or own.state_part is None:
        own = heldout_predictions(dataset, estimate.trajectory, estimate.calibration, estimate.following,
                                  sensors=[name])[name]
    e, state_part, noise = judged_errors(own, held.cov)
    S = state_part + noise
    units = np.linalg.slogdet(held.cov[own.index])[1] if own.conditioned is not None else 0.0
    sign, log_det = np.linalg.slogdet(S)
    nis = np.einsum("ma,ma->m", e, np.linalg.solve(S, e[..., None])[..., 0])
    return own.index, np.where(sign > 0, nis + log_det + units, np.nan)
