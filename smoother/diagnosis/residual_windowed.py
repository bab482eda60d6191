"""A drifting sensor's own residuals as the fixed-lag smoother's window weighed them: its in-sample
verdict, as the batch smoother's of its factors (:mod:`smoother.diagnosis.residual_consistency`).

A drifting sensor's factors are innovations ``f_m = s_m (u_m - phi_m u_(m-1))`` on the keyframes of
two consecutive measurements (``u`` each one's whitened residual; :mod:`smoother.model.correlated`).
Their residuals at the estimate have ``E |f_m|^2 = d - h_m``, with the leverage
``h_m = tr(A_m Sigma A_m^T)`` over the joint covariance ``Sigma`` of both keyframes -- which a
fixed-lag smoother's output, each keyframe's marginal as it left the window, does not keep; its own
measurements' residuals judged as white would instead blame the sigma for the drift its estimate
follows. So each innovation is evaluated inside the window (:class:`WindowedResiduals`, an online
smoother's ``before_leaving``) at the last update that holds both keyframes -- when the earlier is
about to leave, as a white sensor's residual is read at its keyframe's estimate as it left --
with their estimates and joint covariance (:meth:`smoother.fixed_lag.sliding.window.SlidingWindow.joint_span`).
The first measurement's factor is its own, ``u_0``, evaluated as its keyframe leaves. One the
window weighed alone instead -- its predecessor's keyframe left before it arrived, or lies more
keyframes back than the window reaches (:func:`smoother.fixed_lag.sliding.window.keeps_innovation`) -- is not judged:
its factor takes its error as independent of the one before, which the model does not (the run
warns of them, and the verdict counts them, ``weighed_alone``). Whitened, not robustly reweighted:
outliers count, as in the batch's verdict.
"""
from __future__ import annotations

from dataclasses import replace

import numpy as np

from factors.imu import STATE_DIM, ImuState
from smoother.diagnosis.heldout_windowed import check_keyframes
from smoother.diagnosis.verdicts import verdict
from smoother.fixed_lag.sliding.window import keeps_innovation
from smoother.model.blocks import evaluate_block
from smoother.model.correlated import CorrelatedBlock, innovation_weights

DIM = STATE_DIM


class WindowedResiduals:
    """The in-sample verdicts of the drifting ``sensors`` (names) whose block in ``problem`` (the
    batch's factors on the fixed-lag smoother's keyframes) is a
    :class:`~smoother.model.correlated.CorrelatedBlock`, from the window as its keyframes leave it
    (module docstring): call it with the window and the keyframes about to leave, then read
    :meth:`verdicts`."""

    def __init__(self, problem, sensors):
        self._times = problem.times
        self._sensors = []
        for block in problem.blocks:
            if not isinstance(block, CorrelatedBlock) or block.name not in sensors or not len(block):
                continue
            phi, scale = innovation_weights(block.name, block.times, block.correlation_time)
            own = block.measurements.keyframes[:, 0]
            due = np.concatenate([own[:1], own[:-1]])  # the earlier keyframe of each pair (the first: its own)
            self._sensors.append({"block": block, "measured": replace(block.measurements, whiten=block.whiten),
                                  "phi": phi, "scale": scale, "own": own, "due": due,
                                  "done": np.zeros(len(own), dtype=bool), "total": 0.0, "dof": 0.0, "count": 0,
                                  "weighed_alone": 0})

    def __bool__(self) -> bool:
        return bool(self._sensors)

    def __call__(self, window, leaving) -> None:
        """Evaluate the innovations due at this update (``leaving``: the keyframes the next update
        marginalises, or the whole window at the end)."""
        leaving = np.asarray(list(leaving), dtype=int)
        if not len(leaving):
            return
        check_keyframes(window, self._times, "in-sample verdicts")
        newest_t = window.time(window.newest)
        finishing = window.newest in leaving
        for s in self._sensors:
            block, own = s["block"], s["own"]
            # the pairs whose earlier keyframe leaves (in time order: a range of them, found by bisection)
            due = np.arange(int(np.searchsorted(s["due"], leaving.min(), side="left")),
                            int(np.searchsorted(s["due"], leaving.max(), side="right")))
            due = due[~s["done"][due] & np.isin(s["due"][due], leaving)]
            held = (own[due] <= window.newest) & (block.times[due] <= newest_t)  # factors the window holds
            # a pair whose later measurement has not arrived (its earlier keyframe leaves now), or one the
            # window would not make: the window weighs it alone
            gone = (due > 0) & ~(held & keeps_innovation(s["due"][due], own[due], window.first))
            s["weighed_alone"] += int((gone & (held | ~finishing)).sum())  # (at the end, unheld: never used)
            s["done"][due] = True
            due = due[~gone & held]
            if len(due):
                self._evaluate(window, s, due)

    def _evaluate(self, window, s: dict, rows: np.ndarray) -> None:
        """Add sensor ``s``'s innovations ``rows`` at the window's estimate now to its sums."""
        previous = np.maximum(rows - 1, 0)  # (the first reads itself there, with weight phi_0 = 0)
        own, earlier = s["own"][rows], s["own"][previous]
        lo, hi = int(earlier.min()), int(own.max())
        count = hi - lo + 1
        joint = window.joint_span(lo, count).reshape(count, DIM, count, DIM).transpose(0, 2, 1, 3)
        states = ImuState.stack([window.state(k) for k in range(lo, hi + 1)])
        needed = np.unique(np.concatenate([rows, previous]))
        ev = evaluate_block(s["measured"], states, True, rows=needed, keyframe_offset=lo, reweight=False)
        place = np.searchsorted(needed, rows), np.searchsorted(needed, previous)
        scale = s["scale"][rows]
        k = s["phi"][rows] * scale
        f = scale[:, None] * ev.e[place[0]] - k[:, None] * ev.e[place[1]]
        A_own, A_earlier = scale[:, None, None] * ev.A[0][place[0]], -k[:, None, None] * ev.A[0][place[1]]
        a, b = own - lo, earlier - lo
        P = (A_own @ joint[a, a] @ np.swapaxes(A_own, 1, 2) + A_earlier @ joint[b, b] @ np.swapaxes(A_earlier, 1, 2)
             + A_own @ joint[a, b] @ np.swapaxes(A_earlier, 1, 2) + A_earlier @ joint[b, a] @ np.swapaxes(A_own, 1, 2))
        d = f.shape[1]
        s["total"] += float(np.sum(f * f))
        s["dof"] += float(np.sum(np.clip(d - np.trace(P, axis1=1, axis2=2), 0.0, d)))
        s["count"] += len(rows)

    def verdicts(self) -> dict[str, dict]:
        """Per sensor with innovations evaluated, the :func:`smoother.diagnosis.verdicts.verdict` of
        their residuals (statistic ``"residual"``), with ``weighed_alone``: how many of its
        measurements the window weighed alone, not judged."""
        return {s["block"].name: {**verdict(s["total"], s["dof"], s["count"], "residual"),
                                  "weighed_alone": s["weighed_alone"]}
                for s in self._sensors if s["count"]}
