"""The covariances' tangent (smoother/model/covariances.py: ``covariance_tangent``): the change of
the selected inverse's blocks for a change of the information, against the dense inverse."""
from __future__ import annotations

import gtsam
import numpy as np

from smoother.model.blocks import Layout, unit_model
from smoother.model.covariances import covariance_tangent, joint_block, marginal_covariances


def _graph(rng, n: int, extra: tuple):
    """A chain of ``n`` keyframes with priors; keyframe 1 reads the first calibration variable
    only, keyframes 2 and 3 every one, the last none and no other keyframe either (its conditional
    has no parents)."""
    factors = [([k], [rng.normal(size=(15, 15)) + 5 * np.eye(15)]) for k in range(n)]
    factors += [([k, k + 1], [rng.normal(size=(15, 15)), rng.normal(size=(15, 15))]) for k in range(n - 2)]
    factors.append(([1, n], [rng.normal(size=(4, 15)), rng.normal(size=(4, extra[0]))]))
    for k in (2, 3):
        factors += [([k, n + j], [rng.normal(size=(3, 15)), rng.normal(size=(3, d))]) for j, d in enumerate(extra)]
    factors += [([n + j], [np.eye(d)]) for j, d in enumerate(extra)]
    graph = gtsam.GaussianFactorGraph()
    for keys, A in factors:
        parts = [x for pair in zip(keys, A) for x in pair]
        graph.add(gtsam.JacobianFactor(*parts, np.zeros(A[0].shape[0]), unit_model(A[0].shape[0])))
    return graph, factors


def test_the_tangent_of_the_covariance_blocks_is_minus_sigma_dlambda_sigma():
    rng = np.random.default_rng(4)
    n, extra = 6, (2, 3)
    layout = Layout(n, extra)
    graph, factors = _graph(rng, n, extra)
    _, joint, root = marginal_covariances(graph, n, None, True, layout, square_root=True)
    offsets = np.cumsum([0, *(layout.dim(k) for k in layout.keys)])
    # two directions: a binary factor's and a calibration factor's weight
    information, dense = {}, np.zeros((2, offsets[-1], offsets[-1]))
    for x, f in enumerate((n + 1, len(factors) - len(extra) - 1)):
        keys, A = factors[f]
        for s, (a, Aa) in enumerate(zip(keys, A)):
            for b, Ab in zip(keys[s:], A[s:]):
                information.setdefault((a, b), np.zeros((2, Aa.shape[1], Ab.shape[1])))[x] += Aa.T @ Ab
        rows = sum(np.pad(Ak, ((0, 0), (offsets[k], offsets[-1] - offsets[k + 1]))) for k, Ak in zip(keys, A))
        dense[x] = rows.T @ rows
    A = graph.jacobian(gtsam.Ordering(list(layout.keys)))[0]
    sigma = np.linalg.inv(A.T @ A)
    expected = -sigma @ dense @ sigma
    tangent = covariance_tangent(root, joint, information)
    # every pair of a conditional and its parent, and right wherever given
    assert {(k[0], p) if k[0] <= p else (p, k[0]) for k in root.keys for p in k} <= set(tangent)
    for (a, b), value in tangent.items():
        rows, cols = slice(offsets[a], offsets[a + 1]), slice(offsets[b], offsets[b + 1])
        np.testing.assert_allclose(joint_block(joint, a, b), sigma[rows, cols], rtol=0, atol=1e-12)
        np.testing.assert_allclose(value, expected[:, rows, cols], rtol=0, atol=1e-12)
