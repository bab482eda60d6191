"""Robust kernels on the factors: GTSAM's ``mEstimator`` of each kernel a spec names
(:mod:`datasets.robust` parses the specs and holds the kernels' names), its dimension-aware
default threshold, and the noise models that wrap a Gaussian in one."""
from __future__ import annotations

import gtsam
import numpy as np

from datasets.robust import ROBUST_KERNEL_NAMES
from factors import priors
from smoother.stats import chi2_quantile

#: The probability that sets each kernel's default threshold (:func:`default_threshold`).
_DEFAULT_PROBABILITY = {"huber": 0.95, "cauchy": 0.95, "tukey": 0.999}

#: Per kernel name (:data:`datasets.robust.ROBUST_KERNEL_NAMES`), GTSAM's mEstimator class and the
#: probability that sets its default threshold.
ROBUST_KERNELS = {name: (getattr(gtsam.noiseModel.mEstimator, name.capitalize()), _DEFAULT_PROBABILITY[name])
                  for name in ROBUST_KERNEL_NAMES}


def default_threshold(kernel: str, dim: int) -> float:
    """The default threshold of a kernel on a ``dim``-dimensional factor.

    GTSAM's ``Robust`` noise model applies the kernel to the NORM of the whole whitened error,
    which for an inlier is chi-distributed with ``dim`` degrees of freedom (mean ~2.35 for a
    6-dim pose). The textbook constants (Huber 1.345, ...) are for a scalar residual and would
    down-weight nearly every inlier of a pose factor. The default is therefore
    ``sqrt(chi2_dim(p))``: Huber and Cauchy leave 95% of inliers at full weight, Tukey (which
    rejects completely beyond it) 99.9%."""
    return float(np.sqrt(chi2_quantile(ROBUST_KERNELS[kernel][1], dim)))


def robust_threshold(spec, dim: int) -> float:
    """The threshold of a kernel spec ``(name, threshold or None)`` on a ``dim``-dimensional factor."""
    name, threshold = spec
    return float(threshold) if threshold is not None else default_threshold(name, dim)


def robust_estimator(spec, dim: int):
    """GTSAM's mEstimator of a kernel spec ``(name, threshold or None)`` on a ``dim``-dimensional
    factor, or None for no kernel."""
    if spec is None:
        return None
    kernel, _ = ROBUST_KERNELS[spec[0]]
    return kernel.Create(robust_threshold(spec, dim))


def noise_model(cov: np.ndarray, robust=None):
    """A Gaussian model of ``cov``, wrapped in a robust kernel ``(name, threshold)`` if given."""
    base = priors.covariance_model(cov)
    if robust is None:
        return base
    return gtsam.noiseModel.Robust.Create(robust_estimator(robust, np.shape(cov)[-1]), base)
