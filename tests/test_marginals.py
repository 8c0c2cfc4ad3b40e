"""graph.solve.marginals against dense linear algebra: the chain's and the arrow-head's marginal
covariances equal the blocks of the inverse of the whole information matrix."""

from __future__ import annotations

import numpy as np
import pytest

from graph.solve.marginals import banded_marginals, chain_band, chain_marginals


def _arrow(N: int, d: int, G: int, seed: int, stiff: float):
    """A chain's information (per-frame blocks plus third-difference weights ``stiff``) and a
    coupling of every frame to ``G`` shared unknowns, as band blocks and as one dense matrix built
    from the definitions: ``blockdiag(G_n) + D^T (stiff I) D`` with D the third difference."""
    rng = np.random.default_rng(seed)
    A = rng.normal(size=(N, d, d))
    G_frames = A @ np.transpose(A, (0, 2, 1)) + 0.1 * np.eye(d)
    band = chain_band(G_frames, np.full(d, stiff))
    B = rng.normal(size=(N, d, G)) * 0.3
    Dw = np.eye(G) * (N * 0.5) + 0.1
    D3 = np.zeros(((N - 3) * d, N * d))
    for j in range(N - 3):
        for c, coef in enumerate((-1.0, 3.0, -3.0, 1.0)):
            D3[j * d:(j + 1) * d, (j + c) * d:(j + c + 1) * d] = coef * np.eye(d)
    chain = np.zeros((N * d, N * d))
    for n in range(N):
        chain[n * d:(n + 1) * d, n * d:(n + 1) * d] = G_frames[n]
    chain += stiff * D3.T @ D3
    coupling = B.reshape(N * d, G)
    full = np.block([[chain, coupling], [coupling.T, Dw]])
    return G_frames, band, B, Dw, full


@pytest.mark.parametrize("N, d, G, stiff", [(3, 2, 2, 1.0), (12, 3, 2, 10.0), (40, 4, 3, 1e4), (30, 3, 0, 1e3)])
@pytest.mark.slow  # over 12 s here
def test_banded_marginals_are_the_blocks_of_the_inverse(N, d, G, stiff):
    G_frames, band, B, Dw, full = _arrow(N, d, G, seed=N + G, stiff=stiff)
    inv = np.linalg.inv(full)
    Sigma, cross, SW = banded_marginals(band, B, Dw)
    scale = np.max(np.abs(inv))
    for n in range(N):
        assert np.allclose(Sigma[n], inv[n * d:(n + 1) * d, n * d:(n + 1) * d], rtol=1e-7, atol=1e-9 * scale)
        if G:
            assert np.allclose(cross[n], inv[n * d:(n + 1) * d, N * d:], rtol=1e-7, atol=1e-9 * scale)
    if G:
        assert np.allclose(SW, inv[N * d:, N * d:], rtol=1e-7, atol=1e-9 * scale)
    chain = np.linalg.inv(full[:N * d, :N * d])
    plain, _ = chain_marginals(G_frames, np.full(d, stiff))
    for n in range(N):
        assert np.allclose(plain[n], chain[n * d:(n + 1) * d, n * d:(n + 1) * d], rtol=1e-7,
                           atol=1e-9 * np.max(np.abs(chain)))


@pytest.mark.parametrize("order", [1, 2])
def test_chain_marginals_of_a_lower_order_prior_are_the_blocks_of_the_inverse(order):
    """The first- and second-difference priors (motion_order 1, 2) leave the band's outer blocks
    zero; the same recursion gives the blocks of the dense inverse."""
    from graph.solve.smoothing import STENCILS

    N, d, stiff = 25, 3, 1e3
    rng = np.random.default_rng(order)
    A = rng.normal(size=(N, d, d))
    G_frames = A @ np.transpose(A, (0, 2, 1)) + 0.1 * np.eye(d)
    Dk = np.zeros(((N - order) * d, N * d))
    for j in range(N - order):
        for c, coef in enumerate(STENCILS[order]):
            Dk[j * d:(j + 1) * d, (j + c) * d:(j + c + 1) * d] = coef * np.eye(d)
    full = stiff * Dk.T @ Dk
    for n in range(N):
        full[n * d:(n + 1) * d, n * d:(n + 1) * d] += G_frames[n]
    inv = np.linalg.inv(full)
    ours, _ = chain_marginals(G_frames, np.full(d, stiff), STENCILS[order])
    for n in range(N):
        assert np.allclose(ours[n], inv[n * d:(n + 1) * d, n * d:(n + 1) * d], rtol=1e-7, atol=1e-9 * np.abs(inv).max())


def test_a_chain_nothing_fixes_takes_a_ridge_and_says_so():
    """The motion prior alone (no frame's information): its null space (the polynomials it leaves
    free) makes the Cholesky meet a pivot that is not positive; the marginals take the smallest
    ridge that factors and return it, instead of numpy's LinAlgError."""
    from graph.solve.marginals import RIDGES, chain_marginals

    S, ridge = chain_marginals(np.zeros((30, 2, 2)), np.ones(2))
    assert ridge in RIDGES and np.isfinite(S).all() and (np.diagonal(S, axis1=1, axis2=2) > 0).all()
    S, ridge = chain_marginals(np.tile(np.eye(2), (30, 1, 1)), np.ones(2))
    assert ridge == 0.0
