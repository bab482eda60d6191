"""factors.chart: the one adapter between GTSAM's right chart and the primer's left chart.

What is proved here:

* ``to_gtsam_chart(J, C) = J C`` is the derivative GTSAM itself measures: it equals
  ``gtsam.utils.numerical_derivative`` (GTSAM's right chart) of a primer-convention residual;
* ``state_covariance_to_primer`` maps a keyframe covariance in GTSAM's chart -- variables
  ``(Rot3, Point3, velocity, bias)`` -- to the covariance of the primer's error state
  ``(dr, dv, dphi, db_f, db_w)``: against sampled perturbations (drawn in GTSAM's chart, applied
  with ``Rot3.retract``, mapped to the primer's error exactly with ``so3.log``), and end to end
  through ``gtsam.Marginals`` of a state prior.

Tolerances. The map ``d -> log(R Exp(d) R^T) = C d`` is linear and exact for ``|d| < pi``, so the
sample covariance of the mapped samples equals the mapped sample covariance to round-off (1e-14
relative). Against the population covariance the comparison is statistical: the mapped samples are
whitened by the predicted covariance and every distinct entry of their sample covariance must be
within 5 standard deviations of the identity's (sd ``1/sqrt(N)`` off the diagonal,
``sqrt(2/N)`` on it; N = 20000: 0.035 and 0.05); the chance that one of the 120 entries exceeds
that under the hypothesis is ~1e-4 (and the seed is fixed). Using ``C^T`` in place of ``C``
fails the same statistic by far.
"""
from __future__ import annotations

import math

import gtsam
import numpy as np
import pytest
from gtsam.utils.numerical_derivative import numericalDerivative11

from factors import imu, priors, so3
from factors.chart import to_gtsam_chart
from factors.keys import keyframe_keys
from factors.sensor_models import orientation_error_into
from factors.uncertainty import state_covariance_to_primer

N_SAMPLES = 20000


def random_rotation(rng: np.random.Generator, regime: str) -> np.ndarray:
    axis = rng.normal(size=3)
    axis /= np.linalg.norm(axis)
    if regime == "tiny":
        angle = 10.0 ** rng.uniform(-12, -6)
    elif regime == "near_pi":
        angle = math.pi - 10.0 ** rng.uniform(-12, -3)
    else:
        angle = rng.uniform(0.5, math.pi - 0.5)  # far from symmetric: C and C^T differ
    return so3.exp(angle * axis)


def random_covariance(rng: np.random.Generator, sigmas: np.ndarray) -> np.ndarray:
    n = len(sigmas)
    A = rng.normal(size=(n, n))
    corr = A @ A.T + n * np.eye(n)
    d = np.sqrt(np.diag(corr))
    return corr / np.outer(d, d) * np.outer(sigmas, sigmas)


def gtsam_sigmas(rng) -> np.ndarray:
    """Standard deviations in GTSAM's variable order (Rot3 [rad], Point3 [m], velocity [m/s],
    bias (acc [m/s^2], gyro [rad/s])). Attitude up to 0.5 rad: a large perturbation is still exact."""
    return np.concatenate([rng.uniform(0.05, 0.5, 3), rng.uniform(0.1, 5, 3), rng.uniform(0.01, 1, 3),
                           rng.uniform(0.01, 0.2, 3), rng.uniform(1e-3, 0.05, 3)])


def primer_errors(R: gtsam.Rot3, xi: np.ndarray) -> np.ndarray:
    """Apply GTSAM-chart perturbations ``xi (N, 15)`` (order Rot3, Point3, vel, bias) and return
    the primer error states ``(dr, dv, dphi, db_f, db_w)``: ``dphi = log(R' R^T)`` with
    ``R' = R.retract(d)`` computed by GTSAM; vectors are added (GTSAM's chart for Point3,
    vectors and ConstantBias is addition, checked in ``test_vector_charts_are_addition``)."""
    C = R.matrix()
    moved = np.stack([R.retract(d).matrix() for d in xi[:, 0:3]])
    dphi = so3.log(moved @ C.T)  # vectorised over the samples
    return np.concatenate([xi[:, 3:6], xi[:, 6:9], dphi, xi[:, 9:15]], axis=1)


def z_score(samples: np.ndarray, cov: np.ndarray) -> float:
    """Largest standardised deviation of the whitened sample covariance from I (see module)."""
    n = len(samples)
    w = np.linalg.solve(np.linalg.cholesky(cov), samples.T).T
    S = w.T @ w / n
    sd = np.full(S.shape, 1.0 / math.sqrt(n))
    np.fill_diagonal(sd, math.sqrt(2.0 / n))
    return float(np.abs((S - np.eye(len(S))) / sd).max())


def test_vector_charts_are_addition():
    """GTSAM's retract of Point3, a velocity vector and ConstantBias adds the increment, and Rot3's
    is ``R Exp(d)`` (the right chart): the facts :func:`primer_errors` relies on."""
    rng = np.random.default_rng(0)
    k = keyframe_keys(0)
    values = gtsam.Values()
    C = random_rotation(rng, "ordinary")
    values.insert(k.rot, gtsam.Rot3(C))
    values.insert(k.pos, gtsam.Point3(1.0, 2.0, 3.0))
    values.insert(k.vel, np.array([4.0, 5.0, 6.0]))
    values.insert(k.bias, gtsam.imuBias.ConstantBias(np.array([0.1, 0.2, 0.3]), np.array([0.01, 0.02, 0.03])))
    d = rng.normal(0, 0.3, 15)
    delta = gtsam.VectorValues()
    for key, part in zip(k.all(), (d[0:3], d[3:6], d[6:9], d[9:15])):
        delta.insert(key, part)
    moved = values.retract(delta)
    assert np.abs(moved.atRot3(k.rot).matrix() - C @ so3.exp(d[0:3])).max() < 1e-15
    assert np.abs(moved.atPoint3(k.pos) - (np.array([1.0, 2.0, 3.0]) + d[3:6])).max() < 1e-15
    assert np.abs(moved.atVector(k.vel) - (np.array([4.0, 5.0, 6.0]) + d[6:9])).max() < 1e-15
    bias = np.array([0.1, 0.2, 0.3, 0.01, 0.02, 0.03])
    assert np.abs(moved.atConstantBias(k.bias).vector() - (bias + d[9:15])).max() < 1e-15


@pytest.mark.parametrize("regime", ["tiny", "ordinary", "near_pi"])
def test_state_covariance_to_primer_against_sampled_perturbations(regime):
    rng = np.random.default_rng({"tiny": 1, "ordinary": 2, "near_pi": 3}[regime])
    C = random_rotation(rng, regime)
    R = gtsam.Rot3(C)
    cov_gtsam = random_covariance(rng, gtsam_sigmas(rng))
    xi = rng.multivariate_normal(np.zeros(15), cov_gtsam, size=N_SAMPLES)
    e = primer_errors(R, xi)
    predicted = state_covariance_to_primer(cov_gtsam, R)
    assert np.array_equal(predicted, predicted.T)

    # exact: the mapped sample covariance is the sample covariance of the mapped samples
    sample_gtsam = xi.T @ xi / N_SAMPLES
    sample_primer = e.T @ e / N_SAMPLES
    scale = np.abs(sample_primer).max()
    assert np.abs(state_covariance_to_primer(sample_gtsam, C) - sample_primer).max() <= 1e-14 * scale

    # statistical: against the population covariance
    assert z_score(e, predicted) < 5.0

    # negative control: a transposed rotation, or forgetting the rotation, is rejected
    if regime == "ordinary":
        assert z_score(e, state_covariance_to_primer(cov_gtsam, C.T)) > 5.0
        assert z_score(e, state_covariance_to_primer(cov_gtsam, np.eye(3))) > 5.0


@pytest.mark.parametrize("regime", ["tiny", "ordinary", "near_pi"])
def test_gtsam_marginal_of_a_state_prior_maps_back_to_the_prior(regime):
    """A state prior with covariance ``P`` (primer coordinates) is the only factor on a keyframe:
    at its mean GTSAM's joint marginal of ``(Rot3, Point3, velocity, bias)`` is ``P`` in GTSAM's
    chart, and ``state_covariance_to_primer`` must give ``P`` back (to 1e-12 relative: one
    factorisation and inversion of a well-conditioned 15x15 matrix)."""
    rng = np.random.default_rng({"tiny": 4, "ordinary": 5, "near_pi": 6}[regime])
    prior = imu.ImuState(rng.normal(0, 10, 3), rng.normal(0, 2, 3), random_rotation(rng, regime),
                         rng.normal(0, 0.1, 3), rng.normal(0, 0.01, 3))
    P = random_covariance(rng, np.concatenate([rng.uniform(0.1, 5, 3), rng.uniform(0.01, 1, 3),
                                               rng.uniform(0.05, 0.5, 3), rng.uniform(0.01, 0.2, 3),
                                               rng.uniform(1e-3, 0.05, 3)]))
    k = keyframe_keys(7)
    graph = gtsam.NonlinearFactorGraph()
    graph.add(priors.state_prior_factor(k, prior, P))
    values = gtsam.Values()
    values.insert(k.rot, gtsam.Rot3(prior.C))
    values.insert(k.pos, gtsam.Point3(*prior.r))
    values.insert(k.vel, np.array(prior.v))
    values.insert(k.bias, gtsam.imuBias.ConstantBias(prior.b_f, prior.b_w))
    joint = gtsam.Marginals(graph, values).jointMarginalCovariance(gtsam.KeyVector(k.all())).fullMatrix()
    back = state_covariance_to_primer(joint, values.atRot3(k.rot))
    assert np.abs(back - P).max() <= 1e-12 * np.abs(P).max()
    if regime == "ordinary":  # the rotation block alone is NOT the primer's: C matters
        assert np.abs(joint[0:3, 0:3] - P[6:9, 6:9]).max() > 1e-3 * np.abs(P[6:9, 6:9]).max()


@pytest.mark.parametrize("regime", ["tiny", "ordinary", "near_pi"])
def test_to_gtsam_chart_is_gtsams_own_numerical_derivative(regime):
    """For the primer residual ``f(C) = log(C C_m^T)`` with analytic primer Jacobian
    ``Gamma^-1(f)``, ``to_gtsam_chart`` gives what GTSAM's ``numericalDerivative11`` (central
    differences in GTSAM's right chart, step 1e-5) measures, to 1e-8 (its truncation error is
    ~1e-10 here); with ``C^T`` in place of ``C`` the difference is of order one."""
    rng = np.random.default_rng({"tiny": 7, "ordinary": 8, "near_pi": 9}[regime])
    C = random_rotation(rng, regime)
    C_m = so3.exp(rng.normal(0, 0.5, 3)) @ C
    def residual(C):
        e, J = np.empty(3), np.empty((3, 3))
        orientation_error_into(np.ascontiguousarray(C), C_m, e, J)
        return e, J

    e, J_primer = residual(C)
    numeric = numericalDerivative11(lambda R: residual(R.matrix())[0], gtsam.Rot3(C))
    assert np.abs(to_gtsam_chart(J_primer, C) - numeric).max() < 1e-8
    assert np.abs(to_gtsam_chart(J_primer, gtsam.Rot3(C)) - numeric).max() < 1e-8  # Rot3 accepted too
    if regime == "ordinary":
        assert np.abs(to_gtsam_chart(J_primer, C.T) - numeric).max() > 0.1
