"""What an estimator predicts of the measurements it did not use: a sensor's held-out measurements
(a rig's ``every = K``), each predicted from the estimate's state at its time."""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass
class Conditioned:
    """A prediction of held-out measurements given the errors of the used ones, where a sensor's
    errors are correlated in time (:mod:`smoother.diagnosis.heldout_correlated`), in the model's
    whitened units: ``e (M, d)``, the held-out error less its expectation given those errors;
    ``state_part (M, d, d)``, the estimate's share of its covariance; ``noise (M, d, d)``, the
    measurement noise's share (what a white sensor's ``R`` is)."""

    e: np.ndarray
    state_part: np.ndarray
    noise: np.ndarray


@dataclass
class HeldoutPrediction:
    """An estimator's prediction of a sensor's held-out measurements (those within its span):
    ``index (M,)``, their places among the sensor's held-out measurements; ``e (M, d)``, the residual
    ``e = h(x^) - z`` of the state at each one's time and of the calibrations the estimator has; and
    ``state_part (M, d, d)``, the share of the prediction's covariance that is the estimate's,
    ``H P H^T``, or None where the estimate has no covariances. A filter's are its own, taken in its
    loop after the updates at that time (``P`` its whole augmented covariance, a calibration's
    uncertainty in it: :mod:`smoother.ekf.filter`; NaN where it had diverged before); a smoother's
    are its states bridged or carried to the times (:func:`smoother.diagnosis.heldout.heldout_predictions`)."""

    index: np.ndarray
    e: np.ndarray
    state_part: np.ndarray | None
    #: The prediction given the used measurements' errors, for a sensor whose errors are correlated
    #: in time (:class:`Conditioned`): what its verdict judges; None for a white sensor.
    conditioned: Conditioned | None = None
