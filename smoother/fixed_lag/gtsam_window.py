"""GTSAM's fixed-lag smoothers (``BatchFixedLagSmoother``, ``IncrementalFixedLagSmoother``) as a window of
the fixed-lag contract (:class:`smoother.fixed_lag.contract.FixedLagWindow`): :class:`KeyframeWindow`, and the
marginal covariances of its keyframes (:func:`window_covariances`).

:class:`KeyframeWindow` takes keyframes one at a time, in time order, each with its time stamp and
its factors; variables older than the lag (seconds) are marginalised by GTSAM, and the window lets
go of the factors GTSAM has marginalised, so what a run holds of the graph stays the size of the
window however long it is. It is fed the factors of a whole :class:`smoother.model.problem.Problem`
keyframe by keyframe (``Problem.keyframe_factors``, by :func:`smoother.fixed_lag.offline.run_fixed_lag`) or
keyframes made as IMU samples and measurements arrive (:class:`smoother.online.smoother.OnlineSmoother`).

GTSAM pitfalls handled here:

* the Python ``BatchFixedLagSmoother`` has no ``marginalCovariance``: covariances come from the
  smoother's current factors (its marginal factors included), linearised and eliminated
  (:func:`window_covariances`: Cholesky, QR for the windows GTSAM's Cholesky calls nearly
  indeterminant, a dense pseudo-inverse as the last resort), which works for both smoothers,
  gives the joint block of the keyframe's four variables, and survives nearly singular windows;
* both smoothers factorise with QR: with Cholesky, sparse GPS (KITTI) is declared
  indeterminant within seconds and ISAM2 cannot continue after a failed update;
* a factor that refers to a variable already marginalised out (a relative pose longer than the
  lag) would make GTSAM fail: it is skipped and counted;
* a keyframe that no factor ties to the window (no IMU factor) gets a weak prior around its
  prediction in the same update, and an update GTSAM still calls
  indeterminant is repeated with that prior, so one bad stretch does not stop the run; an
  update that fails beyond that raises :class:`smoother.fixed_lag.contract.FixedLagFailed` naming the
  keyframe and time instead of a bare GTSAM exception;
* ISAM2 relinearises at every update (:func:`make_smoother`), so that a measurement's
  correction reaches the states' linearisation before they leave the window;
* the ``BatchFixedLagSmoother`` keeps the state at its window's edge linearised where it first
  was (its ``enforceConsistency``, which the Python wrapper cannot turn off), so where
  measurements are further apart than the lag it drifts off
  (:func:`smoother.fixed_lag.lag.sparse_measurement_warning`). Of GTSAM's kinds the incremental one is
  the better.
"""
from __future__ import annotations

import time
from collections import deque

import gtsam
import numpy as np

from datasets.kinds import KINDS
from factors import imu, preintegration, priors
from factors.errors import InputError
from factors.imu_factor import ImuFactor
from factors.keys import keyframe_keys
from smoother.errors import IndeterminantSystem, is_indeterminant
from smoother.fixed_lag.contract import HISTORY, WEAK_PRIOR_SIGMAS, FixedLagFailed, TakenKeyframes
from smoother.fixed_lag.kinds import GTSAM_KINDS
from smoother.fixed_lag.lag import check_lag
from smoother.model.blocks import evaluate_block
from smoother.model.covariances import keyframe_covariance, marginal_covariances
from smoother.model.problem import attached_factor, insert_state, read_state
from smoother.model.robust import noise_model

#: Keyframes this close to the next update's marginalisation boundary (its time minus the lag)
#: count as leaving (:meth:`KeyframeWindow.leaving`), so that their estimates are taken before it as
#: well: GTSAM marginalises those strictly older than the boundary.
LAG_MARGIN_S = 1e-6


def make_smoother(kind: str, lag_s: float):
    """GTSAM's smoother of ``kind`` with QR factorisation: Cholesky declares the nearly
    singular systems of sparse GPS (KITTI, a fix every 10 s with 1 s keyframes) indeterminant
    at the velocity variables within seconds, and ISAM2 cannot continue after a failed update;
    QR solves them (the price is about 1.5x per update).

    ISAM2 reuses the slots of removed factors (``findUnusedFactorSlots``, off in
    ``ISAM2Params`` by default): the smoother removes every factor that marginalisation
    replaces, and with the default each left an empty slot behind, so ISAM2's factor graph grew
    with the length of the run and so did every relinearisation (the updates that set the 99th
    percentile): 7.7 -> 8.9 ms from the first to the last 6 minutes of an hour at 10 Hz. With reuse
    the graph holds the window only and those updates stay flat (``benchmarks/run.py``: median and
    99th percentile per tenth of an hour).

    ISAM2 considers relinearising at every update (``relinearizeSkip`` 1; GTSAM's default is
    every 10th), of the variables whose estimate moved more than 0.05 from their linearisation
    point. With every 10th update and a measurement every 10th keyframe (KITTI: 1-s keyframes, a
    GPS fix every 10 s) the relinearisations fell on the measured keyframes, before their
    correction, so a corrected state left a window shorter than 10 s still linearised where dead
    reckoning had put it (median 39 m away) and its marginal was built there: held-out RMS
    25.7 m at a 2-s lag, against 7.7 m now (the EKF: 14.2 m). A threshold of 1e-3 with
    relinearisation at every update costs ~6 ms per update; 0.05 costs ~1.2 ms."""
    if kind == "batch":
        params = gtsam.LevenbergMarquardtParams()
        params.setLinearSolverType("MULTIFRONTAL_QR")
        return gtsam.BatchFixedLagSmoother(lag_s, params)
    if kind == "incremental":
        params = gtsam.ISAM2Params()
        params.relinearizeSkip = 1
        params.setRelinearizeThreshold(0.05)
        params.setFactorization("QR")
        params.findUnusedFactorSlots = True
        return gtsam.IncrementalFixedLagSmoother(lag_s, params)
    raise InputError(f"fixed-lag smoother kind {kind!r}: expected one of {', '.join(GTSAM_KINDS)}")


def window_covariances(blocks: list, smoother, estimate: gtsam.Values, first: int,
                       states: imu.ImuState, rows_of: dict, wanted=None) -> np.ndarray:
    """Primer-convention 15x15 covariances of the window's keyframes ``first, first + 1, ...``
    (their states ``states``, their variables ``factors.keys.keyframe_keys``) from the smoother's
    current factors linearised at ``estimate``; of those at the window positions ``wanted`` only
    (0 = ``first``; default all). ``rows_of``: ``id(factor) -> (block index, row)`` of the
    project's factors in the smoother, rows of ``blocks`` (a :class:`smoother.model.problem.Problem`'s).

    The project's own factors in the window (those in ``rows_of``) are linearised together by the
    vectorised blocks of :mod:`smoother.model.blocks` (no Python callback per factor), the smoother's
    marginal factors (``LinearContainerFactor``) by GTSAM with their ``Rot3`` columns moved into
    the primer's chart (``J C^T``). The resulting linear system -- one 15-dim variable per window
    keyframe -- is solved for the marginals by :func:`window_marginals`."""
    n = len(states)
    wanted = range(n) if wanted is None else wanted
    dim = imu.STATE_DIM
    ours: dict[int, list[int]] = {}
    containers = gtsam.NonlinearFactorGraph()
    factors = smoother.getFactors()
    for i in range(factors.size()):
        f = factors.at(i)
        if f is None:
            continue
        where = rows_of.get(id(f))
        if where is None:
            containers.add(f)
        else:
            ours.setdefault(where[0], []).append(where[1])
    groups = []  # (window keyframes, [A per keyframe]) of one factor each
    for b, block_rows in ours.items():
        block = blocks[b]
        idx = np.array(block_rows)
        ev = evaluate_block(block, states, True, idx, keyframe_offset=first)
        local = block.keyframes[idx] - first
        groups += [(tuple(int(j) for j in local[m]), [A[m] for A in ev.A]) for m in range(len(idx))]
    if containers.size():
        dense = _container_rows(containers, estimate, first, n)
        used = [j for j in range(n) if np.any(dense[:, j * dim:(j + 1) * dim])]
        groups.append((tuple(used), [dense[:, j * dim:(j + 1) * dim] for j in used]))
    return window_marginals(groups, n, wanted)


def window_marginals(groups, n: int, wanted) -> np.ndarray:
    """Marginal covariances of the window positions ``wanted`` (``n`` 15-dim variables) of the
    whitened linear system ``groups`` (``(positions, [A per position])`` per factor).

    Sparse elimination with Cholesky first (``gtsam.Marginals``, the fastest). GTSAM refuses it
    for windows it judges nearly indeterminant -- a third of them with keyframes 25 ms apart and
    several kinds of measurement -- although they have full rank: those go to the square-root
    information (:func:`smoother.model.covariances.marginal_covariances`, QR), which works on the rows
    themselves rather than their squares (a dense pseudo-inverse of ``A^T A`` is 4e-5 off on these
    windows and 3x slower). What neither takes -- a
    rank-deficient window, or a factor on more than three keyframes, which the Python
    ``JacobianFactor`` cannot hold -- goes to that dense pseudo-inverse."""
    if all(len(keys) <= 3 for keys, _ in groups):
        graph = linear_graph(groups)
        try:
            return cholesky_marginals(graph, n, wanted)
        except RuntimeError:
            pass
        try:
            return marginal_covariances(graph, n, wanted)
        except IndeterminantSystem:
            pass
    return _dense_marginals(groups, n, wanted)


def linear_graph(groups) -> gtsam.GaussianFactorGraph:
    """``groups`` (at most three positions per factor) as GTSAM ``JacobianFactor`` s on keys
    ``0 .. n - 1``, unit noise (the rows are whitened already)."""
    graph = gtsam.GaussianFactorGraph()
    for keys, blocks in groups:
        args = [x for pair in zip(keys, blocks) for x in pair]
        graph.add(gtsam.JacobianFactor(*args, np.zeros(blocks[0].shape[0]),
                                       gtsam.noiseModel.Unit.Create(blocks[0].shape[0])))
    return graph


def cholesky_marginals(graph: gtsam.GaussianFactorGraph, n: int, wanted) -> np.ndarray:
    """GTSAM's ``Marginals`` (Cholesky) of ``graph``'s keys ``wanted``; RuntimeError where GTSAM
    calls the system indeterminant."""
    zero = gtsam.VectorValues()
    for j in range(n):
        zero.insert(j, np.zeros(imu.STATE_DIM))
    marginals = gtsam.Marginals(graph, zero)
    return np.stack([marginals.marginalCovariance(j) for j in wanted])


def stacked_rows(groups, n: int) -> np.ndarray:
    """``groups`` as one dense matrix of rows over the ``n`` window positions' 15 columns each."""
    dim = imu.STATE_DIM
    rows = []
    for keys, blocks in groups:
        part = np.zeros((blocks[0].shape[0], n * dim))
        for j, A in zip(keys, blocks):
            part[:, j * dim:(j + 1) * dim] += A
        rows.append(part)
    return np.vstack(rows)


def _dense_marginals(groups, n: int, wanted) -> np.ndarray:
    dim = imu.STATE_DIM
    A = stacked_rows(groups, n)
    cov = np.linalg.pinv(A.T @ A, hermitian=True)
    cov = 0.5 * (cov + cov.T)
    return np.stack([cov[j * dim:(j + 1) * dim, j * dim:(j + 1) * dim] for j in wanted])


def _container_rows(containers, estimate, first: int, n: int) -> np.ndarray:
    """Dense rows of GTSAM's marginal factors in the window's primer columns."""
    keys = sorted({int(k) for i in range(containers.size()) for k in containers.at(i).keys()})
    linear = containers.linearize(estimate)
    A, _ = linear.jacobian(gtsam.Ordering(keys))
    dims = [estimate.zeroVectors().at(k).shape[0] for k in keys]
    out = np.zeros((A.shape[0], n * imu.STATE_DIM))
    column = 0
    slots = {}
    for j in range(first, first + n):
        kk = keyframe_keys(j)
        base = (j - first) * imu.STATE_DIM
        slots[kk.rot] = (base + 6, estimate.atRot3(kk.rot).matrix().T)  # d = C^T phi
        slots[kk.pos] = (base + 0, None)
        slots[kk.vel] = (base + 3, None)
        slots[kk.bias] = (base + 9, None)
    for key, d in zip(keys, dims):
        block = A[:, column:column + d]
        start, to_gtsam = slots[key]
        out[:, start:start + d] += block if to_gtsam is None else block @ to_gtsam
        column += d
    return out


def _weak_prior(keys, guess: imu.ImuState):
    return priors.state_prior_factor(keys, guess, np.diag(WEAK_PRIOR_SIGMAS**2))


def _update_failed(k: int, t: float, error: Exception) -> FixedLagFailed:
    first_line = str(error).strip().splitlines()[0] if str(error).strip() else type(error).__name__
    return FixedLagFailed(f"the fixed-lag smoother failed at keyframe {k} (t = {t:.6f} s): {first_line}. "
                          "Check the data around that time (an IMU gap, a measurement far off).")


class KeyframeWindow:
    """GTSAM's fixed-lag smoother of ``kind`` (:data:`smoother.fixed_lag.kinds.GTSAM_KINDS`) fed one keyframe at
    a time: a window of the fixed-lag contract (:class:`smoother.fixed_lag.contract.FixedLagWindow`: the
    keyframes, the lag, :meth:`leaving` and :meth:`taken` and the order of the calls).

    Keyframe ``k`` has the variables ``factors.keys.keyframe_keys(k)``; :meth:`update` adds it with
    its GTSAM factors (the module docstring's pitfalls: factors on marginalised variables skipped
    and counted, a weak prior where nothing ties the keyframe to the window or GTSAM calls the
    update indeterminant), :meth:`add_keyframe` with factors made here from their ingredients,
    :meth:`add_problem_keyframe` with a problem's. ``gravity`` and ``reintegration_threshold`` are
    those of the IMU factors :meth:`add_keyframe` makes. When the next keyframe is more than the lag
    later (an IMU gap), GTSAM marginalises the newest one in the update that adds it, after adding
    the IMU factor between them, whose information the marginal keeps."""

    def __init__(self, lag_s: float, kind: str = "incremental", gravity=imu.DEFAULT_GRAVITY,
                 reintegration_threshold: float = preintegration.REINTEGRATION_THRESHOLD):
        lag_s = check_lag(lag_s)
        self.smoother = make_smoother(kind, lag_s)
        self.gravity = np.asarray(gravity, dtype=float)
        self.threshold = float(reintegration_threshold)
        self.lag_s = lag_s
        self.kind = kind
        self.first = 0  # the oldest keyframe in the window
        self.newest = -1  # the newest keyframe (-1 before the first update)
        self.estimate: gtsam.Values | None = None  # the smoother's estimate after the last update
        self.newest_state: imu.ImuState | None = None  # the newest keyframe's, read from ``estimate``
        self.recovered: list[int] = []
        self.skipped = 0
        self.weighed_alone = 0
        self.update_s: deque[float] = deque(maxlen=HISTORY)
        #: ``id(factor) -> tag`` of the factors given with a tag, while GTSAM holds them
        self.rows_of: dict[int, object] = {}
        #: the blocks of the problem whose factors :meth:`add_problem_keyframe` gave, tagged with
        #: their rows in them (None: none given)
        self.blocks: list | None = None
        self._times: dict[int, float] = {}  # the window's keyframe times
        self._present: set[int] = set()
        self._held: dict[int, list] = {}  # the factors by their earliest keyframe, until marginalised
        self._taken = TakenKeyframes()

    @property
    def calibration(self):
        """None: GTSAM's windows estimate no calibration (the values given are used)."""
        return None

    def time(self, k: int) -> float:
        """The time stamp of window keyframe ``k``."""
        return self._times[k]

    def leaving(self, t_next: float) -> list[int]:
        """The window keyframes (the newest too, after a gap longer than the lag) that an update
        at ``t_next`` marginalises: older than ``t_next`` minus the lag, within :data:`LAG_MARGIN_S`."""
        boundary = t_next - self.lag_s + LAG_MARGIN_S
        return [j for j in range(self.first, self.newest + 1) if self._times[j] < boundary]

    def taken(self, keyframes) -> None:
        """Record that the estimates of ``keyframes`` were read after the last update."""
        self._taken.record(keyframes, self.newest)

    def update(self, t: float, factors: list, guess: imu.ImuState, oldest: list[int], tags=None) -> imu.ImuState:
        """Add the next keyframe at time ``t`` (after the newest) with ``factors`` (GTSAM factors on
        it and older window keyframes; ``oldest[i]`` the earliest keyframe of ``factors[i]``,
        ``tags[i]`` kept in :attr:`rows_of` unless None) and the initial value ``guess``; returns
        its estimate. Raises :class:`FixedLagFailed` where GTSAM cannot go on."""
        k = self.newest + 1
        keys = keyframe_keys(k)
        new_keys = set(keys.all())
        graph = gtsam.NonlinearFactorGraph()
        tags = tags if tags is not None else [None] * len(factors)
        for f, tag, first_k in zip(factors, tags, oldest):
            if all(key in self._present or key in new_keys for key in f.keys()):
                graph.add(f)
                self._held.setdefault(first_k, []).append(f)
                if tag is not None:
                    self.rows_of[id(f)] = tag
            else:
                self.skipped += 1
        values = gtsam.Values()
        insert_state(values, keys, guess)
        stamps = gtsam.FixedLagSmootherKeyTimestampMap()
        for key in keys.all():
            stamps.insert((key, float(t)))
        linked = k == 0 or any(
            any(key in new_keys for key in graph.at(i).keys())
            and any(key in self._present for key in graph.at(i).keys())
            for i in range(graph.size()))
        if not linked:  # nothing ties the new keyframe to the window (no IMU factor): weak prior
            graph.add(_weak_prior(keys, guess))
            self.recovered.append(k)
        tick = time.perf_counter()
        try:
            self.smoother.update(graph, values, stamps)
        except RuntimeError as error:
            if not is_indeterminant(error) or not linked:
                raise _update_failed(k, t, error) from None
            self.recovered.append(k)
            weak = gtsam.NonlinearFactorGraph()
            weak.add(_weak_prior(keys, guess))
            try:
                self.smoother.update(weak, gtsam.Values(), gtsam.FixedLagSmootherKeyTimestampMap())
            except (RuntimeError, IndexError) as again:
                raise _update_failed(k, t, again) from None
        except IndexError as error:  # ISAM2's Bayes tree is inconsistent: cannot continue
            raise _update_failed(k, t, error) from None
        self.estimate = self.smoother.calculateEstimate()
        self.update_s.append(time.perf_counter() - tick)
        self.newest = k
        self._times[k] = float(t)
        self._present = set(int(key) for key in self.estimate.keys())
        while keyframe_keys(self.first).rot not in self._present:  # the window is contiguous: [first, k]
            # read after the update before this one, or GTSAM marginalised earlier than leaving() says
            self._taken.leave(self.first, self._times[self.first], k - 1)
            for f in self._held.pop(self.first, ()):  # marginalised with the keyframe: GTSAM has let go of it
                self.rows_of.pop(id(f), None)
            del self._times[self.first]
            self.first += 1
        self.newest_state = read_state(self.estimate, keys)
        return self.newest_state

    def state(self, k: int) -> imu.ImuState:
        """Window keyframe ``k``'s estimate after the last update."""
        return read_state(self.estimate, keyframe_keys(k))

    def add_keyframe(self, t: float, guess: imu.ImuState, pre=None, measurements=(), prior=None,
                     held=None) -> imu.ImuState:
        """:meth:`update` with the keyframe's factors made here (the contract's
        :meth:`~smoother.fixed_lag.contract.FixedLagWindow.add_keyframe`): the IMU factor of the
        preintegrated interval ``pre`` from the newest keyframe (None: none), the factors of
        ``measurements`` (``(spec, m, keyframes, robust, attached)``; one attached to the newest
        keyframe through ``pre``'s samples: :func:`smoother.model.problem.attached_factor`) and a
        ``prior`` ``(state, cov)`` on the new keyframe; ``held`` is not used (no calibration here)."""
        k = self.newest + 1
        keys = keyframe_keys(k)
        factors, oldest = [], []
        if prior is not None:
            factors.append(priors.state_prior_factor(keys, *prior))
            oldest.append(k)
        if pre is not None and k > 0:
            factors.append(ImuFactor(pre, keyframe_keys(k - 1), keys, self.gravity,
                                     reintegration_threshold=self.threshold).factor)
            oldest.append(k - 1)
        for spec, m, keyframes, robust, attached in measurements:
            model = noise_model(spec.cov[m], robust)
            if attached is None:
                factors.append(spec.factor([keyframe_keys(j) for j in keyframes], m, model))
            else:  # attached to keyframes[0], the keyframe before this one: in the interval pre
                factors.append(attached_factor(KINDS[spec.kind], keyframe_keys(keyframes[0]), pre.samples, attached,
                                               spec.rows[m], model, self.gravity))
            oldest.append(min(keyframes))
        return self.update(t, factors, guess, oldest)

    def add_problem_keyframe(self, t: float, guess: imu.ImuState, made, blocks: list) -> imu.ImuState:
        """:meth:`update` with the problem's own GTSAM factors ``made``
        (:class:`smoother.model.problem.KeyframeFactors`), each tagged with its row of ``blocks`` (the
        problem's), so that :meth:`covariances` linearises them with those blocks. A drifting sensor's
        measurement is its own factor here, counted in ``weighed_alone``."""
        self.blocks = blocks
        self.weighed_alone += sum(len(m) > 5 and m[5] is not None for m in made.measurements)
        return self.update(t, made.factors, guess, made.oldest, made.rows)

    def covariances(self, wanted) -> np.ndarray:
        """The 15x15 marginal covariances (primer convention) of window keyframes ``wanted``: those
        of the smoother's factors linearised at the estimate (:func:`window_covariances`; a
        problem's own factors by its vectorised blocks, the rest -- the marginals, and every factor
        of the batch kind fed :meth:`add_keyframe`, whose Python wrapper has no covariance -- by
        GTSAM); the incremental kind fed :meth:`add_keyframe` takes them from ISAM2's Bayes tree
        instead (``jointMarginalCovariance`` of a keyframe's four variables, at its linearisation
        point; the newest keyframes sit at the root, so this costs little)."""
        if self.kind == "incremental" and self.blocks is None:
            isam = self.smoother.getISAM2()
            return np.stack([keyframe_covariance(isam, keyframe_keys(j), self.estimate.atRot3(keyframe_keys(j).rot))
                             for j in wanted])
        states = imu.ImuState.stack([self.state(j) for j in range(self.first, self.newest + 1)])
        return window_covariances(self.blocks or [], self.smoother, self.estimate, self.first, states, self.rows_of,
                                  [j - self.first for j in wanted])

    def joint_with_next(self, wanted) -> None:
        """None: GTSAM's windows hand out marginals alone (a state between their keyframes is
        carried from the one before, :func:`smoother.model.between.states_between`)."""
        return None
