"""The covariances (smoother/model/covariances.py) against the dense inverse: the selected
inverse's blocks and the solution whatever the elimination's order and pieces, and their tangent
(``covariance_tangent``) for a change of the information."""
from __future__ import annotations

import gtsam
import numpy as np
import pytest

from factors import imu
from smoother.model import covariances
from smoother.model.blocks import Block, Layout, nested_dissection, unit_model
from smoother.model.covariances import covariance_tangent, joint_block, marginal_covariances


def _graph(rng, n: int, extra: tuple, last_reads: bool = False):
    """A chain of ``n`` keyframes with priors; keyframe 1 reads the first calibration variable
    only, keyframes 2 and 3 every one, the last no other keyframe, and no calibration variable
    either (its conditional has no parents) unless ``last_reads``: then the last one."""
    factors = [([k], [rng.normal(size=(15, 15)) + 5 * np.eye(15)]) for k in range(n)]
    factors += [([k, k + 1], [rng.normal(size=(15, 15)), rng.normal(size=(15, 15))]) for k in range(n - 2)]
    factors.append(([1, n], [rng.normal(size=(4, 15)), rng.normal(size=(4, extra[0]))]))
    if last_reads:
        factors.append(([n - 1, n + len(extra) - 1], [rng.normal(size=(2, 15)), rng.normal(size=(2, extra[-1]))]))
    for k in (2, 3):
        factors += [([k, n + j], [rng.normal(size=(3, 15)), rng.normal(size=(3, d))]) for j, d in enumerate(extra)]
    factors += [([n + j], [np.eye(d)]) for j, d in enumerate(extra)]
    graph = gtsam.GaussianFactorGraph()
    for keys, A in factors:
        parts = [x for pair in zip(keys, A) for x in pair]
        graph.add(gtsam.JacobianFactor(*parts, np.zeros(A[0].shape[0]), unit_model(A[0].shape[0])))
    return graph, factors


@pytest.mark.parametrize("last_reads", [False, True])
@pytest.mark.parametrize("chain", [False, True])
def test_the_tangent_of_the_covariance_blocks_is_minus_sigma_dlambda_sigma(chain, last_reads):
    """COLAMD's order and a chain's sweep, with and without the last keyframe reading a
    calibration variable."""
    rng = np.random.default_rng(4)
    n, extra = 6, (2, 3)
    layout = Layout(n, extra, chain)
    graph, factors = _graph(rng, n, extra, last_reads)
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


@pytest.mark.parametrize("last_reads", [False, True])
@pytest.mark.parametrize("piece", [1, 2, 100])
@pytest.mark.parametrize("chain", [True, False])
def test_covariances_and_solution_match_the_dense_inverse_whatever_the_sweep_pieces(monkeypatch, piece, chain,
                                                                                   last_reads):
    """A chain's sweep in pieces of any length (GTSAM's partial eliminations, the calibrations
    last) and COLAMD's order, and the calibrations' share added in pieces of any length, give
    every joint block and the least-squares solution of the dense system."""
    monkeypatch.setattr(covariances, "SWEEP_PIECE", piece)
    monkeypatch.setattr(covariances, "SHARE_PIECE", piece)
    rng = np.random.default_rng(7)
    n, extra = 6, (2, 3)
    layout = Layout(n, extra, chain)
    graph, _ = _graph(rng, n, extra, last_reads)
    b = rng.normal(size=15)
    graph.add(gtsam.JacobianFactor(4, np.eye(15), b, unit_model(15)))  # a right-hand side
    _, joint, root = marginal_covariances(graph, n, None, True, layout, square_root=True)
    offsets = np.cumsum([0, *(layout.dim(k) for k in layout.keys)])
    A, rhs = graph.jacobian(gtsam.Ordering(list(layout.keys)))
    sigma = np.linalg.inv(A.T @ A)
    np.testing.assert_allclose(root.solution, sigma @ A.T @ rhs, rtol=0, atol=1e-12)
    for (a, c), value in joint.items():
        np.testing.assert_allclose(value, sigma[offsets[a]:offsets[a + 1], offsets[c]:offsets[c + 1]],
                                   rtol=0, atol=1e-12)
    assert len(joint) >= 2 * n - 1


def test_a_chain_is_ordered_by_its_structure_and_anything_else_by_colamd():
    """Nested dissection is a permutation whose last keyframe halves the chain; a factor two
    keyframes apart makes the layout no chain."""
    order = nested_dissection(15)
    assert sorted(order.tolist()) == list(range(15)) and order[-1] == 7
    assert set(order[:8].tolist()) == set(range(0, 15, 2))
    states = imu.ImuState.identity((4,))

    def block(keyframes):
        return Block("b", np.array(keyframes), None, None)

    assert Layout.of(states, None, [block([[0], [3]]), block([[0, 1], [2, 3]])]).chain
    assert not Layout.of(states, None, [block([[0, 2]])]).chain
    assert not Layout.of(states).chain
