"""An estimate's states at times between its own keyframes, with their covariances: where a
held-out measurement is predicted (:mod:`smoother.diagnosis.heldout`) and a fix scored
(:mod:`smoother.evaluation.scoring`), neither of which is a keyframe.

A filter's state at keyframe ``k`` holds what the data up to ``t_k`` say, and its prediction
to ``tau`` is the state carried through the IMU's Euler steps with the EKF's covariance step
(:func:`smoother.model.timeline.states_at`). A smoother's states hold the data on both sides,
and so must the state between two of them. In the linearised model, with ``x_tau = f_1(x_k) [+]
w_1`` and ``x_(k+1) = f_2(x_tau) [+] w_2`` (``F_1``, ``F_2`` the steps' error-state transitions,
``S_1``, ``S_2`` their process noise, ``w_1``, ``w_2`` independent), the state at ``tau`` given
both keyframes' is the bridge

    E[dx_tau | dx_k, d'] = F_1 dx_k + K (d' - F_2 F_1 dx_k),   K = S_1 F_2^T (F_2 S_1 F_2^T + S_2)^-1
    Cov[dx_tau | dx_k, d'] = S_1 - K F_2 S_1

(``d'`` the error of ``x_(k+1)`` about ``f_2(f_1(x^_k))``). The smoother's errors at its
keyframes have mean zero given the data, so its state at ``tau`` is ``f_1(x^_k) [+] K d`` with
``d = x^_(k+1) [-] f_2(f_1(x^_k))`` (what the next keyframe says the carried state missed), and its
error is ``A dx_k + K dx_(k+1) + e`` with ``A = (I - K F_2) F_1`` and ``e`` the bridge's own,
independent of the data:

    P_tau = [A K] Sigma_(k, k+1) [A K]^T + S_1 - K F_2 S_1

with ``Sigma_(k, k+1)`` the two keyframes' joint covariance (:class:`Following`: the batch
smoother's from the selected inversion, :func:`smoother.model.covariances.marginal_covariances`;
a fixed-lag smoother's from its window as keyframe ``k`` leaves it, with its estimate of ``k + 1``
then). ``F_2 S_1 F_2^T +
S_2`` is the interval's process noise: positive definite where every noise density is positive,
singular where one is zero (a bias taken as constant); it is inverted in its range, scaled to unit
diagonal first (the biases' noise lies orders of magnitude below the attitude's), which gives a
generalised inverse that conditions exactly where ``d`` lies in that range, as it does in the
model. Carried from a smoothed state alone, without
the bridge, ``P`` holds ``S_1`` whole: where the IMU's noise over a keyframe interval is not small
beside a sensor's, the held-out errors would lie below their band (an AHRS beside a gyro whose
noise was fitted large: 0.82 per dof carried, 1.0 bridged, on a ground robot's recording).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from datasets.types import ImuSamples, Trajectory
from factors.imu import DEFAULT_GRAVITY, ImuNoise, ImuState, boxminus, boxplus
from smoother.model.timeline import STATES_CHUNK, carry, states_at

#: Eigenvalues of the scaled interval noise below this fraction of its largest are taken as no
#: noise (its range: :func:`_range_inverse`).
RANGE_TOLERANCE = 1e-12


def _range_inverse(S: np.ndarray) -> np.ndarray:
    """The pseudo-inverses of the symmetric positive semi-definite ``S (M, n, n)``, each scaled to
    unit diagonal first (``D S D``, ``D = diag(S)^-1/2``, zero where the diagonal is) so that the
    tolerance is relative to each component's own size."""
    diag = np.einsum("mii->mi", S)
    d = np.where(diag > 0.0, 1.0 / np.sqrt(np.where(diag > 0.0, diag, 1.0)), 0.0)
    scaled = d[:, :, None] * S * d[:, None, :]
    w, V = np.linalg.eigh(scaled)
    keep = w > RANGE_TOLERANCE * np.max(w, axis=1, keepdims=True)
    inv_w = np.where(keep, 1.0 / np.where(keep, w, 1.0), 0.0)
    inverse = (V * inv_w[:, None, :]) @ np.swapaxes(V, 1, 2)
    return d[:, :, None] * inverse * d[:, None, :]


@dataclass(frozen=True)
class Following:
    """Each state ``k < N - 1`` of a smoother's trajectory with the next one as the smoother had
    them together: the next state ``states (N - 1,)``, its covariance ``cov (N - 1, 15, 15)`` and
    the two's joint block ``cross (N - 1, 15, 15)``, ``Sigma_(k, k+1)``. A batch smoother's are its
    own next states (:meth:`of_batch`); a fixed-lag smoother's, its window's estimate of keyframe
    ``k + 1`` when keyframe ``k`` left it, beside which its estimate of ``k`` was made."""

    states: ImuState
    cov: np.ndarray
    cross: np.ndarray
    #: Which states have theirs (``(N - 1,)`` bool; None: all). A state between one without and
    #: the next is carried from it.
    valid: np.ndarray | None = None

    @staticmethod
    def of_batch(trajectory: Trajectory, cross: np.ndarray) -> "Following":
        """A trajectory's own next states with the joint blocks ``cross`` of consecutive ones."""
        return Following(trajectory.states[1:], trajectory.cov[1:], cross)

    @staticmethod
    def of_handed_over(estimates: list) -> "Following | None":
        """A fixed-lag smoother's from its estimates in time order
        (:class:`smoother.online.handover.OnlineEstimate`): each one's ``following``, where it is
        that of the estimate after it (the same keyframe's time); None where none is."""
        nxt = [e.following for e in estimates[:-1]]
        valid = np.array([f is not None and f.t == e.t for f, e in zip(nxt, estimates[1:])], dtype=bool)
        if not valid.any():
            return None
        missing = np.full((15, 15), np.nan)
        states = ImuState.stack([f.state if ok else e.state for f, e, ok in zip(nxt, estimates[1:], valid)])
        cov = np.stack([f.cov if ok else missing for f, ok in zip(nxt, valid)])
        cross = np.stack([f.cross if ok else missing for f, ok in zip(nxt, valid)])
        return Following(states, cov, cross, valid)


def states_between(trajectory: Trajectory, imu: ImuSamples, t, noise: ImuNoise, gravity=DEFAULT_GRAVITY,
                   following: Following | None = None) -> Trajectory:
    """The states of ``trajectory`` at times ``t`` (within the IMU span, none before its first
    state): a time at one of its states takes that state; one strictly between states ``k`` and
    ``k + 1`` is bridged between state ``k`` and ``following``'s ``k`` (module docstring) where
    it is given (and the trajectory has covariances), else carried from the state before
    (:func:`smoother.model.timeline.states_at`: a filter's, or a smoother's without its joint
    covariances). The bridge runs over :data:`smoother.model.timeline.STATES_CHUNK` times at once."""
    t = np.asarray(t, dtype=float)
    k = np.searchsorted(trajectory.t, t, side="right") - 1
    bridged = np.zeros(len(t), dtype=bool)
    if following is not None and trajectory.cov is not None and len(trajectory.t) > 1:
        bridged = (k >= 0) & (k < len(trajectory.t) - 1) & (t > trajectory.t[np.maximum(k, 0)])
        if following.valid is not None:
            bridged &= following.valid[np.clip(k, 0, len(following.valid) - 1)]
    if not bridged.any():
        return states_at(trajectory, imu, t, noise, gravity)
    carried = states_at(trajectory, imu, t[~bridged], noise, gravity)
    states = ImuState(*(np.empty((len(t),) + getattr(carried.states, f).shape[1:])
                        for f in ("r", "v", "C", "b_f", "b_w")))
    cov = np.empty((len(t), 15, 15))
    _put(states, cov, ~bridged, carried.states, carried.cov)
    at = np.flatnonzero(bridged)
    for lo in range(0, len(at), STATES_CHUNK):
        rows = at[lo:lo + STATES_CHUNK]
        _put(states, cov, rows, *_bridge(trajectory, following, imu, k[rows], t[rows], noise, gravity))
    return Trajectory(t, states, cov)


def _put(states: ImuState, cov: np.ndarray, where, part: ImuState, part_cov: np.ndarray) -> None:
    """Write the states ``part`` and covariances ``part_cov`` into ``states`` and ``cov`` at ``where``."""
    for name in ("r", "v", "C", "b_f", "b_w"):
        getattr(states, name)[where] = getattr(part, name)
    cov[where] = part_cov


def _bridge(trajectory: Trajectory, following: Following, imu: ImuSamples, k: np.ndarray, tau: np.ndarray,
            noise: ImuNoise, gravity) -> tuple[ImuState, np.ndarray]:
    """The bridged states and covariances at times ``tau`` between states ``k`` and ``k + 1``
    (module docstring)."""
    states, AK, own = bridge_parts(trajectory, following, imu, k, tau, noise, gravity)
    cross = following.cross[k]
    joint = np.block([[trajectory.cov[k], cross], [np.swapaxes(cross, 1, 2), following.cov[k]]])
    cov = AK @ joint @ np.swapaxes(AK, 1, 2) + own
    return states, 0.5 * (cov + np.swapaxes(cov, 1, 2))


def bridge_parts(trajectory: Trajectory, following: Following, imu: ImuSamples, k: np.ndarray, tau: np.ndarray,
                 noise: ImuNoise, gravity=DEFAULT_GRAVITY) -> tuple[ImuState, np.ndarray, np.ndarray]:
    """``(states, AK, own)``: the states bridged at times ``tau`` strictly between states ``k`` and
    ``k + 1`` of a smoother's ``trajectory`` (``following``: its states ``k + 1``), their errors'
    linear map ``[A K] (M, 15, 30)`` on the two states' errors and the bridge's own covariance
    ``S_1 - K F_2 S_1 (M, 15, 15)``, independent of the data (module docstring): what a covariance
    of the bridged state with states other than these two needs."""
    x1, S1, F1 = carry(trajectory.states[k], imu, trajectory.t[k], tau, noise, gravity, transition=True)
    x2, S2, F2 = carry(x1, imu, tau, trajectory.t[k + 1], noise, gravity, transition=True)
    F2T = np.swapaxes(F2, 1, 2)
    K = S1 @ F2T @ _range_inverse(F2 @ S1 @ F2T + S2)
    d = boxminus(following.states[k], x2)
    AK = np.concatenate([(np.eye(15) - K @ F2) @ F1, K], axis=2)
    return boxplus(x1, np.einsum("mab,mb->ma", K, d)), AK, S1 - K @ F2 @ S1
