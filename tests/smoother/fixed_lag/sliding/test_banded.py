"""The sliding window's block-banded linear algebra (:mod:`smoother.fixed_lag.sliding.banded`) against SciPy's banded
Cholesky (``scipy.linalg.cholesky_banded``, ``solveh_banded``) on the window's shapes: blocks of
15, bandwidths 1 (IMU factors only) to 4 (a relative pose or a marginal prior spanning keyframes),
windows of up to 24 keyframes in a ring that wraps round, well and badly conditioned."""
from __future__ import annotations

import numpy as np
import pytest
from banded_cases import band, random_banded
from scipy.linalg import LinAlgError, cholesky_banded, solveh_banded

from smoother.fixed_lag.sliding import banded
from smoother.fixed_lag.sliding.banded import DIM

SHAPES = [(1, 1), (2, 1), (20, 1), (13, 2), (24, 3), (9, 4)]


def _scipy_band(H: np.ndarray, S: int) -> np.ndarray:
    """``H`` in SciPy's lower banded storage (``ab[i - j, j] = H[i, j]``), scalar bandwidth
    ``(S + 1) * 15 - 1``: the whole of the block band (or of ``H``, if that is smaller)."""
    N = len(H)
    u = min((S + 1) * DIM, N) - 1
    ab = np.zeros((u + 1, N))
    for offset in range(u + 1):
        ab[offset, :N - offset] = np.diagonal(H, -offset)
    return ab


def _dense_factor(L: np.ndarray, first: int, n: int, cap: int, S: int) -> np.ndarray:
    """The ring factor's window ``first .. first + n - 1`` as a dense lower triangular matrix."""
    out = np.zeros((n * DIM, n * DIM))
    for b in range(n):
        for s in range(min(b, S) + 1):
            out[b * DIM:(b + 1) * DIM, (b - s) * DIM:(b - s + 1) * DIM] = L[(first + b) % cap, s]
    return out


def _factorised(H: np.ndarray, S: int, first: int, cap: int) -> np.ndarray:
    n = len(H) // DIM
    L = np.zeros((cap, S + 1, DIM, DIM))
    assert banded.factorise(band(H, S), L, first, first, first + n - 1, cap, S) == -1
    return L


def _solved(L: np.ndarray, B: np.ndarray, first: int, cap: int, S: int) -> np.ndarray:
    """``H^-1 B`` through the ring factor: forward then backward solve."""
    n = len(B) // DIM
    b = np.zeros((cap, DIM, B.shape[1]))
    for k in range(n):
        b[(first + k) % cap] = B[k * DIM:(k + 1) * DIM]
    banded.forward_solve(L, b, first, first, first, first + n - 1, cap, S)
    banded.backward_solve(L, b, first, first + n - 1, cap, S)
    return np.concatenate([b[(first + k) % cap] for k in range(n)])


def _ring(n: int) -> tuple[int, int]:
    """A window start and a ring of slots shorter than twice the window, so that it wraps round."""
    cap = 1 << max(1, (n - 1).bit_length())
    return cap - 1, cap


@pytest.mark.parametrize("n, S", SHAPES)
def test_the_factor_is_scipys_banded_cholesky(n, S):
    rng = np.random.default_rng(100 * n + S)
    H = random_banded(rng, n, S)
    first, cap = _ring(n)
    L = _dense_factor(_factorised(H, S, first, cap), first, n, cap, S)
    expected = cholesky_banded(_scipy_band(H, S), lower=True)
    for offset in range(expected.shape[0]):
        np.testing.assert_allclose(np.diagonal(L, -offset), expected[offset, :len(H) - offset], rtol=1e-10,
                                   atol=1e-12)
    assert np.count_nonzero(np.tril(L, -((S + 1) * DIM))) == 0  # nothing outside the band


@pytest.mark.parametrize("n, S", SHAPES)
@pytest.mark.parametrize("m", [1, DIM])
def test_solves_equal_scipys_banded_solve(n, S, m):
    """One right-hand side (the update's step) and fifteen (a keyframe's marginal covariance)."""
    rng = np.random.default_rng(10 * n + S + m)
    H = random_banded(rng, n, S)
    B = rng.normal(size=(len(H), m))
    first, cap = _ring(n)
    x = _solved(_factorised(H, S, first, cap), B, first, cap, S)
    np.testing.assert_allclose(x, solveh_banded(_scipy_band(H, S), B, lower=True), rtol=1e-9, atol=1e-12)


@pytest.mark.parametrize("n, S", SHAPES)
def test_badly_scaled_matrices_solve_as_scipys_does(n, S):
    """Components scaled over twelve decades (condition numbers of 1e12 and more, as a short IMU
    interval's position information beside a bias's): the factor's diagonal agrees with SciPy's
    entry by entry, the solutions in each component's own units (the error scaled as the
    component is)."""
    rng = np.random.default_rng(7 * n + S)
    H0 = random_banded(rng, n, S)
    d = 10.0 ** rng.uniform(-6.0, 6.0, size=len(H0))
    H = H0 * np.outer(d, d)
    assert np.linalg.cond(H) > 1e10
    g = H @ rng.normal(size=(len(H), 1))
    first, cap = _ring(n)
    L = _factorised(H, S, first, cap)
    expected = cholesky_banded(_scipy_band(H, S), lower=True)
    np.testing.assert_allclose(np.diagonal(_dense_factor(L, first, n, cap, S)), expected[0], rtol=1e-9)
    x, x_scipy = _solved(L, g, first, cap, S), solveh_banded(_scipy_band(H, S), g, lower=True)
    error = np.linalg.norm(d[:, None] * (x - x_scipy)) / np.linalg.norm(d[:, None] * x_scipy)
    assert error <= 1e3 * np.finfo(float).eps * np.linalg.cond(H0)


@pytest.mark.parametrize("n, S", [(20, 1), (13, 2), (9, 4)])
def test_nearly_singular_matrices_solve_as_scipys_does(n, S):
    """Factors that leave directions all but uninformed (each informs 14 of the 15 directions it
    adds, over a floor of 1e-10): condition numbers beyond 1e11. Both solutions satisfy the
    equations to working precision and agree to the accuracy the condition number allows."""
    rng = np.random.default_rng(n + S)
    N = n * DIM
    H = 1e-10 * np.eye(N)
    for k in range(n):
        lo = max(0, k - S) * DIM
        J = rng.normal(size=(DIM - 1, (k + 1) * DIM - lo))
        H[lo:(k + 1) * DIM, lo:(k + 1) * DIM] += J.T @ J
    condition = np.linalg.cond(H)
    assert condition > 1e11
    g = rng.normal(size=(N, 1))
    first, cap = _ring(n)
    x = _solved(_factorised(H, S, first, cap), g, first, cap, S)
    expected = solveh_banded(_scipy_band(H, S), g, lower=True)
    eps = np.finfo(float).eps
    for solution in (x, expected):
        assert np.linalg.norm(H @ solution - g) <= 1e3 * eps * np.linalg.norm(H, 2) * np.linalg.norm(solution)
    assert np.linalg.norm(x - expected) <= 1e3 * eps * condition * np.linalg.norm(expected)


@pytest.mark.parametrize("n, S", [(20, 1), (13, 2), (24, 3)])
def test_refactorising_from_a_row_on_is_scipys_factor_of_the_changed_matrix(n, S):
    """The update changes the rows of ``H`` from a keyframe on (the new keyframe's factors reach
    ``S`` back): factorising those rows only, over the rows kept, gives SciPy's factor of the
    changed matrix."""
    rng = np.random.default_rng(n * S)
    H = random_banded(rng, n, S)
    first, cap = _ring(n)
    L = _factorised(H, S, first, cap)
    start = n - S - 1
    J = rng.normal(size=(DIM, (S + 1) * DIM))
    H2 = H.copy()
    H2[start * DIM:, start * DIM:] += J.T @ J
    rows = band(H2, S)[start:]
    assert banded.factorise(rows, L, first, first + start, first + n - 1, cap, S) == -1
    expected = cholesky_banded(_scipy_band(H2, S), lower=True)
    dense = _dense_factor(L, first, n, cap, S)
    for offset in range(expected.shape[0]):
        np.testing.assert_allclose(np.diagonal(dense, -offset), expected[offset, :len(H) - offset], rtol=1e-10,
                                   atol=1e-12)


@pytest.mark.parametrize("n, S", [(6, 1), (13, 2), (9, 4)])
def test_a_matrix_that_is_not_positive_definite_is_refused_at_its_first_failing_block(n, S):
    """SciPy refuses it too; the keyframe named is the first whose leading block is indefinite."""
    rng = np.random.default_rng(n - S)
    H = random_banded(rng, n, S)
    bad = n // 2
    H[bad * DIM + 3, bad * DIM + 3] -= 1e4
    with pytest.raises(LinAlgError):
        cholesky_banded(_scipy_band(H, S), lower=True)
    first, cap = _ring(n)
    L = np.zeros((cap, S + 1, DIM, DIM))
    failed = banded.factorise(band(H, S), L, first, first, first + n - 1, cap, S)
    leading = [np.linalg.eigvalsh(H[:(k + 1) * DIM, :(k + 1) * DIM]).min() > 0 for k in range(n)]
    assert failed == first + leading.index(False) == first + bad


@pytest.mark.parametrize("n, S, nl", [(4, 1, 1), (13, 2, 3), (9, 4, 2), (24, 3, 5)])
def test_the_schur_complement_is_scipys(n, S, nl):
    """Marginalising the ``nl`` oldest keyframes: ``H_mm - H_ml H_ll^-1 H_lm`` and ``g_m - H_ml
    H_ll^-1 g_l`` with ``H_ll^-1`` from SciPy's banded solve, and the marginal prior's square root
    ``R^T R`` equal to it on the keyframes it ties."""
    rng = np.random.default_rng(n + 31 * nl)
    d = 10.0 ** rng.uniform(-3.0, 3.0, size=n * DIM)  # badly scaled too
    H = random_banded(rng, n, S) * np.outer(d, d)
    g = rng.normal(size=len(H))
    m = nl * DIM
    X = solveh_banded(_scipy_band(H[:m, :m], min(S, nl - 1)), np.column_stack([H[:m, m:], g[:m]]), lower=True)
    Hs_expected = H[m:, m:] - H[m:, :m] @ X[:, :-1]
    gs_expected = g[m:] - H[m:, :m] @ X[:, -1]
    Hs, gs, ok = banded.schur(band(H, S), g, *banded.no_border(n), nl)
    assert ok
    scale = np.sqrt(np.outer(np.diag(Hs_expected), np.diag(Hs_expected)))
    np.testing.assert_allclose(Hs / scale, Hs_expected / scale, atol=1e-9)
    np.testing.assert_allclose(gs, gs_expected, rtol=1e-8, atol=1e-10 * np.abs(gs_expected).max())
    status, touched, R, e0, _, _ = banded.marginal_prior(band(H, S), g, *banded.no_border(n), nl)
    keep = (touched[:, None] * DIM + np.arange(DIM)).ravel()
    informed = [b for b in range(n - nl) if np.any(Hs_expected[b * DIM:(b + 1) * DIM] != 0.0)]
    assert status == 0 and touched.tolist() == informed
    np.testing.assert_allclose((R.T @ R) / scale[np.ix_(keep, keep)], Hs_expected[np.ix_(keep, keep)]
                               / scale[np.ix_(keep, keep)], atol=1e-9)
    np.testing.assert_allclose(R.T @ e0, gs_expected[keep], rtol=1e-8, atol=1e-10 * np.abs(gs_expected).max())
